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
Attitude of the array: unit quaternions, their checks and rotation matrices.

Hamilton, scalar first (qw, qx, qy, qz), body to world (NED or ENU, the user's): v_w = R v_b.
"""
import numpy as np

#: largest allowed deviation of |q| from 1 (beyond it: a unit or column mix-up, not rounding)
UNIT_TOLERANCE = 1e-3
#: largest angle (deg) between an epoch's world-frame field direction and the median of all
MAX_FIELD_DISAGREEMENT_DEG = 10.0

COLUMNS = ('att_qw', 'att_qx', 'att_qy', 'att_qz')


class AttitudeError(ValueError):
    """Attitude input that cannot be used; the message names the row and column."""


def _where(k, t=None, rows=None):
    if rows is not None:
        return f'data row {rows[k]}'
    return f'epoch {k}' + ('' if t is None else f' (t = {float(t[k]):.3f} s)')


def check_quaternions(q, t=None, rows=None, tol=UNIT_TOLERANCE):
    """
    Validate (N, 4) quaternions (qw, qx, qy, qz); return them normalised, sign-continuous.

    ``rows`` (N,) file rows or ``t`` (N,) s name an epoch in an error; ``tol`` the allowed
    | |q| - 1 |.  AttitudeError for a non-finite component or a quaternion that is not unit.
    """
    q = np.asarray(q, float)
    if q.ndim != 2 or q.shape[1] != 4:
        raise AttitudeError(f'attitude must have shape (N, 4) (qw, qx, qy, qz); got {q.shape}')
    bad = ~np.isfinite(q)
    if bad.any():
        k, c = np.argwhere(bad)[0]
        raise AttitudeError(f'attitude: {_where(k, t, rows)}: {COLUMNS[c]} is not a number '
                            f'({q[k, c]!r}); {int(bad.any(axis=1).sum())} rows are affected: give '
                            'all four attitude columns in every row or drop those rows')
    norm = np.linalg.norm(q, axis=1)
    off = np.abs(norm - 1.0) > tol
    if off.any():
        k = int(np.flatnonzero(off)[0])
        raise AttitudeError(
            f'attitude: {_where(k, t, rows)}: |q| = {norm[k]:.6g}, not a unit quaternion ('
            f'{int(off.sum())} rows beyond |q| = 1 +- {tol:g}); att_qw..att_qz must be the unit '
            'quaternion (Hamilton, scalar first) of the body-to-world rotation')
    q = q / norm[:, None]
    # q and -q are the same rotation: make the sequence continuous
    flip = np.concatenate([[False], np.einsum('ij,ij->i', q[1:], q[:-1]) < 0])
    sign = np.where(np.logical_xor.accumulate(flip), -1.0, 1.0)
    return q * sign[:, None]


def interpolate(t_msg, q_msg, t):
    """Return (N, 4) the slerp of ``q_msg`` (M, 4) at ``t_msg`` (M,) s (any order) to t (N,)."""
    from scipy.spatial.transform import Rotation, Slerp
    t_u, first = np.unique(np.asarray(t_msg, float), return_index=True)     # the first of each
    rot = Rotation.from_quat(np.asarray(q_msg, float)[first], scalar_first=True)
    if len(t_u) == 1:
        return np.repeat(rot.as_quat(scalar_first=True), len(t), axis=0)
    return Slerp(t_u, rot)(np.asarray(t, float)).as_quat(scalar_first=True)


def with_attitude(data, t_msg, q_msg, source='attitude'):
    """
    Attach the attitude of timed messages to ``data`` (slerp; epochs outside their span dropped).

    ``t_msg`` (M,) s on ``data.t``'s clock; ``q_msg`` (M, 4) (:func:`check_quaternions`);
    ``source`` names it in errors.  Returns (Dataset, (N,) bool mask of the epochs kept).
    """
    t_msg = np.asarray(t_msg, float)
    if len(t_msg) == 0:
        raise AttitudeError(f'{source}: no attitude messages')
    order = np.argsort(t_msg, kind='stable')
    t_msg = t_msg[order]
    try:
        q_msg = check_quaternions(np.asarray(q_msg, float)[order], t=t_msg)
    except AttitudeError as exc:
        raise AttitudeError(f'{source}: {exc}') from None
    inside = (data.t >= t_msg[0]) & (data.t <= t_msg[-1])
    if not inside.any():
        raise AttitudeError(f'{source}: the attitude messages ({t_msg[0]:.3f} .. '
                            f'{t_msg[-1]:.3f} s) do not overlap the magnetometer epochs '
                            f'({data.t[0]:.3f} .. {data.t[-1]:.3f} s)')
    out = data.subset(np.flatnonzero(inside)) if not inside.all() else data
    from dataclasses import replace
    out = replace(out, attitude=interpolate(t_msg, q_msg, out.t))
    return out, inside


def quaternion_matrices(q):
    """(N, 3, 3) body-to-world rotation matrices of (N, 4) unit quaternions (qw, qx, qy, qz)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_quat(np.asarray(q, float), scalar_first=True).as_matrix()


def check_against_field(rot, field_body, t=None, max_deg=MAX_FIELD_DISAGREEMENT_DEG):
    """
    Refuse an attitude that disagrees with the measured field direction (R_k b_k wanders).

    ``rot`` (N, 3, 3) body-to-world; ``field_body`` (N, 3) nT; ``t`` (N,) s names an epoch;
    ``max_deg`` the largest accepted angle from the median.  Returns the (N,) angles, deg;
    AttitudeError naming the first epoch beyond ``max_deg``.
    """
    u = np.asarray(field_body, float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    w = np.einsum('nij,nj->ni', rot, u)
    ref = np.median(w, axis=0)
    ref /= np.linalg.norm(ref)
    ang = np.degrees(np.arccos(np.clip(w @ ref, -1.0, 1.0)))
    bad = ang > max_deg
    if not bad.any():
        return ang
    k = int(np.flatnonzero(bad)[0])
    frac = bad.mean()
    hint = ('most epochs disagree: check the convention (body-to-world, not world-to-body; '
            "Hamilton, scalar first: att_qw is the scalar), that the IMU axes are the array's "
            "(sensor 1's) axes, and that the attitude and magnetometer stamps share one clock (a "
            'lag of a few tenths of a second while turning does this too)' if frac > 0.3 else
            'a jump or a time lag of the attitude against the magnetometer: check the IMU '
            'stream and its time stamps, or drop those rows')
    raise AttitudeError(f'attitude: {_where(k, t)}: the field seen by the array points '
                        f'{ang[k]:.1f} deg away from its median world direction ({int(bad.sum())} '
                        f'of {len(ang)} epochs beyond {max_deg:g} deg); {hint}')
