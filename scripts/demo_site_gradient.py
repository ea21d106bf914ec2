#!/usr/bin/env python3

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
The demo's site-gradient option (``scripts/demo.sh --site-gradient``): offline before/after.

Where the field is not uniform over the cross, the four sensors see different fields and a
``base`` calibration (paper 004, uniform field) cannot fit them. This script shows it on the
simulated cross with an attitude (docs/site_gradient.md):

1. ``magcal simulate --site-gradient G --attitude``: paper 004's cross (Table 1 errors) turning
   smoothly in a constant world-frame gradient ``G`` (nT/m, symmetric and traceless: five
   numbers GXX,GXY,GXZ,GYY,GYZ, gzz = -gxx - gyy), with the true attitude as att_qw..att_qz;
2. ``magcal fit --model base`` (before: the gradient is not modelled);
3. ``magcal fit --model base,site_gradient`` (after: the gradient is fitted with the
   calibration).

The same library calls as those commands run in-process (so that the per-set residuals can be
drawn); the commands are printed for the user to rerun on the CSV left in the output folder.
Writes ``site_gradient_residuals.png`` (per-sensor total-field residual, before/after),
``site_gradient_tensor.png`` (recovered gradient against the truth, +- 2 standard
uncertainties) and ``summary.json`` to ``--out`` and prints a before/after table against the
noise floor. The exit status is 0 only if the ``base,site_gradient`` fit leaves every sensor
within :data:`ACCEPT_FACTOR` of the noise floor and recovers every gradient component within
:data:`Z_MAX` standard uncertainties of the truth.

This path is OFFLINE: the live demo (simulated fluxgates + ROS nodes) does not take a site
gradient yet.
"""
import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: default site gradient GXX,GXY,GXZ,GYY,GYZ (nT/m): a few hundred nT/m, as near buildings
DEFAULT_GRADIENT = '300,-250,400,-150,200'
#: the fitted residual must stay within this factor of the noise floor (as scripts/demo.py)
ACCEPT_FACTOR = 1.5
#: recovered gradient components must lie within this many standard uncertainties of the truth
Z_MAX = 4.0
COMPONENTS = ('gxx', 'gxy', 'gxz', 'gyy', 'gyz')
FIELD_NT = 50000.0


def parse_gradient(text):
    """Five numbers 'GXX,GXY,GXZ,GYY,GYZ' (nT/m) -> (5,) array; SystemExit(2) if malformed."""
    try:
        g5 = np.array([float(v) for v in text.split(',')])
    except ValueError:
        g5 = np.array([])
    if g5.shape != (5,) or not np.all(np.isfinite(g5)):
        print(f'demo: --site-gradient {text!r}: expected five numbers GXX,GXY,GXZ,GYY,GYZ in '
              'nT/m (gzz = -gxx - gyy), e.g. --site-gradient=' + DEFAULT_GRADIENT,
              file=sys.stderr)
        raise SystemExit(2)
    return g5


def scalar_residuals(run, field_nt):
    """(S, N) nT: |field at the array centre| - F per sensor and set (about the modelled shift)."""
    from magcal_ros.core.model.site_gradient import centred_fields
    return np.linalg.norm(centred_fields(run.result), axis=-1) - field_nt


def fit(data, model, geometry):
    """Run the fit of ``magcal fit DATA --model MODEL --field-nt 50000`` (magcal_ros.cli)."""
    from magcal_ros.pipeline import calibrate
    return calibrate(data, model, field_nt=FIELD_NT, geometry=geometry,
                     field_reference={'kind': 'constant', 'magnitude_nt': FIELD_NT})


def make_figures(out, res_before, res_after, floor, g_true, g_fit, g_se):
    """Write the residual and tensor figures (PNG) to ``out``; return their file names."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    n_s = res_before.shape[0]
    fig = Figure(figsize=(9, 2.2 * n_s))
    FigureCanvasAgg(fig)
    for j in range(n_s):
        ax = fig.add_subplot(n_s, 1, j + 1)
        ax.plot(res_before[j], lw=0.6, color='tab:red',
                label=f'base (RMS {np.sqrt(np.mean(res_before[j] ** 2)):.1f} nT)')
        ax.plot(res_after[j], lw=0.6, color='tab:blue',
                label=f'base,site_gradient (RMS {np.sqrt(np.mean(res_after[j] ** 2)):.2f} nT)')
        ax.axhspan(-floor, floor, color='0.85', label=f'+- noise floor {floor:.2f} nT')
        ax.set_ylabel(f'sensor {j + 1}\n|B| - F [nT]')
        ax.legend(loc='upper right', fontsize=7)
    ax.set_xlabel('set')
    fig.suptitle('total-field residual per sensor: base (before) vs base,site_gradient (after)')
    fig.tight_layout()
    names = ['site_gradient_residuals.png', 'site_gradient_tensor.png']
    fig.savefig(out / names[0], dpi=90)

    fig = Figure(figsize=(10, 3.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    x = np.arange(len(COMPONENTS))
    ax.bar(x - 0.2, g_true, width=0.4, color='0.6', label='true')
    ax.errorbar(x + 0.2, g_fit, yerr=2 * g_se, fmt='o', color='tab:blue', capsize=4,
                label='recovered +- 2 sigma')
    ax.set_xticks(x, COMPONENTS)
    ax.set_ylabel('nT/m (world frame)')
    ax.axhline(0, color='k', lw=0.5)
    ax.legend(fontsize=8)
    ax.set_title('site gradient recovered by base,site_gradient')
    ax = fig.add_subplot(1, 2, 2)      # the error at its own scale, against the uncertainty
    ax.errorbar(x, g_fit - g_true, yerr=2 * g_se, fmt='o', color='tab:blue', capsize=4,
                label='recovered - true, +- 2 sigma')
    ax.axhline(0, color='k', lw=0.5)
    ax.set_xticks(x, COMPONENTS)
    ax.set_ylabel('nT/m')
    ax.legend(fontsize=8)
    ax.set_title('error of the recovered gradient')
    fig.tight_layout()
    fig.savefig(out / names[1], dpi=90)
    return names


def main(argv=None):
    """Simulate, fit base and base,site_gradient, write figures and summary; exit status."""
    p = argparse.ArgumentParser(
        prog='scripts/demo.sh',
        description='Offline before/after of a site gradient on the simulated cross with '
                    'attitude: magcal simulate -> magcal fit --model base -> magcal fit '
                    '--model base,site_gradient (the live demo does not take a gradient yet).')
    p.add_argument('--site-gradient', nargs='?', const=DEFAULT_GRADIENT, required=True,
                   metavar='GXX,GXY,GXZ,GYY,GYZ',
                   help=f'world-frame (NED) site gradient, nT/m (default {DEFAULT_GRADIENT}; '
                        'a negative first value needs the = form: --site-gradient=-300,...)')
    p.add_argument('--out', default='demo_out', help='output folder (default ./demo_out)')
    p.add_argument('--n', type=int, default=3000,
                   help='number of sets (100 Hz, smooth tumble; default 3000)')
    p.add_argument('--noise-nt', type=float, default=3.0, help='noise sd per axis, nT')
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args(argv)
    g5 = parse_gradient(args.site_gradient)
    if args.n < 100 or not args.noise_nt > 0:
        p.error('--n must be >= 100 and --noise-nt > 0')

    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.core.geometry.tensor import symmetric_traceless
    from magcal_ros.io.csvio import write_csv
    from magcal_ros.pipeline import cross_geometry
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv = out / 'site.csv'
    g_text = ','.join(f'{v:g}' for v in g5)
    commands = [
        f'magcal simulate --out {csv} --site-gradient={g_text} --attitude --n {args.n} '
        f'--noise-nt {args.noise_nt:g} --seed {args.seed}',
        f'magcal fit {csv} --model base --field-nt {FIELD_NT:g} --json',
        f'magcal fit {csv} --model base,site_gradient --field-nt {FIELD_NT:g} --json']
    print('site-gradient demo (OFFLINE: simulated cross with attitude; the live ROS demo does '
          'not take a site gradient yet). Equivalent commands:')
    for c in commands:
        print('  ' + c)
    data, _ = simulate(gradient_nt_per_m=symmetric_traceless(g5), attitude=True,
                       n_samples=args.n, rate_hz=100.0, trajectory='smooth',
                       noise_nt=args.noise_nt, seed=args.seed,
                       field_nt=FIELD_NT, errors='paper004')
    write_csv(csv, data, comment='scripts/demo.sh --site-gradient: ' + commands[0])
    geometry = cross_geometry(0.5)
    try:
        before = fit(data, 'base', geometry)
        after = fit(data, 'base,site_gradient', geometry)
    except ValueError as exc:           # an identifiability refusal names what to change
        print(f'demo: the fit refused the data: {exc}', file=sys.stderr)
        return 1

    floor = float(after.summary['noise_floor_nt'])
    floor_status = after.summary['noise_floor_status']
    res_b = scalar_residuals(before, FIELD_NT)
    res_a = scalar_residuals(after, FIELD_NT)
    rms_b = np.sqrt(np.mean(res_b ** 2, axis=1))
    rms_a = np.sqrt(np.mean(res_a ** 2, axis=1))
    g_fit_m = np.array(after.summary['site_gradient_nt_per_m'])
    g_se_m = np.array(after.summary['site_gradient_stderr_nt_per_m'])
    idx = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2)]
    g_fit = np.array([g_fit_m[i] for i in idx])
    g_se = np.array([g_se_m[i] for i in idx])
    z = (g_fit - g5) / g_se
    at_floor = bool(np.all(rms_a <= ACCEPT_FACTOR * floor))
    g_ok = bool(np.all(np.abs(z) <= Z_MAX))
    ok = at_floor and g_ok and bool(after.result.success)
    figures = make_figures(out, res_b, res_a, floor, g5, g_fit, g_se)

    sensors = [str(j + 1) for j in range(len(rms_b))]
    summary = {
        'mode': 'offline (simulated cross with attitude; the live demo takes no gradient yet)',
        'commands': commands,
        'n_sets': int(args.n),
        'noise_sd_simulated_nt': args.noise_nt,
        'field_nt': FIELD_NT,
        'noise_floor_nt': floor,
        'noise_floor_status': floor_status,
        'scalar_rms_before_nt': dict(zip(sensors, rms_b.tolist())),
        'scalar_rms_after_nt': dict(zip(sensors, rms_a.tolist())),
        'tensor_rms_before_max_nt_per_m': float(np.max(before.summary['tensor_rms_nt_per_m'])),
        'tensor_rms_after_max_nt_per_m': float(np.max(after.summary['tensor_rms_nt_per_m'])),
        'tensor_floor_max_nt_per_m': float(np.max(after.summary['tensor_floor_nt_per_m'])),
        'gradient_components': list(COMPONENTS),
        'gradient_true_nt_per_m': g5.tolist(),
        'gradient_fit_nt_per_m': g_fit.tolist(),
        'gradient_stderr_nt_per_m': g_se.tolist(),
        'gradient_z': z.tolist(),
        'gradient_frame': after.summary['site_gradient_frame'],
        'base_converged': bool(before.result.success),
        'site_gradient_converged': bool(after.result.success),
        'accept_factor': ACCEPT_FACTOR,
        'z_max': Z_MAX,
        'after_at_floor': at_floor,
        'gradient_within_uncertainty': g_ok,
        'ok': ok,
        'figures': figures,
        'csv': csv.name,
    }
    (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')

    print(f'\n{"sensor":>6}  {"base RMS [nT]":>14}  {"base,site_gradient RMS [nT]":>28}'
          f'   (noise floor {floor:.2f} nT, {"/".join(sorted(set(floor_status.values())))})')
    for s, b, a in zip(sensors, rms_b, rms_a):
        print(f'{s:>6}  {b:14.2f}  {a:28.2f}')
    print(f'tensor RMS max: base {summary["tensor_rms_before_max_nt_per_m"]:.1f} nT/m, '
          f'base,site_gradient {summary["tensor_rms_after_max_nt_per_m"]:.1f} nT/m '
          f'(noise floor {summary["tensor_floor_max_nt_per_m"]:.1f} nT/m)')
    print(f'site gradient ({summary["gradient_frame"]}), nT/m:')
    for c, t, f, e, zz in zip(COMPONENTS, g5, g_fit, g_se, z):
        print(f'  {c}: true {t:8.1f}  fitted {f:8.2f} +- {e:.2f}  ({zz:+.1f} sigma)')
    print(f'figures and summary.json in {out}/')
    if not ok:
        print('demo: FAILED: ' + ('' if at_floor else
                                  f'a sensor is above {ACCEPT_FACTOR} x the noise floor; ')
              + ('' if g_ok else f'a gradient component is beyond {Z_MAX:g} sigma of the '
                 'truth; ') + ('' if after.result.success else 'the fit did not converge'),
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
