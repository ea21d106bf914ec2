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
"""
from magcal_ros.core.effects.base import Registry
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


#: the couplings ``name(driver)`` by name (docs/plugins.md)
COUPLINGS = Registry(Coupling, 'coupling', 'magcal_ros.core.effects.couplings.Coupling')
register_coupling = COUPLINGS.register
unregister_coupling = COUPLINGS.unregister
coupling_class = COUPLINGS.get
registered_couplings = COUPLINGS.names

for _cls in (Offset, Scale, Linear, NonOrth, Rotation, Field):
    register_coupling(_cls)

#: the couplings that ship with the library
BUILTIN_COUPLINGS = COUPLINGS.seal_builtin()
