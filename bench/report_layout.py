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
The report's hand-written parts against the libraries they stand in for (issue 22, item 6).

Side by side in one process, alternating, in CPU seconds of the process (robust to other
processes on a shared machine), on the figures ``write_report`` draws by default for a
diagnosis at 4 x N epochs (the simulator's tumbling cross with a temperature coefficient on
sensor 2):

- PNG: Pillow's encoder (``PIL.Image.save``) at zlib level 1, as the report uses it, against
  its default level 6, on the same RGB buffers; the bytes must decode to the same pixels;
- layout: the report's fixed margins against matplotlib's constrained layout
  (``report.FIXED_LAYOUT``; the same 3-5 ticks per axis), each figure made and drawn.

Until the commit that made them Pillow's and matplotlib's, the report had its own PNG
encoder (``png_bytes``) and placed the axis labels itself; BENCHMARKS.md has the run that
compared them (this script then had those two variants as well).

The PNG encoders are timed on the buffers of the figures just drawn with the fixed margins
(the report's layout).  Every figure is first made and encoded once, untimed (matplotlib's
one-off costs); ``--no-warmup`` skips that round (for a smoke test: its one-off costs then
land in the first timed round).

    python bench/report_layout.py --n 10000 --repeat 3
"""
import argparse
import io
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402


def _cpu(fn, *args):
    t0 = time.process_time()
    out = fn(*args)
    return time.process_time() - t0, out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    p.add_argument('--n', type=int, default=10000, help='epochs (default 10000)')
    p.add_argument('--repeat', type=int, default=3, help='alternating rounds (default 3)')
    p.add_argument('--no-warmup', action='store_true',
                   help='skip the untimed first drawing of every figure (a smoke test: the '
                   "one-off costs then land in the first round's times)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    started = time.perf_counter()

    import matplotlib
    from magcal_ros import report
    from magcal_ros.core.discovery import diagnose
    from magcal_ros.core.model import fit
    from magcal_ros.core.data.simulate import simulate
    import numpy as np
    from PIL import Image

    data, _ = simulate(n_samples=args.n, rate_hz=args.n / 600.0, trajectory='smooth', seed=0,
                       truth={'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]})
    base = fit(data, 'base', field_nt=50000.0)
    diag = diagnose(data, base=base, field_nt=50000.0)
    makers = report.default_views(data, diag)

    variants = {
        'fixed margins (the report)': True,
        'constrained layout': False,
    }

    layout = {}
    png = {'Pillow level 1 (the report)': [], 'Pillow level 6 (default)': []}
    sizes = dict.fromkeys(png, 0)
    with matplotlib.rc_context(report.RC):
        if not args.no_warmup:
            for name, make in makers:             # untimed: one-off costs
                report.figure_png(make())
        for _ in range(args.repeat):
            rgbs = []
            for label, fixed in variants.items():
                report.FIXED_LAYOUT = fixed
                try:
                    total = 0.0
                    for name, make in makers:
                        dt, fig = _cpu(lambda: make())
                        dt2, _ = _cpu(fig.canvas.draw)
                        total += dt + dt2
                        if fixed:                 # the report's figures: the PNGs' pixels
                            rgbs.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
                    layout.setdefault(label, []).append(total)
                finally:
                    report.FIXED_LAYOUT = True

            def pil(rgb, level):
                buf = io.BytesIO()
                Image.fromarray(rgb).save(buf, 'PNG', compress_level=level)
                return buf.getvalue()
            for label, enc in (('Pillow level 1 (the report)', lambda r: pil(r, 1)),
                               ('Pillow level 6 (default)', lambda r: pil(r, 6))):
                total, size = 0.0, 0
                for rgb in rgbs:
                    dt, b = _cpu(enc, rgb)
                    total += dt
                    size += len(b)
                    dec = np.asarray(Image.open(io.BytesIO(b)).convert('RGB'))
                    assert np.array_equal(dec, rgb), label
                png[label].append(total)
                sizes[label] = size
    best = {k: min(v) for k, v in {**layout, **png}.items()}
    ref_l, ref_p = best['fixed margins (the report)'], best['Pillow level 1 (the report)']
    rows = [[k, f'{best[k]:.3f}', f'{best[k] / ref_l:.2f}', ''] for k in layout]
    rows += [[k, f'{best[k]:.3f}', f'{best[k] / ref_p:.2f}', f'{sizes[k] / 1024:.0f}']
             for k in png]
    results = {'n': args.n, 'figures': [n for n, _ in makers], 'cpu_s_best': best,
               'cpu_s_all': {**layout, **png}, 'png_kib': {k: v / 1024 for k, v in
                                                           sizes.items()}}
    tab = common.table(['variant', 'CPU s (best)', 'ratio to the report', 'PNG KiB'], rows,
                       title=f'{len(makers)} default report figures at 4 x {args.n} epochs, '
                             f'best of {args.repeat} alternating rounds')
    print(tab)
    common.write_result('report_layout', vars(args), results, [tab], args.out_dir, started)
    print(json.dumps(best))


if __name__ == '__main__':
    main()
