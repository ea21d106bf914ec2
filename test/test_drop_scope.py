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
``drop(t0, t1)@J``: sensor J's readings of a window left out, the other sensors' kept (issue 32).

The record is the four-sensor cross of test/injection.py (1500 sets at 5 Hz, 3 nT Gaussian
noise per axis, each sensor written out by hand, not by ``Model.forward``), with a magnet-like
offset of (250, -180, 120) nT on sensor 2 alone in [120, 160] s.  The truth is the
injection's: sensor j's matrix K_j and offset o_j, turned into the model's parameters by
``Model.params_from_linear`` (checked: the model's matrix at them is K_j).  Tolerances come
from the noise: an RMS of n Gaussian values of sd sigma is within sigma (1 +- 4 / sqrt(n)),
a fitted parameter within 4 of its stated standard errors.
"""
import injection as inj
from magcal_ros.core.data.dataset import Dataset
from magcal_ros.core.effects import formula as fm
from magcal_ros.core.model import fit, Model
from magcal_ros.core.model.engine import ProfiledProblem
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, parse_calibration
import numpy as np
import pytest

N = 1500
T0, T1 = 120.0, 160.0
MAGNET = np.array([250.0, -180.0, 120.0])
SIGMA = inj.SIGMA_NT
CACHE = {}


def _inject(t, temp, aux, b):
    return {2: np.outer((t >= T0) & (t <= T1), MAGNET)}


def _record():
    if 'data' not in CACHE:
        CACHE['data'] = inj.make(n=N, seed=5, inject=_inject)
    return CACHE['data']


def _fit(formula, data=None):
    key = formula if data is None else None
    if key is None or key not in CACHE:
        res = fit(_record() if data is None else data, formula, inj.F_NT)
        if key is None:
            return res
        CACHE[key] = res
    return CACHE[key]


def _truth(model, j):
    """(P,) parameters with sensor j's set to the injection's truth (others default)."""
    k = inj.sensor_matrix(j)
    p = model.params_from_linear(j, k, np.array(inj.SENSORS[j - 1][3]))
    np.testing.assert_allclose(model.matrix(j, p), k, rtol=0, atol=1e-12)
    return p


def test_a_disturbance_on_one_sensor_is_left_out_of_that_sensor_alone():
    data = _record()
    inside = (data.t >= T0) & (data.t <= T1)
    n_in = int(inside.sum())
    plain = _fit('base')
    # without the drop, sensor 2 is far above its 3 nT noise
    assert plain.scalar_rms_nt[2] > 10 * SIGMA, plain.scalar_rms_nt
    assert plain.sigma_nt[1] > 10 * SIGMA, plain.sigma_nt
    res = _fit('base + drop(120, 160)@2')
    assert res.model.spec()[-1] == 'drop(120, 160)@2'
    # every set is fitted; sensor 2 has n_in readings fewer, the others all of theirs
    assert res.n_fit_samples == N
    assert list(res.n_fit_readings) == [N, N - n_in, N, N]
    # every sensor at the noise: scalar RMS (outside sensor 2's window for sensor 2) and
    # the estimated noise level within sigma (1 +- 4 / sqrt(n))
    for j in range(1, 5):
        n_j = res.n_fit_readings[j - 1]
        assert abs(res.scalar_rms_nt[j] / SIGMA - 1) < 4 / np.sqrt(n_j), (j, res.scalar_rms_nt)
        assert abs(res.sigma_nt[j - 1] / SIGMA - 1) < 4 / np.sqrt(n_j), (j, res.sigma_nt)
    # the field of the window's sets is the other three sensors': their raw residual there
    # is their noise less the field's two directions, sd sigma sqrt((3 G - 2) / (3 G)),
    # G = 3 (sensor 2's 300 nT would pull it by tens of nT)
    expect = SIGMA * np.sqrt(7.0 / 9.0)
    for j in (1, 3, 4):
        r = np.sqrt(np.mean(res.residual_nt[j - 1][inside] ** 2))
        assert abs(r / expect - 1) < 4 / np.sqrt(3 * n_in), (j, r, expect)
    # sensor 2's own readings of the window show the magnet against that field
    r2 = np.linalg.norm(np.mean(res.residual_nt[1][inside], axis=0))
    assert abs(r2 - np.linalg.norm(MAGNET)) < 0.1 * np.linalg.norm(MAGNET), r2
    # sensor 2's parameters are the truth within 4 stated standard errors; without the drop
    # they are not
    truth = _truth(res.model, 2)
    sl = res.model.sensor_slices[1]
    z = (res.params[sl] - truth[sl]) / res.stderr[sl]
    assert np.all(np.abs(z) < 4), z
    z0 = (plain.params[sl] - truth[sl]) / plain.stderr[sl]
    assert np.max(np.abs(z0)) > 10, z0


def test_every_sensor_dropped_is_the_array_wide_drop():
    data = _record()
    res = _fit('base + drop(120, 160)@{1,2,3,4}')
    whole = _fit('base + drop(120, 160)')
    n_in = int(np.sum((data.t >= T0) & (data.t <= T1)))
    assert res.n_fit_samples == whole.n_fit_samples == N - n_in
    np.testing.assert_allclose(res.params, whole.params, rtol=0, atol=1e-9)
    # the per-sensor drop keeps the window's readings of sensors 1, 3, 4: more data, and
    # their standard errors are smaller
    one = _fit('base + drop(120, 160)@2')
    for j in (1, 3, 4):
        sl = res.model.sensor_slices[j - 1]
        assert np.all(one.stderr[sl] < whole.stderr[sl]), j


def test_one_sensor_drop_at_1_is_drop():
    data = _record()
    one = Dataset(t=data.t, raw=data.raw[1:2], temp=data.temp[1:2], aux=data.aux)
    a = _fit('base + drop(120, 160)@1', one)
    b = _fit('base + drop(120, 160)', one)
    np.testing.assert_allclose(a.params, b.params, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.stderr, b.stderr, rtol=1e-9, atol=0)
    assert a.n_fit_samples == b.n_fit_samples and list(a.n_fit_readings) == [b.n_fit_samples]
    # and it left the magnet out: the sensor at its noise
    assert abs(a.sigma_nt[0] / SIGMA - 1) < 4 / np.sqrt(a.n_fit_samples), a.sigma_nt


@pytest.mark.parametrize('formula, words', [
    ('base + drop(120, 160)@0', ['sensor 0 does not exist', '1..4']),
    ('base + drop(120, 160)@5', ['sensor 5 does not exist', 'sensors 1..4']),
    ('base + drop(160, 120)@2', ['must follow its start']),
    ('base + drop(120, 120)@2', ['must follow its start']),
    ('base + drop(120, 160)@alike', ['drop takes a sensor scope']),
    ('base + drop(-1, 400)@3', ['sensor 3', 'with 0 of 1500 samples', 'drop less']),
    ('base + drop(0, 299)@3', ['sensor 3', 'with 4 of 1500 samples', 'at least 12']),
])
def test_bad_drops_are_refused_in_one_line(formula, words):
    with pytest.raises(ValueError) as err:
        fit(_record(), formula, inj.F_NT)
    msg = str(err.value)
    assert '\n' not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_the_attitude_rows_stay_when_one_sensor_is_dropped():
    """A ``drop@J`` leaves the attitude's rows; the array-wide drop removes the sets."""
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.core.model.attitude_fit import with_attitude
    data, _ = simulate(n_samples=400, rate_hz=10, n_sensors=2, trajectory='vehicle',
                       tilt_deg=15.0, attitude=True, seed=1, aux=False, temp_swing_c=0)
    model = with_attitude('base + drop(10, 20)@2', 'tilt', 2)
    assert model.drops == [(10.0, 20.0, (2,))]
    ctx = [data.context(j) for j in (1, 2)]
    model.prepare(ctx)
    mask = model.reading_mask(data.t)
    n_in = int(np.sum(~mask[1]))
    f = np.full(data.n_samples, 50000.0)
    prob = ProfiledProblem(model, data.raw, ctx, f, [1, 2], np.array([3.0, 3.0]))
    assert prob.aid is not None
    assert list(prob.member_counts) == [400, 400 - n_in, 400]
    # rows: sensors 3 each, the attitude its rank, less the field's 2 per set
    rank = prob.aid.rank
    assert prob.n_observations == (3 * 2 + rank - 2) * 400 - 3 * n_in
    x = prob.p_full[prob.cols]
    _, _, _, res = prob.evaluate(x)
    inside = ~mask[1]
    assert np.all(res[inside, 1] == 0) and np.all(np.abs(res[inside, 0]) > 0)
    assert np.all(np.any(res[inside, 2] != 0, axis=1))          # the attitude's rows
    # J^T J and J^T r block by block are the dense Jacobian's, with the rows left out
    a, g = prob.normal_equations(x)
    jac, r = prob.jacobian(x), prob.residuals(x)
    np.testing.assert_allclose(a, jac.T @ jac, rtol=1e-7, atol=1e-9 * np.abs(a).max())
    np.testing.assert_allclose(g, jac.T @ r, rtol=1e-7, atol=1e-9 * np.abs(g).max())
    assert np.all(jac.reshape(400, 3, 3, -1)[inside, 1] == 0)
    # the array-wide drop leaves the attitude's rows of those sets out too
    model = with_attitude('base + drop(10, 20)', 'tilt', 2)
    model.prepare(ctx)
    prob = ProfiledProblem(model, data.raw, ctx, f, [1, 2], np.array([3.0, 3.0]))
    assert list(prob.member_counts) == [400 - n_in] * 3
    assert prob.n_observations == (3 * 2 + rank - 2) * (400 - n_in)
    _, _, _, res = prob.evaluate(prob.p_full[prob.cols])
    assert np.all(res[inside] == 0) and np.all(np.any(res[~inside, 2] != 0, axis=1))


def test_the_diagnosis_does_not_call_dropped_readings_misfit():
    """The diagnosis of base + drop@2: every measure on the readings kept, at the floor."""
    from magcal_ros.core.discovery import diagnose
    before = diagnose(_record(), 'base', inj.F_NT, base=_fit('base'))
    assert not before.at_floor and before.scalar_rms_nt[2] > 10 * SIGMA
    # the finding that leaves the window out scopes it to the one sensor that carries it
    (loc,) = [f for f in before.findings.items if f.kind == 'localised']
    assert loc.token.startswith('drop(') and loc.token.endswith(')@2'), loc.token
    lo, hi = (float(x) for x in loc.token[5:-3].split(','))
    assert lo <= T0 and hi >= T1 and hi - lo < T1 - T0 + 5, loc.token
    dg = diagnose(_record(), 'base + drop(120, 160)@2', inj.F_NT,
                  base=_fit('base + drop(120, 160)@2'))
    assert dg.at_floor, dg.verdict_reason
    assert dg.verdict_token is None
    n2 = N - int(np.sum((_record().t >= T0) & (_record().t <= T1)))
    for j in range(1, 5):
        assert abs(dg.scalar_rms_nt[j] / SIGMA - 1) < 4 / np.sqrt(n2), dg.scalar_rms_nt
        # the floor, from the sets every sensor keeps, is the noise (a robust sd of about
        # 3 x 1300 differences: a few per cent of scatter; 0.1 is more than 4 of it)
        assert abs(dg.noise_floor.per_sensor_nt[j - 1] / SIGMA - 1) < 0.1, dg.noise_floor
    # the combined residual and its held-out value: the noise, sensor 2's window left out
    assert abs(dg.residual_rms_nt / SIGMA - 1) < 4 / np.sqrt(n2)
    assert abs(dg.cv_rms_nt / SIGMA - 1) < 4 / np.sqrt(n2)
    assert not any(f.kind == 'localised' for f in dg.findings.items)


def test_the_scope_round_trips_through_the_spec_and_the_calibration_file():
    text = 'base + drop(120, 160)@{3, 1} + drop(10,20.0)@4 + drop(200, 210)'
    m = Model.from_spec(text, 4)
    assert m.drops == [(120.0, 160.0, (1, 3)), (10.0, 20.0, (4,)), (200.0, 210.0, None)]
    spec = m.spec()
    assert spec[-3:] == ['drop(120, 160)@{1,3}', 'drop(10, 20)@4', 'drop(200, 210)']
    assert [str(t) for t in fm.parse(text).terms[1:]] == spec[-3:]
    assert Model.from_spec(spec, 4).drops == m.drops
    res = _fit('base + drop(120, 160)@2')
    cal, doc = parse_calibration(dump_calibration(calibration_to_doc(res.calibration)), 'x')
    assert 'drop(120, 160)@2' in doc['model']
    assert cal.model.drops == [(120.0, 160.0, (2,))]
    t = _record().t
    np.testing.assert_array_equal(cal.model.reading_mask(t), res.model.reading_mask(t))
    np.testing.assert_array_equal(cal.params, res.params)


def test_the_noise_variances_count_each_sensor_s_own_rows():
    """
    group_noise_variances with a sensor's rows left out: unbiased, by simulation.

    Three sensors' normalised noise e_j ~ N(0, d_j I) at N epochs, sensor 2's rows of 40 %
    of them left out (zero), the field's two directions projected out of each epoch's rows
    kept: r = (I - G (G^T G)^-1 G^T) e.  The estimate of d_j has a relative sd of about
    sqrt(2 / (3 n_j - 2 n_j / G)); counting sensor 2's left-out rows as rows would bias its
    d low by about 40 % x 3 / 2.
    """
    from magcal_ros.core.model.fitting import group_noise_variances
    rng = np.random.default_rng(7)
    n, g = 4000, 3
    d_true = np.array([1.0, 4.0, 0.25])
    keep = np.ones((n, g))
    keep[rng.random(n) < 0.4, 1] = 0.0
    basis = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0][:, :, :2]       # (N, 3, 2)
    mats = np.eye(3) + 0.05 * rng.normal(size=(g, 3, 3))
    cols = np.concatenate([mats[j] @ basis * keep[:, j, None, None] for j in range(g)],
                          axis=1)                                        # (N, 3G, 2)
    e = rng.normal(size=(n, g, 3)) * np.sqrt(d_true)[None, :, None] * keep[:, :, None]
    e = e.reshape(n, 3 * g)
    gtg = np.swapaxes(cols, 1, 2) @ cols
    proj = cols @ np.linalg.solve(gtg, np.swapaxes(cols, 1, 2))
    res = (e - np.einsum('nab,nb->na', proj, e)).reshape(n, g, 3)
    d = group_noise_variances(res, cols, 0, keep=keep)
    n_j = keep.sum(axis=0)
    tol = 4 * np.sqrt(2.0 / (3 * n_j - 2 * n_j / g))
    assert np.all(np.abs(d / d_true - 1) < tol), (d, tol)
    # without the counts (every row taken for one) sensor 2 comes out far too low
    wrong = group_noise_variances(res, cols, 0)
    assert wrong[1] / d_true[1] - 1 < -5 * tol[1], wrong


def test_the_search_counts_only_the_readings_kept_when_it_subsamples(monkeypatch):
    """
    The formula search's observation count on a subsample leaves a ``drop``'s readings out.

    The search fits at most ``SEARCH_MAX_EPOCHS`` evenly spaced sets (lowered here to 1000 of
    the 1500); its likelihood-ratio tests and BIC count the observations net of the field.
    With ``base + drop(10, 30)@2`` on the cross (rigid: one field per set, each set 3 x 4
    readings less the field's 2), a set in the window keeps 3 x 3 - 2 = 7 and every other
    10: counted by hand from the subsample's times.  The magnet in [120, 160] s is still in,
    so the search runs.
    """
    from magcal_ros.core.discovery import diagnose, run
    from magcal_ros.core.model.fitting import fit_epochs
    seen = []

    def spy(data, resid, screen, sigma, floor, n_obs, **kw):
        seen.append((data.t.copy(), n_obs))
        return real(data, resid, screen, sigma, floor, n_obs, **kw)
    real = run.run_search
    monkeypatch.setattr(run, 'run_search', spy)
    monkeypatch.setattr(run, 'SEARCH_MAX_EPOCHS', 1000)
    formula = 'base + drop(10, 30)@2'
    base = _fit(formula)
    assert base.model.joint, 'the hand count below is for one field per set'
    diagnose(_record(), formula, inj.F_NT, base=base)
    (t, n_obs), = seen
    t_all = _record().t
    np.testing.assert_array_equal(t, t_all[fit_epochs(N, 1000)])
    inside = int(np.sum((t >= 10.0) & (t <= 30.0)))
    assert 50 < inside < len(t)
    assert n_obs == 10 * len(t) - 3 * inside, (n_obs, len(t), inside)
