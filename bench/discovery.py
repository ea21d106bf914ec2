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
Discovery on invented field situations, through the command line as a user runs it.

For each case of test/discovery_cases.py (kinds the effect catalog did not hold, plus
controls) and each size, the record is written to a CSV file and

1. ``magcal diagnose CSV --model base --json`` (default options) offers a term: the verdict's
   token, or when the verdict is "none" the first finding that carries a token;
2. ``magcal fit CSV --model base,<term> --json`` (and ``--model 'base + <term>'``) refits;
3. the case passes when every sensor's scalar RMS is within 1.15x its noise floor (and the
   vector RMS of each sensor against sensor 1 within 1.15x sqrt(floor_1^2 + floor_j^2)),
   and the term names the right sensors and channel or time (discovery_cases.attributed);
   a control passes when nothing is offered and the base fit is within 1.10x the floor.

``--code DIR`` runs another tree's ``magcal_ros`` (e.g. main's, extracted with
``git archive``) on the same CSV files: the baseline of BENCHMARKS.md.

    python bench/discovery.py --sizes 3000 10000 --out bench/results/discovery.json
    python bench/discovery.py --cases warmup rotor --sizes 3000
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(BENCH_DIR)
sys.path[:0] = [ROOT, os.path.join(ROOT, 'test')]
PASS_RATIO = 1.15
CONTROL_RATIO = 1.10


def _magcal(code, args, timeout=600):
    env = dict(os.environ, PYTHONPATH=code)
    t0 = time.perf_counter()
    # cwd: not this tree (python -m puts the working directory first on sys.path)
    p = subprocess.run([sys.executable, '-m', 'magcal_ros.cli'] + args, env=env,
                       capture_output=True, text=True, timeout=timeout,
                       cwd=os.path.dirname(args[1]))
    dt = time.perf_counter() - t0
    out = None
    if p.returncode == 0:
        try:
            out = json.loads(p.stdout)
        except ValueError:
            out = None
    return out, p.stderr.strip().splitlines()[-1:] if p.returncode else [], dt


def offered_term(diag):
    """Return the term a user would add: the verdict's token, else a finding's token."""
    tok = (diag.get('verdict') or {}).get('token')
    if tok:
        return tok, 'verdict'
    for fd in diag.get('findings') or []:
        if fd.get('token'):
            return fd['token'], 'finding'
    return None, None


def ratios(fit):
    """({j: scalar RMS / floor}, {j: vector RMS / vector floor}) of a fit's JSON."""
    fl = {int(k): v for k, v in fit['noise_floor_per_sensor_nt'].items()}
    sc = {int(k): v / fl[int(k)] for k, v in fit['scalar_rms_nt'].items()}
    vec = {int(k): v / (fl[1] ** 2 + fl[int(k)] ** 2) ** 0.5
           for k, v in (fit.get('vector_rms_nt') or {}).items()}
    return sc, vec


def run_case(case, n, code, tmp, seed):
    """Run one case at one size; return its row (dict)."""
    import discovery_cases as dc
    from magcal_ros.io.csvio import write_csv
    data = case.data(n, seed=seed)
    path = os.path.join(tmp, f'{case.name}_{n}.csv')
    write_csv(path, data)
    row = {'case': case.name, 'n': n, 'expected': _expected(case, data.t)}
    diag, err, dt = _magcal(code, ['diagnose', path, '--model', 'base', '--json'])
    row['diagnose_s'] = dt
    if diag is None:
        row.update(term=None, ok=False, ok_comma=False, why=f'diagnose failed: {err}')
        return row
    term, source = offered_term(diag)
    row.update(term=term, source=source, verdict_reason=diag['verdict'].get('reason'),
               base_ratio=diag.get('ratio_to_floor'))
    att_ok, why = dc.attributed(case, term, data.t)
    row['attributed'], row['attribution'] = att_ok, why
    models = ['base'] if term is None else [f'base,{term}', f'base + {term}']
    worst = []
    for m in models:
        fit, err, _ = _magcal(code, ['fit', path, '--model', m, '--json'])
        if fit is None:
            worst.append(None)
            row.setdefault('fit_errors', []).append(f'{m}: {err}')
            continue
        sc, vec = ratios(fit)
        worst.append(max(list(sc.values()) + list(vec.values())))
        if 'scalar_ratio' not in row:
            row['scalar_ratio'] = sc
            row['vector_ratio'] = vec
    row['worst_ratio'] = worst[0]
    row['worst_ratio_plus'] = worst[-1]
    limit = CONTROL_RATIO if not case.sensors else PASS_RATIO
    fits_ok = all(w is not None and w <= limit for w in worst)
    # the comma form alone: the only one the code before the formula grammar reads
    row['ok_comma'] = bool(att_ok and worst[0] is not None and worst[0] <= limit)
    row['ok'] = bool(att_ok and fits_ok)
    row['why'] = why if not att_ok else ('ok' if fits_ok else f'residual {worst} > {limit}')
    return row


def _expected(case, t):
    if not case.sensors:
        return 'none'
    s = ('all' if len(case.sensors) == 4 else
         ','.join(str(j) for j in case.sensors))
    win = case.window(t)
    w = '' if win is None else f' {win[0]:.0f}-{win[1]:.0f}s'
    return f'sensor {s}, {case.channel}{w}'


def main(argv=None):
    """Run the cases; print the table and write JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[3000, 10000])
    ap.add_argument('--cases', nargs='+', help='case names (default all)')
    ap.add_argument('--code', default=ROOT, help='tree whose magcal_ros is run')
    ap.add_argument('--seed', type=int, default=11)
    ap.add_argument('--out', help='JSON file to write')
    args = ap.parse_args(argv)
    import discovery_cases as dc
    cases = [dc.BY_NAME[c] for c in args.cases] if args.cases else dc.CASES
    rows = []
    print(f'{"case":18s} {"n":>6s} {"expected":28s} {"term offered":44s} '
          f'{"worst/floor":>11s} {"s":>5s}  result')
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            for case in cases:
                row = run_case(case, n, args.code, tmp, args.seed)
                rows.append(row)
                w = row.get('worst_ratio')
                print(f'{case.name:18s} {n:6d} {row["expected"]:28s} '
                      f'{str(row.get("term"))[:44]:44s} '
                      f'{"-" if w is None else f"{w:.2f}":>11s} {row["diagnose_s"]:5.1f}  '
                      f'{"PASS" if row["ok"] else "fail: " + row["why"]}', flush=True)
    n_ok = sum(r['ok'] for r in rows)
    n_comma = sum(r['ok_comma'] for r in rows)
    print(f'{n_ok} of {len(rows)} pass ({n_comma} with the comma form alone)')
    if args.out:
        with open(args.out, 'w') as fh:
            json.dump({'code': args.code, 'seed': args.seed, 'rows': rows,
                       'passed': n_ok, 'passed_comma': n_comma, 'total': len(rows),
                       'load': os.getloadavg()[0]}, fh, indent=1)


if __name__ == '__main__':
    main()
