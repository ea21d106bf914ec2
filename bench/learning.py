# Copyright 2026 The magcal_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
Learning in operation at 1 kHz: CPU per set and memory over a long drive (issue 34).

The simulator's vehicle drives a 4-sensor cross at ``--rate`` sets per second for
``--duration`` s (simulated in chunks of 10 s, so the bench itself needs no memory in
proportion to the run), with an offset step of sensor 2 at half time; every set goes to a
:class:`magcal_ros.core.live.learning.Learner` as the calibration node hands it over
(``add``; the attitude every 20 ms, ``add_attitude``), and the refits run when due
(:func:`magcal_ros.pipeline.refit_recent`, synchronously here; in the node a worker thread).

Measured per segment of ``--segment-s`` of data: the CPU time of ``add`` and
``add_attitude`` per set (process time, the simulator's outside it), the refits' CPU, and the
memory the Python allocator holds at the segment's end (tracemalloc, the segment's
simulated chunk freed): flat when the learner's memory does not grow with the run.  One
more line: the CPU of a refit that learns a driven effect's coupling (one sensor, a motor
current's) against the same refit of the model without it (:func:`coupling_refit`).

    python bench/learning.py                    # 300 s at 1 kHz
    python bench/learning.py --duration 40      # short
"""
import argparse
import os
import sys
import time
import tracemalloc

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
import numpy as np  # noqa: E402


def main(argv=None):
    """Run the benchmark; print the table, write the JSON and return the results."""
    p = common.add_common_args(argparse.ArgumentParser(description=__doc__.split('\n\n')[0]))
    p.add_argument('--rate', type=float, default=1000.0, help='sets per second, Hz')
    p.add_argument('--duration', type=float, default=300.0, help='simulated drive, s')
    p.add_argument('--segment-s', type=float, default=20.0, help='segment length, s')
    p.add_argument('--persist-s', type=float, default=30.0, help='learn_persist_s, s')
    p.add_argument('--seed', type=int, default=3)
    args = p.parse_args(argv)
    started = time.perf_counter()

    from magcal_ros.core.data.simulate import set_truth_refs, SimConfig, simulate, Simulator
    from magcal_ros.core.live.learning import LearnConfig, Learner, READY
    from magcal_ros.pipeline import calibrate, refit_recent
    f = 50000.0
    tumble, _ = simulate(n_samples=3000, rate_hz=20.0, trajectory='smooth', seed=1)
    active = calibrate(tumble, 'base', f).result.calibration
    change_s = round(args.duration / 2)
    sim = Simulator(SimConfig(rate_hz=args.rate, trajectory='vehicle', attitude=True,
                              seed=args.seed, aux=False,
                              truth={f'offset(step({change_s}))@2': [120.0, 0.0, -60.0]}))
    set_truth_refs(sim, np.arange(0.0, 60.0, 0.01))
    learner = Learner(4, LearnConfig(persist_s=args.persist_s))
    learner.set_active(active, f)

    def refit(d, a, sensors):
        return refit_recent(d, a, f, sensors=sensors)

    n_total = int(args.duration * args.rate)
    chunk = int(10 * args.rate)
    seg_sets = int(args.segment_s * args.rate)
    att_every = max(1, int(round(0.02 * args.rate)))
    tracemalloc.start()
    rows, add_cpu, refit_cpu, refits, done = [], 0.0, 0.0, 0, 0
    seg_add, seg_refit, seg_n = 0.0, 0.0, 0
    for k0 in range(0, n_total, chunk):
        t = np.arange(k0, min(n_total, k0 + chunk)) / args.rate
        data = sim.sample(t)
        raw = np.ascontiguousarray(data.raw.transpose(1, 0, 2))     # (N, S, 3)
        temp = np.ascontiguousarray(data.temp.T)
        att = data.attitude
        del data
        for k in range(len(t)):
            c0 = time.process_time()
            if k % att_every == 0:
                learner.add_attitude(t[k], att[k])
            closed = learner.add(t[k], raw[k], temp[k])
            c1 = time.process_time()
            seg_add += c1 - c0
            seg_n += 1
            if closed and learner.refit_due(t[k]):
                learner.refit(t[k], refit)
                if learner.state == READY:
                    learner.adopt(t[k])
                refits += 1
                seg_refit += time.process_time() - c1
            done += 1
        del raw, temp, att
        # segment ends fall on chunk ends when segment_s is a multiple of 10 s
        if done % seg_sets == 0 or done == n_total:
            current, _ = tracemalloc.get_traced_memory()
            rows.append({'until_s': round(done / args.rate, 1), 'sets': seg_n,
                         'add_us_per_set': 1e6 * seg_add / max(seg_n, 1),
                         'refit_cpu_s': seg_refit, 'traced_mib': current / 2 ** 20,
                         'state': learner.state})
            add_cpu += seg_add
            refit_cpu += seg_refit
            seg_add, seg_refit, seg_n = 0.0, 0.0, 0
    tracemalloc.stop()
    coupling = coupling_refit(f)
    per_set = [r['add_us_per_set'] for r in rows]
    mem = [r['traced_mib'] for r in rows]
    results = {
        'rate_hz': args.rate, 'sets': n_total, 'segments': rows,
        'add_us_per_set_first': per_set[0], 'add_us_per_set_last': per_set[-1],
        'add_us_per_set_median': float(np.median(per_set)),
        'refits': refits, 'refit_cpu_s_total': refit_cpu,
        'refit_cpu_s_each': refit_cpu / max(refits, 1),
        'traced_mib_first': mem[0], 'traced_mib_last': mem[-1], 'traced_mib_max': max(mem),
        'adoptions_s': [round(a, 2) for a, _ in learner.adoptions], 'change_s': change_s,
        'cpu_share_at_rate': (add_cpu + refit_cpu) / args.duration,
        'coupling_refit': coupling,
    }
    tables = [common.table(
        ['until (s)', 'sets', 'add + attitude (us/set)', 'refits (CPU s)', 'traced (MiB)',
         'state'],
        [[r['until_s'], r['sets'], r['add_us_per_set'], r['refit_cpu_s'], r['traced_mib'],
          r['state']] for r in rows],
        title=f'learning at {args.rate:g} Hz, 4 sensors, offset step of sensor 2 at '
              f'{change_s} s')]
    for tb in tables:
        print(tb)
    print(f'adoptions at {results["adoptions_s"]} s; {refits} refits, '
          f'{results["refit_cpu_s_each"]:.2f} s of CPU each; learning CPU '
          f'{100 * results["cpu_share_at_rate"]:.1f} % of a core at {args.rate:g} Hz')
    print(f"one sensor, 60 s window at 50 Hz: refit {coupling['base_cpu_s']:.2f} s of CPU with "
          f"'base', {coupling['coupled_cpu_s']:.2f} s with a motor current's coupling "
          f"(learned {coupling['learned_nt_per_a']} +- {coupling['stderr_nt_per_a']} nT/A, "
          f"truth {coupling['truth_nt_per_a']})")
    path = common.write_result('learning', vars(args), results, tables, args.out_dir,
                               started)
    print(f'wrote {path}')
    return results


def coupling_refit(f):
    """
    CPU of one refit with a driven effect's coupling learned, against the same without.

    One sensor, 60 s of the vehicle at 50 Hz whose motor current's coupling (truth
    (18, -11, 9) nT/A) differs from the active calibration's ((8, -5, 4) nT/A, fitted on a
    tumble): :func:`magcal_ros.pipeline.refit_recent` with the model ``base`` and
    ``base + aux:aux_motor_current`` (process time; the second has one more stage).
    """
    from magcal_ros.core.data.simulate import set_truth_refs, SimConfig, simulate, Simulator
    from magcal_ros.pipeline import calibrate, refit_recent
    token, c0, new = 'aux:aux_motor_current', [8.0, -5.0, 4.0], [18.0, -11.0, 9.0]
    tumble, _ = simulate(n_samples=3000, rate_hz=20.0, trajectory='smooth', seed=5,
                         n_sensors=1, truth={token + '@1': c0})
    sim = Simulator(SimConfig(n_sensors=1, rate_hz=50.0, trajectory='vehicle', attitude=True,
                              seed=5, truth={token + '@1': new}))
    t = np.arange(3000) / 50.0
    set_truth_refs(sim, t)
    window = sim.sample(t)
    out = {'truth_nt_per_a': new}
    for key, model in (('base', 'base'), ('coupled', 'base + ' + token)):
        active = calibrate(tumble, model, f).result.calibration
        c0_cpu = time.process_time()
        cal, _, _ = refit_recent(window, active, f)
        out[f'{key}_cpu_s'] = time.process_time() - c0_cpu
    idx = [i for i, info in enumerate(cal.model.param_info()) if info[1] == token]
    out['learned_nt_per_a'] = [round(float(x), 2) for x in cal.params[idx]]
    out['stderr_nt_per_a'] = [round(float(x), 2) for x in cal.stderr[idx]]
    return out


if __name__ == '__main__':
    main()
