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
Smoke test of the benchmarks: each command runs with tiny settings and writes valid JSON.

Performance is measured by the benchmarks themselves (bench/, BENCHMARKS.md), never here:
these tests only check that every benchmark still runs end to end and that its result file
holds the machine description and the figures BENCHMARKS.md is built from.
"""
import json
import math
import pathlib
import subprocess
import sys

import pytest

BENCH = pathlib.Path(__file__).resolve().parents[1] / 'bench'

CASES = {
    'accuracy': ['--seeds', '2', '--holdout', '100', '--scenarios', 'paper004', 'cone60',
                 'site_gradient'],
    'papers': ['--seeds', '2', '--holdout', '100'],
    'solve_time': ['--sizes', '400', '800', '--models', 'base', '--diagnose-max-n', '400',
                   '--no-blas-compare', '--repeat', '1'],
    'live': ['--rates', '50', '--repeats', '1', '--duration', '1', '--warmup', '0.5',
             '--drain', '0.5', '--no-search'],
    'real_data': ['--no-diagnose'],
    # the node at 4 x 100 Hz, not the default 4 x 1 kHz: the driver still uses ~12 % of a core
    'driver_rate': ['--samples', '300', '--pty-mbytes', '0.05', '--protocols', 'ascii',
                    'lemi025', '--node-duration', '1', '--node-warmup', '0.5',
                    '--node-rate', '100'],
    'workbench': ['--sizes', '300', '--before', 'none', '--no-ladder', '--no-warmup'],
    'pairing': ['--epochs', '1500', '--repeats', '1'],
    'report_layout': ['--n', '600', '--repeat', '1', '--no-warmup'],
    'grammar_speed': ['--n', '300', '--repeat', '1', '--pairs', '2'],
    # one storage: both are read by the same code, tested in test_bag_decode / test_long_records
    'scale': ['--sizes', '1500', '--bag-max', '1500', '--storages', 'mcap', '--plot-at-end'],
    'reduction_accuracy': ['--sizes', '6000'],
    'executor': ['--rate', '50', '--duration', '1', '--repeats', '1'],
    'vehicle_logs': ['--minutes', '1', '--mag-rate', '50'],
    'attitude_aided': ['--seeds', '1', '--tilts', '15', '--n', '1200'],
}


def _run(name, tmp_path, extra=()):
    out = tmp_path / name
    proc = subprocess.run([sys.executable, str(BENCH / f'{name}.py'), '--out-dir', str(out)]
                          + CASES[name] + list(extra), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads((out / f'{name}.json').read_text())
    assert doc['benchmark'] == name
    for key in ('cpu_model', 'cpu_count', 'python', 'numpy'):
        assert doc['machine'][key]
    assert doc['tables'] and all(t.strip() for t in doc['tables'])
    assert doc['tables'][0] in proc.stdout        # the same table is printed
    return doc


def test_accuracy(tmp_path):
    res = _run('accuracy', tmp_path)['results']['scenarios']
    ml = res['paper004']['methods']['ml']
    assert ml['n_ok'] == 2
    # even 2 seeds land near the floor: 2000 nT-level errors would mean a broken pipeline
    assert 0.8 < ml['scalar_hold_over_floor'] < 1.5
    assert math.isfinite(ml['params']['scale']['over_crb'])
    assert set(res['cone60']['methods']) >= {'algebraic', 'ml', 'ml_constrained'}
    site = res['site_gradient']
    # with attitude the fit reaches the floor; without the effect it stays far above
    assert site['methods']['ml_site']['scalar_over_floor'] < 1.1
    assert site['methods']['ml_base']['scalar_over_floor'] > 5
    assert site['crb_sd_by_group']['none_undetermined_directions'] == 20


def test_papers(tmp_path):
    res = _run('papers', tmp_path)['results']
    assert res['paper000_sigma3']['methods']['paper000']['n_ok'] == 2
    assert res['paper002_3d']['methods']['paper002']['scalar_hold_over_floor'] < 1.5
    # both methods must say that single-axis data do not determine the model
    assert not res['paper002_table2']['paper002']['identifiable']
    assert res['paper002_table2']['planar36']['refined']['refused']


def test_solve_time(tmp_path):
    res = _run('solve_time', tmp_path)['results']
    cases = res['cases']
    assert [c['n'] for c in cases] == [400, 800]
    assert all(c['calibrate_s'] > 0 and c['calibrate_peak_mib'] is not None for c in cases)
    # the diagnosis is part of the package: it must run, never be reported as missing
    assert cases[0]['diagnose_s'] > 0 and 'diagnose_error' not in cases[0]
    assert res['exponents']['base']['calibrate_all'] is not None


@pytest.mark.live           # a live pipeline: beside the batch tests it lost half its messages
def test_live(tmp_path):
    res = _run('live', tmp_path)['results']
    runs = {r['node']: r for r in res['runs']}
    assert set(runs) == {'relay', 'corrector'}
    for r in runs.values():
        assert 'error' not in r, r.get('error')
        # 50 Hz x 4 sensors for 1 s is far below any limit: nearly everything arrives
        assert r['published'] >= 150 and r['received'] >= 0.9 * r['published']
        assert r['latency_ms']['p50'] > 0


@pytest.mark.timeout(180)
def test_driver_rate(tmp_path):
    res = _run('driver_rate', tmp_path)['results']
    for proto in ('ascii', 'lemi025'):
        p = res['protocols'][proto]
        assert p['parser_samples_per_s'] > 0 and p['reader_samples_per_s'] > 0
    node = res['driver_node']
    assert 'error' not in node, node.get('error')
    assert node['received'] > 0 and node['cpu_percent']['driver'] > 0


def test_real_data(tmp_path):
    res = _run('real_data', tmp_path)['results']
    rows = {r['recording']: r for r in res['recordings']}
    assert len(rows) == 14                   # 13 HMC5883L recordings and ck-accmag
    assert {r['coverage'] for k, r in rows.items() if 'rotate' in k} == {'single axis'}
    # the independent geometric fit and this package's agree on the full spheres
    for k in ('hmc5883l/full-sphere', 'ck-accmag'):
        assert rows[k]['scalar_rms_nt'] == pytest.approx(rows[k]['independent_rms_nt'],
                                                         rel=0.02)
    assert not res['static']['consistent'] and len(res['static']['rows']) == 4


def test_workbench(tmp_path):
    doc = _run('workbench', tmp_path)
    case = doc['results']['cases'][0]
    assert case['n'] == 300 and 'before' not in case
    assert case['after']['diagnose_s'] > 0 and case['after']['report_s'] > 0


def test_report_layout(tmp_path):
    doc = _run('report_layout', tmp_path)
    best = doc['results']['cpu_s_best']
    assert set(best) == {'fixed margins (the report)', 'constrained layout',
                         'Pillow level 1 (the report)', 'Pillow level 6 (default)'}
    assert all(v > 0 for v in best.values())


def test_pairing(tmp_path):
    doc = _run('pairing', tmp_path)
    res = doc['results']
    # clean streams: the check changes no set; under load it drops the sets it cannot pair
    assert res['clean']['checked'] == res['clean']['stamps_only']
    assert res['clean']['checked']['rejected'] == 0
    assert res['loaded']['checked']['repaired'] >= 1
    assert all(r['us_per_sample_checked'] > 0 for r in res.values())


def test_grammar_speed(tmp_path):
    doc = _run('grammar_speed', tmp_path)
    pairs = doc['results']['pairs']
    assert [p['alias'] for p in pairs] == ['drift2', 'periodic(0.05)@3']
    assert all(p['cpu_comp_s'] > 0 and p['nfev_comp'] > 0 for p in pairs)


def test_scale(tmp_path):
    # its own data folder: the default /tmp/magcal_scale is shared by every run on the
    # machine (a record or bag left there by other code would be reused, and the simulation
    # and the bag writing would not run)
    doc = _run('scale', tmp_path, ['--data-dir', str(tmp_path / 'data')])
    runs = doc['results']['runs']
    assert {(r['input'], r['command']) for r in runs} == {
        (i, c) for i in ('csv', 'bag mcap') for c in ('fit', 'diagnose')}
    assert all(r['exit'] == 0 and r['peak_rss_mb'] > 0 for r in runs)
    assert (tmp_path / 'scale' / 'scale.png').exists()
    assert len(doc['results']['bag_reads']) == 1
    assert doc['results']['bag_reads'][0]['write']['messages'] > 0    # written, not cached


def test_reduction_accuracy(tmp_path):
    rows = _run('reduction_accuracy', tmp_path)['results']['rows']
    assert rows[0]['epochs'] == 6000 and rows[0]['sample_epochs'] < 6000
    assert rows[0]['max_param_diff_sd'] < 4.5


@pytest.mark.live           # ROS messages counted in real time (see test_live)
def test_executor(tmp_path):
    res = _run('executor', tmp_path)['results']
    runs = res['runs']
    assert [r['executor'] for r in runs] == ['single', 'events']
    # 4 topics at 50 Hz for 1 s: about 200 messages each, some lost to start-up at most
    assert all(100 <= r['messages'] <= 220 and r['cpu_s'] > 0 for r in runs), runs
    assert res['ratio'] > 0


def test_vehicle_logs(tmp_path):
    runs = _run('vehicle_logs', tmp_path)['results']['runs']
    assert [r['format'] for r in runs] == ['dataflash', 'ulog']
    for r in runs:
        # a minute at 50 Hz: every epoch read, the fit takes IGRF from the log's GPS
        assert r['read_exit'] == 0 and r['epochs'] == 3000 and r['sensors'] == 3
        assert r['fit_exit'] == 0 and r['fit_field_reference'] == 'igrf'
        assert r['read_peak_rss_mb'] > 0 and r['fit_cpu_s'] > 0


def test_attitude_aided(tmp_path):
    cases = _run('attitude_aided', tmp_path)['results']['cases']
    assert [(c['tilt_deg'], c['mode']) for c in cases] == [(15.0, 'tilt'), (15.0, 'full')]
    for c in cases:
        # one seed, 1200 epochs of 3 nT noise: the residual at the noise, nothing left open
        assert abs(c['residual_over_noise_median'] - 1) < 0.1 and c['n_z'] == 9
        assert c['undetermined_counts'] == {} and c['cpu_s_median'] > 0
