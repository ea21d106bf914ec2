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
Signals of the grammar's couplings and drivers, written out by hand for injection.

Each function returns ``inject(t, temp, aux, b)`` for :func:`injection.make`: the nT added
to each sensor's raw reading, computed here from the physics of the term (docs/formulas.md),
not by ``magcal_ros.core.effects``.  ``b`` is the true field in the body frame (N, 3) nT; a
sensor's linear reading is ``b @ K_j^T`` (:func:`injection.sensor_matrix`).
"""
from injection import sensor_matrix
import numpy as np


def lin(b, j):
    """(N, 3) nT the linear reading K_j b of sensor j."""
    return b @ sensor_matrix(j).T


def centred(x):
    """X minus its mean over the record (the calibration mean the drivers centre on)."""
    return x - x.mean(axis=0)


def offset(sensor, signal):
    """Inject an offset coupling: ``signal(t, temp, aux)`` -> (N, 3) nT added on ``sensor``."""
    def inject(t, temp, aux, b):
        return {sensor: signal(t, temp, aux)}
    return inject


def offset_alike(signal, sensors=(1, 2, 3, 4)):
    """Inject the same (N, 3) nT ``signal(t)`` in every sensor's own axes."""
    def inject(t, temp, aux, b):
        return {j: signal(t, temp, aux) for j in sensors}
    return inject


def scale(sensor, coef, driver):
    """dB_i = coef_i x(t) lin_i: the scale factors follow the driver x (N,)."""
    def inject(t, temp, aux, b):
        x = driver(t, temp, aux)
        return {sensor: x[:, None] * np.asarray(coef) * lin(b, sensor)}
    return inject


def linear(sensor, m, driver):
    """Linear coupling, dB = x(t) M lin: the 9 entries of the map follow x; M (3, 3) per unit."""
    def inject(t, temp, aux, b):
        x = driver(t, temp, aux)
        return {sensor: x[:, None] * (lin(b, sensor) @ np.asarray(m).T)}
    return inject


def nonorth(sensor, angles, driver):
    """First-order C_NO change: (psi, varphi, theta) = angles x; dB = dC lin."""
    psi, phi, th = angles

    def inject(t, temp, aux, b):
        x = driver(t, temp, aux)
        ll = lin(b, sensor)
        dc = np.array([[0.0, phi, th], [0.0, 0.0, psi], [0.0, 0.0, 0.0]])
        return {sensor: x[:, None] * (ll @ dc.T)}
    return inject


def rotation(sensor, angles, driver):
    """First-order rotation: (alpha, beta, gamma) = angles x; dB = W lin (paper 004 eq. 3)."""
    a, bb, g = angles

    def inject(t, temp, aux, b):
        x = driver(t, temp, aux)
        w = np.array([[0.0, a, -g], [-a, 0.0, bb], [g, -bb, 0.0]])
        return {sensor: x[:, None] * (lin(b, sensor) @ w.T)}
    return inject


def field(dm):
    """Change the field's magnitude by dm(t) nT at every sensor: K_j b dm / |b|."""
    def inject(t, temp, aux, b):
        d = dm(t, temp, aux)
        bb = b * (d / np.linalg.norm(b, axis=1))[:, None]
        return {j: lin(bb, j) for j in range(1, 5)}
    return inject


def combine(*injects):
    """Sum of several injections."""
    def inject(t, temp, aux, b):
        out = {}
        for f in injects:
            for j, v in f(t, temp, aux, b).items():
                out[j] = out.get(j, 0.0) + v
        return out
    return inject
