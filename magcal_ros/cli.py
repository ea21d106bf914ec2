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
The offline ``magcal`` command line (docs/design.md §2).  Imports no rclpy.

Exit status: 0 success, 2 bad input (one-line reason on stderr), 1 other failure.
"""
import argparse
from contextlib import contextmanager
from itertools import islice
import json
import os
import sys

from magcal_ros.core.effects import load_plugins
from magcal_ros.core.model.notes import format_note
from magcal_ros.progress import Progress, wanted
from magcal_ros.runtime import limit_blas_threads
from magcal_ros.units import check_field_units, UNITS_NT
import numpy as np

EXIT_OK, EXIT_FAIL, EXIT_BAD_INPUT = 0, 1, 2


class BadInput(ValueError):
    """Bad user input: reported on stderr with exit status 2."""


def load_data(path, unit=None, rate_hz=100.0, allow_gaps=False):
    """
    Dataset in nT from a wide CSV file, a rosbag2 directory, a vehicle log or a single-sensor CSV.

    A vehicle log (:mod:`magcal_ros.io.vehicle`, found by its first bytes) prints its
    warnings on stderr; ``allow_gaps`` keeps one whose compass stops for a while. ``unit`` (a
    key of :data:`magcal_ros.units.UNITS_NT`): the field columns' unit, converted here, once.
    A CSV without wide-format columns is one magnetometer's log (needs ``unit``; ``rate_hz``
    without a time column).
    """
    if os.path.isdir(path):
        from magcal_ros.io.bag import read_bag
        data = read_bag(path)
    elif not os.path.exists(path):
        raise BadInput(f'{path}: no such file or directory')
    elif _vehicle_log(path):
        return _read_vehicle(path, unit, allow_gaps)
    elif unit and not _is_wide_csv(path):
        from magcal_ros.io.single_csv import read_single_sensor_csv
        return read_single_sensor_csv(path, unit=unit, rate_hz=rate_hz)
    else:
        from magcal_ros.io.csvio import read_csv
        data = read_csv(path)
    k = UNITS_NT[unit or 'nT']
    if k != 1.0:
        _scale_to_nt(data, k)
        data.meta['unit'] = unit
    return data


def load_record(path, unit=None, rate_hz=100.0, progress=None, reduce_above=None,
                allow_gaps=False):
    """
    (Dataset, Record or None): a recording, reduced when it is too long to hold.

    Above ``reduce_above`` (default :data:`magcal_ros.core.data.reduce.REDUCE_ABOVE`) epochs
    the Dataset is the evenly spread sample read in chunks, the Record reads the whole again
    for the residual statistics; anything else is read whole (:func:`load_data`).
    """
    from magcal_ros.core.data import reduce
    limit = reduce.REDUCE_ABOVE if reduce_above is None else int(reduce_above)
    if os.path.exists(path) and _vehicle_log(path):
        # a vehicle log is read once, whole (its compass epochs: io.vehicle), then reduced
        data = _read_vehicle(path, unit, allow_gaps)
        if data.n_samples <= limit:
            return data, None
        from magcal_ros.io.vehicle import VehicleRecord
        rec = VehicleRecord(path, data)
        red = reduce.reduce_chunks(rec.chunks())
        return red.sample, rec
    other_csv = unit and not os.path.isdir(path) and not _is_wide_csv(path)
    if not os.path.exists(path) or other_csv or _estimated_rows(path) <= limit:
        return load_data(path, unit, rate_hz), None
    from magcal_ros.io.chunks import open_record
    rec = open_record(path)
    k = UNITS_NT[unit or 'nT']
    with _byte_bar(progress, 'reading', rec) as tick:
        red = reduce.reduce_chunks(_scale_to_nt(c, k) for c in rec.chunks(progress=tick))
    if unit:
        red.sample.meta['unit'] = unit
    rec.scale = k
    return red.sample, rec


@contextmanager
def _byte_bar(progress, step, record):
    """Give the ``progress`` callback of ``record.chunks``: a bar of its bytes (None: silent)."""
    bar = (progress or Progress(False)).bar(step, total=record.size, unit='B', scale=True)
    try:
        yield lambda b: bar.update(b - bar.n)
    finally:
        bar.close()


def _vehicle_log(path):
    """Tell whether ``path`` is an ArduPilot or PX4 log (magcal_ros.io.vehicle.log_format)."""
    from magcal_ros.io.vehicle import log_format
    return log_format(path) is not None


def _read_vehicle(path, unit, allow_gaps=False):
    """Read a vehicle log (nT from the log's own units); print its warnings on stderr."""
    if unit not in (None, 'nT'):
        raise BadInput(f'--unit {unit}: a vehicle log is read in its own units (ArduPilot '
                       'milligauss, PX4 gauss) and converted to nT; leave --unit out')
    from magcal_ros.io.vehicle import read_vehicle_log
    data = read_vehicle_log(path, allow_gaps=allow_gaps)
    for w in data.meta.get('warnings', []):
        print(format_note(w), file=sys.stderr)
    return data


def _scale_to_nt(data, k):
    """Multiply the field columns of a Dataset (raw, ref_total, ref_vec) by ``k``, in place."""
    for name in ('raw', 'ref_total', 'ref_vec'):
        if k != 1.0 and getattr(data, name) is not None:
            setattr(data, name, getattr(data, name) * k)
    return data


def _estimated_rows(path, probe=200):
    """Epochs of a recording: a CSV's from its size and first lines, a bag's from metadata."""
    if os.path.isdir(path):
        from magcal_ros.io.bag import bag_epoch_count
        return bag_epoch_count(path)
    with open(path, 'rb') as fh:
        data = (line for line in fh if line.strip() and not line.lstrip().startswith(b'#'))
        sizes = [len(line) for line in islice(data, probe + 1)]
    return 0 if len(sizes) < 2 else int(os.path.getsize(path) / (sum(sizes) / len(sizes)))


def full_record_statistics(run, record, positions, progress=None):
    """
    Put the residual statistics of every epoch of ``record`` into ``run`` (a long record).

    ``run`` (fitted on the reduced sample): its summary's RMS, largest deviations and
    ``n_samples`` become the whole record's
    (:func:`magcal_ros.core.data.reduce.residual_statistics`).
    """
    from magcal_ros.core.data.reduce import residual_statistics
    with _byte_bar(progress, 'residuals', record) as tick:
        chunks = (_scale_to_nt(c, record.scale) for c in record.chunks(progress=tick))
        stats = residual_statistics(chunks, run.result, positions)
    run.summary.update(stats)
    prov = run.doc['provenance']
    prov['samples'] = stats['n_samples']
    for key in ('scalar_rms_nt', 'vector_rms_nt', 'tensor_rms_nt_per_m'):
        if key in stats:
            prov['residuals'][key] = stats[key]
    return stats


def _is_wide_csv(path):
    """Tell whether the first non-comment line of ``path`` names a wide-format column."""
    import re
    from magcal_ros.io.compressed import open_text
    with open_text(path, encoding='utf-8-sig', errors='replace') as fh:
        for line in fh:
            if line.strip() and not line.lstrip().startswith('#'):
                return re.search(r'(^|[,;\t ])s\d+_x($|[,;\t ])', line.strip()) is not None
    return False


def add_gaps_arg(p):
    """Add --allow-gaps (a vehicle log whose compass stops for a while is kept whole)."""
    p.add_argument('--allow-gaps', action='store_true',
                   help='a vehicle log whose compass stops for more than 10 sample periods '
                        '(a log dropout) is refused; keep it whole, with a warning')


def add_unit_arg(p):
    """Add the --unit option (the unit of the data's field columns)."""
    p.add_argument('--unit', choices=list(UNITS_NT),
                   help='unit of the field columns of DATA (readings, ref_total, ref_x/y/z), '
                        'converted to nT at load (default nT); a single-magnetometer CSV '
                        '(mx,my,mz or x,y,z columns) needs it')


def add_field_args(p):
    """--field-nt / --igrf options."""
    g = p.add_mutually_exclusive_group()
    g.add_argument('--field-nt', metavar='NT',
                   help="reference field magnitude in nT, or 'auto' (shape-only calibration); "
                        'default: the ref_total column')
    g.add_argument('--igrf', nargs=4, metavar=('LAT', 'LON', 'ALT_KM', 'DATE'),
                   help='reference magnitude from the IGRF model (ppigrf) at a place and date')


def resolve_field(args, data):
    """
    (field_nt or None, field_reference dict) from the options and the data.

    Readings and reference must agree, in nT (:func:`magcal_ros.units.check_field_units`).
    """
    f, fref = _resolve_field(args, data)
    kind = fref['kind']
    name = {'constant': '--field-nt', 'igrf': 'the IGRF magnitude',
            'ref_total': 'the ref_total column (median)'}.get(kind)
    ref = None if name is None else (float(np.median(data.ref_total)) if kind == 'ref_total'
                                     else f)
    check_field_units(data.raw, ref, name or '')
    return f, fref


def _resolve_field(args, data):
    # the node's field_source, from the options (core.data.magnitude.site_field_reference)
    from magcal_ros.core.data.magnitude import site_field_reference
    if args.igrf:
        try:
            lat, lon, alt = (float(x) for x in args.igrf[:3])
        except ValueError:
            raise BadInput('--igrf LAT LON ALT_KM DATE: LAT, LON, ALT_KM must be numbers')
        return site_field_reference('igrf', None, lat, lon, alt * 1000.0, args.igrf[3])
    if args.field_nt is not None:
        if args.field_nt == 'auto':
            # an ellipsoid needs a sphere; a turn gives a circle and the mean along it
            source = 'shape-planar' if getattr(args, 'planar', False) else 'shape'
            if source == 'shape' and data.attitude is not None and args.attitude != 'off':
                # the attitude-aided fit's priors hold the scales near 1: a magnitude from a
                # partly covered ellipsoid (tens of per cent off) would be fitted as fact
                raise BadInput(
                    "--field-nt auto takes the magnitude from sensor 1's ellipsoid, which a "
                    'vehicle that stays near level does not determine, and the fit with the '
                    "data's attitude needs the site's own: give --field-nt NT (IGRF's for the "
                    'place and date) or --igrf LAT LON ALT_KM DATE, or fit the magnitude '
                    'alone with --attitude off')
            return site_field_reference(source, raw=data.raw[0])
        try:
            f = float(args.field_nt)
        except ValueError:
            raise BadInput(f"--field-nt must be a number of nT or 'auto', got {args.field_nt!r}")
        if not np.isfinite(f) or f <= 0:
            raise BadInput('--field-nt must be positive')
        return site_field_reference('constant', f)
    if data.ref_total is not None:
        return None, {'kind': 'ref_total', 'magnitude_nt': float(np.mean(data.ref_total))}
    site = data.meta.get('igrf')
    if site:
        # a vehicle log's GPS: IGRF at its median fix and date (magcal_ros.io.vehicle)
        f, ref = site_field_reference('igrf', None, site['lat_deg'], site['lon_deg'],
                                      site['alt_km'] * 1000.0, site['date'])
        ref['note'] = f"from the log's GPS (median of {site.get('fixes', 0)} 3-D fixes)"
        return f, ref
    raise BadInput('no reference field: the data have no ref_total column; give --field-nt NT, '
                   '--field-nt auto or --igrf LAT LON ALT_KM DATE')


def print_json(obj):
    """One JSON object on stdout."""
    from magcal_ros.core.data.plain import jsonable
    print(json.dumps(jsonable(obj)))


# -- simulate -------------------------------------------------------------------------------

def _parse_truth(items):
    from magcal_ros.core.data.simulate import parse_truth
    try:
        return parse_truth(items)
    except ValueError as exc:
        raise BadInput(f'--truth {exc}') from None


def cmd_simulate(args):
    from magcal_ros.core.data.simulate import simulate
    load_plugins(args.plugin)
    truth = _parse_truth(args.truth)
    grad = None
    if args.site_gradient:
        from magcal_ros.core.geometry.tensor import symmetric_traceless
        try:
            g5 = [float(v) for v in args.site_gradient.split(',')]
        except ValueError:
            g5 = []
        if len(g5) != 5 or not np.all(np.isfinite(g5)):
            raise BadInput(f'--site-gradient {args.site_gradient!r}: expected five numbers '
                           'GXX,GXY,GXZ,GYY,GYZ in nT/m (gzz = -gxx - gyy)')
        grad = symmetric_traceless(g5)
    settings = {'gradient_nt_per_m': grad, 'attitude': args.attitude, 'n_samples': args.n,
                'rate_hz': args.rate, 'trajectory': args.trajectory,
                'noise_nt': args.noise_nt, 'seed': args.seed, 'truth': truth,
                'model': args.model, 'aux': not args.no_aux,
                'diurnal_swing_nt': args.diurnal_nt, 'outlier_fraction': args.outliers,
                'field_nt': args.field_nt, 'errors': None if args.ideal else 'paper004'}
    from magcal_ros.core.data.reduce import REDUCE_ABOVE
    if args.n <= REDUCE_ABOVE:
        data, sim = simulate(**settings)
        pieces = [data]
    else:
        # a long record: made and written a chunk at a time (core.data.simulate.simulate_chunks)
        from magcal_ros.core.data.simulate import simulate_chunks
        sim, pieces = simulate_chunks(**settings)
    comment = (f'magcal simulate: paper 004 cross, {args.n} samples at {args.rate} Hz, '
               f'trajectory {args.trajectory}, noise {args.noise_nt} nT, seed {args.seed}\n'
               f'truth model: {",".join(sim.model.spec())}\n'
               'truth params: ' + ' '.join(f'{v:.6g}' for v in sim.params))
    from magcal_ros.io.chunks import write_csv_chunks
    prog = Progress(wanted(args.quiet))
    bar = prog.bar('simulate', total=args.n, unit='sets', scale=True)

    def with_ref(pieces):
        for piece in pieces:
            if args.ref_total and piece.ref_total is None:
                piece.ref_total = sim.field_magnitude(piece.t)
            bar.update(piece.n_samples)
            yield piece
    try:
        n = write_csv_chunks(args.out, with_ref(pieces), comment=comment)
    finally:
        bar.close()
    print(f'wrote {args.out}: {n} samples of {sim.config.n_sensors} sensors', file=sys.stderr)
    return EXIT_OK


# -- fit ------------------------------------------------------------------------------------

def cmd_fit(args):
    from magcal_ros.io.calfile import save_calibration, stamp_checksum
    from magcal_ros.pipeline import (CalibrationRequest, cross_geometry, geometry_positions,
                                     run_request, summary_lines)
    load_plugins(args.plugin)
    prog = Progress(wanted(args.quiet, args.json))
    if args.method != 'ellipsoid':
        return _fit_paper_method(args, load_data(args.data, args.unit, allow_gaps=args.allow_gaps))
    data, record = load_record(args.data, args.unit, progress=prog, allow_gaps=args.allow_gaps)
    field_nt, fref = resolve_field(args, data)
    geometry = cross_geometry(args.baseline_m) if data.n_sensors == 4 else None
    request = CalibrationRequest(
        model=args.model, field_nt=field_nt, field_reference=fref, geometry=geometry,
        attitude=args.attitude, planar=args.planar, heading_unknown=args.heading_unknown,
        robust=args.robust, constrained=args.constrained,
        on_degenerate='flag' if args.flag_degenerate else 'raise')
    prog('fit', 0, 1, args.model)
    run = run_request(data, request)
    prog('fit', 1, 1)
    if record is not None:
        full_record_statistics(run, record, geometry_positions(geometry, data.n_sensors), prog)
        run.summary['reduction'] = data.meta['reduction']
        run.doc['provenance']['reduction'] = data.meta['reduction']
    out = args.output
    refused = not run.result.success and not args.force
    if out and not refused:
        save_calibration(out, run.doc)
    s = {**run.summary, 'output': None if refused else out, 'field_reference': fref}
    if 'onboard_calibration' in data.meta:
        # a vehicle log: the autopilot's own calibration (its parameters) beside ours
        s['onboard_calibration'] = data.meta['onboard_calibration']
        s['log'] = {k: data.meta.get(k) for k in (
            'source_format', 'firmware', 'vehicle', 'compasses', 'attitude_source',
            'attitude_frame', 'aux_units', 'dropped_epochs')}
    # the document the file holds (or would hold), built once: the JSON and the file agree
    s['calibration'] = None if refused else stamp_checksum(run.doc)
    if args.json:
        print_json(s)
    else:
        print(run.result.summary())
        # the degenerate and not-converged warnings are in the fit's own summary
        for line in summary_lines(s, request, skip_kinds=('degenerate', 'not_converged')):
            print(line)
        kinds = sorted(set(s['noise_floor_status'].values()) - {'white'})
        print(f'noise floor (from the data): {s["noise_floor_nt"]:.2f} nT'
              + (f' ({" / ".join(kinds)}: see the noise_floor warnings)' if kinds else ''))
        if out and not refused:
            print(f'calibration written to {out}')
    if refused:
        print(f'magcal: failed: the fit did not converge ({run.result.message}); '
              + ('no calibration written; ' if out else '')
              + 'rerun with --force to accept it anyway', file=sys.stderr)
        return EXIT_FAIL
    return EXIT_OK


def add_attitude_arg(p):
    """Add the --attitude option (how an attitude in the data is used)."""
    p.add_argument('--attitude', default='auto', choices=['auto', 'tilt', 'full', 'off'],
                   help="use the data's attitude (att_q* columns, an Imu topic, a vehicle "
                        "log): tilt = roll and pitch only (auto's choice when the data carry "
                        "an attitude: a vehicle's heading often comes from this compass), "
                        'full = the heading too, off = the field magnitude alone')


def _fit_paper_method(args, data):
    """``magcal fit --method sine|reference``: the closed forms of papers 000 and 002."""
    from magcal_ros.core.model import paper_methods
    from magcal_ros.io.calfile import calibration_to_doc, save_calibration, stamp_checksum
    from magcal_ros.pipeline import cross_geometry
    for opt, given in (('--model', args.model != 'base'), ('--robust', args.robust),
                       ('--constrained', args.constrained)):
        if given:
            raise BadInput(f'{opt} applies to --method ellipsoid only (the maximum-likelihood '
                           f'fit); --method {args.method} has a fixed model')
    field_nt, fref = None, {'kind': 'reference vector (|ref_x, ref_y, ref_z|)'}
    if (args.method == 'sine' or args.field_nt is not None or args.igrf
            or data.ref_total is not None):
        field_nt, fref = resolve_field(args, data)
        field_nt = data.ref_total if field_nt is None else field_nt
    if args.method == 'sine':
        res = paper_methods.sine_calibration(data, field_nt)
        geometry = None                     # the rotations between sensors are unknown
    else:
        res = paper_methods.reference_calibration(
            data, field_nt, on_degenerate='flag' if args.flag_degenerate else 'raise')
        geometry = cross_geometry(args.baseline_m) if data.n_sensors == 4 else None
    out = args.output
    doc = calibration_to_doc(res.calibration, geometry=geometry, field_reference=fref,
                             provenance={'method': args.method, 'samples': int(data.n_samples),
                                         'warnings': list(res.warnings)})
    if out:
        save_calibration(out, doc)
    if args.json:
        print_json({**res.to_dict(), 'noise_floor_nt': None, 'output': out,
                    'field_reference': fref, 'calibration': stamp_checksum(doc)})
    else:
        print(res.summary())
        if out:
            print(f'calibration written to {out}')
    return EXIT_OK


# -- rollback -------------------------------------------------------------------------------

def cmd_rollback(args):
    from magcal_ros.io import calfile
    path = args.calfile
    hist = calfile.list_history(path)
    if args.list:
        active = calfile.active_history_index(path)
        rows = []
        for k, entry in enumerate(hist):
            try:
                _, doc = calfile.load_calibration(entry)
                prov = doc.get('provenance') or {}
                info = {'created': prov.get('created'), 'model': doc.get('model'),
                        'samples': prov.get('samples')}
            except calfile.CalibrationFileError as exc:
                info = {'error': str(exc)}
            rows.append({'path': entry, 'active': k == active, **info})
        if args.json:
            print_json({'calfile': path, 'history': rows})
        else:
            if not rows:
                print(f'{path}: no history ({path}.history/ is empty or missing)')
            for k, row in enumerate(rows):
                mark = '*' if row['active'] else ' '
                what = row.get('error') or (f'created {row["created"]}, model '
                                            f'{",".join(row["model"] or [])}, '
                                            f'{row["samples"]} samples')
                print(f'{mark} {k - (active if active is not None else len(rows) - 1):+d} '
                      f'{row["path"]}: {what}')
        return EXIT_OK
    if args.steps < 1:
        raise BadInput(f'--steps must be >= 1, got {args.steps}')
    if not hist:
        raise BadInput(f'{path}: no calibration history ({path}.history/ is empty or missing)')
    chosen = calfile.rollback(path, steps=args.steps)
    _, doc = calfile.load_calibration(path)
    out = {'calfile': path, 'restored': chosen,
           'created': (doc.get('provenance') or {}).get('created'),
           'backup': path + '.bak'}
    if args.json:
        print_json(out)
    else:
        print(f'{path} is now the calibration created {out["created"]} ({chosen}); the one it '
              f'replaced is kept as {out["backup"]}')
    return EXIT_OK


# -- check ----------------------------------------------------------------------------------

def cmd_check(args):
    """`magcal check CALFILE DATA...`: a calibration against static recordings."""
    from magcal_ros.core.data.static_check import check_static
    from magcal_ros.io import calfile
    cal, doc = calfile.load_calibration(args.calfile)
    j = args.sensor
    if not 1 <= j <= cal.n_sensors:
        raise BadInput(f'--sensor {j}: the calibration has sensors 1..{cal.n_sensors}')
    ref = (doc.get('field_reference') or {}).get('magnitude_nt')
    rms = (((doc.get('provenance') or {}).get('residuals') or {}).get('scalar_rms_nt')
           or {}).get(str(j))
    if ref is None or rms is None:
        raise BadInput(f'{args.calfile}: no field_reference.magnitude_nt or provenance '
                       f'residual of sensor {j}: write it with magcal fit')
    corrected = {}
    prog = Progress(wanted(args.quiet, args.json))
    for path in args.data:
        # a long static recording: its evenly spread sample (core.data.reduce), read in chunks
        data, _ = load_record(path, args.unit, progress=prog, allow_gaps=args.allow_gaps)
        try:
            check_field_units(data.raw, None, '')
        except ValueError as exc:
            raise BadInput(f'{path}: {exc}') from None
        if data.n_sensors < j:
            raise BadInput(f'{path}: has {data.n_sensors} sensor(s), no sensor {j}')
        corrected[os.path.basename(path.rstrip('/'))] = cal.correct(
            j, data.raw[j - 1], data.context(j))
    res = check_static(corrected, float(ref), float(rms))
    if args.json:
        print_json({'calfile': args.calfile, 'sensor': j, 'reference_nt': float(ref),
                    'tolerance_nt': res.tolerance_nt, 'consistent': res.consistent,
                    'recordings': res.rows, 'findings': res.findings})
    else:
        print(f'sensor {j}: corrected |B| of each recording (reference {float(ref):.0f} nT, '
              f'agreement within {res.tolerance_nt:.0f} nT)')
        for r in res.rows:
            d = ', '.join(f'{x:+.2f}' for x in r['direction'])
            print(f'  {r["name"]}: {r["b_nt"]:.0f} nT (sd {r["sd_nt"]:.0f}, {r["n"]} samples, '
                  f'{r["minus_reference_nt"]:+.0f} nT vs reference; field along ({d}))')
        for text in res.findings:
            print(f'- {text}')
    return EXIT_OK


# -- diagnose, report -----------------------------------------------------------------------

def _add_workbench_args(p):
    p.add_argument('data', help='wide CSV file (.csv, .csv.gz, .csv.zst), rosbag2 directory, '
                                'vehicle log (ArduPilot .bin/.log, PX4 .ulg), or '
                                'single-sensor CSV (with --unit)')
    p.add_argument('--model', default='base',
                   help="effects of the model to diagnose, e.g. 'base,temperature@2' "
                        '(default base)')
    add_field_args(p)
    p.add_argument('--plugin', action='append', metavar='MODULE[:CLASS]',
                   help='import a module defining effects (repeatable); they become '
                        'candidates and can be used in --model')
    p.add_argument('--folds', type=int, default=3,
                   help='contiguous time blocks of the cross-validation (default 3)')
    p.add_argument('--alpha', type=float, default=0.01,
                   help='family-wise significance level (Bonferroni; default 0.01)')
    p.add_argument('--robust', action='store_true',
                   help='robust loss for the base fit (spikes/outliers)')
    p.add_argument('--constrained', action='store_true',
                   help='priors on scale and angles, for partial attitude coverage (a '
                        'vehicle that cannot turn over); every fit of the diagnosis uses them')
    p.add_argument('--flag-degenerate', action='store_true',
                   help='diagnose degenerate data anyway and flag it instead of refusing')
    p.add_argument('--baseline-m', type=float, default=0.5, help='cross baseline, m')
    add_unit_arg(p)
    add_gaps_arg(p)
    p.add_argument('--rate-hz', type=float, default=100.0,
                   help='assumed sample rate of a single-sensor CSV without a time column')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress on stderr')
    add_attitude_arg(p)


def _run_diagnosis(args, with_ladder):
    from magcal_ros.core.discovery import diagnose, ladder
    from magcal_ros.core.model import Model
    from magcal_ros.pipeline import diagnosis_base
    if args.folds != 0 and args.folds < 2:
        raise BadInput(f'--folds must be 0 (no cross-validation) or >= 2, got {args.folds}')
    if not 0 < args.alpha < 1:
        raise BadInput(f'--alpha must be between 0 and 1, got {args.alpha}')
    load_plugins(args.plugin)
    prog = Progress(wanted(args.quiet, getattr(args, 'json', False)))
    data, _ = load_record(args.data, args.unit, args.rate_hz, progress=prog,
                          allow_gaps=args.allow_gaps)
    try:
        model = Model.from_spec(args.model, data.n_sensors)
    except ValueError as exc:
        raise BadInput(f'--model {args.model!r}: {exc}') from exc
    field_nt, fref = resolve_field(args, data)
    # readings no field produces (pinned, clipped, repeating channels, spikes): named, left out
    from magcal_ros.core.data.readings import leave_out_unphysical
    data, field_nt, screen = leave_out_unphysical(data, field_nt)
    prog('fit', 0, 1, ','.join(model.spec()))
    base, constrained, aided = diagnosis_base(
        data, model, field_nt, attitude=args.attitude, robust=args.robust,
        inclination_deg=fref.get('inclination_deg'), constrained=args.constrained,
        on_degenerate='flag' if args.flag_degenerate else 'raise')
    if aided is not None:
        fref = dict(fref, attitude=aided)
    prog('fit', 1, 1)
    kw = {'field_nt': field_nt, 'folds': args.folds, 'alpha': args.alpha, 'progress': prog,
          'baseline_m': args.baseline_m, 'constrained': constrained}
    diag = diagnose(data, base=base, **kw)
    if 'reduction' in data.meta:
        # a long record: the epochs are the whole record's, tested on its reduced sample
        from dataclasses import replace
        diag = replace(diag, n_samples=data.meta['reduction']['epochs'],
                       n_used=diag.n_used or diag.n_samples)
    lad = ladder(data, base, diagnosis=diag, **kw) if with_ladder else None
    return data, diag, lad, fref, screen, prog


def cmd_diagnose(args):
    """`magcal diagnose`: print the diagnosis (text or one JSON object)."""
    data, diag, lad, fref, screen, prog = _run_diagnosis(args, args.ladder)
    index = None
    if args.report:
        from magcal_ros.report import write_report
        index = write_report(args.report, data, diagnosis=diag, ladder=lad,
                             baseline_m=args.baseline_m, figures=args.figures, progress=prog)
    from magcal_ros.core.model.notes import note_dict
    from magcal_ros.pipeline import attitude_lines, fit_warnings
    warnings = [note_dict(w) for w in screen.notes()] + fit_warnings(diag.result, diag.noise_floor)
    if args.json:
        doc = {**diag.to_dict(), 'warnings': warnings, 'readings_left_out': screen.to_dict(),
               'field_reference': fref, 'constrained': bool(args.constrained)}
        if 'attitude' in fref:
            doc['attitude'] = fref['attitude']
            doc['undetermined'] = fref['attitude']['undetermined']
        doc['report'] = None if index is None else str(index)
        if 'reduction' in data.meta:
            doc['reduction'] = data.meta['reduction']
        if lad is not None:
            doc['ladder'] = lad.to_dict()
        print_json(doc)
    else:
        if 'reduction' in data.meta:
            print(reduction_line(data.meta['reduction']))
        print(diag.summary())
        if 'attitude' in fref:
            for line in attitude_lines(fref['attitude']):
                print(line)
        for w in warnings:
            print(format_note(w))
        if lad is not None:
            print('\nerror ladder (held-out RMS on contiguous time blocks):')
            print(lad.table())
        if index is not None:
            print(f'report written to {index}')
    return EXIT_OK


def cmd_report(args):
    """`magcal report`: diagnosis + error ladder as PNGs and a self-contained HTML page."""
    data, diag, lad, _, screen, prog = _run_diagnosis(args, not args.no_ladder)
    from magcal_ros.report import write_report
    if not args.quiet:
        for w in screen.notes():
            print(format_note(w), file=sys.stderr)
    index = write_report(args.out, data, diagnosis=diag, ladder=lad,
                         baseline_m=args.baseline_m, figures=args.figures, progress=prog)
    print(index)
    if not args.quiet:
        print(f'verdict: {diag.verdict_token or "none"} ({diag.verdict_reason})', file=sys.stderr)
    return EXIT_OK


def reduction_line(info):
    """One line saying that a long record was diagnosed on its reduction (and how)."""
    return (f'long record: {info["epochs"]} epochs over {info["span_s"]:.0f} s, read in '
            f'chunks; fitted and diagnosed on {info["sample_epochs"]} evenly spread epochs '
            f'(every {info["sample_stride"]}th), noise floor from {info["noise_blocks"]} '
            f'full-rate blocks of {info["noise_block_epochs"]} epochs')


def _figures_arg(p):
    p.add_argument('--figures', choices=('relevant', 'all'), default='relevant',
                   help="report views: 'relevant' (default) draws the residual against "
                        'temperature, aux channels and field rate, the direction map, the '
                        'change-point and lag views only when the diagnosis points at them '
                        "(the page lists the others and why); 'all' draws every view")


# -- main -----------------------------------------------------------------------------------

def build_parser():
    """Build the argparse parser of ``magcal``."""
    p = argparse.ArgumentParser(prog='magcal', description='Calibrate and diagnose vector '
                                'magnetometers and a four-fluxgate gradient tensor array.')
    sub = p.add_subparsers(dest='command', required=True)

    s = sub.add_parser('simulate', help='write a simulated cross-gradiometer recording (CSV)')
    s.add_argument('--out', required=True, help='output CSV file (.csv.gz, .csv.zst: compressed)')
    s.add_argument('--n', type=int, default=3000, help='number of samples (default 3000)')
    s.add_argument('--rate', type=float, default=100.0, help='sample rate, Hz')
    s.add_argument('--trajectory', default='smooth',
                   choices=['random', 'smooth', 'turntable', 'cone', 'vehicle'])
    s.add_argument('--noise-nt', type=float, default=3.0, help='noise sd per axis, nT')
    s.add_argument('--field-nt', type=float, default=50000.0, help='total field, nT')
    s.add_argument('--seed', type=int, default=0)
    s.add_argument('--model', default='base', help='truth model (default base)')
    s.add_argument('--truth', action='append', metavar='TERM=V1,V2,...',
                   help='switch on a hidden term with these parameter values (in the order of '
                   'its parameters, docs/formulas.md), e.g. temperature@2=3,-2,1.5,0,0,0 or '
                   "'offset(window(20, 40))@2=30,0,0'")
    s.add_argument('--no-aux', action='store_true', help='omit the auxiliary channels')
    s.add_argument('--ideal', action='store_true', help='ideal sensors (no paper 004 errors)')
    s.add_argument('--diurnal-nt', type=float, default=0.0,
                   help='peak-to-peak variation of the field magnitude (adds ref_total)')
    s.add_argument('--ref-total', action='store_true', help='write a ref_total column')
    s.add_argument('--outliers', type=float, default=0.0, help='fraction of spike outliers')
    s.add_argument('--plugin', action='append', help='import a module defining effects')
    s.add_argument('-q', '--quiet', action='store_true', help='no progress bar on stderr')
    s.add_argument('--site-gradient', metavar='GXX,GXY,GXZ,GYY,GYZ',
                   help='constant site gradient in the world (NED) frame, nT/m: the field is '
                        'not uniform over the cross (fit it with --model base,site_gradient)')
    s.add_argument('--attitude', action='store_true',
                   help='write the true attitude as att_qw..att_qz (body-to-world, NED), '
                        'as an IMU would give it')
    s.set_defaults(func=cmd_simulate)

    f = sub.add_parser('fit', help='fit a model and write a calibration file')
    f.add_argument('data', help='wide CSV file (.csv, .csv.gz, .csv.zst), rosbag2 directory, '
                                'or vehicle log (ArduPilot .bin/.log, PX4 .ulg)')
    f.add_argument('--model', default='base', help="effects, e.g. 'base,temperature@2'")
    f.add_argument('--method', default='ellipsoid', choices=['ellipsoid', 'sine', 'reference'],
                   help='ellipsoid: maximum-likelihood fit of --model from rotations in a '
                        'uniform field (paper 004, default); sine: turntable sine fits '
                        '(paper 000; columns angle_deg, plane); reference: least squares '
                        'against a reference vector (paper 002; columns ref_x, ref_y, ref_z)')
    f.add_argument('-o', '--output', help='calibration YAML to write')
    f.add_argument('--json', action='store_true', help='print one JSON object on stdout')
    add_field_args(f)
    add_unit_arg(f)
    add_gaps_arg(f)
    f.add_argument('--baseline-m', type=float, default=0.5, help='cross baseline, m')
    f.add_argument('--robust', action='store_true', help='robust (soft-L1) loss for outliers')
    f.add_argument('--constrained', action='store_true',
                   help='priors on scale and angles, for partial attitude coverage')
    f.add_argument('--flag-degenerate', action='store_true',
                   help='fit degenerate data anyway and flag the result instead of refusing')
    f.add_argument('--force', action='store_true',
                   help='write the calibration even when the fit did not converge')
    f.add_argument('--plugin', action='append', help='import a module defining effects')
    f.add_argument('-q', '--quiet', action='store_true', help='no progress bars on stderr')
    f.add_argument('--planar', action='store_true',
                   help='a turn about one axis only (a ground robot): fit what it determines '
                        '(in-plane offsets, scale ratio, angle: heading-grade), hold the rest '
                        'at a prior and name it; reports the heading error')
    add_attitude_arg(f)
    f.add_argument('--heading-unknown', action='store_true',
                   help='site_gradient without attitude columns: estimate the rotation about '
                        'the field at every epoch; the gradient is then given in a '
                        'field-aligned frame (docs/site_gradient.md)')
    f.set_defaults(func=cmd_fit)

    r = sub.add_parser('rollback', help='make an earlier calibration from the history of a '
                       'calibration file the active one')
    r.add_argument('calfile', help='the calibration YAML (its history is CALFILE.history/)')
    r.add_argument('--steps', type=int, default=1,
                   help='how many calibrations back from the active one (default 1); '
                        'repeated rollbacks walk further back')
    r.add_argument('--list', action='store_true',
                   help='list the history (oldest first, * = active) instead of rolling back')
    r.add_argument('--json', action='store_true', help='print one JSON object on stdout')
    r.set_defaults(func=cmd_rollback)

    c = sub.add_parser('check', help='check a calibration against static recordings: one '
                       '|B| at every attitude, equal to the reference, or why not')
    c.add_argument('calfile', help='calibration YAML written by magcal fit')
    c.add_argument('data', nargs='+', help='static recordings (wide CSV, also .csv.gz or '
                   '.csv.zst, rosbag2, or vehicle log), each at one attitude')
    c.add_argument('--sensor', type=int, default=1, help='sensor to check (default 1)')
    c.add_argument('-q', '--quiet', action='store_true', help='no progress bars on stderr')
    add_unit_arg(c)
    add_gaps_arg(c)
    c.add_argument('--json', action='store_true', help='print one JSON object on stdout')
    c.set_defaults(func=cmd_check)

    d = sub.add_parser('diagnose', help='find which physical effect the model is missing')
    _add_workbench_args(d)
    d.add_argument('--json', action='store_true', help='print one JSON object on stdout')
    d.add_argument('--report', metavar='DIR', help='also write the HTML/PNG report to DIR')
    d.add_argument('--ladder', action='store_true',
                   help='keep adding the verdict and refitting until nothing is missing')
    _figures_arg(d)
    d.set_defaults(func=cmd_diagnose)

    r = sub.add_parser('report', help='write an HTML page with the diagnosis plots')
    _add_workbench_args(r)
    r.add_argument('--out', required=True, metavar='DIR', help='output directory')
    r.add_argument('--no-ladder', action='store_true', help='skip the error ladder')
    _figures_arg(r)
    r.set_defaults(func=cmd_report)
    return p


def main(argv=None):
    """Entry point of ``magcal``."""
    limit_blas_threads()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:                     # BadInput and the library's refusals
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f'magcal: error: {msg}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return EXIT_FAIL
    except Exception as exc:                      # noqa: BLE001 - the CLI boundary
        print(f'magcal: failed: {type(exc).__name__}: {exc}', file=sys.stderr)
        return EXIT_FAIL


if __name__ == '__main__':
    sys.exit(main())
