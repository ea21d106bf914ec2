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
``fluxgate_driver``: serial fluxgates -> ``sensor{j}/raw`` (tesla), temperature, diagnostics.

One :class:`~magcal_ros.serial.transport.PortReader` thread per sensor reads and parses its
port (:mod:`magcal_ros.serial`); this node maps the device axes to the sensor frame and
publishes ``sensor{j}/raw`` (T, covariance diag(noise_nt^2) in T^2, reliable, stamped with the
bytes' arrival on the ROS clock), ``sensor{j}/temperature`` (degC) when the device reports it,
and per port a ``/diagnostics`` status ``fluxgate_driver: sensor{j}``. A lost port is reopened
with exponential backoff (optionally at alternative paths); the others keep publishing. The
defaults (namespace ``/magcal``, four sensors on ``/tmp/magcal_sim/fluxgate1..4``, ASCII) are
what ``fluxgate_sim`` provides. Parameters (``ros2 param describe``): global defaults, and
per sensor, flat, ``sensor{j}.<name>``, each defaulting to the global one.
"""

from dataclasses import dataclass, replace
import logging
import math
import os
import re
import sys
import threading

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from magcal_ros.ros import params as prm
from magcal_ros.ros.conversions import field_nt_to_msg, temperature_msg
from magcal_ros.ros.diagnostics import fill, Updater
from magcal_ros.ros.run import DEFAULT_NAMESPACE, spin_node
from magcal_ros.serial import make_parser, parse_options, PROTOCOLS, transport
from magcal_ros.serial.transport import PortReader, STATE_OPEN
from magcal_ros.sim import device_dir
from rcl_interfaces.msg import SetParametersResult
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField, Temperature

NODE_NAME = 'fluxgate_driver'
#: the links of ``fluxgate_sim`` in the default namespace (``/tmp/magcal_sim/fluxgate{j}``
#: unless TMPDIR is set); in another namespace those of the simulator in that namespace
DEFAULT_PORT = os.path.join(device_dir(), 'fluxgate{j}')
AXES = ('x', 'y', 'z')

#: Sensor streams: reliable (REP 2003), deep enough for 1 kHz bursts.
SENSOR_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.RELIABLE)


# -- pure settings (no Node) -----------------------------------------------------------------

@dataclass(frozen=True)
class SensorSettings:
    """Settings of one sensor, converted once from the parameters (units in the names)."""

    index: int
    port: str
    alternatives: tuple
    baud: int
    protocol: str
    options: dict
    axes: tuple
    frame_id: str
    noise_nt: float
    expected_rate_hz: float


def parse_axes(axes):
    """Turn e.g. ``['-y', 'x', 'z']`` into ((device index, sign), ...) or raise ValueError."""
    axes = list(axes)
    if len(axes) != 3:
        raise ValueError(f'axes must list 3 device axes, e.g. ["x", "-z", "y"], got {axes}')
    out = []
    for a in axes:
        a = str(a).strip().lower()
        sign = -1.0 if a.startswith('-') else 1.0
        name = a.lstrip('+-')
        if name not in AXES:
            raise ValueError(f'axes entries must be x, y or z with an optional sign, got {a!r}')
        out.append((AXES.index(name), sign))
    if sorted(i for i, _ in out) != [0, 1, 2]:
        raise ValueError(f'axes must use each device axis once, got {axes}')
    return tuple(out)


def map_axes(field_nt, mapping):
    """Apply a :func:`parse_axes` mapping: sensor axis i = sign_i * device axis k_i (nT)."""
    return tuple(sign * field_nt[k] for k, sign in mapping)


def check_sensor(s):
    """Validate a :class:`SensorSettings`; return the reason it is refused, or None."""
    if not s.port.strip():
        return f'sensor{s.index}.port: missing device path (e.g. /dev/ttyUSB0)'
    if s.baud <= 0:
        return f'sensor{s.index}.baud: must be a positive baud rate in bit/s, got {s.baud}'
    if s.protocol not in PROTOCOLS:
        return (f'sensor{s.index}.protocol: unknown protocol {s.protocol!r}; choose one of '
                f'{sorted(PROTOCOLS)}')
    if not (math.isfinite(s.noise_nt) and s.noise_nt >= 0):
        return f'sensor{s.index}.noise_nt: must be a finite noise sd >= 0 nT, got {s.noise_nt}'
    if not (math.isfinite(s.expected_rate_hz) and s.expected_rate_hz >= 0):
        return (f'sensor{s.index}.expected_rate_hz: must be a rate >= 0 Hz (0: unknown), got '
                f'{s.expected_rate_hz}')
    try:
        parse_axes(s.axes)
        make_parser(s.protocol, **s.options)
    except ValueError as exc:
        return f'sensor{s.index}: {exc}'
    return None


def diagnostic_status(settings, stats, previous_errors=0, previous=None):
    """
    Build the ``DiagnosticStatus`` of one port from a ``PortStats`` snapshot.

    ERROR when the port is not open; WARN on parse errors since ``previous_errors``, on bytes
    without one valid frame since the ``previous`` snapshot (wrong protocol, options or baud:
    a binary parser only drops them), or a rate below half ``expected_rate_hz``; else OK.
    """
    level = DiagnosticStatus.WARN
    if stats.state != STATE_OPEN:
        level = DiagnosticStatus.ERROR
        message = f'port {stats.state}: {stats.last_error or "not open yet"}'
    elif stats.parse_errors > previous_errors:
        message = f'{stats.parse_errors - previous_errors} parse errors'
    elif (previous is not None and stats.bytes_in > previous.bytes_in
          and stats.samples == previous.samples):
        message = (f'{stats.bytes_in - previous.bytes_in} bytes but no valid frame since the '
                   'last report (wrong protocol, options or baud rate?)')
    elif settings.expected_rate_hz > 0 and stats.rate_hz < 0.5 * settings.expected_rate_hz:
        message = (f'rate {stats.rate_hz:.1f} Hz below half the expected '
                   f'{settings.expected_rate_hz:g} Hz')
    else:
        level, message = DiagnosticStatus.OK, f'open, {stats.rate_hz:.1f} Hz'
    values = [('state', stats.state), ('path', stats.path or ''),
              ('protocol', settings.protocol), ('rate_hz', f'{stats.rate_hz:.2f}'),
              ('samples', stats.samples), ('bytes_in', stats.bytes_in),
              ('parse_errors', stats.parse_errors), ('bytes_dropped', stats.bytes_dropped),
              ('reconnects', stats.reconnects), ('disconnects', stats.disconnects),
              ('open_failures', stats.open_failures),
              ('seconds_since_data', '' if stats.seconds_since_data is None
               else f'{stats.seconds_since_data:.3f}'),
              ('last_error', stats.last_error)]
    values += [(f'errors.{kind}', n) for kind, n in sorted(stats.errors.items())]
    return DiagnosticStatus(name=f'{NODE_NAME}: sensor{settings.index}',
                            hardware_id=settings.port, level=level, message=message,
                            values=[KeyValue(key=k, value=str(v)) for k, v in values])


# -- node ------------------------------------------------------------------------------------

class _RosLogHandler(logging.Handler):
    """Forward the transport's Python log records (reconnects, errors) to the node logger."""

    def __init__(self, ros_logger):
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record):
        # one call site per severity: rclpy refuses a call site whose severity changes
        text = self.format(record)
        if record.levelno >= logging.ERROR:
            self.ros_logger.error(text)
        elif record.levelno >= logging.WARNING:
            self.ros_logger.warning(text)
        else:
            self.ros_logger.info(text)


#: the global parameters (read-only): name, default, description with the unit
_GLOBALS = (
    ('n_sensors', 4, 'number of sensors (parameters sensor1.* .. sensor<n>.*); count'),
    ('protocol', 'ascii',
     f'default serial protocol of every sensor, one of {sorted(PROTOCOLS)}; no unit'),
    ('baud', 115200, 'default baud rate of every port, bit/s'),
    ('options', '', 'default protocol options of every sensor as a YAML mapping, e.g. '
     '"{columns: \'x,y,z,temp,time\', scale: 1.0e5}" (units per option: scale nT per '
     'device unit, time_scale s per unit, max_abs_nt nT)'),
    ('noise_nt', 3.0,
     'default noise standard deviation per axis for the published covariance, nT'),
    ('backoff_min_s', 0.1,
     'first wait before reopening a lost port (doubles after each failure), s'),
    ('backoff_max_s', 5.0, 'longest wait between reopen attempts, s'),
    ('diagnostics_period_s', 1.0, 'period of the /diagnostics status, s'))


class FluxgateDriver(Node):
    """The ``fluxgate_driver`` node (keyword arguments go to ``rclpy.node.Node``)."""

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)
        super().__init__(NODE_NAME, **kwargs)
        self._lock = threading.Lock()
        self.readers = []
        prm.declare(self, [prm.ParamSpec(*g, read_only=True) for g in _GLOBALS])
        n = self.get_parameter('n_sensors').value
        if n < 1:
            raise ValueError(f'n_sensors must be >= 1, got {n}')
        self.sensors = [self._declare_sensor(j) for j in range(1, n + 1)]
        for s in self.sensors:
            reason = check_sensor(s)
            if reason:
                raise ValueError(reason)
        self._check_global_values()
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._raw_pubs = [self.create_publisher(MagneticField, f'sensor{s.index}/raw',
                                                SENSOR_QOS) for s in self.sensors]
        self._temp_pubs = [self.create_publisher(Temperature, f'sensor{s.index}/temperature',
                                                 SENSOR_QOS) for s in self.sensors]
        self._mappings = [parse_axes(s.axes) for s in self.sensors]
        self._last_errors = [0] * n
        self._last_stats = [None] * n
        self._log_handler = _RosLogHandler(self.get_logger())
        logging.getLogger(transport.__name__).addHandler(self._log_handler)
        logging.getLogger(transport.__name__).setLevel(logging.INFO)
        self.readers = [PortReader(
            s.port, s.baud, make_parser(s.protocol, **s.options), self._make_callback(k),
            alternatives=s.alternatives, backoff_min=self.get_parameter('backoff_min_s').value,
            backoff_max=self.get_parameter('backoff_max_s').value, name=f'sensor{s.index}',
            clock=self._now) for k, s in enumerate(self.sensors)]
        for reader, s in zip(self.readers, self.sensors):
            reader.start()
            self.get_logger().info(f'sensor{s.index}: {s.protocol} on {s.port} at {s.baud} '
                                   f'baud -> {self.get_namespace().rstrip("/")}/sensor'
                                   f'{s.index}/raw')
        # one status per port (hardware_id: its device path); the array's is the namespace
        self._updater = Updater(self, self.get_parameter('diagnostics_period_s').value)
        self._updater.setHardwareID(self.get_namespace())
        for k, s in enumerate(self.sensors):
            self._updater.add(f'sensor{s.index}', self._port_task(k))

    # -- parameters --------------------------------------------------------------------------
    def _check_global_values(self):
        def num(name):
            return self.get_parameter(name).value
        for name in ('backoff_min_s', 'backoff_max_s', 'diagnostics_period_s'):
            if not (math.isfinite(num(name)) and num(name) > 0):
                raise ValueError(f'{name} must be a finite time > 0 s, got {num(name)}')
        if num('backoff_max_s') < num('backoff_min_s'):
            raise ValueError(f'backoff_max_s ({num("backoff_max_s")}) must be >= '
                             f'backoff_min_s ({num("backoff_min_s")})')

    def _declare_sensor(self, j):
        g = self.get_parameter
        specs = (   # name, default, description, read-only
            ('port', os.path.join(device_dir(self.get_namespace()), f'fluxgate{j}'),
             'serial device path (a missing device is retried with backoff); no unit', True),
            ('alternatives', (), 'glob patterns of other device paths to try when port is '
             'gone (e.g. /dev/serial/by-id/*FTDI*); no unit', True),
            ('baud', g('baud').value, 'baud rate, bit/s (default: the global baud)', True),
            ('protocol', g('protocol').value,
             'serial protocol (default: the global protocol); no unit', True),
            ('options', g('options').value,
             'protocol options as a YAML mapping (default: the global options)', True),
            ('axes', AXES, 'device axis (optionally signed) giving sensor x, y, z, e.g. '
             '[-y, x, z]; no unit', True),
            ('frame_id', f'fluxgate{j}', 'header frame_id of sensor{j}/raw and temperature; '
             'no unit', True),
            ('noise_nt', g('noise_nt').value, 'noise standard deviation per axis for the '
             'covariance, nT (default: the global noise_nt)', False),
            ('expected_rate_hz', 0.0, 'expected sample rate for the diagnostics warning, Hz '
             '(0: not checked)', False))
        prm.declare(self, [prm.ParamSpec(f'sensor{j}.{name}', default, text, read_only=ro)
                           for name, default, text, ro in specs])
        values = {name: prm.value(self, f'sensor{j}.{name}') for name, *_ in specs}
        try:
            options = parse_options(values['options'])
        except ValueError as exc:
            raise ValueError(f'sensor{j}.options: {exc}') from None
        return SensorSettings(
            index=j, port=values['port'], alternatives=tuple(values['alternatives'] or ()),
            baud=int(values['baud']), protocol=values['protocol'], options=options,
            axes=tuple(values['axes']), frame_id=values['frame_id'],
            noise_nt=float(values['noise_nt']),
            expected_rate_hz=float(values['expected_rate_hz']))

    def _on_set_parameters(self, params):
        updated = list(self.sensors)
        for param in params:
            m = re.fullmatch(r'sensor(\d+)\.(noise_nt|expected_rate_hz)', param.name)
            if m is None or not 0 < int(m[1]) <= len(updated):
                continue
            if not isinstance(param.value, (int, float)):
                return SetParametersResult(successful=False,
                                           reason=f'{param.name}: must be a number')
            k = int(m[1]) - 1
            updated[k] = replace(updated[k], **{m[2]: float(param.value)})
            reason = check_sensor(updated[k])
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        with self._lock:
            self.sensors = updated
        return SetParametersResult(successful=True)

    # -- data path (reader threads) ----------------------------------------------------------
    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _make_callback(self, k):
        raw_pub, temp_pub, mapping = self._raw_pubs[k], self._temp_pubs[k], self._mappings[k]

        def on_sample(sample, arrival):
            if not self.context.ok():
                return          # shutting down: the readers are being stopped
            s = self.sensors[k]
            msg = field_nt_to_msg(map_axes(sample.field_nt, mapping), stamp=arrival,
                                  frame_id=s.frame_id, covariance_nt2=s.noise_nt ** 2)
            try:
                raw_pub.publish(msg)
                if sample.temp_c is not None:
                    temp_pub.publish(temperature_msg(sample.temp_c, stamp=msg.header.stamp,
                                                     frame_id=s.frame_id))
            except _rclpy.RCLError:
                if self.context.ok():
                    raise
                # SIGINT shut the context down between the check above and publish()
        return on_sample

    # -- diagnostics -------------------------------------------------------------------------
    def _port_task(self, k):
        """Return the updater task of sensor k + 1: its port's status since the last report."""
        def task(stat):
            stats = self.readers[k].stats()
            status = diagnostic_status(self.sensors[k], stats, self._last_errors[k],
                                       self._last_stats[k])
            self._last_errors[k] = stats.parse_errors
            self._last_stats[k] = stats
            return fill(stat, status)
        return task

    def port_stats(self):
        """Return the ``PortStats`` of every sensor (index 0 is sensor 1)."""
        return [r.stats() for r in self.readers]

    def destroy_node(self):
        """Stop the reader threads, then destroy the node."""
        for reader in self.readers:
            reader.stop()
        if self.readers:
            logging.getLogger(transport.__name__).removeHandler(self._log_handler)
        return super().destroy_node()


def main(args=None):
    """Console script ``fluxgate_driver`` (Jazzy style)."""
    return spin_node(FluxgateDriver, NODE_NAME, args)


if __name__ == '__main__':
    sys.exit(main())
