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

"""`magcal simulate` and `magcal fit` (docs/design.md §2), run as a user would."""
import json
import subprocess
import sys

from magcal_ros.cli import main
import pytest


def run_cli(*args):
    """Run the real command in a subprocess; returns (rc, stdout, stderr)."""
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                       capture_output=True, text=True, timeout=240)
    return p.returncode, p.stdout, p.stderr


@pytest.fixture(scope='module')
def sim_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp('cli') / 'sim.csv'
    rc, _, err = run_cli('simulate', '--out', path, '--n', 3000, '--seed', 3)
    assert rc == 0, err
    return path


def test_fit_json_and_calibration_file(sim_csv, tmp_path):
    out = tmp_path / 'cal.yaml'
    rc, stdout, err = run_cli('fit', sim_csv, '--model', 'base', '--field-nt', 50000, '--json',
                              '-o', out)
    assert rc == 0, err
    doc = json.loads(stdout)
    for key in ('model', 'scalar_rms_nt', 'vector_rms_nt', 'noise_floor_nt',
                'tensor_rms_nt_per_m', 'output'):
        assert key in doc
    assert doc['output'] == str(out) and out.exists()
    # 3 nT simulated noise; RMS of 3000 samples within 6 %
    assert all(v < 3.0 * 1.06 for v in doc['scalar_rms_nt'].values())
    assert abs(doc['noise_floor_nt'] - 3.0) < 0.3
    assert max(max(r) for r in doc['tensor_rms_nt_per_m']) < 1.1 * 12.0


def test_exit_codes(sim_csv, tmp_path):
    rc, out, err = run_cli('fit', sim_csv, '--model', 'base')
    assert rc == 2 and 'no reference field' in err and out == ''
    rc, _, err = run_cli('fit', sim_csv, '--model', 'base,warp', '--field-nt', 5e4)
    assert rc == 2 and "unknown effect 'warp'" in err
    rc, _, err = run_cli('fit', tmp_path / 'missing.csv', '--field-nt', 5e4)
    assert rc == 2 and 'no such file' in err
    turn = tmp_path / 'turn.csv'
    assert run_cli('simulate', '--out', turn, '--trajectory', 'turntable', '--n', 2000)[0] == 0
    rc, _, err = run_cli('fit', turn, '--field-nt', 5e4)
    assert rc == 2 and 'rotation about one axis only' in err
    assert len(err.strip().splitlines()) == 1


def test_igrf_reference(sim_csv, capsys):
    rc = main(['fit', str(sim_csv), '--model', 'base', '--igrf', '45', '10', '0', '2025-01-01',
               '--json', '--flag-degenerate'])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0
    # IGRF at 45N 10E is about 47 500 nT (within 2 %)
    assert abs(doc['field_reference']['magnitude_nt'] - 47500) < 1000
