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
import csv
import io as _io
import os
import re
import warnings

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.geometry.attitude import check_quaternions, COLUMNS as ATT_COLUMNS
from magcal_ros.io.atomic import atomic_write_text
from magcal_ros.io.compressed import compress_text, compression, CorruptArchiveError, open_text
import numpy as np

_SENSOR_COL = re.compile(r'^s(\d+)_(x|y|z|temp)$')
_KNOWN = {'t', 'ref_total', 'ref_x', 'ref_y', 'ref_z', 'angle_deg', 'plane', *ATT_COLUMNS}


class CsvFormatError(ValueError):
    """The file is not a valid wide CSV; the message says what and where."""


class _Recheck(Exception):
    """The fast read met something to report: read again row by row to name line and column."""


def read_csv(path):
    """
    Read a wide CSV file into a :class:`Dataset`.

    Columns: ``t`` (s, non-decreasing), ``s{j}_x/y/z`` (nT), optional ``s{j}_temp`` (degC),
    ``ref_total`` (nT), ``ref_x/y/z`` (nT), ``angle_deg``, ``plane`` (xy|xz), ``aux_<name>``,
    ``att_qw, att_qx, att_qy, att_qz`` (all four: body-to-world unit quaternion, Hamilton,
    scalar first).
    ``#`` lines are comments.  Unknown columns are an error.  A ``.csv.gz`` or ``.csv.zst``
    file is decompressed as it is read (:mod:`magcal_ros.io.compressed`).  Numbers are parsed
    by :func:`numpy.loadtxt` (again with empty cells, an optional value not given, filled with
    NaN); a file with a ``plane`` column or anything to report is read row by row with the
    :mod:`csv` module, so that the error names the line and the column.
    """
    path = os.fspath(path)
    for how in ('numpy', 'numpy, empty cells filled'):
        try:
            return _read(path, fast=True, fill=how != 'numpy')
        except _Recheck:
            pass
    return _read(path, fast=False)


def _read(path, fast, fill=False):
    try:
        # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name
        with open_text(path, encoding='utf-8-sig') as fh:
            header_no, first = header_line(fh)
            if first is None:
                raise CsvFormatError(f'{path} has no header row')
            header, sensors = _parse_header(path, first)
            plane_col = header.index('plane') if 'plane' in header else None
            if fast:
                if plane_col is not None:
                    raise _Recheck()
                arr, planes, rows_no = _fast_rows(fh, len(header), fill), None, None
            else:
                try:
                    arr, planes, rows_no, cells = _csv_rows(path, fh, header, plane_col,
                                                            header_no)
                except (CsvFormatError, UnicodeDecodeError):
                    if compression(path):
                        # a corrupt archive garbles rows before its checksum is reached:
                        # read to its end, so that the archive's own error is the one told
                        while fh.read(1 << 20):
                            pass
                    raise
    except CorruptArchiveError as exc:
        raise CsvFormatError(str(exc)) from None
    except OSError as exc:
        raise CsvFormatError(f'cannot read {path}: {exc.strerror}') from exc
    except UnicodeDecodeError as exc:
        raise CsvFormatError(f'{path} is not a text CSV file ({exc})') from exc
    if fast:
        if _first_non_finite(header, arr) is not None:
            raise _Recheck()
    else:
        _check_finite(path, header, arr, rows_no, cells)
    return _dataset(path, header, sensors, plane_col, arr, rows_no,
                    np.array(planes) if plane_col is not None else None,
                    recheck=fast)


def _dataset(path, header, sensors, plane_col, arr, rows_no, planes, recheck=False):
    """
    Return the checked rows ``arr`` (R, C) of a wide CSV as a :class:`Dataset` (both readers).

    ``rows_no`` (R,) are the rows' line numbers (for the messages); with ``recheck`` a bad
    attitude sends the fast reader back to the row-by-row one, which names the line.
    """
    n_s = max(sensors)
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
            if recheck:
                raise _Recheck() from None
            raise CsvFormatError(f'{path}: {exc}') from None
    return Dataset(t=t, raw=raw, temp=temp, ref_total=col.get('ref_total'), ref_vec=ref_vec,
                   angle_deg=col.get('angle_deg'), plane=planes,
                   aux={h: col[h] for h in header if h.startswith('aux_')},
                   meta={'source': path}, attitude=attitude)


def is_content(line):
    """Tell whether a line is data or a header (neither blank nor a ``#`` comment)."""
    return bool(line.strip()) and not line.lstrip().startswith('#')


def header_line(fh):
    """(line number, text) of the first line that is neither blank nor a comment."""
    for no, line in enumerate(fh, start=1):
        if is_content(line):
            return no, line
    return None, None


def _parse_header(path, line):
    """(column names, {sensor: {axis: column index}}) of the header line, checked."""
    for sep, name in ((';', 'semicolon'), ('\t', 'tab')):
        if line.count(sep) > line.count(','):
            raise CsvFormatError(f'{path}: the fields are separated by {name}s ({sep!r}); the '
                                 "wide CSV is comma separated: export it with ',' as the "
                                 'separator')
    header = [h.strip() for h in next(csv.reader([line]))]
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
    for j in range(1, max(sensors) + 1):
        missing = [a for a in 'xyz' if a not in sensors.get(j, {})]
        if missing:
            raise CsvFormatError(f'{path}: sensor {j} lacks column(s) '
                                 f'{", ".join(f"s{j}_{a}" for a in missing)}')
    return header, sensors


#: an empty cell (between commas, or at either end of a line)
_EMPTY_CELL = re.compile(r'(?:(?<=,)|^)[ \t]*(?=,|\r?\n?$)')


def _filled(lines):
    for line in lines:
        if ',,' in line or line.startswith(',') or line.rstrip().endswith(','):
            line = _EMPTY_CELL.sub('nan', line)
        yield line


def _fast_rows(fh, n_cols, fill):
    """(N, n_cols) floats of the rest of ``fh`` by numpy's C reader, or raise _Recheck."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', UserWarning)        # 'input contained no data'
            arr = np.loadtxt(_filled(fh) if fill else fh, delimiter=',', comments='#',
                             dtype=float, ndmin=2)
    except ValueError:
        raise _Recheck() from None
    if arr.shape[0] == 0 or arr.shape[1] != n_cols:
        raise _Recheck()
    return arr


def _row_values(path, header, ln_no, parts, plane_col, planes):
    """
    Return the floats of one row's cells ``parts`` (empty: nan), or raise CsvFormatError.

    The plane cell, when there is one, is appended to ``planes`` and read as nan.
    """
    if len(parts) != len(header):
        raise CsvFormatError(f'{path}: line {ln_no} has {len(parts)} fields, header has '
                             f'{len(header)}')
    if plane_col is not None:
        planes.append(parts[plane_col])
        parts[plane_col] = 'nan'
    try:
        return [float(p) if p != '' else np.nan for p in parts]
    except ValueError:
        i = next(i for i, p in enumerate(parts) if not _isfloat(p))
        raise CsvFormatError(f'{path}: line {ln_no}, column {header[i]}: {parts[i]!r} is '
                             'not a number') from None


def _csv_rows(path, fh, header, plane_col, header_no):
    """Rows after the header by the csv module: (floats, planes, line numbers, cells)."""
    rows, planes, line_nos, cells = [], [], [], []
    for ln_no, line in enumerate(fh, start=header_no + 1):
        if not is_content(line):
            continue
        parts = [p.strip() for p in next(csv.reader([line]))]
        cells.append(list(parts))
        rows.append(_row_values(path, header, ln_no, parts, plane_col, planes))
        line_nos.append(ln_no)
    if not rows:
        raise CsvFormatError(f'{path}: no data rows (only the header)')
    return np.array(rows, float).reshape(-1, len(header)), planes, np.array(line_nos), cells


#: columns that must hold a finite number in every row (the others may be empty: no value)
_REQUIRED_FINITE = re.compile(r'^(t|s\d+_[xyz]|ref_total|ref_[xyz])$')


def _first_non_finite(header, arr):
    """(row, column index) of the first empty, nan or inf required cell, or None."""
    cols = [i for i, h in enumerate(header) if _REQUIRED_FINITE.match(h)]
    bad = ~np.isfinite(arr[:, cols])
    if not bad.any():
        return None
    r, c = np.argwhere(bad)[0]
    return int(r), cols[c], int(bad.any(axis=1).sum())


def _check_finite(path, header, arr, line_nos, cells):
    """Raise a CsvFormatError naming the first line and column with an empty, nan or inf cell."""
    found = _first_non_finite(header, arr)
    if found is None:
        return
    r, i, n_bad = found
    cell = cells[r][i]
    what = 'an empty cell' if cell == '' else f'{cell!r} is not a finite number'
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
    """Write a :class:`Dataset` as a wide CSV file, atomically (``.gz``/``.zst``: compressed)."""
    atomic_write_text(path, compress_text(path, format_csv(data, comment)), backup=False)


# -- pieces of a long file (magcal_ros.io.chunks) --------------------------------------------

def parse_header(path, line):
    """Return the column layout of a header ``line``: (header, {j: {axis: column}}, plane col)."""
    header, sensors = _parse_header(path, line)
    return header, sensors, (header.index('plane') if 'plane' in header else None)


def parse_rows(path, layout, line_nos, lines):
    """Return ((R, C) float array, plane strings or None) of data ``lines`` (R rows)."""
    header, _, plane_col = layout
    rows = []
    planes = []
    for ln_no, ln in zip(line_nos, lines):
        parts = [p.strip() for p in ln.strip().split(',')]
        rows.append(_row_values(path, header, ln_no, parts, plane_col, planes))
    return (np.array(rows, float).reshape(-1, len(header)),
            np.array(planes) if plane_col is not None else None)


class _Cells:
    """The cells of ``lines``, split when one is asked for (an error message)."""

    def __init__(self, lines):
        self.lines = lines

    def __getitem__(self, r):
        return [c.strip() for c in self.lines[r].strip().split(',')]


def build_dataset(path, layout, arr, rows_no, lines, planes=None):
    """
    Check the rows ``arr`` (R, C) of a wide CSV and return them as a :class:`Dataset`.

    ``rows_no`` (R,) are their line numbers and ``lines`` their text (for the messages).
    """
    header, sensors, plane_col = layout
    _check_finite(path, header, arr, rows_no, _Cells(lines))
    return _dataset(path, header, sensors, plane_col, arr, rows_no, planes)
