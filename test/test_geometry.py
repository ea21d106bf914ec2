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

"""Array geometry from parameters, the tensor of any geometry, field magnitude of a site."""
from magcal_ros.core.data.magnitude import site_field_reference
from magcal_ros.core.data.simulate import Simulator
from magcal_ros.core.geometry.tensor import cross_positions, tensor_lstsq
from magcal_ros.core.live.corrector import calibration_covariance_nt2, ResidualMonitor
from magcal_ros.core.model import Calibration, Model
from magcal_ros.pipeline import array_geometry, geometry_mismatch, tensor_undetermined
import numpy as np
import pytest

#: the corners of a 0.4 m cube (config/geometry_8.yaml)
CUBE = [[x, y, z] for z in (0.2, -0.2)
        for x, y in ((0.2, 0.2), (-0.2, 0.2), (-0.2, -0.2), (0.2, -0.2))]


def test_array_geometry_from_parameters():
    # paper 004's cross (docs/papers.md, eq. 1: G_xx = (B1x - B3x) / d, G_xy = (B2x - B4x) / d):
    # sensor 1 at +x, 3 at -x, 2 at +y, 4 at -y, d between the two sensors of an arm
    assert array_geometry(4, (), 0.5)['positions_m'] == [
        [0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [-0.25, 0.0, 0.0], [0.0, -0.25, 0.0]]
    assert array_geometry(4, (), 0.5)['type'] == 'cross'
    assert array_geometry(1)['positions_m'] == [[0.0, 0.0, 0.0]]
    assert array_geometry(2) is None                   # no positions: no tensor
    g = array_geometry(2, [0, 0, 0.25, 0, 0, -0.25])
    assert g == {'type': 'positions', 'positions_m': [[0, 0, 0.25], [0, 0, -0.25]]}
    with pytest.raises(ValueError, match='6 for 2 sensors, got 3'):
        array_geometry(2, [0, 0, 0.25])


@pytest.mark.parametrize('positions, reason', [
    ([[0, 0, 0]], 'one sensor measures no field difference'),
    ([[0, 0, 0.25], [0, 0, -0.25]], 'the 2 sensors are collinear'),
    ([[0, 0, 0], [1, 1, 1], [2, 2, 2]], 'the 3 sensors are collinear'),
    ([[0.1, 0, 0], [0.1, 0, 0]], 'the 2 sensors are at one point'),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], None),
    (CUBE, None),
    (cross_positions(0.5).tolist(), None),
])
def test_tensor_undetermined_says_why(positions, reason):
    got = tensor_undetermined(np.array(positions, float))
    assert (got is None) if reason is None else (reason in got)


def test_tensor_of_the_cube_recovers_an_injected_gradient():
    # a symmetric traceless gradient and a centre field written by hand: B(r) = B0 + G r
    g = np.array([[300.0, -250.0, 400.0], [-250.0, -150.0, 200.0], [400.0, 200.0, -150.0]])
    b0 = np.array([17000.0, -1000.0, 47000.0])
    fields = np.array([b0 + g @ np.array(r) for r in CUBE])[:, None, :]     # (8, 1, 3)
    got, centre = tensor_lstsq(fields, np.array(CUBE))
    np.testing.assert_allclose(got[0], g, atol=1e-9)
    np.testing.assert_allclose(centre[0], b0, atol=1e-9)


def test_geometry_mismatch_names_both():
    node = array_geometry(4, (), 0.3)
    assert geometry_mismatch(array_geometry(4, (), 0.3), node) is None
    msg = geometry_mismatch(array_geometry(4, (), 0.5), node)
    assert '[0.25, 0.0, 0.0]' in msg and '[0.15, 0.0, 0.0]' in msg
    assert geometry_mismatch({}, node) is None            # a file without positions
    assert geometry_mismatch(array_geometry(4), None) is None   # a node without a geometry


def test_field_reference_of_a_site():
    f, ref = site_field_reference('constant', field_nt=48000.0)
    assert f == 48000.0 and ref == {'kind': 'constant', 'magnitude_nt': 48000.0}
    with pytest.raises(ValueError, match='site_latitude_deg'):
        site_field_reference('igrf', lon_deg=10.0, date='2025-01-01')
    # shape only: the median radius of the data, here points on a sphere of 48 000 nT about
    # an offset (written here, not by the simulator)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(2000, 3))
    raw = 48000.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [300.0, -200.0, 100.0]
    f, ref = site_field_reference('shape', raw=raw)
    assert f == pytest.approx(48000.0, rel=1e-6) and ref['kind'].startswith('auto')


def test_calibration_covariance_by_hand():
    model = Model.from_spec('base', 1)
    cal = Calibration(model, model.default_params())
    np.testing.assert_array_equal(calibration_covariance_nt2(cal, 1, 50000.0), np.zeros((3, 3)))
    names = [f'{e.name}.{p}' for e in model.effects[0] for p in e.param_names]
    stderr = np.zeros(len(names))
    stderr[names.index('offset.bx')] = 2.0                          # nT
    cal = Calibration(model, model.default_params(), stderr=stderr)
    # identity A: an offset error of 2 nT on x is 4 nT^2 on x of every corrected field
    np.testing.assert_allclose(calibration_covariance_nt2(cal, 1, 50000.0),
                               np.diag([4.0, 0.0, 0.0]), atol=1e-9)


def test_residual_monitor_of_one_sensor():
    mon = ResidualMonitor(1, 50000.0)
    assert mon.kinds == ('scalar',)
    rng = np.random.default_rng(0)
    for k in range(400):
        d = np.array([np.cos(k / 30.0), np.sin(k / 30.0), 0.3])
        b = 50000.0 * d / np.linalg.norm(d) + rng.normal(scale=3.0, size=3)
        scalar, vector = mon.add(b[None])
        assert np.isnan(vector[0])
    r = mon.ratios()
    # white noise: the scalar residual at its floor (RMS over 400: 1/sqrt(800) ~ 3.5 %)
    assert abs(r['scalar_ratio'][0] - 1.0) < 4.0 / np.sqrt(400)


def test_simulator_places_any_number_of_sensors():
    g = np.array([[300.0, -250.0, 400.0], [-250.0, -150.0, 200.0], [400.0, 200.0, -150.0]])
    sim = Simulator(n_sensors=8, positions_m=np.ravel(CUBE), errors='paper004',
                    gradient_nt_per_m=g, trajectory='smooth', seed=3)
    t = np.arange(5) / 100.0
    rot = sim.attitude(t)
    b = sim.true_field(t, rot)
    # field differences between sensors: R^T G R (r_i - r_j), computed here
    rm = rot.as_matrix()
    for k in range(5):
        gb = rm[k].T @ g @ rm[k]
        np.testing.assert_allclose(b[4, k] - b[0, k], gb @ (np.array(CUBE[4]) - CUBE[0]),
                                   atol=1e-8)
    assert sim.sample(t).raw.shape == (8, 5, 3)


def test_pairing_check_of_the_cube_and_off_for_collinear_sensors():
    from magcal_ros.core.live.corrector import LiveCorrector
    sigma = 3.0
    model = Model.from_spec('base', 8)
    cal = Calibration(model, model.default_params(), sigma_nt=np.full(8, sigma))
    live = LiveCorrector(cal, 8, CUBE)
    assert live.no_check_reason is None and live.pairing_dof == 3 * 8 - 8
    g = np.array([[300.0, -250.0, 400.0], [-250.0, -150.0, 200.0], [400.0, 200.0, -150.0]])
    b0 = np.array([17000.0, -1000.0, 47000.0])
    rng = np.random.default_rng(4)
    chi2 = []
    for _ in range(2000):
        fields = [b0 + g @ np.array(r) + rng.normal(scale=sigma, size=3) for r in CUBE]
        chi2.append(live.pairing_chi2(fields))
    # chi-square with 16 degrees of freedom: mean 16, sd of the mean of 2000 sqrt(32/2000)
    assert abs(np.mean(chi2) - 16.0) < 4 * np.sqrt(32.0 / 2000)
    # one sensor one epoch late on a turning array: its field 150 nT off (written here)
    late = [b0 + g @ np.array(r) for r in CUBE]
    late[3] = late[3] + np.array([0.0, 150.0, 0.0])
    assert live.pairing_chi2(late) > live.pairing_threshold
    # a vertical gradiometer: no tensor, so no set check, and it says so
    cal2 = Calibration(Model.from_spec('base', 2), Model.from_spec('base', 2).default_params(),
                       sigma_nt=np.full(2, sigma))
    live2 = LiveCorrector(cal2, 2, [[0, 0, 0.25], [0, 0, -0.25]])
    assert live2.gradient_op is None and 'no gradient' in live2.no_gradient_reason
    assert live2.no_check_reason and live2.pairing_dof == 0


def test_simulator_command_line_takes_positions(capsys):
    from magcal_ros.sim import devices
    st = devices.resolve_settings(['--sensors', '2', '--sensor-positions-m',
                                   '0,0,0.25,0,0,-0.25', '--smooth-period-s', '10'])
    assert st.sensor_positions_m == [0.0, 0.0, 0.25, 0.0, 0.0, -0.25]
    assert st.sensors == 2 and st.smooth_period_s == 10.0
    with pytest.raises(SystemExit) as exit_:
        devices.resolve_settings(['--sensors', '3', '--sensor-positions-m', '0,0,0.25'])
    assert exit_.value.code == 2
    assert '9 numbers, got 3' in capsys.readouterr().err
