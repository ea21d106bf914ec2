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

"""The error ladder: diagnose, add the verdict, refit, until nothing is missing."""
from dataclasses import dataclass, field

from magcal_ros.core.data.noise import data_noise_floor, NoiseFloor
from magcal_ros.core.discovery.candidates import extend_model
from magcal_ros.core.discovery.constants import DEFAULT_FOLDS
from magcal_ros.core.discovery.measures import dof_factor, evaluate_residuals
from magcal_ros.core.discovery.results import compact_spec
from magcal_ros.core.discovery.run import diagnose, report_progress
from magcal_ros.core.discovery.validation import cross_validate
from magcal_ros.core.model.fitting import fit
import numpy as np


@dataclass(frozen=True, eq=False)
class LadderStep:
    """
    One rung: a model (spec), the token ``added`` (None at the start), its fit and RMS (nT).

    ``scalar_rms_nt``, ``vector_rms_nt``: {sensor: RMS}; ``residual_rms_nt``, ``cv_rms_nt``:
    combined in-sample and held-out (or None) RMS.
    """

    model: tuple
    added: str | None
    n_params: int
    scalar_rms_nt: dict
    vector_rms_nt: dict
    residual_rms_nt: float
    cv_rms_nt: float | None
    cv_per_sensor_nt: tuple
    diagnosis: object = field(repr=False, default=None)
    result: object = field(repr=False, default=None)


@dataclass(frozen=True, eq=False)
class Ladder:
    """The error ladder: ``steps`` (LadderStep), ``noise_floor``, why it stopped (``reason``)."""

    steps: tuple
    noise_floor: NoiseFloor
    reason: str = ''

    @property
    def final(self):
        """Return the last step."""
        return self.steps[-1]

    def to_dict(self):
        """JSON-ready dict."""
        return {'noise_floor_nt': self.noise_floor.value_nt,
                'steps': [{'model': list(st.model), 'added': st.added, 'n_params': st.n_params,
                           'scalar_rms_nt': {str(j): v for j, v in st.scalar_rms_nt.items()},
                           'vector_rms_nt': {str(j): v for j, v in st.vector_rms_nt.items()},
                           'residual_rms_nt': st.residual_rms_nt, 'cv_rms_nt': st.cv_rms_nt,
                           'verdict': getattr(st.diagnosis, 'verdict_token', None),
                           'explained_fraction': getattr(getattr(st.diagnosis, 'verdict', None),
                                                         'explained_fraction', None)}
                          for st in self.steps],
                'final_reason': self.reason}

    def table(self):
        """Text table of the steps."""
        fl = self.noise_floor.value_nt
        lines = [f'{"step":>4s}  {"added":32s} {"P":>4s} {"max scalar":>10s} '
                 f'{"max vector":>10s} {"combined":>9s} {"held-out":>9s} {"/floor":>7s}']
        for i, st in enumerate(self.steps):
            cv = st.cv_rms_nt
            vmax = max(st.vector_rms_nt.values()) if st.vector_rms_nt else float('nan')
            lines.append(f'{i:4d}  {(st.added or ",".join(st.model)):32s} {st.n_params:4d} '
                         f'{max(st.scalar_rms_nt.values()):10.2f} {vmax:10.2f} '
                         f'{st.residual_rms_nt:9.2f} '
                         f'{(cv if cv is not None else float("nan")):9.2f} '
                         f'{((cv or st.residual_rms_nt) / fl):7.2f}')
        lines.append(f'noise floor (from the data): {fl:.2f} nT')
        if self.reason:
            lines.append(f'stopped: {self.reason}')
        return '\n'.join(lines)


def _rung(result, data, f, added, diagnosis, folds, constrained=False):
    model = result.model
    contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    ev = evaluate_residuals(model, result.params, data, f, result.sigma_nt, contexts)
    if diagnosis is not None and diagnosis.cv_rms_nt is not None:
        cv, cvp = diagnosis.cv_rms_nt, ()
    elif folds:
        c = cross_validate(data, model, result.params, f, result.sigma_nt, folds,
                           constrained=constrained)
        cv, cvp = c['rms_nt'], tuple(float(x) for x in c['per_sensor_nt'])
    else:
        cv, cvp = None, ()
    return LadderStep(
        model=tuple(compact_spec(model)), added=added, n_params=model.n_params,
        scalar_rms_nt=dict(result.scalar_rms_nt), vector_rms_nt=dict(result.vector_rms_nt),
        residual_rms_nt=float(np.sqrt(dof_factor(model) * ev.mean_square)), cv_rms_nt=cv,
        cv_per_sensor_nt=cvp, diagnosis=diagnosis, result=result)


def ladder(data, start_model='base', steps=None, auto=True, field_nt=None, *,
           max_steps=6, folds=DEFAULT_FOLDS, progress=None, diagnosis=None, **diag_kwargs):
    """
    Error ladder: diagnose, add the verdict, refit, repeat until nothing is missing (Ladder).

    ``data``: Dataset (S sensors, N epochs) of rotation data in time order, nT;
    ``start_model``: str, Model or FitResult to start from (a FitResult on ``data`` is used
    as is); ``steps``: effects to add in this order (e.g. ['temperature@2',
    'aux:aux_motor_current']); ``auto``: after ``steps``, keep adding the verdict until it is
    'none'; ``field_nt``: reference magnitude, nT (float or (N,)); ``max_steps``: most
    effects added; ``folds``: of the cross-validation; ``progress``: ``progress(stage, i, n,
    label)`` called as the work proceeds; ``diagnosis``: an existing Diagnosis of
    ``start_model`` (a FitResult), for the first step; ``diag_kwargs``: passed to
    :func:`diagnose`, ``constrained=True`` also constrains every fit.
    """
    f = data.reference_magnitude(field_nt)
    constrained = bool(diag_kwargs.get('constrained', False))
    if hasattr(start_model, 'params') and hasattr(start_model, 'model'):
        result = start_model
    else:
        result = fit(data, start_model, field_nt=f, on_degenerate='flag', constrained=constrained)
    todo = list(steps or [])
    rungs, added, floor = [], None, None
    while True:
        diag = None
        if auto and not todo:
            if diagnosis is not None and diagnosis.result is result:
                diag = diagnosis
            else:
                diag = diagnose(data, field_nt=f, base=result, folds=folds, progress=progress,
                                **diag_kwargs)
            floor = diag.noise_floor
        rungs.append(_rung(result, data, f, added, diag, folds, constrained))
        if floor is None:
            floor = data_noise_floor(data, result)
        if len(rungs) > max_steps:
            reason = (f'{max_steps} effects added (max_steps)'
                      + ('' if diag is None or not diag.verdict_token else
                         f'; the next verdict would be {diag.verdict_token}'))
            break
        if todo:
            token, warm = todo.pop(0), None
        elif auto and diag is not None and diag.verdict_token:
            token, warm = diag.verdict_token, diag.verdict
        else:
            reason = ('the given steps were added (no diagnosis without auto)' if diag is None
                      else f'verdict none: {diag.verdict_reason}')
            break
        contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
        m_ext, p_ext, added_mask = extend_model(result.model, result.params, token, contexts)
        if warm is not None:
            vals = [p['value'] for p in warm.params]
            if len(vals) == added_mask.sum():
                p_ext[added_mask] = vals
        report_progress(progress, 'fit', 0, 1, ','.join(m_ext.spec()))
        result = fit(data, m_ext, field_nt=f, init=p_ext, on_degenerate='flag',
                     constrained=constrained)
        added = token
    return Ladder(steps=tuple(rungs), noise_floor=floor, reason=reason)
