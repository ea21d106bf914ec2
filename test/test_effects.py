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

"""Every built-in effect: simulate it with known parameters, fit it, recover them."""
import injection as inj  # test/injection.py: the cross written out by hand
from magcal_ros.core import effects as fx
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.model import fit, Model
import numpy as np
import pytest

F = 50000.0

CASES = [
    ('temperature@2', [3.0, -2.0, 1.5, 2e-4, -1e-4, 1e-4]),
    ('drift@3', [0.5, -0.3, 0.2]),
    ('drift2@1', [0.3, -0.2, 0.1, 0.01, -0.01, 0.005]),
    ('nonlinearity@1', [200.0, -150.0, 100.0, 80.0, -60.0, 50.0]),
    ('aux:aux_motor_current', [4.0, -3.0, 2.0]),
    ('field_rate@2', [2e-3, 1e-3, 1.5e-3]),
]


@pytest.mark.parametrize('token,values', CASES, ids=[c[0] for c in CASES])
def test_effect_is_recovered(token, values):
    data, sim = simulate(n_samples=3000, trajectory='smooth', seed=11, truth={token: values})
    res = fit(data, 'base,' + token, field_nt=F)
    z = (res.params - sim.params) / res.stderr
    # all parameters (base + effect) within 4.5 standard uncertainties of the truth
    assert np.abs(z).max() < 4.5, res.param_table()
    # and the residual is at the 3 nT noise (RMS over 3000 samples: +-1.3 % sd)
    assert max(res.scalar_rms_nt.values()) < 3.0 * 1.06
    # without the effect the residual is larger (the effect is really there)
    base = fit(data, 'base', field_nt=F)
    worse = max(max(base.scalar_rms_nt.values()), max(base.vector_rms_nt.values()) / np.sqrt(2))
    assert worse > 3.0 * 1.15


def _temperature_fault(t, temp, aux, b):
    # dB = c (T - T0) + s (T - T0) * (K_2 b), T0 the mean temperature of the record
    dt = (temp[1] - temp[1].mean())[:, None]
    return {2: dt * np.array([3.0, -2.0, 1.5])
            + dt * np.array([2e-4, -1e-4, 1e-4]) * (b @ inj.sensor_matrix(2).T)}


def _drift_fault(t, temp, aux, b):
    return {3: (t - t[0])[:, None] * np.array([0.5, -0.3, 0.2])}          # nT/s


def _aux_fault(t, temp, aux, b):
    a = aux['aux_motor_current']
    return {4: (a - a.mean())[:, None] * np.array([4.0, -3.0, 2.0])}      # nT/A


HAND = [('temperature@2', _temperature_fault, [3.0, -2.0, 1.5, 2e-4, -1e-4, 1e-4]),
        ('drift@3', _drift_fault, [0.5, -0.3, 0.2]),
        ('aux:aux_motor_current@4', _aux_fault, [4.0, -3.0, 2.0])]


@pytest.mark.parametrize('token,inject,values', HAND, ids=[c[0] for c in HAND])
def test_hand_written_effect_is_recovered(token, inject, values):
    # the effect written out in the test (not by the effect's own code), on the hand-written
    # cross: the fitted coefficients are the stated ones within 4.5 of the fit's standard
    # uncertainties (checked against Monte Carlo in test_model_ml.py), and each sensor's
    # linear map and offset the stated K_j and o_j (noise bounds as in
    # test_model_paper004.py: 6 sd per entry, 5 sd per offset, N = 600)
    n = 600
    res = fit(inj.make(n=n, seed=5, inject=inject), 'base,' + token, field_nt=inj.F_NT)
    sl = [s for e, s in zip(res.model.effects[int(token[-1]) - 1],
                            res.model.slices[int(token[-1]) - 1]) if e.label == token[:-2]]
    assert len(sl) == 1, res.model.spec()
    z = (res.params[sl[0]] - values) / res.stderr[sl[0]]
    assert np.abs(z).max() < 4.5, (res.params[sl[0]], values, res.stderr[sl[0]])
    cal = res.calibration
    for j in range(1, 5):
        a = np.linalg.inv(cal.correction_matrix(j))
        assert np.abs(a - inj.sensor_matrix(j)).max() < 6 * 3.0 / F / np.sqrt(n / 3), j
        assert np.abs(cal.offset(j) - inj.SENSORS[j - 1][3]).max() < 5 * 3.0 * np.sqrt(3 / n)


def test_field_rate_shows_in_vector_residual_not_scalar():
    """A lag is perpendicular to B under rotation: invisible in |B|, visible between sensors."""
    data, _ = simulate(n_samples=3000, trajectory='smooth', seed=12, truth={
        'field_rate@2': [2e-3, 2e-3, 2e-3]})
    # each sensor calibrated on its own (scalar residual only): sensor 2 looks perfect
    scalar_only = fit(data, 'offset,scale,nonorthogonality', field_nt=F)
    assert scalar_only.scalar_rms_nt[2] < 3.0 * 1.06
    # the joint fit with misalignment sees it between sensors (3 nT x sqrt(2) = 4.2 nT floor)
    base = fit(data, 'base', field_nt=F)
    assert base.vector_rms_nt[2] > 3.0 * np.sqrt(2) * 1.5
    assert base.vector_rms_nt[3] < 3.0 * np.sqrt(2) * 1.06


def test_unexcited_effects_are_refused_with_reason():
    data, _ = simulate(n_samples=500, trajectory='smooth', seed=1, temp_swing_c=0.2)
    with pytest.raises(ValueError, match=r'temperature of sensor 2 varies only 0\.\d+ degC'):
        fit(data, 'base,temperature@2', field_nt=F)
    data.aux['aux_motor_current'][:] = 2.0
    with pytest.raises(ValueError, match="'aux_motor_current' never changes"):
        fit(data, 'base,aux:aux_motor_current', field_nt=F)
    with pytest.raises(ValueError, match="no auxiliary column 'aux_heater'"):
        fit(data, 'base,aux:heater', field_nt=F)


def test_plugin_registration_and_errors():
    class Hum(fx.Effect):
        """Mains hum pickup: dB = a sin(2 pi 50 t) + b cos(2 pi 50 t)."""

        name = 'hum_test'
        param_names = ('ax', 'ay', 'az')
        units = ('nT',) * 3

        def contribution(self, p, ctx, lin):
            return np.sin(2 * np.pi * 0.37 * ctx.t)[:, None] * p

    fx.register_effect(Hum)
    try:
        assert 'hum_test' in fx.registered_effects()
        m = Model.from_spec('base,hum_test@1', 4)
        assert m.has(1, 'hum_test') and not m.has(2, 'hum_test')
        with pytest.raises(ValueError, match='already registered'):
            fx.register_effect(type('Other', (fx.Effect,), {'name': 'hum_test'}))
    finally:
        # a registered effect is a candidate of every later diagnosis: never leave it behind
        fx.unregister_effect('hum_test')
    assert 'hum_test' not in fx.registered_effects()
    with pytest.raises(TypeError, match='not a subclass'):
        fx.register_effect(int)
    with pytest.raises(ValueError, match='cannot import effect plugin'):
        fx.load_plugin('no_such_module_xyz')


def test_misalignment_angle_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.uniform(-0.3, 0.3, 3)
        r = fx.misalignment_matrix(*a)
        assert np.allclose(fx.misalignment_angles(r), a, atol=1e-12)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)


# -- effects with arguments (issue 11), on data written without Model.forward ---------------

#: (token, fault, {parameter: (true value, tolerance)}).  Tolerances: 4 standard uncertainties
#: of the fit at 3 nT noise and 3000 samples (stderr printed by the fit: 0.13 nT for a step,
#: 0.09 nT for a sinusoid's amplitude, 0.7 s for the 90 s lag, 0.013 nT/A^2 for the square).
NEW_CASES = [
    ('step(300)@1', inj.step_fault(300.0, (40.0, 0.0, 0.0), 1),
     {'sx': (40.0, 0.6), 'sy': (0.0, 0.6), 'sz': (0.0, 0.6)}),
    # x = 15 cos(ph); y = 15 sin(ph + 0.4) = 15 cos(0.4) sin(ph) + 15 sin(0.4) cos(ph)
    ('periodic(0.23)@3', inj.periodic_fault(0.23, 15.0, 3),
     {'ax': (15.0, 0.4), 'bx': (0.0, 0.4), 'ay': (15 * np.sin(0.4), 0.4),
      'by': (15 * np.cos(0.4), 0.4), 'az': (15 * np.cos(2.0), 0.4),
      'bz': (-15 * np.sin(2.0), 0.4)}),
    ('lag(temperature)@2', inj.lag_fault(90.0, (4.0, -3.0, 2.5), 2),
     {'tau': (90.0, 3.0), 'cx': (4.0, 0.12), 'cy': (-3.0, 0.12), 'cz': (2.5, 0.12)}),
]


@pytest.mark.parametrize('token,fault,truth', NEW_CASES, ids=[c[0] for c in NEW_CASES])
def test_effect_with_arguments_fits_a_fault_written_by_hand(token, fault, truth):
    data = inj.make(3000, seed=1, inject=fault)
    base = fit(data, 'base', field_nt=inj.F_NT)
    res = fit(data, 'base,' + token, field_nt=inj.F_NT)
    label = token.split('@')[0]
    got = {n: (v, e) for (_, lab, n, _), v, e in zip(res.model.param_info(), res.params,
                                                     res.stderr) if lab == label}
    for name, (true, tol) in truth.items():
        assert abs(got[name][0] - true) < tol, (name, got[name], true)
    # the effect was really there (3.5x the noise on its sensor) and is now fully explained:
    # every scalar RMS within 4 % of the 3 nT noise (RMS of 3000 samples: 1.3 % sd)
    assert max(base.scalar_rms_nt.values()) > 3 * inj.SIGMA_NT
    assert max(res.scalar_rms_nt.values()) < 1.04 * inj.SIGMA_NT


def test_aux_poly_fits_current_squared_on_all_sensors():
    data = inj.make(3000, seed=1, inject=inj.current_squared_fault((0.6, -0.4, 0.5)))
    res = fit(data, 'base,aux_poly(aux_motor_current,2)', field_nt=inj.F_NT)
    assert max(res.scalar_rms_nt.values()) < 1.04 * inj.SIGMA_NT
    for j in range(1, 5):
        v2 = [v for (s, _, n, _), v in zip(res.model.param_info(), res.params)
              if s == j and n in ('v2x', 'v2y', 'v2z')]
        assert len(v2) == 3
        # i^2 = (i - a0)^2 + 2 a0 (i - a0) + a0^2: the square's coefficient is the truth
        assert np.allclose(v2, np.array([0.6, -0.4, 0.5]) * (1 + 0.3 * j), atol=0.06), (j, v2)


def test_token_syntax_and_errors():
    m = Model.from_spec('base,step(120,300)@2,periodic(0.23)@3,lag(temperature)@2,'
                        'aux_poly(motor_current,2)@1', 4)
    assert 'step(120,300)@2' in m.spec() and 'aux_poly(aux_motor_current,2)@1' in m.spec()
    assert [n for (s, lab, n, _) in m.param_info() if lab == 'step(120,300)'] == [
        's1x', 's1y', 's1z', 's2x', 's2y', 's2z']
    assert [t.strip() for t in fx.formula.split_top('base, step(1,2)@2 ,x', ',')] == [
        'base', 'step(1,2)@2', 'x']
    assert fx.parse_token('step(120, 300)@2') == ('step', ('120', '300'), 2)
    assert fx.parse_token('drift') == ('drift', (), None)
    # the same model spelled from its own spec
    assert Model.from_spec(m.spec(), 4).spec() == m.spec()
    for bad, msg in [('base,step', 'needs arguments'), ('base,periodic(x)', 'not a number'),
                     ('base,periodic(-1)', 'positive'), ('base,step(1,2', 'unbalanced'),
                     ('base,drift(3)', 'takes no arguments'),
                     ('base,aux_poly(aux_motor_current,7)', 'degree')]:
        with pytest.raises(ValueError, match=msg):
            Model.from_spec(bad, 4)
    # the polynomial contains the linear coupling: it replaces it, in either order
    for spec in ('base,aux:aux_motor_current@1,aux_poly(aux_motor_current,2)@1',
                 'base,aux_poly(aux_motor_current,2)@1,aux:aux_motor_current@1'):
        m = Model.from_spec(spec, 4)
        assert 'aux_poly(aux_motor_current,2)@1' in m.spec()
        assert not any(t.startswith('aux:') for t in m.spec())


def test_lag_keeps_its_state_in_a_subset():
    """A held-out block of a record sees the lag filter run over the whole record."""
    t = np.arange(2000) * 0.2
    x = np.where(t > 100, 10.0, 0.0)
    ctx = fx.SensorContext(t=t, temp=x)
    eff = fx.make_effect('lag(temperature)', 1)
    p = np.array([1.0, 0.0, 0.0, 50.0])
    eff.prepare(ctx)
    whole = eff.contribution(p, ctx, np.zeros((2000, 3)))
    idx = np.arange(1000, 1500)
    part = eff.contribution(p, ctx.subset(idx), np.zeros((500, 3)))
    assert np.allclose(part, whole[idx])
    # and the filter is the lag: 1 - exp(-(t - 100)/50) of the 10 degC step (hand formula)
    ref = 10.0 * (1 - np.exp(-np.clip(t - 100, 0, None) / 50.0)) - eff.refs['x0']
    assert np.max(np.abs(whole[:, 0] - ref)[t > 101]) < 0.05


def test_lag_one_sample_at_a_time_keeps_its_state():
    """
    Keep the state of the lag filter between one-sample calls.

    Live correction feeds one sample per call: the filter state is carried between calls
    and takes the batch filter's steps (one discretisation: equal to rounding).
    """
    t = np.arange(2000) * 0.2
    x = np.where(t > 100, 10.0, 0.0)
    eff = fx.make_effect('lag(temperature)', 1)
    eff.prepare(fx.SensorContext(t=t, temp=x))
    p = np.array([1.0, 0.0, 0.0, 50.0])
    batch = eff.contribution(p, fx.SensorContext(t=t, temp=x), np.zeros((2000, 3)))[:, 0]
    live = [eff.contribution(p, fx.SensorContext(t=t[k:k + 1], temp=x[k:k + 1]),
                             np.zeros((1, 3)))[0, 0] for k in range(2000)]
    np.testing.assert_allclose(live, batch, rtol=0, atol=1e-12)
    # by hand: x ramps 0 -> 10 over the sample at 100 .. 100.2 s (linear between samples),
    # y(100.2) = 10 (1 - tau/h (1 - e^-h/tau)), then relaxes to 10 with e^-(t - 100.2)/tau
    h, tau = 0.2, 50.0
    y0 = 10.0 * (1 - tau / h * (1 - np.exp(-h / tau)))
    want = 10.0 + (y0 - 10.0) * np.exp(-(t[-1] - 100.2) / tau) - eff.refs['x0']
    assert live[-1] == pytest.approx(want, abs=1e-9)
