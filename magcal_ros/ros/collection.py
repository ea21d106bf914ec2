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
The calibration node's collection (docs/design.md §3): :class:`CollectionMixin`.

The sensor callbacks (matching samples into sets while collecting, feeding the live residual
and the learning), ``calibration/start`` and ``calibration/reset``, the snapshot a solve or a
turn reads (with the attitude interpolated onto it), ``calibration/status`` and the
``calibration_node: buffer`` status; and the node's Trigger replies (:func:`reply`).
"""
import json
from operator import attrgetter
import time

from diagnostic_msgs.msg import DiagnosticStatus
from magcal_ros.core.model.identifiability import check_coverage
from magcal_ros.ros import params as prm
from magcal_ros.ros.conversions import msg_to_attitude, msg_to_field_nt, stamp_to_seconds
from magcal_ros.ros.diagnostics import node_status
import numpy as np
from std_msgs.msg import String

#: at most this many sets enter the coverage figures of the status message
_STATUS_SUBSAMPLE = 2000
#: longest first line of a service reply
HEADLINE = 100


def reply(response, success, summary, payload):
    """
    Fill a Trigger response: a short first line, more lines, newline, one JSON object.

    ``ros2 service call`` prints the message on one line: the first line is what a user reads.
    A long first line is broken after its lead (``not calibrated: <reason>`` becomes
    ``not calibrated:`` and the reason on the next line).
    """
    first, _, rest = summary.strip().partition('\n')
    lead, sep, reason = first.partition(': ')
    if len(first) > HEADLINE and sep:
        first = lead + ':\n' + reason
    summary = first + ('\n' + rest if rest else '')
    response.success = bool(success)
    response.message = summary + '\n' + json.dumps(payload, sort_keys=False)
    return response


def silent_sensors(received):
    """Name the sensors that sent nothing, or far less than the others (``received`` counts)."""
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


class SignalsMixin:
    """The latest temperatures and aux values (``_temp``, ``_aux``), fed to ``_live`` too."""

    def _temp_cb(self, j):
        def cb(msg):
            with self._lock:
                self._temp[j] = msg.temperature
            live = self._live
            if live is not None:
                live.set_temperature(j + 1, msg.temperature)
        return cb

    def _aux_cb(self, column):
        def cb(msg):
            with self._lock:
                self._aux[column] = float(msg.data)
            live = self._live
            if live is not None:
                live.set_aux(column, msg.data)
        return cb


class CollectionMixin(SignalsMixin):
    """The collection of sample sets of the calibration node, and its status."""

    @property
    def received(self):
        """(S,) raw samples taken per sensor since calibration/start (a copy; counts)."""
        return self._received.copy()

    imu_received = property(attrgetter('_imu_count'),
                            doc='Attitude (Imu) samples taken since calibration/start.')
    state = property(attrgetter('_state'), doc="'idle', 'collecting' or 'calibrating'.")

    def _on_start(self, request, response):
        if not self._busy.acquire(blocking=False):
            return self._reject_busy(response, 'start')
        try:
            dropped = self._clear('collecting')
            s = prm.calibration_settings(self)
            return reply(response, True,
                         f'collecting ({dropped} old sets dropped): rotate the array through '
                         f'many attitudes; calibrate after at least {s.min_samples} sets',
                         {'state': 'collecting', 'min_samples': s.min_samples,
                          'sets_dropped': dropped})
        finally:
            self._busy.release()

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
            return reply(response, True, f'reset: {dropped} sets dropped; {what}',
                         {'state': state, 'sets_dropped': dropped})
        finally:
            self._busy.release()

    def _reject_busy(self, response, service):
        """Answer a call that arrived during a calibration (the state is not touched)."""
        return reply(response, False, f'rejected: a calibration is running; call '
                     f'calibration/{service} again when it has finished',
                     {'state': self._state})

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

    def _raw_cb(self, j):
        def cb(msg):
            self._taken += 1
            collecting = self._collecting
            live = self._live
            if not collecting and live is None and self._learner is None:
                return
            t = stamp_to_seconds(msg.header.stamp)
            b = msg_to_field_nt(msg)
            if not np.all(np.isfinite(b)):
                return
            if self._learner is not None:
                self._learn_raw(j, t, b)
            if collecting:
                with self._lock:
                    self._received[j] += 1
                    for epoch, t_set, items in self._matcher.add(j, t, b):
                        self._buffer.append(epoch, t_set, np.array(items), self._temp, self._aux)
            if live is not None:
                self._residual(live, j + 1, t, b)
        return cb

    def _imu_cb(self, msg):
        attitude = msg_to_attitude(msg)
        if self._learner is not None and attitude is not None:
            self._learn_imu(*attitude)
        if not self._collecting:
            return
        with self._lock:
            if attitude is None:
                self._imu_refused += 1
                return
            self._imu[self._imu_count % len(self._imu)] = (attitude[0], *attitude[1])
            self._imu_count += 1

    def _snapshot(self):
        with self._lock:
            buf = self._buffer
            if not len(buf):
                return 0, None, None
            return len(buf), *self._attitude(buf.dataset(), buf.epochs(), buf.stamps())

    def _attitude(self, data, epochs, stamps):
        """
        Attach the collected attitude to (data, epochs) (under the lock).

        Interpolated at the sets' stamps (``stamps`` (N,) s, the Imu messages' clock), not at
        ``data.t``; sets outside the Imu messages' span are dropped; unchanged without any.
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
        out.meta['attitude_frame'] = 'ENU'     # sensor_msgs/Imu: body to ENU (REP 103)
        out.meta['attitude_source'] = f"sensor_msgs/Imu on {prm.value(self, 'imu_topic')}"
        return out, epochs[kept]

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
            missing.extend(silent_sensors(received))
        if n_sets < s.min_samples:
            missing.append(f'{s.min_samples - n_sets} more complete sample sets '
                           f'(have {n_sets}, need {s.min_samples})')
        eigenvalues = {}
        if raw is not None and raw.shape[1] >= 3:
            rep = check_coverage(raw)
            for j, v in rep['sensors'].items():
                out['coverage'][str(j)] = v['status']
                eigenvalues[str(j)] = [round(float(x), 4) for x in v['eigenvalues']]
            # partial or single-axis coverage is what the constrained (planar) mode is for
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
                    'field_source': s.field_source, 'max_samples': s.max_samples,
                    'coverage_eigenvalues': eigenvalues, 'buffer': buffer,
                    'incomplete_sets_dropped': dropped, 'out_of_order_dropped': out_of_order,
                    'stream_realignments': realigned, 'intake_dropped': self._intake.dropped,
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

    def buffer_status(self):
        """``DiagnosticStatus`` of the buffer: sets held of received, one in how many, span."""
        with self._lock:
            cov = self._buffer.coverage()
            cap = self._buffer.capacity
        message = 'no sample sets yet' if not cov['sets_received'] else (
            f'{cov["sets_held"]} of {cov["sets_received"]} sets held (one in {cov["stride"]}, at '
            f'most {cap}), spread over {100 * cov.get("fraction_of_run", 1.0):.0f} % of the '
            f'{cov["run_s"]:.0f} s run')
        return node_status(self, 'buffer', DiagnosticStatus.OK, message,
                           [*cov.items(), ('max_samples', cap)])
