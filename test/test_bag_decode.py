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
The bag reader's own CDR decoding (magcal_ros.io.bag._decode_fixed) and write_bag's templates.

References: messages packed here byte by byte with ``struct`` from the CDR rules (4-byte
encapsulation header, then each primitive aligned to its size from the payload start) with
known numbers, and rosbags' own deserialiser on the same bytes.  Every comparison is exact:
the decoder copies the IEEE bytes, so any difference is a wrong offset or byte order.
"""
import struct

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.io.bag import _decode_fixed, BagFormatError, read_bag, write_bag
import numpy as np
import pytest

MAG = 'sensor_msgs/msg/MagneticField'
TEMP = 'sensor_msgs/msg/Temperature'
IMU = 'sensor_msgs/msg/Imu'
F64 = 'std_msgs/msg/Float64'
F32 = 'std_msgs/msg/Float32'
T0 = 1_700_000_000                       # s, the stamps' seconds


def _typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def cdr_header(sec, nsec, frame, little=True):
    """Return the encapsulation and the std_msgs/Header padded to 8 (CDR rules)."""
    e = '<' if little else '>'
    enc = b'\x00\x01\x00\x00' if little else b'\x00\x00\x00\x00'
    s = frame.encode() + b'\x00'
    payload = struct.pack(e + 'iiI', sec, nsec, len(s)) + s
    payload += b'\x00' * (-len(payload) % 8)
    return enc, payload


def mag_bytes(sec, nsec, frame, xyz, little=True):
    enc, p = cdr_header(sec, nsec, frame, little)
    e = '<' if little else '>'
    return enc + p + struct.pack(e + '3d', *xyz) + struct.pack(e + '9d', *range(9))


def temp_bytes(sec, nsec, frame, deg, little=True):
    enc, p = cdr_header(sec, nsec, frame, little)
    e = '<' if little else '>'
    return enc + p + struct.pack(e + '2d', deg, 0.25)


def test_hand_packed_lengths_match_the_cdr_rules():
    # frame_id 'abc': 12 bytes + 4 chars (with NUL) = 16, no padding: 4 + 16 + 96 = 116 bytes;
    # frame_id 'abcd': 12 + 5 = 17 -> padded to 24: 4 + 24 + 96 = 124 bytes
    assert len(mag_bytes(1, 2, 'abc', (0, 0, 0))) == 116
    assert len(mag_bytes(1, 2, 'abcd', (0, 0, 0))) == 124
    # and rosbags serialises the same bytes
    ts = _typestore()
    hdr = ts.types['std_msgs/msg/Header'](
        stamp=ts.types['builtin_interfaces/msg/Time'](sec=1, nanosec=2), frame_id='abcd')
    msg = ts.types[MAG](header=hdr,
                        magnetic_field=ts.types['geometry_msgs/msg/Vector3'](1.0, 2.0, 3.0),
                        magnetic_field_covariance=np.arange(9.0))
    assert bytes(ts.serialize_cdr(msg, MAG)) == mag_bytes(1, 2, 'abcd', (1.0, 2.0, 3.0))
    assert bytes(ts.serialize_cdr(msg, MAG, little_endian=False)) == mag_bytes(
        1, 2, 'abcd', (1.0, 2.0, 3.0), little=False)


@pytest.mark.parametrize('little', [True, False])
def test_decoder_reads_known_numbers_at_every_padding(little):
    # frame_id lengths 0..8 cover all 8 paddings before the float64 fields, mixed in a batch
    datas, want_t, want_v = [], [], []
    for k in range(90):
        frame = 'f' * (k % 9)
        xyz = (1e-5 * (k + 1), -2.5e-5 + 1e-9 * k, 3.25e-5)
        datas.append(mag_bytes(T0 + k, 1000 * k + 7, frame, xyz, little))
        want_t.append((T0 + k) * 1_000_000_000 + 1000 * k + 7)
        want_v.append(xyz)
    stamp, vals, ok = _decode_fixed(datas, MAG)
    assert ok.all()
    np.testing.assert_array_equal(stamp, want_t)
    np.testing.assert_array_equal(vals, want_v)
    stamp, vals, ok = _decode_fixed([temp_bytes(T0, 5, 'f' * k, 20.5 + k, little)
                                     for k in range(9)], TEMP)
    assert ok.all()
    np.testing.assert_array_equal(stamp, [T0 * 1_000_000_000 + 5] * 9)
    np.testing.assert_array_equal(vals[:, 0], 20.5 + np.arange(9))
    e = '<' if little else '>'
    enc = b'\x00\x01\x00\x00' if little else b'\x00\x00\x00\x00'
    stamp, vals, ok = _decode_fixed([enc + struct.pack(e + 'd', 0.125),
                                     enc + struct.pack(e + 'd', -3e-5)], F64)
    assert stamp is None and ok.all()
    np.testing.assert_array_equal(vals[:, 0], [0.125, -3e-5])
    stamp, vals, ok = _decode_fixed([enc + struct.pack(e + 'f', 1.5)], F32)
    assert ok.all() and vals[0, 0] == 1.5


def test_decoder_equals_rosbags_on_every_type():
    ts = _typestore()
    rng = np.random.default_rng(5)
    T = ts.types
    vec = T['geometry_msgs/msg/Vector3']
    for little in (True, False):
        for k in range(9):
            hdr = T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                sec=int(rng.integers(0, 2 ** 31)), nanosec=int(rng.integers(0, 10 ** 9))),
                frame_id='x' * k)
            r = rng.normal(size=40)
            msgs = {
                MAG: T[MAG](header=hdr, magnetic_field=vec(*r[:3]),
                            magnetic_field_covariance=r[3:12]),
                TEMP: T[TEMP](header=hdr, temperature=r[0], variance=r[1]),
                IMU: T[IMU](header=hdr, orientation=T['geometry_msgs/msg/Quaternion'](
                    *r[:4]), orientation_covariance=r[4:13], angular_velocity=vec(*r[13:16]),
                    angular_velocity_covariance=r[16:25], linear_acceleration=vec(*r[25:28]),
                    linear_acceleration_covariance=r[28:37]),
                F64: T[F64](data=r[0]),
                F32: T[F32](data=np.float32(r[0])),
            }
            for typ, msg in msgs.items():
                raw = bytes(ts.serialize_cdr(msg, typ, little_endian=little))
                back = ts.deserialize_cdr(raw, typ)
                stamp, vals, ok = _decode_fixed([raw], typ)
                assert ok.all(), (typ, k, little)
                if typ == MAG:
                    want = [back.magnetic_field.x, back.magnetic_field.y, back.magnetic_field.z]
                elif typ == TEMP:
                    want = [back.temperature]
                elif typ == IMU:
                    o = back.orientation
                    want = [o.x, o.y, o.z, o.w, back.orientation_covariance[0]]
                else:
                    want = [back.data]
                np.testing.assert_array_equal(vals[0], want)
                if stamp is not None:
                    st = back.header.stamp
                    assert stamp[0] == st.sec * 1_000_000_000 + st.nanosec


def test_decoder_leaves_what_it_cannot_read_to_rosbags():
    good = mag_bytes(T0, 0, 'ab', (1.0, 2.0, 3.0))
    bad = [
        good + b'\x00\x00',                       # trailing bytes (rosbags accepts up to 3)
        good[:-8],                                # truncated
        b'\x00\x03' + good[2:],                   # not plain CDR
        good[:12] + struct.pack('<I', 40) + good[16:],   # string longer than the message
        good[:12] + struct.pack('<I', 0) + good[16:],    # no NUL (length 0)
        good[:16] + b'\xc3\xa9\x00' + good[19:],  # non-ASCII frame_id
    ]
    _, vals, ok = _decode_fixed([good] + bad, MAG)
    assert ok.tolist() == [True] + [False] * len(bad)
    np.testing.assert_array_equal(vals[0], [1.0, 2.0, 3.0])


def _hand_bag(path, storage, corrupt=None, stop=None):
    """
    Bag of 3 sensors x 400 hand-packed messages (frame_ids of lengths 0..8), + temps.

    ``stop``: (epoch where sensor 2's temperature stops, epoch where sensor 3 stops).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    ts = _typestore()
    plugin = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}[storage]
    n = 400
    t_ns = [T0 * 1_000_000_000 + k * 10_000_000 for k in range(n)]     # 100 Hz
    field = np.zeros((3, n, 3))
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = [w.add_connection(f'/magcal/sensor{j}/raw', MAG, typestore=ts)
                 for j in (1, 2, 3)]
        temp = w.add_connection('/magcal/sensor2/temperature', TEMP, typestore=ts)
        aux = w.add_connection('/magcal/aux/heater', F32, typestore=ts)
        for k in range(n):
            for j, c in enumerate(conns):
                if stop and j == 2 and k >= stop[1]:
                    continue
                xyz = (1e-6 * (j + 1) + 1e-9 * k, -2e-5 - 1e-10 * k, 4.5e-5)
                field[j, k] = xyz
                frame = 'g' * ((k + 3 * j) % 9)
                little = not (j == 2 and k % 2)      # sensor 3: every other one big-endian
                data = mag_bytes(t_ns[k] // 10 ** 9, t_ns[k] % 10 ** 9, frame, xyz, little)
                if corrupt == (j, k):
                    data = data[:-5]
                w.write(c, t_ns[k], data)
            if not stop or k < stop[0]:
                w.write(temp, t_ns[k], temp_bytes(t_ns[k] // 10 ** 9, t_ns[k] % 10 ** 9, 'tt',
                                                  20.0 + 0.01 * k))
            w.write(aux, t_ns[k], b'\x00\x01\x00\x00' + struct.pack('<f', 0.5 * (k // 100)))
    return np.array(t_ns) * 1e-9, field


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_bag_of_hand_packed_messages_reads_the_known_numbers(tmp_path, storage):
    from magcal_ros.io.bag import bag_chunks
    t, field = _hand_bag(tmp_path / 'bag', storage)
    got = read_bag(tmp_path / 'bag')
    # stamps: float64 of the integer ns times 1e-9 (as the reader defines the time)
    np.testing.assert_array_equal(got.t, t)
    np.testing.assert_array_equal(got.raw, field * 1e9)     # T -> nT: units.NT_PER_T = 1e9
    np.testing.assert_array_equal(got.temp[1], 20.0 + 0.01 * np.arange(400))
    assert np.isnan(got.temp[0]).all()
    np.testing.assert_array_equal(got.aux['aux_heater'], 0.5 * (np.arange(400) // 100))
    chunks = list(bag_chunks(tmp_path / 'bag', rows=37))
    assert len(chunks) > 5
    np.testing.assert_array_equal(np.concatenate([c.raw for c in chunks], axis=1), got.raw)


def test_a_stream_that_stops_is_not_waited_for(tmp_path):
    # sensor 2's temperature stops at epoch 60, sensor 3 at epoch 150 (of 400): the chunks
    # stay about `rows` epochs (not everything after the stop in one piece at the end), and
    # they hold what read_bag reads (epochs without sensor 3 dropped, the temperature held)
    from magcal_ros.io.bag import bag_chunks
    _hand_bag(tmp_path / 'bag', 'mcap', stop=(60, 150))
    whole = read_bag(tmp_path / 'bag')
    assert whole.n_samples == 150 and whole.meta['dropped_epochs'] == 250
    chunks = list(bag_chunks(tmp_path / 'bag', rows=20))
    assert max(c.n_samples for c in chunks) <= 2 * 20
    for key in ('t', 'raw', 'temp'):
        np.testing.assert_array_equal(
            np.concatenate([getattr(c, key) for c in chunks], axis=-2 if key == 'raw' else -1),
            getattr(whole, key))
    np.testing.assert_array_equal(whole.temp[1, 59:], 20.0 + 0.01 * 59)


def test_a_damaged_message_is_named(tmp_path):
    _hand_bag(tmp_path / 'bag', 'sqlite3', corrupt=(1, 250))
    with pytest.raises(BagFormatError, match=r'message 251 of /magcal/sensor2/raw \(sensor_msgs'
                       r'/msg/MagneticField, recorded at 1700000002500000000 ns\) cannot be '
                       r'decoded .*damaged there; re-record it, or leave this topic out'):
        read_bag(tmp_path / 'bag')


def test_write_bag_templates_write_what_rosbags_serialises(tmp_path):
    from rosbags.highlevel import AnyReader
    ts = _typestore()
    rng = np.random.default_rng(2)
    n = 300
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    data = Dataset(t=T0 + 0.001 * np.arange(n), raw=rng.normal(0, 3e4, (2, n, 3)),
                   temp=20 + rng.normal(size=(2, n)), ref_total=5e4 + rng.normal(size=n),
                   aux={'aux_pump': rng.normal(size=n)}, attitude=q)
    path = write_bag(tmp_path / 'bag', [data], storage='mcap', frame_id='abcde')
    count = 0
    with AnyReader([path], default_typestore=ts) as reader:
        for c, _, raw in reader.messages():
            msg = reader.deserialize(raw, c.msgtype)
            assert bytes(ts.serialize_cdr(msg, c.msgtype)) == bytes(raw)
            count += 1
    assert count == n * 7
    got = read_bag(path)
    np.testing.assert_allclose(got.raw, data.raw, rtol=1e-15, atol=1e-9)
    np.testing.assert_array_equal(got.temp, data.temp)
    np.testing.assert_array_equal(got.aux['aux_pump'], data.aux['aux_pump'])
    np.testing.assert_allclose(np.abs(np.sum(got.attitude * q, axis=1)), 1.0, atol=1e-12)
