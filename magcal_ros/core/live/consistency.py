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
Find and repair sample sets whose sensors were paired from different epochs.

A sensor whose bytes come more than half a period after sensor 1's can be paired epochs
off, and a rotating array then gives each such set the field change over those epochs.  For
a rigid array in a uniform field with paper 004's linear model (eq. 1-3), every sensor's raw
reading is an affine function of sensor 1's at the same epoch::

    raw_j(e) = M_j raw_1(e) + c_j,    M_j = A_j R_j A_1^-1,   c_j = b_j - M_j b_1,

whatever the attitude.  :func:`find_slips` compares, in a sliding window, the misfit of
pairing sensor j's epoch e + L with sensor 1's epoch e, L = -max_lag .. max_lag, and takes a
lag only where it fits clearly better than 0; :func:`resync` re-pairs.
"""
from dataclasses import dataclass, replace

from magcal_ros.core.data.noise import estimate_noise
from magcal_ros.core.papers.ellipsoid import fit_ellipsoid, procrustes_rotation
import numpy as np

#: largest slip searched, epochs
DEFAULT_MAX_LAG = 10
#: sets in the sliding window that decides a slip
DEFAULT_WINDOW = 25
#: a lag replaces lag 0 only where its windowed squared misfit is this many times smaller
DEFAULT_MIN_CONTRAST = 4.0
#: ... and only where that misfit is within this factor of the noise alone (per set:
#: 3 (sigma_1^2 + sigma_j^2))
DEFAULT_NOISE_FACTOR = 4.0
#: a stretch is re-paired only if its field-change directions spread this much (second
#: eigenvalue of their mean outer product; 0.1: about +-20 deg)
MIN_SPREAD = 0.1
#: value of :attr:`Slips.lags` for a set to drop (its partner was lost in a slip)
DROP = np.iinfo(np.int64).max // 4
#: windowed misfit, in units of the noise alone, beyond which a set counts as inconsistent
INCONSISTENT_FACTOR = 100.0
#: the longer search that tells an inconsistent set paired from epochs further apart from a
#: property of the sensor (no pairing fits), epochs
LONG_MAX_LAG = 50


@dataclass(frozen=True)
class Slips:
    """
    Outcome of :func:`find_slips` (arrays per sensor j; row 0, sensor 1, all 0 / False).

    ``rms_nt``: per-axis RMS misfit of sensor j's ellipsoid-corrected reading rotated onto
    sensor 1's (paper 004 eq. 5, 14), about sqrt(sigma_1^2 + sigma_j^2) when consistent.
    """

    #: (S, N) int: the right partner of set e is sensor j's sample of set e + lag; DROP: lost
    lags: np.ndarray
    rms_nt: np.ndarray                  # (S,) misfit after re-pairing, nT per axis
    rms_as_paired_nt: np.ndarray        # (S,) the same as paired, nT
    noise_nt: np.ndarray                # (S,) per-axis noise from each sensor's series, nT
    #: (S,) sets no lag within max_lag brings within :data:`INCONSISTENT_FACTOR` x the noise
    #: (a longer slip, a spike, an effect of the sensor); resync's ``drop_inconsistent``
    inconsistent: np.ndarray
    inconsistent_sets: np.ndarray | None = None     # (S, N) bool, which sets those are
    dropped_inconsistent: int = 0       # sets resync dropped as inconsistent

    @property
    def n_slipped(self):
        """(S,) number of sets re-paired per sensor."""
        return np.count_nonzero((self.lags != 0) & (self.lags != DROP), axis=1)

    @property
    def n_drop(self):
        """(S,) number of sets whose partner of this sensor was lost, to drop."""
        return np.count_nonzero(self.lags == DROP, axis=1)

    def summary(self):
        """One line per sensor with re-paired sets (empty list if none)."""
        out = []
        for j in range(1, self.lags.shape[0]):
            row = self.lags[j]
            moved = row[(row != 0) & (row != DROP)]
            if not len(moved):
                continue
            values, counts = np.unique(moved, return_counts=True)
            out.append(f'sensor {j + 1}: {len(moved)} sets paired with the wrong epoch ('
                       + ', '.join(f'{c} by {v:+d}' for v, c in zip(values, counts))
                       + f' epochs), re-paired: misfit to sensor 1 '
                       f'{self.rms_as_paired_nt[j]:.1f} -> {self.rms_nt[j]:.1f} nT per axis')
        return out


#: a sample this fraction of the field off the mean of its two neighbours is not a reading
GROSS_FRACTION = 0.02


def gross_outliers(raw, fraction=GROSS_FRACTION):
    """
    Find the sets holding a sample that cannot be a reading: a cut or garbled line.

    A line that lost its first bytes can still parse: one sample thousands of nT off.  A
    sample is one where d(e) = |m(e) - (m(e-1) + m(e+1)) / 2| exceeds ``fraction`` of the
    median field and is the largest of the three around it, in a series smooth at its rate
    (median d below 1 % of that).  ``raw`` (S, N, 3) nT in time order; returns (S, N) bool.
    """
    raw = np.asarray(raw, float)
    s, n = raw.shape[:2]
    out = np.zeros((s, n), bool)
    if n < 5:
        return out
    threshold = fraction * float(np.median(np.linalg.norm(raw[0], axis=1)))
    d = np.linalg.norm(raw[:, 1:-1] - 0.5 * (raw[:, :-2] + raw[:, 2:]), axis=2)  # (S, N-2)
    side = np.pad(d, ((0, 0), (1, 1)), constant_values=-np.inf)
    # not smooth at this rate (median d): nothing can be told
    smooth = np.median(d, axis=1) < 0.01 * threshold
    out[:, 1:-1] = smooth[:, None] & (d > threshold) & (d >= side[:, :-2]) & (d >= side[:, 2:])
    return out


def _runs(n, epochs):
    """(N,) id of the run of consecutive epochs each set belongs to."""
    if epochs is None:
        return np.zeros(n, int)
    e = np.asarray(epochs)
    if e.shape != (n,):
        raise ValueError(f'epochs must have shape ({n},), got {e.shape}')
    return np.concatenate([[0], np.cumsum(np.diff(e) != 1)])


def _shifted(y, lag, run):
    """y[e + lag] where e + lag lies in the same run as e, else nan; y (N, 3)."""
    n = len(y)
    out = np.full_like(y, np.nan)
    src = np.arange(n) + lag
    ok = (src >= 0) & (src < n)
    ok[ok] &= run[src[ok]] == run[ok]
    out[ok] = y[src[ok]]
    return out


def find_slips(raw, epochs=None, max_lag=DEFAULT_MAX_LAG, window=DEFAULT_WINDOW,
               min_contrast=DEFAULT_MIN_CONTRAST, noise_factor=DEFAULT_NOISE_FACTOR):
    """
    Find the sets of a rigid array whose sensors were paired from different epochs.

    Each sensor is calibrated alone by paper 004's ellipsoid fit (eq. 8-13), u_j = Q_j B,
    and rotated onto sensor 1 by the Procrustes solution (eq. 14) on the sets that agree.
    Each set's lag minimises the windowed *median* of |u_1(e) - R u_j(e + L)|^2, the rotation
    refitted, until the lags stop changing; a lag other than 0 must fit better than 0 by
    ``min_contrast`` *and* down to the noise (``noise_factor``).

    ``raw`` (S, N, 3) nT of S >= 2 sensors in set order; ``epochs`` (N,) epoch numbers, a
    jump other than +1 starting a new run (no set is re-paired across runs; default one
    run); ``max_lag`` the largest slip searched, epochs; ``window`` sets deciding a slip.
    Returns :class:`Slips`, all lags 0 when the record is too short or poor to tell.
    """
    raw = np.asarray(raw, float)
    if raw.ndim != 3 or raw.shape[2] != 3:
        raise ValueError(f'raw must have shape (S, N, 3), got {raw.shape}')
    s, n = raw.shape[:2]
    if max_lag < 0 or window < 1 or not min_contrast > 1 or not noise_factor > 0:
        raise ValueError('need max_lag >= 0, window >= 1, min_contrast > 1, noise_factor > 0')
    lags = np.zeros((s, n), int)
    rms, rms0, inconsistent = np.zeros(s), np.zeros(s), np.zeros(s, int)
    bad = np.zeros((s, n), bool)
    if s < 2 or n < max(4 * window, 8 * (2 * max_lag + 1)):
        return Slips(lags, rms, rms0, np.zeros(s), inconsistent)
    run = _runs(n, epochs)
    noise = estimate_noise(raw).sigma
    f0 = float(np.median(np.linalg.norm(raw[0], axis=1)))
    try:
        u = np.stack([fit_ellipsoid(raw[j], f0).correct(raw[j]) for j in range(s)])
    except (ValueError, np.linalg.LinAlgError):
        return Slips(lags, rms, rms0, noise, inconsistent)   # too few attitudes to tell
    candidates = np.arange(-max_lag, max_lag + 1)
    k0 = max_lag                                   # index of lag 0
    cols = np.arange(n)
    for j in range(1, s):
        noise_cost = 3.0 * (noise[0] ** 2 + noise[j] ** 2)
        fits = noise_factor * noise_cost        # the most a set at the noise costs
        shifted = np.stack([_shifted(u[j], lag, run) for lag in candidates])  # (L, N, 3)

        def rotation(y, use):
            """Return the Procrustes rotation of y onto u_1, rows ``use`` (paper 004 eq. 14)."""
            use = use & np.all(np.isfinite(y), axis=1)
            return procrustes_rotation(u[0][use], y[use])

        # the pairing as it is, unless one lag (its own rotation) explains the record better
        med = [np.nanmedian(np.sum((u[0] - y @ rotation(y, np.ones(n, bool)).T) ** 2, axis=1))
               for y in shifted]
        i_best = int(np.argmin(med))
        k = np.full(n, i_best if med[i_best] * min_contrast < med[k0] else k0)
        # alternate rotation and lags (on contrast alone: a rotation biased by slipped sets
        # may keep the right lag off the noise), then the final choice on both tests
        for final in [False] * 10 + [True]:
            y = shifted[k, cols]
            # least trimmed squares (the best half), then all within 3x the median
            use = np.ones(n, bool)
            for cut in (1.0, 1.0, 1.0, 1.0, 9.0):
                rot = rotation(y, use)
                r = np.sum((u[0] - y @ rot.T) ** 2, axis=1)
                use = np.isfinite(r) & (r <= cut * np.nanmedian(r))
            cost = np.sum((u[0][None] - shifted @ rot.T) ** 2, axis=2)   # (L, N), nan: none
            big = 1e6 * (np.nanmedian(cost[k0]) + noise_cost)
            from scipy.ndimage import median_filter    # here: slow to import (0.3 s)
            windowed = median_filter(np.nan_to_num(cost, nan=big), size=(1, window),
                                     mode='nearest')
            best = np.argmin(windowed, axis=0)
            w_best = windowed[best, cols]
            take = w_best * min_contrast < windowed[k0]
            new = np.where(take, best, k0)
            if final or np.array_equal(new, k):
                k = np.where(take & (w_best <= fits), best, k0)
                break
            k = new
        # the window blurs a change of lag a -> b: put it where "a before, b after" fits best
        for c in np.flatnonzero(np.diff(k)) + 1:
            lo, hi = max(0, c - window), min(n, c + window)
            a, b = k[c - 1], k[c]
            if not ((k[lo:c] == a).all() and (k[c:hi] == b).all()):
                continue            # several changes close together: leave them
            ca = np.nan_to_num(cost[a, lo:hi], nan=big)
            cb = np.nan_to_num(cost[b, lo:hi], nan=big)
            total = (np.concatenate([[0.0], np.cumsum(ca)])
                     + np.concatenate([np.cumsum(cb[::-1])[::-1], [0.0]]))
            split = lo + int(np.argmin(total))
            k[lo:split], k[split:hi] = a, b
        lag = candidates[k].copy()      # a set whose partner is missing: dropped by resync
        # a slip moves each set along its field change, whose direction turns with the array
        # (an offset a lag cancels by chance stays put): those directions must spread
        # (MIN_SPREAD), and the stretch fit to the noise
        rate = np.gradient(u[j], axis=0)
        rate /= np.maximum(np.linalg.norm(rate, axis=1, keepdims=True), 1e-300)
        edges = np.flatnonzero(np.diff(lag)) + 1
        for lo, hi in zip(np.r_[0, edges], np.r_[edges, n]):
            if lag[lo] == 0:
                continue
            spread = np.linalg.eigvalsh(rate[lo:hi].T @ rate[lo:hi] / (hi - lo))[1]
            # medians: the sets at its ends may have lost partners
            c_l = np.nanmedian(cost[lag[lo] + k0, lo:hi])
            if (spread < MIN_SPREAD or not c_l <= fits
                    or not np.nanmedian(cost[k0, lo:hi]) >= min_contrast * c_l):
                lag[lo:hi] = 0
        # grow each re-paired stretch over neighbours that fit its lag (or have no partner at
        # it); those that fit neither it nor 0 (the sample a slip skipped) are dropped
        edges = np.flatnonzero(np.diff(lag)) + 1
        for lo, hi in zip(np.r_[0, edges], np.r_[edges, n]):
            ell = lag[lo]
            if ell == 0 or ell == DROP:
                continue

            def grow(e):
                """Return the lag of neighbour e, or None to stop growing."""
                if lag[e] != 0:
                    return None
                c = cost[ell + k0, e]
                if not np.isfinite(c) or c <= fits:
                    return ell          # its partner is at this lag, or missing
                if cost[k0, e] > fits:
                    return DROP         # fits neither: its partner was lost in the slip
                return None
            # its end sets must fit its lag too: else 0 if that fits, else drop them
            for e in [*range(lo, min(lo + 3, hi)), *range(max(hi - 3, lo), hi)]:
                if np.isfinite(cost[ell + k0, e]) and cost[ell + k0, e] > fits:
                    lag[e] = 0 if cost[k0, e] <= fits else DROP
            while lo > 0 and (g := grow(lo - 1)) is not None:
                lo -= 1
                lag[lo] = g
            while hi < n and (g := grow(hi)) is not None:
                lag[hi] = g
                hi += 1
        rms0[j] = np.sqrt(np.mean(cost[k0]) / 3.0)
        kept = lag != DROP
        rms[j] = np.sqrt(np.nanmean(cost[lag[kept] + k0, cols[kept]]) / 3.0)
        if rms[j] >= rms0[j]:
            lag[:], rms[j] = 0, rms0[j]        # never a re-pairing that fits worse overall
            kept[:] = True
        lags[j] = lag
        at = np.where(lag == DROP, 0, lag) + k0
        bad[j] = (kept & np.isfinite(cost[at, cols])
                  & (windowed[at, cols] > INCONSISTENT_FACTOR * noise_cost))
        inconsistent[j] = int(np.count_nonzero(bad[j]))
    return Slips(lags, rms, rms0, noise, inconsistent, bad)


def resync(data, epochs=None, slips=None, drop_inconsistent=False, **kwargs):
    """
    Drop garbled samples and re-pair the sets whose sensors came from different epochs.

    ``data``: (S sensors, N sets) in set order; ``epochs`` as for :func:`find_slips`;
    ``slips``: its result on ``data``, default: the sets with a :func:`gross_outliers` sample
    dropped, then :func:`find_slips` (``**kwargs``) on the rest.  ``drop_inconsistent``: also
    drop the inconsistent sets a search to :data:`LONG_MAX_LAG` epochs finds paired further
    apart; sets no pairing fits are kept.  A sample claimed twice, or without a partner in
    its run of epochs, drops its set.

    Returns (re-paired Dataset, Slips (indexed like the sets left after the gross outliers),
    sets dropped in re-pairing, sets dropped as gross outliers).
    """
    n_gross = 0
    if slips is None:
        gross = gross_outliers(data.raw).any(axis=0)
        n_gross = int(gross.sum())
        if n_gross:
            keep = np.flatnonzero(~gross)
            data = data.subset(keep)
            epochs = None if epochs is None else np.asarray(epochs)[keep]
        slips = find_slips(data.raw, epochs, **kwargs)
    bad = None
    if drop_inconsistent and slips.inconsistent_sets is not None and \
            slips.inconsistent_sets.any():
        longer = find_slips(data.raw, epochs, max_lag=LONG_MAX_LAG).inconsistent_sets
        # None: too short a record for the longer search, none is known
        bad = None if longer is None else slips.inconsistent_sets.any(axis=0) & ~longer.any(axis=0)
    if not (slips.n_slipped.any() or slips.n_drop.any()):
        if bad is not None and bad.any():
            return (data.subset(np.flatnonzero(~bad)),
                    replace(slips, dropped_inconsistent=int(bad.sum())), 0, n_gross)
        return data, slips, 0, n_gross
    s, n = data.raw.shape[:2]
    raw = data.raw.copy()
    temp = None if data.temp is None else data.temp.copy()
    keep = np.ones(n, bool)
    run = _runs(n, epochs)
    idx = np.arange(n)
    for j in range(1, s):
        drop = slips.lags[j] == DROP
        src = idx + np.where(drop, 0, slips.lags[j])
        ok = (src >= 0) & (src < n) & ~drop
        ok[ok] &= run[src[ok]] == run[ok]
        # a sample claimed by two sets (at a change of lag): keep neither pairing
        values, counts = np.unique(src[ok], return_counts=True)
        ok[ok] &= ~np.isin(src[ok], values[counts > 1])
        keep &= ok
        raw[j, ok] = data.raw[j, src[ok]]
        if temp is not None:
            temp[j, ok] = data.temp[j, src[ok]]
    out = replace(data, raw=raw, temp=temp)
    n_repair = int(n - keep.sum())
    if bad is not None and bad.any():
        slips = replace(slips, dropped_inconsistent=int((bad & keep).sum()))
        keep &= ~bad
    return out.subset(np.flatnonzero(keep)), slips, n_repair, n_gross
