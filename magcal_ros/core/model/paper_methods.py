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
The closed-form calibrations of papers 000 and 002 on a recording (``magcal fit --method``).

- ``sine`` (paper 000): ``raw = L B + B0`` per sensor on a turntable (``angle_deg``,
  ``plane``); of ``L = U Q`` (RQ) the calibration keeps U (``offset,scale,nonorthogonality``).
- ``reference`` (paper 002): ``Hm = K He + Hh`` against ``ref_x, ref_y, ref_z``; sensor 1's
  ``K_1 = U_1 Q_1`` defines the array frame, ``A_j = K_j Q_1^T`` (``offset,soft_iron``).

Both give an ordinary :class:`~magcal_ros.core.model.Calibration` (docs/papers.md).
"""
from dataclasses import dataclass, field

from magcal_ros.core.effects import rq_positive
from magcal_ros.core.model.calibration import Calibration
from magcal_ros.core.model.fitting import DegenerateDataError
from magcal_ros.core.model.spec import Model
import numpy as np


@dataclass
class PaperFit:
    """Result of :func:`sine_calibration` or :func:`reference_calibration`."""

    #: 'sine' or 'reference'
    method: str
    calibration: Calibration
    #: per sensor, the paper's parameters as (name, value, unit)
    sensor_params: list
    #: {sensor: RMS of |raw| - F} and {sensor: RMS of |corrected| - F}, nT
    scalar_rms_before_nt: dict
    scalar_rms_nt: dict
    #: reference: {sensor: per-component RMS of corrected - reference}, nT
    vector_rms_nt: dict = field(default_factory=dict)
    #: what the data cannot determine
    warnings: list = field(default_factory=list)
    #: (S, N, 3) corrected readings in the array frame, nT
    corrected_nt: np.ndarray | None = None

    def summary(self):
        """Short text report."""
        lines = [f'method: {self.method} (closed form, {_PAPER[self.method]}); model '
                 f'{",".join(self.calibration.model.spec())}']
        for j, rows in enumerate(self.sensor_params, 1):
            vals = ', '.join(f'{n} {v:.6g}{"" if u == "1" else " " + u}' for n, v, u in rows)
            lines.append(f'  sensor {j}: {vals}')
            v = self.vector_rms_nt.get(j)
            lines.append(f'    scalar RMS {self.scalar_rms_before_nt[j]:.2f} nT before, '
                         f'{self.scalar_rms_nt[j]:.2f} nT after'
                         + (f'; vector RMS vs reference {v:.2f} nT' if v is not None else ''))
        lines += [f'[{i}] {w}' for i, w in enumerate(self.warnings, 1)]
        return '\n'.join(lines)

    def to_dict(self):
        """JSON-ready dict (the keys of ``magcal fit --json``)."""
        return {'method': self.method, 'model': self.calibration.model.spec(),
                'scalar_rms_nt': self.scalar_rms_nt,
                'scalar_rms_before_nt': self.scalar_rms_before_nt,
                'vector_rms_nt': self.vector_rms_nt,
                'params': [{n: {'value': v, 'unit': u} for n, v, u in rows}
                           for rows in self.sensor_params],
                'warnings': list(self.warnings)}


_PAPER = {'sine': 'paper 000 turntable sine fits', 'reference': 'paper 002 reference field'}


def _rms_scalar(vectors, f):
    return float(np.sqrt(np.mean((np.linalg.norm(vectors, axis=1) - f) ** 2)))


def _finish(method, model, p, data, f, rows, warnings, reference=None):
    # the closed forms give no uncertainty: nan, never a zero that would claim exactness
    cal = Calibration(model, p, stderr=np.full(model.n_params, np.nan))
    sensors = range(1, data.n_sensors + 1)
    corrected = np.stack([cal.correct(j, data.raw[j - 1]) for j in sensors])
    before = {j: _rms_scalar(data.raw[j - 1], f) for j in sensors}
    after = {j: _rms_scalar(corrected[j - 1], f) for j in sensors}
    vec = {} if reference is None else {
        j: float(np.sqrt(np.mean((corrected[j - 1] - reference) ** 2))) for j in sensors}
    return PaperFit(method=method, calibration=cal, sensor_params=rows,
                    scalar_rms_before_nt=before, scalar_rms_nt=after, vector_rms_nt=vec,
                    warnings=warnings, corrected_nt=corrected)


def _magnitude(f, n):
    """(N,) nT from a scalar or (N,) magnitude."""
    return np.broadcast_to(np.asarray(f, float), (n,)).astype(float)


def sine_calibration(data, field_nt):
    """
    Return the :class:`PaperFit` of paper 000 on a turntable recording.

    ``data`` (S, N) readings in nT with ``angle_deg`` and ``plane`` ('xy': position 1,
    'xz': position 2, each a turn); ``field_nt`` B (eq. 16), nT, scalar or (N,) (the mean).
    """
    if data.angle_deg is None or data.plane is None:
        raise ValueError('--method sine needs the turntable columns angle_deg and plane '
                         '(xy for position 1, xz for position 2; paper 000)')
    from magcal_ros.core.papers.sine import calibrate_turntable
    plane = np.char.lower(np.char.strip(np.asarray(data.plane, str)))
    pos1, pos2 = plane == 'xy', plane == 'xz'
    other = sorted(set(plane[~(pos1 | pos2)].tolist()))
    if other:
        raise ValueError(f'plane must be xy or xz on every row, found {other}')
    if pos1.sum() < 3 or pos2.sum() < 3:
        raise ValueError(f'--method sine needs a turn in both positions: {int(pos1.sum())} '
                         f'rows with plane xy and {int(pos2.sum())} with plane xz (at least '
                         '3 distinct angles each)')
    theta = np.radians(np.asarray(data.angle_deg, float))
    f = _magnitude(field_nt, data.n_samples)
    model = Model.from_spec('offset,scale,nonorthogonality', data.n_sensors)
    p = model.default_params()
    rows = []
    for j, m in enumerate(data.raw, 1):
        par = calibrate_turntable(theta[pos1], m[pos1], theta[pos2], m[pos2], float(f.mean()))
        low, b0 = par.to_general()
        u, _ = rq_positive(low)          # drop paper 000's frame rotation (module docstring)
        p = model.params_from_linear(j, u, b0, p)
        rows.append([(n, float(np.degrees(getattr(par, n))), 'deg')
                     for n in ('alpha', 'beta', 'gamma')]
                    + [(n, getattr(par, n), '1') for n in ('kx', 'ky', 'kz')]
                    + [(f'B{a}0', float(v), 'nT') for a, v in zip('xyz', b0)])
    warnings = []
    if data.n_sensors > 1:
        warnings.append('paper 000 calibrates each sensor alone: the rotations between the '
                        'sensors are not determined, each sensor is corrected into its own '
                        'axes and no gradient can be formed; use --method ellipsoid (the '
                        'joint fit) for an array')
    return _finish('sine', model, p, data, f, rows, warnings)


def reference_calibration(data, field_nt=None, on_degenerate='raise'):
    """
    Return the :class:`PaperFit` of paper 002 on a recording with a reference field vector.

    ``data`` (S, N) readings Hm, nT, with ``ref_vec`` (N, 3) nT; ``field_nt`` nT of the scalar
    residual (default |ref_vec|); ``on_degenerate`` 'raise' (DegenerateDataError) or 'flag'.
    """
    if data.ref_vec is None:
        raise ValueError('--method reference needs the reference field columns ref_x, ref_y, '
                         'ref_z (paper 002)')
    from magcal_ros.core.papers.reference_vector import fit_reference
    he = np.asarray(data.ref_vec, float)
    f = np.linalg.norm(he, axis=1) if field_nt is None else _magnitude(field_nt, data.n_samples)
    fits = [fit_reference(he, data.raw[j - 1]) for j in range(1, data.n_sensors + 1)]
    warnings = [f'sensor {j}: {ft.warning}' for j, ft in enumerate(fits, 1) if ft.warning]
    if warnings and on_degenerate == 'raise':
        raise DegenerateDataError(warnings[0] + ' (--flag-degenerate writes it anyway)')
    model = Model.from_spec('offset,soft_iron', data.n_sensors)
    _, q1 = rq_positive(fits[0].K)
    p = model.default_params()
    rows = []
    for j, ft in enumerate(fits, 1):
        p = model.params_from_linear(j, ft.K @ q1.T, ft.Hh, p)     # A_j = K_j Q_1^T
        rows.append([(f'K{r + 1}{c + 1}', float(ft.K[r, c]), '1')
                     for r in range(3) for c in range(3)]
                    + [(f'Hh{a}', float(v), 'nT') for a, v in zip('xyz', ft.Hh)])
    return _finish('reference', model, p, data, f, rows, warnings, reference=he @ q1.T)
