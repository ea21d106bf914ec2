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
PX4 ULog logs (``.ulg``) -> :class:`~.vehicle_base.VehicleLog` (through pyulog).

pyulog reads only the topics of :data:`TOPICS`.  PX4's ``Magnetometer::Correct``
(src/lib/sensor_calibration) gives v = R S ((d + p c) - o) (docs/design.md §1, "Vehicle
logs"), the parameters ``CAL_MAGn_*`` of the slot n whose ``CAL_MAGn_ID`` is the device's.
The compasses are ``sensor_mag`` (r = R d) when logged at :data:`RAW_RATE_HZ` or more, else
``vehicle_magnetometer`` undone by :func:`px4_raw` (a stream that names no device is kept as
corrected, with a warning).  Attitude: ``vehicle_attitude.q``, body (FRD) to NED.
"""
import contextlib
import datetime
import io

from magcal_ros.io.vehicle_base import gps_site, NT_PER_GAUSS, SLOW_RATE_HZ, Stream, \
    ULOG_MAGIC, VehicleLog, VehicleLogError
import numpy as np

TOPICS = ['sensor_mag', 'vehicle_magnetometer', 'sensor_combined', 'vehicle_attitude',
          'battery_status', 'actuator_motors', 'actuator_outputs', 'actuator_controls_0',
          'vehicle_thrust_setpoint', 'sensor_accel', 'sensor_baro', 'vehicle_gps_position',
          'sensor_gps']
#: sensor_mag is the compass stream when logged at least this often, Hz
RAW_RATE_HZ = 5.0
#: PX4's rotation enum (src/lib/conversion/rotation.h): roll, pitch, yaw in deg
ROTATIONS = [
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270),
    (0, 0, 315), (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0),
    (180, 0, 225), (180, 0, 270), (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90),
    (90, 0, 135), (270, 0, 0), (270, 0, 45), (270, 0, 90), (270, 0, 135), (0, 90, 0),
    (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0), (180, 90, 0), (270, 90, 0),
    (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0), (90, 180, 90),
    (90, 0, 270), (90, 68, 293), (0, 315, 0), (90, 315, 0),
]


def rotation_matrix(rot, level_deg=(0.0, 0.0, 0.0)):
    """
    (3, 3) sensor-to-body rotation of PX4's rotation enum ``rot``, times the level adjustment.

    ``level_deg`` (roll, pitch, yaw) deg: SENS_BOARD_{X,Y,Z}_OFF.  PX4's Dcm(Euler(roll,
    pitch, yaw)) is Rz(yaw) Ry(pitch) Rx(roll).
    """
    from scipy.spatial.transform import Rotation
    rot = int(rot)
    if not 0 <= rot < len(ROTATIONS):
        raise VehicleLogError(f"rotation {rot} is not one of PX4's 0..{len(ROTATIONS) - 1}")
    r, p, y = ROTATIONS[rot]
    m = np.round(Rotation.from_euler('ZYX', [y, p, r], degrees=True).as_matrix(), 12)
    lr, lp, ly = level_deg
    return Rotation.from_euler('ZYX', [ly, lp, lr], degrees=True).as_matrix() @ m


def px4_raw(v, rot, scale, offset, comp=None, power=None):
    """
    Return the raw body-frame reading r = R d from PX4's corrected v = R S ((d + p c) - o).

    ``v`` (N, 3) any unit, ``offset`` o and ``comp`` c (3,) in it (c per unit of power),
    ``rot`` (3, 3) R, ``scale`` (3, 3) S, ``power`` (N,) p or None.
    """
    v = np.asarray(v, float)
    d = np.linalg.solve(np.asarray(scale, float), (v @ np.asarray(rot, float)).T).T \
        + np.asarray(offset, float)
    if comp is not None and power is not None:
        d = d - np.asarray(power, float)[:, None] * np.asarray(comp, float)
    return d @ np.asarray(rot, float).T


def read_ulog(path):
    """Read a PX4 ULog log into a :class:`VehicleLog`."""
    with open(path, 'rb') as fh:
        head = fh.read(16)
    if len(head) < 16 or head[:7] != ULOG_MAGIC:
        raise VehicleLogError(f"{path}: not a ULog file (its header is not ULog's): the file "
                              'is damaged or not a PX4 log; download it again')
    if head[7] > 1:
        raise VehicleLogError(f'{path}: ULog file version {head[7]}: only versions 0 and 1 are '
                              'supported (update pyulog and magcal_ros, or convert the log)')
    from pyulog import ULog
    try:
        with contextlib.redirect_stdout(io.StringIO()):          # pyulog's own prints
            u = ULog(path, message_name_filter_list=TOPICS)
    except Exception as exc:            # pyulog raises its own and struct errors
        raise VehicleLogError(f'{path}: cannot read this ULog ({type(exc).__name__}: {exc}): '
                              'the file is damaged; download it again') from None
    out = VehicleLog('PX4 ULog')
    if u.file_corruption:
        out.warnings.append(f'{path}: pyulog found damaged data in the log; what could be '
                            'read is used')
    info = u.msg_info_dict
    if info.get('ver_sw'):
        out.info['firmware'] = f"PX4 {info.get('ver_sw_release', '')} {info['ver_sw']}".strip()
    if info.get('sys_name') or info.get('ver_hw'):
        out.info['vehicle'] = ' '.join(str(info[k]) for k in ('sys_name', 'ver_hw')
                                       if info.get(k))
    topics = {}
    for d in u.data_list:
        topics.setdefault(d.name, {})[d.multi_id] = d.data
    params = dict(u.initial_parameters)
    _compasses(path, topics, params, out)
    att = topics.get('vehicle_attitude', {}).get(0)
    if att is not None and len(att['timestamp']):
        q = np.column_stack([att[f'q[{i}]'] for i in range(4)])
        out.attitude = Stream(att['timestamp'] * 1e-6, q, 'vehicle_attitude.q')
        out.attitude_source = 'PX4 vehicle_attitude (EKF2)'
    _gps(topics, out)
    _aux(topics, out)
    return out


def _rate(d):
    t = d['timestamp']
    return (len(t) - 1) / ((t[-1] - t[0]) * 1e-6) if len(t) > 1 and t[-1] > t[0] else 0.0


def _calibration(params, device_id):
    """{slot, R, S (3, 3), o, c (3,) gauss, rotation, internal} of a device, or None."""
    slot = next((n for n in range(8) if device_id
                 and int(params.get(f'CAL_MAG{n}_ID', 0)) == int(device_id)), None)
    if slot is None:
        return None
    p = f'CAL_MAG{slot}_'
    rot = int(params.get(p + 'ROT', -1))
    level = tuple(float(params.get(f'SENS_BOARD_{a}_OFF', 0.0)) for a in 'XYZ')
    internal = rot < 0
    rot_enum = int(params.get('SENS_BOARD_ROT', 0)) if internal else rot
    r = rotation_matrix(rot_enum, level)

    def vec(key, default):
        return np.array([float(params.get(p + f'{a}{key}', default)) for a in 'XYZ'])
    dg, od = vec('SCALE', 1.0), vec('ODIAG', 0.0)
    s = np.array([[dg[0], od[0], od[1]], [od[0], dg[1], od[2]], [od[1], od[2], dg[2]]])
    return {'slot': slot, 'R': r, 'S': s, 'o': vec('OFF', 0.0), 'c': vec('COMP', 0.0),
            'rotation': rot_enum, 'internal': internal}


def _onboard(j, device_id, cal, params):
    out = {'compass': j, 'autopilot': 'PX4',
           'device_id': None if device_id is None else int(device_id)}
    if cal is None:
        out['calibration'] = 'none found (no CAL_MAGn_ID is this device)'
        return out
    typ = int(params.get('CAL_MAG_COMP_TYP', 0))
    out.update({
        'calibration_slot': cal['slot'], 'external': not cal['internal'],
        'rotation': cal['rotation'], 'rotation_matrix': cal['R'].tolist(),
        'offsets_nt': (cal['o'] * NT_PER_GAUSS).tolist(),
        'scale_matrix': cal['S'].tolist(),
        'power_compensation': {
            'type': {0: 'none', 1: 'throttle', 2: 'current (battery 0)',
                     3: 'current (battery 1)'}.get(typ, f'unknown ({typ})'),
            'vector_nt_per_unit': (cal['c'] * NT_PER_GAUSS).tolist(),
            'unit': {1: 'nT per unit throttle (0..1)'}.get(typ, 'nT per kA')}})
    return out


def _power(topics, params, t):
    """(N,) PX4's compensation power at times ``t`` s (CAL_MAG_COMP_TYP), or None."""
    typ = int(params.get('CAL_MAG_COMP_TYP', 0))
    if typ == 1:
        ac = topics.get('actuator_controls_0', {}).get(0)
        if ac is not None and len(ac['timestamp']):
            return np.interp(t, ac['timestamp'] * 1e-6, ac['control[3]'])
    elif typ in (2, 3):
        bat = topics.get('battery_status', {}).get(typ - 2)
        if bat is not None and len(bat['timestamp']):
            return np.interp(t, bat['timestamp'] * 1e-6, bat['current_a']) * 1e-3
    return None


def _device(d):
    """Return the device id of a topic's data, or None."""
    return int(d['device_id'][0]) if 'device_id' in d and len(d['device_id']) else None


def _compasses(path, topics, params, out):
    raw = topics.get('sensor_mag', {})
    if raw and _rate(raw[min(raw)]) >= RAW_RATE_HZ:
        for j, k in enumerate(sorted(raw), start=1):
            d = raw[k]
            dev = _device(d)
            cal = _calibration(params, dev)
            r = cal['R'] if cal is not None else np.eye(3)
            if cal is None:
                out.warnings.append(f'compass {j} (sensor_mag instance {k}, device {dev}): no '
                                    'CAL_MAGn_ID is this device: its axes are taken as the '
                                    "body's")
            v = np.column_stack([d['x'], d['y'], d['z']]) @ r.T * NT_PER_GAUSS
            t = d['timestamp'] * 1e-6
            out.compasses.append(Stream(t, v, f'sensor_mag instance {k}'))
            out.compass_temps.append(Stream(t, d['temperature'], 'sensor_mag.temperature')
                                     if 'temperature' in d else None)
            out.onboard.append(_onboard(j, dev, cal, params))
        return
    corrected = topics.get('vehicle_magnetometer') or {}
    name = 'vehicle_magnetometer'
    if not corrected and 0 in topics.get('sensor_combined', {}) and \
            'magnetometer_ga[0]' in topics['sensor_combined'][0]:
        sc = topics['sensor_combined'][0]
        t0 = sc['timestamp'] + sc.get('magnetometer_timestamp_relative', 0)
        corrected = {0: {**sc, 'timestamp': t0}}
        name = 'sensor_combined'
    undone = []
    for j, k in enumerate(sorted(corrected), start=1):
        d = corrected[k]
        dev = _device(d)
        if dev is None and len(raw) == 1:
            dev = _device(raw[min(raw)])
        cal = _calibration(params, dev)
        undone.append(cal is not None)
        t = d['timestamp'] * 1e-6
        v = np.column_stack([d[f'magnetometer_ga[{i}]'] for i in range(3)])
        if cal is None:
            out.warnings.append(f"compass {j} ({name} instance {k}): the autopilot's corrected "
                                'field, whose calibration is not matched to a device in the '
                                'log: its corrections are not undone')
            r = v
        else:
            power = _power(topics, params, t)
            if np.any(cal['c'] != 0) and power is None:
                out.warnings.append(f'compass {j}: power compensation is on but its signal '
                                    'is not in the log: it is not undone')
            r = px4_raw(v, cal['R'], cal['S'], cal['o'], cal['c'], power)
        out.compasses.append(Stream(t, r * NT_PER_GAUSS, f'{name} instance {k}'))
        out.compass_temps.append(None)
        out.onboard.append(_onboard(j, dev, cal, params))
    if raw and corrected:
        how = ('with its calibration undone' if all(undone) else
               'as the autopilot corrected it' if not any(undone) else
               'with the calibrations undone where the log holds them')
        out.warnings.append(f'{path}: sensor_mag (raw) is logged at {_rate(raw[min(raw)]):.1f} '
                            f'Hz only: the compass is read from {name} {how} (log sensor_mag '
                            'faster: SDLOG_PROFILE "high rate" or the logger topics file)')


def _gps(topics, out):
    for name in ('vehicle_gps_position', 'sensor_gps'):
        d = topics.get(name, {}).get(0)
        if d is None or not len(d['timestamp']):
            continue
        good = d['fix_type'] >= 3 if 'fix_type' in d else np.ones(len(d['timestamp']), bool)
        if not good.any():
            continue
        if 'latitude_deg' in d:
            lat, lon, alt = d['latitude_deg'], d['longitude_deg'], d['altitude_msl_m']
        else:
            lat, lon, alt = d['lat'] * 1e-7, d['lon'] * 1e-7, d['alt'] * 1e-3
        utc = d.get('time_utc_usec', np.zeros(len(lat)))
        dates = [datetime.datetime.fromtimestamp(u * 1e-6, datetime.timezone.utc)
                 .strftime('%Y-%m-%d') if u > 0 else '' for u in utc[good]]
        out.gps = gps_site(lat[good], lon[good], alt[good], dates)
        return


def _aux(topics, out):
    for k, d in sorted(topics.get('battery_status', {}).items()):
        tag = 'battery' if k == 0 else f'battery{k + 1}'
        t = d['timestamp'] * 1e-6
        out.add_aux(f'aux_{tag}_current', t, d['current_a'], 'A', f'battery_status[{k}]')
        out.add_aux(f'aux_{tag}_voltage', t, d['voltage_v'], 'V', f'battery_status[{k}]')
        if 'temperature' in d and np.any(np.isfinite(d['temperature'])):
            out.add_aux(f'aux_{tag}_temp', t, d['temperature'], 'degC', f'battery_status[{k}]')
    ac = topics.get('actuator_controls_0', {}).get(0)
    th = topics.get('vehicle_thrust_setpoint', {}).get(0)
    if ac is not None and 'control[3]' in ac:
        out.add_aux('aux_throttle', ac['timestamp'] * 1e-6, ac['control[3]'], '0..1',
                    'actuator_controls_0.control[3]')
    elif th is not None:
        norm = np.linalg.norm(np.column_stack([th[f'xyz[{i}]'] for i in range(3)]), axis=1)
        out.add_aux('aux_throttle', th['timestamp'] * 1e-6, norm, '0..1',
                    '|vehicle_thrust_setpoint.xyz|')
    motors = topics.get('actuator_motors', {}).get(0)
    if motors is not None:
        for i in range(16):
            col = f'control[{i}]'
            if col in motors and np.isfinite(motors[col]).any():
                out.add_aux(f'aux_motor{i + 1}', motors['timestamp'] * 1e-6, motors[col],
                            '0..1', f'actuator_motors.{col}')
    else:
        ao = topics.get('actuator_outputs', {}).get(0)
        if ao is not None and len(ao['timestamp']):
            n = int(np.max(ao.get('noutputs', [0])))
            for i in range(n):
                col = f'output[{i}]'
                if col in ao:
                    out.add_aux(f'aux_output{i + 1}', ao['timestamp'] * 1e-6, ao[col],
                                'PWM us', f'actuator_outputs.{col}')
    for topic, tag in (('sensor_accel', 'imu'), ('sensor_baro', 'baro')):
        for k, d in sorted(topics.get(topic, {}).items()):
            s = slice(None, None, max(1, int(_rate(d) / SLOW_RATE_HZ)))  # ~SLOW_RATE_HZ
            out.add_aux(f'aux_{tag}_temp' if k == 0 else f'aux_{tag}{k + 1}_temp',
                        d['timestamp'][s] * 1e-6, d['temperature'][s], 'degC',
                        f'{topic}[{k}].temperature')
