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
Effect plug-ins whose code fails, for test_effect_containment.py (not examples to follow).

- :class:`SneakyHeat` reads the temperature (``ctx.temp``) but declares only the time: the
  offline fit, which has every column, would accept it; live the corrector does not receive
  the temperature for it, and ``ctx.temp`` is None.  Refused at start-up.
- :class:`Fragile` declares what it reads, but its code assumes more than one sample
  (``ctx.t[1]``): the start-up probe (200 samples) and the offline fit pass, and every live
  sample (one at a time) raises IndexError.  It also raises RuntimeError whenever
  ``BROKEN['on']`` is set (a calibrate call that fails inside effect code).
"""
from magcal_ros.core.effects import Effect
import numpy as np

#: set BROKEN['on'] to make every call of Fragile's contribution raise RuntimeError
BROKEN = {'on': False}


class SneakyHeat(Effect):
    """Temperature coupling that reads ctx.temp without declaring the temperature."""

    name = 'sneaky_heat'
    kind = 'additive'
    param_names = ('vx', 'vy', 'vz')
    units = ('nT/degC',) * 3
    signals = ('time',)

    def prepare(self, ctx):
        if ctx.temp is not None:
            self.refs.setdefault('t0', float(np.mean(ctx.temp)))

    def contribution(self, p, ctx, lin):
        return (ctx.temp - self.refs.get('t0', 20.0))[:, None] * p


class Fragile(Effect):
    """Drift written for whole records: fails on a single sample (live)."""

    name = 'fragile'
    kind = 'additive'
    param_names = ('dx', 'dy', 'dz')
    units = ('nT/sample',) * 3
    signals = ('time',)

    def contribution(self, p, ctx, lin):
        if BROKEN['on']:
            raise RuntimeError('fragile is broken')
        step = ctx.t[1] - ctx.t[0]                  # IndexError on one sample
        return ((ctx.t - ctx.t[0]) / step)[:, None] * p


MAGCAL_EFFECTS = [SneakyHeat]
