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
corrector_node in-process: correction, gradient, calibration updates, refusals, diagnostics.

The calibrations used here are the simulator's true ones (:attr:`Simulator.truth`), so the
corrected field must equal the simulated true field up to the sensor noise (3 nT per axis,
propagated through A^-1), and the gradient of the uniform simulated field is zero up to the
noise-propagated floor of :func:`magcal_ros.core.geometry.tensor.tensor_noise_floor`.
"""
import copy
import sys
import types

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import injection
from magcal_interfaces.msg import GradientTensorStamped
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.effects import SensorContext
from magcal_ros.core.geometry.tensor import cross_positions, tensor_noise_floor
from magcal_ros.core.model import Calibration, fit, Model
from magcal_ros.io.calfile import (calibration_to_doc, dump_calibration, save_calibration)
from magcal_ros.pipeline import cross_geometry
from magcal_ros.ros.calibration_node import RESULT_QOS
from magcal_ros.ros.conversions import (msg_to_covariance_nt2, msg_to_field_nt,
                                        msg_to_gradient_stamped, msg_to_tensor, stamp_to_seconds)
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import spin_until
from sensor_msgs.msg import MagneticField
from sim_feed import Feeder, T0
from std_msgs.msg import Float64MultiArray, String
import test_live

NOISE_NT = 3.0


@pytest.fixture(scope='module')
def sim():
    """300 epochs of the tumbling array and its true calibration document."""
    data, simulator = simulate(n_samples=300, rate_hz=100.0, trajectory='smooth', seed=11)
    doc = calibration_to_doc(simulator.truth, geometry=cross_geometry(0.5))
    return data, simulator.truth, doc


@pytest.fixture(scope='module')
def hand():
    """
    300 epochs written without the model (test/injection.py), a fit to 600 others.

    The reference values are the hand-written ones: the body-frame field (the same at every
    sensor: uniform) and each sensor's K_j (injection.sensor_matrix).  The calibration is a
    fit of other epochs of the same sensors; its K_j is within ~2e-5 of the stated one
    (test_model_paper004.py), 1 nT at 50 000 nT, added in quadrature to the 3 nT noise.
    """
    t, field = injection.tumbling_field(300, seed=11)
    data = injection.make(n=300, seed=11)
    cal = fit(injection.make(n=600, seed=4), 'base', field_nt=injection.F_NT).calibration
    return data, field, cal, calibration_to_doc(cal, geometry=cross_geometry(0.5))


def write(path, doc):
    path.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(path, doc, history=0)
    return path


class Probe:
    """Subscriptions of the corrector's outputs in the test namespace."""

    def __init__(self, node, namespace, n_sensors=4):
        self.corrected = [[] for _ in range(n_sensors)]
        self.gradient = []
        self.stamped = []
        self.diagnostics = []
        for j in range(n_sensors):
            node.create_subscription(MagneticField, f'sensor{j + 1}/corrected',
                                     self.corrected[j].append, 500)
        node.create_subscription(Float64MultiArray, 'gradient', self.gradient.append, 500)
        node.create_subscription(GradientTensorStamped, 'gradient_stamped',
                                 self.stamped.append, 500)
        node.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: self.diagnostics.extend(s for s in m.status
                                              if s.hardware_id == namespace), 50)

    def last_status(self, executor, since=0, timeout_sec=5.0):
        spin_until(executor, lambda: len(self.diagnostics) > since, timeout_sec,
                   'a /diagnostics status of the corrector')
        return self.diagnostics[-1]

    def count(self):
        return sum(len(c) for c in self.corrected)


def start(make_node, namespace, path, **params):
    overrides = {'calibration_file': str(path)}
    overrides.update(params)
    return make_node(CorrectorNode, namespace=namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in overrides.items()])


def test_without_calibration_nothing_is_published(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, sim):
    data, _, doc = sim
    node = start(make_node, ros_namespace, tmp_path / 'missing.yaml')
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    result = ros_node.create_publisher(String, 'calibration/result', RESULT_QOS)
    feeder.wait_for_subscribers(ros_executor)
    feeder.feed(ros_executor, data, stop=50, taken=lambda: node.received)
    status = probe.last_status(ros_executor, since=len(probe.diagnostics))
    assert status.level == DiagnosticStatus.WARN
    assert status.message.startswith('no calibration: publishing nothing')
    # sentinel, not a fixed wait: give the node a calibration and one more epoch; its
    # corrected samples are then the first the probe sees, so none of the 50 was published
    result.publish(String(data=dump_calibration(doc)))
    spin_until(ros_executor, lambda: node.calibration is not None, 5.0, 'the calibration')
    feeder.feed(ros_executor, data, start=50, stop=51, taken=lambda: node.received)
    spin_until(ros_executor, lambda: all(probe.corrected), 5.0, 'the sentinel epoch')
    stamp = T0 + float(data.t[50])
    for c in probe.corrected:
        assert len(c) == 1
        assert c[0].header.stamp.sec + 1e-9 * c[0].header.stamp.nanosec == \
            pytest.approx(stamp, abs=1e-6)


def test_corrects_to_the_true_field_and_publishes_the_gradient(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, hand):
    data, true_field, cal, doc = hand
    node = start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc))
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    feeder.feed(ros_executor, data, taken=lambda: node.received, temperature=False)
    n = data.n_samples
    spin_until(ros_executor, lambda: (probe.count() == 4 * n and len(probe.gradient) == n
                                      and len(probe.stamped) == n),
               10.0, 'all corrected samples and tensors')

    for j in range(4):
        msgs = probe.corrected[j]
        stamps = np.array([stamp_to_seconds(m.header.stamp) for m in msgs])
        np.testing.assert_allclose(stamps, T0 + data.t, atol=1e-6)   # the raw stamps
        # corrected fields are in the array frame, not the raw sensor's
        assert {m.header.frame_id for m in msgs} == {'magcal_array'}
        b = np.array([msg_to_field_nt(m) for m in msgs])
        err = b - true_field
        # A^-1 (3 nT white noise); A = I +- a few %: RMS over 900 values within +-15 %
        assert 0.85 * NOISE_NT < np.sqrt(np.mean(err ** 2)) < 1.15 * NOISE_NT
        # sigma_j^2 A_j^-1 A_j^-T with the calibration's noise estimate and the stated K_j
        # (the fitted K_j within 2e-5: every entry within 2 x 2e-5 x 9 nT^2 = 4e-4 nT^2)
        a_inv = np.linalg.inv(injection.sensor_matrix(j + 1))
        np.testing.assert_allclose(msg_to_covariance_nt2(msgs[0]),
                                   cal.sigma_nt[j] ** 2 * a_inv @ a_inv.T, rtol=0, atol=1e-3)
    g = np.array([msg_to_tensor(m) for m in probe.gradient])
    assert all([d.label for d in m.layout.dim] == ['row', 'col'] for m in probe.gradient)
    floor = tensor_noise_floor(NOISE_NT, cross_positions(0.5))
    ratio = np.sqrt(np.mean(g ** 2, axis=0)) / floor
    # each component's RMS over 300 tensors: relative sd ~4 %; +-20 % bounds
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    # the stamped tensor: the same values, the set's stamp (the feeder stamps all four
    # samples of an epoch alike), the array frame, and a covariance whose measured diagonal
    # entries (the differences of two sensors over the 0.5 m baseline) are 2 sigma^2 / d^2
    stamped = [msg_to_gradient_stamped(m) for m in probe.stamped]
    np.testing.assert_allclose(np.array([g for _, g, _ in stamped]), g, rtol=1e-12)
    np.testing.assert_allclose([t for t, _, _ in stamped], T0 + data.t, atol=1e-6)
    assert {m.header.frame_id for m in probe.stamped} == {'magcal_array'}
    cov = stamped[0][2]
    np.testing.assert_allclose(cov, cov.T, rtol=1e-12)
    # G_xx = (B1x - B3x) / d, G_yy = (B2y - B4y) / d; A^-1 = I +- a few %
    for k in (0, 4):
        assert cov[k, k] == pytest.approx(2 * NOISE_NT ** 2 / 0.5 ** 2, rel=0.15)
    status = probe.last_status(ros_executor, since=len(probe.diagnostics))
    assert status.level == DiagnosticStatus.OK, status.message
    assert {v.key: v.value for v in status.values}['gradient_stamped'] == 'published'


def test_a_sensor_stamped_late_is_re_paired_from_the_data(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, sim):
    """
    Sensor 4's stamps 16 ms late (1.6 periods, e.g. a USB-serial latency timer).

    By stamps alone its samples pair one or two epochs off for good: on the tumbling array
    (~200 nT of field change per epoch) every tensor was off by hundreds of nT/m.  The
    corrector's check re-pairs the stream once from the data; /diagnostics counts it.
    """
    data, truth, doc = sim
    node = start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc))
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    feeder.feed(ros_executor, data, taken=lambda: node.received, temperature=False,
                latency_s=[0.0, 0.0, 0.0, 0.016])
    n = data.n_samples
    # all but the epochs before the first vote (10 samples per stream) and the set the
    # re-pairing found wrong
    spin_until(ros_executor, lambda: probe.count() == 4 * n and len(probe.gradient) >= n - 15,
               10.0, 'all corrected samples and the tensors')
    g = np.array([msg_to_tensor(m) for m in probe.gradient])
    floor = tensor_noise_floor(NOISE_NT, cross_positions(0.5))
    ratio = np.sqrt(np.mean(g ** 2, axis=0)) / floor
    # as in the test above: each component's RMS over ~290 tensors within +-20 % of the floor
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    status = probe.last_status(ros_executor, since=len(probe.diagnostics))
    assert status.level == DiagnosticStatus.OK, status.message
    values = {v.key: v.value for v in status.values}
    assert values['streams_re_paired'] == '1'
    assert values['sets_failed_pairing_check'] == '0'
    assert values['pairing_check'].startswith('chi-square of 4 redundant components <= 33.4')


class _FakeBroadcaster:
    """Stands in for tf2_ros.StaticTransformBroadcaster (no tf2_ros wheel here)."""

    sent = []

    def __init__(self, node):
        self.node = node

    def sendTransform(self, transforms):   # noqa: N802 (tf2_ros's name)
        self.sent.append(list(transforms))


def test_static_transforms_from_the_calibration(make_node, ros_node, ros_executor,
                                                ros_namespace, tmp_path, monkeypatch):
    """Array -> fluxgate{j}: the rotations written by hand in test_live, at the positions."""
    monkeypatch.setitem(sys.modules, 'tf2_ros',
                        types.SimpleNamespace(StaticTransformBroadcaster=_FakeBroadcaster))
    _FakeBroadcaster.sent = []
    cal = test_live._calibration()
    doc = calibration_to_doc(cal, geometry=cross_geometry(0.5))
    start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc),
          array_frame_id='my_array')
    assert len(_FakeBroadcaster.sent) == 1
    transforms = _FakeBroadcaster.sent[0]
    assert [(m.header.frame_id, m.child_frame_id) for m in transforms] == [
        ('my_array', f'fluxgate{j}') for j in range(1, 5)]
    for m, rot, pos in zip(transforms, test_live.R, cross_positions(0.5)):
        q = m.transform.rotation
        w, v = q.w, np.array([q.x, q.y, q.z])
        # rotation matrix of the unit quaternion (w, v), written out
        r = ((w * w - v @ v) * np.eye(3) + 2 * np.outer(v, v)
             + 2 * w * np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]))
        np.testing.assert_allclose(r, rot, atol=1e-9)
        t = m.transform.translation
        np.testing.assert_allclose([t.x, t.y, t.z], pos, atol=1e-12)


def test_without_the_message_package_the_rest_is_published(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, sim, monkeypatch):
    """magcal_interfaces missing: no gradient_stamped publisher, diagnostics say why."""
    monkeypatch.setitem(sys.modules, 'magcal_interfaces.msg', None)   # import fails
    _, _, doc = sim
    node = start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc))
    assert node.get_publishers_info_by_topic(f'{ros_namespace}/gradient_stamped') == []
    assert len(node.get_publishers_info_by_topic(f'{ros_namespace}/gradient')) == 1
    probe = Probe(ros_node, ros_namespace)
    status = probe.last_status(ros_executor)
    values = {v.key: v.value for v in status.values}
    assert values['gradient_stamped'] == 'not published: magcal_interfaces is not importable'


def _shifted(doc, shift_nt):
    """Return the calibration document with each offset moved by ``shift_nt`` (3,) nT."""
    new = copy.deepcopy(doc)
    for sensor in new['sensors']:
        for eff in sensor['effects']:
            if eff['name'] == 'offset':
                for axis, name in enumerate(('bx', 'by', 'bz')):
                    eff['params'][name]['value'] += float(shift_nt[axis])
        sensor.pop('correction_matrix')          # derived; the loader recomputes it
        sensor['offset_nt'] = [float(x + d) for x, d in zip(sensor['offset_nt'], shift_nt)]
    return new


def test_follows_updates_and_refuses_a_bad_calibration(make_node, ros_node, ros_executor,
                                                       ros_namespace, tmp_path, sim):
    data, truth, doc = sim
    node = start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc))
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    result = ros_node.create_publisher(String, 'calibration/result', RESULT_QOS)
    feeder.wait_for_subscribers(ros_executor)

    def corrected_epoch(k):
        before = [len(c) for c in probe.corrected]
        feeder.publish(data, k, temperature=False)
        spin_until(ros_executor, lambda: all(len(c) > b for c, b in
                                             zip(probe.corrected, before)), 5.0)
        return np.array([msg_to_field_nt(c[-1]) for c in probe.corrected])

    a = corrected_epoch(0)
    shift = np.array([100.0, -50.0, 25.0])
    updated = _shifted(doc, shift)
    result.publish(String(data=dump_calibration(updated)))
    spin_until(ros_executor, lambda: node.calibration_source == 'calibration/result'
               and np.isclose(node.calibration.offset(1)[0], truth.offset(1)[0] + 100.0),
               5.0, 'the new calibration to be installed')
    b = corrected_epoch(1)
    a_next = np.array([truth.correct(j + 1, data.raw[j, 1]) for j in range(4)])
    for j in range(4):
        np.testing.assert_allclose(a[j], truth.correct(j + 1, data.raw[j, 0]), atol=1e-6)
        # corrected = A^-1 (raw - o): moving o by `shift` moves the output by -A^-1 shift
        np.testing.assert_allclose(b[j] - a_next[j], -truth.correction_matrix(j + 1) @ shift,
                                   atol=1e-6)

    n_diag = len(probe.diagnostics)
    result.publish(String(data='schema_version: 1\nkind: magcal_ros/calibration\nsensors: ['))
    spin_until(ros_executor, lambda: any('refused' in s.message
                                         for s in probe.diagnostics[n_diag:]), 5.0,
               'the refusal on /diagnostics')
    status = [s for s in probe.diagnostics[n_diag:] if 'refused' in s.message][-1]
    assert status.level == DiagnosticStatus.WARN
    assert 'refused the calibration from calibration/result: calibration/result: not valid ' \
           'YAML' in status.message
    assert 'keeping the calibration from calibration/result' in status.message
    c = corrected_epoch(1)
    np.testing.assert_allclose(c, b, atol=1e-9)        # the last good one is still used

    # a calibration for another sensor count is refused too
    two = calibration_to_doc(Calibration(Model.from_spec('base', 2),
                                         Model.from_spec('base', 2).default_params()))
    n_diag = len(probe.diagnostics)
    result.publish(String(data=dump_calibration(two)))
    spin_until(ros_executor, lambda: any('is for 2 sensors but this corrector handles 4'
                                         in s.message for s in probe.diagnostics[n_diag:]),
               5.0)


def test_refuses_a_corrupt_file_at_start_up(make_node, ros_node, ros_executor,
                                            ros_namespace, tmp_path, sim):
    path = tmp_path / 'cal.yaml'
    path.write_text('schema_version: 7\nkind: magcal_ros/calibration\nsensors: []\n')
    start(make_node, ros_namespace, path)
    probe = Probe(ros_node, ros_namespace)
    status = probe.last_status(ros_executor)
    assert status.level == DiagnosticStatus.WARN
    assert 'schema_version 7 is newer than this magcal_ros understands' in status.message
    assert 'no calibration is active' in status.message


def test_temperature_effect_waits_for_its_signal(make_node, ros_node, ros_executor,
                                                 ros_namespace, tmp_path):
    data, simulator = simulate(n_samples=40, rate_hz=100.0, trajectory='smooth', seed=5,
                               truth={'temperature@2': [3.0, -2.0, 1.0, 1e-4, 0.0, -1e-4]})
    truth = simulator.truth
    doc = calibration_to_doc(truth, geometry=cross_geometry(0.5))
    node = start(make_node, ros_namespace, write(tmp_path / 'cal.yaml', doc))
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    # without temperature messages sensor 2 is withheld, the others are corrected
    feeder.feed(ros_executor, data, stop=10, taken=lambda: node.received, temperature=False)
    # sensor 2's samples are handled between sensor 1's and 3's: once sensors 3 and 4 have
    # all 10 out (the sentinel), anything of sensor 2 would have arrived
    spin_until(ros_executor, lambda: len(probe.corrected[3]) >= 10, 5.0, 'sensor 4')
    assert [len(c) for c in probe.corrected] == [10, 0, 10, 10]
    assert probe.gradient == []
    status = probe.last_status(ros_executor, since=len(probe.diagnostics), timeout_sec=3.0)
    assert status.level == DiagnosticStatus.WARN
    assert 'sensor 2: waiting for sensor2/temperature' in status.message
    # with them, sensor 2 is corrected with the live temperature like the core model does
    spin_until(ros_executor, lambda: all(p.get_subscription_count() for p in feeder.temp),
               5.0, 'the temperature subscriptions of the corrector')
    feeder.feed(ros_executor, data, start=10, taken=lambda: node.received)
    spin_until(ros_executor, lambda: len(probe.corrected[1]) >= 25, 5.0)
    msg = probe.corrected[1][-1]
    k = int(round((stamp_to_seconds(msg.header.stamp) - T0) * 100.0))
    ctx = SensorContext(t=data.t[k:k + 1], temp=data.temp[1, k:k + 1])
    # the node uses the latest temperature it has, that of this epoch or of the one before:
    # 0.002 degC apart, i.e. < 0.01 nT through the 3 nT/degC coefficient
    np.testing.assert_allclose(msg_to_field_nt(msg), truth.correct(2, data.raw[1, k], ctx),
                               atol=0.02)
    assert np.sqrt(np.mean((msg_to_field_nt(msg) - data.meta['truth_field'][1, k]) ** 2)) \
        < 5 * NOISE_NT
