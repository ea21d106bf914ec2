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
Long records in bounded memory (issue 19): chunked reading, the reduction, progress bars.

Small versions of each path: chunk boundaries that fall inside a step, beside a field-rate
lag and across a periodic line; a bag in each storage format; equality with the record
held in memory, and the tolerance within which the reduced fit agrees with the in-memory
one (derived in the test).  The hour-long runs are in bench/scale.py.
"""
import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios

from magcal_ros.core.data.noise import data_noise_floor
from magcal_ros.core.data.reduce import concat, reduce_chunks, residual_statistics
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.model import fit, Model
from magcal_ros.io.bag import bag_chunks, read_bag, write_bag
from magcal_ros.io.chunks import write_csv_chunks
from magcal_ros.io.csvio import CsvFormatError, read_csv, read_pieces as csv_chunks, write_csv
from magcal_ros.pipeline import cross_geometry, geometry_positions, summarize
import numpy as np
import pytest

#: a step at 151.3 s (inside chunk 4 of 997 epochs at 20 Hz), a line at 0.05 Hz on sensor
#: 3, a field-rate lag on sensor 2
TRUTH = {'step(151.3)@1': [40.0, -30.0, 20.0],
         'periodic(0.05)@3': [15.0, 0.0, -10.0, 0.0, 12.0, 5.0],
         'field_rate@2': [2e-3, 2e-3, 2e-3]}
SPEC = 'base,step(151.3)@1,periodic(0.05)@3,field_rate@2'


def pieces(data, rows):
    """Cut ``data`` into consecutive Datasets of ``rows`` epochs (the last one shorter)."""
    for i in range(0, data.n_samples, rows):
        yield data.subset(np.arange(i, min(data.n_samples, i + rows)))


@pytest.fixture(scope='module')
def record():
    data, _ = simulate(n_samples=6000, rate_hz=20.0, trajectory='smooth', seed=5, truth=TRUTH)
    return data


def test_csv_in_chunks_is_what_read_csv_reads(tmp_path, record):
    path = tmp_path / 'r.csv'
    write_csv(path, record.subset(np.arange(1500)), comment='a comment')
    lines = path.read_text().splitlines(keepends=True)
    # a comment and a blank line inside the third chunk of 97 rows
    lines.insert(250, '# operator note\n')
    lines.insert(260, '\n')
    path.write_text(''.join(lines))
    whole = read_csv(path)
    got = concat(list(csv_chunks(path, rows=97)))
    for key in ('t', 'raw', 'temp'):
        np.testing.assert_array_equal(getattr(got, key), getattr(whole, key))
    assert sorted(got.aux) == sorted(whole.aux)
    for k in whole.aux:
        np.testing.assert_array_equal(got.aux[k], whole.aux[k])
    # a bad cell far into the file: the same message, naming the same line
    bad = list(lines)
    bad[1000] = bad[1000].replace(',', ',x', 1)
    path.write_text(''.join(bad))
    with pytest.raises(CsvFormatError) as whole_err:
        read_csv(path)
    with pytest.raises(CsvFormatError) as chunk_err:
        list(csv_chunks(path, rows=97))
    for err in (whole_err, chunk_err):
        assert 'line 1001' in str(err.value) and 'x' in str(err.value)
    # time going back across a chunk boundary is refused, naming the line
    back = list(lines)
    t_line = back[400].split(',')
    back[400] = ','.join(['0.0'] + t_line[1:])
    path.write_text(''.join(back))
    with pytest.raises(CsvFormatError, match='non-decreasing'):
        list(csv_chunks(path, rows=97))


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_bag_in_chunks_is_what_read_bag_reads(tmp_path, storage):
    data, _ = simulate(n_samples=600, rate_hz=20.0, trajectory='smooth', seed=3, attitude=True,
                       diurnal_swing_nt=20.0)
    bag = write_bag(tmp_path / 'bag', pieces(data, 250), storage=storage)
    whole = read_bag(bag)
    got = concat(list(bag_chunks(bag, rows=64)))
    assert got.n_samples == whole.n_samples == 600
    for key in ('t', 'raw', 'temp', 'ref_total'):
        np.testing.assert_array_equal(getattr(got, key), getattr(whole, key))
    for k in whole.aux:
        np.testing.assert_array_equal(got.aux[k], whole.aux[k])
    # slerp of the same messages on a window of them: equal to rounding
    np.testing.assert_allclose(got.attitude, whole.attitude, rtol=0, atol=1e-12)


def test_reduction_keeps_the_field_rate_and_the_statistics_of_every_epoch(record):
    data = record
    red = reduce_chunks(pieces(data, 997), sample=1000, block=500, blocks=3)
    s = red.sample
    # 6000 epochs into 1000..2000: every 4th, evenly spread from the first epoch
    assert red.n_total == 6000 and red.info['sample_stride'] == 4
    idx = np.arange(0, 6000, 4)
    np.testing.assert_array_equal(s.t, data.t[idx])
    np.testing.assert_array_equal(s.raw, data.raw[:, idx])
    # the field rate of the record held whole (central differences of the full rate), not
    # of the sample's spacing, at chunk boundaries too
    for j in range(1, 5):
        np.testing.assert_array_equal(s.context(j).raw_rate, data.context(j).raw_rate[idx])
    # residual statistics of every epoch, chunk by chunk, equal the in-memory summary of the
    # same fit (the model holds the step, the line and the lag: all exact in chunks)
    res = fit(data, Model.from_spec(SPEC, 4), field_nt=50000.0)
    pos = geometry_positions(cross_geometry(), 4)
    stats = residual_statistics(pieces(data, 997), res, pos)
    summ = summarize(res, data, pos)
    for key, v in stats.items():
        if key == 'n_samples':
            assert v == summ[key] == 6000
        elif isinstance(v, dict):
            np.testing.assert_allclose(list(v.values()), list(summ[key].values()), rtol=1e-12)
        else:
            np.testing.assert_allclose(v, summ[key], rtol=1e-12)
    # the noise floor from 6 blocks of 500 full-rate epochs (3000 epochs x 3 axes): a robust
    # sd from n = 9000 differences has a relative sd of about 1 / sqrt(2 n) = 0.75 %, the
    # in-memory one (18 000) 0.5 %: 3 % is 3.3 sd of their difference
    floor_mem = data_noise_floor(data, res).per_sensor_nt
    floor_red = data_noise_floor(s, fit(s, Model.from_spec(SPEC, 4), field_nt=50000.0))
    np.testing.assert_allclose(floor_red.per_sensor_nt, floor_mem, rtol=0.03)
    assert floor_red.status == ('white',) * 4


def test_reduced_fit_and_verdict_agree_with_the_record_held_in_memory():
    # the held-out style: a hidden temperature effect on sensor 2, 4 x 12 000 epochs
    from magcal_ros.core.discovery import diagnose
    data, _ = simulate(n_samples=12000, rate_hz=20.0, trajectory='smooth', seed=11,
                       truth={'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]})
    red = reduce_chunks(pieces(data, 5000), sample=1500)
    assert red.info['sample_stride'] == 4
    model = 'base,temperature@2'
    full = fit(data, model, field_nt=50000.0, max_fit_samples=None)
    part = fit(red.sample, model, field_nt=50000.0, max_fit_samples=None)
    # each estimate is unbiased with standard uncertainty stderr; the two share the sample's
    # epochs, so their errors are positively correlated and var(difference) <= sf^2 + sr^2.
    # 4.5 sd: a Gaussian exceeds it with probability 6.8e-6, 4e-4 over the 57 parameters
    tol = 4.5 * np.hypot(full.stderr, part.stderr)
    assert np.all(np.abs(part.params - full.params) <= tol), np.max(
        np.abs(part.params - full.params) / np.hypot(full.stderr, part.stderr))
    # and the diagnosis of the base model comes to the same verdict
    v_full = diagnose(data, 'base', field_nt=50000.0, folds=3).verdict_token
    v_part = diagnose(red.sample, 'base', field_nt=50000.0, folds=3).verdict_token
    assert v_full == v_part == 'temperature@2'


def test_simulate_writes_a_long_record_in_chunks(tmp_path):
    from magcal_ros.core.data.simulate import simulate_chunks
    sim, parts = simulate_chunks(n_samples=2500, rate_hz=20.0, seed=4, rows=1000)
    n = write_csv_chunks(tmp_path / 'sim.csv', parts, comment='chunks')
    back = read_csv(tmp_path / 'sim.csv')
    assert n == back.n_samples == 2500
    np.testing.assert_allclose(back.t, np.arange(2500) / 20.0, atol=1e-6)
    # the same time functions as the in-memory simulator (the noise drawn per chunk)
    np.testing.assert_allclose(back.temp, sim.temperature(back.t), atol=1e-4)


# -- progress bars --------------------------------------------------------------------------

@pytest.fixture(scope='module')
def small_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp('prog') / 'small.csv'
    data, _ = simulate(n_samples=1500, rate_hz=10.0, trajectory='smooth', seed=2)
    write_csv(path, data)
    return str(path)


def run_fit(small_csv, extra, tty):
    """Run ``magcal fit`` with stderr on a pseudo-terminal (``tty``) or a pipe; its stderr."""
    cmd = [sys.executable, '-m', 'magcal_ros.cli', 'fit', small_csv, '--field-nt', '50000',
           *extra]
    env = dict(os.environ, COLUMNS='100')
    if not tty:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
        assert p.returncode == 0, p.stderr
        return p.stderr
    master, slave = pty.openpty()
    # a terminal of 24 x 100 characters (a new pseudo-terminal has none: 0 columns)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack('HHHH', 24, 100, 0, 0))
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=slave, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            b = os.read(master, 4096)
        except OSError:                 # the child closed the terminal
            break
        if not b:
            break
        chunks.append(b)
    os.close(master)
    assert p.wait(timeout=120) == 0
    return b''.join(chunks).decode(errors='replace')


def test_a_terminal_shows_a_bar_with_the_step_and_the_time_left(small_csv):
    err = run_fit(small_csv, [], tty=True)
    # tqdm: "fit: 100%|####| 1/1 [elapsed<remaining, rate]"
    assert 'fit:' in err and '1/1 [' in err and '<' in err.split('1/1 [', 1)[1]


@pytest.mark.parametrize('extra, tty', [(['--quiet'], True), (['--json'], True), ([], False)])
def test_no_bar_with_quiet_with_json_or_off_a_terminal(small_csv, extra, tty):
    err = run_fit(small_csv, extra, tty)
    assert '1/1 [' not in err and '%|' not in err


def test_cli_reads_a_long_record_in_chunks_to_the_in_memory_result(
        tmp_path, monkeypatch, capsys):
    # 3000 epochs above a lowered threshold: read in chunks of 65 536 (one), sampled every
    # epoch (3000 < 20 000) and one noise block (3000 < 4096): the reduced path must give
    # exactly the in-memory figures, plus what it did
    import json
    from magcal_ros.cli import main
    from magcal_ros.core.data import reduce
    data, _ = simulate(n_samples=3000, rate_hz=10.0, trajectory='smooth', seed=8,
                       truth={'temperature@2': [3.0, -2.0, 1.5, 0.0, 0.0, 0.0]})
    path = tmp_path / 'r.csv'
    write_csv(path, data)
    argv = ['fit', str(path), '--field-nt', '50000', '--json']
    assert main(argv) == 0
    whole = json.loads(capsys.readouterr().out)
    monkeypatch.setattr(reduce, 'REDUCE_ABOVE', 1000)
    assert main(argv) == 0
    chunked = json.loads(capsys.readouterr().out)
    assert chunked.pop('reduction') == {
        'epochs': 3000, 'sample_epochs': 3000, 'sample_stride': 1, 'noise_block_epochs': 4096,
        'noise_blocks': 1, 'noise_epochs': 3000, 'span_s': 299.9}
    assert chunked.keys() == whole.keys()
    assert chunked['warnings'] == whole['warnings']
    assert chunked['n_samples'] == whole['n_samples'] == 3000
    for key in ('noise_floor_nt', 'scalar_rms_nt', 'vector_rms_nt', 'total_field_rms_before_nt',
                'total_field_max_dev_after_nt', 'tensor_rms_nt_per_m', 'sigma_nt'):
        a, b = chunked[key], whole[key]
        if isinstance(a, dict):
            a, b = list(a.values()), list(b.values())
        np.testing.assert_allclose(np.array(a, float), np.array(b, float), rtol=1e-12,
                                   err_msg=key)
    assert main(['diagnose', str(path), '--field-nt', '50000', '--json', '--folds', '0']) == 0
    diag = json.loads(capsys.readouterr().out)
    assert diag['reduction']['epochs'] == diag['n_samples'] == 3000
    assert diag['verdict']['token'] == 'temperature@2'
