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
Site gradient (issue 13): a constant world-frame gradient seen through a known attitude.

The data are generated here, independently of Model.forward: a world field and a world
gradient are rotated into the body frame with scipy's Rotation, and per-sensor linear maps and
offsets written out below are applied.
"""
import json
import subprocess
import sys

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.effects import SensorContext, SiteGradient
from magcal_ros.core.geometry.attitude import AttitudeError, check_quaternions
from magcal_ros.core.model import DegenerateDataError, fit, Model
from magcal_ros.io.calfile import calibration_from_doc, load_calibration, save_calibration
from magcal_ros.io.csvio import CsvFormatError, read_csv, write_csv
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

NOISE_NT = 3.0
FIELD_NT = 50000.0
H = 0.25                                        # half baseline of the cross, m
POS = np.array([[H, 0, 0], [0, H, 0], [-H, 0, 0], [0, -H, 0]])
# world-frame gradient, nT/m: symmetric, traceless, components up to 400 nT/m
G_W = np.array([[300.0, -250.0, 400.0], [-250.0, -150.0, 200.0], [400.0, 200.0, -150.0]])
# per-sensor linear maps (sensor 1 upper triangular: it defines the array frame) and offsets
A_TRUE = [np.array([[1.02, 0.01, -0.015], [0.0, 0.98, 0.02], [0.0, 0.0, 1.01]]),
          np.array([[0.99, 0.03, 0.01], [-0.02, 1.01, 0.015], [0.005, -0.01, 1.005]]),
          np.array([[1.015, -0.01, 0.02], [0.012, 0.985, -0.02], [-0.015, 0.02, 0.995]]),
          np.array([[0.98, 0.02, -0.01], [-0.015, 1.02, 0.01], [0.02, -0.005, 1.01]])]
O_TRUE = np.array([[120.0, -80.0, 45.0], [-60.0, 150.0, -30.0], [35.0, 40.0, -110.0],
                   [-95.0, -20.0, 70.0]])


def make_data(n=3000, seed=1, g_w=G_W, attitude=True, smooth_period_s=None, rate_hz=100.0):
    """
    (Dataset, rotations): raw_j = A_j R^T (B_w + G_w R r_j) + o_j + noise.

    Random attitudes, or with ``smooth_period_s`` a continuous tumbling (yaw, pitch, roll
    sinusoids of incommensurate frequencies) that covers the sphere in about that time.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    if smooth_period_s:
        w = 2 * np.pi / smooth_period_s
        rot = Rotation.from_euler('ZYX', np.column_stack([
            3.1 * w * t, np.radians(85) * np.sin(1.7 * w * t + 0.3),
            np.pi * np.sin(1.13 * w * t + 1.1)]))
    else:
        rot = Rotation.random(n, random_state=rng)
    b_w = np.array([21000.0, -2500.0, 45000.0])
    b_w *= FIELD_NT / np.linalg.norm(b_w)            # |B| = F at the centre of the array
    raw = np.empty((4, n, 3))
    for j in range(4):
        b_world_j = b_w + rot.apply(POS[j]) @ g_w.T   # field at sensor j, world frame
        b_body_j = rot.inv().apply(b_world_j)
        raw[j] = b_body_j @ A_TRUE[j].T + O_TRUE[j] + rng.normal(0, NOISE_NT, (n, 3))
    q = rot.as_quat(scalar_first=True) if attitude else None
    return Dataset(t=t, raw=raw, attitude=q), rot


def test_shift_hand_computed():
    """
    Check the shift of the site gradient against a hand computation.

    R = 90 deg about z, only gxy = 100 nT/m: r_1 = (0.25, 0, 0) m lies along world y, the
    world shift is G (0, 0.25, 0) = (25, 0, 0) nT, which is body (0, -25, 0) nT.
    """
    eff = SiteGradient(sensor=0)
    eff.set_positions(POS)
    rz = Rotation.from_euler('z', 90, degrees=True).as_matrix()[None]
    ctx = SensorContext(t=np.zeros(1), attitude=rz)
    np.testing.assert_allclose(eff.shift([0, 100.0, 0, 0, 0], ctx, 1), [[0, -25.0, 0]],
                               atol=1e-12)
    # sensor 2 at body +y -> world -x; gxx = 200 nT/m gives world (-50, 0, 0) -> body (0, 50, 0)
    np.testing.assert_allclose(eff.shift([200.0, 0, 0, 0, 0], ctx, 2), [[0, 50.0, 0]],
                               atol=1e-12)


@pytest.fixture(scope='module')
def fitted():
    data, rot = make_data()
    return data, rot, fit(data, 'base,site_gradient', field_nt=FIELD_NT)


def test_fit_recovers_gradient_and_calibration(fitted):
    data, _, res = fitted
    g = res.calibration.site_gradient()
    assert g is not None
    g_hat, se = g
    # each component within 4 standard uncertainties; the uncertainty itself is small:
    # about sigma / (baseline * sqrt(N)) ~ 3 / (0.5 * 55) = 0.1 nT/m
    assert np.all(np.abs(g_hat - G_W) < 4 * se), (g_hat - G_W, se)
    assert np.all(se < 0.5)
    # offsets of every sensor within 4 standard uncertainties of the truth
    for j in range(1, 5):
        o = res.calibration.offset(j)
        sl = [i for i, (s, e, _, _) in enumerate(res.model.param_info())
              if s == j and e == 'offset']
        assert np.all(np.abs(o - O_TRUE[j - 1]) < 4 * res.stderr[sl]), (j, o, O_TRUE[j - 1])
        np.testing.assert_allclose(res.calibration.matrix(j), A_TRUE[j - 1], atol=2e-4)
    # residuals at the noise: scalar RMS within 5 % of 3 nT, vector RMS of a difference of
    # two sensors sqrt(2) x 3 nT within 5 %
    for v in res.scalar_rms_nt.values():
        assert v < 1.05 * NOISE_NT
    for v in res.vector_rms_nt.values():
        assert v < 1.05 * np.sqrt(2) * NOISE_NT


def test_without_the_effect_the_fit_is_far_from_the_noise(fitted):
    data, _, _ = fitted
    res = fit(data, 'base', field_nt=FIELD_NT)
    # the gradient shifts a sensor by up to |G| r ~ 170 nT: the base model cannot absorb it
    assert min(res.scalar_rms_nt.values()) > 10 * NOISE_NT


def test_gradient_needs_attitude():
    data, _ = make_data(n=400, attitude=False)
    with pytest.raises(DegenerateDataError, match='att_qw'):
        fit(data, 'base,site_gradient', field_nt=FIELD_NT)


def test_spec_is_array_wide():
    m = Model.from_spec('base,site_gradient', 4)
    assert m.spec()[-1] == 'site_gradient'
    assert m.n_params == 4 * 12 - 3 + 5
    assert [i[0] for i in m.param_info()[-5:]] == [0] * 5
    with pytest.raises(ValueError, match='whole array'):
        Model.from_spec('base,site_gradient@2', 4)


def test_attitude_jump_is_refused():
    data, rot = make_data(n=600)
    q = data.attitude.copy()
    # 20 epochs with the attitude of a quarter turn about an axis normal to the field
    jump = Rotation.from_rotvec([np.pi / 2, 0, 0]) * rot[300:320]
    q[300:320] = jump.as_quat(scalar_first=True)
    bad = Dataset(t=data.t, raw=data.raw, attitude=q)
    with pytest.raises(AttitudeError, match=r'epoch 30\d .*jump'):
        fit(bad, 'base,site_gradient', field_nt=FIELD_NT)


def test_attitude_convention_is_refused():
    data, rot = make_data(n=600)
    inverse = Dataset(t=data.t, raw=data.raw, attitude=rot.inv().as_quat(scalar_first=True))
    with pytest.raises(AttitudeError, match='convention'):
        fit(inverse, 'base,site_gradient', field_nt=FIELD_NT)


def test_quaternion_checks():
    q = np.tile([1.0, 0, 0, 0], (5, 1))
    q[3] = [0.5, 0.5, 0.5, 0.6]
    with pytest.raises(AttitudeError, match=r'epoch 3 .*not a unit quaternion'):
        check_quaternions(q, t=np.arange(5.0))
    q[3] = [np.nan, 0, 0, 0]
    with pytest.raises(AttitudeError, match='epoch 3.*att_qw is not a number'):
        check_quaternions(q, t=np.arange(5.0))
    # a sign flip is the same rotation: accepted and made continuous
    q[3] = [-1.0, 0, 0, 0]
    assert np.all(check_quaternions(q)[:, 0] == 1.0)


def test_csv_attitude_roundtrip_and_errors(tmp_path):
    data, _ = make_data(n=50)
    path = tmp_path / 'att.csv'
    write_csv(path, data)
    back = read_csv(path)
    np.testing.assert_allclose(back.attitude, data.attitude, atol=2e-9)
    lines = path.read_text().splitlines()
    header = lines[0].split(',')
    # NaN in one attitude cell: the row and the column are named
    row = lines[5].split(',')
    row[header.index('att_qy')] = 'nan'
    bad = tmp_path / 'nan.csv'
    bad.write_text('\n'.join(lines[:5] + [','.join(row)] + lines[6:]) + '\n')
    with pytest.raises(CsvFormatError, match='data row 6: att_qy is not a number'):
        read_csv(bad)
    # a quaternion that is not unit
    row = lines[3].split(',')
    row[header.index('att_qw')] = str(2 * float(row[header.index('att_qw')]) + 0.5)
    bad.write_text('\n'.join(lines[:3] + [','.join(row)] + lines[4:]) + '\n')
    with pytest.raises(CsvFormatError, match='data row 4: .*not a unit quaternion'):
        read_csv(bad)
    # three of the four columns
    k = header.index('att_qz')
    cut = [','.join(c for i, c in enumerate(ln.split(',')) if i != k) for ln in lines]
    bad.write_text('\n'.join(cut) + '\n')
    with pytest.raises(CsvFormatError, match='missing att_qz'):
        read_csv(bad)


def test_calibration_file_keeps_gradient(fitted, tmp_path):
    from magcal_ros.io.calfile import calibration_to_doc
    _, _, res = fitted
    doc = calibration_to_doc(res.calibration)
    assert 'site_gradient_nt_per_m' in doc and list(doc)[-1] == 'provenance'
    path = tmp_path / 'cal.yaml'
    save_calibration(path, doc)
    cal, _ = load_calibration(path)
    g0, se0 = res.calibration.site_gradient()
    g1, se1 = cal.site_gradient()
    np.testing.assert_allclose(g1, g0, rtol=1e-12)
    np.testing.assert_allclose(se1, se0, rtol=1e-9)
    # the correction itself ignores the gradient: the field at each sensor
    raw = np.array([[20000.0, 3000.0, 40000.0]])
    np.testing.assert_allclose(cal.correct(2, raw), res.calibration.correct(2, raw))
    assert calibration_from_doc(doc).model.spec() == res.model.spec()


def test_cli_fit_reports_gradient(tmp_path):
    data, _ = make_data(n=2000, seed=4)
    path = tmp_path / 'site.csv'
    write_csv(path, data)
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', 'fit', str(path), '--model',
                        'base,site_gradient', '--field-nt', '50000', '--json'],
                       capture_output=True, text=True, timeout=240)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    g = np.array(doc['site_gradient_nt_per_m'])
    se = np.array(doc['site_gradient_stderr_nt_per_m'])
    assert g.shape == (3, 3) and np.all(se > 0)
    assert np.all(np.abs(g - G_W) < 4 * se), (g - G_W, se)
    # the tensor after correction, about the modelled site gradient, is at its noise floor
    floor = np.array(doc['tensor_floor_nt_per_m'])
    assert np.all(np.array(doc['tensor_rms_nt_per_m']) < 1.1 * floor)


def test_bounds_of_the_three_cases():
    """
    Compare the Cramer-Rao bounds of the three cases.

    Information can only be lost: heading unknown >= attitude known, per parameter; and with
    a per-epoch nuisance gradient exactly 20 of base's 45 directions are undetermined
    (5 differential offsets + 15 differential linear terms: docs/site_gradient.md).
    """
    from magcal_ros.core.model.site_gradient import crb_covariance
    data, _ = make_data(n=300, seed=7)
    m = Model.from_spec('base,site_gradient', 4)
    truth = m.default_params()
    for j in range(1, 5):
        truth = m.params_from_linear(j, A_TRUE[j - 1], O_TRUE[j - 1], truth)
    truth[m.array_cols] = [G_W[0, 0], G_W[0, 1], G_W[0, 2], G_W[1, 1], G_W[1, 2]]
    att = crb_covariance(data, m, truth, FIELD_NT, NOISE_NT, 'attitude')
    head = crb_covariance(data, m, truth, FIELD_NT, NOISE_NT, 'heading')
    k = m.array_cols[0]
    v_att, v_head = np.diag(att['covariance'])[:k], np.diag(head['covariance'])[:k]
    assert np.all(np.isfinite(v_head)) and np.all(v_head >= v_att * (1 - 1e-9))
    # the gauge: rotating G_w about the field direction, d G = G N - N G (N = [n]x)
    n_w = np.array([21000.0, -2500.0, 45000.0]) / np.linalg.norm([21000.0, -2500.0, 45000.0])
    nx = np.array([[0, -n_w[2], n_w[1]], [n_w[2], 0, -n_w[0]], [-n_w[1], n_w[0], 0]])
    d = G_W @ nx - nx @ G_W
    gauge = np.array([d[0, 0], d[0, 1], d[0, 2], d[1, 1], d[1, 2]])
    assert abs(abs(head['gauge_direction'] @ gauge) / np.linalg.norm(gauge) - 1) < 1e-3
    base = Model.from_spec('base', 4)
    none = crb_covariance(data, base, truth[:k], FIELD_NT, NOISE_NT, 'epoch_gradient')
    assert none['undetermined_directions'] == 20


def test_readme_commands(tmp_path):
    """The two commands of the README's site-gradient paragraph, as written."""
    import pathlib
    import shlex

    def run(*args):
        return subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=240)
    readme = (pathlib.Path(__file__).resolve().parents[1] / 'README.md').read_text()
    lines = [ln.strip() for ln in readme.splitlines()
             if ln.strip().startswith(('magcal simulate --out site.csv', 'magcal fit site.csv'))]
    assert len(lines) == 2, lines
    p = run(*shlex.split(lines[0])[1:])
    assert p.returncode == 0, p.stderr
    p = run(*shlex.split(lines[1])[1:])
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    # the simulator's world frame is NED; gzz = -gxx - gyy = -150
    truth = np.array([[300, -250, 400], [-250, -150, 200], [400, 200, -150.0]])
    se = np.array(doc['site_gradient_stderr_nt_per_m'])
    assert np.all(np.abs(np.array(doc['site_gradient_nt_per_m']) - truth) < 4 * se)
    assert all(v < 1.05 * 3.0 for v in doc['scalar_rms_nt'].values())
    # a malformed gradient is one line on stderr and exit status 2
    p = run('simulate', '--out', 'x.csv', '--site-gradient', '1,2,3')
    assert p.returncode == 2 and 'five numbers' in p.stderr


def test_bag_imu_orientation_round_trip(tmp_path):
    """rosbag2: the attitude travels as sensor_msgs/Imu orientation on {ns}/imu."""
    from magcal_ros.io.bag import read_bag, write_bag
    data, _ = make_data(n=120, seed=5)
    path = write_bag(tmp_path / 'bag', data)
    got = read_bag(path)
    assert '/magcal/imu' in got.meta['topics'] and got.meta['dropped_attitude_epochs'] == 0
    # same rotations (q and -q are the same rotation)
    dots = np.abs(np.einsum('ij,ij->i', got.attitude, data.attitude))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)
    with pytest.raises(ValueError, match='no sensor_msgs/msg/Imu messages on /other'):
        read_bag(path, imu_topic='/other')


def test_bag_imu_interpolation_hand_computed():
    """Orientation about z at 0, 40, 80 deg at t = 0, 1, 2 s: at 0.5 s slerp gives 20 deg."""
    from magcal_ros.core.geometry.attitude import interpolate
    q = Rotation.from_euler('z', [[0], [40], [80]], degrees=True).as_quat(scalar_first=True)
    got = interpolate(np.array([0.0, 1.0, 2.0]), q, np.array([0.5, 1.5]))
    want = np.array([[np.cos(np.radians(10)), 0, 0, np.sin(np.radians(10))],
                     [np.cos(np.radians(30)), 0, 0, np.sin(np.radians(30))]])
    np.testing.assert_allclose(got, want, atol=1e-12)


def _field_aligned(g_w, b_w):
    """
    Return G_w in the frame of fit_heading_unknown.

    G_w in the frame of fit_heading_unknown: z along b_w, x along the part of G z
    perpendicular to the field (so gyz = 0, gxz >= 0); computed here with scipy.
    """
    z = b_w / np.linalg.norm(b_w)
    gz = g_w @ z
    x = gz - (gz @ z) * z
    x /= np.linalg.norm(x)
    frame = np.stack([x, np.cross(z, x), z])          # rows: the new axes in the old frame
    return frame @ g_w @ frame.T


def test_heading_unknown_reaches_its_bound():
    """
    No attitude: the heading about the field estimated per epoch.

    The calibration comes
    out as with attitude (offsets within 4 sigma of the truth), the gradient in the
    field-aligned frame (its rotation about the field is not determined) within 4 sigma.
    """
    from magcal_ros.core.model.site_gradient import fit_heading_unknown
    data, _ = make_data(n=800, seed=2, attitude=False)
    res = fit_heading_unknown(data, field_nt=FIELD_NT)
    info = res.model.param_info()
    for j in range(1, 5):
        sl = [i for i, (s, e, _, _) in enumerate(info) if s == j and e == 'offset']
        assert np.all(np.abs(res.params[sl] - O_TRUE[j - 1]) < 4 * res.stderr[sl])
    g, se = res.calibration.site_gradient()
    b_w = np.array([21000.0, -2500.0, 45000.0])
    want = _field_aligned(G_W, b_w)
    assert abs(g[1, 2]) < 1e-9 and g[0, 2] > 0
    # the five independent components but gyz (fixed to 0 by the gauge)
    for (a, b) in ((0, 0), (0, 1), (0, 2), (1, 1)):
        assert abs(g[a, b] - want[a, b]) < 4 * se[a, b], (a, b, g[a, b], want[a, b], se[a, b])
    assert all(v < 1.05 * NOISE_NT for v in res.scalar_rms_nt.values())
    assert 'field-aligned' in res.identifiability['site_gradient_frame']
    # the correlation is that of the reported covariance where both are defined (gyz,
    # fixed by the gauge, has none; the bound leaves some cross terms unknown: inf)
    se = res.stderr
    ok = np.isfinite(res.covariance) & (np.outer(se, se) > 0)
    with np.errstate(invalid='ignore', divide='ignore'):     # only the `ok` entries are read
        expected = res.covariance / np.outer(se, se)
    np.testing.assert_allclose(res.correlation[ok], expected[ok], rtol=1e-12, atol=1e-12)


def test_cli_without_attitude(tmp_path):
    """
    Refuse site_gradient without attitude, naming --heading-unknown.

    Without attitude columns, site_gradient is refused with the way out named; with
    --heading-unknown the fit runs and names the frame of the gradient.
    """
    def run(*args):
        return subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=240)
    data, _ = make_data(n=1000, seed=9, attitude=False)
    write_csv(tmp_path / 'noatt.csv', data)
    p = run('fit', 'noatt.csv', '--model', 'base,site_gradient', '--field-nt', '50000')
    assert p.returncode == 2 and 'att_qw' in p.stderr and '--heading-unknown' in p.stderr
    p = run('fit', 'noatt.csv', '--model', 'base,site_gradient', '--field-nt', '50000',
            '--heading-unknown', '--json')
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    assert doc['site_gradient_frame'].startswith('field-aligned')
    g, se = np.array(doc['site_gradient_nt_per_m']), np.array(doc['site_gradient_stderr_nt_per_m'])
    want = _field_aligned(G_W, np.array([21000.0, -2500.0, 45000.0]))
    assert abs(g[2, 2] - want[2, 2]) < 4 * se[2, 2]


def test_nonuniform_field_finding_points_to_the_effect():
    """
    Name site_gradient by the finding on the base fit.

    The workbench's model-free finding on the base fit names site_gradient (a smooth
    tumbling: the finding separates signal from noise by its continuity in time).
    """
    from magcal_ros.core.discovery.findings import find
    data, _ = make_data(n=3000, smooth_period_s=10.0)
    found = find(data, fit(data, 'base', field_nt=FIELD_NT))
    texts = [f.text for f in found.items if f.kind == 'nonuniform_field']
    assert texts and 'site_gradient' in texts[0] and '--heading-unknown' in texts[0]


def test_fluxgate_sim_site_gradient_option(make_node, ros_namespace, tmp_path, capsys):
    """
    Pass fluxgate_sim's site gradient, as an option or a parameter, to the simulator.

    A malformed value is one line on stderr and exit status 2.
    """
    from magcal_ros.core.geometry.tensor import symmetric_traceless
    from magcal_ros.ros.sim_node import FluxgateSimNode
    from magcal_ros.sim import devices
    from rclpy.parameter import Parameter
    want = symmetric_traceless([300, -250, 400, -150, 200])
    sim = devices.FluxgateSim(devices.resolve_settings(
        ['--dir', str(tmp_path), '--site-gradient', '300,-250,400,-150,200']))
    np.testing.assert_array_equal(sim.sim.config.gradient_nt_per_m, want)
    node = make_node(FluxgateSimNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('dir', value=str(tmp_path / 'node')),
        Parameter('site_gradient', value=[300.0, -250.0, 400.0, -150.0, 200.0])])
    np.testing.assert_array_equal(node.sim.sim.config.gradient_nt_per_m, want)
    with pytest.raises(SystemExit) as exc:
        devices.resolve_settings(['--site-gradient', '1,2'])
    assert exc.value.code == 2 and 'five numbers' in capsys.readouterr().err


def test_diagnose_names_site_gradient():
    """
    Rank site_gradient first in the diagnosis (with attitude).

    The workbench ranks the missing effect: with attitude, site_gradient (array-wide, one
    token, no @j) is the verdict of a base model in a site gradient.
    """
    from magcal_ros.core.discovery import diagnose
    data, _ = make_data(n=1500, seed=6, smooth_period_s=10.0)
    doc = json.loads(diagnose(data, Model.from_spec('base', 4), field_nt=FIELD_NT).to_json())
    assert doc['verdict']['token'] == 'site_gradient', doc['verdict']
    assert not any(c['effect'].startswith('site_gradient@') for c in doc['candidates'])


def test_calibration_file_names_the_frame_without_attitude(tmp_path):
    """A gradient fitted without attitude is stored with its field-aligned frame."""
    from magcal_ros.core.model.site_gradient import FIELD_ALIGNED, fit_heading_unknown
    from magcal_ros.io.calfile import calibration_to_doc
    data, _ = make_data(n=600, seed=3, attitude=False)
    res = fit_heading_unknown(data, field_nt=FIELD_NT)
    doc = calibration_to_doc(res.calibration)
    assert doc['site_gradient_nt_per_m']['frame'] == FIELD_ALIGNED
    save_calibration(tmp_path / 'c.yaml', doc)
    assert load_calibration(tmp_path / 'c.yaml')[0].site_frame == FIELD_ALIGNED
