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
Paper 002: hard- and soft-iron compensation from a reference field vector.

Model (eq. 1-4): ``Hm = K He + Hh``, ``He`` the reference field, ``K = I + D`` soft iron,
``Hh`` hard iron; eq. 5-7's rows solved together, ``Hm = [He 1] X``, ``X = [K^T; Hh^T]``.
Not checked by the paper, here: coplanar reference directions (``n . He = c``) leave ``K n``
and ``Hh`` inseparable, as in paper 002's own Table 2 (docs/papers.md, paper 002).
"""
from dataclasses import dataclass

from magcal_ros.core.geometry.coverage import Coverage, direction_coverage, format_vector
from magcal_ros.core.papers.paper_params import Paper002Params
import numpy as np

#: Minimum number of attitudes: 12 unknowns, 3 equations per attitude (paper 002, §1).
MIN_ATTITUDES = 4


@dataclass(frozen=True, eq=False)
class ReferenceFit:
    """
    Result of :func:`fit_reference`.

    ``K`` (3, 3) soft iron (paper 002 eq. 4); ``Hh`` (3,) hard iron, nT; ``residual`` (N, 3)
    nT; ``singular_values`` (3,) nT of ``He - mean(He)``, descending; ``condition_number``
    of ``[He 1]`` column-scaled (inf if rank deficient); ``coverage`` of ``He``;
    ``unobservable_direction`` (3,) unit, the smallest singular direction; ``identifiable``
    and ``warning`` (None when identifiable); ``xtx_inv`` (4, 4) ``(X^T X)^+`` of
    ``X = [He 1]``.
    """

    K: np.ndarray
    Hh: np.ndarray
    residual: np.ndarray
    singular_values: np.ndarray
    condition_number: float
    coverage: Coverage
    unobservable_direction: np.ndarray
    identifiable: bool
    warning: str | None
    xtx_inv: np.ndarray

    @property
    def n(self):
        """Return the number of attitudes."""
        return int(self.residual.shape[0])

    @property
    def rms(self):
        """(3,) RMS residual per component in nT."""
        return np.sqrt(np.mean(self.residual ** 2, axis=0))

    def to_params(self) -> Paper002Params:
        """Return the fit as :class:`~magcal_ros.core.papers.paper_params.Paper002Params`."""
        return Paper002Params(K=self.K, Hh=self.Hh)

    def stderr(self, sigma_hm_nt, sigma_he_nt=0.0):
        """
        First-order standard errors (k_se (3, 3), hh_se (3,) nT) of K and Hh.

        ``cov(row j) = (sigma_hm^2 + sigma_he^2 |K_j|^2) (X^T X)^-1`` (errors in variables to
        first order), ``sigma_hm_nt``, ``sigma_he_nt`` the noise sd of each Hm, He component.
        """
        var_eff = sigma_hm_nt ** 2 + sigma_he_nt ** 2 * np.sum(self.K ** 2, axis=1)
        diag = np.clip(np.diag(self.xtx_inv), 0.0, None)
        se = np.sqrt(var_eff[:, None] * diag[None, :])         # (3 outputs, 4 unknowns)
        return se[:, :3], se[:, 3]


def fit_reference(He, Hm, strict=False, max_condition=100.0,
                  planar_threshold=0.02) -> ReferenceFit:
    """
    Fit ``Hm = K He + Hh`` by linear least squares (paper 002, eq. 4-7).

    ``He`` (N >= 4, 3) reference field, ``Hm`` (N, 3) readings, nT; ``strict``: ValueError
    instead of a fit flagged not identifiable; ``max_condition`` of the column-scaled
    design; ``planar_threshold`` of :func:`~magcal_ros.core.geometry.coverage.direction_coverage`.
    ValueError on malformed input or fewer than 4 attitudes.
    """
    he = np.asarray(He, dtype=float)
    hm = np.asarray(Hm, dtype=float)
    if he.ndim != 2 or he.shape[1] != 3 or hm.shape != he.shape:
        raise ValueError(f'He and Hm must both have shape (N, 3), got {he.shape} and {hm.shape}')
    if not (np.all(np.isfinite(he)) and np.all(np.isfinite(hm))):
        raise ValueError('He and Hm must be finite: drop NaN/inf rows first')
    n = he.shape[0]
    if n < MIN_ATTITUDES:
        raise ValueError('need at least %d attitudes to solve the 12 unknowns of K and Hh '
                         '(3 equations each), got %d' % (MIN_ATTITUDES, n))
    # paper 002, eq. 5-7: rows [He^T 1], all three output components at once
    design = np.column_stack([he, np.ones(n)])
    sol, _, rank, _ = np.linalg.lstsq(design, hm, rcond=None)
    residual = hm - design @ sol
    col_norm = np.linalg.norm(design, axis=0)
    col_norm[col_norm == 0.0] = 1.0
    sv_scaled = np.linalg.svd(design / col_norm, compute_uv=False)
    cond = float(sv_scaled[0] / sv_scaled[-1]) if sv_scaled[-1] > 0.0 else np.inf
    _, singular_values, vt = np.linalg.svd(he - he.mean(axis=0))
    weak = vt[2] if vt[2] @ he.mean(axis=0) >= 0.0 else -vt[2]
    coverage = direction_coverage(he, planar_threshold=planar_threshold)

    warning = None
    if coverage.narrow:
        warning = (
            f'reference field directions span only a {coverage.cone_half_angle_deg:.0f} deg '
            f'cone around {format_vector(coverage.mean_direction, digits=3)}: K is not '
            'determined in any direction across it and trades off against Hh; the compensation '
            'is valid only near that direction. Turn the sensor over / through larger angles.')
    elif coverage.planar:
        weak_text = format_vector(weak, digits=3)
        warning = (
            'reference field directions lie in one plane with normal %s (singular values of '
            'the centred reference field %.4g, %.4g, %.4g nT): K @ normal and Hh are not '
            'separately identifiable (unobservable direction %s), so the compensation is '
            'valid only for attitudes whose field lies in that plane, i.e. turned about the '
            'same axis. Add attitudes rotated about another axis.'
            % (weak_text, *singular_values, weak_text))
    elif rank < 4 or cond > max_condition:
        warning = (f'the design [He 1] is ill-conditioned (condition number {cond:.3g} after '
                   f'column scaling, limit {max_condition:.3g}): K and Hh are poorly '
                   'determined. Spread the attitudes more widely.')
    if warning is not None and strict:
        raise ValueError(warning)
    return ReferenceFit(K=sol[:3].T, Hh=sol[3].copy(), residual=residual,
                        singular_values=singular_values, condition_number=cond, coverage=coverage,
                        unobservable_direction=weak, identifiable=warning is None, warning=warning,
                        xtx_inv=np.linalg.pinv(design.T @ design))


def correct(fit, Hm):
    """Return K^-1 (Hm - Hh), nT (paper 002 eq. 4), of Hm (N, 3) or (3,) nT; ``fit`` has K, Hh."""
    hm = np.asarray(Hm, dtype=float)
    if hm.shape[-1:] != (3,) or hm.ndim > 2:
        raise ValueError('Hm must have shape (N, 3) or (3,), got %s' % (hm.shape,))
    k = np.asarray(fit.K, dtype=float)
    if np.linalg.matrix_rank(k) < 3:
        raise ValueError('K is singular: the fit cannot be inverted')
    return np.linalg.solve(k, (hm - fit.Hh).T).T
