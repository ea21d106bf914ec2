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
Calibration under bad data, outliers, concurrent requests and invalid parameters.

Already covered elsewhere and not repeated: the core refusals of a single-axis rotation, one
attitude, too few samples and non-finite input, and the robust fit's parameter tolerance
(test_model_ml.py); at the node, a single-axis refusal keeping the previous file, too few
sets without a previous file, a second calibrate and a start during a solve, and the model
parameter's validation (test_calibration_node.py, test_e2e.py). Added here:

- a stuck sensor (all samples identical, or frozen within its noise while the array turns)
  is refused with a message naming that sensor, from the core, the CLI and the node;
- at the node, each refusal (too few sets, one attitude, a stuck sensor, a sensor that never
  reports, a sensor whose data stop half way) answers success=false with the reason naming
  the sensor where there is one, and leaves the previously written file and the latched
  calibration/result untouched; the corrector keeps correcting the sensors that report;
- 5 % spikes of 1000 nT through the CLI and the node with the robust loss: parameters within
  the no-outlier tolerance, and the reported down-weighted count matches the spikes;
- start, calibrate and diagnose requested at the same moment, and invalid parameter values
  (unknown effect, negative rate or tolerance, empty path) set during a solve: clean
  refusals, a consistent state afterwards, and the solve's result unaffected.
"""
import copy
import json
import os
import re
import subprocess
import sys
import threading

from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.live.sync import StampMatcher
from magcal_ros.core.model import DegenerateDataError, fit
from magcal_ros.core.model.identifiability import check_coverage
from magcal_ros.io.calfile import (calibration_to_doc, list_history, load_calibration,
                                   save_calibration)
from magcal_ros.io.csvio import write_csv
from magcal_ros.pipeline import calibrate, cross_geometry
from magcal_ros.ros import calibrating
from magcal_ros.ros.calibration_node import CalibrationNode, RESULT_QOS
from magcal_ros.ros.conversions import field_nt_to_msg, msg_to_field_nt
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import (call_trigger, run_concurrently, spin_for, spin_until,
                         split_response as split, subprocess_env)
from sensor_msgs.msg import MagneticField
from sim_feed import Feeder, intake_batch, T0
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

F = 50000.0                 # simulated field magnitude, nT
NOISE_NT = 3.0              # simulator noise per axis, nT


@pytest.fixture(scope='module')
def tumbling():
    """6 s at 100 Hz of the smooth trajectory with a 6 s period: all attitudes covered."""
    data, sim = simulate(n_samples=600, rate_hz=100.0, trajectory='smooth',
                         smooth_period_s=6.0, seed=7)
    return data, sim


def _copy(data):
    return copy.deepcopy(data)


def stuck(data, sensor, noise_nt=0.0, seed=0):
    """Copy of ``data`` where ``sensor`` (1-based) repeats its first reading (plus noise)."""
    out = _copy(data)
    rng = np.random.default_rng(seed)
    frozen = out.raw[sensor - 1, 0]
    out.raw[sensor - 1] = frozen + rng.normal(scale=noise_nt, size=out.raw[sensor - 1].shape)
    return out


# -- core and CLI ----------------------------------------------------------------------------

@pytest.mark.parametrize('noise_nt, match', [
    (0.0, r'sensor 3: output is constant \(all 600 samples read'),
    (NOISE_NT, r'sensor 3: output \(nearly\) constant .* while sensor 1 saw the array turn'),
])
def test_stuck_sensor_is_refused_naming_it(tumbling, noise_nt, match):
    data = stuck(tumbling[0], 3, noise_nt)
    with pytest.raises(DegenerateDataError, match=match):
        fit(data, 'base', field_nt=F)
    rep = check_coverage(data.raw)
    assert {j: v['status'] for j, v in rep['sensors'].items()} == {
        1: 'good', 2: 'good', 3: 'constant', 4: 'good'}
    assert len(rep['problems']) == 1 and 'stuck' in rep['problems'][0]


def _magcal(*args, cwd):
    return subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=cwd,
                          env=subprocess_env())


def test_cli_refuses_stuck_and_missing_sensors_naming_them(tmp_path, tumbling):
    write_csv(tmp_path / 'stuck.csv', stuck(tumbling[0], 2))
    missing = _copy(tumbling[0])
    missing.raw[3, 200:] = np.nan                   # sensor 4 stopped reporting at 2 s
    write_csv(tmp_path / 'missing.csv', missing)
    cases = (('stuck.csv', 'sensor 2: output is constant'),
             # the CSV reader names the first bad cell and counts the rows
             ('missing.csv', r"line 202, column s4_x: 'nan' is not a finite number "
                             r'\(400 row\(s\) affected\)'))
    # the two refusals are independent: side by side (run_concurrently)
    runs = run_concurrently({name: ([sys.executable, '-m', 'magcal_ros.cli', 'fit', name,
                                     '--field-nt', str(F), '-o', 'cal.yaml'], subprocess_env())
                             for name, _ in cases}, timeout_sec=120, cwd=tmp_path)
    for name, match in cases:
        res = runs[name]
        assert res.returncode == 2, res.stderr
        assert res.stderr.count('\n') == 1 and res.stderr.startswith('magcal: error: ')
        assert re.search(match, res.stderr), res.stderr
        assert not (tmp_path / 'cal.yaml').exists()


@pytest.fixture(scope='module')
def spiky():
    """
    Return spiky data, the same without spikes, and the robust fit.

    5 % spikes of 1000 nT (paper 004 errors, 3 nT noise), the same data without them, and
    the robust pipeline fit of the spiky data.
    """
    data, sim = simulate(n_samples=1000, trajectory='random', seed=6, aux=False,
                         outlier_fraction=0.05, outlier_nt=1000.0)
    clean, _ = simulate(n_samples=1000, trajectory='random', seed=6, aux=False)
    hit = np.linalg.norm(data.raw - clean.raw, axis=2) > 100.0        # (S, N) spiked
    run = calibrate(data, 'base', field_nt=F, robust=True)
    return data, clean, sim, hit, run


def flagged(result):
    """(S, N) samples the soft-L1 loss down-weights: a raw residual component > 3 sigma."""
    return (np.abs(result.residual_nt / result.sigma_nt[:, None, None]) > 3.0).any(axis=2)


def test_robust_fit_down_weights_every_spike_and_counts_them(spiky):
    data, clean, sim, hit, run = spiky
    flag = flagged(run.result)
    assert run.summary['downweighted'] == {str(j + 1): int(flag[j].sum()) for j in range(4)}
    # every spike is down-weighted, on its own sensor
    assert np.all(flag[hit])
    # the other down-weighted samples sit at epochs where another sensor spiked (the field
    # of an epoch is shared by the four sensors: a spike pulls its estimate for all) or are
    # the Gaussian tail, as often as a robust fit of the clean data flags (+5 sd)
    tail = flagged(calibrate(clean, 'base', field_nt=F, robust=True).result).sum(axis=1)
    elsewhere = (flag & ~hit.any(axis=0)).sum(axis=1)
    assert np.all(elsewhere <= tail + 5.0 * np.sqrt(tail) + 3), (elsewhere, tail)
    assert np.all(flag.sum(axis=1) < 0.25 * data.n_samples)
    # and the parameters stay within the no-outlier tolerance (as in test_model_ml.py: 4.5
    # standard errors of the clean fit, x1.3 for the efficiency loss of the soft-L1 loss)
    ref = fit(clean, 'base', field_nt=F)
    assert np.all(np.abs(run.result.params - sim.params) < 4.5 * 1.3 * ref.stderr)


def test_cli_robust_fit_reports_the_spikes_it_down_weighted(tmp_path, spiky):
    data, clean, sim, hit, run = spiky
    write_csv(tmp_path / 'spiky.csv', data)
    res = _magcal('fit', 'spiky.csv', '--field-nt', F, '--robust', '--json', '-o', 'cal.yaml',
                  cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    # the CSV keeps 0.1 nT: a sample exactly at the 3-sigma threshold may flip
    for j in '1234':
        assert abs(out['downweighted'][j] - run.summary['downweighted'][j]) <= 2, j
        assert out['downweighted'][j] >= hit[int(j) - 1].sum()
    ref = fit(clean, 'base', field_nt=F)
    cal, _ = load_calibration(tmp_path / 'cal.yaml')
    assert np.all(np.abs(cal.params - sim.params) < 4.5 * 1.3 * ref.stderr)


# -- the calibration node --------------------------------------------------------------------

def start_node(make_node, namespace, tmp_path, **params):
    overrides = {'calibration_file': str(tmp_path / 'cal' / 'calibration.yaml'),
                 'report_dir': str(tmp_path / 'report'), 'min_samples': 300}
    overrides.update(params)
    return make_node(CalibrationNode, namespace=namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in overrides.items()])


def feed_sensors(feeder, executor, node, data, sensors, stop=None, batch=None):
    """Publish epochs of ``data`` for the given sensors only (1-based); wait until taken."""
    stop = data.n_samples if stop is None else stop
    batch = batch or intake_batch(len(sensors))
    base = int(node.received.sum())
    for k0 in range(0, stop, batch):
        k1 = min(k0 + batch, stop)
        for k in range(k0, k1):
            for j in sensors:
                feeder.raw[j - 1].publish(_msg(data, j, k))
        want = base + len(sensors) * k1
        spin_until(executor, lambda: int(node.received.sum()) >= want, 30.0,
                   f'{want - base} samples taken')


def _msg(data, j, k):
    return field_nt_to_msg(data.raw[j - 1, k], stamp=T0 + float(data.t[k]),
                           frame_id=f'fluxgate{j}')


def test_every_refusal_names_the_reason_and_keeps_the_previous_calibration(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, tumbling):
    data, _ = tumbling
    path = tmp_path / 'cal' / 'calibration.yaml'
    path.parent.mkdir()
    save_calibration(path, calibrate(data, 'base', field_nt=F).doc)
    before = path.read_bytes()
    history_before = sorted(os.listdir(str(path) + '.history'))
    results = []
    ros_node.create_subscription(String, 'calibration/result', results.append, RESULT_QOS)
    node = start_node(make_node, ros_namespace, tmp_path)
    spin_until(ros_executor, lambda: results, 5.0, 'the existing calibration on start-up')
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)

    static = _copy(data)
    static.raw[:] = static.raw[:, :1] + np.random.default_rng(1).normal(
        scale=NOISE_NT, size=static.raw.shape)           # the array never moved
    cases = [
        ('too few sets', data, (1, 2, 3, 4), 100,
         r'only 100 complete sample sets collected, need at least 300'),
        ('one attitude', static, (1, 2, 3, 4), None, 'same field direction'),
        ('stuck sensor', stuck(data, 3), (1, 2, 3, 4), None,
         r'sensor 3: output is constant'),
        ('noisy stuck sensor', stuck(data, 2, NOISE_NT), (1, 2, 3, 4), None,
         r'sensor 2: output \(nearly\) constant'),
        ('silent sensor', data, (1, 2, 4), None,
         r'only 0 complete sample sets .*sensor 3 sent no samples since calibration/start'),
    ]
    for name, d, sensors, stop, match in cases:
        assert call_trigger(ros_node, ros_executor, 'calibration/start').success
        feed_sensors(feeder, ros_executor, node, d, sensors, stop)
        resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate')
        assert not resp.success, name
        lines, out = split(resp)
        head = ' '.join(lines[:2])     # a short first line, the reason on the next
        assert re.search(match, head), (name, head)
        assert head.endswith('previous calibration stays active'), name
        assert re.search(match, out['reason']), name
        assert path.read_bytes() == before, name
        assert sorted(os.listdir(str(path) + '.history')) == history_before, name
        assert node.state == 'collecting', name     # still collecting: the user may go on

    # a sensor whose data stop half way: the complete sets before are too few, and the
    # refusal says which sensor is short
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feed_sensors(feeder, ros_executor, node, data, (1, 2, 3, 4), 250)
    spin_for(ros_executor, 0.05)
    rest = _copy(data)
    rest.t = rest.t[250:]
    rest.raw = rest.raw[:, 250:]
    feed_sensors(feeder, ros_executor, node, rest, (1, 3, 4))
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate')
    assert not resp.success
    lines, out = split(resp)
    assert 'sensor 2 sent only 250 samples, the others up to 600' in out['reason'], lines[0]
    status = []
    ros_node.create_subscription(String, 'calibration/status', status.append, 10)
    st = json.loads(spin_until(ros_executor, lambda: status and status[-1], 5.0).data)
    assert any('sensor 2 sent only 250 samples' in m for m in st['missing']) and not st['ready']
    assert path.read_bytes() == before
    # the sentinel, not a fixed wait: the whole recording calibrates, and the one new result
    # is its own (none of the refusals above published anything)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feed_sensors(feeder, ros_executor, node, data, (1, 2, 3, 4))
    assert call_trigger(ros_node, ros_executor, 'calibration/calibrate').success
    spin_until(ros_executor, lambda: len(results) > 1, 5.0, 'the new calibration/result')
    assert len(results) == 2 and results[1].data.encode() == path.read_bytes()


def test_node_robust_fit_reports_down_weighted_spikes(make_node, ros_node, ros_executor,
                                                      ros_namespace, tmp_path, spiky):
    data, clean, sim, hit, run = spiky
    node = start_node(make_node, ros_namespace, tmp_path, robust=True, min_samples=500)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()), temperature=False)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60.0)
    assert resp.success, resp.message
    lines, out = split(resp)
    assert out['robust'] is True and out['sets'] == data.n_samples
    assert any(ln.startswith('robust fit: samples down-weighted as outliers per sensor')
               for ln in lines)
    for j in '1234':
        # the same data as the pipeline fit up to the nT -> T -> nT round trip
        assert abs(out['downweighted'][j] - run.summary['downweighted'][j]) <= 2, j
        assert out['downweighted'][j] >= hit[int(j) - 1].sum()
    ref = fit(clean, 'base', field_nt=F)
    cal, _ = load_calibration(out['calibration_file'])
    assert np.all(np.abs(cal.params - sim.params) < 4.5 * 1.3 * ref.stderr)
    # applied to the same epochs without spikes, the calibration leaves only the noise in
    # the total field (3 nT; the RMS of 1000 samples has a relative sd of ~2 %)
    resid = np.linalg.norm(cal.correct_dataset(clean), axis=2) - F
    assert np.all(np.sqrt(np.mean(resid ** 2, axis=1)) < 1.1 * NOISE_NT)


def test_simultaneous_requests_and_invalid_parameters_leave_a_consistent_state(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, tumbling, monkeypatch):
    data, _ = tumbling
    node = start_node(make_node, ros_namespace, tmp_path)
    path = tmp_path / 'cal' / 'calibration.yaml'
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    clients = {name: ros_node.create_client(Trigger, f'calibration/{name}')
               for name in ('start', 'calibrate', 'diagnose')}
    params = AsyncParameterClient(ros_node, f'{ros_namespace}/calibration_node')
    spin_until(ros_executor, lambda: all(c.service_is_ready() for c in clients.values())
               and params.services_are_ready(), 10.0, 'the services')

    def at_once(*names):
        futures = [clients[n].call_async(Trigger.Request()) for n in names]
        spin_until(ros_executor, lambda: all(f.done() for f in futures), 90.0)
        return [f.result() for f in futures]

    # the solve is held inside the fit until the test lets it go (not "a solve slower than
    # two service calls"): every request below arrives during it, on every machine
    entered, release = threading.Event(), threading.Event()
    solve = calibrating.run_calibration

    def held_solve(*args, **kwargs):
        entered.set()
        assert release.wait(60.0), 'the test never released the solve'
        return solve(*args, **kwargs)

    monkeypatch.setattr(calibrating, 'run_calibration', held_solve)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()), temperature=False)
    n_hist = len(list_history(path))
    # during a solve: diagnose and start are refused, invalid parameters are refused, a
    # valid one is taken, and the solve is not disturbed
    calib = clients['calibrate'].call_async(Trigger.Request())
    spin_until(ros_executor, entered.is_set, 10.0, 'the solve')
    assert node.state == 'calibrating'
    diag, start = at_once('diagnose', 'start')
    bad = {'model': ['base', 'warp_drive'], 'min_samples': -5, 'stamp_tolerance_s': -0.01,
           'field_nt': float('nan'), 'calibration_file': ''}
    refused = {}
    for name, value in bad.items():
        fut = params.set_parameters([Parameter(name, value=value)])
        spin_until(ros_executor, fut.done, 10.0, f'set {name}')
        refused[name] = fut.result().results[0]
    fut = params.set_parameters([Parameter('min_samples', value=200)])
    spin_until(ros_executor, fut.done, 10.0)
    assert fut.result().results[0].successful
    assert not calib.done()
    release.set()
    spin_until(ros_executor, calib.done, 120.0)
    assert calib.result().success, calib.result().message
    assert not diag.success and diag.message.startswith('a calibration is already running')
    assert not start.success and 'a calibration is running' in start.message
    for name, res in refused.items():
        # refused by the node's validator ('<name>: ...') or, for a value outside the
        # declared range or a read-only path, by rclpy's descriptor check (naming it too)
        assert not res.successful and name in res.reason, (name, res.reason)
    assert 'read-only' in refused['calibration_file'].reason
    assert 'out of range' in refused['min_samples'].reason
    assert node.get_parameter('model').value == ['base']
    assert node.get_parameter('calibration_file').value == str(path)
    assert node.get_parameter('min_samples').value == 200
    _, out = split(calib.result())
    assert out['sets'] == data.n_samples and out['calibration_file'] == str(path)
    assert len(list_history(path)) == n_hist + 1
    assert load_calibration(path)[1]['provenance']['samples'] == data.n_samples
    assert node.state == 'collecting'         # collection goes on after a calibrate
    # a calibrate right after a start works on the buffer the start emptied: refused, and
    # the calibration file stays the one just written
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    calib = call_trigger(ros_node, ros_executor, 'calibration/calibrate')
    assert not calib.success and calib.message.startswith(
        'not calibrated:\nonly 0 complete sample sets collected'), calib.message
    assert len(list_history(path)) == n_hist + 1
    assert node.state == 'collecting'


def test_corrector_refuses_invalid_parameters_and_keeps_correcting(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, tumbling):
    data, sim = tumbling
    path = tmp_path / 'cal.yaml'
    save_calibration(path, calibration_to_doc(sim.truth, geometry=cross_geometry(0.5)),
                     history=0)
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    corrected = []
    ros_node.create_subscription(MagneticField, 'sensor1/corrected', corrected.append, 100)
    params = AsyncParameterClient(ros_node, f'{ros_namespace}/corrector_node')
    spin_until(ros_executor, params.services_are_ready, 10.0, 'parameter services')
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    for name, value, match in [('stamp_tolerance_s', -0.005, 'out of range Min: 1e-06'),
                               ('stamp_tolerance_s', 0.0, 'out of range Min: 1e-06'),
                               ('diagnostics_period_s', 5.0, 'read-only'),
                               ('calibration_file', '/elsewhere.yaml', 'read-only'),
                               ('n_sensors', 3, 'read-only')]:
        fut = params.set_parameters([Parameter(name, value=value)])
        spin_until(ros_executor, fut.done, 10.0)
        res = fut.result().results[0]
        assert not res.successful and match in res.reason, (name, res.reason)
    assert node.get_parameter('stamp_tolerance_s').value == 0.005
    feeder.feed(ros_executor, data, stop=50, taken=lambda: node.received, temperature=False)
    spin_until(ros_executor, lambda: len(corrected) == 50, 5.0, '50 corrected samples')
    got = np.array([msg_to_field_nt(m) for m in corrected])
    np.testing.assert_allclose(got, sim.truth.correct(1, data.raw[0, :50]), atol=1e-6)


def test_corrector_with_a_silent_sensor_keeps_correcting_the_others(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, tumbling):
    data, sim = tumbling
    path = tmp_path / 'cal.yaml'
    save_calibration(path, calibration_to_doc(sim.truth, geometry=cross_geometry(0.5)),
                     history=0)
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    corrected = [[] for _ in range(4)]
    for j in range(4):
        ros_node.create_subscription(MagneticField, f'sensor{j + 1}/corrected',
                                     corrected[j].append, 500)
    gradient = []
    ros_node.create_subscription(Float64MultiArray, 'gradient', gradient.append, 100)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    # sensor 3 never reports: the others are corrected sample by sample, the gradient needs
    # all four, so none is published, and the queues of the others stay bounded
    n = 300
    for k0 in range(0, n, 5):
        for k in range(k0, k0 + 5):
            for j in (1, 2, 4):
                feeder.raw[j - 1].publish(_msg(data, j, k))
        spin_until(ros_executor, lambda: node.received >= 3 * (k0 + 5), 10.0)
    spin_until(ros_executor, lambda: all(len(corrected[j - 1]) == n for j in (1, 2, 4)), 5.0)
    # no fixed wait for "nothing arrived": the node's own counters (below) say what it sent,
    # and every sample it took is already accounted for on the other topics
    assert corrected[2] == [] and gradient == []
    for j in (1, 2, 4):
        got = np.array([msg_to_field_nt(m) for m in corrected[j - 1]])
        np.testing.assert_allclose(got, sim.truth.correct(j, data.raw[j - 1, :n]), atol=1e-6)
    status = {kv.key: kv.value for kv in node.diagnostic_status().values}
    assert status['sensor3_corrected_published'] == '0'
    assert status['gradient_published'] == '0'
    queued = node.queued
    assert queued[2] == 0 and all(q <= StampMatcher(4, 0.01).max_queue for q in queued), queued


def test_a_calibration_far_above_the_noise_floor_says_so():
    # the fit's own noise estimate against the model-free floor of the raw series: a hidden
    # 4x-floor temperature effect on sensor 2, and sensor 3 paired one epoch late, are both
    # named; a complete model on consistent data gives no such line (1.5x is > 20 sd of the
    # 3 nT estimates from 3000 epochs)
    data, _ = simulate(n_samples=3000, rate_hz=10.0, trajectory='smooth', seed=1,
                       truth={'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]})
    warned = [w for w in calibrate(data, 'base', field_nt=50000.0).summary['warnings']
              if w['kind'] == 'missing_effect']
    assert len(warned) == 1 and warned[0]['sensor'] == 2
    assert warned[0]['text'].startswith('sensor 2: the model leaves')
    assert 'run diagnose' in warned[0]['text']
    clean = calibrate(data, 'base,temperature@2', field_nt=50000.0).summary['warnings']
    assert not [w for w in clean if w['kind'] == 'missing_effect']
    late = data.subset(np.arange(data.n_samples))
    late.raw[2, :-1] = data.raw[2, 1:]
    warned = [w for w in calibrate(late, 'base,temperature@2', field_nt=50000.0)
              .summary['warnings'] if w['kind'] == 'missing_effect']
    assert [w['sensor'] for w in warned] == [3]


def test_garbage_of_a_single_magnetometer_is_excluded():
    # the one magnetometer of an ordinary robot: three garbled lines (a cut line, a lost
    # digit, a 12 000 nT jump) pull the least-squares fit to 160 nT; the robust fit's noise
    # must be that sensor's own (3 nT), so that 5 sigma of it finds the three.  Before
    # 2026-11-27 it read 0.64 nT (the MAD of all three residual components, two of which the
    # field takes up), 194 of 2600 sets were beyond "5 sigma", too many for garbage, and
    # nothing was excluded.  The clean fit's noise within 4/sqrt(2 N) of 3 nT.
    data, _ = simulate(n_samples=2600, rate_hz=100.0, n_sensors=1, trajectory='smooth', seed=0)
    bad = data.subset(np.arange(data.n_samples))
    bad.raw = data.raw.copy()
    bad.raw[0, 500, 0] = 45.6
    bad.raw[0, 1200, 2] /= 10.0
    bad.raw[0, 2000, 1] += 12000.0
    # the readings screen finds the three as spikes before the fit (issue 32, test_spikes);
    # without it, the outlier exclusion after the fit must find them
    spikes = calibrate(bad, 'base', field_nt=50000.0)
    assert spikes.summary['readings_left_out']['sets_left_out'] == 3
    np.testing.assert_allclose(spikes.result.sigma_nt, 3.0, rtol=4.0 / np.sqrt(2 * 2597))
    assert calibrate(bad, 'base', field_nt=50000.0, screen=False).result.sigma_nt[0] > 90.0
    clean = calibrate(bad, 'base', field_nt=50000.0, exclude_outliers=True, screen=False)
    assert clean.summary['outlier_sets_excluded'] == 3
    np.testing.assert_allclose(clean.result.sigma_nt, 3.0, rtol=4.0 / np.sqrt(2 * 2597))


def test_garbage_that_survived_the_transport_is_excluded_and_counted():
    # what a live calibration can be handed: a cut line (x off by ~12 000 nT), a digit lost
    # (z / 10), and 80 sets of one sensor paired 30 epochs off (beyond resync's 10): the
    # least-squares fit is pulled to 250-530 nT on sensors 2-4, which hold the garbage, and
    # to 22 nT on sensor 1, which is clean (the parameters of the array go with the rest);
    # excluding the sets beyond 5 sigma of a robust fit (83 of 2600: 80 + 3 garbled) brings
    # every sensor back to the 3 nT noise
    data, _ = simulate(n_samples=2600, rate_hz=100.0, trajectory='smooth', seed=0)
    raw = data.raw.copy()
    raw[2, 1000:1080] = data.raw[2, 1030:1110]
    raw[3, 1500, 0] = 45.6
    raw[1, 300, 2] /= 10.0
    bad = data.subset(np.arange(data.n_samples))
    bad.raw = raw
    # the readings screen would take the two garbled readings as spikes (test_spikes): off,
    # so that the outlier exclusion after the fit meets all the garbage
    plain = calibrate(bad, 'base', field_nt=50000.0, screen=False)
    assert plain.result.sigma_nt[1:].min() > 30 * 3.0
    assert plain.result.sigma_nt[0] > 5 * 3.0
    clean = calibrate(bad, 'base', field_nt=50000.0, exclude_outliers=True, screen=False)
    assert 80 <= clean.summary['outlier_sets_excluded'] <= 90
    np.testing.assert_allclose(clean.result.sigma_nt, 3.0, rtol=0.06)
    assert clean.doc['provenance']['samples'] == data.n_samples - \
        clean.summary['outlier_sets_excluded']
    assert clean.summary['warnings'][-1]['kind'] == 'outliers'
    assert 'sets excluded' in clean.summary['warnings'][-1]['text']
    assert clean.doc['provenance']['warnings'][-1] == clean.summary['warnings'][-1]
    # a missing effect is not garbage: nothing excluded, the warning stays
    temp, _ = simulate(n_samples=2600, rate_hz=10.0, trajectory='smooth', seed=1,
                       truth={'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]})
    kept = calibrate(temp, 'base', field_nt=50000.0, exclude_outliers=True)
    assert kept.summary['outlier_sets_excluded'] == 0
    assert kept.doc['provenance']['samples'] == temp.n_samples
    assert [w['sensor'] for w in kept.summary['warnings'] if w['kind'] == 'missing_effect'] \
        == [2]
    # clean data: the check costs nothing and changes nothing
    ok = calibrate(data, 'base', field_nt=50000.0, exclude_outliers=True)
    assert ok.summary['outlier_sets_excluded'] == 0
    np.testing.assert_array_equal(ok.result.params,
                                  calibrate(data, 'base', field_nt=50000.0).result.params)
