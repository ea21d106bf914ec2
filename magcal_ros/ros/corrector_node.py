"""corrector_node: live correction of the array with the active calibration.

Topics (relative to the node namespace, default ``/magcal``; docs/design.md §3):

- subscribes ``sensor{j}/raw`` (sensor_msgs/MagneticField, T), ``sensor{j}/temperature``
  (sensor_msgs/Temperature; only while an effect of the calibration reads the temperature)
  and one std_msgs/Float64 topic per name in ``aux_topics`` (the signal of effect
  ``aux:aux_<name>``, latest value), all best effort (:data:`SENSOR_QOS`), and
  ``calibration/result`` (std_msgs/String YAML, reliable + transient local) for new
  calibrations without a restart;
- publishes ``sensor{j}/corrected`` (sensor_msgs/MagneticField, T, in the array frame, same
  stamp and frame_id as the raw sample, covariance sigma_j^2 A_j^-1 A_j^-T from the
  calibration's noise estimate) and ``gradient`` (std_msgs/Float64MultiArray, 3x3 row-major,
  T/m) from stamp-matched corrected samples of all sensors and the calibration's geometry;
- publishes its health on ``/diagnostics``: WARN without a usable calibration (then nothing
  is published), when a calibration was refused (the last good one stays active), or while a
  driven effect lacks its live signal.

Per message the work is a few 3x3 products: every matrix (A_j^-1, the covariance, the
gradient operator) is computed once when a calibration is installed.
"""
from collections import deque
import math
import os
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from magcal_ros.core.effects import SensorContext, SIGNALS
from magcal_ros.core.tensor import tensor_operator
from magcal_ros.io.calfile import CalibrationFileError, load_calibration, parse_calibration
from magcal_ros.ros import params as prm
from magcal_ros.ros.calibration_node import RESULT_QOS, SENSOR_QOS
from magcal_ros.ros.conversions import (covariance_to_t2, msg_to_field_nt, set_field_nt,
                                        stamp_to_seconds, tensor_to_msg)
from magcal_ros.ros.run import spin_node
from magcal_ros.ros.sync import StampMatcher
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import MagneticField, Temperature
from std_msgs.msg import Float64, Float64MultiArray, String

#: consecutive raw samples further apart than this give no field-rate estimate, s
_MAX_RATE_GAP_S = 1.0
#: arrivals per stream used to estimate its sample period (field-rate effect)
_PERIOD_WINDOW = 200


class MissingSignal(Exception):
    """A driven effect of the calibration has no live signal yet (the message says which)."""


class _SensorCorrection:
    """Live correction of one sensor: the calibration's own correction plus signal checks."""

    def __init__(self, cal, j):
        self.cal = cal
        self.j = j
        self.a_inv = cal.correction_matrix(j)
        # the signals the calibration's effects declare (Effect.signals); the stamp ('time')
        # is always there
        self.needs = set(cal.signals(j)) - {'time'}
        self.driven = bool(cal.driven_effects(j))
        self.offset = cal.offset(j)
        sigma = float(cal.sigma_nt[j - 1])
        # corrected = A^-1 raw: white raw noise sigma^2 I maps to sigma^2 A^-1 A^-T (nT^2)
        self.cov_nt2 = (sigma ** 2 * self.a_inv @ self.a_inv.T
                        if np.isfinite(sigma) and sigma > 0 else None)
        if self.cov_nt2 is not None:
            self.cov_nt2 = 0.5 * (self.cov_nt2 + self.cov_nt2.T)
        # validated and converted once, not per message (it was 70 % of the callback)
        self.cov_t2 = covariance_to_t2(self.cov_nt2)

    def correct(self, raw, t, temp, aux, rate):
        """Corrected field (3,) nT in the array frame; raises MissingSignal."""
        if not self.driven:
            return self.a_inv @ (raw - self.offset)          # the common case: one 3x3 product
        ctx = SensorContext(
            t=np.array([t]), temp=np.array([temp]) if np.isfinite(temp) else None,
            aux={k: np.array([v]) for k, v in aux.items()},
            raw_rate=None if rate is None else rate[None])
        for name in sorted(self.needs):
            if not (name in SIGNALS or name.startswith('aux_')) or not ctx.has(name):
                raise MissingSignal(self._waiting(name))
        return self.cal.correct(self.j, raw, ctx)

    def _waiting(self, name):
        """Why the correction waits for the signal ``name``."""
        if name == 'temperature':
            return (f'sensor {self.j}: waiting for sensor{self.j}/temperature (the '
                    'calibration has an effect that reads the temperature)')
        if name == 'field_rate':
            return f'sensor {self.j}: field rate needs two consecutive samples'
        if name.startswith('aux_'):
            return (f'sensor {self.j}: waiting for auxiliary channel {name} (topic '
                    f'{name[4:]} named in aux_topics)')
        return (f'sensor {self.j}: the calibration needs the signal {name!r}, which this node '
                'does not receive')


class LiveCorrection:
    """A calibration made ready for per-message correction.

    Parameters
    ----------
    cal : magcal_ros.core.model.Calibration
    doc : dict
        The calibration document (geometry, provenance).
    n_sensors : int
        Sensors the node subscribes; a calibration for another count is refused.
    """

    def __init__(self, cal, doc, n_sensors):
        if cal.n_sensors != n_sensors:
            raise CalibrationFileError(f'the calibration is for {cal.n_sensors} sensors but '
                                       f'this corrector handles {n_sensors} (n_sensors)')
        self.sensors = [_SensorCorrection(cal, j) for j in range(1, n_sensors + 1)]
        self.model = list(doc.get('model') or cal.model.spec())
        prov = doc.get('provenance') or {}
        self.created = str(prov.get('created', 'unknown time'))
        geometry = doc.get('geometry') or {}
        self.gradient_op = None
        self.no_gradient_reason = None
        pos = geometry.get('positions_m')
        if pos is None:
            self.no_gradient_reason = 'the calibration has no array geometry (positions_m)'
        else:
            try:
                pos = np.asarray(pos, float)
                if pos.shape != (n_sensors, 3):
                    raise ValueError(f'positions_m has shape {pos.shape}, expected '
                                     f'({n_sensors}, 3)')
                # rows 3.. of the operator: G row-major (9, 3 S), paper 004 eq. 1 for the cross
                self.gradient_op = tensor_operator(pos)[3:]
            except ValueError as exc:
                self.no_gradient_reason = f'no gradient: {exc}'

    def describe(self):
        """One line: model and creation time."""
        return f'model {",".join(self.model)} created {self.created}'


class CorrectorNode(Node):
    """Publish corrected fields and the gradient tensor of the array."""

    def __init__(self, **kwargs):
        super().__init__('corrector_node', **kwargs)
        prm.declare(self, [prm.N_SENSORS])
        specs = prm.corrector_specs()
        self._specs = prm.declare(self, specs)
        self._specs[prm.N_SENSORS.name] = prm.N_SENSORS
        self.add_on_set_parameters_callback(self._on_set_parameters)
        s = prm.corrector_settings(self)
        self._n = s.n_sensors
        self._publish_gradient = s.publish_gradient

        self._live = None
        self._source = None
        self._refused = None
        self._missing = {}
        self._temp = np.full(self._n, np.nan)
        self._aux = {}
        self._prev = [None] * self._n          # (t s, raw (3,) nT) of the previous sample
        self._arrivals = [deque(maxlen=_PERIOD_WINDOW) for _ in range(self._n)]
        self._matcher = StampMatcher(self._n, s.stamp_tolerance_s)
        self._counts = np.zeros(self._n, int)     # corrected samples published per sensor
        self._received = 0                          # raw samples taken (all sensors)
        self._n_gradient = 0

        self._pub_corr = [self.create_publisher(MagneticField, f'sensor{j}/corrected', 10)
                          for j in range(1, self._n + 1)]
        self._pub_grad = self.create_publisher(Float64MultiArray, 'gradient', 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._subs = []
        for j in range(1, self._n + 1):
            self._subs.append(self.create_subscription(
                MagneticField, f'sensor{j}/raw', self._raw_cb(j - 1), SENSOR_QOS))
        self._temp_subs = []     # created while the calibration has a temperature effect
        for name in s.aux_topics:
            self._subs.append(self.create_subscription(
                Float64, name, self._aux_cb('aux_' + name), SENSOR_QOS))
        self._subs.append(self.create_subscription(String, 'calibration/result',
                                                   self._result_cb, RESULT_QOS))
        self._load_file(s.calibration_file)
        self._timer = self.create_timer(s.diagnostics_period_s, self._publish_diagnostics)
        self._publish_diagnostics()

    # -- parameters ------------------------------------------------------------------------

    def _on_set_parameters(self, parameters):
        result = prm.validate(self._specs, parameters)
        if result.successful:
            for p in parameters:
                if p.name == 'stamp_tolerance_s':
                    self._matcher.tolerance_s = float(p.value)
                elif p.name == 'publish_gradient':
                    self._publish_gradient = bool(p.value)
        return result

    # -- calibrations ----------------------------------------------------------------------

    def _install(self, cal, doc, source):
        live = LiveCorrection(cal, doc, self._n)
        self._live = live
        self._source = source
        self._refused = None
        self._missing.clear()
        self._matcher.reset()
        self._follow_temperature(any('temperature' in sc.needs for sc in live.sensors))
        self.get_logger().info(f'using the calibration from {source} ({live.describe()})')
        if live.no_gradient_reason:
            self.get_logger().warning(live.no_gradient_reason)

    def _follow_temperature(self, needed):
        """Subscribe sensor{j}/temperature only when a temperature effect needs it."""
        if needed and not self._temp_subs:
            self._temp_subs = [self.create_subscription(
                Temperature, f'sensor{j}/temperature', self._temp_cb(j - 1), SENSOR_QOS)
                for j in range(1, self._n + 1)]
        elif not needed and self._temp_subs:
            for sub in self._temp_subs:
                self.destroy_subscription(sub)
            self._temp_subs = []
            self._temp[:] = np.nan

    def _refuse(self, source, exc):
        keep = (f'keeping the calibration from {self._source} ({self._live.describe()})'
                if self._live else 'no calibration is active')
        self._refused = f'refused the calibration from {source}: {exc}; {keep}'
        self.get_logger().error(self._refused)

    def _load_file(self, path):
        if not os.path.exists(path):
            self.get_logger().warning(
                f'no calibration file {path}: nothing is published until a calibration '
                'arrives on calibration/result')
            return
        try:
            cal, doc = load_calibration(path)
            self._install(cal, doc, path)
        except CalibrationFileError as exc:
            self._refuse(path, exc)

    def _result_cb(self, msg):
        source = 'calibration/result'
        try:
            cal, doc = parse_calibration(msg.data, source)
            self._install(cal, doc, source)
        except CalibrationFileError as exc:
            self._refuse(source, exc)
        self._publish_diagnostics()

    # -- sensor callbacks ------------------------------------------------------------------

    def _temp_cb(self, j):
        def cb(msg):
            self._temp[j] = msg.temperature
        return cb

    def _aux_cb(self, column):
        def cb(msg):
            self._aux[column] = float(msg.data)
        return cb

    def _raw_cb(self, j):
        pub = self._pub_corr[j]

        def cb(msg):
            self._received += 1
            t = stamp_to_seconds(msg.header.stamp)
            v = msg.magnetic_field
            finite = math.isfinite(v.x) and math.isfinite(v.y) and math.isfinite(v.z)
            raw = msg_to_field_nt(msg)
            prev = self._prev[j]
            self._prev[j] = (t, raw)
            live = self._live
            if live is None or not finite:
                return
            arrivals = self._arrivals[j]
            arrivals.append(t)
            rate = None
            if prev is not None and t - prev[0] <= _MAX_RATE_GAP_S and len(arrivals) > 10:
                # consecutive samples of one stream are one period apart; their stamps are
                # not (several samples read at once share one), so use the mean period
                period = (arrivals[-1] - arrivals[0]) / (len(arrivals) - 1)
                if period > 0:
                    rate = (raw - prev[1]) / period       # nT/s, backward difference
            sc = live.sensors[j]
            try:
                b = sc.correct(raw, t, self._temp[j], self._aux, rate)
            except MissingSignal as exc:
                self._missing[j] = str(exc)
                return
            if j in self._missing:
                del self._missing[j]
            # the incoming message becomes the outgoing one: same header (stamp, frame),
            # corrected field and its covariance (a new message per sample cost ~10 us, a
            # quarter of the Python work of the callback; bench/live.py)
            set_field_nt(msg, b, sc.cov_t2)
            pub.publish(msg)
            self._counts[j] += 1
            if self._publish_gradient and live.gradient_op is not None:
                for _, _, fields in self._matcher.add(j, t, b):
                    g = live.gradient_op @ np.concatenate(fields)      # (9,) nT/m
                    self._pub_grad.publish(tensor_to_msg(g.reshape(3, 3), check=False))
                    self._n_gradient += 1
        return cb

    # -- diagnostics -----------------------------------------------------------------------

    def diagnostic_status(self):
        """Return the node's ``diagnostic_msgs/DiagnosticStatus``."""
        st = DiagnosticStatus(name=f'{self.get_name()}: correction',
                              hardware_id=self.get_namespace())
        problems = []
        if self._live is None:
            problems.append('no calibration: publishing nothing (run calibration/calibrate or '
                            'set calibration_file)')
        if self._refused:
            problems.append(self._refused)
        problems.extend(self._missing[j] for j in sorted(self._missing))
        if self._live is not None and self._live.no_gradient_reason:
            problems.append(self._live.no_gradient_reason)
        if problems:
            st.level = DiagnosticStatus.WARN
            st.message = '; '.join(problems)
        else:
            st.level = DiagnosticStatus.OK
            st.message = f'correcting with the calibration from {self._source}'
        values = [('calibration_source', self._source or ''),
                  ('calibration', self._live.describe() if self._live else 'none'),
                  ('last_refused', self._refused or ''),
                  ('gradient_published', str(self._n_gradient)),
                  ('incomplete_sets_dropped', str(self._matcher.incomplete))]
        values += [(f'sensor{j + 1}_corrected_published', str(c))
                   for j, c in enumerate(self._counts)]
        st.values = [KeyValue(key=k, value=v) for k, v in values]
        return st

    def _publish_diagnostics(self):
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostic_status()]
        self._pub_diag.publish(arr)


def main(args=None):
    """Run corrector_node (``ros2 run magcal_ros corrector_node``)."""
    return spin_node(CorrectorNode, 'corrector_node', args)


if __name__ == '__main__':
    sys.exit(main())
