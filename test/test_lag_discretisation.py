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
The lag's one discretisation: the batch filter and the live corrector, against hand values.

Both run the step of ``effects.base.lag_coefficients`` (exact for an input linear between
samples, the first-order-hold equivalent of 1 / (tau s + 1)), so a ramp is followed exactly
at any sampling, and a calibration corrects a record the same whether it sees it whole or
one sample at a time (issue 33: the live lag held zero-order, the batch first-order).
"""
import injection as inj
from magcal_ros.core.effects import SensorContext
from magcal_ros.core.effects.base import first_order_lag, lag_step
from magcal_ros.core.live.corrector import LiveCorrector
from magcal_ros.core.model import fit
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, parse_calibration
import numpy as np
import pytest


def _live(t, x, tau):
    state, out = None, []
    for tk, xk in zip(t, x):
        state, y = lag_step(state, tk, xk, tau)
        out.append(y)
    return np.array(out)


def test_ramp_is_followed_exactly_at_irregular_samples():
    # tau y' = x - y, x = 2 t, y(0) = 0: y = 2 (t - tau + tau e^(-t/tau)) (by hand)
    rng = np.random.default_rng(3)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 0.6, 400))])
    tau = 4.0
    want = 2.0 * (t - tau + tau * np.exp(-t / tau))
    for got in (first_order_lag(t, 2.0 * t, tau), _live(t, 2.0 * t, tau)):
        # rounding: y ~ 200 at 1e-16, the ramp's 2 t to 1e-13 after 400 steps
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11)


def test_two_steps_by_hand():
    # t = 0, 1, 3 s; x = 0, 1, 1; tau = 2 s: a ramp 0 -> 1 over 1 s, then 1 held 2 s
    y1 = 1.0 - 2.0 * (1.0 - np.exp(-0.5))          # ramp response at 1 s: 2 e^-1/2 - 1
    y2 = 1.0 + (y1 - 1.0) * np.exp(-1.0)            # then the constant's: e^-(2/2)
    want = [0.0, y1, y2]
    np.testing.assert_allclose(first_order_lag([0.0, 1.0, 3.0], [0.0, 1.0, 1.0], 2.0), want,
                               rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(_live([0.0, 1.0, 3.0], [0.0, 1.0, 1.0], 2.0), want,
                               rtol=1e-15, atol=1e-15)


def test_a_stamp_repeated_holds_and_a_clock_that_goes_back_restarts():
    t = [0.0, 1.0, 1.0, 2.0, 0.5]
    x = [0.0, 4.0, 8.0, 8.0, 3.0]
    got = first_order_lag(t, x, 1.0)
    assert got[2] == got[1]                    # dt = 0: y held, the next step starts at 8
    # 1 -> 2 s: x = 8 held, y relaxes towards it: 8 + (y - 8) e^-1 (by hand)
    assert got[3] == pytest.approx(8.0 + (got[2] - 8.0) * np.exp(-1.0), rel=1e-15)
    assert got[4] == 3.0                       # back in time: steady state again
    np.testing.assert_array_equal(_live(t, x, 1.0), got)
    # the fixed-point correction calls the live step again at the same stamp: no change
    state, y = lag_step(None, 0.0, 0.0, 1.0)
    state, y = lag_step(state, 1.0, 4.0, 1.0)
    assert lag_step(state, 1.0, 4.0, 1.0) == (state, y)


@pytest.mark.parametrize('jitter', [0.0, 0.3])
def test_live_corrector_corrects_a_record_as_the_fit_does(jitter):
    """A fit with a lag, and the live corrector fed the record sample by sample: equal."""
    data = inj.make(1200, seed=4, inject=inj.lag_fault(40.0, (4.0, -3.0, 2.5), 2))
    # nonlinearity reads the field: the correction of sensor 2 iterates (fixed point) with
    # the lag in it
    res = fit(data, 'base,lag(temperature)@2,nonlinearity@2,aux:aux_motor_current@3',
              inj.F_NT, check_identifiability=False, on_degenerate='flag')
    tau = res.params[[i for i, (s, lab, n, _) in enumerate(res.model.param_info())
                      if lab == 'lag(temperature)' and n == 'tau'][0]]
    assert tau == pytest.approx(40.0, rel=0.2)        # the lag is really there and fitted
    if jitter:
        # stamps 0.1 s +- 30 %: the batch filter then runs its scan, not lfilter
        rng = np.random.default_rng(5)
        data.t = np.cumsum(0.1 * (1 + rng.uniform(-jitter, jitter, len(data.t))))
    cal, _ = parse_calibration(dump_calibration(calibration_to_doc(res.calibration)), 'lag')
    batch = res.calibration.correct_dataset(data)
    live = LiveCorrector(cal, 4, check_pairing=False)
    got = np.empty_like(batch)
    for k, tk in enumerate(data.t):
        live.set_aux('aux_motor_current', data.aux['aux_motor_current'][k])
        for j in range(1, 5):
            live.set_temperature(j, data.temp[j - 1][k])
            got[j - 1, k] = live.correct(j, tk, data.raw[j - 1][k])
    # the same arithmetic in another order: rounding of ~1e5 nT readings (1e-11 nT) and of
    # the filter's 1200 steps; 1e-9 nT is 3e-10 of the 3 nT noise
    np.testing.assert_allclose(got, batch, rtol=0, atol=1e-9)
    # and the lag changes the correction there (the comparison sees it)
    assert np.ptp(batch[1] - res.calibration.correct(2, data.raw[1], SensorContext(
        t=data.t, temp=np.full_like(data.t, np.nan),
        aux={'aux_motor_current': data.aux['aux_motor_current']}))) > 1.0
