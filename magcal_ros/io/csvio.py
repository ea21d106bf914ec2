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
from magcal_ros.io.compressed import compress_text, CorruptArchiveError, open_text
import numpy as np

_SENSOR_COL = re.compile(r'^s(\d+)_(x|y|z|temp)$')
_KNOWN = {'t', 'ref_total', 'ref_x', 'ref_y', 'ref_z', 'angle_deg', 'plane', *ATT_COLUMNS}


class CsvFormatError(ValueError):
    """The file is not a valid wide CSV; the message says what and where."""


def read_csv(path):
    """
    Read a wide CSV file (docs/design.md §1; ``.gz``, ``.zst`` decompressed) into a Dataset.

    Columns: ``t`` (N,) s, ``s{j}_x/y/z`` nT, optional ``s{j}_temp`` degC, ``ref_total``,
    ``ref_x/y/z`` nT, ``angle_deg``, ``plane`` (xy|xz), ``aux_<name>``, ``att_qw..att_qz``
    (body-to-world, scalar first).  ``#`` lines are comments; unknown columns are an error.
    """
    return next(read_pieces(path))


def read_pieces(path, rows=None, progress=None):
    """
    Yield the epochs of a wide CSV as Datasets of about ``rows`` epochs (None: one), in order.

    Parsed by :func:`numpy.loadtxt` (empty cells as NaN); a piece with a ``plane`` column or
    an error is read row by row by :mod:`csv`, so that the error names the line and column.
    ``progress(bytes_read)`` after each piece.
    """
    path = os.fspath(path)
    try:
        yield from _pieces(path, rows, progress)
    except CorruptArchiveError as exc:
        raise CsvFormatError(str(exc)) from None
    except OSError as exc:
        raise CsvFormatError(f'cannot read {path}: {exc.strerror}') from exc


def _pieces(path, rows, progress):
    # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name
    with open_text(path, encoding='utf-8-sig') as fh:
        try:
            no, first = header_line(fh)
            if first is None:
                raise CsvFormatError(f'{path} has no header row')
            layout = parse_header(path, first)
            t_last, n_read, hint = -np.inf, 0, None
            # whole lines of about ``rows`` rows (by the header's, then the mean line length)
            while lines := fh.readlines((hint or max(1, len(first)) * rows) if rows else -1):
                start, no = no, no + len(lines)
                arr, planes, nos, data = _parse_lines(path, layout, lines, start)
                if not len(data):
                    continue
                hint = max(1, sum(map(len, lines[:64])) // min(64, len(lines))) * (rows or 1)
                piece = build_dataset(path, layout, arr, nos, data, planes)
                if piece.t[0] < t_last:
                    raise CsvFormatError(
                        f'{path}: column t must be finite and non-decreasing (line {nos[0]})')
                t_last = piece.t[-1]
                n_read += len(data)
                if progress is not None and hasattr(fh, 'buffer'):
                    progress(fh.buffer.tell())
                yield piece
        except UnicodeDecodeError as exc:
            raise CsvFormatError(f'{path} is not a text CSV file ({exc})') from exc
        if n_read == 0:
            raise CsvFormatError(f'{path}: no data rows (only the header)')


def _loadtxt(lines, n_cols):
    """(N, n_cols) floats of ``lines`` by numpy's C reader, None where it cannot."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', UserWarning)        # 'input contained no data'
            arr = np.loadtxt(lines, delimiter=',', comments='#', dtype=float, ndmin=2)
    except ValueError:
        return None
    return arr if arr.shape[1] == n_cols else None


def _parse_lines(path, layout, lines, start):
    """(floats (R, C), planes or None, line numbers (R,), data lines) of lines after ``start``."""
    header, _, plane_col = layout
    if plane_col is None:
        arr = _loadtxt(lines, len(header))
        if arr is not None and len(arr) == len(lines):
            return arr, None, np.arange(start + 1, start + len(lines) + 1), lines
    kept = [(no, ln) for no, ln in enumerate(lines, start=start + 1) if is_content(ln)]
    nos, data = np.array([no for no, _ in kept], int), [ln for _, ln in kept]
    if plane_col is None:
        for got in (arr, _loadtxt(_filled(data), len(header))):
            if got is not None and len(got) == len(data):
                return got, None, nos, data
    return (*parse_rows(path, layout, nos, data), nos, data)


def build_dataset(path, layout, arr, rows_no, lines, planes=None):
    """Check rows ``arr`` (R, C) (line numbers ``rows_no``, text ``lines``) into a Dataset."""
    header, sensors, _ = layout
    _check_finite(path, header, arr, rows_no, lines)
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
    return next(((no, ln) for no, ln in enumerate(fh, start=1) if is_content(ln)), (None, None))


def parse_header(path, line):
    """Return the column layout of a header ``line``: (header, {j: {axis: column}}, plane col)."""
    for sep, name in ((';', 'semicolon'), ('\t', 'tab')):
        if line.count(sep) > line.count(','):
            raise CsvFormatError(f'{path}: the fields are separated by {name}s ({sep!r}); the '
                                 "wide CSV is comma separated: export it with ',' as the "
                                 'separator')
    header = _cells(line)
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
    return header, sensors, (header.index('plane') if 'plane' in header else None)


#: an empty cell (between commas, or at either end of a line)
_EMPTY_CELL = re.compile(r'(?:(?<=,)|^)[ \t]*(?=,|\r?\n?$)')


def _filled(lines):
    for line in lines:
        if ',,' in line or line.startswith(',') or line.rstrip().endswith(','):
            line = _EMPTY_CELL.sub('nan', line)
        yield line


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
    cell = _cells(lines[r])[i]
    what = 'an empty cell' if cell == '' else f'{cell!r} is not a finite number'
    raise CsvFormatError(f'{path}: line {line_nos[r]}, column {header[i]}: {what} '
                         f'({int(bad.any(axis=1).sum())} row(s) affected); fill or drop '
                         'those rows')


def _cells(line):
    """Return the cells of a line (by the csv module), stripped."""
    return [p.strip() for p in next(csv.reader([line]))]


def parse_rows(path, layout, line_nos, lines):
    """Return ((R, C) floats, plane strings or None) of data ``lines``; empty cells nan."""
    header, _, plane_col = layout
    planes, values = [], []
    for ln_no, line in zip(line_nos, lines):
        parts = _cells(line)
        if len(parts) != len(header):
            raise CsvFormatError(f'{path}: line {ln_no} has {len(parts)} fields, header has '
                                 f'{len(header)}')
        if plane_col is not None:
            planes.append(parts[plane_col])
            parts[plane_col] = 'nan'
        for name, p in zip(header, parts):
            try:
                values.append(float(p) if p != '' else np.nan)
            except ValueError:
                raise CsvFormatError(f'{path}: line {ln_no}, column {name}: {p!r} is not a '
                                     'number') from None
    return (np.array(values, float).reshape(-1, len(header)),
            np.array(planes) if plane_col is not None else None)


def format_csv(data, comment=None):
    """Format a :class:`Dataset` as wide CSV text."""
    cols = {'t': data.t}
    for j in range(1, data.n_sensors + 1):
        cols.update({f's{j}_{a}': data.raw[j - 1, :, i] for i, a in enumerate('xyz')})
        if data.temp is not None and np.isfinite(data.temp[j - 1]).any():
            cols[f's{j}_temp'] = data.temp[j - 1]
    if data.ref_total is not None:
        cols['ref_total'] = data.ref_total
    if data.ref_vec is not None:
        cols.update({f'ref_{a}': data.ref_vec[:, i] for i, a in enumerate('xyz')})
    if data.angle_deg is not None:
        cols['angle_deg'] = data.angle_deg
    cols.update(sorted(data.aux.items()))
    if data.attitude is not None:
        cols.update({c: data.attitude[:, i] for i, c in enumerate(ATT_COLUMNS)})
    head = ''.join(f'# {line}\n' for line in str(comment).splitlines()) if comment else ''
    names = list(cols) + (['plane'] if data.plane is not None else [])
    mat = np.column_stack([np.asarray(v, float) for v in cols.values()])
    fmt = ['%.6f'] + ['%.9f' if c in ATT_COLUMNS else '%.4f' for c in list(cols)[1:]]
    body = _io.StringIO()
    np.savetxt(body, mat, fmt=fmt, delimiter=',')
    text = body.getvalue()
    if data.plane is not None:
        text = ''.join(f'{ln},{p}\n' for ln, p in zip(text.splitlines(), data.plane))
    return head + ','.join(names) + '\n' + text


def write_csv(path, data, comment=None):
    """Write a :class:`Dataset` as a wide CSV file, atomically (``.gz``/``.zst``: compressed)."""
    atomic_write_text(path, compress_text(path, format_csv(data, comment)), backup=False)
