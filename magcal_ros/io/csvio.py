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

"""The wide CSV format of docs/design.md §1 (read and write)."""
import io as _io
import os
import re

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.geometry.attitude import check_quaternions, COLUMNS as ATT_COLUMNS
from magcal_ros.io.atomic import atomic_write_text
import numpy as np

_SENSOR_COL = re.compile(r'^s(\d+)_(x|y|z|temp)$')
_KNOWN = {'t', 'ref_total', 'ref_x', 'ref_y', 'ref_z', 'angle_deg', 'plane', *ATT_COLUMNS}


class CsvFormatError(ValueError):
    """The file is not a valid wide CSV; the message says what and where."""


def read_csv(path):
    """
    Read a wide CSV file into a :class:`Dataset`.

    Columns: ``t`` (s, non-decreasing), ``s{j}_x/y/z`` (nT), optional ``s{j}_temp`` (degC),
    ``ref_total`` (nT), ``ref_x/y/z`` (nT), ``angle_deg``, ``plane`` (xy|xz), ``aux_<name>``,
    ``att_qw, att_qx, att_qy, att_qz`` (all four: body-to-world unit quaternion, Hamilton,
    scalar first).
    ``#`` lines are comments.  Unknown columns are an error.
    """
    path = os.fspath(path)
    try:
        # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name
        with open(path, encoding='utf-8-sig') as fh:
            numbered = [(no, ln) for no, ln in enumerate(fh, start=1)
                        if ln.strip() and not ln.lstrip().startswith('#')]
    except OSError as exc:
        raise CsvFormatError(f'cannot read {path}: {exc.strerror}') from exc
    except UnicodeDecodeError as exc:
        raise CsvFormatError(f'{path} is not a text CSV file ({exc})') from exc
    if not numbered:
        raise CsvFormatError(f'{path} has no header row')
    line_nos = [no for no, _ in numbered]
    lines = [ln for _, ln in numbered]
    for sep, name in ((';', 'semicolon'), ('\t', 'tab')):
        if lines[0].count(sep) > lines[0].count(','):
            raise CsvFormatError(f'{path}: the fields are separated by {name}s ({sep!r}); the '
                                 "wide CSV is comma separated: export it with ',' as the "
                                 'separator')
    if len(lines) == 1:
        raise CsvFormatError(f'{path}: no data rows (only the header)')
    header = [h.strip() for h in lines[0].strip().split(',')]
    sensors = {}
    for i, h in enumerate(header):
        m = _SENSOR_COL.match(h)
        if m:
            sensors.setdefault(int(m.group(1)), {})[m.group(2)] = i
        elif h not in _KNOWN and not h.startswith('aux_'):
            raise CsvFormatError(
                f'{path}: unknown column {h!r}; allowed: t, s<j>_x, s<j>_y, s<j>_z, s<j>_temp, '
                'ref_total, ref_x, ref_y, ref_z, angle_deg, plane, aux_<name>, '
                'att_qw, att_qx, att_qy, att_qz')
    if len(set(header)) != len(header):
        raise CsvFormatError(f'{path}: duplicate column names in the header')
    if 't' not in header:
        raise CsvFormatError(f'{path}: the time column t is missing')
    if not sensors:
        raise CsvFormatError(f'{path}: no sensor columns (s1_x, s1_y, s1_z, ...)')
    n_s = max(sensors)
    for j in range(1, n_s + 1):
        missing = [a for a in 'xyz' if a not in sensors.get(j, {})]
        if missing:
            raise CsvFormatError(f'{path}: sensor {j} lacks column(s) '
                                 f'{", ".join(f"s{j}_{a}" for a in missing)}')
    plane_col = header.index('plane') if 'plane' in header else None
    rows = []
    planes = []
    for ln_no, ln in zip(line_nos[1:], lines[1:]):
        parts = [p.strip() for p in ln.strip().split(',')]
        if len(parts) != len(header):
            raise CsvFormatError(f'{path}: line {ln_no} has {len(parts)} fields, header has '
                                 f'{len(header)}')
        if plane_col is not None:
            planes.append(parts[plane_col])
            parts[plane_col] = 'nan'
        try:
            rows.append([float(p) if p != '' else np.nan for p in parts])
        except ValueError:
            bad = next(p for p in parts if not _isfloat(p))
            raise CsvFormatError(f'{path}: line {ln_no}: {bad!r} is not a number') from None
    arr = np.array(rows, float).reshape(-1, len(header))
    rows_no = np.array(line_nos[1:])
    _check_finite(path, header, arr, rows_no,
                  [lines[k] for k in range(1, len(lines))])
    col = {h: arr[:, i] for i, h in enumerate(header)}
    t = col['t']
    if len(t) and (not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0)):
        raise CsvFormatError(f'{path}: column t must be finite and non-decreasing')
    raw = np.stack([np.column_stack([arr[:, sensors[j][a]] for a in 'xyz'])
                    for j in range(1, n_s + 1)])
    temp = None
    if any('temp' in sensors[j] for j in sensors):
        temp = np.stack([arr[:, sensors[j]['temp']] if 'temp' in sensors[j]
                         else np.full(len(t), np.nan) for j in range(1, n_s + 1)])
    ref_vec = (np.column_stack([col['ref_x'], col['ref_y'], col['ref_z']])
               if 'ref_x' in col else None)
    attitude = None
    have_att = [c for c in ATT_COLUMNS if c in col]
    if have_att:
        if len(have_att) != 4:
            raise CsvFormatError(f'{path}: attitude needs all four columns '
                                 f'{", ".join(ATT_COLUMNS)}; missing '
                                 f'{", ".join(c for c in ATT_COLUMNS if c not in col)}')
        try:
            attitude = check_quaternions(np.column_stack([col[c] for c in ATT_COLUMNS]),
                                         rows=rows_no)
        except ValueError as exc:
            raise CsvFormatError(f'{path}: {exc}') from None
    return Dataset(t=t, raw=raw, temp=temp, ref_total=col.get('ref_total'), ref_vec=ref_vec,
                   angle_deg=col.get('angle_deg'),
                   plane=np.array(planes) if plane_col is not None else None,
                   aux={h: col[h] for h in header if h.startswith('aux_')},
                   meta={'source': path}, attitude=attitude)


#: columns that must hold a finite number in every row (the others may be empty: no value)
_REQUIRED_FINITE = re.compile(r'^(t|s\d+_[xyz]|ref_total|ref_[xyz])$')


def _check_finite(path, header, arr, line_nos, lines):
    """Raise a CsvFormatError naming the first line and column with an empty, nan or inf cell."""
    cols = [i for i, h in enumerate(header) if _REQUIRED_FINITE.match(h)]
    bad = ~np.isfinite(arr[:, cols])
    if not bad.any():
        return
    r, c = np.argwhere(bad)[0]
    i = cols[c]
    cell = lines[r].strip().split(',')[i].strip()
    what = 'an empty cell' if cell == '' else f'{cell!r} is not a finite number'
    n_bad = int(bad.any(axis=1).sum())
    raise CsvFormatError(f'{path}: line {line_nos[r]}, column {header[i]}: {what} '
                         f'({n_bad} row(s) affected); fill or drop those rows')


def _isfloat(s):
    try:
        float(s)
        return True
    except ValueError:
        return s == ''


def format_csv(data, comment=None):
    """Format a :class:`Dataset` as wide CSV text."""
    cols = {'t': data.t}
    for j in range(1, data.n_sensors + 1):
        for i, a in enumerate('xyz'):
            cols[f's{j}_{a}'] = data.raw[j - 1, :, i]
        if data.temp is not None and np.isfinite(data.temp[j - 1]).any():
            cols[f's{j}_temp'] = data.temp[j - 1]
    if data.ref_total is not None:
        cols['ref_total'] = data.ref_total
    if data.ref_vec is not None:
        for i, a in enumerate('xyz'):
            cols[f'ref_{a}'] = data.ref_vec[:, i]
    if data.angle_deg is not None:
        cols['angle_deg'] = data.angle_deg
    for k, v in sorted(data.aux.items()):
        cols[k] = v
    if data.attitude is not None:
        for i, c in enumerate(ATT_COLUMNS):
            cols[c] = data.attitude[:, i]
    buf = _io.StringIO()
    if comment:
        for line in str(comment).splitlines():
            buf.write(f'# {line}\n')
    names = list(cols) + (['plane'] if data.plane is not None else [])
    buf.write(','.join(names) + '\n')
    mat = np.column_stack([np.asarray(v, float) for v in cols.values()])
    fmt = ['%.6f'] + ['%.9f' if c in ATT_COLUMNS else '%.4f' for c in list(cols)[1:]]
    body = _io.StringIO()
    np.savetxt(body, mat, fmt=fmt, delimiter=',')
    text = body.getvalue()
    if data.plane is not None:
        text = ''.join(f'{ln},{p}\n' for ln, p in zip(text.splitlines(), data.plane))
    buf.write(text)
    return buf.getvalue()


def write_csv(path, data, comment=None):
    """Write a :class:`Dataset` as a wide CSV file, atomically."""
    atomic_write_text(path, format_csv(data, comment), backup=False)
