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
Common parts of every serial protocol: the sample record, statistics and validation.

A protocol is a pair (:class:`Parser`, :class:`Encoder`).  The parser never raises on its
input: bad data are counted per kind in :class:`ParserStats` and skipped.  The encoder
writes exactly the bytes the parser reads (for the simulator).
"""
from collections import Counter
import dataclasses
from dataclasses import dataclass, field
import math
import re


@dataclass(frozen=True)
class Sample:
    """
    One decoded reading: ``field_nt`` (x, y, z) nT, device axes, finite.

    ``temp_c`` degC and ``device_time`` s (the device's clock) when carried, else None.
    """

    field_nt: tuple
    temp_c: float | None = None
    device_time: float | None = None


@dataclass
class ParserStats:
    """
    Counters of one parser.

    ``frames`` samples emitted; ``errors`` rejected frames per kind (``'malformed'``,
    ``'non_finite'``, ``'checksum'``, ...); ``ignored`` neither data nor error
    (``'comment'``, ``'blank'``, ...); ``bytes_in`` fed; ``bytes_dropped`` while resyncing.
    """

    frames: int = 0
    errors: Counter = field(default_factory=Counter)
    ignored: Counter = field(default_factory=Counter)
    bytes_in: int = 0
    bytes_dropped: int = 0

    @property
    def total_errors(self):
        """Total number of rejected frames/lines, all kinds."""
        return sum(self.errors.values())

    def copy(self):
        """Return an independent snapshot (safe to read while the parser keeps running)."""
        return dataclasses.replace(self, errors=Counter(self.errors),
                                   ignored=Counter(self.ignored))

    def as_dict(self):
        """Return the counters as plain JSON-friendly types."""
        return {'frames': self.frames, 'errors': dict(self.errors),
                'ignored': dict(self.ignored), 'bytes_in': self.bytes_in,
                'bytes_dropped': self.bytes_dropped, 'total_errors': self.total_errors}


def check_positive(name, value, what='number'):
    """Return ``value`` as a finite positive float, else ValueError naming ``name``."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a {what}, got {value!r}') from None
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f'{name} must be a finite positive {what}, got {value!r}')
    return value


def to_bytes(value, name):
    """Return option ``name``'s bytes: of bytes, of a str (latin-1), ``b''`` of None."""
    if value is None:
        return b''
    if isinstance(value, (bytes, bytearray)):
        return bytes(value)
    if isinstance(value, str):
        try:
            return value.encode('latin-1')
        except UnicodeEncodeError:
            raise ValueError(f'{name} must contain only byte-sized characters, '
                             f'got {value!r}') from None
    raise ValueError(f'{name} must be str or bytes, got {type(value).__name__}')


class Parser:
    """
    Base class of protocol parsers: validation, statistics and timestamp ordering.

    Subclasses implement :meth:`_parse` (bytes -> samples via :meth:`_accept`).  Rejected: a
    ``|component| > max_abs_nt`` (nT; default about 2 G, the HMR2300 range), a temperature
    outside ``temp_range_c`` (degC, inclusive), a device time before the last (until
    ``time_reset_after`` in a row: then ``'time_reset'``, the device restarted its clock).
    """

    #: Bytes the transport writes after opening the port (e.g. a start command).
    start_command = b''
    #: Bytes the transport writes before closing the port (e.g. a stop command).
    stop_command = b''

    def __init__(self, max_abs_nt=200_000.0, temp_range_c=(-100.0, 200.0),
                 time_reset_after=20):
        self.max_abs_nt = check_positive('max_abs_nt', max_abs_nt)
        try:
            lo, hi = (float(v) for v in temp_range_c)
        except (TypeError, ValueError):
            raise ValueError('temp_range_c must be two numbers (min, max) in degC, '
                             f'got {temp_range_c!r}') from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f'temp_range_c must satisfy min < max, got {temp_range_c!r}')
        self.temp_range_c = (lo, hi)
        if int(time_reset_after) < 1:
            raise ValueError(f'time_reset_after must be >= 1, got {time_reset_after!r}')
        self.time_reset_after = int(time_reset_after)
        self.stats = ParserStats()
        self._last_time = None
        self._backwards_run = 0

    def feed(self, data):
        """Consume any bytes (in any chunking); return the samples they complete, in order."""
        data = bytes(data)
        self.stats.bytes_in += len(data)
        out = []
        self._parse(data, out)
        return out

    def reset(self):
        """Forget partial input and the device-time reference (e.g. after a reconnect)."""
        self._last_time = None
        self._backwards_run = 0
        self._reset_buffer()

    # -- for subclasses -------------------------------------------------------------
    def _parse(self, data, out):  # pragma: no cover - abstract
        raise NotImplementedError

    def _reset_buffer(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def _error(self, kind):
        self.stats.errors[kind] += 1

    def _accept(self, out, x, y, z, temp=None, device_time=None):
        """Validate one decoded reading and append it to ``out``; return True if kept."""
        if not all(math.isfinite(v) for v in (x, y, z, temp, device_time) if v is not None):
            self._error('non_finite')
            return False
        if max(abs(x), abs(y), abs(z)) > self.max_abs_nt:
            self._error('out_of_range')
            return False
        if temp is not None and not (self.temp_range_c[0] <= temp <= self.temp_range_c[1]):
            self._error('temp_out_of_range')
            return False
        if device_time is not None:
            if self._last_time is not None and device_time < self._last_time:
                self._backwards_run += 1
                if self._backwards_run < self.time_reset_after:
                    self._error('time_backwards')
                    return False
                self._error('time_reset')
            self._backwards_run = 0
            self._last_time = device_time
        out.append(Sample((float(x), float(y), float(z)),
                          None if temp is None else float(temp),
                          None if device_time is None else float(device_time)))
        self.stats.frames += 1
        return True


class Encoder:
    """Base class of protocol encoders: a :class:`Sample` to the bytes its parser reads."""

    #: Bytes a device would send once before streaming (e.g. a header line).
    preamble = b''

    def encode(self, sample):  # pragma: no cover - abstract
        """Return the bytes of one sample."""
        raise NotImplementedError

    def encode_many(self, samples):
        """Return the concatenated bytes of an iterable of samples."""
        return b''.join(self.encode(s) for s in samples)


#: Terminators that are treated as "any of CR, LF, CRLF" when splitting.
_NEWLINE_TERMINATORS = (b'\r\n', b'\n', b'\r', b'\n\r')
_NEWLINE_SPLIT = re.compile(rb'[\r\n]')


class LineParser(Parser):
    r"""
    Split a byte stream into lines and hand each complete line to :meth:`_parse_line`.

    A newline ``terminator`` splits on either CR or LF (blank pieces ignored); any other
    (e.g. ``';'``) exactly.  A line longer than ``max_line_bytes`` is dropped as
    ``'overlong'``.  ``kwargs``: the options of :class:`Parser`.
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
        pieces = _NEWLINE_SPLIT.split(buf) if self._newline else buf.split(self.terminator)
        return pieces[:-1], pieces[-1]

    def _parse(self, data, out):
        lines, rest = self._split(self._buf + data)
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
