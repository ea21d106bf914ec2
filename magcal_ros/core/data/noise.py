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
Noise floor of a sensor estimated from the data alone: the one estimator of the project.

Every "noise floor" (fit, diagnose, report, the nodes) comes from :func:`data_noise_floor`:

1. *How large is the white noise?*  k-th differences (k = 1..6) of a signal smooth at the
   sample rate leave noise of variance C(2k, k) sigma^2 (von Neumann's successive
   differences, generalised); the lowest orders that agree (a plateau) see the noise alone.
2. *Is it heavy-tailed?*  The scale of the differences is :func:`robust_sd`, right for
   Gaussian, Laplace and Student-t noise, isolated gross spikes set aside and counted.
3. *Is there white noise at all?*  A low-pass-filtered series has no plateau and its spectrum
   falls towards Nyquist: the floor is then a range with status ``'filtered'``.
"""
from dataclasses import dataclass
from math import comb

from magcal_ros.core.model.solvers import mad_sd
import numpy as np

#: difference orders tried by the adaptive estimate
ORDERS = (1, 2, 3, 4, 5, 6)
#: difference orders within this ratio of the smallest estimate form the plateau
PLATEAU_RATIO = 1.05
#: values beyond this many MAD-sd from the median form the tail of :func:`robust_sd`
TAIL_CUT = 6.0
#: at least this many values in the tail to estimate its power-law index (Hill estimator)
MIN_TAIL = 10
#: a tail index at or below this is gross outliers (spikes), not noise
OUTLIER_TAIL_INDEX = 1.5
#: tail indices between the two are taken as this (alpha / (alpha - 2) is unbounded at 2)
MIN_TAIL_INDEX = 2.5
#: "filtered": the spectrum in the top 15 % of the band is this many times below the mid band
FILTERED_DROP = 10.0
#: the raw-difference floor is replaced by the residual one when it exceeds it by this factor
RAW_FLOOR_EXCESS = 1.2


def robust_sd(d):
    """
    sd-consistent scale of a centred sample with heavy tails and a few gross outliers.

    The second moment of the values within a = ``TAIL_CUT`` s_MAD of the median, plus the
    tail's share: with Hill's index alpha = n_tail / sum ln(|d_i| / a), P(|d| > x) =
    p (x / a)^-alpha adds p a^2 alpha / (alpha - 2), alpha at least :data:`MIN_TAIL_INDEX`.
    A tail with alpha <= :data:`OUTLIER_TAIL_INDEX` is gross outliers, left out; fewer than
    :data:`MIN_TAIL` tail values add nothing.

    ``d`` (M,) values about their centre, any unit; returns (sd, s_mad, alpha or nan,
    n_outliers), sd and s_mad in the unit of ``d``.
    """
    d = np.asarray(d, float).ravel()
    a = np.abs(d - np.median(d))
    s_mad = mad_sd(d)
    n = a.size
    if n == 0 or s_mad <= 0:
        return float(np.sqrt(np.mean(a ** 2))) if n else float('nan'), float(s_mad), \
            float('nan'), 0
    cut = TAIL_CUT * s_mad
    tail = a[a > cut]
    var = float(np.sum(a[a <= cut] ** 2)) / n
    alpha = float(tail.size / np.sum(np.log(tail / cut))) if tail.size >= MIN_TAIL else np.nan
    n_out = 0 if alpha > OUTLIER_TAIL_INDEX else int(tail.size)
    if n_out:
        var *= n / (n - n_out)          # at least half the values lie within the cut
    elif tail.size:
        a_eff = max(alpha, MIN_TAIL_INDEX)
        var += tail.size / n * cut ** 2 * a_eff / (a_eff - 2.0)
    return float(np.sqrt(var)), float(s_mad), alpha, n_out


def differences(x, k, starts=None, axis=1):
    """
    k-th differences of ``x`` along ``axis``, without those that span a segment start.

    ``starts``: sorted indices where a contiguous segment begins (the blocks of
    :mod:`magcal_ros.core.data.reduce`); None: one segment.
    """
    d = np.diff(x, n=k, axis=axis)
    if starts is None or len(starts) < 2:
        return d
    keep = np.ones(d.shape[axis], bool)
    for s0 in starts[1:]:
        keep[max(0, s0 - k):s0] = False
    return np.compress(keep, d, axis=axis)


def difference_sigmas(x, orders=ORDERS, starts=None):
    """
    White-noise sd from k-th differences, for each order k (:func:`robust_sd` scale).

    ``x`` (S, N, C) (C channels pooled) or (S, N), in time order, any unit; ``starts`` as for
    :func:`differences`.  Returns (K, S) estimates in the unit of ``x``, a row per order.
    """
    x = np.asarray(x, float)
    x = x[..., None] if x.ndim == 2 else x
    out = np.empty((len(orders), x.shape[0]))
    for i, k in enumerate(orders):
        d = differences(x, k, starts)
        d = d - np.median(d, axis=1, keepdims=True)
        out[i] = [robust_sd(dj)[0] / np.sqrt(comb(2 * k, k)) for dj in d]
    return out


def welch(x, nperseg):
    """
    Welch's (1967) power spectral density along axis 1, at a sampling rate of 1.

    ``scipy.signal.welch(x, fs=1.0, nperseg=nperseg, axis=1)``'s numbers without importing
    scipy.signal (start-up time).  ``x`` (S, N, C) in a unit u, N >= ``nperseg``; returns the
    frequencies (F,) in cycles per sample and the density (S, F, C), u^2 per cycle/sample.
    """
    step = nperseg - nperseg // 2
    seg = np.lib.stride_tricks.sliding_window_view(x, nperseg, axis=1)[:, ::step]
    win = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(nperseg) / nperseg)   # periodic Hann
    spec = np.fft.rfft((seg - seg.mean(axis=-1, keepdims=True)) * win, axis=-1)
    p = (spec.real ** 2 + spec.imag ** 2).mean(axis=1) / np.sum(win ** 2)     # (S, C, F)
    p[..., 1:(nperseg + 1) // 2] *= 2.0            # one-sided: all but 0 and Nyquist twice
    return np.fft.rfftfreq(nperseg), np.moveaxis(p, -1, 1)


def nyquist_drop(x, starts=None):
    """
    How far the spectrum falls from mid band to Nyquist, per series.

    Welch spectrum of the first difference over its gain 4 sin^2(pi f / fs): mean density
    in 0.45-0.65 of the band over that in 0.85-1.0 (white noise ~1).  ``x`` (S, N, C) or
    (S, N) in time order, ``starts`` as for :func:`differences`; returns (S,) ratios (inf:
    the top of the band is empty, nan: too short).
    """
    x = np.asarray(x, float)
    x = x[..., None] if x.ndim == 2 else x
    if x.shape[1] < 64:
        return np.full(x.shape[0], np.nan)
    d = differences(x, 1, starts)
    f, p = welch(d, min(256, d.shape[1]))
    gain = 4 * np.sin(np.pi * f) ** 2
    with np.errstate(divide='ignore', invalid='ignore'):
        p = p / np.where(gain > 0, gain, np.nan)[None, :, None]
    lo = np.nanmean(p[:, (f >= 0.45 * 0.5) & (f <= 0.65 * 0.5)], axis=(1, 2))
    hi = np.nanmean(p[:, f >= 0.85 * 0.5], axis=(1, 2))
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(hi > 0, lo / hi, np.inf)


@dataclass(frozen=True)
class NoiseEstimate:
    """
    Adaptive difference-based noise estimate of one kind of series (S series, K orders).

    ``status`` per series: ``'white'`` (a plateau), ``'filtered'`` (no plateau, the spectrum
    falls :data:`FILTERED_DROP` x or more to Nyquist: the sd is *above* every estimate) or
    ``'upper bound'`` (no plateau, flat spectrum: the signal is not smooth at the rate).
    """

    sigma: np.ndarray               # (S,) noise sd, unit of the input (see status)
    order: np.ndarray               # (S,) lowest difference order of the plateau
    plateau: np.ndarray             # (S,) bool: at least two orders agree
    by_order: np.ndarray            # (K, S) estimate for each order tried
    status: tuple = ()
    drop: np.ndarray | None = None  # (S,) :func:`nyquist_drop`


def estimate_noise(x, orders=ORDERS, starts=None):
    """
    Adaptive noise estimate from the plateau of the difference estimates of several orders.

    The plateau starts at the lowest order within :data:`PLATEAU_RATIO` of the smallest
    estimate; the estimate is its median (not the minimum: no bias low).  ``x`` (S, N, C) or
    (S, N) in time order; ``orders`` tried where there are k + 8 samples; ``starts`` as for
    :func:`differences`.
    """
    x = np.asarray(x, float)
    orders = tuple(k for k in orders if x.shape[1] >= k + 8)
    if not orders:
        raise ValueError(f'need at least {min(ORDERS) + 8} samples to estimate the noise floor')
    by = difference_sigmas(x, orders, starts)                       # (K, S)
    k0 = np.argmax(by <= PLATEAU_RATIO * by.min(axis=0), axis=0)     # first order on it
    plateau = len(orders) - k0 >= 2
    drop = nyquist_drop(x, starts)
    status = tuple('white' if p else 'filtered' if dr >= FILTERED_DROP else 'upper bound'
                   for p, dr in zip(plateau, drop))
    return NoiseEstimate(sigma=np.array([np.median(by[k:, j]) for j, k in enumerate(k0)]),
                         order=np.array(orders)[k0], plateau=plateau, by_order=by,
                         status=status, drop=drop)


@dataclass(frozen=True, eq=False)
class NoiseFloor:
    """
    Per-axis white-noise sd of each sensor (S), estimated from the data alone, nT.

    ``per_sensor_nt`` is the white-noise sd (status ``'white'``), a lower bound
    (``'filtered'``) or an upper bound (``'upper bound'``, also when taken from the model's
    residual: the raw estimate is used unless the trajectory inflates it).
    """

    per_sensor_nt: np.ndarray
    raw_nt: np.ndarray                  # from differences of the raw readings
    residual_nt: np.ndarray | None      # from differences of the model's scalar residual
    method: tuple                       # per sensor: which estimate, which order
    reliable: np.ndarray                # bool: status 'white'
    status: tuple = ()
    lower_nt: np.ndarray | None = None  # the range the data support (0, inf: unknown)
    upper_nt: np.ndarray | None = None
    tail_index: np.ndarray | None = None    # Hill index of the noise tail (nan: Gaussian)

    @property
    def value_nt(self):
        """Pooled floor sqrt(mean sigma_j^2), nT."""
        return float(np.sqrt(np.mean(self.per_sensor_nt ** 2)))

    def vector_floor_nt(self, j):
        """Floor of the vector residual corrected_j - corrected_1 per component, nT."""
        f = self.per_sensor_nt
        return float(np.hypot(f[j - 1], f[0]))

    def describe(self, j):
        """One line on sensor ``j``'s floor (1-based) that does not overstate it."""
        k = j - 1
        v, st = self.per_sensor_nt[k], self.status[k]
        if st == 'white':
            return f'sensor {j}: noise floor {v:.3g} nT ({self.method[k]})'
        if st == 'filtered':
            hi = self.upper_nt[k]
            rng = f'between {v:.3g} and {hi:.3g} nT' if np.isfinite(hi) else \
                f'at least {v:.3g} nT'
            return (f'sensor {j}: the series is low-pass filtered (its spectrum falls '
                    'towards Nyquist and the difference estimates keep falling with the '
                    f'order): no white noise floor; the noise sd is {rng}')
        if self.method[k].startswith('scalar residual'):
            return (f'sensor {j}: the attitudes are not smooth in time at the sample rate, so '
                    f"the floor comes from the model's residual ({v:.3g} nT): an upper bound "
                    'that includes any missing effect following the attitude (record a '
                    'continuous rotation for a model-free floor)')
        return (f'sensor {j}: the signal is not smooth at the sample rate; the noise floor is '
                f'at most {v:.3g} nT')

    def to_dict(self):
        """JSON-ready summary (nT)."""
        return {'noise_floor_nt': self.value_nt,
                'noise_floor_per_sensor_nt': {str(j + 1): float(x)
                                              for j, x in enumerate(self.per_sensor_nt)},
                'noise_floor_status': {str(j + 1): s for j, s in enumerate(self.status)},
                'noise_floor_range_nt': {str(j + 1): [float(lo), float(hi)] for j, (lo, hi)
                                         in enumerate(zip(self.lower_nt, self.upper_nt))},
                'noise_floor_method': {str(j + 1): m for j, m in enumerate(self.method)}}


def data_noise_floor(data, result=None):
    """
    Estimate the noise floor of each sensor (the one estimator of fit, diagnose, report).

    ``data`` (S sensors, N epochs) in time order; ``result``, a fit on it: its scalar
    residual (S, N) nT gives the second estimate, its ``sigma_nt`` (S,) nT the upper end of a
    filtered series' range.  A reduced record uses its ``meta['noise_blocks']``; a fit that
    drops readings, the sets where every reading is kept.
    """
    blocks = data.meta.get('noise_blocks')
    if blocks is not None:
        return blocks.floor(result)
    if result is None:
        return noise_floor_of(data.raw)
    raw, residual, starts = data.raw, result.scalar_residual_nt, None
    kept = getattr(result, 'reading_mask', None)
    if kept is not None and not kept.all():
        sets = np.flatnonzero(kept.all(axis=0))
        starts = [0] + list(np.flatnonzero(np.diff(sets) > 1) + 1)
        raw, residual = raw[:, sets], residual[:, sets]
    return noise_floor_of(raw, residual, result.sigma_nt, starts)


def noise_floor_of(raw, residual=None, sigma_nt=None, starts=None):
    """
    :func:`data_noise_floor` of readings ``raw`` (S, N, 3) nT and segment ``starts``.

    ``residual`` (S, N) nT and ``sigma_nt`` (S,) nT: a fit's scalar residual and sd, or None.
    """
    raw_est = estimate_noise(raw, starts=starts)
    s = raw.shape[0]
    sigma = raw_est.sigma.copy()
    order = raw_est.order.copy()
    status = list(raw_est.status)
    source = ['raw'] * s
    res_sigma = None
    if residual is not None:
        res_est = estimate_noise(residual, starts=starts)
        res_sigma = res_est.sigma
        for j in range(s):
            # the raw estimate (no model) unless the trajectory inflates it
            if (status[j] != 'white' and res_est.sigma[j] < sigma[j]) or (
                    res_est.sigma[j] * RAW_FLOOR_EXCESS < sigma[j]):
                sigma[j] = res_est.sigma[j]
                order[j] = res_est.order[j]
                status[j] = res_est.status[j]
                source[j] = 'scalar residual'
    lower, upper = sigma.copy(), sigma.copy()
    tails = np.empty(s)
    for j in range(s):
        if status[j] == 'filtered':
            # every difference estimate is below the sd of such noise: the residual's first
            # order is the tightest bound, its sd bounds it from above; without a fit only the
            # smallest raw one is sure not to hold the trajectory
            sigma[j] = lower[j] = (res_est.by_order[0, j] if residual is not None
                                   else raw_est.by_order[:, j].min())
            upper[j] = max(float(sigma_nt[j]) if residual is not None else np.inf, lower[j])
        elif status[j] == 'upper bound' or source[j] != 'raw':
            # from the model's residual: a missing effect following the attitude is in it
            status[j] = 'upper bound'
            lower[j] = 0.0
        x = raw[j] if source[j] == 'raw' else residual[j]
        d = differences(np.asarray(x, float), int(order[j]), starts, axis=0)
        tails[j] = robust_sd(d - np.median(d, axis=0))[2]
    method = tuple(f'{src} differences (order {k})' if st != 'filtered' else
                   f'{src} differences (filtered: no plateau up to order {ORDERS[-1]})'
                   for src, k, st in zip(source, order, status))
    return NoiseFloor(per_sensor_nt=sigma, raw_nt=raw_est.sigma, residual_nt=res_sigma,
                      method=method, reliable=np.array([st == 'white' for st in status]),
                      status=tuple(status), lower_nt=lower, upper_nt=upper, tail_index=tails)


def noise_floor(raw, order=None):
    """
    Per-axis noise sd of each sensor's raw series (no model; see :func:`data_noise_floor`).

    ``raw`` (S, N, 3) or (N, 3) nT in time order; ``order`` k, default adaptive
    (:func:`estimate_noise`).  Returns the sd (S,) or a scalar, nT, pooled over the axes.
    """
    raw = np.asarray(raw, float)
    one = raw.ndim == 2
    raw = raw[None] if one else raw
    if order is None:
        sigma = estimate_noise(raw).sigma
    else:
        if raw.shape[1] < order + 8:
            raise ValueError(f'need at least {order + 8} samples to estimate the noise floor')
        sigma = difference_sigmas(raw, (order,))[0]
    return float(sigma[0]) if one else sigma
