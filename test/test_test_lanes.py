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
The lanes of ``make test`` (scripts/test_lanes.py).

Who runs where, at which CPU policy, and that a failing lane fails the run.

The lanes are two pytest sessions side by side; which tests each takes is decided by the
marker ``live`` that test/conftest.py puts on the items, so the partition
is checked on conftest's own hook with items made here, and the policy by a probe that runs
in whatever lane the suite puts it in.
"""
import fcntl
import importlib
import os
import pathlib
import subprocess
import sys
import tempfile
import types

import conftest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'scripts'))
test_lanes = importlib.import_module('test_lanes')


def test_this_process_runs_at_the_policy_of_its_lane():
    """The batch lane (MAGCAL_TEST_LANE=2) at SCHED_IDLE (or nice 19); anything else not."""
    lane = os.environ.get('MAGCAL_TEST_LANE')
    policy = os.sched_getscheduler(0)
    if lane == str(list(test_lanes.lanes(2)).index('batch')):
        assert policy == os.SCHED_IDLE or os.nice(0) == 19, (policy, os.nice(0))
    else:
        # a plain pytest, or the live lanes: the policy pytest was started with
        assert policy != os.SCHED_IDLE, policy


class _Item:
    def __init__(self, name, marks=()):
        self.path = pathlib.Path('/x') / name
        self.marks = set(marks)

    def add_marker(self, mark):
        self.marks.add(mark.name)

    def get_closest_marker(self, name):
        return types.SimpleNamespace(name=name) if name in self.marks else None


def _lane_of(item):
    live, solo = 'live' in item.marks, 'solo' in item.marks
    # the marker expressions of test_lanes.lanes(), evaluated by hand
    return [name for name, ok in (('live', live and not solo),
                                  ('batch', not live and not solo), ('solo', solo)) if ok]


def test_every_test_is_in_exactly_one_lane():
    exprs = {name: ' '.join(marker) for name, (marker, _) in test_lanes.lanes(2, 2).items()}
    xdist = '--dist loadfile --no-loadscope-reorder -n 2'
    assert exprs == {'live': f'-m live and not solo {xdist}',
                     'batch': f'-m not live and not solo {xdist}', 'solo': '-m solo'}
    # one live test at a time: no xdist in the live lane
    assert test_lanes.lanes(2, 1)['live'] == (['-m', 'live and not solo'], 'normal')
    # the solo lane waits for the live lane
    assert test_lanes.AFTER == {'solo': 'live'}
    items = [_Item('test_demo.py'), _Item('test_demo_loop.py'), _Item('test_cli.py'),
             _Item('test_bench_smoke.py', ['live']), _Item('test_bench_smoke.py'),
             _Item('test_reliability_load.py')]
    originals = list(items)
    lanes = [['solo'], ['live'], ['batch'], ['live'], ['batch'], ['solo']]
    conftest.pytest_collection_modifyitems(None, items)
    assert [_lane_of(i) for i in originals] == lanes
    # the slowest files first, in conftest.SLOWEST_FIRST's order, each file's items in theirs
    assert [i.path.name for i in items] == [
        'test_demo_loop.py', 'test_bench_smoke.py', 'test_bench_smoke.py', 'test_demo.py',
        'test_cli.py', 'test_reliability_load.py']
    assert [i for i in items if i.path.name == 'test_bench_smoke.py'] == originals[3:5]
    # the solo files are live files too (a plain pytest -m live runs them)
    assert conftest.SOLO_FILES <= conftest.LIVE_FILES


def test_bytecode_goes_to_a_cache_outside_the_checkout():
    env = test_lanes.bytecode_cache({'PYTHONDONTWRITEBYTECODE': '1'})
    assert 'PYTHONDONTWRITEBYTECODE' not in env
    assert not pathlib.Path(env['PYTHONPYCACHEPREFIX']).resolve().is_relative_to(ROOT)
    assert test_lanes.bytecode_cache({'PYTHONPYCACHEPREFIX': '/mine'}) == {
        'PYTHONPYCACHEPREFIX': '/mine'}


def _run(*args):
    return subprocess.run([sys.executable, str(ROOT / 'scripts' / 'test_lanes.py'),
                           '--report-every', '0', '--tests', __file__, *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=240)


def test_lanes_run_side_by_side_and_the_probe_sees_its_policy():
    p = _run('--pytest-args', '-k this_process_runs_at_the_policy')
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    summary = p.stdout[p.stdout.index('summary:'):]
    # the probe passed in the batch lane (at the idle policy); the live lane had nothing to
    # run (pytest's exit 5, not a failure)
    lines = {ln.split()[1]: ln for ln in summary.splitlines() if ln.startswith('lane ')}
    assert 'ok, exit 0' in lines['batch'] and '1 passed' in lines['batch'], summary
    assert 'ok, exit 5' in lines['live'], summary
    # the solo lane (nothing to run either) started only once the live lane had ended
    assert 'ok, exit 5' in lines['solo'], summary
    out = p.stdout
    assert out.index('lane live: exit 5') < out.index(
        'lane solo: starts now that lane live has ended') < out.index('lane solo: pytest')


def test_a_failing_lane_fails_the_run():
    p = _run('--only', 'batch', '--pytest-args=--no-such-option')
    assert p.returncode == 1, p.stdout[-3000:]
    assert 'lane batch (idle): FAILED, exit 4' in p.stdout, p.stdout[-3000:]
    assert 'lanes that failed: batch' in p.stderr
    # --only: the other lanes were not started
    assert [ln.split()[1] for ln in p.stdout.splitlines()
            if ln.startswith('lane ') and 'pytest' in ln] == ['batch:'], p.stdout[:1000]


def test_processes_choosing_at_once_never_share_a_ros_domain():
    """A domain claimed by a live process is skipped; its claim ends with the process."""
    child = subprocess.Popen(
        [sys.executable, '-c', 'import os, sys; sys.path.insert(0, "test"); import conftest; '
         'print(os.environ["ROS_DOMAIN_ID"], conftest.pick_domain_id(5), flush=True); '
         'sys.stdin.read()'],
        cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        session, picked = (int(x) for x in child.stdout.readline().split())
        taken = {session, picked}
        assert len(taken) == 2                   # its session's domain and one more
        # no DDS port of them is bound yet (no participant): only the claim keeps them apart
        mine = conftest.pick_domain_id(5)
        assert mine not in taken and mine != int(os.environ['ROS_DOMAIN_ID'])
    finally:
        child.communicate('', timeout=30)
    path = pathlib.Path(tempfile.gettempdir()) / f'magcal_ros_domain_{picked}.lock'
    with open(path, 'a') as fh:                   # released with the process
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fh, fcntl.LOCK_UN)


def test_progress_counts_the_results_of_xdist_workers(tmp_path):
    log = tmp_path / 'lane.log'
    # xdist: one character per result, a log line cutting into one line, % only at line ends
    log.write_text('created: 2/2 workers\n2 workers [10 items]\n\n...[WARN] [1.0] lost x\n'
                   '.. [ 50%]\nF\n')
    assert test_lanes._progress(log) == '60%'
    log.write_text('collected 12 items\n\ntest/test_a.py ....                 [ 33%]\n')
    assert test_lanes._progress(log) == '33%'
    assert test_lanes._progress(tmp_path / 'absent.log') == '?'
