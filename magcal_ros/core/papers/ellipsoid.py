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

"""Paper 004 section 3: ellipsoid fit + Cholesky per sensor, Procrustes alignment (the start)."""
from dataclasses import dataclass

from magcal_ros.core.geometry.coverage import format_vector
from magcal_ros.core.geometry.turn import circle_centre
import numpy as np

#: the quadric is an ellipsoid when its smallest eigenvalue exceeds this many sd of its noise
DEFINITE_Z = 3.7
#: readings whose smallest scatter sd is below this fraction of the middle one lie near a plane
PLANE_SD_RATIO = 0.3
#: ... and whose radius varies less than this (coefficient of variation) form a ring
RING_CV = 0.2


def reading_plane(raw):
    """Return the (3,) unit normal of the ring raw (N, 3) nT form (turned about it), or None."""
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
    """Coefficient of variation of u's (N, 3) radius about ``normal`` (3,): 0 ring, 0.35 cap."""
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    p = np.column_stack([u @ e1, u @ np.cross(normal, e1)])
    r = np.linalg.norm(p - circle_centre(p), axis=1)
    return float(np.std(r) / np.mean(r)) if np.mean(r) > 0 else 0.0


def _undetermined_message(raw, why):
    n = reading_plane(raw)
    if n is None:
        return (f'the ellipsoid is not determined by these data ({why}): the readings do not '
                'cover enough attitudes; rotate the sensor about more axes')
    return (f'the ellipsoid is not determined by these data ({why}): the readings lie near '
            f'one plane with normal {format_vector(n, "+")} in the sensor frame, i.e. the '
            'sensor was rotated about that axis only; rotate it about another axis too (tilt '
            'that axis by 45-90 deg and rotate again)')


def quadric_definiteness(sv, vt, a_mat, n_rows):
    """
    Smallest eigenvalue of the fitted quadric's matrix and its noise standard deviation.

    First-order perturbation of the null vector vt[-1]: its error is sum_k vt[k] (vt[k] . e)
    sv[-1] / sv[k], noise variance sv[-1]^2 / (N - 9); lam = e^T A e is linear in it.
    ``sv`` (10,) singular values, descending, ``vt`` (10, 10) right singular vectors of the
    scaled design; ``a_mat`` (3, 3) eq. 11's matrix, mean eigenvalue positive; ``n_rows``
    readings.  Returns (smallest eigenvalue, its sd), dimensionless.
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

    ``c_inv`` (3, 3) upper triangular C^-1 (paper 004 eq. 5); ``b`` (3,) offset, nT (eq. 12);
    ``coeffs`` (10,) eq. 8's unit-norm (a, ..., d); ``residual_nt`` (N,) |C^-1 (m - b)| - |B|.
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

    ``raw`` (N >= 9, 3) nT; ``field_nt`` |B|, nT (eq. 13); ``normalization`` 'svd'
    (|coeffs| = 1, well conditioned) or 'p' (the paper's eq. 9-10; fails for an x offset
    near zero).  ValueError, with the reason, for too few samples or no ellipsoid.
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
        raise ValueError(_undetermined_message(m, 'several quadrics fit these readings exactly'))
    # the best quadric's smallest eigenvalue must be positive beyond its noise
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
    """Paper 004 eq. 14 (Kabsch): R (3, 3), det +1, minimising sum |reference_k - R other_k|^2."""
    from scipy.spatial.transform import Rotation     # here: scipy.spatial is slow to import
    rot, _ = Rotation.align_vectors(np.asarray(reference, float), np.asarray(other, float))
    return rot.as_matrix()
