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
The geometry of a turn about one axis from the readings alone: axis, circle, angle swept.

The planar calibration is :mod:`magcal_ros.core.model.planar`.  Units: nT, rad.
"""
import numpy as np

#: the smallest radius (a fraction of the field) of a circle :func:`swept_angle` counts
MIN_TURN_RADIUS = 0.02


class PlanarError(ValueError):
    """The data are not a turn about one axis that planar mode can use."""


def turn_axis(m):
    """Return the unit axis (3,) of a turn (least spread, along the mean) of m (N, 3) nT."""
    m = np.asarray(m, float)
    c = m - m.mean(axis=0)
    w, v = np.linalg.eigh(c.T @ c / len(m))
    n = v[:, 0]
    if w[1] <= 0 or w[0] > 0.25 * w[1]:
        spreads = ', '.join(f'{np.sqrt(max(x, 0)):.0f}' for x in w)
        raise PlanarError(f'the readings do not lie near one plane (principal spreads {spreads} '
                          'nT): the sensor did not turn about one axis; planar mode is for a turn '
                          'in place about one axis (drop --planar for a full calibration)')
    return n if n @ m.mean(axis=0) >= 0 else -n


def circle_centre(xy):
    """Centre (D,) of the least-squares circle (sphere) through points xy (N, D) (Kasa)."""
    xy = np.asarray(xy, float)
    design = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(design, (xy ** 2).sum(axis=1), rcond=None)
    return sol[:-1]


def plane_axes(axis):
    """(index of the sensor axis nearest ``axis`` (3,), the two other indices)."""
    k = int(np.argmax(np.abs(axis)))
    return k, [a for a in range(3) if a != k]


def planar_magnitude(raw, axis):
    """Shape-only magnitude, nT, of a turn raw (N, 3) nT about axis (3,): radius and mean."""
    raw = np.asarray(raw, float)
    k, plane = plane_axes(axis)
    r = float(np.median(np.linalg.norm(raw[:, plane] - circle_centre(raw[:, plane]), axis=1)))
    return float(np.hypot(r, np.mean(raw[:, k])))


def swept_angle(m):
    """Angle (rad) readings m (N, 3) nT swept about the turn axis (the node's calibration/turn)."""
    m = np.asarray(m, float)
    if len(m) < 8:
        return 0.0
    try:
        n = turn_axis(m)
    except PlanarError:
        n = np.array([0.0, 0.0, 1.0])
    xy = m[:, plane_axes(n)[1]]
    c = circle_centre(xy)
    radius = np.linalg.norm(xy - c, axis=1)
    if np.median(radius) < MIN_TURN_RADIUS * np.median(np.linalg.norm(m, axis=1)):
        return 0.0              # no turn: a circle fitted to noise sweeps any angle
    ang = np.unwrap(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))
    return float(abs(ang[-1] - ang[0]))
