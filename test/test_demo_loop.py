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
The workbench loop, live (README "Demo": ``scripts/demo.sh --loop``).

The README's command as written, two more seeds and a forced wrong model run as separate
processes, one after the other. The references are
independent of the demo's own numbers: the simulator's noise (3 nT per axis, white; the
demo keeps fluxgate_sim's default), the hidden terms the seeds draw (written here by hand,
and read back from the simulator's own log), and for the vector residual |b_j - mean of the
other three| its noise expectation sqrt(3 (1 + 3/9)) sigma = 2 sigma.

Tolerances from the noise: a step's RMS over N = 500 white sets (the demo's window)
scatters by 1/sqrt(2N) = 3.2 % relative, the floor estimated from the differences by a
little more, so their ratio by ~5 %: the demo's closing bound 1.18 is 3.66 of those (a
family-wise 0.1 % over a run's 8 ratios); the floor
against the simulator's 3 nT is held to 4/sqrt(N) (18 %). A missing term shows as tens of
percent to many times the floor.
"""
import importlib
import json
import os
import pathlib
import re
import shlex
import subprocess
import sys

import conftest
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'scripts'))
demo_loop = importlib.import_module('demo_loop')

SIM_NOISE_NT = 3.0
#: the seeds the test runs and the hidden term each draws (README's command: seed 0): three
#: kinds, a fluxgate nonlinearity, a 0.23 Hz interference and a motor current
#: (seed 1's periodic term failed at load 20 on 2026-11-26, x4.25 after: the set times were a
#: straight line through the epoch count, a period off per lost sample; core/live/sync.
#: epoch_times now steps the clock where samples were lost, test_sync)
SEEDS = {0: 'nonlinearity@2', 1: 'periodic(0.23)@4', 2: 'aux:aux_motor_current@3'}
#: a wrong model for the hidden term of seed 2 (the motor current on sensor 3)
FORCED = 'nonlinearity@1'


def _readme_command():
    readme = (ROOT / 'README.md').read_text()
    lines = [ln.split('#')[0].strip() for ln in readme.splitlines()
             if ln.strip().startswith('scripts/demo.sh --loop')]
    assert len(lines) == 1, lines
    return lines[0]


def _argv(cmd):
    argv = shlex.split(cmd)
    return ['bash', str(ROOT / argv[0]), *argv[1:]]


@pytest.fixture(scope='module')
def runs(tmp_path_factory):
    """
    Run the four demo runs, two at a time, each in its own directory and ROS domain.

    Two at a time: a run is real time (30 s of collection, two 10 s windows) at 4 x 50 Hz
    and takes about half a core, so a pair takes about as long as one run. Measured
    2026-11-27: README and seed 1 side by side, 73 and 75 s (one alone: 67 s); seed 2 and the
    forced run beside a busy loop at normal priority on one core, 74 and 63 s, both as
    expected. Each run of a pair in a ROS domain of its own (the second claimed here,
    conftest.pick_domain_id): in one domain the two pipelines would hear each other. An
    earlier pair failed once (2026-11-26 20:36) when domains were chosen without a claim.

    README (seed 0), seeds 1 and 2, seed 2 with a forced wrong model; returns
    ({key: CompletedProcess}, {key: directory}).
    """
    readme = _readme_command()
    assert readme == 'scripts/demo.sh --loop'          # seed 0: the default
    commands = {
        'readme': readme,
        1: 'scripts/demo.sh --loop --seed 1',
        2: 'scripts/demo.sh --loop --seed 2',
        # the default collection: with 20 s the base calibration itself was refused (two
        # offsets correlated), which fails before the wrong model is ever tried
        'forced': f'scripts/demo.sh --loop --seed 2 --force-term {FORCED}',
    }
    dirs = {k: tmp_path_factory.mktemp(f'loop_{k}') for k in commands}
    # the session's domain (claimed by conftest) for the first of a pair, one more for the
    # second; scripts/ros_env.sh keeps the ROS_DOMAIN_ID it is given
    domains = [os.environ['ROS_DOMAIN_ID'], str(conftest.pick_domain_id())]
    results = {}
    for pair in (('readme', 1), (2, 'forced')):
        procs = {}
        try:
            for k, domain in zip(pair, domains):
                # output to files: a pipe not read while the other run is waited for fills
                with open(dirs[k] / 'stdout.txt', 'w') as out, \
                        open(dirs[k] / 'stderr.txt', 'w') as err:
                    procs[k] = subprocess.Popen(_argv(commands[k]), cwd=dirs[k], stdout=out,
                                                stderr=err,
                                                env={**os.environ, 'ROS_DOMAIN_ID': domain})
            for k, p in procs.items():
                p.wait(timeout=400)
                results[k] = subprocess.CompletedProcess(
                    p.args, p.returncode, (dirs[k] / 'stdout.txt').read_text(),
                    (dirs[k] / 'stderr.txt').read_text())
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
                    p.wait()
    return results, dirs


def _loop_json(dirs, k):
    return json.loads((pathlib.Path(dirs[k]) / 'demo_out' / 'loop.json').read_text())


def _name_sensor(term):
    """('aux:aux_motor_current', '3') from a term, written here (not the demo's parser)."""
    m = re.fullmatch(r'([a-z_:]+)(\([^)]*\))?@(\d)', term)
    assert m, term
    return m.group(1), m.group(3)


@pytest.mark.timeout(900)
def test_loop_closes_for_three_hidden_terms(runs):
    results, dirs = runs
    seen = set()
    for k, seed in (('readme', 0), (1, 1), (2, 2)):
        p = results[k]
        print(p.stdout[-3000:])
        assert p.returncode == 0, (k, p.stdout[-4000:], p.stderr[-4000:])
        assert 'loop closed' in p.stdout and 'NOT' not in p.stdout
        res = _loop_json(dirs, k)
        # the draw of the seed, as the simulator was told (its own log)
        assert res['hidden'] == SEEDS[seed], res['hidden']
        sim_log = (pathlib.Path(dirs[k]) / 'demo_out' / 'logs' / 'fluxgate_sim.log').read_text()
        assert f"hidden effects ['{SEEDS[seed]}=" in sim_log
        # the hidden term is told only at the end, after the last step
        assert p.stdout.index(SEEDS[seed] + '=') > p.stdout.rindex('step 2:')
        name, sensor = _name_sensor(res['hidden'])
        assert _name_sensor(res['diagnosed']) == (name, sensor), res['diagnosed']
        seen.add(name)
        first, last = res['steps'][0], res['steps'][-1]
        # the sets left out of the vector RMS (paired from different epochs) are few
        assert last['vector_sets_left_out'] <= 0.05 * last['sets'], last
        assert first['model'] == ['base'] and last['model'] == ['base', res['diagnosed']]
        for step in (first, last):
            tol = 4.0 / step['sets'] ** 0.5
            for j in '1234':
                # the floor is the simulator's noise (independent reference)
                assert abs(step['floor_nt'][j] / SIM_NOISE_NT - 1) < tol, (k, j, step)
                assert abs(step['vector_floor_nt'][j] / (2 * SIM_NOISE_NT) - 1) < tol
        # base: the hidden sensor's residual is clearly above the floor (the others are
        # moved too where the sensors are tied by the vector residual)
        worst = max(first[f'{kind}_rms_nt'][sensor] / first[floor][sensor]
                    for kind, floor in (('scalar', 'floor_nt'), ('vector', 'vector_floor_nt')))
        assert worst > 1.5, (k, first)
        # with the diagnosed term: every sensor at its floor, above it by no more than the
        # noise of the ratio (the demo's bound, above) and not below it by 3 of its ~5 %
        for kind, floor in (('scalar', 'floor_nt'), ('vector', 'vector_floor_nt')):
            for j in '1234':
                ratio = last[f'{kind}_rms_nt'][j] / last[floor][j]
                assert 0.85 < ratio < demo_loop.CLOSE_FACTOR, (k, kind, j, ratio)
        png = pathlib.Path(dirs[k]) / 'demo_out' / 'loop.png'
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20_000
    assert len(seen) == 3, seen


@pytest.mark.timeout(900)
def test_loop_with_a_wrong_model_says_so_and_fails(runs):
    results, dirs = runs
    p = results['forced']
    assert p.returncode == 1, (p.stdout[-4000:], p.stderr[-4000:])
    assert 'loop closed' not in p.stdout and 'loop NOT closed' in p.stdout
    assert 'LOOP NOT CLOSED' in p.stderr and 'did not fall to the floor' in p.stderr
    res = _loop_json(dirs, 'forced')
    assert res['closed'] is False and res['forced_term'] == FORCED
    # the model is the user's, not the diagnosis': none is asked for
    assert res['diagnosed'] is None and 'diagnosis' not in res
    assert 'calibration/diagnose is not called' in p.stdout
    assert 'calling calibration/diagnose' not in p.stdout
    assert res['hidden'] == SEEDS[2]
    last = res['steps'][-1]
    assert last['model'] == ['base', FORCED]
    # what is left is shown: the hidden sensor (3) still far above its floor
    ratio = last['vector_rms_nt']['3'] / last['vector_floor_nt']['3']
    assert ratio > 1.5, last
    assert 'sensor 3' in p.stderr


def test_same_term_by_hand():
    """The demo's matching of a diagnosed term with the hidden one, on hand-written terms."""
    assert demo_loop.same_term('aux:aux_motor_current@3', 'aux:aux_motor_current@3')
    assert not demo_loop.same_term('aux:aux_motor_current@3', 'aux:aux_motor_current@2')
    assert not demo_loop.same_term('aux:aux_motor_current@3', 'aux:aux_pump_current@3')
    # a refined frequency within 2 %: 0.2346 / 0.23 = 1.02
    assert demo_loop.same_term('periodic(0.23)@4', 'periodic(0.2345)@4')
    assert not demo_loop.same_term('periodic(0.23)@4', 'periodic(0.2347)@4')
    # on every sensor: the model holds the hidden term too
    assert demo_loop.same_term('field_rate@2', 'field_rate')
    assert not demo_loop.same_term('field_rate@2', None)


def test_judge_by_hand():
    """A loop is closed only with the term named and every ratio within 1.18, by hand."""
    def step(model, scalar, vector):
        return {'model': model, 'scalar_rms_nt': {'1': scalar, '2': 3.0},
                'vector_rms_nt': {'1': vector, '2': 6.0},
                'floor_nt': {'1': 3.0, '2': 3.0}, 'vector_floor_nt': {'1': 6.0, '2': 6.0},
                'sets': 500, 'vector_sets_left_out': 0}
    base = step(['base'], 9.0, 12.0)
    ok = {'hidden': 'nonlinearity@1', 'diagnosed': 'nonlinearity@1',
          'steps': [base, step(['base', 'nonlinearity@1'], 3.3, 6.6)]}   # x1.10
    failures = []
    assert demo_loop.judge(ok, failures) and failures == []
    high = dict(ok, steps=[base, step(['base', 'nonlinearity@1'], 3.6, 6.0)])  # x1.20
    failures = []
    assert not demo_loop.judge(high, failures)
    assert 'sensor 1 scalar 3.60 nT' in failures[0]
    # 26 of 500 sets (5.2 %) left out of the vector RMS: not closed, and said why
    far = dict(ok, steps=[base, dict(ok['steps'][1], vector_sets_left_out=26)])
    failures = []
    assert not demo_loop.judge(far, failures)
    assert '26 of 500 sets had a vector residual beyond 10 x its floor' in failures[0]
    wrong = dict(ok, diagnosed='drift@1')
    failures = []
    assert not demo_loop.judge(wrong, failures)
    assert 'not the hidden nonlinearity@1' in failures[0]
