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
Reading a long vehicle log: an hour of an ArduPilot DataFlash and a PX4 ULog log.

    python bench/vehicle_logs.py [--minutes 60] [--mag-rate 100] [--formats dataflash ulog]

Writes a synthetic log (test/vehicle_log_writers.py) as an autopilot would fill it: three
compasses at ``--mag-rate`` Hz, the attitude at the same rate, ATT, CTUN, RCOU at 50 Hz,
the battery at 10 Hz, GPS at 5 Hz, two IMUs at 400 Hz and a 400 Hz message nothing reads
(DataFlash: PIDR), in blocks of a minute; PX4: sensor_mag x3, vehicle_attitude,
battery_status, actuator_motors, sensor_gps, sensor_accel at 400 Hz and sensor_combined
(unread) at 400 Hz.  Then measures, each in a process of its own (bench/peak_rss.py: wall,
CPU, peak RSS), the reading alone (magcal_ros.io.vehicle.read_vehicle_log) and ``magcal fit
LOG --json`` (IGRF from the log's GPS; the hour is reduced as a long record is).  Requirement
(issue 31): an hour at the autopilot's compass rate in well under a minute, within 1 GB.
"""
import argparse
import json
import os
import sys
import tempfile
import time

BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(BENCH_DIR), 'test'))
from common import add_common_args, REPO_DIR, table, write_result  # noqa: E402
import numpy as np  # noqa: E402
from scale import rusage_of  # noqa: E402
import vehicle_log_writers as w  # noqa: E402

LAT, LON, ALT_M = 47.3977, 8.5456, 488.0
FIELD_NED = np.array([21500.0, 300.0, 43000.0])


def _block(t, seed):
    """Attitudes (n, 4) turning through every attitude, the raw fields of 3 compasses (nT)."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(seed)
    yaw = 0.3 * t
    roll = 0.9 * np.sin(0.11 * t)
    pitch = 1.2 * np.sin(0.07 * t + 1.0)
    rot = Rotation.from_euler('ZYX', np.column_stack([yaw, pitch, roll]))
    b = rot.inv().apply(FIELD_NED)
    raws = [b + off + rng.normal(0, 30, b.shape) for off in
            ([3000.0, -2000.0, 1500.0], [-800.0, 600.0, -1200.0], [200.0, 100.0, -300.0])]
    return rot.as_quat(scalar_first=True), raws


def write_dataflash(path, minutes, rate):
    """Write the hour of DataFlash; return the file size in bytes."""
    formats = dict(w.AP4)
    formats['PIDR'] = ('Qffffff', 'TimeUS,Des,P,I,D,FF,AFF')
    with open(path, 'wb') as fh:
        df = w.DataFlash(formats)
        df.write('MSG', TimeUS=[500], Message=['ArduCopter V4.5.1 (deadbeef)'])
        df.params({'AHRS_EKF_TYPE': 3, 'COMPASS_MOTCT': 2, 'COMPASS_OFS_X': -30.0,
                   'COMPASS_DIA_X': 1.02, 'COMPASS_DIA_Y': 0.98, 'COMPASS_DIA_Z': 1.0,
                   'COMPASS_MOT_X': 2.0, 'SERVO1_FUNCTION': 33, 'SERVO2_FUNCTION': 34,
                   'SERVO3_FUNCTION': 35, 'SERVO4_FUNCTION': 36})
        for m in range(minutes):
            t = 10.0 + 60.0 * m + np.arange(int(60 * rate)) / rate
            us = np.round(t * 1e6)
            q, raws = _block(t, m)
            n = len(t)
            for k, raw in enumerate(raws):
                f = np.round(raw / 100.0)
                z = np.zeros(n)
                df.write('MAG', TimeUS=us, I=z + k, MagX=f[:, 0], MagY=f[:, 1], MagZ=f[:, 2],
                         OfsX=z, OfsY=z, OfsZ=z, MOX=z, MOY=z, MOZ=z, Health=z + 1)
            df.write('XKQ', TimeUS=us, C=np.zeros(n), Q1=q[:, 0], Q2=q[:, 1], Q3=q[:, 2],
                     Q4=q[:, 3])
            t50 = 10.0 + 60.0 * m + np.arange(3000) / 50.0
            u50 = np.round(t50 * 1e6)
            from scipy.spatial.transform import Rotation
            yaw, pitch, roll = Rotation.from_quat(q[::int(rate // 50)], scalar_first=True) \
                .as_euler('ZYX', degrees=True).T
            df.write('ATT', TimeUS=u50, Roll=roll, Pitch=pitch, Yaw=np.mod(yaw, 360.0))
            df.write('CTUN', TimeUS=u50, ThO=np.full(3000, 0.4))
            outputs = {f'C{c}': np.full(3000, 1500) for c in range(1, 15)}
            df.write('RCOU', TimeUS=u50, **outputs)
            t10 = t50[::5]
            df.write('BAT', TimeUS=np.round(t10 * 1e6), Inst=np.zeros(600), Volt=16.0 +
                     0 * t10, Curr=10.0 + np.sin(t10))
            g = t50[::10]
            df.write('GPS', TimeUS=np.round(g * 1e6), I=np.zeros(300), Status=np.full(300, 3),
                     GMS=np.full(300, 1000), GWk=np.full(300, 2300), Lat=np.full(300, LAT),
                     Lng=np.full(300, LON), Alt=np.full(300, ALT_M))
            t400 = 10.0 + 60.0 * m + np.arange(24000) / 400.0
            u400 = np.round(t400 * 1e6)
            for k in range(2):
                df.write('IMU', TimeUS=u400, I=np.full(24000, k), T=40.0 + 0 * t400)
            df.write('PIDR', TimeUS=u400, Des=np.zeros(24000))
            fh.write(bytes(df.buf))
            df.buf = bytearray()
        return fh.tell()


def write_ulog(path, minutes, rate):
    """Write the hour of ULog; return the file size in bytes."""
    u = w.ULog()
    for name, fields in (('sensor_mag', w.SENSOR_MAG), ('vehicle_attitude', w.VEHICLE_ATTITUDE),
                         ('battery_status', w.BATTERY_STATUS),
                         ('actuator_motors', w.ACTUATOR_MOTORS), ('sensor_gps', w.SENSOR_GPS),
                         ('sensor_accel', [('uint64_t', 'timestamp'), ('float', 'x'),
                                           ('float', 'y'), ('float', 'z'),
                                           ('float', 'temperature')]),
                         ('sensor_combined', [('uint64_t', 'timestamp'),
                                              ('float[3]', 'gyro_rad'),
                                              ('float[3]', 'accelerometer_m_s2')])):
        u.topic(name, fields)
    for k, dev in enumerate((396825, 12345, 67890)):
        u.param(f'CAL_MAG{k}_ID', dev)
        u.param(f'CAL_MAG{k}_ROT', -1 if k == 0 else 0)
    with open(path, 'wb') as fh:
        for m in range(minutes):
            t = 10.0 + 60.0 * m + np.arange(int(60 * rate)) / rate
            us = np.round(t * 1e6).astype(np.int64)
            q, raws = _block(t, m)
            n = len(t)
            for k, (raw, dev) in enumerate(zip(raws, (396825, 12345, 67890))):
                d = raw / 1e5
                u.data('sensor_mag', k, timestamp=us, timestamp_sample=us,
                       device_id=np.full(n, dev), x=d[:, 0], y=d[:, 1], z=d[:, 2],
                       temperature=np.full(n, 30.0))
            u.data('vehicle_attitude', 0, timestamp=us, timestamp_sample=us, q=q)
            t10 = 10.0 + 60.0 * m + np.arange(600) / 10.0
            u10 = np.round(t10 * 1e6).astype(np.int64)
            u.data('battery_status', 0, timestamp=u10, voltage_v=np.full(600, 16.0),
                   current_a=10.0 + np.sin(t10), temperature=np.full(600, np.nan))
            t50 = 10.0 + 60.0 * m + np.arange(3000) / 50.0
            u.data('actuator_motors', 0, timestamp=np.round(t50 * 1e6).astype(np.int64),
                   control=np.full((3000, 4), 0.5))
            g = np.round(t50[::10] * 1e6).astype(np.int64)
            u.data('sensor_gps', 0, timestamp=g, latitude_deg=np.full(300, LAT),
                   longitude_deg=np.full(300, LON), altitude_msl_m=np.full(300, ALT_M),
                   time_utc_usec=np.full(300, 1_700_000_000_000_000), fix_type=np.full(300, 3))
            t400 = 10.0 + 60.0 * m + np.arange(24000) / 400.0
            u400 = np.round(t400 * 1e6).astype(np.int64)
            u.data('sensor_accel', 0, timestamp=u400, temperature=np.full(24000, 40.0))
            u.data('sensor_combined', 0, timestamp=u400)
            if m == 0:
                fh.write(u.header + bytes(u.defs))
            fh.write(bytes(u.body))
            u.body = bytearray()
        return fh.tell()


def read_only(path):
    """Read the log alone (in the measured process); print the epochs, sensors, channels."""
    from magcal_ros.io.vehicle import read_vehicle_log
    t0 = time.perf_counter()
    d = read_vehicle_log(path)
    print(json.dumps({'read_s': time.perf_counter() - t0, 'epochs': int(d.n_samples),
                      'sensors': int(d.n_sensors), 'channels': len(d.aux),
                      'attitude': d.attitude is not None}))


def main():
    """Write the logs, measure reading and fitting them, write the JSON and the table."""
    p = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[1]))
    p.add_argument('--minutes', type=int, default=60)
    p.add_argument('--mag-rate', type=float, default=100.0, help='compass rate, Hz')
    p.add_argument('--formats', nargs='+', default=['dataflash', 'ulog'])
    p.add_argument('--no-fit', action='store_true', help='measure the reading only')
    p.add_argument('--read', help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.read:
        return read_only(args.read)
    started = time.perf_counter()
    rows, results = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in args.formats:
            path = os.path.join(tmp, 'hour.bin' if fmt == 'dataflash' else 'hour.ulg')
            t0 = time.perf_counter()
            size = (write_dataflash if fmt == 'dataflash' else write_ulog)(
                path, args.minutes, args.mag_rate)
            write_s = time.perf_counter() - t0
            wall, cpu, rss, rc, out, load = rusage_of(
                [sys.executable, os.path.join(BENCH_DIR, 'vehicle_logs.py'), '--read', path],
                REPO_DIR)
            info = json.loads(out.strip().splitlines()[-1]) if rc == 0 else {}
            res = {'format': fmt, 'minutes': args.minutes, 'mag_rate_hz': args.mag_rate,
                   'file_mb': size / 1e6, 'write_s': write_s, 'read_wall_s': wall,
                   'read_cpu_s': cpu, 'read_peak_rss_mb': rss, 'read_exit': rc, **info,
                   **load}
            if not args.no_fit:
                wall, cpu, rss, rc, out, _ = rusage_of(
                    [sys.executable, '-m', 'magcal_ros.cli', 'fit', path, '--json', '-q'],
                    REPO_DIR)
                doc = json.loads(out) if rc == 0 and out.strip() else {}
                res.update({'fit_wall_s': wall, 'fit_cpu_s': cpu, 'fit_peak_rss_mb': rss,
                            'fit_exit': rc,
                            'fit_scalar_rms_nt': doc.get('scalar_rms_nt'),
                            'fit_field_reference': (doc.get('field_reference') or {}).get(
                                'kind')})
            results.append(res)
            rows.append([fmt, f'{args.minutes} min', f'{res["file_mb"]:.0f}',
                         res.get('epochs'), res['read_wall_s'], res['read_cpu_s'],
                         f'{res["read_peak_rss_mb"]:.0f}', res.get('fit_wall_s'),
                         res.get('fit_cpu_s'),
                         None if args.no_fit else f'{res["fit_peak_rss_mb"]:.0f}'])
    tables = [table(['format', 'length', 'file MB', 'epochs', 'read wall s', 'read CPU s',
                     'read peak MB', 'fit wall s', 'fit CPU s', 'fit peak MB'], rows,
                    title=f'Vehicle logs: 3 compasses at {args.mag_rate:g} Hz')]
    print(tables[0])
    write_result('vehicle_logs', vars(args), {'runs': results}, tables, args.out_dir,
                 started)


if __name__ == '__main__':
    main()
