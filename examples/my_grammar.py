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
Example grammar plug-in: a new driver and a new coupling (docs/plugins.md, docs/formulas.md).

- driver ``relay(aux_<name>, threshold=X)``: 1 while a recorded channel is above X, else 0
  (a relay or a heater switched by a thermostat; the channel's own value does not matter);
- coupling ``zoffset(driver)``: an offset along the sensor's z axis only, one parameter per
  driver column (a compensation coil wound around z).

Both combine with everything built in: ``base + zoffset(relay(aux_motor_current,
threshold=4))@2``, ``offset(relay(aux_heater_power, threshold=5) * t)``, ``zoffset(s(t, k=4))``.
Load with ``magcal ... --plugin my_grammar`` or ``load_plugin('my_grammar')``.
"""
from magcal_ros.core.effects import Coupling, Driver
from magcal_ros.core.effects.base import format_arg, parse_number
from magcal_ros.core.effects.drivers import FormulaError, variable_name
import numpy as np


class Relay(Driver):
    """relay(aux_<name>, threshold=X): 1 while the channel exceeds X, else 0."""

    name = 'relay'
    usage = 'relay(aux_<name>, threshold=<value>)'
    column_names = ('on',)

    @classmethod
    def from_args(cls, args, kwargs):
        """Make the factor from ``relay(channel, threshold=X)``; strings in, errors named."""
        if len(args) != 1 or set(kwargs) != {'threshold'}:
            raise FormulaError(f'usage: {cls.usage}')
        d = cls()
        d.v = variable_name(args[0])
        d.threshold = parse_number(kwargs['threshold'], 'relay threshold')
        return d

    @property
    def text(self):
        """Canonical text, as the calibration file stores it."""
        return f'relay({self.v}, threshold={format_arg(self.threshold)})'

    @property
    def signals(self):
        """Return the channel read (the live corrector subscribes to it)."""
        return (self.v,)

    def check(self, ctx, sensor):
        """Refuse a relay that never switches in the calibration data."""
        on = self.columns(ctx, None, {}, ())
        if on.min() == on.max():
            return f'{self.v} never crosses {self.threshold:g}: the relay never switches'
        return None

    def columns(self, ctx, lin, refs, q, prefix=''):
        """(N, 1) 1.0 while the channel is above the threshold."""
        return (np.asarray(ctx.aux[self.v]) > self.threshold).astype(float)[:, None]


class ZOffset(Coupling):
    """zoffset(driver): an offset along the sensor's z axis only, dB_z = X P."""

    name = 'zoffset'
    stems = ('bz',)
    unit = 'nT'
    doc = 'offset along the sensor z axis only (nT per driver unit)'

    def contribution(self, y, lin):
        """(N, 3) nT: y (N, 1) on the z axis."""
        out = np.zeros_like(lin)
        out[:, 2] = y[:, 0]
        return out


#: what magcal_ros.core.effects.load_plugin('my_grammar') registers
MAGCAL_DRIVERS = [Relay]
MAGCAL_COUPLINGS = [ZOffset]
