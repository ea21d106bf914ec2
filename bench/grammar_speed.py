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
Fit time of a composed term against today's equivalent alias, side by side on the same data.

For each pair (alias token, the composition it stands for: docs/formulas.md) the data are
simulated once (4 sensors, paper 004 errors, 3 nT noise, 'smooth' tumbling over 600 s, the
alias's effect switched on), then ``fit(data, 'base + <term>')`` is timed for the alias and
the composition alternately, ``--repeat`` times each; the table gives the best time of each
and the ratio composition / alias (wall clock, and this process's CPU time, which a
loaded machine disturbs less), the optimiser's evaluations and the chi-square of both
(the same fit: equal to the optimiser's tolerance, except drift2 whose composition is
centred and scaled differently).

    python bench/grammar_speed.py                  # 4 x 10 000 epochs, 3 repeats
    python bench/grammar_speed.py --n 3000 --repeat 2
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
from magcal_ros.core.data.simulate import simulate  # noqa: E402
from magcal_ros.core.model import fit  # noqa: E402

PAIRS = [
    ('drift2', 'offset(poly(t, 2))', {'drift2': [0.02, -0.01, 0.01, 1e-5, 0, -1e-5]}),
    ('periodic(0.05)@3', 'offset(sin(0.05))@3', {'periodic(0.05)@3': [8, -5, 3, 2, 4, -6]}),
    ('step(300)@2', 'offset(step(300))@2', {'step(300)@2': [20, -10, 5]}),
    ('aux:aux_motor_current@3', 'offset(aux_motor_current)@3',
     {'aux:aux_motor_current@3': [8.0, -5.0, 3.0]}),
    ('temperature@2', 'offset(temperature)@2 + scale(temperature)@2',
     {'temperature@2': [2.0, -1.5, 1.0, 1e-4, 0.0, 0.0]}),
    ('lag(temperature)@2', 'offset(lag(temperature))@2',
     {'lag(temperature)@2': [2.0, -1.5, 1.0, 40.0]}),
    ('field_rate@2', 'offset(rate)@2', {'field_rate@2': [0.02, -0.01, 0.01]}),
]


def _time(data, formula, repeat):
    """Best wall and CPU (this process) time of ``repeat`` fits, and the last result."""
    best, cpu, res = float('inf'), float('inf'), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        res = fit(data, formula, 50000.0, check_identifiability=False, on_degenerate='flag')
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return best, cpu, res


def main(argv=None):
    """Run the pairs, print the table and write bench/results/grammar_speed.json."""
    started = time.perf_counter()
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--n', type=int, default=10000, help='epochs (default 10 000)')
    ap.add_argument('--repeat', type=int, default=3)
    ap.add_argument('--pairs', type=int, default=len(PAIRS), help='the first K pairs only')
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    rows, results = [], []
    for alias, comp, truth in PAIRS[:args.pairs]:
        data, _ = simulate(n_samples=args.n, rate_hz=args.n / 600.0, trajectory='smooth',
                           seed=3, truth=truth)
        _time(data, 'base + ' + alias, 1)                   # warm-up of both paths
        _time(data, 'base + ' + comp, 1)
        ta, ca, ra = _time(data, 'base + ' + alias, args.repeat)
        tc, cc, rc = _time(data, 'base + ' + comp, args.repeat)
        results.append({'alias': alias, 'composition': comp, 'wall_alias_s': ta,
                        'wall_comp_s': tc, 'cpu_alias_s': ca, 'cpu_comp_s': cc,
                        'nfev_alias': int(ra.nfev), 'nfev_comp': int(rc.nfev),
                        'chi2_alias': float(ra.chi2), 'chi2_comp': float(rc.chi2)})
        rows.append([alias, comp, ta, tc, tc / ta, ca, cc, cc / ca,
                     f'{ra.nfev}/{rc.nfev}', f'{ra.chi2:.1f}', f'{rc.chi2:.1f}'])
    tab = common.table(['alias', 'composition', 'wall alias s', 'wall comp s', 'ratio',
                        'CPU alias s', 'CPU comp s', 'ratio', 'nfev', 'chi2 alias',
                        'chi2 comp'], rows,
                       title=f'fit time, 4 sensors x {args.n} epochs over 600 s, best of '
                             f'{args.repeat}')
    print(tab)
    common.write_result('grammar_speed', {'n': args.n, 'repeat': args.repeat}, {
        'pairs': results}, [tab], args.out_dir, started)


if __name__ == '__main__':
    main()
