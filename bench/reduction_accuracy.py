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
Accuracy of a long record's reduction against the record held in memory (issue 19).

The held-out style of data: the cross on a smooth trajectory at 100 Hz with a hidden
temperature effect on sensor 2, 1e4 and 1e6 epochs.  Each record is fitted and diagnosed
twice: held whole in memory (the code before the chunked reading: fit on its 20 000 evenly
spaced epochs, noise floor and findings on every epoch) and reduced chunk by chunk
(:mod:`magcal_ros.core.data.reduce`, as ``magcal`` does above 100 000 epochs; at 1e4 forced with
a sample of 2 500 epochs).  Reported: the verdicts, the largest parameter difference in
units of sqrt(sf^2 + sr^2) (the two fits' standard uncertainties: their errors are
positively correlated through the epochs they share, so the difference has at most that
sd; test_long_records.py asserts 4.5), the noise floors and the peak memory of each way.

    python bench/reduction_accuracy.py            # ~5 min on an idle 2-core machine

Writes bench/results/reduction_accuracy.json.
"""
import argparse
import resource
import time

from common import add_common_args, table, write_result  # noqa: I100
from magcal_ros.core.data.noise import data_noise_floor
from magcal_ros.core.data.reduce import reduce_chunks
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.discovery import diagnose
from magcal_ros.core.model import fit
import numpy as np

TRUTH = {'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]}


def pieces(data, rows=65536):
    """Cut ``data`` into consecutive chunks of ``rows`` epochs."""
    for i in range(0, data.n_samples, rows):
        yield data.subset(np.arange(i, min(data.n_samples, i + rows)))


def one(data, model):
    """Fit ``model`` and diagnose 'base' on ``data``: (fit, diagnosis, CPU s)."""
    t0 = time.process_time()
    res = fit(data, model, field_nt=50000.0)
    diag = diagnose(data, 'base', field_nt=50000.0)
    return res, diag, time.process_time() - t0


def floor_ratio(r):
    """Return the largest relative difference of the reduced noise floor from the other."""
    return float(np.max(np.abs(np.array(r['floor_reduced_nt'])
                               / np.array(r['floor_in_memory_nt']) - 1)))


def main():
    """Compare the in-memory and the reduced computation at each size."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[10000, 1000000])
    add_common_args(ap)
    args = ap.parse_args()
    started = time.perf_counter()
    rows = []
    model = 'base,temperature@2'
    for n in args.sizes:
        data, _ = simulate(n_samples=n, rate_hz=100.0, trajectory='smooth', seed=23,
                           truth=TRUTH)
        full, dfull, cpu_full = one(data, model)
        floor_full = data_noise_floor(data, full).per_sensor_nt
        kw = {} if n > 100000 else {'sample': 2500}
        red = reduce_chunks(pieces(data), **kw)
        part, dpart, cpu_part = one(red.sample, model)
        floor_part = data_noise_floor(red.sample, part).per_sensor_nt
        z = np.abs(part.params - full.params) / np.hypot(full.stderr, part.stderr)
        rows.append({'epochs': n, 'sample_epochs': red.info['sample_epochs'],
                     'verdict_in_memory': dfull.verdict_token,
                     'verdict_reduced': dpart.verdict_token,
                     'max_param_diff_sd': float(z.max()), 'median_param_diff_sd':
                     float(np.median(z)), 'n_params': int(len(z)),
                     'floor_in_memory_nt': floor_full.tolist(),
                     'floor_reduced_nt': floor_part.tolist(),
                     'cpu_in_memory_s': cpu_full, 'cpu_reduced_s': cpu_part,
                     'peak_rss_mb_so_far': resource.getrusage(
                         resource.RUSAGE_SELF).ru_maxrss / 1024})
        print(rows[-1], flush=True)
        del data, full, dfull, red, part, dpart
    tab = table(['epochs', 'sample', 'verdict (memory)', 'verdict (reduced)',
                 'max |dp| / sd', 'median |dp| / sd', 'floor ratio (max)'],
                [[r['epochs'], r['sample_epochs'], r['verdict_in_memory'],
                  r['verdict_reduced'], f'{r["max_param_diff_sd"]:.2f}',
                  f'{r["median_param_diff_sd"]:.2f}',
                  f'{floor_ratio(r):.3%}']
                 for r in rows], 'reduced against in-memory, hidden temperature@2')
    print(tab)
    write_result('reduction_accuracy', vars(args), {'rows': rows}, [tab],
                 out_dir=args.out_dir, started=started)


if __name__ == '__main__':
    main()
