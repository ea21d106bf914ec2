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
Feed simulated array samples to in-process nodes (tests of the calibration/corrector nodes).

The core simulator (:mod:`magcal_ros.core.data.simulate`) provides raw readings with known truth;
they are published as ``sensor{j}/raw`` (tesla, exact stamps) and ``sensor{j}/temperature``
through :mod:`magcal_ros.ros.conversions`, in small batches, spinning the executor between
batches until the node under test has taken them (its best-effort queues are finite).
"""
import time

from magcal_ros.ros.conversions import field_nt_to_msg, temperature_msg
from magcal_ros.ros.intake import DRAIN_AT
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField, Temperature

#: stamp of the first simulated sample, s (a plausible ROS time)
T0 = 1_700_000_000.0


def intake_batch(n_topics):
    """
    Epochs per batch on ``n_topics`` raw topics that make DRAIN_AT messages.

    The calibration node's intake hands that many queued messages over at once
    (magcal_ros.ros.intake), a smaller batch only at its next drain period (50 ms).
    """
    return -(-DRAIN_AT // n_topics)


class Feeder:
    """Publishers of the four raw and temperature topics of one namespace."""

    def __init__(self, node, n_sensors=4):
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        self.raw = [node.create_publisher(MagneticField, f'sensor{j}/raw', qos)
                    for j in range(1, n_sensors + 1)]
        self.temp = [node.create_publisher(Temperature, f'sensor{j}/temperature', qos)
                     for j in range(1, n_sensors + 1)]

    def wait_for_subscribers(self, executor, timeout_sec=10.0):
        """Spin until every raw publisher has a subscriber."""
        deadline = time.monotonic() + timeout_sec
        while not all(p.get_subscription_count() > 0 for p in self.raw):
            assert time.monotonic() < deadline, 'no subscriber on sensor{j}/raw'
            executor.spin_once(timeout_sec=0.05)

    def publish(self, data, k, temperature=True, latency_s=None):
        """Publish epoch ``k`` of a Dataset (all sensors, same stamp plus ``latency_s[j]``)."""
        stamp = T0 + float(data.t[k])
        for j, pub in enumerate(self.raw):
            late = 0.0 if latency_s is None else float(latency_s[j])
            pub.publish(field_nt_to_msg(data.raw[j, k], stamp=stamp + late,
                                        frame_id=f'fluxgate{j + 1}'))
        if temperature and data.temp is not None:
            for j, pub in enumerate(self.temp):
                pub.publish(temperature_msg(float(data.temp[j, k]), stamp=stamp))

    def feed(self, executor, data, taken, start=0, stop=None, batch=None, timeout_sec=60.0,
             temperature=True, latency_s=None):
        """
        Publish epochs ``start:stop`` in batches; ``taken()`` counts samples consumed.

        ``taken`` returns how many raw samples (all sensors) the node under test has taken
        so far; each batch waits until it has caught up.  The default batch is
        :func:`intake_batch` of the raw topics (8 epochs of the cross: 8 per topic fit the
        nodes' sensor queues, 25 deep).
        """
        batch = batch or intake_batch(len(self.raw))
        stop = data.n_samples if stop is None else stop
        deadline = time.monotonic() + timeout_sec
        base = taken()
        n_sensors = len(self.raw)
        for k0 in range(start, stop, batch):
            k1 = min(k0 + batch, stop)
            for k in range(k0, k1):
                self.publish(data, k, temperature=temperature, latency_s=latency_s)
            want = base + n_sensors * (k1 - start)
            while taken() < want:
                assert time.monotonic() < deadline, (
                    f'the node took {taken() - base} of {want - base} samples')
                executor.spin_once(timeout_sec=0.01)
