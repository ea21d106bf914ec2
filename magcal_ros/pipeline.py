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

``calibrate(data, ...)`` = identifiability check + closed-form start + ML refinement
(:func:`magcal_ros.core.model.fit`), then the before/after figures (scalar, vector and tensor
residuals) and the calibration document (docs/design.md §4).
"""
from dataclasses import dataclass

from magcal_ros.core.data.magnitude import reference_magnitude
from magcal_ros.core.data.noise import data_noise_floor
from magcal_ros.core.geometry.site_gradient import centred_fields
from magcal_ros.core.geometry.tensor import (cross_positions, gradient_from_fit, tensor_lstsq,
                                             tensor_noise_floor)
from magcal_ros.core.model import data_hash, fit, Model
from magcal_ros.core.model.notes import Note, note_dict
from magcal_ros.core.model.plausibility import (axis_maps, fitted_scales_angles,
                                                mounting_notes, parameter_notes, with_axis_maps)
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
    Geometry dict of an array from node parameters (docs/design.md, "Array geometry").

    Parameters
    ----------
    n_sensors : int
        Sensors of the array.
    positions_m : sequence of float
        Flat x, y, z per sensor in the array frame, m (``sensor_positions_m``, 3 S values);
        empty: paper 004's cross of ``baseline_m`` for four sensors, the origin for one.
    baseline_m : float
        Distance between the two sensors of an arm of the cross, m.

    Returns
    -------
    dict or None
        ``{'type': 'cross', 'baseline_m', 'positions_m'}`` or ``{'type': 'positions',
        'positions_m'}`` (positions (S, 3) m as lists); None when no positions are given for
        2, 3 or more than 4 sensors (the tensor is then not computed).

    Raises
    ------
    ValueError
        Naming the count expected when ``positions_m`` is not 3 finite numbers per sensor.

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
    """
    Why the gradient tensor cannot be computed from sensors at ``positions``, or None.

    ``positions`` (S, 3) m or None. The tensor (symmetric and traceless: 5 numbers, with
    the centre field 8 unknowns, :func:`magcal_ros.core.geometry.tensor.tensor_operator`) needs the
    sensors to span at least a plane: one sensor measures no difference, collinear sensors
    only the derivatives along their line.
    """
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
    """
    Why a calibration file's geometry differs from the node's, naming both, or None.

    Both are geometry dicts (``positions_m`` (S, 3) m); a file without positions, or a node
    without a geometry, is not compared.
    """
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
    """
    RMS (about the mean) and max deviation of each tensor component, nT/m.

    fields (S, N, 3) nT in the array frame. Returns dict rms (3,3), max_abs_dev (3,3), mean.
    """
    g, _ = tensor_lstsq(fields, positions)
    dev = g - g.mean(axis=0)
    return {'rms': np.sqrt(np.mean(dev ** 2, axis=0)), 'max_abs_dev': np.abs(dev).max(axis=0),
            'mean': g.mean(axis=0)}


@dataclass
class CalibrationRun:
    """A fit with its summary figures and calibration document."""

    result: object
    summary: dict
    doc: dict


#: a sensor's fitted noise above this multiple of the data's own noise floor is reported
RESIDUAL_WARN_RATIO = 1.5
#: ... and above this multiple (two orders of magnitude) of the floor, or of the raw
#: readings' difference floor (model-free), as a failed fit, not a missing effect
GROSS_RATIO = 100.0


def _residual_warnings(result, floor):
    """
    Structured warnings (:class:`Note`) on the fit's residual against the data's floor.

    ``result.sigma_nt`` (S,) is the fit's per-axis noise estimate from its residual and
    ``floor`` the :class:`~magcal_ros.core.data.noise.NoiseFloor` of the data (needs no model): a
    fit that is complete meets it; one far above it misses an effect, or was given
    inconsistent data (sets of the array paired from different epochs, a non-uniform field).
    A filtered series has no white floor to compare with: it gets a ``noise_floor`` warning
    with the range instead (never "N x the floor" from a lower bound).
    """
    out = []
    for j, (sig, fl) in enumerate(zip(result.sigma_nt, floor.per_sensor_nt), start=1):
        gross = (None if floor.status[j - 1] == 'filtered' else
                 _gross_note(j, sig, fl, floor.raw_nt[j - 1]))
        if gross is not None:
            # two orders of magnitude above the floor (or above the raw readings' own
            # difference floor, which no fit moves: a floor taken from a diverged fit's
            # residual is as large as the residual); a filtered series has only a lower
            # bound of its floor, never "N x" it (the worse-than-raw check still holds)
            out.append(gross)
            continue
        if floor.status[j - 1] == 'filtered':
            out.append(Note(floor.describe(j) + '; the residual cannot be compared with it',
                            'noise_floor', j))
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
    Return a warning when sensor ``j``'s residual is orders of magnitude above its floor.

    ``sig`` the fit's per-axis residual sd, ``fl`` the floor and ``raw_fl`` the floor from
    the raw readings' differences (model-free), nT.  The lower of the two floors decides.
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
    """
    List every warning on a fit.

    Every warning on a fit as ``{kind, sensor, text}``: the fit's own (degenerate data
    flagged, not converged) and those on its residual against the data's floor.
    """
    return [note_dict(w) for w in list(result.warnings) + _residual_warnings(result, floor)]


def summarize(result, data, positions=None):
    """
    Before/after figures of a fit (all nT, nT/m); JSON-ready.

    The noise floor is :func:`~magcal_ros.core.data.noise.data_noise_floor` of the data and this
    fit (the figure ``diagnose`` reports for the same data and model); the tensor floor is
    propagated from it, not from the fit's sigma (which grows when an effect is missing).
    ``warnings`` is a list of ``{kind, sensor, text}``.
    """
    f = result.field_magnitude_nt
    raw_tot = np.linalg.norm(data.raw, axis=2) - f[None]
    cor_tot = result.scalar_residual_nt
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
        'total_field_max_dev_before_nt': float(np.abs(raw_tot).max()),
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
        before = tensor_stats(data.raw, positions)
        # about the modelled site gradient: what is left is calibration error and noise
        after = tensor_stats(centred_fields(result), positions)
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


def calibrate(data, model='base', field_nt=None, geometry=None, field_reference=None,
              exclude_outliers=False, screen=True, **fit_kwargs):
    """
    Fit ``model`` to ``data`` and build the summary and calibration document.

    Parameters
    ----------
    data : Dataset
        Raw readings (S, N, 3) nT with times and channels.
    model : str or Model
        The model: effect tokens (``'base,temperature@2'``) or a built Model.
    field_nt : float or numpy.ndarray, optional
        Reference magnitude (nT); default ``data.ref_total``.
    geometry : dict, optional
        Array geometry (``positions_m`` (S, 3) m); default: paper 004's cross with a 0.5 m
        baseline when there are four sensors.
    field_reference : dict, optional
        How the reference was obtained (recorded in the provenance).
    exclude_outliers : bool
        When the least-squares fit leaves a sensor above 1.5 x its noise floor (the summary's
        warning), fit again with the soft-L1 loss, and if the sets it finds beyond
        :data:`OUTLIER_SIGMAS` of its robust noise are at most :data:`MAX_OUTLIER_FRACTION`
        of all, fit by least squares without them (an efficient fit on the rest, not the
        1.4 x Cramer-Rao robust one).  Garbage that survived the transport (a cut line, a
        mis-paired stretch) then costs those sets only; a missing effect, which spreads over
        many sets, is left to the warning and to diagnose.  The summary gives
        ``outlier_sets_excluded``.
    screen : bool or ReadingScreen
        Before the fit, leave out the sets holding readings no field produces (a pinned,
        clipped or repeating channel, spikes:
        :func:`magcal_ros.core.data.readings.leave_out_unphysical`); each is named in a
        ``readings`` warning, and the summary and the provenance give ``readings_left_out``.
        Too few sets left raises :class:`~magcal_ros.core.data.readings.UnphysicalReadingsError`
        (a ValueError) naming them.  A ReadingScreen: the caller has left its sets out of
        ``data`` already (the calibration node, before its pairing check); it is reported.

    """
    if not screen:
        return _calibrate_clean(data, model, field_nt, geometry, field_reference,
                                exclude_outliers, **fit_kwargs)
    from magcal_ros.core.data.readings import leave_out_unphysical, ReadingScreen
    if isinstance(screen, ReadingScreen):
        found = screen
    else:
        data, field_nt, found = leave_out_unphysical(data, field_nt)
    run = _calibrate_clean(data, model, field_nt, geometry, field_reference, exclude_outliers,
                           **fit_kwargs)
    left_out = found.to_dict()
    run.summary['readings_left_out'] = left_out
    run.doc['provenance']['readings_left_out'] = left_out
    notes = [note_dict(w) for w in found.notes()]
    run.summary['warnings'][:0] = notes
    run.doc['provenance']['warnings'][:0] = notes
    return run


def _calibrate_clean(data, model, field_nt, geometry, field_reference, exclude_outliers,
                     **fit_kwargs):
    run = _calibrate(data, model, field_nt, geometry, field_reference, **fit_kwargs)
    if (not exclude_outliers or fit_kwargs.get('robust') or fit_kwargs.get('heading_unknown')
            or fit_kwargs.get('planar') is not None):
        return run
    if not [w for w in run.summary['warnings'] if w['kind'] == 'missing_effect']:
        run.summary['outlier_sets_excluded'] = 0
        return run
    rob = fit(data, run.result.model, field_nt=field_nt,
              **dict(fit_kwargs, robust=True, check_identifiability=False,
                     on_degenerate='flag'))
    z = np.abs(rob.residual_nt) / rob.sigma_nt[:, None, None]
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
    clean = _calibrate(data.subset(keep), spec, f_keep, geometry, field_reference,
                       **fit_kwargs)
    clean.summary['outlier_sets_excluded'] = n_bad
    excluded = note_dict(Note(
        f'{n_bad} of {data.n_samples} sets excluded: beyond {OUTLIER_SIGMAS:g} sigma of a '
        'robust fit (garbled samples or mis-paired sets); fitted on the rest', 'outliers'))
    clean.summary['warnings'].append(excluded)
    clean.doc['provenance']['warnings'].append(excluded)
    return clean


def _adopt_axis_maps(result, data, field_nt, positions, fit_kwargs):
    """
    Refit with the axis maps a mirrored, swapped or turned sensor needs (core.model.plausibility).

    Returns the result (the refit when maps were found, else ``result``) and the ``mounting``
    notes naming each map.
    """
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


def _calibrate(data, model, field_nt, geometry, field_reference, **fit_kwargs):
    if geometry is None and data.n_sensors == 4:
        geometry = cross_geometry(0.5)
    if isinstance(model, str):
        model = Model.from_spec(model, data.n_sensors)
    positions = geometry_positions(geometry, data.n_sensors)
    if positions is not None:
        model.set_positions(positions)          # where the site gradient acts
    mounting = []
    planar = fit_kwargs.pop('planar', None)
    if fit_kwargs.pop('heading_unknown', False):
        # site gradient without attitude: the heading about the field per epoch
        from magcal_ros.core.geometry.site_gradient import fit_heading_unknown
        result = fit_heading_unknown(data, model, field_nt=field_nt, **fit_kwargs)
    elif planar is not None:
        # a turn about one axis (a ground robot): what it determines, the rest at a prior
        from magcal_ros.core.model import planar as pl
        fit_kwargs.pop('constrained', None)
        fit_kwargs.pop('on_degenerate', None)
        pr = pl.fit_planar(data, model, reference_magnitude(data, field_nt),
                           prior_params=planar.get('prior_params'),
                           inclination_deg=planar.get('inclination_deg'), **fit_kwargs)
        result = pr.result
    else:
        result = fit(data, model, field_nt=field_nt, **fit_kwargs)
        result, mounting = _adopt_axis_maps(result, data, field_nt, positions, fit_kwargs)
    summary = summarize(result, data, positions)
    if planar is not None:
        summary['planar'] = pl.planar_summary(pr)
        summary['planar']['inclination_source'] = (
            'IGRF' if planar.get('inclination_deg') is not None else 'the fitted field')
        summary['undetermined'] = summary['planar']['undetermined']
        summary['heading_error_deg'] = max(summary['planar']['heading_error_deg'].values())
        summary['warnings'].extend(note_dict(n) for n in pl.planar_notes(pr))
    if planar is None:        # a planar fit holds what a turn cannot determine at its prior
        summary['warnings'] += [note_dict(w) for w in mounting + parameter_notes(
            result.model, result.params, data.raw, float(np.mean(result.field_magnitude_nt)))]
    temp_range = {}
    if data.temp is not None:
        for j in range(data.n_sensors):
            tj = data.temp[j]
            if np.isfinite(tj).any():
                temp_range[str(j + 1)] = [float(np.nanmin(tj)), float(np.nanmax(tj))]
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
                                              'noise_floor_nt', 'noise_floor_status')
                      if k in summary},
        'warnings': list(summary['warnings']),
    }
    if planar is not None:
        # what the turn left open, recorded with the calibration (issue 20)
        prov['planar'] = {k: summary['planar'][k] for k in
                          ('axis', 'undetermined', 'determined', 'heading_error_deg',
                           'inclination_source')}
    if 'tensor_rms_nt_per_m' in summary:
        prov['residuals']['tensor_rms_nt_per_m'] = summary['tensor_rms_nt_per_m']
    fref = dict(field_reference or {})
    fref.setdefault('magnitude_nt', float(np.mean(result.field_magnitude_nt)))
    doc = calibration_to_doc(result.calibration, geometry=geometry or {},
                             field_reference=fref, provenance=prov)
    return CalibrationRun(result=result, summary=summary, doc=doc)
