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
Relay node: the ceiling rclpy allows for the corrector's message pattern.

Subscribes ``sensor{j}/raw`` exactly as ``corrector_node`` does (sensor_msgs/MagneticField,
``qos_profile_sensor_data``) and republishes every message unchanged on
``sensor{j}/corrected`` (depth 10, as the corrector), spun by ``rclpy.spin`` like the
corrector.  Whatever rate this node sustains is the most any Python node of that shape can
reach on the machine; the corrector's figures are reported as a ratio to it.

    python bench/relay_node.py --ros-args -r __ns:=/bench -p n_sensors:=4
"""
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField


class RelayNode(Node):
    """Republish sensor{j}/raw on sensor{j}/corrected, unchanged."""

    def __init__(self, **kwargs):
        super().__init__('relay_node', **kwargs)
        n = self.declare_parameter('n_sensors', 4).value
        # 0: qos_profile_sensor_data (best effort, depth 5) as the corrector; > 0: reliable
        # with this depth (shows what the QoS choice costs under load)
        depth = self.declare_parameter('reliable_depth', 0).value
        qos = qos_profile_sensor_data if depth <= 0 else QoSProfile(
            depth=depth, history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.RELIABLE)
        self._pubs = [self.create_publisher(MagneticField, f'sensor{j}/corrected', 10)
                      for j in range(1, n + 1)]
        self._subs = [self.create_subscription(MagneticField, f'sensor{j}/raw',
                                               self._pubs[j - 1].publish, qos)
                      for j in range(1, n + 1)]


def main(args=None):
    """Run the relay until interrupted (Jazzy style)."""
    rclpy.init(args=args)
    node = None
    try:
        node = RelayNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
