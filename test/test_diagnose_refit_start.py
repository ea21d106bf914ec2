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
The diagnosis' refits start well and skip what they do not read (issue 11 item 7, speed).

A lag's refit starts from the best time constant of a grid, each grid point one linear
step (Screen.lag_start); the data are made by the test's own injection (test/injection.py:
a first-order low-pass written there, not Model.forward).  A refit of a candidate whose
reduction test reads no uncertainties skips the covariance (fit(covariance=False)).
"""
import injection as inj
from magcal_ros.core.discovery.candidates import extend_model, reads_stderr
from magcal_ros.core.discovery.constants import REFIT_CHI2_TOL, REFIT_MAX_NFEV
from magcal_ros.core.discovery.measures import lag_grid
from magcal_ros.core.discovery.screen import Screen
from magcal_ros.core.model import fit
import numpy as np
import pytest

F = inj.F_NT
TAU_S = 90.0


@pytest.fixture(scope='module')
def lagged():
    data = inj.make(3000, seed=5, inject=inj.lag_fault(TAU_S, (4.0, -3.0, 2.5), 2))
    return data, fit(data, 'base', field_nt=F)


def _screen(data, base):
    ctx = [data.context(j) for j in range(1, data.n_sensors + 1)]
    base.model.prepare(ctx)
    f = np.full(data.n_samples, F)
    return Screen(base.model, base.params, data.raw, ctx, f, np.asarray(base.sigma_nt)), ctx, f


def test_lag_start_is_the_grid_point_next_to_the_true_time_constant(lagged):
    data, base = lagged
    screen, ctx, f = _screen(data, base)
    m_ext, p_ext, added = extend_model(base.model, base.params, 'lag(temperature)@2', ctx)
    grid = lag_grid(data.t)
    tau_i = [i for i, info in enumerate(m_ext.param_info()) if added[i] and info[2] == 'tau']
    start = screen.lag_start(m_ext, p_ext, added, grid)
    step = grid[1] / grid[0]
    # the profile's best grid point is within one grid step of the injected 90 s
    assert abs(np.log(start[tau_i[0]] / TAU_S)) <= np.log(step), (start[tau_i[0]], grid)
    # the coupling of that step has the injected signs and sizes within 30 % (the grid
    # point is up to a factor 1.8 off in tau, which biases the coefficients)
    coef = start[np.flatnonzero(added)[:3]]
    assert coef == pytest.approx([4.0, -3.0, 2.5], rel=0.3)
    # from there the refit converges within the diagnosis' cap of iterations and to its
    # precision (as run._refit fits), to the truth
    r = fit(data, m_ext, field_nt=f, sigma_nt=base.sigma_nt, init=start,
            check_identifiability=False, max_nfev=REFIT_MAX_NFEV,
            ftol=REFIT_CHI2_TOL / base.chi2)
    assert r.success and r.nfev < REFIT_MAX_NFEV, r.message
    tau, se = r.params[tau_i[0]], r.stderr[tau_i[0]]
    assert abs(tau - TAU_S) < 3 * se + 1e-9, (tau, se)
    # no lag in the candidate: no start
    m_t, p_t, add_t = extend_model(base.model, base.params, 'temperature@2', ctx)
    assert screen.lag_start(m_t, p_t, add_t, grid) is None


def test_fit_without_covariance_has_the_same_parameters_and_no_uncertainty(lagged):
    data, base = lagged
    kw = {'field_nt': F, 'sigma_nt': base.sigma_nt, 'init': base.params,
          'check_identifiability': False}
    with_cov = fit(data, 'base', **kw)
    without = fit(data, 'base', covariance=False, **kw)
    np.testing.assert_array_equal(without.params, with_cov.params)
    assert without.chi2 == with_cov.chi2
    assert np.isnan(without.stderr).all() and np.isfinite(with_cov.stderr).all()
    with pytest.raises(ValueError, match='check_identifiability'):
        fit(data, 'base', field_nt=F, covariance=False)


def test_only_effects_with_their_own_reduction_test_need_the_covariance(lagged):
    data, base = lagged
    ctx = [data.context(j) for j in range(1, data.n_sensors + 1)]
    for token, label, needs in (('lag(temperature)@2', 'lag(temperature)', True),
                                ('temperature@2', 'temperature', False)):
        m_ext, _, _ = extend_model(base.model, base.params, token, ctx)
        assert reads_stderr(m_ext, label) is needs


def test_a_refit_to_a_tenth_of_chi_square_stops_early_at_the_converged_value(lagged):
    # the diagnosis' refits iterate until chi-square changes by less than REFIT_CHI2_TOL
    # (fit(ftol=tol / chi2)); the converged value is fit's default (iterations to the
    # numerical limit) from the same start: the early stop is within the tolerance of it
    # and needs fewer residual evaluations
    data, base = lagged
    ctx = [data.context(j) for j in range(1, data.n_sensors + 1)]
    m_ext, p_ext, added = extend_model(base.model, base.params, 'lag(temperature)@2', ctx)
    screen, _, f = _screen(data, base)
    start = screen.lag_start(m_ext, p_ext, added, lag_grid(data.t))
    kw = {'field_nt': f, 'sigma_nt': base.sigma_nt, 'init': start,
          'check_identifiability': False, 'covariance': False, 'max_nfev': 50}
    full = fit(data, m_ext, **kw)
    early = fit(data, m_ext, ftol=REFIT_CHI2_TOL / base.chi2, **kw)
    assert full.success and early.success
    assert 0.0 <= early.chi2 - full.chi2 <= REFIT_CHI2_TOL, (early.chi2, full.chi2)
    assert early.nfev < full.nfev, (early.nfev, full.nfev)
