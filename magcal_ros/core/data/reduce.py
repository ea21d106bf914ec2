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
A record too long to hold, reduced chunk by chunk to a bounded, representative form.

In memory bounded by constants (docs/design.md, "Long records"): **the sample** (every k-th
epoch, k doubling, with the full-rate field rate) for the fit; **the noise blocks**
(contiguous full-rate blocks) for the noise floor; a second pass for **the residual
statistics of every epoch** (:func:`residual_statistics`, exact).
"""
from dataclasses import dataclass, replace

from magcal_ros.core.data.dataset import Dataset, EPOCH_AXES
from magcal_ros.core.data.noise import noise_floor_of
from magcal_ros.core.effects import raw_rate
import numpy as np

#: the sample keeps between this many and twice as many evenly spread epochs
SAMPLE_EPOCHS = 20000
#: contiguous full-rate epochs per noise block
NOISE_BLOCK = 4096
#: between this many and twice as many noise blocks are kept
NOISE_BLOCKS = 8
#: records of more epochs than this are reduced
REDUCE_ABOVE = 100000


def concat(pieces):
    """Return one Dataset of the epochs of ``pieces`` (Datasets of the same columns), in order."""
    first = pieces[0]
    if len(pieces) == 1:
        return replace(first, origin=None)
    cols = {}
    for name, axis in EPOCH_AXES.items():
        vals = [getattr(p, name) for p in pieces]
        cols[name] = None if any(v is None for v in vals) else np.concatenate(vals, axis=axis)
    return replace(first, origin=None, meta=dict(first.meta), **cols,
                   aux={k: np.concatenate([p.aux[k] for p in pieces]) for k in first.aux})


def _take(piece, idx):
    """Return the epochs ``idx`` of ``piece`` as a Dataset of its own (no link to ``piece``)."""
    return replace(piece.subset(idx), origin=None)


class NoiseBlocks:
    """Contiguous full-rate blocks of a long record: the data of its noise floor."""

    def __init__(self, blocks):
        self.blocks = [b for b in blocks if b.n_samples >= 64] or blocks
        self.data = concat(self.blocks)
        self.starts = np.cumsum([0] + [b.n_samples for b in self.blocks[:-1]])
        self._cache = {}

    @property
    def n_samples(self):
        """Return the number of epochs in the blocks."""
        return self.data.n_samples

    def floor(self, result=None):
        """
        :class:`~magcal_ros.core.data.noise.NoiseFloor` from the blocks and ``result``'s residual.

        ``result``: a FitResult of the sample (its residual on the blocks: the second estimate).
        """
        key = None if result is None else id(result)
        if key not in self._cache:
            res = sigma = None
            if result is not None:
                res = np.concatenate([np.linalg.norm(corrected(result, b), axis=2)
                                      - field_of(result, b)[None] for b in self.blocks], axis=1)
                sigma = np.asarray(result.sigma_nt, float)
            self._cache[key] = noise_floor_of(self.data.raw, res, sigma, self.starts)
        return self._cache[key]


def field_of(result, piece):
    """(N,) reference magnitude of ``piece``'s epochs for ``result``: its constant or ref_total."""
    f = np.asarray(result.field_magnitude_nt, float)
    if np.ptp(f) == 0 or piece.ref_total is None:
        return np.full(piece.n_samples, f[0])
    return np.asarray(piece.ref_total, float)


def corrected(result, piece):
    """(S, N, 3) nT: ``result``'s calibration applied to ``piece`` (centred on the array)."""
    from magcal_ros.core.model.fitting import centred_readings, corrected_readings
    ctx = [piece.context(j) for j in range(1, piece.n_sensors + 1)]
    cor = corrected_readings(result.model, result.params, piece.raw, ctx)
    return centred_readings(result.model, result.params, cor, ctx)


def _with_rate(piece, idx):
    """:func:`_take` with the ``rate`` (S, N, 3) nT/s of ``piece``'s readings (None: no rise)."""
    rates = [raw_rate(raw, piece.t) for raw in piece.raw]
    out = _take(piece, idx)
    out.rate = None if any(r is None for r in rates) else np.stack(rates)[:, idx]
    return out


def rated(chunks):
    """
    Yield the epochs of consecutive ``chunks`` with the field rate of the whole record.

    Each piece's ``rate`` (S, N, 3) nT/s is :func:`~magcal_ros.core.effects.raw_rate` of the
    record held whole (a chunk's last epoch waits for the next); None where times do not rise.
    """
    carry = None
    for piece in chunks:
        if piece.n_samples == 0:
            continue
        head = 0
        if carry is not None:
            head = carry.n_samples - 1              # the epoch still waiting for its rate
            piece = concat([carry, piece])
        carry = _take(piece, np.arange(max(0, piece.n_samples - 3), piece.n_samples))
        emit = np.arange(head, piece.n_samples - 1)
        if len(emit):
            yield _with_rate(piece, emit)
    if carry is not None:
        yield _with_rate(carry, [carry.n_samples - 1])


class Reducer:
    """
    Reduce a record fed chunk by chunk (:meth:`add`) to a :class:`Reduced` (:meth:`finish`).

    Chunks from :func:`rated`.  Memory: at most 2 x ``sample`` epochs, 2 x ``blocks`` x
    ``block`` epochs of noise blocks and one chunk.
    """

    def __init__(self, sample=SAMPLE_EPOCHS, block=NOISE_BLOCK, blocks=NOISE_BLOCKS):
        self.cap, self.block, self.max_blocks = int(sample), int(block), int(blocks)
        self.stride = self.block_stride = 1
        self.kept = []              # [(global index array, Dataset)]
        self.n_kept = 0
        self.blocks = {}            # block number -> [Dataset pieces]
        self.n = 0                  # epochs seen
        self.t_first = self.t_last = None

    def add(self, piece):
        """Take the next chunk (a Dataset of consecutive epochs, with ``rate``)."""
        if piece.n_samples == 0:
            return
        self.t_first = float(piece.t[0]) if self.t_first is None else self.t_first
        self.t_last = float(piece.t[-1])
        g = self.n + np.arange(piece.n_samples)
        self.n += piece.n_samples
        self._blocks(piece, g)
        self._sample(piece, g)

    def _sample(self, piece, g):
        sel = g % self.stride == 0
        if sel.any():
            self.kept.append((g[sel], _take(piece, np.flatnonzero(sel))))
            self.n_kept += int(sel.sum())
        while self.n_kept > 2 * self.cap:
            self.stride *= 2
            self.kept = [(gi[m], _take(d, np.flatnonzero(m))) for gi, d in self.kept
                         if (m := gi % self.stride == 0).any()]
            self.n_kept = sum(len(gi) for gi, _ in self.kept)

    def _blocks(self, piece, g):
        num = g // self.block
        for b in np.unique(num[num % self.block_stride == 0]):
            self.blocks.setdefault(int(b), []).append(_take(piece, np.flatnonzero(num == b)))
        while len(self.blocks) > 2 * self.max_blocks:
            self.block_stride *= 2
            self.blocks = {b: v for b, v in self.blocks.items() if b % self.block_stride == 0}

    def finish(self):
        """Return the :class:`Reduced` record (after the last chunk)."""
        if not self.kept:
            raise ValueError('the record has no epochs')
        sample = concat([d for _, d in self.kept])
        blocks = NoiseBlocks([concat(v) for _, v in sorted(self.blocks.items())])
        info = {'epochs': int(self.n), 'sample_epochs': int(sample.n_samples),
                'sample_stride': int(self.stride), 'noise_block_epochs': int(self.block),
                'noise_blocks': len(blocks.blocks), 'noise_epochs': int(blocks.n_samples),
                'span_s': float(self.t_last - self.t_first)}
        sample.meta.update(noise_blocks=blocks, reduction=info)
        return Reduced(sample=sample, blocks=blocks, n_total=int(self.n), info=info)


@dataclass
class Reduced:
    """A long record reduced: ``sample`` (Dataset), ``blocks``, ``n_total`` epochs, ``info``."""

    sample: Dataset
    blocks: NoiseBlocks
    n_total: int
    info: dict


def reduce_chunks(chunks, **kwargs):
    """Reduce an iterable of consecutive Dataset chunks (:class:`Reducer`)."""
    red = Reducer(**kwargs)
    for piece in rated(chunks):
        red.add(piece)
    return red.finish()


class _Moments:
    """Running count, sum, sum of squares and extremes, per leading index."""

    def __init__(self):
        self.n, self.s, self.ss, self.lo, self.hi = 0, 0.0, 0.0, np.inf, -np.inf

    def add(self, x, axis):
        self.n = self.n + np.shape(x)[axis]
        self.s = self.s + np.sum(x, axis=axis)
        self.ss = self.ss + np.sum(np.square(x), axis=axis)
        self.lo = np.minimum(self.lo, np.min(x, axis=axis))
        self.hi = np.maximum(self.hi, np.max(x, axis=axis))

    def rms(self):
        return np.sqrt(self.ss / max(self.n, 1))


def residual_statistics(chunks, result, positions=None):
    """
    Residual statistics of ``result``'s calibration on every epoch of ``chunks``, nT, nT/m.

    One pass of sums and extremes; a lag effect filters each chunk afresh (a transient at
    chunk starts).  Returns the keys of :func:`magcal_ros.pipeline.summarize` that read every
    epoch (``scalar_rms_nt``, ``total_field_*``, ``n_samples``, ...; the ``tensor_*`` ones
    with ``positions`` (S, 3) m).
    """
    before, after, vector = _Moments(), _Moments(), _Moments()
    tens = {'b': _Moments(), 'a': _Moments()}
    n = 0
    for piece in rated(chunks):
        f = field_of(result, piece)
        before.add(np.linalg.norm(piece.raw, axis=2) - f[None], 1)
        cen = corrected(result, piece)
        after.add(np.linalg.norm(cen, axis=2) - f[None], 1)
        vector.add((cen - cen[:1]).reshape(cen.shape[0], -1), 1)
        n += piece.n_samples
        if positions is not None and piece.n_sensors >= 3:
            from magcal_ros.core.geometry.tensor import tensor_lstsq
            for key, fields in (('b', piece.raw), ('a', cen)):
                tens[key].add(tensor_lstsq(fields, positions)[0], 0)
    out = {'n_samples': int(n),
           'scalar_rms_nt': {str(j + 1): float(v) for j, v in enumerate(after.rms())},
           'vector_rms_nt': {str(j + 1): float(v) for j, v in enumerate(vector.rms()) if j},
           'total_field_rms_before_nt': {str(j + 1): float(v) for j, v in enumerate(before.rms())},
           'total_field_max_dev_before_nt': float(np.max(np.maximum(before.hi, -before.lo))),
           'total_field_max_dev_after_nt': float(np.max(np.maximum(after.hi, -after.lo)))}
    if positions is not None and after.ss.shape[0] >= 3 and n:
        for key, rms_key, max_key in (('b', 'tensor_rms_before_nt_per_m',
                                       'tensor_max_dev_before_nt_per_m'),
                                      ('a', 'tensor_rms_nt_per_m',
                                       'tensor_max_dev_after_nt_per_m')):
            acc = tens[key]
            mean = acc.s / n
            out[rms_key] = np.sqrt(np.maximum(acc.ss / n - mean ** 2, 0.0)).tolist()
            out[max_key] = float(np.max(np.maximum(acc.hi - mean, mean - acc.lo)))
    return out
