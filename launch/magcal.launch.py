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
Launch the magcal_ros pipeline: (simulated) fluxgates, driver, calibration and corrector.

Usage (on a ROS 2 Jazzy install, after ``colcon build``)::

    ros2 launch magcal_ros magcal.launch.py                 # with the simulated array
    ros2 launch magcal_ros magcal.launch.py use_sim:=false driver_params:=/path/driver.yaml

All nodes run in the namespace given by ``namespace`` (default ``magcal``), each with its
parameters from ``share/magcal_ros/config/<node>.yaml``. ``driver_params`` replaces the
driver's file (``config/driver.yaml`` reads the simulator's pseudo-terminals, so real
fluxgates, ``use_sim:=false``, need a file of their own naming the serial ports);
``calibration_file`` sets the calibration file of both the calibration node and the
corrector (default ``$ROS_HOME/magcal/calibration.yaml``). Then, for example::

    ros2 service call /magcal/calibration/start std_srvs/srv/Trigger
    ros2 service call /magcal/calibration/calibrate std_srvs/srv/Trigger
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch_ros.actions import Node

PACKAGE = 'magcal_ros'

#: (executable, parameter file in share/magcal_ros/config, started only with use_sim:=true)
NODES = (
    ('fluxgate_sim', 'sim.yaml', True),
    ('fluxgate_driver', 'driver.yaml', False),
    ('calibration_node', 'calibration.yaml', False),
    ('corrector_node', 'corrector.yaml', False),
)

#: nodes that read or write the calibration file
CALIBRATION_FILE_USERS = ('calibration_node', 'corrector_node')


def _nodes(context):
    """Return the nodes the launch arguments select (a launch.OpaqueFunction body)."""
    args = context.launch_configurations
    config_dir = os.path.join(get_package_share_directory(PACKAGE), 'config')
    use_sim = args['use_sim'].strip().lower() in ('true', '1', 'yes', 'on')
    driver_params = os.path.expanduser(args['driver_params'].strip())
    calibration_file = args['calibration_file'].strip()
    if not use_sim and not driver_params:
        raise RuntimeError(
            'use_sim:=false needs driver_params:=<driver YAML> naming your serial ports '
            '(sensor{j}.port; start from share/magcal_ros/config/driver.yaml): the shipped '
            "file reads the simulator's pseudo-terminals")
    if driver_params and not os.path.isfile(driver_params):
        raise RuntimeError(f'driver_params: no file {driver_params}')
    nodes = []
    for executable, config, sim_only in NODES:
        if sim_only and not use_sim:
            continue
        params = [os.path.join(config_dir, config)]
        if executable == 'fluxgate_driver' and driver_params:
            params = [driver_params]
        if executable in CALIBRATION_FILE_USERS and calibration_file:
            params.append({'calibration_file': calibration_file})
        nodes.append(Node(package=PACKAGE, executable=executable,
                          namespace=args['namespace'], parameters=params, output='screen'))
    return nodes


def generate_launch_description():
    """Return the launch description: its arguments and the nodes they select."""
    return LaunchDescription([
        DeclareLaunchArgument(
            'use_sim', default_value='true',
            description='start fluxgate_sim (simulated fluxgates on pseudo-terminals '
                        '/tmp/magcal_sim/fluxgate1..4); false for real serial devices '
                        '(then driver_params is required)'),
        DeclareLaunchArgument(
            'namespace', default_value='magcal',
            description='ROS namespace of all nodes (topics sensor{j}/raw, calibration/*, ...)'),
        DeclareLaunchArgument(
            'driver_params', default_value='',
            description="parameter file of fluxgate_driver (ports, protocols, axes); '' = "
                        'the shipped config/driver.yaml (the simulator ports)'),
        DeclareLaunchArgument(
            'calibration_file', default_value='',
            description="calibration file of calibration_node and corrector_node; '' = "
                        'their default $ROS_HOME/magcal/calibration.yaml'),
        OpaqueFunction(function=_nodes),
    ])
