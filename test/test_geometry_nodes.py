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
In-process nodes with another geometry and another input (issue 20 items 1-3).

An IMU's magnetometer on its own topic (``input_topics``), calibrated with the IGRF
magnitude of the site (``field_source: igrf``), corrected in the IMU's own frame with the
covariance filled in; a calibration file of another geometry refused with both named.
"""
from diagnostic_msgs.msg import DiagnosticArray
from magcal_ros.core.data.magnitude import igrf_field
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.calfile import calibration_to_doc, load_calibration, save_calibration
from magcal_ros.pipeline import cross_geometry
from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.conversions import field_nt_to_msg, msg_to_covariance_nt2, msg_to_field_nt
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import call_trigger, spin_until, split_response as split
from sensor_msgs.msg import MagneticField

NOISE_NT = 3.0
#: the site: Oslo, 100 m, 2025-06-01 (IGRF from ppigrf, the reference of the simulation)
SITE = {'site_latitude_deg': 59.91, 'site_longitude_deg': 10.75, 'site_altitude_m': 100.0,
        'site_date': '2025-06-01'}
T0 = 1_700_000_000.0


@pytest.fixture(scope='module')
def imu_data():
    """10 s at 100 Hz of one tumbling magnetometer in the IGRF field of SITE."""
    f = igrf_field(SITE['site_latitude_deg'], SITE['site_longitude_deg'],
                   SITE['site_altitude_m'] / 1000.0, SITE['site_date'])[0]
    data, sim = simulate(n_samples=1000, n_sensors=1, rate_hz=100.0, trajectory='smooth',
                         smooth_period_s=10.0, field_nt=f, seed=5)
    return data, sim, f


def test_imu_topic_calibrated_with_igrf_and_corrected_in_its_frame(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, imu_data):
    data, sim, f_igrf = imu_data
    topic = f'{ros_namespace}_imu/mag'          # absolute, as an IMU driver's /imu/mag
    cal_file = tmp_path / 'calibration.yaml'
    common = {'n_sensors': 1, 'input_topics': [topic], 'calibration_file': str(cal_file)}
    params = dict(common, report_dir=str(tmp_path / 'report'), min_samples=500,
                  field_source='igrf', **SITE)
    diags = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda m: diags.extend(m.status), 50)
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    pub = ros_node.create_publisher(MagneticField, topic,
                                    QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
    spin_until(ros_executor, lambda: pub.get_subscription_count() > 0, 10.0)
    # the node says where its magnitude comes from, on /diagnostics
    setup = spin_until(ros_executor, lambda: [s for s in diags if s.name.endswith('setup')
                                              and s.hardware_id == ros_namespace],
                       10.0, 'the setup status')[-1]
    assert f'field magnitude from IGRF: {f_igrf:.1f} nT' in setup.message
    assert 'one sensor measures no field difference' in setup.message

    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    for k in range(data.n_samples):
        pub.publish(field_nt_to_msg(data.raw[0, k], stamp=T0 + data.t[k], frame_id='imu_link'))
        if k % 5 == 4:
            spin_until(ros_executor, lambda: node.received[0] >= k + 1, 10.0)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60.0)
    lines, out = split(resp)
    assert resp.success, lines
    ref = out['field_reference']
    assert ref['kind'] == 'igrf' and ref['date'] == SITE['site_date']
    assert ref['magnitude_nt'] == pytest.approx(f_igrf, rel=1e-12)
    assert f'field magnitude {f_igrf:.1f} nT (igrf)' in lines
    _, doc = load_calibration(cal_file)
    assert doc['provenance']['field_source'] == 'igrf'
    assert doc['field_reference']['lat_deg'] == SITE['site_latitude_deg']
    # the fit at the noise: RMS over 1000 epochs scatters by 1/sqrt(2000) ~ 2 %; 4 of it
    assert abs(out['scalar_rms_after_nt']['1'] / NOISE_NT - 1.0) < 4.0 / np.sqrt(1000)

    # the corrector on the same topic, keeping the IMU's frame (array_frame_id '')
    corrector = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in dict(common, array_frame_id='').items()])
    assert corrector.calibration is not None, corrector.refusal
    got = []
    ros_node.create_subscription(MagneticField, 'sensor1/corrected', got.append, 500)
    spin_until(ros_executor, lambda: pub.get_subscription_count() >= 2, 10.0)
    for k0 in range(0, 300, 5):
        for k in range(k0, k0 + 5):
            pub.publish(field_nt_to_msg(data.raw[0, k], stamp=T0 + data.t[k],
                                        frame_id='imu_link'))
        spin_until(ros_executor, lambda: corrector.received >= k + 1, 10.0, 'the corrector')
    spin_until(ros_executor, lambda: len(got) >= 300, 10.0, 'corrected samples')
    b = np.array([msg_to_field_nt(m) for m in got])
    err = np.linalg.norm(b, axis=1) - f_igrf
    assert abs(np.sqrt(np.mean(err ** 2)) / NOISE_NT - 1.0) < 4.0 / np.sqrt(len(b))
    assert {m.header.frame_id for m in got} == {'imu_link'}      # REP 145: its own frame
    cov = msg_to_covariance_nt2(got[-1])
    a_inv = sim.truth.correction_matrix(1)
    noise = NOISE_NT ** 2 * a_inv @ a_inv.T
    # noise (the fit's sigma, within 4/sqrt(2000) of 3 nT: 9 % in the variance) plus the
    # calibration's uncertainty, which is positive: more than the noise's lower bound
    extra = np.diag(cov) - np.diag(noise) * (1 - 0.09)
    assert np.all(extra > 0), (cov, noise)
    assert np.all(np.diag(cov) < np.diag(noise) * 1.2), (cov, noise)


def test_corrector_refuses_a_file_of_another_geometry(make_node, ros_namespace, tmp_path):
    data, sim = simulate(n_samples=10, seed=1)
    path = tmp_path / 'cal.yaml'
    save_calibration(path, calibration_to_doc(sim.truth, geometry=cross_geometry(0.5)),
                     history=0)
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)), Parameter('baseline_m', value=0.3)])
    assert node.calibration is None
    refusal = node.refusal
    assert '[[0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [-0.25, 0.0, 0.0], [0.0, -0.25, 0.0]]' \
        in refusal
    assert '[[0.15, 0.0, 0.0], [0.0, 0.15, 0.0], [-0.15, 0.0, 0.0], [0.0, -0.15, 0.0]]' \
        in refusal
    # the same file with the node's geometry given as positions is accepted
    node2 = make_node(CorrectorNode, namespace=ros_namespace + '_b', parameter_overrides=[
        Parameter('calibration_file', value=str(path)),
        Parameter('sensor_positions_m',
                  value=[0.25, 0.0, 0.0, 0.0, 0.25, 0.0, -0.25, 0.0, 0.0, 0.0, -0.25, 0.0])])
    assert node2.calibration is not None and node2.refusal is None


@pytest.mark.parametrize('params, message', [
    ({'n_sensors': 2, 'sensor_positions_m': [0.0, 0.0, 0.25]},
     'sensor_positions_m: must be empty (paper 004 cross for 4 sensors) or x y z per sensor'),
    ({'n_sensors': 2, 'input_topics': ['/imu/mag']},
     'input_topics: must name one sensor_msgs/MagneticField topic per sensor: 2'),
    ({'field_source': 'wmm'}, "field_source: must be one of ['constant', 'igrf', 'shape']"),
    ({'site_date': '1/6/2025'}, 'site_date: must be YYYY-MM-DD'),
])
def test_bad_geometry_parameters_are_refused(ros_context, ros_namespace, tmp_path, params,
                                             message):
    overrides = dict(params, calibration_file=str(tmp_path / 'c.yaml'))
    with pytest.raises(ValueError, match='bad parameter') as err:
        CalibrationNode(context=ros_context, namespace=ros_namespace, parameter_overrides=[
            Parameter(k, value=v) for k, v in overrides.items()])
    assert message in str(err.value)
