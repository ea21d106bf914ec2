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
magcal_ros.ros.intake: the calibration node's streams taken on an EventsExecutor thread.

What must hold: the callbacks run on the node's own executor thread (never on the intake
thread), in the order the messages were published across topics; the helper node is hidden,
in the node's namespace, and subscribes to the names the node resolves (its remaps); the
thread ends with the node; ``MAGCAL_EXECUTOR=single`` gives the node plain subscriptions.
And the calibration node's solve thread runs at a lower CPU priority than the rest.
"""
import os
import sys
import threading
import time

from magcal_ros.ros import intake, run
from magcal_ros.ros.intake import Intake
import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from ros_helpers import spin_until
from std_msgs.msg import Float64, Int32

RELIABLE = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)


def _pair(make_node, ros_node, ros_executor, **intake_kwargs):
    """Make a node with an Intake of topics a and b, and publishers of them on ros_node."""
    node = make_node('intake_owner')
    got = []
    threads = set()

    def cb(tag):
        def f(msg):
            threads.add(threading.get_ident())
            got.append((tag, msg.data))
        return f
    take = Intake(node, **intake_kwargs)
    take.subscribe(Int32, 'a', cb('a'), RELIABLE)
    take.subscribe(Float64, 'b', cb('b'), RELIABLE)
    take.start()
    pubs = ros_node.create_publisher(Int32, 'a', RELIABLE), \
        ros_node.create_publisher(Float64, 'b', RELIABLE)
    spin_until(ros_executor, lambda: all(p.get_subscription_count() for p in pubs), 10.0,
               'the intake subscriptions')
    return node, take, pubs, got, threads


def test_callbacks_run_on_the_node_executor_in_publication_order(make_node, ros_node,
                                                                 ros_executor):
    node, take, (pa, pb), got, threads = _pair(make_node, ros_node, ros_executor)
    assert take.threaded
    # in the graph under the node's namespace, hidden (a leading '_': ros2 node list --all)
    helper = '_intake_owner_intake'
    spin_until(ros_executor, lambda: helper in dict(node.get_node_names_and_namespaces()),
               10.0, 'the helper node in the graph')
    assert dict(node.get_node_names_and_namespaces())[helper] == node.get_namespace()
    # interleaved: a0 b0 a1 b1 ... (each published after the previous one was taken, so the
    # order of arrival is the order of publication)
    expected = []
    for k in range(50):
        pa.publish(Int32(data=k))
        expected.append(('a', k))
        spin_until(ros_executor, lambda: len(got) >= len(expected) or take._queue, 5.0,
                   'the message queued')
        pb.publish(Float64(data=float(k)))
        expected.append(('b', float(k)))
        spin_until(ros_executor, lambda: len(got) >= len(expected), 5.0, 'the message')
    assert got == expected
    # every callback ran on this thread: the one spinning ros_executor (the node's)
    assert threads == {threading.get_ident()}
    assert take.dropped == 0


def test_a_burst_keeps_its_order_and_the_queue_is_bounded(make_node, ros_node, ros_executor,
                                                          monkeypatch):
    node, take, (pa, pb), got, _ = _pair(make_node, ros_node, ros_executor)
    for k in range(300):               # while the node's executor does not spin
        pa.publish(Int32(data=k))
    spin_until(ros_executor, lambda: len(got) >= 300, 10.0, 'the burst')
    assert [v for _, v in got] == list(range(300))
    # at most MAX_QUEUED wait for the node; the rest is counted, not held
    monkeypatch.setattr(intake, 'MAX_QUEUED', 10)
    got.clear()
    take._timer.cancel()               # the node's executor "stalled"
    for k in range(40):
        pa.publish(Int32(data=k))
    deadline = time.monotonic() + 10.0
    while take.dropped + len(take._queue) < 40 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(take._queue) == 10 and take.dropped == 30
    take.drain()
    assert [v for _, v in got] == list(range(10))


def test_helper_follows_the_node_remaps_not_a_node_rename(ros_namespace):
    """A process remap of a topic reaches the helper; a ``__node`` rename does not."""
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO,
               args=['prog', '--ros-args', '-r', '__node:=renamed', '-r', 'a:=moved_a'])
    try:
        node = Node('owner', namespace=ros_namespace, context=context)
        assert node.get_name() == 'renamed'
        take = Intake(node)
        sub = take.subscribe(Int32, 'a', lambda msg: None, RELIABLE)
        assert sub.topic_name == f'{ros_namespace}/moved_a'
        assert take._helper.get_name() == '_renamed_intake'
        assert take._helper.get_namespace() == ros_namespace
        take.start()
        take.destroy()
        assert not take._thread.is_alive()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_without_the_events_executor_the_node_subscribes_itself(make_node, ros_node,
                                                                ros_executor, monkeypatch):
    monkeypatch.setenv('MAGCAL_EXECUTOR', 'single')
    node, take, (pa, pb), got, threads = _pair(make_node, ros_node, ros_executor)
    assert not take.threaded and take._helper is None
    assert [s.topic_name for s in node.subscriptions] == [
        f'{node.get_namespace()}/a', f'{node.get_namespace()}/b']
    pa.publish(Int32(data=7))
    spin_until(ros_executor, lambda: got, 5.0, 'the message')
    assert got == [('a', 7)]


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='per-thread niceness: Linux')
def test_solve_thread_yields_the_cpu_and_only_it():
    base = os.getpriority(os.PRIO_PROCESS, 0)
    seen = {}

    def work():
        run.yield_cpu()
        seen['solve'] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen['solve'] == min(19, base + run.SOLVE_NICENESS)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == base
