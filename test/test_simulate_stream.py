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
The simulator ahead of a live stream: ``Simulator.sample(causal=True)`` and causal_rate.

fluxgate_sim simulates 0.2 s ahead and writes one sample a tick; what it writes must be what
simulating one sample at a time gave (the stream's rate of a sample from it and the two
before, as the live corrector computes it). References: a quadratic, whose rate the
one-sided second-order difference gives exactly (written here), and the simulator called
one sample at a time (numpy's gradient on the last three samples).
"""
from magcal_ros.core.data.simulate import causal_rate, parse_truth, SimConfig, Simulator
import numpy as np


def test_causal_rate_is_exact_for_a_quadratic_on_uneven_times():
    t = np.cumsum([0.0, 0.01, 0.013, 0.008, 0.02, 0.011, 0.009])
    x = np.column_stack([t ** 2, 3 * t ** 2 - t, 5.0 + 0 * t])
    rate = causal_rate(x, t)
    # d/dt of t^2, 3 t^2 - t and a constant, from the samples at and before each time only
    want = np.column_stack([2 * t, 6 * t - 1, 0 * t])
    np.testing.assert_allclose(rate[2:], want[2:], atol=1e-9)
    np.testing.assert_array_equal(rate[:2], 0.0)            # no two samples before these
    # causal: changing a later sample changes no earlier rate
    y = x.copy()
    y[5] += 100.0
    np.testing.assert_array_equal(causal_rate(y, t)[:5], rate[:5])
    assert causal_rate(x[:2], t[:2]) is None
    assert causal_rate(x, t[::-1]) is None


def _sim():
    truth = parse_truth(['field_rate@3=0.01,0.02,0.005'])
    return Simulator(SimConfig(noise_nt=0.0, truth=truth, seed=4, trajectory='smooth'))


def test_a_block_ahead_reads_as_one_sample_at_a_time():
    rate_hz, n = 100.0, 240
    t = np.arange(n) / rate_hz
    sim = _sim()
    one_by_one = np.concatenate([sim.sample(t[k:k + 1]).raw for k in range(n)], axis=1)
    sim = _sim()
    blocks = np.concatenate([sim.sample(t[k:k + 20], causal=True).raw
                             for k in range(0, n, 20)], axis=1)
    np.testing.assert_allclose(blocks, one_by_one, atol=1e-9)
    # the lag is there (nT), and the chunk's own central differences give other readings
    # (by ~1e-3 nT on this smooth turn: far above the 1e-9 the block matches to)
    central = _sim().sample(t).raw
    assert np.abs(one_by_one[2] - _sim_without_lag(t)[2]).max() > 5.0
    assert np.abs(central[2, 2:-1] - one_by_one[2, 2:-1]).max() > 1e-4


def _sim_without_lag(t):
    return Simulator(SimConfig(noise_nt=0.0, seed=4, trajectory='smooth')).sample(t).raw
