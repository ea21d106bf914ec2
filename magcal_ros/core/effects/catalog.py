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
The catalog: the named effects that ship with the library (today's model tokens).

Linear effects (paper 004 eq. 2-3: scale, non-orthogonality, misalignment; soft iron),
additive effects (offset, temperature, drift, nonlinearity, auxiliary channels, field rate),
effects with arguments (steps, sinusoids, lags, polynomials of a channel) and the site
gradient of the array.  In the formula grammar (:mod:`magcal_ros.core.effects.formula`)
each is an alias of a composition coupling(driver)@scope (:mod:`.aliases`), evaluated by
the class below (the same numbers as the composition, test/test_grammar.py).
"""

from magcal_ros.core.effects.base import (channel_name, channel_values, check_channel, Effect,
                                          first_order_lag, format_arg, lag_step,
                                          misalignment_angles, misalignment_matrix,
                                          NONLINEARITY_FULL_SCALE_NT, nonorthogonality_matrix,
                                          parse_number, steps_outside)
from magcal_ros.core.geometry.tensor import symmetric_traceless
import numpy as np


# -- linear effects -------------------------------------------------------------------------


AXIS_NAMES = ('x', 'y', 'z')


def axis_map_matrix(args):
    """
    (3, 3) signed permutation M of an axis map: reading = M @ (the sensor element's axes).

    ``args`` are three of 'x', '-x', 'y', '-y', 'z', '-z' (one per reading axis x, y, z,
    each sensor axis once): ('-x', 'y', 'z') is an x axis read with reversed sign, ('y', 'x',
    'z') the x and y readings exchanged.
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
    out = []
    for row in np.asarray(m):
        k = int(np.argmax(np.abs(row)))
        out.append(('-' if row[k] < 0 else '') + AXIS_NAMES[k])
    return tuple(out)


class AxisMap(Effect):
    """
    How the readings' axes are wired to the sensor's axes: a fixed signed permutation.

    Token ``axes(-x,y,z)@j``: reading x is the sensor's x axis with reversed sign (a coil or
    channel wired with reversed polarity, a mirrored mounting); ``axes(y,x,z)@j``: the x and
    y readings exchanged.  No parameters: A_j = M S C_NO R (the left-most factor, next to the
    reading), so scale and angles stay those of a real sensor (near 1, near 0) and the
    correction A_j^-1 undoes the map.  Found by the calibration when a fitted A_j has
    det < 0 or a negative scale (:mod:`magcal_ros.core.model.plausibility`).
    """

    name = 'axes'
    kind = 'linear'
    usage = 'axes(<+-x|y|z>,<+-x|y|z>,<+-x|y|z>)'
    linear_order = -10

    @classmethod
    def from_args(cls, args, sensor=1):
        m = axis_map_matrix(args)
        eff = cls(sensor=sensor)
        eff.map = m
        eff.args = axis_map_args(m)
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
        times = sorted(parse_number(a, 'step time [s]') for a in args)
        eff = cls(sensor=sensor)
        eff.times = np.array(times)
        eff.args = tuple(format_arg(x) for x in times)
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
        return steps_outside(self.times, ctx.t)

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
        f = parse_number(args[0], 'periodic frequency [Hz]')
        if f <= 0:
            raise ValueError(f'periodic frequency must be positive, got {args[0]!r}')
        eff = cls(sensor=sensor)
        eff.freq_hz = f
        eff.args = (format_arg(f),)
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
        eff.channel = channel_name(args[0])
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
        a = channel_values(ctx, self.channel)
        if a is not None and np.isfinite(a).any():
            self.refs.setdefault('x0', float(np.nanmean(a)))

    def check(self, ctx):
        return check_channel(ctx, self.channel, self.sensor)

    def lagged(self, ctx, tau):
        """(N,) the channel through the lag of time constant ``tau`` s, at ``ctx``'s samples."""
        whole, idx = ctx.whole()
        if idx is None and len(ctx.t) == 1:
            return self._online(float(ctx.t[0]), channel_values(ctx, self.channel), tau)
        x = channel_values(whole, self.channel)
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
        self._state, y = lag_step(self.__dict__.get('_state'), t, x, tau)
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
        eff.channel = channel_name(args[0])
        if eff.channel == 'temperature':
            raise ValueError('aux_poly couples an auxiliary channel (aux_<name>), not the '
                             'temperature')
        d = parse_number(args[1], 'aux_poly degree')
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
        return check_channel(ctx, self.channel, self.sensor)

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
