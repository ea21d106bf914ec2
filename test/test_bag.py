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

"""rosbag2 reader (magcal_ros.io.bag): write simulated data with rosbags' writer, read back."""
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.model import fit
from magcal_ros.io.bag import BagFormatError, read_bag, write_bag
from magcal_ros.units import nt_to_t
import numpy as np
import pytest

#: tesla round trip through float64 messages: relative 1e-16 of 5e-5 T, i.e. < 1e-9 nT;
#: header stamps are integer nanoseconds
ATOL_NT = 1e-6
ATOL_S = 1e-9


@pytest.fixture(scope='module')
def sim_data():
    data, _ = simulate(n_samples=400, rate_hz=5.0, trajectory='smooth', seed=8,
                       diurnal_swing_nt=20.0)
    data.t = data.t + 1.7e9          # absolute stamps, as a live recording has
    return data


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_round_trip(sim_data, tmp_path, storage):
    path = write_bag(tmp_path / 'bag', sim_data, storage=storage)
    got = read_bag(path)
    np.testing.assert_allclose(got.t, sim_data.t, atol=1e-6)
    np.testing.assert_allclose(got.raw, sim_data.raw, atol=ATOL_NT)
    np.testing.assert_allclose(got.temp, sim_data.temp, atol=1e-12)
    np.testing.assert_allclose(got.ref_total, sim_data.ref_total, atol=ATOL_NT)
    assert sorted(got.aux) == sorted(sim_data.aux)
    for k, v in sim_data.aux.items():
        np.testing.assert_allclose(got.aux[k], v, atol=1e-12)
    assert got.meta['dropped_epochs'] == 0
    assert '/magcal/sensor4/raw' in got.meta['topics']


def test_bag_data_calibrates_like_the_original(sim_data, tmp_path):
    path = write_bag(tmp_path / 'bag', sim_data)
    a = fit(sim_data, 'base')
    b = fit(read_bag(path), 'base')
    np.testing.assert_allclose(b.params, a.params, rtol=1e-7, atol=1e-9)


def test_stamps_matched_and_unmatched_epochs_dropped(sim_data, tmp_path):
    # sensor 3 late by a quarter period (kept, matched to nearest); one epoch of sensor 2
    # missing (dropped)
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import get_typestore, Stores
    ts = get_typestore(Stores.ROS2_JAZZY)
    mag = ts.types['sensor_msgs/msg/MagneticField']
    hdr = ts.types['std_msgs/msg/Header']
    tm = ts.types['builtin_interfaces/msg/Time']
    vec = ts.types['geometry_msgs/msg/Vector3']
    n = 50
    t = sim_data.t[:n]
    path = tmp_path / 'skew'
    with Writer(path, version=9) as w:
        conns = [w.add_connection(f'/magcal/sensor{j}/raw', 'sensor_msgs/msg/MagneticField',
                                  typestore=ts) for j in (1, 2, 3)]
        for k in range(n):
            for j, c in enumerate(conns, start=1):
                if j == 2 and k == 10:
                    continue
                tk = t[k] + (0.05 if j == 3 else 0.0)       # 1/4 of 0.2 s
                ns = int(round(tk * 1e9))
                msg = mag(header=hdr(stamp=tm(sec=ns // 10**9, nanosec=ns % 10**9),
                                     frame_id='f'),
                          magnetic_field=vec(*map(float, nt_to_t(sim_data.raw[j - 1, k]))),
                          magnetic_field_covariance=np.zeros(9))
                w.write(c, ns, ts.serialize_cdr(msg, 'sensor_msgs/msg/MagneticField'))
    got = read_bag(path)
    assert got.n_sensors == 3 and got.n_samples == n - 1
    assert got.meta['dropped_epochs'] == 1
    keep = np.arange(n) != 10
    np.testing.assert_allclose(got.raw[2], sim_data.raw[2, :n][keep], atol=ATOL_NT)
    assert got.temp is None and got.aux == {} and got.ref_total is None


def test_bad_bags(tmp_path, sim_data):
    with pytest.raises(BagFormatError, match='not a rosbag2 directory'):
        read_bag(tmp_path)
    path = write_bag(tmp_path / 'other', sim_data, namespace='/robot/mag')
    with pytest.raises(BagFormatError, match='no sensor_msgs/msg/MagneticField topics named '
                       '/magcal/sensor<j>/raw; the bag has: /robot/mag/'):
        read_bag(path)
    assert read_bag(path, namespace='/robot/mag').n_sensors == 4
    with pytest.raises(BagFormatError, match=r"auxiliary topic\(s\) \['/nope'\]"):
        read_bag(path, namespace='/robot/mag', aux_topics={'aux_x': '/nope'})
    got = read_bag(path, namespace='robot/mag',
                   aux_topics={'aux_motor': '/robot/mag/aux/motor_current'})
    np.testing.assert_allclose(got.aux['aux_motor'], sim_data.aux['aux_motor_current'])
    with pytest.raises(ValueError, match='exists'):
        write_bag(path, sim_data)
    with pytest.raises(ValueError, match="storage must be 'sqlite3' or 'mcap'"):
        write_bag(tmp_path / 'x', sim_data, storage='zip')
