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

A :class:`Driver` is one factor of the model formula (docs/formulas.md, FORMULA syntax:
``s(t, k=8)``, ``cc(aux_wheel_angle, k=2)``, ``lag(aux_relay)``, ``poly(temperature, 2)``,
``sin(0.0112)``, ``step(300)``, ``window(120, 160)``, ``temperature * t``, ``rate``) with its
design columns X (N, m) on the tested epochs, centred, so that the search can score it
without building a model.  :func:`drivers_of` lists them from the record: its length and
sampling (smooth bases in time with a number of basis functions up to one per ~10 samples
of the shortest feature worth describing), the change points and spectral lines of the
base residual, each channel (its range; a channel that wraps gets a cyclic basis), the
first-order lag of each channel on a grid of time constants, and products of two channels.

The columns span the same space as the formula's driver (the grammar's own basis may differ
by an invertible map, which changes no fit); the term adopted is refitted by the grammar.
"""
from dataclasses import dataclass, field
import math

from magcal_ros.core.effects import first_order_lag
import numpy as np

#: numbers of basis functions of the smooth in time the search tries (the grammar's s()
#: takes 3..20; capped by the record)
SMOOTH_K = (4, 8, 12, 20)
#: fewest samples per basis function of a smooth in time
MIN_SAMPLES_PER_K = 25
#: time constants of a lag, as fractions of the record (log-spaced grid), plus 1-4 samples
LAG_FRACTIONS = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)
#: harmonics of a cyclic smooth
CYCLIC_K = (1, 2, 3)


@dataclass
class Driver:
    """
    One driver of the formula and its design columns.

    Attributes
    ----------
    text : str
        The formula factor, e.g. 's(t, k=8)' or 'lag(aux_relay)'.
    kind : str
        'time', 'channel', 'product' or 'rate' (what it follows, for the description).
    channel : str
        The channel it reads ('t' for time, 'temperature', 'aux_<name>', 'rate').
    columns : callable
        columns(j) -> (N, m) design of sensor j (1-based) on the tested epochs, centred;
        per-axis drivers (rate) return (N, 3) with per_axis True.
    per_axis : bool
        The driver acts axis by axis (dB_i = P_i X_i): offset coupling only.
    note : str
        What it was built from (a change point, a spectral line, ...).

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
    x = np.asarray(x, float)
    x = x[:, None] if x.ndim == 1 else x
    return x - x.mean(axis=0)


def spline_basis(t, k):
    """
    (N, k) cubic regression-spline basis ``s(t, k=K)`` over t, centred.

    As the grammar's ``s`` (magcal_ros.core.effects.drivers.Spline): k + 1 cubic B-splines
    (scipy.interpolate.BSpline.design_matrix) on equally spaced knots over the record, the
    first dropped (they sum to one: the constant is the model's offset).
    """
    from scipy.interpolate import BSpline
    t = np.asarray(t, float)
    lo, hi = float(t[0]), float(t[-1])
    inner = np.linspace(lo, hi, k + 1 - 3 + 1)
    knots = np.concatenate([[lo] * 3, inner, [hi] * 3])
    x = BSpline.design_matrix(np.clip(t, lo, hi), knots, 3).toarray()
    return centred(x[:, 1:])


def legendre_basis(x, degree):
    """(N, degree) Legendre polynomials 1..degree of ``x`` scaled to [-1, 1], centred."""
    x = np.asarray(x, float)
    lo, hi = float(np.min(x)), float(np.max(x))
    u = 2.0 * (x - lo) / (hi - lo) - 1.0 if hi > lo else np.zeros_like(x)
    cols = [np.polynomial.legendre.legval(u, [0] * d + [1]) for d in range(1, degree + 1)]
    return centred(np.stack(cols, axis=1))


def wrap_period(x):
    """
    Return the period of a channel that wraps (an angle), or None.

    A wrapped angle jumps by about its whole range between two samples several times while
    moving smoothly otherwise: at least two jumps larger than half the range, with the range
    close to 360 (degrees) or 2 pi (radians).
    """
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


def cyclic_basis(x, k, period):
    """(N, 2k) Fourier harmonics 1..k of a wrapped channel of ``period``, centred."""
    ph = 2.0 * math.pi * np.asarray(x, float) / period
    cols = []
    for h in range(1, k + 1):
        cols += [np.cos(h * ph), np.sin(h * ph)]
    return centred(np.stack(cols, axis=1))


def fmt(v):
    """Short decimal text of a number in a formula ('300', '0.0112')."""
    return f'{float(v):.6g}'


def channel_values(data, name, j):
    """(N,) values of channel ``name`` for sensor ``j`` (temperature: the sensor's own)."""
    if name == 'temperature':
        return data.temp[j - 1]
    return data.aux[name]


def _usable(x):
    x = np.asarray(x, float)
    return bool(np.all(np.isfinite(x)) and np.ptp(x) > 0)


def channels_of(data):
    """Return the names of the channels the record holds that vary: temperature, aux_*."""
    out = []
    if data.temp is not None and all(_usable(data.temp[j]) for j in range(data.n_sensors)):
        out.append('temperature')
    out += [n for n in sorted(data.aux) if _usable(data.aux[n])]
    return out


def time_drivers(t, steps=(), windows=(), lines=()):
    """
    Return the drivers in time.

    Smooths with 4 to 20 basis functions (at least 25 samples each), polynomials of degree
    1-3, the steps and windows at the change points given (s) and sinusoids at the lines
    (Hz).
    """
    t = np.asarray(t, float)
    n = len(t)
    out = []
    for d in (1, 2, 3):
        out.append(Driver(f'poly(t, {d})', 'time', 't',
                          lambda j, d=d: legendre_basis(t, d)))
    for k in SMOOTH_K:
        if n >= MIN_SAMPLES_PER_K * k:
            out.append(Driver(f's(t, k={k})', 'time', 't', lambda j, k=k: spline_basis(t, k)))
    for ts in steps:
        ts = tuple(ts)
        txt = ', '.join(fmt(x) for x in ts)
        out.append(Driver(f'step({txt})', 'time', 't',
                          lambda j, ts=ts: centred(np.stack([t >= x for x in ts], 1)),
                          note='change point'))
    for a, b in windows:
        out.append(Driver(f'window({fmt(a)}, {fmt(b)})', 'time', 't',
                          lambda j, a=a, b=b: centred((t >= a) & (t <= b)),
                          note='change points'))
    for f in lines:
        out.append(Driver(f'sin({fmt(f)})', 'time', 't',
                          lambda j, f=f: centred(np.stack([np.cos(2 * np.pi * f * t),
                                                           np.sin(2 * np.pi * f * t)], 1)),
                          note='spectral line'))
    return out


def channel_drivers(data, name):
    """Drivers of one channel: linear, polynomial (2, 3), cyclic when it wraps, lags."""
    t = data.t
    span = float(t[-1] - t[0])
    dt = float(np.median(np.diff(t)))

    def val(j):
        return channel_values(data, name, j)
    period = wrap_period(val(1))
    out = []
    if period is not None:
        p_txt = '' if period == 360.0 else f', period={fmt(period)}'
        for k in CYCLIC_K:
            out.append(Driver(f'cc({name}, k={k}{p_txt})', 'channel', name,
                              lambda j, k=k: cyclic_basis(val(j), k, period)))
        return out
    out.append(Driver(name, 'channel', name, lambda j: centred(val(j))))
    for d in (2, 3):
        out.append(Driver(f'poly({name}, {d})', 'channel', name,
                          lambda j, d=d: legendre_basis(val(j), d)))
    taus = sorted({max(dt, f * span) for f in LAG_FRACTIONS})
    for tau in taus:
        out.append(Driver(f'lag({name})', 'channel', name,
                          lambda j, tau=tau: centred(first_order_lag(t, val(j), tau)),
                          note=f'tau={fmt(tau)}'))
    return out


def product_drivers(data, names):
    """Products of two linear channels (and of each channel with time)."""
    t = data.t
    out = []
    lin = list(names) + ['t']

    def val(name, j):
        return t if name == 't' else channel_values(data, name, j)
    for i, a in enumerate(lin):
        for b in lin[i + 1:]:
            if a != 't' and wrap_period(val(a, 1)) is not None:
                continue
            if b != 't' and wrap_period(val(b, 1)) is not None:
                continue
            out.append(Driver(f'{a} * {b}', 'product', a if b == 't' else f'{a}*{b}',
                              lambda j, a=a, b=b: centred(
                                  centred(val(a, j))[:, 0] * centred(val(b, j))[:, 0])))
    return out


def rate_driver(data):
    """Return the field rate driver, dB/dt of the raw reading per axis (a timing skew)."""
    from magcal_ros.core.effects import raw_rate
    return Driver('rate', 'rate', 'rate',
                  lambda j: centred(raw_rate(data.raw[j - 1], data.t)), per_axis=True)
