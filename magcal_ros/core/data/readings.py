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
Readings no field produces, found before the fit: pinned, clipped, repeated channels, spikes.

Found per sensor and axis and left out with one line each: ``pinned`` (one value holds most
of the channel: a dead axis, the HMC5883L's -4096 on overflow), ``clipped`` (runs at the
extreme of the channel's range), ``repeated`` (the last reading repeated longer than the
noise allows: a stalled driver or link) and ``spike`` (one to three readings off the
channel's smooth course and back).

Runs: the flat-line test of the QARTOD real-time quality-control manuals (U.S. IOOS, 2020),
its count derived from the data.  A channel reads r_k = Q(s_k + e_k), quantum ``q``, white
noise sigma_w^2 = sigma^2 - q^2 / 12 (sigma the median over the sensor's axes of
:func:`magcal_ros.core.data.noise.estimate_noise`); two consecutive readings are equal with
probability at most erf(q / (sqrt(3) sigma_w)) whatever the signal (sqrt(3) = 2 sqrt(0.75),
the conservative conditional spread).  With the rate ``d`` of whole duplicated samples (a
logger faster than the sensor; the median over 20 blocks) that is
p = d + (1 - d) erf(q / (sqrt(3) sigma_w)), and runs of L equal readings with
N p^(L - 1) < :data:`ALPHA` / (3 S) are flagged (at least :data:`MIN_RUN`).

Spikes: a Hampel identifier (Hampel, JASA 69, 1974; Pearson, IEEE Trans. Control Syst.
Technol. 10(1), 2002) on the centred k-th differences of each channel, k even (C(k, k/2)
times the leave-one-out residual from the polynomial through the k neighbours; k the lowest
even order at or above the noise floor's plateau order, 2..6), on axes with a white floor.
The threshold is the Gaussian quantile of :data:`ALPHA` over the N x 3 x S values, unless
the 3-6 MAD band holds :data:`HEAVY_BAND_RATIO` times the Gaussian count: then the power law
fitted beyond 3 MAD (Hill's index less two standard errors) extrapolated to the same rate.
Values beyond it are clustered (gaps of at most k); a cluster is a spike when replacing at
most :data:`SPIKE_MAX_SAMPLES` readings by the interpolation of their neighbours brings it
within the threshold, and this explains it better than a step or a longer transient by the
chi-square(1) quantile of ALPHA.
"""
from dataclasses import dataclass, field
from math import erf, sqrt

from magcal_ros.core.data.noise import estimate_noise, mad_sd
import numpy as np

#: family-wise probability that a live channel of a record is flagged
ALPHA = 1e-3
#: a flagged stretch holds at least this many equal readings
MIN_RUN = 3
#: one value in at least this fraction of a channel's readings (in flagged runs): pinned
PINNED_FRACTION = 0.5
#: fewer than this fraction of the sets left after leaving the flagged ones out: refused
MIN_KEPT_FRACTION = 0.5
#: blocks over which the duplicate rate is taken (its median)
DUPLICATE_BLOCKS = 20
#: most readings one spike may hold (one block of consecutive readings, or two single ones)
SPIKE_MAX_SAMPLES = 3
#: the band of the differences (in MAD-sd) whose count tells heavy-tailed noise: from here ...
SPIKE_BAND = 3.0
#: ... to this (noise.TAIL_CUT); beyond it the power law is extrapolated
SPIKE_BAND_TOP = 6.0
#: the band holds at least this many times the Gaussian count: heavy-tailed noise
HEAVY_BAND_RATIO = 2.5
#: difference orders the spike test may use (even: centred on a reading)
SPIKE_ORDERS = (2, 4, 6)
AXES = 'xyz'


class UnphysicalReadingsError(ValueError):
    """Too many readings no field produces to fit what is left: the message names them."""


@dataclass(frozen=True)
class SuspectChannel:
    """
    One channel's readings that no field produces.

    ``values_nt``: the value it is pinned at, the one or two values it is clipped at, empty
    for 'repeated', the smallest and largest spike size for 'spike' (a spike's largest
    distance from the interpolation of its neighbours), nT.
    """

    sensor: int             # 1-based
    axis: str               # 'x', 'y' or 'z'
    kind: str               # 'pinned', 'clipped', 'repeated' or 'spike'
    values_nt: tuple
    count: int              # readings flagged
    n_samples: int          # readings of the channel
    stretches: tuple        # ((t_start, t_end) s, ...) flagged stretches in time order
    min_run: int            # the shortest flagged run of equal readings (0 for 'spike')

    def describe(self):
        """Say what is wrong, in words (no sensor/axis prefix)."""
        share = 100.0 * self.count / max(self.n_samples, 1)
        where = _stretches_text(self.stretches)
        vals = ' and '.join(f'{v:+.1f}' for v in self.values_nt)
        if self.kind == 'pinned':
            what = f'pinned at {vals} nT'
        elif self.kind == 'clipped':
            ends = 'both ends' if len(self.values_nt) > 1 else 'the end'
            what = (f'clipped at {vals} nT ({ends} of its range: the field went beyond the '
                    'measuring range)')
        elif self.kind == 'spike':
            k = len(self.stretches)
            lo, hi = (abs(v) for v in self.values_nt)
            size = f'{hi:.0f}' if round(lo) == round(hi) else f'{lo:.0f}-{hi:.0f}'
            what = (f'{k} spike{"s" if k > 1 else ""} of {size} nT (one to three readings '
                    'off the course of the channel and back, more than its noise allows: a '
                    'serial or EMI glitch)')
        else:
            what = (f'repeats its last reading (runs of {self.min_run} or more equal readings, '
                    'more than its noise allows: a stalled driver or link)')
        return f'{what} in {self.count} of {self.n_samples} readings ({share:.1f} %), {where}'

    def to_dict(self):
        """JSON-ready dict."""
        return {'sensor': self.sensor, 'axis': self.axis, 'kind': self.kind,
                'values_nt': list(self.values_nt), 'count': self.count,
                'n_samples': self.n_samples,
                'stretches_s': [list(s) for s in self.stretches], 'min_run': self.min_run}


def _stretches_text(stretches, most=3):
    parts = [f'{a:.1f} s' if b - a < 0.05 else f'{a:.1f}-{b:.1f} s' for a, b in stretches[:most]]
    more = len(stretches) - most
    head = ', '.join(parts) + (f' and {more} more stretch{"es" if more > 1 else ""}'
                               if more > 0 else '')
    return f'at t = {head}'


@dataclass
class ReadingScreen:
    """The screen of a record: which readings no field produces (``min_run`` > N: none)."""

    flags: np.ndarray                           # (S, N, 3) bool, True: left out
    channels: list = field(default_factory=list)    # SuspectChannel per channel and kind
    min_run: np.ndarray | None = None           # (S, 3) shortest flagged run per channel
    repeat_bound: np.ndarray | None = None      # (S, 3) bound p of :func:`repeat_bounds`

    @property
    def keep(self):
        """(N,) bool: the sets (epochs) in which no reading is flagged."""
        return ~self.flags.any(axis=(0, 2))

    @property
    def n_left_out(self):
        """Return the number of sets left out."""
        return int((~self.keep).sum())

    def lines(self):
        """One line per flagged channel group (axes of a sensor with the same flags merged)."""
        groups = {}
        for i, c in enumerate(self.channels):
            key = (c.sensor, c.count, c.stretches) if c.kind == 'repeated' else i
            groups.setdefault(key, []).append(c)
        out = []
        for group in groups.values():
            c = group[0]
            axes = ', '.join(g.axis for g in group)
            label = f'axis {axes}' if len(group) == 1 else f'axes {axes}'
            out.append((c.sensor, f'sensor {c.sensor} {label}: {c.describe()}'))
        return out

    def notes(self):
        """:class:`~magcal_ros.core.model.notes.Note` s of kind ``readings``, one per line."""
        from magcal_ros.core.model.notes import Note
        tail = (f'; no field produces these readings: the {self.n_left_out} of '
                f'{self.flags.shape[1]} sets that hold them are left out of the fit')
        return [Note(text + tail, 'readings', j) for j, text in self.lines()]

    def to_dict(self):
        """JSON-ready summary."""
        return {'sets_left_out': self.n_left_out, 'sets': int(self.flags.shape[1]),
                'channels': [c.to_dict() for c in self.channels]}


def _runs(x):
    """Start indices and lengths of the runs of equal consecutive values of x (N,)."""
    starts = np.flatnonzero(np.r_[True, np.diff(x) != 0])
    return starts, np.diff(np.r_[starts, len(x)])


def _quantum(x):
    """Smallest step between distinct values of x (nT), ignoring float jitter; 0 if none."""
    u = np.unique(x)                                    # x not empty
    d = np.diff(u)
    d = d[d > 1e-9 * max(float(np.abs(u).max()), 1.0)]         # not float jitter
    return float(d.min()) if len(d) else 0.0


def _duplicate_rate(raw_j):
    """Median over blocks of the fraction of epochs repeating all three axes (raw_j (N, 3))."""
    same = (np.diff(raw_j, axis=0) == 0).all(axis=1)
    if len(same) < DUPLICATE_BLOCKS:
        return float(np.mean(same)) if len(same) else 0.0
    return float(np.median([b.mean() for b in np.array_split(same, DUPLICATE_BLOCKS)]))


def channel_noise(raw):
    """:func:`estimate_noise` of each channel of ``raw`` (S, N, 3): 3 S series, sensor-major."""
    s_count, n, _ = raw.shape
    return estimate_noise(raw.transpose(0, 2, 1).reshape(3 * s_count, n))


def repeat_bounds(raw, est=None):
    """
    Bound p on the probability that a live reading equals the previous one, per channel.

    ``raw`` (S, N, 3) nT in time order; ``est`` its :func:`channel_noise` (computed when not
    given).  Returns (S, 3) p in [0, 1] (module docstring).
    """
    s_count, n, _ = raw.shape
    p = np.ones((s_count, 3))
    if n < 16:
        return p
    sig = (channel_noise(raw) if est is None else est).sigma.reshape(s_count, 3)
    for j in range(s_count):
        q = np.array([_quantum(raw[j, :, a]) for a in range(3)])
        sw = float(np.median(np.sqrt(np.clip(sig[j] ** 2 - q ** 2 / 12.0, 0.0, None))))
        dup = _duplicate_rate(raw[j])
        for a in range(3):
            p0 = 1.0 if sw <= 0 else (erf(q[a] / (sqrt(3.0) * sw)) if q[a] > 0 else 0.0)
            p[j, a] = min(1.0, dup + (1.0 - dup) * p0)
    return p


def min_flagged_run(p, n, n_channels):
    """
    Shortest run L of equal readings improbable for a live channel.

    N p^(L - 1) <= :data:`ALPHA` / n_channels; at least :data:`MIN_RUN`; ``n + 1`` (never)
    when p >= 1.
    """
    if p >= 1.0:
        return n + 1
    if p <= 0.0:
        return MIN_RUN
    return int(max(MIN_RUN, 1 + np.ceil(np.log(ALPHA / (n_channels * max(n, 1))) / np.log(p))))


def _stretches(t, mask):
    """((t_start, t_end), ...) of the contiguous True stretches of mask (N,)."""
    starts, lengths = _runs(mask)
    on = mask[starts]
    return tuple((round(float(t[a]), 3), round(float(t[a + n - 1]), 3))
                 for a, n in zip(starts[on], lengths[on]))


def _interpolation(nodes, targets):
    """(len(targets), len(nodes)) Lagrange weights: the polynomial through ``nodes`` at targets."""
    nodes = np.asarray(nodes, float)
    targets = np.asarray(targets, float)
    w = np.ones((len(targets), len(nodes)))
    for m, xm in enumerate(nodes):
        for xq in np.delete(nodes, m):
            w[:, m] *= (targets - xq) / (xm - xq)
    return w


def _normal_isf(p):
    """Upper Gaussian quantile of ``p`` (scipy.special: scipy.stats costs a second to import)."""
    from scipy.special import ndtri
    return float(-ndtri(p))


def spike_threshold(z, n_values, alpha=ALPHA):
    """
    Threshold (in MAD-sd) of the spike test on one sensor's pooled differences ``z``.

    ``z`` (M,): centred differences of the sensor's axes over their Gaussian-consistent MAD;
    ``n_values`` tested in the record (N x 3 x S); ``alpha`` the family-wise rate.  Returns
    (threshold, heavy-tailed): the Gaussian quantile of alpha / (2 n_values), or the heavy
    tail's power law at that rate (module docstring; inf when nothing can be told).
    """
    a = np.abs(np.asarray(z, float))
    gauss = _normal_isf(alpha / (2.0 * n_values))
    band = float(np.sum((a > SPIKE_BAND) & (a <= SPIKE_BAND_TOP)))
    from scipy.special import ndtr
    expected = a.size * 2.0 * (ndtr(-SPIKE_BAND) - ndtr(-SPIKE_BAND_TOP))
    if band <= HEAVY_BAND_RATIO * expected or band <= expected + 3.0 * sqrt(expected):
        return gauss, False
    tail = a[a > SPIKE_BAND]
    index = tail.size / float(np.sum(np.log(tail / SPIKE_BAND)))
    low = index * (1.0 - 2.0 / sqrt(tail.size))      # Hill's index less two standard errors
    if low <= 0.5:
        return float('inf'), True
    return max(gauss, SPIKE_BAND * (tail.size / a.size * n_values / alpha) ** (1.0 / low)), True


def _spike_in(x, r0, r1, k, scale, thr):
    """
    Return the readings of one cluster of large differences that form a spike, or None.

    ``x`` (N,) the channel, nT; ``scale`` the sd of a k-th difference, nT; ``thr`` the
    threshold in its units.  Returns (indices (L,) of the spike's readings, each less the
    interpolation of its neighbours (L,) nT).
    """
    h = k // 2
    a0, a1 = r0 - k, r1 + k + 1
    loc = x[a0:a1]
    best = None
    sets = [[np.arange(u, u + n)] for n in range(1, SPIKE_MAX_SAMPLES + 1)
            for u in range(r0, r1 - n + 2)]
    sets += [[np.array([u]), np.array([w])] for u in range(r0, r1 + 1)
             for w in range(u + 2, r1 + 1)]
    for blocks in sets:
        y = loc.copy()
        for blk in blocks:
            nodes = np.r_[np.arange(blk[0] - h, blk[0]), np.arange(blk[-1] + 1, blk[-1] + h + 1)]
            y[blk - a0] = _interpolation(nodes, blk) @ x[nodes]
        z = np.diff(y, k) / scale
        top = float(np.abs(z).max())
        flagged = np.concatenate(blocks)
        if top <= thr and (best is None or (len(flagged), top) < (len(best[0]), best[1])):
            best = (flagged, top, float(z @ z), y[flagged - a0])
    if best is None:
        return None
    # a step, or a transient longer than a spike, explains the cluster as well: no spike
    z0 = np.diff(loc, k) / scale
    idx = np.arange(a0, a1)
    alts = [idx >= p for p in range(r0, r1 + 2)]
    alts += [(idx >= p) & (idx < q) for p in range(r0, r1 + 2)
             for q in range(p + SPIKE_MAX_SAMPLES + 1, r1 + 2)]
    dus = [np.diff(alt.astype(float), k) / scale for alt in alts]
    ss_alt = min([float('inf')] + [float(z0 @ z0 - (z0 @ du) ** 2 / (du @ du)) for du in dus])
    if ss_alt - best[2] < _normal_isf(ALPHA / 2.0) ** 2:     # chi-square(1) quantile
        return None
    return best[0], x[best[0]] - best[3]


def find_spikes(raw, flags=None, est=None):
    """
    Find one-to-three-reading spikes per sensor and axis (module docstring: the method).

    ``raw`` (S, N, 3) nT in time order; ``flags`` (S, N, 3) bool, readings already left out;
    ``est`` :func:`channel_noise` of ``raw`` (or computed).
    Returns ((S, N, 3) bool, True on a spike's readings; per sensor and axis the spike sizes
    in time order, nT: [[array, x3], ...]).
    """
    raw = np.asarray(raw, float)
    s_count, n, _ = raw.shape
    out = np.zeros(raw.shape, bool)
    sizes = [[np.zeros(0) for _ in range(3)] for _ in range(s_count)]
    if n < 4 * max(SPIKE_ORDERS) + 8:
        return out, sizes
    est = channel_noise(raw) if est is None else est
    for j in range(s_count):
        # an axis without a white floor has no smooth course to be off
        white = np.array([est.status[3 * j + a] == 'white' for a in range(3)])
        if not white.any():
            continue
        top = max(int(est.order[3 * j + a]) for a in range(3) if white[a])
        k = min(k for k in SPIKE_ORDERS if k >= min(top, max(SPIKE_ORDERS)))
        h = k // 2
        d = np.diff(raw[j], k, axis=0)                  # (N - k, 3), centred on i + k/2
        mad = np.array([mad_sd(d[:, a]) for a in range(3)])
        live = (mad > 0) & white
        if not live.any():
            continue
        thr, _ = spike_threshold((d[:, live] / mad[live]).ravel(), 3 * s_count * n)
        if not np.isfinite(thr):
            continue
        for a in np.flatnonzero(live):
            over = np.flatnonzero(np.abs(d[:, a]) > thr * mad[a]) + h
            if not len(over):
                continue
            cut = np.flatnonzero(np.diff(over) > k)
            got, size = [], []
            for c0, c1 in zip(np.r_[over[0], over[cut + 1]], np.r_[over[cut], over[-1]]):
                r0, r1 = c0 - h, c1 + h
                if r0 - k < 0 or r1 + k + 1 > n:
                    continue            # at an end of the record: no neighbours on one side
                if flags is not None and flags[j, r0 - k:r1 + k + 1, a].any():
                    continue
                found = _spike_in(raw[j, :, a], r0, r1, k, mad[a], thr)
                if found is not None:
                    got.append(found[0])
                    size.append(float(np.abs(found[1]).max()))
            if got:
                out[j, np.concatenate(got), a] = True
                sizes[j][a] = np.array(size)
    return out, sizes


def screen_readings(data):
    """Find the readings of ``data`` that no field produces (module docstring): a ReadingScreen."""
    raw = np.asarray(data.raw, float)
    s_count, n, _ = raw.shape
    flags = np.zeros(raw.shape, bool)
    est = channel_noise(raw) if n >= 16 else None
    p = repeat_bounds(raw, est)
    min_run = np.full((s_count, 3), n + 1, int)
    out = []

    def flag(j, a, kind, values, m, lr):
        flags[j, :, a] |= m
        out.append(SuspectChannel(j + 1, AXES[a], kind, values, int(m.sum()), n,
                                  _stretches(data.t, m), lr))
    for j, a in np.ndindex(s_count, 3):
        x = raw[j, :, a]
        min_run[j, a] = lr = min_flagged_run(p[j, a], n, 3 * s_count)
        if lr > n:
            continue
        starts, lengths = _runs(x)
        long = lengths >= lr
        if not long.any():
            continue
        values = x[starts[long]]
        hi, lo = float(x.max()), float(x.min())
        vals, counts = np.unique(x, return_counts=True)
        top = int(np.argmax(counts))
        pinned = ((float(vals[top]),) if counts[top] >= PINNED_FRACTION * n
                  and np.isin(vals[top], values) else ())
        clipped = tuple(v for v in (hi, lo) if v not in pinned and np.isin(v, values))
        for kind, special in (('pinned', pinned), ('clipped', clipped)):
            if special:
                flag(j, a, kind, special, np.isin(x, special), lr)
        special = pinned + clipped
        rep = np.zeros(n, bool)
        for s0, ln, v in zip(starts[long], lengths[long], values):
            if float(v) not in special:
                rep[s0 + 1:s0 + ln] = True      # the first is the reading repeated
        if rep.any():
            flag(j, a, 'repeated', (), rep, lr)
    spikes, sizes = find_spikes(raw, flags, est)
    for j, a in np.ndindex(s_count, 3):
        if spikes[j, :, a].any():
            size = sizes[j][a]
            flag(j, a, 'spike', (float(size.min()), float(size.max())), spikes[j, :, a], 0)
    out.sort(key=lambda c: (c.sensor, c.axis))
    return ReadingScreen(flags=flags, channels=out, min_run=min_run, repeat_bound=p)


def leave_out_unphysical(data, field_nt=None):
    """
    Screen ``data`` and leave out the sets that hold readings no field produces.

    ``field_nt``: reference magnitude, nT, a scalar or (N,).  Returns (data, field_nt,
    ReadingScreen), the first two without the flagged sets (the same objects when none).
    UnphysicalReadingsError when fewer than :data:`MIN_KEPT_FRACTION` of the sets are left.
    """
    screen = screen_readings(data)
    if not screen.channels:
        return data, field_nt, screen
    keep = screen.keep
    n = data.n_samples
    if keep.sum() < MIN_KEPT_FRACTION * n:
        what = '; '.join(text for _, text in screen.lines())
        raise UnphysicalReadingsError(
            f'{what}: no field produces these readings, and without them only {int(keep.sum())} '
            f'of {n} sets are left (need at least {MIN_KEPT_FRACTION:.0%}): check the sensor, '
            'its wiring, its range setting and the driver, then record again')
    idx = np.flatnonzero(keep)
    if field_nt is not None and np.ndim(field_nt) > 0:
        field_nt = np.asarray(field_nt)[idx]
    return data.subset(idx), field_nt, screen
