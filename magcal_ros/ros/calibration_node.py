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
calibration_node: collect rotation data from the live array, calibrate, diagnose.

Topics (relative to the node namespace, default ``/magcal``; docs/design.md §3):

- subscribes ``sensor{j}/raw`` (sensor_msgs/MagneticField, T), ``sensor{j}/temperature``
  (sensor_msgs/Temperature, degC) and one std_msgs/Float64 topic per name in ``aux_topics``
  (recorded as column ``aux_<name>``), all best effort like ``qos_profile_sensor_data``
  (with deeper queues: :data:`CALIBRATION_SENSOR_QOS` for the raw fields, 10 s of 100 Hz,
  so that no sample is lost while a solve keeps the executor busy; :data:`SENSOR_QOS`);
- subscribes ``imu_topic`` (sensor_msgs/Imu, optional): its orientation is the attitude of
  the array (body-to-world), interpolated onto the sets, for the ``site_gradient`` effect;
- publishes ``calibration/status`` (std_msgs/String, JSON, every ``status_period_s``):
  sets collected, attitude coverage per sensor, what is still missing;
- publishes ``calibration/result`` (std_msgs/String holding the calibration YAML of
  docs/design.md §4; reliable, transient local, depth 1): the active calibration;
- publishes ``calibration/residual`` (std_msgs/Float64MultiArray, T; one message per
  matched set while a calibration is active, collecting or not): the active calibration
  applied to the incoming data, per sensor the scalar residual |b_j| - F and the vector
  residual |b_j - mean of the others| (:func:`magcal_ros.ros.conversions.residual_to_msg`;
  ``data[j-1]`` and ``data[S+j-1]`` plot in rqt_plot / PlotJuggler), and on ``/diagnostics``
  their rolling RMS over the noise floor of the data, WARN above
  :data:`magcal_ros.core.live.corrector.RESIDUAL_WARN_RATIO`: the calibration no longer fits,
  time to diagnose (:class:`magcal_ros.core.live.corrector.ResidualMonitor`); ERROR, naming
  the effect and counting its errors, when the code of an effect raised (on a live sample: no
  residual for it; in calibrate or diagnose: that call answers success=false naming the
  effect), logged once per effect.

Services (std_srvs/srv/Trigger; the response message is a short summary, a newline, then
one JSON object):

- ``calibration/start``: clear the buffer and start collecting;
- ``calibration/calibrate``: fit the ``model`` parameter to the collected sets
  (:func:`magcal_ros.pipeline.calibrate`), write ``calibration_file`` atomically (the
  previous one kept) and publish it; refused data leave the previous calibration active;
- ``calibration/diagnose``: rank the candidate effects missing from ``model``
  (:func:`magcal_ros.core.discovery.diagnose`) and write the HTML report to ``report_dir``.

The solve must not block the sensor callbacks. It runs in a worker thread; the service
callbacks are coroutines (in a reentrant callback group) that await it, so the executor
keeps taking sensor samples meanwhile, and a non-blocking lock turns a second
calibrate/diagnose/start during a solve into a clean refusal instead of a queued call. The
node spins on a SingleThreadedExecutor: rclpy's MultiThreadedExecutor was measured here to
receive only about half of the 4 x 100 Hz samples (4 threads) or to run callbacks of one
subscription out of order (2 threads), which breaks the matching of sample sets by stamp.
"""
import json
import math
import os
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist
from magcal_ros.core.data.readings import leave_out_unphysical
from magcal_ros.core.effects.safety import culprit, EffectError, EffectErrors
from magcal_ros.core.geometry.attitude import UNIT_TOLERANCE
from magcal_ros.core.live.consistency import (DEFAULT_MAX_LAG, GROSS_FRACTION, LONG_MAX_LAG,
                                              resync)
from magcal_ros.core.live.corrector import (LiveCorrector, MissingSignal, RESIDUAL_WARN_RATIO,
                                            ResidualMonitor, SampleBuffer)
from magcal_ros.core.live.sync import StampMatcher
from magcal_ros.core.model import DegenerateDataError, Model
from magcal_ros.core.model.identifiability import check_coverage
from magcal_ros.core.model.notes import format_note
from magcal_ros.io.calfile import (CalibrationFileError, dump_calibration, load_calibration,
                                   parse_calibration, save_calibration)
from magcal_ros.pipeline import (array_geometry, calibrate as run_calibration,
                                 geometry_mismatch, tensor_undetermined)
from magcal_ros.ros import params as prm
from magcal_ros.ros.conversions import msg_to_field_nt, residual_to_msg, stamp_to_seconds
from magcal_ros.ros.diagnostics import fill, Updater
from magcal_ros.ros.intake import Intake
from magcal_ros.ros.run import DEFAULT_NAMESPACE, spin_node
import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, qos_profile_sensor_data, QoSProfile,
                       ReliabilityPolicy)
from rclpy.task import Future
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import Float64, Float64MultiArray, String
from std_srvs.srv import Trigger

#: QoS of calibration/result (REP 2003: latched state): a late subscriber gets the last one
RESULT_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: sensor streams: the sensor-data profile of REP 2003 (best effort, volatile) with a queue
#: deep enough for a quarter second of 100 Hz, so that a busy executor does not drop samples
#: (the corrector: it prefers the newest samples to a backlog)
SENSOR_QOS = QoSProfile(depth=25, history=HistoryPolicy.KEEP_LAST,
                        reliability=qos_profile_sensor_data.reliability,
                        durability=qos_profile_sensor_data.durability)

#: the calibration node's sensor streams: the same profile with 10 s of 100 Hz of queue.  A
#: sample dropped from one stream shifts that stream's epoch numbering until the set matcher
#: votes again, and the sets in between are paired tens of epochs off; the calibration node
#: needs every sample, not the newest, and its executor is starved for up to a second while
#: a calibrate or diagnose call holds the interpreter in the worker thread (seen in the
#: end-to-end test: 20-125 sets paired far off in 2 of 4 runs with a 25-deep queue)
CALIBRATION_SENSOR_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                                    reliability=qos_profile_sensor_data.reliability,
                                    durability=qos_profile_sensor_data.durability)

#: at most this many sets enter the coverage figures of the status message
_STATUS_SUBSAMPLE = 2000


#: longest first line of a service reply (``ros2 service call`` prints the whole message
#: on one line with ``\n`` escapes: the first line is what a user reads)
_HEADLINE = 100


def _reply(response, success, summary, payload):
    """
    Fill a Trigger response: a short first line, more lines, newline, one JSON object.

    A long first line is broken after its lead (``not calibrated: <reason>`` becomes
    ``not calibrated:`` and the reason on the next line).
    """
    first, _, rest = summary.strip().partition('\n')
    lead, sep, reason = first.partition(': ')
    if len(first) > _HEADLINE and sep:
        first = lead + ':\n' + reason
    summary = first + ('\n' + rest if rest else '')
    response.success = bool(success)
    response.message = summary + '\n' + json.dumps(payload, sort_keys=False)
    return response


def _fmt_per_sensor(d, fmt='{:.2f}'):
    return ', '.join(f'{k}: {fmt.format(v)}' for k, v in d.items())


def _silent_sensors(received):
    """
    Messages naming the sensors that sent nothing, or far less than the others.

    ``received`` lists the raw samples taken per sensor since calibration/start.
    """
    most = max(received) if received else 0
    out = []
    for j, n in enumerate(received, start=1):
        if n == 0:
            out.append(f'sensor {j} sent no samples since calibration/start: check its driver, '
                       f'cable and the topic sensor{j}/raw')
        elif most >= 100 and n < 0.5 * most:
            out.append(f'sensor {j} sent only {n} samples, the others up to {most}: its data '
                       'are missing for part of the collection (unplugged?)')
    return out


#: niceness added to the solve thread (calibrate, diagnose): on a loaded machine the sample
#: intake of this node, and the driver and corrector beside it, keep the CPU they need
#: while a solve takes what is left (a diagnosis beside a 4 x 1 kHz stream starved it)
SOLVE_NICENESS = 5


def _yield_cpu():
    """Lower the calling thread's CPU priority by :data:`SOLVE_NICENESS` (Linux; else no-op)."""
    if not sys.platform.startswith('linux'):   # elsewhere a tid is not a PRIO_PROCESS id
        return
    try:
        tid = threading.get_native_id()
        now = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, now + SOLVE_NICENESS))
    except OSError:
        pass


#: sets the consistency check flags (core/live/consistency.py: no pairing within its lags
#: fits them) are dropped before the fit up to this share of the sets; beyond, the node
#: refuses with the count (issue 32: never a calibration on sets its own check flags)
MAX_INCONSISTENT_FRACTION = 0.1


def _tensor_rms(components):
    """One RMS over the nine tensor components (list of lists, nT/m)."""
    return float(np.sqrt(np.mean(np.square(np.asarray(components, float)))))


class CalibrationNode(Node):
    """Collect rotation data of the array and serve calibrate/diagnose requests."""

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)    # a __ns remap overrides it
        super().__init__('calibration_node', **kwargs)
        first = prm.declare(self, [prm.N_SENSORS, prm.PLUGINS])
        plugins = prm.load_plugins(self)        # before the model is checked
        n = int(prm.value(self, 'n_sensors'))
        self._specs = prm.calibration_specs(n)
        self._specs_by_name = prm.declare(self, self._specs)
        self._specs_by_name.update(first)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        s = prm.calibration_settings(self)
        self._n = s.n_sensors
        self._active_cal = None                 # the calibration applied now (planar prior)
        self._turn_stop = threading.Event()     # set on shutdown: calibration/turn stops
        self._aux_cols = ['aux_' + a for a in s.aux_topics]

        self._lock = threading.Lock()           # buffer, matcher, latest signals, state
        self._busy = threading.Lock()           # one solve (calibrate/diagnose) at a time
        self._buffer = SampleBuffer(self._n, s.max_samples, self._aux_cols)
        self._matcher = StampMatcher(self._n, s.stamp_tolerance_s)
        self._temp = np.full(self._n, np.nan)
        self._aux = {}
        self._received = np.zeros(self._n, int)     # raw samples since start
        # attitude messages (stamp s, qw, qx, qy, qz) since start, interpolated onto the sets
        self._imu = np.zeros((2 * s.max_samples, 5))
        self._imu_count = 0
        self._imu_refused = 0            # Imu messages without a usable orientation
        self._state = 'idle'
        self._collecting = False                # between calibration/start and reset/exit
        self._last_result = None                # summary dict of the last calibration
        self._t_started = None
        self._model_changed = None              # (model, sets buffered then) of the last change
        # the active calibration applied to the incoming data (calibration/residual)
        self._live = None
        self._monitor = None
        self._residual_missing = None
        self._residual_sets = 0                 # residual messages published
        self._effect_errors = EffectErrors()    # errors of effect code (live, calibrate, ...)
        self._taken = 0                         # raw samples taken (all sensors, any state)

        service_group = ReentrantCallbackGroup()
        # the sensor streams are taken on the EventsExecutor in a thread of their own and
        # handed to the callbacks below on this node's executor (magcal_ros.ros.intake)
        self._intake = Intake(self)
        for j, topic in enumerate(s.input_topics, start=1):
            self._intake.subscribe(MagneticField, topic, self._raw_cb(j - 1),
                                   CALIBRATION_SENSOR_QOS)
            self._intake.subscribe(Temperature, f'sensor{j}/temperature',
                                   self._temp_cb(j - 1), SENSOR_QOS)
        for name in s.aux_topics:
            # as deep as the raw streams: a shallow queue dropped the channels' backlog
            # while the interpreter was held by a solve, leaving their values ahead of the
            # raw samples they were paired with
            self._intake.subscribe(Float64, name, self._aux_cb('aux_' + name),
                                   CALIBRATION_SENSOR_QOS)
        if s.imu_topic:
            self._intake.subscribe(Imu, s.imu_topic, self._imu_cb, CALIBRATION_SENSOR_QOS)

        self._status_pub = self.create_publisher(String, 'calibration/status', 10)
        self._result_pub = self.create_publisher(String, 'calibration/result', RESULT_QOS)
        self._residual_pub = self.create_publisher(Float64MultiArray, 'calibration/residual',
                                                   10)
        self._srv = [
            self.create_service(Trigger, 'calibration/start', self._on_start,
                                callback_group=service_group),
            self.create_service(Trigger, 'calibration/calibrate', self._on_calibrate,
                                callback_group=service_group),
            self.create_service(Trigger, 'calibration/diagnose', self._on_diagnose,
                                callback_group=service_group),
            self.create_service(Trigger, 'calibration/reset', self._on_reset,
                                callback_group=service_group),
            self.create_service(Trigger, 'calibration/turn', self._on_turn,
                                callback_group=service_group),
        ]
        self._cmd_vel = (self.create_publisher(Twist, s.cmd_vel_topic, 10)
                         if s.cmd_vel_topic else None)
        self._status_timer = self.create_timer(s.status_period_s, self._publish_status)
        self._updater = Updater(self, s.status_period_s)
        self._updater.setHardwareID(self.get_namespace())
        self._updater.add('residual', lambda stat: fill(stat, self.residual_status()))
        self._updater.add('buffer', lambda stat: fill(stat, self.buffer_status()))
        self._setup = self._describe_setup(s)
        self._updater.add('setup', lambda stat: fill(stat, self.setup_status()))
        say = (self.get_logger().info if self._setup[0] == DiagnosticStatus.OK else
               self.get_logger().warning)
        for line in self._setup[1]:
            say(line)
        # triggered by the worker thread when a solve ends, so the executor wakes up and
        # resumes the awaiting service coroutine even when no sensor data flows
        self._wake = self.create_guard_condition(lambda: None)
        self._publish_existing(s.calibration_file)
        self._intake.start()
        self.get_logger().info(
            f'ready: {self._n} sensors, model {list(s.model)}, field {s.field_nt:.1f} nT, '
            f'calibration file {s.calibration_file}'
            + (f', plug-in effects {plugins}' if plugins else '')
            + '; call calibration/start to collect')

    # -- geometry and field reference ------------------------------------------------------

    def _geometry(self, s):
        """Geometry dict of the node's parameters (None: no positions for 2, 3 or 5+)."""
        return array_geometry(self._n, s.sensor_positions_m, s.baseline_m)

    def _field(self, s, raw=None):
        """(F nT, field_reference dict) of ``field_source`` (raw (N, 3) nT for 'shape')."""
        from magcal_ros.core.data.magnitude import site_field_reference
        date = s.site_date or time.strftime('%Y-%m-%d', time.gmtime())
        lat = None if math.isnan(s.site_latitude_deg) else s.site_latitude_deg
        lon = None if math.isnan(s.site_longitude_deg) else s.site_longitude_deg
        source = 'shape-planar' if s.planar and s.field_source == 'shape' else s.field_source
        return site_field_reference(source, s.field_nt, lat, lon, s.site_altitude_m, date, raw)

    def _describe_setup(self, s):
        """(level, lines) on the geometry and the field reference, said once at start-up."""
        level, lines = DiagnosticStatus.OK, []
        geometry = self._geometry(s)
        inputs = ', '.join(s.input_topics)
        if geometry is None:
            lines.append(f'{self._n} sensors on {inputs} without sensor_positions_m: the '
                         'tensor residuals are not computed')
        else:
            pos = np.asarray(geometry['positions_m'])
            what = (f'paper 004 cross, baseline {geometry["baseline_m"]} m'
                    if geometry['type'] == 'cross' else f'positions {pos.tolist()} m')
            reason = tensor_undetermined(pos)
            lines.append(f'{self._n} sensors on {inputs}, {what}; '
                         + ('gradient tensor determined' if reason is None else
                            f'no gradient tensor: {reason}'))
        if s.field_source == 'igrf':
            try:
                f, ref = self._field(s)
                lines.append(f'field magnitude from IGRF: {f:.1f} nT at {ref["lat_deg"]} deg, '
                             f'{ref["lon_deg"]} deg, {s.site_altitude_m} m on {ref["date"]}')
            except (ValueError, ImportError) as exc:
                level = DiagnosticStatus.WARN
                lines.append(f'field_source igrf: {exc}; calibration/calibrate will refuse')
        elif s.field_source == 'shape':
            lines.append('field magnitude: shape only (no reference; the mean radius of '
                         "sensor 1's data sets the scale)")
        else:
            lines.append(f'field magnitude: constant field_nt {s.field_nt:.1f} nT')
        return level, lines

    def setup_status(self):
        """``DiagnosticStatus``: the geometry, the tensor and the field reference in use."""
        level, lines = self._setup
        st = DiagnosticStatus(name=f'{self.get_name()}: setup',
                              hardware_id=self.get_namespace(), level=level,
                              message='; '.join(lines))
        return st

    # -- read-only state (for in-process users and tests; ROS users see calibration/status)

    @property
    def received(self):
        """(S,) raw samples taken per sensor since calibration/start (a copy; counts)."""
        return self._received.copy()

    @property
    def imu_received(self):
        """Attitude (Imu) samples taken since calibration/start (count)."""
        return self._imu_count

    @property
    def state(self):
        """'idle', 'collecting' or 'calibrating'."""
        return self._state

    # -- parameters ------------------------------------------------------------------------

    def _on_set_parameters(self, parameters):
        result = prm.validate(self._specs_by_name, parameters)
        if result.successful:
            for p in parameters:
                if p.name == 'stamp_tolerance_s':
                    with self._lock:
                        self._matcher.tolerance_s = float(p.value)
                elif p.name == 'model':
                    with self._lock:
                        n_sets = len(self._buffer)
                    self._model_changed = (list(p.value), n_sets)
                    # the buffer holds raw data, valid for any model: it is kept, and said so
                    self.get_logger().info(
                        f'model set to {list(p.value)}: the {n_sets} sets already collected '
                        'stay in the buffer and the next calibration/calibrate fits all of '
                        'them with this model; call calibration/reset to collect afresh')
        return result

    # -- sensor callbacks (short) ----------------------------------------------------------

    def _raw_cb(self, j):
        def cb(msg):
            self._taken += 1
            collecting = self._collecting
            live = self._live
            if not collecting and live is None:
                return
            t = stamp_to_seconds(msg.header.stamp)
            b = msg_to_field_nt(msg)
            if not np.all(np.isfinite(b)):
                return
            if collecting:
                with self._lock:
                    self._received[j] += 1
                    for epoch, t_set, items in self._matcher.add(j, t, b):
                        self._buffer.append(epoch, t_set, np.array(items), self._temp,
                                            self._aux)
            if live is not None:
                self._residual(live, j + 1, t, b)
        return cb

    def _residual(self, live, j, t, raw):
        """Correct a sample with the active calibration; publish the residual of each set."""
        try:
            corrected = live.correct(j, t, raw)
        except MissingSignal as exc:
            self._residual_missing = str(exc)
            return
        except EffectError as exc:
            # contained: no residual of this sample; the node and the other sensors go on
            self._effect_error(exc, f'no residual of sensor {j}')
            return
        self._residual_missing = None
        monitor = self._monitor
        for _, fields in live.sets(j, t, corrected):
            scalar, vector = monitor.add(fields)
            self._residual_pub.publish(residual_to_msg(scalar, vector))
            self._residual_sets += 1

    def _effect_error(self, exc, what):
        """Count an error of effect code (:class:`EffectError`); log the first per effect."""
        if self._effect_errors.add(exc, what):
            self.get_logger().error(f'{exc} ({what}); further errors of it are counted on '
                                    '/diagnostics, not logged')

    def _named(self, exc, service):
        """
        (reason, payload entries) of an exception ending a calibrate/diagnose call.

        An exception raised by the code of an effect names the effect (and is counted like a
        live one, :meth:`_effect_error`); any other is described as it is.
        """
        effect = culprit(exc)
        if effect is None:
            return str(exc), {}
        err = EffectError(exc, effect)
        self._effect_error(err, f'calibration/{service} answered success=false')
        return str(err), {'effect': effect}

    def _failed(self, call, service, exc):
        """Reply (summary, payload) of a calibrate/diagnose call that raised ``exc``."""
        reason, extra = self._named(exc, service)
        if not extra:
            self.get_logger().error(f'{call} failed: {exc!r}')
        return f'{call} failed: {reason}', {'error': reason, 'type': type(exc).__name__,
                                            **extra}

    def _activate(self, cal, doc):
        """Apply ``cal`` to the incoming data from now on (residual and its diagnostics)."""
        s = prm.calibration_settings(self)
        positions = (doc.get('geometry') or {}).get('positions_m')
        # the residual monitor sees every set, also one that fails the pairing check: a
        # calibration that no longer fits must show in the residual, not be dropped
        live = LiveCorrector(cal, self._n, positions, s.stamp_tolerance_s,
                             check_pairing=False)
        self._active_cal = cal
        with self._lock:
            live.temp[:] = self._temp
            live.aux.update(self._aux)
        # the magnitude the calibration was made with (IGRF, shape only or field_nt)
        f = (doc.get('field_reference') or {}).get('magnitude_nt', s.field_nt)
        self._monitor = ResidualMonitor(self._n, float(f))
        self._residual_missing = None
        self._effect_errors.clear()               # those of the calibration replaced
        self._live = live

    def _temp_cb(self, j):
        def cb(msg):
            with self._lock:
                self._temp[j] = msg.temperature
            live = self._live
            if live is not None:
                live.set_temperature(j + 1, msg.temperature)
        return cb

    def _imu_cb(self, msg):
        if not self._collecting:
            return
        o = msg.orientation
        row = (stamp_to_seconds(msg.header.stamp), o.w, o.x, o.y, o.z)
        if (msg.orientation_covariance[0] == -1 or not np.all(np.isfinite(row))
                or abs(math.sqrt(o.w ** 2 + o.x ** 2 + o.y ** 2 + o.z ** 2) - 1.0)
                > UNIT_TOLERANCE):
            # REP 145: no orientation in this message; or not a unit quaternion
            with self._lock:
                self._imu_refused += 1
            return
        with self._lock:
            self._imu[self._imu_count % len(self._imu)] = row
            self._imu_count += 1

    def _attitude(self, data, epochs, stamps):
        """
        Attach the collected attitude to (data, epochs) (under the lock).

        The attitude is interpolated at the sets' own stamps (``stamps`` (N,) s, as the
        sensors' messages arrived), not at the sample instants reconstructed from them
        (``data.t``): Imu messages are stamped the same way by their driver, so the two
        share one clock and one latency even when samples are lost.  Sets outside the time
        span of the Imu messages are dropped; unchanged without any.
        """
        n = min(self._imu_count, len(self._imu))
        if not n:
            return data, epochs
        from dataclasses import replace
        from magcal_ros.core.geometry.attitude import with_attitude
        rows = self._imu[:n]
        out, kept = with_attitude(replace(data, t=stamps), rows[:, 0], rows[:, 1:],
                                  source=prm.value(self, 'imu_topic'))
        out = replace(out, t=data.t[kept], meta=dict(data.meta))
        out.meta['dropped_attitude_epochs'] = int((~kept).sum())
        return out, epochs[kept]

    def _aux_cb(self, column):
        def cb(msg):
            with self._lock:
                self._aux[column] = float(msg.data)
            live = self._live
            if live is not None:
                live.set_aux(column, msg.data)
        return cb

    def buffer_status(self):
        """
        ``diagnostic_msgs/DiagnosticStatus`` of the buffer of sets: what of the run it holds.

        The buffer keeps at most ``max_samples`` sets spread evenly over the whole run
        (:class:`magcal_ros.core.live.corrector.SampleBuffer`): the values say how many it
        holds, of how many received, one in how many, and which span of the run they cover.
        """
        with self._lock:
            cov = self._buffer.coverage()
            cap = self._buffer.capacity
        st = DiagnosticStatus(name=f'{self.get_name()}: buffer',
                              hardware_id=self.get_namespace(), level=DiagnosticStatus.OK)
        if not cov['sets_received']:
            st.message = 'no sample sets yet'
        else:
            st.message = (f'{cov["sets_held"]} of {cov["sets_received"]} sets held (one in '
                          f'{cov["stride"]}, at most {cap}), spread over '
                          f'{100 * cov.get("fraction_of_run", 1.0):.0f} % of the '
                          f'{cov["run_s"]:.0f} s run')
        st.values = [KeyValue(key=k, value=str(v)) for k, v in cov.items()]
        st.values.append(KeyValue(key='max_samples', value=str(cap)))
        return st

    def residual_status(self):
        """
        ``diagnostic_msgs/DiagnosticStatus`` of the active calibration on the live data.

        WARN when a sensor's rolling residual exceeds :data:`RESIDUAL_WARN_RATIO` times what
        its noise floor predicts (:class:`magcal_ros.core.live.corrector.ResidualMonitor`), or
        when a
        driven effect lacks its live signal.
        """
        st = DiagnosticStatus(name=f'{self.get_name()}: residual',
                              hardware_id=self.get_namespace(), level=DiagnosticStatus.OK)
        monitor = self._monitor
        r = monitor.ratios() if monitor is not None else None
        values = [('residual_sets_published', str(self._residual_sets))]
        errors = self._effect_errors
        values += [('effect_errors', str(sum(errors.counts().values())))]
        values += [(f'effect_errors {k}', str(n)) for k, n in errors.counts().items()]
        if errors:
            st.level = DiagnosticStatus.ERROR
            st.message = f'effect code failed: {errors.summary()}'
        elif self._live is None:
            st.message = 'no active calibration: no residual (run calibration/calibrate)'
        elif self._residual_missing:
            st.level = DiagnosticStatus.WARN
            st.message = f'no residual: {self._residual_missing}'
        elif r is None:
            st.message = 'waiting for sets of all sensors to compare with the calibration'
        else:
            bad = []
            for j in range(self._n):
                for kind in monitor.kinds:
                    ratio = float(r[f'{kind}_ratio'][j])
                    values.append((f'sensor{j + 1}_{kind}_ratio', f'{ratio:.2f}'))
                    values.append((f'sensor{j + 1}_{kind}_rms_nt',
                                   f'{float(r[f"{kind}_rms_nt"][j]):.2f}'))
                    if not ratio <= RESIDUAL_WARN_RATIO:
                        bad.append(f'sensor {j + 1} {kind} {ratio:.1f}x')
                values.append((f'sensor{j + 1}_floor_nt', f'{float(r["floor_nt"][j]):.2f}'))
            if bad:
                st.level = DiagnosticStatus.WARN
                st.message = (f'the calibration no longer fits the data: residual / noise floor '
                              f'{", ".join(bad)} (over the last {r["sets"]} sets); run '
                              'calibration/diagnose')
            else:
                st.message = (f'the calibration fits: residuals within {RESIDUAL_WARN_RATIO}x '
                              f'the noise floor over the last {r["sets"]} sets')
        st.values = [KeyValue(key=k, value=v) for k, v in values]
        return st

    # -- status ----------------------------------------------------------------------------

    def status(self):
        """Return progress and coverage (JSON-ready dict), as published on calibration/status."""
        s = prm.calibration_settings(self)
        with self._lock:
            n_sets = len(self._buffer)
            raw = self._buffer.raw_view(_STATUS_SUBSAMPLE) if n_sets else None
            dropped = self._matcher.incomplete
            out_of_order = self._matcher.out_of_order
            realigned = self._matcher.realigned
            received = self._received.tolist()
            buffer = self._buffer.coverage()
            state = self._state
        # the short fields first: `ros2 topic echo` shows the first 128 characters
        out = {'state': state, 'sets': n_sets, 'min_samples': s.min_samples, 'ready': False,
               'coverage': {}, 'missing': []}
        missing = out['missing']
        if not self._collecting:
            missing.append('not collecting: call calibration/start')
        else:
            missing.extend(_silent_sensors(received))
        if n_sets < s.min_samples:
            missing.append(f'{s.min_samples - n_sets} more complete sample sets '
                           f'(have {n_sets}, need {s.min_samples})')
        eigenvalues = {}
        if raw is not None and raw.shape[1] >= 3:
            rep = check_coverage(raw)
            for j, v in rep['sensors'].items():
                out['coverage'][str(j)] = v['status']
                eigenvalues[str(j)] = [round(float(x), 4) for x in v['eigenvalues']]
            # the constrained mode is made for a partial or single-axis coverage (as in
            # model.fit), the planar mode for a single axis: not a missing item then
            excused = (('partial', 'single axis') if s.constrained else
                       ('single axis',) if s.planar else ())
            partial = {j for j, v in rep['sensors'].items() if v['status'] in excused}
            missing.extend(p for p in rep['problems']
                           if not any(p.startswith(f'sensor {j}:') for j in partial))
        if s.imu_topic:
            with self._lock:
                out['attitude_messages'] = int(self._imu_count)
                out['attitude_messages_refused'] = int(self._imu_refused)
            if self._collecting and self._imu_refused and not self._imu_count:
                missing.append(f'every message on {s.imu_topic} lacks a unit orientation '
                               'quaternion (orientation_covariance[0] = -1, NaN or |q| != 1)')
        out['ready'] = self._collecting and not missing
        out.update({'model': list(s.model), 'field_nt': s.field_nt,
                    'field_source': s.field_source,
                    'max_samples': s.max_samples, 'coverage_eigenvalues': eigenvalues,
                    'buffer': buffer,
                    'incomplete_sets_dropped': dropped, 'out_of_order_dropped': out_of_order,
                    'stream_realignments': realigned,
                    'intake_dropped': self._intake.dropped,
                    'samples_received': {str(j + 1): r for j, r in enumerate(received)}})
        if self._t_started is not None and self._collecting:
            dt = time.monotonic() - self._t_started
            out['collecting_for_s'] = round(dt, 1)
            out['set_rate_hz'] = round(n_sets / dt, 2) if dt > 0 else 0.0
        if self._last_result is not None:
            out['last_calibration'] = self._last_result
        return out

    def _publish_status(self):
        try:
            msg = String(data=json.dumps(self.status(), separators=(',', ':')))
        except ValueError as exc:         # a degenerate buffer must not kill the timer
            msg = String(data=json.dumps({'state': self._state, 'error': str(exc)}))
        self._status_pub.publish(msg)

    # -- services --------------------------------------------------------------------------

    def _reject_busy(self, response, service):
        """Answer a call that arrived during a calibration (the state is not touched)."""
        return _reply(response, False, f'rejected: a calibration is running; call '
                      f'calibration/{service} again when it has finished',
                      {'state': self._state})

    def _on_start(self, request, response):
        if not self._busy.acquire(blocking=False):
            return self._reject_busy(response, 'start')
        try:
            dropped = self._clear('collecting')
            s = prm.calibration_settings(self)
            return _reply(response, True,
                          f'collecting ({dropped} old sets dropped): rotate the array through '
                          f'many attitudes; calibrate after at least {s.min_samples} sets',
                          {'state': 'collecting', 'min_samples': s.min_samples,
                           'sets_dropped': dropped})
        finally:
            self._busy.release()

    async def _on_turn(self, request, response):
        # as the ROS calibration packages do: turn the robot in place through cmd_vel while
        # collecting, until sensor 1 has seen turn_count turns or turn_timeout_s passed
        s = prm.calibration_settings(self)
        if self._cmd_vel is None:
            return _reply(response, False, 'no cmd_vel_topic: set it (read-only: at start-up) '
                          'to turn the robot', {'state': self._state})
        if not self._busy.acquire(blocking=False):
            return self._reject_busy(response, 'turn')
        try:
            dropped = self._clear('collecting')
            self.get_logger().info(
                f'turning the robot on {s.cmd_vel_topic}: {s.turn_count:g} turns at '
                f'{s.turn_speed_rad_s:g} rad/s (at most {s.turn_timeout_s:g} s)')
            ok, summary, payload = await self._in_worker(self._turn, s)
            payload['sets_dropped'] = dropped
            return _reply(response, ok, summary, payload)
        except Exception as exc:         # noqa: B902 -- a service must answer, never die
            self.get_logger().error(f'turn failed: {exc!r}')
            return _reply(response, False, f'turn failed: {exc}; the robot is stopped',
                          {'error': str(exc), 'type': type(exc).__name__})
        finally:
            self._stop_robot()
            self._busy.release()

    def _turn(self, s):
        """Drive cmd_vel until the turns are seen or time is up (worker thread)."""
        from magcal_ros.core.geometry.turn import swept_angle
        twist = Twist()
        twist.angular.z = float(s.turn_speed_rad_s)
        want = 2 * math.pi * s.turn_count
        t0 = time.monotonic()
        swept, last_check = 0.0, t0
        try:
            while not self._turn_stop.is_set():
                now = time.monotonic()
                if now - t0 > s.turn_timeout_s:
                    break
                self._cmd_vel.publish(twist)
                if now - last_check >= 0.5:
                    last_check = now
                    n_sets, data, _ = self._snapshot()
                    swept = swept_angle(data.raw[0]) if n_sets else 0.0
                    if swept >= want:
                        break
                self._turn_stop.wait(0.1)
        finally:
            self._stop_robot()
        elapsed = time.monotonic() - t0
        n_sets = self._snapshot()[0]
        payload = {'turns_asked': s.turn_count, 'turns_seen': swept / (2 * math.pi),
                   'elapsed_s': round(elapsed, 2), 'sets': n_sets,
                   'cmd_vel_topic': s.cmd_vel_topic}
        if swept >= want:
            return True, (f'turned {swept / (2 * math.pi):.2f} turns in {elapsed:.1f} s '
                          f'({n_sets} sets collected): the robot is stopped; call '
                          'calibration/calibrate (parameter planar: true for a robot that '
                          'only turns about one axis)'), payload
        why = ('the node is shutting down' if self._turn_stop.is_set() else
               f'turn_timeout_s ({s.turn_timeout_s:g} s) passed')
        return False, (f'turn incomplete: sensor 1 saw {swept / (2 * math.pi):.2f} of '
                       f'{s.turn_count:g} turns when {why}; the robot is stopped (does the '
                       f'base listen on {s.cmd_vel_topic}? wheels slipping?)'), payload

    def _stop_robot(self):
        """Publish a zero velocity on cmd_vel (after a turn, on error, on shutdown)."""
        if self._cmd_vel is not None:
            try:
                self._cmd_vel.publish(Twist())
            except Exception:       # noqa: B902 -- the context may be gone at shutdown
                pass

    def destroy_node(self):
        """Stop a turn in progress (a zero velocity on cmd_vel), then destroy the node."""
        self._turn_stop.set()
        self._stop_robot()
        self._intake.destroy()
        return super().destroy_node()

    def _on_reset(self, request, response):
        """Forget the collected sets; collection goes on if it was running."""
        if not self._busy.acquire(blocking=False):
            return self._reject_busy(response, 'reset')
        try:
            with self._lock:
                state = self._state
            dropped = self._clear(state)
            what = ('collection goes on from now' if state == 'collecting' else
                    'call calibration/start to collect')
            return _reply(response, True, f'reset: {dropped} sets dropped; {what}',
                          {'state': state, 'sets_dropped': dropped})
        finally:
            self._busy.release()

    def _clear(self, state):
        """Empty the buffer and the matcher, set ``state``; return the sets dropped."""
        with self._lock:
            dropped = len(self._buffer)
            self._buffer.clear()
            self._matcher.reset()
            self._received[:] = 0
            self._imu_count = 0
            self._imu_refused = 0
            self._state = state
            self._collecting = state == 'collecting'
            self._t_started = time.monotonic() if self._collecting else None
            self._model_changed = None
        return dropped

    def _snapshot(self):
        with self._lock:
            n_sets = len(self._buffer)
            data = self._buffer.dataset() if n_sets else None
            epochs = self._buffer.epochs() if n_sets else None
            if n_sets:
                data, epochs = self._attitude(data, epochs, self._buffer.stamps())
            return n_sets, data, epochs

    @staticmethod
    def _screen(data, epochs):
        """Leave out readings no field produces: (data, epochs, ReadingScreen) of the rest."""
        data_kept, _, screen = leave_out_unphysical(data)
        if data_kept is not data and epochs is not None:
            epochs = np.asarray(epochs)[screen.keep]
        return data_kept, epochs, screen

    def _resync(self, data, epochs, settings):
        """
        Re-pair sets paired from different epochs; return (data, payload, warning lines).

        The sets the check still finds inconsistent are dropped (counted in the payload and
        a line), up to :data:`MAX_INCONSISTENT_FRACTION` of them; beyond, none is dropped and
        the payload's ``refuse`` says why no calibration may be made of these sets.
        """
        if not settings.resync_sets or data.n_sensors < 2:
            return data, None, []
        fixed, slips, dropped, gross = resync(data, epochs, drop_inconsistent=True)
        n_bad = slips.dropped_inconsistent
        refuse = None
        if n_bad > MAX_INCONSISTENT_FRACTION * data.n_samples:
            # never a calibration on sets the consistency check flags: too many to drop
            fixed, slips, dropped, gross = resync(data, epochs)
            refuse = (
                f'{n_bad} of {data.n_samples} sets are inconsistent with sensor 1 at every '
                f'pairing within +-{DEFAULT_MAX_LAG} epochs (per sensor: '
                + ', '.join(f'{j}: {c}' for j, c in enumerate(slips.inconsistent[1:].tolist(),
                                                              start=2))
                + f') and fit at one up to +-{LONG_MAX_LAG} epochs apart: the sensors were '
                'paired from epochs further apart (a reader that lost pace: CPU starvation, a '
                f'stalled link); more than {MAX_INCONSISTENT_FRACTION:.0%} of the sets, so none '
                'is dropped and no calibration is made: collect again (calibration/start), or '
                'set resync_sets false to fit the sets as paired')
            n_bad = 0
        keys = [str(j) for j in range(2, data.n_sensors + 1)]
        payload = {
            'sets_repaired': dict(zip(keys, slips.n_slipped[1:].tolist())),
            'sets_dropped': dropped,
            'sets_dropped_garbled': gross,
            'misfit_as_paired_nt': dict(zip(keys, np.round(slips.rms_as_paired_nt[1:], 2)
                                            .tolist())),
            'misfit_nt': dict(zip(keys, np.round(slips.rms_nt[1:], 2).tolist())),
            'inconsistent_sets': dict(zip(keys, slips.inconsistent[1:].tolist())),
            'sets_dropped_inconsistent': n_bad,
            'refuse': refuse,
        }
        lines = slips.summary()
        if n_bad:
            lines.append(f'{n_bad} sets dropped: inconsistent with sensor 1 at every pairing '
                         f'within +-{DEFAULT_MAX_LAG} epochs, consistent at one up to '
                         f'+-{LONG_MAX_LAG} epochs apart (paired from epochs further apart)')
        if gross:
            lines.append(f'{gross} sets dropped with a sample more than '
                         f'{GROSS_FRACTION:.0%} of the field off the mean of its neighbours '
                         'in time (a cut or garbled serial line)')
        if dropped:
            lines.append(f'{dropped} sets dropped where a re-paired sample had no unique '
                         'partner')
        for line in lines:
            self.get_logger().warning(f'resync: {line}')
        return fixed, payload, lines

    def _in_worker(self, fn, *args):
        """Run ``fn(*args)`` in a worker thread; return an awaitable rclpy Future."""
        future = Future()

        def work():
            _yield_cpu()
            try:
                future.set_result(fn(*args))
            except Exception as exc:        # noqa: B902 -- handed to the awaiting service
                future.set_exception(exc)
            finally:
                self._wake.trigger()
        threading.Thread(target=work, name='magcal-solve', daemon=True).start()
        return future

    async def _on_calibrate(self, request, response):
        if not self._busy.acquire(blocking=False):
            return _reply(response, False, 'a calibration is already running',
                          {'state': self._state})
        with self._lock:
            prev_state = self._state
            self._state = 'calibrating'
        try:
            ok, summary, payload = await self._in_worker(self._calibrate, prev_state)
            return _reply(response, ok, summary, payload)
        except Exception as exc:         # noqa: B902 -- a service must answer, never die
            return _reply(response, False, *self._failed('calibration', 'calibrate', exc))
        finally:
            with self._lock:
                # collection goes on (the buffer is kept) if it was running before
                self._state = prev_state
            self._busy.release()

    def _calibrate(self, state):
        """Run the fit; returns (success, summary text, JSON payload)."""
        s = prm.calibration_settings(self)
        n_sets, data, epochs = self._snapshot()
        if n_sets < s.min_samples:
            with self._lock:
                received = self._received.tolist()
            silent = [] if state == 'idle' else _silent_sensors(received)
            reason = (f'only {n_sets} complete sample sets collected, need at least '
                      f'{s.min_samples}' + (': call calibration/start and rotate the array'
                                            if state == 'idle' else
                                            '; ' + '; '.join(silent) if silent else
                                            ': keep rotating the array'))
            return False, f'not calibrated: {reason}; previous calibration stays active', {
                'reason': reason, 'sets': n_sets}
        model = Model.from_spec(list(s.model), self._n)
        geometry = self._geometry(s)
        t0 = time.monotonic()
        try:
            # readings no field produces first (a clipped axis of sensor 1 would make every
            # other sensor inconsistent with it), then the pairing check on the rest
            data, epochs, screen = self._screen(data, epochs)
            data, resync_payload, resync_lines = self._resync(data, epochs, s)
        except ValueError as exc:
            reason, extra = self._named(exc, 'calibrate')
            return False, f'not calibrated: {reason}; previous calibration stays active', {
                'reason': reason, 'sets': n_sets, 'model': list(s.model), **extra}
        try:
            field_nt, field_ref = self._field(s, data.raw[0])
        except (ValueError, ImportError) as exc:
            reason = f'no field magnitude: {exc}'
            return False, f'not calibrated: {reason}; previous calibration stays active', {
                'reason': reason, 'sets': n_sets}
        extra = {}
        if s.planar:
            # what the turn leaves open is held at the active calibration (same model), else
            # at an ideal sensor (magcal_ros.core.model.planar)
            active = getattr(self, '_active_cal', None)
            prior = (active.params if active is not None
                     and active.model.spec() == model.spec() else None)
            extra['planar'] = {'inclination_deg': field_ref.get('inclination_deg'),
                               'prior_params': prior}
        try:
            run = run_calibration(
                data, model=model, field_nt=field_nt, geometry=geometry or {},
                field_reference=field_ref,
                robust=s.robust, exclude_outliers=s.exclude_outliers,
                constrained=s.constrained, screen=screen, **extra)
        except DegenerateDataError as exc:
            return False, (f'not calibrated: {exc}; previous calibration stays active'), {
                'reason': str(exc), 'sets': n_sets, 'model': list(s.model)}
        except ValueError as exc:
            reason, extra = self._named(exc, 'calibrate')
            return False, f'not calibrated: {reason}; previous calibration stays active', {
                'reason': reason, 'sets': n_sets, 'model': list(s.model), **extra}
        solve_s = time.monotonic() - t0
        refuse = (resync_payload or {}).get('refuse')
        if refuse:
            # the fit's own refusals (degenerate data, a stuck sensor) came first; a fit of
            # these sets is never activated
            return False, f'not calibrated: {refuse}; previous calibration stays active', {
                'reason': refuse, 'sets': n_sets, 'model': list(s.model),
                'resync': resync_payload}
        if not run.result.success:
            # a fit that ran out of iterations is not a calibration: never installed
            reason = f'the fit did not converge ({run.result.message})'
            return False, f'not calibrated: {reason}; previous calibration stays active', {
                'reason': reason, 'sets': n_sets, 'model': list(s.model), 'converged': False}
        # where the magnitude came from, also in the provenance (field_reference has the rest)
        run.doc['provenance']['field_source'] = s.field_source
        os.makedirs(os.path.dirname(os.path.abspath(s.calibration_file)), exist_ok=True)
        try:
            save_calibration(s.calibration_file, run.doc, history=s.history)
        except (OSError, CalibrationFileError) as exc:
            return False, (f'calibrated but could not write {s.calibration_file}: {exc}; '
                           'previous calibration stays active'), {'reason': str(exc)}
        self._result_pub.publish(String(data=dump_calibration(run.doc)))
        self._activate(run.result.calibration, run.doc)
        summ = run.summary
        payload = {
            'calibration_file': s.calibration_file,
            'field_reference': field_ref,
            'geometry': geometry,
            'model': list(s.model),
            'effects': summ['model'],
            'sets': n_sets,
            'solve_s': round(solve_s, 2),
            'converged': summ['converged'],
            'noise_floor_nt': summ['noise_floor_nt'],
            'scalar_rms_before_nt': summ['total_field_rms_before_nt'],
            'scalar_rms_after_nt': summ['scalar_rms_nt'],
            'vector_rms_after_nt': summ['vector_rms_nt'],
            'robust': s.robust,
            'constrained': s.constrained,
            'downweighted': summ['downweighted'],
            'warnings': summ['warnings'],
            'resync': resync_payload,
            'outlier_sets_excluded': summ.get('outlier_sets_excluded', 0),
            'readings_left_out': summ.get('readings_left_out'),
        }
        after = summ['scalar_rms_nt']
        lines = [f'calibrated {n_sets} sets with model {",".join(s.model)}: total-field RMS '
                 f'{min(after.values()):.2f}-{max(after.values()):.2f} nT, noise floor '
                 f'{summ["noise_floor_nt"]:.2f} nT',
                 f'field magnitude {field_nt:.1f} nT ({field_ref["kind"]})',
                 f'written to {s.calibration_file} (solve {solve_s:.1f} s; effects '
                 f'{",".join(summ["model"])})',
                 f'total-field RMS per sensor before [nT]: '
                 f'{_fmt_per_sensor(summ["total_field_rms_before_nt"], "{:.1f}")}',
                 f'total-field RMS per sensor after  [nT]: '
                 f'{_fmt_per_sensor(summ["scalar_rms_nt"])} '
                 f'(noise floor {summ["noise_floor_nt"]:.2f} nT)']
        if 'tensor_rms_nt_per_m' in summ:
            before = _tensor_rms(summ['tensor_rms_before_nt_per_m'])
            after = _tensor_rms(summ['tensor_rms_nt_per_m'])
            floor = _tensor_rms(summ['tensor_floor_nt_per_m'])
            payload.update(tensor_rms_before_nt_per_m=before, tensor_rms_after_nt_per_m=after,
                           tensor_floor_nt_per_m=floor,
                           tensor_rms_components_after_nt_per_m=summ['tensor_rms_nt_per_m'])
            lines.append(f'tensor RMS before {before:.1f} nT/m, after {after:.2f} nT/m '
                         f'(noise floor {floor:.2f} nT/m)')
        if 'site_gradient_nt_per_m' in summ:
            # world frame of the Imu orientation, nT/m, with standard uncertainties
            payload.update(site_gradient_nt_per_m=summ['site_gradient_nt_per_m'],
                           site_gradient_stderr_nt_per_m=summ['site_gradient_stderr_nt_per_m'],
                           dropped_attitude_epochs=data.meta.get('dropped_attitude_epochs', 0))
            g = np.array(summ['site_gradient_nt_per_m'])
            lines.append('site gradient (world frame, nT/m): ' + ', '.join(
                f'{v:.1f}' for v in g[np.triu_indices(3)]) + ' (xx, xy, xz, yy, yz, zz)')
        if 'planar' in summ:
            pl = summ['planar']
            payload.update(planar=pl, undetermined=summ['undetermined'],
                           heading_error_deg=summ['heading_error_deg'])
            lines.append(f'planar: heading error {summ["heading_error_deg"]:.2f} deg (1 sd, '
                         f'level, inclination from {pl["inclination_source"]}); undetermined: '
                         + (', '.join(summ['undetermined']) or 'none'))
        if s.robust:
            lines.append(f'robust fit: samples down-weighted as outliers per sensor: '
                         f'{_fmt_per_sensor(summ["downweighted"], "{:d}")} of {n_sets}')
        for w in summ['warnings']:
            lines.append(format_note(w))
        for w in resync_lines:
            lines.append(f'resync: {w}')
        changed = self._model_changed
        if changed is not None and changed[1] > 0:
            payload['model_changed_after_sets'] = changed[1]
            lines.append(f'note: the model was set to {",".join(changed[0])} after {changed[1]} '
                         'sets had been collected; all buffered sets were fitted with it '
                         '(calibration/reset collects afresh)')
        if state == 'collecting':
            lines.append('collection goes on: calibrate again later, or call '
                         'calibration/reset to drop the sets collected so far')
        self._last_result = {k: payload[k] for k in ('calibration_file', 'model', 'sets')}
        self.get_logger().info(lines[0])
        return True, '\n'.join(lines), payload

    async def _on_diagnose(self, request, response):
        if not self._busy.acquire(blocking=False):
            return _reply(response, False, 'a calibration is already running',
                          {'state': self._state})
        try:
            ok, summary, payload = await self._in_worker(self._diagnose)
            return _reply(response, ok, summary, payload)
        except Exception as exc:         # noqa: B902 -- a service must answer, never die
            return _reply(response, False, *self._failed('diagnosis', 'diagnose', exc))
        finally:
            self._busy.release()

    def _diagnose(self):
        """Rank the missing effects; returns (success, summary text, JSON payload)."""
        try:
            from magcal_ros.core.discovery import diagnose
            from magcal_ros.report import write_report
        except ImportError as exc:
            return False, f'diagnosis is not available: {exc}', {'error': str(exc)}
        s = prm.calibration_settings(self)
        n_sets, data, epochs = self._snapshot()
        if n_sets < s.min_samples:
            reason = f'only {n_sets} complete sample sets collected, need {s.min_samples}'
            return False, f'not diagnosed: {reason}', {'reason': reason, 'sets': n_sets}
        model = Model.from_spec(list(s.model), self._n)
        try:
            # readings no field produces are named and left out, as in calibrate, before
            # the pairing check
            data, epochs, screen = self._screen(data, epochs)
            data, resync_payload, _ = self._resync(data, epochs, s)
        except ValueError as exc:
            reason, extra = self._named(exc, 'diagnose')
            return False, f'not diagnosed: {reason}', {'reason': reason, 'sets': n_sets,
                                                       **extra}
        field_nt = s.field_nt
        try:
            diag = diagnose(data, model, field_nt=field_nt, constrained=s.constrained,
                            baseline_m=s.baseline_m)
        except ValueError as exc:
            reason, extra = self._named(exc, 'diagnose')
            return False, f'not diagnosed: {reason}', {'reason': reason, 'sets': n_sets,
                                                       **extra}
        ranking = json.loads(diag.to_json())       # non-finite numbers as null
        report = write_report(s.report_dir, data, diagnosis=diag, baseline_m=s.baseline_m)
        ranking['report'] = os.fspath(report)
        ranking['resync'] = resync_payload
        ranking['readings_left_out'] = screen.to_dict()
        verdict = ranking.get('verdict') or {}
        if verdict.get('effect', 'none') == 'none':
            head = (f'nothing missing: model {",".join(ranking["model"])} explains the data '
                    f'down to the noise floor ({ranking["noise_floor_nt"]:.2f} nT)')
        else:
            head = f'most likely missing effect: {verdict.get("token") or verdict["effect"]}'
        lines = [head] + ([verdict['reason']] if verdict.get('reason') else [])
        if ranking.get('findings'):       # model-free: what is left (core.discovery.findings)
            lines.append('left in the residuals: ' + '; '.join(
                f'{f["kind"]}' + (f' (add {f["token"]})' if f.get('token') else '')
                + ('' if f['sensor'] is None else f' on sensor {f["sensor"]}')
                for f in ranking['findings'][:4]))
        lines += [format_note(w) for w in screen.notes()]
        lines.append(f'HTML report: {ranking["report"]}')
        return True, '\n'.join(lines), ranking

    # -- start-up --------------------------------------------------------------------------

    def _publish_existing(self, path):
        """Publish the calibration already on disk, so the corrector starts with it."""
        if not os.path.exists(path):
            return
        try:
            load_calibration(path)
            with open(path, encoding='utf-8') as fh:
                text = fh.read()
            cal, doc = parse_calibration(text, path)
            mismatch = geometry_mismatch(doc.get('geometry'),
                                         self._geometry(prm.calibration_settings(self)))
            if mismatch:
                raise ValueError(f'{path}: {mismatch}')
            self._activate(cal, doc)
        except EffectError as exc:
            self._effect_error(exc, f'the existing calibration {path} was not published')
            return
        except (CalibrationFileError, OSError, ValueError) as exc:
            self.get_logger().warning(f'existing calibration not published: {exc}')
            return
        self._result_pub.publish(String(data=text))
        self.get_logger().info(f'published the existing calibration {path}')


def main(args=None):
    """Run calibration_node (``ros2 run magcal_ros calibration_node``)."""
    # its services are coroutines awaiting the solve thread: not for the EventsExecutor
    return spin_node(CalibrationNode, 'calibration_node', args, events=False)


if __name__ == '__main__':
    sys.exit(main())
