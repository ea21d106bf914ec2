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
Honeywell HMR2300 smart digital magnetometer: ASCII and binary output, commands.

Output formats (HMR2300 data sheet, "Data formats"):

- ASCII (BCD), 28 bytes per reading, per axis ``SN X1 X2 CM X3 X4 X5 SP SP`` then ``<cr>``:
  a sign (``-`` or a space), the counts comma-grouped in six characters, two spaces
  (``- 1,234    2,345  -   345  \r``: -1234, 2345, -345).  Free spacing, LF, CRLF accepted.
- Binary, 7 bytes: ``Xhi Xlo Yhi Ylo Zhi Zlo <cr>``, big-endian int16 and ``0x0D`` (data
  bytes may be 0x0D too).

Scale: 15 000 counts per gauss (6.667 nT a count; +-2 G = +-30 000 counts).  Commands:
:func:`command` and the functions below (``dd`` the two-digit device id, ``99``: all units).
"""
import re
import struct

from magcal_ros.serial.base import Encoder, LineParser, Parser

CR = 0x0D
ESC = b'\x1b'
COUNTS_PER_GAUSS = 15_000.0
NT_PER_GAUSS = 1e5
#: Sample rates accepted by ``*ddR=nnn`` (samples per second).
RATES = (10, 20, 25, 30, 40, 50, 60, 100, 123, 154)
FRAME_BYTES = 7

_ID = re.compile(r'\d\d')
_NUM = rb'(?:\d{1,3}(?:,\d{3})+|\d+)'
_ASCII_LINE = re.compile(rb'\s*([-+]?)\s*(' + _NUM + rb')\s+([-+]?)\s*(' + _NUM + rb')'
                         rb'\s+([-+]?)\s*(' + _NUM + rb')\s*')


def _device_id(dd):
    dd = str(dd)
    if len(dd) == 1 and dd.isdigit():
        dd = '0' + dd
    if not _ID.fullmatch(dd):
        raise ValueError(f'device id must be two digits 00..99 (99 = all units), got {dd!r}')
    return dd


def command(dd, body):
    r"""Build the frame ``*<dd><body><cr>`` of a command; ``b'*99C\r'`` for dd 99, body C."""
    return f'*{_device_id(dd)}{body}\r'.encode('ascii')


def continuous_command(dd='99'):
    """``*ddC``: start continuous output (stopped by :data:`ESC`)."""
    return command(dd, 'C')


def stop_command():
    """ESC (0x1B): stop continuous output."""
    return ESC


def poll_command(dd='99'):
    """``*ddP``: output one reading."""
    return command(dd, 'P')


def rate_command(rate, dd='99'):
    """``*ddR=nnn``: set the sample rate in samples/s (one of :data:`RATES`)."""
    if rate not in RATES:
        raise ValueError(f'HMR2300 rate must be one of {RATES} samples/s, got {rate!r}')
    return command(dd, f'R={int(rate)}')


def ascii_command(dd='99'):
    """``*ddA``: select ASCII (BCD) output."""
    return command(dd, 'A')


def binary_command(dd='99'):
    """``*ddB``: select binary output."""
    return command(dd, 'B')


def write_enable_command(dd='99'):
    """``*ddWE``: enable writing of settings (needed before e.g. ``*ddID=``)."""
    return command(dd, 'WE')


class _Hmr2300Options:
    """Options shared by the HMR2300 parsers and encoders (``binary``: the output format)."""

    binary = False

    def __init__(self, counts_per_gauss=COUNTS_PER_GAUSS, device_id='99', send_start=False,
                 rate=None, **kwargs):
        super().__init__(**kwargs)
        try:
            cpg = float(counts_per_gauss)
        except (TypeError, ValueError):
            cpg = float('nan')
        if not cpg > 0.0 or cpg == float('inf'):
            raise ValueError('counts_per_gauss must be a finite positive number, '
                             f'got {counts_per_gauss!r}')
        self.counts_per_gauss = cpg
        self.device_id = _device_id(device_id)
        self.rate = None if rate is None else int(rate)
        start = (binary_command if self.binary else ascii_command)(self.device_id)
        if self.rate is not None:
            start += rate_command(self.rate, self.device_id)
        start += continuous_command(self.device_id)
        self.send_start = bool(send_start)
        self.start_command = start if self.send_start else b''
        self.stop_command = ESC if self.send_start else b''

    def counts_to_nt(self, counts):
        """Convert counts to nT (multiply first so that 30 000 counts is exactly 2e5 nT)."""
        return counts * NT_PER_GAUSS / self.counts_per_gauss

    def nt_to_counts(self, nt):
        """Convert nT to the nearest count, saturated to the int16 range."""
        counts = int(round(nt * self.counts_per_gauss / NT_PER_GAUSS))
        return max(-32768, min(32767, counts))


class Hmr2300AsciiParser(_Hmr2300Options, LineParser):
    """
    Parser of HMR2300 ASCII output; ``OK`` replies are ignored as ``'response'``.

    ``device_id`` the two digits of the commands (``'99'``: all units); ``send_start``:
    ``*ddA`` [``*ddR=rate``, one of :data:`RATES`] ``*ddC`` on open and ESC on close (default:
    the device left as configured).  ``kwargs``: the options of :class:`LineParser`.
    """

    def __init__(self, terminator=b'\r', max_line_bytes=64, **kwargs):
        super().__init__(terminator=terminator, max_line_bytes=max_line_bytes, **kwargs)

    def _parse_line(self, line, out):
        m = _ASCII_LINE.fullmatch(line)
        if m is None:
            if line.strip() == b'OK':
                self.stats.ignored['response'] += 1
            else:
                self._error('malformed')
            return
        counts = []
        for k in range(3):
            sign, digits = m.group(2 * k + 1), m.group(2 * k + 2)
            digits = digits.replace(b',', b'')
            if len(digits) > 15:        # far beyond int16 (and int()'s digit limit)
                self._error('out_of_range')
                return
            value = int(digits)
            counts.append(-value if sign == b'-' else value)
        self._accept(out, *(self.counts_to_nt(c) for c in counts))


class Hmr2300AsciiEncoder(_Hmr2300Options, Encoder):
    """
    Encoder of HMR2300 ASCII output: 28 bytes per reading.

    Field values are rounded to whole counts and saturated at the int16 range.
    """

    def encode(self, sample):
        """Return the 28-byte reading of ``sample`` (each axis: sign, 6 characters, 2 spaces)."""
        counts = map(self.nt_to_counts, sample.field_nt)
        text = ''.join(f"{'-' if c < 0 else ' '}{abs(c):>6,}  " for c in counts)
        return text.encode('ascii') + b'\r'


class Hmr2300BinaryParser(_Hmr2300Options, Parser):
    """
    Parser of the HMR2300 7-byte binary frame, robust to 0x0D inside data bytes.

    Acquisition: the earliest position where ``sync_frames`` consecutive frames end in 0x0D;
    while another alignment (0x0D data bytes) lines up too, read on up to
    ``max_sync_frames`` frames, then take the one whose values vary least (the field is
    smooth), the earliest on a tie.  Locked, a frame without its CR is ``'sync_lost'`` and
    the search restarts a byte later.  Other options as :class:`Hmr2300AsciiParser`
    (``*ddB``) and :class:`Parser`.
    """

    binary = True

    def __init__(self, sync_frames=3, max_sync_frames=16, **kwargs):
        super().__init__(**kwargs)
        if int(sync_frames) < 1:
            raise ValueError(f'sync_frames must be >= 1, got {sync_frames!r}')
        self.sync_frames = int(sync_frames)
        self.max_sync_frames = max(self.sync_frames, int(max_sync_frames))
        self._buf = b''
        self._locked = False

    def _reset_buffer(self):
        self._buf = b''
        self._locked = False

    @staticmethod
    def _ends_ok(buf, p, frames):
        """Return True if ``frames`` consecutive frames from ``p`` all end in 0x0D."""
        return all(buf[p + 6 + FRAME_BYTES * k] == CR for k in range(frames))

    def _variation(self, buf, p):
        frames = [struct.unpack_from('>3h', buf, p + FRAME_BYTES * k)
                  for k in range(self.max_sync_frames)]
        return sum(abs(b - a) for f0, f1 in zip(frames, frames[1:]) for a, b in zip(f0, f1))

    def _parse(self, data, out):
        buf = self._buf + data
        n = len(buf)
        span = FRAME_BYTES * self.sync_frames
        i = 0
        while True:
            if self._locked:
                if i + FRAME_BYTES > n:
                    break
                if buf[i + 6] == CR:
                    # big-endian two's complement int16: hi*256 + lo, minus 65536 if >= 32768
                    x, y, z = struct.unpack_from('>3h', buf, i)
                    self._accept(out, self.counts_to_nt(x), self.counts_to_nt(y),
                                 self.counts_to_nt(z))
                    i += FRAME_BYTES
                    continue
                self._locked = False
                self._error('sync_lost')
                i += 1
                self.stats.bytes_dropped += 1
                continue
            # acquisition: earliest position where sync_frames frames line up
            j = i
            while j + span <= n and not self._ends_ok(buf, j, self.sync_frames):
                j += 1
            if j + span > n:
                keep = max(i, n - (span - 1))
                self.stats.bytes_dropped += keep - i
                i = keep
                break
            # other alignments j+1..j+6 that line up over the same frames (0x0D in data)
            rivals = [p for p in range(j + 1, j + FRAME_BYTES)
                      if self._ends_ok(buf, p, min(self.sync_frames, (n - p) // FRAME_BYTES))]
            if not rivals:
                best = j
            else:
                # ambiguous: read on (up to max_sync_frames) until one alignment is left
                alive = [(p, min(self.max_sync_frames, (n - p) // FRAME_BYTES))
                         for p in [j] + rivals]
                alive = [(p, f) for p, f in alive if self._ends_ok(buf, p, f)]
                if not alive:
                    # j lined up by chance and failed later: move past it
                    self.stats.bytes_dropped += j + 1 - i
                    i = j + 1
                    continue
                if len(alive) == 1 and alive[0][1] >= self.sync_frames:
                    best = alive[0][0]
                elif all(f >= self.max_sync_frames for _, f in alive):
                    # persistent (a data byte is 0x0D in every frame): smoothest wins
                    best = min((p for p, _ in alive),
                               key=lambda p: (self._variation(buf, p), p))
                else:
                    # wait for the bytes that decide between alignments
                    self.stats.bytes_dropped += j - i
                    i = j
                    break
            self.stats.bytes_dropped += best - i
            i = best
            self._locked = True
        self._buf = buf[i:]


class Hmr2300BinaryEncoder(_Hmr2300Options, Encoder):
    """Encoder of the HMR2300 binary frame: ``>hhh`` counts then 0x0D (7 bytes)."""

    binary = True

    def encode(self, sample):
        """Return the 7-byte frame of ``sample`` (counts rounded and saturated to int16)."""
        counts = [self.nt_to_counts(v) for v in sample.field_nt]
        return struct.pack('>3h', *counts) + b'\r'
