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
Vehicle logs (magcal_ros/io/vehicle.py): synthetic ArduPilot and PX4 logs of known content.

The logs are written by test/vehicle_log_writers.py from the formats' documentation; the
raw readings, the autopilot's parameters and its corrections are chosen here, the logged
(corrected, rounded) values computed by the autopilots' forward correction, and the reader
must give back the raw readings within the rounding the log format imposes.
"""
import datetime
import json

from magcal_ros import cli
from magcal_ros.core.data.magnitude import igrf_field
from magcal_ros.io.dataflash import ardupilot_raw
from magcal_ros.io.vehicle import read_vehicle_log, VehicleLogError
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import vehicle_log_writers as w

RATE = 20.0                      # compass rate, Hz
N = 1200                         # one minute
LAT, LON, ALT_M = 47.3977, 8.5456, 488.0
GPS_WEEK, GPS_MS = 2300, 345600000          # 2024-02-08 00:00 GPS time (by hand: 2300 weeks)


def _world_field():
    f, inc = igrf_field(LAT, LON, ALT_M / 1000.0, '2024-02-08')
    i = np.radians(inc)
    return np.array([f * np.cos(i), 0.0, f * np.sin(i)])       # NED, declination 0


def _matrix(diag, offdiag):
    d, o = diag, offdiag
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


#: compass 1's onboard calibration: offsets (mG), DIA, ODI, SCALE, MOT (mG per A)
CAL1 = {'ofs': np.array([-31.0, 22.0, -14.0]), 'dia': np.array([1.02, 0.98, 1.01]),
        'odi': np.array([0.01, -0.02, 0.005]), 'scale': 1.1, 'mot': np.array([2.0, -1.5, 3.0])}
#: compass 2: no DIA set (all zero: identity), no SCALE (0: not applied)
CAL2 = {'ofs': np.array([5.0, -7.0, 12.0]), 'dia': np.zeros(3), 'odi': np.zeros(3),
        'scale': 0.0, 'mot': np.array([-1.0, 0.5, 0.8])}


def _scenario(seed=0, n=N):
    """Return times (n,) s, attitudes (n, 4), current (n,) A, two compasses' raw fields (nT)."""
    rng = np.random.default_rng(seed)
    t = 10.0 + np.arange(n) / RATE
    rot = Rotation.random(n, random_state=seed)       # every attitude: a full sphere
    b = rot.inv().apply(_world_field())
    raw1 = b + np.array([3000.0, -2000.0, 1500.0]) + rng.normal(0, 30, (n, 3))
    raw2 = b + np.array([-800.0, 600.0, -1200.0]) + rng.normal(0, 30, (n, 3))
    current = 5.0 + 0.2 * (t - t[0])
    return t, rot.as_quat(scalar_first=True), current, raw1, raw2


def _ap_params(extra=None):
    p = {'AHRS_EKF_TYPE': 3, 'COMPASS_MOTCT': 2,
         'COMPASS_SCALE': CAL1['scale'], 'COMPASS_SCALE2': CAL2['scale'],
         'COMPASS_DEV_ID': 97539, 'COMPASS_DEV_ID2': 131874, 'COMPASS_ORIENT': 0,
         'COMPASS_EXTERNAL': 1,
         'SERVO1_FUNCTION': 33, 'SERVO2_FUNCTION': 34, 'SERVO3_FUNCTION': 35,
         'SERVO4_FUNCTION': 36, 'SERVO5_FUNCTION': 0}
    for k, (cal, suffix) in enumerate(((CAL1, ''), (CAL2, '2'))):
        for i, a in enumerate('XYZ'):
            p[f'COMPASS_OFS{suffix}_{a}'] = cal['ofs'][i]
            p[f'COMPASS_DIA{suffix}_{a}'] = cal['dia'][i]
            p[f'COMPASS_ODI{suffix}_{a}'] = cal['odi'][i]
            p[f'COMPASS_MOT{suffix}_{a}'] = cal['mot'][i]
    p.update(extra or {})
    return p


def _ap_logged(raw_nt, cal, current, motor_first=False):
    """Return what ArduPilot logs (MagX.., OfsX.., MOX..; whole mG) for raw readings in nT."""
    r = raw_nt / 100.0
    dia = cal['dia'] if np.any(cal['dia']) else np.ones(3)
    m = _matrix(dia, cal['odi'])
    s = cal['scale'] if 0.85 <= cal['scale'] <= 1.4 else 1.0
    mo = np.outer(current, cal['mot'])
    if motor_first:
        f = (r + cal['ofs'] + np.round(mo)) @ m.T
    else:
        f = s * (r + cal['ofs']) @ m.T + mo
    return np.round(f), np.broadcast_to(cal['ofs'], r.shape), np.round(mo)


def _bound_nt(cal):
    """Largest error of the undone reading per axis from the log's rounding to 1 mG."""
    dia = cal['dia'] if np.any(cal['dia']) else np.ones(3)
    s = cal['scale'] if 0.85 <= cal['scale'] <= 1.4 else 1.0
    minv = np.linalg.inv(_matrix(dia, cal['odi']))
    return float(np.abs(minv).sum(axis=1).max() * (0.5 + 0.5) / s * 100.0 + 1e-6)


def _write_ap(path, seed=0, n=N, attitude='XKQ', gap=None, extra_params=None,
              magless=False, dead=()):
    t, q, cur, raw1, raw2 = _scenario(seed, n)
    df = w.DataFlash()
    df.write('MSG', TimeUS=[500], Message=['ArduCopter V4.5.1 (deadbeef)'])
    df.params(_ap_params(extra_params))
    us = np.round(t * 1e6)
    keep = np.ones(n, bool)
    if gap is not None:
        keep &= ~((t >= gap[0]) & (t < gap[0] + gap[1]))
    if not magless:
        for k, (raw, cal) in enumerate(((raw1, CAL1), (raw2, CAL2))):
            f, o, mo = _ap_logged(raw, cal, cur)
            if k in dead:                   # not connected: ArduPilot logs zeros
                f, o, mo = np.zeros_like(f), np.zeros_like(o), np.zeros_like(mo)
            df.write('MAG', TimeUS=us[keep], I=np.full(keep.sum(), k), MagX=f[keep, 0],
                     MagY=f[keep, 1], MagZ=f[keep, 2], OfsX=o[keep, 0], OfsY=o[keep, 1],
                     OfsZ=o[keep, 2], MOX=mo[keep, 0], MOY=mo[keep, 1], MOZ=mo[keep, 2],
                     Health=np.ones(keep.sum()), S=us[keep] / 1000)
    if attitude == 'XKQ':
        df.write('XKQ', TimeUS=us, C=np.zeros(n), Q1=q[:, 0], Q2=q[:, 1], Q3=q[:, 2],
                 Q4=q[:, 3])
    half = slice(None, None, 2)
    df.write('BAT', TimeUS=us[half], Inst=np.zeros(len(us[half])), Volt=16.8 - 0.01 * t[half],
             Curr=cur[half], Temp=np.zeros(len(us[half])))
    df.write('CTUN', TimeUS=us, ThO=0.4 + 0.001 * (t - t[0]))
    outputs = {f'C{c}': 1100 + 10 * c + np.floor(t - t[0]) for c in range(1, 9)}
    df.write('RCOU', TimeUS=us, **outputs)
    g = np.arange(0, n, 4)
    status = np.where(np.arange(len(g)) < 3, 1, 3)
    lat = np.where(status >= 3, LAT, 10.0)
    df.write('GPS', TimeUS=us[g], I=np.zeros(len(g)), Status=status, GMS=GPS_MS + 200 * g,
             GWk=np.full(len(g), GPS_WEEK), Lat=lat, Lng=np.full(len(g), LON),
             Alt=np.full(len(g), ALT_M))
    for k in range(2):                      # two batteries, four ESCs
        if k:
            df.write('BAT', TimeUS=us[half], Inst=np.ones(len(us[half])),
                     Volt=np.full(len(us[half]), 5.1), Curr=np.full(len(us[half]), 0.3))
    for k in range(4):
        df.write('ESC', TimeUS=us, Instance=np.full(n, k), RPM=5000.0 + 100 * k + 0 * t,
                 Curr=2.0 + k + 0.01 * (t - t[0]), Temp=np.full(n, 30.0 + k))
    ti = 10.0 + np.arange(int(n / RATE * 200)) / 200.0
    df.write('IMU', TimeUS=np.round(ti * 1e6), I=np.zeros(len(ti)), T=40.0 + 0.1 * (ti - 10.0))
    return df.save(path), (t, q, cur, raw1, raw2)


@pytest.fixture(scope='module')
def ap_log(tmp_path_factory):
    return _write_ap(tmp_path_factory.mktemp('ap') / 'flight.bin')


def test_dataflash_gives_the_raw_body_reading_with_every_correction_undone(ap_log):
    path, (t, q, cur, raw1, raw2) = ap_log
    d = read_vehicle_log(path)
    assert d.n_sensors == 2 and d.n_samples == N
    np.testing.assert_allclose(d.t, t, atol=1e-6)
    for j, (raw, cal) in enumerate(((raw1, CAL1), (raw2, CAL2))):
        err = np.abs(d.raw[j] - raw).max()
        assert err <= _bound_nt(cal), (j, err)
        # the logged field itself is far from the raw one: the undo is what recovers it
        f, _, _ = _ap_logged(raw, cal, cur)
        assert np.abs(f * 100.0 - raw).max() > 10 * _bound_nt(cal)
    norm = np.linalg.norm(d.raw[0] - [3000.0, -2000.0, 1500.0], axis=1)
    assert abs(np.median(norm) - np.linalg.norm(_world_field())) < 100
    # attitude: the EKF quaternion at the compass epochs, unchanged
    assert d.meta['attitude_source'] == 'ArduPilot EKF3 XKQ core 0'
    assert d.meta['attitude_frame'] == 'NED'
    dots = np.abs(np.einsum('ij,ij->i', d.attitude, q))
    assert dots.min() > 1 - 1e-6


def test_dataflash_channels_names_units_and_meta(ap_log):
    path, (t, q, cur, raw1, raw2) = ap_log
    d = read_vehicle_log(path)
    units = d.meta['aux_units']
    # the battery at half the compass rate, a linear ramp: interpolation is exact inside
    # its span, and its last message held after it (the last compass epoch)
    np.testing.assert_allclose(d.aux['aux_battery_current'][:-1], cur[:-1], atol=1e-4)
    assert d.aux['aux_battery_current'][-1] == pytest.approx(cur[-2], abs=1e-4)
    np.testing.assert_allclose(d.aux['aux_battery_voltage'][:-1], 16.8 - 0.01 * t[:-1],
                               atol=1e-4)
    np.testing.assert_allclose(d.aux['aux_throttle'], 0.4 + 0.001 * (t - t[0]), atol=1e-6)
    for k in range(1, 5):           # SERVO1..4_FUNCTION = motor 1..4; SERVO5 is no motor
        np.testing.assert_array_equal(d.aux[f'aux_motor{k}'], 1100 + 10 * k +
                                      np.floor(t - t[0]))
    assert 'aux_motor5' not in d.aux
    np.testing.assert_allclose(d.aux['aux_battery2_current'], 0.3, atol=1e-6)
    np.testing.assert_allclose(d.aux['aux_battery2_voltage'], 5.1, atol=1e-6)
    for k in range(1, 5):
        # Curr is a centiamp integer ('c'): 0.005 A of rounding
        np.testing.assert_allclose(d.aux[f'aux_esc{k}_current'], 1.0 + k + 0.01 * (t - t[0]),
                                   atol=0.0051)
        np.testing.assert_allclose(d.aux[f'aux_esc{k}_rpm'], 4900.0 + 100 * k, atol=1e-6)
        np.testing.assert_allclose(d.aux[f'aux_esc{k}_temp'], 29.0 + k, atol=1e-6)
    assert units['aux_esc1_current'] == 'A' and units['aux_esc1_rpm'] == 'rpm'
    # IMU at 200 Hz read at 10 Hz (a temperature is slow): every 20th message
    np.testing.assert_allclose(d.aux['aux_imu_temp'][:-1], 40.0 + 0.1 * (t[:-1] - 10.0),
                               atol=1e-4)
    assert units['aux_battery_current'] == 'A' and units['aux_motor1'] == 'PWM us'
    assert units['aux_imu_temp'] == 'degC' and units['aux_throttle'] == '0..1'
    # GPS: the median of the 3-D fixes (the first three are not), its date by hand
    site = d.meta['igrf']
    assert site['lat_deg'] == pytest.approx(LAT, abs=1e-6)
    assert site['lon_deg'] == pytest.approx(LON, abs=1e-6)
    assert site['alt_km'] == pytest.approx(ALT_M / 1000.0, abs=1e-5)
    assert site['date'] == '2024-02-08'
    assert d.meta['firmware'] == 'ArduCopter V4.5' and d.meta['source_format'] == \
        'ArduPilot DataFlash'
    on = d.meta['onboard_calibration']
    np.testing.assert_allclose(on[0]['offsets_nt'], CAL1['ofs'] * 100.0)
    np.testing.assert_allclose(on[0]['diagonals'], CAL1['dia'], rtol=1e-6)
    np.testing.assert_allclose(on[0]['offdiagonals'], CAL1['odi'], rtol=1e-5)
    assert on[0]['scale'] == pytest.approx(1.1) and on[0]['scale_applied']
    assert on[1]['diagonals'] == [1.0, 1.0, 1.0] and not on[1]['scale_applied']
    assert on[0]['motor_compensation']['type'] == 'current'
    np.testing.assert_allclose(on[0]['motor_compensation']['vector_nt_per_unit'],
                               CAL1['mot'] * 100.0, rtol=1e-6)
    assert on[0]['device_id'] == 97539 and on[1]['device_id'] == 131874
    assert d.meta['warnings'] == []


def test_ardupilot_raw_inverts_the_firmware_correction_exactly():
    rng = np.random.default_rng(3)
    r = rng.normal(0, 400, (50, 3))
    o = rng.normal(0, 50, (50, 3))
    m = rng.normal(0, 20, (50, 3))
    dia, odi, s = np.array([1.1, 0.9, 1.05]), np.array([0.03, -0.02, 0.01]), 1.2
    f = s * (r + o) @ _matrix(dia, odi).T + m
    np.testing.assert_allclose(ardupilot_raw(f, o, m, dia, odi, s), r, atol=1e-9)
    f_old = (r + o + m) @ _matrix(dia, odi).T             # before 3.6, no scale
    np.testing.assert_allclose(ardupilot_raw(f_old, o, m, dia, odi, 0.0, motor_first=True), r,
                               atol=1e-9)
    # a scale outside 0.85..1.4 is not applied by the firmware, nor undone here
    f_noscale = (r + o) @ _matrix(dia, odi).T + m
    np.testing.assert_allclose(ardupilot_raw(f_noscale, o, m, dia, odi, 2.0), r, atol=1e-9)


def test_dataflash_of_firmware_3_5_motor_offset_before_the_matrix(tmp_path):
    t, q, cur, raw1, raw2 = _scenario(1, 400)
    cal = dict(CAL1, scale=0.0, mot=np.array([20.0, -15.0, 30.0]))
    df = w.DataFlash(w.AP35)
    df.write('MSG', TimeUS=[500], Message=['ArduCopter V3.5.7 (0123abcd)'])
    params = _ap_params({'COMPASS_SCALE': 0.0, 'AHRS_EKF_TYPE': 2})
    params.update({f'COMPASS_MOT_{a}': v for a, v in zip('XYZ', cal['mot'])})
    df.params(params)
    us = np.round(t * 1e6)
    for name, raw, c in (('MAG', raw1, cal), ('MAG2', raw2, CAL2)):
        f, o, mo = _ap_logged(raw, c, cur, motor_first=True)
        df.write(name, TimeUS=us, MagX=f[:, 0], MagY=f[:, 1], MagZ=f[:, 2], OfsX=o[:, 0],
                 OfsY=o[:, 1], OfsZ=o[:, 2], MOfsX=mo[:, 0], MOfsY=mo[:, 1], MOfsZ=mo[:, 2],
                 Health=np.ones(len(t)))
    df.write('NKQ1', TimeUS=us, Q1=q[:, 0], Q2=q[:, 1], Q3=q[:, 2], Q4=q[:, 3])
    d = read_vehicle_log(df.save(tmp_path / 'old.bin'))
    assert d.n_sensors == 2 and d.meta['attitude_source'] == 'ArduPilot EKF2 NKQ1 core 0'
    assert np.abs(d.raw[0] - raw1).max() <= _bound_nt(cal)
    assert np.abs(d.raw[1] - raw2).max() <= _bound_nt(CAL2)
    # 4.x's order on these logs is off by M m - m: the version decides
    f, o, mo = _ap_logged(raw1, cal, cur, motor_first=True)
    wrong = ardupilot_raw(f, o, mo, cal['dia'], cal['odi'], 0.0) * 100.0
    assert np.abs(wrong - raw1).max() > 3 * _bound_nt(cal)


def test_att_attitude_has_the_ahrs_trim_removed(tmp_path):
    """The field in the world frame is the same at every epoch only with the trim removed."""
    t, q, cur, raw1, raw2 = _scenario(2, 300)
    trim = np.array([0.05, -0.03, 0.0])                          # rad
    r_ap = Rotation.from_quat(q, scalar_first=True)
    r_trim = Rotation.from_euler('ZYX', trim[::-1])
    r_vehicle = r_ap * r_trim.inv()          # what ATT reports: AP_AHRS's vehicle body
    yaw, pitch, roll = r_vehicle.as_euler('ZYX', degrees=True).T
    b = r_ap.inv().apply(_world_field())
    df = w.DataFlash()
    df.params(_ap_params({'AHRS_TRIM_X': trim[0], 'AHRS_TRIM_Y': trim[1],
                          'COMPASS_OFS_X': 0.0, 'COMPASS_OFS_Y': 0.0, 'COMPASS_OFS_Z': 0.0,
                          'COMPASS_DIA_X': 1.0, 'COMPASS_DIA_Y': 1.0, 'COMPASS_DIA_Z': 1.0,
                          'COMPASS_ODI_X': 0.0, 'COMPASS_ODI_Y': 0.0, 'COMPASS_ODI_Z': 0.0,
                          'COMPASS_SCALE': 0.0, 'COMPASS_MOTCT': 0}))
    us = np.round(t * 1e6)
    z = np.zeros(len(t))
    f = b / 100.0                                   # mG; no offsets, no matrix
    df.write('MAG', TimeUS=us, I=z, MagX=f[:, 0], MagY=f[:, 1], MagZ=f[:, 2], Health=z + 1)
    df.write('ATT', TimeUS=us, Roll=roll, Pitch=pitch, Yaw=np.mod(yaw, 360.0))
    d = read_vehicle_log(df.save(tmp_path / 'att.bin'))
    assert d.meta['attitude_source'].startswith('ArduPilot ATT')
    world = np.einsum('nij,nj->ni', d.attitude_matrix(), d.raw[0])
    # |B| ~ 48 000 nT: 0.5 mG rounding and 0.01 deg steps give a few tens of nT
    assert np.abs(world - _world_field()).max() < 100.0
    # the ATT angles taken as the autopilot's attitude are 0.05 rad = 2400 nT off
    naive = np.einsum('nij,nj->ni', r_vehicle.as_matrix(), d.raw[0])
    assert np.abs(naive - _world_field()).max() > 1000.0


def test_parameters_that_are_not_the_logged_compass_s_are_named(tmp_path):
    path, _ = _write_ap(tmp_path / 'swapped.bin', n=200, extra_params={'COMPASS_OFS_X': 99.0})
    d = read_vehicle_log(path)
    notes = [str(x) for x in d.meta['warnings']]
    assert any(x.startswith('compass 1: its logged offsets (-31, 22, -14 mG) are not its '
                            "parameters' (99, 22, -14 mG)") for x in notes), notes
    assert not any(x.startswith('compass 2') for x in notes)


@pytest.mark.parametrize('with_att', [True, False])
def test_the_ekf_core_the_ahrs_used(tmp_path, with_att):
    """Core 1 is ATT's (core 0, the primary, 10 deg off in yaw); without ATT, EK3_PRIMARY's."""
    t, q, cur, raw1, raw2 = _scenario(6, 200)
    r = Rotation.from_quat(q, scalar_first=True)
    off = r * Rotation.from_euler('z', 10, degrees=True)
    df = w.DataFlash()
    df.params(_ap_params({'EK3_PRIMARY': 0 if with_att else 1}))
    us = np.round(t * 1e6)
    z = np.zeros(len(t))
    f = raw1 / 100.0
    df.write('MAG', TimeUS=us, I=z, MagX=f[:, 0], MagY=f[:, 1], MagZ=f[:, 2], Health=z + 1)
    for core, rot in ((0, off), (1, r)):
        qq = rot.as_quat(scalar_first=True)
        df.write('XKQ', TimeUS=us, C=z + core, Q1=qq[:, 0], Q2=qq[:, 1], Q3=qq[:, 2],
                 Q4=qq[:, 3])
    if with_att:
        yaw, pitch, roll = r.as_euler('ZYX', degrees=True).T
        df.write('ATT', TimeUS=us, Roll=roll, Pitch=pitch, Yaw=np.mod(yaw, 360.0))
    d = read_vehicle_log(df.save(tmp_path / 'cores.bin'))
    assert d.meta['attitude_source'] == 'ArduPilot EKF3 XKQ core 1'
    assert np.abs(np.einsum('ij,ij->i', d.attitude, q)).min() > 1 - 1e-6


def test_a_log_without_attitude_is_plain_compass_data_with_a_warning(tmp_path):
    path, _ = _write_ap(tmp_path / 'noatt.bin', n=200, attitude=None)
    d = read_vehicle_log(path)
    assert d.attitude is None and d.meta['attitude_source'] is None
    assert any('no attitude in the log' in str(x) for x in d.meta['warnings'])
    assert all(x.kind == 'input' for x in d.meta['warnings'])


def test_errors_name_the_problem(tmp_path):
    path, _ = _write_ap(tmp_path / 'nomag.bin', n=200, magless=True)
    with pytest.raises(VehicleLogError, match='no compass data'):
        read_vehicle_log(path)
    path, _ = _write_ap(tmp_path / 'gap.bin', n=600, gap=(25.0, 3.0))
    with pytest.raises(VehicleLogError, match=r'stops for 3\.05 s at t = 24\.95 s .*50 ms'):
        read_vehicle_log(path)
    bad = tmp_path / 'garbage.bin'
    bad.write_bytes(b'\xa3\x95' + bytes(range(256)) * 8)
    with pytest.raises(VehicleLogError, match='garbage.bin: '):
        read_vehicle_log(bad)
    old = w.ULog(version=2)
    with pytest.raises(VehicleLogError, match='ULog file version 2'):
        read_vehicle_log(old.save(tmp_path / 'v2.ulg'))
    notulog = tmp_path / 'x.ulg'
    notulog.write_bytes(b'not a log at all, just text')
    with pytest.raises(VehicleLogError, match='not a ULog file'):
        read_vehicle_log(notulog)


def test_a_compass_that_reads_zero_throughout_is_left_out_and_said(tmp_path):
    # a compass not connected is logged as zeros (erlerobot/logs: pxf/rover/2-8-2014/
    # mpu9250-ms5611/7.BIN, 1 716 MAG messages of (0, 0, 0)); the other compass is the data
    path, (t, _, _, _, raw2) = _write_ap(tmp_path / 'dead1.bin', n=300, dead=(0,))
    d = read_vehicle_log(path)
    assert d.n_sensors == 1 and 'instance 1' in d.meta['compasses'][0]['source']
    np.testing.assert_allclose(d.t, t, atol=1e-6)
    assert np.abs(d.raw[0] - raw2).max() <= _bound_nt(CAL2)
    (note,) = [x for x in d.meta['warnings'] if 'left out' in str(x)]
    assert 'compass 1 (MAG instance 0) reads (0, 0, 0) nT in all 300 of its messages: left out' \
        in str(note)
    assert 'COMPASS_ENABLE' in str(note)
    path, _ = _write_ap(tmp_path / 'dead2.bin', n=300, dead=(0, 1))
    with pytest.raises(VehicleLogError) as err:
        read_vehicle_log(path)
    msg = str(err.value)
    assert 'every compass reads one value throughout, so there is no field to calibrate' in msg
    assert 'compass 2 (MAG instance 1) reads (0, 0, 0) nT in all 300 of its messages' in msg
    assert '\n' not in msg


def test_a_log_cut_inside_its_last_message_reads_the_messages_before(tmp_path, ap_log):
    path, (t, q, cur, raw1, raw2) = ap_log
    data = path.read_bytes()
    cut = tmp_path / 'cut.bin'
    # the writer puts the 2 x 1200 MAG messages first after the PARMs; cut inside MAG 600
    start = data.index(b'\xa3\x95', data.index(b'ArduCopter V4.5.1'))
    mag_len = 3 + 8 + 1 + 9 * 2 + 1 + 4
    first_mag = next(i for i in range(start, len(data)) if data[i:i + 2] == b'\xa3\x95' and
                     data[i + 2] == w.DataFlash().types['MAG'][0])
    cut.write_bytes(data[:first_mag + 599 * mag_len + 10])
    d = read_vehicle_log(cut)
    assert d.n_samples == 599 and d.n_sensors == 1
    assert np.abs(d.raw[0] - raw1[:599]).max() <= _bound_nt(CAL1)
    assert any('no attitude' in str(x) for x in d.meta['warnings'])


def test_cli_exit_2_with_one_line(tmp_path, capsys):
    path, _ = _write_ap(tmp_path / 'gap.bin', n=600, gap=(25.0, 3.0))
    assert cli.main(['fit', str(path), '--field-nt', 'auto']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'gap.bin: compass 1' in err[0] and 't = 24.95 s' in err[0]
    assert cli.main(['fit', str(path), '--unit', 'uT']) == 2
    assert '--unit uT: a vehicle log' in capsys.readouterr().err


def test_cli_fit_takes_igrf_from_the_log_gps_and_reports_the_onboard_calibration(
        ap_log, capsys):
    path, _ = ap_log
    assert cli.main(['fit', str(path), '--json', '-q']) == 0
    out = json.loads(capsys.readouterr().out)
    fref = out['field_reference']
    f, inc = igrf_field(LAT, LON, ALT_M / 1000.0, '2024-02-08')
    assert fref['kind'] == 'igrf' and fref['magnitude_nt'] == pytest.approx(f)
    assert "log's GPS" in fref['note'] and fref['date'] == '2024-02-08'
    assert out['onboard_calibration'][0]['offsets_nt'] == pytest.approx(
        list(CAL1['ofs'] * 100.0))
    assert out['log']['attitude_source'] == 'ArduPilot EKF3 XKQ core 0'
    # raw readings at the IGRF magnitude plus 30 nT noise: the fit finds that noise
    assert max(out['scalar_rms_nt'].values()) < 100.0


def test_text_dataflash_log(tmp_path):
    t, q, cur, raw1, _ = _scenario(4, 40)
    cal = dict(CAL1, scale=0.0, mot=np.zeros(3))
    f, o, mo = _ap_logged(raw1, cal, cur)
    msgs = [('MSG', {'TimeUS': 1, 'Message': 'ArduPlane V4.4.0 (x)'})]
    msgs += [('PARM', {'TimeUS': 2, 'Name': k, 'Value': v})
             for k, v in _ap_params({'COMPASS_SCALE': 0.0, 'COMPASS_MOTCT': 0}).items()]
    for i in range(len(t)):
        us = int(round(t[i] * 1e6))
        msgs.append(('MAG', {'TimeUS': us, 'I': 0, 'MagX': int(f[i, 0]), 'MagY': int(f[i, 1]),
                             'MagZ': int(f[i, 2]), 'OfsX': int(o[i, 0]), 'OfsY': int(o[i, 1]),
                             'OfsZ': int(o[i, 2]), 'MOX': 0, 'MOY': 0, 'MOZ': 0,
                             'Health': 1, 'S': 0}))
        msgs.append(('XKQ', {'TimeUS': us, 'C': 0, 'Q1': q[i, 0], 'Q2': q[i, 1],
                             'Q3': q[i, 2], 'Q4': q[i, 3]}))
    path = w.write_text_dataflash(tmp_path / 'flight.log', msgs)
    d = read_vehicle_log(path)
    assert d.meta['source_format'] == 'ArduPilot DataFlash (text)'
    assert d.n_samples == len(t) and np.abs(d.raw[0] - raw1).max() <= _bound_nt(cal)
    assert np.abs(np.einsum('ij,ij->i', d.attitude, q)).min() > 1 - 1e-6


# -- PX4 ULog -----------------------------------------------------------------------------

#: PX4 calibration slots: 0 is the internal compass (board rotation SENS_BOARD_ROT = 4:
#: yaw 180), 1 an external one (CAL_MAG1_ROT = 8: roll 180); offsets and scale in gauss
PX4_PARAMS = {'CAL_MAG0_ID': 396825, 'CAL_MAG0_ROT': -1, 'SENS_BOARD_ROT': 4,
              'CAL_MAG1_ID': 12345, 'CAL_MAG1_ROT': 8,
              'CAL_MAG0_XOFF': 0.05, 'CAL_MAG0_YOFF': -0.02, 'CAL_MAG0_ZOFF': 0.03,
              'CAL_MAG0_XSCALE': 1.05, 'CAL_MAG0_YSCALE': 0.97, 'CAL_MAG0_ZSCALE': 1.01,
              'CAL_MAG0_XODIAG': 0.01, 'CAL_MAG0_YODIAG': -0.015, 'CAL_MAG0_ZODIAG': 0.02,
              'CAL_MAG0_XCOMP': 0.8, 'CAL_MAG0_YCOMP': -0.5, 'CAL_MAG0_ZCOMP': 0.3,
              'CAL_MAG_COMP_TYP': 2}
#: the body-from-sensor rotations of those, by hand
R_INTERNAL = np.diag([-1.0, -1.0, 1.0])
R_EXTERNAL = np.diag([1.0, -1.0, -1.0])


def _px4_log(path, raw_rate_hz=50.0, n=500, cal_ids=None):
    t, q, cur, raw1, raw2 = _scenario(5, n)
    t_us = np.round(t * 1e6).astype(np.int64)
    u = w.ULog()
    for name, fields in (('sensor_mag', w.SENSOR_MAG),
                         ('vehicle_magnetometer', w.VEHICLE_MAGNETOMETER),
                         ('vehicle_attitude', w.VEHICLE_ATTITUDE),
                         ('battery_status', w.BATTERY_STATUS),
                         ('actuator_motors', w.ACTUATOR_MOTORS),
                         ('sensor_gps', w.SENSOR_GPS)):
        u.topic(name, fields)
    u.info('ver_sw', 'cb09dde606861b90e38b1682eebd3fd91be17ab7')
    u.info('sys_name', 'PX4')
    for k, v in {**PX4_PARAMS, **(cal_ids or {})}.items():
        u.param(k, v)
    # the sensors' own readings (gauss, sensor axes): body raw = R d
    d1 = raw1 @ R_INTERNAL / 1e5
    d2 = raw2 @ R_EXTERNAL / 1e5
    step = max(1, int(round(RATE / raw_rate_hz)))
    for k, (d, dev) in enumerate(((d1, 396825), (d2, 12345))):
        s = slice(None, None, step)
        u.data('sensor_mag', k, timestamp=t_us[s], timestamp_sample=t_us[s],
               device_id=np.full(len(t_us[s]), dev), x=d[s, 0], y=d[s, 1], z=d[s, 2],
               temperature=30.0 + 0.05 * (t[s] - t[0]) + k)
    # the corrected field of compass 1 as VehicleMagnetometer publishes it
    p = PX4_PARAMS
    o = np.array([p['CAL_MAG0_XOFF'], p['CAL_MAG0_YOFF'], p['CAL_MAG0_ZOFF']])
    sm = _matrix([p['CAL_MAG0_XSCALE'], p['CAL_MAG0_YSCALE'], p['CAL_MAG0_ZSCALE']],
                 [p['CAL_MAG0_XODIAG'], p['CAL_MAG0_YODIAG'], p['CAL_MAG0_ZODIAG']])
    c = np.array([p['CAL_MAG0_XCOMP'], p['CAL_MAG0_YCOMP'], p['CAL_MAG0_ZCOMP']])
    v = ((d1 + np.outer(cur * 1e-3, c)) - o) @ sm.T @ R_INTERNAL.T
    u.data('vehicle_magnetometer', 0, timestamp=t_us, timestamp_sample=t_us,
           device_id=np.full(n, 396825), magnetometer_ga=v)
    u.data('vehicle_attitude', 0, timestamp=t_us, timestamp_sample=t_us, q=q)
    u.data('battery_status', 0, timestamp=t_us, voltage_v=16.0 - 0.01 * (t - t[0]),
           current_a=cur, temperature=np.full(n, np.nan))
    u.data('actuator_motors', 0, timestamp=t_us,
           control=np.column_stack([0.5 + 0.01 * i + 0.0 * t for i in range(4)]))
    g = np.arange(0, n, 10)
    utc = int(datetime.datetime(2024, 3, 18, 12, tzinfo=datetime.timezone.utc).timestamp() * 1e6)
    u.data('sensor_gps', 0, timestamp=t_us[g], latitude_deg=np.full(len(g), LAT),
           longitude_deg=np.full(len(g), LON), altitude_msl_m=np.full(len(g), ALT_M),
           time_utc_usec=np.full(len(g), utc), fix_type=np.full(len(g), 3))
    return u.save(path), (t, q, cur, raw1, raw2)


def test_ulog_sensor_mag_rotated_into_the_body_frame(tmp_path):
    path, (t, q, cur, raw1, raw2) = _px4_log(tmp_path / 'px4.ulg')
    d = read_vehicle_log(path)
    assert d.n_sensors == 2 and d.meta['source_format'] == 'PX4 ULog'
    # float32 gauss: ~1e-7 relative of 50 000 nT
    np.testing.assert_allclose(d.raw[0], raw1, atol=0.05)
    np.testing.assert_allclose(d.raw[1], raw2, atol=0.05)
    np.testing.assert_allclose(d.temp[0], 30.0 + 0.05 * (t - t[0]), atol=1e-4)
    np.testing.assert_allclose(d.temp[1], 31.0 + 0.05 * (t - t[0]), atol=1e-4)
    assert np.abs(np.einsum('ij,ij->i', d.attitude, q)).min() > 1 - 1e-6
    np.testing.assert_allclose(d.aux['aux_battery_current'], cur, atol=1e-5)
    np.testing.assert_allclose(d.aux['aux_motor3'], 0.52, atol=1e-7)
    assert d.meta['aux_units']['aux_motor3'] == '0..1'
    assert d.meta['igrf']['date'] == '2024-03-18'
    assert d.meta['igrf']['lat_deg'] == pytest.approx(LAT)
    on = d.meta['onboard_calibration']
    assert on[0]['external'] is False and on[0]['rotation'] == 4
    assert on[1]['external'] is True and on[1]['rotation'] == 8
    np.testing.assert_allclose(on[0]['offsets_nt'], [5000.0, -2000.0, 3000.0], rtol=1e-6)
    np.testing.assert_allclose(on[0]['rotation_matrix'], R_INTERNAL, atol=1e-12)
    np.testing.assert_allclose(on[1]['rotation_matrix'], R_EXTERNAL, atol=1e-12)


def test_ulog_slow_sensor_mag_reads_vehicle_magnetometer_with_its_calibration_undone(
        tmp_path):
    path, (t, q, cur, raw1, raw2) = _px4_log(tmp_path / 'px4slow.ulg', raw_rate_hz=1.0)
    d = read_vehicle_log(path)
    assert d.n_sensors == 1 and d.meta['compasses'][0]['source'].startswith(
        'vehicle_magnetometer')
    np.testing.assert_allclose(d.raw[0], raw1, atol=0.1)
    assert any('logged at 1.0 Hz only: the compass is read from vehicle_magnetometer with its '
               'calibration undone' in str(x) for x in d.meta['warnings'])
    # no CAL_MAGn_ID is the device: the corrected field is read as it is, and both warnings
    # say so (the second said 'with its calibration undone' here too: pyulog's sample log)
    path, _ = _px4_log(tmp_path / 'px4slow2.ulg', raw_rate_hz=1.0,
                       cal_ids={'CAL_MAG0_ID': 1, 'CAL_MAG1_ID': 2})
    warnings = [str(x) for x in read_vehicle_log(path).meta['warnings']]
    assert any('its corrections are not undone' in x for x in warnings), warnings
    assert any('logged at 1.0 Hz only: the compass is read from vehicle_magnetometer as the '
               'autopilot corrected it' in x for x in warnings), warnings
    assert not any('calibration undone' in x for x in warnings), warnings


# -- rosbag2: sensor_msgs/BatteryState ---------------------------------------------------

def test_bag_battery_state_gives_the_vehicle_log_channels(tmp_path):
    """Two BatteryState topics: current and voltage held from each message, NaN left out."""
    from magcal_ros.io.bag import read_bag
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import get_typestore, Stores
    ts = get_typestore(Stores.ROS2_JAZZY)
    mag_t, bat_t = 'sensor_msgs/msg/MagneticField', 'sensor_msgs/msg/BatteryState'
    hdr = ts.types['std_msgs/msg/Header']
    tm = ts.types['builtin_interfaces/msg/Time']
    vec = ts.types['geometry_msgs/msg/Vector3']
    n = 40
    t = 100.0 + np.arange(n) * 0.1

    def header(ns, frame):
        return hdr(stamp=tm(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    path = tmp_path / 'battery'
    with Writer(path, version=9) as w:
        cm = w.add_connection('/magcal/sensor1/raw', mag_t, typestore=ts)
        cb = [w.add_connection(topic, bat_t, typestore=ts) for topic in ('/bat_a', '/bat_b')]
        for k in range(n):
            ns = int(round(t[k] * 1e9))
            w.write(cm, ns, ts.serialize_cdr(ts.types[mag_t](
                header=header(ns, 'imu'), magnetic_field=vec(2e-5, 0.0, 4e-5),
                magnetic_field_covariance=np.zeros(9)), mag_t))
            if k % 4 == 0:                       # 2.5 Hz
                for j, c in enumerate(cb):
                    cur = float('nan') if (j == 0 and k == 8) else 10.0 * (j + 1) + k
                    msg = ts.types[bat_t](
                        header=header(ns, 'battery'), voltage=16.0 - 0.01 * k - j,
                        temperature=25.0, current=cur, charge=1.0, capacity=2.0,
                        design_capacity=2.0, percentage=0.5, power_supply_status=2,
                        power_supply_health=1, power_supply_technology=3, present=True,
                        cell_voltage=np.array([4.0, 4.0, 4.0, 4.0], np.float32),
                        cell_temperature=np.array([], np.float32), location='slot',
                        serial_number='x')
                    w.write(c, ns, ts.serialize_cdr(msg, bat_t))
    d = read_bag(path)
    k = np.arange(n)
    last = (k // 4) * 4                          # the last battery message at or before
    expect_a = 10.0 + last.astype(float)
    expect_a[(last == 8)] = 10.0 + 4            # the NaN message is left out: the one before
    np.testing.assert_allclose(d.aux['aux_battery_current'], expect_a, atol=1e-5)
    np.testing.assert_allclose(d.aux['aux_battery2_current'], 20.0 + last, atol=1e-5)
    np.testing.assert_allclose(d.aux['aux_battery_voltage'], 16.0 - 0.01 * last, atol=1e-5)
    np.testing.assert_allclose(d.aux['aux_battery2_voltage'], 15.0 - 0.01 * last, atol=1e-5)
    assert '/bat_a' in d.meta['topics'] and '/bat_b' in d.meta['topics']


def test_ulog_with_damaged_data_is_read_with_a_warning(tmp_path):
    path, (t, q, cur, raw1, raw2) = _px4_log(tmp_path / 'px4.ulg')
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 200] = bytes(range(200))          # garbage inside the data section
    bad = tmp_path / 'bad.ulg'
    bad.write_bytes(bytes(data))
    d = read_vehicle_log(bad)
    assert any('pyulog found damaged data' in str(x) for x in d.meta['warnings'])
    # what was written before the damage is read exactly
    np.testing.assert_allclose(d.raw[0], raw1[:d.n_samples], atol=0.05)


def test_a_long_log_is_reduced_like_a_long_record(ap_log):
    """Above the reduction threshold: the sample, and a record whose chunks are every epoch."""
    path, (t, q, cur, raw1, raw2) = ap_log
    whole = read_vehicle_log(path)
    sample, rec = cli.load_record(str(path), reduce_above=500)
    assert rec is not None and rec.size == N
    # (the sample keeps at least 20 000 epochs: here all of them)
    assert sample.meta['reduction']['epochs'] == N and sample.n_samples == N
    assert sample.meta['noise_blocks']
    assert sample.meta['igrf']['date'] == '2024-02-08'          # the log's meta kept
    pieces = list(rec.chunks(rows=512))
    assert [p.n_samples for p in pieces] == [512, 512, 176]
    np.testing.assert_array_equal(np.concatenate([p.raw for p in pieces], axis=1), whole.raw)
    dots = np.einsum('ij,ij->i', np.concatenate([p.attitude for p in pieces]), whole.attitude)
    np.testing.assert_allclose(np.abs(dots), 1.0, atol=1e-12)         # q and -q: one rotation
    # the sample's epochs are epochs of the log, with their readings
    idx = np.searchsorted(whole.t, sample.t)
    np.testing.assert_array_equal(sample.raw, whole.raw[:, idx])
