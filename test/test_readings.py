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
Readings no field produces (issue 22, item 7): pinned, clipped and repeating channels.

The faults are written here (clip, hold, pin) on the hand-written cross of test/injection.py
and on quantised channels built below; the counts and times they must be named with are
computed from the injected data, not by the screen under test.
"""
import functools
import pathlib

import injection
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.data.readings import (ALPHA, leave_out_unphysical, repeat_bounds,
                                           screen_readings, UnphysicalReadingsError)
from magcal_ros.io.csvio import read_csv, write_csv
from magcal_ros.io.single_csv import read_single_sensor_csv
from magcal_ros.pipeline import calibrate
import numpy as np
import pytest
from test_cli import run_cli

REPO = pathlib.Path(__file__).resolve().parents[1]
#: the real recordings in the repository (issue 22 item 1), gzip-compressed CSV
REAL = REPO / 'data' / 'real'
#: the HMC5883L quantum: 1/1090 gauss (gain 1.3 Ga), nT
Q_HMC = 1e5 / 1090.0


def clipped_cross(n=3000, sensor=1, axis=0, fraction=0.06):
    """Make the cross with one axis clipped symmetrically so that ``fraction`` of it is clipped."""
    data = injection.make(n=n, seed=0)
    x = data.raw[sensor - 1, :, axis]
    lim = np.quantile(np.abs(x), 1.0 - fraction)
    clipped = np.abs(x) >= lim
    data.raw[sensor - 1, :, axis] = np.clip(x, -lim, lim)
    return data, clipped, lim


@pytest.fixture(scope='module')
def clip1():
    return clipped_cross()


def test_clipped_axis_is_named_and_left_out_not_fitted(clip1):
    data, clipped, lim = clip1
    assert clipped.sum() == 180                     # 6 % of 3000
    # the failure: fitted with the clipped readings, the correlation check blames two
    # sensors whose data are fine
    with pytest.raises(ValueError, match='correlated'):
        calibrate(data, 'base', field_nt=injection.F_NT, screen=False)
    run = calibrate(data, 'base', field_nt=injection.F_NT)
    left = run.summary['readings_left_out']
    assert left['sets_left_out'] == 180 and left['sets'] == 3000
    (ch,) = left['channels']
    assert (ch['sensor'], ch['axis'], ch['kind']) == (1, 'x', 'clipped')
    assert sorted(ch['values_nt']) == pytest.approx([-lim, lim])
    # the stretches are exactly the clipped epochs' times
    idx = np.flatnonzero(clipped)
    starts = idx[np.r_[True, np.diff(idx) > 1]]
    ends = idx[np.r_[np.diff(idx) > 1, True]]
    assert ch['stretches_s'] == [[round(data.t[a], 3), round(data.t[b], 3)]
                                 for a, b in zip(starts, ends)]
    (w,) = [w for w in run.summary['warnings'] if w['kind'] == 'readings']
    assert w['sensor'] == 1 and '\n' not in w['text']
    assert w['text'].startswith(f'sensor 1 axis x: clipped at {lim:+.1f} and {-lim:+.1f} nT')
    assert 'in 180 of 3000 readings (6.0 %)' in w['text']
    assert w in run.doc['provenance']['warnings']
    assert run.doc['provenance']['readings_left_out'] == left
    # what is left is fitted to the noise: 2820 sets, RMS of 3 nT white noise to +-6 %
    for j in '1234':
        assert abs(run.summary['scalar_rms_nt'][j] / injection.SIGMA_NT - 1) < 0.06


def test_cli_fit_and_diagnose_name_the_clipped_axis(clip1, tmp_path):
    data, _, _ = clip1
    path = tmp_path / 'clip.csv'
    write_csv(path, data)
    rc, out, err = run_cli('fit', path, '--field-nt', injection.F_NT)
    assert rc == 0, err
    assert 'warning [readings]: sensor 1 axis x: clipped at' in out
    assert '180 of 3000 sets that hold them are left out of the fit' in out
    rc, out, err = run_cli('diagnose', path, '--field-nt', injection.F_NT, '-q')
    assert rc == 0, err
    assert 'on 2820 epochs' in out and 'warning [readings]: sensor 1 axis x: clipped' in out
    assert 'verdict: none' in out


def test_stalled_sensor_repeats_its_last_reading():
    data = injection.make(n=3000, seed=1)
    s0, length = 1200, 150                    # sensor 3's driver re-sends one sample 149 times
    data.raw[2, s0 + 1:s0 + length] = data.raw[2, s0]
    screen = screen_readings(data)
    assert [(c.sensor, c.axis, c.kind) for c in screen.channels] == [
        (3, 'x', 'repeated'), (3, 'y', 'repeated'), (3, 'z', 'repeated')]
    for c in screen.channels:
        assert c.count == length - 1
        assert c.stretches == ((round(data.t[s0 + 1], 3), round(data.t[s0 + length - 1], 3)),)
    (line,) = screen.lines()            # the three axes, one line
    assert line[0] == 3 and line[1].startswith('sensor 3 axes x, y, z: repeats its last reading')
    assert f'in {length - 1} of 3000 readings' in line[1]
    keep = np.ones(3000, bool)
    keep[s0 + 1:s0 + length] = False    # the first is a genuine reading
    assert np.array_equal(screen.keep, keep)


def test_pinned_axis_refuses_with_the_reason(tmp_path):
    data = injection.make(n=3000, seed=2)
    # an HMC5883L writes -4096 to an axis whose ADC overflowed: here every reading of it
    pinned = -4096 * Q_HMC
    data.raw[1, :, 2] = pinned
    with pytest.raises(UnphysicalReadingsError) as exc:
        leave_out_unphysical(data)
    msg = str(exc.value)
    assert msg.startswith(f'sensor 2 axis z: pinned at {pinned:+.1f} nT in 3000 of 3000 readings')
    assert 'only 0 of 3000 sets are left' in msg
    path = tmp_path / 'pinned.csv'
    write_csv(path, data)
    rc, out, err = run_cli('fit', path, '--field-nt', injection.F_NT)
    assert rc == 2 and out == ''
    assert err.count('\n') == 1
    assert err.startswith('magcal: error: sensor 2 axis z: pinned at')


@functools.lru_cache(maxsize=None)
def _tumble(n, seed):
    """Return injection.tumbling_field(n, seed=seed), once for the four noise levels."""
    return injection.tumbling_field(n, seed=seed)


def quantised(n, q, sigma_w, seed, still=(), dup=0.0):
    """
    One quantised three-axis sensor on the tumbling field: Q(b + e), e ~ N(0, sigma_w^2).

    ``still``: (start, stop) epochs during which the sensor does not turn; ``dup``: fraction
    of epochs at which a logger re-reads the previous sample (all three axes).
    """
    rng = np.random.default_rng(seed)
    t, b = (x.copy() for x in _tumble(n, seed))
    for a, z in still:
        b[a:z] = b[a]
    raw = q * np.round((b + rng.normal(0, sigma_w, b.shape)) / q)
    rep = np.flatnonzero(rng.random(n) < dup)
    for k in rep[rep > 0]:
        raw[k] = raw[k - 1]
    return Dataset(t=t, raw=raw[None])


@pytest.mark.parametrize('sigma_q', [0.3, 0.7, 1.5, 4.0])
def test_bound_on_repeats_holds_for_quantised_noise(sigma_q):
    # the derivation (module docstring) checked by counting: a live quantised channel,
    # still for a third of the record (the worst case: no signal change), repeats its last
    # reading no more often than the bound, and no run reaches the flagged length
    data = quantised(20000, Q_HMC, sigma_q * Q_HMC, seed=5, still=[(2000, 9000)], dup=0.03)
    p = repeat_bounds(data.raw)[0]
    same = np.diff(data.raw[0], axis=0) == 0
    still = same[2000:8999]
    # binomial sd of a frequency over 7000 pairs is below 0.006: 3 sd
    assert np.all(still.mean(axis=0) <= p + 0.018)
    assert screen_readings(data).channels == []


def test_quantised_clipping_and_stall_are_found():
    # the same HMC-like sensor (1.5 quanta of noise, 3 % duplicated epochs), clipped on y
    data = quantised(6000, Q_HMC, 1.5 * Q_HMC, seed=6, dup=0.03)
    y = data.raw[0, :, 1]
    top = Q_HMC * np.round(np.quantile(y, 0.95) / Q_HMC)
    data.raw[0, :, 1] = np.minimum(y, top)
    screen = screen_readings(data)
    (c,) = screen.channels
    assert (c.kind, c.axis, c.values_nt) == ('clipped', 'y', (top,))
    assert c.count == int((data.raw[0, :, 1] == top).sum())


def _run_lengths(x):
    """Lengths of the runs of equal consecutive values of x (N,)."""
    edges = np.flatnonzero(np.diff(x) != 0)
    return np.diff(np.concatenate([[-1], edges, [len(x) - 1]]))


def test_real_recordings_are_not_flagged():
    # the public HMC5883L recordings (quantum 91.7 nT, ~1.5 quanta of noise, 3 % duplicated
    # epochs of an oversampling logger, runs of equal readings up to 15 long) and a consumer
    # IMU's full sphere: live sensors whose repeats are legitimate; one real glitch, a
    # spike (test_spikes.py), in pan-along-z-pointing-up
    files = sorted((REAL / 'sunsided-hmc5883l').glob('*/*.csv.gz'))
    assert len(files) == 13
    records = [np.asarray(read_csv(f).raw, float) for f in files]
    # how long a live channel's runs of equal readings get, from the recordings themselves
    # (counted here with numpy, independent of the screen): the share of epochs that start a
    # run of L or more falls geometrically with L (ratio ~0.22 from L = 2 to 8, where each
    # count is 6 or more); a run as long as L* = the first L at which a record of N epochs
    # and 3 channels expects ALPHA (the screen's family-wise 1e-3) such runs is what the screen
    # may first flag
    lengths = np.concatenate([_run_lengths(r[0, :, a]) for r in records for a in range(3)])
    epochs = sum(3 * r.shape[1] for r in records)
    ls = np.arange(2, 9)
    share = np.array([(lengths >= L).sum() for L in ls]) / epochs
    slope, icept = np.polyfit(ls, np.log(share), 1)
    for f, raw in zip(files, records):
        screen = screen_readings(read_csv(f))
        spikes = [c for c in screen.channels if c.kind == 'spike']
        assert len(spikes) == (f.name == 'pan-along-z-pointing-up.csv.gz'), f.name
        assert [c for c in screen.channels if c.kind != 'spike'] == [], (f.name, screen.lines())
        n = raw.shape[1]
        l_star = int(np.ceil((np.log(ALPHA / (3 * n)) - icept) / slope))
        for a in range(3):
            longest = _run_lengths(raw[0, :, a]).max()
            assert max(longest, l_star) < screen.min_run[0, a], (f.name, a, longest, l_star)
    ck = read_single_sensor_csv(REAL / 'ck-accmag' / 'acc_mag_log.csv.gz', unit='gauss')
    assert screen_readings(ck).channels == []
