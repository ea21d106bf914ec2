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

"""Line framing shared by the text protocols (configurable ASCII, HMR2300 ASCII)."""

import re

from magcal_ros.serial.base import Parser, to_bytes

#: Terminators that are treated as "any of CR, LF, CRLF" when splitting.
_NEWLINE_TERMINATORS = (b'\r\n', b'\n', b'\r', b'\n\r')
_NEWLINE_SPLIT = re.compile(rb'[\r\n]')


class LineParser(Parser):
    r"""
    Split a byte stream into lines and hand each complete line to :meth:`_parse_line`.

    Parameters
    ----------
    terminator : str or bytes
        Line terminator. Any newline flavour (``'\r\n'``, ``'\n'``, ``'\r'``) makes the
        parser split on either CR or LF, so devices that send CR only, LF only or CRLF are
        all read; blank pieces are ignored. Any other terminator (e.g. ``';'``) is split
        on exactly.
    max_line_bytes : int
        A line longer than this without a terminator is discarded up to the next
        terminator and counted as ``'overlong'`` (wrong baud rate produces such input).
    **kwargs
        Validation options of :class:`~magcal_ros.serial.base.Parser`.

    """

    def __init__(self, terminator=b'\r\n', max_line_bytes=256, **kwargs):
        super().__init__(**kwargs)
        term = to_bytes(terminator, 'terminator')
        if not term:
            raise ValueError('terminator must not be empty; use e.g. "\\r\\n"')
        self.terminator = term
        self._newline = term in _NEWLINE_TERMINATORS
        if int(max_line_bytes) < 8:
            raise ValueError(f'max_line_bytes must be >= 8, got {max_line_bytes!r}')
        self.max_line_bytes = int(max_line_bytes)
        self._buf = b''
        self._discarding = False

    def _reset_buffer(self):
        self._buf = b''
        self._discarding = False

    def _split(self, buf):
        """Return (complete pieces, remainder)."""
        if self._newline:
            pieces = _NEWLINE_SPLIT.split(buf)
        else:
            pieces = buf.split(self.terminator)
        return pieces[:-1], pieces[-1]

    def _parse(self, data, out):
        buf = self._buf + data
        lines, rest = self._split(buf)
        for line in lines:
            if self._discarding:
                # tail of an overlong line: already counted, drop it
                self.stats.bytes_dropped += len(line)
                self._discarding = False
                continue
            if len(line) > self.max_line_bytes:
                self._error('overlong')
                self.stats.bytes_dropped += len(line)
                continue
            if not line.strip():
                if line:
                    self.stats.ignored['blank'] += 1
                continue
            self._parse_line(line, out)
        if len(rest) > self.max_line_bytes:
            if not self._discarding:
                self._error('overlong')
                self._discarding = True
            self.stats.bytes_dropped += len(rest)
            rest = b''
        self._buf = rest

    def _parse_line(self, line, out):  # pragma: no cover - abstract
        raise NotImplementedError
