"""Every built-in effect: simulate it with known parameters, fit it, recover them."""
import numpy as np
import pytest

from magcal_ros.core import effects as fx
from magcal_ros.core.model import Model, fit
from magcal_ros.core.simulate import simulate

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
    assert 'hum_test' in fx.registered_effects()
    m = Model.from_spec('base,hum_test@1', 4)
    assert m.has(1, 'hum_test') and not m.has(2, 'hum_test')
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
