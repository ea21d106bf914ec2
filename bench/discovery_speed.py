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
Speed of ``diagnose`` with the formula search, side by side with an earlier tree.

For each size N and each case of test/discovery_cases.py named (default: a control and the
rotor), the record is written once to CSV; each code (this tree, and ``--before DIR``, a
tree extracted with ``git archive REV magcal_ros | tar -x -C DIR``) runs in its own
process: the base fit, then ``diagnose(data, base=fit)`` timed (wall and CPU time of the
process, which another process on a shared machine does not inflate), with the seconds of
each stage.  The codes alternate; with ``--repeat R`` the fastest of R is kept.  The ratio
after/before is the figure to read.

    git archive c43534d magcal_ros | tar -x -C /tmp/main_code
    python bench/discovery_speed.py --before /tmp/main_code --sizes 10000
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(BENCH_DIR)

CHILD = r"""
import json, os, sys, time
try:
    from magcal_ros.core.discovery import diagnose
except ImportError:                       # before core/discovery
    from magcal_ros.core.diagnose import diagnose
try:
    from magcal_ros.core.model import fit
except ImportError:
    from magcal_ros.core.fitting import fit
from magcal_ros.io.csvio import read_csv
data = read_csv(sys.argv[1])
base = fit(data, 'base', field_nt=data.ref_total)
load = os.getloadavg()[0]
w0, c0 = time.perf_counter(), time.process_time()
d = diagnose(data, 'base', field_nt=data.ref_total, base=base)
print(json.dumps({'wall_s': time.perf_counter() - w0, 'cpu_s': time.process_time() - c0,
                  'stages': d.seconds, 'verdict': d.verdict_token, 'load': load}))
"""


def _run(code, path):
    env = dict(os.environ, PYTHONPATH=code, OMP_NUM_THREADS='1', OPENBLAS_NUM_THREADS='1')
    p = subprocess.run([sys.executable, '-c', CHILD, path], env=env, capture_output=True,
                       text=True, cwd=os.path.dirname(path), timeout=1800)
    if p.returncode:
        raise RuntimeError(p.stderr.strip().splitlines()[-1])
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None):
    """Time diagnose with both codes; print a table and write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[10000])
    ap.add_argument('--cases', nargs='+', default=['control', 'rotor'])
    ap.add_argument('--before', help='tree of the earlier code (git archive ... | tar -x)')
    ap.add_argument('--repeat', type=int, default=1)
    ap.add_argument('--out', help='JSON file to write')
    args = ap.parse_args(argv)
    sys.path[:0] = [ROOT, os.path.join(ROOT, 'test')]
    import discovery_cases as dc
    from magcal_ros.io.csvio import write_csv
    codes = [('after', ROOT)] + ([('before', args.before)] if args.before else [])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            for name in args.cases:
                path = os.path.join(tmp, f'{name}_{n}.csv')
                write_csv(path, dc.BY_NAME[name].data(n))
                best = {}
                for _ in range(args.repeat):
                    for label, code in codes:
                        r = _run(code, path)
                        if label not in best or r['cpu_s'] < best[label]['cpu_s']:
                            best[label] = r
                row = {'case': name, 'n': n, **best}
                if 'before' in best:
                    row['ratio_cpu'] = best['after']['cpu_s'] / best['before']['cpu_s']
                    row['ratio_wall'] = best['after']['wall_s'] / best['before']['wall_s']
                rows.append(row)
                a = best['after']
                line = (f'{name:10s} {n:6d}  after {a["wall_s"]:6.2f} s wall '
                        f'{a["cpu_s"]:6.2f} s CPU (search '
                        f'{a["stages"].get("search", 0.0):.2f} s)')
                if 'before' in best:
                    b = best['before']
                    line += (f'  before {b["wall_s"]:6.2f} s wall {b["cpu_s"]:6.2f} s CPU  '
                             f'ratio CPU {row["ratio_cpu"]:.2f}')
                print(line + f'  load {a["load"]:.1f}', flush=True)
    if args.out:
        with open(args.out, 'w') as fh:
            json.dump(rows, fh, indent=1)


if __name__ == '__main__':
    main()
