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

Every figure called "noise floor" (``magcal fit``, ``diagnose``, ``report``, the calibration
node, the tensor floor) comes from :func:`data_noise_floor`.  It answers three questions the
residual RMS of a model cannot answer by itself:

1. *How large is the white noise?*  From k-th differences of the series (k = 1..6): for a
   signal that is smooth at the sample rate the k-th difference removes the signal and leaves
   noise of variance C(2k, k) sigma^2 (von Neumann's successive differences, generalised);
   the lowest orders where the estimates agree (a plateau) see the noise alone.
2. *Is the noise heavy-tailed?*  The scale of the differences is an sd-consistent trimmed
   second moment with a power-law tail correction (:func:`robust_sd`): right for Gaussian,
   Laplace and Student-t noise (3 degrees of freedom included), while isolated gross spikes
   (transport garbage), whose tail is too heavy to have a variance, are set aside and counted.
3. *Is there white noise at all?*  A low-pass-filtered series (an instrument's anti-alias or
   averaging filter) has no white floor: the difference estimates keep falling with the order
   and the spectrum falls towards Nyquist.  The floor is then reported as a range (a lower
   bound from the differences, an upper bound from the model residual when there is one) with
   status ``'filtered'``, never as one number that a residual could be "far above".

Student-t noise of 3 dof and sd 3 nT reads 3.0 nT (the Gaussian-consistent MAD reads 2.2-2.4).
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
#: (a Gaussian puts 2e-9 of its mass there; Student-t 3 dof about 0.4 %)
TAIL_CUT = 6.0
#: at least this many values in the tail to estimate its power-law index (Hill estimator)
MIN_TAIL = 10
#: a tail index at or below this is gross outliers (spikes: 1000 nT on 3 nT noise gives
#: ~0.25, 45 nT ~1.1); Student-t 3 dof gives 3 +- 0.35 from ~70 tail values
OUTLIER_TAIL_INDEX = 1.5
#: tail indices between the two are taken as this (the heaviest tail with a variance that
#: the estimate can tell from outliers; alpha/(alpha - 2) is unbounded as alpha -> 2)
MIN_TAIL_INDEX = 2.5
#: "filtered": the spectrum in the top 15 % of the band is this many times below the mid band
FILTERED_DROP = 10.0
#: the raw-difference floor is replaced by the residual one when it exceeds it by this factor
RAW_FLOOR_EXCESS = 1.2


def robust_sd(d):
    """
    sd-consistent scale of a centred sample with heavy tails and a few gross outliers.

    1. s_MAD = 1.4826 MAD (Gaussian-consistent, too low for heavy tails: 0.73 sd for
       Student-t 3 dof);
    2. the second moment of the values within ``TAIL_CUT * s_MAD`` of the median (``a``);
    3. the tail beyond ``a``: its power-law index alpha by Hill's estimator
       alpha = n_tail / sum ln(|d_i| / a).  For P(|d| > x) = p (x / a)^-alpha the tail
       contributes p a^2 alpha / (alpha - 2) to the variance (finite for alpha > 2), which is
       added, with alpha at least :data:`MIN_TAIL_INDEX` (Hill's estimate scatters by
       alpha / sqrt(n_tail)).  A tail with alpha <= :data:`OUTLIER_TAIL_INDEX` is far heavier
       than any noise with a variance: those values are gross outliers (spikes, garbled
       lines) and are left out, not spread into the floor.
       With fewer than :data:`MIN_TAIL` tail values (Gaussian noise) nothing is added.

    Parameters
    ----------
    d : numpy.ndarray
        (M,) values about their centre (any unit).

    Returns
    -------
    tuple
        (sd, s_mad, alpha or nan, n_outliers) in the unit of ``d``.

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
    alpha, n_out = float('nan'), 0
    if tail.size >= MIN_TAIL:
        alpha = float(tail.size / np.sum(np.log(tail / cut)))
        if alpha > OUTLIER_TAIL_INDEX:
            a_eff = max(alpha, MIN_TAIL_INDEX)
            var += tail.size / n * cut ** 2 * a_eff / (a_eff - 2.0)
        else:
            n_out = int(tail.size)
            var *= n / (n - n_out)
    else:
        n_out = int(tail.size)
        var *= n / max(n - n_out, 1)
    return float(np.sqrt(var)), float(s_mad), alpha, n_out


def differences(x, k, starts=None, axis=1):
    """
    k-th differences of ``x`` along ``axis``, without those that span a segment start.

    ``starts``: sorted indices where a new contiguous segment of the series begins (a
    record reduced to blocks, :mod:`magcal_ros.core.data.reduce`); a difference reaching across
    one would see the jump between two blocks, not the noise.  None: one segment.
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

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) series in time order (any unit; C channels pooled), or (S, N).
    orders : sequence of int
        Difference orders k.
    starts : sequence of int, optional
        Indices where contiguous segments begin (:func:`differences`).

    Returns
    -------
    numpy.ndarray
        (K, S) sd estimates in the unit of ``x``, one row per order.

    """
    x = np.asarray(x, float)
    if x.ndim == 2:
        x = x[..., None]
    out = np.empty((len(orders), x.shape[0]))
    for i, k in enumerate(orders):
        d = differences(x, k, starts)
        d = d - np.median(d, axis=1, keepdims=True)
        for j in range(x.shape[0]):
            out[i, j] = robust_sd(d[j])[0] / np.sqrt(comb(2 * k, k))
    return out


def welch(x, nperseg):
    """
    Welch's (1967) power spectral density along axis 1, at a sampling rate of 1.

    Hann-windowed segments of ``nperseg`` samples overlapping by half, each less its mean,
    their one-sided periodograms averaged: the numbers of
    ``scipy.signal.welch(x, fs=1.0, nperseg=nperseg, axis=1, detrend='constant')``
    (test_noise), written with numpy because importing scipy.signal (which imports
    scipy.stats) cost every process that fits 0.5-0.8 s of CPU (BENCHMARKS.md, "Start-up").

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) series, any unit u, N >= nperseg.
    nperseg : int
        Samples per segment.

    Returns
    -------
    f : numpy.ndarray
        (F,) frequencies, cycles per sample.
    p : numpy.ndarray
        (S, F, C) power spectral density, u^2 per (cycle per sample).

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

    Welch spectrum of the first difference (which whitens a smooth trajectory so window
    leakage cannot fill the top of the band), divided by the difference's gain
    4 sin^2(pi f / fs); ratio of the mean density in 0.45-0.65 of the band to that in
    0.85-1.0.  White noise: ~1; a low-pass-filtered series: many decades.

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) or (S, N) series in time order.
    starts : sequence of int, optional
        Indices where contiguous segments begin (:func:`differences`).

    Returns
    -------
    numpy.ndarray
        (S,) ratio (>= 0; inf when the top of the band is empty, nan for short series).

    """
    x = np.asarray(x, float)
    if x.ndim == 2:
        x = x[..., None]
    n = x.shape[1]
    out = np.full(x.shape[0], np.nan)
    if n < 64:
        return out
    d = differences(x, 1, starts)
    n = d.shape[1] + 1
    f, p = welch(d, min(256, n - 1))
    gain = 4 * np.sin(np.pi * f) ** 2
    with np.errstate(divide='ignore', invalid='ignore'):
        p = p / np.where(gain > 0, gain, np.nan)[None, :, None]
    mid = (f >= 0.45 * 0.5) & (f <= 0.65 * 0.5)
    top = (f >= 0.85 * 0.5)
    lo = np.nanmean(p[:, mid], axis=(1, 2))
    hi = np.nanmean(p[:, top], axis=(1, 2))
    with np.errstate(divide='ignore', invalid='ignore'):
        out = np.where(hi > 0, lo / hi, np.inf)
    return out


@dataclass(frozen=True)
class NoiseEstimate:
    """
    Adaptive difference-based noise estimate of one kind of series.

    Attributes
    ----------
    sigma : numpy.ndarray
        (S,) noise sd, unit of the input (nT for readings): the plateau median for
        ``'white'``, the smallest order's estimate otherwise (see ``status``).
    order : numpy.ndarray
        (S,) lowest difference order of the plateau the estimate comes from.
    plateau : numpy.ndarray
        (S,) bool: at least two difference orders agree, i.e. the signal no longer
        contributes.
    by_order : numpy.ndarray
        (K, S) estimate for each order tried.
    status : tuple of str
        Per series: ``'white'`` (a plateau: the white-noise sd), ``'filtered'`` (no plateau
        and the spectrum falls :data:`FILTERED_DROP` x or more to Nyquist: a low-pass-filtered
        series whose noise sd is *above* every difference estimate) or ``'upper bound'`` (no
        plateau, flat spectrum: the signal is not smooth at the sample rate and adds to every
        order, e.g. random attitudes).
    drop : numpy.ndarray
        (S,) :func:`nyquist_drop` of the series.

    """

    sigma: np.ndarray
    order: np.ndarray
    plateau: np.ndarray
    by_order: np.ndarray
    status: tuple = ()
    drop: np.ndarray | None = None


def estimate_noise(x, orders=ORDERS, starts=None):
    """
    Adaptive noise estimate from the plateau of the difference estimates of several orders.

    A smooth trajectory sampled slowly leaves its curvature in low-order differences (at
    10 Hz a tumbling array adds ~15 nT to the 2nd difference, at 3 Hz ~20 nT to the 3rd);
    higher orders remove it, and from some order on every estimate sees only noise.  The
    plateau starts at the lowest order within :data:`PLATEAU_RATIO` of the smallest
    estimate; the estimate is the median over the plateau (the median of the orders, not
    their minimum, so the selection does not bias it low).  Without a plateau the spectrum
    decides between a filtered series and a signal that is not smooth (``status``).

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) or (S, N) series in time order.
    orders : sequence of int
        Difference orders tried (those with at least k + 8 samples are used).
    starts : sequence of int, optional
        Indices where contiguous segments begin (:func:`differences`).

    Returns
    -------
    NoiseEstimate

    """
    x = np.asarray(x, float)
    n = x.shape[1]
    orders = tuple(k for k in orders if n >= k + 8)
    if not orders:
        raise ValueError(f'need at least {min(ORDERS) + 8} samples to estimate the noise floor')
    by = difference_sigmas(x, orders, starts)
    s = by.shape[1]
    sigma = np.empty(s)
    first = np.empty(s, int)
    plateau = np.empty(s, bool)
    drop = nyquist_drop(x, starts)
    status = []
    for j in range(s):
        on = by[:, j] <= PLATEAU_RATIO * by[:, j].min()
        k0 = int(np.argmax(on))
        sigma[j] = np.median(by[k0:, j])
        first[j] = orders[k0]
        plateau[j] = len(orders) - k0 >= 2
        if plateau[j]:
            status.append('white')
        elif drop[j] >= FILTERED_DROP:
            status.append('filtered')
        else:
            status.append('upper bound')
    return NoiseEstimate(sigma=sigma, order=first, plateau=plateau, by_order=by,
                         status=tuple(status), drop=drop)


@dataclass(frozen=True, eq=False)
class NoiseFloor:
    """
    Per-axis white-noise sd of each sensor, estimated from the data alone.

    Attributes
    ----------
    per_sensor_nt : numpy.ndarray
        (S,) the floor, nT: the white-noise sd (status ``'white'``), a lower bound
        (``'filtered'``) or an upper bound (``'upper bound'``).
    raw_nt : numpy.ndarray
        (S,) from differences of the raw readings (no model), nT; used unless the trajectory
        inflates it (no plateau, or more than :data:`RAW_FLOOR_EXCESS` times the residual
        estimate).
    residual_nt : numpy.ndarray or None
        (S,) from differences of the model's scalar residual, nT: removes the trajectory
        itself, so it works for slowly sampled or random attitudes; a missing effect that is
        smooth in time (temperature, drift, currents) is removed by the differences too.
    method : tuple of str
        Per sensor, which estimate was used and with which difference order.
    reliable : numpy.ndarray
        (S,) bool: status ``'white'``.
    status : tuple of str
        Per sensor ``'white'``, ``'filtered'`` or ``'upper bound'`` (:class:`NoiseEstimate`;
        also when the floor had to come from the model's residual, which holds any missing
        effect that follows the attitude when the attitudes are not smooth in time).
    lower_nt, upper_nt : numpy.ndarray
        (S,) the range the data support, nT (0 and inf when a side is unknown; both equal
        ``per_sensor_nt`` for white noise).
    tail_index : numpy.ndarray
        (S,) Hill index of the noise tail of the lowest-order differences (nan: Gaussian-like
        tails; 3 for Student-t 3 dof).

    """

    per_sensor_nt: np.ndarray
    raw_nt: np.ndarray
    residual_nt: np.ndarray | None
    method: tuple
    reliable: np.ndarray
    status: tuple = ()
    lower_nt: np.ndarray | None = None
    upper_nt: np.ndarray | None = None
    tail_index: np.ndarray | None = None

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

    Parameters
    ----------
    data : Dataset
        (S sensors, N epochs) in time order.
    result : FitResult, optional
        A fit on ``data``: its scalar residual (S, N) nT gives the second estimate, and its
        ``sigma_nt`` (S,) nT the upper end of the range of a filtered series.

    Returns
    -------
    NoiseFloor

    Notes
    -----
    A record too long to hold (:mod:`magcal_ros.core.data.reduce`) is diagnosed on an evenly
    spread sample of its epochs, whose differences would see the motion between them, not
    the noise: its ``meta['noise_blocks']`` holds contiguous full-rate blocks of the record,
    and the floor is estimated from those (and the fit's residual on them).

    A fit whose model leaves readings out (``drop`` terms: its ``reading_mask``) is
    estimated on the sets where every sensor's reading is kept, each stretch between the
    windows a segment: a disturbance the model drops is not noise.

    """
    blocks = data.meta.get('noise_blocks')
    if blocks is not None:
        return blocks.floor(result)
    kept = getattr(result, 'reading_mask', None)
    if kept is None or kept.all():
        return noise_floor_of(data.raw, result)
    sets = np.flatnonzero(kept.all(axis=0))
    starts = [0] + list(np.flatnonzero(np.diff(sets) > 1) + 1)
    return noise_floor_of(data.raw[:, sets],
                          _KeptResidual(result.scalar_residual_nt[:, sets], result.sigma_nt),
                          starts)


@dataclass(frozen=True)
class _KeptResidual:
    """What :func:`noise_floor_of` reads of a fit, on some of its sets."""

    scalar_residual_nt: np.ndarray      # (S, M) nT
    sigma_nt: np.ndarray                # (S,) nT


def noise_floor_of(raw, result, starts=None):
    """:func:`data_noise_floor` of readings ``raw`` (S, N, 3) nT and segment ``starts``."""
    raw_est = estimate_noise(raw, starts=starts)
    s = raw.shape[0]
    sigma = raw_est.sigma.copy()
    order = raw_est.order.copy()
    status = list(raw_est.status)
    by = [raw_est.by_order[:, j] for j in range(s)]
    source = ['raw'] * s
    res_sigma = None
    if result is not None:
        res_est = estimate_noise(result.scalar_residual_nt, starts=starts)
        res_sigma = res_est.sigma
        for j in range(s):
            # the raw estimate pools three axes and needs no model: keep it unless the
            # trajectory itself inflates it (slow sampling, random attitudes)
            if (status[j] != 'white' and res_est.sigma[j] < sigma[j]) or (
                    res_est.sigma[j] * RAW_FLOOR_EXCESS < sigma[j]):
                sigma[j] = res_est.sigma[j]
                order[j] = res_est.order[j]
                status[j] = res_est.status[j]
                by[j] = res_est.by_order[:, j]
                source[j] = 'scalar residual'
    lower = sigma.copy()
    upper = sigma.copy()
    for j in range(s):
        if status[j] == 'filtered':
            # every difference estimate is below the sd of noise whose spectrum falls with
            # frequency (the difference weights grow with frequency); the first order's of
            # the residual (no trajectory in it) is the tightest such bound, the model
            # residual's sd bounds it from above.  Without a fit only the smallest raw one
            # is sure not to contain the trajectory.
            sigma[j] = lower[j] = (res_est.by_order[0, j] if result is not None
                                   else by[j].min())
            upper[j] = (float(result.sigma_nt[j]) if result is not None else np.inf)
            upper[j] = max(upper[j], lower[j])
        elif status[j] == 'upper bound':
            lower[j] = 0.0
        elif source[j] != 'raw':
            # the attitudes are not smooth in time, so the floor comes from the model's
            # residual: a missing effect that follows the attitude is not removed by the
            # differences and is in it (random attitudes with a temperature effect)
            status[j] = 'upper bound'
            lower[j] = 0.0
    tails = np.empty(s)
    for j in range(s):
        x = raw[j] if source[j] == 'raw' else result.scalar_residual_nt[j]
        d = differences(np.asarray(x, float), int(order[j]), starts, axis=0)
        tails[j] = robust_sd(d - np.median(d, axis=0))[2]
    method = tuple(f'{src} differences (order {k})' if st != 'filtered' else
                   f'{src} differences (filtered: no plateau up to order {ORDERS[-1]})'
                   for src, k, st in zip(source, order, status))
    return NoiseFloor(per_sensor_nt=sigma, raw_nt=raw_est.sigma, residual_nt=res_sigma,
                      method=method, reliable=np.array([st == 'white' for st in status]),
                      status=tuple(status), lower_nt=lower, upper_nt=upper, tail_index=tails)


def noise_floor(raw, t=None, order=None):
    """
    Per-axis noise sd of each sensor's raw series (no model; see :func:`data_noise_floor`).

    Parameters
    ----------
    raw : numpy.ndarray
        (S, N, 3) or (N, 3) readings in nT, in time order.
    t : numpy.ndarray, optional
        (N,) times, s; not used (the differences are taken in sample order).
    order : int, optional
        Difference order k; default: adaptive (:func:`estimate_noise`, orders 1..6).

    Returns
    -------
    numpy.ndarray
        (S,) or scalar: noise sd in nT (pooled over the three axes).

    """
    raw = np.asarray(raw, float)
    one = raw.ndim == 2
    if one:
        raw = raw[None]
    if order is None:
        sigma = estimate_noise(raw).sigma
    else:
        if raw.shape[1] < order + 8:
            raise ValueError(f'need at least {order + 8} samples to estimate the noise floor')
        sigma = difference_sigmas(raw, (order,))[0]
    return float(sigma[0]) if one else sigma
