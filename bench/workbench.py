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
Speed of the model workbench: diagnose, the report, the whole ladder, before and after.

For each size N (4 sensors, the seeded simulator's 'smooth' tumbling over 600 s with a
temperature coefficient on sensor 2, written once to a CSV file that both codes read) the
same steps are timed

- ``diagnose`` (given the base fit; every candidate: screening, refits, held-out test),
- ``write_report`` of that diagnosis (the figures and the HTML page),
- ``ladder`` from ``base`` until the verdict is "none" (fits included),

with the current code and with the code of an earlier commit (``--before``, default the
main revision this round started from), each in its own Python process (the earlier tree
extracted with ``git archive``: a whole package, so that a later split of its modules cannot
break the comparison), alternating the two so that a shared machine's load affects both
alike.  Every process first runs its code once on 600 samples, untimed (matplotlib's
one-off costs, lazy imports; ``--no-warmup`` skips it, for a smoke test: those costs then
land in the timed steps).  With ``--repeat R`` each code runs R times per size and the
fastest is reported.  The ratio after/before is the figure to read; absolute seconds depend
on the machine and on what else runs on it (the load average is recorded per run).

    python bench/workbench.py                       # N = 3000, 10000
    python bench/workbench.py --sizes 600 --before none --no-ladder     # tiny
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
#: main when this round started (issue 11 item 7's "today's code")
BEFORE_REV = '2dca2a5'
TRUTH = {'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]}
#: goals of issue 11 item 7 at 4 x 10 000 samples, s
GOALS = {'diagnose+report': 3.0, 'report': 1.0, 'ladder': 10.0}


def _child(args):
    """Time one code on one CSV file (run in its own process); print one JSON object."""
    from magcal_ros.io.csvio import read_csv
    from magcal_ros.report import write_report
    try:
        from magcal_ros.core.data.simulate import simulate
        from magcal_ros.core.discovery import diagnose, ladder
        from magcal_ros.core.model import fit
    except ImportError:                 # the core's layout before it had folders (BEFORE_REV)
        from magcal_ros.core.diagnose import diagnose, ladder
        from magcal_ros.core.model import fit
        from magcal_ros.core.simulate import simulate

    if not args.no_warmup:
        warm, _ = simulate(n_samples=600, rate_hz=1.0, trajectory='smooth', seed=args.seed,
                           truth=TRUTH)
        base = fit(warm, 'base', field_nt=50000.0)
        with tempfile.TemporaryDirectory() as tmp:
            write_report(tmp, warm, diagnosis=diagnose(warm, field_nt=50000.0, base=base))
    data = read_csv(args.child)
    base = fit(data, 'base', field_nt=50000.0)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    diag = diagnose(data, field_nt=50000.0, base=base)
    t_d = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_report(tmp, data, diagnosis=diag)
        t_r = time.perf_counter() - t0
        figures = sorted(f[:-4] for f in os.listdir(tmp) if f.endswith('.png'))
    t_l, rungs = None, None
    if not args.no_ladder:
        t0 = time.perf_counter()
        lad = ladder(data, base, field_nt=50000.0)
        t_l = time.perf_counter() - t0
        rungs = [st.added for st in lad.steps]
    print(json.dumps({'diagnose_s': t_d, 'report_s': t_r, 'diagnose_report_s': t_d + t_r,
                      'ladder_s': t_l, 'verdict': diag.verdict_token,
                      'n_candidates': len(diag.candidates), 'figures': figures,
                      'ladder_rungs': rungs, 'stages_s': dict(diag.seconds),
                      'load_average_1min': load}))


def _extract(rev, into, repo):
    """Extract the package tree at git revision ``rev`` under ``into`` (git archive | tar)."""
    os.makedirs(into)
    archive = subprocess.run(['git', 'archive', rev, 'magcal_ros'], cwd=repo,
                             capture_output=True, check=True).stdout
    subprocess.run(['tar', '-x', '-C', into], input=archive, check=True)
    return into


def _run_child(code_dir, csv, args):
    """Run :func:`_child` on ``csv`` with the package under ``code_dir``; return its dict."""
    env = {**os.environ, 'PYTHONPATH': code_dir}
    cmd = [sys.executable, os.path.abspath(__file__), '--child', csv, '--seed', str(args.seed)]
    if args.no_ladder:
        cmd.append('--no-ladder')
    if args.no_warmup:
        cmd.append('--no-warmup')
    p = subprocess.run(cmd, cwd=code_dir, env=env, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f'{code_dir}: {p.stderr[-2000:]}')
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None):
    """Time both codes on every size and write bench/results/workbench.json."""
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--sizes', type=int, nargs='+', default=[3000, 10000])
    ap.add_argument('--before', default=BEFORE_REV,
                    help=f'git revision of the code compared with (default {BEFORE_REV}; '
                         "'none': current code only)")
    ap.add_argument('--no-ladder', action='store_true', help='skip the whole-ladder timing')
    ap.add_argument('--no-warmup', action='store_true',
                    help='skip the untimed run on 600 samples that every process makes first '
                    '(a smoke test: the one-off costs then land in the timed steps)')
    ap.add_argument('--repeat', type=int, default=1,
                    help='runs per code and size (alternating); the fastest is reported')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--child', metavar='CSV', help=argparse.SUPPRESS)
    ap.add_argument('--out-dir', default=None,
                    help='where to write workbench.json (default bench/results)')
    args = ap.parse_args(argv)
    if args.child:
        # only the code under PYTHONPATH: bench/common.py would put this tree's first
        return _child(args)
    sys.path.insert(0, BENCH_DIR)
    import common
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.io.csvio import write_csv
    started = time.perf_counter()
    results, rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        codes = {'after': common.REPO_DIR}
        if args.before != 'none':
            codes['before'] = _extract(args.before, os.path.join(tmp, 'before'),
                                       common.REPO_DIR)
        for n in args.sizes:
            data, _ = simulate(n_samples=n, rate_hz=n / 600.0, trajectory='smooth',
                               seed=args.seed, truth=TRUTH)
            csv = os.path.join(tmp, f'data_{n}.csv')
            write_csv(csv, data)
            runs = {label: [] for label in codes}
            for i in range(args.repeat):
                order = list(codes) if i % 2 == 0 else list(codes)[::-1]
                for label in order:
                    runs[label].append(_run_child(codes[label], csv, args))
            res = {'n': n}
            for label, rr in runs.items():
                best = {}
                for key in ('diagnose_s', 'report_s', 'diagnose_report_s', 'ladder_s'):
                    vals = [r[key] for r in rr if r[key] is not None]
                    best[key] = min(vals) if vals else None
                # the stage seconds and verdict of the fastest diagnosis
                fastest = min(rr, key=lambda r: r['diagnose_s'])
                res[label] = {**fastest, **best, 'runs': rr}
            results.append(res)
            for key, goal in (('diagnose_report_s', 'diagnose+report'), ('report_s', 'report'),
                              ('ladder_s', 'ladder')):
                after = res['after'][key]
                before = res.get('before', {}).get(key)
                ratio = None if before in (None, 0) or after is None else after / before
                loads = [r['load_average_1min'] for label in runs for r in runs[label]]
                rows.append([n, goal, before, after, ratio,
                             GOALS[goal] if n == 10000 else None,
                             f'{min(loads):.1f}-{max(loads):.1f}'])
    tab = common.table(['N', 'stage', 'before (s)', 'after (s)', 'after/before',
                        'goal at 4 x 10 000 (s)', 'load (1 min)'], rows,
                       title=f'workbench speed, 4 sensors (before = {args.before}, fastest of '
                             f'{args.repeat})')
    verdicts = common.table(
        ['N', 'code', 'verdict', 'candidates', 'figures', 'ladder', 'screen (s)', 'refit (s)',
         'held-out (s)'],
        [[r['n'], k, r[k]['verdict'], r[k]['n_candidates'], len(r[k]['figures']),
          ' + '.join(a for a in (r[k]['ladder_rungs'] or []) if a) or None,
          r[k]['stages_s'].get('screen'), r[k]['stages_s'].get('refit'),
          r[k]['stages_s'].get('cross_validate')]
         for r in results for k in ('before', 'after') if k in r],
        title='what each diagnosis did')
    print(tab)
    print(verdicts)
    common.write_result('workbench', vars(args), {'cases': results}, [tab, verdicts],
                        out_dir=args.out_dir, started=started)


if __name__ == '__main__':
    main()
