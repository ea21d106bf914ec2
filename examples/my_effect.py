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
Example effect plug-in for magcal_ros: interference from a spinning part at a known rate.

A reaction wheel, a fan or a pump running at a steady speed carries a little magnetised
material round and round; each sensor sees a field rotating at that frequency, a sinusoid on
each axis with its own amplitude and phase:

    dB(t) = a cos(2 pi f (t - t0)) + b sin(2 pi f (t - t0)),   a, b in nT (per axis)

None of the built-in effects describes it (drift is monotonic, the auxiliary channels need a
recorded signal), so without it the residual keeps a periodic component that no calibration
removes.  Use it from the command line::

    PYTHONPATH=examples magcal diagnose data.csv --model base --plugin my_effect --field-nt 50000
    PYTHONPATH=examples magcal fit data.csv --model base,wheel@3 --plugin my_effect ...

or from Python::

    from magcal_ros.core.effects import load_plugin
    load_plugin('my_effect')          # registers the classes in MAGCAL_EFFECTS

See docs/plugins.md.
"""
from magcal_ros.core.effects import Effect
import numpy as np


class WheelInterference(Effect):
    """Field of a part spinning at a known frequency: dB = a cos(w (t-t0)) + b sin(w (t-t0))."""

    #: the token used in --model ('wheel', 'wheel@3')
    name = 'wheel'
    #: additive: added to the raw reading in the sensor's own axes
    kind = 'additive'
    param_names = ('ax', 'ay', 'az', 'bx', 'by', 'bz')
    units = ('nT',) * 6
    #: the driving signals contribution() reads: the sample time (the live corrector
    #: subscribes to, and waits for, exactly the signals listed here)
    signals = ('time',)
    #: rotation rate of the part, Hz (a subclass or the calibration file's refs may change it)
    frequency_hz = 0.25

    def prepare(self, ctx):
        """Fix the time origin and the frequency from the calibration data (stored in refs)."""
        if len(ctx.t):
            self.refs.setdefault('t0_s', float(ctx.t[0]))
        self.refs.setdefault('frequency_hz', float(self.frequency_hz))

    def check(self, ctx):
        """Need a few periods of data, sampled faster than twice the frequency."""
        f = self.refs.get('frequency_hz', self.frequency_hz)
        if len(ctx.t) < 3:
            return 'too few samples'
        span = float(ctx.t[-1] - ctx.t[0])
        if span * f < 3:
            return (f'the data span {span:.1f} s, fewer than 3 periods of the {f:g} Hz wheel: '
                    'record longer')
        rate = (len(ctx.t) - 1) / span
        if rate <= 2 * f:
            return (f'sampling at {rate:.2f} Hz cannot resolve a {f:g} Hz interference '
                    '(Nyquist): sample faster')
        return None

    def contribution(self, p, ctx, lin):
        """(N, 3) nT added to the raw reading; ``lin`` (N, 3) nT is not needed here."""
        w = 2.0 * np.pi * self.refs.get('frequency_hz', self.frequency_hz)
        phase = w * (ctx.t - self.refs.get('t0_s', 0.0))
        return np.cos(phase)[:, None] * p[:3] + np.sin(phase)[:, None] * p[3:]


#: what magcal_ros.core.effects.load_plugin('my_effect') registers
MAGCAL_EFFECTS = [WheelInterference]
