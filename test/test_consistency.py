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
Sets paired from different epochs: found and re-paired from the data (core.consistency).

Data: the core simulator's cross (paper 004 Table 1 errors, 3 nT white noise per axis), 30 s
of smooth tumbling at 100 Hz, where the field turns by ~100 nT per epoch (median), so a set
paired one epoch off is off by ~100 nT against a per-axis misfit of sqrt(2) x 3 nT = 4.2 nT
for a right pairing.  Slips are made by re-indexing one sensor's samples, so the right
pairing is known exactly and the repaired sets can be compared sample by sample.
"""
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.live.consistency import DROP, find_slips, gross_outliers, resync
from magcal_ros.core.model import fit
import numpy as np
import pytest

RATE = 100.0
SIGMA = 3.0
F = 50000.0
#: driven effects the check must not take for slips: temperature offsets of sensor 2
#: (+-8 degC swing: +-30 nT) and a 0..5 A motor current on sensor 3 (up to ~60 nT)
EFFECTS = {'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0],
           'aux:aux_motor_current@3': [10.0, -5.0, 7.0]}


def tumbling(seed, truth=None, n=3000):
    data, _ = simulate(n_samples=n, rate_hz=RATE, trajectory='smooth', seed=seed,
                       truth=truth or {})
    return data


def slip(data, source):
    """Sensor j of set e takes the sample of set source[j][e] (clipped to the record)."""
    n = data.n_samples
    raw = np.stack([data.raw[j, np.clip(source[j], 0, n - 1)] for j in range(data.n_sensors)])
    return Dataset(t=data.t, raw=raw)


@pytest.mark.parametrize('seed', [4, 5, 6])
@pytest.mark.parametrize('effects', [False, True])
def test_right_pairings_are_left_alone(seed, effects):
    data = tumbling(seed, EFFECTS if effects else None)
    s = find_slips(data.raw)
    assert s.n_slipped.tolist() == [0, 0, 0, 0]
    fixed, _, dropped, gross = resync(data, slips=s)
    assert fixed is data and dropped == gross == 0
    # the misfit of a right pairing is the two sensors' noise (effect-free sensor 4)
    assert s.rms_nt[3] == pytest.approx(np.sqrt(2) * SIGMA, rel=0.1)
    np.testing.assert_allclose(s.noise_nt, SIGMA, rtol=0.1)


@pytest.mark.parametrize('seed', [4, 5, 6])
def test_slips_are_found_and_re_paired_sample_by_sample(seed):
    data = tumbling(seed)
    n = data.n_samples
    source = np.tile(np.arange(n), (4, 1))
    source[1] += 1                  # sensor 2: the whole record one epoch late
    source[2, 1000:1800] -= 1       # sensor 3: 8 s one epoch early
    source[3, 2000:2400] += 2       # sensor 4: 4 s two epochs late
    bad = slip(data, source)
    s = find_slips(bad.raw)
    # a re-pairing is right when the set it takes sensor j's sample from holds epoch e
    idx = np.arange(n)
    for j in (1, 2, 3):
        moved = np.flatnonzero((s.lags[j] != 0) & (s.lags[j] != DROP))
        src = moved + s.lags[j][moved]
        inside = (src >= 0) & (src < n)
        assert np.all(source[j][src[inside]] == moved[inside]), j
        # and every slipped set is found, but at most two at the ends of a stretch
        slipped = np.flatnonzero(source[j] != idx)
        dropped = np.flatnonzero(s.lags[j] == DROP)
        assert len(np.setdiff1d(slipped, np.r_[moved, dropped])) <= 2, j
        assert len(dropped) <= 2, j
    assert s.rms_as_paired_nt[1:].min() > 5 * SIGMA     # (the record RMS of 800 slipped sets)
    np.testing.assert_allclose(s.rms_nt[1:], np.sqrt(2) * SIGMA, rtol=0.1)
    assert len(s.summary()) == 3 and s.summary()[0].startswith('sensor 2:')

    fixed, _, dropped, _ = resync(bad, slips=s)
    assert dropped <= 6             # the ends of the record and of each stretch
    epoch = np.rint(fixed.t * RATE).astype(int)
    np.testing.assert_array_equal(fixed.raw, data.raw[:, epoch])
    # and the maximum-likelihood fit is back at the noise floor
    r = fit(fixed, 'base', field_nt=F)
    np.testing.assert_allclose(r.sigma_nt, SIGMA, rtol=0.06)


def test_no_re_pairing_across_runs_of_epochs():
    data = tumbling(5)
    n = data.n_samples
    epochs = np.arange(n)
    epochs[1500:] += 7              # sets 1500.. come after a gap of 7 epochs
    source = np.tile(np.arange(n), (4, 1))
    source[2] += 1                  # sensor 3 late everywhere
    source[2, 1499] = 1499          # (a sensor cannot be late across the gap)
    bad = slip(data, source)
    s = find_slips(bad.raw, epochs)
    lags = s.lags[2]
    assert np.all(lags[1:1499] == -1) and np.all(lags[1501:] == -1)
    fixed, _, dropped, _ = resync(bad, epochs, slips=s)
    epoch = np.rint(fixed.t * RATE).astype(int)
    np.testing.assert_array_equal(fixed.raw, data.raw[:, epoch])
    # the first set of each run has no partner in its run; the partner of the set at 1500
    # would be 1499, in the other run
    assert 0 not in epoch and 1500 not in epoch and dropped <= 3


def test_nothing_to_tell_without_attitudes_or_samples():
    turntable, _ = simulate(n_samples=600, rate_hz=RATE, trajectory='turntable', seed=3)
    assert find_slips(turntable.raw).n_slipped.tolist() == [0, 0, 0, 0]   # single axis
    short = tumbling(4, n=80)
    assert find_slips(short.raw).n_slipped.tolist() == [0, 0, 0, 0]
    one = Dataset(t=short.t, raw=short.raw[:1])
    assert find_slips(one.raw).n_slipped.tolist() == [0]
    with pytest.raises(ValueError, match=r'shape \(S, N, 3\)'):
        find_slips(short.raw[:, :, :2])
    with pytest.raises(ValueError, match='epochs must have shape'):
        find_slips(tumbling(4).raw, epochs=np.arange(5))


def test_garbled_samples_are_dropped_and_nothing_else():
    # a line that lost its first bytes still parses: '45.6,...' from '12345.6,...' (x off by
    # ~12 000 nT), a lost leading digit of z (10x smaller); and large but real effects stay
    data = tumbling(4, EFFECTS)
    assert not gross_outliers(data.raw).any()
    bad = Dataset(t=data.t, raw=data.raw.copy(), temp=data.temp, aux=data.aux)
    bad.raw[2, 1234, 0] = 45.6
    bad.raw[1, 77, 2] /= 10.0
    assert np.argwhere(gross_outliers(bad.raw)).tolist() == [[1, 77], [2, 1234]]
    fixed, s, dropped, gross = resync(bad)
    assert gross == 2 and dropped == 0 and s.n_slipped.sum() == 0
    epoch = np.rint(fixed.t * RATE).astype(int)
    assert fixed.n_samples == data.n_samples - 2 and 77 not in epoch and 1234 not in epoch
    np.testing.assert_array_equal(fixed.raw, data.raw[:, epoch])
    np.testing.assert_array_equal(fixed.temp, data.temp[:, epoch])
    # a single-axis rotation cannot tell: nothing is flagged
    turntable, _ = simulate(n_samples=600, rate_hz=RATE, trajectory='turntable', seed=3)
    assert not gross_outliers(turntable.raw).any()
