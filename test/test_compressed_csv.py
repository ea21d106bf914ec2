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
Compressed CSV (issue 19 item 5): ``.csv.gz`` and ``.csv.zst`` read as the plain CSV is.

The compressed files are made here with the standard library's gzip and the zstandard
package directly (not with magcal_ros.io.compressed), and every command's output on them
must equal its output on the plain file; a corrupt, truncated or mislabelled archive is
refused with one line naming the file and the format (exit status 2), never read as a
shorter record.
"""
import gzip
import json
import pathlib

from injection import make
from magcal_ros.cli import main
from magcal_ros.io.csvio import CsvFormatError, format_csv, read_csv, write_csv
import numpy as np
import pytest
import zstandard

REPO = pathlib.Path(__file__).resolve().parents[1]
CK = REPO / 'data' / 'real' / 'ck-accmag' / 'acc_mag_log.csv.gz'


def _gzip(b):
    return gzip.compress(b)


def _zstd(b):
    return zstandard.ZstdCompressor(level=3).compress(b)


def _zstd_two_frames(b):
    # a file made by concatenating two .zst files (zstd -c a b > ab.zst) is one stream
    c = zstandard.ZstdCompressor(level=3)
    half = b.index(b'\n', len(b) // 2) + 1
    return c.compress(b[:half]) + c.compress(b[half:])


@pytest.fixture(scope='module')
def files(tmp_path_factory):
    """Write the same recording as plain, gzip, zstd and two-frame zstd CSV."""
    d = tmp_path_factory.mktemp('compressed')
    text = format_csv(make(n=1200, seed=4), comment='injection.make(n=1200, seed=4)')
    b = text.encode('utf-8')
    out = {'plain': d / 'rec.csv'}
    out['plain'].write_bytes(b)
    for name, suffix, comp in (('gz', '.csv.gz', _gzip), ('zst', '.csv.zst', _zstd),
                               ('zst2', '.frames.csv.zst', _zstd_two_frames)):
        out[name] = d / f'rec{suffix}'
        out[name].write_bytes(comp(b))
    return out


@pytest.mark.parametrize('kind', ['gz', 'zst', 'zst2'])
def test_read_csv_equals_the_plain_file(files, kind):
    plain, packed = read_csv(files['plain']), read_csv(files[kind])
    assert packed.raw.shape == (4, 1200, 3)
    for name in ('t', 'raw', 'temp'):
        np.testing.assert_array_equal(getattr(packed, name), getattr(plain, name))
    assert packed.aux.keys() == plain.aux.keys()
    for k in plain.aux:
        np.testing.assert_array_equal(packed.aux[k], plain.aux[k])


def _json(capsys, *argv):
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    assert rc == 0, out.err
    return json.loads(out.out)


@pytest.mark.parametrize('kind', ['gz', 'zst'])
def test_fit_and_check_answer_as_on_the_plain_file(files, kind, tmp_path, capsys):
    docs = {}
    for k in ('plain', kind):
        cal = tmp_path / f'{k}.yaml'
        docs[k] = _json(capsys, 'fit', files[k], '--field-nt', 50000, '--json', '-o', cal)
        docs[k].pop('output')
        prov = docs[k]['calibration']['provenance']
        assert prov.pop('source') == str(files[k])
        prov.pop('created')                         # the second it was made
        # the checksum covers the source and the time, which differ; it is checked on load
        assert docs[k]['calibration'].pop('checksum').startswith('sha256:')
        chk = _json(capsys, 'check', cal, files[k], '--json')
        chk.pop('calfile')
        docs[k]['check'] = chk
    # the check names each recording by its file name, which differs (rec.csv, rec.csv.gz)
    rows = [docs[k]['check'].pop('recordings') for k in ('plain', kind)]
    assert len(rows[0]) == len(rows[1]) == 1
    names = [r[0].pop('name') for r in rows]
    assert names == ['rec.csv', files[kind].name]
    assert rows[0] == rows[1]
    assert docs[kind] == docs['plain']


def test_diagnose_and_report_read_a_zst_file(files, tmp_path, capsys):
    plain = _json(capsys, 'diagnose', files['plain'], '--field-nt', 50000, '--json')
    packed = _json(capsys, 'diagnose', files['zst'], '--field-nt', 50000, '--json')
    assert packed['verdict'] == plain['verdict']
    assert packed['noise_floor_nt'] == plain['noise_floor_nt']
    rc = main(['report', str(files['gz']), '--field-nt', '50000', '--no-ladder', '--quiet',
               '--out', str(tmp_path / 'rep')])
    assert rc == 0 and (tmp_path / 'rep' / 'index.html').is_file()


def test_simulate_writes_what_its_suffix_says(tmp_path, capsys):
    for suffix, magic in (('.csv.gz', b'\x1f\x8b'), ('.csv.zst', b'\x28\xb5\x2f\xfd')):
        out = tmp_path / f'sim{suffix}'
        assert main(['simulate', '--out', str(out), '--n', '200', '--seed', '1']) == 0
        assert out.read_bytes()[:4].startswith(magic)
        assert read_csv(out).raw.shape == (4, 200, 3)
    plain = tmp_path / 'sim.csv'
    assert main(['simulate', '--out', str(plain), '--n', '200', '--seed', '1']) == 0
    np.testing.assert_array_equal(read_csv(plain).raw, read_csv(tmp_path / 'sim.csv.gz').raw)
    capsys.readouterr()


def test_write_csv_round_trip(tmp_path):
    data = make(n=50, seed=2)
    write_csv(tmp_path / 'a.csv.zst', data)
    raw = zstandard.ZstdDecompressor().decompress((tmp_path / 'a.csv.zst').read_bytes())
    assert raw.decode('utf-8') == format_csv(data)


def test_single_sensor_csv_gz_with_unit(capsys):
    # the MEMS recording of the repository is stored gzipped: read with --unit as a user would
    doc = _json(capsys, 'fit', CK, '--unit', 'gauss', '--field-nt', 'auto', '--json')
    plain = gzip.decompress(CK.read_bytes()).decode().splitlines()
    assert len(plain) == 12001 and plain[0] == 'ax,ay,az,mx,my,mz'
    assert doc['n_samples'] == 12000


def _corrupt(b):
    b = bytearray(b)
    mid = len(b) // 2
    b[mid:mid + 64] = bytes(64)
    return bytes(b)


@pytest.mark.parametrize('suffix,comp', [('.csv.gz', _gzip), ('.csv.zst', _zstd)])
@pytest.mark.parametrize('damage', ['truncated', 'corrupt', 'not compressed'])
def test_a_bad_archive_is_refused_with_one_line(files, tmp_path, capsys, suffix, comp, damage):
    b = files['plain'].read_bytes()
    packed = comp(b)
    body = {'truncated': packed[:len(packed) // 2], 'corrupt': _corrupt(packed),
            'not compressed': b}[damage]
    bad = tmp_path / f'bad{suffix}'
    bad.write_bytes(body)
    fmt = {'.csv.gz': 'gzip', '.csv.zst': 'zstd'}[suffix]
    with pytest.raises(CsvFormatError, match=f'the {fmt} archive is corrupt or truncated'):
        read_csv(bad)
    for argv in (['fit', str(bad), '--field-nt', '50000'],
                 ['diagnose', str(bad), '--field-nt', '50000']):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert str(bad) in err[0] and f'{fmt} archive is corrupt or truncated' in err[0]


def test_a_truncated_single_sensor_archive_is_refused(tmp_path, capsys):
    packed = CK.read_bytes()
    bad = tmp_path / 'log.csv.gz'
    bad.write_bytes(packed[:len(packed) // 2])
    assert main(['fit', str(bad), '--unit', 'gauss', '--field-nt', 'auto']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'gzip archive is corrupt or truncated' in err[0], err
