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
Conversions between library arrays (nT, nT/m, degC) and ROS messages (T, T/m, degC).

This is the one place where nanotesla become tesla (REP 103 SI units in messages) and back.
Every builder validates its input and raises ``ValueError`` naming what was wrong.

Layouts: ``sensor_msgs/MagneticField`` covariance in T^2, 3x3 row-major, all zeros meaning
unknown; the gradient tensor ``std_msgs/Float64MultiArray`` 3x3 row-major in T/m,
``layout.dim`` ``[('row', size 3, stride 9), ('col', size 3, stride 3)]``, ``data_offset`` 0;
``magcal_interfaces/GradientTensorStamped``: the matched set's stamp, the array frame,
``tensor`` 3x3 row-major in T/m, ``tensor_covariance`` 9x9 row-major in (T/m)^2 (zeros:
unknown); the live residual: :func:`residual_to_msg`; ``sensor_msgs/Imu`` carries only the
body-to-world (ENU) orientation, covariance rad^2 about the world axes, angular velocity and
linear acceleration marked not given (``covariance[0] = -1``, REP 145).
"""

import math
import numbers

from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import TransformStamped
from magcal_ros.core.geometry.attitude import UNIT_TOLERANCE
from magcal_ros.units import NT_PER_T, nt_to_t, t_to_nt
import numpy as np
import rclpy.time
from sensor_msgs.msg import Imu, MagneticField, Temperature
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

#: Labels of the gradient tensor's ``layout.dim`` entries (docs/design.md §3).
TENSOR_DIM_LABELS = ('row', 'col')
#: label of the first dimension of the residual message: what its two rows hold
RESIDUAL_KIND_LABEL = 'scalar |b|-F, vector |b-others|'

_NS_PER_S = 1_000_000_000


def to_stamp(stamp):
    """
    Return ``stamp`` as a new ``builtin_interfaces/Time`` (a given message is copied).

    ``stamp``: a ``builtin_interfaces/Time``, an rclpy ``Time``, seconds since the epoch (a
    number >= 0) or None (time zero); anything else is a ValueError.
    """
    if stamp is None:
        return TimeMsg()
    if isinstance(stamp, TimeMsg):
        return TimeMsg(sec=stamp.sec, nanosec=stamp.nanosec)
    if isinstance(stamp, rclpy.time.Time):
        return stamp.to_msg()
    if isinstance(stamp, numbers.Real) and not isinstance(stamp, bool):
        seconds = float(stamp)
        if not math.isfinite(seconds) or seconds < 0.0:
            raise ValueError(
                f'stamp must be a finite, non-negative number of seconds, got {stamp!r}')
        total_ns = int(round(seconds * _NS_PER_S))
        return TimeMsg(sec=total_ns // _NS_PER_S, nanosec=total_ns % _NS_PER_S)
    raise ValueError(
        'stamp must be a builtin_interfaces/Time, an rclpy Time, seconds as a number or None, '
        f'got {type(stamp).__name__}')


def stamp_to_seconds(stamp):
    """Return a ``builtin_interfaces/Time`` as float seconds since the epoch."""
    return stamp.sec + stamp.nanosec * 1e-9


def _check_frame_id(frame_id):
    if not isinstance(frame_id, str):
        raise ValueError(f'frame_id must be a str, got {type(frame_id).__name__}')
    return frame_id


def _header(msg, stamp, frame_id):
    """Set ``msg.header`` (stamp as :func:`to_stamp`, a str frame id); return ``msg``."""
    msg.header.stamp = to_stamp(stamp)
    msg.header.frame_id = _check_frame_id(frame_id)
    return msg


def _non_negative(value, name, unit):
    """Return ``value`` as a float, refusing one that is not finite or is < 0 (ValueError)."""
    x = float(value)
    if not math.isfinite(x) or x < 0.0:
        raise ValueError(f'{name} must be finite and >= 0 {unit}, got {value!r}')
    return x


def _vector3(value, name, unit):
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f'{name} must have shape (3,) in {unit}, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {arr.tolist()}')
    return arr


def _covariance33(covariance_nt2):
    """Return a (3, 3) covariance in nT^2 from None, a scalar variance or a 3x3 matrix."""
    if covariance_nt2 is None:
        return np.zeros((3, 3))
    cov = np.asarray(covariance_nt2, dtype=np.float64)
    if cov.ndim == 0:
        return np.eye(3) * _non_negative(float(cov), 'covariance_nt2 as a scalar variance', 'nT^2')
    if cov.shape != (3, 3):
        raise ValueError(
            'covariance_nt2 must be a scalar variance or a (3, 3) matrix in nT^2, '
            f'got shape {cov.shape}')
    if not np.all(np.isfinite(cov)):
        raise ValueError('covariance_nt2 must be finite')
    if np.any(np.diag(cov) < 0.0):
        raise ValueError(f'covariance_nt2 diagonal must be >= 0 nT^2, got {np.diag(cov).tolist()}')
    scale = max(float(np.max(np.abs(cov))), 1e-300)
    if not np.allclose(cov, cov.T, rtol=0.0, atol=1e-9 * scale):
        raise ValueError('covariance_nt2 must be symmetric; pass (C + C.T) / 2 if it is only '
                         'asymmetric by rounding')
    return cov


def covariance_to_t2(covariance_nt2):
    """Validate a covariance as :func:`field_nt_to_msg` takes it; return it as (9,) T^2."""
    return nt_to_t(nt_to_t(_covariance33(covariance_nt2))).reshape(9)


def field_nt_to_msg(field_nt, stamp=None, frame_id='', covariance_nt2=None, covariance_t2=None):
    """
    Build a ``sensor_msgs/MagneticField`` (field in T, covariance in T^2 row-major).

    ``field_nt`` (3,) nT; ``stamp`` as :func:`to_stamp`; ``covariance_nt2`` (3, 3) nT^2, or
    one variance in nT^2 for all three axes, None: zeros ("unknown"); ``covariance_t2`` (9,)
    T^2 of :func:`covariance_to_t2` takes precedence, unchecked. Raises ValueError if the field
    is not three finite numbers, or the covariance not a finite symmetric one of variances >= 0.
    """
    field = _vector3(field_nt, 'field_nt', 'nT')
    if covariance_t2 is None:
        covariance_t2 = covariance_to_t2(covariance_nt2)
    msg = _header(MagneticField(), stamp, frame_id)
    v = msg.magnetic_field
    v.x, v.y, v.z = nt_to_t(field).tolist()
    msg.magnetic_field_covariance = covariance_t2
    return msg


def set_field_nt(msg, field_nt, covariance_t2):
    """Overwrite field (``field_nt`` (3,) nT) and covariance ((9,) T^2) of ``msg``, unchecked."""
    v = msg.magnetic_field
    v.x = float(field_nt[0]) / NT_PER_T
    v.y = float(field_nt[1]) / NT_PER_T
    v.z = float(field_nt[2]) / NT_PER_T
    msg.magnetic_field_covariance = covariance_t2


def linear_to_t(a_inv, offset_nt):
    """
    Prepare a linear correction A^-1 (raw - o) (``a_inv`` (3, 3), ``offset_nt`` (3,) nT).

    Returns (rows of A^-1, o in T), as 3-tuples of float, for :func:`correct_msg_linear`.
    """
    rows = tuple(tuple(float(v) for v in row) for row in np.asarray(a_inv, np.float64))
    return rows, tuple(float(v) for v in nt_to_t(np.asarray(offset_nt, np.float64)))


def correct_msg_linear(msg, linear_t, covariance_t2):
    """
    Correct ``msg`` in place: field <- A^-1 (field - o) in T (``linear_t`` of :func:`linear_to_t`).

    Covariance (9,) T^2; header left as it is. Plain floats: numpy costs more than the nine
    products for one 3-vector (the hot path of sensors without driven effects).
    """
    (r0, r1, r2), (ox, oy, oz) = linear_t
    v = msg.magnetic_field
    x, y, z = v.x - ox, v.y - oy, v.z - oz
    v.x = r0[0] * x + r0[1] * y + r0[2] * z
    v.y = r1[0] * x + r1[1] * y + r1[2] * z
    v.z = r2[0] * x + r2[1] * y + r2[2] * z
    msg.magnetic_field_covariance = covariance_t2


def msg_to_field_nt(msg):
    """Return the field of a ``sensor_msgs/MagneticField`` (T) as a (3,) array in nT."""
    v = msg.magnetic_field
    return t_to_nt([v.x, v.y, v.z])


def msg_to_covariance_nt2(msg):
    """Return the covariance of a ``sensor_msgs/MagneticField`` as (3, 3) nT^2 (0: unknown)."""
    cov_t2 = np.asarray(msg.magnetic_field_covariance, dtype=np.float64).reshape(3, 3)
    return t_to_nt(t_to_nt(cov_t2))


def tensor_to_msg(gradient_nt_per_m, check=True, out=None):
    """
    Build the gradient-tensor ``std_msgs/Float64MultiArray`` (T/m, layout in the module doc).

    ``gradient_nt_per_m`` (3, 3) G[i, k] = dB_i / dx_k, nT/m. ``check``: raise ValueError
    if it is not a finite (3, 3) array (False on the corrector's hot path). ``out``: a message
    this function built before, whose data are replaced.
    """
    g = np.asarray(gradient_nt_per_m, dtype=np.float64)
    if check:
        if g.shape != (3, 3):
            raise ValueError('gradient tensor must have shape (3, 3) in nT/m, got shape '
                             f'{g.shape}')
        if not np.all(np.isfinite(g)):
            raise ValueError('gradient tensor must be finite')
    msg = out if out is not None else Float64MultiArray(layout=MultiArrayLayout(dim=[
        MultiArrayDimension(label=TENSOR_DIM_LABELS[0], size=3, stride=9),
        MultiArrayDimension(label=TENSOR_DIM_LABELS[1], size=3, stride=3)]))
    msg.data = nt_to_t(g).reshape(9).tolist()
    return msg


def gradient_covariance_to_t2(covariance_nt2):
    """Return the (9, 9) tensor covariance in (nT/m)^2 as (81,) (T/m)^2 (None: zeros)."""
    if covariance_nt2 is None:
        return np.zeros(81)
    cov = np.asarray(covariance_nt2, dtype=np.float64)
    if cov.shape != (9, 9) or not np.all(np.isfinite(cov)):
        raise ValueError(f'tensor covariance must be a finite (9, 9) array in (nT/m)^2, got '
                         f'shape {cov.shape}')
    return nt_to_t(nt_to_t(cov)).reshape(81)


def fill_gradient_stamped(msg, stamp, frame_id, gradient_nt_per_m, covariance_t2):
    """
    Fill a ``magcal_interfaces/GradientTensorStamped`` in place and return it (hot path).

    ``stamp`` as :func:`to_stamp`; ``gradient_nt_per_m`` (3, 3) finite, nT/m; ``covariance_t2``
    (81,) (T/m)^2 of :func:`gradient_covariance_to_t2`, None: left as it is.
    """
    msg.header.stamp = to_stamp(stamp)
    msg.header.frame_id = frame_id
    msg.tensor = nt_to_t(np.asarray(gradient_nt_per_m, np.float64)).reshape(9)
    if covariance_t2 is not None:
        msg.tensor_covariance = covariance_t2
    return msg


def msg_to_gradient_stamped(msg):
    """Return (stamp s, tensor (3, 3) nT/m, covariance (9, 9) (nT/m)^2) of a stamped gradient."""
    g = t_to_nt(np.asarray(msg.tensor, np.float64)).reshape(3, 3)
    cov = t_to_nt(t_to_nt(np.asarray(msg.tensor_covariance, np.float64))).reshape(9, 9)
    return stamp_to_seconds(msg.header.stamp), g, cov


def transform_msg(parent, child, rotation, translation_m, stamp=None):
    """
    Build a ``geometry_msgs/TransformStamped`` parent -> child: v_parent = R v_child + p.

    ``rotation`` (3, 3) proper rotation R (child axes in the parent frame);
    ``translation_m`` (3,) p, m; ``stamp`` as :func:`to_stamp`.
    """
    t = _vector3(translation_m, 'translation_m', 'm')
    from scipy.spatial.transform import Rotation    # here: it costs every node ~0.25 s
    q = Rotation.from_matrix(np.asarray(rotation, np.float64)).as_quat()   # x, y, z, w
    msg = _header(TransformStamped(), stamp, parent)
    msg.child_frame_id = _check_frame_id(child)
    tr, r = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in t)
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    return msg


def residual_to_msg(scalar_nt, vector_nt):
    """
    Build the live residual of one set as ``std_msgs/Float64MultiArray`` (T).

    ``scalar_nt``, ``vector_nt`` (S,) nT: |b_j| - F and |b_j - mean of the others|. The
    message holds 2 S values in T, ``data[j - 1]`` the scalar residual of sensor j and
    ``data[S + j - 1]`` its vector residual; ``layout.dim`` = ``kind`` (size 2, stride 2 S,
    labelled :data:`RESIDUAL_KIND_LABEL`) and ``sensor`` (size S, stride S).
    """
    s = len(scalar_nt)
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=RESIDUAL_KIND_LABEL, size=2, stride=2 * s),
                      MultiArrayDimension(label='sensor', size=s, stride=s)]
    msg.data = nt_to_t(np.concatenate([scalar_nt, vector_nt])).tolist()
    return msg


def msg_to_residual_nt(msg):
    """Return (scalar_nt, vector_nt), (S,) nT each, of a :func:`residual_to_msg` (ValueError)."""
    dims = [(d.label, d.size) for d in msg.layout.dim]
    if len(dims) != 2 or dims[0] != (RESIDUAL_KIND_LABEL, 2) or dims[1][0] != 'sensor':
        raise ValueError(f'residual message layout must be [({RESIDUAL_KIND_LABEL!r}, 2), '
                         f"('sensor', S)] (label, size), got {dims}")
    s = dims[1][1]
    data = np.asarray(msg.data, dtype=np.float64)
    if data.size != 2 * s:
        raise ValueError(f'residual message needs {2 * s} values, got {data.size}')
    return t_to_nt(data[:s]), t_to_nt(data[s:])


def msg_to_tensor(msg):
    """Return the (3, 3) gradient tensor, nT/m, of a :func:`tensor_to_msg` (or ValueError)."""
    dims = [(d.label, d.size, d.stride) for d in msg.layout.dim]
    expected = [(TENSOR_DIM_LABELS[0], 3, 9), (TENSOR_DIM_LABELS[1], 3, 3)]
    if dims != expected:
        raise ValueError(
            f'gradient message layout must be {expected} (label, size, stride), got {dims}')
    offset = msg.layout.data_offset
    data = np.asarray(msg.data, dtype=np.float64)
    if data.size < offset + 9:
        raise ValueError(
            f'gradient message needs {offset + 9} values (data_offset {offset} + 9), '
            f'got {data.size}')
    return t_to_nt(data[offset:offset + 9].reshape(3, 3))


def temperature_msg(temp_c, stamp=None, frame_id='', variance_c2=0.0):
    """
    Build a ``sensor_msgs/Temperature`` of ``temp_c`` degC, ``variance_c2`` degC^2 (0: unknown).

    ``stamp`` as :func:`to_stamp`. Raises ValueError on a value not finite or a variance < 0.
    """
    temp = float(temp_c)
    if not math.isfinite(temp):
        raise ValueError(f'temp_c must be finite, got {temp_c!r}')
    variance = _non_negative(variance_c2, 'variance_c2', 'degC^2')
    msg = _header(Temperature(), stamp, frame_id)
    msg.temperature, msg.variance = temp, variance
    return msg


def attitude_msg(quaternion, stamp=None, frame_id='', sd_rad=0.0):
    """
    Build a ``sensor_msgs/Imu`` that carries an attitude only (layout in the module doc).

    ``quaternion`` (4,) body-to-world unit quaternion (qw, qx, qy, qz), Hamilton, world ENU;
    ``frame_id`` the body frame; ``sd_rad`` the standard uncertainty about each world axis,
    rad (0: unknown). Raises ValueError if the quaternion is not 4 finite numbers of unit
    norm (within ``UNIT_TOLERANCE``) or ``sd_rad`` is negative or not finite.
    """
    q = np.asarray(quaternion, dtype=np.float64).reshape(-1)
    if (q.size != 4 or not np.all(np.isfinite(q))
            or abs(np.linalg.norm(q) - 1.0) > UNIT_TOLERANCE):
        raise ValueError(f'quaternion must be 4 finite numbers (qw, qx, qy, qz) of unit norm, '
                         f'got {quaternion!r}')
    sd = _non_negative(sd_rad, 'sd_rad', 'rad')
    msg = _header(Imu(), stamp, frame_id)
    msg.orientation.w, msg.orientation.x, msg.orientation.y, msg.orientation.z = (
        float(v) for v in q)
    msg.orientation_covariance = [sd * sd, 0.0, 0.0, 0.0, sd * sd, 0.0, 0.0, 0.0, sd * sd]
    msg.angular_velocity_covariance[0] = -1.0
    msg.linear_acceleration_covariance[0] = -1.0
    return msg


def msg_to_attitude(msg):
    """
    Return (stamp s, (qw, qx, qy, qz)) of a ``sensor_msgs/Imu``, or None without an attitude.

    None when the message has no orientation (``orientation_covariance[0] = -1``, REP 145)
    or it is not a finite unit quaternion (within ``UNIT_TOLERANCE``).
    """
    o = msg.orientation
    q = (o.w, o.x, o.y, o.z)
    if (msg.orientation_covariance[0] == -1 or not all(map(math.isfinite, q))
            or abs(math.sqrt(sum(v * v for v in q)) - 1.0) > UNIT_TOLERANCE):
        return None
    return stamp_to_seconds(msg.header.stamp), q
