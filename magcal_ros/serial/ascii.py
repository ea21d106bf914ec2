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
Configurable ASCII line protocol (the project's default device protocol).

Default (docs/design.md §3): one line per sample, ``<x_nT>,<y_nT>,<z_nT>,<temp_C>\r\n``,
e.g. ``12345.6,-2345.1,43210.9,24.31\r\n``; the delimiter, terminator, columns, scales,
commands, comments and header lines are options (:class:`AsciiParser`).
"""
import math
import re

from magcal_ros.serial.base import check_positive, Encoder, LineParser, to_bytes

#: Column names understood by the ASCII protocol.
COLUMN_NAMES = ('x', 'y', 'z', 'temp', 'time', 'skip')
DEFAULT_COLUMNS = ('x', 'y', 'z', 'temp')

#: A decimal number as devices write it (no underscores, no hex), or nan/inf spelled out.
_NUMBER = re.compile(rb'[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?'
                     rb'|[+-]?(?i:nan|inf|infinity)')


def parse_number(text):
    """Parse one field (bytes) strictly as a decimal float (nan, inf too); else ValueError."""
    text = text.strip()
    if not _NUMBER.fullmatch(text):
        raise ValueError(f'not a number: {text[:20]!r}')
    return float(text)


def _check_columns(columns):
    if isinstance(columns, str):
        columns = [c.strip() for c in columns.split(',')]
    columns = tuple(str(c).strip().lower() for c in columns)
    unknown = [c for c in columns if c not in COLUMN_NAMES]
    if unknown:
        raise ValueError(f'unknown column name(s) {unknown}; use {list(COLUMN_NAMES)}')
    for name in ('x', 'y', 'z'):
        if columns.count(name) != 1:
            raise ValueError(f'columns must contain {name!r} exactly once, got {list(columns)}')
    for name in ('temp', 'time'):
        if columns.count(name) > 1:
            raise ValueError(f'columns may contain {name!r} at most once, got {list(columns)}')
    return columns


def _check_delimiter(delimiter):
    if delimiter is None or delimiter == '':
        return None
    delim = to_bytes(delimiter, 'delimiter')
    if delim.strip(b'0123456789+-.eE') != delim or b'\r' in delim or b'\n' in delim:
        raise ValueError(f'delimiter {delimiter!r} would clash with numbers or line ends')
    return delim


class AsciiParser(LineParser):
    r"""
    Parser for the configurable ASCII line protocol.

    ``delimiter`` (None or '': whitespace); ``terminator``; ``columns`` in order, of
    :data:`COLUMN_NAMES`; ``scale`` nT per unit of x, y, z (1e5: gauss); ``time_scale`` s per
    unit of time; ``start_command``, ``stop_command`` bytes; lines starting with
    ``comment_prefix`` and the first ``header_lines`` (again after :meth:`reset`) ignored;
    ``allow_extra_columns``: trailing columns accepted.  ``kwargs``: :class:`LineParser`'s.
    """

    def __init__(self, delimiter=',', terminator='\r\n', columns=DEFAULT_COLUMNS, scale=1.0,
                 time_scale=1.0, start_command=b'', stop_command=b'', comment_prefix='#',
                 header_lines=0, allow_extra_columns=False, **kwargs):
        super().__init__(terminator=terminator, **kwargs)
        self.delimiter = _check_delimiter(delimiter)
        self.columns = _check_columns(columns)
        self.scale = check_positive('scale', scale)
        self.time_scale = check_positive('time_scale', time_scale)
        self.start_command = to_bytes(start_command, 'start_command')
        self.stop_command = to_bytes(stop_command, 'stop_command')
        self.comment_prefix = to_bytes(comment_prefix, 'comment_prefix') or None
        if int(header_lines) < 0:
            raise ValueError(f'header_lines must be >= 0, got {header_lines!r}')
        self.header_lines = int(header_lines)
        self._headers_left = self.header_lines
        self.allow_extra_columns = bool(allow_extra_columns)
        self._index = {name: self.columns.index(name)
                       for name in ('x', 'y', 'z', 'temp', 'time') if name in self.columns}

    def _reset_buffer(self):
        super()._reset_buffer()
        self._headers_left = self.header_lines

    def _parse_line(self, line, out):
        stripped = line.strip()
        if self.comment_prefix and stripped.startswith(self.comment_prefix):
            self.stats.ignored['comment'] += 1
            return
        if self._headers_left > 0:
            self._headers_left -= 1
            self.stats.ignored['header'] += 1
            return
        fields = stripped.split(self.delimiter) if self.delimiter else stripped.split()
        n = len(self.columns)
        if len(fields) < n or (len(fields) > n and not self.allow_extra_columns):
            self._error('malformed')
            return
        try:
            values = {name: parse_number(fields[i]) for name, i in self._index.items()}
        except ValueError:
            self._error('malformed')
            return
        s = self.scale
        self._accept(out, values['x'] * s, values['y'] * s, values['z'] * s,
                     values.get('temp'),
                     None if 'time' not in values else values['time'] * self.time_scale)


class AsciiEncoder(Encoder):
    """
    Encoder for the configurable ASCII line protocol (the parser's options).

    A None delimiter writes a space; ``field_decimals`` in the device unit (default: 0.1 nT);
    ``header`` sent once before streaming (:attr:`preamble`, terminator appended).
    """

    def __init__(self, delimiter=',', terminator='\r\n', columns=DEFAULT_COLUMNS, scale=1.0,
                 time_scale=1.0, field_decimals=None, temp_decimals=2, time_decimals=6,
                 header=None):
        self.delimiter = _check_delimiter(delimiter) or b' '
        self.terminator = to_bytes(terminator, 'terminator')
        if not self.terminator:
            raise ValueError('terminator must not be empty; use e.g. "\\r\\n"')
        self.columns = _check_columns(columns)
        self.scale = check_positive('scale', scale)
        self.time_scale = check_positive('time_scale', time_scale)
        self.field_decimals = int(max(0, math.ceil(math.log10(self.scale)) + 1)
                                  if field_decimals is None else field_decimals)
        self.temp_decimals = int(temp_decimals)
        self.time_decimals = int(time_decimals)
        self.preamble = (to_bytes(header, 'header') + self.terminator) if header else b''

    def encode(self, sample):
        """Return one line for ``sample`` (ValueError: the columns need what it lacks)."""
        parts = []
        for name in self.columns:
            if name in ('x', 'y', 'z'):
                value = sample.field_nt['xyz'.index(name)] / self.scale
                parts.append(f'{value:.{self.field_decimals}f}')
            elif name == 'temp':
                if sample.temp_c is None:
                    raise ValueError('columns include temp but the sample has no temp_c')
                parts.append(f'{sample.temp_c:.{self.temp_decimals}f}')
            elif name == 'time':
                if sample.device_time is None:
                    raise ValueError('columns include time but the sample has no device_time')
                parts.append(f'{sample.device_time / self.time_scale:.{self.time_decimals}f}')
            else:
                parts.append('0')
        return self.delimiter.join(p.encode('ascii') for p in parts) + self.terminator
