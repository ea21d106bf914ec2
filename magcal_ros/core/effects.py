"""Physical error terms ("effects") of a vector magnetometer, composable into a model.

Every sensor j of an array is described by the forward model

    raw_j = A_j @ B + offset_j + sum_k d_k(context, lin_j) + noise,     lin_j = A_j @ B

where ``B`` (nT) is the true field in the array frame (sensor 1's orthogonalised axes) and
``A_j`` is the product of the *linear* effects (composed by matrix product, in the order
scale . nonorthogonality . soft_iron . misalignment, paper 004 eq. 2-3) and ``d_k`` are the
*additive* effects (offset, temperature, drift, nonlinearity, auxiliary currents, field rate),
which add in the raw sensor frame.  This is the composition rule of STYLE.md: linear maps
compose, offsets and driven effects add.

An effect is a small object with named parameters (each with a unit) and either a
``matrix(p)`` (linear effects) or a ``contribution(p, ctx, lin)`` (additive effects).  Users
add their own effects by subclassing :class:`Effect` and calling :func:`register_effect`
(see ``docs/plugins.md``).
"""
from dataclasses import dataclass, field
import importlib

import numpy as np

#: Full-scale field used to normalise the nonlinearity polynomial (nT).
NONLINEARITY_FULL_SCALE_NT = 50000.0


@dataclass
class SensorContext:
    """Driving signals seen by one sensor.

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
    """

    t: np.ndarray
    temp: np.ndarray | None = None
    aux: dict = field(default_factory=dict)
    raw_rate: np.ndarray | None = None

    def subset(self, idx):
        """Return the context restricted to samples ``idx``."""
        return SensorContext(
            t=self.t[idx],
            temp=None if self.temp is None else self.temp[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            raw_rate=None if self.raw_rate is None else self.raw_rate[idx])


class Effect:
    """Base class of an error term.

    Subclasses set ``name``, ``kind`` ('linear' or 'additive'), ``param_names`` and ``units``
    and implement ``matrix`` (linear) or ``contribution`` (additive).  Effects that depend on a
    reference value of a driving signal (mean temperature, start time, mean current) compute it
    in :meth:`prepare` from the calibration data and store it in ``self.refs`` so that live
    correction uses the same reference.
    """

    name = 'effect'
    kind = 'additive'
    param_names = ()
    units = ()
    #: effects that are the same physical degree of freedom, and cannot be combined
    excludes = ()

    def __init__(self, sensor=1, refs=None):
        self.sensor = int(sensor)
        self.refs = dict(refs or {})

    @property
    def n_params(self):
        """Number of parameters."""
        return len(self.param_names)

    @property
    def label(self):
        """Model-spec label of this effect, e.g. ``temperature``."""
        return self.name

    def default_params(self):
        """Parameter values of an ideal sensor (the effect switched off), shape (n_params,)."""
        return np.zeros(self.n_params)

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
        """True if ``contribution`` depends on ``lin`` (needs fixed-point inversion)."""
        return False

    def describe(self):
        """One-line physical description (first docstring line)."""
        return (self.__doc__ or '').strip().splitlines()[0]

    def __repr__(self):
        return f'{type(self).__name__}(sensor={self.sensor})'


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
    """Split an upper-triangular (3, 3) matrix into S = diag(kx, ky, kz) and C_NO angles.

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

    def default_params(self):
        return np.ones(3)

    def matrix(self, p):
        return np.diag(p)


class NonOrthogonality(Effect):
    """Non-orthogonal sensor axes, angles psi, varphi, theta (paper 004 eq. 2, C_NO)."""

    name = 'nonorthogonality'
    kind = 'linear'
    param_names = ('psi', 'varphi', 'theta')
    units = ('rad', 'rad', 'rad')
    excludes = ('soft_iron',)

    def matrix(self, p):
        return nonorthogonality_matrix(*p)


class Misalignment(Effect):
    """Rotation of the sensor's axes relative to sensor 1 (paper 004 eq. 3).

    Sensor 1 defines the array frame, so this effect has no parameters there.
    """

    name = 'misalignment'
    kind = 'linear'
    param_names = ('alpha', 'beta', 'gamma')
    units = ('rad', 'rad', 'rad')
    excludes = ('soft_iron',)

    def matrix(self, p):
        return misalignment_matrix(*p)


class SoftIron(Effect):
    """Full 3x3 linear map (soft iron, paper 002 K = I + D) instead of scale/nonorth./misalignment.

    On sensor 1, which defines the array frame, the matrix is upper triangular (6 parameters):
    its rotation is the frame definition, not something the data can determine.
    """

    name = 'soft_iron'
    kind = 'linear'
    excludes = ('scale', 'nonorthogonality', 'misalignment')
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


# -- additive effects -----------------------------------------------------------------------

class Offset(Effect):
    """Constant offset (hard iron, electronics zero), paper 004 eq. 2 b, in nT."""

    name = 'offset'
    param_names = ('bx', 'by', 'bz')
    units = ('nT', 'nT', 'nT')

    def contribution(self, p, ctx, lin):
        return np.broadcast_to(p, lin.shape)


class Temperature(Effect):
    """Offset and scale drift with sensor temperature: dB = c_off (T-T0) + c_scale (T-T0) * lin."""

    name = 'temperature'
    param_names = ('cx', 'cy', 'cz', 'sx', 'sy', 'sz')
    units = ('nT/degC',) * 3 + ('1/degC',) * 3
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
    """Per-axis quadratic and cubic response: dB = q (lin/F0)^2 + c (lin/F0)^3, F0 = 50 000 nT.

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
    """Response to dB/dt (eddy currents, sensor lag, sampling skew): dB = -tau * d(raw)/dt, s.

    Under pure rotation in a uniform field dB/dt is perpendicular to B, so this term hardly
    shows in the scalar residual; it shows in the inter-sensor vector residual.
    """

    name = 'field_rate'
    param_names = ('tau_x', 'tau_y', 'tau_z')
    units = ('s', 's', 's')

    def check(self, ctx):
        if ctx.raw_rate is None:
            return 'no time derivative of the field available (need a time column t)'
        return None

    def contribution(self, p, ctx, lin):
        return -ctx.raw_rate * p


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


for _cls in (Scale, NonOrthogonality, Misalignment, SoftIron, Offset, Temperature, Drift,
             QuadraticDrift, Nonlinearity, FieldRate):
    register_effect(_cls)

#: the model of paper 004 (offset, scale, nonorthogonality, misalignment)
BASE = ('offset', 'scale', 'nonorthogonality', 'misalignment')


def registered_effects():
    """Names of all registered effects (plus 'aux:<column>')."""
    return sorted(_REGISTRY) + ['aux:<column>']


def load_plugin(ref):
    """Import ``module`` or ``module:Class`` and register the effect classes it names.

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


def make_effect(token, sensor):
    """Create the effect named ``token`` ('offset', 'aux:aux_motor_current', ...) for a sensor."""
    if token.startswith('aux:'):
        return Aux(sensor=sensor, channel=token[4:])
    if token not in _REGISTRY and ':' in token:
        load_plugin(token)
        token = token.partition(':')[2] and getattr(
            importlib.import_module(token.partition(':')[0]), token.partition(':')[2]).name
    if token not in _REGISTRY:
        raise ValueError(f'unknown effect {token!r}; known effects: '
                         f'{", ".join(registered_effects())}')
    return _REGISTRY[token](sensor=sensor)
