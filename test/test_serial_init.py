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

"""Tests of the protocol registry (magcal_ros.serial) and the shared parser base."""

import dataclasses
import subprocess
import sys

from magcal_ros import serial as mserial
from magcal_ros.serial import (Encoder, make_encoder, make_parser, Parser, parser_options,
                               PROTOCOLS, register_protocol, Sample)
import pytest

# values on every protocol's grid: whole HMR2300 counts (6.667 nT), 0.01 nT, 0.1 nT
GRID_NT = [(c * 1e5 / 15000.0) for c in (-7500, -15, 0, 1, 3000)]


@pytest.mark.parametrize('protocol', sorted(PROTOCOLS))
def test_every_protocol_roundtrips_its_own_encoding(protocol):
    enc, par = make_encoder(protocol), make_parser(protocol)
    samples = [Sample((x, -x, 0.5 * x), 21.5, 0.25 * k) for k, x in enumerate(GRID_NT)]
    got = par.feed(enc.preamble + enc.encode_many(samples) + enc.encode_many(samples[-1:]))
    assert len(got) == len(samples) + 1
    for s, g in zip(samples, got):
        # tolerance: half the coarsest quantum of the protocol (HMR2300 count = 6.667 nT)
        assert g.field_nt == pytest.approx(s.field_nt, abs=3.34)
        assert g.temp_c is None or g.temp_c == pytest.approx(21.5, abs=0.005)
    assert par.stats.total_errors == 0


def test_default_protocol_is_ascii():
    assert mserial.DEFAULT_PROTOCOL == 'ascii'
    assert type(make_parser()) is type(make_parser('ascii'))


def test_unknown_protocol_and_option_rejected_with_choices():
    with pytest.raises(ValueError, match=r"unknown serial protocol 'nmea'; choose one of"):
        make_parser('nmea')
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['baud'\]"):
        make_parser('hmr2300_binary', baud=9600)
    with pytest.raises(ValueError, match='unknown serial protocol'):
        make_encoder(None)


def test_one_options_dict_configures_both_sides():
    opts = {'columns': 'x,y,z,time', 'scale': 1e3, 'start_command': 'GO\r\n',
            'field_decimals': 4}
    p, e = make_parser('ascii', **opts), make_encoder('ascii', **opts)
    assert p.start_command == b'GO\r\n'
    (s,) = p.feed(e.encode(Sample((1.5, 2.5, 3.5), None, 9.0)))
    assert s == Sample((1.5, 2.5, 3.5), None, 9.0)
    assert 'columns' in parser_options('ascii') and 'sync_frames' in parser_options(
        'hmr2300_binary')


def test_register_protocol_table_entry():
    class HexParser(Parser):
        def __init__(self, **kwargs):
            super().__init__(**kwargs)
            self._buf = b''

        def _reset_buffer(self):
            self._buf = b''

        def _parse(self, data, out):
            self._buf += data
            *lines, self._buf = self._buf.split(b'\n')
            for line in lines:
                try:
                    x, y, z = (int(v, 16) for v in line.split())
                except ValueError:
                    self._error('malformed')
                    continue
                self._accept(out, x, y, z)

    class HexEncoder(Encoder):
        def encode(self, sample):
            return ' '.join(f'{int(v):x}' for v in sample.field_nt).encode() + b'\n'

    register_protocol('test_hex', HexParser, HexEncoder, 'hex test protocol')
    try:
        assert PROTOCOLS['test_hex'].description == 'hex test protocol'
        data = make_encoder('test_hex').encode(Sample((255.0, 16.0, 1.0)))
        assert data == b'ff 10 1\n'
        assert make_parser('test_hex', max_abs_nt=100).feed(data + b'zz\n') == []
        assert make_parser('test_hex').feed(data)[0].field_nt == (255.0, 16.0, 1.0)
    finally:
        del PROTOCOLS['test_hex']
    with pytest.raises(ValueError, match='must be a Parser subclass'):
        register_protocol('bad', object, HexEncoder)


def test_sample_is_frozen_and_stats_snapshot_is_independent():
    s = Sample((1.0, 2.0, 3.0), 20.0, 1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.temp_c = 5.0
    p = make_parser('ascii')
    p.feed(b'nan,1,1,1\n')
    snap = p.stats.copy()
    p.feed(b'x\n1,2,3,4\n')
    assert snap.errors == {'non_finite': 1} and snap.frames == 0
    assert p.stats.as_dict() == {'frames': 1, 'errors': {'non_finite': 1, 'malformed': 1},
                                 'ignored': {}, 'bytes_in': 20, 'bytes_dropped': 0,
                                 'total_errors': 2}


@pytest.mark.parametrize('options, match', [
    ({'max_abs_nt': float('nan')}, 'max_abs_nt must be a finite positive'),
    ({'temp_range_c': 'hot'}, 'temp_range_c must be two numbers'),
    ({'time_reset_after': 0}, 'time_reset_after must be >= 1'),
])
def test_common_validation_options(options, match):
    for protocol in PROTOCOLS:
        with pytest.raises(ValueError, match=match):
            make_parser(protocol, **options)


def test_serial_package_does_not_import_rclpy():
    code = ('import sys, magcal_ros.serial, magcal_ros.serial.transport; '
            "bad = [m for m in sys.modules if m.startswith(('rclpy', 'sensor_msgs'))]; "
            'print(bad); sys.exit(1 if bad else 0)')
    res = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
