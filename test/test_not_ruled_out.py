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
What a record cannot rule out: effects the base's own parameters absorb over its motion.

A vehicle that stays level and turns through part of a circle while its electronics warm
up: over that arc a temperature coupling moves the readings as the calibration's offsets
and scales do, so the fit takes it up and the residual stays at the floor.  The diagnosis
must not read that as "nothing is missing" without saying what it could not test; the
size it names must cover the hidden effect (the simulator's truth), and on a record that
turns further the same effect is found and not listed.
"""
import json
import math

import injection as inj
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.discovery import diagnose
from magcal_ros.core.discovery.screen import absorbed
from magcal_ros.pipeline import diagnosis_base
from magcal_ros.report import write_report
import numpy as np
import pytest

TRUTH = {'temperature@1': [4.0, -3.0, 2.5, 0.0, 0.0, 0.0]}      # nT/degC, 1/degC
VEHICLE = {'n_sensors': 1, 'trajectory': 'vehicle', 'tilt_deg': 5.0, 'attitude': True, 'seed': 12,
           'temp_swing_c': 8.0, 'n_samples': 2000, 'rate_hz': 10}


def _diagnose_vehicle(period_s, truth=TRUTH):
    data, _ = simulate(smooth_period_s=period_s, truth=truth, **VEHICLE)
    base, constrained, _ = diagnosis_base(data, 'base', 50000.0, attitude='tilt')
    return data, diagnose(data, field_nt=50000.0, base=base, constrained=constrained)


def test_absorbed_share_by_hand():
    """One base column J = (1, 0), one candidate C = (cos a, sin a): sin^2 a is left."""
    for a in (0.0, 0.3, 1.2, math.pi / 2):
        c = np.array([math.cos(a), math.sin(a)])
        share = absorbed(np.array([[c @ c]]), np.array([[c[0]]]), np.array([[1.0]]),
                         np.array([[c @ c]]))
        assert share == pytest.approx(math.sin(a) ** 2, abs=1e-12)
    # the field projection leaving nothing: no fit of the magnitude sees it, not reported
    assert absorbed(np.array([[1e-5]]), np.array([[0.0]]), np.array([[1.0]]),
                    np.array([[1.0]])) is None


def test_a_partial_turn_names_the_temperature_it_cannot_rule_out(tmp_path):
    data, diag = _diagnose_vehicle(1200.0)        # about 50 deg of heading in 200 s
    assert diag.verdict_token is None and diag.at_floor, diag.summary()
    hidden = dict(diag.not_ruled_out)
    assert 'temperature@1' in hidden, diag.summary()
    # the named size covers the effect that did hide: the truth's RMS per axis
    clean, _ = simulate(smooth_period_s=1200.0, **VEHICLE)
    truth_rms = float(np.sqrt(np.mean((data.raw[0] - clean.raw[0]) ** 2)))
    assert truth_rms > 3 * diag.noise_floor.value_nt          # far above the floor, yet hidden
    assert hidden['temperature@1'] >= truth_rms, (hidden, truth_rms)
    doc = json.loads(diag.to_json())
    row = next(r for r in doc['not_ruled_out'] if r['token'] == 'temperature@1')
    assert row['hideable_rms_nt'] == pytest.approx(hidden['temperature@1'])
    assert 'not ruled out by this record' in diag.summary()
    # the HTML report says it beside the candidates, not only in its printed summary
    page = write_report(tmp_path, data, diagnosis=diag).read_text()
    assert page.count('not ruled out by this record') == 2, page


def test_a_fuller_turn_finds_the_temperature_and_does_not_list_it():
    _, diag = _diagnose_vehicle(120.0)            # several part circles in 200 s
    assert diag.verdict_token == 'temperature@1', diag.summary()
    assert 'temperature@1' not in dict(diag.not_ruled_out)


def test_a_tumbling_array_leaves_nothing_above_the_floor_untested():
    data = inj.make(3000, seed=6)
    diag = diagnose(data, 'base', field_nt=inj.F_NT)
    assert diag.verdict_token is None
    assert diag.not_ruled_out == [], diag.not_ruled_out
    assert 'not ruled out' not in diag.summary()
