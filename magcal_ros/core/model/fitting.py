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
The maximum-likelihood fit of a :class:`magcal_ros.core.model.Model` and its result.

:func:`fit`: the closed-form start (paper 004 section 3, eq. 8-14), maximum likelihood with
the field profiled out (:mod:`magcal_ros.core.model.engine`), the noise re-estimated
(:func:`group_noise_variances`) and the Cramer-Rao bound as covariance.
"""
from dataclasses import dataclass, field
from functools import cached_property

from magcal_ros.core.model.calibration import Calibration
from magcal_ros.core.model.engine import ProfiledProblem
from magcal_ros.core.model.notes import Note
from magcal_ros.core.model.solvers import (covariance_from_jacobian, covariance_from_normal,
                                           levenberg_marquardt, mad_sd, resolves_covariance,
                                           single_threaded_blas, Solution,
                                           stderr_and_correlation)
from magcal_ros.core.model.spec import Model
from magcal_ros.core.papers.ellipsoid import fit_ellipsoid, procrustes_rotation
import numpy as np


class DegenerateDataError(ValueError):
    """The data cannot determine the model: the message names what is missing."""


@dataclass(frozen=True, eq=False)
class FitResult:
    """
    Outcome of :func:`fit` (attributes that end in _nt are in nT); immutable.

    The per-epoch arrays are computed from ``params`` on all epochs when first read, then kept.
    """

    model: object
    #: (P,) estimated parameters (units in ``model.param_info()``)
    params: np.ndarray
    #: (P,) standard uncertainties (NaN: a fit with ``covariance=False``)
    stderr: np.ndarray
    #: (P, P) each (NaN and the identity when not computed)
    covariance: np.ndarray
    correlation: np.ndarray
    #: (S,) per-sensor noise sd estimated from the residuals, nT
    sigma_nt: np.ndarray
    #: (N,) reference magnitude used, nT
    field_magnitude_nt: np.ndarray
    #: the optimiser converged; its status, message and residual evaluations
    success: bool
    status: int
    message: str
    nfev: int
    #: epochs the parameters were fitted on (at most ``max_fit_samples``)
    n_fit_samples: int
    #: sum of squared normalised residuals at the solution, on the fitted epochs
    chi2: float
    #: observations net of the profiled field: n_fit_samples sum(3G - 2) over the groups
    n_obs: int
    #: tuple of Note
    warnings: tuple = ()
    #: :mod:`magcal_ros.core.model.identifiability` report
    identifiability: dict = field(default_factory=dict)
    #: (P,) the start
    initial_params: np.ndarray | None = None
    #: (S,) the driving signals of all epochs
    contexts: list | None = None
    robust: bool = False
    f_scale: float = 3.0
    #: (S, N, 3) the raw readings fitted, nT (the data's own array)
    raw_nt: np.ndarray | None = field(default=None, repr=False)
    #: (S,) int, the readings of each sensor fitted on (less what ``drop(t0, t1)@j`` leaves)
    n_fit_readings: np.ndarray | None = None
    #: the priors the fit used, (index, mean, sd) in the parameters' units
    priors: tuple = ()

    @property
    def n_samples(self):
        """Return the number of epochs N of the fitted data."""
        return int(self.raw_nt.shape[1])

    def _profile(self):
        return profile_residuals(self.model, self.params, self.raw_nt,
                                 self.field_magnitude_nt, self.sigma_nt, self.contexts,
                                 robust=self.robust, f_scale=self.f_scale)

    @cached_property
    def field_nt(self):
        """(N, 3) estimated true field per epoch (array frame), nT."""
        return self._profile()[0]

    @cached_property
    def residual_nt(self):
        """(S, N, 3) raw reading minus prediction, nT (also where a ``drop`` leaves it out)."""
        field_nt, residual = self._profile()
        self.__dict__.setdefault('field_nt', field_nt)     # the same computation: keep it
        return residual

    @cached_property
    def corrected_nt(self):
        """(S, N, 3) corrected readings in the array frame, nT."""
        return corrected_readings(self.model, self.params, self.raw_nt, self.contexts)

    def _peek(self, name):
        """Return the cached property ``name``: the one kept, else computed and not kept."""
        return (self.__dict__[name] if name in self.__dict__
                else getattr(type(self), name).func(self))

    def _centred(self):
        return centred_readings(self.model, self.params, self._peek('corrected_nt'),
                                self.contexts)

    @cached_property
    def scalar_residual_nt(self):
        """(S, N) |corrected| - reference magnitude, nT (site gradient shift removed)."""
        return np.linalg.norm(self._centred(), axis=2) - self.field_magnitude_nt[None]

    @cached_property
    def vector_residual_nt(self):
        """(S, N, 3) corrected_j - corrected_1, nT (zero for sensor 1)."""
        centred = self._centred()
        return centred - centred[:1]

    @cached_property
    def downweighted(self):
        """(S,) number of sensor samples the robust loss down-weighted (0 if not robust)."""
        if not self.robust:
            return np.zeros(self.model.n_sensors, int)
        residual = self._peek('residual_nt')
        keep = self.reading_mask
        if keep is not None:
            residual = residual * keep[:, :, None]
        return downweighted_counts(residual, self.sigma_nt, self.f_scale)

    @property
    def n_params(self):
        """Return the number of free parameters."""
        return self.model.n_params

    @cached_property
    def reading_mask(self):
        """(S, N) bool: the readings the summaries cover (``Model.reading_mask``); None: all."""
        if not getattr(self.model, 'drops', ()) or not self.contexts:
            return None
        return self.model.reading_mask(np.asarray(self.contexts[0].t))

    def _kept(self, j, other=None):
        """Index of sensor j's epochs the summaries cover (and sensor ``other``'s)."""
        keep = self.reading_mask
        if keep is None:
            return slice(None)
        return keep[j - 1] if other is None else keep[j - 1] & keep[other - 1]

    @property
    def scalar_rms_nt(self):
        """{sensor: RMS of the scalar residual} in nT (outside its drop() windows)."""
        return {j + 1: float(np.sqrt(np.mean(r[self._kept(j + 1)] ** 2)))
                for j, r in enumerate(self.scalar_residual_nt)}

    @property
    def vector_rms_nt(self):
        """{sensor j > 1: per-component RMS of corrected_j - corrected_1} nT, where both kept."""
        vector = self._peek('vector_residual_nt')     # not kept: the RMS needs only a copy
        return {j + 1: float(np.sqrt(np.mean(vector[j][self._kept(j + 1, 1)] ** 2)))
                for j in range(1, self.model.n_sensors)}

    @property
    def calibration(self):
        """Return the :class:`Calibration` (model + parameters) for live correction."""
        cal = Calibration(self.model, self.params, self.stderr, self.sigma_nt)
        cols = self.model.array_cols
        if len(cols):
            cal.array_covariance = self.covariance[np.ix_(cols, cols)].copy()
            cal.site_frame = self.identifiability.get('site_gradient_frame', cal.site_frame)
        return cal

    def param_table(self):
        """Return a list of dicts: sensor, effect, name, unit, value, stderr."""
        return [{'sensor': s, 'effect': e, 'name': n, 'unit': u, 'value': float(v),
                 'stderr': float(se)}
                for (s, e, n, u), v, se in zip(self.model.param_info(), self.params, self.stderr)]

    def summary(self):
        """Short text report."""
        lines = [f'model: {",".join(self.model.spec())}  ({self.n_params} parameters, '
                 f'{self.n_fit_samples} epochs fitted)',
                 f'converged: {self.success} ({self.message})']
        if self.n_fit_readings is not None and np.any(self.n_fit_readings < self.n_fit_samples):
            lines.append('readings left out by drop(): ' + ', '.join(
                f'sensor {j} {self.n_fit_samples - int(n)}'
                for j, n in enumerate(self.n_fit_readings, start=1) if n < self.n_fit_samples))
        vector_rms = self.vector_rms_nt
        for j, r in self.scalar_rms_nt.items():
            v = vector_rms.get(j)
            lines.append(f'  sensor {j}: scalar RMS {r:8.2f} nT, sigma {self.sigma_nt[j-1]:.2f} nT'
                         + (f', vector RMS vs sensor 1 {v:8.2f} nT' if v is not None else ''))
        lines += [f'[{i}] {w}' for i, w in enumerate(self.warnings, 1)]
        return '\n'.join(lines)


def fit(data, model, field_nt=None, *, robust=False, f_scale=3.0, constrained=False,
        priors=None, sigma_nt=None, on_degenerate='raise', max_fit_samples=20000,
        init=None, max_nfev=200, check_identifiability=True, solver='lm', covariance=True,
        ftol=None, extra_priors=None):
    """
    Fit ``model`` to rotation data in a uniform field by maximum likelihood; a FitResult.

    ``data`` (S sensors, N epochs) raw readings, nT; ``model`` a Model or formula;
    ``field_nt`` the reference magnitude, nT, scalar or (N,) (default ``data.ref_total``);
    ``robust``: the soft-L1 loss of scale ``f_scale`` sigma; ``constrained``: each effect's
    ``Effect.prior`` and the start A = I; ``priors`` {effect name or label: (mean or None,
    sd)} override them; ``extra_priors`` [(index, mean, sd)] are added; ``sigma_nt`` fixed
    per-sensor noise, nT (default estimated); ``on_degenerate`` 'raise'
    (DegenerateDataError) or 'flag' (warnings); ``max_fit_samples`` epochs fitted, evenly
    spaced; ``init`` (P,) the start (default the closed form); ``max_nfev`` residual
    evaluations per group and noise pass; ``ftol`` the relative cost decrease that stops
    (default the solver's); ``solver`` 'lm' (normal equations) or 'scipy'
    (least_squares, the reference); ``check_identifiability``
    (:mod:`magcal_ros.core.model.identifiability`); ``covariance`` False: NaN covariance
    (needs ``check_identifiability=False``).
    """
    if on_degenerate not in ('raise', 'flag'):
        raise ValueError("on_degenerate must be 'raise' or 'flag'")
    if solver not in ('lm', 'scipy'):
        raise ValueError(f"solver must be 'lm' or 'scipy', got {solver!r}")
    if check_identifiability and not covariance:
        raise ValueError('check_identifiability reads the covariance: pass '
                         'check_identifiability=False with covariance=False')
    with single_threaded_blas():
        if isinstance(model, str):
            model = Model.from_spec(model, data.n_sensors)
        if model.n_sensors != data.n_sensors:
            raise ValueError(f'model has {model.n_sensors} sensors, data have {data.n_sensors}')
        notes = []

        def degenerate(msg):
            if on_degenerate == 'raise':
                raise DegenerateDataError(msg)
            notes.append(Note(msg, 'degenerate'))

        f_all = data.reference_magnitude(field_nt)
        contexts_all = [data.context(j) for j in range(1, data.n_sensors + 1)]
        ident = _check_data(data, model, contexts_all, constrained, check_identifiability,
                            degenerate)
        idx, mask = fitted_readings(model, data.t, fit_epochs(data.n_samples, max_fit_samples))
        raw, f = data.raw[:, idx], f_all[idx]
        contexts = [c.subset(idx) for c in contexts_all]
        p0 = (_closed_form_start(raw, f, model, constrained, ident, degenerate, mask)
              if init is None else np.asarray(init, float).copy())
        if (any(hasattr(e, 'set_positions') for e in model.array_effects)
                and contexts_all[0].attitude is not None):
            # the attitude must agree with the field direction (closed-form corrected sensor 1)
            from magcal_ros.core.geometry.attitude import check_against_field
            check_against_field(contexts_all[0].attitude,
                                model.correct(1, p0, data.raw[0], contexts_all[0]), data.t)
        prior_list = priors_for(model, priors or {}, constrained) + list(extra_priors or ())
        solve = _Solve(model, raw, f, contexts, prior_list, robust, f_scale, solver, max_nfev,
                       ftol, mask)
        p, sigma, sol = solve.run(p0, sigma_nt)
        cov, chi2, n_obs = solve.covariance(p, sigma, with_jacobian=covariance)
        stderr, corr = stderr_and_correlation(cov)
        if check_identifiability:
            from magcal_ros.core.model import identifiability as idf
            jac_rep = idf.jacobian_report(model, cov, corr, constrained=constrained)
            ident.update(jac_rep)
            for prob_msg in jac_rep['problems']:
                degenerate(prob_msg)
        if not sol.success:
            notes.append(Note(f'the optimiser did not converge: {sol.message}', 'not_converged'))
    return FitResult(
        model=model, params=p, stderr=stderr, covariance=cov, correlation=corr,
        sigma_nt=sigma, field_magnitude_nt=f_all, success=sol.success, status=sol.status,
        message=sol.message, nfev=sol.nfev, n_fit_samples=len(idx), chi2=chi2, n_obs=n_obs,
        warnings=tuple(notes), identifiability=ident, initial_params=p0,
        contexts=contexts_all, robust=bool(robust), f_scale=float(f_scale), raw_nt=data.raw,
        n_fit_readings=(np.full(model.n_sensors, len(idx)) if mask is None
                        else mask.sum(axis=1)), priors=tuple(prior_list))


def _check_data(data, model, contexts, constrained, check_identifiability, degenerate):
    """Prepare ``model``, refuse or flag data that cannot determine it; the coverage report."""
    raw = data.raw
    if not np.all(np.isfinite(raw)):
        bad = np.unique(np.nonzero(~np.isfinite(raw))[0]) + 1
        raise ValueError(f'non-finite raw readings for sensor(s) {bad.tolist()}: drop those rows')
    model.prepare(contexts)
    for why in model.check(contexts):
        degenerate(why)
    n_min = max(12, int(np.ceil(2 * model.n_params / max(1, data.n_sensors))))
    if data.n_samples < n_min:
        raise DegenerateDataError(f'too few samples: {data.n_samples} epochs for '
                                  f'{model.n_params} parameters; collect at least {n_min}')
    ident = {}
    if check_identifiability:
        from magcal_ros.core.model import identifiability as idf
        ident = idf.check_coverage(raw)
        problems = ident['problems']
        from magcal_ros.core.effects.attitude_ref import attitude_reference
        if attitude_reference(model) is not None and contexts[0].attitude is not None:
            problems = []       # attitude_fit names what the coverage leaves open
        if constrained:
            # the priors stand in for a partial coverage, not for a sensor that did not turn
            excused = [j for j, v in ident['sensors'].items()
                       if v['status'] in ('partial', 'single axis')]
            problems = [p for p in problems
                        if not any(p.startswith(f'sensor {j}:') for j in excused)]
        if problems:
            degenerate(problems[0])
    return ident


def fitted_readings(model, t, idx):
    """
    Return the fitted sets and readings: (M,) indices into ``t`` and (S, M) bool or None.

    ``idx`` (M0,) the candidate sets (:func:`fit_epochs`), ``t`` (N,) s; the ``drop`` terms
    leave readings out, a set without any is removed; None: every reading is used.
    ValueError when fewer than 10 sets, or a sensor keeps fewer than max(10, its parameters).
    """
    if not model.drops:
        return idx, None
    mask = model.reading_mask(np.asarray(t)[idx])
    sets = mask.any(axis=0)
    idx, mask = idx[sets], mask[:, sets]
    terms = ' + '.join(w for w in model.spec() if w.startswith('drop('))
    if len(idx) < 10:
        raise ValueError(f'the drop() windows ({terms}) leave {len(idx)} samples to fit: '
                         'drop less')
    for j, n_j in enumerate(mask.sum(axis=1), start=1):
        need = max(10, model.sensor_slices[j - 1].stop - model.sensor_slices[j - 1].start)
        if n_j < need:
            raise ValueError(f'the drop() windows ({terms}) leave sensor {j} with {int(n_j)} of '
                             f'{len(idx)} samples to fit (it needs at least {need}): drop '
                             'less of it')
    return idx, None if mask.all() else mask


def fit_epochs(n, max_fit_samples):
    """Return the (M,) indices of the epochs fitted: all, or ``max_fit_samples`` evenly spaced."""
    if max_fit_samples and n > max_fit_samples:
        return np.unique(np.linspace(0, n - 1, max_fit_samples).round().astype(int))
    return np.arange(n)


def _closed_form_start(raw, f, model, constrained, ident, degenerate, mask=None):
    """Return the closed-form start; flagged degenerate data start from ideal sensors."""
    try:
        return initial_params(raw, f, model, constrained=constrained, mask=mask)
    except ValueError as exc:
        if constrained:
            raise
        degenerate(f'{exc}. {ident.get("summary", "")}'.strip())
        # flagged: start from ideal sensors and the sphere-fit offsets instead
        return initial_params(raw, f, model, constrained=True, mask=mask)


def group_noise_variances(res, g_cols, n_params, ranks=None, keep=None):
    """
    Unbiased moment estimate of each sensor's noise variance in a group, relative to its weight.

    The profiled residual r = (I - P) e (P the projector on the field-direction columns G, e
    the noise over the current sigma_j, E[e e^T] = diag(d_j I_3)) gives E ||r_j||^2 =
    sum_k C_jk d_k, C_jk = ||(I - P)_jk||_F^2 over epochs, solved for d >= 0 (nnls; Rao 1970,
    docs/papers.md); every d is scaled by :func:`dof_scale` squared.

    ``res`` (N, G, 3) normalised residuals; ``g_cols`` (N, 3 G, 2)
    (:meth:`ProfiledProblem.field_columns`); ``n_params`` of the group; ``ranks`` (G,) each
    member's noise rank (3 a sensor, 1 or 3 the attitude); ``keep`` (N, G) 0/1 the readings
    kept.  Returns (G,) d_j: the new sigma_j is the current one times sqrt(d_j).
    """
    from scipy.optimize import nnls
    n, g = res.shape[0], res.shape[1]
    counts = np.full(g, float(n))
    if keep is not None:
        w = np.ones((n, g))
        w[:, :keep.shape[1]] = keep
        rows = w.any(axis=1)                    # epochs with a reading (or the attitude)
        res, g_cols, w, n = res[rows], g_cols[rows], w[rows], int(rows.sum())
        g_cols = g_cols * np.repeat(w, 3, axis=1)[:, :, None]
        counts = w.sum(axis=0)
    gj = g_cols.reshape(n, g, 3, 2)
    k = np.einsum('ngaq,ngar->ngqr', gj, gj, optimize=True)   # (N, G, 2, 2) G_j^T G_j
    s = np.linalg.inv(k.sum(axis=1))                           # (N, 2, 2) (G^T G)^-1
    sk = np.einsum('nqr,ngrs->ngqs', s, k, optimize=True)      # S K_j
    # ||(I - P)_jk||_F^2 = 3 delta_jk - 2 delta_jk tr(S K_j) + tr(S K_k S K_j), the last
    # summed over epochs as one (G, 4N) x (4N, G) product (half the time of the einsum)
    c = np.tensordot(sk.transpose(0, 1, 3, 2).reshape(n, g, 4), sk.reshape(n, g, 4),
                     axes=([0, 2], [0, 2]))
    rk = np.full(g, 3.0) if ranks is None else np.asarray(ranks, float)
    c[np.diag_indices(g)] += rk * counts - 2.0 * np.einsum('njqq->j', sk)
    m = np.einsum('nga,nga->g', res, res)
    d, _ = nnls(c, m * dof_scale(n, n_params, float(rk @ counts)) ** 2)
    return np.maximum(d, 1e-12)


def dof_scale(n, n_params, row_total):
    """Return sqrt(D / (D - P)), D = row_total - 2 N (each field takes 2): scales a noise sd."""
    dof = row_total - 2 * n
    return float(np.sqrt(dof / max(dof - n_params, 1.0)))


def own_residual(res, g_cols, gi):
    """
    (N,) the residual of sensor ``gi`` of a group normal to its two field-direction columns.

    The profiled field moves sensor j's prediction only within the span of its columns G_j,
    so the component along G_j1 x G_j2 is sensor j's normalised noise alone.  ``res``,
    ``g_cols`` as for :func:`group_noise_variances`; ``gi`` its position in the group.
    """
    cols = g_cols[:, 3 * gi:3 * gi + 3]
    w = np.cross(cols[:, :, 0], cols[:, :, 1])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return np.einsum('na,na->n', w, res[:, gi])


def serial_inflation(r):
    """sqrt((1 + rho) / (1 - rho)), rho the lag-1 correlation of r (N, 3) (Bartlett 1946)."""
    r = np.asarray(r, float)
    num = float(np.sum(r[1:] * r[:-1]))
    den = float(np.sum(r * r))
    rho = min(max(num / den if den > 0 else 0.0, 0.0), 0.999)
    return float(np.sqrt((1 + rho) / (1 - rho)))


class _Solve:
    """The ML problem of each sensor group on the fitted epochs, and its noise levels."""

    def __init__(self, model, raw, f, contexts, prior_list, robust, f_scale, solver,
                 max_nfev, ftol=None, mask=None):
        self.model, self.raw, self.f, self.contexts = model, raw, f, contexts
        #: (S, N) bool, the readings fitted (None: all; :func:`fitted_readings`)
        self.mask = mask
        self.ftol_kw = {} if ftol is None else {'ftol': ftol}
        self.prior_list = prior_list
        self.robust, self.f_scale = robust, f_scale
        self.solver, self.max_nfev = solver, max_nfev

    def problem(self, grp, sigma, p):
        """Return the :class:`ProfiledProblem` of sensor group ``grp`` at ``p``."""
        m = self.model
        pr = [t for t in self.prior_list if t[0] in m.array_cols or any(
            m.sensor_slices[j - 1].start <= t[0] < m.sensor_slices[j - 1].stop for j in grp)]
        return ProfiledProblem(m, self.raw, self.contexts, self.f, grp, sigma, pr,
                               self.robust, self.f_scale, p_full=p)

    def run(self, p0, sigma_nt):
        """
        Return (p, sigma, solution): ML parameters, noise levels and the last solution.

        ``sigma_nt`` given: fixed noise, one pass; else from the MAD of the start's residuals,
        re-estimated until it changes by less than 5 % (3 passes at most, 6 with an attitude).
        """
        model = self.model
        fixed_sigma = sigma_nt is not None
        sigma = (np.broadcast_to(np.asarray(sigma_nt, float), (model.n_sensors,)).copy()
                 if fixed_sigma else self.start_sigma(p0))
        p = p0.copy()
        from magcal_ros.core.effects.attitude_ref import attitude_reference
        passes = 6 if attitude_reference(model) is not None else 3
        for _ in range(1 if fixed_sigma else passes):
            p, problems, sol = self.solve_groups(p, sigma)
            if fixed_sigma:
                break
            self.aid_change = 0.0
            new_sigma = self.residual_sigma(p, sigma, problems)
            converged = (np.all(np.abs(new_sigma / sigma - 1) < 0.05)
                         and self.aid_change < 0.05)
            sigma = np.maximum(new_sigma, 1e-6)
            if converged:
                break
        return p, sigma, sol

    def start_sigma(self, p):
        """Return (S,) a robust noise estimate (MAD) of the scalar residual at ``p``, nT."""
        cor = corrected_readings(self.model, p, self.raw, self.contexts)
        scalar = np.linalg.norm(cor, axis=2) - self.f
        keep = np.ones(scalar.shape, bool) if self.mask is None else self.mask
        return np.array([max(mad_sd(s[k]), 1e-3) for s, k in zip(scalar, keep)])

    def solve_groups(self, p, sigma):
        """Solve each sensor group at fixed ``sigma``; return (p, problems, summary)."""
        p = p.copy()
        problems = []
        nfev, success, status, message = 0, True, 0, ''
        for grp in self.model.sensor_groups:
            prob = self.problem(grp, sigma, p)
            x0 = p[prob.cols]
            if self.solver == 'scipy':
                from scipy.optimize import least_squares     # the reference solver only
                sol = least_squares(prob.residuals, x0, jac=prob.jacobian, x_scale='jac',
                                    loss='soft_l1' if self.robust else 'linear',
                                    f_scale=self.f_scale, max_nfev=self.max_nfev, method='trf',
                                    **self.ftol_kw)
            else:
                # the squares loss needs only the normal equations, the soft-L1 loss the rows
                sol = levenberg_marquardt(prob.residuals, prob.jacobian, x0,
                                          robust=self.robust, f_scale=self.f_scale,
                                          max_nfev=self.max_nfev,
                                          normal=None if self.robust else prob.normal_equations,
                                          **self.ftol_kw)
            p[prob.cols] = sol.x
            problems.append(prob)
            nfev += sol.nfev
            success &= bool(sol.success)
            status, message = sol.status, sol.message
        # the last group's status and message; every group's success and evaluations
        return p, problems, Solution(p, success, status, message, nfev)

    def residual_sigma(self, p, sigma, problems):
        """Return (S,) noise levels at p, nT: :func:`group_noise_variances`, robust MAD."""
        new_sigma = sigma.copy()
        for prob in problems:
            _, b, mats, res = prob.evaluate(p[prob.cols])
            g_cols = prob.field_columns(b, mats)
            if self.robust and prob.aid is None:
                kept = prob.member_counts
                scale = dof_scale(int(np.count_nonzero(prob.keep.any(axis=1)))
                                  if prob.keep is not None else res.shape[0],
                                  len(prob.cols), 3.0 * kept.sum())
                for gi, j in enumerate(prob.sensors):
                    own = own_residual(res, g_cols, gi)
                    if prob.keep is not None:
                        own = own[prob.keep[:, gi] > 0]
                    new_sigma[j - 1] = sigma[j - 1] * scale * mad_sd(own)
                continue
            ranks = [3] * len(prob.sensors) + ([prob.aid.rank] if prob.aid is not None else [])
            ratio = group_noise_variances(res, g_cols, len(prob.cols), ranks, prob.keep)
            for gi, j in enumerate(prob.sensors):
                new_sigma[j - 1] = sigma[j - 1] * np.sqrt(ratio[gi])
            if prob.aid is not None:
                old = prob.aid_sigma
                white = max(prob.aid_sigma * np.sqrt(ratio[-1]),
                            prob.aid.floor_nt(np.mean(self.f)))
                prob.aid.sigma_nt = white * serial_inflation(res[:, -1])
                prob.aid.refs['white_sigma_nt'] = float(white)
                self.aid_change = abs(prob.aid.sigma_nt / old - 1.0)
        return new_sigma

    def covariance(self, p, sigma, with_jacobian=True):
        """Return the (P, P) covariance at p (robust: :meth:`sandwich`), chi-square, n_obs."""
        n_p = self.model.n_params
        cov = np.zeros((n_p, n_p)) if with_jacobian else np.full((n_p, n_p), np.nan)
        chi2, n_obs = 0.0, 0
        for grp in self.model.sensor_groups:
            prob = self.problem(grp, sigma, p)
            x = p[prob.cols]
            chi2 += float(np.sum(prob.residuals(x) ** 2))
            n_obs += prob.n_observations
            if not with_jacobian:
                continue
            # a nearly undetermined problem takes the dense Jacobian (resolves_covariance)
            a = prob.normal_equations(x)[0]
            block = (covariance_from_normal(a) if resolves_covariance(a)
                     else covariance_from_jacobian(prob.jacobian(x)))
            if self.robust:
                block = self.sandwich(prob, x, block)
            cov[np.ix_(prob.cols, prob.cols)] = block
        return cov, chi2, n_obs

    def sandwich(self, prob, x, bound):
        """
        Return a group's robust covariance: the M-estimator's sandwich A^-1 B A^-1.

        ``prob`` the group's :class:`ProfiledProblem` at ``x``, ``bound`` its (P_g, P_g)
        Cramer-Rao bound, kept when a direction is undetermined.  The soft-L1 loss (f_scale
        c) of each normalised residual z (3,) weighs w = 1 / sqrt(1 + |z|^2 / c^2):
        A = sum J^T (w I - w^3 z z^T / c^2) J, B the sum of the epochs' score outer products
        (Huber 1967, Proc. Fifth Berkeley Symposium 1, 221-233); prior rows enter both.
        """
        c2 = self.f_scale ** 2
        _, _, _, res = prob.evaluate(x)
        n, g = res.shape[0], res.shape[1]
        jac = prob.jacobian(x)
        jr = jac[:3 * g * n].reshape(n, g, 3, -1)
        jp = jac[3 * g * n:]
        w = 1.0 / np.sqrt(1.0 + np.einsum('nga,nga->ng', res, res) / c2)
        zj = np.einsum('nga,ngap->ngp', res, jr)                        # z^T J, (N, G, P)
        a = (np.einsum('ng,ngap,ngaq->pq', w, jr, jr, optimize=True)
             - np.einsum('ng,ngp,ngq->pq', w ** 3 / c2, zj, zj, optimize=True)
             + jp.T @ jp)
        score = np.einsum('ng,ngp->np', w, zj)                          # per epoch, (N, P)
        b = score.T @ score + jp.T @ jp
        a_inv = covariance_from_normal(0.5 * (a + a.T))
        if not np.all(np.isfinite(a_inv)):
            return bound
        sw = a_inv @ b @ a_inv
        return 0.5 * (sw + sw.T)


def priors_for(model, spec, constrained=False):
    """[(index, mean, sd)] of {name or label: (mean or None, sd)}; constrained: Effect.prior."""
    out = []
    default = model.default_params()
    for j, eff, sl in model.effect_slices():
        prior = spec.get(eff.label, spec.get(eff.name, eff.prior if constrained else None))
        if j and prior is not None:
            mean, sd = prior
            out += [(i, default[i] if mean is None else mean, sd)
                    for i in range(sl.start, sl.stop)]
    return out


def initial_params(raw, field_nt, model, constrained=False, mask=None):
    """
    Return (P,) closed-form starting values of ``model`` (paper 004 section 3).

    Per sensor of ``raw`` (S, N, 3) nT: ellipsoid + Cholesky (eq. 8-13) at ``field_nt`` (N,)
    nT, Procrustes onto sensor 1 (eq. 14), A_j = C_j R_j^T; ``constrained``: A = I, the
    offset from the sphere |m - o| = F.  ``mask`` (S, N) bool: the readings to start from.
    """
    f0 = float(np.mean(field_nt))
    p = model.default_params()
    corrected, mats = [], []
    keep = np.ones(raw.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    for j in range(1, raw.shape[0] + 1):
        m = raw[j - 1] @ model.axis_map(j)
        mk, fk = m[keep[j - 1]], field_nt[keep[j - 1]]
        if constrained:
            # |m|^2 = 2 m.o + (F^2 - |o|^2): linear in (o, c)
            design = np.column_stack([2 * mk, np.ones(len(mk))])
            sol, *_ = np.linalg.lstsq(design, (mk ** 2).sum(1) - fk ** 2 + f0 ** 2, rcond=None)
            c_inv, o = np.eye(3), sol[:3]
        else:
            ell = fit_ellipsoid(mk, f0)
            c_inv, o = ell.c_inv, ell.b
        corrected.append((m - o) @ c_inv.T)
        mats.append((c_inv, o))
    for j, (c_inv, o) in enumerate(mats, 1):
        rot = np.eye(3)
        if j > 1 and model.frame_rotation(j):
            both = keep[0] & keep[j - 1]
            rot = procrustes_rotation(corrected[0][both], corrected[j - 1][both])   # eq. 14
        amap = model.axis_map(j)
        p = model.params_from_linear(j, amap @ np.linalg.inv(c_inv) @ rot.T, amap @ o, p)
    return p


def profile_residuals(model, p, raw, f, sigma, contexts, robust=False, f_scale=3.0,
                      chunk=200000, field0=None):
    """
    Return the profiled field (N, 3) and the residual (S, N, 3) of ``p``, nT, by chunks.

    ``model`` prepared, ``p`` (P,), ``raw`` (S, N, 3) nT, ``f`` (N,) nT, ``sigma`` (S,) nT,
    ``contexts`` (S,); ``robust``, ``f_scale`` the soft-L1 profile; ``field0`` (N, 3) nT
    the field to start from (joint models).  The field of independent sensors: the last's.
    """
    s, n = raw.shape[0], raw.shape[1]
    field = np.zeros((n, 3))
    residual = np.zeros((s, n, 3))
    for start in range(0, n, chunk):
        sl = slice(start, min(n, start + chunk))
        ctx = (contexts if n <= chunk                   # one chunk: no copies of the signals
               else [c.subset(np.arange(sl.start, sl.stop)) for c in contexts])
        for grp in model.sensor_groups:
            prob = ProfiledProblem(model, raw[:, sl], ctx, f[sl], grp, sigma, (), robust,
                                   f_scale, p_full=p,
                                   field0=field0[sl] if field0 is not None and model.joint
                                   else None)
            field[sl] = prob.evaluate(p[prob.cols])[1]
            res = prob.reading_residuals(p[prob.cols])
            for gi, j in enumerate(grp):
                residual[j - 1, sl] = res[:, gi] * sigma[j - 1]
    return field, residual


def corrected_readings(model, p, raw, contexts):
    """Return (S, N, 3) the corrected readings of ``raw`` (S, N, 3) in the array frame, nT."""
    return np.stack([model.correct(j, p, raw[j - 1], contexts[j - 1])
                     for j in range(1, model.n_sensors + 1)])


def centred_readings(model, p, corrected, contexts):
    """(S, N, 3) ``corrected`` minus each sensor's modelled array shift, nT (centre field)."""
    if not model.array_effects:
        return corrected
    return corrected - np.stack([model.array_shift(j, p, contexts[j - 1], corrected[j - 1])
                                 for j in range(1, model.n_sensors + 1)])


def downweighted_counts(residual, sigma, f_scale):
    """Return (S,) the epochs of each sensor with a normalised residual beyond ``f_scale``."""
    return (np.abs(residual / sigma[:, None, None]) > f_scale).any(axis=2).sum(axis=1)


def evaluate(model, p, data, f, sigma, contexts=None, robust=False, f_scale=3.0,
             chunk=200000, field0=None):
    """
    Return the residuals of parameters ``p`` on all epochs of ``data`` (chunked for large N).

    Arguments as :func:`profile_residuals`'.  Returns a dict: field (N, 3), corrected,
    residual (S, N, 3), scalar (S, N), vector (S, N, 3), all nT, downweighted (S,) counts and
    kept ((S, N) bool or None): the readings ``drop`` leaves out have zero entries.
    """
    if contexts is None:
        contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    field, residual = profile_residuals(model, p, data.raw, f, sigma, contexts, robust,
                                        f_scale, chunk, field0)
    corrected = corrected_readings(model, p, data.raw, contexts)
    centred = centred_readings(model, p, corrected, contexts)
    scalar = np.linalg.norm(centred, axis=2) - f[None]
    vector = centred - centred[:1]
    kept = model.reading_mask(data.t) if getattr(model, 'drops', ()) else None
    if kept is not None:
        residual = residual * kept[:, :, None]
        scalar = scalar * kept
        vector = vector * (kept & kept[:1])[:, :, None]
    down = (downweighted_counts(residual, sigma, f_scale) if robust
            else np.zeros(data.n_sensors, int))
    return {'field': field, 'corrected': corrected, 'residual': residual, 'scalar': scalar,
            'vector': vector, 'downweighted': down, 'kept': kept}
