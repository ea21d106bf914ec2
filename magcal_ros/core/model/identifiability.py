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
Can the data determine the model?  Checks run before and after every solve.

Before: each sensor's attitude coverage about its fitted centre (:func:`check_coverage`);
after: the parameter correlations and their condition number (:func:`jacobian_report`).
"""
from magcal_ros.core.geometry.coverage import direction_coverage, format_vector
from magcal_ros.core.geometry.turn import circle_centre
from magcal_ros.core.papers.ellipsoid import fit_ellipsoid, reading_plane, RING_CV, ring_spread
import numpy as np

#: smallest direction-scatter eigenvalue of a single-axis rotation (noise and wobble only)
SINGLE_AXIS_EIG = 3e-4
#: below this the attitude coverage is partial (about a +-14 deg band or a cap < ~45 deg)
PARTIAL_EIG = 0.02
#: directions on a ring (ellipsoid.RING_CV) spread along its axis below this fraction of
#: the in-plane spread: a rotation about that axis with hand wobble, not a partial coverage
RING_RATIO = 0.015
#: the sphere cross-check applies where the sphere's relative radial residual variance is
#: below this multiple of the ellipsoid's
SPHERE_VAR_FACTOR = 4.0
#: an ellipsoid whose axis ratio exceeds this is bent to a cap: its centre is not used
MAX_AXIS_RATIO = 1.6
#: readings scattered radially by more than this fraction of the radius fill a cloud
MAX_RADIAL_SCATTER = 0.25
#: parameter correlations above this make the pair inseparable
MAX_CORRELATION = 0.995
#: condition number of the correlation matrix above which the solution is unreliable
MAX_CONDITION = 1e6


def fitted_centre(m):
    """
    Fit the ellipsoid of one sensor's readings ``m`` (N, 3) nT; None when not determined.

    Returns (centre (3,) nT (paper 004 eq. 12), var(radial residual / radius), longest over
    shortest axis), or None: no ellipsoid, or a cloud (:data:`MAX_RADIAL_SCATTER`).
    """
    try:
        ell = fit_ellipsoid(m, 1.0)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if np.std(ell.residual_nt) > MAX_RADIAL_SCATTER:
        return None
    axes = np.linalg.svd(ell.c_inv, compute_uv=False)
    return ell.b, float(np.var(ell.residual_nt)), float(axes[0] / axes[-1])


def _single_axis_message(normal, how):
    axis = format_vector(normal, '+')
    return (f'all field directions lie near one plane with normal {axis} ({how}): the data '
            f'come from a rotation about one axis only, about {axis} in the sensor frame; '
            'rotate about another axis too (tilt that axis by 45-90 deg and rotate again)')


def classify_coverage(m):
    """
    Attitude coverage of one sensor's readings ``m`` (N, 3) nT, judged about the fitted centre.

    Returns a dict: ``status`` ('good', 'partial', 'single axis', 'one attitude'),
    ``eigenvalues`` (3,) less the noise's, ``normal`` (3,) sensor frame,
    ``cone_half_angle_deg``, ``centre_nt`` (3,) or None, ``message`` (None when good).
    """
    fitted = fitted_centre(m)
    noise_eig = 0.0
    if fitted is not None:
        centre, noise_eig, axis_ratio = fitted
        if axis_ratio > MAX_AXIS_RATIO:
            centre = circle_centre(m)           # the sphere's centre instead
    else:
        # no ellipsoid: did the sensor turn at all (about the origin), on a ring?
        plane = reading_plane(m)
        cov = direction_coverage(m)
        ev = cov.eigenvalues
        found = {'eigenvalues': ev, 'normal': cov.normal, 'centre_nt': None, 'message': None,
                 'cone_half_angle_deg': cov.cone_half_angle_deg}
        if plane is not None:
            return dict(found, status='single axis', normal=plane, message=_single_axis_message(
                plane, 'the readings are too flat to fit an ellipsoid'))
        if ev[1] < SINGLE_AXIS_EIG or ev[2] < PARTIAL_EIG:
            return dict(found, status='one attitude')
        # turned, no ellipsoid: judge about the sphere's centre (not the arbitrary origin)
        centre = circle_centre(m)
    out = _judge(m, centre, noise_eig)
    if out['status'] == 'good' and fitted is not None and axis_ratio <= MAX_AXIS_RATIO:
        # cross-check about the sphere's centre (stable on a cap), where a sphere fits
        sphere = circle_centre(m)
        rad = np.linalg.norm(m - sphere, axis=1)
        if np.var(rad / np.median(rad)) < SPHERE_VAR_FACTOR * max(noise_eig, 1e-12):
            other = _judge(m, sphere, noise_eig)
            if other['status'] != 'good':
                out = other
    return out


def _judge(m, centre, noise_eig):
    """Coverage status of the readings m (N, 3) nT judged about ``centre`` (3,) nT."""
    cov = direction_coverage(m - centre)
    ev = np.clip(cov.eigenvalues - noise_eig, 0.0, None)
    out = {'eigenvalues': ev, 'normal': cov.normal, 'cone_half_angle_deg': cov.cone_half_angle_deg,
           'centre_nt': centre, 'message': None}
    if ev[2] < PARTIAL_EIG or ev[1] < SINGLE_AXIS_EIG:
        out['status'] = 'one attitude'
    elif (ev[0] < max(SINGLE_AXIS_EIG, RING_RATIO * ev[1]) and ring_spread(
            (m - centre) / np.linalg.norm(m - centre, axis=1)[:, None], cov.normal) < RING_CV):
        out['status'] = 'single axis'
        out['message'] = _single_axis_message(
            cov.normal, f'spread {np.sqrt(ev[0]):.3f} along it against '
                        f'{np.sqrt(ev[1]):.3f} within the plane, about the fitted centre')
    elif ev[0] < PARTIAL_EIG:
        out['status'] = 'partial'
    else:
        out['status'] = 'good'
    return out


def check_coverage(raw):
    """
    Coverage of each sensor's field directions (:func:`classify_coverage`), ``raw`` (S, N, 3) nT.

    Returns a dict: ``sensors`` {j: {eigenvalues, normal, cone_half_angle_deg, status (or
    'constant': stuck)}}, ``problems`` (messages; empty when fine), ``summary`` (one line).
    """
    out = {'sensors': {}, 'problems': []}
    messages = {}
    for j, m in enumerate(raw, 1):
        m = m[np.linalg.norm(m, axis=1) > 0]
        if len(m) < 3:
            messages[j] = f'sensor {j} reported no usable samples: check its cable/port'
            continue
        if not np.any(np.ptp(m, axis=0) > 0):
            out['sensors'][j] = {'eigenvalues': [0.0, 0.0, 1.0], 'normal': [0.0, 0.0, 0.0],
                                 'cone_half_angle_deg': 0.0, 'status': 'constant'}
            messages[j] = (f'sensor {j}: output is constant (all {len(m)} samples read '
                           f'({", ".join(f"{x:.1f}" for x in m[0])}) nT): the sensor is stuck or '
                           'not updating; check its power, cable and driver')
            continue
        c = classify_coverage(m)
        ev, status = c['eigenvalues'], c['status']
        n = ', '.join(f'{x:+.2f}' for x in c['normal'])
        if status == 'one attitude':
            messages[j] = (f'sensor {j}: all samples have (nearly) the same field direction '
                           f'(within a {c["cone_half_angle_deg"]:.0f} deg cone): the sensor '
                           'hardly turned, or turned only about the field; rotate the array '
                           'through many attitudes (turn it over, about at least two axes)')
        elif status == 'single axis':
            messages[j] = f'sensor {j}: {c["message"]}'
        elif status == 'partial':
            cov_dir = direction_coverage(m - c['centre_nt'])
            if cov_dir.mean_resultant_length > 0.5:
                messages[j] = (f'sensor {j}: field directions span only a '
                               f'{2 * c["cone_half_angle_deg"]:.0f} deg cone around '
                               f'({", ".join(f"{x:+.2f}" for x in cov_dir.mean_direction)}) '
                               'about the fitted centre: scale, non-orthogonality and offset '
                               'are poorly separated; turn the array over, or use the '
                               'constrained mode (--constrained: priors on scale and angles)')
            else:
                messages[j] = (f'sensor {j}: field directions stay within a band around the '
                               f'plane with normal ({n}), i.e. mostly a rotation about ({n}) in '
                               'the sensor frame: tilt that axis further, or use the '
                               'constrained mode (--constrained)')
        out['sensors'][j] = {'eigenvalues': [float(x) for x in ev],
                             'normal': [float(x) for x in c['normal']],
                             'cone_half_angle_deg': float(c['cone_half_angle_deg']),
                             'status': status}
    moved = [j for j, v in out['sensors'].items()
             if v['status'] not in ('one attitude', 'constant')]
    for j, v in out['sensors'].items():
        if v['status'] == 'one attitude' and moved:
            spread = float(np.max(np.ptp(raw[j - 1], axis=0)))
            v['status'] = 'constant'
            messages[j] = (f'sensor {j}: output (nearly) constant (spread {spread:.1f} nT) '
                           f'while sensor {moved[0]} saw the array turn: the sensor is stuck, '
                           'saturated or not following the array; check it')
    out['problems'] = [messages[j] for j in sorted(messages)]
    out['summary'] = (out['problems'][0] if out['problems']
                      else 'attitude coverage is adequate for every sensor')
    return out


def jacobian_report(model, cov, corr, constrained=False):
    """
    Parameter correlations and conditioning of ``model``'s (P, P) ``cov`` and ``corr``.

    Returns a dict: ``condition_number``, ``max_correlation`` [(name_a, name_b, rho)],
    ``problems`` (``constrained``: the correlations are ``notes`` instead).
    """
    names = [f'{e}.{n}@{s}' for s, e, n, _ in model.param_info()]
    out = {'problems': []}
    ok = np.isfinite(np.diag(cov)) & (np.diag(cov) > 0)
    if ok.sum() == 0:
        out.update(condition_number=float('inf'), max_correlation=[])
        return out
    c = corr[np.ix_(ok, ok)]
    sv = np.linalg.svd(c, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float('inf')
    out['condition_number'] = cond
    idx = np.flatnonzero(ok)
    tri = np.triu(np.abs(c), 1)
    order = np.dstack(np.unravel_index(np.argsort(-tri, axis=None)[:5], tri.shape))[0]
    top = [(names[idx[a]], names[idx[b]], float(c[a, b])) for a, b in order if tri[a, b] > 0]
    out['max_correlation'] = top
    if constrained:
        out['notes'] = [f'{a} ~ {b}: correlation {rho:+.4f}' for a, b, rho in top[:3]]
    elif top and abs(top[0][2]) > MAX_CORRELATION:
        a, b, rho = top[0]
        out['problems'].append(
            f'parameters {a} and {b} are correlated at {rho:+.4f}: the data cannot separate '
            'them; add attitudes that excite them differently, drop one of the effects, '
            'or use the constrained mode')
    elif cond > MAX_CONDITION:
        out['problems'].append(
            f'the problem is ill-conditioned (condition number {cond:.3g} of the parameter '
            'correlation matrix): add attitudes or simplify the model')
    unexc = [names[i] for i in np.flatnonzero(~ok)]
    if unexc:
        out['problems'].append(f'parameters not determined by the data: {", ".join(unexc)}')
    return out
