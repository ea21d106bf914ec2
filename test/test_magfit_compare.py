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
bench/magfit_compare.py: its copy of MAGFit's error against MAGFit itself and a known truth.

A DataFlash text log is written here with a known compass calibration (offsets, scale, a
battery-current coupling) on known attitudes in pymavlink's table WMM field; the installed
pymavlink's ``magfit_WMM`` is run on it through the bench.  Checked: MAGFit finds the truth
(within the 1 mG steps of the logged integers), the bench's vectorised error equals the
module's ``wmm_error`` at two different parameter vectors, the rotation and heading formulas
against scipy and hand values, the parameter conversion against a direct evaluation, and the
whole bench run end to end.
"""
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip('pymavlink')
BENCH = pathlib.Path(__file__).resolve().parents[1] / 'bench'
sys.path.insert(0, str(BENCH))
import magfit_compare as mc  # noqa: E402, I100

LAT, LON = -35.3632, 149.1652
TRUTH = {'offsets': np.array([40.0, -75.0, 120.0]), 'scale': 1.1,
         'cmot': np.array([2.0, -3.0, 1.5])}       # mG, 1, mG per A


N = 80


def write_log(path, n=N):
    """Write a DataFlash text log whose MAG is TRUTH's raw reading (integers, mG)."""
    from pymavlink import mavextra
    ef = mavextra.expected_earth_field_lat_lon(LAT, LON)
    m = np.array([ef.x, ef.y, ef.z])
    t = np.arange(n) * 0.1 + 1.0
    roll, pitch, yaw = 25 * np.sin(2.1 * t), 20 * np.cos(1.3 * t), (45.0 * t) % 360
    current = 10 + 10 * np.sin(0.9 * t)
    body = np.einsum('nji,j->ni', mc.euler_dcm(roll, pitch, yaw), m)
    # corrected = (raw + ofs) scale + cmot I  =>  raw = (body - cmot I) / scale - ofs
    raw = (body - current[:, None] * TRUTH['cmot']) / TRUTH['scale'] - TRUTH['offsets']
    return mc.write_dataflash_text(path, t, raw, np.c_[roll, pitch, yaw], current, LAT, LON,
                                   580.0, 2300, 345600000)


def test_euler_dcm_is_scipys_zyx():
    from scipy.spatial.transform import Rotation
    rpy = np.array([[10.0, -20.0, 200.0], [-170.0, 80.0, 3.0], [0.0, 0.0, 0.0]])
    want = Rotation.from_euler('ZYX', rpy[:, ::-1], degrees=True).as_matrix()
    assert np.allclose(mc.euler_dcm(rpy[:, 0], rpy[:, 1], rpy[:, 2]), want, atol=1e-12)
    q = mc.rpy_quaternion(rpy)          # (w, x, y, z), the CSV's att_q*
    assert np.allclose(Rotation.from_quat(np.c_[q[:, 1:], q[:, 0]]).as_matrix(), want)


def test_magfit_yaw_by_hand():
    # level, heading 30 deg: the body sees the horizontal field at -30 deg
    h, z = 200.0, -500.0
    body = np.array([[h * np.cos(np.radians(30)), -h * np.sin(np.radians(30)), z]])
    assert mc.magfit_yaw(body, [0.0], [0.0], 0.0)[0] == pytest.approx(30.0)
    assert mc.magfit_yaw(body, [0.0], [0.0], 12.5)[0] == pytest.approx(42.5)
    # rolled 20 deg: the same heading after tilt compensation
    rot = mc.euler_dcm([20.0], [0.0], [30.0])[0]
    ef = np.array([h, 0.0, z])
    assert mc.magfit_yaw((rot.T @ ef)[None], [20.0], [0.0], 0.0)[0] == pytest.approx(30.0)


def test_parameters_raw_form_reproduces_the_correction():
    rng = np.random.default_rng(3)
    prm = {'offsets': [5.0, -7.0, 11.0], 'scale': 1.2, 'diag': [1.05, 0.95, 1.0],
           'offdiag': [0.02, -0.03, 0.01], 'cmot': [1.5, -2.0, 0.5]}
    raw, cur = rng.normal(0, 300, (20, 3)), rng.uniform(0, 30, 20)
    direct = mc.magfit_correct(raw, prm['offsets'], prm['scale'], prm['diag'],
                               prm['offdiag'], prm['cmot'], cur) * mc.MG_NT
    rf = mc.magfit_parameters_raw(prm)
    c, b, k = (np.array(rf['correction_matrix']), np.array(rf['offset_nt']),
               np.array(rf['motor_coupling_raw_nt']))
    mine = (raw * mc.MG_NT - b - cur[:, None] * k) @ c.T
    assert np.allclose(mine, direct, rtol=1e-12, atol=1e-9)
    assert np.allclose(b, [-500.0, 700.0, -1100.0])


@pytest.fixture(scope='module')
def bench_run(tmp_path_factory):
    """Run the bench on the synthetic log: MAGFit without and with --cmot, magcal base."""
    tmp = tmp_path_factory.mktemp('magfit')
    log = write_log(tmp / 'synth.log')
    out, keep = tmp / 'out', tmp / 'work'
    proc = subprocess.run(
        [sys.executable, str(BENCH / 'magfit_compare.py'), str(log), '--out-dir', str(out),
         '--magfit-options', 'offsets+scale,cmot', '--att-source', 'ATT',
         '--magcal-variant', 'base=--constrained', '--no-diagnose', '--keep', str(keep)],
        capture_output=True, text=True, timeout=170)
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads((out / 'magfit_compare.json').read_text())
    return doc, proc.stdout, keep


@pytest.mark.timeout(180)
def test_magfit_finds_the_truth_and_the_bench_scores_it_as_magfit_does(bench_run):
    doc, _, keep = bench_run
    info = doc['results']['logs'][0]['magfit']['cmot']
    arrays = np.load(keep / 'magfit-synth.log-cmot.npz')
    assert json.loads(str(arrays['info']))['argv'][0] == '--cmot'
    n = len(arrays['t'])
    assert info['exit_code'] == 0 and info['n'] == n == N
    prm = mc.unpack_p(info['p'], elliptical=False, cmot=True)
    # the logged integers truncate the raw reading by < 1 mG per axis
    assert np.allclose(prm['offsets'], TRUTH['offsets'], atol=1.0)
    assert prm['scale'] == pytest.approx(TRUTH['scale'], abs=0.005)
    assert np.allclose(prm['cmot'], TRUTH['cmot'], atol=0.1)
    raw, rpy = arrays['raw_mg'], arrays['rpy_deg']
    assert np.allclose(arrays['bat_curr'], 10 + 10 * np.sin(0.9 * arrays['t']), atol=0.01)

    def error(p):
        q = mc.unpack_p(p, elliptical=False, cmot=True)
        corr = mc.magfit_correct(raw, q['offsets'], q['scale'], q['diag'], q['offdiag'],
                                 q['cmot'], arrays['bat_curr'])
        return mc.magfit_error(corr, rpy[:, 0], rpy[:, 1], arrays['earth_mg'],
                               info['declination_deg'])
    # the module's own wmm_error at its solution and at its start (no calibration)
    assert error(info['p']) == pytest.approx(info['module_error_mg'], rel=1e-12)
    assert error(info['p0']) == pytest.approx(info['module_error_at_start_mg'], rel=1e-12)
    assert info['module_error_at_start_mg'] > 50 * info['module_error_mg']
    # at the truth only the truncation is left: < sqrt(3) * 1 mG * scale per sample
    truth = np.r_[TRUTH['offsets'], TRUTH['scale'], TRUTH['cmot']]
    assert error(truth) < np.sqrt(3) * TRUTH['scale']


def test_bench_end_to_end(bench_run):
    doc, stdout, _ = bench_run
    res = doc['results']['logs'][0]
    sc = res['scores']
    assert set(sc) == {'log calibration', 'MAGFit offsets+scale', 'MAGFit cmot',
                       'magcal base'}
    for name in ('MAGFit offsets+scale', 'MAGFit cmot'):
        assert abs(sc[name]['reimplementation_minus_module_mg']) < 1e-9
    # the current coupling is in the data: MAGFit with it is far better than without,
    # and the best MAGFit run is that one, with no parameter on a bound
    assert sc['MAGFit cmot']['magfit_error_mg'] < 2.0 < sc['MAGFit offsets+scale'][
        'magfit_error_mg']
    assert res['magfit_best'] == 'MAGFit cmot'
    assert res['magfit']['cmot']['on_bounds'] == []
    assert res['magcal']['base']['exit_code'] == 0
    # GPS week 2000 began on 2018-05-06; week 2300 plus 4 days (345 600 000 ms)
    assert res['site']['date'] == '2024-02-08' and res['site']['n_samples'] == N
    assert doc['tables'][0] in stdout


def test_simulated_vehicle_log_holds_its_truth(tmp_path):
    """The simulated flight, read back by pymavlink, corrected with its truth: the noise."""
    from pymavlink import mavutil
    truth = mc.simulate_vehicle_log(tmp_path / 'sim.log', seed=3, n=400)
    mlog = mavutil.mavlink_connection(str(tmp_path / 'sim.log'))
    att, bat, mag = [], [], []
    while True:
        m = mlog.recv_match(type=['ATT', 'BAT', 'MAG'])
        if m is None:
            break
        {'ATT': att, 'BAT': bat, 'MAG': mag}[m.get_type()].append(
            [m.Roll, m.Pitch, m.Yaw] if m.get_type() == 'ATT' else
            [m.Curr] if m.get_type() == 'BAT' else [m.MagX, m.MagY, m.MagZ])
    att, cur, raw = np.array(att), np.array(bat)[:, 0], np.array(mag) * mc.MG_NT
    assert len(raw) == len(att) == len(cur) == 400
    assert 4.0 < truth['current_a'][0] and truth['current_a'][1] < 26.0
    site = mc.SIM_SITE
    m_ned = mc.igrf_ned(site['lat'], site['lon'], site['alt_m'] / 1000, site['date'])
    expected = np.einsum('nji,j->ni', mc.euler_dcm(*att.T), m_ned)

    def residual(k):
        c = (raw - truth['offset_nt'] - cur[:, None] * k) @ np.array(
            truth['correction_matrix']).T
        return np.sqrt(np.mean(np.sum((c - expected) ** 2, axis=1)))
    # noise 200 nT per axis and the logged integers' truncation (< 100 nT per axis)
    assert residual(np.array(truth['coupling_nt_per_a'])) < np.sqrt(3) * (200 + 100)
    assert residual(np.zeros(3)) > 5 * np.sqrt(3) * (200 + 100)


def test_magcal_common_form_offset_at_zero_current():
    par = {'offset_nt': [100.0, 0.0, -20.0], 'correction_matrix': np.eye(3).tolist(),
           'couplings': {'aux:aux_battery_current': {'value': [10.0, 0.0, 2.0],
                                                     'refs': {'a0': 5.0}}}}
    out = mc.magcal_common_form(par)
    # the effect is k (I - a0): at I = 0 the offset is b - k a0
    assert np.allclose(out['offset_nt'], [50.0, 0.0, -30.0])
    assert np.allclose(out['coupling_nt_per_a'], [10.0, 0.0, 2.0])
    err = mc.truth_errors(out, {'offset_nt': [50.0, 3.0, -30.0],
                                'coupling_nt_per_a': [10.0, 0.0, 0.0],
                                'correction_matrix': np.eye(3).tolist()})
    assert err == pytest.approx({'offset_nt': 3.0, 'coupling_nt_per_a': 2.0,
                                 'correction_matrix': 0.0})
