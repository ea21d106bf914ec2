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
and the ratio composition / alias, and the chi-square of both (the same fit: equal to the
optimiser's tolerance, except drift2 whose composition is centred and scaled differently).

    python bench/grammar_speed.py                  # 4 x 10 000 epochs, 3 repeats
    python bench/grammar_speed.py --n 3000 --repeat 2
"""
import argparse
import time

from magcal_ros.core.model import fit
from magcal_ros.core.data.simulate import simulate

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
    best, res = float('inf'), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = fit(data, formula, 50000.0, check_identifiability=False, on_degenerate='flag')
        best = min(best, time.perf_counter() - t0)
    return best, res


def main():
    """Run the pairs and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--n', type=int, default=10000, help='epochs (default 10 000)')
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args()
    print(f'fit time, 4 sensors x {args.n} epochs over 600 s, best of {args.repeat}')
    print(f'{"alias":28s} {"composition":46s} {"alias s":>8s} {"comp s":>8s} {"ratio":>6s}'
          f' {"chi2 alias":>11s} {"chi2 comp":>11s}')
    for alias, comp, truth in PAIRS:
        data, _ = simulate(n_samples=args.n, rate_hz=args.n / 600.0, trajectory='smooth',
                           seed=3, truth=truth)
        ta, ra = _time(data, 'base + ' + alias, 1)          # warm-up of both paths
        tc, rc = _time(data, 'base + ' + comp, 1)
        ta, ra = _time(data, 'base + ' + alias, args.repeat)
        tc, rc = _time(data, 'base + ' + comp, args.repeat)
        print(f'{alias:28s} {comp:46s} {ta:8.2f} {tc:8.2f} {tc / ta:6.2f} {ra.chi2:11.1f}'
              f' {rc.chi2:11.1f}', flush=True)


if __name__ == '__main__':
    main()
