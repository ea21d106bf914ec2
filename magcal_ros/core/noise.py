"""Noise floor of a sensor estimated from the data alone (no model, no configuration)."""
from dataclasses import dataclass
from math import comb

import numpy as np

#: difference orders tried by the adaptive estimate
ORDERS = (1, 2, 3, 4, 5, 6)
#: difference orders within this ratio of the smallest estimate form the plateau
PLATEAU_RATIO = 1.05


def difference_sigmas(x, orders=ORDERS):
    """Robust white-noise sd from k-th differences, for each order k.

    For a signal that is smooth at the sample rate the k-th difference removes the signal
    and leaves noise with variance C(2k, k) sigma^2; the median absolute deviation makes it
    robust to spikes.

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) series in time order (any unit; C channels pooled), or (S, N).
    orders : sequence of int
        Difference orders k.

    Returns
    -------
    numpy.ndarray
        (K, S) sd estimates in the unit of ``x``, one row per order.
    """
    x = np.asarray(x, float)
    if x.ndim == 2:
        x = x[..., None]
    out = np.empty((len(orders), x.shape[0]))
    for i, k in enumerate(orders):
        d = np.diff(x, n=k, axis=1)
        mad = np.median(np.abs(d - np.median(d, axis=1, keepdims=True)), axis=(1, 2))
        out[i] = 1.4826 * mad / np.sqrt(comb(2 * k, k))
    return out


@dataclass(frozen=True)
class NoiseEstimate:
    """Adaptive difference-based noise estimate.

    Attributes
    ----------
    sigma : numpy.ndarray
        (S,) noise sd, unit of the input (nT for readings).
    order : numpy.ndarray
        (S,) lowest difference order of the plateau the estimate comes from.
    plateau : numpy.ndarray
        (S,) bool: at least two difference orders agree, i.e. the signal no longer
        contributes.  False means the estimate is only an upper bound (the series is not
        smooth at the sample rate).
    by_order : numpy.ndarray
        (K, S) estimate for each order tried.
    """

    sigma: np.ndarray
    order: np.ndarray
    plateau: np.ndarray
    by_order: np.ndarray


def estimate_noise(x, orders=ORDERS):
    """Adaptive noise estimate from the plateau of the difference estimates of several orders.

    A smooth trajectory sampled slowly leaves its curvature in low-order differences (at
    10 Hz a tumbling array adds ~15 nT to the 2nd difference, at 3 Hz ~20 nT to the 3rd);
    higher orders remove it, and from some order on every estimate sees only noise.  The
    plateau starts at the lowest order within :data:`PLATEAU_RATIO` of the smallest
    estimate; the estimate is the median over the plateau (the median of the orders, not
    their minimum, so the selection does not bias it low).

    Parameters
    ----------
    x : numpy.ndarray
        (S, N, C) or (S, N) series in time order.

    Returns
    -------
    NoiseEstimate
    """
    x = np.asarray(x, float)
    n = x.shape[1]
    orders = tuple(k for k in orders if n >= k + 8)
    if not orders:
        raise ValueError(f'need at least {min(ORDERS) + 8} samples to estimate the noise floor')
    by = difference_sigmas(x, orders)
    s = by.shape[1]
    sigma = np.empty(s)
    first = np.empty(s, int)
    plateau = np.empty(s, bool)
    for j in range(s):
        on = by[:, j] <= PLATEAU_RATIO * by[:, j].min()
        k0 = int(np.argmax(on))
        sigma[j] = np.median(by[k0:, j])
        first[j] = orders[k0]
        plateau[j] = len(orders) - k0 >= 2
    return NoiseEstimate(sigma=sigma, order=first, plateau=plateau, by_order=by)


def noise_floor(raw, t=None, order=None):
    """Per-axis white-noise sd of each sensor from high-order differences of the series.

    When the attitudes are not a smooth time series (e.g. random attitudes), the estimate is
    an upper bound: compare it with the model residual (see
    :func:`magcal_ros.core.diagnose.noise_floor_from_data`).

    Parameters
    ----------
    raw : numpy.ndarray
        (S, N, 3) or (N, 3) readings in nT, in time order.
    order : int, optional
        Difference order k; default: adaptive (:func:`estimate_noise`, orders 1..6).

    Returns
    -------
    numpy.ndarray
        (S,) or scalar: noise sd in nT (pooled over the three axes).
    """
    raw = np.asarray(raw, float)
    one = raw.ndim == 2
    if one:
        raw = raw[None]
    if order is None:
        sigma = estimate_noise(raw).sigma
    else:
        if raw.shape[1] < order + 8:
            raise ValueError(f'need at least {order + 8} samples to estimate the noise floor')
        sigma = difference_sigmas(raw, (order,))[0]
    return float(sigma[0]) if one else sigma
