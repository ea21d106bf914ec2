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
Test data of a four-sensor cross written independently of ``Model.forward``.

The simulator (``magcal_ros.core.data.simulate``) uses the forward model that the fit inverts, so a
wrong physical definition of an effect would pass every test built on it.  Here each sensor
is written out by hand: raw_j = K_j (B_body) + o_j + injected_j(t) + noise, with K_j a scale
times a small non-orthogonal, rotated matrix of the size of paper 004's Table 1 errors, and
the injected faults (a step, a sinusoid, a lagged temperature, a current-squared coupling,
heavy-tailed noise, a random walk) computed by the small functions below, not by
``magcal_ros.core.effects``.
"""
import functools

from magcal_ros.core.data.dataset import Dataset
import numpy as np

F_NT = 50000.0
SIGMA_NT = 3.0
RATE_HZ = 5.0


def _rotation(axis, angle):
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def tumbling_field(n, rate_hz=RATE_HZ, seed=0, rotations=False):
    """
    (N,) t in s and (N, 3) field in the body frame, nT: a smooth tumble covering the sphere.

    With ``rotations``, also the (N, 3, 3) body-to-world rotations (b_body = R^T b_world).

    The body turns at 0.2-0.6 rad/s about an axis that wanders (periods 57-126 s), so every
    direction is visited several times in 600 s.  Fresh arrays at every call (the caller may
    change them); the tumble itself, a product of N small rotations taken one by one, is
    computed once per (n, rate_hz, seed).
    """
    args = (int(n), float(rate_hz), seed)
    t, out, rots = (_tumble(*args) if isinstance(seed, (int, np.integer))
                    else _tumble.__wrapped__(*args))
    return (t.copy(), out.copy(), rots.copy()) if rotations else (t.copy(), out.copy())


@functools.lru_cache(maxsize=32)
def _tumble(n, rate_hz, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    dt = 1.0 / rate_hz
    w_axis = np.stack([np.sin(0.11 * t + 0.3), np.cos(0.07 * t + 1.1),
                       np.sin(0.05 * t + 2.0)], axis=1)
    w_axis /= np.linalg.norm(w_axis, axis=1, keepdims=True)
    speed = 0.4 + 0.2 * np.sin(0.05 * t + rng.uniform(0, 6))
    b_world = np.array([0.3, -0.5, 0.81])
    b_world *= F_NT / np.linalg.norm(b_world)
    r = _rotation(rng.normal(size=3), rng.uniform(0, 6))
    out = np.empty((n, 3))
    rots = np.empty((n, 3, 3))
    for k in range(n):
        out[k] = r.T @ b_world
        rots[k] = r
        r = r @ _rotation(w_axis[k], speed[k] * dt)
    for a in (t, out, rots):
        a.flags.writeable = False           # the cached copy: never handed out
    return t, out, rots


#: per sensor: scale (3,), non-orthogonality (rad, 3), rotation vector (rad, 3), offset nT (3,)
SENSORS = [
    ((1.012, 0.991, 1.004), (0.004, -0.003, 0.002), (0.0, 0.0, 0.0),
     (120.0, -85.0, 60.0)),
    ((0.987, 1.009, 1.015), (-0.002, 0.005, 0.001), (0.012, -0.008, 0.015),
     (-70.0, 140.0, 35.0)),
    ((1.006, 1.013, 0.985), (0.003, 0.002, -0.004), (-0.010, 0.014, 0.006),
     (45.0, 95.0, -150.0)),
    ((0.993, 0.996, 1.011), (-0.005, -0.001, 0.003), (0.007, 0.011, -0.012),
     (-130.0, -40.0, 75.0)),
]


def sensor_matrix(j):
    """(3, 3) matrix of sensor j: scale x upper-triangular non-orthogonality x rotation."""
    k, (psi, phi, th), rv, _ = SENSORS[j - 1]
    non = np.array([[1.0, phi, th], [0.0, 1.0, psi], [0.0, 0.0, 1.0]])
    non /= np.linalg.norm(non, axis=1, keepdims=True)
    rot = np.eye(3) if not np.any(rv) else _rotation(np.array(rv), np.linalg.norm(rv))
    return np.diag(k) @ non @ rot


def channels(t, seed=0):
    """Temperatures (4, N) degC and auxiliary channels {name: (N,)} of a calibration run."""
    rng = np.random.default_rng(seed + 1)
    temp = np.stack([20.0 + 8.0 * np.sin(2 * np.pi * t / 240.0 + 0.7 * j)
                     + 0.05 * rng.normal(size=len(t)) for j in range(4)])
    motor = 5.0 * ((t // 7.0) % 2)                     # 0 / 5 A switched every 7 s
    motor = motor + 1.5 * np.sin(2 * np.pi * t / 53.0) + 1.5  # and a slow ramp: 0..8 A
    pump = 2.0 + np.sin(2 * np.pi * t / 31.0)
    heater = 10.0 * ((t // 13.0) % 3) / 2.0
    return temp, {'aux_motor_current': motor, 'aux_pump_current': pump,
                  'aux_heater_power': heater}


def lowpass(t, x, tau):
    """First-order lag by explicit Euler sub-steps (10 per sample): tau dy/dt = x - y."""
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, len(x)):
        h = (t[k] - t[k - 1]) / 10.0
        yk = y[k - 1]
        for s in range(10):
            xs = x[k - 1] + (x[k] - x[k - 1]) * (s + 0.5) / 10.0
            yk = yk + h * (xs - yk) / tau
        y[k] = yk
    return y


def make(n=3000, seed=0, inject=None, noise=None):
    """
    Dataset of the cross with faults added.

    Parameters
    ----------
    n : int
        Number of epochs (at 10 Hz).
    seed : int
        Seed of the tumble, the channels and the noise.
    inject : callable, optional
        inject(t, temp, aux, field_body) -> {sensor: (N, 3) nT added to its raw reading}.
    noise : callable, optional
        noise(rng, shape) -> nT noise (default Gaussian, 3 nT per axis).

    """
    rng = np.random.default_rng(seed + 2)
    t, b = tumbling_field(n, seed=seed)
    temp, aux = channels(t, seed)
    add = inject(t, temp, aux, b) if inject else {}
    raw = np.empty((4, n, 3))
    for j in range(1, 5):
        raw[j - 1] = b @ sensor_matrix(j).T + np.array(SENSORS[j - 1][3])
        raw[j - 1] += add.get(j, 0.0)
        raw[j - 1] += (noise(rng, (n, 3)) if noise else rng.normal(0, SIGMA_NT, (n, 3)))
    return Dataset(t=t, raw=raw, temp=temp, aux=aux)


# -- the faults of issue 11, written out ------------------------------------------------------

def step_fault(t0=300.0, size=(40.0, 0.0, 0.0), sensor=1):
    """Inject an offset step of ``size`` nT at ``t0`` s on one sensor."""
    def inject(t, temp, aux, b):
        return {sensor: (t >= t0)[:, None] * np.array(size)}
    return inject


def periodic_fault(freq=0.23, amp=15.0, sensor=3):
    """Inject a pump at ``freq`` Hz, ``amp`` nT on each axis with different phases."""
    def inject(t, temp, aux, b):
        ph = 2 * np.pi * freq * t
        return {sensor: amp * np.stack([np.cos(ph), np.sin(ph + 0.4), np.cos(ph + 2.0)], 1)}
    return inject


def lag_fault(tau=90.0, coef=(4.0, -3.0, 2.5), sensor=2):
    """Inject a sensor head that follows its thermometer with a ``tau`` s lag (nT/degC)."""
    def inject(t, temp, aux, b):
        y = lowpass(t, temp[sensor - 1], tau)
        return {sensor: (y - y.mean())[:, None] * np.array(coef)}
    return inject


def current_squared_fault(coef=(0.6, -0.4, 0.5)):
    """Inject a field proportional to the motor current squared (nT/A^2) on every sensor."""
    def inject(t, temp, aux, b):
        i2 = aux['aux_motor_current'] ** 2
        return {j: i2[:, None] * np.array(coef) * (1.0 + 0.3 * j) for j in range(1, 5)}
    return inject


def random_walk_fault(step_nt=0.02):
    """Inject a sub-noise random walk of every offset (per-sample steps ``step_nt`` nT)."""
    def inject(t, temp, aux, b):
        rng = np.random.default_rng(99)
        return {j: np.cumsum(rng.normal(0, step_nt, (len(t), 3)), axis=0) for j in range(1, 5)}
    return inject


def student_noise(rng, shape, dof=3.0):
    """Heavy-tailed (Student t, 3 dof) noise scaled to 3 nT standard deviation."""
    return rng.standard_t(dof, shape) * SIGMA_NT / np.sqrt(dof / (dof - 2.0))


#: sensor positions of a cross of 0.5 m baseline in the body frame, m
CROSS_M = np.array([[0.25, 0, 0], [0, 0.25, 0], [-0.25, 0, 0], [0, -0.25, 0]])


def site_gradient_fault(grad_nt_m, seed=0):
    """Inject a constant world-frame gradient G (3, 3) nT/m: sensor j sees R^T G R r_j."""
    def inject(t, temp, aux, b):
        _, _, rots = tumbling_field(len(t), seed=seed, rotations=True)
        out = {}
        for j in range(1, 5):
            pos_w = rots @ CROSS_M[j - 1]                               # (N, 3) m
            db_w = pos_w @ np.asarray(grad_nt_m).T                      # (N, 3) nT
            out[j] = np.einsum('nij,ni->nj', rots, db_w)                # R^T db_w
        return out
    return inject
