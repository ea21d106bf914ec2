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
Result objects in the statsmodels manner: immutable, per-epoch arrays on demand, signatures.

The data are written here (field directions uniform on the sphere, raw = k B + o + noise per
axis), not by the simulator, and the per-epoch arrays are checked against values computed
here from the fitted parameters: the corrected reading (raw - o) / k, and the
maximum-likelihood field on the sphere |B| = F, B_i = k_i m_i / (k_i^2 + lambda) with the
Lagrange multiplier lambda found per epoch by root finding (scipy.optimize.brentq).
"""
import dataclasses
import inspect

from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.discovery import diagnose, ladder
from magcal_ros.core.model import fit, FitResult
import numpy as np
import pytest
from scipy.optimize import brentq

F = 50000.0
SIGMA = 3.0
#: per sensor: scale factors (1) and offsets (nT)
SCALE = np.array([[1.02, 0.97, 1.01], [0.99, 1.03, 0.98]])
OFFSET = np.array([[120.0, -80.0, 45.0], [-60.0, 150.0, -30.0]])
#: the (S, N, 3) arrays of a FitResult that must not be computed until read
LAZY = ('corrected_nt', 'residual_nt', 'vector_residual_nt', 'scalar_residual_nt',
        'field_nt')


def _data(n=800, seed=5):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    b = F * u / np.linalg.norm(u, axis=1, keepdims=True)
    raw = np.stack([b * SCALE[j] + OFFSET[j] + rng.normal(0.0, SIGMA, (n, 3)) for j in range(2)])
    return Dataset(t=np.arange(n, dtype=float), raw=raw)


@pytest.fixture(scope='module')
def fitted():
    data = _data()
    return data, fit(data, 'offset,scale', field_nt=F)


def _by_hand(res, data):
    """(corrected, ML field) per sensor from the parameter table, computed here."""
    table = {(r['sensor'], r['name']): r['value'] for r in res.param_table()}
    corrected, field = [], []
    for j in (1, 2):
        o = np.array([table[(j, n)] for n in ('bx', 'by', 'bz')])
        k = np.array([table[(j, n)] for n in ('kx', 'ky', 'kz')])
        m = data.raw[j - 1] - o
        corrected.append(m / k)
        b = np.empty_like(m)
        for i, mi in enumerate(m):
            # |B(lambda)| = F with B = k m / (k^2 + lambda); the root next to lambda = 0
            g = lambda lam: np.linalg.norm(k * mi / (k ** 2 + lam)) - F     # noqa: E731
            lam = brentq(g, -0.5, 0.5, xtol=1e-15)
            b[i] = k * mi / (k ** 2 + lam)
        field.append(b)
    return np.stack(corrected), field


def test_fit_result_is_immutable(fitted):
    _, res = fitted
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.params = np.zeros_like(res.params)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.residual_nt = None
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.sigma_nt = res.sigma_nt * 2


def test_per_epoch_arrays_are_computed_on_first_read(fitted):
    data, _ = fitted
    res = fit(data, 'offset,scale', field_nt=F)
    # nothing per epoch is held after the fit
    assert not set(LAZY) & set(vars(res))
    corrected, field = _by_hand(res, data)
    np.testing.assert_allclose(res.corrected_nt, corrected, rtol=0, atol=1e-7)
    assert 'corrected_nt' in vars(res) and 'residual_nt' not in vars(res)
    assert res.corrected_nt is res.corrected_nt               # kept, not recomputed
    # residual = raw - (k B + o) with B the ML field of each sensor on |B| = F
    table = {(r['sensor'], r['name']): r['value'] for r in res.param_table()}
    for j in (1, 2):
        o = np.array([table[(j, n)] for n in ('bx', 'by', 'bz')])
        k = np.array([table[(j, n)] for n in ('kx', 'ky', 'kz')])
        np.testing.assert_allclose(res.residual_nt[j - 1],
                                   data.raw[j - 1] - (k * field[j - 1] + o), rtol=0, atol=1e-6)
    np.testing.assert_allclose(res.scalar_residual_nt,
                               np.linalg.norm(corrected, axis=2) - F, rtol=0, atol=1e-7)
    np.testing.assert_allclose(res.vector_residual_nt, corrected - corrected[:1], rtol=0,
                               atol=1e-7)
    assert set(LAZY) <= set(vars(res))
    # the residual is at the noise written into the data (RMS of 3 x 800 draws: +-3 %)
    assert abs(res.sigma_nt / SIGMA - 1).max() < 0.1


def test_summaries_do_not_keep_the_vector_residual(fitted):
    data, _ = fitted
    res = fit(data, 'offset,scale', field_nt=F)
    corrected, _ = _by_hand(res, data)
    rms = res.vector_rms_nt[2]
    assert rms == pytest.approx(np.sqrt(np.mean((corrected[1] - corrected[0]) ** 2)), rel=1e-9)
    assert 'vector_residual_nt' not in vars(res)


def test_a_replaced_result_recomputes_from_its_own_parameters(fitted):
    data, res = fitted
    where = {(s, n): i for i, (s, _, n, _) in enumerate(res.model.param_info())}
    p = res.params.copy()
    p[where[(1, 'bx')]] += 10.0                               # offset bx of sensor 1, nT
    moved = dataclasses.replace(res, params=p)
    np.testing.assert_allclose(moved.corrected_nt[0, :, 0],
                               res.corrected_nt[0, :, 0] - 10.0 / p[where[(1, 'kx')]],
                               rtol=0, atol=1e-7)


def _keywords(fn):
    params = inspect.signature(fn).parameters.values()
    return ({p.name for p in params if p.kind is p.KEYWORD_ONLY},
            [p.name for p in params if p.kind is p.VAR_KEYWORD])


def test_fit_and_diagnose_show_every_keyword():
    kw, var = _keywords(fit)
    assert kw == {'robust', 'f_scale', 'constrained', 'priors', 'sigma_nt', 'on_degenerate',
                  'max_fit_samples', 'init', 'max_nfev', 'check_identifiability', 'solver',
                  'covariance', 'ftol', 'extra_priors'}
    assert var == []
    kw, var = _keywords(diagnose)
    assert kw == {'base', 'folds', 'alpha', 'max_refit', 'candidates', 'progress',
                  'cv_method', 'max_samples', 'baseline_m', 'constrained', 'propose'}
    assert var == ['fit_kwargs']            # passed on to fit() for the base fit, documented
    assert 'fit_kwargs' in diagnose.__doc__ and 'constrained' in fit.__doc__
    kw, _ = _keywords(ladder)
    assert {'max_steps', 'folds', 'progress', 'diagnosis'} <= kw


def test_diagnosis_is_immutable(fitted):
    data, res = fitted
    diag = diagnose(data, field_nt=F, base=res, folds=0, propose=False,
                    candidates=['temperature@1', 'drift@1'])
    with pytest.raises(dataclasses.FrozenInstanceError):
        diag.verdict_token = 'drift@1'
    with pytest.raises(dataclasses.FrozenInstanceError):
        diag.candidates[0].significant = True
    assert isinstance(diag.result, FitResult)
