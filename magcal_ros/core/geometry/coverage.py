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

A linear sensor model ``raw = A @ B + o`` is determined by rotating the sensor in a uniform
field only if the field directions seen by the sensor spread in all three dimensions. The
offset ``o`` absorbs whatever is common to all samples, so what matters is the spread of the
directions *about their mean*: directions on one circle of the unit sphere (a cone around the
rotation axis, which is what a rotation about a single axis gives) lie in one affine plane and
leave the map undetermined along that plane's normal, even when the cone is wide. This is the
defect of paper 002's Table 2 (six attitudes about one axis; docs/papers.md, paper 002).

The check therefore uses the scatter matrix of the unit directions about their mean,
``(1/N) sum (u - u_mean)(u - u_mean)^T``. For directions uniform on the sphere its eigenvalues
are 1/3 each; their sum is ``1 - |u_mean|^2``. The uncentred scatter
``(1/N) sum u u^T`` only detects great circles (directions through the origin plane)
and misses the single-axis rotation, so the centred form is used here.
"""

from dataclasses import dataclass

import numpy as np

#: Fraction of the directions the reported cone holds.
CONE_FRACTION = 0.95


def _fmt_vec(v):
    return '(' + ', '.join('%.2f' % (0.0 if abs(x) < 0.005 else x) for x in v) + ')'


@dataclass(frozen=True)
class Coverage:
    """
    How well a set of field directions covers the unit sphere.

    Attributes
    ----------
    eigenvalues : numpy.ndarray
        (3,) dimensionless, ascending: eigenvalues of the scatter matrix of the unit
        directions about their mean, ``(1/N) sum (u - u_mean)(u - u_mean)^T``.
        1/3 each for uniform coverage of the sphere; 0 along a direction with no spread.
    eigenvectors : numpy.ndarray
        (3, 3) dimensionless; column ``k`` is the unit eigenvector of ``eigenvalues[k]``,
        in the frame the vectors were given in.
    n : int
        Number of vectors.
    planar : bool
        True when the directions lie near one plane (not necessarily through the origin):
        smallest eigenvalue below ``planar_threshold``. The linear map is then not
        determined along ``normal``.
    normal : numpy.ndarray
        (3,) unit normal of that plane (eigenvector of the smallest eigenvalue), signed so
        that it points to the side of the plane the directions are on (``normal @ u_mean >= 0``).
        This is the axis the sensor was rotated about.
    cone_half_angle_deg : float
        Half-angle in degrees of the cone around ``mean_direction`` that holds 95 % of the
        directions (180 when the mean is zero).
    narrow : bool
        True when the directions do not even spread in two dimensions (the two smallest
        eigenvalues below ``planar_threshold``): they cluster around one direction.
    mean_direction : numpy.ndarray
        (3,) unit vector along the mean of the unit directions (zeros if the mean vanishes).
    mean_resultant_length : float
        ``|u_mean|``, 1 for identical directions, about 0 for full coverage.
    planar_threshold : float
        Threshold used for ``planar`` and ``narrow``.

    """

    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    n: int
    planar: bool
    normal: np.ndarray
    cone_half_angle_deg: float
    narrow: bool
    mean_direction: np.ndarray
    mean_resultant_length: float
    planar_threshold: float

    @property
    def good(self):
        """Tell whether the directions spread in all three dimensions."""
        return not (self.planar or self.narrow)

    def describe(self) -> str:
        """
        Return a one-line message naming what is missing from the attitude set.

        Returns
        -------
        str
            For clustered directions: the cone they span and what to do; for coplanar
            directions: the plane normal (the rotation axis used) and what to do; otherwise a
            statement that the directions cover the sphere.

        """
        ev = self.eigenvalues
        if self.narrow:
            return ('field directions span only a %.0f deg cone around %s: turn the sensor '
                    'over / through larger angles (spread eigenvalues %.3g, %.3g, %.3g; '
                    'each should exceed %.3g)'
                    % (self.cone_half_angle_deg, _fmt_vec(self.mean_direction),
                       ev[0], ev[1], ev[2], self.planar_threshold))
        if self.planar:
            return ('all field directions lie near one plane with normal %s: rotate about '
                    'another axis (tilt the normal %s away from the rotation axis, e.g. lay '
                    'the sensor on its side, and rotate again; smallest spread eigenvalue '
                    '%.3g < %.3g)'
                    % (_fmt_vec(self.normal), _fmt_vec(self.normal), ev[0],
                       self.planar_threshold))
        return ('directions cover the sphere (%d directions, spread eigenvalues %.3g, %.3g, '
                '%.3g; 1/3 each is ideal, each should exceed %.3g)'
                % (self.n, ev[0], ev[1], ev[2], self.planar_threshold))


def direction_coverage(vectors, planar_threshold=0.02) -> Coverage:
    """
    Measure how the directions of field vectors cover the unit sphere.

    Parameters
    ----------
    vectors : array_like
        (N, 3) field vectors in any unit (nT in this package); only their directions are
        used. N >= 1; no zero or non-finite vectors.
    planar_threshold : float, optional
        An eigenvalue of the centred direction scatter below this counts as "no spread"
        along its eigenvector. 0.02 corresponds to directions within about +-14 deg of a
        plane (uniform band: variance h^2/3 with h = sin(14 deg)).

    Returns
    -------
    Coverage
        Eigen-decomposition of the scatter, planarity, plane normal and cone half-angle.

    Raises
    ------
    ValueError
        If ``vectors`` is not (N, 3) with N >= 1, contains non-finite values or zero vectors,
        or ``planar_threshold`` is not in (0, 1/3].

    """
    v = np.asarray(vectors, dtype=float)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 1:
        raise ValueError('vectors must have shape (N, 3) with N >= 1, got %s'
                         % (v.shape,))
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
    scatter = d.T @ d / len(u)
    eigenvalues, eigenvectors = np.linalg.eigh(scatter)
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    normal = eigenvectors[:, 0].copy()
    if normal @ mean < 0.0:
        normal = -normal
    rbar = float(np.linalg.norm(mean))
    if rbar > 1e-12:
        mean_dir = mean / rbar
        angles = np.degrees(np.arccos(np.clip(u @ mean_dir, -1.0, 1.0)))
        cone = float(np.percentile(angles, 100.0 * CONE_FRACTION))
    else:
        mean_dir = np.zeros(3)
        cone = 180.0
    return Coverage(
        eigenvalues=eigenvalues,
        eigenvectors=eigenvectors,
        n=int(len(u)),
        planar=bool(eigenvalues[0] < planar_threshold),
        normal=normal,
        cone_half_angle_deg=cone,
        narrow=bool(eigenvalues[1] < planar_threshold),
        mean_direction=mean_dir,
        mean_resultant_length=rbar,
        planar_threshold=float(planar_threshold),
    )
