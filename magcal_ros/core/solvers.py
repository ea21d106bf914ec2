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

:func:`levenberg_marquardt` minimises a sum of squared (or soft-L1) residuals given the
residual and Jacobian functions of :class:`magcal_ros.core.engine.ProfiledProblem`;
:func:`covariance_from_jacobian` turns the projected Jacobian at the solution into the
parameter covariance (the Cramer-Rao bound, docs/papers.md, "The maximum-likelihood
engine").
"""
import contextlib
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Solution:
    """
    Outcome of :func:`levenberg_marquardt` (the fields of scipy's OptimizeResult used here).

    Attributes
    ----------
    x : numpy.ndarray
        (P,) the solution.
    success : bool
    status : int
        0: evaluation limit, 2: cost decrease below ftol (or no further decrease),
        3: step below xtol.
    message : str
    nfev : int
        Residual evaluations.

    """

    x: np.ndarray
    success: bool
    status: int
    message: str
    nfev: int


def levenberg_marquardt(fun, jac, x0, robust=False, f_scale=3.0, max_nfev=200, xtol=1e-10,
                        ftol=1e-12):
    """
    Minimise sum rho(r_i^2) by Levenberg-Marquardt on the normal equations.

    rho is the identity or the soft-L1 loss 2 f^2 (sqrt(1 + r^2/f^2) - 1) (handled by
    iteratively reweighted least squares).  Marquardt's diagonal scaling makes the damping
    invariant to parameter units (Marquardt 1963).

    Parameters
    ----------
    fun : callable
        x (P,) -> residuals (M,), dimensionless (normalised by the noise sd).
    jac : callable
        x (P,) -> Jacobian (M, P) of ``fun``.
    x0 : numpy.ndarray
        (P,) start.
    robust : bool
        Soft-L1 loss instead of squares.
    f_scale : float
        Scale of the soft-L1 loss, in the residuals' unit.
    max_nfev : int
        Most residual evaluations.
    xtol, ftol : float
        Relative step and relative cost decrease that stop the iteration.

    Returns
    -------
    Solution

    """
    def cost(r):
        if robust:
            return float(np.sum(f_scale ** 2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))
        return 0.5 * float(r @ r)

    x = np.asarray(x0, float).copy()
    r = fun(x)
    c = cost(r)
    nfev = 1
    lam = 1e-3
    for _ in range(max_nfev):
        j = jac(x)
        if robust:
            w = np.sqrt(1.0 / np.sqrt(1 + (r / f_scale) ** 2))
            j, rw = j * w[:, None], r * w
        else:
            rw = r
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
            lam *= 10
            if lam > 1e12:
                return Solution(x, True, 2, 'no further decrease of the cost', nfev)
            if nfev >= max_nfev:
                # out of evaluations while still looking for a downhill step: not converged
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
    """
    Return the (P, P) inverse of J^T J with column scaling; inf for undetermined directions.

    A pseudo-inverse would silently give *zero* variance along directions the data do not
    determine; here such parameters get an infinite standard uncertainty instead.

    Parameters
    ----------
    jac : numpy.ndarray
        (M, P) Jacobian of residuals normalised by the noise sd
        (:meth:`magcal_ros.core.engine.ProfiledProblem.jacobian`).

    Returns
    -------
    numpy.ndarray
        (P, P) covariance in the parameters' units squared: the Cramer-Rao bound at the
        solution.

    """
    d = np.linalg.norm(jac, axis=0)
    d[d == 0] = 1.0
    js = jac / d
    m = js.T @ js
    w, v = np.linalg.eigh(m)
    bad = w <= 1e-14 * max(w.max(), 1e-300)
    w_inv = np.where(bad, 0.0, 1.0 / np.where(bad, 1.0, w))
    cov = (v * w_inv) @ v.T / np.outer(d, d)
    if bad.any():
        involved = np.abs(v[:, bad]).max(axis=1) > 1e-6
        cov[involved, :] = np.inf
        cov[:, involved] = np.inf
        cov[involved, involved] = np.inf
    return cov


def single_threaded_blas():
    """
    Return a context that limits BLAS to one thread (optional threadpoolctl).

    The fit's linear algebra is tall-skinny products and P x P solves; on small machines
    shared with other processes (a robot's computer, CI), BLAS threads only contend:
    measured 2-6x slower with two threads on a loaded 2-core machine (bench/).
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:                   # pragma: no cover - optional dependency
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api='blas')
