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
Scale series: `magcal fit` and `magcal diagnose` from 1e4 to 3.6e6 sets (issue 19).

One hour of the four-fluxgate cross at 1 kHz is 3.6e6 sets (a 0.72 GB wide CSV) with a
hidden temperature effect on sensor 2 (``magcal simulate --rate 1000 --truth
temperature@2=3,-2,1.5,0,0,0``; below a minute the smooth trajectory has not turned the
array over: ``--flag-degenerate``, and ``fit --force``: a few seconds need not converge).
For each size the two commands run as processes of their own, this tree's code and, with
``--base DIR``, another tree's (the code before the chunked reading: ``git worktree add
/work/wt/base c43534d``) up to ``--base-max`` sets;
wall time, CPU time (user + system of the process: on a shared machine the wall time
grows with the other processes' load, the CPU time does not; BLAS runs on one thread)
and peak resident memory (``ru_maxrss``, MB) are recorded with the verdict.
``--bag-max``: the same series from rosbag2 recordings (sqlite3 and MCAP) up to that size,
and the time of the rosbags library's own read loop (deserialise every message) on the
same bag, against which the reading is measured.

    python bench/scale.py --base /work/wt/base            # ~1 h on an idle 2-core machine
    python bench/scale.py --sizes 10000 100000 --bag-max 100000   # a few minutes

Writes bench/results/scale.json and bench/results/scale.png (time and memory against sets).
"""
import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import time

from common import add_common_args, REPO_DIR, table, write_result  # noqa: I100

TRUTH = 'temperature@2=3,-2,1.5,0,0,0'


def rusage_of(cmd, code_dir):
    """Wall s, CPU s, peak RSS MB, exit code, stdout of ``cmd`` (os.wait4 of the child)."""
    import tempfile
    env = dict(os.environ, PYTHONPATH=code_dir)
    with tempfile.TemporaryFile('w+') as out, open(os.devnull, 'w') as devnull:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, cwd=code_dir, env=env, stdout=out, stderr=devnull)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        text = out.read()
    cpu = usage.ru_utime + usage.ru_stime
    return wall, cpu, usage.ru_maxrss / 1024.0, os.waitstatus_to_exitcode(status), text


def simulate(path, n, code_dir):
    """Write the n-set recording (this tree's `magcal simulate`) unless it exists."""
    if not os.path.exists(path):
        subprocess.run([sys.executable, '-m', 'magcal_ros.cli', 'simulate', '--out', path,
                        '--n', str(n), '--rate', '1000', '--truth', TRUTH, '--seed', '19'],
                       cwd=code_dir, env=dict(os.environ, PYTHONPATH=code_dir), check=True)


def to_bag(csv_path, bag_path, storage):
    """Convert a wide CSV to a rosbag2 directory, chunk by chunk (this tree's code)."""
    if os.path.exists(bag_path):
        return
    from magcal_ros.io.bag import write_bag
    from magcal_ros.io.chunks import open_record
    write_bag(bag_path, open_record(csv_path).chunks(), storage=storage)


def rosbags_loop(bag_path):
    """CPU seconds of the rosbags library's own read loop: every message read, deserialised."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import get_typestore, Stores
    t0 = time.process_time()
    with AnyReader([Path(os.path.abspath(bag_path))],
                   default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for c, _, raw in reader.messages():
            reader.deserialize(raw, c.msgtype)
    return time.process_time() - t0


def read_time(bag_path):
    """CPU seconds this tree takes to read and reduce the bag (io.bag.bag_chunks)."""
    from magcal_ros.core.data.reduce import reduce_chunks
    from magcal_ros.io.chunks import open_record
    t0 = time.process_time()
    reduce_chunks(open_record(bag_path).chunks())
    return time.process_time() - t0


def series(data, code, code_dir, rows, field):
    """Run fit and diagnose of ``data`` with ``code_dir``'s magcal; append to ``rows``."""
    for cmd in ('fit', 'diagnose'):
        argv = [sys.executable, '-m', 'magcal_ros.cli', cmd, data, '--field-nt', field,
                '--json', '--flag-degenerate'] + (['-q'] if cmd == 'diagnose' else ['--force'])
        wall, cpu, rss, rc, out = rusage_of(argv, code_dir)
        verdict = None
        if rc == 0 and cmd == 'diagnose':
            v = json.loads(out).get('verdict') or {}
            verdict = v.get('effect', 'none') + (f'@{v["sensor"]}' if v.get('sensor') else '')
        rows.append({'code': code, 'command': cmd, 'wall_s': round(wall, 2),
                     'cpu_s': round(cpu, 2),
                     'peak_rss_mb': round(rss, 1), 'exit': rc, 'verdict': verdict})
        print(rows[-1], flush=True)


def plot(results, path):
    """Wall time and peak RSS against sets, log-log, one line per code x input x command."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    lines = {}
    for r in results:
        if r['exit'] != 0:
            continue
        key = (r['code'], r['input'], r['command'])
        lines.setdefault(key, []).append((r['sets'], r['cpu_s'], r['peak_rss_mb']))
    for (code, inp, cmd), pts in sorted(lines.items()):
        pts.sort()
        n = [p[0] for p in pts]
        style = '-' if code == 'this tree' else '--'
        label = f'{cmd} {inp} ({code})'
        axes[0].loglog(n, [p[1] for p in pts], style, marker='o', label=label)
        axes[1].loglog(n, [p[2] for p in pts], style, marker='o', label=label)
    axes[0].axhline(60, color='grey', lw=0.8)
    axes[1].axhline(1024, color='grey', lw=0.8)
    axes[0].set(xlabel='sets (4 sensors)', ylabel='CPU time of the process, s',
                title='time (goal 60 s)')
    axes[1].set(xlabel='sets (4 sensors)', ylabel='peak RSS, MB', title='memory (goal 1 GB)')
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main():
    """Run the series and write bench/results/scale.json and scale.png."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[10000, 100000, 1000000, 3600000])
    ap.add_argument('--data-dir', default='/tmp/magcal_scale')
    ap.add_argument('--base', help='tree of the code to compare with (e.g. /work/wt/base)')
    ap.add_argument('--base-max', type=int, default=3600000,
                    help='largest size run with the --base code')
    ap.add_argument('--bag-max', type=int, default=0,
                    help='largest size also run from rosbag2 (sqlite3 and mcap); 0: none')
    add_common_args(ap)
    args = ap.parse_args()
    started = time.perf_counter()
    os.makedirs(args.data_dir, exist_ok=True)
    results, reads = [], []
    for n in args.sizes:
        csv_path = os.path.join(args.data_dir, f'cross_{n}.csv')
        simulate(csv_path, n, REPO_DIR)
        inputs = [('csv', csv_path)]
        if n <= args.bag_max:
            for storage in ('sqlite3', 'mcap'):
                bag = os.path.join(args.data_dir, f'cross_{n}_{storage}')
                to_bag(csv_path, bag, storage)
                inputs.append((f'bag {storage}', bag))
                reads.append({'sets': n, 'storage': storage,
                              'rosbags_loop_s': round(rosbags_loop(bag), 2),
                              'magcal_read_s': round(read_time(bag), 2)})
                print(reads[-1], flush=True)
        for inp, path in inputs:
            codes = [('this tree', REPO_DIR)]
            if args.base and n <= args.base_max:
                codes.append(('c43534d', os.path.abspath(args.base)))
            for code, code_dir in codes:
                rows = []
                series(path, code, code_dir, rows, '50000')
                for r in rows:
                    r.update(sets=n, input=inp)
                results.extend(rows)
    tables = [table(['sets', 'input', 'code', 'command', 'wall s', 'CPU s', 'peak RSS MB',
                     'verdict'],
                    [[r['sets'], r['input'], r['code'], r['command'], f'{r["wall_s"]:.1f}',
                      f'{r["cpu_s"]:.1f}', f'{r["peak_rss_mb"]:.0f}',
                      r['verdict'] or ('' if r['exit'] == 0 else f'exit {r["exit"]}')]
                     for r in results], 'fit and diagnose against the record length')]
    if reads:
        tables.append(table(['sets', 'storage', 'rosbags loop CPU s', 'magcal read CPU s',
                             'ratio'],
                            [[r['sets'], r['storage'], r['rosbags_loop_s'], r['magcal_read_s'],
                              f'{r["magcal_read_s"] / r["rosbags_loop_s"]:.2f}']
                             for r in reads], 'bag reading against the rosbags read loop'))
    for t in tables:
        print(t)
    os.makedirs(args.out_dir, exist_ok=True)
    plot(results, os.path.join(args.out_dir, 'scale.png'))
    write_result('scale', vars(args), {'runs': results, 'bag_reads': reads}, tables,
                 out_dir=args.out_dir, started=started)


if __name__ == '__main__':
    main()
