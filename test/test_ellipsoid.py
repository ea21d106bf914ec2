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

"""Paper 004 eq. 8-14: ellipsoid fit, Cholesky factor, Procrustes."""
from magcal_ros.core.papers.ellipsoid import fit_ellipsoid, procrustes_rotation
from magcal_ros.core.papers.paper_params import table1_correction, table1_sensor
import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def _sphere(n, f, rng):
    u = rng.normal(size=(n, 3))
    return f * u / np.linalg.norm(u, axis=1, keepdims=True)


@pytest.mark.parametrize('j', [1, 2, 3, 4])
@pytest.mark.parametrize('normalization', ['svd', 'p'])
def test_noise_free_exact(j, normalization):
    rng = np.random.default_rng(j)
    b = _sphere(100, 50000.0, rng)
    a, o = table1_sensor(j).to_general()
    raw = b @ a.T + o
    ell = fit_ellipsoid(raw, 50000.0, normalization=normalization)
    c_inv, _ = table1_correction(j)
    assert np.allclose(ell.c_inv, c_inv, atol=1e-9)
    assert np.allclose(ell.b, o, atol=1e-5)
    assert np.abs(ell.residual_nt).max() < 1e-5
    assert np.allclose(np.triu(ell.c_inv), ell.c_inv)


def test_planar_data_refused():
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 200)
    raw = np.column_stack([np.cos(ang), np.sin(ang), 0.3 + 0 * ang]) * 40000
    with pytest.raises(ValueError, match=r'not determined.*one plane with normal '
                       r'\(\+0.00, \+0.00, \+1.00\).*rotated about that axis only'):
        fit_ellipsoid(raw + rng.normal(size=raw.shape), 50000.0)


def test_too_few_and_bad_shape():
    with pytest.raises(ValueError, match='at least 9 samples'):
        fit_ellipsoid(np.ones((5, 3)), 1.0)
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        fit_ellipsoid(np.ones((20, 2)), 1.0)
    with pytest.raises(ValueError, match='normalization'):
        fit_ellipsoid(_sphere(20, 1.0, np.random.default_rng(0)), 1.0, normalization='x')


def test_procrustes_proper_rotation():
    rng = np.random.default_rng(3)
    r_true = Rotation.random(random_state=rng).as_matrix()
    b = _sphere(50, 1.0, rng)
    r = procrustes_rotation(b, b @ r_true)          # other = R_true^T b  ->  R = R_true
    assert np.allclose(r, r_true, atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)
