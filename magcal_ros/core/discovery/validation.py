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

"""Held-out tests of a model: interleaved time blocks, k-fold cross-validation, leave-out steps."""
from magcal_ros.core.discovery.constants import BLOCKS_PER_FOLD, DEFAULT_FOLDS, MIN_BLOCK
from magcal_ros.core.discovery.measures import dof_factor, solve_psd
from magcal_ros.core.model.engine import ProfiledProblem
from magcal_ros.core.model.fitting import evaluate, fit
import numpy as np


def time_blocks(n, folds, blocks_per_fold=None):
    """
    Index arrays of ``folds`` held-out sets of ``n`` epochs, each interleaved in time.

    Fold k holds out blocks k, k + folds, ... of ``folds * blocks_per_fold`` contiguous ones
    (default :data:`BLOCKS_PER_FOLD`): correlated neighbours do not leak, and an effect that
    changes over the record is interpolated, not extrapolated.
    """
    if folds < 2:
        raise ValueError(f'cross-validation needs at least 2 folds, got {folds}')
    m = BLOCKS_PER_FOLD if blocks_per_fold is None else int(blocks_per_fold)
    m = max(1, min(m, n // (folds * MIN_BLOCK))) if n >= folds * MIN_BLOCK else 1
    blocks = np.array_split(np.arange(n), folds * m)
    return [np.concatenate(blocks[k::folds]) for k in range(folds)]


def cross_validate(data, model, params, f, sigma, folds=DEFAULT_FOLDS, fold_inits=None,
                   method='newton', constrained=False, extra_priors=()):
    """
    Held-out residual of ``model``: fit on all blocks but one, evaluate on that block.

    ``data``: Dataset (S sensors, N epochs) in time order, nT, and ``model`` prepared on it;
    ``params`` (P,): the fit on all data (``'newton'``: its optimum; ``'refit'``: the warm
    start); ``f`` (N,), ``sigma`` (S,): reference magnitude and fixed noise levels, nT;
    ``folds``: held-out sets, each of interleaved blocks (:func:`time_blocks`);
    ``fold_inits``: per-fold (P,) warm starts of ``'refit'`` (default ``params``);
    ``method``: ``'refit'`` the full fit on the other blocks, ``'newton'`` one Gauss-Newton
    step without the held-out rows, p_b = p - (J^T J - J_b^T J_b)^-1 (J^T r - J_b^T r_b)
    (exact for a linear model); ``constrained``: with the constrained mode's priors, implies
    ``'refit'``; ``extra_priors``: [(index, mean, sd)] priors added to every fold's fit,
    implies ``'refit'``.  Returns {``rms_nt``: combined held-out RMS (pooled),
    ``per_sensor_nt`` (S,), ``scalar_rms_nt`` (S,), ``fold_params``: list of (P,) arrays}.
    """
    if method not in ('newton', 'refit'):
        raise ValueError(f"method must be 'newton' or 'refit', got {method!r}")
    if constrained or len(extra_priors):
        method = 'refit'        # the Newton leave-out step has no prior terms
    n = data.n_samples
    blocks = time_blocks(n, folds)
    params = np.asarray(params, float)
    if method == 'newton':
        fold_params = _newton_leave_out(data, model, params, f, sigma, blocks)
    else:
        fold_params = []
        for b, test in enumerate(blocks):
            train = np.setdiff1d(np.arange(n), test)
            init = params if fold_inits is None else fold_inits[b]
            r = fit(data.subset(train), model, field_nt=f[train], sigma_nt=sigma, init=init,
                    check_identifiability=False, on_degenerate='flag', constrained=constrained,
                    extra_priors=extra_priors)
            fold_params.append(r.params)
    ss, ss_scalar, count = np.zeros((3, data.n_sensors))
    for p_b, test in zip(fold_params, blocks):
        out = evaluate(model, p_b, data.subset(test), f[test], sigma)
        ss += np.sum(out['residual'] ** 2, axis=(1, 2))
        ss_scalar += np.sum(out['scalar'] ** 2, axis=1)
        # the readings a drop() leaves out are zero there and not counted
        count += len(test) if out['kept'] is None else out['kept'].sum(axis=1)
    per = np.sqrt(dof_factor(model) * ss / (3 * count))
    return {'rms_nt': float(np.sqrt(np.mean(per ** 2))), 'per_sensor_nt': per,
            'scalar_rms_nt': np.sqrt(ss_scalar / count), 'fold_params': fold_params}


def _newton_leave_out(data, model, params, f, sigma, blocks):
    """(P,) parameters per block: one Gauss-Newton step without that block's rows."""
    sigma = np.asarray(sigma, float)
    fold_params = [params.copy() for _ in blocks]
    for grp in model.sensor_groups:
        hess, grad = [], []
        for test in blocks:
            sub = data.subset(test)
            prob = ProfiledProblem(model, sub.raw,
                                   [sub.context(j) for j in range(1, sub.n_sensors + 1)],
                                   f[test], grp, sigma, p_full=params)
            a, g = prob.normal_equations(params[prob.cols])
            hess.append(a)
            grad.append(g)
        h_all, g_all = sum(hess), sum(grad)
        for b in range(len(blocks)):
            h, g = h_all - hess[b], g_all - grad[b]
            d = np.sqrt(np.clip(np.diag(h), 0.0, None))
            d[d == 0] = 1.0
            step = solve_psd(h / np.outer(d, d), -g / d) / d
            fold_params[b][prob.cols] += step
    return fold_params
