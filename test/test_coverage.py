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

"""Tests for magcal_ros.core.geometry.coverage."""

from magcal_ros.core.geometry.coverage import direction_coverage
import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _circle(axis, half_angle_rad, n, radius_nt=50000.0):
    """Directions on a cone of the given half-angle around ``axis`` (a single-axis rotation)."""
    axis = _unit(axis)
    start = Rotation.from_rotvec(np.cross(axis, _unit([0.3, -0.2, 0.9]))).apply(axis)
    # tilt the axis by exactly half_angle towards some perpendicular
    perp = _unit(np.cross(axis, start))
    field = Rotation.from_rotvec(perp * half_angle_rad).apply(axis) * radius_nt
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return Rotation.from_rotvec(angles[:, None] * axis).apply(field)


def test_uniform_sphere_is_good():
    rng = np.random.default_rng(1)
    n = 2000
    v = rng.normal(size=(n, 3)) * 50000.0
    cov = direction_coverage(v)
    # Each eigenvalue of the scatter of uniform directions is 1/3; a sample estimate of
    # E[u_x^2] = 1/3 has standard deviation sqrt(Var(u_x^2)/n) = sqrt(4/45/n) = 0.0067
    # at n = 2000, so 0.03 is > 4 sigma.
    np.testing.assert_allclose(cov.eigenvalues, 1.0 / 3.0, atol=0.03)
    assert not cov.planar and not cov.narrow and cov.good
    assert cov.n == n
    assert cov.mean_resultant_length < 0.1
    assert cov.cone_half_angle_deg > 150.0
    assert cov.describe().startswith('directions cover the sphere')
    # eigenvectors are orthonormal columns matching the eigenvalues
    s = np.cov(v.T / np.linalg.norm(v, axis=1), bias=True)
    np.testing.assert_allclose(s @ cov.eigenvectors, cov.eigenvectors * cov.eigenvalues,
                               atol=1e-12)


def test_single_axis_rotation_is_planar_with_the_axis_as_normal():
    axis = _unit([-0.866, 0.5, 0.003])
    # a wide cone (57 deg) as in paper 002: not a great circle, still one plane
    v = _circle(axis, np.radians(57.0), 36)
    cov = direction_coverage(v)
    assert cov.planar and not cov.narrow and not cov.good
    assert abs(cov.normal @ axis) == pytest.approx(1.0, abs=1e-9)
    # every direction is 57 deg from the mean direction (the axis)
    assert cov.cone_half_angle_deg == pytest.approx(57.0, abs=1e-6)
    # normal points to the side of the plane the directions are on
    assert cov.normal @ cov.mean_direction > 0.99
    msg = cov.describe()
    assert msg.startswith('all field directions lie near one plane with normal (')
    assert 'rotate about another axis' in msg
    assert '(%.2f, %.2f, %.2f)' % tuple(cov.normal) in msg


def test_great_circle_is_planar():
    v = _circle([0.0, 0.0, 1.0], np.pi / 2, 24)
    cov = direction_coverage(v)
    assert cov.planar
    assert abs(cov.normal[2]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(cov.eigenvalues, [0.0, 0.5, 0.5], atol=1e-12)
    # the mean of a full great circle vanishes: no meaningful cone
    assert cov.cone_half_angle_deg == 180.0


def test_two_axis_rotation_is_good():
    v = np.vstack([_circle([0, 0, 1], np.radians(60.0), 36),
                   _circle([1, 0, 0], np.radians(60.0), 36)])
    cov = direction_coverage(v)
    assert cov.good
    assert cov.eigenvalues[0] > 0.05


def test_narrow_cone_is_reported_with_its_angle():
    rng = np.random.default_rng(2)
    centre = _unit([1.0, 2.0, -0.5])
    # directions within a 10 deg cone around centre
    rot = Rotation.from_rotvec(rng.uniform(-1, 1, size=(500, 3)) * np.radians(10.0) / np.sqrt(3))
    v = rot.apply(centre) * 40000.0
    cov = direction_coverage(v)
    assert cov.narrow and cov.planar and not cov.good
    assert cov.cone_half_angle_deg < 12.0
    assert cov.mean_direction @ centre > 0.999
    msg = cov.describe()
    assert msg.startswith('field directions span only a %.0f deg cone around'
                          % cov.cone_half_angle_deg)
    assert 'turn the sensor over / through larger angles' in msg


def test_cone_half_angle_is_95th_percentile():
    centre = np.array([0.0, 0.0, 1.0])
    # 100 directions at 1, 2, ..., 100 deg from the mean direction, spread in azimuth so the
    # mean stays on +z (golden-angle azimuths)
    tilt = np.radians(np.arange(1, 101))
    az = np.arange(100) * np.radians(137.508)
    v = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    cov = direction_coverage(v)
    angles = np.degrees(np.arccos(np.clip(v @ cov.mean_direction, -1, 1)))
    assert cov.cone_half_angle_deg == pytest.approx(np.percentile(angles, 95))
    assert cov.mean_direction @ centre > 0.99


def test_units_do_not_matter():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(50, 3))
    a = direction_coverage(v * 5e4)
    b = direction_coverage(v * 5e-5)
    np.testing.assert_allclose(a.eigenvalues, b.eigenvalues, atol=1e-14)


def test_threshold_changes_the_verdict():
    # +-10 deg band around the equator: variance of u_z about 0.01 < 0.02
    rng = np.random.default_rng(4)
    az = rng.uniform(0, 2 * np.pi, 400)
    el = rng.uniform(-np.radians(10), np.radians(10), 400)
    v = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    assert direction_coverage(v).planar
    assert not direction_coverage(v, planar_threshold=0.005).planar


@pytest.mark.parametrize('bad, match', [
    (np.zeros((0, 3)), r'shape \(N, 3\)'),
    (np.ones((4, 2)), r'shape \(N, 3\)'),
    (np.ones(3), r'shape \(N, 3\)'),
    (np.array([[1.0, 0, 0], [np.nan, 0, 0]]), 'NaN or inf'),
    (np.array([[1.0, 0, 0], [0, 0, 0]]), 'zero vector'),
])
def test_bad_input(bad, match):
    with pytest.raises(ValueError, match=match):
        direction_coverage(bad)


def test_bad_threshold():
    with pytest.raises(ValueError, match='planar_threshold'):
        direction_coverage(np.eye(3), planar_threshold=0.5)
