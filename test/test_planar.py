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
Planar mode (issue 20 items 4-5): a turn about one axis, what it determines and its heading.

The synthetic robot is written here by hand (not with the model under test): a level IMU
magnetometer with paper 004's kind of errors turning in place twice, with a small roll and
pitch wobble, in a field of 50 000 nT at 65 deg inclination, 3 nT noise.  The real turn is the
HMC5883L's hand-held turn about its z axis (data/real/sunsided-hmc5883l, PROVENANCE.md): the
axis wobbles and z moves by about 6 000 nT.
"""

import json
import pathlib
import subprocess
import sys

from magcal_ros.cli import load_data
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.model import fit
from magcal_ros.core.model import planar as pl
from magcal_ros.io.csvio import write_csv
import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
REAL = REPO / 'data' / 'real' / 'sunsided-hmc5883l'
Z_TURN = REAL / 'rotate-ccw-around-z-pointing-up' / 'rotate-ccw-around-z-pointing-up.csv.gz'
SPHERE = REAL / 'full-sphere' / 'full-sphere.csv.gz'

F_NT, INC_DEG, SIGMA = 50000.0, 65.0, 3.0
# the sensor: scale (kx, ky, kz), paper 004 eq. 2 angles (psi y-z, varphi x-y, theta x-z), rad
K = np.array([1.02, 0.97, 1.01])
PSI, VARPHI, THETA = 0.010, 0.015, -0.012
OFFSET = np.array([300.0, -450.0, 200.0])


def _rot(axis, angle):
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    r = np.repeat(np.eye(3)[None], len(angle), axis=0)
    r[:, i, i], r[:, i, j], r[:, j, i], r[:, j, j] = c, -s, s, c
    return r


def robot_turn(n=1500, wobble_deg=2.0, seed=0):
    """(t (N,) s, raw (N, 3) nT, heading (N,) rad) of the robot turning twice in place."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    heading = 4 * np.pi * t / t[-1]
    roll = np.radians(wobble_deg) * np.sin(2 * np.pi * t / 7.3)
    pitch = np.radians(wobble_deg) * np.sin(2 * np.pi * t / 5.1 + 1.0)
    inc = np.radians(INC_DEG)
    b_ned = F_NT * np.array([np.cos(inc), 0.0, np.sin(inc)])
    r = _rot(2, heading) @ _rot(1, pitch) @ _rot(0, roll)          # body -> NED
    b_body = np.einsum('nji,j->ni', r, b_ned)
    c_no = np.array([[np.cos(THETA) * np.cos(VARPHI), np.cos(THETA) * np.sin(VARPHI),
                      np.sin(THETA)],
                     [0.0, np.cos(PSI), np.sin(PSI)], [0.0, 0.0, 1.0]])
    a = np.diag(K) @ c_no
    raw = b_body @ a.T + OFFSET + rng.normal(0, SIGMA, (n, 3))
    return t, raw, heading


def level_headings(params_fit, model, heading):
    """Heading error (rad) of the fitted correction on level readings at each heading."""
    inc = np.radians(INC_DEG)
    b = F_NT * np.stack([np.cos(inc) * np.cos(heading), -np.cos(inc) * np.sin(heading),
                         np.full_like(heading, np.sin(inc))], axis=1)
    c_no = np.array([[np.cos(THETA) * np.cos(VARPHI), np.cos(THETA) * np.sin(VARPHI),
                      np.sin(THETA)],
                     [0.0, np.cos(PSI), np.sin(PSI)], [0.0, 0.0, 1.0]])
    raw = b @ (np.diag(K) @ c_no).T + OFFSET
    ctx = Dataset(t=np.arange(len(heading), dtype=float), raw=raw[None]).context(1)
    c = model.correct(1, params_fit, raw, ctx)
    got = np.arctan2(-c[:, 1], c[:, 0])
    return np.angle(np.exp(1j * (got - heading)))


@pytest.fixture(scope='module')
def turn_csv(tmp_path_factory):
    # a robot on a flat floor: no tilt, so nothing about the z axis can be learnt
    t, raw, _ = robot_turn(wobble_deg=0.0)
    path = tmp_path_factory.mktemp('planar') / 'turn.csv'
    write_csv(str(path), Dataset(t=t, raw=raw[None]))
    return path


def magcal(*args):
    return subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_a_turn_is_refused_without_planar_naming_the_axis(turn_csv):
    out = magcal('fit', turn_csv, '--field-nt', F_NT)
    assert out.returncode == 2
    assert 'rotation about one axis only' in out.stderr
    assert '+1.00)' in out.stderr                     # the z axis, in the sensor frame


def test_planar_determines_the_in_plane_parameters(turn_csv):
    out = magcal('fit', turn_csv, '--field-nt', F_NT, '--planar', '--json')
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    pl_ = s['planar']
    e = pl_['in_plane']['1']
    assert e['axes'] == 'xy'
    # the ratio of the in-plane scale factors and their angle, within 4 sd of the truth
    assert abs(e['scale_ratio'] - K[1] / K[0]) < 4 * e['scale_ratio_stderr']
    assert e['scale_ratio_stderr'] < 2e-3                       # and determined
    assert abs(e['nonorth_rad'] - VARPHI) < 4 * e['nonorth_stderr_rad']
    assert e['nonorth_stderr_rad'] < 2e-3
    # level turn: only the in-plane angle is determined one by one; the in-plane offsets only
    # in their sum with the out-of-plane angles times Z (the effective offsets), the in-plane
    # scales only in their ratio
    assert set(s['undetermined']) == {'offset.bx@1', 'offset.by@1', 'offset.bz@1',
                                      'scale.kx@1', 'scale.ky@1', 'scale.kz@1',
                                      'nonorthogonality.psi@1', 'nonorthogonality.theta@1'}
    assert s['planar']['determined'] == ['nonorthogonality.varphi@1']
    # the effective offsets: the circle's centre, o_p + A_pn Z (by hand from the truth)
    z = F_NT * np.sin(np.radians(INC_DEG))
    truth = OFFSET[:2] + np.array([K[0] * np.sin(THETA), K[1] * np.sin(PSI)]) * z
    got, sd = np.array(e['effective_offset_nt']), np.array(e['effective_offset_stderr_nt'])
    assert np.all(sd < 1.0)
    assert np.all(np.abs(got - truth) < 4 * sd)
    assert s['heading_error_deg'] == max(pl_['heading_error_deg'].values())
    assert any('does not determine' in w['text'] for w in s['warnings'])


def test_a_wobble_determines_what_a_level_turn_cannot():
    # 2 deg of roll and pitch move H by ~740 nT into and out of the z axis: against 3 nT of
    # noise that determines the z scale and offset (the data, not a list, decide)
    t, raw, _ = robot_turn(wobble_deg=2.0)
    pr = pl.fit_planar(Dataset(t=t, raw=raw[None]), 'base', F_NT)
    assert 'scale.kz@1' not in pr.undetermined and 'offset.bz@1' not in pr.undetermined
    t, raw, _ = robot_turn(wobble_deg=0.0)
    pr = pl.fit_planar(Dataset(t=t, raw=raw[None]), 'base', F_NT)
    assert 'scale.kz@1' in pr.undetermined and 'offset.bz@1' in pr.undetermined


def test_the_stated_heading_error_holds_on_level_headings():
    # independent seeds: the actual heading error of each calibration on level readings
    # stays within 3 times its stated 1-sd error (largest over headings)
    heading = np.radians(np.arange(0, 360, 5.0))
    worst = []
    for seed in range(3):
        t, raw, _ = robot_turn(seed=seed)
        pr = pl.fit_planar(Dataset(t=t, raw=raw[None]), 'base', F_NT,
                           inclination_deg=INC_DEG)
        err = np.degrees(level_headings(pr.result.params, pr.result.model, heading))
        stated = pr.heading[0]['max_deg']
        assert 0 < stated < 0.05           # 3 nT of noise against H = 21 000 nT
        worst.append(np.abs(err).max() / stated)
    assert max(worst) < 3.0, worst


def test_held_parameters_follow_the_previous_calibration():
    t, raw, _ = robot_turn()
    data = Dataset(t=t, raw=raw[None])
    model = 'base'
    pr0 = pl.fit_planar(data, model, F_NT)
    prior = pr0.result.params.copy()
    info = pr0.result.model.param_info()
    bz = next(i for i, (_, lab, nm, _) in enumerate(info) if (lab, nm) == ('offset', 'bz'))
    prior[bz] = 180.0
    pr1 = pl.fit_planar(data, model, F_NT, prior_params=prior)
    # held near the previous calibration's value (its prior sd is 5 % of F = 2500 nT; the data
    # move it by much less than that)
    assert abs(pr1.result.params[bz] - 180.0) < 0.5 * pl.PRIOR_SD['offset'] * F_NT
    with pytest.raises(ValueError, match='previous calibration of the same model'):
        pl.fit_planar(data, model, F_NT, prior_params=prior[:-1])


def test_data_that_are_not_a_turn_are_refused():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, 3))
    v *= F_NT / np.linalg.norm(v, axis=1, keepdims=True)
    with pytest.raises(pl.PlanarError, match='did not turn about one axis'):
        pl.turn_axis(v)


def test_a_turn_far_from_every_sensor_axis_is_refused():
    t, raw, _ = robot_turn()
    tilt = _rot(0, np.full(1, np.radians(40.0)))[0]
    data = Dataset(t=t, raw=(raw @ tilt.T)[None])
    with pytest.raises(pl.PlanarError, match='deg from the sensor'):
        pl.fit_planar(data, 'base', F_NT)


# -- the real hand-held turn -------------------------------------------------------------

@pytest.fixture(scope='module')
def real_turn():
    return load_data(str(Z_TURN))


def _headings(pr, data):
    c = pr.result.model.correct(1, pr.result.params, data.raw[0], data.context(1))
    return np.arctan2(-c[:, 1], c[:, 0])


def test_real_turn_halves_agree_within_the_stated_heading_error(real_turn):
    # calibrate on each half of the turn (each turns once); the second half's headings
    # corrected with the first half's calibration and with its own agree within the stated
    # errors, up to a constant heading.  Measured: RMS difference 0.32 deg against a
    # combined stated RMS of 0.31 deg (1.05 x); the largest 0.75-0.84 deg against 0.49 deg
    # (1.7 sd).  Without the widening for correlated residuals: 1.2 x and 2 sd
    n = real_turn.n_samples
    halves = [real_turn.subset(np.arange(n // 2)), real_turn.subset(np.arange(n // 2, n))]
    f = pl.planar_magnitude(real_turn.raw[0], pl.turn_axis(real_turn.raw[0]))
    cals = [pl.fit_planar(h, 'base', f) for h in halves]
    stated_rms = np.hypot(*(c.heading[0]['rms_deg'] for c in cals))
    stated_max = np.hypot(*(c.heading[0]['max_deg'] for c in cals))
    for test in halves:
        d = _headings(cals[0], test) - _headings(cals[1], test)
        d = np.angle(np.exp(1j * d))
        d = np.degrees(d - np.angle(np.mean(np.exp(1j * d))))
        assert np.sqrt(np.mean(d ** 2)) < 1.15 * stated_rms
        assert np.abs(d).max() < 2 * stated_max


def test_real_turn_wobble_does_not_leak_into_the_axis_ratio(real_turn):
    # a naive 2D ellipse fit of x, y reads an axis ratio of 1.67 (the wobble moves Z into the
    # plane); the full sphere of the same sensor says ky/kx = 1.062; the planar fit must read
    # the sphere's ratio within 4 of its stated sd, not the ellipse's
    x, y = real_turn.raw[0, :, 0], real_turn.raw[0, :, 1]
    design = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c = np.linalg.svd(design, full_matrices=False)[2][-1][:3]
    w = np.abs(np.linalg.eigvalsh([[a, b / 2], [b / 2, c]]))
    assert np.sqrt(w.max() / w.min()) > 1.6                  # the naive 2D ellipse
    f = pl.planar_magnitude(real_turn.raw[0], pl.turn_axis(real_turn.raw[0]))
    pr = pl.fit_planar(real_turn, 'base', f)
    assert pr.residual_correlation[0] > 0.2         # 0.28: the reason for the widening
    e = pl.planar_summary(pr)['in_plane']['1']
    sphere = load_data(str(SPHERE))
    from magcal_ros.core.data.magnitude import auto_magnitude
    full = fit(sphere, 'base', field_nt=auto_magnitude(sphere.raw[0]))
    kx, ky = full.params[:2]
    assert abs(ky / kx - 1.062) < 0.002
    assert abs(e['scale_ratio'] - ky / kx) < 4 * e['scale_ratio_stderr']


def test_swept_angle_counts_turns_and_not_noise():
    t, raw, heading = robot_turn(wobble_deg=1.0)
    # the angle about the circle's centre is not the heading (the sensor's scale and angle
    # make it an ellipse, the wobble tilts it): a few degrees over whole turns, up to 9 deg
    # on a half turn (the circle fitted to half an ellipse): enough for counting turns
    assert pl.swept_angle(raw) == pytest.approx(heading[-1] - heading[0], abs=0.06)
    quarter = len(t) // 4
    assert pl.swept_angle(raw[:quarter]) == pytest.approx(heading[quarter - 1], abs=0.15)
    rng = np.random.default_rng(3)
    still = raw[0] + rng.normal(0, 3.0, (400, 3))          # a robot that does not move
    assert pl.swept_angle(still) == 0.0
