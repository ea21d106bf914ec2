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
`magcal diagnose` and `magcal report` (docs/design.md §2), registered by magcal_ros.cli.

- ``magcal diagnose DATA --model MODEL [--json] [--report DIR] [--ladder] [--constrained]``:
  noise floor, residuals, every missing effect ranked by evidence, verdict; ``--ladder``
  keeps adding the verdict until nothing is missing.
- ``magcal report DATA --model MODEL --out DIR``: the same plus the error ladder, as PNG
  figures and one self-contained ``index.html``.

DATA as for ``magcal fit`` (``cli.load_record``: a long record is read in chunks and
reduced); progress on stderr when it is a terminal (:mod:`magcal_ros.progress`).  Exit
status 0 on success, 2 on bad input, 1 on other failures (:func:`magcal_ros.cli.main`).
"""
import sys

from magcal_ros.core.effects import load_plugins
from magcal_ros.pipeline import attitude_lines, attitude_mode, diagnosis_base
from magcal_ros.progress import Progress, wanted


def _common(p, cli):
    p.add_argument('data', help='wide CSV file (.csv, .csv.gz, .csv.zst), rosbag2 directory, '
                                'vehicle log (ArduPilot .bin/.log, PX4 .ulg), or '
                                'single-sensor CSV (with --unit)')
    p.add_argument('--model', default='base',
                   help="effects of the model to diagnose, e.g. 'base,temperature@2' "
                        '(default base)')
    cli.add_field_args(p)
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
    cli.add_unit_arg(p)
    cli.add_gaps_arg(p)
    p.add_argument('--rate-hz', type=float, default=100.0,
                   help='assumed sample rate of a single-sensor CSV without a time column')
    p.add_argument('-q', '--quiet', action='store_true', help='no progress on stderr')
    cli.add_attitude_arg(p)


def _run(args, cli, with_ladder):
    from magcal_ros.core.discovery import diagnose, ladder
    from magcal_ros.core.model import Model
    if args.folds != 0 and args.folds < 2:
        raise cli.BadInput(f'--folds must be 0 (no cross-validation) or >= 2, got {args.folds}')
    if not 0 < args.alpha < 1:
        raise cli.BadInput(f'--alpha must be between 0 and 1, got {args.alpha}')
    load_plugins(args.plugin)
    prog = Progress(wanted(args.quiet, getattr(args, 'json', False)))
    data, _ = cli.load_record(args.data, args.unit, args.rate_hz, progress=prog,
                              allow_gaps=args.allow_gaps)
    try:
        model = Model.from_spec(args.model, data.n_sensors)
    except ValueError as exc:
        raise cli.BadInput(f'--model {args.model!r}: {exc}') from exc
    field_nt, fref = cli.resolve_field(args, data)
    # readings no field produces (pinned, clipped, repeating channels, spikes): named, left out
    from magcal_ros.core.data.readings import leave_out_unphysical
    data, field_nt, screen = leave_out_unphysical(data, field_nt)
    prog('fit', 0, 1, ','.join(model.spec()))
    base, constrained, aided = diagnosis_base(
        data, model, field_nt, attitude=attitude_mode(args.attitude, data) or 'off',
        inclination_deg=fref.get('inclination_deg'), robust=args.robust,
        constrained=args.constrained,
        on_degenerate='flag' if args.flag_degenerate else 'raise')
    if aided is not None:
        fref = dict(fref, attitude=aided)
    prog('fit', 1, 1)
    diag = diagnose(data, field_nt=field_nt, base=base, folds=args.folds, alpha=args.alpha,
                    progress=prog, baseline_m=args.baseline_m, constrained=constrained)
    if 'reduction' in data.meta:
        # a long record: the epochs are the whole record's, tested on its reduced sample
        from dataclasses import replace
        diag = replace(diag, n_samples=data.meta['reduction']['epochs'],
                       n_used=diag.n_used or diag.n_samples)
    lad = None
    if with_ladder:
        lad = ladder(data, base, field_nt=field_nt, folds=args.folds, progress=prog,
                     diagnosis=diag, alpha=args.alpha, baseline_m=args.baseline_m,
                     constrained=constrained)
    return data, diag, lad, fref, screen, prog


def cmd_diagnose(args, cli):
    """`magcal diagnose`: print the diagnosis (text or one JSON object)."""
    data, diag, lad, fref, screen, prog = _run(args, cli, args.ladder)
    index = None
    if args.report:
        from magcal_ros.report import write_report
        index = write_report(args.report, data, diagnosis=diag, ladder=lad,
                             baseline_m=args.baseline_m, figures=args.figures, progress=prog)
    from magcal_ros.core.model.notes import format_note, note_dict
    from magcal_ros.pipeline import fit_warnings
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
        cli.print_json(doc)
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
    return cli.EXIT_OK


def cmd_report(args, cli):
    """`magcal report`: diagnosis + error ladder as PNGs and a self-contained HTML page."""
    data, diag, lad, _, screen, prog = _run(args, cli, not args.no_ladder)
    from magcal_ros.core.model.notes import format_note
    from magcal_ros.report import write_report
    if not args.quiet:
        for w in screen.notes():
            print(format_note(w), file=sys.stderr)
    index = write_report(args.out, data, diagnosis=diag, ladder=lad,
                         baseline_m=args.baseline_m, figures=args.figures, progress=prog)
    print(index)
    if not args.quiet:
        print(f'verdict: {diag.verdict_token or "none"} ({diag.verdict_reason})', file=sys.stderr)
    return cli.EXIT_OK


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


def register(sub, cli):
    """Add the ``diagnose`` and ``report`` sub-commands to the ``magcal`` parser."""
    d = sub.add_parser('diagnose', help='find which physical effect the model is missing')
    _common(d, cli)
    d.add_argument('--json', action='store_true', help='print one JSON object on stdout')
    d.add_argument('--report', metavar='DIR', help='also write the HTML/PNG report to DIR')
    d.add_argument('--ladder', action='store_true',
                   help='keep adding the verdict and refitting until nothing is missing')
    _figures_arg(d)
    d.set_defaults(func=lambda a: cmd_diagnose(a, cli))

    r = sub.add_parser('report', help='write an HTML page with the diagnosis plots')
    _common(r, cli)
    r.add_argument('--out', required=True, metavar='DIR', help='output directory')
    r.add_argument('--no-ladder', action='store_true', help='skip the error ladder')
    _figures_arg(r)
    r.set_defaults(func=lambda a: cmd_report(a, cli))
