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
The attitude-aided fit on simulated vehicles: accuracy, honesty of its uncertainties, time.

One compass (paper 004's sensor 1 errors, 3 nT noise) on the simulator's vehicle: heading
swinging through part circles, roll and pitch within +-tilt, 10 Hz, ``--n`` epochs, its
attitude spoiled by a smooth error of ``--att-err`` deg RMS per axis (the simulator's
``attitude_error_deg``).  For each tilt and mode (``tilt``: roll and pitch; ``full``: the
heading too) over ``--seeds`` seeds: the scalar residual over the true noise, the z-values
(estimate - truth) / stated sd of the determined parameters (their RMS is 1 when the
uncertainties are right; a widening for correlation makes it below 1), the parameters named
undetermined, and the fit's CPU time.  The magnitude-only fit is refused on all of these.

    python bench/attitude_aided.py                       # tilts 2, 5, 15, 30 deg, 10 seeds
    python bench/attitude_aided.py --seeds 3 --tilts 15
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
from magcal_ros.core.data.simulate import simulate  # noqa: E402
from magcal_ros.core.model.attitude_fit import fit_attitude  # noqa: E402
import numpy as np  # noqa: E402


def run_case(tilt, mode, seeds, n, att_err):
    """Return the summary dict of one (tilt, mode) over ``seeds``."""
    ratio, zs, cpu, open_ = [], [], [], {}
    for seed in range(seeds):
        data, sim = simulate(n_samples=n, rate_hz=10, n_sensors=1, trajectory='vehicle',
                             tilt_deg=tilt, attitude=True, seed=seed, aux=False,
                             temp_swing_c=0, attitude_error_deg=att_err)
        c0 = time.process_time()
        ar = fit_attitude(data, 'base', field_nt=50000.0, mode=mode)
        cpu.append(time.process_time() - c0)
        r = ar.result
        ratio.append(r.scalar_rms_nt[1] / 3.0)
        labels = [f'{lab}.{nm}@{j}' for j, lab, nm, _ in r.model.param_info()]
        for i in range(9):
            if labels[i] in ar.determined:
                zs.append((r.params[i] - sim.params[i]) / r.stderr[i])
            else:
                open_[labels[i]] = open_.get(labels[i], 0) + 1
    zs = np.array(zs)
    return {'tilt_deg': tilt, 'mode': mode, 'seeds': seeds,
            'residual_over_noise_median': float(np.median(ratio)),
            'z_rms': float(np.sqrt(np.mean(zs ** 2))) if len(zs) else None,
            'z_max_abs': float(np.max(np.abs(zs))) if len(zs) else None,
            'n_z': int(len(zs)), 'undetermined_counts': open_,
            'cpu_s_median': float(np.median(cpu))}


def main(argv=None):
    """Run the cases, print the table and write bench/results/attitude_aided.json."""
    started = time.perf_counter()
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--n', type=int, default=3000, help='epochs (default 3000, 300 s)')
    ap.add_argument('--seeds', type=int, default=10)
    ap.add_argument('--att-err', type=float, default=0.3, help='attitude error, deg RMS')
    ap.add_argument('--tilts', type=float, nargs='+', default=[2.0, 5.0, 15.0, 30.0])
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    results, rows = [], []
    for tilt in args.tilts:
        for mode in ('tilt', 'full'):
            r = run_case(tilt, mode, args.seeds, args.n, args.att_err)
            results.append(r)
            counts = sorted(r['undetermined_counts'].items())
            rows.append([f'{tilt:g}', mode, r['residual_over_noise_median'],
                         r['z_rms'], r['z_max_abs'], r['n_z'],
                         ', '.join(f'{k} ({v})' for k, v in counts) or 'none',
                         r['cpu_s_median']])
    tab = common.table(['tilt deg', 'mode', 'resid/noise', 'z RMS', 'max |z|', 'z values',
                        'undetermined (seeds)', 'CPU s'], rows,
                       title=f'one compass, {args.n} epochs at 10 Hz, attitude error '
                             f'{args.att_err:g} deg RMS, {args.seeds} seeds')
    print(tab)
    common.write_result('attitude_aided', vars(args) | {'out_dir': None}, {'cases': results},
                        [tab], args.out_dir, started)


if __name__ == '__main__':
    main()
