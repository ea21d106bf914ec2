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
Diagnostics of the nodes on ``/diagnostics``: ROS 2's ``diagnostic_updater``, or a shim of it.

Every node publishes its health through an :data:`Updater` (``Updater(node, period)``,
``setHardwareID``, ``add(name, callback)``, ``force_update``), whose tasks fill a
:data:`DiagnosticStatusWrapper` (``summary``, ``add``, ``mergeSummary``). When the ROS
package ``diagnostic_updater`` is importable (a ROS install with
``ros-jazzy-diagnostic-updater``), these names are its classes; otherwise (the pip wheels
of this environment have no ``diagnostic_updater``) they are :class:`FallbackUpdater` and
:class:`FallbackStatusWrapper` below, which publish the same ``DiagnosticArray`` for the
same callbacks:

- one ``DiagnosticStatus`` per task, in the order the tasks were added, named
  ``<node name>: <task name>``, ``hardware_id`` set by ``setHardwareID`` unless the task
  sets its own, header stamp from the node's clock;
- before its callback runs, a task's status is ERROR with the message
  ``No message was set``;
- ``add`` publishes one status ``Node starting up`` (OK) for the new task at once;
- the period is the read-only parameter ``diagnostic_updater.period`` (s), declared with
  the node's own period as its default.

The shim publishes with a history depth of 10 (``diagnostic_updater`` uses 1), so a slow
subscriber does not miss a status; the messages are the same.
"""

import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor

#: name of the parameter holding the publishing period (as ``diagnostic_updater`` names it)
PERIOD_PARAMETER = 'diagnostic_updater.period'


def _level(level):
    """Return a ``DiagnosticStatus`` level as the message's one-byte value (int or bytes in)."""
    if isinstance(level, (bytes, bytearray)):
        return bytes(level[:1])
    return bytes([int(level)])


class FallbackStatusWrapper(DiagnosticStatus):
    """A ``DiagnosticStatus`` with ``diagnostic_updater``'s helpers (used without it)."""

    def summary(self, *args):
        """
        Set the level and message, from a level and a message or from a status.

        Parameters
        ----------
        *args
            Either a ``DiagnosticStatus`` whose level and message are copied, or a level
            (``DiagnosticStatus.OK`` ... ``STALE``) and a message.

        """
        level, message = _level_and_message(args)
        self.level = level
        self.message = message

    def clearSummary(self):  # noqa: N802 (diagnostic_updater's name)
        """Set the level to OK and the message to ''."""
        self.summary(DiagnosticStatus.OK, '')

    def mergeSummary(self, *args):  # noqa: N802 (diagnostic_updater's name)
        """
        Merge a level and message into this summary (arguments as :meth:`summary`).

        The level becomes the higher of the two. When both are OK or both are not OK, the
        messages are joined with ``'; '``; otherwise the message of the higher level is
        kept.

        """
        level, message = _level_and_message(args)
        if (level > DiagnosticStatus.OK) == (self.level > DiagnosticStatus.OK):
            self.message = f'{self.message}; {message}' if self.message else message
        elif level > self.level:
            self.message = message
        if level > self.level:
            self.level = level

    def add(self, key, value):
        """Append the key-value pair ``key``: ``str(value)``."""
        self.values.append(KeyValue(key=str(key), value=str(value)))


def _level_and_message(args):
    if len(args) == 1:
        return _level(args[0].level), args[0].message
    if len(args) == 2:
        return _level(args[0]), str(args[1])
    raise TypeError(f'expected (status) or (level, message), got {len(args)} arguments')


class FallbackUpdater:
    """
    Publish the status of named tasks on ``/diagnostics`` periodically (used without it).

    Parameters
    ----------
    node : rclpy.node.Node
        Node that publishes; statuses are named ``<node name>: <task name>``.
    period : float, optional
        Publishing period, s (default of the parameter ``diagnostic_updater.period``).

    """

    def __init__(self, node, period=1.0):
        self.node = node
        self.hwid = ''
        self.verbose = False
        self._tasks = []
        self._lock = threading.Lock()
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        if node.has_parameter(PERIOD_PARAMETER):
            self._period = node.get_parameter(PERIOD_PARAMETER).value
        else:
            self._period = node.declare_parameter(PERIOD_PARAMETER, float(period),
                                                  ParameterDescriptor(
                description='period of the status on /diagnostics, s', read_only=True)).value
        self.timer = node.create_timer(self._period, self.update)

    @property
    def period(self):
        """Return the publishing period, s."""
        return self._period

    def setHardwareID(self, hwid):  # noqa: N802 (diagnostic_updater's name)
        """Set the ``hardware_id`` of every status (a task may still set its own)."""
        self.hwid = str(hwid)

    def add(self, *args):
        """
        Add a task, given as a name and a callback or as a task object.

        ``callback(stat)`` fills the :class:`FallbackStatusWrapper` ``stat`` and returns it;
        a task object has ``getName()`` and ``run(stat)``. Publishes ``Node starting up``
        for the new task at once.

        """
        if len(args) == 1:
            name, fn = args[0].getName(), args[0].run
        elif len(args) == 2:
            name, fn = args
        else:
            raise TypeError(f'add(name, callback) or add(task), got {len(args)} arguments')
        with self._lock:
            self._tasks.append((name, fn))
        stat = FallbackStatusWrapper(name=name)
        stat.summary(DiagnosticStatus.OK, 'Node starting up')
        self.publish(stat)

    def removeByName(self, name):  # noqa: N802 (diagnostic_updater's name)
        """Remove the first task called ``name``; return whether there was one."""
        with self._lock:
            for k, (task_name, _) in enumerate(self._tasks):
                if task_name == name:
                    del self._tasks[k]
                    return True
        return False

    def update(self):
        """Run every task and publish their statuses in one ``DiagnosticArray``."""
        statuses = []
        with self._lock:
            tasks = list(self._tasks)
        for name, fn in tasks:
            stat = FallbackStatusWrapper(name=name, hardware_id=self.hwid,
                                         message='No message was set')
            stat.level = DiagnosticStatus.ERROR
            stat = fn(stat)
            statuses.append(stat)
            if self.verbose and stat.level != DiagnosticStatus.OK:
                self.node.get_logger().warning(
                    f'non-zero diagnostic status {stat.name}: {stat.message}')
        self.publish(statuses)

    def force_update(self):
        """Publish the tasks' statuses now (e.g. right after a state change)."""
        self.update()

    def broadcast(self, level, message):
        """Publish ``level`` and ``message`` as the status of every task."""
        statuses = []
        with self._lock:
            names = [name for name, _ in self._tasks]
        for name in names:
            stat = FallbackStatusWrapper(name=name)
            stat.summary(level, message)
            statuses.append(stat)
        self.publish(statuses)

    def publish(self, statuses):
        """Publish one status or a list of them, each named ``<node name>: <name>``."""
        if not isinstance(statuses, list):
            statuses = [statuses]
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        for stat in statuses:
            arr.status.append(DiagnosticStatus(
                level=_level(stat.level), name=f'{self.node.get_name()}: {stat.name}',
                message=stat.message, hardware_id=stat.hardware_id, values=list(stat.values)))
        self.publisher.publish(arr)


try:
    from diagnostic_updater import DiagnosticStatusWrapper, Updater
    #: where :data:`Updater` comes from: 'diagnostic_updater' or 'magcal_ros shim'
    SOURCE = 'diagnostic_updater'
except ImportError:
    DiagnosticStatusWrapper, Updater = FallbackStatusWrapper, FallbackUpdater
    SOURCE = 'magcal_ros shim'


def fill(stat, status):
    """
    Copy level, message, hardware_id and values of ``status`` into the task's ``stat``.

    For nodes that build their ``DiagnosticStatus`` in a public method (tests and
    in-process users read it) and publish it through an :data:`Updater` task.

    Returns
    -------
    DiagnosticStatusWrapper
        ``stat``, as an updater callback returns it.

    """
    stat.summary(status)
    stat.hardware_id = status.hardware_id
    stat.values = list(status.values)
    return stat
