"""The site gradient: its report from a fit, and its Cramer-Rao bounds with and without attitude.

The effect itself is :class:`magcal_ros.core.effects.SiteGradient` (docs/site_gradient.md has
the physics and the identifiability analysis summarised here).
"""
import numpy as np

from magcal_ros.core.effects import symmetric_traceless

#: d vec(G) / d (gxx, gxy, gxz, gyy, gyz): the 9 x 5 map of the symmetric traceless tensor
TENSOR_MAP = np.stack([symmetric_traceless(e).ravel() for e in np.eye(5)], axis=1)


def gradient_from_fit(model, params, covariance):
    """World-frame site gradient and its standard uncertainty from a fit.

    Parameters
    ----------
    model : Model
    params : numpy.ndarray
        (P,) parameters.
    covariance : numpy.ndarray
        (P, P) parameter covariance.

    Returns
    -------
    (G (3, 3) nT/m, stderr (3, 3) nT/m, cov5 (5, 5) (nT/m)^2) or None without the effect.
    """
    for eff, sl in zip(model.array_effects, model.array_slices):
        if eff.name == 'site_gradient':
            g5 = params[sl]
            c5 = covariance[sl, sl]
            cov9 = TENSOR_MAP @ c5 @ TENSOR_MAP.T
            se = np.sqrt(np.clip(np.diag(cov9), 0, None)).reshape(3, 3)
            return symmetric_traceless(g5), se, c5
    return None


def centred_fields(result):
    """(S, N, 3) nT corrected fields minus each sensor's modelled site shift (centre field).

    Without array-wide effects this is ``result.corrected_nt`` itself.
    """
    model = result.model
    if not model.array_effects:
        return result.corrected_nt
    shift = np.stack([model.array_shift(j, result.params, result.contexts[j - 1])
                      for j in range(1, model.n_sensors + 1)])
    return result.corrected_nt - shift
