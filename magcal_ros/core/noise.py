"""Noise floor of a sensor estimated from the data alone (no model, no configuration)."""
import numpy as np


def noise_floor(raw, t=None, order=3):
    """Per-axis white-noise sd of each sensor from high-order differences of the series.

    For a signal that is smooth at the sample rate, the k-th difference removes the signal
    and leaves noise with variance C(2k, k) sigma^2 (C(6, 3) = 20 for k = 3).  The median
    absolute deviation makes it robust to spikes.  When the attitudes are not a smooth
    time series (e.g. random attitudes), the estimate is an upper bound: compare it with
    the model residual.

    Parameters
    ----------
    raw : numpy.ndarray
        (S, N, 3) or (N, 3) readings in nT, in time order.
    order : int
        Difference order k (2..4).

    Returns
    -------
    numpy.ndarray
        (S,) or scalar: noise sd in nT (pooled over the three axes).
    """
    raw = np.asarray(raw, float)
    one = raw.ndim == 2
    if one:
        raw = raw[None]
    if raw.shape[1] < order + 8:
        raise ValueError(f'need at least {order + 8} samples to estimate the noise floor')
    from math import comb
    d = np.diff(raw, n=order, axis=1)
    mad = np.median(np.abs(d - np.median(d, axis=1, keepdims=True)), axis=(1, 2))
    sigma = 1.4826 * mad / np.sqrt(comb(2 * order, order))
    return float(sigma[0]) if one else sigma
