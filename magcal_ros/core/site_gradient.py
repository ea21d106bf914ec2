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


#: cases of :func:`crb_covariance`
CRB_CASES = ('attitude', 'heading', 'epoch_gradient')


def _null_dimension(jac, rtol=1e-12):
    """Number of parameter directions the (column-scaled) Jacobian does not determine."""
    d = np.linalg.norm(jac, axis=0)
    d[d == 0] = 1.0
    w = np.linalg.svd(jac / d, compute_uv=False) ** 2
    return int(np.sum(w <= rtol * w.max()))


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def crb_covariance(data, model, params, field_nt, sigma_nt, case='attitude', positions=None):
    """Cramer-Rao bound of the calibration (and site gradient) with or without attitude.

    The Fisher information of the joint ML problem at ``params`` (the truth), with the per-epoch
    nuisances of each case eliminated (variable projection, as in the fit):

    - ``'attitude'``: attitude known; nuisance: the centre field B_k on the sphere |B| = F
      (2 per epoch).  ``model`` has ``site_gradient``.
    - ``'heading'``: attitude known only up to the rotation about the field (what a
      magnetometer array can tell itself: the field direction in the body frame fixes two of
      the three angles); nuisance: B_k and the angle psi_k about the field (3 per epoch).
      The world gradient is then determined only up to a rotation about the field
      direction (one gauge freedom: rotating G_w by delta about the field is the same as
      shifting every psi_k by -delta); its covariance is given on the 4 gauge-free
      directions, the gauge direction gets an infinite variance.  ``model`` has
      ``site_gradient`` and the data the attitude (the truth, as linearisation point).
    - ``'epoch_gradient'``: no attitude at all; the body-frame gradient of every epoch is a
      nuisance restricted by symmetry and zero trace (5 per epoch, plus B_k).  ``model`` has
      no ``site_gradient`` (there is no constant world tensor left to estimate).

    Parameters
    ----------
    data : Dataset
        Raw readings (S, N, 3) nT; with ``attitude`` for 'attitude' and 'heading'.
    model : Model
        Joint model (misalignment on sensors 2..S, or an array-wide effect).
    params : numpy.ndarray
        (P,) parameters at which the information is evaluated (the truth), units of
        ``model.param_info()``.
    field_nt : float or numpy.ndarray
        Reference magnitude at the array centre, nT, scalar or (N,).
    sigma_nt : float or numpy.ndarray
        Per-axis noise sd, nT, scalar or (S,).
    positions : numpy.ndarray, optional
        (S, 3) sensor positions, m, for 'epoch_gradient' (default: paper 004's cross, 0.5 m).

    Returns
    -------
    dict
        ``covariance`` (P, P) bound in the parameters' units squared, inf where the case
        leaves a parameter undetermined (for 'heading': the whole gradient block);
        ``gradient_covariance`` (5, 5) (nT/m)^2 of (gxx, gxy, gxz, gyy, gyz) on the
        gauge-free directions ('heading') or None; ``gauge_direction`` (5,) or None;
        ``undetermined_directions``: how many parameter combinations the data cannot
        determine at all ('epoch_gradient').
    """
    from magcal_ros.core import model as mdl
    from magcal_ros.core.magnitude import reference_magnitude
    if case not in CRB_CASES:
        raise ValueError(f'unknown case {case!r}; use one of {CRB_CASES}')
    contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    model.prepare(contexts)
    f = reference_magnitude(data, field_nt)
    s = model.n_sensors
    sigma = np.broadcast_to(np.asarray(sigma_nt, float), (s,)).copy()
    grp = list(range(1, s + 1))
    prob = mdl._Problem(model, data.raw, contexts, f, grp, sigma, [])
    prob.p_full = np.asarray(params, float).copy()
    x = prob.p_full[prob.cols]
    jac = prob.jacobian(x)                         # (N 3S, P), B_k projected out
    cov = np.full((model.n_params, model.n_params), np.inf)
    out = {'covariance': cov, 'gradient_covariance': None, 'gauge_direction': None,
           'undetermined_directions': 0}
    if case == 'attitude':
        cov[np.ix_(prob.cols, prob.cols)] = mdl._covariance(jac)
        return out
    p, b, mats, _ = prob.evaluate(x)
    n = data.n_samples
    if case == 'heading':
        site = [(e, sl) for e, sl in zip(model.array_effects, model.array_slices)
                if e.name == 'site_gradient']
        if not site or contexts[0].attitude is None:
            raise ValueError("case 'heading' needs a model with site_gradient and the attitude")
        eff, sl = site[0]
        rot = contexts[0].attitude
        n_w = np.einsum('nij,nj->ni', rot, b).mean(axis=0)
        n_w /= np.linalg.norm(n_w)
        nx = _skew(n_w)
        g_w = eff.tensor(p[sl])
        d_g = g_w @ nx - nx @ g_w                   # d(R^T G R)/d psi = R^T (G N - N G) R
        cols = []
        for j in grp:
            v = np.einsum('nji,jk,nkl,l->ni', rot, d_g, rot, eff.position(j))
            cols.append(-(v @ mats[j].T) / sigma[j - 1])
        gn = np.stack(cols, axis=1).reshape(n, 3 * s, 1)
        gauge = np.array([d_g[0, 0], d_g[0, 1], d_g[0, 2], d_g[1, 1], d_g[1, 2]])
    else:
        if model.array_effects:
            raise ValueError("case 'epoch_gradient' takes a model without site_gradient")
        from magcal_ros.core.tensor import cross_positions
        pos = cross_positions(0.5) if positions is None else np.asarray(positions, float)
        cols = []
        for j in grp:
            c = np.stack([mats[j] @ (symmetric_traceless(e) @ pos[j - 1]) for e in np.eye(5)],
                         axis=1) / sigma[j - 1]                          # (3, 5)
            cols.append(np.broadcast_to(-c, (n, 3, 5)))
        gn = np.concatenate(cols, axis=1)                                 # (N, 3S, 5)
        gauge = None
    # project the extra nuisance onto the complement of the sphere directions, then out
    u = b / f[:, None]
    e1, e2 = mdl._tangent_basis(u)
    gb = np.concatenate([np.stack([e1 @ mats[j].T, e2 @ mats[j].T], axis=2)
                         * (f[:, None, None] / sigma[j - 1]) for j in grp], axis=1)
    gbt = np.swapaxes(gb, 1, 2)
    gn = gn - gb @ mdl._solve2x2(gbt @ gb, gbt @ gn)
    gnt = np.swapaxes(gn, 1, 2)
    j3 = jac.reshape(n, 3 * s, -1)
    j3 = j3 - gn @ np.linalg.solve(gnt @ gn, gnt @ j3)
    jac = j3.reshape(n * 3 * s, -1)
    if gauge is None:
        cov[np.ix_(prob.cols, prob.cols)] = mdl._covariance(jac)
        out['undetermined_directions'] = _null_dimension(jac)
        return out
    # heading: drop the gauge direction of the gradient, bound the rest
    where = [list(prob.cols).index(i) for i in range(sl.start, sl.stop)]
    basis = np.linalg.svd(gauge[None])[2][1:].T                  # (5, 4) orthonormal, ⟂ gauge
    jg = jac[:, where] @ basis
    keep = [c for c in range(jac.shape[1]) if c not in where]
    cov_r = mdl._covariance(np.hstack([jac[:, keep], jg]))
    cal_cols = prob.cols[keep]
    cov[np.ix_(cal_cols, cal_cols)] = cov_r[:len(keep), :len(keep)]
    out['gradient_covariance'] = basis @ cov_r[len(keep):, len(keep):] @ basis.T
    out['gauge_direction'] = gauge / np.linalg.norm(gauge)
    return out
