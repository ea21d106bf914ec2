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
Issue 11: the loop closed on faults the catalog did not hold, written by hand.

Each fault is injected by test/injection.py (not Model.forward, not the simulator) into the
cross of paper 004 (3 nT Gaussian noise per axis, 5 Hz, decoy temperature and aux channels):
a 0.23 Hz pump of 15 nT on sensor 3, a 40 nT offset step at t = 300 s on sensor 1, a 90 s
thermal lag on sensor 2, a field growing with the motor current squared on every sensor.
At 3 000 and 10 000 epochs, the diagnosis must name the hidden effect (with its argument),
and the model with it must bring every sensor within 1.15 x its noise floor.  Controls
(nothing, a random walk below the noise) must give "none" with a floor within 10 % of the
3 nT truth.

Tolerances: "within 1.15 x the floor" is the issue's criterion; a complete model is at
1.00 +- 0.03 (RMS of 3000 x 3 values: 1.3 % sd, floor estimate 1.6 % sd, test_diagnose),
so 1.15 is more than 4 sd away from a false failure.  A step time is exact to one sample
(0.2 s); a frequency to 1/(10 span) (the refinement grid of propose_from_residual).
"""
import dataclasses
import json

import injection as inj
from magcal_ros.core import effects as fx
from magcal_ros.core.discovery import diagnose, MIN_EXPLAINED
from magcal_ros.core.model import fit
import numpy as np
import pytest

F = inj.F_NT

KINDS = {
    'periodic': (inj.periodic_fault(0.23, 15.0, 3), ('periodic', 3)),
    'step': (inj.step_fault(300.0, (40.0, 0.0, 0.0), 1), ('step', 1)),
    'lag': (inj.lag_fault(90.0, (4.0, -3.0, 2.5), 2), ('lag', 2)),
    'current_squared': (inj.current_squared_fault(), ('aux_poly', None)),
}


def assert_within(res, floor, ratio=1.15):
    for j, v in res.scalar_rms_nt.items():
        assert v <= ratio * floor.per_sensor_nt[j - 1], (j, v, floor.per_sensor_nt)
    for j, v in res.vector_rms_nt.items():
        assert v <= ratio * floor.vector_floor_nt(j), (j, v)


@pytest.mark.parametrize('n', [3000, 10000])
@pytest.mark.parametrize('kind', list(KINDS))
def test_verdict_names_the_hidden_effect_and_closes_the_gap(kind, n):
    fault, (name, sensor) = KINDS[kind]
    data = inj.make(n, seed=5, inject=fault)
    diag = diagnose(data, 'base', field_nt=F)
    doc = json.loads(diag.to_json())
    token = doc['verdict']['token']
    assert token is not None, diag.summary()
    got, args, where = fx.parse_token(token)
    assert (got, where) == (name, sensor), diag.summary()
    if name == 'step':
        assert len(args) == 1 and abs(float(args[0]) - 300.0) <= 0.2
    if name == 'periodic':
        span = data.t[-1] - data.t[0]
        assert abs(float(args[0]) - 0.23) <= 1.0 / (10 * span)
    if name == 'lag':
        assert args == ('temperature',)
    if name == 'aux_poly':
        assert args == ('aux_motor_current', '2')
    v = doc['verdict']
    assert v['decided_by'] == 'held-out' and v['explained_fraction'] >= 0.9
    # the exact token is what `fit --model base,<token>` takes; with it every sensor is at
    # the floor
    res = fit(data, 'base,' + token, field_nt=F)
    assert_within(res, diag.noise_floor)


CONTROLS = {'nothing': (None, None),
            'random_walk': (inj.random_walk_fault(0.01), None),   # 1 nT sd after 10^4 epochs
            'heavy_tails': (None, inj.student_noise)}


@pytest.mark.parametrize('n', [3000, 10000])
@pytest.mark.parametrize('control', list(CONTROLS))
def test_controls_give_none(control, n):
    fault, noise = CONTROLS[control]
    data = inj.make(n, seed=6, inject=fault, noise=noise)
    diag = diagnose(data, 'base', field_nt=F)
    assert diag.verdict_token is None, diag.summary()
    # the floor is the noise's sd (3 nT; Student-t scaled to it) within the 10 %
    assert diag.noise_floor.value_nt == pytest.approx(inj.SIGMA_NT, rel=0.10)


def test_significant_but_negligible_effect_is_not_adopted():
    """A real drift of 3 nT over the record, next to a 15 nT pump: p ~ 1e-50, share ~ 0."""
    def faults(t, temp, aux, b):
        out = inj.periodic_fault(0.23, 15.0, 3)(t, temp, aux, b)
        out[1] = ((t - t.mean()) / np.ptp(t) * 3.0)[:, None] * np.array([1.0, 0.0, 0.0])
        return out
    data = inj.make(3000, seed=7, inject=faults)
    diag = diagnose(data, 'base', field_nt=F, candidates=['drift@1'])
    c = diag.candidates[0]
    assert c.log10_p_value < -10 and c.delta_bic < -20       # highly significant ...
    assert c.explained_fraction < 0.01 < MIN_EXPLAINED       # ... but removes nothing
    assert not c.significant and diag.verdict_token is None
    assert 'removes only' in diag.verdict_reason


@pytest.mark.parametrize('n', [120, 3000])
def test_without_held_out_test_the_verdict_rests_on_significance_and_share(n):
    data = inj.make(n, seed=8, inject=inj.periodic_fault(0.23, 15.0, 3))
    folds = 0 if n == 3000 else 3           # 120 epochs: too short for 3 x 4 blocks
    # (24 s of tumbling cover a 107 deg cone: flagged, fitted anyway)
    diag = diagnose(data, 'base', field_nt=F, folds=folds, on_degenerate='flag')
    doc = json.loads(diag.to_json())
    assert doc['verdict']['decided_by'].startswith('in-sample')
    assert ('folds=0' if folds == 0 else 'too short') in doc['verdict']['decided_by']
    assert doc['verdict']['token'] is not None
    name, _, sensor = fx.parse_token(doc['verdict']['token'])
    assert (name, sensor) == ('periodic', 3), diag.summary()
    assert doc['verdict']['explained_fraction'] >= MIN_EXPLAINED


def test_a_lag_of_no_time_constant_is_the_plain_coupling():
    """
    Prefer the plain coupling to a lag of no time constant.

    Plain temperature coupling: lag(temperature) fits too (tau -> 0, fewer parameters),
    but the verdict is the established effect, and the lag candidate says why not.
    """
    def plain(t, temp, aux, b):
        return {2: (temp[1] - temp[1].mean())[:, None] * np.array([4.0, -3.0, 2.5])}
    data = inj.make(3000, seed=9, inject=plain)
    diag = diagnose(data, 'base', field_nt=F)
    assert diag.verdict_token == 'temperature@2', diag.summary()
    lag = next(c for c in diag.candidates if c.token == 'lag(temperature)@2')
    assert not lag.significant and 'no lag' in lag.note


def test_tokens_from_findings():
    from magcal_ros.core.discovery import tokens_from_findings
    got = tokens_from_findings([
        {'kind': 'periodic', 'sensor': 3, 'value': 0.23, 'token': 'periodic(0.23)@3'},
        {'kind': 'step', 'sensor': 1, 'value': 300.0, 'token': None},
        {'kind': 'lag', 'sensor': 2, 'channel': 'temperature', 'value': 88.0},
        {'kind': 'channel_nonlinear', 'sensor': None, 'channel': 'aux_motor_current'},
        {'kind': 'heavy_tails', 'sensor': 2}])
    assert got == ['periodic(0.23)', 'step(300)', 'lag(temperature)',
                   'aux_poly(aux_motor_current,2)']


@pytest.mark.parametrize('n', [3000, 10000])
def test_site_gradient_adopts_no_fix_and_is_named_by_the_finding(n):
    """
    Adopt no fix for a site gradient without attitude; the finding names it.

    Issue 11: a constant world-frame gradient (~320 nT/m, ~25 nT per sensor here) gave
    nonlinearity@3 for 68.80 -> 68.54 nT and a ladder stacking nonlinearity.  The catalog
    without attitude has nothing for it: no candidate removes a fifth of the excess, the
    verdict is none, the ladder stops at once, and the finding names the gradient.
    """
    grad = np.array([[200.0, 100.0, 0.0], [100.0, -150.0, 50.0], [0.0, 50.0, -50.0]])
    data = inj.make(n, seed=2, inject=inj.site_gradient_fault(grad, seed=2))
    diag = diagnose(data, 'base', field_nt=F)
    assert diag.verdict_token is None, diag.summary()
    shares = [c.explained_fraction for c in diag.candidates if c.explained_fraction is not None]
    assert shares and max(shares) < MIN_EXPLAINED
    kinds = [f['kind'] for f in json.loads(diag.to_json())['findings']]
    assert 'nonuniform_field' in kinds
    from magcal_ros.core.discovery import ladder
    lad = ladder(data, diag.result, field_nt=F, diagnosis=diag)
    assert len(lad.steps) == 1 and lad.reason.startswith('verdict none')


def test_a_record_stamped_since_1970_names_its_step_to_the_sample():
    # a ROS bag's stamps (~1.8e9 s): the step's token keeps its time to the sample (6
    # significant digits put it 500 s off, and the live loop demo's window drivers failed)
    fault, _ = KINDS['step']
    data = inj.make(3000, seed=5, inject=fault)
    t0 = 1795889560.905
    data = dataclasses.replace(data, t=data.t + t0)
    diag = diagnose(data, 'base', field_nt=F)
    token = json.loads(diag.to_json())['verdict']['token']
    got, args, where = fx.parse_token(token)
    assert (got, where) == ('step', 1), diag.summary()
    assert abs(float(args[0]) - (t0 + 300.0)) <= 0.2
    assert_within(fit(data, 'base,' + token, field_nt=F), diag.noise_floor)
