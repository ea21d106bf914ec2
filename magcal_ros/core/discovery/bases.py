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
The drivers the discovery search tries, built from what a record holds.

A :class:`Driver` is one factor of the model formula (docs/formulas.md: ``s(t, k=8)``,
``lag(aux_relay)``, ``step(300)``, ``temperature * t``, ``rate``, ...) with its centred
design columns on the tested epochs (the grammar's own, :func:`grammar_columns`).
"""
from dataclasses import dataclass, field
import math

from magcal_ros.core.discovery.constants import (CYCLIC_K, LAG_FRACTIONS, LAG_POINTS,
                                                 MIN_SAMPLES_PER_K, SMOOTH_K)
from magcal_ros.core.discovery.measures import lag_grid, usable
from magcal_ros.core.effects.base import format_arg, SensorContext
from magcal_ros.core.effects.formula import parse_driver
import numpy as np


@dataclass
class Driver:
    """
    One driver of the formula and its design columns.

    ``text``: the formula factor; ``kind``: 'time', 'channel', 'product' or 'rate';
    ``channel``: what it reads; ``columns(j)``: sensor j's centred (N, m) design; ``per_axis``:
    it acts axis by axis (dB_i = P_i X_i); ``note``: what it was built from.
    """

    text: str
    kind: str
    channel: str
    columns: object
    per_axis: bool = False
    note: str = ''
    _cache: dict = field(default_factory=dict, repr=False)

    def x(self, j):
        """Return the (N, m) columns of sensor ``j`` (cached)."""
        if j not in self._cache:
            self._cache[j] = np.asarray(self.columns(j), float)
        return self._cache[j]


def centred(x):
    """Columns of ``x`` (N,) or (N, m) less their means, as (N, m)."""
    x = np.asarray(x, float).reshape(len(x), -1)
    return x - x.mean(axis=0)


def grammar_columns(text, ctx, q=()):
    """(N, m) centred columns of the grammar's driver ``text`` in ``ctx``, parameters ``q``."""
    d = parse_driver(text)
    refs = {}
    d.prepare(ctx, refs)
    return centred(d.columns(ctx, None, refs, np.atleast_1d(np.asarray(q, float))))


def wrap_period(x):
    """Return 360 or 2 pi when a channel wraps (two jumps over half its range), else None."""
    x = np.asarray(x, float)
    if len(x) < 10 or not np.all(np.isfinite(x)):
        return None
    rng = float(np.ptp(x))
    d = np.abs(np.diff(x))
    jumps = int(np.sum(d > 0.5 * rng))
    if jumps < 2 or np.median(d) > 0.05 * rng:
        return None
    for period in (360.0, 2.0 * math.pi):
        if 0.8 * period <= rng <= 1.001 * period:
            return period
    return None


def channel_values(data, name, j):
    """(N,) values of channel ``name`` for sensor ``j`` (temperature: the sensor's own)."""
    if name == 'temperature':
        return data.temp[j - 1]
    return data.aux[name]


def channels_of(data):
    """Return the names of the channels the record holds that vary: temperature, aux_*."""
    temp = data.temp is not None and all(usable(data.temp[j]) for j in range(data.n_sensors))
    return (['temperature'] if temp else []) + [n for n in sorted(data.aux) if usable(data.aux[n])]


def _driver(text, kind, channel, ctx_of, note='', q=()):
    """Return a :class:`Driver` whose columns are the grammar's (:func:`grammar_columns`)."""
    return Driver(text, kind, channel, lambda j: grammar_columns(text, ctx_of(j), q), note=note)


def time_drivers(t, steps=(), windows=(), lines=()):
    """Return polynomials and smooths in time, steps and windows (s), sinusoids at lines (Hz)."""
    ctx = SensorContext(t=np.asarray(t, float))
    n = len(ctx.t)

    def drv(text, note=''):
        return _driver(text, 'time', 't', lambda j: ctx, note)
    out = [drv(f'poly(t, {d})') for d in (1, 2, 3)]
    out += [drv(f's(t, k={k})') for k in SMOOTH_K if n >= MIN_SAMPLES_PER_K * k]
    out += [drv(f'step({", ".join(format_arg(x) for x in ts)})', 'change point') for ts in steps]
    out += [drv(f'window({format_arg(a)}, {format_arg(b)})', 'change points') for a, b in windows]
    out += [drv(f'sin({format_arg(f)})', 'spectral line') for f in lines]
    return out


def channel_drivers(data, name):
    """Drivers of one channel: linear, polynomial (2, 3), cyclic when it wraps, lags."""
    period = wrap_period(channel_values(data, name, 1))
    if period is not None:
        p_txt = '' if period == 360.0 else f', period={format_arg(period)}'
        return [_driver(f'cc({name}, k={k}{p_txt})', 'channel', name, data.context)
                for k in CYCLIC_K]
    out = [_driver(t, 'channel', name, data.context)
           for t in (name, f'poly({name}, 2)', f'poly({name}, 3)')]
    out += [_driver(f'lag({name})', 'channel', name, data.context, f'tau={format_arg(tau)}', [tau])
            for tau in lag_grid(data.t, LAG_POINTS, *LAG_FRACTIONS)]
    return out


def product_drivers(data, names):
    """Products of two linear channels (and of each channel with time)."""
    lin = list(names) + ['t']
    wraps = {a for a in names if wrap_period(channel_values(data, a, 1)) is not None}
    return [_driver(f'{a} * {b}', 'product', a if b == 't' else f'{a}*{b}', data.context)
            for i, a in enumerate(lin) for b in lin[i + 1:] if not {a, b} & wraps]


def rate_driver(data):
    """Return the field rate driver, dB/dt of the raw reading per axis (a timing skew)."""
    from magcal_ros.core.effects import raw_rate
    return Driver('rate', 'rate', 'rate',
                  lambda j: centred(raw_rate(data.raw[j - 1], data.t)), per_axis=True)
