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

The nodes use :data:`Updater` (``Updater(node, period)``, ``setHardwareID``, ``add(name,
callback)``, ``force_update``), :func:`node_status` and :func:`fill`. Without
``diagnostic_updater`` (no pip wheel) these are :class:`FallbackUpdater` and
:class:`FallbackStatusWrapper`, publishing the same ``DiagnosticArray`` (a status per task in
the order added, named ``<node>: <task>``, ERROR ``No message was set`` before the callback,
``Node starting up`` on ``add``, the period the read-only parameter
``diagnostic_updater.period``, s) with a history depth of 10 (``diagnostic_updater``'s 1).
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


def _level_and_message(args):
    if len(args) == 1:
        return _level(args[0].level), args[0].message
    if len(args) == 2:
        return _level(args[0]), str(args[1])
    raise TypeError(f'expected (status) or (level, message), got {len(args)} arguments')


class FallbackStatusWrapper(DiagnosticStatus):
    """A ``DiagnosticStatus`` with ``diagnostic_updater``'s helpers (used without it)."""

    def summary(self, *args):
        """Set the level and message: from a ``DiagnosticStatus``, or a level and a message."""
        self.level, self.message = _level_and_message(args)

    def clearSummary(self):  # noqa: N802 (diagnostic_updater's name)
        """Set the level to OK and the message to ''."""
        self.summary(DiagnosticStatus.OK, '')

    def mergeSummary(self, *args):  # noqa: N802 (diagnostic_updater's name)
        """
        Merge a level and message into this summary (arguments as :meth:`summary`).

        The level becomes the higher of the two. When both are OK or both are not OK, the
        messages are joined with ``'; '``; otherwise the message of the higher level is kept.
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


class FallbackUpdater:
    """Publish the status of named tasks on ``/diagnostics`` every ``period`` s (the shim)."""

    def __init__(self, node, period=1.0):
        self.node = node
        self.hwid = ''
        self._tasks = []
        self._lock = threading.Lock()
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        if node.has_parameter(PERIOD_PARAMETER):
            period = node.get_parameter(PERIOD_PARAMETER).value
        else:
            period = node.declare_parameter(PERIOD_PARAMETER, float(period), ParameterDescriptor(
                description='period of the status on /diagnostics, s', read_only=True)).value
        self.timer = node.create_timer(period, self.update)

    def setHardwareID(self, hwid):  # noqa: N802 (diagnostic_updater's name)
        """Set the ``hardware_id`` of every status (a task may still set its own)."""
        self.hwid = str(hwid)

    def add(self, name, fn):
        """Add task ``name``: ``fn(stat)`` fills the status ``stat`` and returns it."""
        with self._lock:
            self._tasks.append((name, fn))
        self.publish([FallbackStatusWrapper(name=name, level=DiagnosticStatus.OK,
                                            message='Node starting up')])

    def update(self):
        """Run every task and publish their statuses in one ``DiagnosticArray``."""
        with self._lock:
            tasks = list(self._tasks)
        self.publish([fn(FallbackStatusWrapper(name=name, hardware_id=self.hwid,
                                               level=DiagnosticStatus.ERROR,
                                               message='No message was set'))
                      for name, fn in tasks])

    force_update = update

    def publish(self, statuses):
        """Publish a list of statuses, each named ``<node name>: <name>``."""
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


class EffectErrorsMixin:
    """The nodes' account of errors of effect code, in their ``self._effect_errors``."""

    def _effect_error(self, exc, what):
        """Count an error of effect code (:class:`EffectError`); log the first per effect."""
        if self._effect_errors.add(exc, what):
            self.get_logger().error(f'{exc} ({what}); further errors of it are counted on '
                                    '/diagnostics, not logged')

    def _effect_error_values(self):
        """Return the status key-value pairs of the effect errors: the total, then per effect."""
        counts = self._effect_errors.counts()
        return [('effect_errors', str(sum(counts.values())))] + [
            (f'effect_errors {k}', str(n)) for k, n in counts.items()]


def node_status(node, task, level, message, values=()):
    """
    Return the ``DiagnosticStatus`` ``<node name>: <task>`` of ``node`` (a ``Node``).

    ``hardware_id`` the node's namespace; ``values`` (key, value) pairs, each value as str.
    """
    return DiagnosticStatus(name=f'{node.get_name()}: {task}', hardware_id=node.get_namespace(),
                            level=level, message=message,
                            values=[KeyValue(key=k, value=str(v)) for k, v in values])


def fill(stat, status):
    """Copy level, message, hardware_id and values of ``status`` into the task's ``stat``."""
    stat.summary(status)
    stat.hardware_id = status.hardware_id
    stat.values = list(status.values)
    return stat
