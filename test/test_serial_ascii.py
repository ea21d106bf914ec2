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

"""Byte-level and property tests of the configurable ASCII line protocol."""

import math
import random

from hypothesis import given, HealthCheck, settings, strategies as st
from magcal_ros.serial import make_encoder, make_parser, Sample
from magcal_ros.serial.ascii import AsciiParser, parse_number
import pytest


def test_default_protocol_is_design_contract_line():
    # docs/design.md §3: '<x_nT>,<y_nT>,<z_nT>,<temp_C>\r\n'
    p = make_parser('ascii')
    out = p.feed(b'12345.6,-2345.1,43210.9,24.31\r\n')
    assert out == [Sample((12345.6, -2345.1, 43210.9), 24.31, None)]
    assert p.stats.frames == 1 and p.stats.total_errors == 0
    assert make_parser().feed(b'1,2,3,4\r\n')[0].field_nt == (1.0, 2.0, 3.0)


def test_default_encoder_writes_contract_example():
    e = make_encoder('ascii')
    assert e.encode(Sample((12345.6, -2345.1, 43210.9), 24.31)) == \
        b'12345.6,-2345.1,43210.9,24.31\r\n'


def test_split_and_merged_lines():
    p = make_parser('ascii')
    stream = b'1,2,3,20\r\n4,5,6,21\r\n7,8,9,22\r\n'
    got = []
    for k in range(len(stream)):          # one byte at a time: lines split everywhere
        got += p.feed(stream[k:k + 1])
    assert [s.field_nt for s in got] == [(1, 2, 3), (4, 5, 6), (7, 8, 9)]
    assert [s.temp_c for s in got] == [20, 21, 22]
    p2 = make_parser('ascii')
    assert len(p2.feed(stream * 3)) == 9   # merged: many lines in one read


def test_cr_only_lf_only_and_blank_lines():
    p = make_parser('ascii')
    out = p.feed(b'1,2,3,4\r5,6,7,8\n\n\r\n9,10,11,12\r\n')
    assert [s.field_nt[0] for s in out] == [1, 5, 9]
    assert p.stats.total_errors == 0


@pytest.mark.parametrize('line, kind', [
    (b'nan,2,3,4', 'non_finite'),
    (b'1,inf,3,4', 'non_finite'),
    (b'1,2,-Infinity,4', 'non_finite'),
    (b'1,2,3,NaN', 'non_finite'),
    (b'1e400,2,3,4', 'non_finite'),           # overflows float -> inf
    (b'-1' + b'0' * 240 + b'e70,2,3,4', 'non_finite'),  # -1e310 -> -inf
    (b'9' * 200 + b',2,3,4', 'out_of_range'),  # 1e200 is finite but saturated
    (b'200000.1,0,0,20', 'out_of_range'),     # saturated beyond the default 200 000 nT
    (b'0,-250000,0,20', 'out_of_range'),
    (b'1,2,3,900', 'temp_out_of_range'),
    (b'1,2,3', 'malformed'),                  # missing column
    (b'1,2,3,4,5', 'malformed'),              # extra column
    (b'1,2,x3,4', 'malformed'),
    (b'1_000,2,3,4', 'malformed'),            # python accepts underscores, devices do not
    (b'0x10,2,3,4', 'malformed'),
    (b'1,,3,4', 'malformed'),
    (b'\xff\xfe,2,3,4', 'malformed'),
])
def test_bad_lines_are_counted_and_skipped(line, kind):
    p = make_parser('ascii')
    out = p.feed(b'1,2,3,20\r\n' + line + b'\r\n' + b'4,5,6,21\r\n')
    assert [s.field_nt for s in out] == [(1, 2, 3), (4, 5, 6)]
    assert p.stats.errors == {kind: 1}


def test_saturation_limit_is_configurable():
    p = make_parser('ascii', max_abs_nt=1000.0)
    assert p.feed(b'999,0,0,20\n1001,0,0,20\n')[0].field_nt[0] == 999
    assert p.stats.errors['out_of_range'] == 1


def test_columns_scale_time_and_skip():
    # gauss input, a status column to skip, device time in ms, no temperature
    p = make_parser('ascii', delimiter=';', terminator='\n', columns='time,skip,z,y,x',
                    scale=1e5, time_scale=1e-3)
    out = p.feed(b'1000;OK;0.5;-0.25;0.125\n1010;OK;0.5;-0.25;0.125\n')
    assert out[0] == Sample((12500.0, -25000.0, 50000.0), None, 1.0)
    assert out[1].device_time == pytest.approx(1.01, abs=1e-12)


def test_whitespace_delimiter_and_extra_columns():
    p = make_parser('ascii', delimiter=None, allow_extra_columns=True)
    out = p.feed(b'  1.5   2.5\t3.5  20.0  extra stuff\n')
    assert out == [Sample((1.5, 2.5, 3.5), 20.0, None)]


def test_backwards_device_time_is_counted_and_dropped():
    p = make_parser('ascii', columns='x,y,z,time', time_reset_after=3)
    out = p.feed(b'1,1,1,10.0\n2,2,2,11.0\n3,3,3,10.5\n4,4,4,12.0\n')
    assert [s.field_nt[0] for s in out] == [1, 2, 4]
    assert p.stats.errors == {'time_backwards': 1}
    # a restarted device clock is accepted after time_reset_after consecutive reversals
    out = p.feed(b'5,5,5,0.1\n6,6,6,0.2\n7,7,7,0.3\n8,8,8,0.4\n')
    assert [s.field_nt[0] for s in out] == [7, 8]
    assert p.stats.errors == {'time_backwards': 3, 'time_reset': 1}


def test_comments_and_header_lines():
    p = make_parser('ascii', header_lines=1)
    out = p.feed(b'# fluxgate v1.2\r\nx,y,z,temp\r\n1,2,3,4\r\n  # late comment\r\n')
    assert len(out) == 1
    assert p.stats.ignored == {'comment': 2, 'header': 1}
    assert p.stats.total_errors == 0
    p.reset()                             # after a reconnect the header comes again
    assert p.feed(b'x,y,z,temp\r\n5,6,7,8\r\n')[0].field_nt == (5, 6, 7)


def test_start_command_bytes():
    p = make_parser('ascii', start_command='START\r\n', stop_command=b'\x1b')
    assert p.start_command == b'START\r\n' and p.stop_command == b'\x1b'
    assert make_parser('ascii').start_command == b''


def test_overlong_garbage_without_terminator_is_dropped():
    p = make_parser('ascii', max_line_bytes=64)
    out = p.feed(b'A' * 1000)
    out += p.feed(b'B' * 10 + b'\r\n1,2,3,4\r\n')
    assert [s.field_nt for s in out] == [(1, 2, 3)]
    assert p.stats.errors == {'overlong': 1}
    assert p.stats.bytes_dropped == 1010


def test_wrong_baud_random_bytes_never_produce_samples():
    # bytes received at the wrong baud rate are noise; mostly no digits/terminators line up
    rng = random.Random(3)
    p = make_parser('ascii')
    noise = bytes(rng.choice(b'\x80\x86\x98\xe0\xf8\xfe\x00\x1e\x66\x78')
                  for _ in range(20000))
    assert p.feed(noise) == []
    assert p.stats.frames == 0 and p.stats.bytes_in == 20000


@pytest.mark.parametrize('options, match', [
    ({'columns': 'x,y,temp'}, "'z' exactly once"),
    ({'columns': 'x,y,z,z'}, "'z' exactly once"),
    ({'columns': 'x,y,z,pressure'}, 'unknown column'),
    ({'columns': 'x,y,z,temp,temp'}, "'temp' at most once"),
    ({'scale': 0}, 'scale must be a finite positive'),
    ({'scale': 'big'}, 'scale must be a number'),
    ({'delimiter': '.'}, 'clash with numbers'),
    ({'terminator': ''}, 'terminator must not be empty'),
    ({'max_abs_nt': -1}, 'max_abs_nt must be a finite positive'),
    ({'temp_range_c': (50, 10)}, 'min < max'),
    ({'header_lines': -1}, 'header_lines must be >= 0'),
    ({'colums': 'x,y,z'}, r"unknown option\(s\) \['colums'\]"),
])
def test_bad_options_are_rejected_with_reason(options, match):
    with pytest.raises(ValueError, match=match):
        make_parser('ascii', **options)


def test_encoder_refuses_missing_temperature():
    with pytest.raises(ValueError, match='no temp_c'):
        make_encoder('ascii').encode(Sample((1.0, 2.0, 3.0), None))


def test_encoder_roundtrip_in_gauss_keeps_0p1_nt():
    opts = {'scale': 1e5, 'columns': 'x,y,z,temp,time'}
    e, p = make_encoder('ascii', **opts), make_parser('ascii', **opts)
    s = Sample((12345.6, -2345.1, 43210.9), 24.31, 12.345678)
    (back,) = p.feed(e.encode(s))
    # the encoder writes 6 decimals of gauss = 0.1 nT resolution: error <= 0.05 nT
    assert back.field_nt == pytest.approx(s.field_nt, abs=0.05 + 1e-9)
    assert back.device_time == pytest.approx(s.device_time, abs=5e-7)


def test_parse_number_is_strict():
    assert parse_number(b' -1.5e3 ') == -1500.0
    assert math.isnan(parse_number(b'nan'))
    for bad in (b'', b'1.2.3', b'--1', b'1e', b'0b1'):
        with pytest.raises(ValueError, match='not a number'):
            parse_number(bad)


# -- property tests ------------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=80), max_size=20),
       st.sampled_from([{}, {'columns': 'x,y,z,time'}, {'delimiter': None},
                        {'terminator': ';', 'scale': 1e5}]))
def test_property_arbitrary_bytes_never_raise_nor_emit_non_finite(chunks, options):
    p = make_parser('ascii', **options)
    for chunk in chunks:
        for s in p.feed(chunk):
            assert all(math.isfinite(v) and abs(v) <= p.max_abs_nt for v in s.field_nt)
            assert s.temp_c is None or math.isfinite(s.temp_c)
            assert s.device_time is None or math.isfinite(s.device_time)
    assert p.stats.bytes_in == sum(map(len, chunks))


# value grids: k/10 nT and k/100 degC print and parse back to the identical double
_field = st.integers(-2_000_000, 2_000_000).map(lambda k: k / 10)
_temp = st.integers(-4000, 8000).map(lambda k: k / 100)
_sample = st.builds(lambda x, y, z, t: Sample((x, y, z), t), _field, _field, _field, _temp)
# noise that cannot hold a valid line: no digits (so no number but nan/inf, which are
# rejected) and no terminator inside; each noise piece ends with a terminator
_noise = st.binary(max_size=40).map(
    lambda b: bytes(c for c in b if c not in b'0123456789\r\n') + b'\r\n')


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(_noise, _sample), max_size=15), st.integers(1, 50))
def test_property_valid_lines_in_noise_are_all_recovered(items, chunk):
    enc, p = make_encoder('ascii'), make_parser('ascii')
    stream = b''.join(n + enc.encode(s) for n, s in items)
    got = []
    for k in range(0, len(stream), chunk):
        got += p.feed(stream[k:k + chunk])
    assert got == [s for _, s in items]


def test_parser_class_direct_use():
    # the class is usable without the registry (same defaults)
    assert AsciiParser().feed(b'1,2,3,4\n') == [Sample((1.0, 2.0, 3.0), 4.0)]
