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

"""`magcal diagnose` and `magcal report` (docs/design.md §2), run as a user would."""
import json
import os
import pathlib
import subprocess
import sys

from magcal_ros.cli import main
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.bag import write_bag
from magcal_ros.io.csvio import write_csv
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
#: hidden offset temperature coefficient of sensor 2, nT/degC: scalar RMS ~4 x the 3 nT floor
TEMP2 = 'temperature@2=3,-2,1.5,0,0,0'


def run_cli(*args, env=None):
    """Run the real command in a subprocess; returns (rc, stdout, stderr)."""
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                       capture_output=True, text=True, timeout=300,
                       env={**os.environ, **(env or {})})
    return p.returncode, p.stdout, p.stderr


@pytest.fixture(scope='module')
def temp_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp('wb') / 'temp2.csv'
    rc, _, err = run_cli('simulate', '--out', path, '--n', 3000, '--rate', 10, '--seed', 9,
                         '--truth', TEMP2)
    assert rc == 0, err
    return path


def test_diagnose_json_and_report(temp_csv, tmp_path):
    rep = tmp_path / 'rep'
    rc, out, err = run_cli('diagnose', temp_csv, '--model', 'base', '--field-nt', 50000,
                           '--json', '--report', rep, '--ladder')
    assert rc == 0, err
    doc = json.loads(out)                       # exactly one JSON object on stdout
    for key in ('model', 'noise_floor_nt', 'scalar_rms_nt', 'vector_rms_nt', 'candidates',
                'verdict'):
        assert key in doc
    assert doc['verdict']['effect'] == 'temperature' and doc['verdict']['sensor'] == 2
    assert doc['candidates'][0]['effect'] == 'temperature'
    assert doc['field_reference'] == {'kind': 'constant', 'magnitude_nt': 50000.0}
    assert doc['report'] == str(rep / 'index.html') and (rep / 'index.html').exists()
    assert (rep / 'candidates.png').exists() and (rep / 'ladder.png').exists()
    steps = doc['ladder']['steps']
    assert [st['added'] for st in steps] == [None, 'temperature@2']
    assert steps[1]['verdict'] is None
    # held-out RMS falls to the 3 nT floor (the diagnosis' 10 % criterion)
    assert steps[1]['cv_rms_nt'] < 1.1 * doc['noise_floor_nt']
    assert steps[0]['cv_rms_nt'] > 2 * doc['noise_floor_nt']
    # stderr is not a terminal here: no progress display (magcal_ros.progress)
    assert 'screen' not in err and 'cross-validate' not in err


def test_report_from_rosbag(tmp_path, capsys):
    # one sensor keeps this fast: the four-sensor path is covered above
    data, _ = simulate(n_samples=1500, rate_hz=5.0, trajectory='smooth', seed=3, n_sensors=1,
                       truth={'aux:aux_motor_current@1': [12.0, -6.0, 8.0]})
    bag = write_bag(tmp_path / 'bag', data)
    out_dir = tmp_path / 'report'
    assert main(['report', str(bag), '--model', 'base', '--field-nt', '50000',
                 '--out', str(out_dir), '-q', '--figures', 'all']) == 0
    out, _ = capsys.readouterr()
    assert out.strip() == str(out_dir / 'index.html')
    html = (out_dir / 'index.html').read_text()
    assert 'verdict: <b>aux:aux_motor_current@1</b>' in html
    assert (out_dir / 'ladder.png').exists()
    # --figures all: also the views nothing points at (by default left out, and listed)
    for name in ('residual_rate', 'residual_direction', 'residual_temperature'):
        assert (out_dir / f'{name}.png').exists(), name
    assert 'nothing points at' not in html


@pytest.mark.parametrize('args, msg', [
    (['diagnose', 'no_such.csv', '--field-nt', '50000'], 'no such file'),
    (['diagnose', '{csv}', '--model', 'base,warp_drive'], "unknown effect 'warp_drive'"),
    (['diagnose', '{csv}', '--field-nt', '50000', '--folds', '1'], '--folds must be'),
    (['diagnose', '{csv}'], 'no reference field'),
    (['report', '{csv}', '--field-nt', '-3', '--out', '{tmp}'], '--field-nt must be positive'),
])
def test_bad_input_exit_2(temp_csv, tmp_path, capsys, args, msg):
    args = [a.format(csv=temp_csv, tmp=tmp_path) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith('magcal: error:') and msg in err and err.count('\n') == 1


def test_plugin_from_cli(tmp_path):
    env = {'PYTHONPATH': os.pathsep.join([str(REPO / 'examples'),
                                          os.environ.get('PYTHONPATH', '')])}
    csv = tmp_path / 'wheel.csv'
    rc, _, err = run_cli('simulate', '--out', csv, '--n', 3000, '--rate', 10, '--seed', 6,
                         '--plugin', 'my_effect', '--truth', 'wheel@3=12,-8,6,4,10,-6', env=env)
    assert rc == 0, err
    rc, out, err = run_cli('diagnose', csv, '--field-nt', 50000, '--plugin', 'my_effect',
                           '--json', env=env)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc['verdict']['token'] == 'wheel@3'
    before = doc['scalar_rms_nt']['3']
    rc, out, err = run_cli('fit', csv, '--model', 'base,wheel@3', '--field-nt', 50000,
                           '--plugin', 'my_effect:WheelInterference', '--json', env=env)
    assert rc == 0, err
    after = json.loads(out)['scalar_rms_nt']['3']
    # the error falls from ~3 x to the 3 nT floor (10 % criterion of the diagnosis)
    assert before > 2.5 * 3.0 and after < 1.1 * 3.0


def test_single_sensor_csv_option(tmp_path, capsys):
    csv = tmp_path / 'imu.csv'
    data, _ = simulate(n_samples=1500, rate_hz=10.0, trajectory='smooth', seed=4,
                       n_sensors=1, aux=False)
    rows = ['mx,my,mz'] + [','.join(f'{v / 1e5:.8f}' for v in r) for r in data.raw[0]]
    csv.write_text('\n'.join(rows) + '\n')
    assert main(['diagnose', str(csv), '--unit', 'gauss', '--rate-hz', '10',
                 '--field-nt', 'auto', '--json', '-q']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['verdict']['effect'] == 'none'
    assert doc['model'] == ['base']
    # text output, with the ladder (a single rung: nothing to add)
    assert main(['diagnose', str(csv), '--unit', 'gauss', '--rate-hz', '10',
                 '--field-nt', 'auto', '--ladder', '-q']) == 0
    out, err = capsys.readouterr()
    assert 'verdict: none (the residual is at the noise floor' in out
    assert 'error ladder' in out and err == ''
    # without --unit the wide-CSV reader refuses the unknown columns
    assert main(['diagnose', str(csv), '--field-nt', 'auto']) == 2
    assert "unknown column 'mx'" in capsys.readouterr().err


def test_wide_csv_round_trip_diagnoses(tmp_path, capsys):
    data, _ = simulate(n_samples=1500, rate_hz=5.0, trajectory='smooth', seed=5,
                       diurnal_swing_nt=30.0)
    path = tmp_path / 'ref.csv'
    write_csv(path, data)
    # the ref_total column is the reference: no --field-nt needed
    assert main(['diagnose', str(path), '--json', '-q', '--folds', '0']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['field_reference']['kind'] == 'ref_total'
    assert doc['cv_rms_nt'] is None
