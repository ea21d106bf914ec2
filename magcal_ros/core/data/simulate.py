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
Seeded simulator of a four-fluxgate cross gradiometer (paper 004 section 4.1), uniform field.

The forward model is the fit's (:class:`magcal_ros.core.model.Model`): any effect, plug-ins
too, can be switched on with known parameters.  Everything is a deterministic function of
time and the seed, so :meth:`Simulator.sample` continues smoothly chunk by chunk.
"""
from dataclasses import dataclass, field

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.effects import raw_rate, SensorContext
from magcal_ros.core.geometry.tensor import cross_positions
from magcal_ros.core.model import Model
from magcal_ros.core.papers.paper_params import table1_sensor
import numpy as np
from scipy.spatial.transform import Rotation

TRAJECTORIES = ('random', 'smooth', 'turntable', 'cone', 'vehicle')
AUX_CHANNELS = ('aux_motor_current', 'aux_pump_current', 'aux_heater_power')


def earth_field(total_nt, declination_deg, inclination_deg):
    """(3,) field in a north-east-down frame, nT, from total intensity, D and I."""
    d, i = np.radians(declination_deg), np.radians(inclination_deg)
    return total_nt * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


@dataclass
class SimConfig:
    """
    Settings of the simulator; defaults are paper 004 section 4.1.

    ``n_sensors``: 4 is the cross (from ``baseline_m``) unless ``positions_m`` ((S, 3) or
    (3 S,) m) is given; other counts sit at ``positions_m`` (default: the origin).
    ``trajectory``: 'random', 'smooth' (tumbling over the sphere in about a minute),
    'turntable' (about body z), 'cone' (field in a cap of ``cone_half_angle_deg`` around
    body +z), 'vehicle' (:func:`vehicle_attitude`).  ``errors``: 'paper004' (Table 1, sensor
    j > 4 as sensor ((j - 1) mod 4) + 1) or None.  ``truth``: {term: parameter values} added
    to ``model``.  ``gradient_nt_per_m``: (3, 3) world (NED) gradient, nT/m, ``field_nt``
    then at the centre.  ``attitude_error_deg``: RMS error per body axis of the attitude put
    into the samples (:func:`attitude_error`).
    """

    n_samples: int = 200                # epochs N (for :func:`simulate`)
    rate_hz: float = 100.0
    n_sensors: int = 4
    baseline_m: float = 0.5             # distance between the two sensors of an arm, m
    field_nt: float = 50000.0           # Earth field: total intensity, nT
    declination_deg: float = -7.0
    inclination_deg: float = 55.0
    noise_nt: object = 3.0              # Gaussian sd per axis, nT (scalar or per sensor)
    trajectory: str = 'random'
    cone_half_angle_deg: float = 30.0
    tilt_deg: float = 15.0              # vehicle: largest roll and pitch, deg
    smooth_period_s: float = 60.0
    errors: str | None = 'paper004'
    model: str = 'base'
    truth: dict = field(default_factory=dict)
    temp_mean_c: float = 25.0           # sensor temperatures: mean and half swing, degC
    temp_swing_c: float = 8.0
    aux: bool = True                    # generate the channels of :data:`AUX_CHANNELS`
    diurnal_swing_nt: float = 0.0       # peak-to-peak |B| variation (a ref_total column), nT
    diurnal_period_s: float = 600.0
    outlier_fraction: float = 0.0       # fraction of samples hit by a spike ...
    outlier_nt: float = 1000.0          # ... of this size, random direction, nT
    gradient_nt_per_m: object = None
    attitude: bool = False              # put the true attitude (Dataset.attitude) in
    attitude_error_deg: float = 0.0
    seed: int = 0
    positions_m: object = None


#: world ENU (REP 103) -> NED (the simulator's world); its own inverse (R_ned = ENU_TO_NED R_enu)
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def attitude_error(t, rms_deg, seed=0):
    """
    Return (N, 3) rad: a smooth attitude error about each body axis at times ``t`` (N,) s.

    Four sinusoids per axis (an EKF's drift), periods 20-200 s and phases from ``seed``,
    ``rms_deg`` RMS each.
    """
    rng = np.random.default_rng([int(seed), 7001])
    per = rng.uniform(20.0, 200.0, (3, 4))
    ph = rng.uniform(0.0, 2 * np.pi, (3, 4))
    t = np.asarray(t, float)
    err = np.sin(2 * np.pi * t[:, None, None] / per[None] + ph[None]).sum(axis=2)
    # each sinusoid has RMS 1/sqrt(2), four independent ones sqrt(2) together
    return err * (np.radians(rms_deg) / np.sqrt(2.0))


def vehicle_attitude(t, period_s=60.0, tilt_deg=15.0, phases=(0.0, 0.0, 0.0)):
    """
    Body-to-world (NED) rotation of a vehicle that stays near level and turns part circles.

    Body axes REP 103's.  The heading swings through +-0.8 of a circle over ``period_s`` and
    drifts by a third of a circle per period; pitch and roll within +-``tilt_deg``.  ``t``
    (N,) s; ``phases`` of heading, pitch and roll, rad.  Returns N scipy Rotations body ->
    NED (``ENU_TO_NED.T @ R`` into ENU).
    """
    t = np.asarray(t, float)
    w = 2 * np.pi / period_s
    tilt = np.radians(tilt_deg)
    yaw = phases[0] + 0.8 * 2 * np.pi * np.sin(w * t) + 2 * np.pi / 3 * t / period_s
    pitch = tilt * np.sin(w * 2.3 * t + phases[1])
    roll = tilt * np.sin(w * 3.7 * t + phases[2])
    body_enu = Rotation.from_euler('ZYX', np.column_stack([yaw, pitch, roll]))
    return Rotation.from_matrix(ENU_TO_NED) * body_enu


def attitude_enu(q_ned):
    """Body-to-ENU quaternions (N, 4) (qw, qx, qy, qz) of body-to-NED ones (N, 4)."""
    rot = Rotation.from_quat(np.asarray(q_ned, float).reshape(-1, 4), scalar_first=True)
    return (Rotation.from_matrix(ENU_TO_NED.T) * rot).as_quat(scalar_first=True)


def causal_rate(x, t):
    """
    Rate of ``x`` (N, 3) nT at times ``t`` (N,) s from each sample and the two before it.

    The live corrector's one-sided difference; (N, 3) nT/s, zero for the first two samples;
    None with fewer than 3 samples or times that do not increase.
    """
    x = np.asarray(x, float)
    t = np.asarray(t, float)
    if len(x) < 3 or not np.all(np.diff(t) > 0):
        return None
    h1 = (t[1:-1] - t[:-2])[:, None]          # t_k-1 - t_k-2
    h2 = (t[2:] - t[1:-1])[:, None]           # t_k - t_k-1
    out = np.zeros_like(x)
    out[2:] = (h2 / (h1 * (h1 + h2)) * x[:-2] - (h1 + h2) / (h1 * h2) * x[1:-1]
               + (2 * h2 + h1) / (h2 * (h1 + h2)) * x[2:])
    return out


class Simulator:
    """Generate samples of the configured array at arbitrary times."""

    def __init__(self, config=None, **overrides):
        cfg = config or SimConfig()
        for k, v in overrides.items():
            if not hasattr(cfg, k):
                raise ValueError(f'unknown simulator setting {k!r}')
            setattr(cfg, k, v)
        if cfg.trajectory not in TRAJECTORIES:
            raise ValueError(f'unknown trajectory {cfg.trajectory!r}; use one of {TRAJECTORIES}')
        self.config = cfg
        self.rng = np.random.default_rng(cfg.seed)
        s = cfg.n_sensors
        tokens = [cfg.model] + [t for t in cfg.truth if t not in ('base',)]
        self.model = Model.from_spec(' + '.join(tokens), s)
        p = self.model.default_params()
        if cfg.errors == 'paper004':
            for j in range(1, s + 1):
                a, o = table1_sensor((j - 1) % 4 + 1).to_general()
                p = self.model.params_from_linear(j, a, o, p)
        elif cfg.errors is not None:
            raise ValueError("errors must be 'paper004' or None")
        for token, values in cfg.truth.items():
            self._set_truth(p, token, values)
        self.params = p
        if cfg.positions_m is not None:
            self.positions = np.asarray(cfg.positions_m, float).reshape(-1, 3)
            if len(self.positions) != s:
                raise ValueError(f'positions_m has {len(self.positions)} positions for {s} '
                                 'sensors')
        else:
            self.positions = cross_positions(cfg.baseline_m) if s == 4 else np.zeros((s, 3))
        self.noise = np.broadcast_to(np.asarray(cfg.noise_nt, float), (s,)).copy()
        self.b_world = earth_field(cfg.field_nt, cfg.declination_deg, cfg.inclination_deg)
        seed_rng = np.random.default_rng([cfg.seed, 7])
        self._phases = seed_rng.uniform(0, 2 * np.pi, size=16)
        self._levels = seed_rng.uniform(0.0, 5.0, size=4096)
        first = np.column_stack([self._phases[6:10], self._phases[10:14]])
        more = seed_rng.uniform(0, 2 * np.pi, size=(max(s - 4, 0), 2))
        self._temp_phases = np.vstack([first, more])[:s]
        self._tail = {}         # sensor -> (times (2,) s, noise-free readings (2, 3) nT)

    def _set_truth(self, p, token, values):
        """Set the true parameters of the term ``token`` on every sensor of its scope."""
        from magcal_ros.core.effects.formula import parse_term
        term = parse_term(token)
        values = np.asarray(values, float)
        sensors = term.sensors(self.model.n_sensors)
        found = [(eff, sl) for j, row in enumerate(self.model.effects) if j + 1 in sensors
                 for eff, sl in zip(row, self.model.slices[j])
                 if eff.label in (term.core, term.text) or eff.name == term.core]
        arr = zip(self.model.array_effects, self.model.array_slices)
        found += [(eff, sl) for eff, sl in arr if eff.label == term.core]
        if not found:
            raise ValueError(f'truth for {token!r} but no such term in the model')
        for eff, sl in found:
            if values.size != eff.n_params:
                raise ValueError(f'{token}: {eff.n_params} values expected '
                                 f'({", ".join(eff.param_names)})')
            p[sl] = values

    def attitude(self, t):
        """Rotation (body -> world) at times t (N,) s, as a scipy Rotation."""
        cfg = self.config
        n = len(t)
        if cfg.trajectory == 'random':
            return Rotation.random(n, random_state=self.rng)
        if cfg.trajectory == 'smooth':
            w, ph = 2 * np.pi / cfg.smooth_period_s, self._phases
            yaw = w * 3.1 * t + ph[0]
            pitch = np.radians(85) * np.sin(w * 1.7 * t + ph[1])
            roll = np.pi * np.sin(w * 1.13 * t + ph[2])
            return Rotation.from_euler('ZYX', np.column_stack([yaw, pitch, roll]))
        if cfg.trajectory == 'turntable':
            yaw = 2 * np.pi * t / cfg.smooth_period_s * 3
            return Rotation.from_euler('Z', yaw[:, None])
        if cfg.trajectory == 'vehicle':
            return vehicle_attitude(t, cfg.smooth_period_s, cfg.tilt_deg, self._phases[3:6])
        # cone: body-frame field directions in a cap around +z
        cos_t = self.rng.uniform(np.cos(np.radians(cfg.cone_half_angle_deg)), 1.0, n)
        phi = self.rng.uniform(0, 2 * np.pi, n)
        sin_t = np.sqrt(1 - cos_t ** 2)
        d = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
        bw = self.b_world / np.linalg.norm(self.b_world)      # body d -> world field
        return Rotation.concatenate([Rotation.align_vectors([bw], [dk])[0] for dk in d])

    def temperature(self, t):
        """(S, N) sensor temperatures, degC."""
        cfg, ph = self.config, self._temp_phases
        j = np.arange(cfg.n_sensors)[:, None]
        return cfg.temp_mean_c + j * 0.7 + cfg.temp_swing_c * np.sin(
            2 * np.pi * t / 240.0 + ph[:, :1]) * (0.8 + 0.2 * np.cos(
                2 * np.pi * t / 97.0 + ph[:, 1:]))

    def aux_channels(self, t):
        """{'aux_motor_current' (A), 'aux_pump_current' (A), 'aux_heater_power' (W)} -> (N,)."""
        ph = self._phases
        step = np.floor(t / 7.0).astype(int) % len(self._levels)
        motor = self._levels[step] * (self._levels[(step * 7 + 3) % len(self._levels)] > 1.5)
        pump = 1.0 + 0.5 * np.sin(2 * np.pi * t / 47.0 + ph[14])
        heater = 10.0 * ((t / 180.0 + ph[15] / (2 * np.pi)) % 1.0)
        return {'aux_motor_current': motor, 'aux_pump_current': pump, 'aux_heater_power': heater}

    def field_magnitude(self, t):
        """(N,) total field, nT (constant unless a diurnal swing is set)."""
        cfg = self.config
        return cfg.field_nt + 0.5 * cfg.diurnal_swing_nt * np.sin(
            2 * np.pi * t / cfg.diurnal_period_s + self._phases[13])

    def true_field(self, t, rot=None):
        """(S, N, 3) true field at each sensor in the array (body) frame, nT."""
        cfg = self.config
        rot = self.attitude(t) if rot is None else rot
        b_body = rot.inv().apply(self.b_world) * (self.field_magnitude(t) / cfg.field_nt)[:, None]
        out = np.repeat(b_body[None], cfg.n_sensors, axis=0)
        if cfg.gradient_nt_per_m is not None:
            g = np.asarray(cfg.gradient_nt_per_m, float)
            rm = rot.as_matrix()
            g_body = np.einsum('nji,jk,nkl->nil', rm, g, rm)     # R^T G R
            out = out + np.einsum('nij,sj->sni', g_body, self.positions)
        return out

    def sample(self, t, causal=False):
        """
        Simulate a Dataset at times t (N,) s; ``meta['truth_field']`` holds the true field.

        The field rate of rate-dependent effects is the fit's (central differences) or, with
        ``causal``, the live corrector's (:func:`causal_rate`), continued across chunks.
        """
        cfg = self.config
        t = np.asarray(t, float)
        n = len(t)
        s = cfg.n_sensors
        temp = self.temperature(t)
        aux = self.aux_channels(t) if cfg.aux else {}
        rot = self.attitude(t)
        b = self.true_field(t, rot)
        raw = np.empty((s, n, 3))
        for j in range(1, s + 1):
            lin = b[j - 1] @ self.model.matrix(j, self.params).T
            # a chunk that continues the previous one takes its last two readings
            tail = self._tail.get(j)
            if tail is not None and n and t[0] > tail[0][-1]:
                tt, ll = np.concatenate([tail[0], t]), np.concatenate([tail[1], lin])
            else:
                tt, ll = t, lin
            rate = causal_rate(ll, tt) if causal else raw_rate(ll, tt)
            rate = np.zeros_like(lin) if rate is None else rate[len(tt) - n:]
            self._tail[j] = (tt[-2:], ll[-2:])
            ctx = SensorContext(t=t, temp=temp[j - 1], aux=aux, raw_rate=rate)
            raw[j - 1] = self.model.forward(j, self.params, b[j - 1], ctx)
        raw += self.rng.normal(size=raw.shape) * self.noise[:, None, None]
        if cfg.outlier_fraction > 0:
            hit = self.rng.random((s, n)) < cfg.outlier_fraction
            d = self.rng.normal(size=(s, n, 3))
            d /= np.linalg.norm(d, axis=2, keepdims=True)
            raw[hit] += cfg.outlier_nt * d[hit]
        ref_total = self.field_magnitude(t) if cfg.diurnal_swing_nt else None
        if cfg.attitude and cfg.attitude_error_deg:
            rot = rot * Rotation.from_rotvec(attitude_error(t, cfg.attitude_error_deg, cfg.seed))
        return Dataset(t=t, raw=raw, temp=temp, ref_total=ref_total, aux=aux,
                       meta={'truth_field': b, 'simulator': cfg},
                       attitude=rot.as_quat(scalar_first=True) if cfg.attitude else None)

    @property
    def truth(self):
        """:class:`magcal_ros.core.model.Calibration` holding the true parameters."""
        from magcal_ros.core.model import Calibration
        return Calibration(self.model, self.params, sigma_nt=self.noise)


def simulate(config=None, **overrides):
    """
    Simulate ``config.n_samples`` epochs at ``config.rate_hz``; returns (Dataset, Simulator).

    Examples
    --------
    >>> data, sim = simulate(n_samples=200, seed=1)
    >>> data.raw.shape
    (4, 200, 3)

    """
    sim = Simulator(config, **overrides)
    t = np.arange(sim.config.n_samples) / sim.config.rate_hz
    set_truth_refs(sim, t)
    return sim.sample(t), sim


def simulate_chunks(config=None, rows=65536, **overrides):
    """
    Simulate a long record piece by piece: (Simulator, iterator of Datasets of ``rows`` epochs).

    As :func:`simulate` in memory bounded by ``rows``; the references come from at most
    100 000 evenly spaced instants; noise and field rate are taken chunk by chunk.
    """
    sim = Simulator(config, **overrides)
    n, rate, rows = int(sim.config.n_samples), float(sim.config.rate_hz), int(rows)
    set_truth_refs(sim, np.arange(0, n, max(1, -(-n // 100000))) / rate)
    return sim, (sim.sample(np.arange(i, min(n, i + rows)) / rate) for i in range(0, n, rows))


def set_truth_refs(sim, t):
    """Fix the truth's reference values (mean temperature etc.) from the times ``t`` (N,) s."""
    temp = sim.temperature(t)
    aux = sim.aux_channels(t) if sim.config.aux else {}
    sim.model.prepare([SensorContext(t=t, temp=temp[j], aux=aux)
                       for j in range(len(sim.model.effects))])


def parse_truth(items):
    """
    Parse hidden effects ``EFFECT=V1,V2,...`` (``magcal simulate --truth``, ``fluxgate_sim``).

    The effect is any model term (``temperature@2``), split at the last ``=`` outside
    parentheses; the values its parameters in ``param_names`` order and ``units``.  Returns
    {term: list of float}, the ``truth`` of :class:`SimConfig`; ValueError naming the bad item.
    """
    truth = {}
    for item in items or []:
        item = str(item)
        depth, cut = 0, -1
        for i, ch in enumerate(item):
            depth += (ch in '({') - (ch in ')}')
            if ch == '=' and depth == 0:
                cut = i
        token, values = item[:cut].strip(), item[cut + 1:]
        if cut < 0 or not token:
            raise ValueError(f'{item!r}: expected TERM=v1,v2,... (e.g. temperature@2=3,-2,1.5,'
                             '0,0,0 or offset(window(20, 40))@2=30,0,0)')
        try:
            nums = [float(v) for v in values.split(',')]
        except ValueError:
            raise ValueError(f'{item!r}: values must be numbers') from None
        if not np.all(np.isfinite(nums)):
            raise ValueError(f'{item!r}: values must be finite numbers')
        truth[token] = nums
    return truth
