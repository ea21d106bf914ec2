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

Topics, services (std_srvs/Trigger, replies by :func:`magcal_ros.ros.collection.reply`) and
parameters: docs/design.md §3. The collection, the solves, the turn and the learning are the
mixins of :mod:`~magcal_ros.ros.collection`, :mod:`~magcal_ros.ros.calibrating`,
:mod:`~magcal_ros.ros.turn` and :mod:`~magcal_ros.ros.learning`; here: the set-up, the
parameters, the live residual of the active calibration (``calibration/residual``, WARN above
:data:`magcal_ros.core.live.corrector.RESIDUAL_WARN_RATIO`) and the worker thread.

A solve runs in a worker thread that the service coroutines (a reentrant callback group) await,
so the sensor callbacks go on; a non-blocking lock refuses a second calibrate/diagnose/start
during a solve. The node spins on a SingleThreadedExecutor: rclpy's MultiThreadedExecutor lost
samples or ran a subscription's callbacks out of order, which breaks the pairing by stamp.
"""
import contextlib
import math
import os
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Twist
from magcal_ros.core.effects.safety import EffectError, EffectErrors
from magcal_ros.core.live.corrector import (LiveCorrector, MissingSignal, RESIDUAL_WARN_RATIO,
                                            ResidualMonitor, SampleBuffer)
from magcal_ros.core.live.sync import StampMatcher
from magcal_ros.io.calfile import CalibrationFileError, load_calibration
from magcal_ros.pipeline import array_geometry, geometry_mismatch, tensor_undetermined
from magcal_ros.ros import params as prm
from magcal_ros.ros.calibrating import CalibrationMixin
from magcal_ros.ros.collection import CollectionMixin
from magcal_ros.ros.conversions import residual_to_msg
from magcal_ros.ros.diagnostics import EffectErrorsMixin, fill, node_status, Updater
from magcal_ros.ros.intake import Intake
from magcal_ros.ros.learning import LearningMixin
from magcal_ros.ros.run import DEFAULT_NAMESPACE, spin_node, yield_cpu
from magcal_ros.ros.turn import TurnMixin
import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.exceptions import InvalidHandle
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

#: the corrector's sensor streams: REP 2003's sensor-data profile, 0.25 s of 100 Hz of queue
SENSOR_QOS = QoSProfile(depth=25, history=HistoryPolicy.KEEP_LAST,
                        reliability=qos_profile_sensor_data.reliability,
                        durability=qos_profile_sensor_data.durability)

#: the calibration node's sensor streams: 10 s of 100 Hz of queue. It needs every sample (one
#: dropped shifts its stream's epochs until the matcher votes again), and a solve starves its
#: executor for up to a second
CALIBRATION_SENSOR_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                                    reliability=qos_profile_sensor_data.reliability,
                                    durability=qos_profile_sensor_data.durability)


class CalibrationNode(CollectionMixin, CalibrationMixin, TurnMixin, LearningMixin,
                      EffectErrorsMixin, Node):
    """Collect rotation data of the array and serve calibrate/diagnose requests."""

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)    # a __ns remap overrides it
        super().__init__('calibration_node', **kwargs)
        self._specs_by_name, plugins = prm.declare_node(self, prm.calibration_specs)
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
        self._live = self._monitor = self._residual_missing = None
        self._residual_sets = 0                 # residual messages published
        self._effect_errors = EffectErrors()    # errors of effect code (live, calibrate, ...)
        self._taken = 0                         # raw samples taken (all sensors, any state)

        service_group = ReentrantCallbackGroup()
        self._intake = Intake(self)
        for j, topic in enumerate(s.input_topics, start=1):
            self._intake.subscribe(MagneticField, topic, self._raw_cb(j - 1),
                                   CALIBRATION_SENSOR_QOS)
            self._intake.subscribe(Temperature, f'sensor{j}/temperature',
                                   self._temp_cb(j - 1), SENSOR_QOS)
        for name in s.aux_topics:
            # as deep as the raw streams: values must not run ahead of their raw samples
            self._intake.subscribe(Float64, name, self._aux_cb('aux_' + name),
                                   CALIBRATION_SENSOR_QOS)
        if s.imu_topic:
            self._intake.subscribe(Imu, s.imu_topic, self._imu_cb, CALIBRATION_SENSOR_QOS)

        self._status_pub = self.create_publisher(String, 'calibration/status', 10)
        self._result_pub = self.create_publisher(String, 'calibration/result', RESULT_QOS)
        self._residual_pub = self.create_publisher(Float64MultiArray, 'calibration/residual', 10)
        self._srv = [self.create_service(Trigger, f'calibration/{name}', callback,
                                         callback_group=service_group)
                     for name, callback in (('start', self._on_start),
                                            ('calibrate', self._on_calibrate),
                                            ('diagnose', self._on_diagnose),
                                            ('reset', self._on_reset), ('turn', self._on_turn))]
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
        # the worker thread wakes the executor when a solve ends (the awaiting service)
        self._wake = self.create_guard_condition(lambda: None)
        self._learn_init(RESULT_QOS)            # learning mode (magcal_ros.ros.learning)
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
        return node_status(self, 'setup', level, '; '.join(lines))

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

    # -- the active calibration on the live data (calibration/residual) ------------------
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

    def _activate(self, cal, doc):
        """Apply ``cal`` to the incoming data from now on (residual and its diagnostics)."""
        s = prm.calibration_settings(self)
        positions = (doc.get('geometry') or {}).get('positions_m')
        # the residual monitor sees every set, also one that fails the pairing check: a
        # calibration that no longer fits must show in the residual, not be dropped
        live = LiveCorrector(cal, self._n, positions, s.stamp_tolerance_s, check_pairing=False)
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
        self._learn_activate(cal, doc)

    def residual_status(self):
        """
        ``diagnostic_msgs/DiagnosticStatus`` of the active calibration on the live data.

        WARN when a sensor's rolling residual exceeds :data:`RESIDUAL_WARN_RATIO` times its
        noise floor (:class:`~magcal_ros.core.live.corrector.ResidualMonitor`), or a driven
        effect lacks its live signal.
        """
        level = DiagnosticStatus.OK
        monitor = self._monitor
        r = monitor.ratios() if monitor is not None else None
        errors = self._effect_errors
        values = [('residual_sets_published', self._residual_sets)]
        values += self._effect_error_values()
        if errors:
            level = DiagnosticStatus.ERROR
            message = f'effect code failed: {errors.summary()}'
        elif self._live is None:
            message = 'no active calibration: no residual (run calibration/calibrate)'
        elif self._residual_missing:
            level = DiagnosticStatus.WARN
            message = f'no residual: {self._residual_missing}'
        elif r is None:
            message = 'waiting for sets of all sensors to compare with the calibration'
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
                level = DiagnosticStatus.WARN
                message = (f'the calibration no longer fits the data: residual / noise floor '
                           f'{", ".join(bad)} (over the last {r["sets"]} sets); run '
                           'calibration/diagnose')
            else:
                message = (f'the calibration fits: residuals within {RESIDUAL_WARN_RATIO}x '
                           f'the noise floor over the last {r["sets"]} sets')
        return node_status(self, 'residual', level, message, values)

    # -- shutdown and the solve thread ----------------------------------------------------
    def destroy_node(self):
        """Stop a turn in progress (a zero velocity on cmd_vel), then destroy the node."""
        self._turn_stop.set()
        self._stop_robot()
        self._intake.destroy()
        return super().destroy_node()

    def _in_worker(self, fn, *args):
        """Run ``fn(*args)`` in a worker thread; return an awaitable rclpy Future."""
        future = Future()

        def work():
            yield_cpu()
            try:
                future.set_result(fn(*args))
            except Exception as exc:        # noqa: B902 -- handed to the awaiting service
                future.set_exception(exc)
            finally:
                with contextlib.suppress(InvalidHandle):    # the node was destroyed meanwhile
                    self._wake.trigger()
        threading.Thread(target=work, name='magcal-solve', daemon=True).start()
        return future

    # -- start-up --------------------------------------------------------------------------
    def _publish_existing(self, path):
        """Publish the calibration already on disk, so the corrector starts with it."""
        if not os.path.exists(path):
            return
        try:
            cal, doc = load_calibration(path)
            with open(path, encoding='utf-8') as fh:
                text = fh.read()
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
