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

"""Calibration file (docs/design.md §4): content, atomic writes, history, refusals."""
import os

from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.model import Calibration, Model
from magcal_ros.io import calfile
from magcal_ros.io.calfile import CalibrationFileError, load_calibration, save_calibration
from magcal_ros.pipeline import calibrate
import numpy as np
import pytest
import yaml


@pytest.fixture(scope='module')
def run():
    data, sim = simulate(n_samples=400, rate_hz=2.0, trajectory='random', seed=3,
                         truth={'temperature@2': [2.0, -1.0, 0.5, 0, 0, 0]})
    return data, calibrate(data, 'base,temperature@2', field_nt=50000.0)


def test_document_content_and_round_trip(tmp_path, run):
    data, r = run
    path = tmp_path / 'cal.yaml'
    save_calibration(path, r.doc)
    cal, doc = load_calibration(path)
    assert doc['schema_version'] == 1
    assert doc['model'] == r.result.model.spec()
    s2 = doc['sensors'][1]
    temp = next(e for e in s2['effects'] if e['name'] == 'temperature')
    assert temp['params']['cx']['unit'] == 'nT/degC'
    assert temp['params']['cx']['stderr'] > 0
    assert 't0_c' in temp['refs']
    # the derived matrices and their relations (paper 004 eq. 5, 14): A^-1 = R C^-1 with
    # C^-1 upper triangular and R a proper rotation; the offset is the offset parameters
    keys = ('correction_matrix', 'intrinsic_correction', 'rotation_to_sensor1')
    a_inv, c_inv, rot = (np.asarray(s2[k]) for k in keys)
    assert a_inv.shape == c_inv.shape == rot.shape == (3, 3)
    np.testing.assert_allclose(rot @ c_inv, a_inv, atol=1e-12)
    assert np.all(np.tril(c_inv, -1) == 0.0)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
    offset = next(e for e in s2['effects'] if e['name'] == 'offset')['params']
    assert s2['offset_nt'] == [offset[k]['value'] for k in ('bx', 'by', 'bz')]
    prov = doc['provenance']
    for key in ('created', 'samples', 'data_hash', 'temperature_range_c', 'attitude_coverage',
                'residuals'):
        assert key in prov
    assert prov['samples'] == 400
    assert doc['geometry']['baseline_m'] == 0.5
    # the loaded calibration corrects exactly like the fitted one
    assert np.allclose(cal.correct_dataset(data), r.result.corrected_nt, atol=1e-6)


def test_the_file_reads_the_same_with_libyaml_and_pyyaml(tmp_path, run):
    # the calibration file is read with libyaml's safe loader when PyYAML has it: the same
    # document as PyYAML's own safe loader, and a truncated file is refused by both
    _, r = run
    path = tmp_path / 'cal.yaml'
    save_calibration(path, r.doc)
    text = path.read_text()
    assert yaml.load(text, Loader=calfile._SAFE_LOADER) == yaml.safe_load(text)
    cut = text[:len(text) // 2] + '  - [1.0, 2.'
    for loader in {calfile._SAFE_LOADER, yaml.SafeLoader}:
        with pytest.raises(yaml.YAMLError):
            yaml.load(cut, Loader=loader)  # noqa: S506 - safe loaders
    with pytest.raises(CalibrationFileError, match='not valid YAML'):
        calfile.parse_calibration(cut)


def test_the_file_is_written_as_pyyaml_writes_it(tmp_path, run):
    # written with libyaml's emitter when PyYAML has it: byte for byte what PyYAML's own
    # emitter writes (the reference), for a fitted document as the file holds it (checksum,
    # provenance, a temperature term) and for one with a sensor without a noise estimate (nan)
    _, r = run
    path = tmp_path / 'cal.yaml'
    save_calibration(path, r.doc)
    doc = yaml.safe_load(path.read_text())
    nan_doc = yaml.safe_load(path.read_text())
    nan_doc['sensors'][2]['sigma_nt'] = float('nan')
    for d in (doc, nan_doc):
        assert calfile._yaml(d) == yaml.safe_dump(d, sort_keys=False, default_flow_style=None,
                                                  width=100)
    assert calfile._SAFE_DUMPER is getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


def test_atomic_write_keeps_previous_on_failing_fsync(tmp_path, run):
    _, r = run
    path = tmp_path / 'cal.yaml'
    save_calibration(path, r.doc)
    before = path.read_text()
    doc2 = dict(r.doc, provenance=dict(r.doc['provenance'], source='second'))

    def broken_fsync(fd):
        raise OSError(5, 'Input/output error')

    with pytest.raises(OSError, match='Input/output'):
        save_calibration(path, doc2, fsync=broken_fsync)
    assert path.read_text() == before
    load_calibration(path)
    assert not [f for f in os.listdir(tmp_path) if f.endswith('.tmp')]


def test_backup_history_and_rollback(tmp_path, run):
    _, r = run
    path = tmp_path / 'cal.yaml'
    for k in range(5):
        doc = dict(r.doc, provenance=dict(r.doc['provenance'], source=f'run{k}'))
        save_calibration(path, doc, history=3)
    assert len(calfile.list_history(path)) == 3
    backup = yaml.safe_load((tmp_path / 'cal.yaml.bak').read_text())
    assert backup['provenance']['source'] == 'run3'
    calfile.rollback(path, steps=1)
    assert load_calibration(path)[1]['provenance']['source'] == 'run3'
    with pytest.raises(CalibrationFileError, match='cannot go back 7'):
        calfile.rollback(path, steps=7)


def _mutate(doc, fn):
    doc = yaml.safe_load(calfile.dump_calibration(doc))
    fn(doc)
    return calfile.dump_calibration(doc)


@pytest.mark.parametrize('make,match', [
    # cut inside the flow list of a sensor position
    (lambda d: calfile.dump_calibration(d)[:200], 'not valid YAML'),
    (lambda d: '', 'file is empty'),
    (lambda d: '\x00\x01garbage: [', 'not valid YAML'),
    (lambda d: _mutate(d, lambda x: x.update(schema_version=99)), 'schema_version 99 is newer'),
    (lambda d: _mutate(d, lambda x: x.update(schema_version='one')), 'must be an integer'),
    (lambda d: _mutate(d, lambda x: x['sensors'][0]['correction_matrix'][0].__setitem__(0, 2.0)),
     'correction_matrix does not match the parameters'),
    (lambda d: _mutate(d, lambda x: x['sensors'][1]['offset_nt'].__setitem__(2, 1.0)),
     'sensor 2: offset_nt does not match the parameters'),
    (lambda d: _mutate(d, lambda x: x['sensors'][0]['effects'][0]['params']['kx'].update(
        value='abc')), 'value is not a number'),
    (lambda d: _mutate(d, lambda x: x['sensors'][0]['effects'][0].update(name='warp')),
     'unknown effect'),
    (lambda d: _mutate(d, lambda x: x.pop('sensors')), "missing key 'sensors'"),
    (lambda d: '[1, 2, 3]', 'not a calibration document'),
])
def test_bad_files_refused(tmp_path, run, make, match):
    _, r = run
    path = tmp_path / 'bad.yaml'
    path.write_text(make(r.doc))
    with pytest.raises(CalibrationFileError, match=match):
        load_calibration(path)


def test_the_written_document_follows_the_declared_schema(run):
    # the schema (jsonschema, draft 2020-12) describes what calibration_to_doc writes: the
    # fitted document with a temperature effect validates, and a matrix of 2 rows does not
    import jsonschema
    _, r = run
    doc = yaml.safe_load(calfile.dump_calibration(r.doc))
    jsonschema.Draft202012Validator.check_schema(calfile.SCHEMA)
    jsonschema.validate(doc, calfile.SCHEMA)
    doc['sensors'][0]['correction_matrix'] = doc['sensors'][0]['correction_matrix'][:2]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, calfile.SCHEMA)


_TODO = r'; write it again with magcal fit or roll back \(magcal rollback\)$'


@pytest.mark.parametrize('edit,message', [
    (lambda d: d['sensors'][1]['effects'][0]['params']['kx'].update(value='abc'),
     r'^bad\.yaml: malformed calibration document: sensors\[1\]\.effects\[0\]\.params\.kx\.'
     r"value: value is not a number \('abc'\)" + _TODO),
    (lambda d: d['sensors'][1].update(correction_matrix=[[1, 2, 3], [1, 2, 3]]),
     r'^bad\.yaml: malformed calibration document: sensors\[1\]\.correction_matrix: '
     r'correction_matrix must have at least 3 entries, has 2' + _TODO),
    (lambda d: d['sensors'][0].update(id='one'),
     r'^bad\.yaml: malformed calibration document: sensors\[0\]\.id: id is not an integer '
     r"\('one'\)" + _TODO),
    (lambda d: d['sensors'][0]['effects'][0].update(refs={'t0_c': 'warm'}),
     r"sensors\[0\]\.effects\[0\]\.refs\.t0_c: t0_c is not a number \('warm'\)" + _TODO),
    (lambda d: d.update(provenance=[1]),
     r'^bad\.yaml: malformed calibration document: provenance: provenance is not a mapping'),
    (lambda d: d['sensors'][2].pop('effects'),
     r"^bad\.yaml: sensors\[2\]: missing key 'effects'; write the calibration again"),
])
def test_schema_errors_say_where_and_what_to_do(run, edit, message):
    _, r = run
    doc = yaml.safe_load(calfile.dump_calibration(r.doc))
    assert len(doc['sensors']) == 4                    # the simulated cross
    edit(doc)
    with pytest.raises(CalibrationFileError, match=message):
        calfile.parse_calibration(calfile.dump_calibration(doc), 'bad.yaml')


def test_a_mirrored_sensor_shows_its_own_scale_and_angles(tmp_path):
    # sensor 2 mounted mirrored (reading y is its y axis reversed): a calibration written by
    # hand, A_2 = M S C_NO R with M = diag(1, -1, 1) (docs/design.md section 4).  The file's
    # intrinsic_correction and rotation_to_sensor1 decompose S C_NO R, without M: the
    # diagonal of C^-1 is 1/k (C_NO's diagonal differs from 1 by at most the square of the
    # angles, < 1e-4 here) and R turns by no more than the misalignment angles (|.| < 0.026
    # rad); M is recorded beside them and A^-1 = R C^-1 M^T
    model = Model.from_spec('base,axes(x,-y,z)@2', 2)
    scale, angles = np.array([1.02, 0.98, 1.01]), np.array([0.01, -0.02, 0.015])
    values = {'offset': [100.0, -50.0, 30.0], 'scale': scale,
              'nonorthogonality': [0.004, -0.003, 0.002], 'misalignment': angles}
    p = model.default_params()
    for eff, sl in zip(model.effects[1], model.slices[1]):
        if eff.name in values:
            p[sl] = values[eff.name]
    path = tmp_path / 'mirrored.yaml'
    save_calibration(path, calfile.calibration_to_doc(Calibration(model, p)))
    _, doc = load_calibration(path)
    s2 = doc['sensors'][1]
    mirror = np.diag([1.0, -1.0, 1.0])
    np.testing.assert_array_equal(s2['axis_map'], mirror)
    c_inv, rot = np.asarray(s2['intrinsic_correction']), np.asarray(s2['rotation_to_sensor1'])
    np.testing.assert_allclose(np.diag(c_inv), 1 / scale, atol=1e-4)
    angle = np.arccos((np.trace(rot) - 1) / 2)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
    assert 0.01 < angle < np.linalg.norm(angles) + 1e-3
    np.testing.assert_allclose(rot @ c_inv @ mirror.T, s2['correction_matrix'], atol=1e-12)
    assert 'axis_map' not in doc['sensors'][0]          # only a sensor with axes(...)
    # a hand edit of the recorded map (a sign) is refused, naming it
    bad = yaml.safe_load(path.read_text())
    bad['sensors'][1]['axis_map'][1][1] = 1.0
    with pytest.raises(CalibrationFileError, match='sensor 2: axis_map does not match'):
        calfile.calibration_from_doc(bad)
