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

"""The result of a diagnosis (:class:`Diagnosis`) and its plain-JSON form."""
from dataclasses import dataclass, field
import json

from magcal_ros.core import effects as fx
from magcal_ros.core.data.noise import NoiseFloor
from magcal_ros.core.data.plain import jsonable
from magcal_ros.core.discovery.constants import AT_FLOOR_RATIO, MIN_DELTA_BIC, MIN_EXPLAINED
import numpy as np


def compact_spec(model):
    """Model spec with paper 004's four effects shown as 'base' when all are present."""
    spec = list(model.spec())
    need = [b for b in fx.BASE if model.n_sensors > 1 or fx.make_effect(b, 1).applies]
    if all(b in spec for b in need):
        spec = ['base'] + [t for t in spec if t not in fx.BASE]
    return spec


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """
    Outcome of :func:`diagnose` (RMS values in nT).

    ``model``: spec of the diagnosed model (tuple of str); ``n_used``: epochs the candidates
    were tested on (at most ``max_samples``, evenly spaced); ``scalar_rms_nt``,
    ``vector_rms_nt``: {sensor: RMS} of the base fit (vector: j > 1, vs sensor 1);
    ``residual_rms_nt``, ``cv_rms_nt`` (None: not computed): its combined in-sample and
    held-out residual RMS (pooled); ``at_floor``: every scalar and vector RMS within
    :data:`AT_FLOOR_RATIO` of its floor; ``candidates``: tuple of Candidate, significant ones
    first, then by delta BIC; ``not_testable``: tuple of (token, reason); ``verdict_token``:
    token to add ('temperature@2'), None when nothing is missing, ``verdict_reason`` why;
    ``p_threshold``: Bonferroni threshold alpha / (number of candidates); ``seconds``: wall
    time per stage, s; ``result``: the base FitResult; ``findings``: what is left in its
    residuals (:func:`.findings.find`), or None.
    """

    model: tuple
    n_samples: int
    n_sensors: int
    n_params: int
    noise_floor: NoiseFloor
    scalar_rms_nt: dict
    vector_rms_nt: dict
    residual_rms_nt: float
    cv_rms_nt: float | None
    at_floor: bool
    candidates: tuple
    not_testable: tuple
    verdict_token: str | None
    verdict_reason: str
    p_threshold: float
    folds: int
    seconds: dict
    result: object = field(repr=False, default=None)
    n_used: int | None = None
    findings: object = field(repr=False, default=None)
    #: which test decided: 'held-out' or 'in-sample (folds=0)' / '(record ... too short)'
    decided_by: str = 'held-out'
    #: combined residual mean square above the pooled floor, nT^2
    excess_ms_nt2: float | None = None

    @property
    def verdict(self):
        """Return the best candidate, or None when nothing is missing."""
        if self.verdict_token is None:
            return None
        return next(c for c in self.candidates if c.token == self.verdict_token)

    @property
    def not_ruled_out(self):
        """
        [(token, RMS nT)]: candidates that could be present at more than the noise floor.

        Not significant, yet their ``hideable_rms_nt`` (the largest effect the base's own
        parameters absorb over this motion) is above the pooled floor; largest first, inf
        when some combination hides at any size.
        """
        fl = self.noise_floor.value_nt
        out = [(c.token, c.hideable_rms_nt) for c in self.candidates
               if not c.significant and c.hideable_rms_nt is not None and c.hideable_rms_nt > fl]
        return sorted(out, key=lambda x: -x[1])

    def not_ruled_out_text(self):
        """One line naming :attr:`not_ruled_out` (the largest six) and how to test them."""
        hidden, big = self.not_ruled_out, 100 * self.noise_floor.value_nt

        def size(x):
            return ('at any size' if x == np.inf else 'over 100 x the floor' if x > big else
                    f'up to {x:.0f} nT' if x >= 10 else f'up to {x:.1f} nT')
        shown = ', '.join(f'{t} ({size(x)})' for t, x in hidden[:6])
        more = f' and {len(hidden) - 6} more (JSON: not_ruled_out)' if len(hidden) > 6 else ''
        return ("not ruled out by this record (over its motion the calibration's own terms "
                "or the field's unknown direction take up effects of these kinds to the size "
                f'shown, RMS per axis): {shown}{more}; a record that turns through more '
                'attitudes, with their drivers varying at several of them, tests them')

    @property
    def ratios(self):
        """{'scalar': {j: RMS / floor}, 'vector': {j: RMS / vector floor}}."""
        fl = self.noise_floor
        return {'scalar': {j: v / fl.per_sensor_nt[j - 1] for j, v in self.scalar_rms_nt.items()},
                'vector': {j: v / fl.vector_floor_nt(j) for j, v in self.vector_rms_nt.items()}}

    def to_dict(self):
        """JSON-ready dict per docs/design.md §2 (plus details)."""
        fl = self.noise_floor
        v = self.verdict
        ratios = self.ratios
        return {
            'model': list(self.model),
            'noise_floor_nt': fl.value_nt,
            'scalar_rms_nt': {str(j): x for j, x in self.scalar_rms_nt.items()},
            'vector_rms_nt': {str(j): x for j, x in self.vector_rms_nt.items()},
            'candidates': [c.to_dict() for c in self.candidates],
            'verdict': {'effect': v.effect if v else 'none', 'sensor': v.sensor if v else None,
                        'token': self.verdict_token, 'reason': self.verdict_reason,
                        'explained_fraction': v.explained_fraction if v else None,
                        'decided_by': self.decided_by},
            'min_explained_fraction': MIN_EXPLAINED,
            'excess_ms_nt2': self.excess_ms_nt2,
            'noise_floor_per_sensor_nt': {str(j + 1): float(x)
                                          for j, x in enumerate(fl.per_sensor_nt)},
            'noise_floor_method': {str(j + 1): m for j, m in enumerate(fl.method)},
            'noise_floor_reliable': bool(np.all(fl.reliable)),
            'noise_floor_status': {str(j + 1): st for j, st in enumerate(fl.status)},
            'noise_floor_range_nt': {str(j + 1): [float(lo), float(hi)] for j, (lo, hi)
                                     in enumerate(zip(fl.lower_nt, fl.upper_nt))},
            'residual_rms_nt': self.residual_rms_nt,
            'cv_rms_nt': self.cv_rms_nt,
            'at_noise_floor': self.at_floor,
            'ratio_to_floor': {k: {str(j): x for j, x in d.items()} for k, d in ratios.items()},
            'not_testable': [{'token': t, 'reason': r} for t, r in self.not_testable],
            'not_ruled_out': [{'token': t, 'hideable_rms_nt': x, 'at_any_size': x == np.inf}
                              for t, x in self.not_ruled_out],
            'n_samples': self.n_samples, 'n_used': self.n_used or self.n_samples,
            'n_sensors': self.n_sensors,
            'n_params': self.n_params, 'p_threshold': self.p_threshold,
            'min_delta_bic': MIN_DELTA_BIC, 'at_floor_ratio': AT_FLOOR_RATIO,
            'cv_folds': self.folds, 'seconds': dict(self.seconds),
            'findings': [] if self.findings is None else self.findings.to_list(),
        }

    def to_json(self, **kwargs):
        """Return :meth:`to_dict` as a JSON string (non-finite numbers as null)."""
        return json.dumps(jsonable(self.to_dict()), **kwargs)

    def summary(self, max_candidates=12):
        """Human-readable report (the best ``max_candidates`` candidates)."""
        fl = self.noise_floor
        used = ('' if not self.n_used or self.n_used == self.n_samples else
                f' (candidates tested on {self.n_used} evenly spaced)')
        lines = [f'diagnosis of model {",".join(self.model)} ({self.n_params} parameters) on '
                 f'{self.n_samples} epochs{used} of {self.n_sensors} sensor(s)',
                 'noise floor from the data: ' + ', '.join(
                     f's{j + 1} {x:.2f}' for j, x in enumerate(fl.per_sensor_nt)) + ' nT'
                 ] + [f'  {fl.describe(j + 1)}' for j, st in enumerate(fl.status) if st != 'white']
        r = self.ratios
        for j, x in self.scalar_rms_nt.items():
            of = 'floor' if fl.status[j - 1] != 'filtered' else 'lower bound of the floor'
            line = f'  sensor {j}: scalar RMS {x:8.2f} nT ({r["scalar"][j]:5.2f} x {of})'
            if j in self.vector_rms_nt:
                line += (f', vector RMS vs sensor 1 {self.vector_rms_nt[j]:8.2f} nT '
                         f'({r["vector"][j]:5.2f} x floor)')
            lines.append(line)
        cv = '' if self.cv_rms_nt is None else f', held-out {self.cv_rms_nt:.2f} nT'
        lines.append(f'combined residual {self.residual_rms_nt:.2f} nT{cv} '
                     f'(floor {fl.value_nt:.2f} nT)')
        if self.candidates:
            lines.append(f'candidates (best first; significant: p < {self.p_threshold:.1e}, '
                         f'dBIC < {MIN_DELTA_BIC:g}, removes >= {MIN_EXPLAINED:.0%} of the '
                         f'excess, {self.decided_by}):')
            lines.append(f'  {"effect":34s} {"k":>2s} {"dBIC":>10s} {"log10 p":>8s} '
                         f'{"scalar RMS":>15s} {"vector RMS":>15s} {"held-out RMS":>15s} '
                         f'{"share":>6s}')
            for c in self.candidates[:max_candidates]:
                vec = _before_after(c.vector_rms_before_nt, c.vector_rms_after_nt)
                cv = _before_after(c.cv_rms_before_nt, c.cv_rms_after_nt)
                share = ('' if c.explained_fraction is None else f'{c.explained_fraction:6.0%}')
                lines.append(f'{"*" if c.significant else " "} {c.token:34s} {c.n_params:2d} '
                             f'{c.delta_bic:10.1f} {c.log10_p_value:8.1f} '
                             f'{_before_after(c.rms_before_nt, c.rms_after_nt)}   '
                             f'{vec:>15s} {cv:>15s} {share:>6s}')
                if c.note:
                    lines.append(f'    not adopted: {c.note}')
            if any(c.method == 'score' for c in self.candidates[:max_candidates]):
                lines.append("  '-': not evaluated, the score test rules the effect out "
                             '(delta BIC from the predicted decrease of chi-square)')
            if len(self.candidates) > max_candidates:
                lines.append(f'  ... {len(self.candidates) - max_candidates} more with less '
                             'evidence (all in the JSON output)')
        lines += [f'  not testable: {tok}: {why}' for tok, why in self.not_testable]
        if self.not_ruled_out:
            lines.append('  ' + self.not_ruled_out_text())
        if self.findings is not None:
            lines.append(self.findings.summary())
        verdict = f'add {self.verdict_token}' if self.verdict_token else 'none'
        lines.append(f'verdict: {verdict} ({self.verdict_reason})')
        return '\n'.join(lines)


def _before_after(before, after):
    """Return 'before>after' (nT, 6.2f each), after '-' when not evaluated, '' without before."""
    if before is None:
        return ''
    return f'{before:6.2f}>' + ('     -' if after is None else f'{after:6.2f}')
