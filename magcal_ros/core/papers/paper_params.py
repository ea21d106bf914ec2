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
Conversions between the general per-sensor model and each source paper's parameters.

The general model is ``raw = A @ B + o``, ``A`` (3, 3), ``o`` (3,) nT, ``B`` in sensor 1's
ideal frame: paper 004 (eq. 2-3) ``A = S C_NO R``; paper 000 (eq. 1) ``A = L Q``, L lower
triangular; paper 002 (eq. 4) ``A = K``, ``o = Hh``.  Angles in rad, offsets in nT.
"""
from dataclasses import dataclass

from magcal_ros.core.effects import (  # noqa: F401  (rot_r*, C_NO re-exported)
    misalignment_angles, nonorthogonality_matrix, rot_r1, rot_r2, rot_r3, rq_positive,
    upper_to_scale_nonorth)
import numpy as np
import scipy.linalg


def _check_general(a, o):
    a, o = np.asarray(a, dtype=float), np.asarray(o, dtype=float)
    if a.shape != (3, 3):
        raise ValueError('A must have shape (3, 3), got %s' % (a.shape,))
    if o.shape != (3,):
        raise ValueError('o must have shape (3,), got %s' % (o.shape,))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(o))):
        raise ValueError('A and o must be finite')
    if np.linalg.matrix_rank(a) < 3:
        raise ValueError('A is singular: it cannot be a sensor response matrix')
    return a, o


def _check_proper(q, what):
    if np.linalg.det(q) < 0.0:
        raise ValueError(f'det(A) < 0: the sensor axes form a left-handed set (an axis sign or '
                         f'wiring swap?), which {what} cannot represent with positive scale '
                         'factors; flip the sign of the reversed axis first')


def _vec3(value, name):
    v = np.array(value, dtype=float).reshape(-1)
    if v.shape != (3,):
        raise ValueError('%s must have 3 elements, got shape %s' % (name, np.shape(value)))
    return v


# ---- paper 004 (R1, R2, R3 of eq. 3 and C_NO of eq. 2 live with the model's effects) -------

@dataclass(frozen=True, eq=False)
class Paper004Params:
    """
    Paper 004 single-sensor error model plus misalignment (eq. 2-3).

    ``raw = S C_NO R B + b``: ``kx, ky, kz`` scale factors (> 0); ``psi, varphi, theta``
    non-orthogonality angles, rad (z reference: psi the y axis' tilt in the yz plane, theta
    the x axis' elevation, varphi its azimuth); ``b`` (3,) offset, nT; ``alpha, beta,
    gamma`` misalignment, rad: about z, then x', then y'' (zero for sensor 1).
    """

    kx: float
    ky: float
    kz: float
    psi: float
    varphi: float
    theta: float
    b: np.ndarray
    alpha: float = 0.0
    beta: float = 0.0
    gamma: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, 'b', _vec3(self.b, 'b'))

    @property
    def scale(self):
        """(3, 3) S = diag(kx, ky, kz), paper 004 eq. 2."""
        return np.diag([self.kx, self.ky, self.kz])

    @property
    def nonorthogonality(self):
        """(3, 3) C_NO of paper 004 eq. 2 (upper triangular, unit rows)."""
        return nonorthogonality_matrix(self.psi, self.varphi, self.theta)

    @property
    def rotation(self):
        """(3, 3) R = R1(gamma) R2(beta) R3(alpha), sensor 1's frame to sensor i's (eq. 3)."""
        return rot_r1(self.gamma) @ rot_r2(self.beta) @ rot_r3(self.alpha)

    def to_general(self):
        """Return ``(A (3, 3), o (3,) nT)`` with ``A = S C_NO R``, ``o = b``."""
        return self.scale @ self.nonorthogonality @ self.rotation, self.b.copy()

    def correction(self):
        """
        Return the paper's correction pair ``(C^-1 (3, 3), R_corr (3, 3))``.

        ``C^-1 = (S C_NO)^-1`` upper triangular (eq. 11-13's Cholesky factor); ``R_corr =
        R^T`` takes ``C^-1 (raw - b)`` into sensor 1's frame (eq. 14).
        """
        c_inv = scipy.linalg.solve_triangular(self.scale @ self.nonorthogonality, np.eye(3))
        return c_inv, self.rotation.T

    @classmethod
    def from_general(cls, a, o):
        """
        Decompose a general ``(A, o)`` into paper 004 parameters.

        ``A = U Q`` (RQ, diag(U) > 0), ``S`` the row norms of ``U``, ``C_NO = S^-1 U``,
        ``R = Q``.  ``a`` (3, 3), det > 0; ``o`` (3,) nT.  Angles: theta, psi, beta in
        [-pi/2, pi/2], varphi in (-pi/2, pi/2), alpha, gamma in (-pi, pi].  ValueError for a
        non-finite, singular or left-handed A.
        """
        a, o = _check_general(a, o)
        _check_proper(a, 'paper 004 (S C_NO R with R a rotation)')
        u, q = rq_positive(a)
        k, psi, varphi, theta = upper_to_scale_nonorth(u)
        alpha, beta, gamma = misalignment_angles(q)
        return cls(kx=float(k[0]), ky=float(k[1]), kz=float(k[2]), psi=psi, varphi=varphi,
                   theta=theta, b=o.copy(), alpha=alpha, beta=beta, gamma=gamma)


#: Paper 004 Table 1: the four simulated magnetometers (angles rad, offsets nT), sensors 1..4
_TABLE1_004 = {
    'kx': (1.013, 1.012, 1.019, 1.015),
    'ky': (0.991, 1.015, 1.011, 1.008),
    'kz': (1.007, 0.986, 0.982, 1.021),
    'psi': (0.017, 0.013, -0.018, -0.016),
    'varphi': (0.024, 0.019, 0.025, 0.018),
    'theta': (-0.021, 0.015, 0.012, -0.028),
    'bx': (25.0, -54.0, -16.0, 45.0),
    'by': (85.0, 31.0, -29.0, 21.0),
    'bz': (-32.0, 19.0, 55.0, -37.0),
    'alpha': (0.0, -0.023, 0.021, -0.038),
    'beta': (0.0, 0.025, -0.026, -0.028),
    'gamma': (0.0, 0.028, 0.031, 0.034),
}


def table1_sensor(j) -> Paper004Params:
    """Return paper 004 Table 1's parameters of sensor ``j`` (1..4: at +x, +y, -x, -y)."""
    if j not in (1, 2, 3, 4):
        raise ValueError('paper 004 Table 1 has sensors 1..4, got %r' % (j,))
    p = {name: row[j - 1] for name, row in _TABLE1_004.items()}
    b = np.array([p.pop('bx'), p.pop('by'), p.pop('bz')])
    return Paper004Params(**p, b=b)


def table1_correction(j):
    """Return paper 004 Table 2's (c_inv, r_corr), (3, 3) each, of sensor j (errata: docs)."""
    return table1_sensor(j).correction()


# ---- paper 000 -----------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Paper000Params:
    """
    Paper 000 error model (eq. 1): ``raw = L B + B0``, B in Fig. 1's frame O-XYZ.

    ``L = [[kx, 0, 0], [ky sin a, ky cos a, 0], [kz cos b sin g, kz sin b sin g, kz cos g]]``:
    ``alpha`` the angle between Ym and Y (towards Xm), ``beta`` the azimuth of Zm's
    projection on OXY, ``gamma`` the angle between Zm and Z (>= 0), rad; ``kx, ky, kz``
    scale factors (> 0); ``B0`` (3,) offsets, nT.
    """

    alpha: float
    beta: float
    gamma: float
    kx: float
    ky: float
    kz: float
    B0: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, 'B0', _vec3(self.B0, 'B0'))

    @property
    def matrix(self):
        """(3, 3) the lower-triangular response matrix of paper 000 eq. 1."""
        sa, ca = np.sin(self.alpha), np.cos(self.alpha)
        sb, cb = np.sin(self.beta), np.cos(self.beta)
        sg, cg = np.sin(self.gamma), np.cos(self.gamma)
        return np.array([[self.kx, 0.0, 0.0],
                         [self.ky * sa, self.ky * ca, 0.0],
                         [self.kz * cb * sg, self.kz * sb * sg, self.kz * cg]])

    @property
    def phi(self):
        """Angle in rad between the Xm and Zm axes: cos(phi) = cos(beta) sin(gamma)."""
        return float(np.arccos(np.cos(self.beta) * np.sin(self.gamma)))

    def to_general(self):
        """Return ``(A (3, 3), o (3,) nT)`` with A the eq. 1 matrix (reference frame = O-XYZ)."""
        return self.matrix, self.B0.copy()

    @classmethod
    def from_general(cls, a, o):
        """
        Decompose a general ``(A, o)`` into (paper 000 parameters, q (3, 3)), A = L q.

        LQ with diag(L) > 0; arguments and errors as :meth:`Paper004Params.from_general`.
        gamma in [0, pi], alpha in (-pi/2, pi/2), beta in (-pi, pi] (0 when gamma = 0).
        """
        a, o = _check_general(a, o)
        qt, rt = scipy.linalg.qr(a.T)
        d = np.sign(np.diag(rt))
        low, q = rt.T * d[None, :], d[:, None] * qt.T
        _check_proper(q, 'paper 000 (L Q with Q a rotation)')
        sin_g = float(np.hypot(low[2, 0], low[2, 1]))
        beta = float(np.arctan2(low[2, 1], low[2, 0])) if sin_g > 0.0 else 0.0
        return cls(alpha=float(np.arctan2(low[1, 0], low[1, 1])), beta=beta,
                   gamma=float(np.arctan2(sin_g, low[2, 2])), kx=float(low[0, 0]),
                   ky=float(np.hypot(low[1, 0], low[1, 1])), kz=float(np.linalg.norm(low[2])),
                   B0=o.copy()), q


# ---- paper 002 -----------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Paper002Params:
    """Paper 002 interference model (eq. 4): ``Hm = K He + Hh``, K = I + D, Hh (3,) nT."""

    K: np.ndarray
    Hh: np.ndarray

    def __post_init__(self):
        k = np.array(self.K, dtype=float)
        if k.shape != (3, 3):
            raise ValueError('K must have shape (3, 3), got %s' % (k.shape,))
        object.__setattr__(self, 'K', k)
        object.__setattr__(self, 'Hh', _vec3(self.Hh, 'Hh'))

    def to_general(self):
        """Return ``(A, o) = (K, Hh)``: (3, 3) dimensionless and (3,) nT."""
        return self.K.copy(), self.Hh.copy()

    @classmethod
    def from_general(cls, a, o):
        """Return ``Paper002Params(K=A, Hh=o)`` for a (3, 3) A and a (3,) o in nT."""
        a, o = _check_general(a, o)
        return cls(K=a.copy(), Hh=o.copy())
