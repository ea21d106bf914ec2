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
Calibration run shared by the `magcal` command line and the calibration node (no rclpy).

Both build a :class:`CalibrationRequest`, run it with :func:`run_request` (the fit, its
before/after figures and the calibration document of docs/design.md §4) and print
:func:`summary_lines`.
"""
from dataclasses import dataclass, fields

from magcal_ros.core.data.noise import data_noise_floor
from magcal_ros.core.effects.attitude_ref import MOUNT_PRIOR_SD_RAD
from magcal_ros.core.geometry.tensor import (cross_positions, gradient_from_fit, tensor_lstsq,
                                             tensor_noise_floor)
from magcal_ros.core.model import data_hash, fit, Model
from magcal_ros.core.model.notes import format_note, Note, note_dict
from magcal_ros.core.model.plausibility import (axis_maps, fitted_scales_angles,
                                                mounting_notes, parameter_notes, with_axis_maps)
from magcal_ros.core.model.site_gradient import centred_fields
from magcal_ros.io.calfile import calibration_to_doc
import numpy as np


def cross_geometry(baseline_m=0.5):
    """Geometry dict of paper 004's cross (positions in m)."""
    return {'type': 'cross', 'baseline_m': float(baseline_m),
            'positions_m': cross_positions(baseline_m).tolist()}


def geometry_positions(geometry, n_sensors):
    """(S, 3) positions in m, or None when the geometry is unknown."""
    if not geometry or 'positions_m' not in geometry:
        return None
    pos = np.asarray(geometry['positions_m'], float)
    if pos.shape != (n_sensors, 3):
        raise ValueError(f'geometry has {len(pos)} positions for {n_sensors} sensors')
    return pos


def array_geometry(n_sensors, positions_m=(), baseline_m=0.5):
    """
    Geometry dict of an array from node parameters (docs/design.md §7).

    ``positions_m``: flat x, y, z per sensor, m (3 S values); empty: paper 004's cross of
    ``baseline_m`` (m) for four sensors, the origin for one, None (no tensor) otherwise.
    Returns a :func:`cross_geometry` or ``{'type': 'positions', 'positions_m'}`` ((S, 3) m
    lists). Raises ValueError naming the count expected unless 3 finite numbers per sensor.
    """
    flat = np.asarray(list(positions_m), float)
    if flat.size == 0:
        if n_sensors == 4:
            return cross_geometry(baseline_m)
        if n_sensors == 1:
            return {'type': 'positions', 'positions_m': [[0.0, 0.0, 0.0]]}
        return None
    if flat.size != 3 * n_sensors or not np.all(np.isfinite(flat)):
        raise ValueError(f'sensor_positions_m must hold 3 finite numbers (x y z, m) per '
                         f'sensor: {3 * n_sensors} for {n_sensors} sensors, got {flat.size}')
    return {'type': 'positions', 'positions_m': flat.reshape(-1, 3).tolist()}


def tensor_undetermined(positions):
    """Why sensors at ``positions`` (S, 3) m (not spanning a plane) give no tensor, or None."""
    if positions is None:
        return ('no sensor positions (give sensor_positions_m, x y z per sensor in m): the '
                'gradient tensor is not computed')
    pos = np.asarray(positions, float)
    if len(pos) == 1:
        return 'one sensor measures no field difference: there is no gradient tensor'
    sv = np.linalg.svd(pos - pos.mean(axis=0), compute_uv=False)
    if sv[0] <= 1e-9:
        return (f'the {len(pos)} sensors are at one point: they measure no field '
                'difference, there is no gradient tensor')
    if len(sv) < 2 or sv[1] <= 1e-9 * sv[0]:
        return (f'the {len(pos)} sensors are collinear: they measure the derivatives along '
                'their line only, not the full gradient tensor (it needs sensors spanning a '
                'plane)')
    return None


def geometry_mismatch(file_geometry, node_geometry, tol_m=1e-6):
    """Why a file's ``positions_m`` (S, 3) m differ from the node's; None: equal or not known."""
    if not node_geometry or not file_geometry or 'positions_m' not in file_geometry:
        return None
    a = np.asarray(file_geometry['positions_m'], float)
    b = np.asarray(node_geometry['positions_m'], float)
    if a.shape == b.shape and np.all(np.abs(a - b) <= tol_m):
        return None
    return (f'its geometry (positions_m {np.round(a, 4).tolist()} m) differs from this '
            f"node's (sensor_positions_m {np.round(b, 4).tolist()} m): calibrate this array, "
            'or set sensor_positions_m (or baseline_m) to the geometry of the file')


def tensor_stats(fields, positions):
    """Return the tensor's rms and max_abs_dev ((3, 3) nT/m) of ``fields`` (S, N, 3) nT."""
    g, _ = tensor_lstsq(fields, positions)
    dev = g - g.mean(axis=0)
    return {'rms': np.sqrt(np.mean(dev ** 2, axis=0)), 'max_abs_dev': np.abs(dev).max(axis=0)}


@dataclass
class CalibrationRun:
    """A fit with its summary figures and calibration document."""

    result: object
    summary: dict
    doc: dict


#: a sensor's fitted noise above this multiple of the data's own noise floor is reported
RESIDUAL_WARN_RATIO = 1.5
#: ... and above this multiple of the floor (or of the raw readings'), as a failed fit
GROSS_RATIO = 100.0


def _residual_warnings(result, floor):
    """
    Warnings (:class:`Note`) on the fit's ``sigma_nt`` (S,) nT against the data's ``floor``.

    A complete fit meets the floor; far above it, an effect is missing or the data are
    inconsistent. A filtered series (a lower bound of its floor only) gets a ``noise_floor``
    warning instead of "N x the floor".
    """
    out = []
    for j, (sig, fl) in enumerate(zip(result.sigma_nt, floor.per_sensor_nt), start=1):
        if floor.status[j - 1] == 'filtered':
            out.append(Note(floor.describe(j) + '; the residual cannot be compared with it',
                            'noise_floor', j))
            continue
        gross = _gross_note(j, sig, fl, floor.raw_nt[j - 1])
        if gross is not None:
            out.append(gross)
            continue
        if floor.status[j - 1] == 'upper bound':
            out.append(Note(floor.describe(j), 'noise_floor', j))
        if np.isfinite(sig) and np.isfinite(fl) and fl > 0 and sig > RESIDUAL_WARN_RATIO * fl:
            out.append(Note(f'sensor {j}: the model leaves {sig:.1f} nT of residual per axis, '
                            f'{sig / fl:.1f} x the noise floor of its data ({fl:.2f} nT): an '
                            'effect is missing (run diagnose) or the data are inconsistent',
                            'missing_effect', j))
    return out


def _lower_floor(*floors):
    """Return the lowest finite positive floor of ``floors`` (nT), nan when there is none."""
    ok = [float(x) for x in floors if np.isfinite(x) and x > 0]
    return min(ok) if ok else float('nan')


def _gross_note(j, sig, fl, raw_fl):
    """
    Return a warning when sensor ``j``'s residual sd ``sig`` is far above its floor, or None.

    The lower of ``fl`` and ``raw_fl`` (from the raw readings' differences, which no diverged
    fit inflates) decides, nT.
    """
    ref = _lower_floor(fl, raw_fl)
    if not (np.isfinite(sig) and np.isfinite(ref)) or sig <= GROSS_RATIO * ref:
        return None
    ratio = sig / ref
    return Note(f'sensor {j}: the model leaves {sig:.3g} nT of residual per axis, {ratio:.3g} x '
                f'({np.log10(ratio):.1f} orders of magnitude above) the noise floor of its data '
                f'({ref:.3g} nT): the fit failed (a term that diverged or data the model cannot '
                'describe); do not use this calibration: fit a simpler model, run diagnose',
                'missing_effect', j)


def fit_warnings(result, floor):
    """List every warning on a fit as ``{kind, sensor, text}``: its own and its residual's."""
    return [note_dict(w) for w in list(result.warnings) + _residual_warnings(result, floor)]


def summarize(result, data, positions=None):
    """
    Before/after figures of a fit (nT, nT/m), JSON-ready; ``warnings`` ``{kind, sensor, text}``.

    The noise floor is :func:`~magcal_ros.core.data.noise.data_noise_floor`'s; the tensor
    floor is propagated from it, not from the fit's sigma (which a missing effect inflates).
    """
    f = result.field_magnitude_nt
    raw_tot = np.linalg.norm(data.raw, axis=2) - f[None]
    cor_tot = result.scalar_residual_nt
    kept = getattr(result, 'reading_mask', None)
    if kept is not None:
        # the readings a drop() leaves out are in neither the before nor the after
        raw_tot = [r[k] for r, k in zip(raw_tot, kept)]
        cor_tot = np.concatenate([r[k] for r, k in zip(cor_tot, kept)])
    floor = data_noise_floor(data, result)
    s = {
        'model': result.model.spec(),
        'n_samples': int(data.n_samples),
        'n_fit_samples': int(result.n_fit_samples),
        'converged': bool(result.success),
        'solver_message': str(result.message),
        **floor.to_dict(),
        'sigma_nt': {str(j + 1): float(x) for j, x in enumerate(result.sigma_nt)},
        'scalar_rms_nt': {str(k): v for k, v in result.scalar_rms_nt.items()},
        'vector_rms_nt': {str(k): v for k, v in result.vector_rms_nt.items()},
        'total_field_rms_before_nt': {str(j + 1): float(np.sqrt(np.mean(r ** 2)))
                                      for j, r in enumerate(raw_tot)},
        'total_field_max_dev_before_nt': float(max(np.abs(r).max() for r in raw_tot)),
        'total_field_max_dev_after_nt': float(np.abs(cor_tot).max()),
        'downweighted': {str(j + 1): int(x) for j, x in enumerate(result.downweighted)},
        'warnings': fit_warnings(result, floor),
    }
    for j, r in enumerate(raw_tot, start=1):
        # worse than no calibration, beyond the scatter of two RMS at the floor
        before, after = float(np.sqrt(np.mean(r ** 2))), result.scalar_rms_nt.get(j)
        if after is not None and np.isfinite(before) and not (
                after <= 1.1 * before or after <= RESIDUAL_WARN_RATIO * _lower_floor(
                    floor.per_sensor_nt[j - 1], floor.raw_nt[j - 1])):
            s['warnings'].append(note_dict(Note(
                f'sensor {j}: the calibrated total field deviates more than the raw readings '
                f'do ({after:.3g} nT RMS after, {before:.3g} nT before): this calibration '
                'makes the sensor worse; do not use it (fit a simpler model, run diagnose)',
                'missing_effect', j)))
    site = gradient_from_fit(result.model, result.params, result.covariance)
    if site is not None:
        # world frame of the attitude (NED or ENU, the user's); standard uncertainties
        s['site_gradient_nt_per_m'] = site[0].tolist()
        s['site_gradient_stderr_nt_per_m'] = site[1].tolist()
        s['site_gradient_frame'] = result.identifiability.get(
            'site_gradient_frame', "world (the attitude's)")
    if positions is not None and tensor_undetermined(positions) is None:
        # on the sets every sensor keeps (a drop() leaves a reading out: no tensor there)
        sets = slice(None) if kept is None else np.flatnonzero(kept.all(axis=0))
        before = tensor_stats(data.raw[:, sets], positions)
        # about the modelled site gradient: what is left is calibration error and noise
        after = tensor_stats(centred_fields(result)[:, sets], positions)
        floor_t = tensor_noise_floor(floor.per_sensor_nt, positions)
        s['tensor_rms_nt_per_m'] = after['rms'].tolist()
        s['tensor_rms_before_nt_per_m'] = before['rms'].tolist()
        s['tensor_max_dev_before_nt_per_m'] = float(before['max_abs_dev'].max())
        s['tensor_max_dev_after_nt_per_m'] = float(after['max_abs_dev'].max())
        s['tensor_floor_nt_per_m'] = floor_t.tolist()
    return s


#: sets whose residual exceeds this many robust standard deviations are outliers
OUTLIER_SIGMAS = 5.0
#: at most this fraction of the sets is excluded as outliers; more is a model problem
MAX_OUTLIER_FRACTION = 0.05


@dataclass
class CalibrationRequest:
    """
    One calibration asked for (``magcal fit``'s options, the calibration node's parameters).

    ``model``: effects (``'base,temperature@2'``) or a Model; ``field_nt``: reference
    magnitude, nT, scalar or (N,) (None: ``data.ref_total``); ``field_reference``: how it
    was obtained (its IGRF ``inclination_deg`` is the planar and attitude-aided fits'
    inclination); ``geometry``: ``positions_m`` (S, 3) m (None: paper 004's cross for four
    sensors); ``attitude``: one of :data:`ATTITUDE_MODES`; ``planar``: a turn about one axis
    (wins over ``heading_unknown``: site gradient without attitude); ``prior_params`` (P,):
    the planar prior (None: an ideal sensor); ``robust``, ``constrained``: as for
    :func:`magcal_ros.core.model.fit`; ``exclude_outliers`` as for :func:`calibrate`;
    ``on_degenerate``: 'raise' or 'flag'.
    """

    model: object = 'base'
    field_nt: object = None
    field_reference: dict = None
    geometry: dict = None
    attitude: str = 'auto'
    planar: bool = False
    prior_params: object = None
    heading_unknown: bool = False
    robust: bool = False
    constrained: bool = False
    exclude_outliers: bool = False
    on_degenerate: str = 'raise'


def run_request(data, request, screen=True, **fit_kwargs):
    """Run a :class:`CalibrationRequest` on ``data`` (S, N, 3) nT, as :func:`calibrate` says."""
    if not screen:
        return _calibrate_clean(data, request, request.field_nt, fit_kwargs)
    from magcal_ros.core.data.readings import leave_out_unphysical, ReadingScreen
    if isinstance(screen, ReadingScreen):
        found, field_nt = screen, request.field_nt       # left out by the caller already
    else:
        data, field_nt, found = leave_out_unphysical(data, request.field_nt)
    run = _calibrate_clean(data, request, field_nt, fit_kwargs)
    left_out, notes = found.to_dict(), [note_dict(w) for w in found.notes()]
    for d in (run.summary, run.doc['provenance']):
        d['readings_left_out'] = left_out
        d['warnings'][:0] = notes
    return run


def calibrate(data, model='base', field_nt=None, geometry=None, field_reference=None,
              exclude_outliers=False, screen=True, **options):
    """
    Fit ``model`` to ``data`` (Dataset, (S, N, 3) nT): a CalibrationRun.

    ``model``, ``field_nt``, ``geometry`` (default: the cross of 0.5 m for four sensors) and
    ``field_reference`` as in :class:`CalibrationRequest`.

    ``exclude_outliers``: when the least-squares fit leaves a sensor above 1.5 x its noise
    floor, fit with the soft-L1 loss; if the sets beyond :data:`OUTLIER_SIGMAS` of its noise
    are at most :data:`MAX_OUTLIER_FRACTION` of all, fit by least squares without them
    (garbage costs those sets only; a missing effect is left to diagnose). The summary gives
    ``outlier_sets_excluded``.

    ``screen``: first leave out the sets with readings no field produces
    (:func:`magcal_ros.core.data.readings.leave_out_unphysical`; ``readings`` warnings and
    ``readings_left_out``; too few left raises a ValueError). A ReadingScreen: the caller
    left its sets out already; it is reported.

    ``**options``: a :class:`CalibrationRequest`'s mode and options (``attitude``,
    ``planar``, ``prior_params``, ``heading_unknown``, ``robust``, ``constrained``,
    ``on_degenerate``); any other keyword goes to :func:`magcal_ros.core.model.fit`.
    """
    mode = {f.name: options.pop(f.name) for f in fields(CalibrationRequest) if f.name in options}
    return run_request(data, CalibrationRequest(
        model=model, field_nt=field_nt, field_reference=field_reference, geometry=geometry,
        exclude_outliers=exclude_outliers, **mode), screen=screen, **options)


def _calibrate_clean(data, request, field_nt, fit_kwargs):
    run = _calibrate(data, request, request.model, field_nt, fit_kwargs)
    if (not request.exclude_outliers or request.robust or request.heading_unknown
            or request.planar):
        return run
    if not [w for w in run.summary['warnings'] if w['kind'] == 'missing_effect']:
        run.summary['outlier_sets_excluded'] = 0
        return run
    from magcal_ros.core.effects.attitude_ref import attitude_reference
    # an attitude-aided fit's model: with its priors (core/model/attitude_fit.py)
    kw = dict(fit_kwargs, constrained=request.constrained
              or attitude_reference(run.result.model) is not None)
    rob = fit(data, run.result.model, field_nt=field_nt,
              **dict(kw, robust=True, check_identifiability=False, on_degenerate='flag'))
    z = np.abs(rob.residual_nt) / rob.sigma_nt[:, None, None]
    if rob.reading_mask is not None:
        z = z * rob.reading_mask[:, :, None]        # a reading a drop() leaves out: no outlier
    bad = (z > OUTLIER_SIGMAS).any(axis=(0, 2))
    n_bad = int(bad.sum())
    if n_bad == 0 or n_bad > MAX_OUTLIER_FRACTION * data.n_samples:
        run.summary['outlier_sets_excluded'] = 0
        if n_bad:
            run.summary['warnings'].append(note_dict(Note(
                f'{n_bad} of {data.n_samples} sets are beyond {OUTLIER_SIGMAS:g} sigma of a '
                'robust fit: too many for garbage, kept (a missing effect? run diagnose)',
                'outliers')))
        return run
    keep = np.flatnonzero(~bad)
    f_keep = field_nt if field_nt is None or np.ndim(field_nt) == 0 else \
        np.asarray(field_nt)[keep]
    spec = Model.from_spec(run.result.model.spec(), data.n_sensors)
    clean = _calibrate(data.subset(keep), request, spec, f_keep, fit_kwargs)
    clean.summary['outlier_sets_excluded'] = n_bad
    excluded = note_dict(Note(
        f'{n_bad} of {data.n_samples} sets excluded: beyond {OUTLIER_SIGMAS:g} sigma of a '
        'robust fit (garbled samples or mis-paired sets); fitted on the rest', 'outliers'))
    clean.summary['warnings'].append(excluded)
    clean.doc['provenance']['warnings'].append(excluded)
    return clean


def _adopt_axis_maps(result, data, field_nt, positions, fit_kwargs):
    """Refit with the axis maps a mis-mounted sensor needs: (result, ``mounting`` notes)."""
    maps = axis_maps(result.model, result.params)
    if not maps:
        return result, []
    model = with_axis_maps(result.model, maps)
    if positions is not None:
        model.set_positions(positions)
    refit = fit(data, model, field_nt=field_nt, **fit_kwargs)
    before = fitted_scales_angles(result.model, result.params)
    after = fitted_scales_angles(refit.model, refit.params)
    return refit, mounting_notes(maps, before, after, data.n_sensors)


#: values of the ``attitude`` option: 'auto' uses the roll and pitch when the data carry an
#: attitude (a vehicle's heading usually comes from the compass being calibrated)
ATTITUDE_MODES = ('auto', 'tilt', 'full', 'off')


def attitude_mode(option, data):
    """
    Return the attitude mode a fit of ``data`` uses: 'tilt', 'full' or None (magnitude only).

    ``option``: one of :data:`ATTITUDE_MODES` or None ('auto'); raises ValueError for 'tilt'
    or 'full' on data without attitude.
    """
    option = option or 'auto'
    if option not in ATTITUDE_MODES:
        raise ValueError(f"attitude must be one of {', '.join(ATTITUDE_MODES)}, got {option!r}")
    if option == 'off' or (option == 'auto' and data.attitude is None):
        return None
    if data.attitude is None:
        raise ValueError(f'attitude {option}: the data carry no attitude (CSV columns '
                         'att_qw..att_qz, a sensor_msgs/Imu topic, a vehicle log); give '
                         'one or fit without it (--attitude off)')
    return 'tilt' if option == 'auto' else option


def diagnosis_base(data, model, field_nt, attitude=None, inclination_deg=None, robust=False,
                   constrained=False, on_degenerate='raise'):
    """
    Return (base fit, constrained, attitude summary or None): the fit a diagnosis starts from.

    With an attitude (:func:`attitude_mode`) the attitude-aided fit, whose priors then hold
    what the motion leaves open in every fit of the diagnosis (``constrained`` True).
    """
    mode = attitude_mode(attitude, data)
    if mode is None:
        return (fit(data, model, field_nt=field_nt, robust=robust, constrained=constrained,
                    on_degenerate=on_degenerate), constrained, None)
    from magcal_ros.core.model.attitude_fit import fit_attitude
    aided = fit_attitude(data, model, field_nt=field_nt, mode=mode, robust=robust,
                         inclination_deg=inclination_deg, on_degenerate='flag')
    return aided.result, True, attitude_summary(aided, data)


def attitude_summary(aided, data):
    """JSON-ready account of an attitude-aided fit (deg, nT as named)."""
    return {'mode': aided.mode,
            'trusted': 'roll and pitch' if aided.mode == 'tilt' else 'roll, pitch and heading',
            'source': data.meta.get('attitude_source', 'the data'),
            'attitude_sd_deg': aided.attitude_sd_deg,
            'world_field': aided.world_field,
            'heading_check': aided.heading,
            'determined': list(aided.determined),
            'undetermined': list(aided.undetermined),
            'residual_lag1_correlation': [float(r) for r in aided.residual_correlation]}


#: a fitted mounting angle beyond this (3 prior sds), deg: compass and attitude conflict
MOUNT_CONFLICT_DEG = 3.0 * float(np.degrees(MOUNT_PRIOR_SD_RAD))


def attitude_notes(aided):
    """Warnings (note dicts) of an attitude-aided fit: what is open, a heading at odds."""
    out = []
    if aided.undetermined:
        out.append({'kind': 'undetermined', 'text': (
            "the motion leaves these parameters open; they are held at an ideal sensor's "
            'value within the prior (tilt or turn the vehicle more to determine them): '
            + ', '.join(aided.undetermined))})
    h = aided.heading
    inplane = {'offset.bx@1', 'offset.by@1', 'scale.kx@1', 'scale.ky@1'}
    if h['disagree'] and inplane & set(aided.undetermined):
        out.append({'kind': 'attitude', 'text': (
            f"the attitude's heading and the corrected compass differ by {h['rms_deg']:.1f} "
            'deg RMS, but the horizontal map of sensor 1 is undetermined: the comparison '
            'says nothing of the attitude until the calibration is determined')})
    elif h['disagree']:
        out.append({'kind': 'attitude', 'text': (
            f"the attitude's heading and the corrected compass disagree by {h['rms_deg']:.1f} "
            f"deg RMS (largest {h['max_deg']:.1f} deg) about a constant {h['offset_deg']:.1f} "
            'deg: the heading in the log may come from this compass (before this calibration), '
            'or the attitude lags the compass; the fit trusted '
            + ('roll and pitch only' if aided.mode == 'tilt' else 'the heading too: '
               'try --attitude tilt'))})
    far = [f'{ax} {v:+.0f}' for ax, v in zip('xyz', aided.world_field['mount_deg'])
           if abs(v) > MOUNT_CONFLICT_DEG]
    if far:
        out.append({'kind': 'attitude', 'text': (
            f"the compass's mounting against the attitude comes out {', '.join(far)} deg, "
            f'beyond {MOUNT_CONFLICT_DEG:.0f} deg (3 x its prior sd): the compass is not in '
            'the body frame the log states (check its rotation setting), or the compass and '
            'the attitude disagree on where the field points (a field the vehicle bends, '
            'axes mixed up); the inclination and the calibration rest on that mounting')})
    return out


def _calibrate(data, request, model, field_nt, fit_kwargs):
    """Fit ``model`` in the request's mode; the summary and document (a CalibrationRun)."""
    geometry = request.geometry
    if geometry is None and data.n_sensors == 4:
        geometry = cross_geometry(0.5)
    if not isinstance(model, Model):
        model = Model.from_spec(model, data.n_sensors)
    positions = geometry_positions(geometry, data.n_sensors)
    if positions is not None:
        model.set_positions(positions)          # where the site gradient acts
    mounting = []
    option = request.attitude
    if request.planar or request.heading_unknown:
        # planar and heading-unknown are their own answers to a partial motion
        if option not in (None, 'auto', 'off'):
            raise ValueError(f'attitude {option} goes with neither planar nor heading_unknown: '
                             'choose one')
        option = 'off'
    attitude = attitude_mode(option, data)
    inclination = (request.field_reference or {}).get('inclination_deg')
    kw = dict(fit_kwargs, robust=request.robust)
    aided = pr = None
    if attitude is not None:
        # a vehicle: the attitude observes the field's direction (core/model/attitude_fit.py)
        from magcal_ros.core.model.attitude_fit import fit_attitude
        aided = fit_attitude(data, model, field_nt=field_nt, mode=attitude,
                             inclination_deg=inclination, on_degenerate='flag',
                             constrained=request.constrained, **kw)
        result = aided.result
    elif request.planar:
        # a turn about one axis (a ground robot): what it determines, the rest at a prior
        from magcal_ros.core.model import planar as pl
        pr = pl.fit_planar(data, model, data.reference_magnitude(field_nt),
                           prior_params=request.prior_params, inclination_deg=inclination,
                           **kw)
        result = pr.result
    else:
        kw.update(constrained=request.constrained, on_degenerate=request.on_degenerate)
        if request.heading_unknown:
            # site gradient without attitude: the heading about the field per epoch
            from magcal_ros.core.model.site_gradient import fit_heading_unknown
            result = fit_heading_unknown(data, model, field_nt=field_nt, **kw)
        else:
            result = fit(data, model, field_nt=field_nt, **kw)
            result, mounting = _adopt_axis_maps(result, data, field_nt, positions, kw)
    summary = summarize(result, data, positions)
    if pr is not None:
        summary['planar'] = pl.planar_summary(pr)
        summary['planar']['inclination_source'] = (
            'IGRF' if inclination is not None else 'the fitted field')
        summary['undetermined'] = summary['planar']['undetermined']
        summary['heading_error_deg'] = max(summary['planar']['heading_error_deg'].values())
        summary['warnings'].extend(note_dict(n) for n in pl.planar_notes(pr))
    if aided is not None:
        summary['attitude'] = attitude_summary(aided, data)
        summary['undetermined'] = list(aided.undetermined)
        summary['warnings'].extend(note_dict(n) for n in attitude_notes(aided))
    if pr is None and aided is None:   # these hold what the motion leaves open at a prior
        summary['warnings'] += [note_dict(w) for w in mounting + parameter_notes(
            result.model, result.params, data.raw, float(np.mean(result.field_magnitude_nt)))]
    temp_range = {} if data.temp is None else {
        str(j + 1): [float(np.nanmin(data.temp[j])), float(np.nanmax(data.temp[j]))]
        for j in range(data.n_sensors) if np.isfinite(data.temp[j]).any()}
    ident = result.identifiability
    prov = {
        'samples': int(data.n_samples),
        'fit_samples': int(result.n_fit_samples),
        'data_hash': 'sha256:' + data_hash(data),
        'source': str(data.meta.get('source', 'live')),
        'temperature_range_c': temp_range,
        'attitude_coverage': {str(j): {'status': v['status'],
                                       'eigenvalues': [float(x) for x in v['eigenvalues']]}
                              for j, v in ident.get('sensors', {}).items()},
        'condition_number': float(ident.get('condition_number', float('nan'))),
        'residuals': {k: summary[k] for k in ('scalar_rms_nt', 'vector_rms_nt',
                                              'noise_floor_nt', 'noise_floor_status',
                                              'tensor_rms_nt_per_m') if k in summary},
        'warnings': list(summary['warnings']),
    }
    if pr is not None:
        # what the turn left open, recorded with the calibration (issue 20)
        prov['planar'] = {k: summary['planar'][k] for k in
                          ('axis', 'undetermined', 'determined', 'heading_error_deg',
                           'inclination_source')}
    if aided is not None:
        prov['attitude'] = summary['attitude']
    fref = dict(request.field_reference or {})
    fref.setdefault('magnitude_nt', float(np.mean(result.field_magnitude_nt)))
    doc = calibration_to_doc(result.calibration, geometry=geometry or {},
                             field_reference=fref, provenance=prov)
    return CalibrationRun(result=result, summary=summary, doc=doc)


def tensor_figures(summary):
    """
    Return the tensor's RMS before, after and its floor (nT/m, one RMS over the components).

    Keys ``tensor_rms_{before,after}_nt_per_m``, ``tensor_floor_nt_per_m``; {} without tensor.
    """
    if 'tensor_rms_nt_per_m' not in summary:
        return {}
    return {key: float(np.sqrt(np.mean(np.square(np.asarray(summary[src], float)))))
            for key, src in (('tensor_rms_before_nt_per_m', 'tensor_rms_before_nt_per_m'),
                             ('tensor_rms_after_nt_per_m', 'tensor_rms_nt_per_m'),
                             ('tensor_floor_nt_per_m', 'tensor_floor_nt_per_m'))}


def summary_lines(summary, request=None, skip_kinds=()):
    """
    Return the human account of a :attr:`CalibrationRun.summary` (CLI and node alike).

    Tensor RMS, site gradient, the planar and attitude-aided accounts, the robust fit's
    down-weighted samples (``request.robust``) and a line per warning not in ``skip_kinds``.
    """
    lines = []
    t = tensor_figures(summary)
    if t:
        lines.append(f"tensor RMS before {t['tensor_rms_before_nt_per_m']:.1f} nT/m, after "
                     f"{t['tensor_rms_after_nt_per_m']:.2f} nT/m (noise floor "
                     f"{t['tensor_floor_nt_per_m']:.2f} nT/m)")
    if 'site_gradient_nt_per_m' in summary:
        lines.append(f"site gradient ({summary['site_gradient_frame']}; nT/m, +- standard "
                     'uncertainty):')
        for row, srow in zip(summary['site_gradient_nt_per_m'],
                             summary['site_gradient_stderr_nt_per_m']):
            lines.append('  ' + '  '.join(f'{v:9.2f} +- {e:5.2f}' for v, e in zip(row, srow)))
    if 'planar' in summary:
        lines += _planar_lines(summary['planar'], summary['heading_error_deg'])
    if 'attitude' in summary:
        lines += attitude_lines(summary['attitude'])
    if request is not None and request.robust:
        per = ', '.join(f'{k}: {v:d}' for k, v in summary['downweighted'].items())
        lines.append(f'robust fit: samples down-weighted as outliers per sensor: {per} of '
                     f"{summary['n_fit_samples']}")
    lines += [format_note(w) for w in summary['warnings'] if w['kind'] not in skip_kinds]
    return lines


def _planar_lines(pl, heading_error_deg):
    """Return the planar fit's account: the heading error, what is open, a line per sensor."""
    lines = [f'planar: heading error {heading_error_deg:.2f} deg (1 sd, level, inclination '
             f"from {pl['inclination_source']}); undetermined (known no better than half the "
             "prior's width): " + (', '.join(pl['undetermined']) or 'none')]
    for j, e in pl['in_plane'].items():
        axis = ', '.join(f'{x:+.2f}' for x in pl['axis'][j])
        parts = [f'sensor {j}: turn about ({axis}); in the {e["axes"]} plane']
        parts.append('effective offsets (level) ' + ', '.join(
            f'{v:.1f} +- {s:.1f}' for v, s in zip(e['effective_offset_nt'],
                                                  e['effective_offset_stderr_nt'])) + ' nT')
        if 'scale_ratio' in e:
            parts.append(f'scale ratio {e["scale_ratio"]:.4f} +- {e["scale_ratio_stderr"]:.4f}')
        if 'nonorth_rad' in e:
            parts.append(f'angle {e["nonorth_rad"]:+.4f} +- {e["nonorth_stderr_rad"]:.4f} rad')
        parts.append(f'heading error {pl["heading_error_deg"][j]:.2f} deg (1 sd, largest over '
                     'headings)')
        lines.append('; '.join(parts))
    return lines


def attitude_lines(at):
    """Return the attitude-aided fit's account (:func:`attitude_summary`) as lines."""
    wf = at['world_field']
    inc, se = wf['inclination_deg'], wf['inclination_stderr_deg']
    line = (f"attitude: {at['mode']} ({at['trusted']} from {at['source']}, error "
            f"{at['attitude_sd_deg']:.2f} deg as estimated); world field inclination ")
    if wf.get('inclination_open'):
        # its +- is the data's only given the values held: not a measurement of the site
        line += (f'{inc:.2f} deg (not determined by the motion: '
                 + ', '.join(wf['inclination_open'])
                 + (f' open; the IGRF prior sets it, +- {se:.2f} deg)'
                    if wf['inclination_prior'] == 'IGRF' else
                    f" open, held at the prior's value; +- {se:.2f} deg only if those values "
                    'are right)'))
    else:
        line += (f'{inc:.2f} +- {se:.2f} deg from the data (a level error of the attitude '
                 'that holds over the record adds to it one for one)')
    if 'declination_deg' in wf:
        line += (f", declination {wf['declination_deg']:.2f} +- "
                 f"{wf['declination_stderr_deg']:.2f} deg")
    h = at['heading_check']
    off = f"{h['offset_deg']:+.1f} deg" + ('' if h.get('offset_determined', True) else (
        " (not determined: sensor 1's horizontal offsets are open, held at the prior's "
        'value)'))
    lines = [line, f'heading: attitude against the corrected compass {off}, '
                   f"{h['rms_deg']:.2f} deg RMS about it"]
    if at['undetermined']:
        lines.append("undetermined (known no better than half the prior's width): "
                     + ', '.join(at['undetermined']))
    return lines


#: the attitude mode of the learning's refits, the one place it is chosen: None, the
#: magnitude-only fit (data.attitude is carried, not used), or 'tilt' / 'full'
LEARN_ATTITUDE = None
#: prior sd of a held (undetermined, or another sensor's) parameter, a fraction of its kind's
HELD_FRACTION = 1e-6
#: a learned offset is determined when its standard uncertainty moves the corrected field
#: by at most this many noise sds; scale and angles (times F) DETERMINED_NOISE_MAP, a
#: coupling (times its reach) DETERMINED_NOISE_COUPLING (one that moved by noise would stay)
DETERMINED_NOISE = 3.0
DETERMINED_NOISE_MAP = 1.0
DETERMINED_NOISE_COUPLING = 1.0
#: a coupling's driver did not vary when the part of its effect the sensor's constant map
#: cannot produce is below this fraction of the whole (about 1e-9 for a constant driver)
STILL_FRACTION = 1e-6


def coupling_reach(cal, data, indices):
    """
    How far parameters of driven effects move the readings over ``data``: (varying, whole).

    For each of ``indices`` (into ``cal.params``), the derivative d raw_j / d p_i (N, 3) at
    ``cal`` and the field its correction of ``data`` ((S, N, 3) nT) gives: ``whole`` its RMS
    over the sets, ``varying`` the RMS of its part sensor j's constant map (offset, scale,
    angles) cannot produce (zero for a driver that did not vary). Both (len(indices),), nT
    per the parameter's unit.
    """
    model, p = cal.model, np.asarray(cal.params, float)
    info = model.param_info()
    indices = [int(i) for i in indices]
    varying, whole = np.zeros(len(indices)), np.zeros(len(indices))
    n = max(data.n_samples, 1)
    for j in sorted({info[i][0] for i in indices}):
        mine = [k for k, i in enumerate(indices) if info[i][0] == j]
        const = [i for eff, sl in zip(model.effects[j - 1], model.slices[j - 1])
                 if eff.kind == 'linear' or eff.constant for i in range(sl.start, sl.stop)]
        ctx = data.context(j)
        b = cal.correct(j, data.raw[j - 1], ctx)
        dc, hc = model.forward_differences(j, p, b, ctx, [indices[k] for k in mine])
        jc = (dc / hc[:, None, None]).reshape(len(mine), -1).T          # (3N, C)
        res = jc
        if const:
            dm, hm = model.forward_differences(j, p, b, ctx, const)
            jm = (dm / hm[:, None, None]).reshape(len(const), -1).T     # (3N, M)
            norm = np.linalg.norm(jm, axis=0)
            jm = jm[:, norm > 0] / norm[norm > 0]
            if jm.shape[1]:
                q, _ = np.linalg.qr(jm)
                res = jc - q @ (q.T @ jc)
        whole[mine] = np.linalg.norm(jc, axis=0) / np.sqrt(n)
        varying[mine] = np.linalg.norm(res, axis=0) / np.sqrt(n)
    return varying, whole


def refit_recent(data, active, field_nt, geometry=None, field_reference=None, sensors=None):
    """
    Refit what recent data determine, the rest held at the active calibration (issue 34).

    ``data`` (S, N, 3) nT, the recent window; ``active`` the Calibration in use, whose model
    and drivers' references are kept; ``field_nt`` nT; ``geometry``, ``field_reference`` as
    for :func:`calibrate`; ``sensors`` (1-based) learned, the others held (default: all).

    Every parameter gets a prior centred on its active value (the sensor map's the planar
    widths, a coupling's from :func:`coupling_reach`); what the data do not determine is held
    there and named. Stages: offsets, the whole map, the couplings whose driver varied
    (docs/design.md §3, *refit*).

    Returns (Calibration, its calibration document with ``provenance.converged``, the
    undetermined parameters as ``<effect>.<param>@<sensor>``).
    """
    from magcal_ros.core.model.planar import (PRIOR_SD, prior_sd, SENSOR_MAP_KINDS,
                                              UNDETERMINED_RATIO)
    spec = active.model.spec()
    model = Model.from_spec(spec, data.n_sensors).take_refs(active.model)
    info = model.param_info()
    f0 = float(np.mean(field_nt))
    sd = prior_sd(model, f0)
    mean = np.asarray(active.params, float)
    learned = set(range(1, data.n_sensors + 1) if sensors is None else sensors)
    owner = [None] * model.n_params
    for row, slices in zip(model.effects, model.slices):
        for eff, sl in zip(row, slices):
            owner[sl] = [eff] * (sl.stop - sl.start)
    mine = np.array([j in learned for j, *_ in info])
    # the constant sensor map (by label: ``offset(aux_x)`` is a coupling, not the offset)
    mapped = mine & np.array([label in SENSOR_MAP_KINDS for _, label, _, _ in info])
    offsets = mapped & np.array([label == 'offset' for _, label, _, _ in info])
    driven = mine & np.array([e is not None and e.kind != 'linear' and not e.constant
                              for e in owner])
    # how far a parameter moves the field per its unit: an offset 1, scale and angles F
    reach = np.where([unit == 'nT' for *_, unit in info], 1.0, f0)
    still = np.zeros(model.n_params, bool)
    held_sd = sd * HELD_FRACTION
    if driven.any():
        di = np.flatnonzero(driven)
        varying, whole = coupling_reach(active, data, di)
        still[di] = varying <= STILL_FRACTION * whole
        with np.errstate(divide='ignore'):
            width = PRIOR_SD['offset'] * f0 / np.where(still[di], whole, varying)
            held = PRIOR_SD['offset'] * f0 / whole
        sd[di] = np.where(np.isfinite(width), width, sd[di])
        reach[di] = whole
        # held, a coupling moves the field by as little as a held offset: its width from
        # its whole reach (the part a constant map could absorb too), not the varying one
        held_sd[di] = np.where(np.isfinite(held), held, sd[di]) * HELD_FRACTION
    kwargs = {} if LEARN_ATTITUDE is None else {'attitude': LEARN_ATTITUDE}
    runs = {}

    def run(open_, init):
        key = open_.tobytes()
        if key not in runs:
            priors = [(i, float(mean[i]), float(sd[i] if open_[i] else held_sd[i]))
                      for i in range(model.n_params)]
            fresh = Model.from_spec(spec, data.n_sensors).take_refs(active.model)
            runs[key] = calibrate(data, fresh, field_nt, geometry, field_reference,
                                  screen=False, init=init, extra_priors=priors,
                                  check_identifiability=False, **kwargs)
        return runs[key]

    def determined(res, open_, noise_sds):
        # known to a fraction of the prior (the planar rule) and to noise_sds noise sds
        noise = np.array([res.sigma_nt[j - 1] if j else np.nan for j, *_ in info])
        with np.errstate(divide='ignore'):
            tol = noise_sds * noise / reach
        # an attitude-aided fit appends the world field's angles after these parameters
        se = res.stderr[:model.n_params]
        return open_ & (se <= UNDETERMINED_RATIO * sd) & (se <= tol)

    first = run(offsets, mean)
    open_ = determined(first.result, offsets, DETERMINED_NOISE)
    open_ = open_ | determined(run(mapped, first.result.params).result, mapped & ~offsets,
                               DETERMINED_NOISE_MAP)
    free = driven & ~still
    if free.any():
        joined = run(open_ | free, first.result.params)
        open_ = open_ | determined(joined.result, free, DETERMINED_NOISE_COUPLING)
    final = run(open_, first.result.params)
    names = [f'{label}.{name}@{j}' for j, label, name, _ in info]
    undetermined = [names[i] for i in range(model.n_params)
                    if (mapped[i] or driven[i]) and not open_[i]]
    # a fit that ran out of iterations is no calibration (the learner never adopts it)
    final.doc['provenance']['converged'] = bool(final.result.success)
    return final.result.calibration, final.doc, undetermined
