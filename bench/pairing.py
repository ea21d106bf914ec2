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
Per-sample cost of the corrector's set pairing with and without the data check, side by side.

The corrector node calls :meth:`LiveCorrector.gradients` once per corrected sample while
someone subscribes a gradient topic (the set matcher, the tensor and, with
``check_pairing``, the chi-square of every set and the re-pairing of a shifted stream).
This times that call alone (CPU time of the process), on the same corrected samples, with
the check on and off, interleaved repetitions in one process (their ratio is what to read;
the absolute figure depends on the machine and its load).  Streams of 4 sensors at
``--rate`` Hz of an array turning at ``--turn`` rad/s (the field is written here: a uniform
field seen from a rotating frame; 3 nT of noise):

- ``clean``: arrival = sampling instant + 0.3 ms + exponential (mean 1 ms);
- ``loaded``: plus a starved reader (0.1-0.5 s, 0.3 times a second per stream) and lost
  samples (one every 2 s in sensor 3, a run of 3 once), the test_live_pairing load.

    python bench/pairing.py
    python bench/pairing.py --epochs 2000 --repeats 3          # tiny
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
from magcal_ros.core.geometry.tensor import cross_positions  # noqa: E402
from magcal_ros.core.live.corrector import LiveCorrector  # noqa: E402
from magcal_ros.core.model import Calibration, Model  # noqa: E402
import numpy as np  # noqa: E402

SIGMA_NT = 3.0


def _calibration():
    """Return a calibration of identity sensors (the cost does not depend on its values)."""
    model = Model.from_spec('base', 4)
    return Calibration(model, model.default_params(), sigma_nt=np.full(4, SIGMA_NT))


def _stream(rate_hz, n, loaded, seed, turn_rad_s):
    """(stamp s, sensor 0-based, corrected field (3,) nT) in arrival order."""
    rng = np.random.default_rng(seed)
    period = 1.0 / rate_hz
    t = period * np.arange(n)
    a, b = turn_rad_s * t, 0.57 * turn_rad_s * t
    field = np.stack([np.cos(a) * 20000.0, np.sin(a) * 20000.0 * np.cos(b),
                      45000.0 + 2000.0 * np.sin(b)], axis=1)             # (n, 3) nT
    events = []
    for j in range(4):
        arrival = 100.0 + t + 0.0003 + rng.exponential(0.001, n)
        keep = np.ones(n, bool)
        if loaded:
            s = t[0]
            while True:
                s += rng.exponential(1.0 / 0.3)
                if s > t[-1]:
                    break
                end = s + rng.uniform(0.1, 0.5)
                late = (arrival >= 100.0 + s) & (arrival < 100.0 + end)
                arrival[late] = 100.0 + end
            if j == 2:
                keep[int(rate_hz)::int(2 * rate_hz)] = False
                keep[n // 2:n // 2 + 3] = False
        arrival = np.maximum.accumulate(arrival)            # a stream arrives in order
        noise = rng.normal(scale=SIGMA_NT, size=(n, 3))
        events += [(arrival[k], j, field[k] + noise[k]) for k in np.flatnonzero(keep)]
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def _time(events, check, pos):
    live = LiveCorrector(_calibration(), 4, pos, stamp_tolerance_s=0.002,
                         check_pairing=check)
    t0 = time.process_time()         # CPU time: the machine's other jobs do not count
    n_out = 0
    for stamp, j, b in events:
        n_out += len(live.gradients(j + 1, stamp, b))
    dt = time.process_time() - t0
    m = live.matcher
    return dt / len(events), {'tensors': n_out, 'rejected': m.rejected,
                              'repaired': m.repaired, 'incomplete': m.incomplete}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--rate', type=float, default=1000.0, help='Hz per sensor')
    ap.add_argument('--epochs', type=int, default=20000, help='samples per sensor')
    ap.add_argument('--repeats', type=int, default=5, help='interleaved repetitions')
    ap.add_argument('--turn', type=float, default=2.0,
                    help='turn rate of the array, rad/s (2: ~40 nT per epoch at 1 kHz)')
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    pos = cross_positions(0.5)
    results, rows = {}, []
    for case in ('clean', 'loaded'):
        events = _stream(args.rate, args.epochs, case == 'loaded', 1, args.turn)
        cost = {False: [], True: []}
        counts = {}
        for _ in range(args.repeats):
            for check in (False, True):
                c, counts[check] = _time(events, check, pos)
                cost[check].append(c)
        off, on = (float(np.median(cost[k])) * 1e6 for k in (False, True))
        results[case] = {'us_per_sample_stamps_only': off, 'us_per_sample_checked': on,
                         'ratio': on / off, 'stamps_only': counts[False],
                         'checked': counts[True], 'samples': len(events)}
        rows.append([case, len(events), off, on, on / off, counts[False]['tensors'],
                     counts[True]['tensors'], counts[True]['rejected'],
                     counts[True]['repaired']])
    tab = common.table(['stream', 'samples', 'us/sample stamps only', 'us/sample checked',
                        'ratio', 'tensors stamps only', 'tensors checked', 'rejected',
                        'repaired'], rows,
                       title=f'LiveCorrector.gradients per sample, 4 x {args.rate:g} Hz '
                             f'(median of {args.repeats})')
    print(tab)
    path = common.write_result('pairing', vars(args), results, [tab], args.out_dir,
                               started)
    print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
