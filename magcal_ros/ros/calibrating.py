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
The calibration node's solves (docs/design.md §3): :class:`CalibrationMixin`.

``calibration/calibrate`` (a :class:`magcal_ros.pipeline.CalibrationRequest` run as ``magcal
fit`` runs it; the calibration written, published, made active) and ``calibration/diagnose``
(:func:`magcal_ros.core.discovery.diagnose`, the HTML report), in a worker thread, on the
buffer's sets re-paired by :func:`magcal_ros.core.live.consistency.resync`.
"""
from functools import partial
import json
import os
import time

from magcal_ros.core.data.readings import leave_out_unphysical
from magcal_ros.core.effects.safety import culprit, EffectError
from magcal_ros.core.live.consistency import (DEFAULT_MAX_LAG, GROSS_FRACTION, LONG_MAX_LAG,
                                              resync)
from magcal_ros.core.model import DegenerateDataError, Model
from magcal_ros.core.model.notes import format_note
from magcal_ros.io.calfile import CalibrationFileError, dump_calibration, save_calibration
from magcal_ros.pipeline import (CalibrationRequest, diagnosis_base,
                                 run_request as run_calibration,
                                 summary_lines, tensor_figures)
from magcal_ros.ros import params as prm
from magcal_ros.ros.collection import reply, silent_sensors
import numpy as np
from std_msgs.msg import String

#: share of the sets the consistency check may drop before the fit; beyond, a refusal
MAX_INCONSISTENT_FRACTION = 0.1
#: a fit leaving a sensor this many times above the noise floor while the check flags more
#: than MAX_INCONSISTENT_FRACTION of its sets is refused (a missing effect: a few x; a
#: mis-paired array: hundreds)
OFF_FLOOR_FACTOR = 10.0

#: the summary's entries (planar, attitude-aided, site-gradient fits) the reply carries as is
_REPLY_KEYS = ('site_gradient_nt_per_m', 'site_gradient_stderr_nt_per_m', 'planar',
               'undetermined', 'heading_error_deg', 'attitude')


def _fmt_per_sensor(d, fmt='{:.2f}'):
    return ', '.join(f'{k}: {fmt.format(v)}' for k, v in d.items())


def _others(values):
    """Return the (S,) ``values`` of sensors 2..S by their number as str (a dict)."""
    return {str(j): v for j, v in enumerate(np.asarray(values)[1:].tolist(), start=2)}


def _not_diagnosed(reason, extra=None, **payload):
    """Reply (False, summary, payload and ``extra``) of a diagnose call that was refused."""
    return False, f'not diagnosed: {reason}', {'reason': reason, **payload, **(extra or {})}


def _not_calibrated(reason, extra=None, **payload):
    """Reply (False, summary, payload and ``extra``) of a calibrate call (the previous stays)."""
    return False, f'not calibrated: {reason}; previous calibration stays active', {
        'reason': reason, **payload, **(extra or {})}


class CalibrationMixin:
    """The calibrate and diagnose services of the calibration node."""

    async def _on_calibrate(self, request, response):
        return await self._solve(response, 'calibration', 'calibrate', True)

    async def _on_diagnose(self, request, response):
        return await self._solve(response, 'diagnosis', 'diagnose', False)

    async def _solve(self, response, call, service, calibrate):
        """Answer calibrate or diagnose: the solve in the worker thread, one at a time."""
        if not self._busy.acquire(blocking=False):
            return reply(response, False, 'a calibration is already running',
                         {'state': self._state})
        with self._lock:
            prev_state = self._state
            if calibrate:
                self._state = 'calibrating'
        try:
            ok, summary, payload = await (self._in_worker(self._calibrate, prev_state)
                                          if calibrate else self._in_worker(self._diagnose))
            return reply(response, ok, summary, payload)
        except Exception as exc:         # noqa: B902 -- a service must answer, never die
            return reply(response, False, *self._failed(call, service, exc))
        finally:
            if calibrate:
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
            silent = [] if state == 'idle' else silent_sensors(received)
            reason = (f'only {n_sets} complete sample sets collected, need at least '
                      f'{s.min_samples}' + (': call calibration/start and rotate the array'
                                            if state == 'idle' else
                                            '; ' + '; '.join(silent) if silent else
                                            ': keep rotating the array'))
            return _not_calibrated(reason, sets=n_sets)
        model = Model.from_spec(list(s.model), self._n)
        geometry = self._geometry(s)
        refused = partial(_not_calibrated, sets=n_sets, model=list(s.model))
        t0 = time.monotonic()
        try:
            data, screen, resync_payload, resync_lines = self._resync(data, epochs, s)
        except ValueError as exc:
            return refused(*self._named(exc, 'calibrate'))
        try:
            field_nt, field_ref = self._field(s, data.raw[0])
        except (ValueError, ImportError) as exc:
            return _not_calibrated(f'no field magnitude: {exc}', sets=n_sets)
        # what a turn leaves open (planar) is held at the active calibration of the same model
        active = self._active_cal
        request = CalibrationRequest(
            model=model, field_nt=field_nt, field_reference=field_ref, geometry=geometry,
            attitude=s.attitude_mode, planar=s.planar,
            prior_params=(active.params if active is not None
                          and active.model.spec() == model.spec() else None),
            robust=s.robust, constrained=s.constrained, exclude_outliers=s.exclude_outliers)
        try:
            run = run_calibration(data, request, screen=screen)
        except DegenerateDataError as exc:
            return refused(str(exc))
        except ValueError as exc:
            return refused(*self._named(exc, 'calibrate'))
        solve_s = time.monotonic() - t0
        refuse = (resync_payload or {}).get('refuse')
        if refuse:         # after the fit's own refusals (degenerate data, a stuck sensor)
            return refused(refuse, resync=resync_payload)
        refuse = self._inconsistent_and_off(resync_payload, run.summary, n_sets)
        if refuse:
            return refused(refuse, resync=resync_payload,
                           scalar_rms_after_nt=run.summary['scalar_rms_nt'])
        if not run.result.success:      # out of iterations: never installed
            return refused(f'the fit did not converge ({run.result.message})', converged=False)
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
            'calibration_file': s.calibration_file, 'field_reference': field_ref,
            'geometry': geometry, 'model': list(s.model), 'effects': summ['model'],
            'sets': n_sets, 'solve_s': round(solve_s, 2), 'converged': summ['converged'],
            'noise_floor_nt': summ['noise_floor_nt'],
            'scalar_rms_before_nt': summ['total_field_rms_before_nt'],
            'scalar_rms_after_nt': summ['scalar_rms_nt'],
            'vector_rms_after_nt': summ['vector_rms_nt'], 'robust': s.robust,
            'constrained': s.constrained, 'downweighted': summ['downweighted'],
            'warnings': summ['warnings'], 'resync': resync_payload,
            'outlier_sets_excluded': summ.get('outlier_sets_excluded', 0),
            'readings_left_out': summ.get('readings_left_out'),
            **tensor_figures(summ), **{k: summ[k] for k in _REPLY_KEYS if k in summ}}
        if 'tensor_rms_nt_per_m' in summ:
            payload['tensor_rms_components_after_nt_per_m'] = summ['tensor_rms_nt_per_m']
        if 'site_gradient_nt_per_m' in summ:
            payload['dropped_attitude_epochs'] = data.meta.get('dropped_attitude_epochs', 0)
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
        lines += summary_lines(summ, request) + [f'resync: {w}' for w in resync_lines]
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
            return _not_diagnosed(f'only {n_sets} complete sample sets collected, need '
                                  f'{s.min_samples}', sets=n_sets)
        model = Model.from_spec(list(s.model), self._n)
        try:                            # as in calibrate
            data, screen, resync_payload, _ = self._resync(data, epochs, s)
        except ValueError as exc:
            return _not_diagnosed(*self._named(exc, 'diagnose'), sets=n_sets)
        field_nt = s.field_nt
        try:                            # with imu_topic attitude-aided, as in calibrate
            base, constrained, aided = diagnosis_base(data, model, field_nt,
                                                      attitude=s.attitude_mode,
                                                      constrained=s.constrained)
            diag = diagnose(data, model, field_nt=field_nt, base=base, constrained=constrained,
                            baseline_m=s.baseline_m)
        except ValueError as exc:
            return _not_diagnosed(*self._named(exc, 'diagnose'), sets=n_sets)
        ranking = json.loads(diag.to_json())       # non-finite numbers as null
        report = write_report(s.report_dir, data, diagnosis=diag, baseline_m=s.baseline_m)
        ranking.update(report=os.fspath(report), resync=resync_payload,
                       readings_left_out=screen.to_dict())
        if aided is not None:
            ranking['attitude'] = aided
        verdict = ranking.get('verdict') or {}
        if verdict.get('effect', 'none') == 'none':
            head = (f'nothing missing: model {",".join(ranking["model"])} explains the data '
                    f'down to the noise floor ({ranking["noise_floor_nt"]:.2f} nT)')
        else:
            head = f'most likely missing effect: {verdict.get("token") or verdict["effect"]}'
        lines = [head] + ([verdict['reason']] if verdict.get('reason') else [])
        if diag.not_ruled_out:
            lines.append(diag.not_ruled_out_text())
        if ranking.get('findings'):       # model-free: what is left (core.discovery.findings)
            lines.append('left in the residuals: ' + '; '.join(
                f'{f["kind"]}' + (f' (add {f["token"]})' if f.get('token') else '')
                + ('' if f['sensor'] is None else f' on sensor {f["sensor"]}')
                for f in ranking['findings'][:4]))
        lines += [format_note(w) for w in screen.notes()]
        lines.append(f'HTML report: {ranking["report"]}')
        return True, '\n'.join(lines), ranking

    @staticmethod
    def _inconsistent_and_off(resync_payload, summ, n_sets):
        """
        Why a fit must not be activated (one line, or None): sensors off the floor.

        Names each sensor above :data:`OFF_FLOOR_FACTOR` x the noise floor while more than
        :data:`MAX_INCONSISTENT_FRACTION` of its sets are inconsistent with sensor 1.
        """
        if not resync_payload:
            return None
        floor = summ['noise_floor_nt']
        bad = {j: (c, summ['scalar_rms_nt'][j])
               for j, c in resync_payload['inconsistent_sets'].items()
               if c > MAX_INCONSISTENT_FRACTION * n_sets
               and summ['scalar_rms_nt'][j] > OFF_FLOOR_FACTOR * floor}
        if not bad:
            return None
        return ('the fit leaves ' + ', '.join(
            f'sensor {j} at {rms:.1f} nT with {c} of {n_sets} sets inconsistent with sensor 1'
            for j, (c, rms) in bad.items())
            + f' (noise floor {floor:.2f} nT): no pairing of its epochs fits those sets (a '
            'reader that lost pace at random: CPU starvation, a stalled link; or the sensors '
            'do not see one field): collect again (calibration/start), or run '
            'calibration/diagnose to see what the residual follows')

    def _resync(self, data, epochs, settings):
        """
        Screen, then re-pair sets paired from different epochs; (data, screen, payload, lines).

        Readings no field produces are left out first (a clipped axis of sensor 1 would make
        the others inconsistent with it; ``screen`` the ReadingScreen). Sets still inconsistent
        are dropped, up to :data:`MAX_INCONSISTENT_FRACTION` of them; beyond, none is and the
        payload's ``refuse`` says why no calibration may be made.
        """
        kept, _, screen = leave_out_unphysical(data)
        if kept is not data and epochs is not None:
            epochs = np.asarray(epochs)[screen.keep]
        data = kept
        if not settings.resync_sets or data.n_sensors < 2:
            return data, screen, None, []
        fixed, slips, dropped, gross = resync(data, epochs, drop_inconsistent=True)
        n_bad = slips.dropped_inconsistent
        refuse = None
        if n_bad > MAX_INCONSISTENT_FRACTION * data.n_samples:     # too many to drop
            fixed, slips, dropped, gross = resync(data, epochs)
            refuse = (
                f'{n_bad} of {data.n_samples} sets are inconsistent with sensor 1 at every '
                f'pairing within +-{DEFAULT_MAX_LAG} epochs (per sensor: '
                + ', '.join(f'{j}: {c}' for j, c in _others(slips.inconsistent).items())
                + f') and fit at one up to +-{LONG_MAX_LAG} epochs apart: the sensors were '
                'paired from epochs further apart (a reader that lost pace: CPU starvation, a '
                f'stalled link); more than {MAX_INCONSISTENT_FRACTION:.0%} of the sets, so none '
                'is dropped and no calibration is made: collect again (calibration/start), or '
                'set resync_sets false to fit the sets as paired')
            n_bad = 0
        payload = {
            'sets_repaired': _others(slips.n_slipped), 'sets_dropped': dropped,
            'sets_dropped_garbled': gross,
            'misfit_as_paired_nt': _others(np.round(slips.rms_as_paired_nt, 2)),
            'misfit_nt': _others(np.round(slips.rms_nt, 2)),
            'inconsistent_sets': _others(slips.inconsistent),
            'sets_dropped_inconsistent': n_bad, 'refuse': refuse}
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
        return fixed, screen, payload, lines

    def _named(self, exc, service):
        """(reason, payload entries) of an exception ending a call; an effect's is named."""
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
        return f'{call} failed: {reason}', {'error': reason, 'type': type(exc).__name__, **extra}
