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
A coupling of a driver composed into an :class:`~.base.Effect` the model and engine consume.

:class:`Part` is the one evaluation of coupling(driver); :class:`ComposedEffect` is a
composed term of one sensor (one Part; the catalog's tokens are sums of Parts), shared by
every sensor with scope ``alike``; :class:`FieldEffect` is the ``field`` coupling, an effect
of the whole array on the magnitude of the field every sensor sees.
"""
from magcal_ros.core.effects.base import cached, Effect
from magcal_ros.core.effects.couplings import per_unit
import numpy as np


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
        """One-line physical description."""
        return f'{self.coupling.doc}, driven by {self.driver.text}'

    def default_params(self):
        """Coupling switched off; the driver's own parameters at their start (a lag's tau)."""
        return self.part.default_params()

    def prepare(self, ctx):
        """Store the driver's reference values (means, ranges, start time) in ``refs``."""
        self.driver.prepare(ctx, self.refs)
        self.part.cache = {}

    def check(self, ctx):
        """Return None if the data can excite the driver, else the reason why not."""
        return self.driver.check(ctx, self.sensor)

    def depends_on_lin(self):
        """Tell whether the contribution reads the linear reading."""
        return self.part.reads_lin

    def coupled(self, p, ctx, lin):
        """Return y = X P: (N, c), or (N, 3) for a per-axis driver."""
        return self.part.coupled(p, ctx, lin, self.refs)

    def contribution(self, p, ctx, lin):
        """(N, 3) nT added to the raw reading."""
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
        dm = self.coupling.magnitude(self.coupled(p, ctx, None))
        return b * (dm / np.linalg.norm(b, axis=1))[:, None]

    def magnitude(self, p, ctx):
        """(N,) nT the modelled change of the field magnitude."""
        return self.coupling.magnitude(self.coupled(p, ctx, None))
