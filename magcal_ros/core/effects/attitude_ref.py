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
The attitude as a reference: the world field seen through the vehicle's attitude.

|B_k| = F alone leaves the vertical axis of a vehicle's compass open.  Its attitude R_k
(body-to-world) gives B_k = R_k^T m in a uniform world field m: an *observation* of B_k
(:class:`magcal_ros.core.model.engine.ProfiledProblem`), a virtual sensor whose noise
``sigma_nt`` (the attitude's error as a field) is estimated with the real sensors'.  Mode
``full`` (token ``attitude_full``) trusts the whole attitude: y_k = Q R_k^T m,
m = F (cos I cos D, cos I sin D, sin I); ``tilt`` (``attitude_tilt``) roll and pitch only:
g_k . B_k = F sin I, g_k = R_k^T e_z.  Both fit Q, the rotation of sensor 1 against the
attitude's body frame (rotation vector ``mount_x``, ``mount_y``, ``mount_z``, rad; prior
:data:`MOUNT_PRIOR_SD_RAD`).  Gebre-Egziabher et al. 2006, "Calibration of strapdown
magnetometers in magnetic field domain", J. Aerosp. Eng. 19(2), use the same constraints;
here they are a weighted observation in the maximum-likelihood problem.  The sensors'
readings are untouched (:meth:`shift` is zero).  Units: nT, rad.
"""
from magcal_ros.core.effects.base import Effect
import numpy as np

#: least attitude error taken (an exact, simulated attitude would weigh infinitely)
MIN_SD_RAD = np.radians(0.01)
#: prior sd of each angle of the compass's mounting against the attitude's frame, rad
MOUNT_PRIOR_SD_RAD = np.radians(10.0)


class AttitudeReference(Effect):
    """The world field seen through the attitude (module docstring); array-wide, no shift."""

    name = 'attitude_tilt'
    kind = 'array'
    scope = 'array'
    signals = ('attitude',)
    param_names = ('inclination', 'mount_x', 'mount_y', 'mount_z')
    units = ('rad',) * 4
    #: the attitude's trust: 'tilt' (roll and pitch) or 'full' (and the heading)
    mode = 'tilt'
    #: rows of the observation per epoch (the rank of its projector)
    rank = 1
    #: a way of fitting, never offered by the diagnosis as a missing effect
    candidate = False

    def check(self, ctx):
        if ctx.attitude is None:
            return ('the attitude reference needs the attitude (CSV columns att_qw..att_qz, '
                    'an Imu topic, a vehicle log)')
        return None

    @property
    def sigma_nt(self):
        """Return the attitude's error as a field sd, nT per observed axis (fitted)."""
        return float(self.refs.get('sigma_nt', np.nan))

    @sigma_nt.setter
    def sigma_nt(self, value):
        self.refs['sigma_nt'] = float(value)

    def floor_nt(self, f_nt):
        """Return the least sd the fit gives the observation, nT (MIN_SD_RAD of the field)."""
        return MIN_SD_RAD * float(f_nt)

    def shift(self, p, ctx, j, b=None):
        """(N, 3) zeros: the attitude corrects no sensor."""
        return np.zeros((len(ctx.t), 3))

    def mount(self, p):
        """Return Q (3, 3), the rotation from the attitude's body frame to sensor 1's (p[-3:])."""
        from scipy.spatial.transform import Rotation
        return Rotation.from_rotvec(np.asarray(p[-3:], float)).as_matrix()

    def observation(self, p, rot, f):
        """
        Return (proj, y): what the attitude observes of the field, in sensor 1's frame.

        ``p`` (n_params,) rad, ``rot`` (N, 3, 3) body-to-world, ``f`` (N,) nT.  ``proj``
        (N, 3, 3) is the projector onto what is observed (the identity, or g g^T with g the
        world vertical), ``y`` (N, 3) nT the observation: a field's residual is proj (y - B).
        """
        q = self.mount(p)
        if self.mode == 'full':
            inc, dec = p[0], p[1]                       # the world field's unit vector
            u = np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])
            y = np.einsum('ab,nkb,k->na', q, rot, u) * f[:, None]       # Q R^T m
            proj = np.broadcast_to(np.eye(3), (len(f), 3, 3))
            return proj, y
        g = rot[:, 2, :] @ q.T                          # world vertical, sensor 1's frame
        proj = g[:, :, None] * g[:, None, :]
        y = g * (f * np.sin(p[0]))[:, None]
        return proj, y

    def residual(self, p, rot, f, b):
        """(N, 3) nT: proj (y - B) of :meth:`observation` for the field ``b`` (N, 3) nT."""
        proj, y = self.observation(p, rot, f)
        return np.einsum('nij,nj->ni', proj, y - b)

    def start(self, rot, field_body):
        """(n_params,) rad: the world field's angles from a corrected ``field_body`` (N, 3) nT."""
        w = np.einsum('nij,nj->ni', rot, field_body)
        w = w / np.linalg.norm(w, axis=1, keepdims=True)
        inc = float(np.arcsin(np.clip(np.median(w[:, 2]), -1.0, 1.0)))
        if self.mode == 'full':
            m = np.median(w, axis=0)
            return np.array([inc, float(np.arctan2(m[1], m[0])), 0.0, 0.0, 0.0])
        return np.array([inc, 0.0, 0.0, 0.0])


class AttitudeFull(AttitudeReference):
    """The whole attitude trusted (heading included): two angles of the world field."""

    name = 'attitude_full'
    param_names = ('inclination', 'declination', 'mount_x', 'mount_y', 'mount_z')
    units = ('rad',) * 5
    mode = 'full'
    rank = 3


#: the attitude modes and their effect classes
MODES = {'tilt': AttitudeReference, 'full': AttitudeFull}


def attitude_reference(model):
    """Return (effect, slice of its parameters) of ``model``'s attitude reference, or None."""
    return next(((eff, sl) for eff, sl in zip(model.array_effects, model.array_slices)
                 if isinstance(eff, AttitudeReference)), None)
