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
corrector_node: live correction of the array with the active calibration.

Topics and parameters: docs/design.md §3 (``sensor{j}/temperature`` is taken only while an
effect reads it; ``calibration/result`` installs a new calibration without a restart). On
``/diagnostics``: WARN without a usable calibration (nothing is published), after a refused
one (the last good one stays), while a driven effect lacks its signal, or when more than
:data:`PAIRING_WARN_SHARE` of the sets failed the pairing check; ERROR naming an effect whose
code raised (that sensor's sample is not published; the others go on). The correction, the
pairing of the tensor's sets and its check, and the site shift subtracted in a stationary test
(``subtract_site_gradient``, docs/site_gradient.md) are
:class:`magcal_ros.core.live.corrector.LiveCorrector`'s (no ROS).
"""
import importlib
import math
from operator import attrgetter
import os
import sys
import threading

from diagnostic_msgs.msg import DiagnosticStatus
from magcal_ros.core.effects.safety import EffectError, EffectErrors
from magcal_ros.core.live.corrector import LiveCorrector, MissingSignal, PAIRING_FALSE_ALARM
from magcal_ros.io.calfile import CalibrationFileError, load_calibration, parse_calibration
from magcal_ros.pipeline import array_geometry, geometry_mismatch, tensor_undetermined
from magcal_ros.ros import params as prm
from magcal_ros.ros.calibration_node import RESULT_QOS, SENSOR_QOS
from magcal_ros.ros.collection import SignalsMixin
from magcal_ros.ros.conversions import (correct_msg_linear, covariance_to_t2,
                                        fill_gradient_stamped, gradient_covariance_to_t2,
                                        linear_to_t, msg_to_field_nt, set_field_nt,
                                        stamp_to_seconds, tensor_to_msg, transform_msg)
from magcal_ros.ros.diagnostics import EffectErrorsMixin, fill, node_status, Updater
from magcal_ros.ros.run import DEFAULT_NAMESPACE, spin_node
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import MagneticField, Temperature
from std_msgs.msg import Float64, Float64MultiArray, String


#: share of the sets since the last diagnostics report that may fail the pairing check
#: before the status is WARN (a lost sample costs one set)
PAIRING_WARN_SHARE = 0.01
#: the parameters a running node follows: its attribute and the value's conversion (start-up
#: values set the same way)
_SETTABLE = {'stamp_tolerance_s': ('_tolerance_s', float),
             'publish_gradient': ('_publish_gradient', bool),
             'subtract_site_gradient': ('_subtract_site', bool),
             'site_attitude': ('_site_attitude', lambda v: tuple(float(x) for x in v))}


def _optional(module, name):
    """(object, None) if ``module`` imports and has ``name``, else (None, the reason)."""
    try:
        return getattr(importlib.import_module(module), name), None
    except (ImportError, AttributeError) as exc:
        return None, f'{module}.{name} is not importable ({exc})'


class CorrectorNode(SignalsMixin, EffectErrorsMixin, Node):
    """Publish corrected fields and the gradient tensor of the array."""

    def __init__(self, **kwargs):
        kwargs.setdefault('namespace', DEFAULT_NAMESPACE)    # a __ns remap overrides it
        super().__init__('corrector_node', **kwargs)
        self._specs, plugins = prm.declare_node(self, prm.corrector_specs)
        s = prm.corrector_settings(self)
        self._n = s.n_sensors
        for name, (attr, convert) in _SETTABLE.items():
            setattr(self, attr, convert(getattr(s, name)))
        self._site_shift = None        # (S, 3) nT subtracted in a stationary test, or None
        self._frame = s.array_frame_id          # '': each input's own frame_id
        # the gradient topics exist only when the geometry determines the tensor
        self._geometry = array_geometry(self._n, s.sensor_positions_m, s.baseline_m)
        self._no_tensor = tensor_undetermined(
            None if self._geometry is None else self._geometry['positions_m'])

        self._live = self._source = self._refused = None
        self._missing = {}
        self._effect_errors = EffectErrors()     # of the active calibration's effect code
        self._lock = threading.Lock()             # the latest signals (SignalsMixin)
        self._temp = np.full(self._n, np.nan)
        self._aux = {}
        self._cov_t2 = [None] * self._n          # per sensor (9,) T^2 of the active calibration
        self._fast = [None] * self._n            # per sensor linear_to_t() or None (see _raw_cb)
        self._gradient_on = False                # the set matcher is being fed
        self._grad_cov_t2 = None                # (81,) (T/m)^2
        self._counts = np.zeros(self._n, int)     # corrected samples published per sensor
        self._received = 0                          # raw samples taken (all sensors)
        self._n_gradient = 0
        self._pairing_seen = (0, 0)                # (failed, complete) at the last report

        self._pub_corr = [self.create_publisher(MagneticField, f'sensor{j}/corrected', 10)
                          for j in range(1, self._n + 1)]
        self._pub_grad = self._pub_stamped = self._stamped_msg = None
        self._grad_msg = tensor_to_msg(np.zeros((3, 3)))          # reused per tensor
        self._stamped_cls, reason = _optional('magcal_interfaces.msg', 'GradientTensorStamped')
        if self._no_tensor is not None:
            # not advertised at all: a subscriber sees no publisher, the log says why once
            self._stamped_cls = None
            self.get_logger().warning(f'gradient and gradient_stamped are not advertised: '
                                      f'{self._no_tensor}')
        else:
            self._pub_grad = self.create_publisher(Float64MultiArray, 'gradient', 10)
            if self._stamped_cls is None:
                self.get_logger().warning(f'not publishing gradient_stamped: {reason}; build '
                                          'the magcal_interfaces package (README: Live: ROS 2)')
            else:
                self._pub_stamped = self.create_publisher(self._stamped_cls,
                                                          'gradient_stamped', 10)
        broadcaster, reason = _optional('tf2_ros', 'StaticTransformBroadcaster')
        self._tf = None if broadcaster is None else broadcaster(self)
        if broadcaster is None:
            self.get_logger().info(f'not publishing the static transforms {self._frame} -> '
                                   f'fluxgate{{j}}: {reason}')
        self._subs = [self.create_subscription(MagneticField, topic, self._raw_cb(j), SENSOR_QOS)
                      for j, topic in enumerate(s.input_topics)]
        self._temp_subs = []     # created while the calibration has a temperature effect
        self._subs += [self.create_subscription(Float64, name, self._aux_cb('aux_' + name),
                                                SENSOR_QOS) for name in s.aux_topics]
        self._subs.append(self.create_subscription(String, 'calibration/result',
                                                   self._result_cb, RESULT_QOS))
        if plugins:
            self.get_logger().info(f'plug-in effects loaded: {plugins}')
        self._load_file(s.calibration_file)
        self._updater = Updater(self, s.diagnostics_period_s)
        self._updater.setHardwareID(self.get_namespace())
        self._updater.add('correction', lambda stat: fill(stat, self.diagnostic_status()))
        self._updater.force_update()

    # -- read-only state (in-process users and tests; ROS users see it on /diagnostics) ----
    received = property(attrgetter('_received'), doc='Raw samples taken so far, all sensors.')
    calibration_source = property(attrgetter('_source'), doc='Where the active calibration '
                                  "came from (file path or 'calibration/result').")
    refusal = property(attrgetter('_refused'), doc='Why the last calibration offered was refused '
                       '(None after one was installed).')

    @property
    def queued(self):
        """Count the samples per sensor waiting for a complete set (S counts; zeros when idle)."""
        live = self._live
        return live.matcher.queued if live is not None else (0,) * self._n

    @property
    def calibration(self):
        """Return the active :class:`~magcal_ros.core.model.Calibration`, or None."""
        return None if self._live is None else self._live.cal

    # -- parameters ------------------------------------------------------------------------
    def _on_set_parameters(self, parameters):
        result = prm.validate(self._specs, parameters)
        if result.successful:
            for p in parameters:
                if p.name in _SETTABLE:
                    attr, convert = _SETTABLE[p.name]
                    setattr(self, attr, convert(p.value))
            if self._live is not None:
                self._live.matcher.tolerance_s = self._tolerance_s
            self._update_site_shift()
        return result

    def _update_fast_path(self):
        """Sensors corrected in tesla by A^-1 (raw - o) alone (no driven effect, no shift)."""
        live = self._live
        linear = ([None] * self._n if live is None or self._site_shift is not None
                  else [live.linear(j) for j in range(1, self._n + 1)])
        self._fast = [None if lin is None else linear_to_t(*lin) for lin in linear]

    def _update_site_shift(self):
        live = self._live
        try:
            self._site_shift = (live.site_shift(self._site_attitude)
                                if self._subtract_site and live is not None else None)
        except EffectError as exc:
            self._site_shift = None
            self._effect_error(exc, 'nothing is subtracted')
        self._update_fast_path()

    # -- calibrations ----------------------------------------------------------------------
    def _install(self, cal, doc, source):
        mismatch = geometry_mismatch(doc.get('geometry'), self._geometry)
        if mismatch:
            raise CalibrationFileError(mismatch)
        try:
            live = LiveCorrector(cal, self._n, (doc.get('geometry') or {}).get('positions_m'),
                                 self._tolerance_s, field_nt=(doc.get('field_reference') or {})
                                 .get('magnitude_nt'))
        except EffectError as exc:
            self._effect_error(exc, 'the calibration was refused')
            raise CalibrationFileError(str(exc)) from exc
        except ValueError as exc:
            raise CalibrationFileError(str(exc)) from exc
        live.temp[:] = self._temp
        live.aux.update(self._aux)
        # validated and converted once, not per message
        self._cov_t2 = [covariance_to_t2(live.published_covariance_nt2(j))
                        for j in range(1, self._n + 1)]
        self._grad_cov_t2 = gradient_covariance_to_t2(live.gradient_cov_nt2)
        if self._stamped_cls is not None:
            # one message object per tensor topic, reused: its covariance is set here once
            self._stamped_msg = self._stamped_cls()
            self._stamped_msg.tensor_covariance = self._grad_cov_t2
        self._live = live
        self._model = list(doc.get('model') or cal.model.spec())
        self._created = str((doc.get('provenance') or {}).get('created', 'unknown time'))
        self._source = source
        self._refused = None
        self._missing.clear()
        self._effect_errors.clear()
        self._follow_temperature(live.needs_temperature)
        self._update_site_shift()
        self.get_logger().info(f'using the calibration from {source} ({self._describe()})')
        if live.no_gradient_reason and self._no_tensor is None:
            self.get_logger().warning(live.no_gradient_reason)
        self._send_transforms(live)

    def _describe(self):
        """One line: model and creation time of the active calibration."""
        return f'model {",".join(self._model)} created {self._created}'

    def _send_transforms(self, live):
        """Send the static transforms array -> fluxgate{j} of the calibration (with tf2_ros)."""
        if self._tf is None or not self._frame:
            return
        frames = live.sensor_frames()
        if not frames:
            self.get_logger().warning(f'no static transforms: {live.no_gradient_reason}')
            return
        stamp = self.get_clock().now()
        self._tf.sendTransform([transform_msg(self._frame, f'fluxgate{j}', rot, pos, stamp)
                                for j, (rot, pos) in enumerate(frames, start=1)])

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
        keep = (f'keeping the calibration from {self._source} ({self._describe()})'
                if self._live else 'no calibration is active')
        self._refused = f'refused the calibration from {source}: {exc}; {keep}'
        self.get_logger().error(self._refused)

    def _load_file(self, path):
        if not os.path.exists(path):
            self.get_logger().warning(
                f'no calibration file {path}: nothing is published until a calibration '
                'arrives on calibration/result')
            return
        self._offer(path, load_calibration, path)

    def _result_cb(self, msg):
        self._offer('calibration/result', parse_calibration, msg.data, 'calibration/result')
        self._updater.force_update()

    def _offer(self, source, read, *args):
        """Install the calibration ``read(*args)`` gives, or refuse it (the active one stays)."""
        try:
            self._install(*read(*args), source)
        except CalibrationFileError as exc:
            self._refuse(source, exc)

    # -- sensor callbacks (temperature and aux: SignalsMixin) -------------------------------
    def _gradient_wanted(self):
        """
        Tell whether someone subscribes a gradient topic (checked per sample: ~1 us).

        Without subscribers no set is matched; the first one starts the matcher afresh.
        """
        on = self._pub_grad is not None and self._publish_gradient and (
            self._pub_grad.get_subscription_count() > 0 or (
                self._pub_stamped is not None
                and self._pub_stamped.get_subscription_count() > 0))
        if on and not self._gradient_on and self._live is not None:
            self._live.matcher.reset()
        self._gradient_on = on
        return on

    def _raw_cb(self, j):
        pub = self._pub_corr[j]
        sensor = j + 1

        def cb(msg):
            self._received += 1
            live = self._live
            v = msg.magnetic_field
            if live is None or not (math.isfinite(v.x) and math.isfinite(v.y)
                                    and math.isfinite(v.z)):
                return
            fast = self._fast[j]
            gradient = self._gradient_wanted() and live.gradient_op is not None
            # the incoming message becomes the outgoing one (cheaper than a new one; bench/live.py)
            if fast is not None:
                correct_msg_linear(msg, fast, self._cov_t2[j])
                b = msg_to_field_nt(msg) if gradient else None
                t = stamp_to_seconds(msg.header.stamp) if gradient else None
            else:
                t = stamp_to_seconds(msg.header.stamp)
                try:
                    b = live.correct(sensor, t, msg_to_field_nt(msg))
                except MissingSignal as exc:
                    self._missing[j] = str(exc)
                    return
                except EffectError as exc:
                    # contained: this sample is not published, the node and the others go on
                    self._effect_error(exc, f'sensor {sensor} samples not published')
                    return
                if j in self._missing:
                    del self._missing[j]
                if self._site_shift is not None:
                    b = b - self._site_shift[j]         # stationary test: the anomaly only
                set_field_nt(msg, b, self._cov_t2[j])
            if self._frame:
                msg.header.frame_id = self._frame
            pub.publish(msg)
            self._counts[j] += 1
            if gradient:
                for t_set, g in live.gradients(sensor, t, b):
                    self._pub_grad.publish(tensor_to_msg(g, check=False, out=self._grad_msg))
                    if self._pub_stamped is not None:
                        self._pub_stamped.publish(fill_gradient_stamped(
                            self._stamped_msg, t_set, self._frame or prm.DEFAULT_ARRAY_FRAME_ID,
                            g, None))
                    self._n_gradient += 1
        return cb

    # -- diagnostics -----------------------------------------------------------------------
    def diagnostic_status(self):
        """Return the node's ``diagnostic_msgs/DiagnosticStatus``."""
        errors = self._effect_errors
        problems = [f'effect code failed: {errors.summary()}'] if errors else []
        if self._live is None:
            problems.append('no calibration: publishing nothing (run calibration/calibrate or '
                            'set calibration_file)')
        if self._refused:
            problems.append(self._refused)
        problems.extend(self._missing[j] for j in sorted(self._missing))
        if (self._live is not None and self._live.no_gradient_reason
                and self._no_tensor is None):
            problems.append(self._live.no_gradient_reason)
        if self._subtract_site and self._live is not None and self._site_shift is None:
            problems.append('subtract_site_gradient is set but the calibration has no '
                            'site_gradient: nothing is subtracted (calibrate with model '
                            "['base', 'site_gradient'] and an imu_topic)")
        pairing = self._pairing_report()
        if pairing:
            problems.append(pairing)
        level = (DiagnosticStatus.ERROR if errors else DiagnosticStatus.WARN if problems
                 else DiagnosticStatus.OK)
        message = ('; '.join(problems) if problems else
                   f'correcting with the calibration from {self._source}')
        m = self._live.matcher if self._live else None
        values = [('calibration_source', self._source or ''),
                  ('calibration', self._describe() if self._live else 'none'),
                  ('last_refused', self._refused or ''),
                  ('gradient_published', self._n_gradient),
                  ('incomplete_sets_dropped', m.incomplete if m else 0),
                  ('pairing_check', self._describe_check()),
                  ('sets_failed_pairing_check', m.rejected if m else 0),
                  ('streams_re_paired', m.repaired if m else 0),
                  ('gradient', 'advertised' if self._no_tensor is None else
                   f'not advertised: {self._no_tensor}'),
                  ('gradient_stamped', 'published' if self._pub_stamped else
                   f'not advertised: {self._no_tensor}' if self._no_tensor else
                   'not published: magcal_interfaces is not importable'),
                  ('geometry', 'none' if self._geometry is None else
                   self._geometry['positions_m']),
                  ('frame_id', self._frame)]
        values += [(f'sensor{j + 1}_corrected_published', c) for j, c in enumerate(self._counts)]
        values += self._effect_error_values()
        return node_status(self, 'correction', level, message, values)

    def _describe_check(self):
        """One line: how the sets of the tensor are checked."""
        live = self._live
        if live is None:
            return 'no calibration'
        if live.no_check_reason:
            return live.no_check_reason
        return (f'chi-square of {live.pairing_dof} redundant components <= '
                f'{live.pairing_threshold:.1f} (false alarm {PAIRING_FALSE_ALARM:g} per set)')

    def _pairing_report(self):
        """Return the problem if too many sets failed the check since the last report."""
        live = self._live
        if live is None:
            return None
        m = live.matcher
        failed, complete = self._pairing_seen
        if m.rejected < failed or m.complete < complete:
            failed = complete = 0               # a new calibration: a new matcher
        self._pairing_seen = (m.rejected, m.complete)
        failed, complete = m.rejected - failed, m.complete - complete
        if failed <= PAIRING_WARN_SHARE * (failed + complete):
            return None
        return (f'{failed} of {failed + complete} sets since the last report failed the '
                'pairing check and gave no tensor (streams mis-paired under load, or a '
                'calibration that no longer fits: see calibration/residual)')


def main(args=None):
    """Run corrector_node (``ros2 run magcal_ros corrector_node``)."""
    return spin_node(CorrectorNode, 'corrector_node', args)


if __name__ == '__main__':
    sys.exit(main())
