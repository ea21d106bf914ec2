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
Residual measures of the diagnosis (nT) and the statistics that compare two nested fits.

Residual measures (all nT):

- scalar residual of sensor j: |corrected_j| - F (at the floor: RMS = sigma_j);
- vector residual of sensor j > 1: corrected_j - corrected_1, per-component RMS (at the floor
  sqrt(sigma_j^2 + sigma_1^2)); some effects (a field-rate term under pure rotation) show
  only here;
- combined residual: the raw-space residual of the maximum-likelihood fit, scaled by
  sqrt(3G / (3G - 2)) (:func:`dof_factor`) for the 2 field directions profiled per epoch
  from G jointly fitted sensors, so that it equals the per-axis noise sd when the model is
  complete.  This is the held-out (cross-validated) measure.
"""
from dataclasses import dataclass
import math

from magcal_ros.core.model.fitting import evaluate
import numpy as np
from scipy import stats


def dof_factor(model):
    """Return 3G / (3G - 2): undo the 2 field directions profiled per epoch from G sensors."""
    g = model.n_sensors if model.joint else 1
    return 3.0 * g / (3.0 * g - 2.0)


def n_observations(model, n, kept=None):
    """
    Return the observations of ``n`` epochs net of the profiled field: N sum(3G - 2).

    ``kept`` (S, N) bool: the readings the model keeps (``drop`` terms); each group's epoch
    then counts 3 per reading kept less 2, nothing without one.
    """
    if kept is None:
        return int(n * sum(3 * len(g) - 2 for g in model.sensor_groups))
    out = 0
    for g in model.sensor_groups:
        rows = 3 * kept[[j - 1 for j in g]].sum(axis=0)
        out += int(np.sum(np.where(rows > 0, rows - 2, 0)))
    return out


def rms(x, kept=None):
    """
    Return the root mean square of ``x`` (any shape, nT); NaN when empty.

    ``kept``: bool of ``x``'s leading dimensions, the entries counted (the readings a
    ``drop`` term leaves out are not).
    """
    x = np.asarray(x, float)
    if kept is not None:
        x = x[np.asarray(kept, bool)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float('nan')


def scalar_rms_of(scalar, sensors, kept=None):
    """
    Return the pooled RMS of the (S, N) scalar residual of ``sensors`` (1-based), nT.

    ``kept`` (S, N) bool: the readings counted (default all).
    """
    rows = [j - 1 for j in sensors]
    return rms(scalar[rows], None if kept is None else kept[rows])


def vector_rms_of(vector, sensors, n_sensors, kept=None):
    """
    Return the pooled per-component RMS of the vector residuals involving ``sensors``, nT.

    ``kept`` (S, N) bool: the readings counted (default all); sensor j's vector residual
    counts where j's and sensor 1's readings are kept.
    """
    if n_sensors < 2:
        return None
    js = sorted({j for j in sensors if j > 1} if 1 not in sensors
                else set(range(2, n_sensors + 1)))
    rows = [j - 1 for j in js]
    return rms(vector[rows], None if kept is None else (kept & kept[:1])[rows])


@dataclass
class Evaluation:
    """
    Residuals of one parameter vector on the full data.

    Attributes
    ----------
    chi2 : float
        Sum of squared normalised residuals (or the robust loss's chi-square equivalent).
    scalar : numpy.ndarray
        (S, N) scalar residual, nT.
    vector : numpy.ndarray
        (S, N, 3) vector residual vs sensor 1, nT.
    residual : numpy.ndarray
        (S, N, 3) raw-space residual, nT.
    field : numpy.ndarray
        (N, 3) the profiled field, nT.
    kept : numpy.ndarray or None
        (S, N) bool, the readings the model keeps (None: all): those a ``drop`` term leaves
        out are zero in ``scalar``, ``vector``, ``residual`` and count in no measure.

    """

    chi2: float
    scalar: np.ndarray
    vector: np.ndarray
    residual: np.ndarray
    field: np.ndarray
    kept: np.ndarray | None = None

    @property
    def mean_square(self):
        """Return the raw-space residual's mean square over the readings kept, nT^2."""
        return rms(self.residual, self.kept) ** 2

    def scalar_rms(self, j):
        """Return sensor j's scalar residual RMS over its readings kept, nT."""
        return rms(self.scalar[j - 1], None if self.kept is None else self.kept[j - 1])

    def vector_rms(self, j):
        """Return sensor j's vector residual RMS (vs sensor 1) where both are kept, nT."""
        return vector_rms_of(self.vector, [j], self.scalar.shape[0], self.kept)


def evaluate_residuals(model, p, data, f, sigma, contexts, field0=None, loss=None):
    """
    Evaluate ``model`` at ``p`` on ``data`` (:func:`magcal_ros.core.model.evaluate`).

    Parameters
    ----------
    model : Model
        The model, prepared.
    p : numpy.ndarray
        (P,) its parameters.
    data : Dataset
        (S sensors, N epochs), nT.
    f : numpy.ndarray
        (N,) reference magnitude, nT.
    sigma : numpy.ndarray
        (S,) noise levels, nT.
    contexts : list of SensorContext
        (S,) driving signals on the same epochs.
    field0 : numpy.ndarray, optional
        (N, 3) field to start the profile from (one Gauss-Newton step of it), nT.
    loss : callable, optional
        Chi-square equivalent of a robust loss (:func:`soft_l1_lr_loss`).

    Returns
    -------
    Evaluation

    """
    out = evaluate(model, p, data, f, sigma, contexts, field0=field0)
    z = out['residual'] / sigma[:, None, None]
    chi2 = float(np.sum(z ** 2)) if loss is None else loss(z)
    return Evaluation(chi2=chi2, scalar=out['scalar'], vector=out['vector'],
                      residual=out['residual'], field=out['field'], kept=out['kept'])


def soft_l1_lr_loss(z0, f_scale):
    """
    Chi-square-equivalent of the soft-L1 loss for the likelihood-ratio test and BIC.

    For an M-estimator with loss L(z) (L = z^2 near 0; soft-L1: 2 f^2 (sqrt(1 + z^2/f^2)
    - 1), the fit's robust loss) the drop of sum L between nested models, times
    E[psi'] / E[psi^2] with psi = L'/2, is asymptotically chi-square with k degrees of
    freedom (Ronchetti's robust likelihood-ratio test, Heritier & Ronchetti 1994); the same
    scaled drop replaces delta chi-square in BIC.  The factor is estimated from the base
    fit's normalised residuals ``z0`` (any shape); for Gaussian residuals and the plain
    square loss it is 1.

    Returns
    -------
    callable
        z (S, N, 3) residual / sigma -> the scaled loss sum (a chi-square equivalent).

    """
    u = 1.0 + (np.asarray(z0, float) / f_scale) ** 2
    c = float(np.mean(u ** -1.5) / np.mean(z0 ** 2 / u))

    def loss(z):
        return c * float(np.sum(2 * f_scale ** 2 * (np.sqrt(1.0 + (z / f_scale) ** 2) - 1)))
    return loss


def likelihood_ratio(delta_chi2, k, n_obs):
    """
    Return the likelihood-ratio test and delta BIC of adding ``k`` parameters.

    Returns
    -------
    tuple of float
        (p-value, log10 p-value, delta BIC): chi-square with ``k`` degrees of freedom of
        ``delta_chi2``, and BIC(with) - BIC(without) = -delta_chi2 + k ln(n_obs).

    """
    d = max(float(delta_chi2), 0.0)
    p = float(stats.chi2.sf(d, k))
    logp = float(stats.chi2.logsf(d, k))
    if not np.isfinite(logp):
        # far tail of the regularised upper gamma function Q(a, x), a = k/2, x = d/2:
        # ln Q = (a - 1) ln x - x - ln Gamma(a) + ln(1 + (a - 1)/x + ...)
        a, x = 0.5 * k, 0.5 * d
        logp = (a - 1) * math.log(x) - x - math.lgamma(a) + math.log1p((a - 1) / x)
    logp /= math.log(10.0)
    return p, logp, float(-delta_chi2 + k * math.log(n_obs))


def explained_share(ms_before, ms_after, floor_nt):
    """
    Share (0..1) of the excess mean square over floor^2 removed: (before - after) / excess.

    0 when there is no excess (the residual is at or below the floor).
    """
    excess = float(ms_before) - float(floor_nt) ** 2
    if not excess > 0:
        return 0.0
    return float(np.clip((float(ms_before) - float(ms_after)) / excess, 0.0, 1.0))


def solve_psd(a, b):
    """Solve a x = b for a symmetric positive semi-definite (n, n) a (pseudo-inverse)."""
    w, v = np.linalg.eigh(a)
    keep = w > 1e-12 * max(w.max(), 1e-300)
    return v[:, keep] @ ((v[:, keep].T @ b) / w[keep])
