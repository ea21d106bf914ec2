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
The one calibration path of ``magcal fit`` and calibration_node (issue 33).

:class:`CalibrationRequest` -> :func:`run_request`, and the one printer :func:`summary_lines`.

The request's mode must reach the fit (each mode leaves its own account in the summary, and
the modes exclude each other as documented), and the printer's figures must be those of the
summary (recomputed here by hand from its components).
"""
from magcal_ros.core.data.simulate import simulate
from magcal_ros.pipeline import (CalibrationRequest, cross_geometry, run_request,
                                 summary_lines)
import numpy as np
import pytest

F = 50000.0


@pytest.fixture(scope='module')
def vehicle():
    """Simulate one compass on a vehicle turning at 15 deg of tilt, its attitude known."""
    data, _ = simulate(n_samples=600, rate_hz=10, n_sensors=1, trajectory='vehicle',
                       tilt_deg=15.0, attitude=True, seed=1, aux=False, temp_swing_c=0)
    return data


@pytest.fixture(scope='module')
def cross():
    """Simulate the four-sensor cross tumbling, no attitude."""
    data, _ = simulate(n_samples=600, seed=3, trajectory='random', aux=False)
    return data


def test_the_attitude_option_reaches_the_fit(vehicle):
    fref = {'kind': 'constant', 'magnitude_nt': F}
    auto = run_request(vehicle, CalibrationRequest(field_nt=F, field_reference=fref))
    assert auto.summary['attitude']['mode'] == 'tilt'           # auto: roll and pitch
    assert auto.doc['provenance']['attitude']['mode'] == 'tilt'
    off = run_request(vehicle, CalibrationRequest(field_nt=F, field_reference=fref,
                                                  attitude='off', constrained=True))
    assert 'attitude' not in off.summary
    lines = summary_lines(auto.summary)
    assert any(ln.startswith('attitude: tilt (roll and pitch') for ln in lines), lines
    assert not any(ln.startswith('attitude:') for ln in summary_lines(off.summary))


def test_planar_wins_over_heading_unknown_and_refuses_an_attitude(vehicle):
    fref = {'kind': 'constant', 'magnitude_nt': F}
    both = run_request(vehicle, CalibrationRequest(field_nt=F, field_reference=fref,
                                                   planar=True, heading_unknown=True))
    assert 'planar' in both.summary and 'attitude' not in both.summary
    assert both.summary['planar']['inclination_source'] == 'the fitted field'
    lines = summary_lines(both.summary)
    assert lines[0].startswith('planar: heading error '), lines
    with pytest.raises(ValueError, match='attitude tilt goes with neither planar'):
        run_request(vehicle, CalibrationRequest(field_nt=F, field_reference=fref,
                                                planar=True, attitude='tilt'))


def test_summary_lines_give_the_summary_s_figures(cross):
    fref = {'kind': 'constant', 'magnitude_nt': F}
    req = CalibrationRequest(field_nt=F, field_reference=fref, geometry=cross_geometry(0.5),
                             robust=True)
    run = run_request(cross, req)
    s = run.summary
    lines = summary_lines(s, req)
    # one RMS over the nine components, by hand
    after = np.sqrt(np.mean(np.square(s['tensor_rms_nt_per_m'])))
    before = np.sqrt(np.mean(np.square(s['tensor_rms_before_nt_per_m'])))
    assert lines[0] == (f'tensor RMS before {before:.1f} nT/m, after {after:.2f} nT/m '
                        f'(noise floor '
                        f'{np.sqrt(np.mean(np.square(s["tensor_floor_nt_per_m"]))):.2f} nT/m)')
    robust = [ln for ln in lines if ln.startswith('robust fit:')]
    assert robust == ['robust fit: samples down-weighted as outliers per sensor: ' + ', '.join(
        f'{j}: {n}' for j, n in s['downweighted'].items()) + f' of {s["n_fit_samples"]}']
    assert not any(ln.startswith('robust fit:') for ln in summary_lines(s))
    # a warning of a kind the caller printed already is left out, the others are not
    s = dict(s, warnings=[{'kind': 'degenerate', 'sensor': 1, 'text': 'flat'},
                          {'kind': 'missing_effect', 'sensor': 2, 'text': 'more'}])
    out = summary_lines(s, skip_kinds=('degenerate',))
    assert 'warning [missing_effect]: more' in out and not any('flat' in ln for ln in out)
