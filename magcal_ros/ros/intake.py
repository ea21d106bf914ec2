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
Sensor streams of a node that must spin on the SingleThreadedExecutor, taken cheaply.

The calibration node's coroutine services need the SingleThreadedExecutor, whose wait set
costs most of its CPU (BENCHMARKS.md). :class:`Intake` takes the streams on an EventsExecutor
thread, through a hidden helper node (``_`` name, the topic names the node resolves: the
interface is unchanged); a timer of the node (every :data:`DRAIN_PERIOD_S`, or at once when
:data:`DRAIN_AT` wait) hands them to the node's callbacks on its executor, in arrival order
across topics. Without the EventsExecutor the subscriptions are the node's own.
"""
import collections
import threading

from magcal_ros.ros.run import make_executor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter

#: longest wait of a queued message for the node's callbacks, s: every wake rebuilds the
#: executor's wait set, so fewer wakes cost less CPU
DRAIN_PERIOD_S = 0.05
#: this many queued messages wake the node's executor at once (a burst is not held back)
DRAIN_AT = 32
#: most messages held for the node's callbacks (beyond: dropped and counted); 60 s of 8
#: sensors at 100 Hz with their temperatures
MAX_QUEUED = 100_000
#: longest spin of the intake thread before it looks whether it should stop, s
_SPIN_S = 0.1


class Intake:
    """
    Subscriptions of ``node`` taken on an EventsExecutor thread, delivered on its executor.

    ``threaded``: the streams are taken on the thread (else they are plain subscriptions of
    ``node``); ``dropped``: messages dropped because :data:`MAX_QUEUED` were waiting.
    """

    def __init__(self, node):
        self._node = node
        self._queue = collections.deque()
        self.dropped = 0
        self._stop = threading.Event()
        self._thread = self._helper = None
        executor, kind = make_executor(context=node.context)
        self.threaded = kind == 'events'
        if not self.threaded:
            executor.shutdown(timeout_sec=0.0)
            self._executor = None
            return
        self._executor = executor
        self._helper = Node(
            f'_{node.get_name()}_intake', namespace=node.get_namespace(),
            context=node.context, use_global_arguments=False, enable_rosout=False,
            start_parameter_services=False,
            parameter_overrides=[Parameter('start_type_description_service',
                                           Parameter.Type.BOOL, False)])
        self._timer = node.create_timer(DRAIN_PERIOD_S, self.drain)
        self._wake = node.create_guard_condition(self.drain)

    def subscribe(self, msg_type, topic, callback, qos):
        """Subscribe ``callback`` (called on the node's executor) to ``topic``."""
        if not self.threaded:
            return self._node.create_subscription(msg_type, topic, callback, qos)
        queue, wake = self._queue, self._wake

        def take(msg):
            n = len(queue)
            if n >= MAX_QUEUED:
                self.dropped += 1
                return
            queue.append((callback, msg))
            if n + 1 == DRAIN_AT:
                wake.trigger()
        return self._helper.create_subscription(
            msg_type, self._node.resolve_topic_name(topic), take, qos)

    def start(self):
        """Start taking messages (after the last :meth:`subscribe`)."""
        if not self.threaded or self._thread is not None:
            return
        self._executor.add_node(self._helper)
        self._thread = threading.Thread(target=self._spin, name='magcal_intake', daemon=True)
        self._thread.start()

    def _spin(self):
        context = self._node.context
        try:
            while not self._stop.is_set() and context.ok():
                self._executor.spin_once(timeout_sec=_SPIN_S)
        except ExternalShutdownException:       # the context was shut down under it
            pass

    def drain(self):
        """Hand the queued messages to their callbacks, oldest first (the node's timer)."""
        queue = self._queue
        for _ in range(len(queue)):
            callback, msg = queue.popleft()
            callback(msg)

    def destroy(self):
        """Stop the thread and destroy the helper node (from the node's destroy_node)."""
        if not self.threaded:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._executor.remove_node(self._helper)
        self._executor.shutdown(timeout_sec=1.0)
        self._helper.destroy_node()
        self._queue.clear()
