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
The nodes' /diagnostics go through diagnostic_updater or its shim, with the same messages.

The expected ``DiagnosticArray`` is written here with diagnostic_msgs alone, from
diagnostic_updater's documented behaviour (task status named ``<node>: <task>``, hardware
ID from ``setHardwareID`` unless the task sets one, ERROR ``No message was set`` before the
callback, ``mergeSummary`` keeping the higher level and joining messages of the same kind,
``Node starting up`` on ``add``). The shim is checked against it always; the real
``diagnostic_updater`` with the same callbacks when it is importable (a ROS install).
"""

import importlib

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from magcal_ros.ros import diagnostics
from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.corrector_node import CorrectorNode
from magcal_ros.ros.driver_node import FluxgateDriver
import pytest
from rclpy.parameter import Parameter
from ros_helpers import spin_until


def _implementation(name):
    if name == 'shim':
        return diagnostics.FallbackUpdater
    # ROS 2's diagnostic_updater (package.xml declares it) has no wheel for this pip-based
    # ROS install (`pip index versions ros-jazzy-diagnostic-updater`: no matching
    # distribution, 2026-11); Debian's python3-diagnostic-updater is ROS 1's (rospy), and
    # building ROS 2's from source needs its repository, which this machine cannot fetch.
    # With a ROS install that has it (apt ros-jazzy-diagnostic-updater) this runs.
    return pytest.importorskip(
        'diagnostic_updater',
        reason='ROS 2 diagnostic_updater is not installed: no wheel for the pip-based ROS '
        '(ros-jazzy-diagnostic-updater is not on PyPI; Debian python3-diagnostic-updater is '
        "ROS 1's); install ros-jazzy-diagnostic-updater from a ROS apt repository to run "
        'these against it').Updater


def _port(stat):
    stat.summary(DiagnosticStatus.WARN, 'two faults')
    stat.add('samples', '12')
    stat.mergeSummary(DiagnosticStatus.ERROR, 'port lost')
    stat.mergeSummary(DiagnosticStatus.OK, 'an OK message is dropped')
    return stat


def _own_hardware(stat):
    stat.hardware_id = '/dev/ttyUSB0'
    stat.summary(DiagnosticStatus.OK, 'fine')
    stat.mergeSummary(DiagnosticStatus.OK, 'still fine')
    return stat


def _expected(node_name):
    """Return the statuses of the three tasks below, written by hand."""
    return [
        DiagnosticStatus(level=DiagnosticStatus.ERROR, name=f'{node_name}: port',
                         message='two faults; port lost', hardware_id='array-7',
                         values=[KeyValue(key='samples', value='12')]),
        DiagnosticStatus(level=DiagnosticStatus.ERROR, name=f'{node_name}: silent',
                         message='No message was set', hardware_id='array-7'),
        DiagnosticStatus(level=DiagnosticStatus.OK, name=f'{node_name}: own_hw',
                         message='fine; still fine', hardware_id='/dev/ttyUSB0'),
    ]


@pytest.mark.parametrize('implementation', ['shim', 'diagnostic_updater'])
def test_updater_publishes_the_documented_message(make_node, ros_node, ros_executor,
                                                  implementation):
    updater_cls = _implementation(implementation)
    node = make_node('diag_source')
    got = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', got.append, 50)
    updater = updater_cls(node, period=100.0)        # only force_update publishes here
    assert node.get_parameter('diagnostic_updater.period').value == 100.0
    spin_until(ros_executor, lambda: node.count_subscribers('/diagnostics') > 0,
               message='the probe subscribed')
    updater.setHardwareID('array-7')
    updater.add('port', _port)
    updater.add('silent', lambda stat: stat)
    updater.add('own_hw', _own_hardware)
    updater.force_update()
    spin_until(ros_executor, lambda: len(got) >= 4, message='3 start-up messages and 1 update')
    name = node.get_name()
    for msg, task in zip(got[:3], ('port', 'silent', 'own_hw')):
        assert [(s.level, s.name, s.message) for s in msg.status] == \
            [(DiagnosticStatus.OK, f'{name}: {task}', 'Node starting up')]
    update = got[3]
    assert update.status == _expected(name)
    assert update.header.stamp.sec > 0


def test_the_module_uses_diagnostic_updater_when_importable():
    try:
        real = importlib.import_module('diagnostic_updater')
    except ImportError:
        assert diagnostics.Updater is diagnostics.FallbackUpdater
        assert diagnostics.DiagnosticStatusWrapper is diagnostics.FallbackStatusWrapper
        assert diagnostics.SOURCE == 'magcal_ros shim'
    else:
        assert diagnostics.Updater is real.Updater
        assert diagnostics.SOURCE == 'diagnostic_updater'


def test_wrapper_merge_rules():
    # diagnostic_updater's rules: the higher level wins; messages of two non-OK (or two OK)
    # levels are joined with '; '; an OK message does not join a non-OK one
    stat = diagnostics.FallbackStatusWrapper()
    stat.clearSummary()
    assert (stat.level, stat.message) == (DiagnosticStatus.OK, '')
    stat.mergeSummary(DiagnosticStatus.OK, 'a')
    assert (stat.level, stat.message) == (DiagnosticStatus.OK, 'a')
    stat.mergeSummary(DiagnosticStatus.WARN, 'b')
    assert (stat.level, stat.message) == (DiagnosticStatus.WARN, 'b')
    stat.mergeSummary(DiagnosticStatus.OK, 'c')
    assert (stat.level, stat.message) == (DiagnosticStatus.WARN, 'b')
    stat.mergeSummary(DiagnosticStatus(level=DiagnosticStatus.STALE, message='d'))
    assert (stat.level, stat.message) == (DiagnosticStatus.STALE, 'b; d')
    stat.summary(2, 'e')                   # an int level is stored as the message's byte
    assert (stat.level, stat.message) == (DiagnosticStatus.ERROR, 'e')
    stat.add('n', 3)
    assert stat.values == [KeyValue(key='n', value='3')]


@pytest.mark.parametrize('node_cls, overrides, names', [
    (FluxgateDriver, {'n_sensors': 2, 'sensor1.port': '/nonexistent/a',
                      'sensor2.port': '/nonexistent/b'},
     ['fluxgate_driver: sensor1', 'fluxgate_driver: sensor2']),
    (CalibrationNode, {}, ['calibration_node: residual', 'calibration_node: buffer',
                           'calibration_node: setup']),
    (CorrectorNode, {}, ['corrector_node: correction']),
])
def test_every_node_publishes_through_the_updater(make_node, ros_node, ros_executor,
                                                  ros_namespace, tmp_path, node_cls,
                                                  overrides, names):
    got = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', got.append, 50)
    params = {'calibration_file': str(tmp_path / 'c.yaml'),
              'report_dir': str(tmp_path / 'r')} if node_cls is CalibrationNode else (
        {'calibration_file': str(tmp_path / 'c.yaml')} if node_cls is CorrectorNode else {})
    params.update(overrides)
    params['diagnostics_period_s' if node_cls is not CalibrationNode
           else 'status_period_s'] = 0.2
    node = make_node(node_cls, namespace=ros_namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    assert node.get_parameter('diagnostic_updater.period').value == 0.2
    msg = spin_until(ros_executor, lambda: next(
        (m for m in got if [s.name for s in m.status] == names
         and m.status[0].message != 'Node starting up'), None),
        message=f'a periodic status of {names}')
    for s in msg.status:
        # the driver names each port's device; the others the array (their namespace)
        assert s.hardware_id == (overrides[f'sensor{s.name[-1]}.port']
                                 if node_cls is FluxgateDriver else ros_namespace)
