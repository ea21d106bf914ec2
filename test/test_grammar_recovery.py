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
Every coupling x driver kind of the grammar recovered from a signal written by hand.

The data are the cross of test/injection.py (1500 epochs at 5 Hz, 300 s, 3 nT Gaussian noise
per axis) with one term's signal added by test/inject_terms.py, computed from the term's
physics and not by ``magcal_ros.core.effects``.  The model ``base + <term>`` is fitted and the
term's fitted change of the reading (the model's contribution at the fitted parameters) is
compared with the injected one, both with their mean over the record removed (a constant is
the base offset's).

Tolerance from the noise: the injected signal lies in the term's span, so the fitted signal
differs from it only by the noise projected onto the term's columns.  With m columns per
axis, N epochs and sigma = 3 nT that error has RMS sigma sqrt(m / N) per axis
(0.08 nT for m = 1, 0.19 nT for m = 6 at N = 1500): the test allows 4 times that (plus
0.05 nT for the base's own parameters that share the span), while the injected signals are
10-40 nT RMS: a wrong sign, factor or basis fails by two orders of magnitude.
"""
import inject_terms as it
import injection as inj
from magcal_ros.core.model import fit, Model
import numpy as np
import pytest

N = 1500
SIGMA = inj.SIGMA_NT


def _t(t, temp, aux):
    return t


def _tc(t, temp, aux):
    return t - t.mean()


def _cubic(t, temp, aux):
    u = (t - 150.0) / 150.0
    return np.stack([20 * u ** 3, -15 * u ** 2 + 8 * u, 12 * u], axis=1)


def _wheel(t, temp, aux):
    """Return a wheel angle (rad, wraps at 2 pi) turning at 0.13 rev/s."""
    return np.mod(2 * np.pi * 0.13 * t, 2 * np.pi)


def _aux_wheel(data):
    data.aux['aux_wheel_angle'] = _wheel(data.t, None, None)
    return data


CASES = {
    # term: (inject, n columns per axis)
    'offset(s(t, k=6))@2': (it.offset(2, _cubic), 6),
    'offset(poly(t, 2))@3': (it.offset(3, lambda t, T, a: np.stack(
        [((t - t.mean()) / 150) ** 2 * 25, (t - t.mean()) / 150 * -10,
         ((t - t.mean()) / 150) ** 2 * 5], axis=1)), 2),
    'offset(sin(0.05))@1': (it.offset(1, lambda t, T, a: np.stack(
        [14 * np.cos(2 * np.pi * 0.05 * t), -9 * np.sin(2 * np.pi * 0.05 * t),
         6 * np.cos(2 * np.pi * 0.05 * t + 1.0)], axis=1)), 2),
    'offset(step(100, 200))@4': (it.offset(4, lambda t, T, a: np.stack(
        [30.0 * (t >= 100) - 10 * (t >= 200), -20.0 * (t >= 200), 0 * t], axis=1)), 2),
    'offset(window(120, 160))@2': (it.offset(2, lambda t, T, a: np.outer(
        (t >= 120) & (t <= 160), [35.0, -25.0, 15.0])), 1),
    'offset(temperature)@3': (it.offset(3, lambda t, T, a: np.outer(
        T[2] - T[2].mean(), [2.5, -1.5, 1.0])), 1),
    'offset(aux_motor_current)@1': (it.offset(1, lambda t, T, a: np.outer(
        a['aux_motor_current'] - a['aux_motor_current'].mean(), [4.0, 2.0, -3.0])), 1),
    'offset(temperature * t)@2': (it.offset(2, lambda t, T, a: np.outer(
        (T[1] - T[1].mean()) * (t - t.mean()), [0.02, -0.015, 0.01])), 1),
    'offset(cc(aux_wheel_angle, k=2))@3': (it.offset(3, lambda t, T, a: np.stack(
        [20 * np.cos(_wheel(t, T, a)), 10 * np.sin(2 * _wheel(t, T, a)),
         -8 * np.sin(_wheel(t, T, a))], axis=1)), 4),
    'scale(temperature)@2': (it.scale(2, [3e-4, -2e-4, 1e-4],
                                      lambda t, T, a: T[1] - T[1].mean()), 1),
    'scale(s(t, k=4))@4': (it.scale(4, [4e-4, 2e-4, -3e-4],
                                    lambda t, T, a: ((t - 150) / 150) ** 3), 4),
    'linear(t)@3': (it.linear(3, np.array([[1, 2, -1], [0.5, -1, 2], [-2, 1, 0.5]]) * 2e-6,
                              _tc), 3),
    'nonorth(t)@2': (it.nonorth(2, (3e-6, -2e-6, 4e-6), _tc), 1),
    'rotation(sin(0.02))@4': (it.rotation(4, (2e-4, -1.5e-4, 1e-4), lambda t, T, a: np.cos(
        2 * np.pi * 0.02 * t)), 2),
    'offset(window(120, 160))@alike': (it.offset_alike(lambda t, T, a: np.outer(
        (t >= 120) & (t <= 160), [25.0, -18.0, 12.0])), 1),
}


def _fit(formula, inject, n=N, prep=None):
    data = inj.make(n=n, seed=3, inject=inject)
    if prep:
        prep(data)
    return fit(data, 'base + ' + formula, inj.F_NT, check_identifiability=False,
               on_degenerate='flag'), data


def _fitted_signals(res, formula):
    """{sensor: (N, 3) nT fitted contribution of the term's effects} at the fitted params."""
    term = Model.from_spec(formula, 4).spec()[0].split('@')[0]
    out = {}
    for j in range(1, 5):
        for eff, sl in zip(res.model.effects[j - 1], res.model.slices[j - 1]):
            if eff.label.split('@')[0] == term:
                ctx = res.contexts[j - 1]
                lin = res.field_nt @ res.model.matrix(j, res.params).T
                out[j] = eff.contribution(res.params[sl], ctx, lin)
    return out


@pytest.mark.parametrize('formula', sorted(CASES))
def test_term_recovered_from_a_signal_written_by_hand(formula):
    inject, m = CASES[formula]
    prep = _aux_wheel if 'wheel' in formula else None
    res, data = _fit(formula, inject, prep=prep)
    # the injected signal, computed again by the hand-written function
    t, b = inj.tumbling_field(N, seed=3)
    temp, aux = inj.channels(t, 3)
    if prep:
        aux['aux_wheel_angle'] = _wheel(t, None, None)
    truth = inject(t, temp, aux, b)
    fitted = _fitted_signals(res, formula)
    assert sorted(fitted) == sorted(truth)
    tol = 4 * SIGMA * np.sqrt(m / N) + 0.05
    for j, sig in truth.items():
        err = it.centred(fitted[j]) - it.centred(sig)
        rms_err = np.sqrt(np.mean(err ** 2, axis=0))
        assert np.all(rms_err < tol), (formula, j, rms_err, tol,
                                       np.sqrt(np.mean(it.centred(sig) ** 2, axis=0)))
    # and nothing left over: every sensor's noise estimate is the injected 3 nT (+-10 %,
    # 1500 x 3 residuals: the sd of a sd estimate is 3 / sqrt(2 x 4500) = 0.03 nT)
    assert np.all(np.abs(res.sigma_nt - SIGMA) < 0.3), res.sigma_nt


def test_lag_with_fitted_time_constant():
    """offset(lag(temperature)): the gain and the time constant of a 40 s lag."""
    coef, tau = np.array([3.0, -2.0, 1.5]), 40.0

    def inject(t, temp, aux, b):
        y = inj.lowpass(t, temp[1], tau)
        return {2: np.outer(y - temp[1].mean(), coef)}
    res, _ = _fit('offset(lag(temperature))@2', inject)
    info = res.model.param_info()
    got = {nm: (v, s) for (j, lab, nm, _), v, s in zip(info, res.params, res.stderr)
           if j == 2 and lab.startswith('offset(lag')}
    # stderr of tau from the fit's covariance (noise 3 nT); 5 standard errors allowed
    assert abs(got['tau'][0] - tau) < 5 * got['tau'][1] + 0.5, got['tau']
    for ax, c in zip('xyz', coef):
        assert abs(got['b' + ax][0] - c) < 5 * got['b' + ax][1] + 0.01, (ax, got['b' + ax])


def test_field_coupling_recovers_a_varying_field_magnitude():
    """field(s(t, k=5)): the magnitude F0 + dm(t) common to every sensor."""
    def dm(t, temp, aux):
        u = (t - 150.0) / 150.0
        return 12.0 * u ** 3 - 6.0 * u

    res, data = _fit('field(s(t, k=5))', it.field(dm))
    eff = res.model.array_effects[0]
    sl = res.model.array_slices[0]
    got = eff.magnitude(res.params[sl], res.contexts[0])
    want = dm(data.t, None, None)
    # 5 parameters for the 12 axes' 1500 epochs (the field direction is profiled out):
    # error RMS about sigma sqrt(5 / (3 N)) per sensor, 0.1 nT; allowed 0.4 nT
    err = (got - got.mean()) - (want - want.mean())
    assert np.sqrt(np.mean(err ** 2)) < 0.4, np.sqrt(np.mean(err ** 2))
    # without the term the scalar residual carries the 6-7 nT RMS of dm
    assert np.all(np.abs(res.sigma_nt - SIGMA) < 0.3), res.sigma_nt


def test_alike_is_one_parameter_set_with_the_expected_standard_error():
    """
    offset(window)@alike: 3 parameters for every sensor, se = sigma sqrt(3 / (S n_in)).

    A vector added alike to every (nearly aligned) sensor is almost a change of the common
    field, whose direction is unknown at every epoch (profiled out): only its component
    along the field is seen, on average 1/3 of its square over a tumble that covers the
    sphere.  So the standard error is sqrt(3) times that of a mean over the S = 4 sensors'
    n_in epochs in the window (less the share n_in / N the base offsets take).
    """
    vec = np.array([25.0, -18.0, 12.0])
    res, data = _fit('offset(window(120, 160))@alike', CASES[
        'offset(window(120, 160))@alike'][0])
    rows = [(i, info) for i, info in enumerate(res.model.param_info())
            if info[1] == 'offset(window(120, 160))@alike']
    assert [info[0] for _, info in rows] == [0, 0, 0]        # one set, the array's
    n_in = int(np.sum((data.t >= 120) & (data.t <= 160)))
    se = SIGMA * np.sqrt(3.0 / (4 * n_in)) / np.sqrt(1 - n_in / N)
    for (i, _), v in zip(rows, vec):
        assert 0.7 * se < res.stderr[i] < 1.5 * se, (res.stderr[i], se)
        assert abs(res.params[i] - v) < 4 * se, (res.params[i], v, se)


def test_drop_leaves_a_disturbance_out_of_the_fit():
    """A 300 nT burst in [120, 160] s on sensor 2: drop(120, 160) fits the rest to the floor."""
    rng = np.random.default_rng(9)
    burst = rng.normal(0, 300.0, (N, 3))

    def inject(t, temp, aux, b):
        return {2: burst * ((t >= 120) & (t <= 160))[:, None]}
    res, data = _fit('drop(120, 160)', inject)
    n_in = int(np.sum((data.t >= 120) & (data.t <= 160)))
    assert res.n_fit_samples == N - n_in
    assert abs(res.sigma_nt[1] - SIGMA) < 0.3, res.sigma_nt
    plain = fit(data, 'base', inj.F_NT, check_identifiability=False, on_degenerate='flag')
    assert plain.sigma_nt[1] > 10 * SIGMA, plain.sigma_nt


def test_sinusoid_frequency_refined():
    """offset(sin(0.05, refine=true))@3: a 0.0503 Hz line found from 0.05 Hz (df fitted)."""
    f_true, amp = 0.0503, np.array([14.0, -9.0, 6.0])

    def inject(t, temp, aux, b):
        return {3: np.outer(np.cos(2 * np.pi * f_true * t), amp)}
    res, _ = _fit('offset(sin(0.05, refine=true))@3', inject)
    info = res.model.param_info()
    i = [k for k, (j, lab, nm, _) in enumerate(info) if j == 3 and nm == 'df'][0]
    # the fit's stderr of df (Cramer-Rao for a line of ~10 nT in 3 nT noise over 300 s is
    # of order 1e-6 Hz); 5 standard errors allowed
    assert abs(res.params[i] - (f_true - 0.05)) < 5 * res.stderr[i], (
        res.params[i], res.stderr[i])
    assert abs(res.sigma_nt[2] - SIGMA) < 0.3, res.sigma_nt
