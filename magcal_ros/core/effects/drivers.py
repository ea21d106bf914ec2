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
Drivers: what an effect follows, as a basis of columns X (docs/formulas.md has the table).

A driver turns the signals of a sensor (:class:`~.base.SensorContext`) into columns X:
(N, m) for a scalar driver, (N, 3, m) for a per-axis one (``rate``, ``lin``), in
:attr:`Driver.unit`.  Its reference values (a mean, a range, a start time) are stored in the
effect's ``refs`` by :meth:`Driver.prepare`, so that live correction uses the same.
"""
import math

from magcal_ros.core.effects.base import (cached, first_order_lag, format_arg, lag_step,
                                          NONLINEARITY_FULL_SCALE_NT, parse_number, Registry,
                                          split_params)
import numpy as np

#: variables a driver may read: name -> (unit, per axis)
VARIABLES = {'t': ('s', False), 'temperature': ('degC', False), 'rate': ('nT/s', True),
             'lin': ('1', True)}
#: the signal (``SensorContext.has``, the live corrector's subscriptions) of each variable
VARIABLE_SIGNALS = {'t': ('time',), 'temperature': ('temperature',),
                    'rate': ('field_rate',), 'lin': ()}


class FormulaError(ValueError):
    """A model formula that cannot be used; the message names the bad part."""


def variable_name(text):
    """Return the canonical variable of ``text`` (t, temperature, aux_<name>, rate, lin)."""
    v = str(text).strip()
    v = {'time': 't', 'temp': 'temperature'}.get(v, v)
    if v.startswith('aux:'):
        v = 'aux_' + v[4:]
    if v in VARIABLES or (v.startswith('aux_') and len(v) > 4 and v[4:].replace('_', 'a')
                          .isalnum()):
        return v
    raise FormulaError(f'unknown variable {text!r}: a driver reads t, temperature, '
                       'aux_<channel>, rate (dB/dt) or lin (the linear reading)')


def variable_values(ctx, v, lin=None):
    """(N,) or (N, 3) values of variable ``v`` in ``ctx`` (None if absent)."""
    if v == 'lin':
        return None if lin is None else lin / NONLINEARITY_FULL_SCALE_NT
    attr = {'t': 't', 'temperature': 'temp', 'rate': 'raw_rate'}.get(v)
    return getattr(ctx, attr) if attr else ctx.aux.get(v)


def _new(cls, args, kwargs, allowed, n_args, example):
    """Return a bare ``cls()`` once the options are ``allowed`` and ``n_args`` are given."""
    bad = sorted(set(kwargs) - set(allowed))
    if bad:
        raise FormulaError(f'unknown option {bad[0]}= in {cls.usage}: allowed '
                           f'{", ".join(a + "=" for a in allowed) or "none"}')
    if (not args) if n_args is None else len(args) != n_args:
        raise FormulaError(f'{example}; usage {cls.usage}')
    return cls()


def _positive(text, what, name):
    """Return the number ``text``, which must be positive (``name`` in the error)."""
    v = parse_number(text, what)
    if v <= 0:
        raise FormulaError(f'{name} must be positive, got {text!r}')
    return v


def _count(text, what, lo, hi):
    v = parse_number(text, what)
    if v != int(v) or not lo <= v <= hi:
        raise FormulaError(f'{what} must be a whole number {lo}..{hi}, got {text!r}')
    return int(v)


class Driver:
    """
    Base class of a driver factor (a plug-in subclasses it and calls :func:`register_driver`).

    Subclasses set ``name`` (written ``name(...)``), ``usage`` and implement
    :meth:`from_args`, :attr:`text`, :attr:`column_names`, :meth:`columns`.
    """

    name = 'driver'
    usage = 'driver(...)'
    #: True when the columns are per axis, (N, 3, m)
    per_axis = False
    #: True when the columns read the sensor's linear reading (fixed-point correction)
    reads_lin = False
    #: the driver's own parameters (a lag's time constant), names and units
    param_names = ()
    units = ()
    #: canonical text of the factor, and the names of its m columns (parameter names)
    text = None
    column_names = ()
    #: unit of every column (the coupling's parameters are per this unit)
    unit = '1'
    #: driving signals read (keys of base.SIGNALS or aux_<name>)
    signals = ()

    @classmethod
    def from_args(cls, args, kwargs):
        """Make the factor ``name(args, key=value)``; ``args`` and values are strings."""
        raise NotImplementedError

    def default_params(self):
        """(n,) starting values of the driver's own parameters."""
        return np.zeros(len(self.param_names))

    def prepare(self, ctx, refs, prefix=''):
        """Store reference values computed from the calibration data ``ctx`` in ``refs``."""

    def check(self, ctx, sensor):
        """Return None if the data can excite the factor, else the reason why not."""
        return None

    def columns(self, ctx, lin, refs, q, prefix=''):
        """(N, m) or (N, 3, m) columns at ``ctx`` (``lin`` (N, 3) nT; ``q`` own params)."""
        raise NotImplementedError

    def __eq__(self, other):
        return type(self) is type(other) and self.text == other.text

    def __hash__(self):
        return hash(self.text)

    def __repr__(self):
        return self.text


class _OfVariable(Driver):
    """A factor of one variable ``v`` (the variable itself, s, cc, poly, lag)."""

    def _var(self, text):
        v = variable_name(text)
        if VARIABLES.get(v, ('', False))[1]:
            raise FormulaError(f'{self.name}({v}, ...) needs a scalar variable (t, '
                               f'temperature, aux_<name>); {v} is per axis')
        return v

    @property
    def signals(self):
        return VARIABLE_SIGNALS.get(self.v, (self.v,))

    def check(self, ctx, sensor):
        """Return None if the variable is present and varies in ``ctx``, else why not."""
        v = self.v
        if v == 'lin':
            return None
        a = variable_values(ctx, v)
        if a is None or not np.isfinite(a).any():
            if v.startswith('aux_'):
                return f'no auxiliary column {v!r} in the data (have: {sorted(ctx.aux) or "none"})'
            col = {'temperature': f's{sensor}_temp', 't': 't', 'rate': 't'}.get(v, v)
            return f'sensor {sensor}: no {v} in the data (column {col})'
        a = np.asarray(a, float)
        if np.nanmax(a) - np.nanmin(a) <= 1e-9 * max(1.0, float(np.nanmax(np.abs(a)))):
            return f'{v!r} never changes: its coupling cannot be separated from the offset'
        return None

    def _values(self, ctx, refs, prefix):
        a = variable_values(ctx, self.v)
        if a is None:
            raise ValueError(f'no {self.v} in the data')
        return np.nan_to_num(np.asarray(a, float), nan=refs.get(prefix + 'mean', 0.0))

    def _range(self, ctx, refs, prefix):
        a = variable_values(ctx, self.v)
        if a is not None and np.isfinite(a).any():
            refs.setdefault(prefix + 'lo', float(np.nanmin(a)))
            refs.setdefault(prefix + 'hi', float(np.nanmax(a)))
            refs.setdefault(prefix + 'mean', float(np.nanmean(a)))

    def _centre(self, x, ctx, refs, prefix):
        """Subtract the calibration means of the columns (stored at the first call)."""
        names = [prefix + f'm{k + 1}' for k in range(x.shape[1])]
        if names[0] not in refs:
            refs.update(zip(names, map(float, x.mean(axis=0))))
        return x - np.array([refs[nm] for nm in names])


class Variable(_OfVariable):
    """A variable itself: t, temperature, aux_<name> centred on its mean; rate, lin per axis."""

    name = 'v'
    usage = 't | temperature | aux_<name> | rate | lin'

    def __init__(self, v):
        self.v = variable_name(v)
        self.per_axis = VARIABLES.get(self.v, ('', False))[1]
        self.reads_lin = self.v == 'lin'
        self.text, self.column_names = self.v, (self.v,)
        self.unit = VARIABLES.get(self.v, ('unit', False))[0]

    def prepare(self, ctx, refs, prefix=''):
        if not self.per_axis:                   # rate and lin: their zero is physical
            a = variable_values(ctx, self.v)
            if a is not None and np.isfinite(a).any():
                refs.setdefault(prefix + self.v + '0', float(np.nanmean(a)))

    def columns(self, ctx, lin, refs, q, prefix=''):
        a = variable_values(ctx, self.v, lin)
        if a is None:
            raise ValueError(f'no {self.v} in the data')
        if self.per_axis:
            return np.asarray(a, float)[:, :, None]
        x0 = refs.get(prefix + self.v + '0', 0.0)
        return (np.nan_to_num(np.asarray(a, float), nan=x0) - x0)[:, None]


class Constant(Driver):
    """The constant 1: ``offset(1)`` is the plain offset."""

    name = '1'
    usage = '1'
    text = '1'
    column_names = ('1',)

    def columns(self, ctx, lin, refs, q, prefix=''):
        return np.ones((len(ctx.t), 1))


class Spline(_OfVariable):
    """
    ``s(v, k=K)``: a smooth function of v, K cubic B-spline columns, centred.

    K + 1 cubic B-splines on equal knots over v's calibration range [lo, hi] (mgcv's
    ``s(v, k=K, bs='bs')``, Wood 2017 ch. 5), the first dropped (they sum to one: collinear
    with the offset); outside [lo, hi] v is held at the nearer end.
    """

    name = 's'
    usage = 's(<v>, k=<3..20>)'

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, ('k',), 1, 's takes one variable and k=, e.g. s(t, k=6)')
        d.v = d._var(args[0])
        d.k = _count(kwargs.get('k', '5'), 's(..., k=K) basis size', 3, 20)
        d.text, d.column_names = f's({d.v}, k={d.k})', tuple(f's{i + 1}' for i in range(d.k))
        return d

    def prepare(self, ctx, refs, prefix=''):
        self._range(ctx, refs, prefix)
        self.columns(ctx, None, refs, (), prefix)        # stores the column means

    def basis(self, x, lo, hi):
        """(N, k) the uncentred columns at x (N,)."""
        from scipy.interpolate import BSpline
        n_basis, deg = self.k + 1, 3
        inner = np.linspace(lo, hi, n_basis - deg + 1)
        knots = np.concatenate([[lo] * deg, inner, [hi] * deg])
        xc = np.clip(x, lo, hi)
        dm = BSpline.design_matrix(xc, knots, deg, extrapolate=False).toarray()
        return dm[:, 1:]

    def columns(self, ctx, lin, refs, q, prefix=''):
        lo, hi = refs.get(prefix + 'lo', 0.0), refs.get(prefix + 'hi', 1.0)
        if not hi > lo:
            hi = lo + 1.0
        return self._centre(self.basis(self._values(ctx, refs, prefix), lo, hi), ctx, refs,
                            prefix)


class Cyclic(_OfVariable):
    """
    ``cc(v, k=K[, period=P])``: a periodic function of a v that wraps (an angle).

    cos and sin of 2 pi h v / P, harmonics h = 1..K (2K columns), centred.  Without
    ``period`` it is 2 pi when the calibration range of v lies within 2 pi (radians), 360
    within 360 (degrees), else the range itself.
    """

    name = 'cc'
    usage = 'cc(<v>, k=<1..10>[, period=<P>])'

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, ('k', 'period'), 1,
                 'cc takes one variable, e.g. cc(aux_wheel_angle, k=2)')
        d.v = d._var(args[0])
        d.k = _count(kwargs.get('k', '2'), 'cc(..., k=K) harmonics', 1, 10)
        d.period = (_positive(kwargs['period'], 'cc period', 'cc period')
                    if 'period' in kwargs else None)
        per = '' if d.period is None else f', period={format_arg(d.period)}'
        d.text = f'cc({d.v}, k={d.k}{per})'
        d.column_names = tuple(f'{c}{h}' for h in range(1, d.k + 1) for c in ('c', 's'))
        return d

    def prepare(self, ctx, refs, prefix=''):
        self._range(ctx, refs, prefix)
        span = refs.get(prefix + 'hi', 1.0) - refs.get(prefix + 'lo', 0.0)
        per = 2 * math.pi if span <= 2 * math.pi * 1.001 else (
            360.0 if span <= 360.0 * 1.001 else span)
        refs.setdefault(prefix + 'period', per if self.period is None else float(self.period))
        self.columns(ctx, None, refs, (), prefix)

    def columns(self, ctx, lin, refs, q, prefix=''):
        ph = (2 * math.pi / refs.get(prefix + 'period', 2 * math.pi)) * self._values(
            ctx, refs, prefix)
        cols = [f(h * ph) for h in range(1, self.k + 1) for f in (np.cos, np.sin)]
        return self._centre(np.stack(cols, axis=1), ctx, refs, prefix)


class Poly(_OfVariable):
    """
    ``poly(v, D)``: u, u^2, .., u^D with u = (v - v0) / h (v0 the mean, h the half range).

    Per-axis variables (``lin``) are not centred or scaled: u = lin / 50 000 nT per axis.
    """

    name = 'poly'
    usage = 'poly(<v>, <degree 1..4>)'

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, (), 2, 'poly takes a variable and a degree, e.g. poly(t, 2)')
        d.v = variable_name(args[0])
        d.per_axis = VARIABLES.get(d.v, ('', False))[1]
        d.reads_lin = d.v == 'lin'
        d.degree = _count(args[1], 'poly degree', 1, 4)
        d.text = f'poly({d.v}, {d.degree})'
        d.column_names = tuple(f'p{i}' for i in range(1, d.degree + 1))
        return d

    def prepare(self, ctx, refs, prefix=''):
        if not self.per_axis:
            self._range(ctx, refs, prefix)

    def columns(self, ctx, lin, refs, q, prefix=''):
        if self.per_axis:
            u = variable_values(ctx, self.v, lin)
        else:
            h = 0.5 * (refs.get(prefix + 'hi', 1.0) - refs.get(prefix + 'lo', -1.0)) or 1.0
            u = (self._values(ctx, refs, prefix) - refs.get(prefix + 'mean', 0.0)) / h
        return np.stack([u ** d for d in range(1, self.degree + 1)], axis=-1)


class Sinusoid(Driver):
    """
    ``sin(F[, refine=true])``: cos and sin of 2 pi F (t - t0), F in Hz, t0 the first time.

    With ``refine=true`` the frequency is F + df, df (Hz) fitted from 0 (F must lie within
    about 1 / (4 span) of the line).
    """

    name = 'sin'
    usage = 'sin(<f_hz>[, refine=true])'
    signals = ('time',)
    column_names = ('cos', 'sin')

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, ('refine',), 1,
                 'sin takes one frequency in Hz, e.g. sin(0.23)')
        d.freq_hz = _positive(args[0], 'sin frequency [Hz]', 'sin frequency')
        refine = kwargs.get('refine', 'false').lower()
        if refine not in ('true', 'false'):
            raise FormulaError(f'sin(..., refine=...) is true or false, got {refine!r}')
        d.refine = refine == 'true'
        d.param_names, d.units = (('df',), ('Hz',)) if d.refine else ((), ())
        d.text = f'sin({format_arg(d.freq_hz)}' + (', refine=true)' if d.refine else ')')
        return d

    def prepare(self, ctx, refs, prefix=''):
        refs.setdefault(prefix + 't0', float(ctx.t[0]) if len(ctx.t) else 0.0)

    def check(self, ctx, sensor):
        span = float(ctx.t[-1] - ctx.t[0]) if len(ctx.t) > 1 else 0.0
        if span * self.freq_hz < 2.0:
            return (f'the data span {span:.1f} s, less than 2 periods of {self.freq_hz:g} Hz: '
                    'the sinusoid cannot be separated from the offset')
        dt = float(np.median(np.diff(ctx.t)))
        if self.freq_hz >= 0.5 / dt:
            return (f'{self.freq_hz:g} Hz is at or above the Nyquist frequency '
                    f'{0.5 / dt:g} Hz of the data')
        return None

    def columns(self, ctx, lin, refs, q, prefix=''):
        f = self.freq_hz + (float(q[0]) if self.refine else 0.0)
        ph = (2 * math.pi * f) * (ctx.t - refs.get(prefix + 't0', 0.0))
        return np.stack([np.cos(ph), np.sin(ph)], axis=1)


class Steps(Driver):
    """``step(T, ...)``: Heaviside steps [t >= T_k] at times T_k s (one column each)."""

    name = 'step'
    usage = 'step(<t_s>[, <t_s>...])'
    signals = ('time',)

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, (), None, 'step needs at least one time in s, e.g. step(300)')
        d.times = tuple(sorted(parse_number(a, 'step time [s]') for a in args))
        d.text = f'step({", ".join(format_arg(x) for x in d.times)})'
        d.column_names = ('step',) if len(d.times) == 1 else tuple(
            f'step{i + 1}' for i in range(len(d.times)))
        return d

    def check(self, ctx, sensor):
        t = ctx.t
        for tk in self.times:
            before = int(np.sum(t < tk))
            if before < 3 or len(t) - before < 3:
                return f'step at t = {tk:g} s lies outside the data ({t[0]:g} .. {t[-1]:g} s)'
        return None

    def columns(self, ctx, lin, refs, q, prefix=''):
        return (ctx.t[:, None] >= np.array(self.times)[None, :]).astype(float)


class Window(Driver):
    """``window(T0, T1)``: a boxcar in time, 1 inside [T0, T1] s, 0 outside."""

    name = 'window'
    usage = 'window(<t0_s>, <t1_s>)'
    signals = ('time',)
    column_names = ('win',)

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, (), 2, 'window takes two times in s, e.g. window(120, 160)')
        d.t0, d.t1 = (parse_number(a, 'window time [s]') for a in args)
        if not d.t1 > d.t0:
            raise FormulaError(f'window({args[0]}, {args[1]}): the end must follow the start')
        d.text = f'window({format_arg(d.t0)}, {format_arg(d.t1)})'
        return d

    def check(self, ctx, sensor):
        inside = int(np.sum((ctx.t >= self.t0) & (ctx.t <= self.t1)))
        if inside < 3 or len(ctx.t) - inside < 3:
            return (f'window {self.t0:g} .. {self.t1:g} s holds {inside} of {len(ctx.t)} '
                    'samples: it cannot be separated from the offset')
        return None

    def columns(self, ctx, lin, refs, q, prefix=''):
        return ((ctx.t >= self.t0) & (ctx.t <= self.t1)).astype(float)[:, None]


class Lagged(_OfVariable):
    """
    ``lag(v[, tau=S])``: v through a first-order lag, tau dy/dt = v - y, centred on v's mean.

    Without ``tau`` the time constant is fitted (s, from 30 s).  The filter
    (:func:`~.base.first_order_lag`) runs over the whole record (``SensorContext.whole``), so
    held-out blocks keep its state; live correction takes its steps (:func:`~.base.lag_step`).
    """

    name = 'lag'
    usage = 'lag(<v>[, tau=<s>])'
    tau0_s = 30.0
    column_names = ('lag',)

    @classmethod
    def from_args(cls, args, kwargs):
        d = _new(cls, args, kwargs, ('tau',), 1, 'lag takes one variable, e.g. lag(temperature)')
        d.v = d._var(args[0])
        d.tau = _positive(kwargs['tau'], 'lag tau [s]', 'lag tau') if 'tau' in kwargs else None
        d.param_names, d.units = ((), ()) if d.tau is not None else (('tau',), ('s',))
        d.text = f'lag({d.v}' + ('' if d.tau is None else f', tau={format_arg(d.tau)}') + ')'
        d.unit = VARIABLES.get(d.v, ('unit', False))[0]
        return d

    @property
    def signals(self):
        return tuple(dict.fromkeys(('time',) + VARIABLE_SIGNALS.get(self.v, (self.v,))))

    def default_params(self):
        return np.array([self.tau0_s]) if self.tau is None else np.zeros(0)

    def prepare(self, ctx, refs, prefix=''):
        self._range(ctx, refs, prefix)

    def columns(self, ctx, lin, refs, q, prefix=''):
        tau = self.tau if self.tau is not None else float(q[0])
        x0 = refs.get(prefix + 'mean', 0.0)
        whole, idx = ctx.whole()
        if idx is None and len(ctx.t) == 1:
            return (self._online(float(ctx.t[0]), variable_values(ctx, self.v), tau, x0)
                    - x0)[:, None]
        x = variable_values(whole, self.v)
        y = cached(self.__dict__.setdefault('_cache', {}), (id(x), len(x), float(tau), x0), x,
                   lambda: first_order_lag(whole.t, np.nan_to_num(np.asarray(x, float), nan=x0),
                                           tau), 4)
        y = y if idx is None else y[idx]
        return (y - x0)[:, None]

    def _online(self, t, x, tau, x0):
        """One sample of the live correction: :func:`~.base.lag_step`, the batch filter's step."""
        x = float(x0 if x is None or not np.isfinite(x[0]) else x[0])
        self._state, y = lag_step(self.__dict__.get('_state'), t, x, tau)
        return np.array([y])


class Product(Driver):
    """``a * b * ...``: the tensor product of the factors' columns (row by row)."""

    name = '*'
    usage = '<factor> * <factor>'

    def __init__(self, factors):
        self.factors = list(factors)
        self.per_axis = any(f.per_axis for f in self.factors)
        self.reads_lin = any(f.reads_lin for f in self.factors)
        self.param_names = tuple(f'{p}{i + 1}' for i, f in enumerate(self.factors)
                                 for p in f.param_names)
        self.units = tuple(u for f in self.factors for u in f.units)
        self.text = ' * '.join(f.text for f in self.factors)
        self.column_names = ('',)
        for f in self.factors:
            self.column_names = tuple(f'{a}*{b}' if a else b for a in self.column_names
                                      for b in f.column_names)
        self.unit = '*'.join(f.unit for f in self.factors if f.unit != '1') or '1'
        self.signals = tuple(dict.fromkeys(s for f in self.factors for s in f.signals))

    def default_params(self):
        return np.concatenate([f.default_params() for f in self.factors] + [np.zeros(0)])

    def prepare(self, ctx, refs, prefix=''):
        for i, f in enumerate(self.factors):
            f.prepare(ctx, refs, f'{prefix}{i + 1}.')

    def check(self, ctx, sensor):
        return next(filter(None, (f.check(ctx, sensor) for f in self.factors)), None)

    def columns(self, ctx, lin, refs, q, prefix=''):
        out = None
        sizes = [len(f.param_names) for f in self.factors]
        for i, (f, qf) in enumerate(zip(self.factors, split_params(q, sizes))):
            x = f.columns(ctx, lin, refs, qf, f'{prefix}{i + 1}.')
            if x.ndim == 2 and self.per_axis:
                x = np.broadcast_to(x[:, None, :], (x.shape[0], 3, x.shape[1]))
            out = x if out is None else (out[..., :, None] * x[..., None, :]).reshape(
                *x.shape[:-1], -1)
        return out


#: the factors ``name(...)`` of a driver by name, those that ship first (docs/plugins.md)
DRIVERS = Registry(Driver, 'driver', 'magcal_ros.core.effects.drivers.Driver',
                   (Spline, Cyclic, Poly, Sinusoid, Steps, Window, Lagged))
register_driver = DRIVERS.register
unregister_driver = DRIVERS.unregister
driver_class = DRIVERS.get
registered_drivers = DRIVERS.names
