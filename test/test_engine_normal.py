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
The variable-projection normal equations formed block by block (ProfiledProblem.normal_equations).

The reference is the dense construction: the projected Jacobian of
ProfiledProblem.jacobian (each epoch's columns multiplied by I - G (G^T G)^-1 G^T) and
J^T J, J^T r formed from it, the path every fit took before.  The data are generated here:
random attitudes, a world field and gradient rotated into the body frame with scipy's
Rotation, per-sensor linear maps and offsets written out below, a temperature drift on
sensor 2.
"""
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.model import fit, Model
from magcal_ros.core.model.engine import ProfiledProblem
from magcal_ros.core.model.fitting import initial_params, priors_for
from magcal_ros.core.model.solvers import (covariance_from_jacobian, covariance_from_normal,
                                           levenberg_marquardt, resolves_covariance)
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

F_NT = 50000.0
NOISE_NT = 3.0
H = 0.25                                            # half baseline of the cross, m
POS = H * np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])
G_W = np.array([[200.0, 150.0, -300.0], [150.0, 100.0, 250.0], [-300.0, 250.0, -300.0]])
_RNG = np.random.default_rng(11)
# per-sensor linear maps: identity + up to 2 % scale, non-orthogonality, misalignment
A_TRUE = np.eye(3) + _RNG.uniform(-0.02, 0.02, (4, 3, 3))
O_TRUE = _RNG.uniform(-150.0, 150.0, (4, 3))       # offsets, nT
TEMP_COEF = np.array([3.0, -2.0, 1.5])              # nT / degC, sensor 2's offset drift


def make_data(n=600, seed=4, gradient=True):
    """Return a Dataset: raw_j = A_j R^T (B_w + G_w R r_j) + o_j (+ drift) + noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 2.0
    rot = Rotation.random(n, random_state=rng)
    b_w = np.array([21000.0, -2500.0, 45000.0])
    b_w *= F_NT / np.linalg.norm(b_w)
    temp = 20.0 + 10.0 * np.sin(2 * np.pi * t / t[-1])[None] + np.arange(4)[:, None]
    raw = np.empty((4, n, 3))
    for j in range(4):
        b_world = b_w + (rot.apply(POS[j]) @ G_W.T if gradient else 0.0)
        raw[j] = rot.inv().apply(b_world) @ A_TRUE[j].T + O_TRUE[j]
        raw[j] += rng.normal(0, NOISE_NT, (n, 3))
    raw[1] += (temp[1] - temp[1].mean())[:, None] * TEMP_COEF
    return Dataset(t=t, raw=raw, temp=temp,
                   attitude=rot.as_quat(scalar_first=True) if gradient else None)


@pytest.fixture(scope='module')
def data():
    return make_data()


def problems(data, spec, constrained=False, seed=0):
    """Yield the ProfiledProblem of each sensor group and a point x away from the optimum."""
    model = Model.from_spec(spec, data.n_sensors)
    ctx = [data.context(j) for j in range(1, data.n_sensors + 1)]
    model.prepare(ctx)
    f = np.full(data.n_samples, F_NT)
    p = initial_params(data.raw, f, model, constrained=constrained)
    rng = np.random.default_rng(seed)
    # the effects' parameters away from their defaults (a lag's time constant stays > 0)
    p = p + 1e-3 * rng.standard_normal(p.size) * np.maximum(1.0, np.abs(p))
    prior_list = priors_for(model, {}, constrained)
    sigma = np.array([3.0, 2.5, 3.5, 3.0])
    for grp in model.sensor_groups:
        pr = [t for t in prior_list if any(
            model.sensor_slices[j - 1].start <= t[0] < model.sensor_slices[j - 1].stop
            for j in grp)]
        prob = ProfiledProblem(model, data.raw, ctx, f, grp, sigma, pr, p_full=p)
        yield prob, p[prob.cols]


CASES = [('base', False), ('base,temperature@2', False), ('base,site_gradient', False),
         ('base', True), ('base,lag(temperature)@2', False),
         ('offset,scale,nonorthogonality', False)]


@pytest.mark.parametrize('spec,constrained', CASES)
def test_normal_equations_equal_the_dense_projection(data, spec, constrained):
    """
    A = J^T J and g = J^T r of the dense projected Jacobian, to 1e-10 of their scale.

    The scale of entry (i, k) of J^T J is |J_i| |J_k| and of (J^T r)_i is |J_i| |r|
    (Cauchy-Schwarz): the two constructions differ by rounding, a few 1e-16 of the raw
    columns' norms (measured: at most 3e-15 here); 1e-10 leaves room for the cancellation
    of the projection (a column's norm shrinks by at most a few times when its field
    directions are removed) and for other BLAS libraries.
    """
    n_groups = 0
    for prob, x in problems(data, spec, constrained):
        n_groups += 1
        jac = prob.jacobian(x)
        r = prob.residuals(x)
        a, g = prob.normal_equations(x)
        a0, g0 = jac.T @ jac, jac.T @ r
        norms = np.sqrt(np.diag(a0))
        assert a.shape == a0.shape and g.shape == g0.shape
        assert np.all(np.abs(a - a0) <= 1e-10 * np.outer(norms, norms))
        assert np.all(np.abs(g - g0) <= 1e-10 * norms * np.linalg.norm(r))
        # not a trivial agreement: the point is off the optimum (g is not rounding noise),
        # the projection removes a part of the columns, the priors add their rows
        assert np.linalg.norm(g0 / norms) > 1e-3 * np.linalg.norm(r)
        p, b, _, _ = prob.evaluate(x)
        own, _ = prob._raw_columns(p, b)
        raw_sq = np.concatenate([np.sum(o.reshape(len(o), -1) ** 2, axis=1) for o in own])
        prior_sq = np.zeros(len(prob.cols))
        for i, _, sd in prob.priors:
            prior_sq[list(prob.cols).index(i)] += 1.0 / sd ** 2
        assert np.max(1.0 - (np.diag(a0)[:len(raw_sq)] - prior_sq[:len(raw_sq)])
                      / raw_sq) > 0.05
        assert bool(prob.priors) == constrained
    assert n_groups == (4 if spec == 'offset,scale,nonorthogonality' else 1)


def dense_normal_equations(self, x):
    """J^T J and J^T r from the dense projected Jacobian: the path of the fit before."""
    jac = self.jacobian(x)
    return jac.T @ jac, jac.T @ self.residuals(x)


@pytest.mark.parametrize('spec,constrained', [('base', False), ('base,temperature@2', False),
                                              ('base,site_gradient', False), ('base', True)])
def test_fit_agrees_with_the_dense_path(data, spec, constrained, monkeypatch):
    """
    The fit's parameters and standard uncertainties equal those of the dense path.

    Both paths run the same Levenberg-Marquardt iteration on normal equations that differ by
    rounding (test above); it stops when the cost decreases by less than ftol = 1e-12 of
    itself, i.e. within about sqrt(1e-12 chi2) ~ 1e-4 standard uncertainties of the minimum
    (chi2 ~ 7000 here): the parameters must agree to 1e-3 of their standard uncertainty, and
    the standard uncertainties (the covariance of nearly the same matrix) to 1e-6.
    """
    new = fit(data, spec, field_nt=F_NT, constrained=constrained)
    monkeypatch.setattr(ProfiledProblem, 'normal_equations', dense_normal_equations)
    old = fit(data, spec, field_nt=F_NT, constrained=constrained)
    assert new.success and old.success
    assert np.all(np.isfinite(new.stderr)) and np.all(new.stderr > 0)
    np.testing.assert_array_less(np.abs(new.params - old.params), 1e-3 * old.stderr)
    np.testing.assert_allclose(new.stderr, old.stderr, rtol=1e-6)
    np.testing.assert_allclose(new.sigma_nt, old.sigma_nt, rtol=1e-6)


def test_undetermined_directions_stay_infinite(monkeypatch):
    """
    Attitudes about one axis only: the fit's covariance is the dense path's, inf included.

    A turntable about one body axis cannot separate that axis' scale and offset from the
    field along it.  Formed block by block, J^T J is rounded to eps |D_i| |D_k| (D: the
    unprojected columns), 20 times |J_i| for those columns here: its undetermined
    eigenvalue can come out above the 1e-14 of the inf rule, so the fit must take the dense
    Jacobian for such a problem and report the same inf and finite values.
    """
    rng = np.random.default_rng(2)
    n = 400
    rot = Rotation.from_euler('z', np.linspace(0, 4 * np.pi, n)[:, None])
    b_w = np.array([20000.0, 0.0, 45000.0])
    b_w *= F_NT / np.linalg.norm(b_w)
    raw = np.stack([rot.inv().apply(b_w) @ A_TRUE[j].T + O_TRUE[j]
                    + rng.normal(0, NOISE_NT, (n, 3)) for j in range(4)])
    flat = Dataset(t=np.arange(n) / 2.0, raw=raw)
    spec = 'offset,scale,nonorthogonality'
    new = fit(flat, spec, field_nt=F_NT, on_degenerate='flag')
    # the block-formed matrix alone would not resolve the undetermined direction
    ctx = [flat.context(j) for j in range(1, 5)]
    prob = ProfiledProblem(new.model, raw, ctx, np.full(n, F_NT), [1], new.sigma_nt,
                           p_full=new.params)
    x = new.params[prob.cols]
    a = prob.normal_equations(x)[0]
    p, b, _, _ = prob.evaluate(x)
    raw_sq = np.sum(prob._raw_columns(p, b)[0][0].reshape(len(x), -1) ** 2, axis=1)
    assert np.max(raw_sq / np.diag(a)) > 100.0        # |D_i| / |J_i| > 10: the cancellation
    assert np.isinf(covariance_from_jacobian(prob.jacobian(x))).any()
    assert not resolves_covariance(a)
    monkeypatch.setattr(ProfiledProblem, 'normal_equations', dense_normal_equations)
    old = fit(flat, spec, field_nt=F_NT, on_degenerate='flag')
    inf = np.isinf(old.stderr)
    assert inf.any() and not inf.all()
    np.testing.assert_array_equal(np.isinf(new.stderr), inf)
    # the undetermined directions leave the optimum free along them: rounding decides where
    # each path stops in that valley, which moves the determined parameter's bound by ~1e-5
    np.testing.assert_allclose(new.stderr[~inf], old.stderr[~inf], rtol=1e-4)


def count_calls(monkeypatch):
    """Count the calls of ProfiledProblem.jacobian and normal_equations."""
    calls = {'jacobian': 0, 'normal_equations': 0}
    for name in calls:
        original = getattr(ProfiledProblem, name)

        def wrapped(self, x, _name=name, _original=original):
            calls[_name] += 1
            return _original(self, x)
        monkeypatch.setattr(ProfiledProblem, name, wrapped)
    return calls


def test_squares_fit_never_forms_the_dense_jacobian(data, monkeypatch):
    calls = count_calls(monkeypatch)
    res = fit(data, 'base,temperature@2', field_nt=F_NT)
    assert res.success
    assert calls['jacobian'] == 0 and calls['normal_equations'] >= 2


def test_robust_fit_uses_the_dense_jacobian(data, monkeypatch):
    """The soft-L1 row weights do not commute with the projection: LM needs J itself."""
    calls = count_calls(monkeypatch)
    res = fit(data, 'base', field_nt=F_NT, robust=True, covariance=False,
              check_identifiability=False)
    assert res.success
    assert calls['jacobian'] >= 2 and calls['normal_equations'] == 0


def test_levenberg_marquardt_on_normal_equations():
    """Rosenbrock: the iterates on (J^T J, J^T r) are those on J; robust needs J."""
    def fun(x):
        return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])

    def jac(x):
        return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])

    def normal(x):
        j = jac(x)
        return j.T @ j, j.T @ fun(x)

    x0 = np.array([-1.2, 1.0])
    with_jac = levenberg_marquardt(fun, jac, x0, max_nfev=500)
    with_normal = levenberg_marquardt(fun, None, x0, max_nfev=500, normal=normal)
    assert with_normal.success and with_normal.nfev == with_jac.nfev
    np.testing.assert_allclose(with_normal.x, [1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(with_normal.x, with_jac.x, rtol=1e-12)
    with pytest.raises(ValueError, match='needs jac'):
        levenberg_marquardt(fun, None, x0, robust=True, normal=normal)


def test_covariance_from_normal_by_hand():
    """
    Inverse of J^T J where determined, inf on the parameters of an undetermined direction.

    J's columns 1 and 2 are equal (only their sum is determined); column 0 is orthogonal to
    them with norm 2, so its variance is 1/4 exactly, in any units: scaling column 0 by
    1000 (a parameter in other units) scales its variance by 1e-6.
    """
    jac = np.array([[2.0, 0, 0], [0, 1, 1], [0, 3, 3], [0, 0, 0]])
    cov = covariance_from_normal(jac.T @ jac)
    assert cov[0, 0] == pytest.approx(0.25, rel=1e-12)
    assert np.isinf(cov[1, 1]) and np.isinf(cov[2, 2]) and np.isinf(cov[1, 2])
    scaled = jac * [1000.0, 1, 1]
    assert covariance_from_normal(scaled.T @ scaled)[0, 0] == pytest.approx(0.25e-6, rel=1e-12)
    full = np.array([[2.0, 0], [1, 1], [0, 3]])
    np.testing.assert_allclose(covariance_from_normal(full.T @ full),
                               np.linalg.inv(full.T @ full), rtol=1e-12)
    assert resolves_covariance(full.T @ full) and not resolves_covariance(jac.T @ jac)


@pytest.mark.parametrize('spec', ['base,temperature@2', 'base,site_gradient',
                                  'base,lag(temperature)@2'])
def test_forward_differences_are_the_differences_of_forward(data, spec):
    """
    Each column is forward(p + h_i e_i) - forward(p) of the whole reading, to rounding.

    Model.forward_differences takes shortcuts (a linear effect's column through the change
    of A_j, an additive effect's through its own contribution); the reference re-evaluates
    Model.forward for each step.  Both are differences of readings of ~5e4 nT, rounded
    to a few 1e-16 of the reading: 1e-12 of |forward(p)| allowed (and 1e-8 of the column).
    """
    for prob, x in problems(data, spec):
        p, b, _, _ = prob.evaluate(x)
        model = prob.model
        for j in (1, 2):
            cols = list(range(model.sensor_slices[j - 1].start,
                              model.sensor_slices[j - 1].stop)) + list(model.array_cols)
            diff, h = model.forward_differences(j, p, b, prob.ctx[j - 1], cols)
            base = model.forward(j, p, b, prob.ctx[j - 1])
            for c, i in enumerate(cols):
                pp = p.copy()
                pp[i] += h[c]
                ref = model.forward(j, pp, b, prob.ctx[j - 1]) - base
                assert np.linalg.norm(diff[c] - ref) <= (1e-12 * np.linalg.norm(base)
                                                         + 1e-8 * np.linalg.norm(ref))
