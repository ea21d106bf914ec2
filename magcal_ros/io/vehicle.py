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

What every format shares (channel names, resampling onto compass 1's epochs, gap checks,
errors, ``meta``); the front-ends (:mod:`~.dataflash`, :mod:`~.ulog`) only read their messages
into a :class:`~.vehicle_base.VehicleLog`.  The Dataset, its channels, units and ``meta``, and
the errors are those of docs/design.md §1, "Vehicle logs": ``raw`` (S, N, 3) nT in the body
frame (x forward, y right, z down), the autopilot's corrections undone; ``t`` (N,) s;
``attitude`` (N, 4) body-to-NED (w, x, y, z) or None; ``temp`` (S, N) degC or None.
"""
import os

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.model.notes import Note
from magcal_ros.io.vehicle_base import DATAFLASH_MAGIC, ULOG_MAGIC, VehicleLogError
import numpy as np

#: a compass stream interval longer than this many median sample periods is a gap
GAP_PERIODS = 10


def log_format(path):
    """
    'dataflash', 'dataflash-text', 'ulog' or None (not a vehicle log) for a file.

    By the first bytes (whatever the name), else a ``.bin``/``.ulg`` name (then damaged).
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
    if suffix == '.log' and b'FMT,' in head:
        return 'dataflash-text'
    return {'.bin': 'dataflash', '.ulg': 'ulog'}.get(suffix)


def read_vehicle_log(path, allow_gaps=False):
    """
    Read an ArduPilot DataFlash (``.bin``, text ``.log``) or PX4 ULog (``.ulg``) log.

    ``allow_gaps``: keep a record whose compass 1 stops for a while, with a warning
    (``meta['gaps']``: [(t s, length s)]).  Returns the Dataset of the module docstring;
    raises :class:`VehicleLogError`.
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
    t, v = np.asarray(stream.t, float), np.asarray(stream.v, float)
    ok = np.isfinite(t) & np.isfinite(v.reshape(len(v), -1)).all(axis=1)
    t, v = t[ok], v[ok]
    order = np.argsort(t, kind='stable')
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], v[keep]


def _inside(t_stream, t, what, warnings, sensor=None):
    """(N,) bool: epochs ``t`` within ``t_stream``'s span, outside its gaps (warned)."""
    ok = (t >= t_stream[0]) & (t <= t_stream[-1])
    _, gaps = _gaps(t_stream)
    for start, length in gaps:
        ok &= ~((t > start) & (t < start + length))
    if gaps:
        warnings.append(Note(f'{what} stops for {_describe_gaps(gaps)}: the epochs inside are '
                             'left out', kind='input', sensor=sensor))
    return ok


def _interp(t_stream, v, t):
    """Linear interpolation of (M,) or (M, k) values onto ``t`` (held beyond the ends)."""
    if v.ndim == 1:
        return np.interp(t, t_stream, v)
    return np.column_stack([np.interp(t, t_stream, v[:, i]) for i in range(v.shape[1])])


def _onto(stream, t):
    """Return a stream's values interpolated onto ``t`` (:func:`_interp`), or None."""
    ts, vs = _clean(stream)
    return _interp(ts, vs, t) if len(ts) else None


def _describe_gaps(gaps):
    start, length = max(gaps, key=lambda g: g[1])
    more = f' and {len(gaps) - 1} more' if len(gaps) > 1 else ''
    return f'{length:.2f} s at t = {start:.2f} s{more}'


def _leave_out_dead(log, path, warnings):
    """Leave out (with a warning) the compasses that read one value throughout (not read)."""
    dead = {}
    for j, comp in enumerate(log.compasses):
        v = _clean(comp)[1]
        if len(v) > 1 and not np.ptp(v, axis=0).any():
            value = ', '.join(f'{x:.0f}' for x in v[0])
            dead[j] = (f'compass {j + 1} ({comp.name}) reads ({value}) nT in all {len(v)} of '
                       'its messages')
    if not dead:
        return
    why = ('not connected or not read when this was logged (ArduPilot: COMPASS_ENABLE, '
           'COMPASS_USE; PX4: SYS_HAS_MAG)')
    if len(dead) == len(log.compasses):
        raise VehicleLogError(f'{path}: every compass reads one value throughout, so there is '
                              f'no field to calibrate: {"; ".join(dead.values())}: {why}')
    for j, text in dead.items():
        warnings.append(Note(f'{text}: left out, {why}; the sensors are the other compasses, '
                             'in order', kind='input'))
    n = len(log.compasses)
    for name in ('compasses', 'compass_temps', 'onboard'):     # one entry per compass each
        items = getattr(log, name)
        if len(items) == n:
            setattr(log, name, [x for j, x in enumerate(items) if j not in dead])


def assemble(log, path, allow_gaps=False):
    """
    Return the :class:`Dataset` of a ``VehicleLog`` (the shared part of every format).

    Epochs outside another compass's or the attitude's span, or in their gaps, are dropped
    (``meta['dropped_epochs']``).
    """
    warnings = [Note(w, kind='input') for w in log.warnings]
    if not log.compasses or not len(log.compasses[0].t):
        raise VehicleLogError(
            f'{path}: no compass data in this {log.source_format} log (no magnetometer '
            'messages): log the compass (ArduPilot: LOG_BITMASK with IMU/compass; PX4: '
            'SDLOG_PROFILE) and record again')
    _leave_out_dead(log, path, warnings)
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
        keep &= _inside(tj, t, f'compass {j} ({comp.name})', warnings, sensor=j)
        raws.append(_interp(tj, vj, t))
    att = None
    if log.attitude is not None and len(log.attitude.t):
        att = _clean(log.attitude)
        keep &= _inside(att[0], t, f'the attitude ({log.attitude_source})', warnings)
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
            if s is not None and (v := _onto(s, t)) is not None:
                temp[j] = v
    aux = {name: v for name, s in log.aux.items() if (v := _onto(s, t)) is not None}
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
                           'rate_hz': 1.0 / p if (p := _median_period(c.t)) > 0 else None}
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
    """A vehicle log read once, as a :class:`magcal_ros.io.chunks.Record` of its epochs."""

    kind = 'vehicle'
    unit = 'sets'

    def __init__(self, path, data):
        self.path, self.data, self.size, self.scale = os.fspath(path), data, data.n_samples, 1.0

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
