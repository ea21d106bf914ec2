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
Real recordings: what the package makes of each public hand-held recording.

    python bench/real_data.py                 # every recording, with the diagnosis
    python bench/real_data.py --no-diagnose   # coverage, fit and floor only (faster)

Recordings: data/real/sunsided-hmc5883l (HMC5883L: full sphere, single-axis
rotations, pans, roll-and-tilt, static; PROVENANCE.md there) and ck-accmag (a consumer IMU's
full sphere, gauss, no time column).  Per recording: the attitude coverage verdict (judged
about the fitted centre), the noise floor of the data, and for the accepted ones the scalar
RMS of the base model against an independent geometric ellipsoid fit (the one of
test/test_real_sunsided.py, not this package's code) and the diagnosis verdict.  The static
recordings are corrected with the full-sphere calibration and checked by
``magcal_ros.core.data.static_check`` (the `magcal check` command).
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
sys.path.insert(0, os.path.join(common.REPO_DIR, 'test'))
from magcal_ros.core.data.magnitude import auto_magnitude  # noqa: E402
from magcal_ros.core.data.noise import noise_floor  # noqa: E402
from magcal_ros.core.data.static_check import check_static  # noqa: E402
from magcal_ros.core.model import DegenerateDataError, fit  # noqa: E402
from magcal_ros.core.model.identifiability import check_coverage  # noqa: E402
from magcal_ros.io.csvio import read_csv  # noqa: E402
from magcal_ros.io.single_csv import read_single_sensor_csv  # noqa: E402
import numpy as np  # noqa: E402
from test_real_sunsided import geometric_ellipsoid_fit  # noqa: E402

REAL = os.path.join(common.REPO_DIR, 'data', 'real')
HMC = os.path.join(REAL, 'sunsided-hmc5883l')


def recordings():
    """[(label, loader)] of every real recording, the full spheres first."""
    out = [('hmc5883l/full-sphere', lambda: read_csv(os.path.join(
        HMC, 'full-sphere', 'full-sphere.csv.gz'))),
        ('ck-accmag', lambda: read_single_sensor_csv(
            os.path.join(REAL, 'ck-accmag', 'acc_mag_log.csv.gz'), unit='gauss'))]
    for name in sorted(os.listdir(HMC)):
        path = os.path.join(HMC, name, f'{name}.csv.gz')
        if name != 'full-sphere' and os.path.exists(path):
            out.append((f'hmc5883l/{name}', lambda p=path: read_csv(p)))
    return out


def _fmt_axis(v):
    return '(' + ', '.join(f'{x:+.2f}' for x in v) + ')'


def one(label, data, f_full, diagnose_too):
    """Figures of one recording (dict)."""
    cov = check_coverage(data.raw)
    s = cov['sensors'][1]
    row = {'recording': label, 'samples': int(data.n_samples), 'coverage': s['status'],
           'floor_nt': float(noise_floor(data.raw)[0])}
    if cov['problems']:
        axis = f' about {_fmt_axis(s["normal"])}' if s['status'] == 'single axis' else ''
        row['verdict'] = f'refused: {s["status"]}{axis}'
        row['reason'] = cov['problems'][0]
        return row
    f = auto_magnitude(data.raw[0]) if f_full is None else f_full
    try:
        res = fit(data, 'base', field_nt=f)
    except DegenerateDataError as exc:
        row['verdict'] = 'refused'
        row['reason'] = str(exc)
        return row
    c, lmat = geometric_ellipsoid_fit(data.raw[0], f)
    m = data.raw[0]
    row.update(field_nt=float(f), scalar_rms_nt=float(res.scalar_rms_nt[1]),
               independent_rms_nt=float(np.sqrt(np.mean(
                   (np.linalg.norm((m - c) @ lmat.T, axis=1) - f) ** 2))),
               result=res)
    row['rms_over_floor'] = row['scalar_rms_nt'] / row['floor_nt']
    if diagnose_too:
        from magcal_ros.core.discovery import diagnose
        diag = diagnose(data, field_nt=f, base=res)
        row['verdict'] = diag.verdict_token or 'none'
        row['reason'] = diag.verdict_reason
    else:
        row['verdict'] = 'accepted'
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--no-diagnose', action='store_true', help='skip the diagnosis')
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    rows, full, full_fit, static = [], None, None, {}
    for label, load in recordings():
        data = load()
        row = one(label, data, None, not args.no_diagnose)
        result = row.pop('result', None)
        if label == 'hmc5883l/full-sphere':
            full, full_fit = row, result
        elif 'unmoved' in label:
            # the static ones: corrected with the full sphere's calibration
            static[label.split('/')[1]] = full_fit.calibration.correct(1, data.raw[0])
        rows.append(row)
        print(f'{label}: {row["coverage"]}, {row["verdict"]}', flush=True)
    check = check_static(static, full['field_nt'], full_fit.scalar_rms_nt[1])
    tables = [common.table(
        ['recording', 'samples', 'coverage', 'floor nT', 'scalar RMS nT',
         'independent fit nT', 'RMS / floor', 'verdict'],
        [[r['recording'], r['samples'], r['coverage'], r['floor_nt'], r.get('scalar_rms_nt'),
          r.get('independent_rms_nt'), r.get('rms_over_floor'), r['verdict']] for r in rows],
        title='Each real recording: coverage (about the fitted centre), noise floor, base '
              'model scalar RMS against an independent geometric ellipsoid fit, verdict')]
    tables.append(common.table(
        ['static recording', 'samples', 'field nT', 'minus full sphere nT', 'sd nT'],
        [[r['name'], r['n'], r['b_nt'], r['minus_reference_nt'], r['sd_nt']]
         for r in check.rows],
        title=f'Static recordings corrected with the full-sphere calibration (|B| '
              f'{full["field_nt"]:.0f} nT; agreement within {check.tolerance_nt:.0f} nT)')
        + '\n\n' + '\n'.join(f'- {t}' for t in check.findings))
    for t in tables:
        print('\n' + t)
    results = {'recordings': rows, 'static': {'rows': check.rows, 'findings': check.findings,
                                              'tolerance_nt': check.tolerance_nt,
                                              'consistent': check.consistent}}
    path = common.write_result('real_data', {'diagnose': not args.no_diagnose,
                                             'out_dir': args.out_dir},
                               results, tables, args.out_dir, started)
    print(f'\nwrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
