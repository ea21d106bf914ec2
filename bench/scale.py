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
``--bag-max``: the same series from rosbag2 recordings (sqlite3 and MCAP, ``--storages``)
up to that size, written from the CSV by ``write_bag`` (its CPU time per million messages
recorded; the bags are kept in ``--data-dir`` and reused), and three read loops over every
message of each bag, each a process of its own: rosbags' ``messages()`` alone (the storage's
cost), the rosbags library's own read loop (every message deserialised) and this tree's
reading (``bag_chunks``); the ratio of the last two is the reading's cost.  Every run
records the 1-minute load average at its start and end.  ``--no-csv --keep``: only the
bags, the other rows of the existing scale.json kept with the commit and date they were
measured at.  Run it under ``nice -n 19`` on a shared machine.

    python bench/scale.py --base /work/wt/base            # ~1 h on an idle 2-core machine
    python bench/scale.py --sizes 10000 100000 --bag-max 100000   # a few minutes
    nice -n 19 python bench/scale.py --sizes 1000000 3600000 --bag-max 3600000 --no-csv --keep

Writes bench/results/scale.json and bench/results/scale.png (time and memory against sets).
"""
import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import time

from common import add_common_args, BENCH_DIR, REPO_DIR, table, write_result  # noqa: I100

TRUTH = 'temperature@2=3,-2,1.5,0,0,0'


def rusage_of(cmd, code_dir):
    """
    Wall s, CPU s, peak RSS MB, exit code, stdout, load averages of ``cmd``.

    ``cmd`` is ``[python, '-m', module, args...]`` or ``[python, script, args...]``; it runs
    under bench/peak_rss.py, whose ``VmHWM`` is the peak RSS (``ru_maxrss`` of ``wait4``
    would carry this benchmark's own peak into the child).  CPU: user + system of the child
    (``wait4``).  The 1-minute load average is read at the start and at the end of the run:
    on a shared machine it says how much the wall time was stretched by the other processes.
    """
    import tempfile
    env = dict(os.environ, PYTHONPATH=code_dir)
    if cmd[1] == '-m':
        module, rest = cmd[2], cmd[3:]
    else:                                   # a script of bench/: run as a module of it
        module, rest = os.path.splitext(os.path.basename(cmd[1]))[0], cmd[2:]
        env['PYTHONPATH'] = os.pathsep.join([os.path.dirname(cmd[1]), code_dir])
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryFile('w+') as out, open(os.devnull, 'w') as devnull, \
            tempfile.NamedTemporaryFile('r') as hwm:
        t0 = time.perf_counter()
        p = subprocess.Popen([cmd[0], os.path.join(BENCH_DIR, 'peak_rss.py'), hwm.name,
                              module] + rest, cwd=code_dir, env=env, stdout=out,
                             stderr=devnull)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        text = out.read()
        hwm.seek(0)
        peak = hwm.read().strip()
    cpu = usage.ru_utime + usage.ru_stime
    return (wall, cpu, int(peak) / 1024.0 if peak else float('nan'),
            os.waitstatus_to_exitcode(status), text,
            {'load_start': round(load0, 2), 'load_end': round(os.getloadavg()[0], 2)})


def simulate(path, n, code_dir):
    """Write the n-set recording (this tree's `magcal simulate`) unless it exists."""
    if not os.path.exists(path):
        subprocess.run([sys.executable, '-m', 'magcal_ros.cli', 'simulate', '--out', path,
                        '--n', str(n), '--rate', '1000', '--truth', TRUTH, '--seed', '19'],
                       cwd=code_dir, env=dict(os.environ, PYTHONPATH=code_dir), check=True)


def to_bag(csv_path, bag_path, storage):
    """
    Convert a wide CSV to a rosbag2 directory, chunk by chunk (this tree's write_bag).

    Returns None when the bag exists (cached in --data-dir), else the write's wall and CPU
    time, its messages and CPU seconds per million messages.
    """
    if os.path.exists(bag_path):
        return None
    import shutil
    from magcal_ros.io.bag import bag_message_count, write_bag
    from magcal_ros.io.chunks import open_record
    part = bag_path + '.part'
    shutil.rmtree(part, ignore_errors=True)
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    write_bag(part, open_record(csv_path).chunks(), storage=storage)
    os.sync()                               # on disk before it is read and timed
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    # written under another name so that an interrupted write is not taken for a bag
    # (metadata.yaml names its file relative to the directory)
    os.rename(part, bag_path)
    msgs = bag_message_count(bag_path)
    return {'messages': msgs, 'write_wall_s': round(wall, 1), 'write_cpu_s': round(cpu, 1),
            'write_cpu_s_per_million': round(cpu / msgs * 1e6, 2),
            'load_start': round(load0, 2), 'load_end': round(os.getloadavg()[0], 2)}


def read_loop(mode, bag_path):
    """
    Read every message of the bag one way (run in a process of its own).

    ``iterate``: rosbags' ``AnyReader.messages()`` alone (what the storage costs);
    ``rosbags``: the rosbags library's own read loop, every message deserialised;
    ``magcal``: this tree's reading, :func:`magcal_ros.io.bag.bag_chunks` (the epochs of the
    whole record, decoded, paired and interpolated, chunk by chunk).
    Returns the count read and the CPU and wall seconds of the loop itself (imports and
    interpreter start left out: they are the same for all three).
    """
    from magcal_ros.io.bag import bag_chunks
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import get_typestore, Stores
    c0, t0 = time.process_time(), time.perf_counter()
    n = 0
    if mode == 'magcal':
        n = sum(piece.n_samples for piece in bag_chunks(bag_path))
    else:
        with AnyReader([Path(os.path.abspath(bag_path))],
                       default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
            for c, _, raw in reader.messages():
                if mode == 'rosbags':
                    reader.deserialize(raw, c.msgtype)
                n += 1
    return {'count': n, 'loop_cpu_s': round(time.process_time() - c0, 2),
            'loop_wall_s': round(time.perf_counter() - t0, 2)}


def read_times(bag_path, modes=('magcal', 'rosbags', 'iterate')):
    """
    Run read loops (:func:`read_loop`) on ``bag_path``, each in its own process.

    Per loop: the process's wall and CPU s and peak RSS MB, and the loop's own CPU and wall
    s (``loop_cpu_s``: what the ratio is taken of).
    """
    out = {}
    for mode in modes:
        wall, cpu, rss, rc, text, load = rusage_of(
            [sys.executable, os.path.abspath(__file__), '--read-loop', mode, bag_path],
            REPO_DIR)
        if rc != 0:
            raise RuntimeError(f'read loop {mode} on {bag_path} failed (exit {rc})')
        out[mode] = {'wall_s': round(wall, 2), 'cpu_s': round(cpu, 2),
                     'peak_rss_mb': round(rss, 1), **json.loads(text), **load}
        print(mode, out[mode], flush=True)
    return out


def series(data, code, code_dir, rows, field, commands=('fit', 'diagnose')):
    """Run fit and diagnose of ``data`` with ``code_dir``'s magcal; append to ``rows``."""
    for cmd in commands:
        argv = [sys.executable, '-m', 'magcal_ros.cli', cmd, data, '--field-nt', field,
                '--json', '--flag-degenerate'] + (['-q'] if cmd == 'diagnose' else ['--force'])
        wall, cpu, rss, rc, out, load = rusage_of(argv, code_dir)
        verdict = None
        if rc == 0 and cmd == 'diagnose':
            v = json.loads(out).get('verdict') or {}
            verdict = v.get('effect', 'none') + (f'@{v["sensor"]}' if v.get('sensor') else '')
        rows.append({'code': code, 'command': cmd, 'wall_s': round(wall, 2),
                     'cpu_s': round(cpu, 2),
                     'peak_rss_mb': round(rss, 1), 'exit': rc, 'verdict': verdict, **load})
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
    ap.add_argument('--storages', nargs='+', default=['sqlite3', 'mcap'],
                    choices=['sqlite3', 'mcap'])
    ap.add_argument('--no-csv', action='store_true',
                    help='only the bags (the CSV rows of an earlier run are kept, --keep)')
    ap.add_argument('--keep', action='store_true',
                    help='keep the rows of the existing scale.json this run does not measure '
                    '(each keeps the commit and date it was measured at)')
    steps = ['read', 'fit', 'diagnose', 'rosbags', 'iterate']
    ap.add_argument('--steps', nargs='+', choices=steps, default=steps,
                    help='what to measure: fit, diagnose, and the read loops of a bag (read: '
                    'ours, rosbags, iterate), in this order per size and input')
    ap.add_argument('--note', help='a remark kept in the settings of the JSON')
    ap.add_argument('--plot-at-end', action='store_true',
                    help='draw scale.png once, at the end (default: after every step with '
                    'the JSON, so that an interrupted series keeps its figure too; each '
                    'drawing costs about half a second of CPU in this process, none of it in the '
                    'processes measured)')
    ap.add_argument('--read-loop', nargs=2, metavar=('MODE', 'BAG'), help=argparse.SUPPRESS)
    add_common_args(ap)
    args = ap.parse_args()
    if args.read_loop:
        print(json.dumps(read_loop(*args.read_loop)))
        return
    started = time.perf_counter()
    os.makedirs(args.data_dir, exist_ok=True)
    from common import machine_info
    from magcal_ros.io.bag import bag_message_count
    stamp = {k: machine_info()[k] for k in ('git_commit', 'date_utc')}
    old = None
    out_json = os.path.join(args.out_dir, 'scale.json')
    if args.keep and os.path.exists(out_json):
        with open(out_json) as fh:
            old = json.load(fh)
    results, reads = [], []

    def save():
        # after every step: an interrupted series keeps what it measured
        report(args, results, reads, old, started, draw=not args.plot_at_end)

    for n in args.sizes:
        csv_path = os.path.join(args.data_dir, f'cross_{n}.csv')
        simulate(csv_path, n, REPO_DIR)
        inputs = [] if args.no_csv else [('csv', csv_path)]
        if n <= args.bag_max:
            inputs += [(f'bag {st}', os.path.join(args.data_dir, f'cross_{n}_{st}'))
                       for st in args.storages]
        for inp, path in inputs:
            read = None
            if inp.startswith('bag'):
                write = to_bag(csv_path, path, inp[4:])
                print('write', n, inp, write, flush=True)
                read = {'sets': n, 'storage': inp[4:], 'messages': bag_message_count(path),
                        **stamp}
                if write is not None:
                    read['write'] = write
                reads.append(read)
            codes = [('this tree', REPO_DIR)]
            if args.base and n <= args.base_max:
                codes.append(('c43534d', os.path.abspath(args.base)))
            for code, code_dir in codes:
                for cmd in ('fit', 'diagnose'):
                    if cmd not in args.steps:
                        continue
                    rows = []
                    series(path, code, code_dir, rows, '50000', (cmd,))
                    for r in rows:
                        r.update(sets=n, input=inp, **stamp)
                    results.extend(rows)
                    save()
            if read is not None:
                # the three read loops one after the other, after the commands (the first read
                # right after the write ran 30-50 % slower: the kernel writing the bag back)
                for mode in ('read', 'rosbags', 'iterate'):
                    if mode in args.steps:
                        mode = 'magcal' if mode == 'read' else mode
                        read.update(read_times(path, (mode,)))
                        save()
    for t in report(args, results, reads, old, started):
        print(t)


def report(args, results, reads, old, started, draw=True):
    """
    Write scale.json and scale.png of the runs so far (+ ``old``'s others); the tables.

    ``draw=False``: scale.json only (``--plot-at-end`` between the steps).
    """
    results, reads = list(results), list(reads)
    if old is not None:
        prev = {k: old['machine'].get(k) for k in ('git_commit', 'date_utc')}
        done = {(r['sets'], r['input'], r['code'], r['command']) for r in results}
        results += [dict(prev, **r) for r in old['results']['runs']
                    if (r['sets'], r['input'], r['code'], r['command']) not in done]
        new = {(r['sets'], r['storage']): r for r in reads}
        reads = [dict(prev, **r) for r in old['results']['bag_reads']
                 if (r['sets'], r['storage']) not in new]
        for r in old['results']['bag_reads']:       # a bag measured in parts: the union
            key = (r['sets'], r['storage'])
            if key in new:
                new[key] = {**(dict(prev, **r) if 'messages' in r else {}), **new[key]}
        reads += list(new.values())
    results.sort(key=lambda r: (r['sets'], r['input'], r['code'] != 'this tree',
                                r['command'] != 'fit'))
    reads.sort(key=lambda r: (r['sets'], r['storage']))
    tables = [table(['sets', 'input', 'code', 'command', 'wall s', 'CPU s', 'peak RSS MB',
                     'verdict', 'load start/end', 'measured'],
                    [[r['sets'], r['input'], r['code'], r['command'], f'{r["wall_s"]:.1f}',
                      f'{r["cpu_s"]:.1f}', f'{r["peak_rss_mb"]:.0f}',
                      r['verdict'] or ('' if r['exit'] == 0 else f'exit {r["exit"]}'),
                      _load(r), _when(r)]
                     for r in results], 'fit and diagnose against the record length')]
    new_reads = [r for r in reads if 'magcal' in r]
    if new_reads:
        def cpu(r, mode):
            return r[mode]['loop_cpu_s'] if mode in r else None

        def ratio(r):
            if 'rosbags' not in r:
                return 'not measured'
            return f'{r["magcal"]["loop_cpu_s"] / r["rosbags"]["loop_cpu_s"]:.2f}'
        tables.append(table(
            ['sets', 'storage', 'messages', 'iterate CPU s', 'rosbags loop CPU s',
             'magcal read CPU s', 'ratio', 'magcal read peak RSS MB', 'write CPU s/1e6 msg',
             'load start/end', 'measured'],
            [[r['sets'], r['storage'], r['messages'], cpu(r, 'iterate'), cpu(r, 'rosbags'),
              cpu(r, 'magcal'), ratio(r), f'{r["magcal"]["peak_rss_mb"]:.0f}',
              r.get('write', {}).get('write_cpu_s_per_million', 'cached'),
              ' '.join(f'{m}: {r[m]["load_start"]}/{r[m]["load_end"]}'
                       for m in ('magcal', 'rosbags', 'iterate') if m in r), _when(r)]
             for r in new_reads], 'bag reading against the rosbags read loop (CPU s)'))
    os.makedirs(args.out_dir, exist_ok=True)
    if draw:
        plot(results, os.path.join(args.out_dir, 'scale.png'))
    write_result('scale', {k: v for k, v in vars(args).items() if k != 'read_loop'},
                 {'runs': results, 'bag_reads': reads}, tables, out_dir=args.out_dir,
                 started=started)
    return tables


def _load(r):
    return f'{r["load_start"]}/{r["load_end"]}' if 'load_start' in r else '-'


def _when(r):
    return f'{r.get("git_commit")} {str(r.get("date_utc"))[11:16]}'


if __name__ == '__main__':
    main()
