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

"""The demo's site-gradient option (README "Demo": ``scripts/demo.sh --site-gradient``)."""
import json
import math
import pathlib
import shlex
import subprocess

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: the README's default gradient GXX,GXY,GXZ,GYY,GYZ (nT/m), written here by hand
TRUTH = np.array([300.0, -250.0, 400.0, -150.0, 200.0])
SIGMA_NT = 3.0          # the simulator's noise sd per axis (the demo's default)
N_SETS = 3000           # the demo's default


def _readme_command():
    readme = (ROOT / 'README.md').read_text()
    lines = [ln.strip() for ln in readme.splitlines()
             if ln.strip().startswith('scripts/demo.sh --site-gradient')]
    assert len(lines) == 1, lines
    return lines[0]


def _run(cmd, cwd):
    argv = shlex.split(cmd)
    return subprocess.run(['bash', str(ROOT / argv[0]), *argv[1:]], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def test_readme_site_gradient_demo(tmp_path):
    """README command as written: after at the floor, gradient within its uncertainty."""
    p = _run(_readme_command(), tmp_path)
    assert p.returncode == 0, p.stdout + p.stderr
    assert 'OFFLINE' in p.stdout
    out = tmp_path / 'demo_out'
    s = json.loads((out / 'summary.json').read_text())
    assert s['noise_sd_simulated_nt'] == SIGMA_NT and s['n_sets'] == N_SETS
    # the RMS of N residuals of sd sigma scatters by sigma / sqrt(2N) (0.04 nT here): allow 5x
    tol = 5 * SIGMA_NT / math.sqrt(2 * N_SETS)
    assert abs(s['noise_floor_nt'] - SIGMA_NT) < tol, s['noise_floor_nt']
    after = np.array(list(s['scalar_rms_after_nt'].values()))
    before = np.array(list(s['scalar_rms_before_nt'].values()))
    assert after.shape == (4,) and np.all(np.abs(after - SIGMA_NT) < tol), after
    # base cannot absorb ~100 nT of difference across the cross: clearly above the floor
    assert np.all(before > 5 * SIGMA_NT), before
    # recovered gradient within 4 of its standard uncertainties of the truth
    g = np.array(s['gradient_fit_nt_per_m'])
    se = np.array(s['gradient_stderr_nt_per_m'])
    assert s['gradient_components'] == ['gxx', 'gxy', 'gxz', 'gyy', 'gyz']
    assert np.all(np.abs(g - TRUTH) < 4 * se), (g, se)
    # ... and an uncertainty of the right size (an inflated one would pass anything): one
    # gradient entry per set from two opposite sensors 0.5 m apart has sd
    # sigma sqrt(2) / 0.5 m = 8.5 nT/m, averaged over N sets: 0.15 nT/m; the calibration
    # unknowns and the turning of the world tensor in the body frame shift it by a factor ~1
    se_hand = SIGMA_NT * math.sqrt(2) / 0.5 / math.sqrt(N_SETS)
    assert np.all((se > 0.5 * se_hand) & (se < 3 * se_hand)), (se, se_hand)
    assert s['ok'] is True
    for name in s['figures']:
        assert (out / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_site_gradient_demo_bad_value(tmp_path):
    """A gradient that is not five numbers: one line naming the format, exit 2."""
    p = _run('scripts/demo.sh --site-gradient=300,-250', tmp_path)
    assert p.returncode == 2
    assert 'expected five numbers' in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_demo_help_names_the_option(tmp_path):
    """``scripts/demo.sh --help`` (the live demo's) points to the offline option."""
    p = _run('scripts/demo.sh --help', tmp_path)
    assert p.returncode == 0 and '--site-gradient' in p.stdout, p.stdout + p.stderr
