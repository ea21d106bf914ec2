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
The catalog: the named effects that ship with the library (the model tokens).

The constant linear map (paper 004 eq. 2-3; soft iron; an axis map), the offset and the
site gradient are effects of their own.  Every driven token (temperature, drift, step(T),
...) is a composition coupling(driver) (:data:`TOKENS`), evaluated by :class:`~.couplings.Part`
under the token's own parameter names and references, so that old calibration files load
and correct as they did (docs/formulas.md).  Effects, couplings and drivers each have a
:class:`.base.Registry` (docs/plugins.md); plug-ins are imported only at start-up (``magcal
--plugin``, the nodes' ``plugins`` parameter), never from a model or a calibration file.
"""
import importlib
import sys

from magcal_ros.core.effects import drivers as dv
from magcal_ros.core.effects.attitude_ref import AttitudeFull, AttitudeReference
from magcal_ros.core.effects.base import (channel_name, Effect, format_arg, misalignment_angles,
                                          misalignment_matrix, nonorthogonality_matrix,
                                          parse_number, Registry, split_params)
from magcal_ros.core.effects.couplings import coupling_class, COUPLINGS, no_lag, Part
from magcal_ros.core.geometry.tensor import symmetric_traceless
import numpy as np


AXIS_NAMES = ('x', 'y', 'z')


def axis_map_matrix(args):
    """
    (3, 3) signed permutation M of an axis map: reading = M @ (the sensor element's axes).

    ``args`` are three of 'x', '-x', 'y', '-y', 'z', '-z', one per reading axis, each sensor
    axis once: ('-x', 'y', 'z') is an x axis read with reversed sign.
    """
    m = np.zeros((3, 3))
    for i, a in enumerate(args):
        a = str(a).strip().lower().lstrip('+')
        sign = -1.0 if a.startswith('-') else 1.0
        name = a.lstrip('-')
        if name not in AXIS_NAMES:
            raise ValueError(f'axes(...): {a!r} is not one of x, -x, y, -y, z, -z')
        m[i, AXIS_NAMES.index(name)] = sign
    if len(args) != 3 or not np.allclose(np.abs(m).sum(axis=0), 1):
        raise ValueError(f'axes({",".join(map(str, args))}): give each of x, y, z once, with '
                         'an optional sign, for the readings x, y, z, e.g. axes(-x,y,z)')
    return m


def axis_map_args(m):
    """Inverse of :func:`axis_map_matrix`: the three tokens of a (3, 3) signed permutation."""
    m = np.asarray(m)
    k = np.argmax(np.abs(m), axis=1)
    return tuple(('-' if m[i, k[i]] < 0 else '') + AXIS_NAMES[k[i]] for i in range(3))


class AxisMap(Effect):
    """
    How the readings' axes are wired to the sensor's axes: a fixed signed permutation.

    ``axes(-x,y,z)@j``: reading x is the sensor's x axis reversed; ``axes(y,x,z)@j``: x and
    y exchanged.  No parameters: A_j = M S C_NO R.  Proposed when a fitted A_j has det < 0 or
    a negative scale (:mod:`magcal_ros.core.model.plausibility`).
    """

    name = 'axes'
    kind = 'linear'
    usage = 'axes(<+-x|y|z>,<+-x|y|z>,<+-x|y|z>)'
    linear_order = -10

    @classmethod
    def from_args(cls, args, sensor=1):
        eff = cls(sensor=sensor)
        eff.map = axis_map_matrix(args)
        eff.args = axis_map_args(eff.map)
        return eff

    def matrix(self, p):
        return self.map


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
    """Rotation of the sensor's axes relative to sensor 1 (paper 004 eq. 3; none on sensor 1)."""

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
        return np.eye(3)[np.triu_indices(3)] if self.sensor == 1 else np.eye(3).ravel()

    def matrix(self, p):
        if self.sensor == 1:
            m = np.zeros((3, 3))
            m[np.triu_indices(3)] = p
            return m
        return np.asarray(p).reshape(3, 3)

    def params_from_linear(self, parts):
        return parts.a[np.triu_indices(3)] if self.sensor == 1 else parts.a.ravel()


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

    def expansion(self, at=''):
        """Return the composition the token stands for, ``offset(1)@2`` (``at``: '@2')."""
        return 'offset(1)' + at


class Composition:
    """
    What one token with its arguments stands for: coupling(driver) parts and its bookkeeping.

    ``parts`` [(coupling name, Driver)]; ``params``, ``units`` the token's own; ``refs``
    {token's reference: (how, variable, the drivers' reference)}, how 'mean' or 'first'
    (the first time); ``fixed`` constant references of the drivers; ``sign`` and ``lead``
    (zero parameters before the token's) map the token's parameters onto the parts'.
    """

    def __init__(self, args, parts, params, units, refs=None, fixed=None, sign=1.0, lead=0,
                 label=None, supersedes=(), note=''):
        self.args, self.parts, self.params, self.units = tuple(args), parts, params, units
        self.refs, self.fixed = refs or {}, fixed or {}
        self.sign, self.lead, self.label = sign, lead, label
        self.supersedes, self.note = tuple(supersedes), note


class TokenEffect(Effect):
    """
    A token of the catalog (``temperature``, ``lag(temperature)``, ...): grammar parts, summed.

    The token keeps the parameter names, units and references (``t0_c``, ``t0_s``, ``a0``,
    ``x0``) of the calibration files; :func:`token_class` makes its class from its row.
    """

    kind = 'additive'
    #: the token's row of :data:`TOKENS`
    row = None

    def __init__(self, sensor=1, refs=None, args=()):
        super().__init__(sensor, refs)
        self.comp = comp = self.row.compose(tuple(args))
        self.args, self.param_names, self.units = comp.args, comp.params, comp.units
        self.supersedes = comp.supersedes
        self.parts = [Part(coupling_class(c)(), d) for c, d in comp.parts]
        self._seen = None

    @classmethod
    def from_args(cls, args, sensor=1):
        if cls.usage is None:
            return super().from_args(args, sensor)
        return cls(sensor=sensor, args=args)

    @classmethod
    def suggest_args(cls, ctx):
        """Argument tuples worth testing on data ``ctx`` (lag, aux_poly: its channels)."""
        return cls.row.suggest(ctx) if cls.row.suggest else []

    @property
    def label(self):
        """Model-spec label: ``temperature``, ``step(300)``, ``aux:aux_x``."""
        return self.comp.label or super().label

    @property
    def signals(self):
        """Driving signals of the parts' drivers."""
        return tuple(dict.fromkeys(s for p in self.parts for s in p.driver.signals))

    def default_params(self):
        """Start at the parts' own values (a lag's tau); zero for a mapped token."""
        if self.comp.sign != 1.0 or self.comp.lead:
            return np.zeros(self.n_params)
        return np.concatenate([p.default_params() for p in self.parts])

    def prepare(self, ctx):
        """Store the token's reference values computed from the calibration data."""
        for key, (how, v, _) in self.comp.refs.items():
            if how == 'first':
                self.refs.setdefault(key, float(ctx.t[0]) if len(ctx.t) else 0.0)
            else:
                a = dv.variable_values(ctx, v)
                if a is not None and np.isfinite(a).any():
                    self.refs.setdefault(key, float(np.nanmean(a)))

    def check(self, ctx):
        why = next(filter(None, (p.driver.check(ctx, self.sensor) for p in self.parts)), None)
        return why or (self.row.check(self, ctx) if self.row.check else None)

    def expansion(self, at=''):
        """Return the composition the token stands for, ``offset(t)@2`` (``at``: '@2')."""
        return ' + '.join(p.text + at for p in self.parts) + self.comp.note

    def depends_on_lin(self):
        return any(p.reads_lin for p in self.parts)

    def _refs(self):
        """Map the token's reference values onto the drivers' (caches cleared on a change)."""
        if self._seen != self.refs:
            self._seen = dict(self.refs)
            self._driver_refs = dict(self.comp.fixed, **{
                new: self.refs[key] for key, (_, _, new) in self.comp.refs.items()
                if key in self.refs})
            for p in self.parts:
                p.cache = {}
        return self._driver_refs

    def contribution(self, p, ctx, lin):
        """(N, 3) nT added to the raw reading: the sum of the parts'."""
        refs = self._refs()
        q = np.concatenate([np.zeros(self.comp.lead), self.comp.sign * np.asarray(p, float)])
        out = 0.0
        for part, qp in zip(self.parts, split_params(q, [len(p.param_names) for p in self.parts])):
            out = out + part.contribution(qp, ctx, lin, refs)
        return out


def _channel_arg(args, example):
    if len(args) != 1:
        raise ValueError(f'{example.partition("(")[0]} needs one channel, e.g. {example}')
    return channel_name(args[0])


def _temperature(args):
    v = dv.Variable('temperature')
    return Composition(args, [('offset', v), ('scale', v)], ('cx', 'cy', 'cz', 'sx', 'sy', 'sz'),
                       ('nT/degC',) * 3 + ('1/degC',) * 3,
                       refs={'t0_c': ('mean', 'temperature', 'temperature0')})


def _drift(degree):
    def compose(args):
        names = ('dx', 'dy', 'dz', 'qx', 'qy', 'qz')[:3 * degree]
        units = ('nT/s',) * 3 + ('nT/s^2',) * 3
        if degree == 1:
            return Composition(args, [('offset', dv.Variable('t'))], names, units[:3],
                               refs={'t0_s': ('first', 't', 't0')})
        return Composition(args, [('offset', dv.Poly.from_args(['t', '2'], {}))], names, units,
                           refs={'t0_s': ('first', 't', 'mean')}, fixed=UNSCALED)
    return compose


def _nonlinearity(args):
    return Composition(args, [('offset', dv.Poly.from_args(['lin', '3'], {}))],
                       ('qx', 'qy', 'qz', 'cx', 'cy', 'cz'), ('nT',) * 6, lead=3,
                       note=' without the linear column (degrees 2 and 3)')


def _aux(args):
    ch = _channel_arg(args, 'aux:aux_motor_current') if args else 'aux_current'
    return Composition((), [('offset', dv.Variable(ch))], ('vx', 'vy', 'vz'), ('nT/unit',) * 3,
                       refs={'a0': ('mean', ch, ch + '0')}, label='aux:' + ch)


def _aux_poly(args):
    if len(args) != 2:
        raise ValueError('aux_poly needs a channel and a degree, e.g. '
                         'aux_poly(aux_motor_current,2)')
    ch = channel_name(args[0])
    if ch == 'temperature':
        raise ValueError('aux_poly couples an auxiliary channel (aux_<name>), not the '
                         'temperature')
    d = parse_number(args[1], 'aux_poly degree')
    if d != int(d) or not 2 <= d <= 4:
        raise ValueError(f'aux_poly degree must be 2, 3 or 4, got {args[1]!r}')
    d = int(d)
    return Composition((ch, str(d)), [('offset', dv.Poly.from_args([ch, str(d)], {}))],
                       tuple(f'v{k if k > 1 else ""}{ax}' for k in range(1, d + 1)
                             for ax in 'xyz'),
                       tuple('nT/unit' if k == 1 else f'nT/unit^{k}'
                             for k in range(1, d + 1) for _ in 'xyz'),
                       refs={'a0': ('mean', ch, 'mean')}, fixed=UNSCALED,
                       supersedes=('aux:' + ch,))


def _step(args):
    d = dv.Steps.from_args(list(args), {})
    k = len(d.times)
    return Composition(tuple(format_arg(x) for x in d.times), [('offset', d)],
                       ('sx', 'sy', 'sz') if k == 1 else tuple(
                           f's{i}{ax}' for i in range(1, k + 1) for ax in 'xyz'),
                       ('nT',) * (3 * k))


def _periodic(args):
    if len(args) != 1:
        raise ValueError('periodic needs one frequency in Hz, e.g. periodic(0.23)')
    f = parse_number(args[0], 'periodic frequency [Hz]')
    if f <= 0:
        raise ValueError(f'periodic frequency must be positive, got {args[0]!r}')
    return Composition((format_arg(f),), [('offset', dv.Sinusoid.from_args([args[0]], {}))],
                       ('ax', 'ay', 'az', 'bx', 'by', 'bz'), ('nT',) * 6,
                       refs={'t0_s': ('first', 't', 't0')})


def _lag(args):
    ch = _channel_arg(args, 'lag(temperature) or lag(aux_motor_current)')
    u = 'nT/degC' if ch == 'temperature' else 'nT/unit'
    return Composition((ch,), [('offset', dv.Lagged.from_args([ch], {}))],
                       ('cx', 'cy', 'cz', 'tau'), (u, u, u, 's'),
                       refs={'x0': ('mean', ch, 'mean')})


def _field_rate(args):
    return Composition(args, [('offset', dv.Variable('rate'))], ('tau_x', 'tau_y', 'tau_z'),
                       ('s',) * 3, sign=-1.0, note=' (dB = -tau rate, tau in s)')


def _min_span(v, least, what):
    """Check that ``v`` spans at least ``least`` (its unit), else ``what(sensor, span)``."""
    def check(eff, ctx):
        a = dv.variable_values(ctx, v)
        span = float(np.nanmax(a) - np.nanmin(a))
        return what(eff.sensor, span) if span < least else None
    return check


def _finite(eff, ctx):
    for p in eff.parts:
        a = dv.variable_values(ctx, p.driver.v)
        if p.driver.v.startswith('aux_') and not np.isfinite(a).all():
            return f'auxiliary channel {p.driver.v!r} contains non-finite values'
    return None


class Token:
    """A row of :data:`TOKENS`: how the token is written, composed, checked and proposed."""

    def __init__(self, doc, compose, usage=None, check=None, suggest=None, lag=False):
        self.doc, self.compose, self.usage = doc, compose, usage
        self.check, self.suggest, self.lag = check, suggest, lag


def _lag_reduces(self, p, stderr, ctx):
    """Say why the fitted lag is no lag (tau indistinguishable from 0): the plain coupling."""
    return no_lag(p[3], None if stderr is None else stderr[3], ctx, self.args[0])


#: references of a polynomial of unscaled powers (v - v0)^k: half range 1
UNSCALED = {'lo': -1.0, 'hi': 1.0}

_DRIFT_SPAN = _min_span('t', 1.0, lambda j, span: (
    f'the data span only {span:.2f} s: drift cannot be separated from the offset'))

#: today's tokens: name -> row (docstring, composition of the arguments, ...)
TOKENS = {
    'temperature': Token(
        'Offset and scale drift with sensor temperature: dB = c_off (T-T0) + c_scale (T-T0) '
        '* lin.', _temperature, check=_min_span('temperature', 1.0, lambda j, span: (
            f'temperature of sensor {j} varies only {span:.2f} degC (< 1 degC): heat or cool '
            'the sensor by several degC during the calibration, or drop the temperature '
            'effect'))),
    'drift': Token('Offset drifting linearly in time: dB = d1 (t - t0), nT/s.', _drift(1),
                   check=_DRIFT_SPAN),
    'drift2': Token('Offset drifting quadratically in time: dB = d1 (t - t0) + d2 (t - t0)^2.',
                    _drift(2), check=_DRIFT_SPAN),
    'nonlinearity': Token(
        'Per-axis quadratic and cubic response: dB = q (lin/F0)^2 + c (lin/F0)^3, '
        'F0 = 50 000 nT.', _nonlinearity),
    'aux': Token('Linear coupling of an auxiliary channel (e.g. a motor current): '
                 'dB = v (a - a0).', _aux, check=_finite),
    'field_rate': Token(
        'Response to dB/dt (eddy currents, sensor lag, sampling skew): dB = -tau * d(raw)/dt, '
        's.', _field_rate),
    'step': Token('Offset change(s) at given times: dB = sum_k s_k [t >= t_k], nT (a jump, '
                  'a relay).', _step, usage='step(<t_s>[,<t_s>...])'),
    'periodic': Token('Sinusoidal interference at a given frequency (pump, fan, wheel): '
                      'dB = a cos(2 pi f (t - t0)) + b sin(2 pi f (t - t0)).', _periodic,
                      usage='periodic(<f_hz>)'),
    'lag': Token('A channel (temperature or aux) acting through a first-order lag: '
                 'dB = c (y - x0), tau dy/dt = x - y.', _lag,
                 usage='lag(temperature|aux_<name>)', check=_finite, lag=True,
                 suggest=lambda ctx: ([('temperature',)] if ctx.temp is not None else [])
                 + [(c,) for c in sorted(ctx.aux)]),
    'aux_poly': Token('Polynomial coupling of an auxiliary channel: dB = sum_k v_k (a - a0)^k, '
                      'k = 1..d, nT.', _aux_poly, usage='aux_poly(aux_<name>,<degree>)',
                      check=_finite, suggest=lambda ctx: [(c, '2') for c in sorted(ctx.aux)]),
}


def token_class(name):
    """Make the :class:`TokenEffect` class of token ``name`` (what the registry holds)."""
    row = TOKENS[name]
    attrs = {'name': name, 'row': row, 'usage': row.usage, '__doc__': row.doc}
    if row.lag:
        attrs['reduces'] = _lag_reduces
    return type(f'Token_{name}', (TokenEffect,), attrs)


#: the class of every token, by name
TOKEN_CLASSES = {name: token_class(name) for name in TOKENS}


class SiteGradient(Effect):
    """
    Constant gradient of the site in the world frame, seen through the known attitude.

    B_j = B_c + R^T G_w R r_j at sensor j (position r_j, m), B_c the field at the centre, R
    body-to-world (``SensorContext.attitude``), G_w (nT/m) symmetric traceless: 5 parameters
    of the array.  The positions are kept in ``refs`` (x1, y1, z1, x2, ...; m).
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
        self.refs.update({f'{a}{j}': float(v) for j, r in
                          enumerate(np.asarray(positions, float), start=1)
                          for a, v in zip('xyz', r)})

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


#: the named effects, the catalog's then plug-ins
EFFECTS = Registry(Effect, 'effect', 'magcal_ros.core.effects.Effect', (
    AxisMap, Scale, NonOrthogonality, Misalignment, SoftIron, Offset,
    *(TOKEN_CLASSES[n] for n in ('temperature', 'drift', 'drift2', 'nonlinearity', 'field_rate',
                                 'step', 'periodic', 'lag', 'aux_poly')),
    SiteGradient, AttitudeReference, AttitudeFull))
register_effect = EFFECTS.register
unregister_effect = EFFECTS.unregister
#: the Effect class registered as a name (without arguments), or None
effect_class = EFFECTS.get
#: names of the effects that ship with the library
BUILTIN_EFFECTS = EFFECTS.builtin

#: the model of paper 004 (offset, scale, nonorthogonality, misalignment)
BASE = ('offset', 'scale', 'nonorthogonality', 'misalignment')


def registered_effects():
    """Names of all registered effects (plus 'aux:<column>')."""
    return EFFECTS.names() + ['aux:<column>']


def needs_args(name):
    """Tell whether the registered effect ``name`` is only written with arguments."""
    cls = EFFECTS.get(name)
    return cls is not None and cls.usage is not None


def load_plugin(ref):
    """
    Import ``module`` or ``module:Class`` and register the classes it names; return the names.

    A module may list ``MAGCAL_EFFECTS``, ``MAGCAL_COUPLINGS`` and ``MAGCAL_DRIVERS``, or
    call the ``register_*`` functions itself; ``module:Class`` registers that one class.
    Each effect class is first probed on its declared signals
    (:func:`magcal_ros.core.effects.safety.probe_effect`): one that reads an undeclared
    signal, or fails, is refused (ValueError naming the effect and the signal).
    """
    from magcal_ros.core.effects.safety import probe_effect   # here: it imports the package
    mod_name, _, attr = ref.partition(':')
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ValueError(f'cannot import effect plugin {ref!r}: {exc}') from exc
    classes = [getattr(mod, attr)] if attr else [
        c for key in ('MAGCAL_EFFECTS', 'MAGCAL_COUPLINGS', 'MAGCAL_DRIVERS')
        for c in getattr(mod, key, [])]
    names = []
    for cls in classes:
        registry = next((r for r in (COUPLINGS, dv.DRIVERS)
                         if isinstance(cls, type) and issubclass(cls, r.base)), EFFECTS)
        if registry.get(cls.name) is not cls:
            if registry is EFFECTS and isinstance(cls, type) and issubclass(cls, Effect):
                probe_effect(cls, ref)
            registry.register(cls)
        names.append(cls.name)
    return names


def parse_token(token):
    """'step(120,300)@2' -> ('step', ('120', '300'), 2); 'drift' -> ('drift', (), None)."""
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
    """Return the names :func:`load_plugin` registers for each of ``refs``, in order."""
    return [name for ref in refs or () for name in load_plugin(ref)]


def _loaded_effect_name(ref):
    """
    Return the registered name of the effect class ``module:Class`` of a loaded plug-in.

    Never imports: a model token or a calibration document (which may come from a ROS
    parameter write or message) must not run code.
    """
    mod_name, _, attr = ref.partition(':')
    module = sys.modules.get(mod_name)
    cls = getattr(module, attr, None) if module is not None and attr else None
    name = getattr(cls, 'name', None)
    if name is None or EFFECTS.get(name) is not cls:
        raise ValueError(f'effect {ref!r} is not loaded: plug-in effects are imported only at '
                         'start-up (magcal --plugin MODULE, ROS start-up parameter plugins), '
                         'never from a model or a calibration file')
    return name


def make_catalog_effect(token, sensor):
    """Create the catalog effect ``token`` ('offset', 'aux:aux_motor_current', 'step(300)')."""
    if '(' in token:
        name, args, _ = parse_token(token)
        cls = EFFECTS.get(name)
        if cls is None:
            raise ValueError(f'unknown effect {name!r} in {token!r}; known effects: '
                             f'{", ".join(registered_effects())}')
        return cls.from_args(args, sensor)
    if token.startswith('aux:'):
        return TOKEN_CLASSES['aux'](sensor=sensor, args=(token[4:],))
    if EFFECTS.get(token) is None and ':' in token:
        token = _loaded_effect_name(token)
    cls = EFFECTS.get(token)
    if cls is None:
        raise ValueError(f'unknown effect {token!r}; known effects: '
                         f'{", ".join(registered_effects())}')
    if cls.usage is not None:
        raise ValueError(f'effect {token!r} needs arguments: {cls.usage}')
    return cls(sensor=sensor)
