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
Every built-in effect against its formula, written out here by hand.

The simulator produces raw data with the same ``Model.forward`` the fit inverts, so a wrong
sign or factor in an effect would be recovered faithfully by the fit and go unnoticed. Here
each effect's raw reading is computed independently, from the formula of its docstring (and
paper 004 eq. 2-3 for the linear ones), for three hand-picked samples.
"""
from magcal_ros.core.effects import SensorContext
from magcal_ros.core.model import Model
import numpy as np
import pytest

B = np.array([[20000.0, -5000.0, 45000.0],
              [-30000.0, 38000.0, 10000.0],
              [1000.0, 2000.0, -49000.0]])                          # (3, 3) nT, true field
T = np.array([10.0, 10.5, 12.0])                                      # s
TEMP = np.array([20.0, 27.0, 31.0])                                   # degC
CUR = np.array([0.0, 2.0, 5.0])                                       # A
RATE = np.array([[100.0, -50.0, 20.0], [0.0, 300.0, -10.0], [-40.0, 0.0, 80.0]])  # nT/s
CTX = SensorContext(t=T, temp=TEMP, aux={'aux_motor_current': CUR}, raw_rate=RATE)


def forward(token, params, refs=None, sensor=1, n_sensors=1):
    """Raw reading (3, 3) nT of sensor ``sensor`` for a model of the effect ``token`` alone."""
    m = Model.from_spec(token, n_sensors)
    effects = m.effects[sensor - 1]
    assert len(effects) == 1, [e.label for e in effects]
    effects[0].refs.update(refs or {})
    p = m.default_params()
    p[m.slices[sensor - 1][0]] = params
    return m.forward(sensor, p, B, CTX)


def rz(a):
    return np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_scale():
    np.testing.assert_allclose(forward('scale', [1.01, 0.98, 1.002]),
                               B * [1.01, 0.98, 1.002], rtol=1e-15)


def test_nonorthogonality():
    psi, phi, th = 0.02, -0.01, 0.03
    # paper 004 eq. 2, C_NO row by row
    c = np.array([[np.cos(th) * np.cos(phi), np.cos(th) * np.sin(phi), np.sin(th)],
                  [0, np.cos(psi), np.sin(psi)],
                  [0, 0, 1]])
    got = forward('nonorthogonality', [psi, phi, th])
    np.testing.assert_allclose(got, B @ c.T, rtol=1e-13, atol=1e-9)
    # one entry by hand: x = cos(th)(cos(phi) Bx + sin(phi) By) + sin(th) Bz
    x0 = np.cos(th) * (np.cos(phi) * 20000 + np.sin(phi) * -5000) + np.sin(th) * 45000
    assert got[0, 0] == pytest.approx(x0, rel=1e-14)


def test_misalignment_on_sensor_2():
    a, b, g = 0.03, -0.02, 0.01
    # paper 004 eq. 3: R1(gamma) about y, R2(beta) about x, R3(alpha) about z
    r1 = np.array([[np.cos(g), 0, -np.sin(g)], [0, 1, 0], [np.sin(g), 0, np.cos(g)]])
    r2 = np.array([[1, 0, 0], [0, np.cos(b), np.sin(b)], [0, -np.sin(b), np.cos(b)]])
    got = forward('misalignment', [a, b, g], sensor=2, n_sensors=2)
    np.testing.assert_allclose(got, B @ (r1 @ r2 @ rz(a)).T, rtol=1e-13, atol=1e-9)
    assert Model.from_spec('misalignment', 2).effects[0] == []     # sensor 1 is the frame


def test_soft_iron():
    k = np.array([[1.1, 0.02, -0.03], [0.01, 0.95, 0.04], [-0.02, 0.03, 1.05]])
    np.testing.assert_allclose(forward('soft_iron', k.ravel(), sensor=2, n_sensors=2),
                               B @ k.T, rtol=1e-15)
    # sensor 1: upper triangular (its rotation is the frame definition)
    np.testing.assert_allclose(forward('soft_iron', k[np.triu_indices(3)]),
                               B @ np.triu(k).T, rtol=1e-15)


def test_offset():
    np.testing.assert_allclose(forward('offset', [25.0, 85.0, -32.0]),
                               B + [25.0, 85.0, -32.0], rtol=1e-15)


def test_temperature():
    c, s = np.array([3.0, -2.0, 1.5]), np.array([1e-4, 0.0, -2e-4])
    dt = (TEMP - 25.0)[:, None]                     # about T0 = 25 degC
    np.testing.assert_allclose(forward('temperature', [*c, *s], {'t0_c': 25.0}),
                               B + dt * c + dt * s * B, rtol=1e-14)


def test_drift_and_drift2():
    d, q = np.array([0.1, -0.2, 0.05]), np.array([1e-3, 0.0, -2e-3])
    tau = (T - 8.0)[:, None]                        # about t0 = 8 s
    np.testing.assert_allclose(forward('drift', d, {'t0_s': 8.0}), B + tau * d, rtol=1e-14)
    np.testing.assert_allclose(forward('drift2', [*d, *q], {'t0_s': 8.0}),
                               B + tau * d + tau ** 2 * q, rtol=1e-14)


def test_nonlinearity():
    q, c = np.array([20.0, -10.0, 5.0]), np.array([-8.0, 4.0, 12.0])
    u = B / 50000.0                                  # full scale F0 = 50 000 nT
    np.testing.assert_allclose(forward('nonlinearity', [*q, *c]),
                               B + q * u ** 2 + c * u ** 3, rtol=1e-14)


def test_aux_coupling():
    v = np.array([4.0, -1.0, 2.5])                   # nT/A
    np.testing.assert_allclose(forward('aux:aux_motor_current', v, {'a0': 1.0}),
                               B + (CUR - 1.0)[:, None] * v, rtol=1e-14)


def test_field_rate():
    tau = np.array([0.002, 0.0, -0.001])             # s
    np.testing.assert_allclose(forward('field_rate', tau), B - RATE * tau, rtol=1e-15)


def test_step():
    s1, s2 = np.array([10.0, 0.0, -5.0]), np.array([0.0, 3.0, 7.0])
    on1 = (T >= 10.2)[:, None]                       # steps at 10.2 s and 11 s
    on2 = (T >= 11.0)[:, None]
    np.testing.assert_allclose(forward('step(10.2,11)', [*s1, *s2]),
                               B + on1 * s1 + on2 * s2, rtol=1e-15)


def test_periodic():
    a, b = np.array([5.0, -3.0, 1.0]), np.array([0.5, 2.0, -4.0])
    ph = (2 * np.pi * 0.25 * (T - 9.0))[:, None]      # 0.25 Hz about t0 = 9 s
    np.testing.assert_allclose(forward('periodic(0.25)', [*a, *b], {'t0_s': 9.0}),
                               B + np.cos(ph) * a + np.sin(ph) * b, rtol=1e-13)


def test_aux_poly():
    v1, v2 = np.array([4.0, -1.0, 2.5]), np.array([0.3, 0.1, -0.2])
    u = (CUR - 1.0)[:, None]
    np.testing.assert_allclose(forward('aux_poly(aux_motor_current,2)', [*v1, *v2],
                                       {'a0': 1.0}),
                               B + u * v1 + u ** 2 * v2, rtol=1e-14)


def test_lag_of_a_ramp():
    # x = 2 degC/s t from x(0) = 0: tau y' = x - y, y(0) = 0 has y = 2 (t - tau + tau e^-t/tau)
    t = np.arange(0.0, 50.0, 0.5)
    x = 2.0 * t
    tau, c = 4.0, np.array([1.5, -0.5, 0.2])
    ctx = SensorContext(t=t, temp=x)
    m = Model.from_spec('lag(temperature)', 1)
    m.effects[0][0].refs['x0'] = 30.0
    p = np.array([*c, tau])
    b = np.tile(B[:1], (len(t), 1))
    y = 2.0 * (t - tau + tau * np.exp(-t / tau))
    np.testing.assert_allclose(m.forward(1, p, b, ctx), b + (y - 30.0)[:, None] * c,
                               rtol=1e-10, atol=1e-9)


def test_linear_effects_compose_in_paper_004_order():
    # A = S C_NO R (paper 004 eq. 2-3), whatever order the tokens are given in
    m = Model.from_spec('misalignment,offset,nonorthogonality,scale', 2)
    p = m.default_params()
    k, no, mis, o = [1.01, 0.99, 1.02], [0.01, 0.02, -0.01], [0.02, 0.0, 0.0], [5.0, 6.0, 7.0]
    for eff, sl in zip(m.effects[1], m.slices[1]):
        p[sl] = {'scale': k, 'nonorthogonality': no, 'misalignment': mis, 'offset': o}[eff.name]
    psi, phi, th = no
    c = np.array([[np.cos(th) * np.cos(phi), np.cos(th) * np.sin(phi), np.sin(th)],
                  [0, np.cos(psi), np.sin(psi)], [0, 0, 1]])
    a = np.diag(k) @ c @ rz(0.02)
    np.testing.assert_allclose(m.forward(2, p, B, CTX), B @ a.T + o, rtol=1e-13, atol=1e-9)
