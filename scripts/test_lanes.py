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
Run the test suite in three lanes: live and batch side by side, solo after live (``make test``).

The suite has two kinds of tests that want the machine differently:

- *live* tests (marked ``live``, test/conftest.py) run ROS pipelines in real time and judge
  them against the noise: a pipeline that does not get the CPU when a sample arrives loses
  it, and the test fails for a reason that is not in the code. Most of their time is real
  time (a 30 s collection, a 10 s window), not CPU, so two run side by side.
- *solo* tests (marked ``solo``: the main job, ``make demo`` at 4 x 100 Hz, and the
  corrector's 4 x 1 kHz burst) judge the pipeline's timing itself (sets lost, latency under
  a burst): beside another live pipeline they lost sets and missed their latency bound
  (2026-11-27: 2.4 % of the main job's sets, a median latency of 149 ms against 31), so
  they run one at a time with no other live test beside them.
- *batch* tests compute: they take CPU whenever they get it and only their total matters.

So the lanes are:

``live``
    the live tests but the solo ones, on two pytest-xdist workers (``--dist loadfile``: a
    file per worker at a time), at normal priority; ``--live-workers 1``: one at a time;
``solo``
    the solo tests one at a time, at normal priority, started when the live lane has ended;
``batch``
    everything else on pytest-xdist workers at the idle CPU policy (``SCHED_IDLE``: the kernel
    runs it only on a core the live lanes leave free, and preempts it the moment a live
    process wakes), or ``nice 19`` where that policy cannot be set.

Each lane is its own pytest session with its own ROS domain; its output goes to a log that
is printed whole when the lane ends, then a summary. The exit status is 0 when every lane
passed or collected nothing (pytest's 5), else 1.

    scripts/test_lanes.py [--workers N] [--live-workers N] [--timeout S] [--pytest-args '...']
                          [--only LANE ...] [--tests PATH ...]
"""
import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: the last progress percentage pytest printed, and its final summary line
_PERCENT = re.compile(r'\[\s*(\d+)%\]')
_SUMMARY = re.compile(r'^=+ (.*(passed|failed|error|no tests ran|deselected).*) =+$', re.M)
#: pytest-xdist's "2 workers [138 items]", and a line's leading run of result characters
_WORKERS = re.compile(r'\d+ workers \[(\d+) items?\]')
_RESULTS = re.compile(r'^[.FEsxX]+', re.M)
#: pytest-xdist workers of the live lane (1: one test at a time, in pytest's own process)
LIVE_WORKERS = 2


#: pytest-xdist for a lane, the worker count last: a file per worker at a time, handed out
#: in the order collected (test/conftest.py puts the slowest files first), not reordered by
#: their number of tests
XDIST = ['--dist', 'loadfile', '--no-loadscope-reorder', '-n']
#: a lane that starts only when another has ended: {lane: the lane it waits for}
AFTER = {'solo': 'live'}


def lanes(workers, live_workers=LIVE_WORKERS):
    """Return {name: (pytest marker arguments, CPU policy)} of the lanes."""
    return {
        'live': (['-m', 'live and not solo']
                 + (XDIST + [str(live_workers)] if live_workers > 1 else []), 'normal'),
        'batch': (['-m', 'not live and not solo']
                  + (XDIST + [str(workers)] if workers > 0 else []), 'idle'),
        'solo': (['-m', 'solo'], 'normal'),
    }


def _idle():
    """Put this (forked) process at the idle CPU policy, else at nice 19."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)


def bytecode_cache(env):
    """
    Let the suite's Python processes keep their bytecode, outside the checkout; return env.

    With ``PYTHONDONTWRITEBYTECODE`` set (this project's machines set it), every pytest
    session and xdist worker rewrote and compiled the ~110 test modules again, and every
    process the suite starts (hundreds: nodes, ``magcal`` commands, benchmarks) compiled
    the ~50 modules of magcal_ros it imports: collecting the suite took 6.8 s of CPU, 3.1 s
    with the cache (BENCHMARKS.md). A user's ``PYTHONPYCACHEPREFIX`` is kept; otherwise the
    bytecode goes to ``$TMPDIR/magcal_pycache-<uid>``, not into the source tree.
    """
    env.setdefault('PYTHONPYCACHEPREFIX', os.path.join(tempfile.gettempdir(),
                                                       f'magcal_pycache-{os.getuid()}'))
    env.pop('PYTHONDONTWRITEBYTECODE', None)
    return env


def _progress(path):
    try:
        with open(path, 'rb') as fh:
            text = fh.read().decode('utf-8', 'replace')
    except OSError:
        return '?'
    workers = _WORKERS.search(text)
    if workers:
        # pytest-xdist prints one character per result, in lines a log line may cut into
        # ('..[WARN] ...'), with a percentage only at each line's end
        body = text[workers.end():].split('\n=', 1)[0]
        done = sum(len(m.group(0)) for m in _RESULTS.finditer(body))
        return f'{100 * done // max(1, int(workers.group(1)))}%'
    found = _PERCENT.findall(text[-4096:])
    return f'{found[-1]}%' if found else 'starting'


def main(argv=None):
    """Run the lanes; return the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--workers', type=int, default=2,
                    help='pytest-xdist workers of the batch lane (0: in its own process)')
    ap.add_argument('--live-workers', type=int, default=LIVE_WORKERS,
                    help='pytest-xdist workers of the live lane (default %(default)s; 1: one '
                         'live test at a time)')
    ap.add_argument('--timeout', type=float, default=300.0, help='seconds per test')
    ap.add_argument('--pytest-args', default='', help='more pytest arguments, one string')
    ap.add_argument('--tests', nargs='+', default=['test'],
                    help='test files or folders (default: test)')
    ap.add_argument('--only', nargs='+', choices=('live', 'solo', 'batch'),
                    help='run these lanes only')
    ap.add_argument('--report-every', type=float, default=60.0,
                    help="print each lane's progress this often, s (0: never)")
    args = ap.parse_args(argv)

    common = [sys.executable, '-m', 'pytest', *args.tests, '-p', 'no:cacheprovider', '-ra',
              '--durations=15', f'--timeout={args.timeout:g}']
    extra = shlex.split(args.pytest_args)
    log_dir = tempfile.mkdtemp(prefix='magcal_lanes_')
    env = bytecode_cache(dict(os.environ))
    procs = {}
    started = time.monotonic()
    layout = lanes(args.workers, args.live_workers)
    chosen = [name for name in layout if not args.only or name in args.only]

    def start(name):
        marker, policy = layout[name]
        log = os.path.join(log_dir, f'{name}.log')
        # a ROS domain of its own per lane (test/conftest.py spreads its choice by this)
        with open(log, 'wb') as out:
            procs[name] = (subprocess.Popen(
                common + marker + extra, cwd=ROOT,
                env=dict(env, MAGCAL_TEST_LANE=str(list(layout).index(name))), stdout=out,
                stderr=subprocess.STDOUT, start_new_session=True,
                preexec_fn=_idle if policy == 'idle' else None), log, policy)
        print(f'lane {name}: pytest {" ".join(marker + extra)} ({policy} CPU policy; log {log})',
              flush=True)

    waiting = [name for name in chosen if AFTER.get(name) in chosen]
    for name in chosen:
        if name not in waiting:
            start(name)
    ended = {}

    def stop_all(signum, frame):
        waiting.clear()                     # a lane not started yet is not started
        for p, _, _ in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
    signal.signal(signal.SIGTERM, stop_all)
    next_report = args.report_every
    try:
        while len(ended) < len(procs) or waiting:
            time.sleep(0.5)
            for name in [n for n in waiting if AFTER[n] in ended]:
                waiting.remove(name)
                print(f'lane {name}: starts now that lane {AFTER[name]} has ended', flush=True)
                start(name)
            for name, (p, log, _) in procs.items():
                if name not in ended and p.poll() is not None:
                    with open(log, encoding='utf-8', errors='replace') as fh:
                        text = fh.read()
                    ended[name] = (p.returncode, time.monotonic() - started, text)
                    print(f'\n{"#" * 20} lane {name}: exit {p.returncode} after '
                          f'{ended[name][1]:.0f} s {"#" * 20}\n{text}', flush=True)
            elapsed = time.monotonic() - started
            if args.report_every and elapsed >= next_report and len(ended) < len(procs):
                print(f'[{elapsed:4.0f} s] ' + ', '.join(
                    f'{name} {_progress(log) if name not in ended else "done"}'
                    for name, (_, log, _) in procs.items()), flush=True)
                next_report += args.report_every
    except KeyboardInterrupt:
        stop_all(None, None)
        for p, _, _ in procs.values():
            p.wait()
        print('interrupted', file=sys.stderr)
        return 1

    print(f'\n{"#" * 20} summary: {time.monotonic() - started:.0f} s {"#" * 20}')
    failed = []
    for name, (_, _, policy) in procs.items():
        rc, t, text = ended[name]
        found = _SUMMARY.findall(text)
        line = found[-1][0] if found else 'no summary line'
        ok = rc in (0, 5)
        if not ok:
            failed.append(name)
        print(f'lane {name:5s} ({policy}): {"ok" if ok else "FAILED"}, exit {rc}, {t:.0f} s: '
              f'{line}')
    if failed:
        print(f'lanes that failed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
