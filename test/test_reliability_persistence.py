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
The calibration file under crashes, truncation, corruption and hand edits; history, rollback.

Already covered elsewhere and not repeated: a failing fsync leaves the previous file (the
writer survives and cleans up), a few corrupt/future/hand-edited files refused by the loader,
the history bound and one rollback (test_calfile.py); the corrector refusing invalid YAML
and a calibration for another sensor count on calibration/result, and a future-schema file at
start-up (test_corrector_node.py). Added here:

- a writer process killed with SIGKILL while it fsyncs (before the rename, and after it while
  writing the history copy): the active file is the complete old (or new) calibration, the
  temporary file left behind is invisible to the loader, the history and rollback, and the
  next write and a rollback work;
- every truncation of a real calibration file, and random byte corruption and structural hand
  edits (hypothesis), are refused with a CalibrationFileError naming the problem, or load a
  calibration identical to the complete one: never another exception, never a silently
  different calibration (both happened before: a file cut inside the sensors list loaded with
  fewer sensors, and cut-short YAML raised TypeError, which crashed the nodes);
- the corrector fed a series of such documents keeps correcting with its last good
  calibration and reports each refusal, with the problem, on /diagnostics; the corrector and
  the calibration node start with a truncated file instead of crashing;
- the calibration node's ``history`` parameter bounds the history, and ``magcal rollback``
  walks back through it.
"""
import copy
import json
import os
import re
import shutil
import signal
import subprocess
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hypothesis import given, HealthCheck, settings, strategies as st
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io import calfile
from magcal_ros.io.calfile import (calibration_to_doc, CalibrationFileError, dump_calibration,
                                   list_history, load_calibration, parse_calibration,
                                   save_calibration)
from magcal_ros.pipeline import calibrate, cross_geometry
from magcal_ros.ros.calibration_node import CalibrationNode, RESULT_QOS
from magcal_ros.ros.conversions import msg_to_field_nt
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import call_trigger, spin_until, subprocess_env
from sensor_msgs.msg import MagneticField
from sim_feed import Feeder
from std_msgs.msg import String
import yaml

F = 50000.0


@pytest.fixture(scope='module')
def fitted():
    """Return a real calibration document (base + temperature on sensor 2) and its data."""
    data, _ = simulate(n_samples=400, rate_hz=2.0, trajectory='random', seed=3,
                       truth={'temperature@2': [2.0, -1.0, 0.5, 0, 0, 0]})
    run = calibrate(data, 'base,temperature@2', field_nt=F)
    return data, run.doc


def variant(doc, tag):
    """Copy ``doc``, told apart by its provenance (``source``)."""
    new = copy.deepcopy(doc)
    new['provenance']['source'] = tag
    return new


def source_of(path):
    return load_calibration(path)[1]['provenance']['source']


# -- a writer killed in the middle -----------------------------------------------------------

WRITER = r"""
from magcal_ros.io.calfile import load_calibration, save_calibration
import os, sys, time
path, new_doc, stage = sys.argv[1], sys.argv[2], int(sys.argv[3])
_, doc = load_calibration(new_doc)
calls = []
def fsync(fd):
    calls.append(fd)
    if len(calls) == stage:          # 1: the new file's temporary, 2: its history copy
        print('IN_FSYNC', flush=True)
        time.sleep(60)
    os.fsync(fd)
save_calibration(path, doc, history=5, fsync=fsync)
print('DONE', flush=True)
"""


def leftovers(directory, keep):
    return sorted(f for f in os.listdir(directory) if f not in keep)


@pytest.mark.parametrize('stage', [1, 2], ids=['before-rename', 'during-history-copy'])
def test_writer_killed_during_fsync_leaves_a_complete_file(tmp_path, fitted, start_process,
                                                           stage):
    _, doc = fitted
    path = tmp_path / 'calibration.yaml'
    save_calibration(path, variant(doc, 'older'), history=5)
    older_bytes = path.read_bytes()
    save_calibration(path, variant(doc, 'old'), history=5)
    old_bytes = path.read_bytes()
    hist_before = list_history(path)
    new_doc = tmp_path / 'new.yaml'
    new_doc.write_text(dump_calibration(variant(doc, 'new')))
    (tmp_path / 'writer.py').write_text(WRITER)
    writer = start_process([sys.executable, tmp_path / 'writer.py', path, new_doc, stage],
                           name='writer', ready='IN_FSYNC')
    os.kill(writer.pid, signal.SIGKILL)
    assert writer.wait(10) == -signal.SIGKILL
    assert 'DONE' not in writer.read_log()

    if stage == 1:
        # killed before the rename: the previous file, byte for byte
        assert path.read_bytes() == old_bytes
        assert source_of(path) == 'old'
        assert (tmp_path / 'calibration.yaml.bak').read_bytes() == older_bytes
    else:
        # killed after the rename: the complete new file, the old one as .bak
        assert source_of(path) == 'new'
        assert (tmp_path / 'calibration.yaml.bak').read_bytes() == old_bytes
    # the temporary left by the killed writer is a hidden *.tmp file, which neither the
    # loader (it opens only the given path), nor the history, nor a rollback ever reads
    left = leftovers(tmp_path, {'calibration.yaml', 'calibration.yaml.bak', 'new.yaml',
                                'writer.py', 'calibration.yaml.history'}
                     | {f for f in os.listdir(tmp_path) if f.endswith('.log')})
    left_hist = leftovers(str(path) + '.history', {os.path.basename(h) for h in hist_before})
    tmp_files = left + left_hist
    assert len(tmp_files) == 1, tmp_files
    assert re.fullmatch(r'\.(calibration\.yaml|calibration-[0-9T.Z]+\.yaml)\.\w+\.tmp',
                        tmp_files[0]), tmp_files
    assert list_history(path) == hist_before

    # a rollback still goes back one calibration from the active one, and the next write
    # works and lands in the history
    calfile.rollback(path, steps=1)
    assert source_of(path) == ('older' if stage == 1 else 'old')
    save_calibration(path, variant(doc, 'after'), history=5)
    assert source_of(path) == 'after'
    assert source_of(list_history(path)[-1]) == 'after'
    assert len(list_history(path)) == len(hist_before) + 1


# -- truncation, corruption and hand edits ---------------------------------------------------

def same_calibration(a, b):
    return (a.n_sensors == b.n_sensors and a.model.spec() == b.model.spec()
            and np.array_equal(a.params, b.params))


def test_every_truncation_is_refused_or_loads_the_complete_calibration(tmp_path, fitted):
    _, doc = fitted
    text = dump_calibration(doc)
    full, _ = parse_calibration(text)
    prov_at = text.index('\nprovenance:')
    # every line end, and every 41st byte (inside keys, numbers, flow mappings)
    cuts = sorted({m.start() for m in re.finditer('\n', text)} | set(range(0, len(text), 41)))
    accepted = refused = 0
    path = str(tmp_path / 'cut.yaml')
    for n in cuts:
        try:
            if not text[:n].strip():
                continue                # load_calibration refuses an empty file up front
            cal, _ = parse_calibration(text[:n], path)
        except CalibrationFileError as exc:
            msg = str(exc)
            assert msg.startswith(path) and len(msg) > len(path) + 10, msg
            refused += 1
            continue
        # accepted only when the whole calibration is there (the cut is in the provenance)
        assert n > prov_at and same_calibration(cal, full), (n, text[n - 40:n])
        accepted += 1
    # every cut before the provenance is refused (the accepted branch asserts n > prov_at);
    # cuts inside the provenance may load, and some must
    before = sum(1 for n in cuts if n <= prov_at and text[:n].strip())
    assert refused >= before and accepted > 0


def _paths(node, prefix=()):
    """Every path (tuple of keys/indices) into a nested dict/list document."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


# junk a hand edit may leave (every value YAML can write: no lone surrogates in the text)
_text = st.text(st.characters(blacklist_categories=('Cs',)), max_size=8)
_junk = st.one_of(st.none(), st.booleans(), st.integers(-3, 10**6), _text,
                  st.floats(allow_nan=True, allow_infinity=True),
                  st.lists(st.integers(0, 3), max_size=4),
                  st.dictionaries(_text, st.integers(), max_size=2))


@pytest.fixture(scope='module')
def original(fitted):
    """Load the calibration of the ``fitted`` document once."""
    return parse_calibration(dump_calibration(fitted[1]))[0]


def same_sensors(a, b):
    """Whether two calibrations correct alike: effects, parameters, noise, matrices."""
    return same_calibration(a, b) and np.array_equal(a.sigma_nt, b.sigma_nt, equal_nan=True) \
        and all(np.array_equal(a.correction_matrix(j), b.correction_matrix(j))
                and np.array_equal(a.offset(j), b.offset(j))
                for j in range(1, a.n_sensors + 1))


def _stated(doc):
    """(parameter values, sigma_nt) as a document writes them (the test's own reading)."""
    values = [float(e['params'][pn]['value']) for sd in doc['sensors'] for e in sd['effects']
              for pn in e['params']]
    return values, [float(sd.get('sigma_nt', np.nan)) for sd in doc['sensors']]


def assert_loads_what_it_states(cal, doc, original, original_doc):
    """
    Assert that a loaded document is the calibration it states (the original where it agrees).

    The parameters and the noise are what the document writes (the parameters are the
    source of truth: a changed number is indistinguishable from a hand edit, see
    docs/design.md §4); when they are the original's numbers, everything is the original.
    """
    assert cal.model.spec() == original.model.spec()
    values, sigma = _stated(doc)
    np.testing.assert_array_equal(cal.params, values)
    np.testing.assert_array_equal(cal.sigma_nt, sigma)
    if (values, sigma) == _stated(original_doc):
        assert same_sensors(cal, original)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_hand_edits_are_refused_or_load_what_the_document_says(
        fitted, original, data):
    _, doc = fitted
    paths = list(_paths(doc))[1:]
    edited = copy.deepcopy(doc)
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        node = edited
        try:
            for key in path[:-1]:
                node = node[key]
            if data.draw(st.booleans()) and isinstance(node, (dict, list)):
                node[path[-1]] = data.draw(_junk)
            elif isinstance(node, dict):
                node.pop(path[-1], None)
        except (KeyError, IndexError, TypeError):
            continue                 # an earlier edit removed or replaced this branch
    text = dump_calibration(edited)          # every junk value is representable
    try:
        cal, _ = parse_calibration(text)
    except CalibrationFileError:
        return
    assert_loads_what_it_states(cal, as_loaded(text), original, doc)


def as_loaded(text):
    """
    Read the YAML document ``text`` as the calibration file's loader does (PyYAML on libyaml).

    libyaml takes a tab after a flow indicator (``bz: {value:<TAB>18.9, ...}``, a flip that
    changes no value, found by hypothesis on 2026-11-27) that PyYAML's pure-Python scanner
    refuses, so the statement a loaded file is checked against is read by the same parser.
    """
    return yaml.load(text, Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))  # noqa: S506


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_byte_corruption_is_refused_or_loads_the_original(fitted, original, data):
    _, doc = fitted
    text = dump_calibration(doc)
    raw = bytearray(text.encode())
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(raw) - 1))
        kind = data.draw(st.sampled_from(['flip', 'delete', 'insert']))
        if kind == 'flip':
            raw[at] = data.draw(st.integers(0, 255))
        elif kind == 'delete':
            del raw[at:at + data.draw(st.integers(1, 40))]
        else:
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=10))
    text = bytes(raw).decode('utf-8', errors='replace')
    try:
        cal, _ = parse_calibration(text)
    except CalibrationFileError:
        return
    assert_loads_what_it_states(cal, as_loaded(text), original, doc)


def _single_byte_flips(text, n_digit=120, n_letter=80, n_any=40, seed=11):
    """
    (position, new byte) of single-byte flips of ``text``, drawn with a fixed seed.

    Mostly the flips most likely to still parse: a digit for another digit (a number that
    reads as another number) and a letter for another letter (a key renamed, e.g. sigma_nt);
    then any byte for any other.
    """
    raw = text.encode()
    rng = np.random.default_rng(seed)
    digits = [i for i, b in enumerate(raw) if chr(b).isdigit()]
    letters = [i for i, b in enumerate(raw) if chr(b).isalpha()]
    out = []
    for at in rng.choice(digits, n_digit, replace=False):
        out.append((int(at), ord(str((int(chr(raw[at])) + rng.integers(1, 10)) % 10))))
    for at in rng.choice(letters, n_letter, replace=False):
        new = chr(raw[at]) if chr(raw[at]).isupper() else 'x'
        while new == chr(raw[at]):
            new = chr(int(rng.integers(ord('a'), ord('z') + 1)))
        out.append((int(at), ord(new)))
    for at in rng.integers(0, len(raw), n_any):
        out.append((int(at), (raw[at] + int(rng.integers(1, 256))) % 256))
    return out


def test_every_single_byte_flip_is_refused_or_loads_the_original(fitted, original):
    # a changed digit of a parameter, sigma_nt or offset_nt, or a renamed key, used to load a
    # different calibration without complaint (18 of 3000 uniform flips before the checksum;
    # this set of flips: see the assertion message); now the checksum refuses them
    _, doc = fitted
    text = dump_calibration(doc)
    raw = text.encode()
    refused = identical = 0
    different = []
    for at, byte in _single_byte_flips(text):
        assert raw[at] != byte
        flipped = bytearray(raw)
        flipped[at] = byte
        try:
            cal, _ = parse_calibration(bytes(flipped).decode('utf-8', errors='replace'))
        except CalibrationFileError as exc:
            assert len(str(exc)) > 30
            refused += 1
            continue
        if same_sensors(cal, original):
            identical += 1                   # a comment, quoting, the layout: nothing changed
        else:
            line_at = text.rfind('\n', 0, at) + 1
            different.append(text[line_at:text.find('\n', at)].strip()[:60])
    assert not different, (f'{len(different)} flips loaded a different calibration '
                           f'({refused} refused, {identical} identical): {different[:5]}')
    assert refused > 0


def test_a_tab_after_a_flow_indicator_loads_the_original(fitted, original):
    # hypothesis' example of 2026-11-27: a space turned into a tab changes no value, the
    # checksum still matches, and the file loads as the original
    _, doc = fitted
    text = dump_calibration(doc)
    at = text.index('{value: ') + len('{value:')
    edited = text[:at] + '\t' + text[at + 1:]
    cal, _ = parse_calibration(edited)
    assert_loads_what_it_states(cal, as_loaded(edited), original, doc)


def test_a_file_without_checksum_still_loads_and_a_changed_digit_is_refused(tmp_path, fitted):
    # files written before the checksum (test/data/legacy_cal/, test_grammar.py) load; a
    # digit changed in a file with one is refused with what to do
    _, doc = fitted
    text = dump_calibration(doc)
    stamp = re.search(r'^checksum: (sha256:[0-9a-f]{64})$', text, re.M)
    assert stamp and stamp.group(1) == calfile.content_checksum(yaml.safe_load(text))
    legacy = text.replace(stamp.group(0) + '\n', '')
    assert same_calibration(parse_calibration(legacy)[0], parse_calibration(text)[0])
    # the first decimal: the last of a 17-digit repr may name the same double once changed
    sigma = re.search(r'sigma_nt: (\d+)\.(\d)(\d*)', text)
    changed = f'{sigma.group(1)}.{(int(sigma.group(2)) + 1) % 10}{sigma.group(3)}'
    assert float(changed) != float(sigma.group(0).split()[1])
    path = tmp_path / 'edited.yaml'
    path.write_text(text.replace(sigma.group(0), 'sigma_nt: ' + changed, 1))
    with pytest.raises(CalibrationFileError, match=r'edited\.yaml: checksum does not match the '
                       r'content.*roll back to the previous calibration \(magcal rollback\)'):
        load_calibration(path)
    # the same edit without the checksum line: a deliberate hand edit, loaded as it states
    path.write_text(legacy.replace(sigma.group(0), 'sigma_nt: ' + changed, 1))
    assert load_calibration(path)[0].sigma_nt[0] == float(changed)


def hand_edited(doc):
    """(label, YAML text, regex the refusal must match) of documents to refuse."""
    text = dump_calibration(doc)

    def edit(fn):
        d = copy.deepcopy(doc)
        fn(d)
        return dump_calibration(d)

    def set_in(d, path, value):
        for key in path[:-1]:
            d = d[key]
        d[path[-1]] = value

    cut = text.index('- id: 3')
    return [
        ('cut inside the sensors list', text[:cut], r"missing key 'provenance'.*truncated"),
        ('cut inside a sensor', text[:text.index('effects:', cut)],
         r"sensors\[2\]: missing key 'effects'"),
        ('effects emptied', edit(lambda d: set_in(d, ['sensors', 1, 'effects'], None)),
         r'malformed calibration document'),
        ('sigma_nt not a number', edit(lambda d: set_in(d, ['sensors', 0, 'sigma_nt'], 'abc')),
         r'malformed calibration document'),
        ('label not a string', edit(lambda d: set_in(d, ['sensors', 0, 'effects', 0, 'label'],
                                                     5)), r'malformed calibration document'),
        ('effect removed', edit(lambda d: d['sensors'][3]['effects'].pop()),
         r'does not match'),
        ('geometry not numbers', edit(lambda d: set_in(d, ['geometry', 'positions_m'],
                                                       {'a': 1})),
         r'geometry.positions_m must be 4 rows of 3 finite numbers'),
        ('future schema', edit(lambda d: d.update(schema_version=2)),
         r'schema_version 2 is newer than this magcal_ros understands'),
        ('matrix edited', edit(lambda d: set_in(d, ['sensors', 2, 'correction_matrix', 1, 1],
                                                1.5)),
         r'sensor 3: correction_matrix does not match the parameters \(hand-edited\?\)'),
        ('binary garbage', '\x00\x9f\x92\x96 \x1b[2J' * 20, r'not valid YAML|not a calibration'),
    ]


def test_hand_edited_documents_are_refused_with_the_problem_named(fitted):
    _, doc = fitted
    for label, text, match in hand_edited(doc):
        with pytest.raises(CalibrationFileError, match=match):
            parse_calibration(text, 'edited.yaml')


# -- the nodes keep their last good calibration ----------------------------------------------

class DiagProbe:
    def __init__(self, node, namespace):
        self.status = []
        node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: self.status.extend(
            s for s in m.status if s.hardware_id == namespace), 50)


def test_corrector_refuses_each_bad_document_and_keeps_correcting(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, fitted):
    data, simulator = simulate(n_samples=50, rate_hz=100.0, trajectory='smooth', seed=11)
    sim_truth = simulator.truth
    good = calibration_to_doc(sim_truth, geometry=cross_geometry(0.5))
    path = tmp_path / 'cal.yaml'
    save_calibration(path, good, history=0)
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)),
        Parameter('diagnostics_period_s', value=0.2)])
    probe = DiagProbe(ros_node, ros_namespace)
    corrected = []
    ros_node.create_subscription(MagneticField, 'sensor1/corrected', corrected.append, 100)
    result = ros_node.create_publisher(String, 'calibration/result', RESULT_QOS)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    spin_until(ros_executor, lambda: result.get_subscription_count() > 0, 5.0)
    expected = sim_truth.correct(1, data.raw[0])
    k = 0
    for label, text, match in hand_edited(fitted[1]):
        n_diag = len(probe.status)
        result.publish(String(data=text))
        spin_until(ros_executor, lambda: any(
            s.level == DiagnosticStatus.WARN and re.search(match, s.message)
            for s in probe.status[n_diag:]), 5.0, f'the refusal of "{label}"')
        assert node.context.ok() and node.refusal and re.search(match, node.refusal)
        assert 'keeping the calibration from ' + str(path) in node.refusal, label
        # still correcting with the good calibration
        feeder.feed(ros_executor, data, start=k, stop=k + 4, taken=lambda: node.received,
                    temperature=False)
        spin_until(ros_executor, lambda: len(corrected) == k + 4, 5.0)
        got = np.array([msg_to_field_nt(m) for m in corrected[k:k + 4]])
        np.testing.assert_allclose(got, expected[k:k + 4], atol=1e-6, err_msg=label)
        k += 4
    # a good document is taken again, and the warning clears
    result.publish(String(data=dump_calibration(good)))
    spin_until(ros_executor, lambda: node.calibration_source == 'calibration/result'
               and node.refusal is None, 5.0)
    n_diag = len(probe.status)
    spin_until(ros_executor, lambda: any(s.level == DiagnosticStatus.OK
                                         for s in probe.status[n_diag:]), 5.0)


def test_nodes_start_with_a_truncated_file(make_node, ros_node, ros_executor, ros_namespace,
                                           tmp_path, fitted):
    _, doc = fitted
    text = dump_calibration(doc)
    path = tmp_path / 'cal.yaml'
    # cut right after an 'effects:' key: its value reads as null, which raised TypeError
    # inside the loader (and so in the nodes' constructors) before it was refused
    path.write_text(text[:text.index('effects:') + len('effects:')])
    with pytest.raises(CalibrationFileError, match='malformed calibration document'):
        load_calibration(path)
    # (document, publication sequence number of the calibration node's result writer)
    results = []
    ros_node.create_subscription(String, 'calibration/result', lambda msg, info: results.append(
        (msg.data, info['publication_sequence_number'])), RESULT_QOS)
    probe = DiagProbe(ros_node, ros_namespace)
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)), Parameter('min_samples', value=300),
        Parameter('report_dir', value=str(tmp_path / 'report'))])
    corrector = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    spin_until(ros_executor, lambda: any('malformed calibration document' in s.message
                                         for s in probe.status), 5.0)
    assert corrector.calibration is None and 'no calibration is active' in corrector.refusal
    # 'the calibration node published nothing' without a fixed wait: a calibration on fresh
    # data is the sentinel.  It must be the result writer's first message (sequence number 1)
    # and the file it replaced the truncated one with; the corrector then installs it.
    data, _ = simulate(n_samples=600, rate_hz=100.0, trajectory='smooth',
                       smooth_period_s=6.0, seed=7)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()), temperature=False)
    assert call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60).success
    spin_until(ros_executor, lambda: results, 5.0)
    assert [seq for _, seq in results] == [1]
    assert results[0][0] == path.read_text()
    load_calibration(path)
    spin_until(ros_executor, lambda: corrector.calibration is not None, 5.0)


# -- history and rollback --------------------------------------------------------------------

def magcal(*args):
    return subprocess.run([sys.executable, '-m', 'magcal_ros.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=60, env=subprocess_env())


def test_node_history_is_bounded_and_magcal_rollback_walks_back(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    data, _ = simulate(n_samples=600, rate_hz=100.0, trajectory='smooth',
                       smooth_period_s=6.0, seed=7)
    path = tmp_path / 'cal' / 'calibration.yaml'
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)), Parameter('min_samples', value=300),
        Parameter('history', value=3), Parameter('report_dir', value=str(tmp_path / 'r'))])
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()), temperature=False)
    # five calibrations told apart by the reference magnitude they assume
    fields = [50000.0, 50010.0, 50020.0, 50030.0, 50040.0]
    for f in fields:
        assert node.set_parameters([Parameter('field_nt', value=f)])[0].successful
        resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60)
        assert resp.success, resp.message

    def field_of(p):
        return load_calibration(p)[1]['field_reference']['magnitude_nt']

    hist = list_history(path)
    assert [field_of(h) for h in hist] == fields[-3:]          # bounded by `history`
    assert field_of(path) == fields[-1]

    res = magcal('rollback', path, '--list', '--json')
    assert res.returncode == 0, res.stderr
    listing = json.loads(res.stdout)['history']
    assert [row['active'] for row in listing] == [False, False, True]

    res = magcal('rollback', path)
    assert res.returncode == 0, res.stderr
    assert field_of(path) == fields[-2]
    assert 'is now the calibration created' in res.stdout
    res = magcal('rollback', path, '--json')                  # again: one further back
    assert res.returncode == 0 and field_of(path) == fields[-3]
    assert json.loads(res.stdout)['restored'] == hist[0]
    res = magcal('rollback', path)                              # nothing older is kept
    assert res.returncode == 2
    assert 'only 0 calibration(s) older than the active one in the history (3 kept)' in \
        res.stderr
    assert field_of(path) == fields[-3]
    assert magcal('rollback', path, '--steps', '0').returncode == 2

    # with history 0 nothing is kept and a rollback says so (calibration_file is read-only
    # at run time: the same path, its file and history removed first)
    assert node.set_parameters([Parameter('history', value=0)])[0].successful
    shutil.rmtree(str(path) + '.history')
    path.unlink()
    other = path
    assert call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60).success
    assert other.exists() and list_history(other) == []
    res = magcal('rollback', other)
    assert res.returncode == 2 and 'no calibration history' in res.stderr


def test_node_write_failure_keeps_the_previous_calibration(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path):
    data, _ = simulate(n_samples=600, rate_hz=100.0, trajectory='smooth',
                       smooth_period_s=6.0, seed=7)
    target = tmp_path / 'taken'
    target.mkdir()                  # the calibration path is a directory: the write fails
    # (document, publication sequence number of the node's result writer)
    results = []
    ros_node.create_subscription(String, 'calibration/result', lambda msg, info: results.append(
        (msg.data, info['publication_sequence_number'])), RESULT_QOS)
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(target)), Parameter('min_samples', value=300),
        Parameter('report_dir', value=str(tmp_path / 'r'))])
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    feeder.feed(ros_executor, data, taken=lambda: int(node.received.sum()), temperature=False)
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60)
    assert not resp.success
    assert resp.message.startswith(f'calibrated but could not write {target}')
    assert 'previous calibration stays active' in ' '.join(resp.message.splitlines()[:2])
    assert target.is_dir() and not [f for f in os.listdir(tmp_path) if f.endswith('.tmp')]
    # the path writable again (calibration_file is read-only at run time): the same data
    # calibrate
    target.rmdir()
    good = target
    assert call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60).success
    load_calibration(good)
    spin_until(ros_executor, lambda: results, 5.0)
    # no fixed wait for 'nothing published': the good document is the sentinel. It is the
    # result writer's first message (sequence number 1), so the failed calibrate published
    # nothing, and it is the file just written
    assert [seq for _, seq in results] == [1]
    assert results[0][0] == good.read_text()
