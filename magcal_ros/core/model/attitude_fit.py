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
Attitude-aided calibration: a vehicle that stays near level and turns part of a circle.

The attitude observes the field's direction (:mod:`magcal_ros.core.effects.attitude_ref`);
:func:`fit_attitude` fits with it and the constrained mode's priors, names what the priors
determine (:func:`prior_held`, docs/planar.md) and checks the heading (:func:`heading_check`).
Units: nT, rad; degrees where a name says so.
"""
from dataclasses import dataclass

from magcal_ros.core.effects.attitude_ref import (attitude_reference, AttitudeReference,
                                                  MODES, MOUNT_PRIOR_SD_RAD)
from magcal_ros.core.model.fitting import fit, initial_params, priors_for
from magcal_ros.core.model.planar import (inflate_for_correlation, SENSOR_MAP_KINDS,
                                          split_determined)
from magcal_ros.core.model.spec import Model
import numpy as np

#: a parameter is held by the priors when twice as strong priors would shrink its variance
#: by more than this factor (:func:`prior_held`)
PRIOR_HELD_RATIO = 1.25
#: heading disagreement (deg, RMS about its mean) above which attitude and compass disagree
HEADING_DISAGREE_DEG = 5.0
#: sensor 1's offsets in the horizontal plane: open, they leave the compass's heading open
HORIZONTAL_OFFSETS = frozenset({'offset.bx@1', 'offset.by@1'})
#: what the inclination rests on besides the data (sensor 1's scales, vertical offset, the
#: mounting's tilt): one of them open, the inclination rests on its held value
VERTICAL_PARAMS = frozenset({'kx@1', 'ky@1', 'kz@1', 'bz@1', 'mount_x@0', 'mount_y@0'})


@dataclass(frozen=True)
class AttitudeResult:
    """Outcome of :func:`fit_attitude` (parameter names as planar mode's)."""

    #: the fit (its model with the attitude's effect; covariance widened)
    result: object
    #: 'tilt' or 'full'
    mode: str
    undetermined: tuple
    determined: tuple
    #: the attitude's white error as an angle, deg
    attitude_sd_deg: float
    #: inclination (and declination) in the attitude's frame, deg, stderr, the mounting
    world_field: dict
    #: :func:`heading_check`
    heading: dict
    #: (S,) lag-1 correlation of each sensor's scalar residual
    residual_correlation: np.ndarray


def with_attitude(model, mode, n_sensors=None):
    """Return ``model`` (Model or formula) with the attitude's observation of ``mode`` only."""
    if mode not in MODES:
        raise ValueError(f"attitude mode must be one of {', '.join(MODES)}, got {mode!r}")
    if isinstance(model, str):
        model = Model.from_spec(model, n_sensors)
    keep = [e for e in model.array_effects if not isinstance(e, AttitudeReference)]
    return Model(model.effects, keep + [MODES[mode](sensor=0)], model.drops)


def attitude_start(data, model, f):
    """(P,) start: offsets, Z from |raw - o| = F, g_k . (raw - o) = Z (A = I); f (N,) nT."""
    rot = data.attitude_matrix()
    g = rot[:, 2, :]                                   # world vertical in the body frame
    f0 = float(np.mean(f))
    p = initial_params(data.raw, f, model, constrained=True)
    for j, m in enumerate(data.raw, 1):
        n = len(m)
        # 2 m.o + c = |m|^2 - F^2 (over 2F: nT) and g.o + Z = g.m
        sphere = np.column_stack([2 * m, np.ones(n), np.zeros(n)]) / (2 * f0)
        vert = np.column_stack([g, np.zeros(n), np.ones(n)])
        rhs = np.concatenate([((m ** 2).sum(1) - f ** 2) / (2 * f0), (g * m).sum(1)])
        sol, *_ = np.linalg.lstsq(np.vstack([sphere, vert]), rhs, rcond=None)
        p = model.params_from_linear(j, model.matrix(j, p), sol[:3], p)
    eff, sl = attitude_reference(model)
    p[sl] = eff.start(rot, model.correct(1, p, data.raw[0], data.context(1)))
    return p


#: sd of the prior an IGRF inclination puts on the fitted one, rad
INCLINATION_PRIOR_SD = np.radians(0.5)


def fit_attitude(data, model, field_nt=None, mode='tilt', inclination_deg=None,
                 **fit_kwargs):
    """
    Fit ``model`` with the attitude observing the field; return an :class:`AttitudeResult`.

    ``data`` (S, N) raw readings, nT, with ``attitude`` (N, 4); ``model`` without the
    attitude; ``field_nt`` nT; ``mode`` 'tilt' or 'full'; ``inclination_deg`` the site's,
    positive down: a prior when ``data.meta['attitude_frame']`` is 'NED' or 'ENU';
    ``fit_kwargs`` go to :func:`magcal_ros.core.model.fitting.fit`.
    """
    if data.attitude is None:
        raise ValueError('the data carry no attitude (att_qw..att_qz, an Imu topic or a '
                         'vehicle log): fit without --attitude, or add it')
    model = with_attitude(model, mode, data.n_sensors)
    f = data.reference_magnitude(field_nt)
    f0 = float(np.mean(f))
    eff, sl = attitude_reference(model)
    info = model.param_info()
    init = fit_kwargs.pop('init', None)
    if init is None and mode == 'full':
        # from the roll and pitch first: the heading's larger error does not pull the start
        tilt = fit_attitude(data, model, field_nt, 'tilt', **dict(fit_kwargs, covariance=False,
                                                                  check_identifiability=False))
        init = model.default_params()
        where = model.param_positions()
        for k, i in tilt.result.model.param_positions().items():
            if k in where:                      # every parameter but the attitude's own
                init[where[k]] = tilt.result.params[i]
        cor = model.correct(1, init, data.raw[0], data.context(1))
        init[sl] = eff.start(data.attitude_matrix(), cor)
        init[sl.stop - 3:sl.stop] = tilt.result.params[-3:]      # the mounting found
    elif init is None:
        init = attitude_start(data, model, f)
    elif len(init) == model.n_params - eff.n_params and sl.stop == model.n_params:
        # the parameters without the attitude's (a calibration in use)
        init = np.concatenate([np.asarray(init, float), np.zeros(eff.n_params)])
        init[sl] = eff.start(data.attitude_matrix(),
                             model.correct(1, init, data.raw[0], data.context(1)))
    if not np.isfinite(eff.sigma_nt):
        eff.sigma_nt = _start_sigma(data, model, init, f)
    fit_kwargs.pop('constrained', None)
    fit_kwargs.setdefault('max_nfev', 1000)
    # the caller's priors (pipeline.refit_recent) instead of the constrained mode's
    own = list(fit_kwargs.pop('extra_priors', None) or [])
    # the compass's mounting against the attitude's frame
    extra = [(i, 0.0, MOUNT_PRIOR_SD_RAD) for i in range(sl.stop - 3, sl.stop)]
    frame = str(data.meta.get('attitude_frame', '')).upper()
    if inclination_deg is not None and frame in ('NED', 'ENU'):
        inc = np.radians(float(inclination_deg)) * (1.0 if frame == 'NED' else -1.0)
        extra.append((sl.start, inc, INCLINATION_PRIOR_SD))
        if init[sl.start] * inc < 0:
            init[sl.start] = inc
    result = fit(data, model, field_nt=field_nt, init=init, constrained=not own,
                 extra_priors=extra + own, **fit_kwargs)
    open_ = prior_held(result, (own or priors_for(model, {}, constrained=True)) + extra)
    result, rho = inflate_for_correlation(result)
    mount = list(range(sl.stop - 3, sl.stop))
    open_ = {i for i in open_ if (info[i][0] and info[i][1] in SENSOR_MAP_KINDS)
             or i in mount}
    undetermined, determined = split_determined(info, open_, mount)
    ang, se = result.params[sl], result.stderr[sl]
    world = {'frame': data.meta.get('attitude_frame', "the attitude's world frame"),
             'inclination_prior': ('IGRF' if len(extra) > 3 else 'none (estimated)' if
                                   inclination_deg is None else
                                   "none: the attitude's world frame is not known to be NED "
                                   'or ENU (the inclination was estimated)'),
             'inclination_deg': float(np.degrees(ang[0])),
             'inclination_stderr_deg': float(np.degrees(se[0])),
             'inclination_open': sorted(u for u in undetermined
                                        if u.split('.', 1)[1] in VERTICAL_PARAMS)}
    if mode == 'full':
        world.update(declination_deg=float(np.degrees(ang[1])),
                     declination_stderr_deg=float(np.degrees(se[1])))
    world['mount_deg'] = [float(v) for v in np.degrees(ang[-3:])]
    world['mount_stderr_deg'] = [float(v) for v in np.degrees(se[-3:])]
    return AttitudeResult(
        result=result, mode=mode, undetermined=undetermined, determined=determined,
        attitude_sd_deg=float(np.degrees(eff.refs.get('white_sigma_nt', eff.sigma_nt) / f0)),
        world_field=world, heading=heading_check(result, data, undetermined),
        residual_correlation=rho)


def prior_held(result, prior_list, ratio=PRIOR_HELD_RATIO):
    """
    Return the set of indices of the parameters the priors, not the data, determine.

    With A the posterior information (of ``result``'s unwidened covariance) and L the priors'
    (1 / sd^2 of ``prior_list``'s (index, mean, sd)), priors twice as strong shrink the
    variance [(A + L)^-1]_ii by more than ``ratio`` (1.25: data information 3 times the
    prior's, docs/planar.md).
    """
    cov = np.asarray(result.covariance, float)
    if not np.all(np.isfinite(cov)):
        return {i for i in range(len(cov)) if not np.isfinite(cov[i, i])}
    lam = np.zeros(len(cov))
    for i, _, sd in prior_list:
        lam[i] += 1.0 / sd ** 2
    d = np.sqrt(np.diag(cov))
    d[d == 0] = 1.0
    # in correlation units, so that nT and rad do not spoil the inverse
    a = np.linalg.inv(cov / np.outer(d, d))
    cov2 = np.linalg.inv(a + np.diag(lam * d * d))
    return {i for i in range(len(cov)) if 1.0 / cov2[i, i] > ratio}


def _start_sigma(data, model, p, f):
    """Return the attitude observation's sd at the start, nT: its residual against sensor 1."""
    eff, sl = attitude_reference(model)
    cor = model.correct(1, p, data.raw[0], data.context(1))
    b = cor / np.linalg.norm(cor, axis=1, keepdims=True) * f[:, None]
    r = eff.residual(p[sl], data.attitude_matrix(), f, b)
    return max(float(np.sqrt(np.mean(np.sum(r * r, axis=1)) / eff.rank)),
               1e-3 * float(np.mean(f)))


def heading_check(result, data, undetermined=()):
    """
    Compare the attitude's heading with the corrected compass's (sensor 1).

    The azimuth of R_k b_k is the heading error plus the declination.  Returns a dict:
    ``offset_deg`` (circular mean), ``offset_determined`` (False when ``undetermined`` holds
    a horizontal offset of sensor 1), ``rms_deg`` (about the mean), ``max_deg``,
    ``disagree`` (``rms_deg`` above :data:`HEADING_DISAGREE_DEG`).
    """
    p = result.params
    cor = result.model.correct(1, p, data.raw[0], data.context(1))
    eff, sl = attitude_reference(result.model)
    cor = cor @ eff.mount(p[sl])            # into the attitude's body frame
    w = np.einsum('nij,nj->ni', data.attitude_matrix(), cor)
    ang = np.arctan2(w[:, 1], w[:, 0])
    mean = np.angle(np.mean(np.exp(1j * ang)))
    dev = np.degrees(np.angle(np.exp(1j * (ang - mean))))
    rms = float(np.sqrt(np.mean(dev ** 2)))
    return {'offset_deg': float(np.degrees(mean)),
            'offset_determined': not HORIZONTAL_OFFSETS & set(undetermined), 'rms_deg': rms,
            'max_deg': float(np.max(np.abs(dev))), 'disagree': rms > HEADING_DISAGREE_DEG}
