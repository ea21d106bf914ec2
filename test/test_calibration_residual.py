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
calibration_node compares the active calibration with the live data (calibration/residual).

The array data are written here, not by the simulator: a uniform 50 000 nT field seen by a
tumbling array, four sensors with scale, non-orthogonality, misalignment and offset chosen
here, 2 nT of white noise per axis, and a temperature term on sensor 2 (k (T - 25 degC),
T swinging +-10 degC) that the model ``base`` lacks. With ``base`` the published residual
of sensor 2 stays far above the noise and /diagnostics says the calibration no longer fits;
after ``model: [base, temperature@2]`` and a calibrate it falls to the noise.
"""

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.conversions import RESIDUAL_KIND_LABEL
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import call_trigger, spin_until
from sim_feed import Feeder
from std_msgs.msg import Float64MultiArray
from test_live import _rot_x, _rot_z, C, OFFSETS, R   # sensors written by hand

F_NT = 50000.0
SIGMA_NT = 2.0
RATE_HZ = 100.0
K_TEMP = np.array([3.0, -2.0, 1.5])      # nT/degC, sensor 2


def _recording(n, seed):
    """Dataset of n epochs at 100 Hz: raw_j = C_j R_j^T b + o_j (+ k (T - 25) on sensor 2)."""
    t = np.arange(n) / RATE_HZ
    b_world = np.array([20000.0, 5000.0, -np.sqrt(F_NT ** 2 - 20000.0 ** 2 - 5000.0 ** 2)])
    b = np.array([(_rot_z(360 * tk / 5.0) @ _rot_x(360 * tk / 7.0) @ _rot_z(360 * tk / 3.0)).T
                  @ b_world for tk in t])                                   # (n, 3) nT
    temp = 25.0 + 10.0 * np.sin(2 * np.pi * t / 4.0)
    rng = np.random.default_rng(seed)
    raw = np.empty((4, n, 3))
    for j in range(4):
        raw[j] = b @ (C[j] @ R[j].T).T + OFFSETS[j] + rng.normal(scale=SIGMA_NT, size=(n, 3))
    raw[1] += np.outer(temp - 25.0, K_TEMP)
    return Dataset(t=t, raw=raw, temp=np.tile(temp, (4, 1)))


def _residual_status(box, namespace):
    return [s for m in box for s in m.status
            if s.hardware_id == namespace and s.name.endswith(': residual')]


def test_residual_falls_after_the_missing_effect_is_added(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(tmp_path / 'calibration.yaml')),
        Parameter('report_dir', value=str(tmp_path / 'report')),
        Parameter('min_samples', value=600), Parameter('field_nt', value=F_NT),
        Parameter('status_period_s', value=0.2)])
    residuals, diagnostics = [], []
    ros_node.create_subscription(Float64MultiArray, 'calibration/residual',
                                 residuals.append, 2000)
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 100)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    data = _recording(2400, seed=1)

    def feed(start, stop):
        """Publish epochs start:stop, each batch until the node took it."""
        feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()),
                    start=start, stop=stop)

    def calibrate(start, stop):
        assert call_trigger(ros_node, ros_executor, 'calibration/start').success
        feed(start, stop)
        response = call_trigger(ros_node, ros_executor, 'calibration/calibrate')
        assert response.success, response.message

    def watch(start, stop):
        """Feed epochs start:stop; return the scalar residuals (sets, 4) nT and a status."""
        residuals.clear()
        feed(start, stop)
        spin_until(ros_executor, lambda: len(residuals) >= 0.8 * (stop - start), 10.0,
                   'the residual of the fed sets')
        assert [d.label for d in residuals[0].layout.dim] == [RESIDUAL_KIND_LABEL, 'sensor']
        diagnostics.clear()
        spin_until(ros_executor, lambda: _residual_status(diagnostics, ros_namespace), 5.0,
                   'a residual status')
        values = np.array([m.data for m in residuals]) * 1e9           # T -> nT
        return values[:, :4], values[:, 4:], _residual_status(diagnostics, ros_namespace)[-1]

    # before any calibration: no residual, and the status says why
    spin_until(ros_executor, lambda: _residual_status(diagnostics, ros_namespace), 5.0)
    assert 'no active calibration' in _residual_status(diagnostics, ros_namespace)[-1].message

    calibrate(0, 700)                                    # model: base
    scalar, vector, status = watch(700, 1200)
    before = np.sqrt(np.mean(scalar ** 2, axis=0))
    # sensor 2 carries the temperature term, the others only noise (scalar RMS ~ sigma)
    assert before[1] > 3 * SIGMA_NT, before
    assert np.all(before[[0, 2, 3]] < 1.5 * SIGMA_NT), before
    assert status.level == DiagnosticStatus.WARN, status.message
    assert 'no longer fits' in status.message and 'sensor 2 scalar' in status.message

    # the user adds the effect and calibrates again on fresh data
    assert node.set_parameters([Parameter('model', value=['base', 'temperature@2'])])[0] \
        .successful
    calibrate(1200, 1900)
    scalar, vector, status = watch(1900, 2400)
    after = np.sqrt(np.mean(scalar ** 2, axis=0))
    assert after[1] < before[1] / 3, (before, after)
    # scalar RMS of noise alone: sigma within +-20 % (500 sets: 3 %; fitted parameters)
    assert after == pytest.approx(np.full(4, SIGMA_NT), rel=0.2)
    assert status.level == DiagnosticStatus.OK, status.message
    values = {v.key: float(v.value) for v in status.values if v.key.endswith('_ratio')}
    assert max(values.values()) < 1.5 and values['sensor2_scalar_ratio'] > 0.8
