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
Smoke test of the ROS setup: rclpy from the wheels, two processes over the loopback profile.

A child process publishes ``sensor_msgs/MagneticField``; this test process subscribes. Both
run with the session's environment (conftest): config/fastdds_loopback.xml, a per-run
ROS_DOMAIN_ID. The sockets of both processes are then read from /proc to check that DDS
bound nothing but 127.0.0.1.
"""

import os
import pathlib
import signal
import subprocess
import sys

from magcal_ros.ros.conversions import msg_to_covariance_nt2, msg_to_field_nt
import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from ros_helpers import (bound_inet_sockets, call_trigger, console_script, REPO_ROOT,
                         spin_until, subprocess_env, wait_for_messages)
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

FIELD_NT = (12345.6, -2345.1, 43210.9)
SIGMA_NT = 3.0

PUBLISHER = f"""
import sys
import rclpy
from rclpy.executors import ExternalShutdownException
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger
from magcal_ros.ros.conversions import field_nt_to_msg

rclpy.init()
node = rclpy.create_node('smoke_publisher', namespace=sys.argv[1])
pub = node.create_publisher(MagneticField, 'smoke/field', 10)
calls = []


def ping(request, response):
    calls.append(1)
    response.success = True
    response.message = f'pong {{len(calls)}}'
    return response


node.create_service(Trigger, 'smoke/ping', ping)


def tick():
    pub.publish(field_nt_to_msg({FIELD_NT!r}, stamp=node.get_clock().now(),
                                frame_id='smoke_frame', covariance_nt2={SIGMA_NT ** 2!r}))


node.create_timer(0.05, tick)
print('publishing', flush=True)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
print('publisher stopped', flush=True)
"""


def test_rclpy_and_messages_come_from_the_environment():
    # rclpy and the messages are the Jazzy wheels installed in this interpreter's environment
    for module in (rclpy, sys.modules[MagneticField.__module__]):
        assert pathlib.Path(module.__file__).resolve().is_relative_to(
            pathlib.Path(sys.prefix).resolve()), module.__file__
    assert len(MagneticField().magnetic_field_covariance) == 9
    assert os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] == \
        str(REPO_ROOT / 'config' / 'fastdds_loopback.xml')
    assert os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] == \
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE']
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SYSTEM_DEFAULT'
    assert os.environ['RMW_IMPLEMENTATION'] == 'rmw_fastrtps_cpp'
    assert 1 <= int(os.environ['ROS_DOMAIN_ID']) <= 101


LOOPBACK = ('127.0.0.1', '0000:0000:0000:0000:0000:ffff:7f00:0001')   # IPv4, v4-mapped v6


def _non_loopback(sockets):
    return [s for s in sockets if s[1] not in LOOPBACK]


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc (Linux)')
def test_magnetic_field_between_processes_over_loopback(ros_node, ros_executor, ros_namespace,
                                                        start_process):
    pub = start_process([sys.executable, '-c', PUBLISHER, ros_namespace],
                        name='smoke_publisher', ready='publishing')
    msgs = wait_for_messages(ros_node, ros_executor, MagneticField, 'smoke/field', count=3,
                             timeout_sec=20.0)

    for msg in msgs:
        # tesla on the wire, nT back: exact to float64 rounding (relative 1e-15)
        np.testing.assert_allclose(msg_to_field_nt(msg), FIELD_NT, rtol=1e-15)
        np.testing.assert_allclose(msg_to_covariance_nt2(msg), np.eye(3) * SIGMA_NT ** 2,
                                   rtol=1e-15)
        assert msg.header.frame_id == 'smoke_frame'
        assert msg.header.stamp.sec > 0

    # a service in the other process, called with call_async + bounded spinning
    for k in (1, 2):
        response = call_trigger(ros_node, ros_executor, 'smoke/ping', timeout_sec=20.0)
        assert (response.success, response.message) == (True, f'pong {k}')

    # DDS sockets of both processes: UDP only, bound to 127.0.0.1 only.  The publisher runs
    # rclpy alone: no TCP at all.  This process also runs the test runner, whose pytest-xdist
    # plug-in holds a TCP socket on 127.0.0.1 (not DDS): here every socket is on loopback.
    for pid in (pub.pid, os.getpid()):
        sockets = bound_inet_sockets(pid)
        assert any(proto == 'udp' for proto, _, _ in sockets), f'no UDP socket in {pid}'
        assert _non_loopback(sockets) == [], f'non-loopback sockets of {pid}: {sockets}'
    assert [s for s in bound_inet_sockets(pub.pid) if s[0].startswith('tcp')] == []

    # SIGINT gives the publisher a clean rclpy shutdown.
    assert pub.stop() == 0, pub.log_tail()
    assert pub.signals_sent == ['SIGINT']
    assert 'publisher stopped' in pub.read_log()


def test_spin_until_times_out_with_a_message(ros_executor):
    with pytest.raises(AssertionError, match=r'timed out after 0\.2 s waiting for nothing'):
        spin_until(ros_executor, lambda: False, timeout_sec=0.2, message='nothing')


def test_stop_escalates_when_sigint_is_ignored(start_process):
    code = ('import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); '
            'print("ready", flush=True); time.sleep(60)')
    proc = start_process([sys.executable, '-c', code], name='stubborn', ready='ready')
    assert proc.stop(sigint_timeout_sec=0.3) == -signal.SIGTERM
    assert proc.signals_sent == ['SIGINT', 'SIGTERM']


class _Counter(Node):
    """Node with a Trigger service, built the way the project's nodes are (kwargs to Node)."""

    def __init__(self, **kwargs):
        super().__init__('counter', **kwargs)
        self.count = 0
        self.create_service(Trigger, 'count', self._on_count)

    def _on_count(self, request, response):
        self.count += 1
        response.success = self.count % 2 == 1
        response.message = f'count {self.count}'
        return response


def test_make_node_and_call_trigger_in_process(make_node, ros_node, ros_executor, ros_namespace):
    server = make_node(_Counter, namespace=ros_namespace)
    assert server.context is ros_node.context
    first = call_trigger(ros_node, ros_executor, 'count', timeout_sec=10.0)
    second = call_trigger(ros_node, ros_executor, f'{ros_namespace}/count', timeout_sec=10.0)
    assert (first.success, first.message) == (True, 'count 1')
    assert (second.success, second.message) == (False, 'count 2')
    with pytest.raises(AssertionError, match='service .*/missing to become available'):
        call_trigger(ros_node, ros_executor, 'missing', timeout_sec=0.3)


def test_console_script_command():
    with pytest.raises(ValueError, match="'no_such_tool' is not a console script"):
        console_script('no_such_tool')
    result = subprocess.run(console_script('magcal') + ['--help'], env=subprocess_env(),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert 'usage' in result.stdout.lower()
