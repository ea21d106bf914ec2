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
Solve time and scaling: calibrate and diagnose 4 sensors for N = 1e3 .. 1e6 samples.

Each case runs in a fresh subprocess (so that the peak memory of one case is not hidden by
another, and the BLAS thread setting can differ between cases) and reports

- wall time of ``magcal_ros.pipeline.calibrate`` (identifiability checks, closed-form start,
  maximum-likelihood fit on at most ``max_fit_samples`` epochs, residuals of all epochs,
  summary and calibration document) and of ``magcal_ros.core.discovery.diagnose`` (every
  candidate effect) given that fit;
- peak memory of each step: the kernel's high-water mark of the resident set (VmHWM) is
  reset before the step (``/proc/self/clear_refs``) and read after it; the figure is the
  increase over the resident set before the step (MiB);
- the fitted scaling exponent b of time = a N^b (least squares in log-log);
- side by side in one process on the same data (model ``base+2``, N = 3 000 and 10 000, at
  most the largest ``--sizes``): the variable-projection normal equations J^T J, J^T r formed
  from the dense projected Jacobian (the fit's path before) and block by block
  (``ProfiledProblem.normal_equations``), per evaluation and per ``fit``, as ratios.

Data: the seeded simulator (paper 004 section 4.1 errors, 3 nT noise, 'smooth' tumbling) over
a fixed 600 s, so the sample rate grows with N (1.7 Hz .. 1.7 kHz); the models are ``base``
and ``base`` + two driven effects (temperature on sensor 2, a motor-current coupling on
sensor 3), simulated with those effects present.

    python bench/solve_time.py                      # full run
    python bench/solve_time.py --sizes 1000 --models base --no-blas-compare   # tiny
"""
import argparse
import json
import os
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
import numpy as np  # noqa: E402

DURATION_S = 600.0
MODELS = {
    'base': ('base', {}),
    'base+2': ('base,temperature@2,aux:aux_motor_current@3',
               {'temperature@2': [2.0, -1.5, 1.0, 1e-4, 0.0, 0.0],
                'aux:aux_motor_current@3': [8.0, -5.0, 3.0]}),
}


def _status_kib(key):
    with open('/proc/self/status') as fh:
        for line in fh:
            if line.startswith(key + ':'):
                return int(line.split()[1])
    return 0


def _reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0); False when not possible."""
    try:
        with open('/proc/self/clear_refs', 'w') as fh:
            fh.write('5')
        return True
    except OSError:
        return False


class _Step:
    """Context manager: wall time and peak memory increase of a block."""

    def __enter__(self):
        self.exact = _reset_peak()
        self.rss0 = _status_kib('VmRSS')
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
        self.peak_mib = (_status_kib('VmHWM') - self.rss0) / 1024.0 if self.exact else None
        return False


def worker(n, model_key, seed, diagnose_too, max_fit_samples, repeat=1):
    """Run one case in this process; return a dict of figures."""
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.pipeline import calibrate
    spec, truth = MODELS[model_key]
    data, _ = simulate(n_samples=n, rate_hz=n / DURATION_S, trajectory='smooth', truth=truth,
                       seed=seed)
    out = {'n': n, 'model': model_key, 'spec': spec, 'seed': seed}
    kwargs = {} if max_fit_samples is None else {'max_fit_samples': max_fit_samples}
    times = []
    for k in range(max(1, repeat)):
        with _Step() as st:
            run = calibrate(data, spec, field_nt=50000.0, **kwargs)
        times.append(st.seconds)
        if k == 0:
            peak = st.peak_mib
    res = run.result
    out.update(calibrate_s=float(np.median(times)), calibrate_min_s=float(min(times)),
               calibrate_repeats=len(times), calibrate_peak_mib=peak,
               n_fit_samples=int(res.n_fit_samples), nfev=int(res.nfev),
               converged=bool(res.success),
               scalar_rms_nt=float(np.sqrt(np.mean(res.scalar_residual_nt ** 2))),
               sigma_nt=float(np.mean(res.sigma_nt)))
    if diagnose_too:
        from magcal_ros.core.discovery import diagnose
        with _Step() as st:
            d = diagnose(data, base=res, field_nt=50000.0)
        verdict = d.verdict
        out.update(diagnose_s=st.seconds, diagnose_peak_mib=st.peak_mib,
                   diagnose_stage_s=getattr(d, 'seconds', None),
                   n_candidates=len(getattr(d, 'candidates', []) or []),
                   verdict=verdict if isinstance(verdict, (str, dict)) or verdict is None
                   else str(verdict))
    out['rss_end_mib'] = _status_kib('VmRSS') / 1024.0
    return out


def run_case(n, model_key, seed, diagnose_too, timeout_s, blas_threads, max_fit_samples,
             repeat=1):
    """Run :func:`worker` in a subprocess; returns its dict (or the failure)."""
    env = dict(os.environ)
    env['PYTHONPATH'] = common.REPO_DIR + os.pathsep + env.get('PYTHONPATH', '')
    if blas_threads is not None:
        env['OPENBLAS_NUM_THREADS'] = str(blas_threads)
        env['OMP_NUM_THREADS'] = str(blas_threads)
    else:
        env.pop('OPENBLAS_NUM_THREADS', None)
        env.pop('OMP_NUM_THREADS', None)
    cmd = [sys.executable, os.path.abspath(__file__), '--worker', str(n), model_key,
           '--seed', str(seed)]
    if diagnose_too:
        cmd.append('--diagnose')
    if max_fit_samples is not None:
        cmd += ['--max-fit-samples', str(max_fit_samples)]
    cmd += ['--repeat', str(repeat)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {'n': n, 'model': model_key, 'error': f'timed out after {timeout_s:.0f} s',
                'diagnose': diagnose_too}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith('{')]
    if proc.returncode != 0 or not lines:
        return {'n': n, 'model': model_key, 'error': (proc.stderr.strip().splitlines()
                                                      or ['no output'])[-1][:300]}
    out = json.loads(lines[-1])
    out['process_s'] = time.perf_counter() - t0
    out['blas_threads'] = 'default' if blas_threads is None else blas_threads
    return out


def _dense_normal_equations(prob, x):
    """J^T J, J^T r from the dense projected Jacobian (the fit's path before)."""
    jac = prob.jacobian(x)
    return jac.T @ jac, jac.T @ prob.residuals(x)


def engine_compare(n, seed, repeat):
    """
    Time the dense and the block-by-block normal equations side by side (one process).

    Per evaluation at the fitted parameters (the same cached profile for both) and per
    ``fit`` (closed-form start, LM, covariance) of model ``base+2`` on the same data;
    interleaved, the minimum of the evaluations' and the median of the fits' CPU times of
    this process (BLAS on one thread: CPU time is the work, unlike wall time on a machine
    shared with other processes).
    """
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.core.model import fit
    from magcal_ros.core.model.engine import ProfiledProblem
    from magcal_ros.core.model.solvers import single_threaded_blas
    spec, truth = MODELS['base+2']
    data, _ = simulate(n_samples=n, rate_hz=n / DURATION_S, trajectory='smooth', truth=truth,
                       seed=seed)
    block = ProfiledProblem.normal_equations
    paths = {'dense': _dense_normal_equations, 'block': block}
    fits = {k: [] for k in paths}
    res = {}
    try:
        for _ in range(max(1, repeat)):
            for key, fn in paths.items():
                ProfiledProblem.normal_equations = fn
                t0 = time.process_time()
                res[key] = fit(data, spec, field_nt=50000.0)
                fits[key].append(time.process_time() - t0)
    finally:
        ProfiledProblem.normal_equations = block
    r = res['block']
    ctx = [data.context(j) for j in range(1, data.n_sensors + 1)]
    prob = ProfiledProblem(r.model, data.raw, ctx, r.field_magnitude_nt,
                           r.model.sensor_groups[0], r.sigma_nt, p_full=r.params)
    x = r.params[prob.cols]
    prob.residuals(x)
    evals = {k: [] for k in paths}
    with single_threaded_blas():
        for _ in range(max(3, 3 * repeat)):
            for key, fn in paths.items():
                t0 = time.process_time()
                fn(prob, x)
                evals[key].append(time.process_time() - t0)
    d_ref = res['dense']
    return {'n': n, 'n_params': int(len(prob.cols)),
            'eval_dense_s': min(evals['dense']), 'eval_block_s': min(evals['block']),
            'fit_dense_s': float(np.median(fits['dense'])),
            'fit_block_s': float(np.median(fits['block'])),
            'nfev_dense': int(d_ref.nfev), 'nfev_block': int(r.nfev),
            'max_param_diff_in_stderr': float(np.max(np.abs(r.params - d_ref.params)
                                                     / d_ref.stderr))}


def scaling_exponent(ns, ts):
    """Slope b of log t = log a + b log N (None with fewer than two finite points)."""
    pts = [(n, t) for n, t in zip(ns, ts) if t is not None and t > 0]
    if len(pts) < 2:
        return None
    x = np.log([p[0] for p in pts])
    y = np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--sizes', type=float, nargs='+', default=[1e3, 1e4, 1e5, 1e6],
                    help='numbers of epochs N (4 sensors each)')
    ap.add_argument('--models', nargs='+', default=list(MODELS), choices=list(MODELS))
    ap.add_argument('--diagnose-max-n', type=float, default=1e6,
                    help='run diagnose only up to this N')
    ap.add_argument('--diagnose-models', nargs='+', default=['base', 'base+2'],
                    choices=list(MODELS))
    ap.add_argument('--timeout', type=float, default=300.0, help='per case, s')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--blas-threads', type=int, default=0,
                    help='OPENBLAS_NUM_THREADS of the main table (0: unset, what a user gets)')
    ap.add_argument('--no-blas-compare', action='store_true',
                    help='skip the default-vs-1-thread comparison at N = 1e4')
    ap.add_argument('--engine-sizes', type=int, nargs='+', default=[3000, 10000],
                    help='N of the dense vs block normal-equation comparison (at most the '
                    'largest --sizes; that one when none is)')
    ap.add_argument('--no-engine-compare', action='store_true',
                    help='skip the dense vs block normal-equation comparison')
    ap.add_argument('--max-fit-samples', type=int, default=None,
                    help='override fit(max_fit_samples=...) (default: the library default)')
    ap.add_argument('--repeat', type=int, default=3,
                    help='calibrate repeats for N <= 1e4 (median reported; 1 above)')
    ap.add_argument('--worker', nargs=2, metavar=('N', 'MODEL'), help=argparse.SUPPRESS)
    ap.add_argument('--diagnose', action='store_true', help=argparse.SUPPRESS)
    common.add_common_args(ap)
    args = ap.parse_args(argv)

    if args.worker:
        out = worker(int(float(args.worker[0])), args.worker[1], args.seed, args.diagnose,
                     args.max_fit_samples, args.repeat)
        print(json.dumps(common.jsonable(out)))
        return 0

    started = time.perf_counter()
    threads = None if args.blas_threads == 0 else args.blas_threads
    sizes = [int(s) for s in args.sizes]
    cases = []
    for model_key in args.models:
        for n in sizes:
            diag = model_key in args.diagnose_models and n <= args.diagnose_max_n
            reps = args.repeat if n <= 10000 else 1
            r = run_case(n, model_key, args.seed, diag, args.timeout, threads,
                         args.max_fit_samples, reps)
            if 'error' in r and diag:
                # keep the calibrate figure even when diagnose is too slow
                r2 = run_case(n, model_key, args.seed, False, args.timeout, threads,
                              args.max_fit_samples, reps)
                r2['diagnose_error'] = r['error']
                r = r2
            cases.append(r)
            cal_s = r.get('calibrate_s', float('nan'))
            print(f'  N={n:>8} {model_key:7s} calibrate {cal_s:8.3f} s'
                  f'  diagnose {r.get("diagnose_s", float("nan")):8.3f} s'
                  f'  {r.get("error", "")}{r.get("diagnose_error", "")}', flush=True)

    rows = []
    for r in cases:
        rows.append([r['n'], r['model'], r.get('n_fit_samples'), r.get('calibrate_s'),
                     r.get('calibrate_peak_mib'), r.get('diagnose_s'),
                     r.get('diagnose_peak_mib'),
                     r.get('error') or r.get('diagnose_error') or ''])
    t_main = common.table(
        ['N', 'model', 'fit on', 'calibrate s (median)', 'peak MiB', 'diagnose s', 'peak MiB',
         'note'],
        rows, title=f'Solve time, 4 sensors (OPENBLAS_NUM_THREADS={threads or "default"})')

    exps = {}
    exp_rows = []
    for model_key in args.models:
        sel = [r for r in cases if r['model'] == model_key and 'calibrate_s' in r]
        ns = [r['n'] for r in sel]
        e_all = scaling_exponent(ns, [r['calibrate_s'] for r in sel])
        big = [r for r in sel if r['n'] >= 1e4]
        e_big = scaling_exponent([r['n'] for r in big], [r['calibrate_s'] for r in big])
        dsel = [r for r in sel if r.get('diagnose_s')]
        e_diag = scaling_exponent([r['n'] for r in dsel], [r['diagnose_s'] for r in dsel])
        exps[model_key] = {'calibrate_all': e_all, 'calibrate_n_ge_1e4': e_big,
                           'diagnose': e_diag}
        exp_rows.append([model_key, e_all, e_big, e_diag])
    t_exp = common.table(['model', 'calibrate b (all N)', 'calibrate b (N >= 1e4)',
                          'diagnose b'], exp_rows, title='Scaling exponent b of time ~ N^b')

    goal = None
    goals = {}
    for model_key in args.models:
        g = [r for r in cases
             if r['n'] == 10000 and r['model'] == model_key and 'calibrate_s' in r]
        if g:
            total = g[0]['calibrate_s'] + (g[0].get('diagnose_s') or float('nan'))
            goals[model_key] = {'n': 10000, 'calibrate_s': g[0]['calibrate_s'],
                                'diagnose_s': g[0].get('diagnose_s'), 'total_s': total,
                                'goal_s': 2.0, 'met': bool(total < 2.0)}
    goal = goals.get('base')

    blas = []
    if not args.no_blas_compare:
        for th in (None, 1):
            r = run_case(10000, 'base', args.seed, True, args.timeout, th,
                         args.max_fit_samples, args.repeat)
            blas.append(r)
        t_blas = common.table(['OPENBLAS_NUM_THREADS', 'calibrate s (N = 1e4, base)',
                               'diagnose s'],
                              [[r.get('blas_threads', '?'), r.get('calibrate_s'),
                                r.get('diagnose_s')] for r in blas],
                              title='BLAS threads (fit() and diagnose() limit BLAS to 1 '
                              'thread themselves: both rows should agree)')
    engine = []
    if not args.no_engine_compare:
        e_sizes = [n for n in args.engine_sizes if n <= max(sizes)] or [max(sizes)]
        engine = [engine_compare(n, args.seed, args.repeat) for n in e_sizes]
        t_engine = common.table(
            ['N', 'P', 'evaluation dense / block', 'fit dense / block', 'nfev dense, block',
             'largest parameter difference / stderr'],
            [[e['n'], e['n_params'], e['eval_dense_s'] / e['eval_block_s'],
              e['fit_dense_s'] / e['fit_block_s'], f'{e["nfev_dense"]}, {e["nfev_block"]}',
              e['max_param_diff_in_stderr']] for e in engine],
            title='Normal equations J^T J, J^T r of model base+2: from the dense projected '
            'Jacobian vs block by block (ProfiledProblem.normal_equations), one process, '
            'same data (ratios of CPU times)')
    tables = [t_main, t_exp] + ([t_blas] if blas else []) + ([t_engine] if engine else [])
    for model_key, gl in goals.items():
        tables.append(f'Goal 4 x 10 000 calibrated + diagnosed < 2 s, model {model_key}: '
                      f'{gl["total_s"]:.2f} s -> {"met" if gl["met"] else "MISSED"}')
    for t in tables:
        print()
        print(t)
    settings = {k: v for k, v in vars(args).items() if k not in ('worker', 'diagnose')}
    settings['duration_s'] = DURATION_S
    settings['models'] = {k: MODELS[k][0] for k in args.models}
    path = common.write_result('solve_time', settings,
                               {'cases': cases, 'exponents': exps, 'goal': goal, 'goals': goals,
                                'blas_compare': blas, 'engine_compare': engine}, tables,
                               args.out_dir, started)
    print(f'\nwrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
