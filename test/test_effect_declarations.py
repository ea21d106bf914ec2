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
Effects describe themselves: a plug-in is one class, and every part of the code obeys it.

The plug-in here reads the sensor temperature (a thermal offset quadratic in T - T0, which the
built-in linear ``temperature`` effect cannot describe) and is used in models WITHOUT the
built-in temperature effect: simulation, fit, diagnosis, the calibration file and the live
correction must all hand it the temperature because it declares ``signals``, not because
of its name.  The recordings for the fit are made in this file from the formula, not with
``Model.forward``.
"""
from magcal_ros.core import effects as fx
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.discovery import diagnose
from magcal_ros.core.model import fit, Model, priors_for
from magcal_ros.io.calfile import calibration_from_doc, calibration_to_doc
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

F = 50000.0                       # nT
SIGMA = 3.0                       # nT, white noise per axis
C_TRUE = np.array([0.5, -0.3, 0.4])   # nT/degC^2
K_TRUE = np.array([1.01, 0.99, 1.02])
O_TRUE = np.array([120.0, -80.0, 40.0])   # nT


class ThermalSquare(fx.Effect):
    """Offset quadratic in the temperature: dB = c (T - T0)^2, T0 the mean temperature."""

    name = 'thermal_square_test'
    param_names = ('cx', 'cy', 'cz')
    units = ('nT/degC^2',) * 3
    signals = ('temperature',)

    def prepare(self, ctx):
        if ctx.temp is not None:
            self.refs.setdefault('t0_c', float(np.nanmean(ctx.temp)))

    def check(self, ctx):
        if ctx.temp is None:
            return 'no temperature column'
        return None

    def contribution(self, p, ctx, lin):
        return ((ctx.temp - self.refs.get('t0_c', 0.0)) ** 2)[:, None] * p


class Tilt(fx.Effect):
    """A linear plug-in: rotation about z of sensor j relative to sensor 1 (angle a, rad)."""

    name = 'tilt_test'
    kind = 'linear'
    param_names = ('a',)
    units = ('rad',)
    linear_order = 5              # right of the misalignment (3)
    frame_rotation = True
    on_sensor1 = False
    prior = (0.0, 0.01)

    def matrix(self, p):
        return fx.rot_r3(p[0])


@pytest.fixture
def plugins():
    fx.register_effect(ThermalSquare)
    fx.register_effect(Tilt)
    yield
    fx.unregister_effect(ThermalSquare.name)
    fx.unregister_effect(Tilt.name)
    assert ThermalSquare.name not in fx.registered_effects()


def _recording(n=2000, seed=3):
    """
    One sensor tumbled smoothly (as by hand) while its temperature swings 25 +- 8 degC.

    raw = diag(k) B + o + c (T - mean T)^2 + noise, written out here (not Model.forward).
    The attitude changes little between samples, so the noise floor from sample differences
    sees the noise, not the missing effect.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.25                                        # s, 4 Hz, 500 s
    w = 2 * np.pi / 60.0
    rot = Rotation.from_euler('ZYX', np.column_stack(
        [w * 3.1 * t, np.radians(85) * np.sin(w * 1.7 * t), np.pi * np.sin(w * 1.13 * t)]))
    b = rot.inv().apply(F * np.array([np.cos(0.96), 0.0, np.sin(0.96)]))   # (N, 3) nT
    temp = 25.0 + 8.0 * np.sin(2 * np.pi * t / 250.0)             # degC, two periods
    dt2 = (temp - temp.mean()) ** 2
    raw = b * K_TRUE + O_TRUE + dt2[:, None] * C_TRUE + rng.normal(scale=SIGMA, size=(n, 3))
    return Dataset(t=t, raw=raw[None], temp=temp[None]), b


def test_declarations_of_the_builtin_effects():
    # what model.py and the corrector once recognised by name, now declared by each class
    def token(name, *args):
        return fx.TOKEN_CLASSES[name](args=args)
    assert token('temperature').signals == ('temperature',)
    assert token('field_rate').signals == ('field_rate',)
    assert token('drift').signals == ('time',)
    assert token('aux', 'motor_current').signals == ('aux_motor_current',)
    assert token('lag', 'aux_pump').signals == ('time', 'aux_pump')
    assert token('nonlinearity').signals == () and token('nonlinearity').depends_on_lin()
    assert token('temperature').depends_on_lin() and not token('drift2').depends_on_lin()
    assert fx.Offset.constant and not token('temperature').constant
    assert [c.linear_order for c in (fx.Scale, fx.NonOrthogonality, fx.SoftIron,
                                     fx.Misalignment)] == [0, 1, 2, 3]
    assert not fx.Misalignment(sensor=1).applies and fx.Misalignment(sensor=2).applies
    assert fx.SoftIron(sensor=1).applies and fx.SoftIron.frame_rotation
    assert fx.Scale.prior == (1.0, 0.02) and fx.Offset.prior is None


def test_context_has_signal():
    ctx = fx.SensorContext(t=np.zeros(2), temp=np.array([np.nan, np.nan]),
                           aux={'aux_pump': np.ones(2)})
    assert ctx.has('time') and ctx.has('aux_pump')
    assert not ctx.has('temperature') and not ctx.has('field_rate') and not ctx.has('aux_x')
    with pytest.raises(ValueError, match="unknown signal 'attitud'"):
        ctx.has('attitud')
    assert not ctx.has('attitude')


def test_linear_plugin_order_frame_and_prior(plugins):
    m = Model.from_spec('offset,tilt_test,scale,misalignment', 3)
    # sensor 1 defines the frame: neither frame rotation exists there
    assert [e.name for e in m.effects[0]] == ['scale', 'offset']
    assert [e.name for e in m.effects[1]] == ['scale', 'misalignment', 'tilt_test', 'offset']
    assert m.joint and m.spec() == ['scale', 'offset', 'misalignment', 'tilt_test']
    # A_2 = diag(k) R(misalignment) R3(a), multiplied in the declared order
    p = m.default_params()
    p[m.slices[1][0]] = (1.1, 0.9, 1.0)
    p[m.slices[1][1]] = (0.01, -0.02, 0.03)
    p[m.slices[1][2]] = (0.2,)
    expected = np.diag([1.1, 0.9, 1.0]) @ fx.misalignment_matrix(0.01, -0.02, 0.03) @ \
        np.array([[np.cos(0.2), np.sin(0.2), 0], [-np.sin(0.2), np.cos(0.2), 0], [0, 0, 1]])
    np.testing.assert_allclose(m.matrix(2, p), expected, atol=1e-15)
    # the constrained mode takes the declared prior; a user prior by name overrides it
    idx = m.slices[1][2].start
    assert (idx, 0.0, 0.01) in priors_for(m, {}, constrained=True)
    assert (idx, 0.1, 0.5) in priors_for(m, {'tilt_test': (0.1, 0.5)}, constrained=True)
    assert not [pr for pr in priors_for(m, {}) if pr[0] == idx]


def test_clash_names_both_effects_and_is_symmetric(plugins):
    class Gain(fx.Effect):
        """A common gain of the three axes."""

        name = 'gain_test'
        kind = 'linear'
        param_names = ('g',)
        units = ('1',)
        excludes = ('scale',)

    fx.register_effect(Gain)
    try:
        for spec in ('scale,gain_test', 'gain_test,scale'):
            with pytest.raises(ValueError, match='describe the same degrees of freedom') as exc:
                Model.from_spec(spec, 1)
            assert 'A common gain' in str(exc.value) and 'Per-axis scale' in str(exc.value)
    finally:
        fx.unregister_effect('gain_test')
    with pytest.raises(ValueError, match='built-in'):
        fx.unregister_effect('scale')


def test_temperature_plugin_in_simulate(plugins):
    kw = {'n_samples': 300, 'rate_hz': 1.0, 'n_sensors': 1, 'trajectory': 'random', 'seed': 4}
    plain, _ = simulate(**kw)
    data, sim = simulate(truth={f'{ThermalSquare.name}@1': list(C_TRUE)}, **kw)
    assert not sim.model.has(1, 'temperature')
    # same seed, same noise: the difference is the plug-in's term, computed here by hand
    dt2 = (data.temp[0] - data.temp[0].mean()) ** 2
    np.testing.assert_allclose(data.raw[0] - plain.raw[0], dt2[:, None] * C_TRUE, atol=1e-9)


def test_temperature_plugin_fit_diagnose_file_and_live_correction(plugins):
    from magcal_ros.core.live.corrector import LiveCorrector, MissingSignal

    data, b = _recording()
    spec = f'offset,scale,{ThermalSquare.name}'
    res = fit(data, spec, field_nt=F)
    assert not res.model.has(1, 'temperature')
    i = res.model.slices[0][-1]
    # stderr: 3 nT / (std((T-T0)^2) = 22.6 degC^2 * sqrt(N)) = 0.003 per axis on a full
    # vector; the scalar constraint sees about one axis in three -> < 0.02
    assert np.all(res.stderr[i] < 0.02)
    assert np.all(np.abs(res.params[i] - C_TRUE) < 5 * res.stderr[i])
    assert res.scalar_rms_nt[1] == pytest.approx(SIGMA, rel=0.1)

    # the diagnosis offers the plug-in as a candidate and picks it (the model has no
    # temperature effect, the built-in linear one cannot fit a symmetric square)
    d = diagnose(data, 'offset,scale', field_nt=F)
    assert d.verdict_token == f'{ThermalSquare.name}@1'

    # the calibration file keeps the plug-in's reference temperature
    cal = calibration_from_doc(calibration_to_doc(res.calibration))
    assert cal.model.effects[0][-1].refs['t0_c'] == pytest.approx(data.temp[0].mean())
    corrected = cal.correct(1, data.raw[0], data.context(1))
    # corrected = A^-1 (raw - o - c dT^2): the true field to within the noise
    err = corrected - b
    assert np.sqrt(np.mean(err ** 2)) < 2 * SIGMA

    # live: the corrector subscribes the temperature because the plug-in declares it
    live = LiveCorrector(cal, 1)
    assert live.needs_temperature
    with pytest.raises(MissingSignal, match='waiting for sensor1/temperature'):
        live.correct(1, data.t[0], data.raw[0, 0])
    for k in (0, 700, 1999):
        live.set_temperature(1, data.temp[0, k])
        got = live.correct(1, data.t[k], data.raw[0, k])
        np.testing.assert_allclose(got, corrected[k], rtol=1e-12, atol=1e-9)
