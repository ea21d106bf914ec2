#!/usr/bin/env python3

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
Learning in operation, live (README "Demo": ``scripts/demo.sh --learn``).

The array was calibrated on a tumble (done here offline, on the simulator's sensors: the
calibration file the node finds at start-up).  Then it drives: ``fluxgate_sim`` runs the
vehicle trajectory (near level, turning part circles) with its attitude on ``imu``, and an
offset of sensor 2 steps at ``--change-s`` (a payload put on: the truth term
``offset(step(T))@2``).  ``fluxgate_driver``, ``calibration_node`` (parameters ``learn`` and
``auto_adopt``, ``imu_topic: imu``) and ``corrector_node`` run as separate processes; no
service is called.  The live residual of the active calibration (``calibration/residual``)
is measured against its floor before the change, after it, and after learning (once the
node has adopted a learned calibration and no refinement followed for ``--settle-s``);
``<out>/learn.png`` draws it over time with the change and the adoptions marked,
``<out>/learn.json`` holds the numbers (``change``, ``steps`` with ``t``, ``event``,
``scalar_rms_nt``, ``vector_rms_nt``, ``floor_nt`` per sensor, ``adopted_at_s``, ``learned``:
exactly the keys of issue 34; ``floor_nt`` is the scalar residual's floor sigma_j, the vector
residual's is sqrt(3 (sigma_j^2 + sum_{k != j} sigma_k^2 / 9)) for the cross).

The residual returns when, after learning, every sensor's scalar and vector residual RMS is
within :data:`RETURN_FACTOR` of its floor; the floor is the data's own (the noise of each
residual series from its high-order differences, :func:`demo_loop.window_stats`).  Otherwise
the demo says what is left and exits with status 1.  The corrector's switch is checked too:
its corrected stream of sensor 2 has no gap longer than :data:`MAX_GAP_PERIODS` sample
periods around each adoption.  Times are s since the simulator started.
"""
import argparse
import importlib
import json
import os
import pathlib
import shutil
import sys
import tempfile
import time

import numpy as np

SCRIPTS = pathlib.Path(__file__).resolve().parent
for _path in (SCRIPTS, SCRIPTS.parent):     # demo.py, demo_loop.py, this magcal_ros
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))
demo = importlib.import_module('demo')
demo_loop = importlib.import_module('demo_loop')

ROOT = demo.ROOT
NAMESPACE = demo.NAMESPACE
N_SENSORS = demo.N_SENSORS
#: the residual has returned when every RMS is within this factor of its floor (issue 34)
RETURN_FACTOR = 1.15
#: the corrector's switch: no gap in its corrected stream longer than this many periods
MAX_GAP_PERIODS = 5
#: the change: sensor 2's offset steps by this (nT, its own axes)
CHANGE_VALUES = (120.0, 0.0, -60.0)
DIAG_LEARN = 'calibration_node: learning'


class LearnClient(demo_loop.LoopClient):
    """The loop demo's client, with the learned and active calibrations and the corrector."""

    def __init__(self, rclpy, context):
        super().__init__(rclpy, context)
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField
        from std_msgs.msg import String
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.results = []                    # (arrival s, YAML) on calibration/result
        self.learned = []                    # (arrival s, YAML) on calibration/learned
        self.learning = []                   # (arrival s, level, message, values)
        self.corrected = []                  # (arrival s, stamp s) of sensor2/corrected
        n = self.node
        n.create_subscription(String, 'calibration/result', self._keep(self.results), latched)
        n.create_subscription(String, 'calibration/learned', self._keep(self.learned),
                              latched)
        n.create_subscription(DiagnosticArray, '/diagnostics', self._on_learning, 50)
        n.create_subscription(MagneticField, 'sensor2/corrected', self._on_corrected, 50)

    def _keep(self, box):
        def cb(msg):
            with self.lock:
                box.append((self.now(), msg.data))
        return cb

    def _on_learning(self, msg):
        for st in msg.status:
            if st.name.endswith(DIAG_LEARN):
                with self.lock:
                    self.learning.append((self.now(), int.from_bytes(st.level, 'little')
                                          if isinstance(st.level, bytes) else int(st.level),
                                          st.message, {v.key: v.value for v in st.values}))

    def _on_corrected(self, msg):
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        with self.lock:
            self.corrected.append((self.now(), stamp))


def initial_calibration(path, field_nt, seed):
    """Calibrate the simulator's sensors on a tumble (offline) and write ``path``."""
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.io.calfile import save_calibration
    from magcal_ros.pipeline import calibrate
    data, _ = simulate(n_samples=3000, rate_hz=20.0, trajectory='smooth', seed=seed + 1000,
                       field_nt=field_nt)
    run = calibrate(data, 'base', field_nt)
    run.doc['provenance']['source'] = 'a tumble before the drive (scripts/demo.sh --learn)'
    save_calibration(path, run.doc, history=10)
    return run


def adoptions(client, t_sim0):
    """[(sim s, doc)] of the learned calibrations published on calibration/result."""
    from magcal_ros.io.calfile import parse_calibration
    with client.lock:
        results = list(client.results)
    out = []
    for t, text in results:
        _, doc = parse_calibration(text, 'calibration/result')
        if str(doc['provenance'].get('source', '')).startswith('learned'):
            out.append((t - t_sim0, doc))
    return out


def step(client, t_sim0, t_from, t_to, event):
    """
    One entry of ``steps``: the live residual in [t_from, t_to] sim s against its floor.

    The floor sigma_j is the noise of sensor j's scalar residual series from its high-order
    differences (:func:`magcal_ros.core.data.noise.noise_floor`, no model; as the loop demo's
    :func:`demo_loop.window_stats`); the vector residual's is
    sqrt(3 (sigma_j^2 + sum_{k != j} sigma_k^2 / (S - 1)^2)).  Every set counts (a change
    of one sensor puts every set's vector residual far off: none is left out here).
    """
    from magcal_ros.core.data.noise import noise_floor
    with client.lock:
        res = [r for r in client.residual if t_from + t_sim0 <= r[0] <= t_to + t_sim0]
    if len(res) < 100:
        raise RuntimeError(f'only {len(res)} calibration/residual messages between '
                           f'{t_from:.1f} and {t_to:.1f} s')
    scalar = np.array([r[1] for r in res])                  # (M, S) nT
    vector = np.array([r[2] for r in res])
    sigma = np.atleast_1d(noise_floor(scalar.T[:, :, None]))
    var = sigma ** 2
    vector_floor = np.sqrt(3 * (var + (var.sum() - var) / (N_SENSORS - 1) ** 2))

    def per_sensor(v):
        return {str(j + 1): round(float(x), 3) for j, x in enumerate(v)}
    return {'t': round(0.5 * (t_from + t_to), 2),
            'window_s': [round(t_from, 2), round(t_to, 2)],
            'event': event, 'scalar_rms_nt': per_sensor(np.sqrt(np.mean(scalar ** 2, 0))),
            'vector_rms_nt': per_sensor(np.sqrt(np.mean(vector ** 2, 0))),
            'floor_nt': per_sensor(sigma), 'vector_floor_nt': per_sensor(vector_floor),
            'sets': int(len(scalar))}


def print_step(s):
    """Print a step's residual per sensor against its floor."""
    print(f'{s["event"]} ({s["window_s"][0]:.0f}-{s["window_s"][1]:.0f} s, {s["sets"]} sets): '
          'live residual RMS (floor), nT')
    for kind, floor in (('scalar', 'floor_nt'), ('vector', 'vector_floor_nt')):
        print(f'  {kind:>6}: ' + ', '.join(
            f'{j}: {v:6.2f} ({s[floor][j]:.2f}) x{v / s[floor][j]:.2f}'
            for j, v in s[f'{kind}_rms_nt'].items()))


def summary(doc):
    """Return the learned calibration in brief (``learned`` of learn.json)."""
    learning = doc['provenance'].get('learning', {})
    return {'model': doc['model'], 'created': doc['provenance'].get('created'),
            'offset_nt': {str(s['id']): s['offset_nt'] for s in doc['sensors']},
            'undetermined': learning.get('undetermined'),
            'held_out_improvement': learning.get('held_out_improvement'),
            'held_out_improvement_stderr': learning.get('held_out_improvement_stderr'),
            'held_out_rms_nt': learning.get('held_out_rms_nt'),
            'fitted_window_s': learning.get('window_s'), 'sets': learning.get('sets')}


def write_figure(client, t_sim0, events, steps, path):
    """Draw the live residual over time with the change and the adoptions marked."""
    # the events and windows are in seconds since the simulator started
    return demo_loop.write_figure(
        client, [(te + t_sim0, label) for te, label in events],
        [{**s, 'window_s': [w + t_sim0 for w in s['window_s']]} for s in steps], path,
        t0=t_sim0, floor_step=0,
        title='calibration/residual while driving (live, one point per set; shaded: the '
              'RMS windows)', xlabel='time since the simulator started (s)')


def parse_args(argv=None):
    """Parse the command line of the learning demo."""
    p = argparse.ArgumentParser(prog='scripts/demo.sh --learn',
                                description=__doc__.strip().split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--learn', action='store_true', help='(this mode; given by demo.sh)')
    p.add_argument('--out', default='demo_out', help='output directory (default ./demo_out)')
    p.add_argument('--seed', type=int, default=0, help='seeds the simulator (default 0)')
    p.add_argument('--change-s', type=float, default=20.0,
                   help="time of sensor 2's offset step, s after the simulator started "
                        '(default 20)')
    p.add_argument('--persist-s', type=float, default=10.0,
                   help="the node's learn_persist_s: how long a change must last before it "
                        "is learned, s (default 10: the demo is short; the node's default 90 "
                        'lets a minute-long excursion pass)')
    p.add_argument('--refit-period-s', type=float, default=5.0,
                   help="the node's learn_refit_period_s, s (default 5)")
    p.add_argument('--settle-s', type=float, default=10.0,
                   help='after an adoption, wait this long for a refinement before measuring '
                        '"after learning", s (default 10)')
    p.add_argument('--window-s', type=float, default=12.0,
                   help='length of each residual window, s (default 12)')
    p.add_argument('--timeout-s', type=float, default=60.0,
                   help='give up when nothing is adopted this long after the change, s')
    p.add_argument('--rate', type=float, default=50.0,
                   help='samples per second per sensor, Hz (default 50)')
    p.add_argument('--field-nt', type=float, default=50000.0,
                   help='field magnitude of the simulator and the reference, nT')
    return p.parse_args(argv)


def _wait_until(client, procs, t_sim0, t_sim, what):
    """Sleep until the simulator's time ``t_sim`` s (the processes must stay up)."""
    while client.now() - t_sim0 < t_sim:
        if procs.dead():
            raise RuntimeError(f'process(es) stopped while waiting for {what}: {procs.dead()}')
        time.sleep(0.1)


def run(args, client, procs, t_sim0, result, events):
    """Watch the drive: before, after the change, after learning; fill ``result``."""
    change = args.change_s
    _wait_until(client, procs, t_sim0, change - 0.5, 'the change')
    t_from = max(2.0, change - 0.5 - args.window_s)
    result['steps'].append(step(client, t_sim0, t_from, change - 0.5, 'before the change'))
    print_step(result['steps'][-1])
    events.append((change, 'offset of sensor 2 changes'))
    # after it: the residual of the old calibration, before anything can be adopted
    end = change + min(args.window_s, args.persist_s - 0.5)
    _wait_until(client, procs, t_sim0, end, 'the residual after the change')
    result['steps'].append(step(client, t_sim0, change + 0.5, end, 'after the change'))
    print_step(result['steps'][-1])
    deadline = change + args.timeout_s
    while True:
        found = adoptions(client, t_sim0)
        now = client.now() - t_sim0
        if found and now - found[-1][0] >= args.settle_s:
            break
        if now > deadline:
            if not found:
                raise RuntimeError(f'nothing adopted within {args.timeout_s:g} s of the '
                                   f'change; learning: {last_learning(client)}')
            break
        if procs.dead():
            raise RuntimeError(f'process(es) stopped while learning: {procs.dead()}')
        time.sleep(0.2)
    for t, _ in found:
        events.append((t, 'adopted'))
        print(f'adopted a learned calibration at {t:.1f} s ({t - change:.1f} s after the '
              'change)')
    result['adopted_at_s'] = round(found[0][0], 2)
    result['adoptions_s'] = [round(t, 2) for t, _ in found]
    result['learned'] = summary(found[-1][1])
    t_from = found[-1][0] + 0.5
    _wait_until(client, procs, t_sim0, t_from + args.window_s, 'the residual after learning')
    result['steps'].append(step(client, t_sim0, t_from, t_from + args.window_s,
                                'after learning'))
    print_step(result['steps'][-1])
    # the corrector switched between two samples: no sample missing from its stream around
    # each adoption (the stamps of the corrected samples, those of the raw ones, run on)
    with client.lock:
        got = np.array(client.corrected)

    def longest(t0, t1):
        near = got[(got[:, 0] - t_sim0 > t0) & (got[:, 0] - t_sim0 < t1), 1]
        return float(np.diff(np.sort(near)).max()) if len(near) > 1 else float('inf')
    gaps = [longest(t - 2.0, t + 2.0) for t, _ in found]
    # the stamps' own jitter (the driver stamps on arrival): the same before the change
    result['corrector_gap_before_s'] = longest(2.0, change - 0.5)
    result['corrector_max_gap_s'] = gaps
    print('corrector (sensor2/corrected): longest interval between the stamps of two '
          'consecutive samples within 2 s of each adoption: '
          + ', '.join(f'{g * 1000:.0f} ms' for g in gaps)
          + f'; before the change {result["corrector_gap_before_s"] * 1000:.0f} ms '
          f'(sample period {1000 / args.rate:.0f} ms)')


def last_learning(client):
    """Return the last learning status on /diagnostics, as text."""
    with client.lock:
        got = list(client.learning)
    return got[-1][2] if got else 'no calibration_node: learning status seen'


def judge(result, args, failures):
    """Return True when the residual returned within RETURN_FACTOR x its floor."""
    steps = {s['event']: s for s in result['steps']}
    after = steps.get('after learning')
    if after is None:
        failures.append('no residual after learning')
        return False
    left = []
    for kind, floor in (('scalar', 'floor_nt'), ('vector', 'vector_floor_nt')):
        for j, v in after[f'{kind}_rms_nt'].items():
            if v > RETURN_FACTOR * after[floor][j]:
                left.append(f'sensor {j} {kind} {v:.2f} nT = x{v / after[floor][j]:.2f} its '
                            f'floor {after[floor][j]:.2f} nT')
    if left:
        failures.append(f'the residual did not return within {RETURN_FACTOR} x its floor: '
                        + '; '.join(left))
    changed = steps.get('after the change')
    if changed is not None:
        worst = max(v / changed['floor_nt'][j] for j, v in changed['scalar_rms_nt'].items())
        if worst < 1.5:
            failures.append(f'the change did not show in the residual (x{worst:.2f})')
    period = 1.0 / args.rate
    for t, gap in zip(result.get('adoptions_s', []), result.get('corrector_max_gap_s', [])):
        if not gap <= MAX_GAP_PERIODS * period:
            failures.append(f'the corrector stream of sensor 2 had a gap of {gap:.3f} s at '
                            f'the adoption at {t:.1f} s (more than {MAX_GAP_PERIODS} periods: '
                            'samples lost while it switched)')
    return not failures


def learn_json(result):
    """learn.json: exactly the keys of issue 34 (the scalar floor per sensor as floor_nt)."""
    return {'change': result['change'],
            'steps': [{k: s[k] for k in ('t', 'event', 'scalar_rms_nt', 'vector_rms_nt',
                                         'floor_nt')} for s in result['steps']],
            'adopted_at_s': result['adopted_at_s'], 'learned': result['learned']}


def main(argv=None):
    """Run the learning demo; return the exit status."""
    args = parse_args(argv)
    demo._ensure_ros_env()
    out_dir = os.path.abspath(args.out)
    os.makedirs(out_dir, exist_ok=True)
    sim_dir = tempfile.mkdtemp(prefix='magcal_learn_sim_')
    cal_dir = os.path.join(out_dir, 'learn_calibration')
    shutil.rmtree(cal_dir, ignore_errors=True)
    os.makedirs(cal_dir)
    cal_file = os.path.join(cal_dir, 'calibration.yaml')
    change = f'offset(step({args.change_s:g}))@2=' + ','.join(f'{v:g}' for v in CHANGE_VALUES)
    print(f'magcal_ros learning demo: ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}, output in '
          f"{out_dir}; the vehicle drives, sensor 2's offset changes at {args.change_s:g} s "
          f'({change})')
    initial_calibration(cal_file, args.field_nt, args.seed)
    print(f'calibrated on a tumble before the drive: {cal_file}')

    import rclpy
    from rclpy.context import Context
    procs = demo.Processes(os.path.join(out_dir, 'logs'))
    context = Context()
    rclpy.init(context=context)
    client = None
    failures, events = [], []
    result = {'change': change, 'steps': [], 'adopted_at_s': None, 'learned': None}
    t_sim0 = None
    try:
        ros = ['--ros-args', '-r', f'__ns:={NAMESPACE}']
        client = LearnClient(rclpy, context)
        procs.start('calibration_node', ros + [
            '--params-file', str(ROOT / 'config' / 'calibration.yaml'),
            '-p', f'calibration_file:={cal_file}',
            '-p', f'report_dir:={os.path.join(out_dir, "report")}',
            '-p', f'field_nt:={args.field_nt}', '-p', 'imu_topic:=imu',
            '-p', 'learn:=true', '-p', 'auto_adopt:=true',
            '-p', f'learn_persist_s:={args.persist_s}',
            '-p', f'learn_refit_period_s:={args.refit_period_s}'])
        procs.start('corrector_node', ros + ['-p', f'calibration_file:={cal_file}'])
        demo._wait(lambda: client.results, 60, 'the calibration on calibration/result', procs)
        procs.start('fluxgate_sim', ['--dir', sim_dir, '--seed', str(args.seed),
                                     '--field-nt', str(args.field_nt), '--rate', str(args.rate),
                                     '--trajectory', 'vehicle']
                    + ros + ['-p', 'imu_topic:=imu', '-p', f'truth:={json.dumps([change])}'])
        ports = [os.path.join(sim_dir, f'fluxgate{j}') for j in range(1, N_SENSORS + 1)]
        demo._wait(lambda: all(os.path.exists(p) for p in ports), 15, 'the simulated ports',
                   procs)
        t_sim0 = client.now()               # the stream starts as its ports appear
        procs.start('fluxgate_driver', ros + [a for j, p in enumerate(ports, 1)
                                              for a in ('-p', f'sensor{j}.port:={p}',
                                                        '-p', f'sensor{j}.expected_rate_hz:='
                                                        f'{args.rate}')])
        print(f'started calibration_node (learn, auto_adopt), corrector_node, fluxgate_sim '
              f'(vehicle), fluxgate_driver (logs in {procs.log_dir})')
        demo._wait(lambda: np.all(client.raw_count > 10), 30, 'raw samples of all sensors',
                   procs)
        client.stop_counting_raw()
        run(args, client, procs, t_sim0, result, events)
    except (RuntimeError, TimeoutError, ValueError) as exc:
        failures.append(str(exc))
    except KeyboardInterrupt:
        failures.append('interrupted')
    finally:
        demo.shut_down(client, rclpy, context, procs, sim_dir, failures)
    ok = judge(result, args, failures) and not failures
    figure = None
    if client is not None and t_sim0 is not None:
        figure = write_figure(client, t_sim0, events, result['steps'],
                              os.path.join(out_dir, 'learn.png'))
    with open(os.path.join(out_dir, 'learn.json'), 'w') as fh:
        json.dump(learn_json(result), fh, indent=2)
    print(f'figure: {figure}\nnumbers: {os.path.join(out_dir, "learn.json")}')
    if not ok:
        print('\nRESIDUAL NOT RETURNED:\n- ' + '\n- '.join(failures), file=sys.stderr)
        print('learning demo FAILED (see above)')
        return 1
    print(f'\nlearned: the live residual of every sensor is back within {RETURN_FACTOR} x its '
          'floor after the change')
    return 0


if __name__ == '__main__':
    sys.exit(main())
