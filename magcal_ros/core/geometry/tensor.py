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

"""Magnetic gradient tensor of a sensor array (paper 004 eq. 1 and a least-squares form)."""
import numpy as np


def cross_positions(baseline_m=0.5):
    """(4, 3) positions in m of paper 004's cross: 1 at +x, 2 at +y, 3 at -x, 4 at -y."""
    h = baseline_m / 2.0
    return np.array([[h, 0, 0], [0, h, 0], [-h, 0, 0], [0, -h, 0]], float)


def tensor_cross(b, baseline_m=0.5):
    """Paper 004 eq. 1: G_ij = dB_i/dx_j (N, 3, 3) nT/m of b (4, N, 3) nT, arms baseline_m long."""
    b = np.asarray(b, float)
    one = b.ndim == 2
    b = b[:, None] if one else b
    if b.shape[0] != 4 or b.shape[2] != 3:
        raise ValueError(f'expected the field of 4 sensors, shape (4, N, 3); got {b.shape}')
    d13, d24 = b[0] - b[2], b[1] - b[3]     # the columns x and y; z from symmetry, trace 0
    gz = np.stack([d13[:, 2], d24[:, 2], b[3, :, 1] - b[1, :, 1] + b[2, :, 0] - b[0, :, 0]], 1)
    g = np.stack([d13, d24, gz], axis=2) / baseline_m
    return g[0] if one else g


def tensor_operator(positions):
    """
    Return (12, 3 S) L, [B0 (3), G row-major (9)] = L @ b.ravel() of fields b (S, 3).

    B(r) = B0 + G r by least squares, ``positions`` (S, 3) m: G symmetric traceless in 3-D;
    planar: the in-plane columns, the third from symmetry and zero trace (eq. 1 on a cross).
    """
    r = np.asarray(positions, float)
    s = len(r)
    rc = r - r.mean(axis=0)
    _, sv, vt = np.linalg.svd(rc)
    rank = int(np.sum(sv > 1e-9 * max(sv[0], 1e-12)))
    if rank < 2:
        raise ValueError('sensor positions must span at least a plane to measure a tensor')
    basis = vt.T        # principal directions, last = normal if planar
    # unknowns in that frame: B0 (3) + in-plane columns G'[:, :rank]
    rp = rc @ basis     # (S, 3)
    # rows 3 k + i: B0_i + sum_c rp[k, c] G'[i, c] (+ 0.0: zeros, not kron's -0.0)
    design = np.hstack([np.tile(np.eye(3), (s, 1)), np.kron(rp[:, :rank], np.eye(3)) + 0.0])
    rot = np.kron(np.eye(s), basis.T)
    if rank == 3:
        # G' symmetric traceless: its column-major vec is its row-major one, TENSOR_MAP g
        full = np.zeros((12, 8))
        full[:3, :3] = np.eye(3)
        full[3:, 3:] = TENSOR_MAP
        x = full @ (np.linalg.pinv(design @ full) @ rot)
        cols = x[3:].reshape(3, 3, -1)          # [column c][row i]
    else:
        x = np.linalg.pinv(design) @ rot
        c0, c1 = x[3:6], x[6:9]
        c2 = np.stack([c0[2], c1[2], -c0[0] - c1[1]])   # symmetry + zero trace
        cols = np.stack([c0, c1, c2])
    g_prime = np.transpose(cols, (1, 0, 2))      # (3 rows, 3 cols, 3S)
    # back to the array frame: G = basis G' basis^T, B0 = basis B0'
    g = np.einsum('ia,abk,jb->ijk', basis, g_prime, basis)
    return np.vstack([basis @ x[:3], g.reshape(9, -1)])      # B0 = basis B0'


def tensor_lstsq(b, positions):
    """(G (N, 3, 3) nT/m, B0 (N, 3) nT) of ``b`` (S, N, 3) nT at ``positions`` (S, 3) m."""
    b = np.asarray(b, float)
    op = tensor_operator(positions)
    stacked = np.transpose(b, (1, 0, 2)).reshape(b.shape[1], -1)    # (N, 3S)
    out = stacked @ op.T
    return out[:, 3:].reshape(-1, 3, 3), out[:, :3]


def tensor_noise_floor(sigma_nt, positions):
    """(3, 3) sd of each tensor component, nT/m, for white noise ``sigma_nt`` (scalar or (S,))."""
    op = tensor_operator(positions)[3:]
    var = np.repeat(np.broadcast_to(np.asarray(sigma_nt, float) ** 2, (len(positions),)), 3)
    return np.sqrt((op ** 2) @ var).reshape(3, 3)


def symmetric_traceless(g):
    """(3, 3) symmetric traceless tensor (curl B = div B = 0) of (gxx, gxy, gxz, gyy, gyz)."""
    gxx, gxy, gxz, gyy, gyz = g
    return np.array([[gxx, gxy, gxz], [gxy, gyy, gyz], [gxz, gyz, -gxx - gyy]], float)


#: d vec(G) / d (gxx, gxy, gxz, gyy, gyz): the 9 x 5 map of the symmetric traceless tensor
TENSOR_MAP = np.stack([symmetric_traceless(e).ravel() for e in np.eye(5)], axis=1)


def gradient_from_fit(model, params, covariance):
    """(G, stderr) (3, 3) nT/m, cov5 (5, 5) of a fit's params (P,), covariance (P, P); or None."""
    for eff, sl in zip(model.array_effects, model.array_slices):
        if eff.name == 'site_gradient':
            c5 = covariance[sl, sl]
            se = np.sqrt(np.clip(np.diag(TENSOR_MAP @ c5 @ TENSOR_MAP.T), 0, None)).reshape(3, 3)
            return symmetric_traceless(params[sl]), se, c5
    return None
