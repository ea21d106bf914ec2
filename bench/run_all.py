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
Run every benchmark (one subprocess each) and refresh the results section of BENCHMARKS.md.

    python bench/run_all.py            # full run (about 16 min on this 2-core machine)
    python bench/run_all.py --quick    # reduced settings (a few minutes)
    python bench/run_all.py --only accuracy papers

Results: bench/results/<name>.json (machine, settings, figures, tables); with
``--update-doc`` (default for a full run) the block between the RESULTS markers of
BENCHMARKS.md is regenerated from those files (bench/report.py).
"""
import argparse
import os
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402

BENCHES = {
    'accuracy': (['accuracy.py'], ['--seeds', '10', '--holdout', '500']),
    'papers': (['papers.py'], ['--seeds', '10', '--holdout', '500']),
    'solve_time': (['solve_time.py'], ['--sizes', '1000', '10000', '100000',
                                       '--diagnose-max-n', '10000']),
    'live': (['live.py'], ['--rates', '100', '1000', '--duration', '4', '--no-search']),
    'driver_rate': (['driver_rate.py'], ['--samples', '5000', '--pty-mbytes', '2',
                                         '--node-duration', '4']),
    'real_data': (['real_data.py'], ['--no-diagnose']),
    'workbench': (['workbench.py'], ['--sizes', '3000', '--no-ladder']),
    'report_layout': (['report_layout.py'], ['--n', '10000', '--repeat', '3']),
    'pairing': (['pairing.py'], ['--epochs', '2000', '--repeats', '3']),
    'executor': (['executor.py'], ['--rate', '200', '--duration', '8', '--repeats', '3']),
    'grammar_speed': (['grammar_speed.py'], ['--n', '10000', '--repeat', '3']),
    # the hour-long series: python bench/scale.py --base <tree of c43534d> (BENCHMARKS.md)
    'scale': (['scale.py'], ['--sizes', '10000', '100000', '--bag-max', '10000']),
    'reduction_accuracy': (['reduction_accuracy.py'], ['--sizes', '10000', '200000']),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='reduced settings')
    ap.add_argument('--only', nargs='+', choices=list(BENCHES), default=list(BENCHES))
    ap.add_argument('--update-doc', dest='update_doc', action='store_true', default=None,
                    help='regenerate the results section of BENCHMARKS.md (default: full run)')
    ap.add_argument('--no-update-doc', dest='update_doc', action='store_false')
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    update_doc = (not args.quick) if args.update_doc is None else args.update_doc
    status = {}
    t_all = time.perf_counter()
    for name in args.only:
        script, quick = BENCHES[name]
        cmd = [sys.executable, os.path.join(common.BENCH_DIR, script[0]), '--out-dir',
               args.out_dir] + (quick if args.quick else [])
        print(f'== {name}: {" ".join(cmd[1:])}', flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd)
        status[name] = {'exit_code': rc, 'seconds': time.perf_counter() - t0}
        print(f'== {name}: exit {rc} in {status[name]["seconds"]:.0f} s', flush=True)
    total = time.perf_counter() - t_all
    print(f'\nall benchmarks: {total:.0f} s; '
          + ', '.join(f'{k} {v["exit_code"]}' for k, v in status.items()))
    if update_doc:
        import report
        path = report.update(args.out_dir)
        print(f'updated {path}')
    return 0 if all(v['exit_code'] == 0 for v in status.values()) else 1


if __name__ == '__main__':
    sys.exit(main())
