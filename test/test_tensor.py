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

"""Gradient tensor: paper 004 eq. 1, the least-squares form, and its noise floor."""
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.geometry.tensor import (cross_positions, tensor_cross, tensor_lstsq,
                                             tensor_noise_floor, tensor_operator)
import numpy as np
import pytest


def _sym_traceless(rng):
    g = rng.normal(size=(3, 3)) * 100
    g = (g + g.T) / 2
    return g - np.eye(3) * np.trace(g) / 3


def test_lstsq_equals_eq1_for_the_cross():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(4, 50, 3)) * 1000
    g1 = tensor_cross(b, 0.5)
    g2, _ = tensor_lstsq(b, cross_positions(0.5))
    assert np.allclose(g1, g2, atol=1e-9)


@pytest.mark.parametrize('positions', [
    cross_positions(0.5),
    cross_positions(1.3) + np.array([0.1, -0.2, 0.4]),             # shifted cross
    np.array([[0.3, 0, 0], [-0.1, 0.25, 0], [-0.1, -0.25, 0], [0, 0, 0.35]]),   # 3-D
    np.array([[0.2, 0.1, 0], [0, 0.3, 0], [-0.25, 0, 0], [0.05, -0.3, 0], [0.1, 0.1, 0]]),
])
def test_linear_field_recovered_exactly(positions):
    """A curl- and divergence-free linear field B0 + G r is recovered exactly by any geometry."""
    rng = np.random.default_rng(1)
    g = _sym_traceless(rng)
    b0 = rng.normal(size=3) * 30000
    b = (b0 + positions @ g.T)[:, None, :]                        # (S, 1, 3)
    g_hat, b0_hat = tensor_lstsq(b, positions)
    assert np.allclose(g_hat[0], g, atol=1e-6)
    assert np.allclose(b0_hat[0], b0 + positions.mean(0) @ g.T, atol=1e-6)


def test_noise_floor_matches_monte_carlo():
    pos = cross_positions(0.5)
    floor = tensor_noise_floor(3.0, pos)
    assert np.allclose(floor[:2, :], 3 * np.sqrt(2) / 0.5)
    assert np.isclose(floor[2, 2], 2 * 3 / 0.5)
    rng = np.random.default_rng(2)
    g = tensor_cross(rng.normal(size=(4, 20000, 3)) * 3.0)
    # 20 000 samples: sd of the sample sd is 0.5 %; allow 3 %
    assert np.allclose(g.std(axis=0), floor, rtol=0.03)


def test_simulated_gradient_measured_after_calibration_truth():
    g_world = np.array([[10.0, 5, -3], [5, -4, 2], [-3, 2, -6]])
    data, sim = simulate(n_samples=50, noise_nt=0.0, errors=None, gradient_nt_per_m=g_world,
                         seed=0, aux=False)
    g = tensor_cross(data.raw)
    # the measured tensor is R^T G R in the body frame: its invariants equal the world ones
    for gk in g:
        assert np.isclose(np.trace(gk), 0, atol=1e-6)
        assert np.allclose(np.linalg.eigvalsh((gk + gk.T) / 2), np.linalg.eigvalsh(g_world),
                           atol=1e-6)


def test_bad_geometry_refused():
    with pytest.raises(ValueError, match='span at least a plane'):
        tensor_operator(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]))
    with pytest.raises(ValueError, match='shape \\(4, N, 3\\)'):
        tensor_cross(np.zeros((3, 5, 3)))
