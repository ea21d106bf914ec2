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
Solvers of the maximum-likelihood fit: Levenberg-Marquardt, the covariance, one BLAS thread.

Also :func:`mad_sd`, the robust sd the fit and the noise floor (core/data/noise.py) use.
The covariance is the Cramer-Rao bound (docs/papers.md, "The maximum-likelihood engine").
"""
import contextlib
from dataclasses import dataclass

import numpy as np

#: 1 / Phi^-1(3/4): the MAD of Gaussian values times this is their sd
MAD_TO_SD = 1.482602218505602


def mad_sd(x):
    """1.4826 MAD of ``x`` (any shape; nan when empty), as scipy.stats' (slow to import) gives."""
    x = np.asarray(x, float).ravel()
    if not x.size:
        return float('nan')
    return float(np.median(np.abs(x - np.median(x))) * MAD_TO_SD)


@dataclass(frozen=True)
class Solution:
    """Outcome of :func:`levenberg_marquardt`: x (P,); status 0 nfev limit, 2 ftol, 3 xtol."""

    x: np.ndarray
    success: bool
    status: int
    message: str
    nfev: int


def levenberg_marquardt(fun, jac, x0, robust=False, f_scale=3.0, max_nfev=200, xtol=1e-10,
                        ftol=1e-12, normal=None):
    """
    Minimise sum rho(r_i^2) by Levenberg-Marquardt with Marquardt's (1963) diagonal scaling.

    rho the identity or the soft-L1 loss 2 f^2 (sqrt(1 + r^2/f^2) - 1) (IRLS).  ``fun``: x
    (P,) -> normalised residuals (M,); ``jac``: x -> (M, P) (None only with ``normal`` and
    not ``robust``); ``normal``: x -> (J^T J, J^T r), for the squares loss; ``x0`` (P,);
    ``f_scale`` the loss's scale; ``xtol``, ``ftol`` the relative step and cost decrease
    that stop.  Returns a :class:`Solution`.
    """
    def cost(r):
        if robust:
            return float(np.sum(f_scale ** 2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))
        return 0.5 * float(r @ r)

    if normal is None or robust:
        if jac is None:
            raise ValueError('levenberg_marquardt needs jac (the soft-L1 loss weights the '
                             'rows of the Jacobian), or normal= with the squares loss')
        normal = None
    x = np.asarray(x0, float).copy()
    r = fun(x)
    c, nfev, lam = cost(r), 1, 1e-3
    for _ in range(max_nfev):
        if normal is not None:
            a, g = normal(x)
        else:
            j = jac(x)
            rw = r
            if robust:
                w = np.sqrt(1.0 / np.sqrt(1 + (r / f_scale) ** 2))
                j, rw = j * w[:, None], r * w
            a = j.T @ j
            g = j.T @ rw
        d = np.diag(a).copy()
        d[d <= 0] = 1.0
        while True:
            try:
                step = -np.linalg.solve(a + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step
            r_new = fun(x_new)
            nfev += 1
            c_new = cost(r_new)
            if c_new <= c:
                break
            # predicted and actual change both below ftol: converged (MINPACK's test, More 1978)
            predicted = -float(g @ step) - 0.5 * float(step @ a @ step)
            if max(predicted, c_new - c) <= ftol * max(c, 1e-300):
                return Solution(x, True, 2, 'cost decrease below ftol', nfev)
            lam *= 10
            if lam > 1e12:
                return Solution(x, True, 2, 'no further decrease of the cost', nfev)
            if nfev >= max_nfev:
                return Solution(x, False, 0, f'maximum number of evaluations ({max_nfev}) '
                                'reached', nfev)
        dc = c - c_new
        x, r, c = x_new, r_new, c_new
        lam = max(lam / 10, 1e-12)
        scaled = np.sqrt(d)
        if np.linalg.norm(scaled * step) <= xtol * (np.linalg.norm(scaled * x) + xtol):
            return Solution(x, True, 3, 'step below xtol', nfev)
        if dc <= ftol * max(c, 1e-300):
            return Solution(x, True, 2, 'cost decrease below ftol', nfev)
        if nfev >= max_nfev:
            break
    return Solution(x, False, 0, f'maximum number of evaluations ({max_nfev}) reached', nfev)


def covariance_from_jacobian(jac):
    """(P, P) :func:`covariance_from_normal` of ``jac.T @ jac``, ``jac`` (M, P) normalised."""
    return covariance_from_normal(jac.T @ jac)


def covariance_from_normal(a):
    """
    Return the (P, P) inverse of J^T J ``a`` (P, P); inf for undetermined directions.

    Column-scaled (unit-free): a parameter weighing above 1e-6 in an eigenvector whose
    eigenvalue is below 1e-14 of the largest gets an infinite uncertainty (not a
    pseudo-inverse's zero).
    """
    d = np.sqrt(np.clip(np.diag(a), 0.0, None))
    d[d == 0] = 1.0
    w, v = np.linalg.eigh(a / np.outer(d, d))
    bad = w <= 1e-14 * max(w.max(), 1e-300)
    w_inv = np.where(bad, 0.0, 1.0 / np.where(bad, 1.0, w))
    cov = (v * w_inv) @ v.T / np.outer(d, d)
    if bad.any():
        involved = np.abs(v[:, bad]).max(axis=1) > 1e-6
        cov[involved, :] = np.inf
        cov[:, involved] = np.inf
        cov[involved, involved] = np.inf
    return cov


def resolves_covariance(a, rcond=1e-8):
    """
    Return True when J^T J formed block by block, ``a`` (P, P), determines the covariance.

    ``ProfiledProblem.normal_equations`` rounds to ~1e-13 of the column-scaled matrix: a
    smallest scaled eigenvalue above ``rcond`` of the largest keeps the error below 1e-5;
    else the caller uses :func:`covariance_from_jacobian`.
    """
    d = np.sqrt(np.clip(np.diag(a), 0.0, None))
    if np.any(d == 0):
        return False
    w = np.linalg.eigvalsh(a / np.outer(d, d))
    return bool(w[0] > rcond * w[-1])


def single_threaded_blas():
    """Return a context that limits BLAS to one thread (threads only contend here, bench/)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:                   # pragma: no cover - optional dependency
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api='blas')


def stderr_and_correlation(cov):
    """Return (stderr (P,), correlation (P, P), 0 where undefined) of ``cov`` (P, P)."""
    stderr = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid='ignore', divide='ignore'):
        corr = cov / np.outer(stderr, stderr)
    corr[~np.isfinite(corr)] = 0.0
    np.fill_diagonal(corr, 1.0)
    return stderr, corr
