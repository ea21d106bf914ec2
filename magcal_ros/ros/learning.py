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
The calibration node's learning mode (issue 34; docs/design.md §3): :class:`LearningMixin`.

With ``learn`` the raw samples are matched into sets of its own for a
:class:`magcal_ros.core.live.learning.Learner`, refitted in a worker thread
(:func:`magcal_ros.pipeline.refit_recent`), each estimate published on ``calibration/learned``;
a ready proposal is adopted with ``auto_adopt`` or on ``calibration/adopt``.
"""
from collections import deque
from operator import attrgetter
import threading

from diagnostic_msgs.msg import DiagnosticStatus
from magcal_ros.core.live.learning import (ADOPTED, CHANGE, LearnConfig, Learner, READY,
                                           TRACKING, UNDETERMINED)
from magcal_ros.core.live.sync import StampMatcher
from magcal_ros.io.calfile import dump_calibration, save_calibration
from magcal_ros.pipeline import refit_recent
from magcal_ros.ros import params as prm
from magcal_ros.ros.diagnostics import fill, node_status
from magcal_ros.ros.run import yield_cpu
import numpy as np
from std_msgs.msg import String
from std_srvs.srv import Trigger

#: /diagnostics level of each learning state
_LEVEL = {TRACKING: DiagnosticStatus.OK, ADOPTED: DiagnosticStatus.OK,
          CHANGE: DiagnosticStatus.WARN, READY: DiagnosticStatus.WARN,
          UNDETERMINED: DiagnosticStatus.WARN}


def learning_specs():
    """Parameters of the learning mode (declared by the calibration node)."""
    return [
        prm.ParamSpec('learn', False, 'learning in operation: keep estimating from the recent '
                      'sets (and imu_topic), publish calibration/learned, detect persistent '
                      'changes and propose a validated calibration; no unit, read-only',
                      read_only=True),
        prm.ParamSpec('auto_adopt', False, 'adopt a validated proposal of the learning at '
                      'once (else on calibration/adopt); no unit'),
        prm.ParamSpec('learn_persist_s', 90.0, 'a change must last this long before it is '
                      'learned (shorter disturbances are not), s; read-only',
                      read_only=True, limits=(1.0, 1.0e5)),
        prm.ParamSpec('learn_window_s', 120.0, 'the recent data a learning refit sees, s; '
                      'read-only', read_only=True, limits=(5.0, 1.0e5)),
        prm.ParamSpec('learn_refit_period_s', 10.0, 'interval of the learning refits (the '
                      'estimate on calibration/learned), s; read-only',
                      read_only=True, limits=(1.0, 1.0e5)),
    ]


class LearningMixin:
    """The learning mode of the calibration node (its methods start with ``_learn``)."""

    def _learn_init(self, result_qos):
        """Declare the parameters; with ``learn`` set up the learner, topic and service."""
        self._specs_by_name.update(prm.declare(self, learning_specs()))
        self._learner = None
        self._learn_busy = False                 # a refit thread runs
        self._learn_lock = threading.RLock()     # the learner (callbacks, refits, adopt)
        self._learn_queue = deque()
        self._learn_errors = deque(maxlen=5)     # the latest refit failures (text)
        self._learn_failed = 0                    # refits that failed
        if not prm.value(self, 'learn'):
            return
        cfg = LearnConfig(persist_s=float(prm.value(self, 'learn_persist_s')),
                          window_s=float(prm.value(self, 'learn_window_s')),
                          refit_period_s=float(prm.value(self, 'learn_refit_period_s')))
        self._learner = Learner(self._n, cfg, self._aux_cols)
        s = prm.calibration_settings(self)
        self._learn_matcher = StampMatcher(self._n, s.stamp_tolerance_s)
        self._learned_pub = self.create_publisher(String, 'calibration/learned', result_qos)
        self._srv.append(self.create_service(Trigger, 'calibration/adopt', self._learn_on_adopt))
        self._updater.add('learning', lambda stat: fill(stat, self.learning_status()))

    learner = property(attrgetter('_learner'), doc='The :class:`Learner` (None without learn).')

    def _learn_activate(self, cal, doc, now=None):
        """Track the calibration made active (``doc`` its document)."""
        if self._learner is None:
            return
        f = (doc.get('field_reference') or {}).get('magnitude_nt', prm.value(self, 'field_nt'))
        with self._learn_lock:
            if self._learner.active is not cal:
                self._learner.set_active(cal, float(f), now)
        self._learn_field_ref = dict(doc.get('field_reference') or {})

    def _learn_raw(self, j, t, b):
        """Match a raw sample of sensor j (0-based, stamp t s, b (3,) nT) into learning sets."""
        done = self._learn_matcher.add(j, t, b)
        if not done:
            return
        with self._lock:
            temp = self._temp.copy()
            aux = dict(self._aux)
        self._learn_queue.extend((t_set, np.array(items), temp, aux) for _, t_set, items in done)
        self._learn_drain()

    def _learn_imu(self, t, q):
        """Queue an attitude (stamp s, unit quaternion (qw, qx, qy, qz)) for the learner."""
        self._learn_queue.append((t, None, q, None))

    def _learn_drain(self):
        """Hand the queued sets to the learner unless a refit holds it; start a due refit."""
        if not self._learn_lock.acquire(blocking=False):
            return                              # a refit holds it: the queue waits
        try:
            learner = self._learner
            now = None
            while self._learn_queue:
                t, raw, temp, aux = self._learn_queue.popleft()
                if raw is None:
                    learner.add_attitude(t, temp)
                    continue
                learner.add(t, raw, temp, aux)
                now = t
            if (now is not None and not self._learn_busy and learner.active is not None
                    and learner.refit_due(now)):
                self._learn_busy = True
                threading.Thread(target=self._learn_refit, args=(now,),
                                 name='magcal-learn', daemon=True).start()
        finally:
            self._learn_lock.release()

    def _learn_refit(self, now):
        """Worker thread: refit, publish the estimate, adopt when ready and auto_adopt."""
        yield_cpu()
        s = prm.calibration_settings(self)
        geometry = self._geometry(s) or {}
        ref = getattr(self, '_learn_field_ref', {})
        try:
            with self._learn_lock:
                learner = self._learner
                f = learner.field_nt
                p = learner.refit(now, lambda d, a, sensors: refit_recent(
                    d, a, f, geometry=geometry, field_reference=ref, sensors=sensors))
                self._learn_errors.clear()        # ERROR only while the latest failed
                if p is None:
                    return
                p.doc['provenance']['field_source'] = s.field_source
                self._learned_pub.publish(String(data=dump_calibration(p.doc)))
                if learner.state == READY and prm.value(self, 'auto_adopt'):
                    self._learn_adopt(now)
        except Exception as exc:      # noqa: B902 -- a refit must never end the node
            self._learn_errors.append(str(exc))
            self._learn_failed += 1
            self.get_logger().error(f'learning refit failed: {exc!r}')
        finally:
            self._learn_busy = False

    def _learn_adopt(self, now):
        """Adopt the ready proposal (under the learn lock); return (ok, text)."""
        learner = self._learner
        if learner.state != READY:
            return False, (f'no proposal ready: the learning is {learner.state!r}'
                           + ('' if learner.proposal is None else
                              f' (last proposal valid: {learner.proposal.valid})'))
        s = prm.calibration_settings(self)
        p = learner.adopt(now)
        p.doc['provenance']['source'] = 'learned (calibration_node learn)'
        try:
            save_calibration(s.calibration_file, p.doc, history=s.history)
        except Exception as exc:      # noqa: B902 -- written or not, say it
            self.get_logger().error(f'learned calibration adopted but not written: {exc}')
        self._result_pub.publish(String(data=dump_calibration(p.doc)))
        self._activate(p.calibration, p.doc)
        text = (f'adopted the learned calibration (sets stamped up to {now:.1f} s): held-out '
                f'residual {np.round(p.held_out_rms["active"], 2).tolist()} -> '
                f'{np.round(p.held_out_rms["proposal"], 2).tolist()} nT; undetermined '
                f'(held): {len(p.undetermined)}')
        self.get_logger().info(text)
        return True, text

    def _learn_on_adopt(self, request, response):
        if self._learner is None:
            ok, text = False, 'learning is off (parameter learn)'
        else:
            with self._learn_lock:
                ok, text = self._learn_adopt(self._learner.last_block_t or 0.0)
        response.success, response.message = ok, text
        return response

    def learning_status(self):
        """``DiagnosticStatus`` of the learning (``calibration_node: learning``)."""
        learner = self._learner
        with self._learn_lock:
            info = learner.status()
        state = info['state']
        level = _LEVEL.get(state, DiagnosticStatus.OK)
        if learner.active is None:
            message = 'learning waits for an active calibration (calibration/calibrate)'
        elif state == CHANGE:
            message = (f'change detected at {info.get("change_onset_s", 0.0):.1f} s: '
                       f'learned when it lasts {learner.config.persist_s:g} s')
        elif state == READY:
            message = 'proposal ready: validated on held-out data; call calibration/adopt'
        elif state == UNDETERMINED:
            message = ('not determined by the recent motion: the proposal does not lower the '
                       'held-out residual beyond the noise; keep moving')
        elif state == ADOPTED:
            message = f'adopted a learned calibration ({info["adoptions"]} so far)'
        else:
            message = 'tracking: the active calibration fits the recent data'
        if self._learn_errors:
            level = DiagnosticStatus.ERROR
            message += (f'; {self._learn_failed} refit(s) failed, the latest: '
                        f'{self._learn_errors[-1]}')
        return node_status(self, 'learning', level, message, info.items())
