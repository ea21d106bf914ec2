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
Real recordings (issue 10, item 7): what each of the shared hand-held recordings must show.

data/real/sunsided-hmc5883l (HMC5883L, 13 recordings, PROVENANCE.md there) and
data/real/ck-accmag (a consumer IMU's full sphere), gzip-compressed CSV in the repository.
Real data have no noise model to derive tolerances from: each threshold below says where it
comes from (the issue's 2 %, the noise floor measured on the static recordings, the sensor
axes of the README).
"""
import json
import pathlib
import re
import shutil
import subprocess
import sys

from magcal_ros.core.data.magnitude import auto_magnitude
from magcal_ros.core.data.noise import noise_floor
from magcal_ros.core.model import DegenerateDataError, fit
from magcal_ros.core.model.identifiability import check_coverage
from magcal_ros.io.csvio import read_csv
from magcal_ros.io.single_csv import read_single_sensor_csv
import numpy as np
import pytest
from scipy.optimize import least_squares
from test_cli import run_cli

REPO = pathlib.Path(__file__).resolve().parents[1]
REAL = REPO / 'data' / 'real'
HMC = REAL / 'sunsided-hmc5883l'
CK = REAL / 'ck-accmag' / 'acc_mag_log.csv.gz'
STATIC = ('unmoved-with-x-pointing-forward', 'unmoved-with-x-pointing-forward-10min',
          'unmoved-with-z-pointing-front-and-x-up', 'unmoved-with-z-pointing-front-and-y-down')


def hmc(name):
    return read_csv(HMC / name / f'{name}.csv.gz')


def geometric_ellipsoid_fit(m, f):
    """
    Fit an ellipsoid geometrically, independently of the package.

    Independent geometric fit: centre c (3,) nT and upper-triangular L (3, 3) minimising
    the distance, along the ray from c, of each reading m (N, 3) nT to the ellipsoid
    |L (x - c)| = f: d = |m - c| (1 - f / |L (m - c)|).  Started from a sphere at the mean.
    """
    c0 = m.mean(axis=0)
    s = np.median(np.linalg.norm(m - c0, axis=1)) / f

    def unpack(p):
        return p[:3], np.array([[p[3], p[4], p[5]], [0, p[6], p[7]], [0, 0, p[8]]])

    def resid(p):
        c, lmat = unpack(p)
        d = m - c
        return np.linalg.norm(d, axis=1) * (1.0 - f / np.linalg.norm(d @ lmat.T, axis=1))

    sol = least_squares(resid, np.r_[c0, 1 / s, 0, 0, 1 / s, 0, 1 / s], method='lm',
                        x_scale=np.r_[[f] * 3, [1 / s] * 6])
    assert sol.success
    return unpack(sol.x)


@pytest.fixture(scope='module')
def full_sphere():
    data = hmc('full-sphere')
    f = auto_magnitude(data.raw[0])
    return data, f, fit(data, 'base', field_nt=f)


@pytest.fixture(scope='module')
def full_sphere_file(full_sphere, tmp_path_factory):
    """Write the full sphere's calibration file with `magcal fit` as a user would."""
    _, f, _ = full_sphere
    cal = tmp_path_factory.mktemp('cal') / 'full.yaml'
    rc, _, err = run_cli('fit', HMC / 'full-sphere' / 'full-sphere.csv.gz', '--field-nt',
                         f'{f:.1f}', '-o', cal)
    assert rc == 0, err
    return cal


@pytest.mark.parametrize('which', ['hmc5883l', 'ck-accmag'])
def test_full_sphere_within_2_percent_of_an_independent_geometric_fit(which, full_sphere):
    if which == 'hmc5883l':
        data, f, res = full_sphere
    else:
        data = read_single_sensor_csv(CK, unit='gauss')
        f = auto_magnitude(data.raw[0])
        res = fit(data, 'base', field_nt=f)
    m = data.raw[0]
    c, lmat = geometric_ellipsoid_fit(m, f)
    cal = res.calibration
    q_ours = cal.correction_matrix(1).T @ cal.correction_matrix(1)
    q_geo = lmat.T @ lmat                        # the quadric: independent of the frame
    rms_geo = np.sqrt(np.mean((np.linalg.norm((m - c) @ lmat.T, axis=1) - f) ** 2))
    print(f'\n{which}: |B| {f:.0f} nT; offset differs by {np.linalg.norm(cal.offset(1) - c):.1f}'
          f' nT; quadric by {np.linalg.norm(q_ours - q_geo, 2) / np.linalg.norm(q_geo, 2):.2e};'
          f' scalar RMS {res.scalar_rms_nt[1]:.1f} vs {rms_geo:.1f} nT')
    assert np.linalg.norm(cal.offset(1) - c) < 0.02 * f
    assert np.linalg.norm(q_ours - q_geo, 2) < 0.02 * np.linalg.norm(q_geo, 2)
    assert res.scalar_rms_nt[1] == pytest.approx(rms_geo, rel=0.02)


#: the rotation axis of each single-axis recording in the sensor frame (README-set-2.md: x
#: forward, y left, z up; the magnetometer's z is the board's z)
SINGLE_AXIS = {'rotate-ccw-around-x-pointing-forward': (1, 0, 0),
               'rotate-ccw-around-x-pointing-up': (1, 0, 0),
               'rotate-ccw-around-y-pointing-left': (0, 1, 0),
               'rotate-ccw-around-z-pointing-up': (0, 0, 1)}


def named_axis(message):
    """Return the (3,) axis a refusal names: the first '(+a, +b, +c)' in the message."""
    found = re.search(r'\(([-+]\d\.\d\d), ([-+]\d\.\d\d), ([-+]\d\.\d\d)\)', message)
    assert found, message
    v = np.array([float(x) for x in found.groups()])
    return v / np.linalg.norm(v)


@pytest.mark.parametrize('name', sorted(SINGLE_AXIS))
def test_single_axis_recording_refused_naming_the_axis(name):
    data = hmc(name)
    with pytest.raises(DegenerateDataError, match='rotation about one axis only') as exc:
        fit(data, 'base', field_nt=54000.0)
    # within 15 deg of the axis turned about (hand-held: a few degrees of wobble)
    assert abs(named_axis(str(exc.value)) @ SINGLE_AXIS[name]) > np.cos(np.radians(15.0))
    assert check_coverage(data.raw)['sensors'][1]['status'] == 'single axis'


#: what refuses a turn about one axis, by --field-nt: with a number the fit's coverage check
#: (core/model/identifiability.py) comes first; with 'auto' the CLI takes the magnitude from
#: an ellipsoid fit of the readings (core/data/magnitude.py auto_magnitude) before any fit,
#: and the ellipsoid fit (core/papers/ellipsoid.py) finds its quadric not definite and the
#: readings near a plane. Each message names the turn's axis.
SINGLE_AXIS_REFUSAL = {'54000': 'the data come from a rotation about one axis only',
                       'auto': 'i.e. the sensor was rotated about that axis only'}


def test_single_axis_refusal_on_the_command_line():
    """As a user runs it, also with --field-nt auto (whose ellipsoid fit notices first)."""
    path = HMC / 'rotate-ccw-around-z-pointing-up' / 'rotate-ccw-around-z-pointing-up.csv.gz'
    for field, refusal in SINGLE_AXIS_REFUSAL.items():
        rc, _, err = run_cli('fit', path, '--field-nt', field)
        assert rc == 2
        assert len(err.strip().splitlines()) == 1
        assert refusal in err, (field, err)
        assert abs(named_axis(err)[2]) > np.cos(np.radians(15.0)), err


@pytest.mark.parametrize('name', ['pan-along-x-pointing-forward', 'pan-along-y-pointing-left',
                                  'pan-along-z-pointing-up'])
def test_pan_is_refused_as_one_attitude(name):
    """
    Refuse the pans (translations) as one attitude.

    The pans are translations (README of each: 'translation along the x axis'): the
    attitude only wobbles by a few degrees, so no calibration; the refusal says the sensor
    hardly turned (not 'rotate about another axis', which would name a meaningless axis).
    """
    data = hmc(name)
    rep = check_coverage(data.raw)
    assert rep['sensors'][1]['status'] == 'one attitude'
    assert rep['sensors'][1]['cone_half_angle_deg'] < 15.0
    with pytest.raises(DegenerateDataError, match='same field direction'):
        fit(data, 'base', field_nt=54000.0)


def test_roll_and_tilt_calibrates_the_full_sphere(full_sphere, tmp_path):
    """
    Calibrate on the rolls and tilts and check on the full sphere.

    Rolls and tilts of +-90 deg at three headings: the directions about the fitted centre
    spread in 3-D (smallest scatter eigenvalue 0.12 of the ideal 1/3), so the coverage is
    accepted; the constrained mode runs on it from the command line; and its calibration,
    applied to the independent full-sphere recording, removes most of that recording's
    raw |B| spread (the two recordings also differ in field and drift: PROVENANCE.md).
    """
    data = hmc('roll-and-tilt-at-45-90')
    cov = check_coverage(data.raw)['sensors'][1]
    assert cov['status'] == 'good' and min(cov['eigenvalues']) > 0.1
    fs, f, own = full_sphere
    path = HMC / 'roll-and-tilt-at-45-90' / 'roll-and-tilt-at-45-90.csv.gz'
    rc, _, err = run_cli('fit', path, '--field-nt', f'{f:.1f}', '--constrained',
                         '-o', tmp_path / 'rt.yaml')
    assert rc == 0, err
    rt = fit(data, 'base', field_nt=f, constrained=True)
    raw_b = np.linalg.norm(fs.raw[0], axis=1)
    b = np.linalg.norm(rt.calibration.correct(1, fs.raw[0]), axis=1)
    print(f'\nfull sphere |B| sd: raw {raw_b.std():.0f} nT, with the roll-and-tilt '
          f'calibration {b.std():.0f} nT, with its own {own.scalar_rms_nt[1]:.0f} nT')
    assert b.std() < raw_b.std() / 5
    assert b.std() < 0.03 * f


@pytest.mark.parametrize('name', [STATIC[0], 'pan-along-z-pointing-up'])
def test_constrained_mode_does_not_accept_one_attitude(name):
    """
    Refuse one attitude also in the constrained mode.

    The priors of the constrained mode stand in for attitudes a partial coverage never
    saw; a sensor that did not turn determines no offset, with or without them.
    """
    with pytest.raises(DegenerateDataError, match='same field direction'):
        fit(hmc(name), 'base', field_nt=54000.0, constrained=True)


@pytest.fixture(scope='module')
def static_floors():
    return {name: float(noise_floor(hmc(name).raw)[0]) for name in STATIC}


def test_static_recordings_give_the_sensor_noise(static_floors, full_sphere):
    """
    Read the sensor's noise from the four static recordings.

    The four static recordings are the sensor's own noise: their floors agree with each
    other and with the per-axis sd of the raw readings (nothing else moves), and with the
    floor that the full sphere's differences give (HMC5883L: about 140 nT).
    """
    floors = np.array(list(static_floors.values()))
    assert floors.max() < 1.15 * floors.min()
    for name in STATIC:
        sd = hmc(name).raw[0].std(axis=0)
        # white noise: the floor is the sd; drift over minutes adds a little to the sd
        assert static_floors[name] == pytest.approx(np.median(sd), rel=0.2)
    fs, _, _ = full_sphere
    assert float(noise_floor(fs.raw)[0]) == pytest.approx(np.median(floors), rel=0.15)


def test_static_recordings_checked_against_the_full_sphere(full_sphere, full_sphere_file):
    """
    Check the static recordings against the full sphere with `magcal check`.

    The corrected |B| of the static recordings is not one value: `magcal check` says
    why.  The two x-forward recordings share an attitude yet differ by about 7 000 nT, so
    the field or the sensor's offset changed between recordings (the 10-min one is the
    3 300 nT of PROVENANCE.md below the full sphere); the x-up and y-down recordings, 75 deg
    apart, agree within the calibration's residual, so the calibration holds and their
    field differs from the full sphere's.
    """
    _, f, _ = full_sphere
    cal = full_sphere_file
    rc, out, err = run_cli('check', cal, *[HMC / n / f'{n}.csv.gz' for n in STATIC], '--json')
    assert rc == 0, err
    d = json.loads(out)
    assert not d['consistent']
    b = {r['name'].removesuffix('.csv.gz'): r['b_nt'] for r in d['recordings']}
    tol = d['tolerance_nt']
    assert abs(b[STATIC[0]] - b[STATIC[1]]) > 5000.0
    assert abs(b[STATIC[2]] - b[STATIC[3]]) < tol
    assert -4000.0 < b[STATIC[1]] - f < -2500.0
    assert any(STATIC[0] in t and STATIC[1] in t and 'same attitude' in t
               for t in d['findings'])
    assert any(STATIC[2] in t and 'the calibration holds there' in t for t in d['findings'])


def test_readme_check_commands(tmp_path):
    """
    Run the README's `magcal fit` and `magcal check` lines as written, from the root.

    Run in a directory holding a link to the repository's data/ (so that hmc.yaml does not
    land in the checkout): the README's paths are relative to the repository root.
    """
    lines = [ln for ln in (REPO / 'README.md').read_text().splitlines()
             if ln.startswith('magcal ') and 'sunsided' in ln and '--planar' not in ln]
    assert [ln.split()[1] for ln in lines] == ['fit', 'check']
    work = tmp_path / 'repo'
    work.mkdir()
    (work / 'data').symlink_to(REPO / 'data')
    magcal = shutil.which('magcal') or f'{sys.executable} -m magcal_ros.cli'
    for ln in lines:
        p = subprocess.run(ln.replace('magcal ', magcal + ' ', 1), shell=True, cwd=work,
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr
    assert "the field at the sensor or the sensor's offset changed" in p.stdout
    assert p.stdout.count('nT vs reference') == 4


def test_check_reads_other_units(full_sphere_file, tmp_path):
    """
    Read a recording in gauss with `magcal check --unit gauss`.

    A static recording in gauss (a single magnetometer's mx,my,mz log): `magcal check
    --unit gauss` gives the |B| of the nT file; without --unit the unit is named.
    """
    cal = full_sphere_file
    name = STATIC[2]
    gauss = tmp_path / 'static_gauss.csv'
    np.savetxt(gauss, hmc(name).raw[0] / 1e5, delimiter=',', fmt='%.8f', header='mx,my,mz',
               comments='')
    rc, out, err = run_cli('check', cal, HMC / name / f'{name}.csv.gz', gauss, '--unit', 'gauss',
                           '--json')
    assert rc == 2 and 'not a geomagnetic field' in err     # the nT file read as gauss
    rc, out, err = run_cli('check', cal, gauss, '--unit', 'gauss', '--json')
    assert rc == 0, err
    rc2, out2, err2 = run_cli('check', cal, HMC / name / f'{name}.csv.gz', '--json')
    assert rc2 == 0, err2
    b = json.loads(out)['recordings'][0]['b_nt']
    assert b == pytest.approx(json.loads(out2)['recordings'][0]['b_nt'], abs=1.0)
    rc, _, err = run_cli('check', cal, gauss)
    assert rc == 2 and len(err.strip().splitlines()) == 1
