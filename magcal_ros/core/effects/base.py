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
The foundation of every effect: :class:`Effect`, :class:`SensorContext`, :class:`LinearParts`.

Every sensor j of an array is described by the forward model

    raw_j = A_j @ B + offset_j + sum_k d_k(context, lin_j) + noise,     lin_j = A_j @ B

with ``B`` (nT) the true field in the array frame, ``A_j`` the product of the *linear*
effects (paper 004 eq. 2-3) and ``d_k`` the *additive* effects.  Also paper 004's rotations,
the signal helpers every effect shares and the :class:`Registry` of named classes.
"""
from dataclasses import dataclass, field
import math

import numpy as np


#: Full-scale field used to normalise the nonlinearity polynomial (nT).
NONLINEARITY_FULL_SCALE_NT = 50000.0

#: Driving signals an effect may declare in :attr:`Effect.signals`, and the
#: :class:`SensorContext` attribute that holds each; auxiliary channels are named by their
#: column, ``aux_<name>`` (held in ``SensorContext.aux``).
SIGNALS = {'time': 't', 'temperature': 'temp', 'field_rate': 'raw_rate',
           'attitude': 'attitude'}


@dataclass(frozen=True)
class LinearParts:
    """
    A closed-form linear map and offset of one sensor, decomposed (paper 004 eq. 2-3).

    ``a = u @ q`` (RQ decomposition, each (3, 3)) with ``u`` upper triangular with a
    positive diagonal (scale and non-orthogonality) and ``q`` a proper rotation
    (misalignment); ``scale`` (3,) the row norms of ``u``, ``nonorth`` (psi, varphi, theta)
    of C_NO in rad, ``offset`` (3,) nT.
    """

    a: np.ndarray
    u: np.ndarray
    q: np.ndarray
    scale: np.ndarray
    nonorth: tuple
    offset: np.ndarray


def decompose_linear(a, offset):
    """:class:`LinearParts` of the (3, 3) map ``a`` and the (3,) nT ``offset``."""
    a = np.asarray(a, float)
    u, q = rq_positive(a)
    k, psi, varphi, theta = upper_to_scale_nonorth(u)
    return LinearParts(a=a, u=u, q=q, scale=k, nonorth=(psi, varphi, theta),
                       offset=np.asarray(offset, float))


def rq_positive(a):
    """
    RQ decomposition a = u @ q of a (3, 3) matrix with det(a) > 0 (paper 004 eq. 2-3).

    ``u`` (3, 3) upper triangular with a positive diagonal, ``q`` (3, 3) a proper rotation.
    """
    from scipy.linalg import rq          # here: scipy.linalg is slow to import
    u, q = rq(np.asarray(a, float))
    sign = np.sign(np.diag(u))
    u, q = u * sign[None, :], sign[:, None] * q
    if np.linalg.det(q) < 0:
        u, q = -u, -q
    return u, q


@dataclass
class SensorContext:
    """Driving signals seen by one sensor."""

    #: (N,) time in s
    t: np.ndarray
    #: (N,) sensor temperature in degC
    temp: np.ndarray | None = None
    #: auxiliary channels, each (N,), in the channel's own unit (A, W, ...)
    aux: dict = field(default_factory=dict)
    #: (N, 3) time derivative of the raw reading, nT/s
    raw_rate: np.ndarray | None = None
    #: the whole record this context was cut from (:meth:`subset`; a lag filter runs over it)
    parent: 'SensorContext | None' = None
    #: (N,) int, positions of these samples in ``parent``
    index: np.ndarray | None = None
    #: (N, 3, 3) body-to-world rotations of the array, or None when unknown
    attitude: np.ndarray | None = None

    def has(self, signal):
        """Tell whether the driving signal ``signal`` (see :data:`SIGNALS`) is present."""
        if signal.startswith('aux_'):
            return signal in self.aux
        if signal not in SIGNALS:
            raise ValueError(f'unknown signal {signal!r}: known signals are '
                             f'{", ".join(SIGNALS)} and aux_<column>')
        value = getattr(self, SIGNALS[signal])
        return value is not None and bool(np.isfinite(value).any())

    def subset(self, idx):
        """Return the context restricted to samples ``idx`` (remembering the whole record)."""
        pos = np.arange(len(self.t))[idx]
        root = self if self.parent is None else self.parent
        return SensorContext(
            t=self.t[idx], temp=None if self.temp is None else self.temp[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            raw_rate=None if self.raw_rate is None else self.raw_rate[idx],
            attitude=None if self.attitude is None else self.attitude[idx],
            parent=root, index=pos if self.index is None else self.index[pos])

    def whole(self):
        """(context of the whole record, (N,) int positions of these samples in it)."""
        return (self, None) if self.parent is None else (self.parent, self.index)


class Effect:
    """
    Base class of an error term; the class attributes below are its declarations.

    Subclasses implement ``matrix`` (kind 'linear') or ``contribution`` (kind 'additive').
    Reference values of a driving signal (mean temperature, start time) are stored in
    ``self.refs`` by :meth:`prepare`, so that live correction uses the same.
    """

    name = 'effect'
    kind = 'additive'
    param_names = ()
    units = ()
    #: effects that are the same physical degree of freedom, and cannot be combined
    excludes = ()
    #: labels of effects this one contains, which adding it replaces (aux_poly > aux)
    supersedes = ()
    #: how a token of an effect that needs arguments is written (None: takes none)
    usage = None
    #: the arguments of a token ``name(a, b)``, as canonical strings
    args = ()
    #: driving signals ``contribution`` reads (keys of :data:`SIGNALS` or 'aux_<name>')
    signals = ()
    #: True for an additive effect whose contribution is a constant (the offset); any other
    #: additive effect is *driven* and evaluated per sample
    constant = False
    #: prior of every parameter, constrained mode: (mean or None: :meth:`default_params`, sd)
    prior = None
    #: place of a linear effect in the product A = A_1 A_2 ... (the smallest left-most)
    linear_order = 0
    #: True if the effect holds the rotation of the sensor's axes into the array frame
    frame_rotation = False
    #: False if the effect does not exist on sensor 1, which defines the array frame
    on_sensor1 = True
    #: 'sensor': one instance and parameter set per sensor; 'array': one for the whole array
    scope = 'sensor'

    def __init__(self, sensor=1, refs=None):
        self.sensor = int(sensor)
        self.refs = dict(refs or {})

    @classmethod
    def suggest_args(cls, ctx):
        """Argument tuples worth testing on data ``ctx`` (diagnosis candidates); [] if none."""
        return []

    @classmethod
    def from_args(cls, args, sensor=1):
        """Make the effect of token ``name(args)`` on ``sensor`` (``args`` strings; here none)."""
        if args:
            raise ValueError(f'effect {cls.name!r} takes no arguments, got '
                             f'{cls.name}({",".join(args)})')
        return cls(sensor=sensor)

    @property
    def n_params(self):
        """Return the number of parameters."""
        return len(self.param_names)

    @property
    def label(self):
        """Model-spec label of this effect, e.g. ``temperature`` or ``step(300)``."""
        return f'{self.name}({",".join(self.args)})' if self.args else self.name

    @property
    def applies(self):
        """Tell whether this effect exists on its sensor (see :attr:`on_sensor1`)."""
        return self.on_sensor1 or self.sensor != 1

    def default_params(self):
        """Parameter values of an ideal sensor (the effect switched off), shape (n_params,)."""
        return np.zeros(self.n_params)

    def params_from_linear(self, parts):
        """(n_params,) this effect's share of the :class:`LinearParts` ``parts``, or None."""
        return None

    def prepare(self, ctx):
        """Compute reference values from calibration data (default: none)."""

    def check(self, ctx):
        """Return None if the data can excite this effect, else the reason why not."""
        return None

    def matrix(self, p):
        """(3, 3) dimensionless matrix of a linear effect."""
        raise NotImplementedError

    def contribution(self, p, ctx, lin):
        """(N, 3) nT added to the raw reading, given ``lin`` = A @ B (N, 3) nT."""
        raise NotImplementedError

    def depends_on_lin(self):
        """Tell whether ``contribution`` depends on ``lin`` (needs fixed-point inversion)."""
        return False

    def reduces(self, p, stderr, ctx):
        """Say why the fitted ``p`` (+- ``stderr`` or None) is a simpler effect, or None."""
        return None

    def describe(self):
        """One-line physical description (first docstring line)."""
        return (self.__doc__ or '').strip().splitlines()[0]

    def __repr__(self):
        return f'{type(self).__name__}(sensor={self.sensor})'


class Registry:
    """
    Classes registered by name, built-in then plug-ins (docs/plugins.md).

    The one mechanism of the named effects, couplings and drivers.  Every class subclasses
    ``base``; messages call one ``what`` ('effect', 'coupling', 'driver') and name the base
    ``base_name`` (where users import it from).  The classes ``builtin`` are registered at
    once, and their names (:attr:`builtin`) are never unregistered.
    """

    def __init__(self, base, what, base_name, builtin=()):
        self.base, self.what, self.base_name = base, what, base_name
        self._classes = {}
        for cls in builtin:
            self.register(cls)
        self.builtin = tuple(self._classes)

    def register(self, cls, name=None):
        """Register a subclass of the base under ``name`` (default ``cls.name``); return it."""
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise TypeError(f'{cls!r} is not a subclass of {self.base_name}')
        key = name or cls.name
        if key in self._classes and self._classes[key] is not cls:
            article = 'an' if self.what[0] in 'aeiou' else 'a'
            raise ValueError(f'{article} {self.what} named {key!r} is already registered '
                             f'({self._classes[key]!r})')
        self._classes[key] = cls
        return cls

    def unregister(self, name):
        """Remove the plug-in registered under ``name`` (tests, interactive sessions)."""
        if name in self.builtin:
            raise ValueError(f'{name!r} is a built-in {self.what} and cannot be unregistered')
        self._classes.pop(name, None)

    def get(self, name):
        """Return the class registered under ``name``, or None."""
        return self._classes.get(name)

    def names(self):
        """Return the registered names, sorted."""
        return sorted(self._classes)


def raw_rate(x, t=None, period=None):
    """
    (N, 3) nT/s time derivative of readings ``x`` (N, 3) nT: the field-rate signal.

    The one estimator for a recording, the simulator and the live corrector:
    ``numpy.gradient``, ``edge_order=2`` (central inside: a fitted tau is unbiased; one-sided
    at the last sample, all a live stream has).  ``t`` (N,) increasing times, s, or
    ``period`` a uniform sample period, s.  None with fewer than 3 samples or times that do
    not increase.
    """
    x = np.asarray(x, float)
    if len(x) < 3:
        return None
    if period is not None:
        return np.gradient(x, float(period), axis=0, edge_order=2) if period > 0 else None
    t = np.asarray(t, float)
    if not np.all(np.diff(t) > 0):
        return None
    return np.gradient(x, t, axis=0, edge_order=2)


def rot_r1(g):
    """Paper 004 eq. 3: R1(gamma), rotation about y."""
    c, s = np.cos(g), np.sin(g)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def rot_r2(b):
    """Paper 004 eq. 3: R2(beta), rotation about x."""
    c, s = np.cos(b), np.sin(b)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def rot_r3(a):
    """Paper 004 eq. 3: R3(alpha), rotation about z."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_z(psi):
    """(N, 3, 3) rotations by the angles ``psi`` (N,) rad about z."""
    c, s = np.cos(psi), np.sin(psi)
    out = np.zeros((len(psi), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 2, 2] = 1.0
    return out


def misalignment_matrix(alpha, beta, gamma):
    """Paper 004 eq. 3: B_i = R1(gamma) R2(beta) R3(alpha) B_1, angles in rad."""
    return rot_r1(gamma) @ rot_r2(beta) @ rot_r3(alpha)


def misalignment_angles(r):
    """Inverse of :func:`misalignment_matrix`: (3, 3) rotation -> (alpha, beta, gamma) rad."""
    # R[1] = [-cb sa, cb ca, sb], R[0, 2] = -sg cb, R[2, 2] = cg cb
    beta = np.arcsin(np.clip(r[1, 2], -1.0, 1.0))
    alpha = np.arctan2(-r[1, 0], r[1, 1])
    gamma = np.arctan2(-r[0, 2], r[2, 2])
    return float(alpha), float(beta), float(gamma)


def nonorthogonality_matrix(psi, varphi, theta):
    """Paper 004 eq. 2: C_NO, upper triangular, z axis as reference (angles in rad)."""
    ct = np.cos(theta)
    return np.array([
        [ct * np.cos(varphi), ct * np.sin(varphi), np.sin(theta)],
        [0.0, np.cos(psi), np.sin(psi)],
        [0.0, 0.0, 1.0]])


def upper_to_scale_nonorth(u):
    """
    Split an upper-triangular (3, 3) matrix into S = diag(kx, ky, kz) and C_NO angles.

    The rows of C_NO are unit vectors (paper 004 eq. 2), so k = row norms of ``u``.
    Returns (k (3,), psi, varphi, theta) in rad.
    """
    k = np.linalg.norm(u, axis=1)
    c = u / k[:, None]
    theta = np.arcsin(np.clip(c[0, 2], -1.0, 1.0))
    varphi = np.arctan2(c[0, 1], c[0, 0])
    psi = np.arctan2(c[1, 2], c[1, 1])
    return k, float(psi), float(varphi), float(theta)


def parse_number(text, what):
    """Return the finite float of the argument ``text`` (``what`` names it in the error)."""
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f'{what}: {text!r} is not a number') from None
    if not np.isfinite(v):
        raise ValueError(f'{what}: {text!r} is not finite')
    return v


def split_params(q, sizes):
    """Cut the parameter vector ``q`` into consecutive pieces of the lengths ``sizes``."""
    ends = np.cumsum([0, *sizes])
    return [q[a:b] for a, b in zip(ends[:-1], ends[1:])]


def format_arg(v):
    """
    Canonical text of a token argument: 6 significant digits, a value of 1e5 or more to 1e-3.

    A time on a clock since 1970 (a ROS stamp, about 1.8e9 s) keeps its milliseconds.
    """
    v = float(v)
    if abs(v) >= 1e5 and math.isfinite(v):
        return format(round(v, 3), 'f').rstrip('0').rstrip('.')
    return format(v, '.6g')


def channel_name(name):
    """'temperature' or an auxiliary column, with its 'aux_' prefix."""
    name = name.strip()
    if name in ('temperature', 'temp'):
        return 'temperature'
    if name.startswith('aux:'):
        name = name[4:]
    return name if name.startswith('aux_') else 'aux_' + name


def lag_coefficients(dt, tau):
    """
    Return (a, b0, b1) of one step of tau dy/dt = x - y: y_k = a y_k-1 + b0 x_k + b1 x_k-1.

    The one discretisation of the lag, batch and live, exact for x linear between samples
    (first-order hold: Franklin, Powell and Workman, Digital Control of Dynamic Systems, 3rd
    ed. 1998, sec. 6.3): a = exp(-dt/tau), b0 = 1 - g, b1 = g - a, g = tau/dt (1 - a).
    dt = 0 holds y, dt < 0 restarts at y = x; tau >= 1e-3 dt.  ``dt`` s, a float or (K,).
    g is not written with expm1, so that old calibration files correct to the same digits.
    """
    dt = np.asarray(dt, float)
    tau = np.maximum(abs(float(tau)), 1e-3 * dt)
    pos = dt > 0
    with np.errstate(divide='ignore', invalid='ignore'):
        a = np.where(pos, np.exp(-dt / tau), np.where(dt == 0, 1.0, 0.0))
        g = np.where(pos, (tau / dt) * (1.0 - a), a)
    return a, 1.0 - g, g - a


def first_order_lag(t, x, tau):
    """
    (N,) response y of tau dy/dt = x - y to x (N,) sampled at t (N,) s, y(t0) = x(t0).

    The recursion of :func:`lag_coefficients` (scipy.signal.lfilter when every step is the
    same, else a scan by recursive doubling): :func:`lag_step` one sample at a time.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    y = x.copy()
    if len(x) < 2:
        return y
    dt = np.diff(t)
    if np.ptp(dt) == 0:
        from scipy.signal import lfilter
        a, b0, b1 = (float(c) for c in lag_coefficients(dt[0], tau))
        # y_k = b0 x_k + (b1 x_k-1 + a y_k-1), in lag_step's order; the state after y_0 = x_0
        y[1:], _ = lfilter([b0, b1], [1.0, -a], x[1:], zi=[b1 * x[0] + a * x[0]])
        return y
    a, b0, b1 = lag_coefficients(dt, tau)
    # y_k = A_k y_k-1 + U_k; doubling composes each step with the d before it
    u = np.concatenate([x[:1], b0 * x[1:] + b1 * x[:-1]])
    g = np.concatenate([[0.0], a])
    d = 1
    while d < len(u) and g[d:].any():
        u[d:] += g[d:] * u[:-d]
        g[d:] = g[d:] * g[:-d]
        d *= 2
    return u


def lag_step(state, t, x, tau):
    """
    One sample of the lag for the live correction: (new state, y).

    ``state`` is the previous sample's (t s, x, y), or None before the first (y = x); ``x``
    the input at ``t`` s.  The step of :func:`first_order_lag`, so it gives the batch values.
    """
    if state is None:
        return (t, x, x), x
    a, b0, b1 = lag_coefficients(t - state[0], tau)
    y = float(b0 * x + (b1 * state[1] + a * state[2]))
    return (t, x, y), y


def cached(cache, key, anchor, make, size):
    """
    Return ``make()``, kept in the dict ``cache`` under ``key`` while ``anchor`` is the same.

    A key holding an id() (which Python reuses) counts only with its ``anchor`` object; the
    oldest entry goes once ``size`` are kept.
    """
    hit = cache.get(key)
    if hit is None or hit[0] is not anchor:
        value = make()
        if len(cache) >= size:
            cache.pop(next(iter(cache)))
        hit = cache[key] = (anchor, value)
    return hit[1]
