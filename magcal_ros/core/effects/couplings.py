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
Couplings: how a driver's columns X enter the reading (docs/formulas.md has the table).

With X (N, m) and parameters P (m, c), c per column, a coupling is the change dB (N, 3) nT
of a sensor's reading, lin = A B its linear reading.  ``nonorth`` and ``rotation`` vary the
angles of paper 004 eq. 2 and 3 to first order: dB = dC lin, dC = [[0, varphi, theta],
[0, 0, psi], [0, 0, 0]], and dB = W lin, W = [[0, alpha, -gamma], [-alpha, 0, beta],
[gamma, -beta, 0]].  Per-axis drivers (X (N, 3, m)) act axis by axis, dB_i = sum_k X_ik P_ki.

A coupling of a driver is composed into an :class:`~.base.Effect` here: :class:`Part` is the
one evaluation of coupling(driver); :class:`ComposedEffect` is a composed term of one sensor
(one Part; the catalog's tokens are sums of Parts), shared by every sensor with scope
``alike``; :class:`FieldEffect` is the ``field`` coupling, an effect of the whole array on
the magnitude of the field every sensor sees.
"""
from magcal_ros.core.effects.base import cached, Effect, Registry
import numpy as np


def per_unit(num, du):
    """Return the unit ``num`` per driver unit ``du``: 'nT' per 'degC' -> 'nT/degC'."""
    if du == '1':
        return num
    if num == 'nT' and du == 'nT/s':
        return 's'
    return f'{num}/({du})' if ('/' in du or '*' in du) else f'{num}/{du}'


class Coupling:
    """
    Base class of a coupling (a plug-in subclasses it and calls :func:`register_coupling`).

    Subclasses set the attributes below and implement :meth:`contribution` (or, for
    ``scope = 'array'``, :meth:`magnitude`).
    """

    name = 'coupling'
    #: names of the parameters of one driver column (c per column)
    stems = ()
    #: unit of a parameter times a unit of the driver
    unit = 'nT'
    #: True when the change reads the linear reading lin (fixed-point correction)
    reads_lin = False
    #: True when per-axis drivers (rate, lin) are allowed
    per_axis_ok = False
    #: 'array' for a coupling of the whole array (the field), else None
    scope = None
    #: one line for the documentation and the error messages
    doc = ''

    @property
    def n_per_column(self):
        """Return c, the number of parameters per driver column."""
        return len(self.stems)

    def contribution(self, y, lin):
        """
        (N, 3) nT change of the reading.

        ``y`` is X P: (N, c) for a scalar driver, (N, 3) for a per-axis one (already summed
        axis by axis); ``lin`` (N, 3) nT the linear reading.
        """
        raise NotImplementedError


class Offset(Coupling):
    """Additive in the sensor's axes: dB = X P."""

    name = 'offset'
    stems = ('bx', 'by', 'bz')
    unit = 'nT'
    per_axis_ok = True
    doc = 'additive in the sensor axes, dB = X P (nT per driver unit)'

    def contribution(self, y, lin):
        return y


class Scale(Coupling):
    """Scale factors follow the driver: dB_i = (X P)_i lin_i."""

    name = 'scale'
    stems = ('kx', 'ky', 'kz')
    unit = '1'
    reads_lin = True
    per_axis_ok = True
    doc = 'scale factors vary, dB_i = (X P)_i lin_i (1 per driver unit)'

    def contribution(self, y, lin):
        return y * lin


class Linear(Coupling):
    """All nine entries of the linear map follow the driver: dB = (sum_k X_k P_k) lin."""

    name = 'linear'
    stems = ('k11', 'k12', 'k13', 'k21', 'k22', 'k23', 'k31', 'k32', 'k33')
    unit = '1'
    reads_lin = True
    doc = 'all 9 entries of the linear map vary, dB = M lin (1 per driver unit)'

    def contribution(self, y, lin):
        return np.einsum('nij,nj->ni', y.reshape(-1, 3, 3), lin)


class NonOrth(Coupling):
    """The non-orthogonality angles (psi, varphi, theta) follow the driver (eq. 2, 1st order)."""

    name = 'nonorth'
    stems = ('psi', 'varphi', 'theta')
    unit = 'rad'
    reads_lin = True
    doc = 'non-orthogonality angles vary (rad per driver unit)'

    def contribution(self, y, lin):
        out = np.zeros_like(lin)
        out[:, 0] = y[:, 1] * lin[:, 1] + y[:, 2] * lin[:, 2]
        out[:, 1] = y[:, 0] * lin[:, 2]
        return out


class Rotation(Coupling):
    """The orientation angles (alpha, beta, gamma) follow the driver (eq. 3, 1st order)."""

    name = 'rotation'
    stems = ('alpha', 'beta', 'gamma')
    unit = 'rad'
    reads_lin = True
    doc = 'orientation angles vary (rad per driver unit)'

    def contribution(self, y, lin):
        a, b, g = y[:, 0], y[:, 1], y[:, 2]
        return np.stack([a * lin[:, 1] - g * lin[:, 2],
                         -a * lin[:, 0] + b * lin[:, 2],
                         g * lin[:, 0] - b * lin[:, 1]], axis=1)


class Field(Coupling):
    """The field itself, common to every sensor: magnitude F0 + X P."""

    name = 'field'
    stems = ('f',)
    unit = 'nT'
    scope = 'array'
    doc = 'the field magnitude itself varies, F = F0 + X P, common to every sensor'

    def magnitude(self, y):
        """(N,) nT change of the field magnitude, ``y`` = X P (N, 1)."""
        return y[:, 0]


#: the couplings ``name(driver)`` by name, those that ship first (docs/plugins.md)
COUPLINGS = Registry(Coupling, 'coupling', 'magcal_ros.core.effects.couplings.Coupling',
                     (Offset, Scale, Linear, NonOrth, Rotation, Field))
register_coupling = COUPLINGS.register
unregister_coupling = COUPLINGS.unregister
coupling_class = COUPLINGS.get
registered_couplings = COUPLINGS.names


class Part:
    """
    coupling(driver): dB = coupling(X P, lin), the grammar's one evaluation of a term.

    Parameters: c per driver column, ``<stem>`` for a one-column driver (bx, by, bz) or
    ``<stem>_<column>`` (bx_s1, ...), then the driver's own (a lag's tau).
    """

    def __init__(self, coupling, driver):
        self.coupling, self.driver = coupling, driver
        cols = driver.column_names
        self.m, self.c = len(cols), coupling.n_per_column
        self.param_names = tuple(
            (st if self.m == 1 else f'{st}_{col}') for col in cols for st in coupling.stems
        ) + tuple(driver.param_names)
        self.units = (per_unit(coupling.unit, driver.unit),) * (self.m * self.c) + tuple(
            driver.units)
        self.cache = {}

    @property
    def text(self):
        """Canonical text, ``offset(s(t, k=6))``."""
        return f'{self.coupling.name}({self.driver.text})'

    @property
    def reads_lin(self):
        """Tell whether the change reads the linear reading."""
        return bool(self.coupling.reads_lin or self.driver.reads_lin)

    def default_params(self):
        """Coupling switched off; the driver's own parameters at their start (a lag's tau)."""
        return np.concatenate([np.zeros(self.m * self.c), self.driver.default_params()])

    def columns(self, ctx, lin, q, refs):
        """(N, m) or (N, 3, m) driver columns, cached per context and driver parameters."""
        if self.driver.reads_lin:
            return self.driver.columns(ctx, lin, refs, q)
        return cached(self.cache, (id(ctx), tuple(np.asarray(q, float))), ctx,
                      lambda: self.driver.columns(ctx, lin, refs, q), 8)

    def coupled(self, p, ctx, lin, refs):
        """Return y = X P: (N, c), or (N, 3) for a per-axis driver."""
        mc = self.m * self.c
        x = self.columns(ctx, lin, p[mc:], refs)
        pm = np.asarray(p[:mc], float).reshape(self.m, self.c)
        if x.ndim == 3:
            return np.einsum('nim,mi->ni', x, pm)
        return x @ pm

    def contribution(self, p, ctx, lin, refs):
        """(N, 3) nT added to the raw reading."""
        return self.coupling.contribution(self.coupled(p, ctx, lin, refs), lin)


def no_lag(tau, se, ctx, what):
    """
    Say why a fitted time constant ``tau`` +- ``se`` s is no lag, or return None.

    Below two sample intervals, or within 3 standard uncertainties of zero, the lag is the
    plain coupling of ``what`` (the variable), which the diagnosis then prefers.
    """
    tau, se = abs(float(tau)), float(se) if se is not None else 0.0
    if len(ctx.t) < 2:
        return None
    dt = float(np.median(np.diff(ctx.t)))
    if tau < 2.0 * dt or (np.isfinite(se) and tau < 3.0 * se):
        return (f'fitted time constant {tau:.3g} +- {se:.2g} s is no lag (below '
                f'{max(2 * dt, 3 * se):.3g} s): the plain coupling of {what}')
    return None


class ComposedEffect(Effect):
    """coupling(driver) on one sensor: one :class:`Part`, parameters named as the Part's."""

    kind = 'additive'

    def __init__(self, coupling, driver, sensor=1, refs=None, shared=False):
        super().__init__(sensor, refs)
        self.part = Part(coupling, driver)
        self.coupling, self.driver, self.shared = coupling, driver, bool(shared)
        self.name, self.param_names, self.units = (self.part.text, self.part.param_names,
                                                   self.part.units)
        self.signals = tuple(driver.signals)

    @property
    def label(self):
        """Term text without the sensor: ``offset(s(t, k=6))``, ``...@alike`` when shared."""
        return self.name + ('@alike' if self.shared else '')

    def describe(self):
        return f'{self.coupling.doc}, driven by {self.driver.text}'

    def default_params(self):
        """Coupling switched off; the driver's own parameters at their start (a lag's tau)."""
        return self.part.default_params()

    def prepare(self, ctx):
        """Store the driver's reference values (means, ranges, start time) in ``refs``."""
        self.driver.prepare(ctx, self.refs)
        self.part.cache = {}

    def check(self, ctx):
        return self.driver.check(ctx, self.sensor)

    def depends_on_lin(self):
        return self.part.reads_lin

    def coupled(self, p, ctx, lin):
        """Return y = X P: (N, c), or (N, 3) for a per-axis driver."""
        return self.part.coupled(p, ctx, lin, self.refs)

    def contribution(self, p, ctx, lin):
        return self.part.contribution(p, ctx, lin, self.refs)

    def reduces(self, p, stderr, ctx):
        """Say why a fitted lag of zero time constant is the plain coupling, or None."""
        if 'tau' not in self.param_names:
            return None
        return no_lag(p[-1], None if stderr is None else stderr[-1], ctx, 'the variable')

    def __repr__(self):
        return f'ComposedEffect({self.label!r}, sensor={self.sensor})'


class FieldEffect(ComposedEffect):
    """
    field(driver): the field magnitude every sensor sees is F0 + X P (nT).

    An effect of the whole array: the field at every sensor is B_k (1 + (X P)_k / |B_k|),
    B_k the engine's profiled field of magnitude F0_k (:meth:`shift` returns the change).
    The corrected readings keep it (it is the field).
    """

    kind = 'array'
    scope = 'array'
    #: the shift reads the field (Model.array_shift passes it)
    reads_field = True

    @property
    def label(self):
        """Term text (always of the whole array)."""
        return self.name

    def shift(self, p, ctx, j, b=None):
        """(N, 3) nT change of the field at sensor j, along the field ``b`` (N, 3) nT."""
        if b is None:
            return np.zeros((len(ctx.t), 3))
        return b * (self.magnitude(p, ctx) / np.linalg.norm(b, axis=1))[:, None]

    def magnitude(self, p, ctx):
        """(N,) nT the modelled change of the field magnitude."""
        return self.coupling.magnitude(self.coupled(p, ctx, None))
