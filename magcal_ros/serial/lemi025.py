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
LEMI-025 *style* fixed-length binary packets with a sync tag and CRC.

This project's layout in the spirit of the LEMI-025 fluxgate's binary stream; **not**
byte-compatible with a real LEMI-025 (that needs its own protocol entry).

Packet, 32 bytes, little-endian:

====== ==== ====== ===========================================================
offset size type   field
====== ==== ====== ===========================================================
0      4    bytes  sync tag ``AA 55 25 02``
4      4    uint32 packet counter (increments by one, wraps at 2**32)
8      8    int64  device time, microseconds
16     4    int32  x, units of 0.01 nT
20     4    int32  y, units of 0.01 nT
24     4    int32  z, units of 0.01 nT
28     2    int16  temperature, units of 0.01 degC (``0x7FFF`` = not measured)
30     2    uint16 CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 0..29
====== ==== ====== ===========================================================

The parser accepts a packet at a sync tag only if its CRC matches (else ``'checksum'``, and
the search resumes a byte later); a jump of the counter counts as ``'counter_gap'``.
"""
import binascii
import struct

from magcal_ros.serial.base import Encoder, Parser

SYNC = b'\xaa\x55\x25\x02'
PACKET_BYTES = 32
_BODY = struct.Struct('<4sIq3ih')
_CRC = struct.Struct('<H')
UNITS_PER_NT = 100  # field unit 0.01 nT (divide: 2431 / 100 is exactly 24.31)
UNITS_PER_DEGC = 100  # temperature unit 0.01 degC
US_PER_S = 1_000_000
TEMP_MISSING = 0x7FFF


def crc16(data):
    """CRC-16/CCITT-FALSE of ``data`` (bytes): poly 0x1021, init 0xFFFF, no reflection."""
    return binascii.crc_hqx(data, 0xFFFF)


class Lemi025Parser(Parser):
    """Parser of LEMI-025 style packets (module docstring); the options of :class:`Parser`."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._buf = b''
        self._last_counter = None

    def _reset_buffer(self):
        self._buf = b''
        self._last_counter = None

    def _parse(self, data, out):
        buf = self._buf + data
        n = len(buf)
        i = 0
        while True:
            p = buf.find(SYNC, i)
            if p < 0:
                keep = max(i, n - (len(SYNC) - 1))  # a sync tag may straddle two reads
                self.stats.bytes_dropped += keep - i
                i = keep
                break
            self.stats.bytes_dropped += p - i
            i = p
            if i + PACKET_BYTES > n:
                break
            body = buf[i:i + _BODY.size]
            (crc,) = _CRC.unpack_from(buf, i + _BODY.size)
            if crc16(body) != crc:
                self._error('checksum')
                i += 1
                self.stats.bytes_dropped += 1
                continue
            _, counter, time_us, x, y, z, temp = _BODY.unpack(body)
            if self._last_counter is not None and counter != (self._last_counter + 1) % 2**32:
                self._error('counter_gap')
            self._last_counter = counter
            self._accept(out, x / UNITS_PER_NT, y / UNITS_PER_NT, z / UNITS_PER_NT,
                         None if temp == TEMP_MISSING else temp / UNITS_PER_DEGC,
                         time_us / US_PER_S)
            i += PACKET_BYTES
        self._buf = buf[i:]


def _clip(value, lo, hi):
    return max(lo, min(hi, value))


class Lemi025Encoder(Encoder):
    """
    Encoder of LEMI-025 style packets, counting them from ``counter``.

    Samples must carry ``device_time``; a missing temperature is written as
    :data:`TEMP_MISSING`.  Values are rounded to 0.01 nT / 0.01 degC / 1 us and saturated to
    the field widths.
    """

    def __init__(self, counter=0):
        self.counter = int(counter) % 2**32

    def encode(self, sample):
        """Return the 32-byte packet of ``sample`` (ValueError without its device_time)."""
        if sample.device_time is None:
            raise ValueError('lemi025 packets carry the device time: sample.device_time '
                             'must be set (seconds)')
        comps = [_clip(int(round(v * UNITS_PER_NT)), -2**31, 2**31 - 1) for v in sample.field_nt]
        temp = TEMP_MISSING if sample.temp_c is None else _clip(
            int(round(sample.temp_c * UNITS_PER_DEGC)), -2**15, 2**15 - 2)
        time_us = _clip(int(round(sample.device_time * US_PER_S)), -2**63, 2**63 - 1)
        body = _BODY.pack(SYNC, self.counter, time_us, *comps, temp)
        self.counter = (self.counter + 1) % 2**32
        return body + _CRC.pack(crc16(body))
