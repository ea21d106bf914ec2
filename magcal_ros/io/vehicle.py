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
Vehicle logs (ArduPilot DataFlash, PX4 ULog) -> :class:`~magcal_ros.core.data.dataset.Dataset`.

One implementation of what every log format shares (docs/design.md §1, "Vehicle logs"):
the channel names, the resampling onto common epochs, the gap checks, the errors and the
``meta``.  The format front-ends (:mod:`magcal_ros.io.dataflash` through pymavlink's
DFReader, :mod:`magcal_ros.io.ulog` through pyulog) only read their messages into a
:class:`VehicleLog`: timed streams already in the library's units.

What the Dataset holds:

- ``raw`` (S, N, 3) nT: every compass of the log is a sensor, the raw reading **in the
  vehicle's body frame** (x forward, y right, z down, as the autopilot rotates it), with the
  autopilot's own corrections (offsets, scale, soft iron, motor compensation) undone;
  compass 1 is the autopilot's first (ArduPilot: MAG instance 0; PX4: sensor_mag instance 0).
- ``t`` (N,) s: the epochs of compass 1, s since the autopilot booted (the log's clock).
- ``attitude`` (N, 4): body-to-world unit quaternion (w, x, y, z), world = NED; slerp onto
  the epochs (:func:`magcal_ros.core.geometry.attitude.interpolate`).  None when the log has
  no attitude message (a warning says so: the data are still plain compass data).
- ``temp`` (S, N) degC: each compass's own temperature where the log has one (PX4), else
  None.
- ``aux``: the channels below, linearly interpolated onto the epochs (held at the first and
  last value outside their span).  Names are stable; ``meta['aux_units']`` gives each one's
  unit.

====================================  =======  ================================================
channel                               unit     source
====================================  =======  ================================================
``aux_battery_current``               A        ArduPilot BAT.Curr (instance 0; CURR in old
                                               logs); PX4 battery_status.current_a (instance 0)
``aux_battery_voltage``               V        BAT.Volt; battery_status.voltage_v
``aux_battery{k}_current``, ``_voltage``  A, V  the k-th battery (k = 2, 3, ...)
``aux_battery_temp``                  degC     BAT.Temp; battery_status.temperature (when
                                               the battery reports one)
``aux_throttle``                      0..1     ArduPilot CTUN.ThO (Copter 0..1; Plane % / 100);
                                               PX4 actuator_controls_0.control[3], else
                                               the norm of vehicle_thrust_setpoint.xyz
``aux_motor{k}``                      PWM us   ArduPilot RCOU: the output whose SERVOn_FUNCTION
                                               is motor k (33..40, 82..85); Copter 3.4 and
                                               older: output k of the frame ('Frame: QUAD')
``aux_motor{k}``                      0..1     PX4 actuator_motors.control[k-1] (normalised)
``aux_output{k}``                     PWM us   PX4 actuator_outputs (instance 0) output[k-1],
                                               for logs without actuator_motors
``aux_esc{k}_current``                A        ArduPilot ESC (instance k-1)
``aux_esc{k}_rpm``                    rpm      ArduPilot ESC
``aux_esc{k}_temp``                   degC     ArduPilot ESC
``aux_imu_temp``, ``aux_imu{k}_temp``  degC    ArduPilot IMU.T; PX4 sensor_accel.temperature
``aux_baro_temp``                     degC     ArduPilot BARO.Temp; PX4 sensor_baro.temperature
``aux_board_voltage``                 V        ArduPilot POWR.Vcc
====================================  =======  ================================================

``meta``: ``source``, ``source_format`` ('ArduPilot DataFlash', 'ArduPilot DataFlash (text)',
'PX4 ULog'), ``vehicle`` and ``firmware`` when the log says, ``compasses`` (one entry per
sensor: the message it came from, its rate), ``attitude_source`` (e.g. 'ArduPilot EKF3 XKQ
core 0') and ``attitude_frame`` ('NED'), ``igrf`` ({lat_deg, lon_deg, alt_km, date}: the median
position of the 3-D GPS fixes and the date of the first one; absent without a fix),
``onboard_calibration`` (per compass the autopilot's own calibration as the log's parameters
say, in nT and plain numbers), ``aux_units``, ``dropped_epochs`` and ``warnings``
(:class:`~magcal_ros.core.model.notes.Note`, kind ``input``).

Errors (:class:`VehicleLogError`, a ValueError: one line, exit status 2 from ``magcal``): a
file that is not a log of its format or is damaged, an unsupported log version, a log without
compass data, and a gap in compass 1's stream longer than :data:`GAP_PERIODS` sample periods
(its epochs are the record's: a gap there cuts the record in two; ``allow_gaps``, the CLI's
``--allow-gaps``, keeps such a record whole with a warning).  A gap in another
compass's stream or in the attitude drops the epochs inside it, with a warning.

A long log is held in memory as its compass epochs only (about 100 bytes an epoch for three
compasses, attitude and a dozen channels): an hour at 100 Hz is ~40 MB.  :class:`VehicleRecord`
hands it to the reduction of long records (:mod:`magcal_ros.core.data.reduce`) in chunks.
"""
import os

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.model.notes import Note
# the shared types, re-exported: the front-ends import them from vehicle_base (no cycle)
from magcal_ros.io.vehicle_base import DATAFLASH_MAGIC, gps_site, NT_PER_GAUSS, \
    NT_PER_MGAUSS, SLOW_RATE_HZ, Stream, ULOG_MAGIC, VehicleLog, VehicleLogError  # noqa: F401
import numpy as np

#: a compass stream interval longer than this many median sample periods is a gap
GAP_PERIODS = 10


def log_format(path):
    """
    'dataflash', 'dataflash-text', 'ulog' or None (not a vehicle log) for a file.

    By the first bytes (ULog's magic, DataFlash's 0xA3 0x95 message header), so a log is
    found whatever its name; a ``.bin``/``.ulg`` file without them, and a ``.log`` file with
    no DataFlash ``FMT`` line, are named as damaged by :func:`read_vehicle_log`.
    """
    path = os.fspath(path)
    if os.path.isdir(path) or not os.path.isfile(path):
        return None
    with open(path, 'rb') as fh:
        head = fh.read(8192)
    if head.startswith(ULOG_MAGIC[:4]):
        return 'ulog'
    if head.startswith(DATAFLASH_MAGIC):
        return 'dataflash'
    suffix = os.path.splitext(path)[1].lower()
    if suffix == '.log' and (b'FMT, ' in head or b'FMT,' in head):
        return 'dataflash-text'
    if suffix in ('.bin', '.ulg'):
        return 'ulog' if suffix == '.ulg' else 'dataflash'
    return None


def read_vehicle_log(path, allow_gaps=False):
    """
    Read an ArduPilot DataFlash (``.bin``, text ``.log``) or PX4 ULog (``.ulg``) log.

    ``allow_gaps``: keep a record whose compass 1 stops for a while (a log dropout) as it
    is, with a warning naming the gaps (``meta['gaps']``: [(t s, length s)]), instead of
    refusing it.

    Returns
    -------
    Dataset
        ``t`` (N,) s, ``raw`` (S, N, 3) nT body frame, ``attitude`` (N, 4) or None, ``temp``
        (S, N) degC or None, ``aux`` {name: (N,)}, ``meta`` (module docstring).

    Raises
    ------
    VehicleLogError
        One line: what is wrong with the log and what to do.

    """
    path = os.fspath(path)
    kind = log_format(path)
    if kind is None:
        raise VehicleLogError(f'{path}: not an ArduPilot DataFlash (.bin, .log) or PX4 ULog '
                              '(.ulg) log')
    if kind == 'ulog':
        from magcal_ros.io.ulog import read_ulog
        log = read_ulog(path)
    else:
        from magcal_ros.io.dataflash import read_dataflash
        log = read_dataflash(path, text=kind == 'dataflash-text')
    return assemble(log, path, allow_gaps)


def _median_period(t):
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.0


def _gaps(t, periods=GAP_PERIODS):
    """Return (period s, [(start s, length s), ...]) of the gaps of a sorted time stream."""
    p = _median_period(t)
    if p <= 0:
        return p, []
    d = np.diff(t)
    at = np.flatnonzero(d > periods * p)
    return p, [(float(t[i]), float(d[i])) for i in at]


def _clean(stream):
    """Return (t, v) of a stream sorted by time, duplicates and non-finite rows dropped."""
    t = np.asarray(stream.t, float)
    v = np.asarray(stream.v, float)
    ok = np.isfinite(t) & np.isfinite(v.reshape(len(v), -1)).all(axis=1)
    t, v = t[ok], v[ok]
    order = np.argsort(t, kind='stable')
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], v[keep]


def _inside(t_stream, t, periods=GAP_PERIODS):
    """(N,) bool: epochs ``t`` within the span of ``t_stream`` and not inside one of its gaps."""
    ok = (t >= t_stream[0]) & (t <= t_stream[-1])
    _, gaps = _gaps(t_stream, periods)
    for start, length in gaps:
        ok &= ~((t > start) & (t < start + length))
    return ok


def _interp(t_stream, v, t):
    """Linear interpolation of (M,) or (M, k) values onto ``t`` (held beyond the ends)."""
    if v.ndim == 1:
        return np.interp(t, t_stream, v)
    return np.column_stack([np.interp(t, t_stream, v[:, i]) for i in range(v.shape[1])])


def _describe_gaps(gaps):
    start, length = max(gaps, key=lambda g: g[1])
    more = f' and {len(gaps) - 1} more' if len(gaps) > 1 else ''
    return f'{length:.2f} s at t = {start:.2f} s{more}'


def assemble(log, path, allow_gaps=False):
    """
    Return the :class:`Dataset` of a :class:`VehicleLog` (the shared part of every format).

    The epochs are compass 1's; the other compasses and every channel are interpolated onto
    them (linear; the attitude by slerp); epochs outside another compass's or the attitude's
    span, or inside one of their gaps, are dropped and counted in ``meta['dropped_epochs']``.
    """
    warnings = [Note(w, kind='input') for w in log.warnings]
    if not log.compasses or not len(log.compasses[0].t):
        raise VehicleLogError(
            f'{path}: no compass data in this {log.source_format} log (no magnetometer '
            'messages): log the compass (ArduPilot: LOG_BITMASK with IMU/compass; PX4: '
            'SDLOG_PROFILE) and record again')
    t, v1 = _clean(log.compasses[0])
    if len(t) < 2:
        raise VehicleLogError(f'{path}: compass 1 has only {len(t)} valid sample(s)')
    period, gaps = _gaps(t)
    if gaps and not allow_gaps:
        raise VehicleLogError(
            f'{path}: compass 1 ({log.compasses[0].name}) stops for {_describe_gaps(gaps)} '
            f'(more than {GAP_PERIODS} of its {period * 1e3:.0f} ms sample periods): the '
            'record is cut there; calibrate each part alone (cut the log at the gap, e.g. '
            'with mavlogdump.py or ulog2csv), or keep it whole with --allow-gaps')
    if gaps:
        warnings.append(Note(
            f'compass 1 ({log.compasses[0].name}) stops for {_describe_gaps(gaps)} (kept '
            'with --allow-gaps): the epochs on both sides are used; a noise floor, a drift or '
            'a lag estimated across a gap is less sure', kind='input', sensor=1))
    keep = np.ones(len(t), bool)
    raws = [v1]
    for j, comp in enumerate(log.compasses[1:], start=2):
        tj, vj = _clean(comp)
        if len(tj) < 2:
            raise VehicleLogError(f'{path}: compass {j} ({comp.name}) has only {len(tj)} '
                                  'valid sample(s)')
        inside = _inside(tj, t)
        _, gj = _gaps(tj)
        if gj:
            warnings.append(Note(f'compass {j} ({comp.name}) stops for {_describe_gaps(gj)}: '
                                 'the epochs inside are left out', kind='input', sensor=j))
        keep &= inside
        raws.append(_interp(tj, vj, t))
    att = None
    if log.attitude is not None and len(log.attitude.t):
        ta, qa = _clean(log.attitude)
        inside = _inside(ta, t)
        _, ga = _gaps(ta)
        if ga:
            warnings.append(Note(f'the attitude ({log.attitude_source}) stops for '
                                 f'{_describe_gaps(ga)}: the epochs inside are left out',
                                 kind='input'))
        keep &= inside
        att = (ta, qa)
    else:
        warnings.append(Note(
            f'{os.path.basename(path)}: no attitude in the log: read as plain compass data '
            '(no attitude-aided calibration, no world-frame terms)', kind='input'))
    if not keep.any():
        raise VehicleLogError(f'{path}: no epoch of compass 1 lies inside the spans of the '
                              'other compasses and the attitude')
    dropped = int((~keep).sum())
    t = t[keep]
    raw = np.stack([r[keep] for r in raws])
    temp = None
    if any(s is not None for s in log.compass_temps):
        temp = np.full((len(raws), len(t)), np.nan)
        for j, s in enumerate(log.compass_temps[:len(raws)]):
            if s is not None:
                ts, vs = _clean(s)
                if len(ts):
                    temp[j] = _interp(ts, vs, t)
    aux = {}
    for name, s in log.aux.items():
        ts, vs = _clean(s)
        if len(ts):
            aux[name] = _interp(ts, vs, t)
    attitude = None
    if att is not None:
        from magcal_ros.core.geometry.attitude import AttitudeError, check_quaternions, \
            interpolate
        try:
            qa = check_quaternions(att[1], t=att[0])
        except AttitudeError as exc:
            raise VehicleLogError(f'{path}: {log.attitude_source}: {exc}') from None
        attitude = interpolate(att[0], qa, t)
    meta = {'source': path, 'source_format': log.source_format,
            'compasses': [{'sensor': j, 'source': c.name,
                           'rate_hz': (1.0 / _median_period(c.t)
                                       if _median_period(c.t) > 0 else None)}
                          for j, c in enumerate(log.compasses, start=1)],
            'attitude_source': log.attitude_source if att is not None else None,
            'attitude_frame': 'NED' if att is not None else None,
            'onboard_calibration': log.onboard,
            'aux_units': {k: log.aux_units[k] for k in aux},
            'dropped_epochs': dropped,
            'gaps': gaps,
            'warnings': warnings}
    if log.gps is not None:
        meta['igrf'] = dict(log.gps)
    meta.update(log.info)
    return Dataset(t=t, raw=raw, temp=temp, aux=aux, attitude=attitude, meta=meta)


class VehicleRecord:
    """
    A long vehicle log as a record read in chunks (:class:`magcal_ros.io.chunks.Record`).

    The log is read once (its compass epochs held in memory, module docstring); ``chunks``
    yields consecutive pieces of ``rows`` epochs, as many times as asked.
    """

    kind = 'vehicle'
    unit = 'sets'

    def __init__(self, path, data):
        self.path = os.fspath(path)
        self.data = data
        self.size = data.n_samples
        self.scale = 1.0

    def chunks(self, rows=65536, progress=None):
        """Yield Dataset pieces of at most ``rows`` epochs; ``progress(epochs done)``."""
        n = self.data.n_samples
        for a in range(0, n, rows):
            b = min(n, a + rows)
            piece = self.data.subset(np.arange(a, b))
            piece.origin = None
            if progress is not None:
                progress(b)
            yield piece
