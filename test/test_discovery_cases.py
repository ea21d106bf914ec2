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
Discovery on invented field situations (issue 18 items 3 and 6), through the Python API.

Each case of test/discovery_cases.py is written by hand with numpy (never Model.forward).
``diagnose(data, 'base')`` with its defaults offers a term (the verdict); the term must name
the right sensors and channel or time (discovery_cases.attributed), and ``fit`` of
``base + <term>`` must bring every sensor within 1.15x its noise floor, scalar and vector.

Tolerance: the noise floor is estimated from the data (4th differences, 3 000-10 000 epochs:
its relative standard error is below 1 %), and a model that holds the truth leaves the
residual at the floor up to the parameters it fits (k / 3N < 1 %): 1.15 is the issue's
bound, at least 10 standard errors above what a right model leaves.  Controls must stay
"none", at the floor by the diagnosis' own rule, with the base fit leaving the noise the
case was written with (3 nT per axis) within 4 standard errors of an RMS.

The cases here cover each driver kind (smooth/step/window in time, a channel linear, its
lag, a cyclic channel, a product, a step), each coupling (offset, scale, linear, field), each scope
(one sensor, a set, alike, the array) and the model-free drop at least once, at both sizes
between them; the rest run in bench/discovery.py.
"""
import discovery_cases as dc
from magcal_ros.core.discovery import diagnose
from magcal_ros.core.model import fit, Model
import numpy as np
import pytest

PASS_RATIO = 1.15

#: (case, epochs): which driver, coupling and scope each one exercises
CHOSEN = [
    ('control', 3000),              # nothing missing, decoy channels
    ('control_fast', 10000),        # nothing missing at 10 Hz
    ('rotor', 3000),                # cc() of a wrapped channel, offset, one sensor
    ('arm', 3000),                  # a channel, offset, a set of sensors {2,4}
    ('vehicle', 3000),              # confined in time, every sensor: drop(t0, t1)
    ('scale_temperature', 10000),   # temperature, scale (or the temperature alias)
    ('induced', 3000),              # a channel, linear (field-proportional)
    ('diurnal', 3000),              # smooth in time, the field itself
    ('common_warmup', 3000),        # smooth in time, offset alike on every sensor
    ('product', 3000),              # a product of two channels
    ('relay_lag', 10000),           # a channel through a lag
    ('gain_switch', 3000),          # a step in time, scale: found in the gains' change point
]

_CACHE = {}


def _run(name, n):
    if (name, n) not in _CACHE:
        case = dc.BY_NAME[name]
        data = case.data(n)
        diag = diagnose(data, 'base', field_nt=data.ref_total)
        _CACHE[(name, n)] = (case, data, diag)
    return _CACHE[(name, n)]


def _worst_ratio(data, r):
    """Return the largest residual RMS / noise floor of the fit ``r`` on ``data``."""
    from magcal_ros.core.data.noise import data_noise_floor
    floor = data_noise_floor(data, r)
    sc = [r.scalar_rms_nt[j] / floor.per_sensor_nt[j - 1] for j in r.scalar_rms_nt]
    vc = [v / floor.vector_floor_nt(j) for j, v in (r.vector_rms_nt or {}).items()]
    return max(sc + vc)


@pytest.mark.parametrize('name,n', [c for c in CHOSEN if not dc.BY_NAME[c[0]].sensors])
def test_control_stays_none(name, n):
    case, data, diag = _run(name, n)
    assert diag.verdict_token is None, diag.verdict_reason
    assert diag.at_floor
    # the base fit is the diagnosis' own: diagnose(data, 'base', field_nt=data.ref_total)
    # fits 'base' on every epoch with fit()'s defaults, as fit(data, 'base',
    # field_nt=data.ref_total) would (asserted: the same model, on all the epochs)
    base = diag.result
    assert base.model.spec() == Model.from_spec('base', data.n_sensors).spec()
    assert base.n_fit_samples == data.n_samples
    # and it leaves the noise the case was written with (independent of the floor the
    # diagnosis estimates): the scalar residual SIGMA_NT, sensor j against sensor 1
    # sqrt(2) SIGMA_NT per axis, each within 4 standard errors of an RMS of N values
    # (1 / sqrt(2 N): 5.2 % at 3 000 epochs, 2.8 % at 10 000; the 45 fitted parameters
    # take less than 0.4 % of it)
    tol = 4.0 / np.sqrt(2 * n)
    for j, rms in base.scalar_rms_nt.items():
        assert abs(rms / dc.SIGMA_NT - 1) < tol, (j, rms)
    for j, rms in base.vector_rms_nt.items():
        assert abs(rms / (np.sqrt(2) * dc.SIGMA_NT) - 1) < tol, (j, rms)


@pytest.mark.parametrize('name,n', [c for c in CHOSEN if dc.BY_NAME[c[0]].sensors])
def test_offered_term_is_attributed_and_reaches_the_floor(name, n):
    case, data, diag = _run(name, n)
    term = diag.verdict_token
    assert term is not None, diag.verdict_reason
    ok, why = dc.attributed(case, term, data.t)
    assert ok, f'{term}: {why}'
    # both separators of the formula build the same model (the same effects, parameters
    # and dropped windows), so one fit of it checks both
    comma = Model.from_spec(f'base,{term}', data.n_sensors)
    plus = Model.from_spec(f'base + {term}', data.n_sensors)
    assert comma.spec() == plus.spec() and comma.param_info() == plus.param_info()
    assert _worst_ratio(data, fit(data, plus, field_nt=data.ref_total)) <= PASS_RATIO


def test_json_contract_keys_and_verdict_among_candidates():
    _, data, diag = _run('rotor', 3000)
    d = diag.to_dict()
    # docs/design.md §2, `diagnose --json`: the keys at the top and in the verdict
    assert {'model', 'noise_floor_nt', 'scalar_rms_nt', 'vector_rms_nt', 'candidates',
            'verdict', 'findings'} <= set(d)
    verdict = d['verdict']
    assert {'effect', 'sensor', 'token', 'explained_fraction', 'decided_by'} <= set(verdict)
    assert verdict['token'] == diag.verdict_token == f"{verdict['effect']}@{verdict['sensor']}"
    # candidates best first: the verdict is the first, with its own explained fraction, at
    # least the 80 % of the held-out excess a search term must remove to become the verdict
    top = d['candidates'][0]
    assert top['token'] == verdict['token']
    assert top['explained_fraction'] == verdict['explained_fraction'] >= 0.8
    assert verdict['decided_by'] == 'held-out'
    for finding in d['findings']:
        assert {'kind', 'sensor', 'channel', 'value', 'unit', 'explained_fraction', 'text',
                'token'} <= set(finding)


def test_localised_finding_names_the_window():
    case, data, diag = _run('vehicle', 3000)
    loc = [f for f in diag.findings.to_list() if f['kind'] == 'localised']
    assert len(loc) == 1 and loc[0]['token'].startswith('drop(')
    t0, t1 = case.window(data.t)
    tc = 0.5 * (t0 + t1)
    lo, hi = (float(x) for x in loc[0]['token'][5:-1].split(','))
    # the bump is a Gaussian of sd 10 s (45 nT peak) centred in the case's window: where it
    # exceeds the 3 nT noise (|t - tc| < 2.3 sd) must be left out, and no more than the
    # case's 60 s window with 20 s to spare
    assert lo <= tc - 15 and hi >= tc + 15 and hi - lo <= (t1 - t0) + 20


def test_attribution_helper_rejects_wrong_scope_and_channel():
    t = np.arange(3000) / 5.0
    arm = dc.BY_NAME['arm']
    assert dc.attributed(arm, 'offset(aux_pump_current)@{2,4}', t)[0]
    assert not dc.attributed(arm, 'offset(aux_pump_current)', t)[0]
    assert not dc.attributed(arm, 'offset(aux_relay)@{2,4}', t)[0]
    assert not dc.attributed(dc.BY_NAME['control'], 'offset(t)@1', t)[0]
    # a disturbance in time must be named by a driver of its kind: a gain switch by a step
    # (a smooth basis also brings its residual to the floor: BENCHMARKS.md, the gain switch
    # before the gains' change points), the diurnal variation by a smooth basis
    switch, diurnal = dc.BY_NAME['gain_switch'], dc.BY_NAME['diurnal']
    assert dc.attributed(switch, 'scale(step(330))@2', t)[0]
    assert not dc.attributed(switch, 'scale(s(t, k=12))@2', t)[0]
    assert dc.attributed(diurnal, 'field(poly(t, 1))', t)[0]
    assert not dc.attributed(diurnal, 'field(step(100))', t)[0]
