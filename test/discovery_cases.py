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
Invented field situations for the discovery search (issue 18 items 3 and 6).

Ordinary things that happen to a magnetometer array in the field, of kinds the effect
catalog did not hold when they were written: a warm-up that is smooth but not polynomial,
scale factors that follow a temperature or a supply voltage, a rotor periodic in a wrapped
angle channel, a relay seen through a lag, a passing vehicle and the diurnal variation seen
by the whole array, a disturbance on one arm, a coupling that follows the product of two
channels, a magnetised part whose induced field moves with a servo, a gain switch, a
sensor sampled late, a periodic source at a frequency of the trajectory, and an error
localised in time that nothing simple describes.  Plus controls where nothing is missing.

Every record is written by hand with numpy, as :mod:`injection` does, never by
``Model.forward``: raw_j = K_j B_body + o_j + injected_j + noise, on the cross of
``injection.SENSORS`` (paper 004 Table 1 sized errors, 3 nT noise per axis), with the same
decoy channels in every record (temperatures that vary by +-8 degC, a motor, pump and heater
current, a supply voltage, a relay, a servo position, a wheel angle that wraps), of which at
most one drives anything.  A reference magnitude column (``ref_total``) of the undisturbed
50 000 nT is written, as a magnetometer operator would from a survey value: when the field
itself changes (a vehicle, the diurnal variation) the reference does not know it.

Each :class:`Case` states the attribution a right answer must have (``sensors``, the
``channel`` or ``time`` window) and :func:`attributed` checks a formula term against it.
"""
from dataclasses import dataclass, field
import re

import injection as inj
from magcal_ros.core.data.dataset import Dataset
import numpy as np

SIGMA_NT = inj.SIGMA_NT
ALL = (1, 2, 3, 4)


def _rng(seed, k):
    return np.random.default_rng(1000 * seed + k)


def decoy_channels(t, seed):
    """
    Auxiliary channels {name: (N,)} present in every case (most of them drive nothing).

    aux_motor_current, aux_pump_current, aux_heater_power (A, A, W) as injection.channels;
    aux_supply_v (V): 12 V with slow wander and load sags; aux_relay (A): a relay coil
    switched at irregular intervals; aux_servo_pos (deg): a servo moved between set points;
    aux_wheel_angle (deg): a wheel turning at 0.03-0.09 rev/s, wrapped to [0, 360).
    """
    _, aux = inj.channels(t, seed)
    rng = _rng(seed, 1)
    span = t[-1] - t[0]
    supply = (12.0 + 0.25 * np.sin(2 * np.pi * t / (0.7 * span) + rng.uniform(0, 6))
              + 0.15 * np.sin(2 * np.pi * t / 97.0))
    supply -= 0.4 * ((t // 23.0) % 4 == 1)                       # load sags
    edges = np.cumsum(rng.uniform(8.0, 30.0, size=int(span / 8) + 2))
    relay = 2.0 * (np.searchsorted(edges, t) % 2)                 # 0 / 2 A, irregular
    levels = rng.uniform(-40.0, 40.0, size=int(span / 20) + 2)
    servo = levels[(t // 20.0).astype(int)]
    servo = np.convolve(np.pad(servo, 5, mode='edge'), np.ones(11) / 11, 'valid')
    rev_s = 0.06 + 0.03 * np.sin(2 * np.pi * t / (0.45 * span))
    wheel = np.mod(360.0 * np.cumsum(rev_s) * np.median(np.diff(t)), 360.0)
    aux.update({'aux_supply_v': supply, 'aux_relay': relay, 'aux_servo_pos': servo,
                'aux_wheel_angle': wheel})
    return aux


def sensor_readings(b_body):
    """(4, N, 3) undisturbed readings K_j B (offsets excluded), nT."""
    return np.stack([b_body @ inj.sensor_matrix(j).T for j in ALL])


def build(n, seed, inject=None, rate_hz=inj.RATE_HZ, field_change=None):
    """
    Dataset of the cross with the case's disturbance.

    Parameters
    ----------
    n : int
        Epochs.
    seed : int
        Seed of the tumble, the channels and the noise.
    inject : callable, optional
        inject(t, temp (4, N) degC, aux, clean (4, N, 3) nT) -> {sensor: (N, 3) nT}.
    rate_hz : float
        Sampling rate, Hz.
    field_change : callable, optional
        field_change(t) -> (N,) nT added to the field's magnitude (seen by every sensor,
        along the field); the reference column keeps 50 000 nT.

    """
    rng = _rng(seed, 2)
    t, b = inj.tumbling_field(n, rate_hz=rate_hz, seed=seed)
    temp, _ = inj.channels(t, seed)
    aux = decoy_channels(t, seed)
    if field_change is not None:
        b = b * (1.0 + field_change(t) / inj.F_NT)[:, None]
    clean = sensor_readings(b)
    add = inject(t, temp, aux, clean) if inject else {}
    raw = np.empty((4, n, 3))
    for j in ALL:
        raw[j - 1] = clean[j - 1] + np.array(inj.SENSORS[j - 1][3]) + add.get(j, 0.0)
        raw[j - 1] += rng.normal(0, SIGMA_NT, (n, 3))
    return Dataset(t=t, raw=raw, temp=temp, aux=aux, ref_total=np.full(n, inj.F_NT))


@dataclass
class Case:
    """
    One invented situation and the attribution a right answer must have.

    Attributes
    ----------
    name : str
        Short name.
    what : str
        The situation in words.
    sensors : tuple of int
        The sensors that carry the disturbance (ALL for the whole array; () for a control).
    channel : str or None
        The channel that drives it ('t' for time, 'rate' for the field rate).
    time : tuple or None
        (t0, t1) s of a disturbance localised in time, as fractions of the span.
    inject, field_change : callable or None
        As :func:`build`.
    rate_hz : float
        Sampling rate.
    time_kind : tuple of str
        For a disturbance in time ('t'): the kinds of time driver that describe it
        (:data:`TIME_KINDS`): a smooth basis, steps, a sinusoid, a window or left-out interval.

    """

    name: str
    what: str
    sensors: tuple
    channel: str | None = None
    time: tuple | None = None
    inject: object = None
    field_change: object = None
    rate_hz: float = inj.RATE_HZ
    tags: tuple = field(default_factory=tuple)
    time_kind: tuple = ()

    def data(self, n, seed=11):
        """Return the Dataset of this case with ``n`` epochs."""
        return build(n, seed, self.inject, self.rate_hz, self.field_change)

    def window(self, t):
        """(t0, t1) s of a localised disturbance in a record of times ``t``, or None."""
        if self.time is None:
            return None
        span = t[-1] - t[0]
        return (t[0] + self.time[0] * span, t[0] + self.time[1] * span)


def _vec(*c):
    return np.array(c, float)


# -- the disturbances, each written out ---------------------------------------------------------

def warmup(sensor=2, tau_frac=0.12, amp=_vec(28.0, -20.0, 14.0)):
    """Return an offset settling exponentially after switch-on (tau: a share of the record)."""
    def f(t, temp, aux, clean):
        tau = tau_frac * (t[-1] - t[0])
        return {sensor: np.exp(-(t - t[0]) / tau)[:, None] * amp}
    return f


def scale_follows(channel, sensor, coef, ref=None):
    """Return scale factors (per axis, 1/unit) following a channel (``sensor``'s temperature)."""
    def f(t, temp, aux, clean):
        x = temp[sensor - 1] if channel == 'temperature' else aux[channel]
        x = x - (np.mean(x) if ref is None else ref)
        return {sensor: x[:, None] * np.asarray(coef) * clean[sensor - 1]}
    return f


def rotor(sensor=1, channel='aux_wheel_angle', amp=(18.0, 12.0, -9.0), harmonic=1):
    """Return a magnetised rotating part: a field periodic in the wheel angle (360 deg)."""
    def f(t, temp, aux, clean):
        th = np.deg2rad(aux[channel]) * harmonic
        a = np.asarray(amp)
        return {sensor: np.stack([a[0] * np.cos(th), a[1] * np.sin(th + 0.5),
                                  a[2] * np.cos(th - 1.0)], 1)}
    return f


def relay_lag(sensor=4, tau=6.0, coef=_vec(9.0, -7.0, 5.0)):
    """Return a relay's current reaching the sensor through eddy currents (first-order lag)."""
    def f(t, temp, aux, clean):
        y = inj.lowpass(t, aux['aux_relay'], tau)
        return {sensor: (y - y.mean())[:, None] * coef}
    return f


def vehicle(t_frac=0.45, width_s=40.0, amp=45.0):
    """Return a vehicle passing: the field magnitude changes by a smooth bump of ~40 s."""
    def g(t):
        tc = t[0] + t_frac * (t[-1] - t[0])
        return amp * np.exp(-0.5 * ((t - tc) / (width_s / 4.0)) ** 2)
    return g


def diurnal(amp=120.0, period_s=3 * 3600.0, phase=0.8):
    """Return the field's diurnal variation (all sensors alike), a slow curve."""
    def g(t):
        return amp * np.sin(2 * np.pi * t / period_s + phase) - amp * np.sin(phase)
    return g


def arm(sensors=(2, 4), channel='aux_pump_current', coef=_vec(10.0, 6.0, -8.0)):
    """Return a cable along one arm: the sensors of that arm see a current's field."""
    def f(t, temp, aux, clean):
        x = aux[channel] - aux[channel].mean()
        return {j: x[:, None] * coef * (1.0 + 0.2 * k) for k, j in enumerate(sensors)}
    return f


def product(sensor=1, a='aux_motor_current', b='temperature', coef=_vec(1.2, -0.9, 0.7)):
    """
    Return a coupling following the product of two centred channels.

    A current's field whose gain drifts with temperature: nT per A degC.
    """
    def f(t, temp, aux, clean):
        xa = aux[a] - aux[a].mean()
        xb = temp[sensor - 1] if b == 'temperature' else aux[b]
        xb = xb - xb.mean()
        return {sensor: (xa * xb)[:, None] * coef}
    return f


def induced(sensor=3, channel='aux_servo_pos', gain=2.0e-5):
    """
    Return a soft part moved by a servo: an induced field proportional to the field.

    Its 3 x 3 coupling matrix (per degree) follows the servo's position.
    """
    m = gain * np.array([[0.6, 0.3, -0.2], [-0.4, 0.8, 0.1], [0.2, -0.3, -0.5]])

    def f(t, temp, aux, clean):
        x = aux[channel] - aux[channel].mean()
        return {sensor: x[:, None] * (clean[sensor - 1] @ m.T)}
    return f


def gain_switch(sensor=2, t_frac=0.55, dk=_vec(4e-4, -3e-4, 5e-4)):
    """Return a range (gain) switch: the scale factors step at one time."""
    def f(t, temp, aux, clean):
        t0 = t[0] + t_frac * (t[-1] - t[0])
        return {sensor: (t >= t0)[:, None] * dk * clean[sensor - 1]}
    return f


def skew(sensor=4, delay_s=6e-4):
    """Return one sensor sampled late by ``delay_s``: it reads B(t - delay)."""
    def f(t, temp, aux, clean):
        # B(t - d) = B(t) - d dB/dt to first order (d dB/dt ~ 12 nT, the next term ~1e-5 nT)
        return {sensor: -delay_s * np.gradient(clean[sensor - 1], t, axis=0)}
    return f


def trajectory_line(sensor=2, amp=_vec(12.0, -10.0, 8.0)):
    """Return a source periodic at a frequency of the trajectory (the axis wander)."""
    def f(t, temp, aux, clean):
        ph = 0.07 * t + 1.1           # the same phase as the axis wander in injection
        return {sensor: np.stack([amp[0] * np.cos(ph), amp[1] * np.sin(ph),
                                  amp[2] * np.cos(ph + 0.7)], 1)}
    return f


def localized(sensor=3, t_frac=(0.30, 0.37), amp=35.0, seed=5):
    """Return something nothing simple describes, over a few tens of seconds on one sensor."""
    def f(t, temp, aux, clean):
        t0, t1 = (t[0] + q * (t[-1] - t[0]) for q in t_frac)
        inside = (t >= t0) & (t <= t1)
        rng = np.random.default_rng(seed)
        x = np.cumsum(rng.normal(size=(len(t), 3)), axis=0)
        x = x - np.mean(x[inside], axis=0)
        x /= np.std(x[inside]) + 1e-9
        env = np.sin(np.pi * np.clip((t - t0) / (t1 - t0), 0, 1)) ** 2
        return {sensor: amp * x * env[:, None]}
    return f


def temp_drifting_coef(sensor=1, coef=_vec(0.8, -0.6, 0.5)):
    """Return a temperature coefficient (nT/degC) that changes linearly over the record."""
    def f(t, temp, aux, clean):
        x = temp[sensor - 1] - temp[sensor - 1].mean()
        u = (t - t.mean()) / (t[-1] - t[0]) * 2.0
        return {sensor: (x * u)[:, None] * coef * 3.0}
    return f


def common_offset(amp=_vec(14.0, -10.0, 9.0), period_frac=0.9):
    """Return every sensor's electronics warming alike: one slow offset in its axes."""
    def f(t, temp, aux, clean):
        u = (t - t[0]) / (t[-1] - t[0])
        s = np.tanh((u - 0.35) / 0.12) + 0.3 * np.sin(2 * np.pi * u / period_frac)
        return {j: s[:, None] * amp for j in ALL}
    return f


def supply_offset_sq(sensor=3, coef=_vec(25.0, -18.0, 12.0)):
    """Return a regulator's stray field, with the square of the supply's deviation."""
    def f(t, temp, aux, clean):
        x = aux['aux_supply_v'] - 12.0
        x2 = x ** 2 - np.mean(x ** 2)
        return {sensor: x2[:, None] * coef * 4.0}
    return f


#: the kinds of time driver a term in time may use, by what they match in the term
TIME_KINDS = {
    'smooth': r'\bs\(t\b|\bpoly\(t\b|\bdrift2?\b',
    'step': r'\bstep\(',
    'periodic': r'\bperiodic\(|\bsin\(t\b',
    'window': r'\bdrop\(|\bwindow\(',
}

CASES = [
    Case('control', 'nothing missing; every decoy channel varies', (), None),
    Case('control_fast', 'nothing missing, sampled at 10 Hz', (), None, rate_hz=10.0),
    Case('warmup', 'offset settling exponentially after switch-on, sensor 2', (2,), 't',
         inject=warmup(), time_kind=('smooth', 'step')),   # steps at its fast start
    Case('scale_temperature', 'scale factors of sensor 3 follow its temperature', (3,),
         'temperature', inject=scale_follows('temperature', 3, _vec(5e-5, -4e-5, 6e-5))),
    Case('rotor', 'a magnetised wheel near sensor 1, periodic in the wrapped wheel angle',
         (1,), 'aux_wheel_angle', inject=rotor()),
    Case('relay_lag', 'a relay current through a 6 s lag, sensor 4', (4,), 'aux_relay',
         inject=relay_lag()),
    Case('vehicle', 'a vehicle passing: a 40 s bump of the field seen by every sensor', ALL,
         't', time=(0.40, 0.50), field_change=vehicle(), time_kind=('window',)),
    Case('diurnal', 'the diurnal variation: the field changes alike for every sensor', ALL,
         't', field_change=diurnal(), time_kind=('smooth',)),
    Case('arm', 'a current along the arm of sensors 2 and 4', (2, 4), 'aux_pump_current',
         inject=arm()),
    Case('product', 'a current coupling whose gain follows temperature, sensor 1', (1,),
         'aux_motor_current', inject=product()),
    Case('supply_scale', 'scale factors of sensor 2 follow the supply voltage', (2,),
         'aux_supply_v', inject=scale_follows('aux_supply_v', 2, _vec(6e-4, -5e-4, 4e-4))),
    Case('induced', 'a soft part moved by a servo near sensor 3 (field-proportional)', (3,),
         'aux_servo_pos', inject=induced()),
    Case('gain_switch', 'the scale factors of sensor 2 step at a range switch', (2,), 't',
         time=(0.55, 0.55), inject=gain_switch(), time_kind=('step',)),
    Case('skew', 'sensor 4 sampled 0.6 ms late', (4,), 'rate', inject=skew()),
    Case('trajectory_line', 'a source at a frequency of the trajectory, sensor 2', (2,), 't',
         inject=trajectory_line(), time_kind=('periodic',)),
    Case('localized', 'a 40 s disturbance nothing simple describes, sensor 3', (3,), 't',
         time=(0.30, 0.37), inject=localized(), time_kind=('window',)),
    Case('temp_coef_drift', 'a temperature coefficient that drifts over the record, sensor 1',
         (1,), 'temperature', inject=temp_drifting_coef()),
    Case('common_warmup', "every sensor's offset drifting alike (common electronics)", ALL,
         't', inject=common_offset(), time_kind=('smooth',)),
    Case('supply_squared', 'a stray field with the square of the supply deviation, sensor 3',
         (3,), 'aux_supply_v', inject=supply_offset_sq()),
]

BY_NAME = {c.name: c for c in CASES}


# -- attribution of a formula term --------------------------------------------------------------

def term_sensors(term, n_sensors=4):
    """Return the sensors a formula term acts on (tuple), from its scope."""
    if term is None:
        return ()
    m = re.search(r'@\s*\{([^}]*)\}\s*$', term)
    if m:
        return tuple(sorted(int(x) for x in m.group(1).split(',') if x.strip()))
    m = re.search(r'@\s*(\d+)\s*$', term)
    if m:
        return (int(m.group(1)),)
    return tuple(range(1, n_sensors + 1))


def _numbers(term):
    return [float(x) for x in re.findall(r'(?<![\w.])-?\d+(?:\.\d+)?(?:e-?\d+)?', term)]


def attributed(case, term, t):
    """
    Return (ok, why): whether ``term`` names the case's sensors and channel or time.

    Sensors: the term's scope must be exactly the case's sensors (a term on every sensor,
    alike or on the array, for a disturbance of the whole array).  Channel: the channel's
    name must appear in the term ('t' for time: a driver of one of the case's
    ``time_kind``, e.g. a step for a gain switch, not a smooth basis that also brings the
    residual to the floor; 'rate': the field rate).  Time: a localised
    disturbance's term must name a time inside its window widened by 5 % of the span (a
    step), or an interval overlapping it by at least half of the window.
    """
    if term is None:
        return (not case.sensors), 'no term' if case.sensors else 'none (control)'
    if not case.sensors:
        return False, 'a control needs no term'
    scope = term_sensors(term)
    if tuple(sorted(scope)) != tuple(sorted(case.sensors)):
        return False, f'sensors {scope} != {case.sensors}'
    ch = case.channel
    if ch == 't':
        kinds = [k for k in case.time_kind if re.search(TIME_KINDS[k], term)]
        if not kinds:
            return False, f'not a function of time of the kind {" or ".join(case.time_kind)}'
    elif ch == 'rate':
        if 'rate' not in term:
            return False, 'not the field rate'
    elif ch == 'temperature':
        if 'temperature' not in term:
            return False, 'not the temperature'
    elif ch and ch not in term:
        return False, f'not {ch}'
    win = case.window(t)
    if win is not None:
        span = t[-1] - t[0]
        nums = _numbers(term.split('@')[0])
        lo, hi = win[0] - 0.05 * span, win[1] + 0.05 * span
        if not any(lo <= x <= hi for x in nums):
            return False, f'no time within {lo:.0f}..{hi:.0f} s'
    return True, 'ok'
