"""Can the data determine the model?  Checks run before and after every solve.

Before: attitude coverage of each sensor (:func:`magcal_ros.core.coverage.direction_coverage`):
a rotation about a single axis leaves the field directions on one circle, so the linear map is
not determined along the rotation axis; a partial coverage (a cone, as on a ground vehicle)
makes scale, non-orthogonality and offset strongly correlated.

After: the parameter correlations and the condition number of the correlation matrix from
the projected Jacobian (the Fisher information at the solution).
"""
import numpy as np

from magcal_ros.core.coverage import direction_coverage

#: smallest direction-scatter eigenvalue of a single-axis rotation (noise and wobble only)
SINGLE_AXIS_EIG = 3e-4
#: below this the attitude coverage is partial (about a +-14 deg band or a cap < ~45 deg)
PARTIAL_EIG = 0.02
#: parameter correlations above this make the pair inseparable
MAX_CORRELATION = 0.995
#: condition number of the correlation matrix above which the solution is unreliable
MAX_CONDITION = 1e6


def _sphere_centre(m):
    """Centre (3,) nT of the least-squares sphere |m - o|^2 = r^2, or None if ill-determined."""
    design = np.column_stack([2.0 * m, np.ones(len(m))])
    scale = np.linalg.norm(design, axis=0)
    scale[scale == 0] = 1.0
    sv = np.linalg.svd(design / scale, compute_uv=False)
    if sv[-1] < 1e-6 * sv[0]:
        return None
    sol, *_ = np.linalg.lstsq(design / scale, np.sum(m ** 2, axis=1), rcond=None)
    return sol[:3] / scale[:3]


def coverage_report(raw):
    """Coverage of each sensor's raw field directions.

    Parameters
    ----------
    raw : numpy.ndarray
        (S, N, 3) raw readings in nT.

    Returns
    -------
    dict
        ``sensors``: {j: {eigenvalues, normal, cone_half_angle_deg, status}} with status
        'good', 'partial', 'single axis', 'one attitude' or 'constant' (stuck output),
        ``problems``: list of messages naming the missing rotation (empty when fine),
        ``summary``: one line.
    """
    out = {'sensors': {}, 'problems': []}
    messages = {}
    for j in range(1, raw.shape[0] + 1):
        m = raw[j - 1]
        m = m[np.linalg.norm(m, axis=1) > 0]
        if len(m) < 3:
            messages[j] = f'sensor {j} reported no usable samples: check its cable/port'
            continue
        spread = np.ptp(m, axis=0)
        if not np.any(spread > 0):
            # a stuck sensor (frozen ADC, driver repeating its last value): not an attitude
            # problem, rotating more would not help
            out['sensors'][j] = dict(eigenvalues=[0.0, 0.0, 1.0], normal=[0.0, 0.0, 0.0],
                                     cone_half_angle_deg=0.0, status='constant')
            messages[j] = (f'sensor {j}: output is constant (all {len(m)} samples read '
                           f'({", ".join(f"{x:.1f}" for x in m[0])}) nT): the sensor is stuck or '
                           'not updating; check its power, cable and driver')
            continue
        cov = direction_coverage(m)
        ev = cov.eigenvalues
        n = ', '.join(f'{x:+.2f}' for x in cov.normal)
        if ev[1] < SINGLE_AXIS_EIG:
            status = 'one attitude'
            msg = (f'sensor {j}: all samples have (nearly) the same field direction: rotate the '
                   'array through many attitudes (turn it over, about at least two axes)')
        elif ev[0] < SINGLE_AXIS_EIG:
            status = 'single axis'
            msg = (f'sensor {j}: all field directions lie near one plane with normal ({n}): '
                   'the data come from a rotation about one axis only; rotate about another '
                   'axis too (tilt that axis by 45-90 deg and rotate again)')
        elif ev[0] < PARTIAL_EIG:
            status = 'partial'
            if cov.mean_resultant_length > 0.5:
                msg = (f'sensor {j}: field directions span only a '
                       f'{2 * cov.cone_half_angle_deg:.0f} deg cone around '
                       f'({", ".join(f"{x:+.2f}" for x in cov.mean_direction)}): scale, '
                       'non-orthogonality and offset are poorly separated; turn the array '
                       'over, or use the constrained mode (priors on scale and angles)')
            else:
                msg = (f'sensor {j}: field directions stay within a band around the plane with '
                       f'normal ({n}): tilt the array further out of that plane, or use the '
                       'constrained mode')
        else:
            status = 'good'
            msg = None
        if status == 'partial':
            # a hard-iron offset comparable with the field squeezes the *raw* directions into
            # a cone although the attitudes cover the sphere: judge the directions about the
            # centre of the best-fit sphere when that centre is well determined
            centre = _sphere_centre(m)
            if centre is not None:
                cov_c = direction_coverage(m - centre)
                if cov_c.eigenvalues[0] >= PARTIAL_EIG:
                    cov, ev, status, msg = cov_c, cov_c.eigenvalues, 'good', None
        out['sensors'][j] = dict(eigenvalues=ev.tolist(), normal=cov.normal.tolist(),
                                 cone_half_angle_deg=cov.cone_half_angle_deg, status=status)
        if msg:
            messages[j] = msg
    moved = [j for j, v in out['sensors'].items()
             if v['status'] not in ('one attitude', 'constant')]
    for j, v in out['sensors'].items():
        if v['status'] == 'one attitude' and moved:
            # the array turned (sensor moved[0] saw it) but this sensor's direction did not
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
    """Parameter correlations and conditioning at the solution.

    Parameters
    ----------
    model : Model
    cov, corr : numpy.ndarray
        (P, P) parameter covariance and correlation.

    Returns
    -------
    dict with ``condition_number``, ``max_correlation`` [(name_a, name_b, rho)], ``problems``.
    """
    info = model.param_info()
    names = [f'{e}.{n}@{s}' for s, e, n, _ in info]
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
        # priors bound every parameter; strong posterior correlations are expected then
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
