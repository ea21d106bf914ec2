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
The field-rate signal: one estimate offline, in the simulator and live.

The field-rate signal is estimated by one function (effects.raw_rate) offline, in the
simulator and live, so a lag tau fitted from a recording corrects the live stream as it
corrected the recording, to second order in the sample period, also when the stream is
decimated 20x (a 100 Hz array read at 5 Hz), where the corrector's former backward
difference was off by several times the noise.

The recording is written here from the physics (a true delay of sensor 2, evaluated from the
attitude at t - tau), not with Model.forward.
"""
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.live.corrector import LiveCorrector, MissingSignal
from magcal_ros.core.model import fit
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

F = 50000.0                                   # nT
TAU = 0.01                                    # s, sensor 2 lags by 10 ms
SIGMA = 1.0                                   # nT
H = 0.2                                       # s: 100 Hz decimated 20x
W = 2 * np.pi / 60.0


def _attitude(t):
    """Smooth tumbling (a hand-turned array): angular rate up to about 1 rad/s."""
    return Rotation.from_euler('ZYX', np.column_stack(
        [W * 3.1 * t, np.radians(85) * np.sin(W * 1.7 * t), np.pi * np.sin(W * 1.13 * t)]))


@pytest.fixture(scope='module')
def lagged():
    rng = np.random.default_rng(5)
    t = np.arange(3000) * H                                        # s, 10 min at 5 Hz
    b_world = F * np.array([np.cos(1.0), 0.0, np.sin(1.0)])
    b1 = _attitude(t).inv().apply(b_world)                         # (N, 3) nT, body frame
    b2 = _attitude(t - TAU).inv().apply(b_world)                   # what sensor 2 shows now
    rot2 = Rotation.from_euler('ZYX', [0.01, -0.02, 0.015]).as_matrix()
    raw = np.stack([b1, b2 @ rot2.T + [40.0, -25.0, 10.0]])
    raw = raw + rng.normal(scale=SIGMA, size=raw.shape)
    data = Dataset(t=t, raw=raw)
    return data, fit(data, 'offset,misalignment,field_rate@2', field_nt=F)


def _turn_rate(t):
    """(N,) angular rate of the tumbling, rad/s (from the attitude, by hand)."""
    d = (_attitude(t + 1e-3) * _attitude(t - 1e-3).inv()).as_rotvec()
    return np.linalg.norm(d, axis=1) / 2e-3


def test_fitted_lag(lagged):
    data, res = lagged
    tau = res.params[res.model.slices[1][-1]]
    se = res.stderr[res.model.slices[1][-1]]
    # the central difference's gain 1 - (w h)^2 / 6 (w <= 0.7 rad/s here: >= 0.997) and the
    # noise: within 0.4 % + 5 sd of the true lag
    assert np.all(np.abs(tau / TAU - 1) < 0.004 + 5 * se / TAU), (tau, se)
    # sensor 2 against sensor 1: the noise of both (sqrt(2) sigma), plus the second order of
    # the lag, tau^2/2 |B''| (<= 0.6 nT here), that the first-order field_rate term leaves
    assert res.vector_rms_nt[2] < 1.1 * np.sqrt(2) * SIGMA


def test_live_correction_agrees_with_the_offline_one(lagged):
    data, res = lagged
    cal = res.calibration
    offline = cal.correct(2, data.raw[1], data.context(2))          # (N, 3) nT
    live = LiveCorrector(cal, 2)
    got = np.full_like(offline, np.nan)
    for k, tk in enumerate(data.t):
        live.correct(1, tk, data.raw[0, k])
        try:
            got[k] = live.correct(2, tk, data.raw[1, k])
        except MissingSignal:
            assert k < 11                       # until the stream's period is known
    ok = np.isfinite(got[:, 0])
    assert ok.sum() == data.n_samples - 10
    diff = np.sqrt(np.mean((got[ok] - offline[ok]) ** 2))
    # live has only the past: the one-sided second-order rate against the fit's central
    # one, (w h)^2 / 2 + (w h)^3 / 4 of tau |dB/dt| = tau w F at most, per vector (so
    # / sqrt(3) per component), plus their noise difference sqrt(5) sigma / h tau = 0.1 nT
    w = _turn_rate(data.t[ok])
    th = w * H
    bound = np.sqrt(np.mean((TAU * (th ** 2 / 2 + th ** 3 / 4) * w * F) ** 2) / 3)
    assert diff < bound + np.sqrt(5) * SIGMA / H * TAU, (diff, bound)

    # the control: the first-order backward difference the corrector used before lags half
    # a sample, (w h)/2 of the rate along the field: with this lag its live output would be
    # off the offline one by several times that (4.7 nT against a bound of 0.9 nT)
    tau = res.params[res.model.slices[1][-1]]
    rate = data.context(2).raw_rate
    backward = np.diff(data.raw[1], axis=0) / H
    off = (cal.correction_matrix(2) @ (tau * (backward - rate[1:])).T).T
    assert np.sqrt(np.mean(off[20:] ** 2)) > 4 * bound
