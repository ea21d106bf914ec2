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
Physical error terms ("effects") of a vector magnetometer, composable into a model.

Every sensor j of an array is described by the forward model

    raw_j = A_j @ B + offset_j + sum_k d_k(context, lin_j) + noise,     lin_j = A_j @ B

where ``B`` (nT) is the true field in the array frame (sensor 1's orthogonalised axes) and
``A_j`` is the product of the *linear* effects (composed by matrix product, in the order
scale . nonorthogonality . soft_iron . misalignment, paper 004 eq. 2-3) and ``d_k`` are the
*additive* effects (offset, temperature, drift, nonlinearity, auxiliary currents, field rate),
which add in the raw sensor frame.  This is the composition rule: linear maps
compose, offsets and driven effects add.

An effect is a small object with named parameters (each with a unit) and either a
``matrix(p)`` (linear effects) or a ``contribution(p, ctx, lin)`` (additive effects).  It also
declares everything the rest of the code asks about it (the live signals it reads, its prior
in the constrained mode, its place in the product of linear effects, whether it carries the
rotation into the array frame, how it takes its share of a closed-form linear map): the
model, the fit, the diagnosis and the live corrector derive their behaviour from these
declarations and never from effect names, so a new effect is one class in one file.  Users
add their own effects by subclassing :class:`Effect` and calling :func:`register_effect`
(see ``docs/plugins.md``).
"""
from dataclasses import dataclass, field
import importlib
import math
import sys

from magcal_ros.core.geometry.tensor import symmetric_traceless
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

    ``a = u @ q`` (RQ decomposition) with ``u`` upper triangular with a positive diagonal
    (scale and non-orthogonality) and ``q`` a proper rotation (misalignment).

    Attributes
    ----------
    a, u, q : numpy.ndarray
        (3, 3) dimensionless.
    scale : numpy.ndarray
        (3,) row norms of ``u`` (kx, ky, kz), dimensionless.
    nonorth : tuple of float
        (psi, varphi, theta) of C_NO, rad.
    offset : numpy.ndarray
        (3,) nT.

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
    RQ decomposition a = u @ q of a (3, 3) matrix with det(a) > 0.

    ``u`` (3, 3) upper triangular with a positive diagonal, ``q`` (3, 3) a proper rotation
    (det +1): the split of paper 004 eq. 2-3 (intrinsic map times misalignment).
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
    """
    Driving signals seen by one sensor.

    Attributes
    ----------
    t : numpy.ndarray
        (N,) time in s.
    temp : numpy.ndarray or None
        (N,) sensor temperature in degC.
    aux : dict of str to numpy.ndarray
        Auxiliary channels, each (N,), in the channel's own unit (A, W, ...).
    raw_rate : numpy.ndarray or None
        (N, 3) time derivative of the raw reading, nT/s.
    parent : SensorContext or None
        The whole record this context was cut from (:meth:`subset`), so that an effect with
        memory (a lag filter) runs over the whole record and keeps its state across the
        cut, e.g. across the held-out blocks of a cross-validation.
    index : numpy.ndarray or None
        (N,) int, positions of these samples in ``parent``.
    attitude : numpy.ndarray or None
        (N, 3, 3) body-to-world rotation matrices of the array (from the quaternion columns
        att_qw..att_qz), or None when the attitude is unknown.

    """

    t: np.ndarray
    temp: np.ndarray | None = None
    aux: dict = field(default_factory=dict)
    raw_rate: np.ndarray | None = None
    parent: 'SensorContext | None' = None
    index: np.ndarray | None = None
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
            t=self.t[idx],
            temp=None if self.temp is None else self.temp[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            raw_rate=None if self.raw_rate is None else self.raw_rate[idx],
            attitude=None if self.attitude is None else self.attitude[idx],
            parent=root, index=pos if self.index is None else self.index[pos])

    def whole(self):
        """(context of the whole record, (N,) int positions of these samples in it)."""
        if self.parent is None:
            return self, None
        return self.parent, self.index


class Effect:
    """
    Base class of an error term.

    Subclasses set ``name``, ``kind`` ('linear' or 'additive'), ``param_names`` and ``units``
    and implement ``matrix`` (linear) or ``contribution`` (additive).  Effects that depend on a
    reference value of a driving signal (mean temperature, start time, mean current) compute it
    in :meth:`prepare` from the calibration data and store it in ``self.refs`` so that live
    correction uses the same reference.

    The class attributes below are the effect's declarations;
    :class:`~magcal_ros.core.model.Model`, the fit, the diagnosis and the live corrector read
    them instead of recognising names.
    """

    name = 'effect'
    kind = 'additive'
    param_names = ()
    units = ()
    #: effects that are the same physical degree of freedom, and cannot be combined
    excludes = ()
    #: labels of effects this one contains (its parameters of the same name are theirs):
    #: adding it to a model replaces them, e.g. aux_poly(aux_x,2) replaces aux:aux_x
    supersedes = ()
    #: how a token of an effect that needs arguments is written (None: takes none)
    usage = None
    #: the arguments of a token ``name(a, b)`` (a step time, a frequency, a channel), as
    #: canonical strings; () for an effect without arguments
    args = ()
    #: driving signals ``contribution`` reads from the :class:`SensorContext`: keys of
    #: :data:`SIGNALS` ('time', 'temperature', 'field_rate') or an auxiliary column
    #: 'aux_<name>'.  The live corrector subscribes and waits for exactly these.
    signals = ()
    #: True for an additive effect whose contribution is a constant (N, 3) vector (the
    #: offset): live correction folds it into ``A^-1 (raw - offset)``.  Any other additive
    #: effect is *driven* and evaluated per sample.
    constant = False
    #: prior of the constrained mode (partial attitude coverage) on every parameter:
    #: (mean, or None for :meth:`default_params`, standard deviation in the parameters' unit);
    #: None: no prior
    prior = None
    #: place of a linear effect in the product A = A_1 A_2 ... (paper 004 eq. 2-3): effects
    #: are multiplied in increasing order (the smallest is left-most, next to the output)
    linear_order = 0
    #: True if the effect holds the rotation of the sensor's axes into the array frame
    #: (sensor 1's axes): on a sensor j > 1 it ties the sensors to one field per epoch
    frame_rotation = False
    #: False if the effect does not exist on sensor 1 because sensor 1 defines the array
    #: frame (the misalignment); the model leaves it out there
    on_sensor1 = True
    #: 'sensor': one instance and parameter set per sensor; 'array': one for the whole array
    #: (the site gradient)
    scope = 'sensor'

    def __init__(self, sensor=1, refs=None):
        self.sensor = int(sensor)
        self.refs = dict(refs or {})

    @classmethod
    def suggest_args(cls, ctx):
        """
        Argument tuples worth testing on data ``ctx`` (the diagnosis' candidates); [] if none.

        Effects whose arguments come from the residual (a step time, a frequency) are
        proposed by the diagnosis itself and return [].
        """
        return []

    @classmethod
    def from_args(cls, args, sensor=1):
        """
        Make the effect of token ``name(args)`` on ``sensor``; ``args`` are strings.

        Effects with arguments override this (and set :attr:`args`); the default accepts none.
        """
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
        """
        Return this effect's share of a closed-form linear map and offset (closed-form start).

        ``parts`` is a :class:`LinearParts`; return the (n_params,) parameters, or None when
        the effect has no share (it then starts at :meth:`default_params`).
        """
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
        """
        Say why the fitted effect reduces to a simpler one of the catalog, or return None.

        Reason why the fitted parameters ``p`` (stderr: their uncertainties, or None) make
        this effect a simpler one already in the catalog (a lag of zero time constant), else
        None.  The diagnosis does not adopt such a candidate: the simpler effect is tested
        on its own.
        """
        return None

    def describe(self):
        """One-line physical description (first docstring line)."""
        return (self.__doc__ or '').strip().splitlines()[0]

    def __repr__(self):
        return f'{type(self).__name__}(sensor={self.sensor})'


def raw_rate(x, t=None, period=None):
    """
    (N, 3) nT/s time derivative of readings ``x`` (N, 3) nT: the field-rate signal.

    The one estimator of ``SensorContext.raw_rate`` for a recording (Dataset), the simulator
    and the live corrector.  Second-order finite differences (``numpy.gradient``,
    ``edge_order=2``): central at interior samples, and one-sided at the ends, at the last
    sample (3 x_k - 4 x_k-1 + x_k-2) / 2h, which is all a live stream has (only the past).
    The central difference leaves the sample's own noise out of its rate, so a tau fitted
    with it is unbiased (a one-sided rate shares the sample's noise: biased by
    1.5 sigma^2 / (h |dB/dt|^2)).  For a field turning at w rad/s sampled every h s the two
    forms give (1 - (w h)^2 / 6) and (1 + (w h)^2 / 3) times the true rate, so live and
    offline correction agree to (w h)^2 / 2 of tau |dB/dt|: 2 % at w h = 0.2 (1 rad/s at
    5 Hz).  The backward difference x_k - x_k-1 the corrector used before lags half a
    sample instead: (w h) / 2 of the rate, 10 % at w h = 0.2, along the field.

    Parameters
    ----------
    x : numpy.ndarray
        (N, 3) readings, nT.
    t : numpy.ndarray, optional
        (N,) strictly increasing sample times, s.
    period : float, optional
        Uniform sample period, s, instead of ``t`` (a live stream, whose stamps bunch when
        samples are read together).

    Returns
    -------
    numpy.ndarray or None
        (N, 3) nT/s; None with fewer than 3 samples or times that do not increase.

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


# -- rotations of paper 004 eq. 3 ----------------------------------------------------------

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


def misalignment_matrix(alpha, beta, gamma):
    """Paper 004 eq. 3: B_i = R1(gamma) R2(beta) R3(alpha) B_1, angles in rad."""
    return rot_r1(gamma) @ rot_r2(beta) @ rot_r3(alpha)


def misalignment_angles(r):
    """Inverse of :func:`misalignment_matrix`: (3, 3) rotation -> (alpha, beta, gamma) rad."""
    # R = R1(g) R2(b) R3(a); row 1 of R = [-cb sa ... ] -- solve from the closed form:
    # R[1] = [-cb*sa, cb*ca, sb]
    beta = np.arcsin(np.clip(r[1, 2], -1.0, 1.0))
    alpha = np.arctan2(-r[1, 0], r[1, 1])
    # R[0,2] = -sg*cb, R[2,2] = cg*cb
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


# -- linear effects -------------------------------------------------------------------------

class Scale(Effect):
    """Per-axis scale factors kx, ky, kz (paper 004 eq. 2, S)."""

    name = 'scale'
    kind = 'linear'
    param_names = ('kx', 'ky', 'kz')
    units = ('1', '1', '1')
    excludes = ('soft_iron',)
    prior = (1.0, 0.02)
    linear_order = 0

    def default_params(self):
        return np.ones(3)

    def matrix(self, p):
        return np.diag(p)

    def params_from_linear(self, parts):
        return parts.scale


class NonOrthogonality(Effect):
    """Non-orthogonal sensor axes, angles psi, varphi, theta (paper 004 eq. 2, C_NO)."""

    name = 'nonorthogonality'
    kind = 'linear'
    param_names = ('psi', 'varphi', 'theta')
    units = ('rad', 'rad', 'rad')
    excludes = ('soft_iron',)
    prior = (0.0, 0.02)
    linear_order = 1

    def matrix(self, p):
        return nonorthogonality_matrix(*p)

    def params_from_linear(self, parts):
        return np.array(parts.nonorth)


class Misalignment(Effect):
    """
    Rotation of the sensor's axes relative to sensor 1 (paper 004 eq. 3).

    Sensor 1 defines the array frame, so this effect has no parameters there.
    """

    name = 'misalignment'
    kind = 'linear'
    param_names = ('alpha', 'beta', 'gamma')
    units = ('rad', 'rad', 'rad')
    excludes = ('soft_iron',)
    prior = (0.0, 0.05)
    linear_order = 3
    frame_rotation = True
    on_sensor1 = False

    def matrix(self, p):
        return misalignment_matrix(*p)

    def params_from_linear(self, parts):
        return np.array(misalignment_angles(parts.q))


class SoftIron(Effect):
    """
    Full 3x3 linear map (soft iron, paper 002 K = I + D) instead of scale/nonorth./misalignment.

    On sensor 1, which defines the array frame, the matrix is upper triangular (6 parameters):
    its rotation is the frame definition, not something the data can determine.
    """

    name = 'soft_iron'
    kind = 'linear'
    excludes = ('scale', 'nonorthogonality', 'misalignment')
    prior = (None, 0.02)
    linear_order = 2
    frame_rotation = True
    _full = ('k11', 'k12', 'k13', 'k21', 'k22', 'k23', 'k31', 'k32', 'k33')
    _upper = ('k11', 'k12', 'k13', 'k22', 'k23', 'k33')

    @property
    def param_names(self):
        return self._upper if self.sensor == 1 else self._full

    @property
    def units(self):
        return ('1',) * len(self.param_names)

    def default_params(self):
        if self.sensor == 1:
            return np.array([1.0, 0, 0, 1.0, 0, 1.0])
        return np.eye(3).ravel()

    def matrix(self, p):
        if self.sensor == 1:
            m = np.zeros((3, 3))
            m[np.triu_indices(3)] = p
            return m
        return np.asarray(p).reshape(3, 3)

    def params_from_linear(self, parts):
        return parts.a[np.triu_indices(3)] if self.sensor == 1 else parts.a.ravel()


# -- additive effects -----------------------------------------------------------------------

class Offset(Effect):
    """Constant offset (hard iron, electronics zero), paper 004 eq. 2 b, in nT."""

    name = 'offset'
    param_names = ('bx', 'by', 'bz')
    units = ('nT', 'nT', 'nT')
    constant = True

    def contribution(self, p, ctx, lin):
        return np.broadcast_to(p, lin.shape)

    def params_from_linear(self, parts):
        return parts.offset


class Temperature(Effect):
    """Offset and scale drift with sensor temperature: dB = c_off (T-T0) + c_scale (T-T0) * lin."""

    name = 'temperature'
    param_names = ('cx', 'cy', 'cz', 'sx', 'sy', 'sz')
    units = ('nT/degC',) * 3 + ('1/degC',) * 3
    signals = ('temperature',)
    min_span_c = 1.0

    def prepare(self, ctx):
        if ctx.temp is not None and np.isfinite(ctx.temp).any():
            self.refs.setdefault('t0_c', float(np.nanmean(ctx.temp)))

    def check(self, ctx):
        if ctx.temp is None or not np.isfinite(ctx.temp).any():
            return (f'sensor {self.sensor} has no temperature column (s{self.sensor}_temp): '
                    'the temperature effect cannot be fitted')
        span = float(np.nanmax(ctx.temp) - np.nanmin(ctx.temp))
        if span < self.min_span_c:
            return (f'temperature of sensor {self.sensor} varies only {span:.2f} degC '
                    f'(< {self.min_span_c} degC): heat or cool the sensor by several degC during '
                    'the calibration, or drop the temperature effect')
        return None

    def contribution(self, p, ctx, lin):
        dt = (np.nan_to_num(ctx.temp, nan=self.refs.get('t0_c', 0.0))
              - self.refs.get('t0_c', 0.0))[:, None]
        return dt * p[:3] + dt * p[3:] * lin

    def depends_on_lin(self):
        return True


class Drift(Effect):
    """Offset drifting linearly in time: dB = d1 (t - t0), nT/s."""

    name = 'drift'
    param_names = ('dx', 'dy', 'dz')
    units = ('nT/s',) * 3
    signals = ('time',)
    min_span_s = 1.0

    def prepare(self, ctx):
        self.refs.setdefault('t0_s', float(ctx.t[0]) if len(ctx.t) else 0.0)

    def check(self, ctx):
        span = float(ctx.t[-1] - ctx.t[0]) if len(ctx.t) else 0.0
        if span < self.min_span_s:
            return f'the data span only {span:.2f} s: drift cannot be separated from the offset'
        return None

    def _tau(self, ctx):
        return (ctx.t - self.refs.get('t0_s', 0.0))[:, None]

    def contribution(self, p, ctx, lin):
        return self._tau(ctx) * p[:3]


class QuadraticDrift(Drift):
    """Offset drifting quadratically in time: dB = d1 (t - t0) + d2 (t - t0)^2."""

    name = 'drift2'
    param_names = ('dx', 'dy', 'dz', 'qx', 'qy', 'qz')
    units = ('nT/s',) * 3 + ('nT/s^2',) * 3

    def contribution(self, p, ctx, lin):
        tau = self._tau(ctx)
        return tau * p[:3] + tau ** 2 * p[3:]


class Nonlinearity(Effect):
    """
    Per-axis quadratic and cubic response: dB = q (lin/F0)^2 + c (lin/F0)^3, F0 = 50 000 nT.

    ``q`` and ``c`` are the deviations (nT) at a full-scale field F0 along that axis.
    """

    name = 'nonlinearity'
    param_names = ('qx', 'qy', 'qz', 'cx', 'cy', 'cz')
    units = ('nT',) * 6

    def contribution(self, p, ctx, lin):
        u = lin / NONLINEARITY_FULL_SCALE_NT
        u2 = u * u                      # products, not float powers: 5x faster (profile)
        return p[:3] * u2 + p[3:] * (u2 * u)

    def depends_on_lin(self):
        return True


class Aux(Effect):
    """Linear coupling of an auxiliary channel (e.g. a motor current): dB = v (a - a0)."""

    name = 'aux'

    def __init__(self, sensor=1, refs=None, channel='aux_current'):
        super().__init__(sensor, refs)
        self.channel = channel if channel.startswith('aux_') else 'aux_' + channel

    @property
    def label(self):
        return 'aux:' + self.channel

    param_names = ('vx', 'vy', 'vz')
    units = ('nT/unit',) * 3

    @property
    def signals(self):
        return (self.channel,)

    def prepare(self, ctx):
        if self.channel in ctx.aux:
            self.refs.setdefault('a0', float(np.nanmean(ctx.aux[self.channel])))

    def check(self, ctx):
        if self.channel not in ctx.aux:
            return (f'no auxiliary column {self.channel!r} in the data '
                    f'(have: {sorted(ctx.aux) or "none"})')
        a = ctx.aux[self.channel]
        if not np.isfinite(a).all():
            return f'auxiliary channel {self.channel!r} contains non-finite values'
        if np.ptp(a) <= 1e-9 * max(1.0, float(np.abs(a).max())):
            return (f'auxiliary channel {self.channel!r} never changes: its coupling cannot be '
                    'separated from the offset; switch the load on and off during calibration')
        return None

    def contribution(self, p, ctx, lin):
        return (ctx.aux[self.channel] - self.refs.get('a0', 0.0))[:, None] * p


class FieldRate(Effect):
    """
    Response to dB/dt (eddy currents, sensor lag, sampling skew): dB = -tau * d(raw)/dt, s.

    Under pure rotation in a uniform field dB/dt is perpendicular to B, so this term hardly
    shows in the scalar residual; it shows in the inter-sensor vector residual.
    """

    name = 'field_rate'
    param_names = ('tau_x', 'tau_y', 'tau_z')
    units = ('s', 's', 's')
    signals = ('field_rate',)

    def check(self, ctx):
        if ctx.raw_rate is None:
            return 'no time derivative of the field available (need a time column t)'
        return None

    def contribution(self, p, ctx, lin):
        return -ctx.raw_rate * p


# -- effects with arguments (issue 11: what the workbench's findings point to) --------------

def _number(text, what):
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f'{what}: {text!r} is not a number') from None
    if not np.isfinite(v):
        raise ValueError(f'{what}: {text!r} is not finite')
    return v


def _fmt(v):
    """Canonical text of a token argument: 4 significant digits are kept as given."""
    return format(float(v), '.6g')


def _channel(name):
    """'temperature' or an auxiliary column, with its 'aux_' prefix."""
    name = name.strip()
    if name in ('temperature', 'temp'):
        return 'temperature'
    if name.startswith('aux:'):
        name = name[4:]
    return name if name.startswith('aux_') else 'aux_' + name


def _signal(ctx, channel):
    """(N,) values of 'temperature' or an auxiliary channel in ``ctx`` (None if absent)."""
    if channel == 'temperature':
        return ctx.temp
    return ctx.aux.get(channel)


def _check_channel(ctx, channel, sensor):
    a = _signal(ctx, channel)
    if a is None or not np.isfinite(a).any():
        col = f's{sensor}_temp' if channel == 'temperature' else channel
        return f'sensor {sensor}: no {channel} column ({col}) in the data'
    if channel != 'temperature' and not np.isfinite(a).all():
        return f'channel {channel!r} contains non-finite values'
    if np.nanmax(a) - np.nanmin(a) <= 1e-9 * max(1.0, float(np.nanmax(np.abs(a)))):
        return (f'channel {channel!r} never changes: its coupling cannot be separated from '
                'the offset')
    return None


class Step(Effect):
    """
    Offset change(s) at given times: dB = sum_k s_k [t >= t_k], nT (a jump, a relay).

    Token ``step(t1, t2, ...)``, times in s on the data's time axis; 3 parameters per step.
    """

    name = 'step'
    usage = 'step(<t_s>[,<t_s>...])'
    signals = ('time',)

    @classmethod
    def from_args(cls, args, sensor=1):
        if not args:
            raise ValueError('step needs the time(s) of the offset change, e.g. step(300)')
        times = sorted(_number(a, 'step time [s]') for a in args)
        eff = cls(sensor=sensor)
        eff.times = np.array(times)
        eff.args = tuple(_fmt(x) for x in times)
        return eff

    @property
    def param_names(self):
        if len(self.args) == 1:
            return ('sx', 'sy', 'sz')
        return tuple(f's{k}{ax}' for k in range(1, len(self.args) + 1) for ax in 'xyz')

    @property
    def units(self):
        return ('nT',) * (3 * len(self.args))

    def check(self, ctx):
        for tk in self.times:
            before = int(np.sum(ctx.t < tk))
            if before < 3 or len(ctx.t) - before < 3:
                return (f'step at t = {tk:g} s lies outside the data '
                        f'({ctx.t[0]:g} .. {ctx.t[-1]:g} s)')
        return None

    def contribution(self, p, ctx, lin):
        on = (ctx.t[:, None] >= self.times[None, :]).astype(float)        # (N, K)
        return on @ np.asarray(p).reshape(-1, 3)


class Periodic(Effect):
    """
    Sinusoidal interference at a given frequency (pump, fan, wheel), per axis, nT.

    Token ``periodic(f_hz)``: dB = a cos(2 pi f (t - t0)) + b sin(2 pi f (t - t0)).
    """

    name = 'periodic'
    usage = 'periodic(<f_hz>)'
    signals = ('time',)
    param_names = ('ax', 'ay', 'az', 'bx', 'by', 'bz')
    units = ('nT',) * 6

    @classmethod
    def from_args(cls, args, sensor=1):
        if len(args) != 1:
            raise ValueError('periodic needs one frequency in Hz, e.g. periodic(0.23)')
        f = _number(args[0], 'periodic frequency [Hz]')
        if f <= 0:
            raise ValueError(f'periodic frequency must be positive, got {args[0]!r}')
        eff = cls(sensor=sensor)
        eff.freq_hz = f
        eff.args = (_fmt(f),)
        return eff

    def prepare(self, ctx):
        self.refs.setdefault('t0_s', float(ctx.t[0]) if len(ctx.t) else 0.0)

    def check(self, ctx):
        span = float(ctx.t[-1] - ctx.t[0]) if len(ctx.t) > 1 else 0.0
        if span * self.freq_hz < 2.0:
            return (f'the data span {span:.1f} s, less than 2 periods of {self.freq_hz:g} Hz: '
                    'the sinusoid cannot be separated from the offset')
        dt = float(np.median(np.diff(ctx.t)))
        if self.freq_hz >= 0.5 / dt:
            return (f'{self.freq_hz:g} Hz is at or above the Nyquist frequency '
                    f'{0.5 / dt:g} Hz of the data')
        return None

    def contribution(self, p, ctx, lin):
        ph = (2.0 * np.pi * self.freq_hz) * (ctx.t - self.refs.get('t0_s', 0.0))
        return np.cos(ph)[:, None] * p[:3] + np.sin(ph)[:, None] * p[3:]


def first_order_lag(t, x, tau):
    """
    (N,) response y of tau dy/dt = x - y to x (N,) sampled at t (N,) s, y(t0) = x(t0).

    Exact for x linear between samples (first-order hold): y_k = a y_k-1 + b0 x_k + b1 x_k-1,
    a = exp(-dt/tau), b0 = 1 - tau/dt (1 - a), b1 = tau/dt (1 - a) - a.  Irregular sampling
    is interpolated onto a uniform grid at the median interval and back.
    """
    from scipy.signal import lfilter
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    if len(x) < 2:
        return x.copy()
    dts = np.diff(t)
    dt = float(np.median(dts))
    uniform = np.ptp(dts) <= 1e-6 * dt
    if not uniform:
        grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
        xs = np.interp(grid, t, x)
    else:
        xs = x
    tau = max(abs(float(tau)), 1e-3 * dt)
    a = math.exp(-dt / tau)
    g = (tau / dt) * (1.0 - a)
    b = [1.0 - g, g - a]
    # steady state at the first sample: y[0] = b0 x0 + z0 = x0
    y, _ = lfilter(b, [1.0, -a], xs, zi=np.array([(1.0 - b[0]) * xs[0]]))
    return y if uniform else np.interp(t, grid, y)


class Lag(Effect):
    """
    A channel (temperature or aux) acting through a first-order lag: dB = c (y - x0), nT.

    Token ``lag(temperature)`` or ``lag(aux_<name>)``; y solves tau dy/dt = x - y (a sensor
    head that follows its thermometer with time constant tau, fitted, s).  The filter runs
    over the whole record (``SensorContext.whole``), so held-out blocks keep its state.
    """

    name = 'lag'
    usage = 'lag(temperature|aux_<name>)'
    #: starting time constant, s, of a fit that starts from nothing (the diagnosis tries more)
    tau0_s = 30.0

    @classmethod
    def from_args(cls, args, sensor=1):
        if len(args) != 1:
            raise ValueError('lag needs one channel, e.g. lag(temperature) or '
                             'lag(aux_motor_current)')
        eff = cls(sensor=sensor)
        eff.channel = _channel(args[0])
        eff.args = (eff.channel,)
        return eff

    @classmethod
    def suggest_args(cls, ctx):
        out = [('temperature',)] if ctx.temp is not None else []
        return out + [(c,) for c in sorted(ctx.aux)]

    @property
    def signals(self):
        return ('time', self.channel)

    @property
    def param_names(self):
        return ('cx', 'cy', 'cz', 'tau')

    @property
    def units(self):
        u = 'nT/degC' if self.channel == 'temperature' else 'nT/unit'
        return (u, u, u, 's')

    def default_params(self):
        return np.array([0.0, 0.0, 0.0, self.tau0_s])

    def prepare(self, ctx):
        a = _signal(ctx, self.channel)
        if a is not None and np.isfinite(a).any():
            self.refs.setdefault('x0', float(np.nanmean(a)))

    def check(self, ctx):
        return _check_channel(ctx, self.channel, self.sensor)

    def lagged(self, ctx, tau):
        """(N,) the channel through the lag of time constant ``tau`` s, at ``ctx``'s samples."""
        whole, idx = ctx.whole()
        if idx is None and len(ctx.t) == 1:
            return self._online(float(ctx.t[0]), _signal(ctx, self.channel), tau)
        x = _signal(whole, self.channel)
        # the fit's Jacobian perturbs every other parameter at the same tau (and tau itself):
        # keep the last few filtered series, keyed by the record and tau
        key = (id(x), len(x), float(tau), self.refs.get('x0', 0.0))
        cache = self.__dict__.setdefault('_cache', {})
        hit = cache.get(key)
        if hit is None or hit[1] is not x:
            xx = np.nan_to_num(x, nan=self.refs.get('x0', 0.0))
            hit = (first_order_lag(whole.t, xx, tau), x)
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[key] = hit
        y = hit[0]
        return y if idx is None else y[idx]

    def _online(self, t, x, tau):
        """
        Filter one sample at a time for the live correction.

        Live correction, one sample at a time: the filter's state is kept between calls
        (y <- x + (y - x) exp(-dt / tau), the exact response to x held since the last
        sample; the first sample starts in steady state).
        """
        x = float(self.refs.get('x0', 0.0) if x is None or not np.isfinite(x[0]) else x[0])
        state = self.__dict__.get('_state')
        if state is None or t <= state[0]:
            y = x
        else:
            y = x + (state[1] - x) * math.exp(-(t - state[0]) / max(abs(float(tau)), 1e-9))
        self._state = (t, y)
        return np.array([y])

    def reduces(self, p, stderr, ctx):
        """
        Why the fitted lag is no lag (tau indistinguishable from 0), or None.

        A time constant below two sample intervals, or within 3 standard uncertainties of
        zero, is the plain coupling of the channel (``temperature``, ``aux:<channel>``):
        the diagnosis then prefers that simpler, established effect.
        """
        tau, se = abs(float(p[3])), float(stderr[3]) if stderr is not None else 0.0
        dt = float(np.median(np.diff(ctx.t))) if len(ctx.t) > 1 else 0.0
        if tau < 2.0 * dt or (np.isfinite(se) and tau < 3.0 * se):
            return (f'fitted time constant {tau:.3g} +- {se:.2g} s is no lag (below '
                    f'{max(2 * dt, 3 * se):.3g} s): the plain coupling of {self.channel}')
        return None

    def contribution(self, p, ctx, lin):
        y = self.lagged(ctx, p[3]) - self.refs.get('x0', 0.0)
        return y[:, None] * p[:3]


class AuxPoly(Effect):
    """
    Polynomial coupling of an auxiliary channel: dB = sum_k v_k (a - a0)^k, k = 1..d, nT.

    Token ``aux_poly(aux_<name>, d)``, 2 <= d <= 4 (e.g. a field that grows with the square
    of a current, from heating or saturation).  Includes the linear term, so it replaces
    ``aux:aux_<name>`` (its linear parameters vx, vy, vz are that effect's).
    """

    name = 'aux_poly'
    usage = 'aux_poly(aux_<name>,<degree>)'

    @classmethod
    def from_args(cls, args, sensor=1):
        if len(args) != 2:
            raise ValueError('aux_poly needs a channel and a degree, e.g. '
                             'aux_poly(aux_motor_current,2)')
        eff = cls(sensor=sensor)
        eff.channel = _channel(args[0])
        if eff.channel == 'temperature':
            raise ValueError('aux_poly couples an auxiliary channel (aux_<name>), not the '
                             'temperature')
        d = _number(args[1], 'aux_poly degree')
        if d != int(d) or not 2 <= d <= 4:
            raise ValueError(f'aux_poly degree must be 2, 3 or 4, got {args[1]!r}')
        eff.degree = int(d)
        eff.args = (eff.channel, str(eff.degree))
        eff.supersedes = ('aux:' + eff.channel,)
        return eff

    @classmethod
    def suggest_args(cls, ctx):
        return [(c, '2') for c in sorted(ctx.aux)]

    @property
    def signals(self):
        return (self.channel,)

    @property
    def param_names(self):
        return ('vx', 'vy', 'vz') + tuple(f'v{k}{ax}' for k in range(2, self.degree + 1)
                                          for ax in 'xyz')

    @property
    def units(self):
        return tuple('nT/unit' if k == 1 else f'nT/unit^{k}'
                     for k in range(1, self.degree + 1) for _ in 'xyz')

    def prepare(self, ctx):
        if self.channel in ctx.aux:
            self.refs.setdefault('a0', float(np.nanmean(ctx.aux[self.channel])))

    def check(self, ctx):
        return _check_channel(ctx, self.channel, self.sensor)

    def contribution(self, p, ctx, lin):
        u = (ctx.aux[self.channel] - self.refs.get('a0', 0.0))[:, None]
        v = np.asarray(p).reshape(-1, 3)
        out = u * v[0]
        uk = u
        for k in range(1, self.degree):
            uk = uk * u
            out = out + uk * v[k]
        return out


# -- array-wide effects --------------------------------------------------------------------


class SiteGradient(Effect):
    """
    Constant gradient of the site in the world frame, seen through the known attitude.

    The field at sensor j (position r_j, m, body = array frame) is
    B_j = B_c + R^T G_w R r_j, with B_c the field at the array centre (the origin of the
    positions; its magnitude is the reference magnitude), R the body-to-world rotation
    (``SensorContext.attitude``) and G_w (nT/m) symmetric and traceless: 5 parameters
    (gxx, gxy, gxz, gyy, gyz) shared by the whole array.  The shift enters before the
    sensor's linear map: raw_j = A_j B_j + offset_j + ...  The positions are stored in
    ``refs`` (x1, y1, z1, x2, ...; m) so that the calibration file carries them.
    """

    name = 'site_gradient'
    kind = 'array'
    #: one set of parameters for the whole array, not one per sensor
    scope = 'array'
    signals = ('attitude',)
    param_names = ('gxx', 'gxy', 'gxz', 'gyy', 'gyz')
    units = ('nT/m',) * 5

    def set_positions(self, positions):
        """Store the (S, 3) sensor positions, m, in the array frame."""
        pos = np.asarray(positions, float)
        for j, r in enumerate(pos, start=1):
            for a, v in zip('xyz', r):
                self.refs[f'{a}{j}'] = float(v)

    def position(self, j):
        """(3,) position of sensor j, m."""
        try:
            return np.array([self.refs[f'{a}{j}'] for a in 'xyz'])
        except KeyError:
            raise ValueError(f'site_gradient: no position of sensor {j}; give the array '
                             'geometry') from None

    def check(self, ctx):
        if ctx.attitude is None:
            return ('site_gradient needs the attitude of the array (CSV columns att_qw, att_qx, '
                    'att_qy, att_qz; an Imu topic): without it the world-frame gradient cannot '
                    'be told from the calibration; or estimate the heading per epoch '
                    '(magcal fit --heading-unknown, docs/site_gradient.md)')
        return None

    def tensor(self, p):
        """(3, 3) world-frame gradient G_w, nT/m."""
        return symmetric_traceless(p)

    def shift(self, p, ctx, j):
        """(N, 3) nT: R^T G_w R r_j, the field at sensor j minus the field at the centre."""
        rot = ctx.attitude
        v = rot @ self.position(j)                       # (N, 3) r_j in the world frame, m
        w = v @ self.tensor(p)                           # G symmetric: (G v)^T = v^T G
        return np.einsum('nji,nj->ni', rot, w)           # back to the body frame


# -- registry -------------------------------------------------------------------------------

_REGISTRY = {}


def register_effect(cls, name=None):
    """Register an :class:`Effect` subclass under ``name`` (default ``cls.name``)."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise TypeError(f'{cls!r} is not a subclass of magcal_ros.core.effects.Effect')
    key = name or cls.name
    if key in _REGISTRY and _REGISTRY[key] is not cls:
        raise ValueError(f'an effect named {key!r} is already registered ({_REGISTRY[key]!r})')
    _REGISTRY[key] = cls
    return cls


def unregister_effect(name):
    """Remove the effect registered under ``name`` (tests, interactive sessions)."""
    if name in BUILTIN_EFFECTS:
        raise ValueError(f'{name!r} is a built-in effect and cannot be unregistered')
    _REGISTRY.pop(name, None)


for _cls in (Scale, NonOrthogonality, Misalignment, SoftIron, Offset, Temperature, Drift,
             QuadraticDrift, Nonlinearity, FieldRate, Step, Periodic, Lag, AuxPoly,
             SiteGradient):
    register_effect(_cls)

#: names of the effects that ship with the library
BUILTIN_EFFECTS = tuple(_REGISTRY)

#: the model of paper 004 (offset, scale, nonorthogonality, misalignment)
BASE = ('offset', 'scale', 'nonorthogonality', 'misalignment')


def registered_effects():
    """Names of all registered effects (plus 'aux:<column>')."""
    return sorted(_REGISTRY) + ['aux:<column>']


def effect_class(name):
    """Return the Effect class registered as ``name`` (without arguments), or None."""
    return _REGISTRY.get(name)


def needs_args(name):
    """Tell whether the registered effect ``name`` is only written with arguments."""
    cls = _REGISTRY.get(name)
    return cls is not None and cls.usage is not None


def load_plugin(ref):
    """
    Import ``module`` or ``module:Class`` and register the effect classes it names.

    A module may define ``MAGCAL_EFFECTS = [Cls, ...]`` or call :func:`register_effect`
    itself.  Returns the list of registered names.
    """
    mod_name, _, attr = ref.partition(':')
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ValueError(f'cannot import effect plugin {ref!r}: {exc}') from exc
    classes = [getattr(mod, attr)] if attr else list(getattr(mod, 'MAGCAL_EFFECTS', []))
    names = []
    for cls in classes:
        if _REGISTRY.get(cls.name) is not cls:
            register_effect(cls)
        names.append(cls.name)
    return names


def split_spec(spec):
    """
    Tokens of a comma-separated model spec; commas inside ``name(a, b)`` do not split.

    'base,step(120,300)@2, periodic(0.23)' -> ['base', 'step(120,300)@2', 'periodic(0.23)'].
    """
    out, depth, cur = [], 0, []
    for ch in str(spec):
        if ch == '(':
            depth += 1
        elif ch == ')':
            depth -= 1
            if depth < 0:
                raise ValueError(f'unbalanced ")" in model {spec!r}')
        if ch == ',' and depth == 0:
            out.append(''.join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    if depth:
        raise ValueError(f'unbalanced "(" in model {spec!r}')
    out.append(''.join(cur).strip())
    return [t for t in out if t]


def parse_token(token):
    """
    'step(120,300)@2' -> ('step', ('120', '300'), 2); 'drift' -> ('drift', (), None).

    The sensor is None when the token has no ``@j`` (the effect on every sensor).
    """
    tok = token.strip()
    name, at, where = tok.rpartition('@') if tok.rfind('@') > tok.rfind(')') else (tok, '', '')
    sensor = None
    if at:
        try:
            sensor = int(where)
        except ValueError:
            raise ValueError(f'bad sensor in {token!r}: expected name@<sensor number>') from None
    name = name.strip()
    args = ()
    if '(' in name:
        if not name.endswith(')'):
            raise ValueError(f'bad effect {token!r}: expected name(arguments)@sensor')
        name, _, inner = name[:-1].partition('(')
        args = tuple(a.strip() for a in inner.split(','))
        if any(not a for a in args):
            raise ValueError(f'empty argument in {token!r}')
        name = name.strip()
    return name, args, sensor


def load_plugins(refs):
    """
    Load every plug-in of ``refs`` and return the registered names.

    :func:`load_plugin` for each of ``refs`` (``--plugin``, a node's ``plugins``); the
    registered names, in order.
    """
    return [name for ref in refs or () for name in load_plugin(ref)]


def _loaded_effect_name(ref):
    """
    Return the registered name of the effect class ``module:Class`` of a loaded plug-in.

    Never imports: a model token or a calibration document (which may come from a ROS
    parameter write or message) must not run code; plug-ins are loaded beforehand by
    :func:`load_plugin` (``magcal --plugin``, the nodes' start-up parameter ``plugins``).
    """
    mod_name, _, attr = ref.partition(':')
    module = sys.modules.get(mod_name)
    cls = getattr(module, attr, None) if module is not None and attr else None
    name = getattr(cls, 'name', None)
    if name is None or _REGISTRY.get(name) is not cls:
        raise ValueError(f'effect {ref!r} is not loaded: plug-in effects are imported only at '
                         'start-up (magcal --plugin MODULE, ROS start-up parameter plugins), '
                         'never from a model or a calibration file')
    return name


def make_effect(token, sensor):
    """Create the effect ``token`` ('offset', 'aux:aux_motor_current', 'step(300)', ...)."""
    if '(' in token:
        name, args, _ = parse_token(token)
        if name not in _REGISTRY:
            raise ValueError(f'unknown effect {name!r} in {token!r}; known effects: '
                             f'{", ".join(registered_effects())}')
        return _REGISTRY[name].from_args(args, sensor)
    if token.startswith('aux:'):
        return Aux(sensor=sensor, channel=token[4:])
    if token not in _REGISTRY and ':' in token:
        token = _loaded_effect_name(token)
    if token not in _REGISTRY:
        raise ValueError(f'unknown effect {token!r}; known effects: '
                         f'{", ".join(registered_effects())}')
    if needs_args(token):
        raise ValueError(f'effect {token!r} needs arguments: {_REGISTRY[token].usage}')
    return _REGISTRY[token](sensor=sensor)
