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
Group the samples of S sensors into sets taken at the same epoch (no rclpy).

A serial driver stamps each sample with the arrival time of its bytes: samples read in one
chunk share a stamp and a starved reader delivers bursts, so matching stamps within a
tolerance drops and mismatches sets.  Sets are formed by epoch number instead: the k-th
sample of sensor j belongs to epoch k + o_j, the offsets o_j voted from the stamps; with a
``misfit`` from the data a stream shifted by a lost sample is re-paired at the first set
that shows it (:class:`StampMatcher`).
"""
from collections import deque

import numpy as np


def backdate(stamps, period_s):
    """
    Spread samples that arrived together back along the sample grid.

    In a run of stamps less than a quarter period apart (one read) the last keeps its stamp,
    each earlier one is put a period before its successor.  ``stamps`` (N,) non-decreasing
    stamps of one stream, s; ``period_s`` its sample period, s.  Returns (N,) stamps, s.
    """
    a = np.asarray(stamps, float)
    n = len(a)
    if n < 2:
        return a.copy()
    together = np.diff(a) < 0.25 * period_s         # sample i arrived with sample i + 1
    # out[i] = a[j] - (j - i) T, j the first index >= i that ends a run
    idx = np.arange(n)
    ends = np.where(np.append(~together, True), idx, n)
    last = np.minimum.accumulate(ends[::-1])[::-1]
    return a[last] - (last - idx) * period_s


#: length of the blocks whose earliest stamp tracks the sample clock in epoch_times, s
CLOCK_BLOCK_S = 2.0


def epoch_times(epochs, stamps_s, block_s=CLOCK_BLOCK_S):
    """
    Sample instants of epochs from noisy, late stamps: a linear clock, stepped where lost.

    A lost sample puts every later epoch a period off one line t = t0 + T e.  Latency is
    never negative, so the promptest stamp of each block of ``block_s`` carries its instant:
    T puts those stamps on one grid (equal phases t_k / T - e_k, within 3 % of the line's
    slope), each block's phase counts the periods lost before it (median of three, never
    decreasing), and a set takes the largest count that keeps its own and every later stamp
    after its instant.  Phases that disagree (resultant length <= 0.9) keep the line; t0
    sits on the lower envelope of the stamps.

    ``epochs`` (N,) increasing integers (gaps where sets were dropped); ``stamps_s`` (N,) a
    stamp of each (the median of its sensors'), s.  Returns (N,) times, s, strictly
    increasing.
    """
    from scipy.ndimage import median_filter
    e = np.asarray(epochs, float)
    t = np.asarray(stamps_s, float)
    if len(e) < 2:
        return t.copy()
    e = e - e[0]
    slope = np.polyfit(e, t - t[0], 1)[0]
    if not slope > 0:
        raise ValueError('stamps do not increase with the epoch number')
    n_blocks = int(np.clip(round((t[-1] - t[0]) / block_s), 1, len(e) // 10))
    if n_blocks >= 3:
        edges = np.linspace(0, len(e), n_blocks + 1).round().astype(int)
        sizes = np.diff(edges)
        d = t - slope * e
        first = np.array([a + np.argmin(d[a:b]) for a, b in zip(edges[:-1], edges[1:])])
        ek, tk = e[first], t[first] - t[0]
        period = slope
        for span, n in ((0.03, 6001), (2e-5, 401)):
            grid = period * (1.0 + np.linspace(-span, span, n))
            phase = np.exp(2j * np.pi * (tk[None, :] / grid[:, None] - ek[None, :]))
            r = np.abs(phase.mean(axis=1))
            period = grid[np.argmax(r)]
        ph = tk / period - ek
        mean_phase = np.angle(np.exp(2j * np.pi * ph).mean()) / (2 * np.pi)
        if r.max() > 0.9:
            steps = np.round(ph - mean_phase)
            steps = median_filter(steps, size=3, mode='nearest')
            steps = np.maximum.accumulate(steps - steps[0])
            slope = np.polyfit(ek + steps, tk, 1)[0]
            t0 = t[0] + np.min(tk - slope * (ek + steps))
            upto = np.floor((t - t0) / slope - e + 0.5)
            upto = np.minimum.accumulate(upto[::-1])[::-1]
            floor_ = np.repeat(np.concatenate([[0.0], steps[:-1]]), sizes)
            e = e + np.clip(upto, floor_, steps[-1])
            return t0 + slope * e
    t0 = np.min(t - slope * e)
    return t0 + slope * e


#: largest backward shift of one stream, and largest change of the offsets by the stamp
#: vote's proposal, that StampMatcher with ``misfit`` tries, epochs
MAX_VOTE_SHIFT = 25
#: sets after a failed one that a re-pairing must pass before it is taken
MIN_PASS = 2


class _Ring:
    """Last ``size`` (sequence number, stamp) pairs of one stream, as numpy arrays."""

    def __init__(self, size):
        self.q = np.zeros(size)
        self.s = np.zeros(size)
        self.size = size
        self.count = 0

    def clear(self):
        self.count = 0

    def __len__(self):
        return min(self.count, self.size)

    def append(self, q, s):
        k = self.count % self.size
        self.q[k] = q
        self.s[k] = s
        self.count += 1

    def arrays(self):
        """(sequence numbers, stamps), oldest first (copies)."""
        if self.count <= self.size:
            return self.q[:self.count].copy(), self.s[:self.count].copy()
        k = self.count % self.size
        return np.concatenate([self.q[k:], self.q[:k]]), np.concatenate([self.s[k:], self.s[:k]])


def _median(values):
    """Median of a short list of floats (np.median costs ~10 us per call on the hot path)."""
    v = sorted(values)
    m = len(v) // 2
    return float(v[m]) if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


class StampMatcher:
    """
    Group the samples of ``n_sensors`` streams into epochs.

    The k-th sample of sensor j belongs to epoch k + o_j (o_1 = 0).  Every ``align_every``
    samples each sample of sensor j in a sliding window votes for the epoch of the sensor-1
    sample nearest in stamp (raw and :func:`backdate`-ed) within ``tolerance_s``; a clear
    majority wins.  When every sensor has a queued sample the heads share an epoch (a set)
    or the oldest are dropped (an epoch some sensor never delivered).

    ``n_sensors`` streams S; ``tolerance_s`` (s, ~half a period); ``window`` samples per
    stream in the vote, ``align_every`` samples between votes; ``max_queue`` samples kept per
    stream while another is silent.  ``misfit(items) -> float``, optional, a chi-square of the
    S items of a set as one epoch (:meth:`.LiveCorrector.pairing_chi2`): a set passes at most
    ``threshold``, a failing one is never emitted.  After a failure the candidate offsets
    (:meth:`_candidates`, forward shifts up to ``max_shift``) are scored over ``confirm``
    sets; one whose every set passes and whose sum beats every other by ``margin`` (2 ln of
    a likelihood ratio) is adopted, else the set is dropped (with no clear candidate the vote
    restarts).  Once aligned, a new vote is taken unless the next ``confirm`` sets refute it.

    Counters: ``complete`` sets emitted, ``incomplete`` epochs missing a sensor's sample,
    ``out_of_order`` samples older than their sensor's previous one, ``realigned`` offsets
    the vote changed after the first alignment, ``rejected`` sets over ``threshold``,
    ``repaired`` offsets changed from the misfit.
    """

    def __init__(self, n_sensors, tolerance_s, window=200, align_every=40, max_queue=1000,
                 misfit=None, threshold=np.inf, max_shift=3, confirm=5, margin=25.0):
        if n_sensors < 1:
            raise ValueError(f'n_sensors must be >= 1, got {n_sensors}')
        if not tolerance_s > 0:
            raise ValueError(f'tolerance_s must be > 0 s, got {tolerance_s}')
        self.n_sensors = int(n_sensors)
        self.tolerance_s = float(tolerance_s)
        self.window = int(window)
        self.align_every = int(align_every)
        self.max_queue = int(max_queue)
        self.misfit = misfit
        self.threshold = float(threshold)
        self.max_shift = int(max_shift)
        self.confirm = int(confirm)
        self.margin = float(margin)
        self._hist = [_Ring(self.window) for _ in range(self.n_sensors)]
        self._queues = [deque() for _ in range(self.n_sensors)]
        # with misfit: (sequence number, stamp, item) last taken from each queue (shifts back)
        self._past = [deque(maxlen=MAX_VOTE_SHIFT + confirm + 2)
                      for _ in range(self.n_sensors)]
        self.reset()

    def reset(self):
        """Forget queued samples, offsets and counters."""
        for h, q, p in zip(self._hist, self._queues, self._past):
            h.clear()
            q.clear()
            p.clear()
        self._seq = [0] * self.n_sensors
        self._last_arrival = [None] * self.n_sensors
        self._offset = [0] + [None] * (self.n_sensors - 1)
        self._proposal = [0] + [None] * (self.n_sensors - 1)    # the stamp vote's, checked
        self._pending = None            # a proposal to compare with the pairing as it is
        self._refuted = deque(maxlen=4)     # the last proposals the data refuted
        self._aligned = self.n_sensors == 1
        self._since_align = 0
        self._backoff = self._skip = 0
        self.complete = self.incomplete = self.out_of_order = self.realigned = 0
        self.rejected = self.repaired = 0

    @property
    def queued(self):
        """Count the samples waiting for the other sensors of their set (tuple of S counts)."""
        return tuple(len(q) for q in self._queues)

    def add(self, j, stamp_s, item):
        """
        Add the sample ``item`` of sensor ``j`` (0-based) stamped ``stamp_s`` seconds.

        Returns the completed sets, oldest first: [(epoch number, median stamp of the set s,
        [item of sensor 0, ..., item of sensor S-1])] (:func:`epoch_times` gives instants).
        """
        last = self._last_arrival[j]
        if last is not None and stamp_s < last:
            self.out_of_order += 1
            return []
        self._last_arrival[j] = stamp_s
        q = self._seq[j]
        self._seq[j] += 1
        self._hist[j].append(q, stamp_s)
        queue = self._queues[j]
        queue.append((q, stamp_s, item))
        if len(queue) > self.max_queue:
            self._past[j].append(queue.popleft())
            self.incomplete += 1
        self._since_align += 1
        if self._since_align >= (self.align_every if self._aligned else 8):
            self._align()
        return self._emit() if self._aligned else []

    def _align(self):
        """Vote the epoch offset of every stream against sensor 1's."""
        self._since_align = 0
        ref = self._hist[0]
        if len(ref) < 10:
            return
        q0, s0 = ref.arrays()
        if s0[-1] <= s0[0]:
            return
        period = (s0[-1] - s0[0]) / (len(s0) - 1)
        # raw stamps vote well for samples one by one, backdated ones for chunks: both vote
        refs = (s0, backdate(s0, period))
        for j in range(1, self.n_sensors):
            hist = self._hist[j]
            if len(hist) < 10:
                continue
            qj, sj = hist.arrays()
            votes = []
            for ref_s, s in zip(refs, (sj, backdate(sj, period))):
                k = np.clip(np.searchsorted(ref_s, s), 1, len(ref_s) - 1)
                k = np.where(np.abs(ref_s[k - 1] - s) <= np.abs(ref_s[k] - s), k - 1, k)
                ok = np.abs(ref_s[k] - s) <= self.tolerance_s
                votes.append((q0[k] - qj)[ok])
            votes = np.concatenate(votes).astype(int)
            if len(votes) < 10:
                continue
            values, counts = np.unique(votes, return_counts=True)
            if counts.max() <= 0.5 * len(votes):
                continue           # no clear majority: keep the offset we have
            best = int(values[np.argmax(counts)])
            if self.misfit is not None and self._aligned:
                self._proposal[j] = best    # stamps propose, the data decide (_emit)
                continue
            if self._offset[j] is not None and best != self._offset[j]:
                self.realigned += 1
            self._offset[j] = best
        if self.misfit is not None and self._aligned:
            vote = self._vote()
            self._pending = (vote if vote != self._offset and vote not in self._refuted
                             else None)
        self._aligned = all(o is not None for o in self._offset)

    def _emit(self):
        out = []
        queues, misfit, threshold = self._queues, self.misfit, self.threshold
        pasts = self._past if misfit is not None else None
        while all(queues):
            if self._pending is not None and self._decide_vote() is None:
                break                       # wait for the samples that decide it
            offset = self._offset
            epochs = [qq[0][0] + o for qq, o in zip(queues, offset)]
            e = min(epochs)
            if all(x == e for x in epochs):
                items = [qq[0][2] for qq in queues]
                if misfit is not None and not misfit(items) <= threshold:
                    repaired = self._repair()
                    if repaired is None:
                        break               # wait for the samples that decide it
                    if not repaired:
                        for qq, pp in zip(queues, pasts):
                            pp.append(qq.popleft())
                        self.rejected += 1
                    continue                # repaired: the heads pair anew
                heads = [qq.popleft() for qq in queues]
                if pasts is not None:
                    self._backoff = self._skip = 0
                    for pp, h in zip(pasts, heads):
                        pp.append(h)
                out.append((e, _median([h[1] for h in heads]), items))
                self.complete += 1
            else:
                for k, (qq, x) in enumerate(zip(queues, epochs)):
                    if x == e:
                        h = qq.popleft()
                        if pasts is not None:
                            pasts[k].append(h)
                self.incomplete += 1
        return out

    def _candidates(self):
        """
        Offsets to try after a failed set: (stream, shift, offsets), each once.

        As they are (shift 0); one stream forward by 1 .. ``max_shift`` (lost samples); the
        stamp vote's proposal (stream -1); one stream back by 1 .. :data:`MAX_VOTE_SHIFT`
        (lagging stamps).  One stream moves at a time; several slips wait for the vote.
        """
        base = self._offset
        seen = {tuple(base)}
        yield 0, 0, list(base)
        single = []
        for j in range(self.n_sensors):
            for delta in (*range(1, self.max_shift + 1), *range(-1, -MAX_VOTE_SHIFT - 1, -1)):
                o = list(base)
                if j == 0:              # sensor 1 keeps offset 0: shift the others instead
                    o[1:] = [x - delta for x in o[1:]]
                else:
                    o[j] += delta
                seen.add(tuple(o))
                single.append((j, delta, o))
        vote = self._vote()
        reach = self._reach(vote)
        if tuple(vote) not in seen and reach <= MAX_VOTE_SHIFT:
            yield -1, reach, vote       # e.g. a run of lost samples, once the vote sees it
        yield from single

    def _vote(self):
        """Return the offsets the stamp vote proposes (the current one where it has none)."""
        return [p if p is not None else o for p, o in zip(self._proposal, self._offset)]

    def _reach(self, offsets):
        """Return how far ``offsets`` move the streams against each other, epochs."""
        diff = [p - o for p, o in zip(offsets, self._offset)]
        return max(diff) - min(diff)    # diff[0] = 0: sensor 1 keeps offset 0

    def _item(self, k, seq):
        """Return the item of stream k with sequence number ``seq`` (queued or past), or None."""
        qq = self._queues[k]
        i = seq - qq[0][0]
        if i >= 0:
            return qq[i][2] if i < len(qq) else None
        past = self._past[k]
        i += len(past)
        return past[i][2] if i >= 0 else None

    def _fit(self, offset, first):
        """
        Score a pairing on the ``confirm`` sets from epoch ``first`` on.

        Returns (-n, sum): n sets pass before the first that fails (or lacks a sample),
        sum is their misfit; smaller is better.
        """
        total = 0.0
        for n, e in enumerate(range(first, first + self.confirm)):
            items = [self._item(k, e - o) for k, o in enumerate(offset)]
            if any(item is None for item in items):
                return -n, total
            m = self.misfit(items)
            if not m <= self.threshold:
                return -n, total
            total += m
        return -self.confirm, total

    def _better(self, a, b):
        """Tell whether score ``a`` beats ``b`` clearly: more sets pass, or by ``margin``."""
        return a[0] < b[0] or (a[0] == b[0] and a[1] + self.margin <= b[1])

    def _decide_vote(self):
        """
        Take the stamp vote's proposal unless the data refute it: True, False or None (wait).

        Refuted when its first :data:`MIN_PASS` of the next ``confirm`` sets do not all pass or
        the pairing as it is fits clearly better (:meth:`_better`), else taken.
        """
        vote = self._pending
        reach = self._reach(vote)
        queues = self._queues
        if reach <= MAX_VOTE_SHIFT:
            if min(len(qq) for qq in queues) < reach + self.confirm + 1:
                return None
            heads = [qq[0][0] for qq in queues]
            now = self._fit(self._offset, max(h + o for h, o in zip(heads, self._offset)))
            new = self._fit(vote, max(h + o for h, o in zip(heads, vote)))
        self._pending = None
        if reach > MAX_VOTE_SHIFT or -new[0] < MIN_PASS or self._better(now, new):
            self._refuted.append(vote)
            return False
        self._offset = vote
        self.realigned += 1
        return True

    def _repair(self):
        """
        Decide a failed set: True (offsets changed), False (drop it) or None (wait).

        After a failure no candidate explains, the next 1, 3, 7 .. 64 failing sets are
        dropped without a search.
        """
        if self._skip:
            self._skip -= 1
            return False
        queues = self._queues
        candidates = list(self._candidates())
        ahead = max([self.max_shift] + [d for j, d, _ in candidates if j == -1])
        if min(len(qq) for qq in queues) < ahead + self.confirm + 1:
            return None
        heads = [qq[0][0] for qq in queues]
        fits = []
        for j, delta, o in candidates:
            if delta == 0:              # the sets after the failed one
                first = heads[0] + o[0] + 1
            elif j >= 0:                # the shifted stream's samples from its head on
                first = heads[j] + o[j]
            else:                       # every stream's samples from its head on
                first = max(h + x for h, x in zip(heads, o))
            fits.append((self._fit(o, first), delta, o))
        fits.sort(key=lambda f: f[0])
        (best, delta, o), second = fits[0], fits[1][0]
        if delta == 0 and -best[0] >= MIN_PASS:
            return False                # the pairing holds: this set alone is bad
        if not (-best[0] >= MIN_PASS and self._better(best, second)):
            if not self._backoff:
                # a longer slip: vote afresh on the samples from now on
                for h in self._hist:
                    h.clear()
                self._since_align = 0
            self._skip = self._backoff
            self._backoff = min(64, 2 * self._backoff + 1)
            return False
        self._offset = o
        self.repaired += 1
        return True
