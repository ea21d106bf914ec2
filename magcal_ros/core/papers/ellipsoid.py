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
Paper 004 section 3: algebraic ellipsoid fit + Cholesky per sensor, and Procrustes alignment.

These closed-form solutions are the starting values of the maximum-likelihood refinement in
:mod:`magcal_ros.core.model`.
"""
from dataclasses import dataclass

from magcal_ros.core.geometry.turn import circle_centre
import numpy as np

#: the fitted quadric counts as an ellipsoid when its smallest eigenvalue exceeds this many
#: standard deviations of its noise uncertainty (one-sided, false-acceptance rate ~ 1e-4)
DEFINITE_Z = 3.7
#: readings whose smallest scatter standard deviation is below this fraction of the middle
#: one lie "near one plane" (0.25 for a ring at SNR 10) ...
PLANE_SD_RATIO = 0.3
#: ... and whose in-plane radius varies less than this (coefficient of variation about the
#: fitted circle) form a ring; a filled cap gives about 0.35
RING_CV = 0.2


def _fmt(v):
    return '(' + ', '.join(f'{0.0 if abs(x) < 0.005 else x:+.2f}' for x in v) + ')'


def reading_plane(raw):
    """
    Return the normal of the plane the readings lie near, or None when they spread in 3-D.

    ``raw`` (N, 3) nT, sensor frame.  The (3,) unit normal (largest component positive) when
    the smallest standard deviation of the readings about their mean is below
    :data:`PLANE_SD_RATIO` times the middle one and they form a ring in that plane
    (:func:`ring_spread` below :data:`RING_CV`, not a filled cap): the sensor turned about
    that axis only.
    """
    m = np.asarray(raw, float)
    w, vec = np.linalg.eigh(np.cov((m - m.mean(axis=0)).T))
    w = np.clip(w, 0.0, None)
    n = vec[:, 0]
    if w[1] <= 0 or np.sqrt(w[0] / w[1]) >= PLANE_SD_RATIO or ring_spread(m, n) >= RING_CV:
        return None
    return n if n[np.argmax(np.abs(n))] > 0 else -n


def _quadric_matrix(v):
    """(3, 3) matrix of the quadratic part of eq. 8's coefficients v (10,) (eq. 11)."""
    return np.array([[v[0], v[5], v[4]], [v[5], v[1], v[3]], [v[4], v[3], v[2]]])


def ring_spread(u, normal):
    """
    Measure how far the points ``u`` are from a ring about ``normal``.

    Coefficient of variation of the radius of the points ``u`` (N, 3) (directions or
    readings) about the circle fitted to them in the plane normal to ``normal``: about 0 for
    a ring (a rotation about one axis, however unevenly sampled), about 0.35 for a filled
    cap.
    """
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    p = np.column_stack([u @ e1, u @ e2])
    r = np.linalg.norm(p - circle_centre(p), axis=1)
    return float(np.std(r) / np.mean(r)) if np.mean(r) > 0 else 0.0


def _undetermined_message(raw, why):
    n = reading_plane(raw)
    if n is None:
        return (f'the ellipsoid is not determined by these data ({why}): the readings do not '
                'cover enough attitudes; rotate the sensor about more axes')
    return (f'the ellipsoid is not determined by these data ({why}): the readings lie near '
            f'one plane with normal {_fmt(n)} in the sensor frame, i.e. the sensor was '
            'rotated about that axis only; rotate it about another axis too (tilt that axis '
            'by 45-90 deg and rotate again)')


def quadric_definiteness(sv, vt, a_mat, n_rows):
    """
    Smallest eigenvalue of the fitted quadric's matrix and its noise standard deviation.

    The algebraic fit's coefficient vector ``v`` is the last right singular vector of the
    design matrix; to first order in the noise its error is
    ``sum_k vt[k] (vt[k] . e) sv[-1] / sv[k]`` over the other singular directions, with the
    residual variance estimated from ``sv[-1]^2 / (N - 9)`` (the classical perturbation of
    a total-least-squares null vector).  The eigenvalue lam = e^T A e (e its eigenvector)
    is linear in ``v``, so its variance is ``g^T Cov(v) g`` with ``g = d lam / d v``.

    ``sv`` (10,) singular values of the (scaled) design matrix, descending; ``vt`` (10, 10)
    its right singular vectors (rows); ``a_mat`` (3, 3) the quadric matrix of eq. 11 for the
    unit coefficient vector, its mean eigenvalue positive; ``n_rows`` the number of readings.
    Returns (smallest eigenvalue, its standard deviation), dimensionless, scaled frame.
    """
    lam, vec = np.linalg.eigh(a_mat)
    e = vec[:, 0]
    g = np.array([e[0] ** 2, e[1] ** 2, e[2] ** 2, 2 * e[1] * e[2], 2 * e[0] * e[2],
                  2 * e[0] * e[1], 0.0, 0.0, 0.0, 0.0])
    sigma2 = sv[-1] ** 2 / max(1, n_rows - len(sv) + 1)
    var = float(sigma2 * np.sum((vt[:-1] @ g / sv[:-1]) ** 2))
    return float(lam[0]), float(np.sqrt(var))


@dataclass(frozen=True)
class EllipsoidFit:
    """
    Result of :func:`fit_ellipsoid`.

    ``c_inv`` (3, 3) upper-triangular correction matrix C^-1, dimensionless (paper 004 eq. 5);
    ``b`` (3,) offset, nT (eq. 12); ``coeffs`` (10,) the unit-norm coefficients (a, b, c, f,
    g, h, p, q, r, d) of eq. 8; ``residual_nt`` (N,) |C^-1 (m - b)| - |B|, nT.
    """

    c_inv: np.ndarray
    b: np.ndarray
    coeffs: np.ndarray
    residual_nt: np.ndarray

    def correct(self, raw):
        """Paper 004 eq. 5: B = C^-1 (Bm - b); raw (N, 3) nT -> (N, 3) nT."""
        return (np.asarray(raw, float) - self.b) @ self.c_inv.T


def fit_ellipsoid(raw, field_nt, normalization='svd'):
    """
    Fit the ellipsoid of paper 004 eq. 8 to raw readings and factor it (eq. 11-13, Cholesky).

    ``raw`` (N, 3) nT, N >= 9; ``field_nt`` the uniform field's magnitude |B|, nT (eq. 13);
    ``normalization`` 'svd' solves the homogeneous system with |coeffs| = 1 (the smallest
    right singular vector of the centred, scaled design matrix; well conditioned), 'p'
    divides by the coefficient p as the paper does (eq. 9-10; fails when the x offset is near
    zero).  Raises ValueError, with the reason, for too few samples or a quadric that is not
    an ellipsoid (degenerate data, e.g. a single-axis rotation).
    """
    m = np.asarray(raw, float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f'raw must have shape (N, 3), got {m.shape}')
    if len(m) < 9:
        raise ValueError(f'an ellipsoid fit needs at least 9 samples, got {len(m)}')
    # centre and scale for conditioning; undone below
    c0 = m.mean(axis=0)
    s0 = np.abs(m - c0).max() or 1.0
    x, y, z = ((m - c0) / s0).T
    # paper 004 eq. 8: a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0
    design = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y,
                              2 * x, 2 * y, 2 * z, np.ones_like(x)])
    _, sv, vt = np.linalg.svd(design, full_matrices=False)
    if sv[-2] <= 1e-12 * sv[0]:
        # noise-free degenerate data: a whole family of quadrics passes through the points
        raise ValueError(_undetermined_message(m, 'several quadrics fit these readings exactly'))
    # determinacy against the noise (not a fixed singular-value ratio): the best quadric
    # must be an ellipsoid, its smallest eigenvalue positive beyond its own uncertainty
    a_svd = _quadric_matrix(vt[-1])
    a_svd = a_svd if np.linalg.eigvalsh(a_svd).mean() >= 0 else -a_svd
    lam, lam_sd = quadric_definiteness(sv, vt, a_svd, len(m))
    if not lam > DEFINITE_Z * lam_sd:
        raise ValueError(_undetermined_message(
            m, f'the smallest eigenvalue of the fitted quadric, {lam:.3g}, is not positive '
               f'beyond its noise uncertainty ({lam_sd:.2g}; need > {DEFINITE_Z:g} x)'))
    if normalization == 'svd':
        v = vt[-1]
    elif normalization == 'p':
        # paper 004 eq. 9-10: divide by p, move 2x to the right-hand side
        sol, *_ = np.linalg.lstsq(np.delete(design, 6, axis=1), -2 * x, rcond=None)
        v = np.insert(sol, 6, 1.0)
    else:
        raise ValueError(f"normalization must be 'svd' or 'p', got {normalization!r}")
    a_mat = _quadric_matrix(v)                                       # eq. 11
    if np.linalg.eigvalsh(a_mat).mean() < 0:
        v, a_mat = -v, -a_mat
    eig = np.linalg.eigvalsh(a_mat)
    if eig.min() <= 1e-9 * eig.max():
        raise ValueError(_undetermined_message(
            m, f'the fitted quadric is not an ellipsoid: eigenvalues '
               f'{np.array2string(eig, precision=3)}'))
    centre_s = -np.linalg.solve(a_mat, v[6:9])                     # eq. 12 (scaled frame)
    k = centre_s @ a_mat @ centre_s - v[9]                          # eq. 13: b^T A b - d
    if k <= 0:
        raise ValueError('degenerate ellipsoid fit (b^T A b - d <= 0): data too noisy or too few '
                         'attitudes')
    # back to nT: (m-b)^T A (m-b) = |B|^2 with A_nT = A_s * |B|^2 / (k s0^2)
    a_nt = a_mat * field_nt ** 2 / (k * s0 ** 2)
    b = c0 + s0 * centre_s
    c_inv = np.linalg.cholesky(a_nt).T            # (C^-1)^T C^-1 = A, C^-1 upper triangular
    return EllipsoidFit(c_inv=c_inv, b=b, coeffs=v / np.linalg.norm(v),
                        residual_nt=np.linalg.norm((m - b) @ c_inv.T, axis=1) - field_nt)


def procrustes_rotation(reference, other):
    """
    Paper 004 eq. 14: rotation R minimising sum |reference_k - R other_k|^2.

    Solved by SVD of M_1 M_i^T (orthogonal Procrustes, Kabsch), constrained to det R = +1.

    ``reference`` (N, 3) corrected field of sensor 1 and ``other`` (N, 3) of sensor i, nT.
    Returns the (3, 3) rotation taking sensor i's corrected field into sensor 1's frame.
    """
    from scipy.spatial.transform import Rotation     # here: scipy.spatial is slow to import
    rot, _ = Rotation.align_vectors(np.asarray(reference, float), np.asarray(other, float))
    return rot.as_matrix()
