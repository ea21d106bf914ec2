"""Speed of the model workbench: diagnose, the report, the whole ladder, before and after.

For each size N (4 sensors, the seeded simulator's 'smooth' tumbling over 600 s with a
temperature coefficient on sensor 2) the same process times

- ``diagnose`` (given the base fit; every candidate: screening, refits, held-out test),
- ``write_report`` of that diagnosis (every figure and the HTML page),
- ``ladder`` from ``base`` until the verdict is "none" (fits included),

with the current code and with the code of an earlier commit (``--before``, default the
diagnosis engine before issue 11's explained fraction / interleaved blocks / proposals),
loaded from git into a separate module, alternating the two so that a shared machine's load
affects both alike.  The ratio after/before is the figure to read; absolute seconds depend
on the machine and on what else runs on it.

    python bench/workbench.py                       # N = 3000, 10000
    python bench/workbench.py --sizes 600 --before none --no-ladder     # tiny
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
import types

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402

from magcal_ros.core.model import fit  # noqa: E402
from magcal_ros.core.simulate import simulate  # noqa: E402

#: main before issue 11 part B (the diagnosis engine with contiguous held-out blocks)
BEFORE_REV = '1af1ff0'
TRUTH = {'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]}
#: goals of issue 11 item 7 at 4 x 10 000 samples, s
GOALS = {'diagnose+report': 3.0, 'report': 1.0, 'ladder': 10.0}


def _module_at(rev, path, name):
    """Import ``path`` as it was at git revision ``rev`` under the module name ``name``."""
    src = subprocess.run(['git', 'show', f'{rev}:{path}'], cwd=common.REPO_DIR,
                         capture_output=True, text=True, check=True).stdout
    mod = types.ModuleType(name)
    mod.__file__ = f'{rev}:{path}'
    sys.modules[name] = mod
    exec(compile(src, mod.__file__, 'exec'), mod.__dict__)
    return mod


def _codes(before):
    from magcal_ros.core import diagnose as diag_now
    from magcal_ros import report as report_now
    codes = {'after': (diag_now, report_now)}
    if before != 'none':
        d_old = _module_at(before, 'magcal_ros/core/diagnose.py', '_bench_diagnose_before')
        r_old = _module_at(before, 'magcal_ros/report.py', '_bench_report_before')
        codes['before'] = (d_old, r_old)
    return codes


def _time(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _warm_up(codes, seed):
    """Run every code once, untimed, on a small data set.

    The first ``write_report`` in a process pays matplotlib's one-off costs (font cache,
    lazily imported modules, the first figure: about 4 s at 4 x 10 000 on a loaded machine,
    measured 8.9 s cold vs 4.9 s warm); without this they fell on whichever code ran first.
    """
    data, _ = simulate(n_samples=600, rate_hz=1.0, trajectory='smooth', seed=seed, truth=TRUTH)
    base = fit(data, 'base', field_nt=50000.0)
    for dmod, rmod in codes.values():
        diag = dmod.diagnose(data, field_nt=50000.0, base=base)
        with tempfile.TemporaryDirectory() as tmp:
            rmod.write_report(tmp, data, diagnosis=diag)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sizes', type=int, nargs='+', default=[3000, 10000])
    ap.add_argument('--before', default=BEFORE_REV,
                    help=f'git revision of the code compared with (default {BEFORE_REV}; '
                         "'none': current code only)")
    ap.add_argument('--no-ladder', action='store_true', help='skip the whole-ladder timing')
    ap.add_argument('--seed', type=int, default=1)
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    codes = _codes(args.before)
    _warm_up(codes, args.seed)
    results, rows = [], []
    for n in args.sizes:
        data, _ = simulate(n_samples=n, rate_hz=n / 600.0, trajectory='smooth', seed=args.seed,
                           truth=TRUTH)
        base = fit(data, 'base', field_nt=50000.0)
        res = {'n': n}
        for label, (dmod, rmod) in codes.items():
            t_d, diag = _time(lambda: dmod.diagnose(data, field_nt=50000.0, base=base))
            with tempfile.TemporaryDirectory() as tmp:
                t_r, _ = _time(lambda: rmod.write_report(tmp, data, diagnosis=diag))
            t_l = None
            if not args.no_ladder:
                t_l, lad = _time(lambda: dmod.ladder(data, base, field_nt=50000.0))
            res[label] = {'diagnose_s': t_d, 'report_s': t_r, 'diagnose_report_s': t_d + t_r,
                          'ladder_s': t_l, 'verdict': diag.verdict_token,
                          'n_candidates': len(diag.candidates),
                          'stages_s': dict(diag.seconds)}
        results.append(res)
        for key, goal in (('diagnose_report_s', 'diagnose+report'), ('report_s', 'report'),
                          ('ladder_s', 'ladder')):
            after = res['after'][key]
            before = res.get('before', {}).get(key)
            ratio = None if before in (None, 0) or after is None else after / before
            rows.append([n, goal, before, after, ratio,
                         GOALS[goal] if n == 10000 else None])
    tab = common.table(['N', 'stage', 'before (s)', 'after (s)', 'after/before',
                        'goal at 4 x 10 000 (s)'], rows,
                       title=f'workbench speed, 4 sensors (before = {args.before})')
    verdicts = common.table(
        ['N', 'code', 'verdict', 'candidates', 'screen (s)', 'refit (s)', 'held-out (s)'],
        [[r['n'], k, r[k]['verdict'], r[k]['n_candidates'],
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
