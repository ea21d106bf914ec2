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
`magcal fit --json` carries the calibration (issue 22 item 3), the same document as the file.

The data are written by test/injection.py (each sensor raw_j = K_j B + o_j + noise, by hand),
so the offsets and the field the JSON's matrices give back are checked against values stated
there, not against the package's own forward model.
"""
import contextlib
import io
import json
import pathlib

from injection import F_NT, make, SENSORS, SIGMA_NT
from magcal_ros.cli import main
from magcal_ros.core.discovery import jsonable
from magcal_ros.io.csvio import write_csv
import numpy as np
import pytest
import yaml

REPO = pathlib.Path(__file__).resolve().parents[1]
N = 3000


@pytest.fixture(scope='module')
def fitted(tmp_path_factory):
    """Fit injected data: (data, JSON printed by fit --json, the YAML file it wrote)."""
    d = tmp_path_factory.mktemp('fitjson')
    data = make(n=N, seed=7)
    write_csv(d / 'rec.csv', data)
    cal = d / 'cal.yaml'
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(['fit', str(d / 'rec.csv'), '--field-nt', str(F_NT), '--json', '-o', str(cal)])
    assert rc == 0
    return data, json.loads(out.getvalue()), yaml.safe_load(cal.read_text())


def test_the_json_holds_the_document_of_the_file(fitted):
    _, doc, filed = fitted
    # the same document: equal key for key, number for number (non-finite -> null in JSON)
    assert doc['calibration'] == jsonable(filed)
    assert doc['calibration']['kind'] == 'magcal_ros/calibration'


def test_every_parameter_has_value_unit_and_standard_uncertainty(fitted):
    _, doc, _ = fitted
    cal = doc['calibration']
    assert [s['id'] for s in cal['sensors']] == [1, 2, 3, 4]
    names = set()
    for s in cal['sensors']:
        for eff in s['effects']:
            names.add(eff['name'])
            for p in eff['params'].values():
                assert set(p) == {'value', 'unit', 'stderr'}
                assert isinstance(p['unit'], str) and p['unit']
                assert p['stderr'] > 0
        for key, shape in (('correction_matrix', (3, 3)), ('intrinsic_correction', (3, 3)),
                           ('rotation_to_sensor1', (3, 3)), ('offset_nt', (3,))):
            assert np.shape(s[key]) == shape
    assert {'offset', 'scale', 'nonorthogonality'} <= names
    geo = cal['geometry']
    assert geo['type'] == 'cross' and geo['baseline_m'] == 0.5
    assert np.shape(geo['positions_m']) == (4, 3)


def test_the_json_calibration_gives_back_the_injected_sensors(fitted):
    data, doc, _ = fitted
    cal = doc['calibration']
    corrected = []
    for j, s in enumerate(cal['sensors']):
        # offsets: injection.SENSORS (nT), within 5 of the stated standard uncertainties
        off = next(e for e in s['effects'] if e['name'] == 'offset')['params']
        se = np.array([p['stderr'] for p in off.values()])
        assert np.all(np.abs(np.array(s['offset_nt']) - SENSORS[j][3]) < 5 * se), (j, se)
        assert np.allclose([p['value'] for p in off.values()], s['offset_nt'])
        # the matrix and offset alone (base model: nothing driven) correct the raw readings
        a_inv = np.array(s['correction_matrix'])
        corrected.append((data.raw[j] - np.array(s['offset_nt'])) @ a_inv.T)
    corrected = np.array(corrected)
    # |B| = F within the noise: the RMS of N(0, 3 nT) over 3000 samples is 3 nT +- 1.3 %;
    # 10 % covers that and the fit's few degrees of freedom
    rms = np.sqrt(np.mean((np.linalg.norm(corrected, axis=2) - F_NT) ** 2, axis=1))
    assert np.all(rms < 1.1 * SIGMA_NT), rms
    # and every sensor in sensor 1's frame: the vectors agree to the noise of two sensors
    # (sqrt(2) x 3 nT per axis)
    diff = corrected[1:] - corrected[0]
    assert np.all(np.sqrt(np.mean(diff ** 2, axis=(1, 2))) < 1.1 * np.sqrt(2) * SIGMA_NT)


def test_paper_method_json_holds_the_document_of_the_file(tmp_path, capsys):
    cal = tmp_path / 'ref.yaml'
    rc = main(['fit', str(REPO / 'test' / 'data' / 'paper002_table2.csv'), '--method',
               'reference', '--flag-degenerate', '--json', '-o', str(cal)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['calibration'] == jsonable(yaml.safe_load(cal.read_text()))
    assert doc['calibration']['sensors'][0]['effects']
