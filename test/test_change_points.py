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
Change points of the base fit's residual (core/discovery/candidates.residual_features).

Residuals written here by hand: white noise of 3 nT per axis on 4 sensors, readings of a
50 000 nT field turning through every direction. A step of an offset changes the
residual's mean; a step of a scale factor (a range switch) leaves dk * m, whose mean over
the attitudes is 0, and changes instead the mean of r_a u_b (u = m / |m|): dk_a * F / 3 on
the diagonal, 4e-4 * 50 000 / 3 = 6.7 nT here, against 3 nT / sqrt(3) of noise per epoch.
"""
from magcal_ros.core.discovery.candidates import residual_features
import numpy as np
import pytest

N = 3000
SIGMA = 3.0


def _record(seed):
    """Return times (N,) s, readings (4, N, 3) nT and a white residual (4, N, 3) nT."""
    rng = np.random.default_rng(seed)
    return np.arange(N) * 0.1, _readings(), rng.normal(0, SIGMA, (4, N, 3))


def _readings():
    """(4, N, 3) nT: a 50 000 nT field in directions spread over the sphere, in time order."""
    k = np.arange(N)
    th = np.arccos(1 - 2 * ((k * 0.618034) % 1.0))     # spread over the sphere
    ph = 0.05 * k
    u = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return np.repeat(50000.0 * u[None], 4, axis=0)


def test_a_scale_step_is_found_in_the_gains_not_in_the_mean():
    t, m, resid = _record(2)
    k0 = 1650
    dk = np.array([4e-4, -3e-4, 5e-4])
    resid[1, k0:] += dk * m[1, k0:]
    # the mean alone misses it (the step averages out over the attitudes)
    found_mean, _ = residual_features(t, resid)
    assert not any(abs(k - k0) <= 30 for k in found_mean), found_mean
    found, _ = residual_features(t, resid, readings=m)
    assert any(abs(k - k0) <= 30 for k in found), found


def test_an_offset_step_is_found_once():
    t, m, resid = _record(4)
    k0 = 900
    resid[2, k0:] += np.array([4.0, -3.0, 2.0])
    found, _ = residual_features(t, resid, readings=m)
    near = [k for k in found if abs(k - k0) <= 30]
    assert len(near) == 1, found


@pytest.mark.parametrize('seed', range(5))
def test_white_noise_has_no_change_point_and_a_step_at_the_stated_threshold_is_one(seed):
    # the stated threshold (candidates._binary_segmentation): a split's statistic
    # |c_k - k/n c_n|^2 / (k (n - k) / n) above T = sigma^2 C (10 + 5 ln n), C = 3 S columns;
    # here T = 600 sigma^2.  An offset step d at the middle adds n |d|^2 / 4 to the
    # statistic at its split (white noise: ~ sigma^2 C = 12 sigma^2, its cross term with
    # the step of sd 2 sigma |d| sqrt(n / 4), 60 sigma^2 at 1.5 T): a step worth 1.5 T is
    # found once, within 30 epochs of its own (as above; the split's error is in units of
    # sigma^2 / |d|^2 = 0.8 epoch here), one worth 0.5 T is not, white noise alone gives none
    t, m, resid = _record(100 + seed)
    found, _ = residual_features(t, resid, readings=m)
    assert found == []
    k0 = N // 2
    threshold = SIGMA ** 2 * 12 * (10 + 5 * np.log(N))
    direction = np.array([2.0, -1.0, 2.0]) / 3.0
    for worth, expected in ((1.5, True), (0.5, False)):
        stepped = resid.copy()
        stepped[3, k0:] += direction * np.sqrt(worth * threshold * 4 / N)
        found, _ = residual_features(t, stepped, readings=m)
        if expected:
            assert len(found) == 1 and abs(found[0] - k0) <= 30, (worth, found)
        else:
            assert found == [], (worth, found)


@pytest.mark.parametrize('seed', range(5))
def test_the_threshold_is_in_units_of_the_mean_noise_variance_of_unequal_sensors(seed):
    # sensors of 3, 4.5, 6 and 3 nT: the statistic's null mean is sum sigma_c^2, so the
    # threshold is stated in the mean column variance, here 18.6 nT^2 (the median of the
    # pooled squared differences read 14.4: a step worth 0.75 T then counted as 0.97 T).
    # A step worth 1.5 T of it is found, within 30 epochs; one worth 0.75 T is not (its
    # statistic 0.75 T + C, sd 2 sqrt(0.75 T) = 42 below T = 600 by 3.3 sd)
    rng = np.random.default_rng(200 + seed)
    t = np.arange(N) * 0.1
    sd = np.array([1.0, 1.5, 2.0, 1.0]) * SIGMA
    resid = rng.normal(0.0, 1.0, (4, N, 3)) * sd[:, None, None]
    mean_var = float(np.mean(sd ** 2))
    threshold = mean_var * 12 * (10 + 5 * np.log(N))
    k0 = N // 2
    direction = np.array([2.0, -1.0, 2.0]) / 3.0
    for worth, expected in ((1.5, True), (0.75, False)):
        stepped = resid.copy()
        stepped[0, k0:] += direction * np.sqrt(worth * threshold * 4 / N)
        found, _ = residual_features(t, stepped)
        if expected:
            assert len(found) == 1 and abs(found[0] - k0) <= 30, (worth, found)
        else:
            assert found == [], (worth, found)
