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
The calibration node with an attitude (issue 31 item 2): imu_topic on a vehicle near level.

A stand-in vehicle written here publishes its compass on imu/mag and its attitude on imu
(sensor_msgs/Imu, body to ENU as REP 103 says) while it turns at 0.6 rad/s and rocks by
+-12 deg: a sensor with hand-written errors in a field of 50 000 nT at 65 deg (ENU: the
field points down, -z), 3 nT noise.  The magnitude alone refuses such a cone of directions;
with the attitude (attitude_mode auto: roll and pitch) the node calibrates, says so, and
reaches the noise.
"""

import math

from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.conversions import attitude_msg, field_nt_to_msg
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import call_trigger, spin_for, split_response
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Imu, MagneticField

pytestmark = pytest.mark.live

F_NT, INC = 50000.0, math.radians(65.0)
A = np.array([[1.02, 0.015, 0.0], [0.0, 0.97, 0.01], [0.0, 0.0, 1.01]])
OFFSET = np.array([300.0, -450.0, 200.0])
#: the field in ENU: north, no east, down (-z)
M_ENU = F_NT * np.array([0.0, math.cos(INC), -math.sin(INC)])


class Vehicle:
    """Turns and rocks; publishes imu/mag (T) and imu (the attitude) at 50 Hz."""

    def __init__(self, node, ns):
        self.node, self.t = node, 0.0
        self.rng = np.random.default_rng(1)
        self.mag = node.create_publisher(MagneticField, f'{ns}/imu/mag', 50)
        self.imu = node.create_publisher(Imu, f'{ns}/imu', 50)
        node.create_timer(0.02, self._tick)

    def _tick(self):
        self.t += 0.02
        t = self.t
        rot = Rotation.from_euler('ZYX', [0.6 * t, math.radians(12) * math.sin(0.7 * t),
                                          math.radians(12) * math.sin(1.1 * t + 1.0)])
        b = rot.inv().apply(M_ENU)                     # the field in the body frame
        raw = A @ b + OFFSET + self.rng.normal(0, 3.0, 3)
        stamp = self.node.get_clock().now().to_msg()
        self.imu.publish(attitude_msg(rot.as_quat(scalar_first=True), stamp=stamp))
        self.mag.publish(field_nt_to_msg(raw, stamp=stamp, frame_id='imu_link'))


def _node(make_node, ns, tmp_path, **extra):
    params = {'n_sensors': 1, 'input_topics': [f'{ns}/imu/mag'], 'imu_topic': f'{ns}/imu',
              'field_nt': F_NT, 'min_samples': 600,
              'calibration_file': str(tmp_path / 'cal.yaml'), **extra}
    return make_node(CalibrationNode, namespace=ns,
                     parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def _collect(ros_node, ros_executor):
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    spin_for(ros_executor, 16.0)                   # 800 sets: more than a full turn


def test_attitude_aided_calibration_on_the_node(make_node, ros_node, ros_executor,
                                                ros_namespace, tmp_path):
    Vehicle(make_node('vehicle'), ros_namespace)
    _node(make_node, ros_namespace, tmp_path)
    _collect(ros_node, ros_executor)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60.0)
    summary, payload = split_response(resp)
    assert resp.success, summary
    assert payload['attitude']['mode'] == 'tilt'
    assert any(line.startswith('attitude: tilt') for line in summary)
    # at the noise: the scalar residual of a 3 nT sensor (radial noise, one axis' worth)
    assert payload['scalar_rms_after_nt']['1'] < 3.0 * 1.15
    # ENU: the fitted inclination is that of -z, -65 deg
    assert abs(payload['attitude']['world_field']['inclination_deg'] + 65.0) < 1.0
    # calibration/diagnose starts from the same attitude-aided fit, and finds nothing missing
    resp = call_trigger(ros_node, ros_executor, 'calibration/diagnose', timeout_sec=120.0)
    summary, diag = split_response(resp)
    assert resp.success, summary
    assert diag['attitude']['mode'] == 'tilt' and diag['verdict']['effect'] == 'none', diag
    # what the record cannot rule out is said in the reply as in the JSON (one line, or none)
    listed = [r['token'] for r in diag['not_ruled_out']]
    said = [line for line in summary if line.startswith('not ruled out by this record')]
    assert len(said) == (1 if listed else 0), (said, listed)
    assert all(f'{t} (' in said[0] for t in listed[:6]), (said, listed)


def test_without_the_attitude_the_cone_is_refused(make_node, ros_node, ros_executor,
                                                  ros_namespace, tmp_path):
    Vehicle(make_node('vehicle'), ros_namespace)
    _node(make_node, ros_namespace, tmp_path, attitude_mode='off')
    _collect(ros_node, ros_executor)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60.0)
    summary, _ = split_response(resp)
    assert not resp.success
    assert any('cone' in line or 'one axis' in line for line in summary), summary
