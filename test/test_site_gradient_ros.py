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
calibration_node with an Imu topic: the site gradient fitted live (issue 13).

The array data are generated in test_site_gradient.make_data (a world field and gradient
rotated through a smooth tumbling with scipy, sensor maps written there); the attitude is
published as sensor_msgs/Imu on the node's ``imu_topic``.
"""
import time

from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.conversions import to_stamp
import numpy as np
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import call_trigger, split_response as split
from sensor_msgs.msg import Imu
from sim_feed import Feeder, intake_batch, T0
from test_site_gradient import G_W, make_data


def test_calibration_node_fits_site_gradient_with_imu(make_node, ros_node, ros_executor,
                                                      ros_namespace, tmp_path):
    data, _ = make_data(n=1500, seed=11, smooth_period_s=10.0)
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(tmp_path / 'cal.yaml')),
        Parameter('report_dir', value=str(tmp_path / 'report')),
        Parameter('min_samples', value=500),
        Parameter('model', value=['base', 'site_gradient']),
        Parameter('imu_topic', value='imu')])
    imu_pub = ros_node.create_publisher(
        Imu, 'imu', QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE))
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    # messages without a usable orientation are counted and never used
    for bad in ((2.0, 0.0, 0.0, 0.0), (float('nan'), 0.0, 0.0, 1.0)):
        msg = Imu()
        msg.header.stamp = to_stamp(T0)
        msg.orientation.w, msg.orientation.x, msg.orientation.y, msg.orientation.z = bad
        imu_pub.publish(msg)
    deadline = time.monotonic() + 10.0
    while node.status()['attitude_messages_refused'] < 2:
        assert time.monotonic() < deadline, 'the bad Imu messages did not arrive'
        ros_executor.spin_once(timeout_sec=0.01)
    status = node.status()
    assert status['attitude_messages'] == 0 and status['attitude_messages_refused'] == 2
    assert any('unit orientation' in m for m in status['missing'])
    batch = intake_batch(1)                  # one IMU topic
    for k in range(data.n_samples):
        msg = Imu()
        msg.header.stamp = to_stamp(T0 + float(data.t[k]))
        qw, qx, qy, qz = data.attitude[k]
        msg.orientation.w, msg.orientation.x = float(qw), float(qx)
        msg.orientation.y, msg.orientation.z = float(qy), float(qz)
        imu_pub.publish(msg)
        if k % batch == batch - 1 or k == data.n_samples - 1:
            # wait until the node has taken this batch (as many as its intake hands over at
            # once)
            deadline = time.monotonic() + 30.0
            while node.imu_received < k + 1:
                assert time.monotonic() < deadline, f'the node took {node.imu_received} of {k + 1}'
                ros_executor.spin_once(timeout_sec=0.01)
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()),
                temperature=False)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=120.0)
    assert resp.success, resp.message
    _, payload = split(resp)
    g = np.array(payload['site_gradient_nt_per_m'])
    se = np.array(payload['site_gradient_stderr_nt_per_m'])
    assert np.all(np.abs(g - G_W) < 4 * se), (g - G_W, se)
    assert all(v < 1.1 * 3.0 for v in payload['scalar_rms_after_nt'].values())
    # the Imu stream spans the sets: at most the edge sets lost for want of an attitude
    assert payload['dropped_attitude_epochs'] <= 2


def test_corrector_subtracts_the_site_gradient_only_when_asked(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    """
    Subtract the site gradient from the corrected fields only when asked.

    Stationary array at a fixed attitude, noise-free readings written here: by default the
    corrected field is the field at each sensor (the site gradient is part of the field);
    with subtract_site_gradient it is the centre field and the tensor is zero.
    """
    from magcal_ros.core.data.dataset import Dataset
    from magcal_ros.core.model import Calibration, Model
    from magcal_ros.io.calfile import calibration_to_doc, save_calibration
    from magcal_ros.pipeline import cross_geometry
    from magcal_ros.ros.conversions import msg_to_field_nt, msg_to_tensor
    from magcal_ros.ros.corrector_node import CorrectorNode
    from ros_helpers import spin_until
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import MagneticField
    from std_msgs.msg import Float64MultiArray
    from test_site_gradient import A_TRUE, O_TRUE, POS

    m = Model.from_spec('base,site_gradient', 4)
    p = m.default_params()
    for j in range(1, 5):
        p = m.params_from_linear(j, A_TRUE[j - 1], O_TRUE[j - 1], p)
    p[m.array_cols] = [G_W[0, 0], G_W[0, 1], G_W[0, 2], G_W[1, 1], G_W[1, 2]]
    path = tmp_path / 'cal.yaml'
    save_calibration(path, calibration_to_doc(Calibration(m, p, sigma_nt=np.full(4, 3.0)),
                                              geometry=cross_geometry(0.5)), history=0)
    rot = Rotation.from_euler('ZYX', [30.0, 10.0, -20.0], degrees=True)
    b_w = np.array([21000.0, -2500.0, 45000.0])
    b_c = rot.inv().apply(b_w)                                    # centre field, body
    at_sensor = np.array([rot.inv().apply(b_w + G_W @ rot.apply(r)) for r in POS])
    n = 10
    raw = np.stack([np.repeat((A_TRUE[j] @ at_sensor[j] + O_TRUE[j])[None], n, axis=0)
                    for j in range(4)])
    data = Dataset(t=np.arange(n) * 0.01, raw=raw)
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    corrected = [[] for _ in range(4)]
    tensors = []
    for j in range(4):
        ros_node.create_subscription(MagneticField, f'sensor{j + 1}/corrected',
                                     corrected[j].append, 100)
    ros_node.create_subscription(Float64MultiArray, 'gradient', tensors.append, 100)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    feeder.feed(ros_executor, data, taken=lambda: node.received, temperature=False)
    spin_until(ros_executor, lambda: all(len(c) == n for c in corrected) and len(tensors) == n,
               10.0, 'the corrected samples')
    for j in range(4):       # default: the field where each sensor is
        np.testing.assert_allclose(msg_to_field_nt(corrected[j][-1]), at_sensor[j], atol=1e-6)
    r = rot.as_matrix()
    np.testing.assert_allclose(msg_to_tensor(tensors[-1]), r.T @ G_W @ r, atol=1e-6)
    node.set_parameters([Parameter('subtract_site_gradient', value=True),
                         Parameter('site_attitude', value=list(rot.as_quat(scalar_first=True)))])
    for c in corrected:
        c.clear()
    tensors.clear()
    later = Dataset(t=data.t + 1.0, raw=raw)          # stamps go on after the first feed
    feeder.feed(ros_executor, later, taken=lambda: node.received, temperature=False)
    spin_until(ros_executor, lambda: all(len(c) == n for c in corrected) and len(tensors) == n,
               10.0, 'the corrected samples')
    for j in range(4):       # stationary test: the centre field, the anomaly is zero
        np.testing.assert_allclose(msg_to_field_nt(corrected[j][-1]), b_c, atol=1e-6)
    np.testing.assert_allclose(msg_to_tensor(tensors[-1]), np.zeros((3, 3)), atol=1e-6)
    # a site attitude that is not a unit quaternion is refused
    res = node.set_parameters([Parameter('site_attitude', value=[1.0, 1.0, 0.0, 0.0])])
    assert not res[0].successful and 'unit quaternion' in res[0].reason
