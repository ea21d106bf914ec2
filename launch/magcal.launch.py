"""Launch the magcal_ros pipeline: (simulated) fluxgates, driver, calibration and corrector.

Usage (on a ROS 2 Jazzy install, after ``colcon build``)::

    ros2 launch magcal_ros magcal.launch.py                 # with the simulated array
    ros2 launch magcal_ros magcal.launch.py use_sim:=false  # real fluxgates on serial ports

All nodes run in the namespace given by ``namespace`` (default ``magcal``), each with its
parameters from ``share/magcal_ros/config/<node>.yaml``. Then, for example::

    ros2 service call /magcal/calibration/start std_srvs/srv/Trigger
    ros2 service call /magcal/calibration/calibrate std_srvs/srv/Trigger
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = 'magcal_ros'

#: (executable, parameter file in share/magcal_ros/config, started only with use_sim:=true)
NODES = (
    ('fluxgate_sim', 'sim.yaml', True),
    ('fluxgate_driver', 'driver.yaml', False),
    ('calibration_node', 'calibration.yaml', False),
    ('corrector_node', 'corrector.yaml', False),
)


def generate_launch_description():
    """Return the launch description of the four nodes."""
    config_dir = os.path.join(get_package_share_directory(PACKAGE), 'config')
    use_sim = LaunchConfiguration('use_sim')
    namespace = LaunchConfiguration('namespace')
    actions = [
        DeclareLaunchArgument(
            'use_sim', default_value='true',
            description='start fluxgate_sim (simulated fluxgates on pseudo-terminals '
                        '/tmp/magcal_sim/fluxgate1..4); false for real serial devices'),
        DeclareLaunchArgument(
            'namespace', default_value='magcal',
            description='ROS namespace of all nodes (topics sensor{j}/raw, calibration/*, ...)'),
    ]
    for executable, config, sim_only in NODES:
        actions.append(Node(
            package=PACKAGE,
            executable=executable,
            namespace=namespace,
            parameters=[os.path.join(config_dir, config)],
            output='screen',
            condition=IfCondition(use_sim) if sim_only else None,
        ))
    return LaunchDescription(actions)
