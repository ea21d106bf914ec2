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
Single-magnetometer CSV logs in other tools' layouts -> one-sensor :class:`Dataset` in nT.

Public logs (IMU calibration tools, phone loggers): one row per sample, ``mx,my,mz`` in
gauss or uT, maybe ``ax,ay,az``, maybe no time (then a *synthetic* axis at an assumed rate,
``meta['synthetic_time']``).  The accelerometer is kept in ``meta['accel']`` (N, 3), its own
unit, not as a channel: gravity depends on the attitude.
"""
import os

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.io.compressed import open_text
from magcal_ros.units import t_to_nt
import numpy as np

#: nanotesla per unit
UNITS_NT = {'nT': 1.0, 'uT': 1e3, 'mG': 100.0, 'gauss': 1e5, 'G': 1e5, 'T': None}

_FIELD_NAMES = (('mx', 'my', 'mz'), ('mag_x', 'mag_y', 'mag_z'), ('magx', 'magy', 'magz'),
                ('x', 'y', 'z'), ('bx', 'by', 'bz'))
_ACC_NAMES = (('ax', 'ay', 'az'), ('acc_x', 'acc_y', 'acc_z'), ('accx', 'accy', 'accz'))
_TIME_NAMES = ('t', 'time', 'timestamp', 'time_s')


def to_nt(values, unit):
    """Convert a field from ``unit`` (nT, uT, mG, gauss/G, T) to nT."""
    if unit not in UNITS_NT:
        raise ValueError(f'unknown field unit {unit!r}; use one of {", ".join(UNITS_NT)}')
    if unit == 'T':
        return t_to_nt(values)
    return np.asarray(values, float) * UNITS_NT[unit]


def _find(low, options):
    return next(([low.index(n) for n in names] for names in options
                 if all(n in low for n in names)), None)


def read_single_sensor_csv(path, unit='gauss', rate_hz=100.0, field_columns=None,
                           accel_columns=None):
    """
    Read a one-magnetometer CSV (header row, comma separated) into a Dataset in nT.

    ``unit`` of the field (:data:`UNITS_NT`); ``rate_hz`` of the synthetic time without a
    time column (t, time, timestamp, time_s); ``field_columns``, ``accel_columns`` three
    names each (default: found by name).  Returns ``raw`` (1, N, 3) nT, ``t`` (N,) s,
    ``meta``: source, unit, synthetic_time, assumed_rate_hz, accel (N, 3) or None.
    """
    path = os.fspath(path)
    try:
        with open_text(path, encoding='utf-8') as fh:
            header = fh.readline().strip().split(',')
            low = [h.strip().lower() for h in header]
            fcols, acols = _columns(path, header, low, field_columns, accel_columns)
            try:
                arr = np.loadtxt(fh, delimiter=',', ndmin=2, comments='#')
            except ValueError as exc:
                raise ValueError(f'{path}: not a numeric CSV after the header ({exc})') from exc
    except OSError as exc:
        raise ValueError(f'cannot read {path}: {exc.strerror}') from exc
    if arr.shape[0] < 3:
        raise ValueError(f'{path}: only {arr.shape[0]} data rows')
    raw = to_nt(arr[:, fcols], unit)
    tcol = next((low.index(n) for n in _TIME_NAMES if n in low), None)
    synthetic = tcol is None
    if synthetic and (not rate_hz or rate_hz <= 0):
        raise ValueError('the file has no time column: give a positive rate_hz')
    t = np.arange(arr.shape[0]) / float(rate_hz) if synthetic else arr[:, tcol].astype(float)
    if not np.all(np.isfinite(raw)):
        raise ValueError(f'{path}: non-finite magnetometer values')
    return Dataset(t=t, raw=raw[None], meta={
        'source': path, 'unit': unit, 'synthetic_time': synthetic,
        'assumed_rate_hz': float(rate_hz) if synthetic else None,
        'accel': None if acols is None else arr[:, acols]})


def _columns(path, header, low, field_columns, accel_columns):
    """(field column indices, accelerometer column indices or None) from the header."""
    if field_columns:
        missing = [c for c in field_columns if c.lower() not in low]
        if missing:
            raise ValueError(f'{path}: no column(s) {missing}; header: {header}')
        fcols = [low.index(c.lower()) for c in field_columns]
    else:
        fcols = _find(low, _FIELD_NAMES)
        if fcols is None:
            raise ValueError(f'{path}: cannot find the magnetometer columns (mx,my,mz or '
                             f'x,y,z ...) in the header {header}; name them with '
                             'field_columns=')
    acols = _find(low, (tuple(c.lower() for c in accel_columns),) if accel_columns
                  else _ACC_NAMES)
    return fcols, acols
