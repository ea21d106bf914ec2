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
Papers 000 and 002 on their own scenarios, against this package's refined fit on the same data.

Paper 000 (sine fits on a two-position turntable, :mod:`magcal_ros.core.papers.sine`): the sensor
of
the paper's section 3.1 (alpha 1.35 deg, beta 32.7 deg, gamma 1.07 deg, k = 0.909, 1.146,
1.103, B0 = (143, 97.4, 123.7) nT; |B| = 50 000 nT, I = 43 deg) turned in 36 equal steps in
each of the two positions, Gaussian noise sigma = 3 nT and 25 nT.

Paper 002 (reference least squares ``Hm = K He + Hh``,
:mod:`magcal_ros.core.papers.reference_vector`):
a Helmholtz-coil field of 4 000 nT as in the paper, a soft-iron K and hard-iron Hh of an iron
plate (K = [[1.08, .03, -.02], [.05, .95, .04], [-.01, .02, 1.12]], Hh = (350, -220, 480) nT),
60 random attitudes, reading noise 3 nT and reference noise 1 nT per axis; plus the paper's
own Table 2 (six attitudes turned about one axis), where both methods must say the data
cannot determine the model.

The refined fit is :func:`magcal_ros.core.model.fit` with one sensor and the field magnitude
known (``offset,scale,nonorthogonality`` for paper 000's model, ``offset,soft_iron`` for
paper 002's), i.e. it uses the magnitude only, where the papers also use the turntable angles
or the reference vector.  A magnitude fixes A A^T and the offset, not the rotation of A, so
the methods are compared on what both determine:

- held-out scalar residual RMS (2000 random attitudes over the whole sphere) over the noise
  floor (the same residual with the true parameters);
- error of A A^T (RMS over its 6 entries, ppm) and of the offset (RMS over 3 axes, nT), as
  RMS over seeds, with the Cramer-Rao bound of the refined fit at the truth for scale;
- paper 002 only: vector error of the corrected field against the true field on held-out
  attitudes (its reference fixes the orientation; the refined fit's field is in the sensor's
  own frame, so its figure is after the best rotation, as is paper 002's second figure).

    python bench/papers.py --seeds 100
"""
import argparse
import io
import os
import sys
import time
import warnings

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
from magcal_ros.core import model as mdl  # noqa: E402
from magcal_ros.core.data.dataset import Dataset  # noqa: E402
from magcal_ros.core.model.engine import ProfiledProblem  # noqa: E402
from magcal_ros.core.model.solvers import covariance_from_jacobian  # noqa: E402
from magcal_ros.core.papers import reference_vector as ref  # noqa: E402
from magcal_ros.core.papers import sine  # noqa: E402
from magcal_ros.core.papers.paper_params import Paper000Params  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

P000 = Paper000Params(alpha=np.radians(1.35), beta=np.radians(32.7), gamma=np.radians(1.07),
                      kx=0.909, ky=1.146, kz=1.103, B0=np.array([143.0, 97.4, 123.7]))
F000 = 50000.0
I000 = np.radians(43.0)
K002 = np.array([[1.08, 0.03, -0.02], [0.05, 0.95, 0.04], [-0.01, 0.02, 1.12]])
HH002 = np.array([350.0, -220.0, 480.0])
F002 = 4000.0
TABLE2 = os.path.join(common.REPO_DIR, 'test', 'data', 'paper002_table2.csv')


def _random_field(rng, n, magnitude):
    return Rotation.random(n, random_state=rng).apply([0.0, 0.0, magnitude])


def _aat(a):
    return a @ a.T


def _aat_err(a_est, a_true):
    """RMS over the 6 distinct entries of A A^T, dimensionless."""
    d = _aat(a_est) - _aat(a_true)
    return float(np.sqrt(np.mean(d[np.triu_indices(3)] ** 2)))


def _scalar_rms(corr, f):
    return float(np.sqrt(np.mean((np.linalg.norm(corr, axis=1) - f) ** 2)))


def _aligned_vector_rms(est, true):
    rot, _ = Rotation.align_vectors(true, est)
    return float(np.sqrt(np.mean((rot.apply(est) - true) ** 2)))


def _refined(raw, f, spec, init=None):
    """
    Single-sensor refined fit; returns (A, o, FitResult) or raises ValueError.

    ``init`` = (A, o) of another method to start from (default: the closed-form start).
    """
    n = len(raw)
    data = Dataset(t=np.arange(n, dtype=float), raw=raw[None])
    model = mdl.Model.from_spec(spec, 1)
    p0 = None if init is None else model.params_from_linear(1, *init)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        res = mdl.fit(data, model, field_nt=f, on_degenerate='flag', init=p0)
    cal = res.calibration
    return cal.matrix(1), cal.offset(1), res


def _crb_scale_ppm(raw, f, spec, a, o, sigma):
    """Return the square root of the mean CRB of the scale factors at the truth (ppm)."""
    n = len(raw)
    data = Dataset(t=np.arange(n, dtype=float), raw=raw[None])
    model = mdl.Model.from_spec(spec, 1)
    p = model.params_from_linear(1, a, o)
    contexts = [data.context(1)]
    prob = ProfiledProblem(model, data.raw, contexts, np.full(n, f), [1], np.array([sigma]),
                           p_full=p)
    cov = covariance_from_jacobian(prob.jacobian(p))
    names = [nm for _, lab, nm, _ in model.param_info()]
    info = model.param_info()
    sel = [i for i, (_, lab, _, _) in enumerate(info) if lab == 'scale']
    if not sel:
        return None
    del names
    return float(np.sqrt(np.mean(np.diag(cov)[sel])) * 1e6)


def paper000(seeds, sigma, n_steps, n_hold, first_seed):
    """Monte Carlo of paper 000 vs the refined fit on the turntable data."""
    a_true, o_true = P000.to_general()
    rows = {'paper000': [], 'refined': [], 'refined_from_paper000': []}
    crb = []
    floor = []
    t_m = dict.fromkeys(rows, 0.0)
    for k in range(seeds):
        rng = np.random.default_rng(first_seed + k)
        d = sine.simulate_turntable(P000, F000, I000, n_steps, noise_sigma=sigma, rng=rng)
        b_hold = _random_field(rng, n_hold, F000)
        raw_hold = b_hold @ a_true.T + o_true + sigma * rng.standard_normal(b_hold.shape)
        fl = _scalar_rms((raw_hold - o_true) @ np.linalg.inv(a_true).T, F000)
        floor.append(fl)
        # paper 000: eq. 4-16
        t0 = time.perf_counter()
        p = sine.calibrate_turntable(d.theta, d.raw1, d.theta, d.raw2, F000)
        t_m['paper000'] += time.perf_counter() - t0
        a0, o0 = p.to_general()
        rows['paper000'].append({
            'scalar': _scalar_rms(sine.correct(p, raw_hold), F000) / fl,
            'aat': _aat_err(a0, a_true), 'off': float(np.sqrt(np.mean((o0 - o_true) ** 2)))})
        # refined fit on both positions together, magnitude known
        raw = np.vstack([d.raw1, d.raw2])
        for meth, init in (('refined', None), ('refined_from_paper000', (a0, o0))):
            t0 = time.perf_counter()
            try:
                a1, o1, res = _refined(raw, F000, 'offset,scale,nonorthogonality', init)
            except ValueError as exc:
                rows[meth].append({'error': str(exc).splitlines()[0][:160]})
            else:
                corr = (raw_hold - o1) @ np.linalg.inv(a1).T
                rows[meth].append({
                    'scalar': _scalar_rms(corr, F000) / fl, 'aat': _aat_err(a1, a_true),
                    'off': float(np.sqrt(np.mean((o1 - o_true) ** 2))),
                    'warnings': len(res.warnings), 'first_warning': (res.warnings or [''])[-1]})
            t_m[meth] += time.perf_counter() - t0
        crb.append(_crb_scale_ppm(raw, F000, 'offset,scale,nonorthogonality', a_true, o_true,
                                  sigma))
    return _summ(rows, t_m, seeds, crb, floor, sigma)


def _summ(rows, t_m, seeds, crb, floor, sigma):
    crb = [c for c in crb if c]
    out = {'sigma_nt': sigma, 'floor_over_sigma': float(np.mean(floor) / sigma),
           'crb_scale_ppm': float(np.sqrt(np.mean(np.square(crb)))) if crb else None,
           'methods': {}}
    for meth, rs in rows.items():
        ok = [r for r in rs if 'error' not in r]
        m = {'n_ok': len(ok), 'n_failed': len(rs) - len(ok),
             'errors': sorted({r['error'] for r in rs if 'error' in r})[:3],
             'seconds_mean': t_m[meth] / seeds}
        if ok:
            m['scalar_hold_over_floor'] = float(np.mean([r['scalar'] for r in ok]))
            m['aat_error_rms_ppm'] = float(np.sqrt(np.mean([r['aat'] ** 2 for r in ok])) * 1e6)
            m['offset_error_rms_nt'] = float(np.sqrt(np.mean([r['off'] ** 2 for r in ok])))
            for key in ('vec', 'vec_aligned'):
                vals = [r[key] for r in ok if key in r]
                if vals:
                    m[f'{key}_rms_nt'] = float(np.sqrt(np.mean(np.square(vals))))
            m['flagged'] = int(sum(1 for r in ok if r.get('warnings')))
            notes = sorted({r['first_warning'][:200] for r in ok if r.get('first_warning')})
            if notes:
                m['warning_example'] = notes[0]
        out['methods'][meth] = m
    return out


def paper002(seeds, sigma_hm, sigma_he, n_att, n_hold, first_seed):
    """Monte Carlo of paper 002 vs the refined fit, full 3-D attitudes."""
    rows = {'paper002': [], 'refined': []}
    t_m = {'paper002': 0.0, 'refined': 0.0}
    crb, floor = [], []
    for k in range(seeds):
        rng = np.random.default_rng(first_seed + k)
        he = _random_field(rng, n_att, F002)
        hm = he @ K002.T + HH002 + sigma_hm * rng.standard_normal(he.shape)
        he_meas = he + sigma_he * rng.standard_normal(he.shape)
        b_hold = _random_field(rng, n_hold, F002)
        raw_hold = b_hold @ K002.T + HH002 + sigma_hm * rng.standard_normal(b_hold.shape)
        true_corr = (raw_hold - HH002) @ np.linalg.inv(K002).T
        fl = _scalar_rms(true_corr, F002)
        floor.append(fl)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            fr = ref.fit_reference(he_meas, hm)
        t_m['paper002'] += time.perf_counter() - t0
        c2 = ref.correct(fr, raw_hold)
        rows['paper002'].append({
            'scalar': _scalar_rms(c2, F002) / fl, 'aat': _aat_err(fr.K, K002),
            'off': float(np.sqrt(np.mean((fr.Hh - HH002) ** 2))),
            'vec': float(np.sqrt(np.mean((c2 - b_hold) ** 2))),
            'vec_aligned': _aligned_vector_rms(c2, b_hold),
            'warnings': 0 if fr.identifiable else 1})
        t0 = time.perf_counter()
        try:
            a1, o1, res = _refined(hm, F002, 'offset,soft_iron')
        except ValueError as exc:
            rows['refined'].append({'error': str(exc).splitlines()[0][:160]})
        else:
            c1 = (raw_hold - o1) @ np.linalg.inv(a1).T
            rows['refined'].append({
                'scalar': _scalar_rms(c1, F002) / fl, 'aat': _aat_err(a1, K002),
                'off': float(np.sqrt(np.mean((o1 - HH002) ** 2))),
                'vec_aligned': _aligned_vector_rms(c1, b_hold), 'warnings': len(res.warnings)})
        t_m['refined'] += time.perf_counter() - t0
        crb.append(None)
    out = _summ(rows, t_m, seeds, crb, floor, sigma_hm)
    out['sigma_he_nt'] = sigma_he
    out['n_attitudes'] = n_att
    return out


def table2_case():
    """Paper 002's Table 2 (single-axis rotation): what each method says."""
    lines = [ln for ln in open(TABLE2) if not ln.startswith('#')]
    d = np.genfromtxt(io.StringIO(''.join(lines)), delimiter=',', names=True)
    he = np.column_stack([d['ref_x'], d['ref_y'], d['ref_z']])
    hm = np.column_stack([d['s1_x'], d['s1_y'], d['s1_z']])
    fr = ref.fit_reference(he, hm)
    out = {'paper002': {'identifiable': bool(fr.identifiable),
                        'message': (fr.warning or '')[:300],
                        'condition_number': float(fr.condition_number),
                        'fit_rms_nt': [float(x) for x in fr.rms]}}
    out['refined'] = _refine_or_refuse(hm, np.linalg.norm(he, axis=1))
    # the paper's procedure with more attitudes: 36 steps of 10 deg about one axis
    rng = np.random.default_rng(2)
    he = Rotation.from_euler('z', np.radians(np.arange(0, 360, 10.0))[:, None]).apply(
        F002 * np.array([np.cos(np.radians(60)), 0.0, np.sin(np.radians(60))]))
    hm = he @ K002.T + HH002 + 3.0 * rng.standard_normal(he.shape)
    fr = ref.fit_reference(he, hm)
    out['planar36'] = {'paper002': {'identifiable': bool(fr.identifiable),
                                    'message': (fr.warning or '')[:300]},
                       'refined': _refine_or_refuse(hm, F002)}
    return out


def _refine_or_refuse(hm, f):
    data = Dataset(t=np.arange(len(hm), dtype=float), raw=hm[None])
    try:
        mdl.fit(data, 'offset,soft_iron', field_nt=f)
        return {'refused': False, 'message': 'fit accepted the data'}
    except ValueError as exc:
        return {'refused': True, 'message': str(exc)[:300]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--seeds', type=int, default=100)
    ap.add_argument('--holdout', type=int, default=2000)
    ap.add_argument('--first-seed', type=int, default=5000)
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    res = {}
    for sigma in (3.0, 25.0):
        res[f'paper000_sigma{sigma:g}'] = paper000(args.seeds, sigma, 36, args.holdout,
                                                   args.first_seed)
    res['paper002_3d'] = paper002(args.seeds, 3.0, 1.0, 60, args.holdout, args.first_seed)
    res['paper002_table2'] = table2_case()

    rows = []
    for name, r in res.items():
        if 'methods' not in r:
            continue
        for meth, m in r['methods'].items():
            if not m['n_ok']:
                rows.append([name, meth, '-', '-', '-', '-', '-', f'{m["n_failed"]} failed'])
                continue
            rows.append([name, meth, f'{m["scalar_hold_over_floor"]:.3f}',
                         f'{m["aat_error_rms_ppm"]:.0f}', f'{m["offset_error_rms_nt"]:.2f}',
                         f'{m["vec_rms_nt"]:.2f}' if 'vec_rms_nt' in m else 'n/a',
                         f'{m["vec_aligned_rms_nt"]:.2f}' if 'vec_aligned_rms_nt' in m
                         else '-',
                         (f'{m["n_failed"]} failed ' if m['n_failed'] else '')
                         + (f'{m["flagged"]} flagged' if m.get('flagged') else '')])
    t1 = common.table(['scenario', 'method', 'held-out scalar / floor', 'A A^T err ppm',
                       'offset err nT', 'vector err nT', 'vector err (aligned) nT', 'note'],
                      rows, title=f'Papers 000 and 002 on their own scenarios '
                      f'({args.seeds} seeds; RMS over seeds)')
    t2 = res['paper002_table2']
    rows2 = []
    for label, case in (('Table 2 (6 attitudes)', t2), ('36 steps, one axis', t2['planar36'])):
        rows2.append([label, 'paper002', ('identifiable' if case['paper002']['identifiable']
                                          else 'flagged: ') + case['paper002']['message'][:110]])
        rows2.append([label, 'refined', ('refused: ' if case['refined']['refused'] else '')
                      + case['refined']['message'][:110]])
    t2s = common.table(['data', 'method', 'outcome (rotation about one axis only)'], rows2,
                       title='Paper 002 single-axis data')
    tables = [t1, t2s]
    for t in tables:
        print()
        print(t)
    path = common.write_result('papers', vars(args), res, tables, args.out_dir, started)
    print(f'\nwrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
