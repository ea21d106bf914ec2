"""calibration_node with an Imu topic: the site gradient fitted live (issue 13).

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
from sim_feed import Feeder, T0
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
    for k in range(data.n_samples):
        msg = Imu()
        msg.header.stamp = to_stamp(T0 + float(data.t[k]))
        qw, qx, qy, qz = data.attitude[k]
        msg.orientation.w, msg.orientation.x = float(qw), float(qx)
        msg.orientation.y, msg.orientation.z = float(qy), float(qz)
        imu_pub.publish(msg)
        if k % 5 == 4 or k == data.n_samples - 1:
            # best-effort queue: wait until the node has taken this batch
            deadline = time.monotonic() + 30.0
            while node._imu_count < k + 1:
                assert time.monotonic() < deadline, f'the node took {node._imu_count} of {k + 1}'
                ros_executor.spin_once(timeout_sec=0.01)
    feeder.feed(ros_executor, data, taken=lambda: int(node._received.sum()),
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
