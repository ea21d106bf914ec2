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
Planar calibration: what a turn about one axis determines, and what not (docs/planar.md).

:func:`fit_planar` fits the full model with a prior (:data:`PRIOR_SD`) on each parameter the
turn leaves open and names the undetermined ones; :func:`heading_error` propagates the
covariance to a level sensor's heading.  Units: nT, rad, deg where the name says so.
"""
from dataclasses import dataclass

from magcal_ros.core.geometry.turn import (circle_centre,  # noqa: F401 - public here too
                                           planar_magnitude, PlanarError, plane_axes,
                                           swept_angle, turn_axis)
from magcal_ros.core.model.fitting import fit
import numpy as np

#: how far (deg) the turn axis may be from the sensor axis whose parameters are held
MAX_AXIS_OFFSET_DEG = 25.0

#: sd of the prior on a parameter the turn leaves open: an offset's as a fraction of F, a
#: scale's and an angle's (rad)
PRIOR_SD = {'offset': 0.05, 'scale': 0.05, 'angle': 0.05}

#: a parameter is undetermined when its posterior sd exceeds this fraction of its prior sd
UNDETERMINED_RATIO = 0.5

#: the parameters a turn about sensor axis a (0, 1, 2) leaves open (paper 004 eq. 2)
_HELD = {
    0: {'offset': ('bx',), 'scale': ('kx',), 'nonorthogonality': ('varphi', 'theta'),
        'soft_iron': ('a00', 'a01', 'a02', 'a10', 'a20')},
    1: {'offset': ('by',), 'scale': ('ky',), 'nonorthogonality': ('varphi', 'psi'),
        'soft_iron': ('a11', 'a01', 'a10', 'a12', 'a21')},
    2: {'offset': ('bz',), 'scale': ('kz',), 'nonorthogonality': ('psi', 'theta'),
        'soft_iron': ('a22', 'a02', 'a20', 'a12', 'a21')},
}

#: the effects whose parameters are judged determined or not (the constant sensor map)
SENSOR_MAP_KINDS = ('offset', 'scale', 'nonorthogonality', 'soft_iron', 'misalignment')


@dataclass(frozen=True)
class PlanarResult:
    """A planar calibration: ``held`` indexes ``result.params``, names ``<effect>.<param>@<j>``."""

    #: the fit (its covariance widened by :func:`inflate_for_correlation`)
    result: object
    #: (S, 3) unit turn axis n of each sensor, in its own frame
    axis: np.ndarray
    #: the sensor axis (0, 1, 2 for x, y, z) n is nearest to, per sensor
    axis_index: tuple
    held: tuple
    undetermined: tuple
    determined: tuple
    #: per sensor, :func:`heading_error` at the site's H and Z
    heading: list
    #: (S,) horizontal and vertical field used for the heading error, nT
    h_nt: np.ndarray
    z_nt: np.ndarray
    #: (S,) lag-1 correlation of each sensor's scalar residual
    residual_correlation: np.ndarray


def prior_sd(model, field_nt):
    """(P,) :data:`PRIOR_SD` of each parameter of ``model`` (an offset's times ``field_nt``)."""
    return np.array([PRIOR_SD['offset'] * float(field_nt) if unit == 'nT' else
                     PRIOR_SD['angle'] if unit == 'rad' else PRIOR_SD['scale']
                     for _, _, _, unit in model.param_info()])


def held_parameters(model, axis_index):
    """Return the indices of the parameters a turn about the given axes leaves open."""
    return [k for k, (j, label, name, _) in enumerate(model.param_info())
            if j and name in _HELD[axis_index[j - 1]].get(label.split('(')[0], ())]


def fit_planar(data, model, field_nt, *, prior_params=None, inclination_deg=None,
               **fit_kwargs):
    """
    Fit ``model`` to a turn about one axis, the undetermined parameters held at a prior.

    ``data`` (S, N, 3) nT; ``model`` a Model or spec; ``field_nt`` F, nT, scalar or (N,);
    ``prior_params`` (P,) the held values (default an ideal sensor's); ``inclination_deg``
    the site's, for the heading error (default the fitted field's split); ``fit_kwargs`` go
    to :func:`magcal_ros.core.model.fitting.fit`.  Returns a :class:`PlanarResult`.
    """
    from magcal_ros.core.model.spec import Model
    if isinstance(model, str):
        model = Model.from_spec(model, data.n_sensors)
    axes = []
    for j in range(data.n_sensors):
        n = turn_axis(data.raw[j])
        k = plane_axes(n)[0]
        off = np.degrees(np.arccos(min(1.0, abs(n[k]))))
        if off > MAX_AXIS_OFFSET_DEG:
            raise PlanarError(
                f'sensor {j + 1}: the turn axis ({", ".join(f"{x:+.2f}" for x in n)}) is '
                f'{off:.0f} deg from the sensor\'s {"xyz"[k]} axis (more than '
                f'{MAX_AXIS_OFFSET_DEG:.0f}): planar mode holds the parameters of the axis '
                'the sensor turns about; mount the sensor with one axis along the turn axis')
        axes.append(n)
    axis_index = [plane_axes(n)[0] for n in axes]
    held = held_parameters(model, axis_index)
    p_prior = (model.default_params() if prior_params is None
               else np.asarray(prior_params, float))
    if p_prior.shape != (model.n_params,):
        raise ValueError(f'prior_params has {p_prior.shape} values, the model '
                         f'{model.n_params}: give the previous calibration of the same model')
    info = model.param_info()
    kind_sd = prior_sd(model, float(np.mean(field_nt)))
    prior_list = [(i, float(p_prior[i]), float(kind_sd[i])) for i in held]
    init = fit_kwargs.pop('init', None)
    # priors alone hold a long, flat valley: chi-square to 0.01 is enough
    fit_kwargs.setdefault('max_nfev', 1000)
    fit_kwargs.setdefault('ftol', 0.01 / max(1, data.n_samples * data.n_sensors))
    if init is None:
        init = _planar_start(data, model, field_nt, p_prior, held, axes)
    result = fit(data, model, field_nt=field_nt, extra_priors=prior_list, init=init,
                 check_identifiability=False, **fit_kwargs)
    result, rho = inflate_for_correlation(result)
    # held or not, known no better than UNDETERMINED_RATIO of a prior's width: undetermined
    open_ = {i for i in range(model.n_params)
             if info[i][0] and info[i][1] in SENSOR_MAP_KINDS and
             not result.stderr[i] <= UNDETERMINED_RATIO * kind_sd[i]}
    undetermined, determined = split_determined(info, open_)
    split = [_field_split(result, j, axes[j - 1], inclination_deg)
             for j in range(1, data.n_sensors + 1)]
    heading = [heading_error(result, j, axes[j - 1], axis_index[j - 1], *split[j - 1])
               for j in range(1, data.n_sensors + 1)]
    return PlanarResult(result=result, axis=np.array(axes), axis_index=tuple(axis_index),
                        held=tuple(held), undetermined=undetermined, determined=determined,
                        heading=heading, h_nt=np.array([h for h, _ in split]),
                        z_nt=np.array([z for _, z in split]), residual_correlation=rho)


def split_determined(info, open_, also=()):
    """Return (undetermined ``open_``, determined: the other sensors' and ``also``) as names."""
    label = [f'{lab}.{nm}@{j}' for j, lab, nm, _ in info]
    return (tuple(label[k] for k in sorted(open_)),
            tuple(label[k] for k in range(len(info))
                  if k not in open_ and (info[k][0] or k in also)))


def central_jacobian(fun, p, cols, steps, wrap=lambda d: d):
    """(M, K) central differences of ``fun`` (p (P,) -> (M,)) in ``cols``, ``steps`` (K,)."""
    jac = np.empty((len(fun(p)), len(cols)))
    for col, (i, step) in enumerate(zip(cols, steps)):
        dp = np.zeros_like(p)
        dp[i] = step
        jac[:, col] = wrap(fun(p + dp) - fun(p - dp)) / (2 * step)
    return jac


def inflate_for_correlation(result):
    """Return (fit, (S,) rho), each sensor's block times (1 + rho) / (1 - rho) (Bartlett 1946)."""
    from dataclasses import replace
    model = result.model
    owner = np.array([s for s, *_ in model.param_info()])
    scale = np.ones(model.n_params)
    rho = np.zeros(model.n_sensors)
    for j in range(1, model.n_sensors + 1):
        r = result.scalar_residual_nt[j - 1]
        if len(r) > 3 and np.std(r) > 0:
            rho[j - 1] = float(np.corrcoef(r[:-1], r[1:])[0, 1])
        c = min(max(rho[j - 1], 0.0), 0.99)
        scale[owner == j] = np.sqrt((1 + c) / (1 - c))
    cov = result.covariance * np.outer(scale, scale)
    return replace(result, covariance=cov, stderr=result.stderr * scale), rho


def _planar_start(data, model, field_nt, p_prior, held, axes):
    """Start: the prior, with each sensor's in-plane offset from a circle fit."""
    p = p_prior.copy()
    info = model.param_info()
    for j in range(1, data.n_sensors + 1):
        plane = plane_axes(axes[j - 1])[1]
        centre = circle_centre(data.raw[j - 1][:, plane])
        for i, (s, label, name, _) in enumerate(info):
            if s == j and label == 'offset' and i not in held:
                p[i] = centre[plane.index('xyz'.index(name[1]))]
    return p


def _field_split(result, j, axis, inclination_deg):
    """(H, Z) nT for the heading error: the site's inclination, else the fitted field's."""
    f = float(np.mean(result.field_magnitude_nt))
    if inclination_deg is not None:
        inc = np.radians(inclination_deg)
        return f * abs(np.cos(inc)), f * np.sin(inc)
    b = result.corrected_nt[j - 1]
    along = b @ axis
    return float(np.median(np.linalg.norm(b - np.outer(along, axis), axis=1))), \
        float(np.median(along))


def heading_error(result, j, axis, axis_index, h_nt, z_nt, n_headings=72):
    """
    Return the standard uncertainty of the heading of a level sensor j (fit's covariance).

    Turning about ``axis`` (its own frame) in horizontal field ``h_nt`` and vertical ``z_nt``
    (nT), propagated by central differences on a grid of headings.  Returns a dict:
    ``max_deg`` and ``rms_deg`` over psi, ``psi_deg`` (M,), ``sd_deg`` (M,).
    """
    model, p = result.model, result.params
    u, v = np.eye(3)[[a for a in range(3) if a != axis_index]]
    psi = np.radians(np.arange(n_headings) * 360.0 / n_headings)
    b = (h_nt * (np.cos(psi)[:, None] * u - np.sin(psi)[:, None] * v)
         + z_nt * np.asarray(axis, float)[None, :])
    ctx0 = result.contexts[j - 1].subset(np.zeros(n_headings, int))
    raw = model.forward(j, p, b, ctx0)

    def heading(params):
        c = model.correct(j, params, raw, ctx0)
        return np.arctan2(-(c @ v), c @ u)

    free = [i for i, (s, *_rest) in enumerate(model.param_info()) if s == j]
    cov = result.covariance[np.ix_(free, free)]
    se = np.where(np.isfinite(result.stderr), result.stderr, 0.0)
    jac = central_jacobian(heading, p, free,
                           [max(1e-6, 1e-4 * max(abs(p[i]), se[i])) for i in free],
                           wrap=lambda d: np.angle(np.exp(1j * d)))
    sd = np.degrees(np.sqrt(np.clip(np.einsum('ij,jk,ik->i', jac, cov, jac), 0, None)))
    return {'max_deg': float(sd.max()), 'rms_deg': float(np.sqrt(np.mean(sd ** 2))),
            'psi_deg': np.degrees(psi), 'sd_deg': sd}


#: the in-plane non-orthogonality angle of a turn about sensor axis a (paper 004 eq. 2)
_IN_PLANE_ANGLE = {0: 'psi', 1: 'theta', 2: 'varphi'}


def planar_summary(pr):
    """
    JSON-ready account of a :class:`PlanarResult` (nT, rad, deg as named).

    ``axis``, ``in_plane`` (offsets, scale ratio, non-orthogonality, each with its stderr),
    ``heading_error_deg`` and ``_rms_deg``, ``field_split_nt`` per sensor, and the
    ``determined`` / ``undetermined`` names.
    """
    r = pr.result
    where = r.model.param_positions()
    out = {'axis': {}, 'in_plane': {}, 'heading_error_deg': {}, 'heading_error_rms_deg': {},
           'field_split_nt': {}, 'determined': list(pr.determined),
           'undetermined': list(pr.undetermined)}
    for j in range(1, r.model.n_sensors + 1):
        k, plane = plane_axes(pr.axis[j - 1])

        def index(label, name, j=j):
            return where.get((j, label, name))
        entry = {'axes': ''.join('xyz'[a] for a in plane)}
        off = [index('offset', 'b' + 'xyz'[a]) for a in plane]
        if None not in off:
            entry['offset_nt'] = [float(r.params[i]) for i in off]
            entry['offset_stderr_nt'] = [float(r.stderr[i]) for i in off]
        eff, eff_sd = effective_offset(r, j, pr.axis[j - 1], k, pr.z_nt[j - 1])
        entry['effective_offset_nt'] = eff.tolist()
        entry['effective_offset_stderr_nt'] = eff_sd.tolist()
        ku, kv = (index('scale', 'k' + 'xyz'[a]) for a in plane)
        if ku is not None and kv is not None:
            ratio = r.params[kv] / r.params[ku]
            g = np.array([-ratio / r.params[ku], 1.0 / r.params[ku]])
            c = r.covariance[np.ix_([ku, kv], [ku, kv])]
            entry['scale_ratio'] = float(ratio)
            entry['scale_ratio_stderr'] = float(np.sqrt(max(g @ c @ g, 0.0)))
        ang = index('nonorthogonality', _IN_PLANE_ANGLE[k])
        if ang is not None:
            entry['nonorth_rad'] = float(r.params[ang])
            entry['nonorth_stderr_rad'] = float(r.stderr[ang])
        out['axis'][str(j)] = [float(x) for x in pr.axis[j - 1]]
        out['in_plane'][str(j)] = entry
        out['heading_error_deg'][str(j)] = pr.heading[j - 1]['max_deg']
        out['heading_error_rms_deg'][str(j)] = pr.heading[j - 1]['rms_deg']
        out['field_split_nt'][str(j)] = {'horizontal': float(pr.h_nt[j - 1]),
                                         'vertical': float(pr.z_nt[j - 1])}
        out.setdefault('residual_lag1_correlation', {})[str(j)] = float(
            pr.residual_correlation[j - 1])
    return out


def effective_offset(result, j, axis, axis_index, z_nt):
    """((2,) nT, (2,) nT sd): the centre A_pn Z + o_p of a level turn's in-plane circle."""
    model, p = result.model, result.params
    plane = [a for a in range(3) if a != axis_index]
    ctx = result.contexts[j - 1].subset(np.zeros(1, int))

    def centre(params):
        b = z_nt * np.asarray(axis, float)[None, :]
        return model.forward(j, params, b, ctx)[0, plane]

    own = [i for i, (s, *_rest) in enumerate(model.param_info()) if s == j]
    jac = central_jacobian(centre, p, own, [1e-6 * max(1.0, abs(p[i])) for i in own])
    cov = jac @ result.covariance[np.ix_(own, own)] @ jac.T
    return centre(p), np.sqrt(np.clip(np.diag(cov), 0, None))


def planar_notes(pr):
    """Warnings (:class:`~magcal_ros.core.model.notes.Note`) of what the turn left open."""
    from magcal_ros.core.model.notes import Note
    if not pr.undetermined:
        return []
    return [Note(
        'planar calibration: a turn about one axis does not determine '
        f'{", ".join(pr.undetermined)}: held at their prior (the previous calibration or an '
        'ideal sensor, within 5 % and 0.05 rad) and marked undetermined; the in-plane '
        'offsets, scale ratio and angle are heading-grade for a sensor that turns level at '
        'this site; tilt the robot or turn the sensor about another axis for a full '
        'calibration', 'degenerate')]
