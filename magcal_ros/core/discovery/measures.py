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
Residual measures of the diagnosis (nT), statistics of nested fits, the residual toolkit.

Measures: sensor j's scalar residual |corrected_j| - F (RMS sigma_j at the floor); the vector
residual corrected_j - corrected_1 (j > 1; sqrt(sigma_j^2 + sigma_1^2) per component); the
combined residual, the raw-space residual scaled by :func:`dof_factor` (the per-axis noise sd
at the floor; the held-out measure).  The toolkit (one implementation each): noise level,
sampling tests, periodograms, change points, lag grid, regression.
"""
from dataclasses import dataclass
import math

from magcal_ros.core.discovery.constants import (CLOCK_JITTER, CLOCK_OUTLIERS, EVEN_SAMPLING,
                                                 LAG_GRID_POINTS, LS_BUDGET)
from magcal_ros.core.model.fitting import evaluate
import numpy as np
from scipy import stats


def dof_factor(model):
    """Return 3G / (3G - 2): undo the 2 field directions profiled per epoch from G sensors."""
    g = model.n_sensors if model.joint else 1
    return 3.0 * g / (3.0 * g - 2.0)


def n_observations(model, n, kept=None):
    """
    Return the observations of ``n`` epochs net of the profiled field: N sum(3G - 2).

    ``kept`` (S, N) bool: the readings kept (``drop``): 3 per reading less 2 per group's epoch.
    """
    if kept is None:
        return int(n * sum(3 * len(g) - 2 for g in model.sensor_groups))
    out = 0
    for g in model.sensor_groups:
        rows = 3 * kept[[j - 1 for j in g]].sum(axis=0)
        out += int(np.sum(np.where(rows > 0, rows - 2, 0)))
    return out


def rms(x, kept=None):
    """Return the RMS of ``x`` (any shape, nT) over the entries ``kept`` (bool); NaN if none."""
    x = np.asarray(x, float)
    if kept is not None:
        x = x[np.asarray(kept, bool)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float('nan')


def scalar_rms_of(scalar, sensors, kept=None):
    """Return the pooled RMS of the (S, N) scalar residual of ``sensors`` where ``kept``, nT."""
    rows = [j - 1 for j in sensors]
    return rms(scalar[rows], None if kept is None else kept[rows])


def vector_rms_of(vector, sensors, n_sensors, kept=None):
    """Return the pooled RMS of the vector residuals of ``sensors`` where they and 1 are kept."""
    if n_sensors < 2:
        return None
    js = sorted({j for j in sensors if j > 1} if 1 not in sensors
                else set(range(2, n_sensors + 1)))
    rows = [j - 1 for j in js]
    return rms(vector[rows], None if kept is None else (kept & kept[:1])[rows])


@dataclass
class Evaluation:
    """
    Residuals of one parameter vector on the full data.

    ``chi2``: sum of squared normalised residuals (or the robust loss's equivalent);
    ``scalar`` (S, N), ``vector`` (S, N, 3) and raw-space ``residual`` (S, N, 3), nT;
    ``field`` (N, 3) nT; ``kept`` (S, N) bool: the readings the model keeps (None: all).
    """

    chi2: float
    scalar: np.ndarray
    vector: np.ndarray
    residual: np.ndarray
    field: np.ndarray
    kept: np.ndarray | None = None

    @property
    def mean_square(self):
        """Return the raw-space residual's mean square over the readings kept, nT^2."""
        return rms(self.residual, self.kept) ** 2

    def scalar_rms(self, j):
        """Return sensor j's scalar residual RMS over its readings kept, nT."""
        return scalar_rms_of(self.scalar, [j], self.kept)

    def vector_rms(self, j):
        """Return sensor j's vector residual RMS (vs sensor 1) where both are kept, nT."""
        return vector_rms_of(self.vector, [j], self.scalar.shape[0], self.kept)


def evaluate_residuals(model, p, data, f, sigma, contexts, field0=None, loss=None):
    """
    Evaluate ``model`` at ``p`` on ``data``: an :class:`Evaluation`.

    As :func:`magcal_ros.core.model.evaluate`; ``loss``: a robust loss's chi-square
    equivalent (:func:`soft_l1_lr_loss`).
    """
    out = evaluate(model, p, data, f, sigma, contexts, field0=field0)
    z = out['residual'] / sigma[:, None, None]
    chi2 = float(np.sum(z ** 2)) if loss is None else loss(z)
    return Evaluation(chi2=chi2, scalar=out['scalar'], vector=out['vector'],
                      residual=out['residual'], field=out['field'], kept=out['kept'])


def soft_l1_lr_loss(z0, f_scale):
    """
    Chi-square-equivalent of the soft-L1 loss for the likelihood-ratio test and BIC.

    The drop of sum L (soft-L1: 2 f^2 (sqrt(1 + z^2/f^2) - 1)) between nested models, times
    E[psi'] / E[psi^2] (psi = L'/2), is asymptotically chi-square with k degrees of freedom
    (Heritier & Ronchetti 1994); the factor is estimated from the base fit's normalised
    residuals ``z0`` (any shape).  Returns z (S, N, 3) residual / sigma -> the scaled loss sum.
    """
    u = 1.0 + (np.asarray(z0, float) / f_scale) ** 2
    c = float(np.mean(u ** -1.5) / np.mean(z0 ** 2 / u))

    def loss(z):
        return c * float(np.sum(2 * f_scale ** 2 * (np.sqrt(1.0 + (z / f_scale) ** 2) - 1)))
    return loss


def likelihood_ratio(delta_chi2, k, n_obs):
    """
    Return (p-value, log10 p-value, delta BIC) of adding ``k`` parameters.

    Chi-square with ``k`` degrees of freedom of ``delta_chi2``, and BIC(with) - BIC(without)
    = -delta_chi2 + k ln(n_obs).
    """
    d = max(float(delta_chi2), 0.0)
    p = float(stats.chi2.sf(d, k))
    logp = float(stats.chi2.logsf(d, k))
    if not np.isfinite(logp):
        # far tail of the regularised upper gamma function Q(a, x), a = k/2, x = d/2:
        # ln Q = (a - 1) ln x - x - ln Gamma(a) + ln(1 + (a - 1)/x + ...)
        a, x = 0.5 * k, 0.5 * d
        logp = (a - 1) * math.log(x) - x - math.lgamma(a) + math.log1p((a - 1) / x)
    logp /= math.log(10.0)
    return p, logp, float(-delta_chi2 + k * math.log(n_obs))


def explained_share(ms_before, ms_after, floor_nt):
    """Share (0..1) of the excess mean square over floor^2 removed (0 without an excess)."""
    excess = float(ms_before) - float(floor_nt) ** 2
    if not excess > 0:
        return 0.0
    return float(np.clip((float(ms_before) - float(ms_after)) / excess, 0.0, 1.0))


def solve_psd(a, b, rcond=1e-12):
    """Solve a x = b for a symmetric PSD (n, n) a, directions below ``rcond`` dropped."""
    w, v = np.linalg.eigh(a)
    keep = w > rcond * max(w.max(), 1e-300)
    vb = v[:, keep].T @ b
    return v[:, keep] @ (vb / (w[keep] if vb.ndim == 1 else w[keep][:, None]))


# -- the residual toolkit ----------------------------------------------------------------------

def white_noise_sd(x):
    """
    Per-component white-noise sd of a series (N,) or (N, C), any unit: (C,).

    sqrt(mean((Delta^3 x)^2) / 20) (C(6, 3) = 20): unbiased for any noise distribution; a
    smooth signal or a few steps barely contribute.
    """
    x = np.asarray(x, float)
    d = np.diff(x.reshape(len(x), -1), n=3, axis=0)
    return np.sqrt(np.mean(d ** 2, axis=0) / 20.0)


def usable(x):
    """Tell whether a channel (N,) is finite and varies."""
    x = np.asarray(x, float)
    return bool(np.all(np.isfinite(x)) and np.ptp(x) > 0)


def evenly_sampled(t):
    """Return (every interval within EVEN_SAMPLING of the median, median interval s)."""
    d = np.diff(np.asarray(t, float))
    med = float(np.median(d)) if d.size else 0.0
    return med > 0 and bool(np.all(np.abs(d - med) <= EVEN_SAMPLING * med)), med


def sampled_on_a_clock(t, dt=None):
    """
    Tell whether times ``t`` (N,) s are a fixed-rate clock read with jitter, samples lost.

    At most CLOCK_OUTLIERS of the intervals outside (1 -+ CLOCK_JITTER) ``dt`` (s, default
    the median): the series can be interpolated onto the clock's grid and FFT-ed.
    """
    d = np.diff(np.asarray(t, float))
    dt = (float(np.median(d)) if dt is None else dt) if d.size else 0.0
    if dt <= 0:
        return False
    return bool(np.mean(np.abs(d - dt) > CLOCK_JITTER * dt) <= CLOCK_OUTLIERS)


def periodogram(t, x, oversample=2):
    """
    Power spectrum of a residual series, also for irregular sampling.

    ``t`` (N,) s; ``x`` (N,) or (N, C) nT (the mean is removed); ``oversample``: frequencies
    per independent frequency.  Returns (freqs (M,) Hz, about 1/T to the Nyquist frequency;
    power (M, C) nT^2, a sinusoid's squared amplitude times N / 4; the number of independent
    frequencies).  The FFT zero-padded ``oversample`` x when evenly sampled, of the series
    interpolated onto the median interval for a jittered clock or above LS_BUDGET; else
    :func:`lomb_scargle`.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float).reshape(len(x), -1)
    x = x - x.mean(axis=0)
    n = len(t)
    even, dt = evenly_sampled(t)
    span = float(t[-1] - t[0]) + dt
    m = max(1, int(oversample * 0.5 / dt * span))
    if not even and (n * m > LS_BUDGET or sampled_on_a_clock(t, dt)):
        grid = t[0] + dt * np.arange(int((t[-1] - t[0]) / dt) + 1)
        x = np.stack([np.interp(grid, t, x[:, c]) for c in range(x.shape[1])], axis=1)
        x, n, even = x - x.mean(axis=0), len(grid), True
    if even:
        nfft = oversample * n
        power = np.abs(np.fft.rfft(x, n=nfft, axis=0)) ** 2 / n
        return np.fft.rfftfreq(nfft, dt)[1:], power[1:], n // 2
    freqs = np.linspace(1.0 / span, 0.5 / dt, m)
    return freqs, lomb_scargle(t, x, freqs), max(1, int(0.5 / dt * span))


def lomb_scargle(t, x, freqs, chunk=256):
    """
    Classical Lomb-Scargle periodogram (Lomb 1976, Scargle 1982 eq. 10), vectorised.

    ``t`` (N,) sample times, s; ``x`` (N, C) series with its mean removed; ``freqs`` (M,) Hz;
    ``chunk`` frequencies computed at a time.  Returns the (M, C) power: N A^2 / 4 for a
    sinusoid of amplitude A, the numbers of :func:`scipy.signal.lombscargle`.
    """
    t = np.asarray(t, float) - t[0]
    freqs = np.asarray(freqs, float)
    out = np.empty((len(freqs), x.shape[1]))
    df = np.diff(freqs)
    even = len(freqs) > 1 and np.allclose(df, df[0], rtol=1e-9, atol=0)
    for a in range(0, len(freqs), chunk):
        f = freqs[a:a + chunk]
        if even:
            # exp(i w t) for the chunk's frequencies by repeated multiplication with
            # exp(i dw t): one complex product per sample instead of two trigonometric calls
            rows = np.empty((len(f), len(t)), complex)
            rows[0] = np.exp(2j * np.pi * f[0] * t)
            rows[1:] = np.exp(2j * np.pi * df[0] * t)
            z = np.cumprod(rows, axis=0)
        else:
            z = np.exp(2j * np.pi * f[:, None] * t)
        z2 = z * z
        tau2 = np.angle(z2.sum(axis=1))                                 # 2 w tau
        zr = z * np.exp(-0.5j * tau2)[:, None]                          # exp(i w (t - tau))
        c, s = zr.real, zr.imag
        out[a:a + chunk] = 0.5 * ((c @ x) ** 2 / (c * c).sum(axis=1)[:, None]
                                  + (s @ x) ** 2 / (s * s).sum(axis=1)[:, None])
    return out


def cusum(z, margin=0):
    """
    Return (k, statistic) of the most likely single change in the mean of ``z`` (N, C).

    ``z`` standardised per column; the likelihood-ratio of one mean shift before epoch k,
    |c_k - k/N c_N|^2 N / (k (N - k)) (c: cumulative sums; CUSUM, Hawkins 1977), maximised
    over k but ``margin`` splits at each end.
    """
    n = len(z)
    c = np.cumsum(z, axis=0)
    k = np.arange(1, n)
    stat = np.sum((c[:-1] - k[:, None] / n * c[-1]) ** 2, axis=1) * n / (k * (n - k))
    if margin:
        stat[:margin] = stat[-margin:] = 0.0
    i = int(np.argmax(stat))
    return i + 1, float(stat[i])


def binary_segmentation(x, max_changes, threshold, min_length=20, margin=5):
    """
    Change points of the mean of ``x`` (N, C): binary segmentation (Vostrikova 1981).

    On ``x`` over its pooled white-noise sd, the largest :func:`cusum` of the segments of at
    least ``min_length`` epochs splits its segment while above ``threshold``, at most
    ``max_changes`` times.  Returns the epochs after each change, in the order found.
    """
    sd = float(np.sqrt(np.mean(white_noise_sd(x) ** 2)))
    z = np.asarray(x, float) / (sd if sd > 0 else np.inf)
    found, segs = [], [(0, len(z))]
    for _ in range(max_changes):
        best = max(((cusum(z[a:b], margin), (a, b)) for a, b in segs if b - a >= min_length),
                   key=lambda r: r[0][1], default=None)
        if best is None or best[0][1] < threshold:
            break
        (k, _), (a, b) = best
        found.append(a + k)
        segs.remove((a, b))
        segs += [(a, a + k), (a + k, b)]
    return found


def lag_grid(t, points=LAG_GRID_POINTS, shortest=0.0, longest=0.25, samples=1):
    """
    Return log-spaced time constants, s, of a first-order lag for times ``t`` (N,) s.

    ``points`` values from ``samples`` median intervals (at least ``shortest`` of the record)
    to ``longest`` of the record; empty when that range is empty.
    """
    t = np.asarray(t, float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    span = float(t[-1] - t[0]) if len(t) else 0.0
    lo, hi = max(samples * dt, shortest * span), longest * span
    return np.geomspace(lo, hi, points) if hi > lo else np.array([])


def regress(x, design):
    """
    Least-squares fit of every column of x (N, C) on design (N, K); (fitted, rank).

    Normal equations of unit-norm columns, directions below 1e-10 of the largest dropped.
    """
    g = design.T @ design
    d = np.sqrt(np.diag(g))
    d[d == 0] = 1.0
    w, v = np.linalg.eigh(g / np.outer(d, d))
    keep = w > 1e-10 * w.max()
    coef = (v[:, keep] / w[keep]) @ (v[:, keep].T @ ((design.T @ x) / d[:, None]))
    return design @ (coef / d[:, None]), int(keep.sum())
