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

r"""
Simulated fluxgates on pseudo-terminals, without ROS: the devices ``fluxgate_sim`` serves.

One :class:`~magcal_ros.serial.transport.PtyDevice` per sensor, linked as
``<dir>/fluxgate1`` ... (:func:`device_dir` of the namespace), streams
:class:`magcal_ros.core.data.simulate.Simulator`'s output in a serial protocol, once per
tick.  The defaults are paper 004 §4.1 (|B| = 50 000 nT, D = -7 deg, I = 55 deg, 3 nT noise,
the Table 1 errors, 100 Hz); the settings (site gradient, hidden effects, trajectory,
attitude) are described in docs/design.md §3.  ``unplug`` entries
``SENSOR:AT_S:FOR_S[:NEW_PATH]`` close a sensor's pseudo-terminal at ``AT_S`` s and plug a
new one ``FOR_S`` s later.  The ROS node (:mod:`magcal_ros.ros.sim_node`) also publishes
the channels and the attitude; ``python -m magcal_ros.sim`` has no topics.
"""
import argparse
from dataclasses import dataclass
import math
import os
import signal
import sys
import threading
import time

from magcal_ros.core.data.simulate import (AUX_CHANNELS, parse_truth, set_truth_refs,
                                           SimConfig, Simulator, TRAJECTORIES)
from magcal_ros.serial import (load_yaml, make_encoder, parse_options, parse_value, PROTOCOLS,
                               Sample)
from magcal_ros.serial.transport import PtyDevice
from magcal_ros.sim import DEFAULT_DIR, DEFAULT_NAMESPACE, DEFAULT_PREFIX, device_dir
import numpy as np
import yaml

#: name of the ROS node, and of this program in its messages
NODE_NAME = 'fluxgate_sim'


@dataclass(frozen=True)
class Unplug:
    """One scheduled unplug of a sensor (sensor numbered from 1, times in s)."""

    sensor: int
    at_s: float
    for_s: float
    new_path: str | None = None


def parse_unplug(text):
    """Parse ``SENSOR:AT_S:FOR_S[:NEW_PATH]`` into an :class:`Unplug` (ArgumentTypeError)."""
    parts = str(text).split(':', 3)
    try:
        if len(parts) < 3:
            raise ValueError
        sensor, at_s, for_s = int(parts[0]), float(parts[1]), float(parts[2])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f'--unplug expects SENSOR:AT_S:FOR_S[:NEW_PATH] (e.g. 2:5:1.5), got {text!r}'
        ) from None
    if sensor < 1 or not (math.isfinite(at_s) and at_s >= 0) or \
            not (math.isfinite(for_s) and for_s >= 0):
        raise argparse.ArgumentTypeError(
            f'--unplug needs SENSOR >= 1 and times >= 0 s, got {text!r}')
    return Unplug(sensor, at_s, for_s, parts[3] if len(parts) == 4 and parts[3] else None)


def parse_option(text):
    """Parse a protocol option ``KEY=VALUE`` (VALUE read as YAML: numbers, lists, ...)."""
    key, sep, raw = str(text).partition('=')
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f'--option expects KEY=VALUE, got {text!r}')
    return key.strip(), parse_value(raw)


def parse_truth_item(text):
    """Check one hidden effect ``EFFECT=V1,V2,...`` (``--truth``); return it unchanged."""
    try:
        parse_truth([text])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f'--truth {exc}') from None
    return str(text)


def _positive(strict=True):
    """Return an argparse type: a finite number, > 0 (``strict``) or >= 0."""
    def check(text):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expected a number, got {text!r}') from None
        if not (math.isfinite(value) and (value > 0 if strict else value >= 0)):
            raise argparse.ArgumentTypeError(
                f'must be {">" if strict else ">="} 0, got {text!r}')
        return value
    return check


_non_negative = _positive(strict=False)


def parse_gradient(text):
    """``GXX,GXY,GXZ,GYY,GYZ`` (nT/m) -> list of five floats (gzz = -gxx - gyy)."""
    try:
        values = [float(v) for v in str(text).strip('[] ').split(',')]
    except ValueError:
        values = []
    if len(values) != 5 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f'expected five numbers GXX,GXY,GXZ,GYY,GYZ in nT/m, got {text!r}')
    return values


#: most sensors the simulator serves (as the nodes' n_sensors)
MAX_SENSORS = 64
#: samples are simulated this far ahead of the stream, s (:meth:`FluxgateSim._samples`)
PREFETCH_S = 0.2


def parse_positions(text):
    """Parse 'X1,Y1,Z1,...' (m, 3 per sensor) into a list of floats."""
    try:
        values = [float(v) for v in text.split(',')] if text.strip() else []
    except ValueError:
        raise argparse.ArgumentTypeError(
            f'sensor positions must be numbers X1,Y1,Z1,... in m, got {text!r}') from None
    if len(values) % 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f'sensor positions must be 3 finite numbers (x y z, m) per sensor, got {text!r}')
    return values


def build_parser():
    """Return the argparse parser of ``fluxgate_sim``."""
    p = argparse.ArgumentParser(
        prog='fluxgate_sim',
        description='Simulated four-fluxgate cross gradiometer on pseudo-terminals '
                    '(default: paper 004 section 4.1, ASCII protocol, 100 Hz).')
    p.add_argument('--config', help='YAML file with a fluxgate_sim: ros__parameters: section '
                                    '(keys as the long options, underscores for dashes)')
    p.add_argument('--dir', help=f'directory of the device links (default {DEFAULT_DIR} in '
                                 f'the namespace {DEFAULT_NAMESPACE}, <that>_<ns> in another)')
    p.add_argument('--prefix', help=f'link name prefix, sensor j is <dir>/<prefix>j '
                                    f'(default {DEFAULT_PREFIX})')
    p.add_argument('--sensors', type=int, choices=range(1, MAX_SENSORS + 1),
                   metavar=f'{{1..{MAX_SENSORS}}}', help='number of sensors (default 4)')
    p.add_argument('--sensor-positions-m', type=parse_positions, metavar='X1,Y1,Z1,...',
                   help='x y z of each sensor in the array frame, m (default: paper 004 '
                        'cross of 0.5 m for 4 sensors, the origin otherwise)')
    p.add_argument('--smooth-period-s', type=_positive(),
                   help='period of the smooth tumbling, s (default 60: the sphere in about '
                        'a minute)')
    p.add_argument('--rate', type=_positive(), help='samples per second per sensor, Hz '
                                                    '(default 100)')
    p.add_argument('--tick', type=_positive(),
                   help='write period, s (default 0.01: one sample per write at 100 Hz)')
    p.add_argument('--protocol', choices=sorted(PROTOCOLS), help='serial protocol '
                                                                 '(default ascii)')
    p.add_argument('--option', type=parse_option, action='append', metavar='KEY=VALUE',
                   help='protocol option (repeatable), e.g. --option columns=x,y,z,temp,time')
    p.add_argument('--seed', type=int, help='random seed (default 0)')
    p.add_argument('--trajectory', choices=TRAJECTORIES, help='attitude trajectory '
                                                              '(default smooth)')
    p.add_argument('--field-nt', type=_positive(), help='total field, nT (default 50000)')
    p.add_argument('--noise-nt', type=_non_negative, help='noise sd per axis, nT (default 3)')
    p.add_argument('--errors', choices=['paper004', 'none'],
                   help='sensor errors: paper 004 Table 1 or ideal (default paper004)')
    p.add_argument('--site-gradient', type=parse_gradient, metavar='GXX,GXY,GXZ,GYY,GYZ',
                   help='constant site gradient in the world (NED) frame, nT/m '
                        '(default: none, a uniform field)')
    p.add_argument('--truth', type=parse_truth_item, action='append',
                   metavar='EFFECT=V1,V2,...',
                   help='hidden effect with its parameter values, as magcal simulate --truth '
                        '(repeatable), e.g. --truth aux:aux_motor_current@2=15,-10,8; one '
                        'that changes during the run is a term of time: an offset step of '
                        "sensor 1 at 60 s 'offset(step(60))@1=100,0,0', a magnet passing "
                        "for 5 s 'offset(window(60, 65))@1=500,0,0', a slow drift "
                        "'drift@1=0.5,0,0' (nT/s), a minute in another field "
                        "'field(window(60, 120))=80' (nT; times in s from the start)")
    p.add_argument('--tilt-deg', type=_non_negative,
                   help='largest roll and pitch of the vehicle trajectory, deg (default 15)')
    p.add_argument('--plugin', dest='plugins', action='append', metavar='MODULE',
                   help='import a module defining effects before the truth is read '
                        '(repeatable, as magcal --plugin)')
    p.add_argument('--duration', type=_positive(),
                   help='stop after this many seconds (default: run until SIGINT/SIGTERM)')
    p.add_argument('--unplug', type=parse_unplug, action='append',
                   metavar='SENSOR:AT_S:FOR_S[:NEW_PATH]',
                   help='unplug a sensor at AT_S s for FOR_S s (repeatable), optionally '
                        'coming back at NEW_PATH')
    return p


DEFAULTS = {'dir': DEFAULT_DIR, 'prefix': DEFAULT_PREFIX, 'sensors': 4, 'rate': 100.0,
            'tick': 0.01, 'protocol': 'ascii', 'option': [], 'seed': 0,
            'trajectory': 'smooth', 'field_nt': 50000.0, 'noise_nt': 3.0,
            'errors': 'paper004', 'duration': None, 'unplug': [], 'site_gradient': None,
            'sensor_positions_m': None, 'smooth_period_s': 60.0,
            'truth': [], 'plugins': [], 'aux_period_s': 0.0, 'imu_topic': '',
            'imu_period_s': 0.02, 'tilt_deg': 15.0,
            'aux_topics': [c[len('aux_'):] for c in AUX_CHANNELS]}


def settings_from_parameters(section, source):
    """
    Turn ``fluxgate_sim`` parameters (ROS names and types) into settings like :data:`DEFAULTS`.

    ROS parameters cannot be null: ``dir: ''``, ``duration: 0.0``, an empty list mean the
    default; ``options`` is a YAML mapping.  ValueError names ``source`` and the setting.
    """
    out = {}
    for key, value in section.items():
        try:
            out.update(_setting(key, value, source))
        except argparse.ArgumentTypeError as exc:
            raise ValueError(f'{source}: {key}: {exc}') from None
    return out


def _setting(key, value, source):
    """One setting of :func:`settings_from_parameters` as a dict (empty: keep the default)."""
    if key == 'options':
        try:
            return {'option': list(parse_options(value).items())}
        except ValueError as exc:
            raise ValueError(f'{source}: {exc}') from None
    if key in ('sensor_positions_m', 'site_gradient'):
        parse = parse_positions if key == 'sensor_positions_m' else parse_gradient
        return {key: None if value is None or len(value) == 0 else parse(
            ','.join(map(str, value)) if isinstance(value, (list, tuple)) else value)}
    lists = {'unplug': lambda v: v if isinstance(v, Unplug) else parse_unplug(v),
             'truth': parse_truth_item, 'plugins': str, 'aux_topics': str}
    if key in lists:                    # empty entries left out
        return {key: [lists[key](v) for v in (value or []) if v]}
    convert = {'aux_period_s': float, 'imu_period_s': float, 'tilt_deg': float,
               'imu_topic': lambda v: str(v or ''), 'duration': lambda v: v or None}
    if key in convert:
        return {key: convert[key](value)}
    if key == 'dir':
        return {key: value} if value else {}
    if key in DEFAULTS and key != 'option':
        return {key: value}
    raise ValueError(f'{source}: unknown {NODE_NAME} setting {key!r}; '
                     f'known: {sorted(k for k in DEFAULTS if k != "option")} and options')


def load_config(path):
    """Read the ``fluxgate_sim`` section of a ROS parameter file (ValueError: none, bad)."""
    with open(path, encoding='utf-8') as f:
        doc = load_yaml(f.read()) or {}
    section = None
    for key, value in doc.items():
        if str(key).rstrip('/').split('/')[-1] in (NODE_NAME, '**'):
            section = (value or {}).get('ros__parameters', {})
    if section is None:
        raise ValueError(f'{path}: no "{NODE_NAME}: ros__parameters:" section')
    return settings_from_parameters(section, path)


def check_settings(st):
    """Validate merged settings; raise ValueError naming the bad one."""
    for name in ('rate', 'tick', 'field_nt', 'noise_nt', 'duration', 'smooth_period_s',
                 'imu_period_s', 'tilt_deg'):
        v, strict = st[name], name not in ('noise_nt', 'duration', 'tilt_deg')
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                and (v > 0 if strict else v >= 0)) and (name != 'duration' or v is not None):
            raise ValueError(f'{name} must be a number {">" if strict else ">="} 0, got {v!r}')
    if not (isinstance(st['sensors'], int) and 1 <= st['sensors'] <= MAX_SENSORS):
        raise ValueError(f'sensors must be 1..{MAX_SENSORS}, got {st["sensors"]!r}')
    pos = st['sensor_positions_m']
    if pos is not None and len(pos) != 3 * st['sensors']:
        raise ValueError(f'sensor_positions_m must hold x y z (m) of each of the '
                         f'{st["sensors"]} sensors: {3 * st["sensors"]} numbers, got {len(pos)}')
    if st['protocol'] not in PROTOCOLS:
        raise ValueError(f'unknown protocol {st["protocol"]!r}; choose one of '
                         f'{sorted(PROTOCOLS)}')
    if st['trajectory'] not in TRAJECTORIES:
        raise ValueError(f'unknown trajectory {st["trajectory"]!r}; choose one of '
                         f'{list(TRAJECTORIES)}')
    if st['errors'] not in ('paper004', 'none', None):
        raise ValueError(f"errors must be 'paper004' or 'none', got {st['errors']!r}")
    for u in st['unplug']:
        if u.sensor > st['sensors']:
            raise ValueError(f'unplug sensor {u.sensor} but only {st["sensors"]} sensors')
    make_encoder(st['protocol'], **dict(st['option']))     # raises on bad options
    for name in st.get('aux_topics') or []:
        if 'aux_' + name not in AUX_CHANNELS:
            raise ValueError(f'aux_topics: no simulated channel {name!r}; the simulator has '
                             f'{[c[len("aux_"):] for c in AUX_CHANNELS]}')
    if st.get('truth'):
        _simulator(st)          # an unknown term or a wrong number of values raises here


def _simulator(st):
    """Build the :class:`Simulator` of settings ``st`` (plug-ins imported first, refs set)."""
    from magcal_ros.core.effects import load_plugins
    load_plugins(st.get('plugins') or None)
    grad = st.get('site_gradient')
    if grad is not None:
        from magcal_ros.core.geometry.tensor import symmetric_traceless
        grad = symmetric_traceless(grad)
    sim = Simulator(SimConfig(
        n_sensors=st['sensors'], rate_hz=st['rate'], field_nt=st['field_nt'],
        noise_nt=st['noise_nt'], trajectory=st['trajectory'],
        errors=None if st['errors'] == 'none' else st['errors'],
        seed=st['seed'], gradient_nt_per_m=grad, truth=parse_truth(st.get('truth')),
        smooth_period_s=st.get('smooth_period_s') or 60.0,
        tilt_deg=float(st.get('tilt_deg', 15.0)),
        attitude=bool(st.get('imu_topic')),
        positions_m=st.get('sensor_positions_m')))
    # driven hidden effects act about the references of the first minute
    set_truth_refs(sim, np.arange(0.0, 60.0, 1.0 / st['rate']))
    return sim


def resolve_settings(argv=None, namespace=DEFAULT_NAMESPACE):
    """
    Return the settings (argparse.Namespace keyed like :data:`DEFAULTS`) of a command line.

    :data:`DEFAULTS` (``dir`` of ``namespace``), then ``--config``, then the options; bad
    settings exit 2 with one line (argparse's ``error``).
    """
    parser = build_parser()
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    settings = dict(DEFAULTS, dir=device_dir(namespace))
    try:
        if args.config:
            settings = merge_settings(settings, load_config(args.config))
        settings = merge_settings(settings, options_given(args))
        check_settings(settings)
    except (OSError, ValueError, yaml.YAMLError, argparse.ArgumentTypeError) as exc:
        parser.error(str(exc))
    return argparse.Namespace(**settings)


def options_given(args):
    """Return the settings the command line gave (``args`` of :func:`build_parser`)."""
    return {k: v for k, v in vars(args).items() if k != 'config' and v is not None}


def merge_settings(settings, new):
    """Return ``settings`` updated by ``new`` (protocol options accumulate key by key)."""
    out = dict(settings)
    for key, value in new.items():
        out[key] = out[key] + list(value) if key == 'option' else value
    return out


class FluxgateSim:
    """The simulated array of ``settings`` (:func:`resolve_settings`), faults included."""

    def __init__(self, settings):
        self.settings = settings
        self.encoders = [make_encoder(settings.protocol, **dict(settings.option))
                         for _ in range(settings.sensors)]
        self.sim = _simulator(dict(DEFAULTS, **vars(settings)))
        #: ``f(t, data)`` after each chunk: t (n,) s since start, data its Dataset
        self.listeners = []
        self.paths = [os.path.join(settings.dir, f'{settings.prefix}{j}')
                      for j in range(1, settings.sensors + 1)]
        self.devices = []
        self.sent = 0                   # samples generated per sensor
        self._ahead = None              # (first sample, Dataset) simulated ahead of time
        self.events = sorted([(u.at_s, 'unplug', u) for u in settings.unplug]
                             + [(u.at_s + u.for_s, 'replug', u) for u in settings.unplug],
                             key=lambda e: (e[0], e[1] != 'unplug'))

    def plug_all(self):
        """Create the pseudo-terminals and links; return the list of link paths."""
        for path, enc in zip(self.paths, self.encoders):
            dev = PtyDevice(path)
            self.devices.append(dev)
            if enc.preamble:
                dev.write(enc.preamble)
        return list(self.paths)

    def close(self):
        """Unplug every device and remove the links."""
        for dev in self.devices:
            dev.close()

    def _fault_events(self, now_s, log):
        while self.events and self.events[0][0] <= now_s:
            _, kind, u = self.events.pop(0)
            dev = self.devices[u.sensor - 1]
            if kind == 'unplug':
                dev.unplug()
                log(f'sensor{u.sensor} unplugged at {now_s:.3f} s')
            else:
                dev.replug(u.new_path)
                log(f'sensor{u.sensor} replugged at {now_s:.3f} s -> {dev.path} '
                    f'({dev.slave_name})')

    def _samples(self, first, n):
        """
        (t (n,) s, Dataset) of samples ``first .. first + n - 1`` of each sensor.

        A chunk shorter than :data:`PREFETCH_S` is sliced from that much simulated ahead with
        causal rates (``Simulator.sample(causal=True)``): as if simulated one by one.
        """
        rate = self.settings.rate
        size = int(math.ceil(PREFETCH_S * rate))
        ahead = self._ahead
        inside = (ahead is not None and ahead[0] <= first
                  and first + n <= ahead[0] + len(ahead[1].t))
        if not inside and n >= size:
            self._ahead = None
            t = (first + np.arange(n)) / rate
            return t, self.sim.sample(t)
        if not inside:
            ahead = self._ahead = (first, self.sim.sample((first + np.arange(size)) / rate,
                                                          causal=True))
        k = first - ahead[0]
        data = ahead[1].subset(np.arange(k, k + n))
        return data.t, data

    def step(self, now_s, log=lambda msg: None, warn=None):
        """
        Generate and write every sample due by ``now_s`` (s since start); return the count.

        ``log(text)`` for the faults, ``warn(text)`` (default ``log``) for a reader behind.
        """
        warn = warn or log
        self._fault_events(now_s, log)
        rate = self.settings.rate
        due = int(math.floor(now_s * rate)) + 1
        n = due - self.sent
        if n <= 0:
            return 0
        t, data = self._samples(self.sent, n)
        for j, (dev, enc) in enumerate(zip(self.devices, self.encoders)):
            raw, temp = data.raw[j], data.temp[j]
            chunk = enc.encode_many(
                Sample((float(raw[k, 0]), float(raw[k, 1]), float(raw[k, 2])),
                       float(temp[k]), float(t[k])) for k in range(n))
            flushes = dev.flushes
            dev.write(chunk)
            if dev.flushes != flushes:
                warn(f'sensor{j + 1}: the reader fell behind at {now_s:.3f} s; its unread '
                     f'output was discarded (flush {dev.flushes})')
            dev.read()              # drain commands a reader sent (start/stop); ignored
        for listener in self.listeners:
            listener(t, data)
        self.sent = due
        return n


def stream(sim, settings, log, stop, warn=None):
    """
    Write the samples as they fall due until ``stop`` (an Event) is set or the duration ends.

    ``sim`` plugged in; ``log``, ``warn`` as :meth:`FluxgateSim.step`.  Returns samples sent.
    """
    t0 = time.monotonic()
    tick = settings.tick
    next_tick = t0
    while not stop.is_set():
        now = time.monotonic() - t0
        if settings.duration is not None and now >= settings.duration:
            break
        sim.step(now, log, warn)
        next_tick += tick
        delay = next_tick - time.monotonic()
        if delay > 0:
            stop.wait(delay)
        else:
            next_tick = time.monotonic()    # overloaded: do not try to catch up in bursts
    return sim.sent


def describe_start(sim, settings):
    """Return the lines saying where each sensor is and what streams (logged at start)."""
    lines = [f'sensor{j} -> {path} ({dev.slave_name})'
             for j, (path, dev) in enumerate(zip(sim.paths, sim.devices), start=1)]
    truth = list(getattr(settings, 'truth', None) or [])
    return lines + [f'streaming {settings.protocol} at {settings.rate:g} Hz per sensor '
                    f'(trajectory {settings.trajectory}, seed {settings.seed})'
                    + (f'; hidden effects {truth}' if truth else '')]


def describe_stop(sim):
    """Return the line logged when the stream ends."""
    flushed = sum(dev.flushes for dev in sim.devices)
    return (f'stopped after {sim.sent} samples per sensor'
            + (f'; output discarded {flushed} times because a reader fell behind'
               if flushed else ''))


def run(settings, out=sys.stdout):
    """Run the simulator until the duration elapses or SIGINT/SIGTERM; return exit code."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set())
                for s in (signal.SIGINT, signal.SIGTERM)}

    def log(msg):
        print(f'{NODE_NAME}: {msg}', file=out, flush=True)

    sim = FluxgateSim(settings)
    try:
        sim.plug_all()
        for line in describe_start(sim, settings):
            log(line)
        stream(sim, settings, log, stop)
        log(describe_stop(sim))
    finally:
        sim.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0


def main(args=None):
    """``python -m magcal_ros.sim``: the devices without ROS (``args`` as ``sys.argv[1:]``)."""
    settings = resolve_settings(args)
    try:
        return run(settings)
    except ValueError as exc:           # e.g. the link path is an existing regular file
        print(f'{NODE_NAME}: {exc}', file=sys.stderr)
        return 2
