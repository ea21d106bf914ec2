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
Direction coverage of field vectors: whether they can determine a linear sensor map.

``raw = A @ B + o`` needs directions spread in 3-D *about their mean* (``o`` absorbs the
mean; a rotation about one axis leaves them on one affine plane, as paper 002's Table 2):
hence the centred scatter ``(1/N) sum (u - u_mean)(u - u_mean)^T`` (1/3 each when uniform).
"""
from dataclasses import dataclass

import numpy as np

#: Fraction of the directions the reported cone holds.
CONE_FRACTION = 0.95


def format_vector(v, sign='', digits=2):
    """Return (3,) ``v`` as text, ``(0.12, -0.99, 0.00)``, never -0.00 (``sign='+'``: +0.12)."""
    zero = 0.5 * 10.0 ** -digits
    return '(' + ', '.join(f'{0.0 if abs(x) < zero else x:{sign}.{digits}f}' for x in v) + ')'


@dataclass(frozen=True)
class Coverage:
    """
    How well a set of field directions covers the unit sphere (all dimensionless).

    ``planar``: the smallest eigenvalue is below ``planar_threshold`` (map undetermined along
    ``normal``, ``normal @ u_mean >= 0``); ``narrow``: the two smallest are.
    """

    eigenvalues: np.ndarray             # (3,) ascending, of the centred scatter
    eigenvectors: np.ndarray            # (3, 3) column k: unit eigenvector of eigenvalues[k]
    n: int                              # number of vectors
    planar: bool
    normal: np.ndarray                  # (3,) unit eigenvector of the smallest eigenvalue
    cone_half_angle_deg: float          # cone about mean_direction holding 95 % (180: none)
    narrow: bool
    mean_direction: np.ndarray          # (3,) unit, along the mean (zeros if it vanishes)
    mean_resultant_length: float        # |u_mean|: 1 for one direction, ~0 for full cover
    planar_threshold: float

    @property
    def good(self):
        """Tell whether the directions spread in all three dimensions."""
        return not (self.planar or self.narrow)

    def describe(self) -> str:
        """Return one line naming what is missing from the attitudes, and what to do."""
        ev = self.eigenvalues
        if self.narrow:
            return (f'field directions span only a {self.cone_half_angle_deg:.0f} deg cone '
                    f'around {format_vector(self.mean_direction)}: turn the sensor over / through '
                    f'larger angles (spread eigenvalues {ev[0]:.3g}, {ev[1]:.3g}, {ev[2]:.3g}; '
                    f'each should exceed {self.planar_threshold:.3g})')
        if self.planar:
            normal = format_vector(self.normal)
            return (f'all field directions lie near one plane with normal {normal}: rotate '
                    f'about another axis (tilt the normal {normal} away from the rotation axis, '
                    'e.g. lay the sensor on its side, and rotate again; smallest spread '
                    f'eigenvalue {ev[0]:.3g} < {self.planar_threshold:.3g})')
        return (f'directions cover the sphere ({self.n} directions, spread eigenvalues '
                f'{ev[0]:.3g}, {ev[1]:.3g}, {ev[2]:.3g}; 1/3 each is ideal, each should exceed '
                f'{self.planar_threshold:.3g})')


def direction_coverage(vectors, planar_threshold=0.02) -> Coverage:
    """
    Return the :class:`Coverage` of the directions of ``vectors`` (N >= 1, 3), any unit.

    ``planar_threshold``: an eigenvalue below it is "no spread" (0.02: about +-14 deg).
    ValueError for another shape, non-finite or zero vectors, or a threshold not in (0, 1/3].
    """
    v = np.asarray(vectors, dtype=float)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 1:
        raise ValueError('vectors must have shape (N, 3) with N >= 1, got %s' % (v.shape,))
    if not np.all(np.isfinite(v)):
        raise ValueError('vectors contain NaN or inf: drop those samples first')
    if not 0.0 < planar_threshold <= 1.0 / 3.0:
        raise ValueError('planar_threshold must be in (0, 1/3], got %r' % planar_threshold)
    norms = np.linalg.norm(v, axis=1)
    if np.any(norms == 0.0):
        raise ValueError('vectors contain %d zero vector(s), which have no direction: '
                         'drop them first' % int(np.sum(norms == 0.0)))
    u = v / norms[:, None]
    mean = u.mean(axis=0)
    d = u - mean
    eigenvalues, eigenvectors = np.linalg.eigh(d.T @ d / len(u))
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    normal = eigenvectors[:, 0] * (-1.0 if eigenvectors[:, 0] @ mean < 0.0 else 1.0)
    rbar = float(np.linalg.norm(mean))
    if rbar > 1e-12:
        mean_dir = mean / rbar
        angles = np.degrees(np.arccos(np.clip(u @ mean_dir, -1.0, 1.0)))
        cone = float(np.percentile(angles, 100.0 * CONE_FRACTION))
    else:
        mean_dir = np.zeros(3)
        cone = 180.0
    return Coverage(eigenvalues=eigenvalues, eigenvectors=eigenvectors, n=int(len(u)),
                    planar=bool(eigenvalues[0] < planar_threshold), normal=normal,
                    cone_half_angle_deg=cone, narrow=bool(eigenvalues[1] < planar_threshold),
                    mean_direction=mean_dir, mean_resultant_length=rbar,
                    planar_threshold=float(planar_threshold))
