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

"""Wide CSV (docs/design.md §1): round trip and clear errors."""
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.csvio import CsvFormatError, read_csv, write_csv
import numpy as np
import pytest


def test_round_trip(tmp_path):
    data, _ = simulate(n_samples=50, trajectory='smooth', seed=0, diurnal_swing_nt=10)
    data.angle_deg = np.arange(50.0)
    data.plane = np.array(['xy'] * 25 + ['xz'] * 25)
    path = tmp_path / 'd.csv'
    write_csv(path, data, comment='test\nsecond line')
    back = read_csv(path)
    assert back.n_sensors == 4 and back.n_samples == 50
    assert np.allclose(back.raw, data.raw, atol=1e-4)           # written with 4 decimals
    assert np.allclose(back.temp, data.temp, atol=1e-4)
    assert np.allclose(back.ref_total, data.ref_total, atol=1e-4)
    assert sorted(back.aux) == sorted(data.aux)
    assert list(back.plane) == list(data.plane)
    assert path.read_text().startswith('# test\n# second line\n')


@pytest.mark.parametrize('text,match', [
    ('t,s1_x,s1_y,s1_z,bogus\n0,1,2,3,4\n', "unknown column 'bogus'"),
    ('t,s1_x,s1_y\n0,1,2\n', r'sensor 1 lacks column\(s\) s1_z'),
    ('s1_x,s1_y,s1_z\n1,2,3\n', 'time column t is missing'),
    ('t,s1_x,s1_y,s1_z\n0,1,2,abc\n', "line 2, column s1_z: 'abc' is not a number"),
    ('# c\n\nt,s1_x,s1_y,s1_z\n0,1,2,3\n\n# c\n1,x1,2,3\n',
     "line 7, column s1_x: 'x1' is not a number"),
    ('t,s1_x,s1_y,s1_z\n0,1,2,3\n1,1,2,3,4\n', 'line 3 has 5 fields, header has 4'),
    ('t,s1_x,s1_y,s1_z\n0,1,2\n', 'line 2 has 3 fields, header has 4'),
    # issue 10: careless input, each with the line and column or the cause named
    ('# c\nt,s1_x,s1_y,s1_z\n0,1,2,3\n1,1,,3\n2,1,2,3\n',
     r'line 4, column s1_y: an empty cell \(1 row\(s\) affected\)'),
    ('t,s1_x,s1_y,s1_z\n0,1,2,3\n1,nan,2,3\n', "line 3, column s1_x: 'nan' is not a finite"),
    ('t,s1_x,s1_y,s1_z,ref_total\n0,1,2,3,inf\n', "line 2, column ref_total: 'inf' is not a "
                                                  'finite number'),
    ('t,s1_x,s1_y,s1_z\n', r'no data rows \(only the header\)'),
    ('t;s1_x;s1_y;s1_z\n0;1;2;3\n', r"separated by semicolons \(';'\).*comma separated"),
    ('t\ts1_x\ts1_y\ts1_z\n0\t1\t2\t3\n', r"separated by tabs \('\\t'\)"),
    ('t,s1_x,s1_y,s1_z\n1,1,2,3\n0,1,2,3\n', 'non-decreasing'),
    ('# only a comment\n', 'no header row'),
    ('t,aux_a\n0,1\n', 'no sensor columns'),
])
def test_bad_files(tmp_path, text, match):
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(CsvFormatError, match=match):
        read_csv(path)


def test_missing_file(tmp_path):
    with pytest.raises(CsvFormatError, match='cannot read'):
        read_csv(tmp_path / 'nope.csv')


def test_utf8_byte_order_mark_loads(tmp_path):
    # a spreadsheet's UTF-8 export starts with a BOM; the first column is still t
    path = tmp_path / 'bom.csv'
    path.write_bytes('\ufefft,s1_x,s1_y,s1_z,s1_temp\n0,1,2,3,\n1,4,5,6,20.5\n'.encode('utf-8'))
    data = read_csv(path)
    np.testing.assert_array_equal(data.t, [0.0, 1.0])
    np.testing.assert_array_equal(data.raw[0], [[1, 2, 3], [4, 5, 6]])
    # an empty optional cell (temperature) is "no value", not an error
    assert np.isnan(data.temp[0, 0]) and data.temp[0, 1] == 20.5
