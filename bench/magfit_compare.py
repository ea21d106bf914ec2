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
MAGFit against magcal_ros on the same vehicle logs, side by side (issue 31 item 4).

    python bench/magfit_compare.py LOG.bin [LOG.bin ...]
    python bench/magfit_compare.py LOG.bin --condition 'MAG.TimeMS<220000' --att-source ATT
    python bench/magfit_compare.py LOG.bin --magfit-options none,elliptical   # fewer runs

MAGFit is pymavlink's ``tools/magfit_WMM.py`` from the *installed* pymavlink package (no
copy of it here): each option set runs in its own Python process (:func:`_magfit_child`,
headless: ``MPLBACKEND=Agg``, no ``--save-plot``), which executes the module's code
unmodified and then hands back what it worked on (its samples after it undid the log's
calibration, its attitude, its earth field) and what it found (the SLSQP result, recorded by
wrapping ``scipy.optimize.fmin_slsqp``).  Option sets: offsets+scale, ``--elliptical``, each
with ``--cmot`` (battery current) and ``--cmot-throttle``; MAGFit's "best" is the one with the
lowest MAGFit error among the runs that exit 0.

magcal_ros runs ``python -m magcal_ros.cli fit INPUT --json`` (and ``diagnose --json``) on the
same samples: INPUT is the log itself when this tree can read vehicle logs
(``magcal_ros.io.vehicle``), else a wide CSV (docs/design.md §1) the bench writes from
MAGFit's own samples (raw in nT, ``att_q*`` from MAGFit's attitude, ``aux_battery_current``,
``aux_throttle``) -- which is said in the JSON (``magcal_input``).

Every calibration (the log's own, each MAGFit fit, each magcal fit) is then scored on the
same samples by

- MAGFit's own error: the mean over samples of |R(roll, pitch, yaw_mag)^T m - c| in mG, c the
  corrected field, yaw_mag the heading of c tilt-compensated with the log's roll and pitch,
  m pymavlink's table WMM at the log's first GPS fix (:func:`magfit_error`, the formula of
  magfit_WMM.py's ``wmm_error``/``get_yaw``/``expected_field`` in a few vectorised lines;
  checked here against the module's own ``wmm_error`` at MAGFit's fitted parameters);
- magcal_ros's: the RMS of |c| - F and the RMS of |c - R^T m| (nT), R the log's whole
  attitude (yaw included), m the IGRF (ppigrf) at the log's GPS position and date;
- and the heading of c (MAGFit's tilt-compensated one) minus the log's yaw (median and
  quartiles, deg): where the autopilot's heading does not follow the compass, the vector
  RMS measures that disagreement, not the calibration.

Units: MAGFit works in milligauss (1 mG = 100 nT).  The parameters, the time of each tool
(wall time of its process) and whether a MAGFit parameter ended on its bound are written to
``bench/results/magfit_compare.json``.
"""
import argparse
import datetime
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
import numpy as np  # noqa: E402

MG_NT = 100.0  # nT per milligauss
#: MAGFit option sets: name -> magfit_WMM arguments
MAGFIT_OPTIONS = {
    'offsets+scale': [],
    'elliptical': ['--elliptical'],
    'cmot': ['--cmot'],
    'elliptical+cmot': ['--elliptical', '--cmot'],
    'cmot-throttle': ['--cmot-throttle'],
    'elliptical+cmot-throttle': ['--elliptical', '--cmot-throttle'],
}
#: magfit_WMM's default bounds (its argparse defaults), for the "on a bound" flags
MAGFIT_MODULE = 'pymavlink.tools.magfit_WMM'
GPS_EPOCH = datetime.datetime(1980, 1, 6)
#: per-log MAGFit arguments of the known public logs, by the file's sha256 (PROVENANCE
#: of each in the data folder): dronekit-la-testdata's log171.bin (Copter 3.3 has no
#: AHRS_EKF_TYPE; it crashes after 220 s: the flight before the crash)
LOG_PRESETS = {
    'a4a3883fa13f28d55878c041cb4cc14deb3e5335aad6b9091f235c9b4e0d95f0':
        ['--att-source', 'ATT', '--condition', 'MAG.TimeMS<220000'],
}


# -- MAGFit's error, re-implemented (pymavlink tools/magfit_WMM.py) ------------------------

def euler_dcm(roll_deg, pitch_deg, yaw_deg):
    """
    (N, 3, 3) body-to-NED rotation matrices from Euler angles in degrees (ZYX).

    What pymavlink's ``Matrix3.from_euler(roll, pitch, yaw)`` builds (rotmat.py).
    """
    r, p, y = (np.radians(np.asarray(a, float)) for a in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    out = np.empty(r.shape + (3, 3))
    out[..., 0, 0] = cp * cy
    out[..., 0, 1] = sr * sp * cy - cr * sy
    out[..., 0, 2] = cr * sp * cy + sr * sy
    out[..., 1, 0] = cp * sy
    out[..., 1, 1] = sr * sp * sy + cr * cy
    out[..., 1, 2] = cr * sp * sy - sr * cy
    out[..., 2, 0] = -sp
    out[..., 2, 1] = sr * cp
    out[..., 2, 2] = cr * cp
    return out


def magfit_yaw(corrected, roll_deg, pitch_deg, declination_deg):
    """
    (N,) deg: magfit_WMM's ``get_yaw``: the tilt-compensated heading of the corrected field.

    corrected (N, 3) any unit, body frame; roll, pitch (N,) deg; declination deg.
    """
    c = euler_dcm(roll_deg, pitch_deg, np.zeros_like(np.asarray(roll_deg, float)))[:, 2, :]
    m = np.asarray(corrected, float)
    head_y = m[:, 1] * c[:, 2] - m[:, 2] * c[:, 1]
    head_x = m[:, 0] * (1.0 - c[:, 0] ** 2) - c[:, 0] * (m[:, 1] * c[:, 1] + m[:, 2] * c[:, 2])
    return np.degrees(np.arctan2(-head_y, head_x)) + declination_deg


def magfit_error(corrected_mg, roll_deg, pitch_deg, earth_mg, declination_deg):
    """
    Return MAGFit's error of a calibration: mean |R(roll, pitch, yaw_mag)^T m - c|, mG.

    corrected_mg (N, 3) mG, body frame; roll, pitch (N,) deg (with AHRS_TRIM added, as
    magfit_WMM does); earth_mg (3,) NED mG; declination deg.  The loop of magfit_WMM.py's
    ``wmm_error`` (``get_yaw``, ``expected_field``), vectorised.
    """
    yaw = magfit_yaw(corrected_mg, roll_deg, pitch_deg, declination_deg)
    rot = euler_dcm(roll_deg, pitch_deg, yaw)
    expected = np.einsum('nji,j->ni', rot, np.asarray(earth_mg, float))
    return float(np.mean(np.linalg.norm(expected - corrected_mg, axis=1)))


def magfit_correct(raw_mg, offsets, scale, diag, offdiag, cmot, motor):
    """
    (N, 3) mG: magfit_WMM's ``correct``: S ((raw + offsets) scale) + cmot * motor.

    S the symmetric matrix of diag (3,) and offdiag (xy, xz, yz); motor (N,) the current
    (A) or throttle, NaN where the log has none (no compensation there, as in MAGFit).
    """
    s = np.array([[diag[0], offdiag[0], offdiag[1]],
                  [offdiag[0], diag[1], offdiag[2]],
                  [offdiag[1], offdiag[2], diag[2]]], float)
    out = ((np.asarray(raw_mg, float) + offsets) * scale) @ s.T
    motor = np.nan_to_num(np.asarray(motor, float), nan=0.0)
    return out + motor[:, None] * np.asarray(cmot, float)[None, :]


def unpack_p(p, elliptical, cmot):
    """Split MAGFit's parameter vector (offsets, scale, [diag, offdiag], [cmot]) into a dict."""
    p = list(map(float, p))
    out = {'offsets': p[0:3], 'scale': p[3], 'diag': [1.0, 1.0, 1.0],
           'offdiag': [0.0, 0.0, 0.0], 'cmot': [0.0, 0.0, 0.0]}
    k = 4
    if elliptical:
        out['diag'], out['offdiag'] = p[4:7], p[7:10]
        k = 10
    if cmot:
        out['cmot'] = p[k:k + 3]
    return out


# -- the MAGFit child process ------------------------------------------------------------

def _magfit_child(out_npz, magfit_argv):
    """
    Run the installed magfit_WMM with ``magfit_argv``, save what it used and found.

    Executes the module's code object as ``__main__`` in a dict we keep (so that its
    samples are still there after it exits, even by ``sys.exit``).
    """
    import importlib.util
    import io
    import contextlib
    os.environ['MPLBACKEND'] = 'Agg'
    import matplotlib
    matplotlib.use('Agg')
    import scipy.optimize
    record = {}
    slsqp = scipy.optimize.fmin_slsqp

    def recorded(*a, **k):
        t0 = time.perf_counter()
        res = slsqp(*a, **k)
        record['slsqp_s'] = time.perf_counter() - t0
        record['result'] = res
        record['start'] = np.array(a[1], float)
        record['bounds'] = k.get('bounds')
        return res
    scipy.optimize.fmin_slsqp = recorded
    spec = importlib.util.find_spec(MAGFIT_MODULE)
    code = spec.loader.get_code(MAGFIT_MODULE)
    g = {'__name__': '__main__', '__file__': spec.origin, '__builtins__': __builtins__}
    sys.argv = [spec.origin] + list(magfit_argv)
    stdout = io.StringIO()
    exit_code = 0
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(stdout):
        try:
            exec(code, g)
        except SystemExit as exc:
            exit_code = exc.code if isinstance(exc.code, int) else 1
    wall = time.perf_counter() - t0
    data = g.get('data') or []
    args = g['args']
    info = {'argv': list(magfit_argv), 'exit_code': exit_code, 'run_s': wall,
            'slsqp_s': record.get('slsqp_s'),
            'stdout': [ln for ln in stdout.getvalue().splitlines() if ln.startswith((
                'Attitude source', 'Earth field', 'Extracted', 'Current:', 'New:',
                'Fit failed', 'Optimization', '            '))],
            'pymavlink_file': spec.origin, 'n': len(data)}
    arrays = {}
    if data:
        def num(msg, field):
            v = getattr(msg, field, None) if msg is not None else None
            return np.nan if v is None else float(v)
        mag = [d[0] for d in data]
        att = [d[1] for d in data]
        arrays['t'] = np.array([m.TimeUS * 1e-6 if hasattr(m, 'TimeUS') else m.TimeMS * 1e-3
                                for m in mag])
        arrays['raw_mg'] = np.array([[m.MagX, m.MagY, m.MagZ] for m in mag], float)
        arrays['rpy_deg'] = np.array([[a.Roll, a.Pitch, a.Yaw] for a in att], float)
        arrays['bat_curr'] = np.array([num(d[2], 'Curr') for d in data])
        arrays['ctun_tho'] = np.array([num(d[3], 'ThO') for d in data])
        ef = g['earth_field']
        arrays['earth_mg'] = np.array([ef.x, ef.y, ef.z], float)
        info['declination_deg'] = float(g['declination'])
        old = g['old_corrections']
        info['log_calibration'] = {
            'offsets': [old.offsets.x, old.offsets.y, old.offsets.z], 'scale': old.scaling,
            'diag': [old.diag.x, old.diag.y, old.diag.z],
            'offdiag': [old.offdiag.x, old.offdiag.y, old.offdiag.z],
            'cmot': [old.cmot.x, old.cmot.y, old.cmot.z], 'cmot_mode': int(old.cmot_mode)}
    if 'result' in record:
        p, err, iters, imode, smode = record['result']
        info.update(p=[float(x) for x in p], slsqp_error_mg=float(err), iterations=int(iters),
                    exit_mode=int(imode), exit_message=str(smode),
                    bounds=[list(map(float, b)) for b in record['bounds']])
        # the module's own error function at its own solution: the reference that
        # magfit_error() must reproduce
        info['module_error_mg'] = float(g['wmm_error'](p))
        info['p0'] = record['start'].tolist()
        info['module_error_at_start_mg'] = float(g['wmm_error'](record['start']))
    info['options'] = {'elliptical': bool(args.elliptical), 'cmot': bool(args.cmot),
                       'cmot_throttle': bool(args.cmot_throttle)}
    np.savez(out_npz, info=json.dumps(info), **arrays)


def run_magfit(log, options, extra, workdir, tag='run'):
    """Run MAGFit once in its own process (its samples go to WORKDIR/magfit-TAG.npz)."""
    out = os.path.join(workdir, f'magfit-{tag}.npz')
    cmd = [sys.executable, os.path.abspath(__file__), '--magfit-child', out, '--'] \
        + options + extra + [log]
    env = dict(os.environ, MPLBACKEND='Agg')
    t0 = time.perf_counter()
    # common.popen: the child cannot outlive the benchmark (parent-death signal)
    with common.popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                      env=env) as child:
        _, stderr = child.communicate()
    proc = subprocess.CompletedProcess(cmd, child.returncode, '', stderr)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not os.path.exists(out):
        raise RuntimeError(f'MAGFit child failed on {log} {options}: '
                           f'{proc.stderr.strip().splitlines()[-1:]}')
    z = np.load(out)
    info = json.loads(str(z['info']))
    info['wall_s'] = wall
    return info, {k: z[k] for k in z.files if k != 'info'}


def on_bounds(info, tol=1e-6):
    """Names of MAGFit's parameters that ended on a bound (a pinned one is not counted)."""
    names = ['ofs_x', 'ofs_y', 'ofs_z', 'scale']
    if info['options']['elliptical']:
        names += ['dia_x', 'dia_y', 'dia_z', 'odi_x', 'odi_y', 'odi_z']
    if info['options']['cmot'] or info['options']['cmot_throttle']:
        names += ['mot_x', 'mot_y', 'mot_z']
    out = []
    for name, v, (lo, hi) in zip(names, info['p'], info['bounds']):
        span = hi - lo
        if span > 0 and (v - lo <= tol * span or hi - v <= tol * span):
            out.append(name)
    return out


# -- the log's other channels and place (until magcal_ros.io.vehicle reads them) ----------

def log_channels(log):
    """
    Time series the bench needs beside MAGFit's samples: current, throttle, GPS fixes.

    A minimal pymavlink pass (CURR of old logs as well as BAT; CTUN.ThO or ThrOut/1000);
    returns {'current': (t, A), 'bat': (t, A) of BAT only, 'throttle': (t, 0..1),
    'tho': (t, 0..1) of CTUN.ThO only (what MAGFit reads), 'gps': [(lat, lon, alt_m, date)]}.
    """
    from pymavlink import mavutil
    mlog = mavutil.mavlink_connection(log)
    cur, bat, thr, tho, gps = [], [], [], [], []
    while True:
        m = mlog.recv_match(type=['BAT', 'CURR', 'CTUN', 'GPS'])
        if m is None:
            break
        typ = m.get_type()
        t = m.TimeUS * 1e-6 if hasattr(m, 'TimeUS') else getattr(m, 'TimeMS', 0) * 1e-3
        if typ == 'BAT' and getattr(m, 'Instance', 0) == 0:
            cur.append((t, m.Curr))
            bat.append((t, m.Curr))
        elif typ == 'CURR':
            cur.append((t, m.Curr / 100.0))  # old logs: centiamps
        elif typ == 'CTUN':
            v = getattr(m, 'ThO', None)
            thr.append((t, v if v is not None else getattr(m, 'ThrOut', np.nan) / 1000.0))
            if v is not None:
                tho.append((t, v))
        elif typ == 'GPS' and m.Status >= 3:
            week = getattr(m, 'GWk', getattr(m, 'Week', 0))
            ms = getattr(m, 'GMS', getattr(m, 'TimeMS', 0))
            date = (GPS_EPOCH + datetime.timedelta(weeks=week, milliseconds=ms)).date() \
                if week else None
            gps.append((m.Lat, m.Lng, m.Alt, date))

    def arr(rows):
        a = np.array(rows, float).reshape(-1, 2)
        return a[:, 0], a[:, 1]
    return {'current': arr(cur), 'bat': arr(bat), 'throttle': arr(thr), 'tho': arr(tho),
            'gps': gps}


def hold(t_stream, v, t):
    """(N,) the latest value of a stream at each time t (zero-order hold, MAGFit's pairing)."""
    if len(t_stream) == 0:
        return np.full(len(t), np.nan)
    i = np.searchsorted(t_stream, t, side='right') - 1
    out = v[np.clip(i, 0, None)].astype(float)
    out[i < 0] = np.nan
    return out


def site(channels):
    """(lat, lon, alt_km, date) of the log: the median of the 3-D fixes, the first fix's date."""
    fixes = channels['gps']
    if not fixes:
        return None
    a = np.array([f[:3] for f in fixes], float)
    dates = [f[3] for f in fixes if f[3] is not None]
    return (float(np.median(a[:, 0])), float(np.median(a[:, 1])),
            float(np.median(a[:, 2])) / 1000.0, dates[0] if dates else None)


def igrf_ned(lat, lon, alt_km, date):
    """(3,) nT: the IGRF field vector (north, east, down) at a place and date (ppigrf)."""
    import ppigrf
    when = datetime.datetime(date.year, date.month, date.day)
    be, bn, bu = (float(np.ravel(x)[0]) for x in ppigrf.igrf(lon, lat, alt_km, when))
    return np.array([bn, be, -bu])


def rpy_quaternion(rpy_deg):
    """(N, 4) body-to-NED unit quaternions (w, x, y, z) of ZYX Euler angles in degrees."""
    from scipy.spatial.transform import Rotation
    q = Rotation.from_euler('ZYX', np.asarray(rpy_deg)[:, ::-1], degrees=True).as_quat()
    return np.c_[q[:, 3], q[:, :3]]


def write_csv(path, t, raw_nt, rpy_deg, aux):
    """Wide CSV (docs/design.md §1) of one compass with attitude and aux channels."""
    q = rpy_quaternion(rpy_deg)
    cols = {'t': t, 's1_x': raw_nt[:, 0], 's1_y': raw_nt[:, 1], 's1_z': raw_nt[:, 2],
            'att_qw': q[:, 0], 'att_qx': q[:, 1], 'att_qy': q[:, 2], 'att_qz': q[:, 3]}
    for name, v in aux.items():
        if np.all(np.isfinite(v)):
            cols[name] = v
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=',',
               header=','.join(cols), comments='', fmt='%.9g')
    return list(cols)


# -- a simulated vehicle, written as a DataFlash text log ----------------------------------

def write_dataflash_text(path, t, mag_mg, rpy_deg, current, lat, lon, alt_m, gps_week,
                         gps_ms):
    """
    Write a DataFlash text log (pymavlink reads it as ArduPilot's) of one compass.

    t (N,) s; mag_mg (N, 3) the raw reading in mG, body frame, logged as integers (MAG is
    int16 in ArduPilot's logs) with the log's calibration all zero (so MAGFit's raw is the
    logged value); rpy_deg (N, 3) ATT roll, pitch, yaw; current (N,) A (BAT.Curr) or None;
    one 3-D GPS fix at the start (its week and milliseconds give the date).
    """
    lines = ['FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns',
             'FMT, 129, 31, PARM, QNf, TimeUS,Name,Value',
             'FMT, 130, 36, GPS, QBIHLLf, TimeUS,Status,GMS,GWk,Lat,Lng,Alt',
             'FMT, 131, 27, ATT, Qfff, TimeUS,Roll,Pitch,Yaw',
             'FMT, 132, 39, MAG, Qhhhhhh, TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ',
             'FMT, 133, 20, BAT, QBf, TimeUS,Instance,Curr']
    for k in ('AHRS_TRIM_X', 'AHRS_TRIM_Y', 'AHRS_TRIM_Z', 'COMPASS_OFS_X', 'COMPASS_OFS_Y',
              'COMPASS_OFS_Z'):
        lines.append(f'PARM, 0, {k}, 0')
    lines.append('PARM, 0, AHRS_EKF_TYPE, 3')
    lines.append(f'GPS, {int(t[0] * 1e6) - 1000}, 3, {gps_ms}, {gps_week}, {lat:.7f}, '
                 f'{lon:.7f}, {alt_m:.2f}')
    for i in range(len(t)):
        us = int(round(t[i] * 1e6))
        lines.append(f'ATT, {us}, {rpy_deg[i, 0]:.4f}, {rpy_deg[i, 1]:.4f}, '
                     f'{rpy_deg[i, 2] % 360:.4f}')
        if current is not None:
            lines.append(f'BAT, {us + 50}, 0, {current[i]:.4f}')
        lines.append(f'MAG, {us + 100}, ' + ', '.join(str(int(v)) for v in mag_mg[i])
                     + ', 0, 0, 0')
    with open(path, 'w') as fh:
        fh.write('\n'.join(lines) + '\n')
    return path


#: the simulated vehicle: CMAC (Canberra), GPS week 2300 + 4 days (2024-02-08)
SIM_SITE = {'lat': -35.3632, 'lon': 149.1652, 'alt_m': 585.0, 'gps_week': 2300,
            'gps_ms': 345600000, 'date': datetime.date(2024, 2, 8)}


def simulate_vehicle_log(path, seed, n=3000, rate_hz=10.0, noise_nt=200.0, tilt_deg=20.0):
    """
    Write a multirotor's compass on a simulated flight as a DataFlash text log; return the truth.

    magcal_ros's simulator (``trajectory='vehicle'``: roll and pitch within +-tilt_deg,
    the heading turning through 270 deg over the record; paper 004's errors of sensor 1;
    Gaussian noise) in the IGRF field at :data:`SIM_SITE`, plus a drone-sized hard-iron
    offset and a battery-current coupling the simulator does not have: raw += b + k I(t),
    I(t) between about 5 and 25 A.  The truth, in the form corrected = C (raw - b0 - k I):
    ``correction_matrix`` C (3, 3), ``offset_nt`` b0 (3,), ``coupling_nt_per_a`` k (3,).
    """
    from magcal_ros.core.data.simulate import simulate
    m = igrf_ned(SIM_SITE['lat'], SIM_SITE['lon'], SIM_SITE['alt_m'] / 1000.0,
                 SIM_SITE['date'])
    total = float(np.linalg.norm(m))
    data, sim = simulate(n_samples=n, rate_hz=rate_hz, n_sensors=1, trajectory='vehicle',
                         tilt_deg=tilt_deg, smooth_period_s=8.0 * n / rate_hz / 3.0,
                         field_nt=total,
                         declination_deg=float(np.degrees(np.arctan2(m[1], m[0]))),
                         inclination_deg=float(np.degrees(np.arcsin(m[2] / total))),
                         noise_nt=noise_nt, errors='paper004', aux=False, attitude=True,
                         seed=seed)
    t = data.t + 10.0
    rng = np.random.default_rng(seed + 1000)
    ph = rng.uniform(0, 2 * np.pi, 2)
    current = 15 + 8 * np.sin(2 * np.pi * t / 53 + ph[0]) + 2 * np.sin(2 * np.pi * t / 11
                                                                       + ph[1])
    b_extra = np.array([15000.0, -8000.0, 22000.0])
    k = np.array([300.0, -500.0, 150.0])
    raw = data.raw[0] + b_extra + current[:, None] * k
    from scipy.spatial.transform import Rotation
    q = data.attitude
    ypr = Rotation.from_quat(np.c_[q[:, 1:], q[:, 0]]).as_euler('ZYX', degrees=True)
    write_dataflash_text(path, t, raw / MG_NT, ypr[:, ::-1], current, SIM_SITE['lat'],
                         SIM_SITE['lon'], SIM_SITE['alt_m'], SIM_SITE['gps_week'],
                         SIM_SITE['gps_ms'])
    truth = sim.truth
    return {'seed': seed, 'n': n, 'rate_hz': rate_hz, 'noise_nt': noise_nt,
            'tilt_deg': tilt_deg, 'correction_matrix': truth.correction_matrix(1).tolist(),
            'offset_nt': (truth.offset(1) + b_extra).tolist(),
            'coupling_nt_per_a': k.tolist(), 'current_a': [float(current.min()),
                                                           float(current.max())]}


def truth_errors(par, truth):
    """
    Distance of a calibration's parameters from the truth (dict).

    par: ``offset_nt`` b0 (at zero current), ``correction_matrix`` C, ``coupling_nt_per_a``
    k (None: no coupling fitted, compared as zero).  Offsets and couplings in nT and nT/A
    (Euclidean norm of the difference), the matrix as the Frobenius norm of C - C_true.
    """
    k = np.zeros(3) if par.get('coupling_nt_per_a') is None else par['coupling_nt_per_a']
    return {'offset_nt': float(np.linalg.norm(np.subtract(par['offset_nt'],
                                                          truth['offset_nt']))),
            'coupling_nt_per_a': float(np.linalg.norm(np.subtract(
                k, truth['coupling_nt_per_a']))),
            'correction_matrix': float(np.linalg.norm(np.subtract(
                par['correction_matrix'], truth['correction_matrix'])))}


# -- magcal_ros ------------------------------------------------------------------------------

def can_read_logs():
    """Return True when this tree reads vehicle logs (magcal_ros.io.vehicle, issue 31 item 1)."""
    import importlib.util
    return importlib.util.find_spec('magcal_ros.io.vehicle') is not None


def run_magcal(command, data_path, args, workdir):
    """``magcal COMMAND DATA --json ARGS`` in its own process: (exit code, JSON, stderr, s)."""
    cmd = [sys.executable, '-m', 'magcal_ros.cli', command, data_path, '--json'] + args
    env = dict(os.environ, PYTHONPATH=common.REPO_DIR + os.pathsep
               + os.environ.get('PYTHONPATH', ''))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=workdir)
    wall = time.perf_counter() - t0
    doc = None
    if proc.stdout.strip():
        try:
            doc = json.loads(proc.stdout)
        except json.JSONDecodeError:
            doc = None
    return proc.returncode, doc, proc.stderr.strip(), wall


def magcal_corrected(cal_path, csv_path):
    """
    (N, 3) nT: sensor 1 of the CSV corrected with a calibration file of magcal_ros.

    Sensor 1 only: a calibration fitted on the log itself has every compass of it.  In the
    attitude's body frame: an attitude-aided fit's mounting rotation is undone.
    """
    from magcal_ros.io.calfile import load_calibration
    from magcal_ros.io.csvio import read_csv
    from magcal_ros.core.effects.attitude_ref import attitude_reference
    cal = load_calibration(cal_path)[0]
    data = read_csv(csv_path)
    cor = cal.correct(1, data.raw[0], data.context(1))
    found = attitude_reference(cal.model)
    if found is not None:
        # an attitude-aided fit also found the compass's mounting Q against the attitude's
        # body frame (sensor 1's frame = Q x the body's): the scores read the body frame
        eff, sl = found
        cor = cor @ eff.mount(cal.params[sl])
    return cor


def scores(corrected_nt, rpy_deg, earth_mg, declination_deg, m_ned_nt):
    """Score one calibration on the samples by the three measures (dict)."""
    f = float(np.linalg.norm(m_ned_nt))
    rot = euler_dcm(rpy_deg[:, 0], rpy_deg[:, 1], rpy_deg[:, 2])
    expected = np.einsum('nji,j->ni', rot, m_ned_nt)
    # the heading the corrected compass gives (MAGFit's) against the log's yaw
    dyaw = (magfit_yaw(corrected_nt, rpy_deg[:, 0], rpy_deg[:, 1], declination_deg)
            - rpy_deg[:, 2] + 180.0) % 360.0 - 180.0
    return {'heading_minus_log_yaw_deg': dict(zip(('p25', 'median', 'p75'), map(
                float, np.percentile(dyaw, [25, 50, 75])))),
            'magfit_error_mg': magfit_error(corrected_nt / MG_NT, rpy_deg[:, 0], rpy_deg[:, 1],
                                            earth_mg, declination_deg),
            'scalar_rms_nt': float(np.sqrt(np.mean(
                (np.linalg.norm(corrected_nt, axis=1) - f) ** 2))),
            'vector_rms_nt': float(np.sqrt(np.mean(
                np.sum((corrected_nt - expected) ** 2, axis=1))))}


# -- one log ---------------------------------------------------------------------------------

def sha256(path):
    """Hex sha256 of a file."""
    import hashlib
    h = hashlib.sha256()
    with open(path, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def compare_log(log, option_names, extra, magcal_variants, diagnose_args, workdir,
                magcal_input, truth=None):
    """Every MAGFit option set and every magcal variant on one log (dict)."""
    channels = log_channels(log)
    where = site(channels)
    digest = sha256(log)
    out = {'log': os.path.abspath(log), 'sha256': digest, 'magfit_extra_args': extra,
           'site': None, 'magfit': {}, 'magcal': {}, 'scores': {}, 'skipped': {}}
    if truth is not None:
        out['truth'] = truth
    has = {'cmot': len(channels['bat'][0]) > 0, 'cmot_throttle': len(channels['tho'][0]) > 0}
    base = None
    for name in option_names:
        opts = MAGFIT_OPTIONS[name]
        if '--cmot' in opts and not has['cmot']:
            out['skipped'][name] = 'the log has no BAT current (MAGFit reads BAT.Curr only)'
            continue
        if '--cmot-throttle' in opts and not has['cmot_throttle']:
            out['skipped'][name] = 'the log has no CTUN throttle'
            continue
        print(f'  MAGFit {name} ...', flush=True)
        info, arrays = run_magfit(log, opts, extra, workdir,
                                  tag=f'{os.path.basename(log)}-{name}')
        if base is None and arrays:
            base = arrays
            base_info = info
        out['magfit'][name] = info
    if base is None:
        out['error'] = 'MAGFit extracted no samples (no MAG with attitude)'
        return out
    t, raw_mg, rpy = base['t'], base['raw_mg'], base['rpy_deg']
    earth_mg, decl = base['earth_mg'], base_info['declination_deg']
    current = hold(*channels['current'], t)
    throttle = hold(*channels['throttle'], t)
    if where is None or where[3] is None:
        out['error'] = 'no GPS fix with a date: no IGRF for magcal_ros'
        return out
    m_ned = igrf_ned(*where)
    out['site'] = {'lat_deg': where[0], 'lon_deg': where[1], 'alt_km': where[2],
                   'date': where[3].isoformat(), 'igrf_ned_nt': m_ned,
                   'magfit_earth_nt': earth_mg * MG_NT, 'n_samples': int(len(t)),
                   'span_s': float(t[-1] - t[0]),
                   'current_a': [float(np.nanmin(current)), float(np.nanmax(current))]
                   if np.isfinite(current).any() else None}

    # the log's own calibration and each MAGFit fit, scored on the same samples
    lc = base_info['log_calibration']
    motor = {0: np.full(len(t), np.nan), 1: base['ctun_tho'], 2: base['bat_curr']}
    out['scores']['log calibration'] = scores(
        magfit_correct(raw_mg, lc['offsets'], lc['scale'], lc['diag'], lc['offdiag'],
                       lc['cmot'], motor.get(lc['cmot_mode'], motor[0])) * MG_NT,
        rpy, earth_mg, decl, m_ned)
    if truth is not None:
        # the true calibration on the same samples: what every measure reads at the floor
        # (the noise and the logged integers' truncation)
        corr = (raw_mg * MG_NT - np.asarray(truth['offset_nt'])
                - current[:, None] * np.asarray(truth['coupling_nt_per_a'])) \
            @ np.asarray(truth['correction_matrix']).T
        out['scores']['truth'] = scores(corr, rpy, earth_mg, decl, m_ned)
        rf = magfit_parameters_raw(lc)
        out['scores']['log calibration']['truth_error'] = truth_errors(
            {'offset_nt': rf['offset_nt'], 'correction_matrix': rf['correction_matrix'],
             'coupling_nt_per_a': None}, truth)
    for name, info in out['magfit'].items():
        if 'p' not in info:
            continue
        o = info['options']
        prm = unpack_p(info['p'], o['elliptical'], o['cmot'] or o['cmot_throttle'])
        info['parameters'] = prm
        info['parameters_raw_form'] = magfit_parameters_raw(prm)
        info['on_bounds'] = on_bounds(info)
        mot = motor[2] if o['cmot'] else motor[1] if o['cmot_throttle'] else motor[0]
        corr = magfit_correct(raw_mg, prm['offsets'], prm['scale'], prm['diag'],
                              prm['offdiag'], prm['cmot'], mot)
        s = scores(corr * MG_NT, rpy, earth_mg, decl, m_ned)
        # the re-implementation against the module's own error at the same parameters
        s['module_error_mg'] = info['module_error_mg']
        s['reimplementation_minus_module_mg'] = s['magfit_error_mg'] - info['module_error_mg']
        s['exit_code'] = info['exit_code']
        if truth is not None:
            rf = info['parameters_raw_form']
            s['truth_error'] = truth_errors(
                {'offset_nt': rf['offset_nt'], 'correction_matrix': rf['correction_matrix'],
                 'coupling_nt_per_a': rf['motor_coupling_raw_nt'] if o['cmot'] else None},
                truth)
        out['scores'][f'MAGFit {name}'] = s
    ok = {k: v for k, v in out['scores'].items()
          if k.startswith('MAGFit') and v['exit_code'] == 0}
    out['magfit_best'] = min(ok, key=lambda k: ok[k]['magfit_error_mg']) if ok else None

    # magcal_ros on the same samples
    csv_path = os.path.join(workdir, os.path.basename(log) + '.csv')
    columns = write_csv(csv_path, t, raw_mg * MG_NT, rpy,
                        {'aux_battery_current': current, 'aux_throttle': throttle})
    use_log = magcal_input == 'log'
    out['magcal_input'] = ("the log itself (magcal_ros.io.vehicle); scored on MAGFit's "
                           'samples' if use_log else
                           "wide CSV written by the bench from MAGFit's samples: "
                           + ', '.join(columns))
    data_path = os.path.abspath(log) if use_log else csv_path
    igrf = ['--igrf', f'{where[0]:.7f}', f'{where[1]:.7f}', f'{where[2]:.4f}',
            where[3].isoformat()]
    for label, vargs in magcal_variants:
        cal = os.path.join(workdir, f'cal-{len(os.listdir(workdir))}.yaml')
        print(f'  magcal fit {label} ...', flush=True)
        # 'log:...' variants read the log itself (every compass; its own samples and place,
        # e.g. with drop(T0, T1) for a window), scored on MAGFit's samples like the others
        on_log = label.startswith('log:')
        if on_log and not can_read_logs():
            out['magcal'][label] = {'args': vargs, 'exit_code': None,
                                    'stderr': ['this tree reads no vehicle logs']}
            continue
        code, doc, err, wall = run_magcal(
            'fit', os.path.abspath(log) if on_log else data_path,
            (vargs if on_log else igrf + vargs) + ['-o', cal], workdir)
        rec = {'args': vargs, 'exit_code': code, 'wall_s': wall,
               'stderr': err.splitlines()[-3:], 'input': 'log' if on_log else
               ('log' if use_log else 'csv')}
        if doc is not None:
            rec['json'] = fit_summary(doc)
        out['magcal'][label] = rec
        if code == 0 and os.path.exists(cal):
            s = scores(magcal_corrected(cal, csv_path), rpy, earth_mg, decl, m_ned)
            s['exit_code'] = code
            rec['parameters'] = magcal_parameters(doc)
            if truth is not None and rec['parameters']:
                s['truth_error'] = truth_errors(magcal_common_form(rec['parameters']), truth)
            if doc and doc.get('attitude'):
                rec['attitude'] = doc['attitude']
            out['scores'][f'magcal {label}'] = s
    if diagnose_args is None:
        return out
    print('  magcal diagnose ...', flush=True)
    code, doc, err, wall = run_magcal('diagnose', data_path, igrf + diagnose_args, workdir)
    out['diagnose'] = {'args': diagnose_args, 'exit_code': code, 'wall_s': wall,
                       'stderr': err.splitlines()[-3:], 'summary': diagnose_summary(doc)}
    return out


def fit_summary(doc):
    """Keep the figures of a ``fit --json`` (its calibration is summed up in 'parameters')."""
    keep = ('model', 'n_samples', 'n_fit_samples', 'converged', 'noise_floor_nt',
            'scalar_rms_nt', 'undetermined', 'onboard_calibration')
    out = {k: doc.get(k) for k in keep if k in doc}
    out['warnings'] = [w.get('text') if isinstance(w, dict) else w
                       for w in doc.get('warnings') or []]
    return out


def diagnose_summary(doc):
    """Sum up a ``diagnose --json``: its verdict, findings and each candidate's figures."""
    if not doc:
        return None
    keep = ('token', 'delta_bic', 'log10_p_value', 'cv_rms_before_nt', 'cv_rms_after_nt',
            'explained_fraction', 'significant', 'decided_by')
    return {'verdict': doc.get('verdict'), 'noise_floor_nt': doc.get('noise_floor_nt'),
            'residual_rms_nt': doc.get('residual_rms_nt'),
            'ratio_to_floor': doc.get('ratio_to_floor'),
            'findings': [{k: f.get(k) for k in ('token', 'text', 'explained_fraction')}
                         for f in doc.get('findings') or []],
            'candidates': [{k: c.get(k) for k in keep} for c in doc.get('candidates') or []],
            'warnings': [w.get('text') if isinstance(w, dict) else w
                         for w in doc.get('warnings') or []]}


def magfit_parameters_raw(prm):
    """
    Put MAGFit's parameters in magcal_ros's form: corrected = C (raw - b) + k I.

    C = scale S (3, 3); b = -offsets (nT); the motor term stays additive after the
    correction in MAGFit: its raw-side equivalent is -C^-1 cmot (nT per A or per unit of
    throttle), the form of magcal_ros's ``aux`` coupling.
    """
    s = np.array([[prm['diag'][0], prm['offdiag'][0], prm['offdiag'][1]],
                  [prm['offdiag'][0], prm['diag'][1], prm['offdiag'][2]],
                  [prm['offdiag'][1], prm['offdiag'][2], prm['diag'][2]]]) * prm['scale']
    return {'offset_nt': (-np.asarray(prm['offsets']) * MG_NT).tolist(),
            'correction_matrix': s.tolist(),
            'motor_coupling_raw_nt': (-np.linalg.solve(s, prm['cmot']) * MG_NT).tolist()}


def magcal_parameters(doc):
    """Offset, correction matrix and aux couplings (with uncertainties) of a fit's JSON."""
    sensors = ((doc or {}).get('calibration') or {}).get('sensors') or []
    if not sensors:
        return None
    s1 = sensors[0]
    out = {'offset_nt': s1.get('offset_nt'), 'correction_matrix': s1.get('correction_matrix'),
           'couplings': {}}
    for eff in s1.get('effects', []):
        if eff.get('name') == 'aux':
            out['couplings'][eff['label']] = {
                'value': [eff['params'][k]['value'] for k in ('vx', 'vy', 'vz')],
                'stderr': [eff['params'][k]['stderr'] for k in ('vx', 'vy', 'vz')],
                'unit': eff['params']['vx']['unit'], 'refs': eff.get('refs')}
    return out


def magcal_common_form(par, current='aux:aux_battery_current'):
    """magcal_parameters() -> offset at zero current, correction matrix, current coupling."""
    b = np.array(par['offset_nt'], float)
    k = None
    c = par['couplings'].get(current)
    if c is not None:
        k = np.array(c['value'], float)
        b = b - k * float((c.get('refs') or {}).get('a0', 0.0))   # the effect is k (I - a0)
    return {'offset_nt': b, 'correction_matrix': par['correction_matrix'],
            'coupling_nt_per_a': k}


def _table(res):
    rows = []
    for name, s in res['scores'].items():
        h = s['heading_minus_log_yaw_deg']
        info = res['magfit'].get(name.replace('MAGFit ', ''), {}) if name.startswith(
            'MAGFit') else res['magcal'].get(name.replace('magcal ', ''), {})
        te = s.get('truth_error') or {}
        rows.append([name, s['magfit_error_mg'], s['scalar_rms_nt'], s['vector_rms_nt'],
                     f"{h['median']:+.1f} ({h['p25']:+.1f}..{h['p75']:+.1f})",
                     ', '.join(info.get('on_bounds', [])) or '-',
                     info.get('wall_s')] + ([te.get('offset_nt'), te.get('coupling_nt_per_a'),
                                             te.get('correction_matrix')]
                                            if 'truth' in res else []))
    extra = ['offset error nT', 'current coupling error nT/A', 'matrix error'] \
        if 'truth' in res else []
    out = common.table(['calibration', 'MAGFit error mG', 'RMS of abs(B)-F nT',
                        'vector RMS nT', 'heading - log yaw deg, median (IQR)',
                        'on a bound', 'time s'] + extra, rows,
                       title=f'{os.path.basename(res["log"])}: '
                             f'{res["site"]["n_samples"]} samples, '
                             f'{res["site"]["span_s"]:.0f} s' if res.get('site') else
                             os.path.basename(res['log']))
    notes = [f'MAGFit best: {res.get("magfit_best")}']
    if res.get('skipped'):
        notes.append('MAGFit not run: ' + ', '.join(sorted(res['skipped'])) + ' (no channel)')
    summary = (res.get('diagnose') or {}).get('summary')
    if summary:
        v = summary.get('verdict') or {}
        notes.append(f'magcal diagnose {" ".join(res["diagnose"]["args"])}: '
                     f'{v.get("token") or v.get("effect")} ({v.get("reason")})')
    elif res.get('diagnose'):
        notes.append(f'magcal diagnose: exit {res["diagnose"]["exit_code"]}: '
                     + ' '.join(res['diagnose']['stderr'][-1:]))
    return out + '\n\n' + '\n'.join(f'- {n}' for n in notes)


def main(argv=None):
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ['--magfit-child']:
        _magfit_child(argv[1], argv[3:])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('logs', nargs='*', help='ArduPilot DataFlash logs (.bin, .log)')
    ap.add_argument('--simulate', type=int, default=0, metavar='K',
                    help='also K simulated multirotor flights with a known calibration and '
                    'current coupling (seeds 0..K-1; simulate_vehicle_log)')
    ap.add_argument('--sim-samples', type=int, default=3000,
                    help='samples of each simulated flight at 10 Hz (default 3000)')
    ap.add_argument('--magfit-options', default=','.join(MAGFIT_OPTIONS),
                    help='comma-separated MAGFit option sets: ' + ', '.join(MAGFIT_OPTIONS))
    ap.add_argument('--condition', help='MAGFit --condition (e.g. a time window), also '
                    'defines the samples magcal_ros gets')
    ap.add_argument('--att-source', help='MAGFit --att-source (ATT for logs without '
                    'AHRS_EKF_TYPE)')
    ap.add_argument('--magcal-input', choices=['auto', 'csv', 'log'], default='csv',
                    help="what magcal_ros's variants read: the CSV of MAGFit's samples "
                    '(default: both tools see the same samples), the log (when this tree '
                    'reads logs), or auto: the CSV when MAGFit gets a --condition, else the '
                    "log if readable; a variant labelled 'log:...' always reads the log")
    ap.add_argument('--diagnose-args', default='--constrained',
                    help="arguments of 'magcal diagnose' (default --constrained)")
    ap.add_argument('--no-diagnose', action='store_true', help="skip 'magcal diagnose'")
    ap.add_argument('--magcal-variant', action='append', metavar='LABEL=ARGS',
                    help="a magcal fit run, e.g. 'current=--model base,aux:aux_battery_current"
                    " --constrained' (default: base and base+current, both --constrained); "
                    "a LABEL starting with 'log:' fits the log itself (this tree must read "
                    "logs), e.g. 'log:tilt=--allow-gaps --model base,drop(220,400)'")
    ap.add_argument('--keep', metavar='DIR', help='keep the work files (CSV, YAML) in DIR')
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    names = [n.strip() for n in args.magfit_options.split(',') if n.strip()]
    if not args.logs and not args.simulate:
        ap.error('give LOG files or --simulate K')
    bad = [n for n in names if n not in MAGFIT_OPTIONS]
    if bad:
        ap.error(f'unknown MAGFit option set(s) {bad}; known: {list(MAGFIT_OPTIONS)}')
    extra = []
    if args.condition:
        extra += ['--condition', args.condition]
    if args.att_source:
        extra += ['--att-source', args.att_source]
    extra = extra or None  # None: the log's preset (LOG_PRESETS), if any
    variants = [tuple(v.split('=', 1)) for v in args.magcal_variant or []] or [
        ('base', '--constrained'),
        ('base+current', '--model base,aux:aux_battery_current --constrained')]
    variants = [(label, shlex.split(a)) for label, a in variants]
    readable = can_read_logs()
    if args.magcal_input == 'log' and not readable:
        ap.error('--magcal-input log: this tree has no magcal_ros.io.vehicle (issue 31 item 1)')
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or tmp
        os.makedirs(work, exist_ok=True)
        runs = [(log, None) for log in args.logs]
        for seed in range(args.simulate):
            path = os.path.join(work, f'sim_vehicle_{seed}.log')
            runs.append((path, simulate_vehicle_log(path, seed, n=args.sim_samples)))
        for log, truth in runs:
            print(f'{log}:', flush=True)
            x = extra if extra is not None else LOG_PRESETS.get(sha256(log), [])
            if truth is not None and extra is None:
                x = ['--att-source', 'ATT']     # its ATT is the true attitude
            mode = args.magcal_input
            if mode == 'auto':
                mode = 'log' if readable and '--condition' not in x else 'csv'
            diag = None if args.no_diagnose else shlex.split(args.diagnose_args)
            results.append(compare_log(log, names, x, variants, diag, work, mode, truth))
            if results[-1].get('site'):
                print('\n' + _table(results[-1]) + '\n', flush=True)
    tables = [_table(r) for r in results if r.get('site')]
    settings = {'logs': args.logs, 'simulate': args.simulate, 'sim_samples': args.sim_samples,
                'magfit_options': names, 'magfit_extra_args': extra,
                'magcal_variants': variants, 'magcal_reads_logs': readable,
                'magcal_input': args.magcal_input,
                'diagnose_args': None if args.no_diagnose else args.diagnose_args}
    from importlib.metadata import version
    settings['pymavlink'] = version('pymavlink')
    path = common.write_result('magfit_compare', settings, {'logs': results}, tables,
                               args.out_dir, started)
    print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
