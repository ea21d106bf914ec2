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
Paper 000: sine-fit calibration of a three-axis magnetometer on a turntable.

Model (eq. 1): ``raw = L B + B0``, L lower triangular
(:class:`~magcal_ros.core.papers.paper_params.Paper000Params`); the procedure (eq. 4-17) is
docs/papers.md's.

Geometry and sign conventions (found by reproducing the numbers of the paper's §3.1; the paper
states none of them):

- ``theta`` is the turntable angle, 0 when the Xm axis points to magnetic north. In position 1
  the OXmYm plane is horizontal with Zm pointing *down* (the Zm curve's shift is
  +37 729.4 nT = +kz cos(g) B sin(I) + Bz0 for inclination I = 43 deg > 0) and theta turns Xm
  towards Ym. Then ``Bx = Bxy cos(theta)``, ``By = -Bxy sin(theta)`` with
  ``Bxy = B cos(I)``: the Xm curve has phase +90 deg and, for alpha = 1.35 deg, the Ym curve
  ``ky Bxy sin(alpha - theta) = ky Bxy sin(theta + 180 deg - alpha)`` has phase 178.65 deg, as
  printed. The opposite turning sense would print phase 1.35 deg.
- In position 2 the plane spanned by the *physical* Xm and Zm axes is horizontal (not the ideal
  XZ plane): Zm then has no vertical component, so the Zm curve's shift is exactly Bz0
  (123.7 nT, as printed) and its amplitude is exactly kz Bxy (40 334.2 nT, as printed; the
  ideal-XZ-plane reading would give 40 332.1 nT and a shift of 503 nT). Zm lies at azimuth
  ``theta - phi`` (the sensor is rolled about Xm so that Ym points down and theta turns Zm
  towards Xm), giving the printed phase 90 deg - phi = 0.9004 deg.
- Eq. 7 and §3.1's phi are misprinted (docs/papers.md): k_yx = 41 906.6 / 33 240.0.
- Eq. 5, 9 and 12 take absolute values of phase differences, which loses the signs of alpha
  and beta. Here the turning sense ``s`` is read from the data (the Ym phase leads the Xm
  phase by about +90 deg for s = +1, lags by about 90 deg for s = -1, since |alpha| < 90 deg),
  and ``alpha = 90 deg - |C_y - C_x|``, ``beta = s (C_z - C_x)`` (phase differences wrapped to
  (-180, 180] deg), ``phi = |C'_x - C'_z|``. For positive alpha, beta and s = +1 these are the
  paper's eq. 5, 9 and 12.

With these :func:`simulate_turntable` reproduces §3.1's printed curves, k_yx and k_zx, and
:func:`calibrate_turntable` the nine parameters exactly.
"""
from dataclasses import dataclass

from magcal_ros.core.papers.paper_params import Paper000Params
import numpy as np


def _wrap(angle):
    """Wrap angles in rad to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle, dtype=float), 2.0 * np.pi)


@dataclass(frozen=True)
class SineFit:
    """Fit y = A sin(theta + C) + D (paper 000 eq. 4): A, D, rms nT; C in (-pi, pi] rad; n."""

    A: float
    C: float
    D: float
    rms: float
    n: int

    def __call__(self, theta):
        """Evaluate the curve: theta (N,) rad -> (N,) nT."""
        return self.A * np.sin(np.asarray(theta, dtype=float) + self.C) + self.D


def fit_sine(theta_rad, y) -> SineFit:
    """
    Fit ``y = A sin(theta + C) + D`` by linear least squares (paper 000, eq. 4).

    Linear in ``(A cos C, A sin C, D)`` on ``[sin, cos, 1]``.  ``theta_rad`` (N,) rad; ``y``
    (N,) nT.  ValueError for other shapes, non-finite values, fewer than 3 distinct angles.
    """
    theta = np.asarray(theta_rad, dtype=float)
    y = np.asarray(y, dtype=float)
    if theta.ndim != 1 or y.shape != theta.shape:
        raise ValueError('theta_rad and y must both have shape (N,), got %s and %s'
                         % (theta.shape, y.shape))
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(y))):
        raise ValueError('theta_rad and y must be finite: drop NaN/inf samples first')
    design = np.column_stack([np.sin(theta), np.cos(theta), np.ones_like(theta)])
    if np.linalg.matrix_rank(design) < 3:           # also for fewer than 3 samples
        raise ValueError('a sine fit needs at least 3 distinct turntable angles (modulo 360 '
                         'deg), got %d samples' % len(theta))
    coef, _, _, _ = np.linalg.lstsq(design, y, rcond=None)
    a, b, d = coef
    resid = y - design @ coef
    return SineFit(A=float(np.hypot(a, b)), C=float(np.arctan2(b, a)), D=float(d),
                   rms=float(np.sqrt(np.mean(resid ** 2))), n=int(len(y)))


@dataclass(frozen=True)
class TurntableFits:
    """
    The five sine fits of the two-position procedure and the derived intermediate values.

    ``x1, y1, z1`` position 1's curves, ``x2, z2`` position 2's; ``sense`` +1 if theta turns
    Xm towards Ym in position 1, else -1; ``phi`` rad (eq. 12); ``k_yx``, ``k_zx`` (eq. 7, 14).
    """

    x1: SineFit
    y1: SineFit
    z1: SineFit
    x2: SineFit
    z2: SineFit
    sense: int
    phi: float
    k_yx: float
    k_zx: float


def _check_position(theta, m, name):
    theta = np.asarray(theta, dtype=float)
    m = np.asarray(m, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3 or theta.shape != (m.shape[0],):
        raise ValueError(f'position {name}: need theta (N,) and raw (N, 3) with the same N, got '
                         f'{theta.shape} and {m.shape}')
    return theta, m


def fit_turntable(theta1, m1, theta2, m2) -> TurntableFits:
    """Fit the curves of positions 1 (theta1 (N1,) rad, m1 (N1, 3) nT) and 2; eq. 5-14."""
    theta1, m1 = _check_position(theta1, m1, '1')
    theta2, m2 = _check_position(theta2, m2, '2')
    x1, y1, z1 = (fit_sine(theta1, m1[:, i]) for i in range(3))
    x2, z2 = fit_sine(theta2, m2[:, 0]), fit_sine(theta2, m2[:, 2])
    if min(x1.A, y1.A, x2.A, z2.A) <= 0.0:
        raise ValueError('an axis output does not vary with the turntable angle: the '
                         'horizontal field is zero or the axis is not in the turned plane')
    sense = 1 if _wrap(y1.C - x1.C) >= 0.0 else -1
    return TurntableFits(
        x1=x1, y1=y1, z1=z1, x2=x2, z2=z2, sense=sense,
        phi=float(abs(_wrap(x2.C - z2.C))),          # paper 000, eq. 12
        k_yx=y1.A / x1.A,                            # paper 000, eq. 7 (see erratum)
        k_zx=z2.A / x2.A)                            # paper 000, eq. 14


def calibrate_turntable(theta1, m1, theta2, m2, field_nt) -> Paper000Params:
    """
    Solve paper 000's nine calibration parameters from two turntable rotations.

    Arguments as :func:`fit_turntable`'s; ``field_nt`` eq. 16's B, nT.  Returns
    Paper000Params; ValueError on malformed input, a non-positive field, or no eq. 13.
    """
    if not np.isfinite(field_nt) or field_nt <= 0.0:
        raise ValueError(f'field_nt must be a positive field magnitude in nT, got {field_nt!r}')
    f = fit_turntable(theta1, m1, theta2, m2)
    alpha = np.pi / 2 - abs(_wrap(f.y1.C - f.x1.C))            # paper 000, eq. 5
    bx0, by0 = f.x1.D, f.y1.D                                  # eq. 6
    beta = f.sense * _wrap(f.z1.C - f.x1.C)                    # eq. 9
    bz0 = f.z2.D                                               # eq. 11
    ratio = np.cos(f.phi) / np.cos(beta)                       # eq. 13
    if not abs(ratio) <= 1.0:
        raise ValueError('eq. 13 has no solution: cos(phi)/cos(beta) = %.4g; beta is near '
                         '90 deg or the two positions are inconsistent' % ratio)
    gamma = np.arcsin(ratio)
    # eq. 15 on every sample of both positions, eq. 16 pooled over them
    m = np.vstack([np.asarray(m1, dtype=float), np.asarray(m2, dtype=float)])
    sa, ca = np.sin(alpha), np.cos(alpha)
    sb, cb = np.sin(beta), np.cos(beta)
    sg, cg = np.sin(gamma), np.cos(gamma)
    kxbx = m[:, 0] - bx0
    kyby = (m[:, 1] - by0 - f.k_yx * kxbx * sa) / ca
    kzbz = (m[:, 2] - bz0 - f.k_zx * kxbx * cb * sg
            - (f.k_zx / f.k_yx) * kyby * sb * sg) / cg
    kx = np.sqrt(np.mean(kxbx ** 2 + (kyby / f.k_yx) ** 2 + (kzbz / f.k_zx) ** 2)) / field_nt
    return Paper000Params(float(alpha), float(beta), float(gamma), float(kx),
                          float(f.k_yx * kx), float(f.k_zx * kx), np.array([bx0, by0, bz0]))


def correct(params: Paper000Params, raw):
    """Correct raw outputs (N, 3) nT with paper 000's parameters (eq. 17): (N, 3) nT in O-XYZ."""
    raw = np.asarray(raw, dtype=float)
    if raw.ndim != 2 or raw.shape[1] != 3:
        raise ValueError('raw must have shape (N, 3), got %s' % (raw.shape,))
    p = params
    sa, ca = np.sin(p.alpha), np.cos(p.alpha)
    sb, cb = np.sin(p.beta), np.cos(p.beta)
    sg, cg = np.sin(p.gamma), np.cos(p.gamma)
    bx = (raw[:, 0] - p.B0[0]) / p.kx                                        # eq. 17
    by = (raw[:, 1] - p.B0[1] - p.ky * bx * sa) / (p.ky * ca)
    bz = (raw[:, 2] - p.B0[2] - p.kz * bx * cb * sg - p.kz * by * sb * sg) / (p.kz * cg)
    return np.column_stack([bx, by, bz])


@dataclass(frozen=True)
class TurntableData:
    """Simulated turntable: theta (N,) rad, raw1, raw2 and the true field1, field2 (N, 3) nT."""

    theta: np.ndarray
    raw1: np.ndarray
    raw2: np.ndarray
    field1: np.ndarray
    field2: np.ndarray


def _turntable_attitudes(axis_a, axis_b, down, theta):
    """(N, 3, 3) O-XYZ to level (NED): axis_a at azimuth theta, axis_a x axis_b down if down."""
    e3 = np.cross(axis_a, axis_b)
    e3 = e3 / np.linalg.norm(e3)
    sensor = np.column_stack([axis_a, np.cross(e3, axis_a), e3])
    w1 = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=-1)
    w3 = np.broadcast_to(np.array([0.0, 0.0, 1.0 if down else -1.0]), w1.shape)
    return np.stack([w1, np.cross(w3, w1), w3], axis=-1) @ sensor.T


def simulate_turntable(params: Paper000Params, field_nt, inclination_rad, n_steps,
                       noise_sigma=0.0, noise_mean=0.0, rng=None) -> TurntableData:
    """
    Simulate paper 000's two-position turntable experiment (§2, Fig. 2-3, §3.1).

    Field ``B (cos I, 0, sin I)`` (north, east, down); positions as the module docstring.
    ``params`` the true sensor; ``field_nt`` B, nT; ``inclination_rad`` I (down > 0);
    ``n_steps`` equal steps over a turn; Gaussian noise ``noise_sigma`` nT of mean
    ``noise_mean`` nT (Table 1's "white noise mean"); ``rng`` a Generator or seed.
    """
    if int(n_steps) < 3:
        raise ValueError('n_steps must be >= 3 for a sine fit, got %r' % (n_steps,))
    if noise_sigma < 0.0:
        raise ValueError('noise_sigma must be >= 0 nT, got %r' % (noise_sigma,))
    rng = np.random.default_rng(rng)
    theta = 2.0 * np.pi * np.arange(int(n_steps)) / int(n_steps)
    b_level = field_nt * np.array([np.cos(inclination_rad), 0.0, np.sin(inclination_rad)])
    low = params.matrix
    xm, ym, zm = (row / np.linalg.norm(row) for row in low)
    out = []
    for axis_b, down in ((ym, True), (zm, False)):
        rot = _turntable_attitudes(xm, axis_b, down, theta)
        field = np.einsum('nji,j->ni', rot, b_level)     # R^T b: level -> O-XYZ
        raw = field @ low.T + params.B0                  # paper 000, eq. 1
        raw = raw + noise_mean + noise_sigma * rng.standard_normal(raw.shape)
        out.append((raw, field))
    return TurntableData(theta=theta, raw1=out[0][0], raw2=out[1][0],
                         field1=out[0][1], field2=out[1][1])
