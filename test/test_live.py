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
magcal_ros.core.live.corrector.LiveCorrector: the live correction without ROS.

References are written here, not taken from the model code: raw readings are made by hand
from a chosen A_j, offset and field; the tensor of a linear field B(r) = B0 + G r is chosen
here; the field rate is the slope of a line; the tensor covariance is checked by Monte Carlo.
"""
from magcal_ros.core.effects import SensorContext
from magcal_ros.core.geometry.tensor import cross_positions
from magcal_ros.core.live.corrector import (LiveCorrector, MissingSignal, RESIDUAL_WARN_RATIO,
                                            ResidualMonitor)
from magcal_ros.core.model import Calibration, Model
import numpy as np
import pytest


def _rot_z(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


#: intrinsic matrices C_j (upper triangular: scale and non-orthogonality) and rotations R_j
#: (sensor j's axes in the array frame); raw_j = C_j R_j^T b + o_j (paper 004 eq. 2-3)
C = [np.array([[1.02, 0.004, -0.003], [0.0, 0.97, 0.002], [0.0, 0.0, 1.01]]),
     np.array([[0.99, -0.002, 0.001], [0.0, 1.03, 0.003], [0.0, 0.0, 0.98]]),
     np.array([[1.01, 0.001, 0.002], [0.0, 0.995, -0.004], [0.0, 0.0, 1.02]]),
     np.array([[0.98, 0.003, 0.0], [0.0, 1.01, 0.001], [0.0, 0.0, 1.005]])]
R = [np.eye(3), _rot_z(8.0), _rot_x(-5.0), _rot_z(-3.0) @ _rot_x(4.0)]
#: offsets o_j, nT
OFFSETS = np.array([[120.0, -80.0, 30.0], [-50.0, 60.0, 200.0], [10.0, 0.0, -40.0],
                    [300.0, -250.0, 75.0]])
SIGMA_NT = 2.0


def _calibration(spec='base'):
    model = Model.from_spec(spec, 4)
    p = model.default_params()
    for j in range(1, 5):
        p = model.params_from_linear(j, C[j - 1] @ R[j - 1].T, OFFSETS[j - 1], p)
    return Calibration(model, p, sigma_nt=np.full(4, SIGMA_NT))


def _raw(j, b):
    return C[j - 1] @ R[j - 1].T @ b + OFFSETS[j - 1]


def test_correction_recovers_the_field_written_by_hand():
    live = LiveCorrector(_calibration(), 4, cross_positions(0.5))
    b = np.array([21000.0, -4000.0, 43000.0])
    for j in range(1, 5):
        np.testing.assert_allclose(live.correct(j, 1.0, _raw(j, b)), b, atol=1e-6)


def test_gradient_of_a_linear_field_and_its_stamp():
    baseline = 0.5
    pos = cross_positions(baseline)
    live = LiveCorrector(_calibration(), 4, pos, stamp_tolerance_s=0.004)
    g_true = np.array([[10.0, 3.0, -2.0], [3.0, -4.0, 5.0], [-2.0, 5.0, -6.0]])  # nT/m
    b0 = np.array([20000.0, 1000.0, 45000.0])
    out = []
    for k in range(300):                      # 300 epochs at 100 Hz, sensor stamps 1 ms apart
        for j in range(1, 5):
            t = 10.0 + 0.01 * k + 0.001 * (j - 1)
            b = live.correct(j, t, _raw(j, b0 + g_true @ pos[j - 1]))
            out.extend(live.gradients(j, t, b))
    assert len(out) > 250                      # all but the epochs before the first vote
    t_set, g = out[-1]
    np.testing.assert_allclose(g, g_true, atol=1e-6)
    # the set's stamp: the median of its four stamps (10 + 0.01 k + 1.5 ms)
    assert t_set == pytest.approx(10.0 + 0.01 * 299 + 0.0015, abs=1e-9)


def test_tensor_covariance_matches_monte_carlo():
    """gradient_cov_nt2 against the sample covariance of tensors from noisy raw readings."""
    live = LiveCorrector(_calibration(), 4, cross_positions(0.5))
    rng = np.random.default_rng(3)
    b = np.array([20000.0, 1000.0, 45000.0])
    n = 20000
    gs = np.empty((n, 9))
    for i in range(n):
        fields = [live.correct(j, 0.0, _raw(j, b) + rng.normal(scale=SIGMA_NT, size=3))
                  for j in range(1, 5)]
        gs[i] = live.gradient_op @ np.concatenate(fields)
    mc = np.cov(gs.T)
    cov = live.gradient_cov_nt2
    # variances: relative standard error of a sample variance is sqrt(2 / n) = 1 %; 5 sigma
    d = np.diag(cov)
    np.testing.assert_allclose(np.diag(mc), d, rtol=5 * np.sqrt(2 / n))
    # for the cross, a measured component is a difference of two sensors over the baseline:
    # var = 2 sigma^2 / d^2 (C_j ~ 1: within the few % of the scale factors)
    assert d[0] == pytest.approx(2 * SIGMA_NT ** 2 / 0.5 ** 2, rel=0.08)
    # covariances: standard error sqrt((var_a var_b + cov^2) / n)
    se = np.sqrt((np.outer(d, d) + cov ** 2) / n)
    assert np.all(np.abs(mc - cov) < 5 * se + 1e-12)


def test_sensor_frames_are_the_rotations_written_by_hand():
    pos = cross_positions(0.5)
    live = LiveCorrector(_calibration(), 4, pos)
    frames = live.sensor_frames()
    assert len(frames) == 4
    for j, (rot, p) in enumerate(frames, start=1):
        np.testing.assert_allclose(rot, R[j - 1], atol=1e-9)
        np.testing.assert_allclose(p, pos[j - 1])
    no_geometry = LiveCorrector(_calibration(), 4)
    assert no_geometry.sensor_frames() == []
    assert no_geometry.gradients(1, 0.0, np.zeros(3)) == []
    assert 'no array geometry' in no_geometry.no_gradient_reason


def test_field_rate_from_a_ramp():
    """field_rate: the rate is the slope of the raw ramp (constant sample period)."""
    model = Model.from_spec('base,field_rate', 4)
    p = model.default_params()
    for j in range(1, 5):
        p = model.params_from_linear(j, np.eye(3), np.zeros(3), p)
    tau = np.array([1e-3, -2e-3, 5e-4])            # s, per axis
    for eff, sl in zip(model.effects[0], model.slices[0]):
        if eff.name == 'field_rate':
            p[sl] = tau
    live = LiveCorrector(Calibration(model, p, sigma_nt=np.full(4, 1.0)), 4)
    slope = np.array([300.0, -150.0, 80.0])        # nT/s of the true field
    period = 0.01
    with pytest.raises(MissingSignal, match='field rate needs three consecutive samples'):
        live.correct(1, 0.0, np.zeros(3))
    for k in range(1, 30):
        t = period * k
        b = np.array([20000.0, 0.0, 40000.0]) + slope * t
        # raw = b - tau * d(raw)/dt (FieldRate: lag), and d(raw)/dt = slope for a ramp
        try:
            got = live.correct(1, t, b - tau * slope)
        except MissingSignal:
            continue
        np.testing.assert_allclose(got, b, atol=1e-6)
    assert k == 29 and got is not None


def _driven_calibration(seed=0):
    """Every built-in driven effect on every sensor, with random parameters."""
    model = Model.from_spec('base,temperature,aux:aux_motor_current,field_rate,nonlinearity,'
                            'drift', 4)
    rng = np.random.default_rng(seed)
    p = model.default_params() + rng.normal(scale=1e-3, size=model.n_params)
    for j, row in enumerate(model.effects):
        for eff, sl in zip(row, model.slices[j]):
            eff.refs = {'t0_c': 25.0, 'a0': 1.0, 't0_s': 100.0}
            if eff.name in ('offset', 'nonlinearity'):
                p[sl] = rng.normal(scale=50.0, size=eff.n_params)
            elif eff.name == 'temperature':
                p[sl] = np.r_[rng.normal(scale=2.0, size=3), rng.normal(scale=1e-4, size=3)]
            elif eff.name == 'aux':
                p[sl] = rng.normal(scale=20.0, size=3)
    return Calibration(model, p, sigma_nt=np.full(4, 2.0))


def test_driven_effects_use_the_latest_signals_and_name_the_missing_one():
    """The per-sample path equals the batch correction of the same calibration."""
    cal = _driven_calibration()
    live = LiveCorrector(cal, 4, cross_positions(0.5))
    with pytest.raises(MissingSignal, match='waiting for auxiliary channel aux_motor_current'):
        live.correct(2, 0.0, np.full(3, 1000.0))
    live = LiveCorrector(cal, 4, cross_positions(0.5))
    live.set_aux('aux_motor_current', 2.5)
    messages = []
    for k in range(12):
        with pytest.raises(MissingSignal) as exc:
            live.correct(2, 0.01 * k, np.full(3, 1000.0 + k))
        messages.append(str(exc.value))
    # the period needs 11 arrivals, then the temperature is what is missing
    assert messages[0] == 'sensor 2: field rate needs three consecutive samples'
    assert 'waiting for sensor2/temperature' in messages[-1]
    live.set_temperature(2, 31.0)
    raw = np.array([1012.0, 1012.0, 1012.0])
    got = live.correct(2, 0.12, raw)
    ctx = SensorContext(t=np.array([0.12]), temp=np.array([31.0]),
                        aux={'aux_motor_current': np.array([2.5])},
                        raw_rate=np.array([[100.0, 100.0, 100.0]]))   # 1 nT per 10 ms
    np.testing.assert_allclose(got, cal.correct(2, raw[None], ctx)[0], rtol=1e-9, atol=1e-6)
    with pytest.raises(ValueError, match='is for 4 sensors but this corrector handles 3'):
        LiveCorrector(cal, 3)


# -- ResidualMonitor ---------------------------------------------------------------------------

def test_residuals_of_one_set_by_hand():
    mon = ResidualMonitor(4, 50000.0)
    b = np.array([[30000.0, 40000.0, 3.0],        # |b| = 50000.00009 -> scalar ~ 0
                  [0.0, 0.0, 50010.0],             # scalar +10
                  [0.0, -49990.0, 0.0],            # scalar -10
                  [50000.0, 0.0, 0.0]])
    scalar, vector = mon.add(b)
    np.testing.assert_allclose(scalar, [np.hypot(np.hypot(30000, 40000), 3) - 50000, 10, -10, 0],
                               atol=1e-6)
    others1 = (b[1] + b[2] + b[3]) / 3
    assert vector[0] == pytest.approx(np.linalg.norm(b[0] - others1), rel=1e-12)
    others4 = (b[0] + b[1] + b[2]) / 3
    assert vector[3] == pytest.approx(np.linalg.norm(b[3] - others4), rel=1e-12)
    assert mon.ratios() is None                     # one set: no rolling figure yet


def _tumble(n, rate_hz=100.0):
    """(n, 3) field of a uniform 50 000 nT field seen by a tumbling array, nT."""
    t = np.arange(n) / rate_hz
    b_world = np.array([20000.0, 5000.0, -45553.3])     # |b| = 50 000 nT
    out = np.empty((n, 3))
    for k, tk in enumerate(t):
        out[k] = (_rot_z(360 * tk / 7.0) @ _rot_x(360 * tk / 11.0)).T @ b_world
    return t, out


def test_rolling_ratio_is_one_on_noise_and_flags_a_hidden_effect():
    sigma = 2.0
    n = 1000
    t, b = _tumble(n)
    rng = np.random.default_rng(5)
    noise = rng.normal(scale=sigma, size=(4, n, 3))
    ok = ResidualMonitor(4, float(np.linalg.norm(b[0])), window=n)
    for k in range(n):
        ok.add(b[k][None] + noise[:, k])
    r = ok.ratios()
    assert r['sets'] == n
    # the floor is the noise; RMS of n = 1000 values: relative sd 2 %; the floor's estimate
    # a few % more: 15 % bounds
    np.testing.assert_allclose(r['floor_nt'], sigma, rtol=0.1)
    assert np.all(np.abs(r['scalar_ratio'] - 1) < 0.15), r['scalar_ratio']
    assert np.all(np.abs(r['vector_ratio'] - 1) < 0.15), r['vector_ratio']
    assert np.all(r['scalar_ratio'] <= RESIDUAL_WARN_RATIO)

    # a temperature term the calibration lacks, written here: sensor 2 reads
    # k (T - 25 degC) more, T swinging +-10 degC over 6 s
    temp = 25.0 + 10.0 * np.sin(2 * np.pi * t / 6.0)
    term = np.outer(temp - 25.0, [3.0, -2.0, 1.5])           # (n, 3) nT
    bad = ResidualMonitor(4, float(np.linalg.norm(b[0])), window=n)
    for k in range(n):
        fields = b[k][None] + noise[:, k]
        fields[1] += term[k]
        bad.add(fields)
    r = bad.ratios()
    # the term is smooth: the floor stays the noise, the residual of sensor 2 grows
    np.testing.assert_allclose(r['floor_nt'], sigma, rtol=0.1)
    assert r['scalar_ratio'][1] > 3 and r['vector_ratio'][1] > 3
    assert np.all(r['scalar_ratio'][[0, 2, 3]] < 1.15)
