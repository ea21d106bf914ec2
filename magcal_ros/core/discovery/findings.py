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
What is left in the residuals of a fit, model-free: lines, steps, lags, gradients, tails.

:func:`find` names the structure a fitted model leaves, without the effect catalog; each
:class:`Finding` says what it is, how much of the sensor's excess over the noise floor its own
simple model removes, and which effect token to add (``periodic(0.23)@3``, ...).

Series analysed (nT): with 3 or more sensors, sensor j's consensus residual ``c_j -
median_{k != j} c_k`` (``c``: corrected readings in the array frame, (N, 3)), noise plus
sensor j's own faults under a uniform field; with 1 or 2 sensors, the scalar residual
``|c_j| - F``.  Noise: each component's mean square of third differences / 20
(:func:`~.measures.white_noise_sd`, right for heavy tails too).

Method (docs/papers.md, "Methods of the findings"): per sensor, greedily, the significant
test with the largest BIC gain is kept and its fitted signal removed, at most
:data:`MAX_PER_SENSOR` times.  A finding needs p below ``alpha`` / (number of tests) and a
model that removes at least :data:`MIN_SIGNAL_RATIO` x the noise variance and
:data:`MIN_EXPLAINED` of the sensor's excess mean square.

- ``periodic``: periodogram, the channels' powers summed; the power over its local median is
  Gamma(C, 1) under white noise, times the independent frequencies (Scargle 1982): a line
  stands out of its neighbourhood (a random walk is not a line).
- ``step``: the most likely change of the mean (CUSUM), repeated by the greedy loop: binary
  segmentation (Vostrikova 1981); chi-square with C degrees of freedom, Bonferroni over the
  change times; segments of at least :data:`MIN_SEGMENT_FRACTION` of the record.
- ``time``: Legendre trend of degree 1-5 (by BIC); ``direction``: polynomial of degree <= 3
  in the field direction (soft iron, non-linearity, body field); F-tests against none.
- ``channel`` / ``lag`` / ``channel_nonlinear``: per driving channel (temperature, every
  ``aux_*``): linear; through a first-order lag ``tau dy/dt = x - y`` (tau on a log grid);
  x^2, x^3 and sign(dx/dt); F-tests against the linear fit.
- ``heavy_tails``: D'Agostino's kurtosis test on what is left, excess kurtosis above
  :data:`MIN_EXCESS_KURTOSIS`.
- ``nonuniform_field`` (paper 004's cross): the arms' antisymmetric parts of the inter-sensor
  residuals against their symmetric part (:func:`_gradient`), value the RMS Frobenius norm of
  the gradient left, nT/m; the gradient is taken out of the per-sensor series first.
"""
from dataclasses import asdict, dataclass, field, replace
import math

from magcal_ros.core.discovery.constants import (ALPHA, ECHO_RATIO, LINE_NEIGHBOURHOOD,
                                                 MAX_PER_SENSOR, MIN_EPOCHS,
                                                 MIN_EXCESS_KURTOSIS, MIN_EXPLAINED,
                                                 MIN_SEGMENT_FRACTION, MIN_SIGNAL_RATIO, N_TAU,
                                                 STEP_OVER_TREND)
from magcal_ros.core.discovery.measures import (cusum, evenly_sampled, lag_grid, periodogram,
                                                regress, usable, white_noise_sd)
from magcal_ros.core.effects import first_order_lag
from magcal_ros.core.effects.base import format_arg
from magcal_ros.core.model.solvers import single_threaded_blas
import numpy as np
from scipy import ndimage, stats


@dataclass(frozen=True)
class Finding:
    """
    One structure found in the residuals.

    ``kind``: one of :data:`KINDS` ('periodic', 'step', 'lag', 'channel', ...); ``sensor``:
    1-based, None for the array or every sensor alike; ``channel``: the driving channel or
    None; ``value`` (None: none): frequency (Hz) for 'periodic', change time (s) for 'step',
    time constant (s) for 'lag', gradient (nT/m) for 'nonuniform_field', excess kurtosis for
    'heavy_tails', peak-to-peak trend (nT) for 'time', ``unit`` says which;
    ``explained_fraction``: share (0..1) of the sensor's excess mean square over its floor
    its own model removes; ``text``: what it is and what to add; ``token``: the effect token
    to add (None: the catalog has none); ``p_value``: the test's false-alarm probability
    (before Bonferroni); ``rms_nt``: its signal's RMS, nT; ``replaces``: tuple of the tokens
    of the fitted model ``token`` takes the place of (``aux:<col>`` for
    ``aux_poly(<col>,2)``).
    """

    kind: str
    sensor: int | None
    channel: str | None
    value: float | None
    unit: str
    explained_fraction: float
    text: str
    token: str | None = None
    p_value: float = float('nan')
    rms_nt: float = float('nan')
    replaces: tuple = ()

    def to_dict(self):
        """JSON-ready dict (docs/design.md §2 keys first)."""
        return {**asdict(self), 'replaces': list(self.replaces)}


@dataclass(frozen=True, eq=False)
class Findings:
    """
    Outcome of :func:`find`: the findings and the series they were found in.

    ``items``: tuple of Finding, array-level findings first, then per sensor the largest
    effect first; ``t`` (N,) time, s; ``series``: {sensor: (N, C) series analysed, nT},
    'consensus' (C = 3) or 'scalar' (C = 1, ``kind_of_series``), the gradient taken out;
    ``noise_nt``: {sensor: (C,) its white-noise sd, nT}; ``common``: (N, 1) mean scalar
    residual less the sensors' own findings, nT, or None; ``note``: why nothing was searched
    (too short a record), else ''; ``direction``: (N, 3) unit field direction in the array
    frame, or None.
    """

    items: tuple
    t: np.ndarray
    series: dict = field(repr=False)
    noise_nt: dict = field(repr=False)
    kind_of_series: str = 'consensus'
    common: np.ndarray | None = field(repr=False, default=None)
    note: str = ''
    direction: np.ndarray | None = field(repr=False, default=None)

    def to_list(self):
        """List of the findings as dicts."""
        return [f.to_dict() for f in self.items]

    def summary(self):
        """One line per finding."""
        if self.note:
            return f'findings (model-free): not searched: {self.note}'
        if not self.items:
            return 'findings (model-free): none'
        return '\n'.join(['findings (model-free, largest share of the excess first):']
                         + [f'  {f.text}' for f in self.items])


# -- helpers ---------------------------------------------------------------------------------

def _f_test(ss0, ss1, k, dof):
    """p-value of the F-test of k extra regressors lowering SS from ss0 to ss1."""
    if k <= 0 or dof <= 0 or ss1 <= 0:
        return 1.0
    f = max(ss0 - ss1, 0.0) / k / (ss1 / dof)
    return float(stats.f.sf(f, k, dof))


def _f_mean(x, fitted, rank):
    """p-value of the F-test of ``fitted`` ((N, C), ``rank`` columns, one the mean) vs the mean."""
    n, c = x.shape
    return _f_test(float(np.sum((x - x.mean(axis=0)) ** 2)), float(np.sum((x - fitted) ** 2)),
                   c * (rank - 1), n * c - c * rank)


def _nuisance(u):
    """(N, 10) columns 1, u_a, u_a u_b: an offset c and matrix E in the scalar, u.c + u.E u."""
    cols = [np.ones(len(u)), *u.T]
    cols += [u[:, a] * u[:, b] for a in range(3) for b in range(a, 3)]
    return np.column_stack(cols)


def _expand(design, mod):
    """
    Design of a vector effect seen through the scalar residual along the field direction u.

    Columns phi_k u_c (``mod``: u, (N, 3)) after the :func:`_nuisance` ones (replacing the
    constant first column of ``design``).
    """
    if mod is None:
        return design
    cols = [_nuisance(mod)] + [design[:, k:k + 1] * mod for k in range(1, design.shape[1])]
    return np.concatenate(cols, axis=1)


def _detect(x, sd, mod):
    """Series (N, C') and sd (C',) to detect lines and steps in: demodulated with u."""
    if mod is None:
        return x, sd
    xd = 3.0 * x * mod          # E[u u^T] = I / 3 over the attitudes: 3 (u.e) u ~ e
    return xd, white_noise_sd(xd)


@dataclass
class _Candidate:
    kind: str
    fitted: np.ndarray           # (N, C) nT
    k: int                       # parameters (per all components)
    p: float                     # p-value
    n_tests: int                 # Bonferroni factor
    channel: str | None = None
    value: float | None = None
    unit: str = ''
    detail: dict = field(default_factory=dict)


# -- the tests -------------------------------------------------------------------------------

def _test_periodic(t, x, sd, mod=None):
    n, c0 = x.shape
    x_det, sd = _detect(x, sd, mod)
    c = x_det.shape[1]
    freqs, power, n_ind = periodogram(t, x_det)
    z = np.sum(power / sd ** 2, axis=1)            # Gamma(C, 1) under white noise
    span = t[-1] - t[0]
    ok = freqs >= 3.0 / span
    if not ok.any():
        return None
    step = max(1, len(freqs) // max(n_ind, 1))
    half = LINE_NEIGHBOURHOOD * step
    # the local continuum: running median of the summed power
    back = ndimage.median_filter(z, size=2 * half + 1, mode='nearest')
    rel = z / np.maximum(back, 1e-300) * stats.gamma.median(c)
    rel[~ok] = 0.0
    i = int(np.argmax(rel))
    p = float(stats.gamma.sf(rel[i], c))
    # refine the frequency (parabola through the peak of the summed power)
    f0 = freqs[i]
    if 0 < i < len(freqs) - 1:
        y0, y1, y2 = z[i - 1], z[i], z[i + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            f0 = freqs[i] + 0.5 * (y0 - y2) / den * (freqs[1] - freqs[0])
    w = 2 * np.pi * f0 * (t - t[0])
    design = _expand(np.column_stack([np.ones(n), np.cos(w), np.sin(w)]), mod)
    fitted, rank = regress(x, design)
    fitted -= x.mean(axis=0)
    return _Candidate('periodic', fitted, c0 * (rank - 1) + 1, p, n_ind, value=float(f0),
                      unit='Hz',
                      detail={'peak_over_continuum': float(rel[i] / stats.gamma.median(c))})


def _test_step(t, x, sd, mod=None):
    n, c0 = x.shape
    m = max(10, int(MIN_SEGMENT_FRACTION * n))
    if n < 2 * m + 1:
        return None
    x_det, sd = _detect(x, sd, mod)
    c = x_det.shape[1]
    kk, stat = cusum((x_det - x_det.mean(axis=0)) / sd, margin=m - 1)
    p = float(stats.chi2.sf(stat, c))
    after = (np.arange(n) >= kk).astype(float)
    design = _expand(np.column_stack([np.ones(n), after]), mod)
    fitted, rank = regress(x, design)
    coef = np.linalg.lstsq(design, fitted, rcond=None)[0]
    fitted = fitted - x.mean(axis=0)
    jump = coef[10:, 0] if mod is not None else coef[1]
    return _Candidate('step', fitted, c0 * (rank - 1) + 1, p, n - 2 * m, value=float(t[kk]),
                      unit='s', detail={'index': kk, 'jump_nt': np.ravel(jump).tolist()})


def _trend(t, degree):
    """(N, degree + 1) Legendre polynomials 0..degree of time scaled to [-1, 1]."""
    u = 2.0 * (t - t[0]) / max(t[-1] - t[0], 1e-300) - 1.0
    return np.polynomial.legendre.legvander(u, degree)


def _test_time(t, x, sd, mod=None):
    n, c = x.shape
    fits = []
    for d in range(1, 6):
        fitted, rank = regress(x, _expand(_trend(t, d), mod))
        bic = np.sum(np.sum((x - fitted) ** 2, axis=0) / sd ** 2) + c * (rank - 1) * math.log(n)
        fits.append((bic, d, fitted, rank))
    _, d, fitted, rank = min(fits, key=lambda f: f[0])
    p = _f_mean(x, fitted, rank)
    fitted = fitted - x.mean(axis=0)
    ptp = float(np.max(np.ptp(fitted, axis=0)))         # as seen in the series
    return _Candidate('time', fitted, c * (rank - 1), p, 5, value=ptp, unit='nT',
                      detail={'degree': d})


def _test_direction(u, x):
    # (N, 20) the :func:`_nuisance` columns and the cubes u_a u_b u_c of the direction
    fitted, rank = regress(x, np.column_stack(
        [_nuisance(u)] + [u[:, a] * u[:, b] * u[:, c] for a in range(3)
                          for b in range(a, 3) for c in range(b, 3)]))
    return _Candidate('direction', fitted - x.mean(axis=0), x.shape[1] * (rank - 1),
                      _f_mean(x, fitted, rank), 1)


class _Driver:
    """A driving channel, standardised, with its lagged versions (computed once)."""

    def __init__(self, t, name, values):
        self.t, self.name = t, name
        a = np.asarray(values, float)
        self.ok = usable(a)
        if not self.ok:
            return
        n = len(a)
        self.a = (a - a.mean()) / np.std(a)
        self.taus = lag_grid(t, N_TAU, shortest=1e-4, longest=0.5, samples=3)
        self.base = np.column_stack([np.ones(n), self.a])
        self.q = q = np.linalg.qr(self.base)[0]
        self.lags = lags = (np.column_stack([first_order_lag(t, self.a, tau) for tau in self.taus])
                            if len(self.taus) else np.zeros((n, 0)))
        self.lags_perp = lags - q @ (q.T @ lags)          # orthogonal to [1, a]
        self.lag_norm2 = np.sum(self.lags_perp ** 2, axis=0)
        rate = np.gradient(ndimage.uniform_filter1d(self.a, max(3, n // 200)), t)
        hyst = np.tanh(rate / (np.std(rate) + 1e-300) * 3.0)
        self.nonlin = np.column_stack([self.base, self.a ** 2, self.a ** 3, hyst])

    def lag_response(self, tau):
        """(N,) the standardised channel through a first-order lag of ``tau`` s."""
        return first_order_lag(self.t, self.a, tau)


def _refined_tau(drv, neg_gain, grid_values):
    """Time constant, s: the grid's best (least ``grid_values``), refined between neighbours."""
    from scipy.optimize import minimize_scalar
    i = int(np.argmin(grid_values))
    logs = np.log(drv.taus)
    lo, hi = logs[max(i - 1, 0)], logs[min(i + 1, len(logs) - 1)]
    if hi <= lo:
        return float(drv.taus[i])
    return float(math.exp(minimize_scalar(neg_gain, bounds=(lo, hi), method='bounded',
                                          options={'xatol': 3e-3}).x))


def _best_tau(drv, x_perp):
    """Time constant (refined between grid points) maximising the fit of x_perp (N, C)."""
    good = drv.lag_norm2 > 1e-12 * len(drv.a)
    if not good.any():
        return None
    gain = np.sum((drv.lags_perp.T @ x_perp) ** 2, axis=1) / np.where(good, drv.lag_norm2, 1)

    def neg(log_tau):
        y = drv.lag_response(math.exp(log_tau))
        y = y - drv.q @ (drv.q.T @ y)
        return -float(np.sum((y @ x_perp) ** 2) / max(y @ y, 1e-300))
    return _refined_tau(drv, neg, np.where(good, -gain, 1.0))


def _test_channel(t, x, drv, mod=None):
    """Linear, lagged and non-linear coupling of the series to one driving channel."""
    n, c = x.shape
    if not drv.ok:
        return []
    name = drv.name
    ss = lambda f: float(np.sum((x - f) ** 2))      # noqa: E731
    xm = x.mean(axis=0)
    if mod is None:
        lin, r1 = drv.q @ (drv.q.T @ x), 2
    else:
        lin, r1 = regress(x, _expand(drv.base, mod))
    ss1 = ss(lin)
    out = [_Candidate('channel', lin - xm, c * (r1 - 1), _f_mean(x, lin, r1), 1, channel=name)]
    # first-order lag: the best time constant (grid, then refined)
    if mod is None:
        tau = _best_tau(drv, x - lin) if len(drv.taus) else None
    else:
        tau = _best_tau_modulated(drv, x, mod)
    if tau is not None:
        fit_l, rank = regress(x, _expand(np.column_stack([drv.base, drv.lag_response(tau)]), mod))
        out.append(_Candidate('lag', fit_l - xm, c * (rank - 1) + 1,
                              _f_test(ss1, ss(fit_l), c * (rank - r1), n * c - c * rank),
                              N_TAU, channel=name, value=tau, unit='s'))
    # curved, saturating or hysteretic: x^2, x^3 and the direction of change
    design = drv.nonlin

    def ss_of(cols):
        return ss(regress(x, _expand(design[:, :cols], mod))[0])
    fit_n, rank = regress(x, _expand(design, mod))
    s = ss(fit_n)
    # which term carries it: refit without the hysteresis column, then without x^3
    form = 'hysteretic' if ss_of(4) - s > 0.5 * (ss1 - s) else 'curved'
    degree = 3 if form == 'curved' and ss_of(3) - s > 0.5 * (ss1 - s) else 2
    out.append(_Candidate('channel_nonlinear', fit_n - xm, c * (rank - r1),
                          _f_test(ss1, s, c * (rank - r1), n * c - c * rank), 1, channel=name,
                          detail={'form': form, 'degree': degree}))
    return out


def best_lag(t, x, drive):
    """
    Time constant (s) of the first-order lag through which ``drive`` best explains ``x``.

    ``t`` (N,) s; ``x`` (N, C) residual series, nT; ``drive`` (N,) the channel, in its unit.
    None when the channel is constant or the record too short for a lag grid.
    """
    drv = _Driver(np.asarray(t, float), 'channel', drive)
    if not drv.ok or not len(drv.taus):
        return None
    x = np.asarray(x, float)
    x = (x[:, None] if x.ndim == 1 else x) - np.mean(x, axis=0)
    return _best_tau(drv, x - drv.q @ (drv.q.T @ x))


def _best_tau_modulated(drv, x, mod):
    """Lag time constant for a series seen through the field direction (grid, refined)."""
    if not len(drv.taus):
        return None
    q, _ = np.linalg.qr(_expand(drv.base, mod))

    def neg_gain(log_tau, y=None):
        y = (drv.lag_response(math.exp(log_tau)) if y is None else y)[:, None] * mod
        y = y - q @ (q.T @ y)                                     # (N, 3)
        return -float(np.sum(regress(x, y)[0] ** 2))
    return _refined_tau(drv, neg_gain, [neg_gain(0.0, drv.lags[:, i])
                                        for i in range(len(drv.taus))])


# -- the kinds of finding: one table the description, the tokens and the report read -------

@dataclass(frozen=True)
class Kind:
    """
    One kind of finding (:data:`KINDS`): its token, text, words and the report's figure.

    ``token(value, channel, detail, '@j' or '')``: the token to add, or None (detail empty for
    a finding read back as a dict); ``text(candidate, at, token, on, share)``: what it is and
    what to add; ``follows(finding)``: what the residual follows, in words.
    """

    token: object
    text: object = None
    follows: object = None
    view: str | None = None


def _drift(v, ch, d, at):
    return {1: f'drift{at}', 2: f'drift2{at}'}.get(d.get('degree'))


def _poly(v, ch, d, at):
    curved = d.get('form', 'curved') == 'curved'
    return f'aux_poly({ch},{d.get("degree", 2)}){at}' if ch and ch != 'temperature' and curved \
        else None


_LAGGED = 'residual_lagged'
#: the kinds of finding, kind -> :class:`Kind`
KINDS = {
    'periodic': Kind(
        lambda v, ch, d, at: None if v is None else f'periodic({v:.4g}){at}',
        lambda c, at, tok, on, pct: (
            f'{on}: a spectral line at {c.value:.4g} Hz (period {1 / c.value:.3g} s, '
            f'{c.detail["peak_over_continuum"]:.0f} x the spectrum around it) removes {pct}: '
            f'add {tok} (or log the source as an aux channel)'),
        lambda f: f'a line at {f.value:.4g} Hz', 'residual_spectrum'),
    'step': Kind(
        lambda v, ch, d, at: None if v is None else f'step({format_arg(v)}){at}',
        lambda c, at, tok, on, pct: (
            f'{on}: an offset step of {np.linalg.norm(c.detail["jump_nt"]):.1f} nT at '
            f't = {format_arg(c.value)} s removes {pct}: add {tok}'),
        lambda f: f'a step at {format_arg(f.value)} s', 'change_points'),
    'time': Kind(
        _drift,
        lambda c, at, tok, on, pct: (
            f'{on}: a slow trend over time ({c.value:.1f} nT peak to peak) removes {pct}: '
            + (f'add {tok}' if tok else
               f'a slow trend of degree {c.detail["degree"]}: drift2{at} takes its quadratic '
               'part; check the reference field (a diurnal variation) or the temperature')),
        lambda f: 'time (a trend)'),
    'direction': Kind(
        lambda v, ch, d, at: f'nonlinearity{at}',
        lambda c, at, tok, on, pct: (
            f'{on}: the residual depends on the field direction (attitude) and removes {pct}: '
            f'add {tok} or soft_iron{at} (or a magnetic part that turns with the sensor)'),
        lambda f: 'the field direction in the sensor (the attitude)', 'residual_direction'),
    'channel': Kind(
        lambda v, ch, d, at: f'temperature{at}' if ch == 'temperature' else f'aux:{ch}{at}',
        lambda c, at, tok, on, pct: (
            f'{on}: the residual follows {c.channel} linearly ({pct}): add {tok}'),
        lambda f: f'the channel {f.channel}', _LAGGED),
    'lag': Kind(
        lambda v, ch, d, at: f'lag({ch}){at}' if ch else None,
        lambda c, at, tok, on, pct: (
            f'{on}: {c.channel} acts through a first-order lag of about {c.value:.3g} s '
            f'({pct}): add {tok}'),
        lambda f: f'the channel {f.channel} through a lag', _LAGGED),
    'channel_nonlinear': Kind(
        _poly,
        lambda c, at, tok, on, pct: (
            f'{on}: the residual against {c.channel} is {c.detail["form"]} ({pct}): '
            + (f'add {tok}' if tok else 'the catalog has no such coupling: write a plug-in '
               'effect (docs/plugins.md)')),
        lambda f: f'the channel {f.channel}, not linearly', _LAGGED),
    'nonuniform_field': Kind(lambda v, ch, d, at: 'site_gradient',
                             follows=lambda f: 'a field gradient across the array'),
    'heavy_tails': Kind(lambda v, ch, d, at: None),
}


def view_of(finding):
    """Return the report's figure that shows ``finding`` (:attr:`Kind.view`), or None."""
    return getattr(KINDS.get(finding.kind), 'view', None)


def _describe(cand, sensor, share):
    """(token or None, text) of a finding on ``sensor`` (None: every sensor alike)."""
    at = '' if sensor is None else f'@{sensor}'
    on = (f'sensor {sensor}' if sensor is not None else
          'every sensor alike (in the mean scalar residual)')
    pct = f'{100 * min(share, 1.0):.0f} % of the excess over the floor'
    kind = KINDS[cand.kind]
    tok = kind.token(cand.value, cand.channel, cand.detail, at)
    return tok, kind.text(cand, at, tok, on, pct)


# -- the array: a non-uniform field ----------------------------------------------------------

def _gradient(t, corrected, baseline_m, alpha, drivers=None):
    """
    Test for a gradient across the cross: (finding or None, (S, N, 3) part to take out, nT).

    With m_j = c_j - mean_k c_k, the arms' antisymmetric parts a_x = (m1 - m3) / 2, a_y =
    (m2 - m4) / 2 and the symmetric part s = (m1 + m3 - m2 - m4) / 4 obey E[a_x^2 + a_y^2] =
    4 E[s^2] for noise and one sensor's fault; a gradient adds G r_j to the a's only (paper
    004 eq. 1): F-test of the two.  ``drivers`` (N, m): taken out of the m_j first.
    """
    from magcal_ros.core.geometry.tensor import tensor_cross
    from scipy.signal import savgol_filter
    m = corrected - corrected.mean(axis=0)
    if drivers is not None and len(drivers):
        # sensors a channel or time moves differently: not a gradient of the site
        n_ = m.shape[1]
        flat = m.transpose(1, 0, 2).reshape(n_, -1)
        flat = flat - regress(flat, drivers)[0]
        m = flat.reshape(n_, 4, 3).transpose(1, 0, 2)
    ax = 0.5 * (m[0] - m[2])
    ay = 0.5 * (m[1] - m[3])
    sym = 0.25 * (m[0] + m[2] - m[1] - m[3])
    n = m.shape[1]
    a_ms = float(np.mean(ax ** 2) + np.mean(ay ** 2))       # per component
    s_ms = float(np.mean(sym ** 2))
    excess = a_ms - 4.0 * s_ms
    if s_ms <= 0 or excess <= 0:
        return None, None
    p = float(stats.f.sf(a_ms / (4.0 * s_ms), 6 * n, 3 * n))
    # effect size: the gradient's mean square per component against the sensors' own
    if not (p < alpha and excess / 2.0 >= MIN_SIGNAL_RATIO * 4.0 * s_ms):
        return None, None
    # share of the arms' excess over their white noise that only a gradient explains
    white = float(np.mean(white_noise_sd(ax) ** 2) + np.mean(white_noise_sd(ay) ** 2))
    share = excess / max(a_ms - white, excess)
    # |G|_F^2 of tensor_cross has the noise bias 5 sum_j sigma_j^2 / L^2 = 80 mean(s^2) / L^2
    g = tensor_cross(m, baseline_m)
    g2 = float(np.mean(np.sum(g ** 2, axis=(1, 2)))) - 80.0 * s_ms / baseline_m ** 2
    value = math.sqrt(max(g2, 0.0))
    text = (f'array: the sensors disagree as a field gradient does (opposite sensors of the '
            f'cross antisymmetric: {a_ms / (4 * s_ms):.1f} x what independent sensor errors '
            f'give), about {value:.0f} nT/m left in the residuals (baseline {baseline_m:g} m): '
            'the field is not uniform over the array (a magnetic object nearby); calibrate '
            'where the field is uniform, or model the site gradient: add site_gradient with '
            'the attitude (att_qw..att_qz, an Imu topic) or with --heading-unknown '
            '(docs/site_gradient.md)')
    f = Finding(kind='nonuniform_field', sensor=None, channel=None, value=value, unit='nT/m',
                explained_fraction=float(np.clip(share, 0.0, 1.0)), text=text,
                token=KINDS['nonuniform_field'].token(value, None, {}, ''), p_value=p,
                rms_nt=float(math.sqrt(excess / 2.0)))
    # smoothed (cubic Savitzky-Golay, 11 samples): the gradient follows the attitude, noise not
    if n < 11:
        return f, None
    gx = savgol_filter(ax, 11, 3, axis=0)
    gy = savgol_filter(ay, 11, 3, axis=0)
    return f, np.stack([gx, gy, -gx, -gy])


# -- the analysis ----------------------------------------------------------------------------

def _series(corrected, scalar):
    """{sensor: (N, C) series} and the kind of series."""
    s = corrected.shape[0]
    if s >= 3:
        return {j + 1: corrected[j] - np.median(np.delete(corrected, j, axis=0), axis=0)
                for j in range(s)}, 'consensus'
    return {j + 1: scalar[j][:, None] for j in range(s)}, 'scalar'


def _sensor_findings(t, x, sd, u, drivers, sensor, alpha_test, mod=None):
    """Greedy search on one series: ([(Finding, ms removed)], remainder); ``mod``: _expand's."""
    n, c = x.shape
    x = x - x.mean(axis=0)
    noise = float(np.mean(sd ** 2))
    excess0 = float(np.mean(x ** 2)) - noise
    found = []
    if excess0 <= MIN_SIGNAL_RATIO * noise:
        return found, x
    used = set()
    for _ in range(MAX_PER_SENSOR):
        cands = [fn(t, x, sd, mod) for fn in (_test_periodic, _test_step, _test_time)]
        cands += ([] if u is None else [_test_direction(u, x)])
        cands += [cand for drv in drivers for cand in _test_channel(t, x, drv, mod)]
        passed = []
        for cand in filter(None, cands):
            removed = float(np.mean(cand.fitted ** 2 + 2 * cand.fitted * (x - cand.fitted)))
            share = removed / excess0
            if not (cand.p * cand.n_tests > alpha_test or removed < MIN_SIGNAL_RATIO * noise
                    or share < MIN_EXPLAINED):
                gain = removed * n * c / noise - cand.k * math.log(n)
                passed.append((gain, cand, removed, share))
        if not passed:
            break
        best = max(passed, key=lambda b: b[0])
        if best[1].kind == 'time':      # a step explaining nearly as much describes it better
            steps = [b for b in passed
                     if b[1].kind == 'step' and b[2] >= STEP_OVER_TREND * best[2]]
            if steps:
                best = steps[0]
        _, cand, removed, share = best
        key = (cand.kind, cand.channel)
        tok, text = _describe(cand, sensor, share)
        if key not in used or cand.kind in ('periodic', 'step'):
            found.append((Finding(kind=cand.kind, sensor=sensor, channel=cand.channel,
                                  value=cand.value, unit=cand.unit,
                                  explained_fraction=float(min(1.0, share)), text=text,
                                  token=tok, p_value=cand.p,
                                  rms_nt=float(np.sqrt(np.mean(cand.fitted ** 2)))), removed))
            used.add(key)
        x = x - cand.fitted
    return found, x


def _tails(x, sd, sensor, alpha_test):
    """
    heavy_tails finding of one sensor's remainder x (N, C), or None.

    Tested on the first differences (a slow leftover does not reach them; their excess
    kurtosis is half the noise's).
    """
    if x.shape[0] < 40:
        return None
    d = np.diff(x, axis=0) / (math.sqrt(2.0) * sd)
    kurt = 2.0 * float(np.mean(stats.kurtosis(d, axis=0, fisher=True)))
    p = float(stats.kurtosistest(d.ravel()).pvalue)
    # the robust (MAD) noise level reads low for heavy tails
    mad = stats.median_abs_deviation(d, axis=0, scale='normal') * sd
    low = 1.0 - float(np.sqrt(np.mean(mad ** 2) / np.mean(sd ** 2)))
    if not (p < alpha_test and kurt >= MIN_EXCESS_KURTOSIS and low > 0):
        return None
    ex_robust = float(np.mean(x ** 2)) - float(np.mean(mad ** 2))
    share = (float(np.mean(sd ** 2)) - float(np.mean(mad ** 2))) / ex_robust \
        if ex_robust > 0 else 1.0
    text = (f'sensor {sensor}: heavy-tailed noise (excess kurtosis {kurt:.1f}; a Gaussian has '
            f'0): fit with --robust (soft-L1 loss); a robust (MAD) noise floor reads '
            f'{100 * low:.0f} % low')
    return Finding(kind='heavy_tails', sensor=sensor, channel=None, value=kurt, unit='',
                   explained_fraction=float(np.clip(share, 0.0, 1.0)), text=text, token=None,
                   p_value=p, rms_nt=float(np.sqrt(np.mean(sd ** 2))))


def _in_model(f, model):
    """``f`` with the tokens of ``model`` its token takes the place of (see Finding)."""
    if model is None or not f.token:
        return f
    from magcal_ros.core.discovery.results import compact_spec
    spec = compact_spec(model)

    def takes(new):
        try:
            return new().with_effect(f.token)
        except ValueError:
            return None
    kept = takes(lambda: model)
    if kept is not None:
        # a larger form replaces what it contains (aux_poly > aux: Effect.supersedes)
        kept = compact_spec(kept)
        gone = tuple(t for t in spec if t != 'base' and t not in kept)
    else:
        gone = tuple(tok for tok in spec if tok != 'base' and takes(
            lambda: type(model).from_spec(','.join(x for x in spec if x != tok),
                                          model.n_sensors)) is not None)
    if not gone:
        return f
    return replace(f, replaces=gone, text=f'{f.text} in place of {" ".join(gone)}')


def _sameness(t):
    """Return same(a, b): findings ``a`` and ``b`` are one (kind, channel, time or frequency)."""
    _, dt = evenly_sampled(t)
    t_res = max(5 * dt, 0.01 * (t[-1] - t[0]))
    f_res = 2.0 / max(t[-1] - t[0], 1e-300)

    def same(a, b):
        return a.kind == b.kind and a.channel == b.channel and (
            a.kind not in ('step', 'periodic')
            or abs(a.value - b.value) <= (t_res if a.kind == 'step' else f_res))
    return same


# -- the stages of find ------------------------------------------------------------------------

def _array_stage(data, t, corrected, baseline_m, alpha):
    """Test the four-sensor cross: ([nonuniform_field finding] or [], corrected less it)."""
    if corrected.shape[0] != 4:
        return [], corrected
    cols = [_trend(t, 3)]
    for a in list(data.aux.values()) + ([] if data.temp is None else list(data.temp)):
        a = np.asarray(a, float)
        if usable(a):
            a = (a - a.mean()) / np.std(a)
            cols.append(np.column_stack([a, a ** 2]))
    grad, part = _gradient(t, corrected, baseline_m, alpha, np.concatenate(cols, axis=1))
    if grad is None:
        return [], corrected
    return [grad], corrected if part is None else corrected - part


def _sensor_stage(data, t, series, kind, noise, u, aux_drivers, alpha_test, alpha_tails):
    """Every sensor's tests: ([(Finding, ms removed)], {sensor: (N, C) its findings' fit, nT})."""
    per, explained = [], {}
    for j, x in series.items():
        if np.any(noise[j] <= 0):
            continue
        # a scalar series: the vector faults show along the field direction only
        mod = u if kind == 'scalar' else None
        if mod is not None:
            x = x - regress(x, _nuisance(u))[0]
        drivers = list(aux_drivers)
        if data.temp is not None and np.all(np.isfinite(data.temp[j - 1])):
            drivers.insert(0, _Driver(data.t, 'temperature', data.temp[j - 1]))
        found, rest = _sensor_findings(t, x, noise[j], u, drivers, j, alpha_test, mod=mod)
        explained[j] = x - x.mean(axis=0) - rest
        tails = _tails(rest, noise[j], j, alpha_tails)
        per.extend(found + ([] if tails is None else [(tails, 0.0)]))
    return per, explained


def _attribute(per, gradient, same):
    """
    Return the findings each sensor has of its own (list of Finding).

    A much smaller same finding on another sensor is the echo through the consensus; with a
    ``gradient``, what both sensors of an arm show is left of the gradient.
    """
    keep = []
    for f, removed in per:
        rivals = [r for g, r in per if g is not f and g.sensor != f.sensor
                  and g.kind != 'heavy_tails' and same(f, g)]
        if not rivals or removed >= ECHO_RATIO * max(rivals):
            keep.append(f)
    if gradient:
        arm = {1: 3, 3: 1, 2: 4, 4: 2}
        keep = [f for f in keep if f.kind != 'direction' and not any(
            g.sensor == arm.get(f.sensor) and same(f, g) for g in keep)]
    return keep


def _common_stage(data, t, scalar, explained, u, aux_drivers, alpha_test, keep, same):
    """Test the mean scalar residual less each sensor's own: (found, ``keep`` less them, x0)."""
    s = scalar.shape[0]
    x0 = np.mean(scalar, axis=0)
    for j, e in explained.items():
        x0 = x0 - np.sum(e * u, axis=1) / s
    x0 = x0[:, None] - regress(x0[:, None], _nuisance(u))[0]
    sd0 = white_noise_sd(x0)
    common = []
    if not np.all(sd0 > 0):
        return common, keep, x0
    drivers = aux_drivers
    if data.temp is not None and np.all(np.isfinite(data.temp)):
        drivers = [_Driver(t, 'temperature', np.mean(data.temp, axis=0))] + drivers
    found, _ = _sensor_findings(t, x0, sd0, None, drivers, None, alpha_test, mod=u)
    for f, _ in found:
        alike = {g.sensor for g in keep if same(f, g)}
        if len(alike) != 1:         # one sensor's fault, seen in the mean: reported there
            keep = [g for g in keep if g.sensor not in alike or not same(f, g)]
            common.append(f)
    return common, keep, x0


def find(data, result, *, baseline_m=0.5, alpha=ALPHA, corrected=None, field=None):
    """
    Model-free findings in the residuals of a fit; returns :class:`Findings`.

    ``data``: Dataset (S sensors, N epochs) in time order, its temperatures and ``aux_*``
    drive the channel tests; ``result``: a FitResult on ``data``, its corrected readings
    (S, N, 3), ``scalar_residual_nt`` (S, N) and ``field_nt`` (N, 3), nT, where its ``drop``
    terms keep every sensor; ``baseline_m``: arm length of the four-sensor cross, m (paper
    004), for the gradient magnitude; ``alpha``: family-wise false-alarm probability
    (Bonferroni over sensors and tests); ``corrected`` (S, N, 3), ``field`` (N, 3), nT:
    instead of the result's.
    """
    # one BLAS thread: the designs are thin (N x 10-30), threads only contend
    with single_threaded_blas():
        t = np.asarray(data.t, float)
        if corrected is None:
            # the field where each sensor is, minus a modelled site gradient (site_gradient)
            from magcal_ros.core.model.site_gradient import centred_fields
            corrected = centred_fields(result)
        corrected = np.asarray(corrected, float)
        field_ = np.asarray(result.field_nt if field is None else field, float)
        scalar = np.asarray(result.scalar_residual_nt, float)
        kept = getattr(result, 'reading_mask', None)
        if kept is not None and not kept.all():
            # the model's drop() terms: the tests look at the sets every sensor keeps
            sets = np.flatnonzero(kept.all(axis=0))
            data, t = data.subset(sets), t[sets]
            corrected, field_, scalar = corrected[:, sets], field_[sets], scalar[:, sets]
        s, n = corrected.shape[:2]
        if n < MIN_EPOCHS:
            return Findings(items=(), t=t, series={}, noise_nt={}, note=(
                f'{n} epochs, fewer than the {MIN_EPOCHS} the tests need'))
        array_items, corrected = _array_stage(data, t, corrected, baseline_m, alpha)
        series, kind = _series(corrected, scalar)
        norm = np.linalg.norm(field_, axis=1, keepdims=True)
        u = field_ / np.where(norm > 0, norm, 1.0)
        noise = {j: white_noise_sd(x) for j, x in series.items()}
        n_tests = 5 + 3 * (len(data.aux) + (data.temp is not None))
        alpha_test = alpha / ((s + 1) * n_tests)      # the sensors and their common part
        aux_drivers = [_Driver(t, name, data.aux[name]) for name in sorted(data.aux)]
        per, explained = _sensor_stage(data, t, series, kind, noise, u, aux_drivers, alpha_test,
                                       alpha / s)
        same = _sameness(t)
        keep = _attribute(per, array_items, same)
        common, x0 = [], None
        if kind == 'consensus':
            common, keep, x0 = _common_stage(data, t, scalar, explained, u, aux_drivers,
                                             alpha_test, keep, same)
        items = tuple(_in_model(f, getattr(result, 'model', None)) for f in
                      array_items + common + sorted(keep, key=lambda f: (f.sensor,
                                                                         -f.explained_fraction)))
        return Findings(items=items, t=t, series=series, noise_nt=noise, kind_of_series=kind,
                        common=x0, direction=u)
