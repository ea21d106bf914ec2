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

:class:`ComposedEffect` is an additive effect of one sensor: its contribution is the
coupling's change of the reading for the driver's columns X (:mod:`.drivers`) and the
parameters P (:mod:`.couplings`); scale, linear, nonorth and rotation couplings read the
linear reading (``depends_on_lin``: the correction inverts them by fixed-point iteration,
as for the catalog's temperature scale).  With scope ``alike`` one instance per sensor
shares one parameter set (:attr:`ComposedEffect.shared`, laid out once by the Model).
:class:`FieldEffect` is the ``field`` coupling: an effect of the whole array that changes
the magnitude of the field every sensor sees (``Model.array_shift`` with the field).
"""
from magcal_ros.core.effects.base import Effect
from magcal_ros.core.effects.couplings import per_unit
import numpy as np


class ComposedEffect(Effect):
    """
    coupling(driver) on one sensor: dB = coupling(X P, lin).

    Parameters (``param_names``): c per driver column, named ``<stem>`` for a one-column
    driver (bx, by, bz; kx, ky, kz; ...) or ``<stem>_<column>`` (bx_s1, ...), then the
    driver's own (a lag's tau).
    """

    kind = 'additive'

    def __init__(self, coupling, driver, sensor=1, refs=None, shared=False):
        super().__init__(sensor, refs)
        self.coupling = coupling
        self.driver = driver
        self.shared = bool(shared)
        self.name = f'{coupling.name}({driver.text})'
        cols = driver.column_names
        self._m = len(cols)
        self._c = coupling.n_per_column
        self.param_names = tuple(
            (st if self._m == 1 else f'{st}_{col}') for col in cols for st in coupling.stems
        ) + tuple(driver.param_names)
        self.units = (per_unit(coupling.unit, driver.unit),) * (self._m * self._c) + tuple(
            driver.units)
        self.signals = tuple(driver.signals)
        self._cache = {}

    @property
    def label(self):
        """Term text without the sensor: ``offset(s(t, k=6))``, ``...@alike`` when shared."""
        return self.name + ('@alike' if self.shared else '')

    def describe(self):
        """One-line physical description."""
        return f'{self.coupling.doc}, driven by {self.driver.text}'

    def default_params(self):
        """Coupling switched off; the driver's own parameters at their start (a lag's tau)."""
        return np.concatenate([np.zeros(self._m * self._c), self.driver.default_params()])

    def prepare(self, ctx):
        """Store the driver's reference values (means, ranges, start time) in ``refs``."""
        self.driver.prepare(ctx, self.refs)
        self._cache = {}

    def check(self, ctx):
        """Return None if the data can excite the driver, else the reason why not."""
        return self.driver.check(ctx, self.sensor)

    def depends_on_lin(self):
        """Tell whether the contribution reads the linear reading."""
        return bool(self.coupling.reads_lin or self.driver.reads_lin)

    def columns(self, ctx, lin, q):
        """(N, m) or (N, 3, m) driver columns, cached per context and driver parameters."""
        if self.driver.reads_lin:
            return self.driver.columns(ctx, lin, self.refs, q)
        key = (id(ctx), tuple(np.asarray(q, float)))
        hit = self._cache.get(key)
        if hit is None or hit[0] is not ctx:
            hit = (ctx, self.driver.columns(ctx, lin, self.refs, q))
            if len(self._cache) >= 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = hit
        return hit[1]

    def coupled(self, p, ctx, lin):
        """Return y = X P: (N, c), or (N, 3) for a per-axis driver."""
        mc = self._m * self._c
        x = self.columns(ctx, lin, p[mc:])
        pm = np.asarray(p[:mc], float).reshape(self._m, self._c)
        if x.ndim == 3:
            return np.einsum('nim,mi->ni', x, pm)
        return x @ pm

    def contribution(self, p, ctx, lin):
        """(N, 3) nT added to the raw reading."""
        return self.coupling.contribution(self.coupled(p, ctx, lin), lin)

    def reduces(self, p, stderr, ctx):
        """Say why a fitted lag of zero time constant is the plain coupling, or None."""
        if 'tau' not in self.param_names or len(ctx.t) < 2:
            return None
        i = len(self.param_names) - 1
        tau = abs(float(p[i]))
        se = float(stderr[i]) if stderr is not None else 0.0
        dt = float(np.median(np.diff(ctx.t)))
        if tau < 2.0 * dt or (np.isfinite(se) and tau < 3.0 * se):
            return (f'fitted time constant {tau:.3g} +- {se:.2g} s is no lag: the plain '
                    'coupling of the variable')
        return None

    def __repr__(self):
        return f'ComposedEffect({self.label!r}, sensor={self.sensor})'


class FieldEffect(ComposedEffect):
    """
    field(driver): the field magnitude every sensor sees is F0 + X P (nT).

    An effect of the whole array (``scope = 'array'``): the profiled field B_k of the engine
    lies on the sphere of the reference magnitude F0_k; the field at every sensor is
    B_k (1 + (X P)_k / |B_k|) (:meth:`shift` returns the change).  It is not a site shift:
    the corrected readings keep it (it is the field).
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
