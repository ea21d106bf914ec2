"""Paper 004 section 3: algebraic ellipsoid fit + Cholesky per sensor, and Procrustes alignment.

These closed-form solutions are the starting values of the maximum-likelihood refinement in
:mod:`magcal_ros.core.model`.
"""
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class EllipsoidFit:
    """Result of :func:`fit_ellipsoid`.

    Attributes
    ----------
    c_inv : numpy.ndarray
        (3, 3) upper-triangular correction matrix C^-1 (dimensionless), paper 004 eq. 5.
    b : numpy.ndarray
        (3,) offset in nT, paper 004 eq. 12.
    coeffs : numpy.ndarray
        (10,) ellipsoid coefficients (a, b, c, f, g, h, p, q, r, d) of eq. 8, unit norm.
    residual_nt : numpy.ndarray
        (N,) |C^-1 (m - b)| - |B| in nT.
    """

    c_inv: np.ndarray
    b: np.ndarray
    coeffs: np.ndarray
    residual_nt: np.ndarray

    def correct(self, raw):
        """Paper 004 eq. 5: B = C^-1 (Bm - b); raw (N, 3) nT -> (N, 3) nT."""
        return (np.asarray(raw, float) - self.b) @ self.c_inv.T


def fit_ellipsoid(raw, field_nt, normalization='svd'):
    """Fit the ellipsoid of paper 004 eq. 8 to raw readings and factor it (eq. 11-13, Cholesky).

    Parameters
    ----------
    raw : numpy.ndarray
        (N, 3) raw readings in nT, N >= 9.
    field_nt : float
        Magnitude |B| of the uniform field in nT (eq. 13).
    normalization : {'svd', 'p'}
        'svd' solves the homogeneous system with |coeffs| = 1 (smallest right singular
        vector of the centred, scaled design matrix; well conditioned). 'p' divides by the
        coefficient p as the paper does (eq. 9-10); it fails when the x offset is near zero.

    Returns
    -------
    EllipsoidFit

    Raises
    ------
    ValueError
        Too few samples, or the quadric is not an ellipsoid (data too degenerate: e.g. a
        single-axis rotation), with the reason.
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
    # a unique ellipsoid needs a one-dimensional null space: the second smallest singular
    # value must stand well above the smallest (noise) one.  Planar data (a rotation about
    # one axis) leave several conics through the points.
    if sv[-2] < 10 * sv[-1] or sv[-2] < 1e-3 * sv[0]:
        raise ValueError(
            'the ellipsoid is not determined by these data (singular values '
            f'{sv[-2]:.3g} and {sv[-1]:.3g} of the design matrix are alike): the field '
            'directions do not span three dimensions; rotate the sensor about more axes')
    if normalization == 'svd':
        v = vt[-1]
    elif normalization == 'p':
        # paper 004 eq. 9-10: divide by p, move 2x to the right-hand side
        cols = [0, 1, 2, 3, 4, 5, 7, 8, 9]
        sol, *_ = np.linalg.lstsq(design[:, cols], -2 * x, rcond=None)
        v = np.insert(sol, 6, 1.0)
    else:
        raise ValueError(f"normalization must be 'svd' or 'p', got {normalization!r}")
    a_mat = np.array([[v[0], v[5], v[4]], [v[5], v[1], v[3]], [v[4], v[3], v[2]]])  # eq. 11
    if np.linalg.eigvalsh(a_mat).mean() < 0:
        v = -v
        a_mat = -a_mat
    eig = np.linalg.eigvalsh(a_mat)
    if eig.min() <= 1e-9 * eig.max():
        raise ValueError(
            'the fitted quadric is not an ellipsoid (eigenvalues '
            f'{np.array2string(eig, precision=3)}): the data do not cover enough attitudes '
            '(for example a rotation about one axis only); rotate the sensor about more axes')
    centre_s = -np.linalg.solve(a_mat, v[6:9])                     # eq. 12 (scaled frame)
    k = centre_s @ a_mat @ centre_s - v[9]                          # eq. 13: b^T A b - d
    if k <= 0:
        raise ValueError('degenerate ellipsoid fit (b^T A b - d <= 0): data too noisy or too few '
                         'attitudes')
    # back to nT: (m-b)^T A (m-b) = |B|^2 with A_nT = A_s * |B|^2 / (k s0^2)
    a_nt = a_mat * field_nt ** 2 / (k * s0 ** 2)
    b = c0 + s0 * centre_s
    c_inv = np.linalg.cholesky(a_nt).T            # (C^-1)^T C^-1 = A, C^-1 upper triangular
    coeffs = v / np.linalg.norm(v)
    res = np.linalg.norm((m - b) @ c_inv.T, axis=1) - field_nt
    return EllipsoidFit(c_inv=c_inv, b=b, coeffs=coeffs, residual_nt=res)


def procrustes_rotation(reference, other):
    """Paper 004 eq. 14: rotation R minimising sum |reference_k - R other_k|^2.

    Solved by SVD of M_1 M_i^T (orthogonal Procrustes, Kabsch), constrained to det R = +1.

    Parameters
    ----------
    reference : numpy.ndarray
        (N, 3) corrected field of the reference sensor (sensor 1), nT.
    other : numpy.ndarray
        (N, 3) corrected field of sensor i, nT.

    Returns
    -------
    numpy.ndarray
        (3, 3) rotation taking sensor i's corrected field into the reference frame.
    """
    rot, _ = Rotation.align_vectors(np.asarray(reference, float), np.asarray(other, float))
    return rot.as_matrix()
