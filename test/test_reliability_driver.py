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
Reliability of the serial path: faults injected into every parser and into the driver node.

Already covered elsewhere and not repeated here: each protocol's own byte-level and property
tests (test_serial_ascii/hmr2300/lemi025.py), the transport's unplug/replug and backoff
(test_serial_transport.py), three unplug cycles at 1 kHz and garbage on one ASCII port of the
driver (test_driver_node.py). Added here:

- property tests driven by the protocol registry, so a newly registered protocol is covered
  too, with stressed options (very long lines allowed): arbitrary bytes, and byte soups built
  from the protocols' own tokens and frames, never raise out of ``feed``, never yield a
  non-finite or saturated value, keep the statistics consistent, and never let the device
  time run backwards without a counted ``time_reset``;
- the driver node fed a fault mix on three protocols at once (garbage, split and merged
  frames, bytes at a wrong baud rate, 0x0D and the sync tag inside binary data, NaN, inf,
  overflowing and saturated values, an implausible temperature, a device time going back,
  a lost byte, a bad checksum): exactly the valid frames are published, in order, and each
  fault is counted under its kind on ``/diagnostics``; binary ports fed only bytes at a wrong
  baud rate (which never frame, so no parse error either) report a WARN;
- twelve unplug/replug cycles of one sensor at 1 kHz, coming back alternately at its own path
  and at a new path, each unplug cutting a line in half: the driver reopens every time and
  counts each event, the cut line never merges with the next one, and the other three
  sensors deliver every sample without a gap.
"""

import math
import random
import struct
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hypothesis import given, HealthCheck, settings, strategies as st
from magcal_ros.ros.conversions import msg_to_field_nt, stamp_to_seconds
from magcal_ros.ros.driver_node import FluxgateDriver
from magcal_ros.serial import make_encoder, make_parser, PROTOCOLS, Sample
from magcal_ros.serial.lemi025 import crc16, SYNC
from magcal_ros.serial.transport import PtyDevice
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import spin_for, spin_until
from sensor_msgs.msg import MagneticField, Temperature

NT_PER_COUNT = 1e5 / 15000.0          # HMR2300: 15 000 counts per gauss


# -- property tests over the registry --------------------------------------------------------

#: every registered protocol with its defaults, plus stressed option sets
CASES = [(name, {}) for name in sorted(PROTOCOLS)] + [
    ('ascii', {'columns': 'time,x,y,z,temp', 'max_line_bytes': 8192, 'time_reset_after': 3}),
    ('ascii', {'delimiter': None, 'scale': 1e5, 'max_line_bytes': 8192}),
    ('hmr2300_ascii', {'max_line_bytes': 8192}),
    ('hmr2300_binary', {'sync_frames': 1}),
    ('lemi025', {'max_abs_nt': 1e6, 'time_reset_after': 2}),
]

#: pieces of the protocols' own syntax, so that random input often looks almost valid
TOKENS = [b'0', b'7', b'12', b'1,234', b'30,000', b'-', b'+', b'.', b',', b' ', b'  ', b'e',
          b'E', b'+308', b'-400', b'9' * 400, b'9' * 5000, b'nan', b'NaN', b'inf', b'-inf',
          b'Infinity', b'#', b'OK', b'\r', b'\n', b'\r\n', b'\x00', b'\xff', b'\x0d\x0d',
          SYNC, SYNC + b'\x00' * 26, b'\x7f\xff\x7f\xff\x7f\xff\r']

_sample = st.builds(lambda x, y, z, t, d: Sample((x, y, z), t, d),
                    st.floats(-3e5, 3e5), st.floats(-3e5, 3e5), st.floats(-3e5, 3e5),
                    st.floats(-150.0, 250.0), st.floats(-10.0, 1e6))


def _encoded(protocol, options, sample):
    """Return the frame of ``sample`` in ``protocol`` (saturated where the encoder must)."""
    try:
        return make_encoder(protocol, **options).encode(sample)
    except ValueError:      # e.g. columns without temp; not what is tested here
        return b''


def _soup(protocol, options):
    piece = st.one_of(st.binary(max_size=40), st.sampled_from(TOKENS),
                      _sample.map(lambda s: _encoded(protocol, options, s)))
    return st.lists(st.lists(piece, max_size=25).map(b''.join), max_size=12)


def _check_stream(protocol, options, chunks):
    p = make_parser(protocol, **options)
    emitted = 0
    last_time = None
    for chunk in chunks:
        resets = p.stats.errors['time_reset']
        out = p.feed(chunk)                      # must not raise, whatever the bytes
        emitted += len(out)
        backwards = 0
        for s in out:
            assert len(s.field_nt) == 3
            assert all(math.isfinite(v) and abs(v) <= p.max_abs_nt for v in s.field_nt), s
            if s.temp_c is not None:
                lo, hi = p.temp_range_c
                assert math.isfinite(s.temp_c) and lo <= s.temp_c <= hi, s
            if s.device_time is not None:
                assert math.isfinite(s.device_time), s
                if last_time is not None and s.device_time < last_time:
                    backwards += 1
                last_time = s.device_time
        # the device time only goes back with a counted reset (a restarted device clock)
        assert backwards <= p.stats.errors['time_reset'] - resets
    assert p.stats.frames == emitted
    assert p.stats.bytes_in == sum(map(len, chunks))
    assert 0 <= p.stats.bytes_dropped <= p.stats.bytes_in
    assert all(n > 0 for n in p.stats.errors.values())


@pytest.mark.parametrize('protocol, options', CASES, ids=lambda v: str(v))
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_every_parser_survives_arbitrary_and_almost_valid_bytes(
        protocol, options, data):
    chunks = data.draw(st.one_of(st.lists(st.binary(max_size=200), max_size=15),
                                 _soup(protocol, options)))
    _check_stream(protocol, options, chunks)


def test_long_digit_runs_are_counted_not_raised():
    # found by the property test above: with long lines allowed, an HMR2300 ASCII line with
    # 400 digits overflowed float() and one with 5000 digits hit int()'s digit limit, raising
    # out of feed() (and killing the reader thread's parse); now counted as out of range
    p = make_parser('hmr2300_ascii', max_line_bytes=8192)
    assert p.feed(b' 1  2 ' + b'9' * 400 + b'\r' + b' 1  2 ' + b'9' * 5000 + b'\r') == []
    assert p.stats.errors == {'out_of_range': 2}
    assert p.feed(b' 1,000  2,000 -3,000\r')[0].field_nt == pytest.approx(
        (1000 * NT_PER_COUNT, 2000 * NT_PER_COUNT, -3000 * NT_PER_COUNT))


# -- the driver node under a fault mix -------------------------------------------------------

def overrides(**values):
    """Parameter overrides from keyword names (``sensor1__port`` -> ``sensor1.port``)."""
    return [Parameter(k.replace('__', '.'), value=v) for k, v in values.items()]


class Recorder:
    """Collect messages of one topic (reliable, deep: the driver's publishers are reliable)."""

    def __init__(self, node, msg_type, topic, depth=1000):
        self.msgs = []
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.sub = node.create_subscription(msg_type, topic, self.msgs.append, qos)

    def __len__(self):
        return len(self.msgs)


def hmr_frame(x, y, z):
    """HMR2300 binary frame by hand: big-endian int16 counts then CR."""
    return struct.pack('>3h', x, y, z) + b'\r'


def lemi_packet(counter, time_us, x, y, z, temp, crc=None):
    """LEMI-025 style packet by hand from the documented layout (0.01 nT, 0.01 degC, us)."""
    body = struct.pack('<4sIq3ih', SYNC, counter, time_us, x, y, z, temp)
    return body + struct.pack('<H', crc16(body) if crc is None else crc)


def ascii_fault_script():
    """Return (writes, expected samples (x, y, z nT, temp degC), expected error counts)."""
    enc = make_encoder('ascii', columns='x,y,z,temp,time')
    good = [Sample((1000.0 + k, -2000.0 - k, 43000.5), 20.0 + 0.01 * k, 10.0 + 0.01 * k)
            for k in range(12)]
    line = [enc.encode(s) for s in good]
    rng = random.Random(5)
    # the same line at a wrong baud rate: every byte smeared into one of the values a UART
    # produces then (no CR/LF survives), 300 bytes: one overlong line
    wrong_baud = bytes(rng.choice(b'\x80\x86\x98\xe0\xf8\xfe\x00\x1e\x66\x78')
                       for _ in range(300))
    writes = [
        line[0] + line[1],                                   # merged in one write
        line[2][:9], line[2][9:],                           # split across two writes
        b'\x8f\x13garbage\xfe\r\n',                         # malformed
        wrong_baud + b'\r\n',                               # overlong
        line[3],
        b'nan,1.0,2.0,20.0,10.031\r\n',                     # non-finite
        b'1.0,inf,2.0,20.0,10.032\r\n',                     # non-finite
        b'1e400,1.0,2.0,20.0,10.033\r\n',                   # overflows to inf: non-finite
        b'250000.0,1.0,2.0,20.0,10.034\r\n',                # saturated (> 200 000 nT)
        b'1.0,2.0,3.0,999.0,10.035\r\n',                    # temperature out of range
        line[4],
        b'1.0,2.0,3.0,20.0,3.0\r\n',                        # device time jumps back 7 s
        line[5] + b'1.0,2.0\r\n' + line[6],                 # a short line between two
        line[7] + line[8] + line[9][:5], line[9][5:] + line[10] + line[11],
    ]
    expected = [(s.field_nt, s.temp_c) for s in good]
    errors = {'malformed': 2, 'overlong': 1, 'non_finite': 3, 'out_of_range': 1,
              'temp_out_of_range': 1, 'time_backwards': 1}
    return writes, expected, errors


def hmr_fault_script():
    clean = [(100 * k + 1, -100 * k - 2, 3000 + k) for k in range(1, 14)]
    f = [hmr_frame(*c) for c in clean]
    writes = [
        f[0] + f[1] + f[2] + f[3],                          # acquisition
        hmr_frame(0x0D00, 0x000D, -0x0D0D),                 # 0x0D in every data word
        f[4],
        hmr_frame(32767, 0, 0),                             # 218 447 nT: saturated
        f[5][:3], f[5][3:],                                 # split frame
        b'\x01\x02\x03\x04\x05',                            # garbage: lock lost once
        f[6] + f[7] + f[8],
        f[9][:2] + f[9][3:],                                # a byte lost: frame lost
        f[10] + f[11] + f[12],
    ]
    valid = clean[:4] + [(0x0D00, 0x000D, -0x0D0D)] + clean[4:9] + clean[10:]
    expected = [(tuple(c * 1e5 / 15000.0 for c in v), None) for v in valid]
    errors = {'out_of_range': 1, 'sync_lost': 2}
    return writes, expected, errors


def lemi_fault_script():
    t0 = 36_000_000                                         # device time 36 s, in us
    tag_time = int.from_bytes(SYNC, 'little')               # 36 001 194 us: tag in the data
    assert t0 < tag_time < t0 + 2000
    rows = [(t0, 150000, -2000, 4300000, 2431), (t0 + 1000, 150100, -2000, 4300000, 2431),
            (tag_time, 150200, -2000, 4300000, 2432), (t0 + 2000, 150300, -2100, 4300000, 2432),
            (t0 + 3000, 150400, -2100, 4300100, 2433), (t0 + 4000, 150500, -2200, 4300100, 2433),
            (t0 + 5000, 150600, -2200, 4300200, 2433)]
    pk = [lemi_packet(k, *r) for k, r in enumerate(rows)]
    n = len(rows)
    writes = [
        pk[0] + pk[1],
        pk[2],                                              # sync tag inside its time field
        lemi_packet(n, t0 + 2500, 1, 2, 3, 2000, crc=0x1234),   # bad CRC (counter n lost)
        b'\x00garbage\xaa\x55',                             # garbage, half a sync tag
        pk[3][:10], pk[3][10:] + pk[4],                     # split, then merged
        lemi_packet(n + 1, t0 - 10_000_000, 1, 2, 3, 2000),     # device time 10 s back
        lemi_packet(n + 2, t0 + 4500, 30_000_000, 0, 0, 2000),  # 300 000 nT: saturated
        lemi_packet(n + 3, t0 + 4600, 1, 2, 3, 25000),      # 250 degC: implausible
        pk[5] + pk[6],
    ]
    # counters: the bad-CRC packet (n) is never decoded, so pk[3] follows pk[2] regularly;
    # the backwards packet (n + 1) after pk[4] and pk[5] after the packet n + 3 are gaps
    expected = [((r[1] / 100, r[2] / 100, r[3] / 100), r[4] / 100) for r in rows]
    errors = {'checksum': 1, 'time_backwards': 1, 'out_of_range': 1, 'temp_out_of_range': 1}
    return writes, expected, errors


def test_driver_publishes_only_valid_frames_and_counts_every_fault(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    scripts = {1: ascii_fault_script(), 2: hmr_fault_script(), 3: lemi_fault_script()}
    devs = {j: PtyDevice(str(tmp_path / f'dev{j}')) for j in scripts}
    try:
        node = make_node(FluxgateDriver, namespace=ros_namespace, parameter_overrides=overrides(
            n_sensors=3, diagnostics_period_s=0.2,
            sensor1__port=devs[1].path, sensor1__options="{columns: 'x,y,z,temp,time'}",
            sensor2__port=devs[2].path, sensor2__protocol='hmr2300_binary',
            sensor3__port=devs[3].path, sensor3__protocol='lemi025'))
        raw = {j: Recorder(ros_node, MagneticField, f'sensor{j}/raw') for j in scripts}
        temp = {j: Recorder(ros_node, Temperature, f'sensor{j}/temperature') for j in scripts}
        diag = Recorder(ros_node, DiagnosticArray, '/diagnostics', 50)
        spin_until(ros_executor, lambda: all(s.state == 'open' for s in node.port_stats()),
                   message='three ports open')
        spin_until(ros_executor, lambda: all(r.sub.get_publisher_count() == 1
                                             for r in list(raw.values()) + list(temp.values())),
                   message='discovery')
        # interleave the three scripts write by write, with pauses so that split frames
        # really arrive in separate reads
        for k in range(max(len(w) for w, _, _ in scripts.values())):
            for j, (writes, _, _) in scripts.items():
                if k < len(writes):
                    assert devs[j].write(writes[k]) == len(writes[k])
            spin_for(ros_executor, 0.01)

        # the sentinel: each script ends with a valid frame, and one port's frames are
        # parsed and published in byte order on reliable topics, so once that last frame
        # (and its temperature) is here, every message the faults could have produced is too
        def ended(j):
            field, temp_c = scripts[j][1][-1]
            return (raw[j].msgs and tuple(msg_to_field_nt(raw[j].msgs[-1])) ==
                    pytest.approx(field, abs=1e-6) and (temp_c is None or (
                        temp[j].msgs and temp[j].msgs[-1].temperature == pytest.approx(temp_c))))

        spin_until(ros_executor, lambda: all(ended(j) for j in scripts),
                   message='the last valid frame of every script')
        stats = node.port_stats()
        for j, (_, expected, errors) in scripts.items():
            got = [tuple(msg_to_field_nt(m)) for m in raw[j].msgs]
            assert len(got) == len(expected), (j, got)
            for g, (field, _) in zip(got, expected):
                assert g == pytest.approx(field, abs=1e-6), j
            temps = [m.temperature for m in temp[j].msgs]
            assert temps == pytest.approx([t for _, t in expected if t is not None]), j
            st = stats[j - 1]
            kinds = {k: v for k, v in st.errors.items() if k != 'counter_gap'}
            assert kinds == errors, (j, st.errors)
            assert st.callback_errors == 0 and st.reconnects == 0 and st.state == 'open'
            stamps = [stamp_to_seconds(m.header.stamp) for m in raw[j].msgs]
            assert stamps == sorted(stamps)
        # LEMI counter gaps are counted (a lost packet) but the samples are published
        assert stats[2].errors.get('counter_gap') == 2
        # every kind is reported on /diagnostics, with a WARN for the new errors
        spin_until(ros_executor, lambda: diag.msgs and all(
            {kv.key: kv.value for kv in s.values}.get('parse_errors') ==
            str(stats[k].parse_errors) for k, s in enumerate(diag.msgs[-1].status)),
            message='diagnostics with the final error counts')
        assert any(s.level == DiagnosticStatus.WARN for m in diag.msgs for s in m.status)
        for k, s in enumerate(diag.msgs[-1].status):
            values = {kv.key: kv.value for kv in s.values}
            for kind, n in stats[k].errors.items():
                assert values[f'errors.{kind}'] == str(n)
    finally:
        for d in devs.values():
            d.close()


def test_binary_port_at_a_wrong_baud_rate_warns_and_publishes_nothing(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    # binary parsers only drop bytes while they search for a frame (no parse error): the
    # diagnostics must still say that bytes arrive but nothing decodes
    devs = {j: PtyDevice(str(tmp_path / f'dev{j}')) for j in (1, 2)}
    rng = random.Random(11)
    try:
        node = make_node(FluxgateDriver, namespace=ros_namespace, parameter_overrides=overrides(
            n_sensors=2, diagnostics_period_s=0.2,
            sensor1__port=devs[1].path, sensor1__protocol='hmr2300_binary',
            sensor2__port=devs[2].path, sensor2__protocol='lemi025'))
        raw = {j: Recorder(ros_node, MagneticField, f'sensor{j}/raw') for j in devs}
        diag = Recorder(ros_node, DiagnosticArray, '/diagnostics', 50)
        spin_until(ros_executor, lambda: all(s.state == 'open' for s in node.port_stats()))
        spin_until(ros_executor, lambda: diag.msgs, message='diagnostics')
        # what a UART at the wrong baud rate makes of a stream: no CR, no sync tag
        smear = bytes(rng.choice(b'\x80\x86\x98\xe0\xf8\xfe\x00\x1e\x66\x78')
                      for _ in range(200))
        n0 = len(diag.msgs)
        for _ in range(8):
            for d in devs.values():
                d.write(smear)
            spin_for(ros_executor, 0.1)
        spin_until(ros_executor, lambda: any(
            all(s.level == DiagnosticStatus.WARN and 'no valid frame' in s.message
                for s in m.status) for m in diag.msgs[n0:]),
            message='a WARN on both ports for bytes without a frame')
        st = node.port_stats()
        assert all(s.samples == 0 and s.bytes_dropped > 0 and s.state == 'open' for s in st)
        # the right bytes again: published, and the warning clears. They are also the
        # sentinel for "the smear published nothing": a port's frames are published in byte
        # order on a reliable topic, so anything decoded from the smear would come first
        want = {1: [(100.0 * k * NT_PER_COUNT, 2 * NT_PER_COUNT, 3 * NT_PER_COUNT)
                    for k in range(1, 6)],
                2: [(k + 1.0, 2.0, 3.0) for k in range(5)]}
        devs[1].write(b''.join(hmr_frame(100 * k, 2, 3) for k in range(1, 6)))
        devs[2].write(b''.join(lemi_packet(k, 1000 * k, 100 * (k + 1), 200, 300, 2000)
                               for k in range(5)))
        spin_until(ros_executor, lambda: all(
            raw[j].msgs and tuple(msg_to_field_nt(raw[j].msgs[-1])) ==
            pytest.approx(want[j][-1], abs=1e-6) for j in devs), message='the valid frames')
        for j in devs:
            got = [tuple(msg_to_field_nt(m)) for m in raw[j].msgs]
            assert len(got) == 5, (j, got)
            for g, w in zip(got, want[j]):
                assert g == pytest.approx(w, abs=1e-6), j
        n1 = len(diag.msgs)
        spin_until(ros_executor, lambda: len(diag.msgs) > n1 + 1)
        assert all(s.level == DiagnosticStatus.OK for s in diag.msgs[-1].status), \
            [s.message for s in diag.msgs[-1].status]
    finally:
        for d in devs.values():
            d.close()


# -- repeated unplugging at 1 kHz ------------------------------------------------------------

def test_twelve_replugs_alternating_paths_cut_lines_never_merge(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    n_cycles = 12
    devs = [PtyDevice(str(tmp_path / f'flux{j}')) for j in range(1, 5)]
    stop = threading.Event()
    hold = threading.Event()          # sensor 2 is being cut: the writer skips it
    wlock = threading.Lock()
    written = [0]
    enc = make_encoder('ascii')

    def writer():
        # 1 kHz per sensor in 10-sample chunks every 10 ms; x is the sample number
        k = 0
        while not stop.is_set():
            chunk = enc.encode_many(Sample((float(i), 2000.0, 3000.0), 20.0)
                                    for i in range(k, k + 10))
            with wlock:
                for j, d in enumerate(devs):
                    if not (j == 1 and hold.is_set()):
                        d.write(chunk)
                k += 10
                written[0] = k
            time.sleep(0.01)

    thread = threading.Thread(target=writer, daemon=True)
    try:
        node = make_node(FluxgateDriver, namespace=ros_namespace, parameter_overrides=overrides(
            backoff_min_s=0.01, backoff_max_s=0.05, diagnostics_period_s=0.2,
            **{f'sensor{j}__port': devs[j - 1].path for j in range(1, 5)},
            sensor2__alternatives=[str(tmp_path / 'moved2_*')]))
        raw = [Recorder(ros_node, MagneticField, f'sensor{j}/raw', 20000) for j in range(1, 5)]
        diag = Recorder(ros_node, DiagnosticArray, '/diagnostics', 50)
        spin_until(ros_executor, lambda: all(s.state == 'open' for s in node.port_stats()))
        spin_until(ros_executor, lambda: all(r.sub.get_publisher_count() == 1 for r in raw))
        thread.start()

        def samples(j):
            return node.port_stats()[j - 1].samples

        def bytes_in(j):
            return node.port_stats()[j - 1].bytes_in

        spin_until(ros_executor, lambda: samples(2) > 100)
        paths = []
        for cycle in range(n_cycles):
            with wlock:
                hold.set()
            # everything written to sensor 2 has been read; then cut a line: a lone
            # '9999999' without terminator, read by the driver before the unplug. Merged with
            # the first line after the replug it would read as x = 9999999<k> (out of range)
            # or, for a shorter cut, as a wrong but valid value
            spin_until(ros_executor, lambda: bytes_in(2) == devs[1].bytes_written)
            devs[1].write(b'9999999')
            spin_until(ros_executor, lambda: bytes_in(2) == devs[1].bytes_written,
                       message='the cut line read by the driver')
            devs[1].unplug()
            spin_until(ros_executor, lambda: node.port_stats()[1].disconnects == cycle + 1,
                       message=f'disconnect {cycle + 1}')
            others = [samples(j) for j in (1, 3, 4)]
            spin_until(ros_executor, lambda: all(samples(j) >= n + 50 for j, n in
                                                 zip((1, 3, 4), others)),
                       message='the other sensors flowing while sensor 2 is out')
            new_path = str(tmp_path / f'moved2_{cycle}') if cycle % 2 else None
            devs[1].replug(new_path)
            paths.append(devs[1].path)
            spin_until(ros_executor, lambda: node.port_stats()[1].reconnects == cycle + 1
                       and node.port_stats()[1].path == devs[1].path
                       and node.port_stats()[1].state == 'open',
                       message=f'reconnect {cycle + 1} at {devs[1].path}')
            hold.clear()
            back = samples(2)
            spin_until(ros_executor, lambda: samples(2) >= back + 50,
                       message='sensor 2 delivering again')
        stop.set()
        thread.join(2)
        total = written[0]
        spin_until(ros_executor, lambda: all(samples(j) == total for j in (1, 3, 4))
                   and all(len(raw[j - 1]) == total for j in (1, 3, 4)),
                   timeout_sec=20, message=f'all {total} samples of sensors 1, 3, 4')
        st = node.port_stats()
        assert st[1].reconnects == st[1].disconnects == n_cycles
        assert [s.reconnects for s in (st[0], st[2], st[3])] == [0, 0, 0]
        assert all(s.parse_errors == 0 and s.callback_errors == 0 for s in st)
        # sensor 2: never a merged value, in order, with exactly one gap per unplug
        spin_until(ros_executor, lambda: len(raw[1]) == st[1].samples)
        x2 = np.round([msg_to_field_nt(m)[0] for m in raw[1].msgs], 6)
        assert x2.max() < total and np.all(np.diff(x2) > 0)
        gaps = np.flatnonzero(np.diff(x2) > 1)
        assert len(gaps) == n_cycles, [(x2[g], x2[g + 1]) for g in gaps]
        # sensors 1, 3, 4: every sample, in order (x = 0, 1, 2, ...)
        for j in (1, 3, 4):
            xs = np.round([msg_to_field_nt(m)[0] for m in raw[j - 1].msgs], 6)
            np.testing.assert_array_equal(xs, np.arange(total))
        # /diagnostics counts the events
        spin_until(ros_executor, lambda: diag.msgs and {
            kv.key: kv.value for kv in diag.msgs[-1].status[1].values}.get('reconnects')
            == str(n_cycles), message='the reconnect count on /diagnostics')
        assert {kv.key: kv.value for kv in diag.msgs[-1].status[1].values}['path'] == paths[-1]
    finally:
        stop.set()
        if thread.is_alive():
            thread.join(2)
        for d in devs:
            d.close()
