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

"""Byte-level and property tests of the LEMI-025 style packet protocol."""

import math
import random
import struct

from hypothesis import given, HealthCheck, settings, strategies as st
from magcal_ros.serial import make_encoder, make_parser, Sample
from magcal_ros.serial.lemi025 import crc16, PACKET_BYTES, SYNC, TEMP_MISSING
import pytest


def packet(counter, time_us, x, y, z, temp, crc=None):
    """Build a packet by hand from the documented layout (independent of the encoder)."""
    body = struct.pack('<4sIq3ih', SYNC, counter, time_us, x, y, z, temp)
    return body + struct.pack('<H', crc16(body) if crc is None else crc)


def test_crc_is_ccitt_false():
    # standard check value of CRC-16/CCITT-FALSE for '123456789'
    assert crc16(b'123456789') == 0x29B1


def test_documented_layout_decodes():
    data = packet(7, 1_500_000, 1234567, -2345678, 4321098, 2431)
    assert len(data) == PACKET_BYTES == 32
    p = make_parser('lemi025')
    (s,) = p.feed(data)
    assert s == Sample((12345.67, -23456.78, 43210.98), 24.31, 1.5)


def test_encoder_matches_layout_and_counts_packets():
    e = make_encoder('lemi025', counter=7)
    assert e.encode(Sample((12345.67, -23456.78, 43210.98), 24.31, 1.5)) == \
        packet(7, 1_500_000, 1234567, -2345678, 4321098, 2431)
    no_temp = packet(8, 1_600_000, 0, 0, 0, TEMP_MISSING)
    assert e.encode(Sample((0.0, 0.0, 0.0), None, 1.6)) == no_temp
    with pytest.raises(ValueError, match='device_time must be set'):
        e.encode(Sample((0.0, 0.0, 0.0), 20.0, None))


def test_missing_temperature_sentinel():
    (s,) = make_parser('lemi025').feed(packet(0, 0, 1, 2, 3, TEMP_MISSING))
    assert s.temp_c is None and s.field_nt == (0.01, 0.02, 0.03)


def test_corrupted_packet_is_counted_and_next_recovered():
    good = [packet(k, 1000 * k, 100 * k, -100 * k, 5, 2000 + k) for k in range(5)]
    bad = bytearray(good[2])
    bad[18] ^= 0x40                       # bit error in x
    p = make_parser('lemi025')
    out = p.feed(b''.join(good[:2]) + bytes(bad) + b''.join(good[3:]))
    assert [s.device_time for s in out] == [0.0, 0.001, 0.003, 0.004]
    assert [s.temp_c for s in out] == [20.0, 20.01, 20.03, 20.04]   # temperature carried
    assert p.stats.errors == {'checksum': 1, 'counter_gap': 1}


def test_sync_tag_inside_data_and_truncated_packet():
    # counter 0x022555AA is stored as AA 55 25 02: a sync tag inside the packet data
    inner = packet(0x022555AA, 10, 1, 2, 3, 2500)
    assert inner.count(SYNC) == 2
    tail = packet(0x022555AB, 20, 4, 5, 6, 2501)
    truncated = packet(5, 0, 0, 0, 0, 0)[:20]   # cut: its sync tag is followed by junk
    p = make_parser('lemi025')
    out = p.feed(b'\x00junk' + truncated + inner + tail)
    assert [s.field_nt for s in out] == [(0.01, 0.02, 0.03), (0.04, 0.05, 0.06)]
    assert p.stats.errors == {'checksum': 1}
    # start reading in the middle of the packet whose data holds a sync tag
    p2 = make_parser('lemi025')
    out2 = p2.feed(inner[3:] + tail)
    assert [s.field_nt for s in out2] == [(0.04, 0.05, 0.06)]


def test_split_and_merged_packets():
    data = b''.join(packet(k, k, k, k, k, 2000) for k in range(10))
    p = make_parser('lemi025')
    out = []
    for k in range(len(data)):
        out += p.feed(data[k:k + 1])
    assert [s.device_time for s in out] == [k / 1e6 for k in range(10)]
    assert p.stats.total_errors == 0 and p.stats.bytes_dropped == 0


def test_backwards_time_saturation_and_temperature_limits():
    p = make_parser('lemi025', max_abs_nt=50_000)
    out = p.feed(packet(0, 2_000_000, 0, 0, 0, 2000)
                 + packet(1, 1_000_000, 0, 0, 0, 2000)      # time jumps back 1 s
                 + packet(2, 3_000_000, 5_000_001, 0, 0, 2000)  # 50 000.01 nT: saturated
                 + packet(3, 4_000_000, 0, 0, 0, 30000)     # 300 degC: implausible
                 + packet(4, 5_000_000, 0, 0, 4_999_999, 2000))
    assert [s.device_time for s in out] == [2.0, 5.0]
    assert p.stats.errors == {'time_backwards': 1, 'out_of_range': 1,
                              'temp_out_of_range': 1}


def test_wrong_baud_random_bytes_never_frame():
    rng = random.Random(5)
    noise = bytes(rng.randrange(256) for _ in range(100_000))
    p = make_parser('lemi025')
    assert p.feed(noise) == []
    assert p.stats.frames == 0


# -- property tests ------------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=80), max_size=20))
def test_property_arbitrary_bytes_never_raise_nor_emit_bad_values(chunks):
    p = make_parser('lemi025')
    for chunk in chunks:
        for s in p.feed(chunk):
            assert all(math.isfinite(v) and abs(v) <= 200_000 for v in s.field_nt)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(min_size=2, max_size=40), max_size=20))
def test_property_bytes_with_valid_crc_never_raise(bodies):
    # also drive the decoding path: arbitrary packet bodies behind a real tag and CRC
    p = make_parser('lemi025')
    for b in bodies:
        body = (SYNC + b * 26)[:30]
        for s in p.feed(body + struct.pack('<H', crc16(body))):
            assert all(math.isfinite(v) for v in s.field_nt)
            assert s.temp_c is None or math.isfinite(s.temp_c)


_units = st.integers(-20_000_000, 20_000_000)
# noise without the first sync byte 0xAA cannot hold (or start) a sync tag
_noise = st.binary(max_size=50).map(lambda b: b.replace(b'\xaa', b''))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(_noise, _units, _units, _units, st.integers(-5000, 12000)),
                max_size=12),
       st.integers(1, 60))
def test_property_packets_in_noise_all_recovered(items, chunk):
    enc, p = make_encoder('lemi025'), make_parser('lemi025')
    expected = [Sample((x / 100, y / 100, z / 100), t / 100, k / 100)
                for k, (_, x, y, z, t) in enumerate(items)]
    stream = b''.join(n + enc.encode(s) for (n, *_), s in zip(items, expected))
    got = []
    for k in range(0, len(stream), chunk):
        got += p.feed(stream[k:k + chunk])
    assert got == expected
