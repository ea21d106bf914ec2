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
The site gradient: its Cramer-Rao bounds with and without attitude, the fit without attitude.

The effect is :class:`magcal_ros.core.effects.SiteGradient` (docs/site_gradient.md).  Units:
nT, nT/m, m, rad.
"""
from magcal_ros.core.effects.base import rot_z
from magcal_ros.core.geometry.tensor import symmetric_traceless
from magcal_ros.core.model.engine import ProfiledProblem
from magcal_ros.core.model.fitting import centred_readings, corrected_readings
from magcal_ros.core.model.solvers import covariance_from_jacobian, stderr_and_correlation
import numpy as np


def centred_fields(result):
    """(S, N, 3) nT a fit's corrected fields less each sensor's site shift (centre field)."""
    return centred_readings(result.model, result.params, result.corrected_nt, result.contexts)


#: the frame of the site gradient found without attitude (:func:`fit_heading_unknown`)
FIELD_ALIGNED = 'field-aligned: z along the field, x along the part of G z perpendicular to it'

#: cases of :func:`crb_covariance`
CRB_CASES = ('attitude', 'heading', 'epoch_gradient')


def _site_gradient(model):
    """Return (effect, slice) of ``model``'s site gradient, or None."""
    return next(((e, sl) for e, sl in zip(model.array_effects, model.array_slices)
                 if e.name == 'site_gradient'), None)


def _null_dimension(jac, rtol=1e-12):
    """Count the parameter directions the (column-scaled) Jacobian does not determine."""
    d = np.linalg.norm(jac, axis=0)
    d[d == 0] = 1.0
    w = np.linalg.svd(jac / d, compute_uv=False) ** 2
    return int(np.sum(w <= rtol * w.max()))


def crb_covariance(data, model, params, field_nt, sigma_nt, case='attitude', fix_gyz=False):
    """
    Cramer-Rao bound of the calibration (and site gradient) with or without attitude.

    The Fisher information at ``params`` with each case's per-epoch nuisances projected out:
    ``'attitude'`` B_k on the sphere |B| = F; ``'heading'`` also the rotation psi_k about the
    field (G_w then known up to that rotation, the gauge); ``'epoch_gradient'`` no attitude,
    a body-frame gradient per epoch (paper 004's cross, ``model`` without ``site_gradient``).

    ``data`` (S, N, 3) nT readings (with the attitude, but for 'epoch_gradient'); ``model``
    joint; ``params`` (P,); ``field_nt`` nT, scalar or (N,); ``sigma_nt`` nT, scalar or
    (S,); ``fix_gyz``: the 'heading' gauge fixed by gyz = 0.  Returns a dict: ``covariance``
    (P, P), inf where undetermined; ``gradient_covariance`` (5, 5) (nT/m)^2 on the
    gauge-free directions ('heading') or None; ``gauge_direction`` (5,) or None;
    ``undetermined_directions`` (count; 'epoch_gradient').
    """
    if case not in CRB_CASES:
        raise ValueError(f'unknown case {case!r}; use one of {CRB_CASES}')
    contexts = [data.context(j) for j in range(1, data.n_sensors + 1)]
    model.prepare(contexts)
    f = data.reference_magnitude(field_nt)
    s = model.n_sensors
    sigma = np.broadcast_to(np.asarray(sigma_nt, float), (s,)).copy()
    grp = list(range(1, s + 1))
    prob = ProfiledProblem(model, data.raw, contexts, f, grp, sigma, p_full=params)
    x = prob.p_full[prob.cols]
    jac = prob.jacobian(x)                         # (N 3S, P), B_k projected out
    cov = np.full((model.n_params, model.n_params), np.inf)
    out = {'covariance': cov, 'gradient_covariance': None, 'gauge_direction': None,
           'undetermined_directions': 0}
    if case == 'attitude':
        cov[np.ix_(prob.cols, prob.cols)] = covariance_from_jacobian(jac)
        return out
    p, b, mats, _ = prob.evaluate(x)
    n = data.n_samples
    if case == 'heading':
        site = _site_gradient(model)
        if site is None or contexts[0].attitude is None:
            raise ValueError("case 'heading' needs a model with site_gradient and the attitude")
        eff, sl = site
        rot = contexts[0].attitude
        n_w = np.einsum('nij,nj->ni', rot, b).mean(axis=0)
        n_w /= np.linalg.norm(n_w)
        nx = np.array([[0.0, -n_w[2], n_w[1]], [n_w[2], 0.0, -n_w[0]], [-n_w[1], n_w[0], 0.0]])
        g_w = eff.tensor(p[sl])
        d_g = g_w @ nx - nx @ g_w                   # d(R^T G R)/d psi = R^T (G N - N G) R
        cols = [-(np.einsum('nji,jk,nkl,l->ni', rot, d_g, rot, eff.position(j)) @ mats[j].T)
                / sigma[j - 1] for j in grp]
        gn = np.stack(cols, axis=1).reshape(n, 3 * s, 1)
        gauge = np.array([d_g[0, 0], d_g[0, 1], d_g[0, 2], d_g[1, 1], d_g[1, 2]])
    else:
        if model.array_effects:
            raise ValueError("case 'epoch_gradient' takes a model without site_gradient")
        from magcal_ros.core.geometry.tensor import cross_positions
        pos = cross_positions(0.5)
        cols = []
        for j in grp:
            c = np.stack([mats[j] @ (symmetric_traceless(e) @ pos[j - 1]) for e in np.eye(5)],
                         axis=1) / sigma[j - 1]                          # (3, 5)
            cols.append(np.broadcast_to(-c, (n, 3, 5)))
        gn = np.concatenate(cols, axis=1)                                 # (N, 3S, 5)
        gauge = None
    # project the extra nuisance onto the complement of the sphere directions, then out
    gn = prob.project_out_field(b, mats, gn)
    gnt = np.swapaxes(gn, 1, 2)
    j3 = jac.reshape(n, 3 * s, -1)
    j3 = j3 - gn @ np.linalg.solve(gnt @ gn, gnt @ j3)
    jac = j3.reshape(n * 3 * s, -1)
    if gauge is None:
        cov[np.ix_(prob.cols, prob.cols)] = covariance_from_jacobian(jac)
        out['undetermined_directions'] = _null_dimension(jac)
        return out
    # heading: drop the gauge direction of the gradient, bound the rest
    where = [list(prob.cols).index(i) for i in range(sl.start, sl.stop)]
    basis = (np.eye(5)[:, :4] if fix_gyz                          # gxx, gxy, gxz, gyy free
             else np.linalg.svd(gauge[None])[2][1:].T)           # (5, 4) orthonormal, ⟂ gauge
    jg = jac[:, where] @ basis
    keep = [c for c in range(jac.shape[1]) if c not in where]
    cov_r = covariance_from_jacobian(np.hstack([jac[:, keep], jg]))
    cal_cols = prob.cols[keep]
    cov[np.ix_(cal_cols, cal_cols)] = cov_r[:len(keep), :len(keep)]
    out['gradient_covariance'] = basis @ cov_r[len(keep):, len(keep):] @ basis.T
    out['gauge_direction'] = gauge / np.linalg.norm(gauge)
    return out


def _align_to_z(u):
    """(N, 3, 3) rotations R_a with R_a u_k = z (the smallest rotation), u (N, 3) unit."""
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s = np.linalg.norm(axis, axis=1)
    ang = np.arctan2(s, u[:, 2])
    axis = np.where(s[:, None] > 1e-12, axis / np.maximum(s, 1e-300)[:, None],
                    np.array([1.0, 0.0, 0.0]))
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(axis * ang[:, None]).as_matrix()


def _best_heading(shift, r_a, g_w, positions, psi):
    """Refine the headings psi (N,) rad: min sum_j |shift_j - R^T G R r_j|^2, R = Rz(psi) R_a."""
    def cost(psi):
        rot = rot_z(psi) @ r_a
        pred = np.einsum('nji,jk,nkl,sl->sni', rot, g_w, rot, positions)
        return np.sum((shift - pred) ** 2, axis=(0, 2))

    h = 1e-4
    for _ in range(6):
        c0, cp, cm = cost(psi), cost(psi + h), cost(psi - h)
        d1 = (cp - cm) / (2 * h)
        d2 = (cp - 2 * c0 + cm) / h ** 2
        step = np.where(d2 > 0, -d1 / np.where(d2 > 0, d2, 1.0), 0.0)
        psi = psi + np.clip(step, -0.2, 0.2)
    return psi


def fit_heading_unknown(data, model='base,site_gradient', field_nt=None, n_iter=8,
                        **fit_kwargs):
    """
    Calibrate the cross in a site gradient without attitude (docs/site_gradient.md, 'heading').

    ``data`` (4, N, 3) nT (an attitude is not used); ``model`` with ``site_gradient``;
    ``field_nt`` nT; ``n_iter`` most alternations (fewer once no parameter moves by 1 % of
    its stderr).  Returns a FitResult in the :data:`FIELD_ALIGNED` frame, ``contexts``
    with the estimated attitudes, stderr from :func:`crb_covariance`'s heading case.
    """
    from dataclasses import replace
    from magcal_ros.core import model as mdl
    from scipy.spatial.transform import Rotation
    if isinstance(model, str):
        model = mdl.Model.from_spec(model, data.n_sensors)
    site = _site_gradient(model)
    if site is None:
        raise ValueError('fit_heading_unknown needs a model with site_gradient')
    eff, sl = site
    positions = np.stack([eff.position(j) for j in range(1, model.n_sensors + 1)])
    if np.abs(positions.mean(axis=0)).max() > 1e-9:
        raise ValueError('fit_heading_unknown needs sensor positions centred on the origin '
                         "(paper 004's cross)")
    bare = replace(data, attitude=None)
    base = mdl.Model.from_spec([t for t in model.spec() if t != 'site_gradient'], data.n_sensors)
    r0 = mdl.fit(bare, base, field_nt=field_nt, **fit_kwargs)
    p = model.default_params()
    p[:base.n_params] = r0.params
    ctx0 = [bare.context(j) for j in range(1, data.n_sensors + 1)]
    psi = res = None
    for it in range(n_iter):
        c = corrected_readings(model, p, bare.raw, ctx0)
        centre = c.mean(axis=0)
        r_a = _align_to_z(centre / np.linalg.norm(centre, axis=1, keepdims=True))
        shift = c - centre[None]
        if it == 0:
            # start: psi_k the phase of (Gxz + i Gyz) of the body tensor in the aligned frame
            from magcal_ros.core.geometry.tensor import tensor_lstsq
            g_b, _ = tensor_lstsq(c, positions)
            m_k = np.einsum('nij,njk,nlk->nil', r_a, g_b, r_a)
            psi = -np.angle(m_k[:, 0, 2] + 1j * m_k[:, 1, 2])
            rot = rot_z(psi) @ r_a
            g_w = np.einsum('nij,njk,nlk->il', rot, g_b, rot) / len(psi)   # mean R G_b R^T
            g_w = 0.5 * (g_w + g_w.T)
            g_w -= np.trace(g_w) / 3 * np.eye(3)
            p[sl] = [g_w[0, 0], g_w[0, 1], g_w[0, 2], g_w[1, 1], g_w[1, 2]]
        else:
            g_w = eff.tensor(p[sl])
        psi = _best_heading(shift, r_a, g_w, positions, psi)
        att = Rotation.from_matrix(rot_z(psi) @ r_a).as_quat(scalar_first=True)
        res = mdl.fit(replace(bare, attitude=att), model, field_nt=field_nt, init=p,
                      check_identifiability=False, **fit_kwargs)
        moved = np.abs(res.params - p) / np.where(res.stderr > 0, res.stderr, np.inf)
        p = res.params.copy()
        if it >= 2 and np.all(moved[np.isfinite(moved)] < 0.01):
            break
    # gauge: rotate the world frame about the field so that gyz = 0 (gxz >= 0)
    g_w = eff.tensor(p[sl])
    phi = np.angle(g_w[0, 2] + 1j * g_w[1, 2])
    rz = rot_z(np.array([phi]))[0]
    g_w = rz.T @ g_w @ rz
    p[sl] = [g_w[0, 0], g_w[0, 1], g_w[0, 2], g_w[1, 1], 0.0]
    att = Rotation.from_matrix(rot_z(psi - phi) @ r_a).as_quat(scalar_first=True)
    fixed = replace(bare, attitude=att)
    # the heading psi_k takes one more of the 3 S - 2 degrees of freedom per epoch
    s = data.n_sensors
    sigma = res.sigma_nt * np.sqrt((3 * s - 2) / (3 * s - 3))
    out = crb_covariance(fixed, model, p, data.reference_magnitude(field_nt), sigma,
                         case='heading', fix_gyz=True)
    cov = out['covariance']
    cov[sl.start:sl.start + 4, sl.start:sl.start + 4] = out['gradient_covariance'][:4, :4]
    cov[sl.start + 4, :] = 0.0
    cov[:, sl.start + 4] = 0.0
    stderr, corr = stderr_and_correlation(cov)
    warnings = tuple(res.warnings) + (
        'no attitude: the heading about the field was estimated at every epoch; the site '
        'gradient is given in a field-aligned frame (z along the field, x along the part of '
        'G z perpendicular to it, so gyz = 0): its rotation about the field is not '
        'determined without attitude; uncertainties from the Cramer-Rao bound with the '
        'headings unknown',)
    ident = dict(res.identifiability, site_gradient_frame=FIELD_ALIGNED)
    return replace(res, params=p, covariance=cov, correlation=corr, stderr=stderr,
                   warnings=warnings, sigma_nt=sigma, identifiability=ident,
                   contexts=[fixed.context(j) for j in range(1, data.n_sensors + 1)])
