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
Effect tokens with arguments (``step(300)@1``) accepted everywhere a model is given.

The fault is written by hand (test/injection.py), the command line is run as a user would,
the calibration file is read back, and the calibration node's validator is asked.
"""
import json

import injection as inj
from magcal_ros.cli import main
from magcal_ros.io.calfile import load_calibration
from magcal_ros.io.csvio import write_csv
from magcal_ros.ros.params import model_check
import numpy as np

TOKENS = 'step(300)@1,periodic(0.23)@3,lag(temperature)@2'


def test_cli_fit_accepts_tokens_with_arguments_and_the_file_round_trips(tmp_path, capsys):
    def faults(t, temp, aux, b):
        out = inj.step_fault(300.0, (40.0, -20.0, 10.0), 1)(t, temp, aux, b)
        out[3] = inj.periodic_fault(0.23, 15.0, 3)(t, temp, aux, b)[3]
        out[2] = inj.lag_fault(90.0, (4.0, -3.0, 2.5), 2)(t, temp, aux, b)[2]
        return out
    data = inj.make(3000, seed=4, inject=faults)
    csv = tmp_path / 'd.csv'
    write_csv(csv, data)
    cal = tmp_path / 'cal.yaml'
    rc = main(['fit', str(csv), '--model', 'base,' + TOKENS, '--field-nt', '50000', '-o',
               str(cal), '--json'])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    # every fault explained: each sensor's scalar RMS within 4 % of the 3 nT noise
    assert max(out['scalar_rms_nt'].values()) < 1.04 * inj.SIGMA_NT, out['scalar_rms_nt']
    loaded, doc = load_calibration(cal)
    for tok in TOKENS.split(',')[:1] + ['periodic(0.23)@3', 'lag(temperature)@2']:
        assert tok in doc['model']
    # the calibration read back corrects like the fit: |corrected| = F to the noise
    cor = loaded.correct_dataset(data)
    mag = np.linalg.norm(cor, axis=2) - inj.F_NT
    assert np.sqrt(np.mean(mag ** 2, axis=1)).max() < 1.04 * inj.SIGMA_NT


def test_bad_token_is_one_line_exit_2(tmp_path, capsys):
    data = inj.make(300, seed=4)
    csv = tmp_path / 'd.csv'
    write_csv(csv, data)
    rc = main(['fit', str(csv), '--model', 'base,step(abc)@1', '--field-nt', '50000'])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and 'not a number' in err


def test_calibration_node_validator_uses_the_same_parser():
    check = model_check(4)
    assert check(['base'] + TOKENS.split(',')) is None
    assert check(['base', 'aux_poly(aux_motor_current,2)@1']) is None
    assert 'needs arguments' in check(['base', 'step'])
