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
`magcal fit --method sine|reference` against the numbers of the papers.

`magcal fit --method sine|reference` (papers 000 and 002 from the command line), run as a
user would, against the numbers the papers print (docs/papers.md).
"""
import json
import pathlib
import subprocess
import sys

from magcal_ros.core.papers.paper_params import Paper000Params
from magcal_ros.core.papers.sine import simulate_turntable
from magcal_ros.io.calfile import load_calibration
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

DEG = np.pi / 180.0
TABLE2 = pathlib.Path(__file__).parent / 'data' / 'paper002_table2.csv'


def run_cli(*args):
    """Run the real command in a subprocess; returns (rc, stdout, stderr)."""
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                       capture_output=True, text=True, timeout=240)
    return p.returncode, p.stdout, p.stderr


def _write(path, header, rows):
    path.write_text(','.join(header) + '\n'
                    + ''.join(','.join(str(v) for v in r) + '\n' for r in rows))
    return path


# -- paper 000 §3.1: a = 1.35 deg, b = 32.7 deg, g = 1.07 deg, k = (0.909, 1.146, 1.103),
# B0 = (143, 97.4, 123.7) nT, B = 50 000 nT, I = 43 deg
PAPER000 = Paper000Params(alpha=1.35 * DEG, beta=32.7 * DEG, gamma=1.07 * DEG, kx=0.909,
                          ky=1.146, kz=1.103, B0=[143.0, 97.4, 123.7])


@pytest.fixture(scope='module')
def turntable_csv(tmp_path_factory):
    sim = simulate_turntable(PAPER000, 50000.0, 43.0 * DEG, 36)
    angle = np.degrees(sim.theta)
    # the recording must be the paper's: position 1 follows the three curves printed in
    # §3.1 (A sin(theta + C) + D), to the rounding of their printed coefficients
    for col, (a, a_dec, c, c_dec, d, d_dec) in enumerate(
            [(33240.0, 1, 90.0, 0, 143.0, 1), (41906.6, 1, 178.65, 2, 97.4, 1),
             (753.2, 1, 122.7, 1, 37729.4, 1)]):
        printed = a * np.sin(sim.theta + c * DEG) + d
        tol = 0.5 * 10.0 ** -a_dec + a * 0.5 * 10.0 ** -c_dec * DEG + 0.5 * 10.0 ** -d_dec
        np.testing.assert_allclose(sim.raw1[:, col], printed, atol=tol)
    rows = ([(k, a, 'xy', *m) for k, (a, m) in enumerate(zip(angle, sim.raw1))]
            + [(36 + k, a, 'xz', *m) for k, (a, m) in enumerate(zip(angle, sim.raw2))])
    path = tmp_path_factory.mktemp('sine') / 'turntable.csv'
    return _write(path, ['t', 'angle_deg', 'plane', 's1_x', 's1_y', 's1_z'], rows)


def test_sine_method_recovers_the_papers_parameters(turntable_csv, tmp_path):
    out = tmp_path / 'cal.yaml'
    rc, stdout, err = run_cli('fit', turntable_csv, '--method', 'sine', '--field-nt', 50000,
                              '--json', '-o', out)
    assert rc == 0, err
    doc = json.loads(stdout)
    p = {k: v['value'] for k, v in doc['params'][0].items()}
    # noise-free: the printed values, to their printed precision
    printed = {'alpha': (1.35, 2), 'beta': (32.7, 1), 'gamma': (1.07, 2), 'kx': (0.909, 3),
               'ky': (1.146, 3), 'kz': (1.103, 3), 'Bx0': (143.0, 1), 'By0': (97.4, 1),
               'Bz0': (123.7, 1)}
    for name, (value, dec) in printed.items():
        assert p[name] == pytest.approx(value, abs=0.5 * 10.0 ** -dec), name
    assert doc['method'] == 'sine' and doc['warnings'] == []
    assert doc['scalar_rms_before_nt']['1'] > 1000.0 and doc['scalar_rms_nt']['1'] < 1e-6
    # the file corrects like paper 000's eq. 17, up to the rotation of its frame: the total
    # field is 50 000 nT on every row
    cal, _ = load_calibration(out)
    raw = np.loadtxt(turntable_csv, delimiter=',', skiprows=1, usecols=(3, 4, 5))
    np.testing.assert_allclose(np.linalg.norm(cal.correct(1, raw), axis=1), 50000.0,
                               atol=1e-6)
    assert np.isnan(cal.stderr).all()          # a closed form gives no uncertainty


def test_sine_method_needs_its_columns(tmp_path):
    path = _write(tmp_path / 'x.csv', ['t', 's1_x', 's1_y', 's1_z'],
                  [(k, 30000.0 + k, 20000.0, 30000.0) for k in range(10)])
    rc, _, err = run_cli('fit', path, '--method', 'sine', '--field-nt', 50000)
    assert rc == 2 and 'angle_deg and plane' in err and len(err.strip().splitlines()) == 1
    rc, _, err = run_cli('fit', path, '--method', 'sine', '--model', 'base,temperature',
                         '--field-nt', 50000)
    assert rc == 2 and '--model applies to --method ellipsoid only' in err


def test_reference_method_on_paper002_table2(tmp_path):
    # paper 002's Table 2 turns the sensor about one axis: refused, naming the plane
    rc, _, err = run_cli('fit', TABLE2, '--method', 'reference')
    assert rc == 2 and 'lie in one plane' in err and len(err.strip().splitlines()) == 1
    out = tmp_path / 'cal.yaml'
    rc, stdout, err = run_cli('fit', TABLE2, '--method', 'reference', '--flag-degenerate',
                              '--json', '-o', out)
    assert rc == 0, err
    doc = json.loads(stdout)
    p = {k: v['value'] for k, v in doc['params'][0].items()}
    # docs/papers.md (paper 002 erratum): with the corrected Hmy signs, K row 2 =
    # (-4.653, 11.122, -0.0019) and Hhy = 11 724 nT
    assert (p['K21'], p['K22']) == pytest.approx((-4.653, 11.122), abs=0.5e-3)
    assert p['K23'] == pytest.approx(-0.0019, abs=0.5e-4)
    assert p['Hhy'] == pytest.approx(11724.0, abs=0.5)
    assert any('one plane' in w for w in doc['warnings'])
    cal, saved = load_calibration(out)
    assert any('one plane' in w for w in saved['provenance']['warnings'])


def test_reference_method_recovers_a_soft_iron_array(tmp_path):
    """Two sensors behind different soft and hard iron, 40 attitudes about all axes."""
    rng = np.random.default_rng(7)
    he = Rotation.random(40, random_state=rng).apply([20000.0, 0.0, 45000.0])   # nT
    k = [np.eye(3) + rng.normal(scale=0.05, size=(3, 3)) for _ in range(2)]
    hh = [np.array([300.0, -150.0, 80.0]), np.array([-40.0, 220.0, 510.0])]    # nT
    noise = 2.0                                                                # nT
    hm = [he @ kj.T + hj + rng.normal(scale=noise, size=he.shape) for kj, hj in zip(k, hh)]
    rows = [(i, *he[i], *hm[0][i], *hm[1][i]) for i in range(40)]
    path = _write(tmp_path / 'ref.csv', ['t', 'ref_x', 'ref_y', 'ref_z', 's1_x', 's1_y', 's1_z',
                                         's2_x', 's2_y', 's2_z'], rows)
    out = tmp_path / 'cal.yaml'
    rc, stdout, err = run_cli('fit', path, '--method', 'reference', '--json', '-o', out)
    assert rc == 0, err
    doc = json.loads(stdout)
    assert doc['warnings'] == []
    for j in (1, 2):
        kk = np.array([[doc['params'][j - 1][f'K{r}{c}']['value'] for c in (1, 2, 3)]
                       for r in (1, 2, 3)])
        # 40 attitudes of a 49 000 nT field with 2 nT noise: sd(K) ~ 2/(49000 sqrt(40/3))
        # = 1.1e-5 (5 sd: 6e-5); sd(Hh) ~ 2 sqrt(1/40 + mean(He)^2/var(He)) <= 0.7 nT
        # for the random mean of 40 directions (3 sd: 2 nT)
        np.testing.assert_allclose(kk, k[j - 1], atol=6e-5)
        hhj = [doc['params'][j - 1][f'Hh{a}']['value'] for a in 'xyz']
        np.testing.assert_allclose(hhj, hh[j - 1], atol=2.0)
        # corrected vs reference: the noise mapped through K^-1, about 2 nT per component
        assert doc['vector_rms_nt'][str(j)] < 1.3 * noise
    # both sensors in one frame: their corrected readings agree to the noise
    cal, _ = load_calibration(out)
    diff = cal.correct(2, hm[1]) - cal.correct(1, hm[0])
    assert np.sqrt(np.mean(diff ** 2)) < 1.3 * np.sqrt(2) * noise


def test_readme_command_as_written():
    """The `--method reference` line of the README, run from the repository root."""
    root = pathlib.Path(__file__).resolve().parents[1]
    line = next(ln for ln in (root / 'README.md').read_text().splitlines()
                if ln.startswith('magcal fit') and '--method reference' in ln)
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *line.split()[1:]],
                       capture_output=True, text=True, timeout=240, cwd=root)
    assert p.returncode == 0, p.stderr
    assert 'method: reference' in p.stdout and 'lie in one plane' in p.stdout
