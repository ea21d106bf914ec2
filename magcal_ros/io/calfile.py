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
The calibration file (docs/design.md §4, which shows its layout): YAML, schema_version 1.

Written atomically, with a ``.bak`` and a bounded history (:func:`rollback`).  The effects'
parameters are the truth; the derived matrices and offset are checked on load, and the
checksum (:func:`content_checksum`) catches a changed digit.  A file without one still loads.
"""
import datetime
import functools
import glob
import hashlib
import json
import os

from magcal_ros.core import effects as fx
from magcal_ros.core.model import Calibration, Model
from magcal_ros.io.atomic import atomic_write_text
from magcal_ros.units import coupling_unit
import numpy as np
import yaml

SCHEMA_VERSION = 1
KIND = 'magcal_ros/calibration'
_SAFE_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
_SAFE_DUMPER = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used; the message names the problem."""


_NUMBER = {'type': 'number'}
_VEC3 = {'type': 'array', 'items': _NUMBER, 'minItems': 3, 'maxItems': 3}
_MAT3 = {'type': 'array', 'items': _VEC3, 'minItems': 3, 'maxItems': 3}
_EFFECT = {
    'type': 'object',
    'required': ['name', 'params'],
    'properties': {
        'name': {'type': 'string'},
        'label': {'type': 'string'},
        'refs': {'type': ['object', 'null'], 'additionalProperties': _NUMBER},
        'params': {'type': 'object', 'additionalProperties': {
            'type': 'object',
            'required': ['value'],
            'properties': {'value': _NUMBER, 'unit': {'type': 'string'},
                           'stderr': _NUMBER}}},
    },
}

#: The document's structure (schema_version 1), a JSON Schema (draft 2020-12); what it
#: cannot say (effects and their parameters, ids, shapes, derived values) is checked by
#: :func:`calibration_from_doc`.
SCHEMA = {
    '$schema': 'https://json-schema.org/draft/2020-12/schema',
    'title': 'magcal_ros calibration file, schema_version 1 (docs/design.md section 4)',
    'type': 'object',
    'required': ['schema_version', 'sensors', 'provenance'],
    'properties': {
        'schema_version': {'type': 'integer'},
        'kind': {'const': 'magcal_ros/calibration'},
        'checksum': {'type': 'string'},
        'model': {'type': 'array', 'items': {'type': 'string'}},
        # positions_m: one row of 3 numbers (m) per sensor, checked against the sensors
        'geometry': {'type': ['object', 'null']},
        'field_reference': {'type': ['object', 'null']},
        'sensors': {'type': 'array', 'minItems': 1, 'items': {
            'type': 'object',
            'required': ['id', 'effects'],
            'properties': {
                'id': {'type': 'integer'},
                'sigma_nt': _NUMBER,
                'effects': {'type': 'array', 'items': _EFFECT},
                'correction_matrix': _MAT3,
                'intrinsic_correction': _MAT3,
                'offset_nt': _VEC3,
                'rotation_to_sensor1': _MAT3,
                'axis_map': _MAT3,
            }}},
        'array_effects': {'type': ['array', 'null'], 'items': _EFFECT},
        'site_gradient_nt_per_m': {'type': 'object', 'properties': {
            'frame': {'type': 'string'},
            'value': _MAT3, 'stderr': _MAT3,
            'covariance_5': {'type': 'array', 'items': {'type': 'array', 'items': _NUMBER}}}},
        'provenance': {'type': 'object'},
    },
}

_TYPE_WORDS = {'object': 'a mapping', 'array': 'a list', 'number': 'a number',
               'integer': 'an integer', 'string': 'a string', 'null': 'empty'}


def _where(path):
    """'sensors[2].effects[0].params.kx' from a jsonschema error path."""
    return ''.join(f'[{p}]' if isinstance(p, int) else f'.{p}' for p in path).removeprefix('.')


def _schema_error(err, source):
    """One CalibrationFileError naming where in the document and what is wrong."""
    where = _where(err.absolute_path)
    at = f'{source}: {where}' if where else source
    if err.validator == 'required':
        missing = next(k for k in err.validator_value if k not in err.instance)
        if missing == 'provenance' and not where:
            return CalibrationFileError(f"{source}: missing key 'provenance' (the file ends "
                                        'early: truncated write?)')
        return CalibrationFileError(f'{at}: missing key {missing!r}; write the calibration '
                                    'again with magcal fit or roll back (magcal rollback)')
    key = where.rsplit('.', 1)[-1] if where else 'the document'
    if err.validator == 'type':
        want = err.validator_value if isinstance(err.validator_value, list) \
            else [err.validator_value]
        what = ' or '.join(_TYPE_WORDS.get(w, w) for w in want)
        problem = f'{key} is not {what} ({err.instance!r:.40})'
    elif err.validator in ('minItems', 'maxItems'):
        problem = (f'{key} must have {"at least" if err.validator == "minItems" else "at most"}'
                   f' {err.validator_value} entries, has {len(err.instance)}')
    else:
        problem = err.message[:120]
    return CalibrationFileError(
        f'{source}: malformed calibration document: {where or "top level"}: {problem}; write '
        'it again with magcal fit or roll back (magcal rollback)')


@functools.cache
def _validator():
    import jsonschema                        # here: not every user of calfile needs it
    return jsonschema.Draft202012Validator(SCHEMA)


def validate_document(doc, source='calibration'):
    """
    Check ``doc`` against :data:`SCHEMA`; raise CalibrationFileError on the first problem.

    jsonschema's ``best_match``, but a missing ``provenance`` (written last: a cut file) only
    when nothing else is wrong, so that a cut inside the sensors names the sensor.
    """
    from jsonschema.exceptions import best_match
    errors = list(_validator().iter_errors(doc))
    if not errors:
        return
    truncated = [e for e in errors if e.validator == 'required' and not e.absolute_path
                 and 'provenance' not in e.instance]
    rest = [e for e in errors if e not in truncated]
    raise _schema_error(best_match(rest) if rest else truncated[0], source)


def _mat(a):
    return [[float(x) for x in row] for row in np.asarray(a)]


def calibration_to_doc(cal, geometry=None, field_reference=None, provenance=None):
    """Build the YAML document (a dict) of a :class:`Calibration`."""
    def effect_doc(eff, sl):
        return {'name': eff.name, 'label': eff.label,
                'refs': {k: float(v) for k, v in eff.refs.items()},
                'params': {n: {'value': float(v), 'unit': coupling_unit(u, eff.label),
                               'stderr': float(s)}
                           for n, u, v, s in zip(eff.param_names, eff.units,
                                                 cal.params[sl], cal.stderr[sl])}}

    sensors = []
    for j in range(1, cal.n_sensors + 1):
        effs = [effect_doc(eff, sl)
                for eff, sl in zip(cal.model.effects[j - 1], cal.model.slices[j - 1])]
        c_inv, rot = cal.intrinsic_and_rotation(j)
        sdoc = {
            'id': j,
            'sigma_nt': float(cal.sigma_nt[j - 1]),
            'effects': effs,
            'correction_matrix': _mat(cal.correction_matrix(j)),
            'intrinsic_correction': _mat(c_inv),
            'offset_nt': [float(x) for x in cal.offset(j)],
            'rotation_to_sensor1': _mat(rot),
        }
        if _has_axis_map(cal.model, j):
            # intrinsic_correction and rotation_to_sensor1 decompose the map without it
            sdoc['axis_map'] = _mat(cal.model.axis_map(j))
        sensors.append(sdoc)
    prov = {'created': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
            'software': 'magcal_ros', **(provenance or {})}
    doc = {'schema_version': SCHEMA_VERSION, 'kind': KIND, 'model': cal.model.spec(),
           'geometry': geometry or {}, 'field_reference': field_reference or {},
           'sensors': sensors}
    if cal.model.array_effects:
        # effects of the whole array (site gradient: world frame of the attitude, nT/m)
        doc['array_effects'] = [effect_doc(eff, sl) for eff, sl in
                                zip(cal.model.array_effects, cal.model.array_slices)]
        g = cal.site_gradient()
        if g is not None:
            doc['site_gradient_nt_per_m'] = {'frame': cal.site_frame, 'value': _mat(g[0]),
                                             'stderr': _mat(g[1])}
            if cal.array_covariance is not None:
                doc['site_gradient_nt_per_m']['covariance_5'] = _mat(cal.array_covariance)
    doc['provenance'] = prov             # last: its absence reveals a truncated file
    return doc


def _has_axis_map(model, j):
    return any(isinstance(e, fx.AxisMap) for e in model.effects[j - 1])


def _yaml(doc):
    # libyaml's emitter where PyYAML has it: the same text, faster (BENCHMARKS.md)
    return yaml.dump(doc, Dumper=_SAFE_DUMPER, sort_keys=False, default_flow_style=None,
                     width=100)


def content_checksum(doc):
    """
    Return ``'sha256:<hex>'`` of a document's content, its ``checksum`` entry left out.

    Serialised as compact JSON in the document's key order, floats as Python's shortest
    repr: comments, layout and quoting do not count, every key and value does.
    """
    body = {k: v for k, v in doc.items() if k != 'checksum'}
    text = json.dumps(body, separators=(',', ':'), ensure_ascii=True, allow_nan=True,
                      default=repr)
    return 'sha256:' + hashlib.sha256(text.encode('ascii')).hexdigest()


def stamp_checksum(doc):
    """
    Return a copy of a document with a new ``checksum`` (after ``kind``).

    Of the document as its YAML reads back (a tuple becomes a list); ``fit --json`` prints it.
    """
    body = {k: v for k, v in doc.items() if k != 'checksum'}
    stamp = content_checksum(yaml.load(_yaml(body), Loader=_SAFE_LOADER))  # noqa: S506
    items = list(body.items())
    at = next((i + 1 for i, (k, _) in enumerate(items) if k == 'kind'), 0)
    return dict(items[:at] + [('checksum', stamp)] + items[at:])


def dump_calibration(doc):
    """YAML text of a calibration document, with its checksum (:func:`stamp_checksum`)."""
    return _yaml(stamp_checksum(doc))


def calibration_from_doc(doc, source='calibration'):
    """
    Rebuild a :class:`Calibration` from a document.

    Every defect raises :class:`CalibrationFileError` naming it, never another exception.
    """
    try:
        return _calibration_from_doc(doc, source)
    except CalibrationFileError:
        raise
    except (TypeError, AttributeError, KeyError, IndexError, ValueError) as exc:
        raise CalibrationFileError(
            f'{source}: malformed calibration document ({type(exc).__name__}: {exc}); '
            'write it again with magcal fit or roll back (magcal rollback)') from None


def _check_complete(doc, model, source):
    """Refuse a document whose parts disagree (a missing provenance, the schema refuses)."""
    spec = doc.get('model')
    if spec is not None:
        if not isinstance(spec, list) or sorted(map(str, spec)) != sorted(model.spec()):
            raise CalibrationFileError(
                f'{source}: model {spec!r} does not match the effects of the sensors '
                f'{model.spec()!r} (truncated or hand-edited?)')
    geometry = doc.get('geometry') or {}
    if 'positions_m' in geometry:
        try:
            pos = np.asarray(geometry['positions_m'], float)
        except (TypeError, ValueError):
            pos = np.zeros(0)
        if pos.shape != (model.n_sensors, 3) or not np.all(np.isfinite(pos)):
            raise CalibrationFileError(
                f'{source}: geometry.positions_m must be {model.n_sensors} rows of 3 finite '
                'numbers (m), one per sensor')


def _calibration_from_doc(doc, source):
    if not isinstance(doc, dict):
        raise CalibrationFileError(f'{source}: not a calibration document (top level is '
                                   f'{type(doc).__name__}, expected a mapping)')
    if 'schema_version' not in doc:
        raise CalibrationFileError(f"{source}: missing key 'schema_version'")
    version = doc['schema_version']
    if not isinstance(version, int):
        raise CalibrationFileError(f'{source}: schema_version must be an integer, got {version!r}')
    if version > SCHEMA_VERSION:
        raise CalibrationFileError(
            f'{source}: schema_version {version} is newer than this magcal_ros understands '
            f'({SCHEMA_VERSION}); upgrade magcal_ros or recalibrate')
    if version < 1:
        raise CalibrationFileError(f'{source}: unknown schema_version {version}')
    if doc.get('kind', KIND) != KIND:
        raise CalibrationFileError(f'{source}: kind is {doc.get("kind")!r}, expected {KIND!r}')
    validate_document(doc, source)
    sensors = doc['sensors']
    effects, sigma = [], []
    values = {}                  # id(effect) -> ((n,) values, (n,) stderr) from the file

    def read_effects(edocs, k, where):
        row = []
        for e in edocs:
            name = e['name']
            label = e.get('label', name)
            try:
                eff = fx.make_effect(label if label.startswith('aux:') or '(' in label
                                     else name, k)
            except ValueError as exc:
                raise CalibrationFileError(f'{where}: {exc}') from None
            eff.refs = {str(a): float(b) for a, b in (e.get('refs') or {}).items()}
            pdoc = e['params']
            if list(pdoc) != list(eff.param_names):
                raise CalibrationFileError(
                    f'{where} effect {label}: parameters {list(pdoc)} but expected '
                    f'{list(eff.param_names)}')
            v = [float(pdoc[pn]['value']) for pn in eff.param_names]     # numbers: the schema
            bad = [pn for pn, x in zip(eff.param_names, v) if not np.isfinite(x)]
            if bad:
                raise CalibrationFileError(f'{where} {label}.{bad[0]}: value is not finite')
            values[id(eff)] = (v, [float(pdoc[pn].get('stderr', 0.0)) for pn in eff.param_names])
            row.append(eff)
        return row

    for k, sdoc in enumerate(sensors, start=1):
        where = f'{source}: sensors[{k - 1}]'
        if sdoc['id'] != k:
            raise CalibrationFileError(f'{where}: id must be {k} (sensors in order 1..S)')
        effects.append(read_effects(sdoc['effects'], k, where))
        sigma.append(float(sdoc.get('sigma_nt', np.nan)))
    array_effects = read_effects(doc.get('array_effects') or [], 0, f'{source}: array_effects')
    drops = []
    for term in doc.get('model') or []:
        if isinstance(term, str) and term.replace(' ', '').startswith('drop('):
            try:
                drops.extend(fx.formula.parse(term).drops)
            except ValueError as exc:
                raise CalibrationFileError(f'{source}: model term {term!r}: {exc}') from None
    model = Model(effects, array_effects, drops)
    # every effect's values into its place of the parameter vector; an @alike term's one set
    # (written under every sensor) into its shared slice, the same on every sensor
    params, stderr = np.full(model.n_params, np.nan), np.zeros(model.n_params)
    placed = [(e, sl) for row, sls in zip(model.effects, model.slices) for e, sl in zip(row, sls)]
    for eff, sl in placed + list(zip(model.array_effects, model.array_slices)):
        v, s = values[id(eff)]
        if not np.isnan(params[sl]).all() and not np.allclose(params[sl], v, rtol=0, atol=0):
            raise CalibrationFileError(f'{source}: {eff.label}: the sensors disagree on the '
                                       'values of a parameter set they share (hand-edited?)')
        params[sl], stderr[sl] = v, s
    cal = Calibration(model, params, stderr, np.array(sigma))
    site = doc.get('site_gradient_nt_per_m')
    if array_effects and isinstance(site, dict) and 'covariance_5' in site:
        cov = np.asarray(site['covariance_5'], float)
        if cov.shape != (len(model.array_cols),) * 2 or not np.all(np.isfinite(cov)):
            raise CalibrationFileError(f'{source}: site_gradient_nt_per_m.covariance_5 must be '
                                       f'{len(model.array_cols)}x{len(model.array_cols)} finite '
                                       'numbers')
        cal.array_covariance = cov
    if array_effects and isinstance(site, dict):
        cal.site_frame = str(site.get('frame', 'world'))
    for k, sdoc in enumerate(sensors, start=1):
        a = cal.matrix(k)
        if not np.all(np.isfinite(a)) or abs(np.linalg.det(a)) < 1e-6:
            raise CalibrationFileError(f'{source}: sensor {k}: the linear map is singular')
        stored = sdoc.get('correction_matrix')
        if stored is not None:
            stored = np.asarray(stored, float)                  # 3 x 3 numbers: the schema
            if not np.allclose(stored, np.linalg.inv(a), atol=1e-6):
                raise CalibrationFileError(
                    f'{source}: sensor {k}: correction_matrix does not match the parameters '
                    '(hand-edited?); edit the parameters, not the derived matrices')
        _check_derived(cal, k, sdoc, source)
    _check_complete(doc, model, source)
    _check_checksum(doc, source)
    return cal


def _check_derived(cal, k, sdoc, source):
    """Refuse offset_nt, axis_map, intrinsic_correction, rotation_to_sensor1 not derived."""
    def refuse(key):
        raise CalibrationFileError(
            f'{source}: sensor {k}: {key} does not match the parameters (hand-edited?); edit '
            'the parameters, not the derived values')

    stored = sdoc.get('offset_nt')
    # written from the same parameters by the same sum: equal to rounding (1e-9 nT)
    if stored is not None and not np.allclose(np.asarray(stored, float), cal.offset(k),
                                              rtol=1e-9, atol=1e-9):
        refuse('offset_nt')
    has_map = _has_axis_map(cal.model, k)
    stored = sdoc.get('axis_map')
    if stored is not None and not np.array_equal(np.asarray(stored, float),
                                                 cal.model.axis_map(k)):
        refuse('axis_map')
    if has_map and stored is None:
        return          # written before axis_map was: decomposed from the whole map
    c_inv, rot = cal.intrinsic_and_rotation(k)
    for key, value in (('intrinsic_correction', c_inv), ('rotation_to_sensor1', rot)):
        stored = sdoc.get(key)
        if stored is not None and not np.allclose(np.asarray(stored, float), value,
                                                  atol=1e-6):
            refuse(key)


def _check_checksum(doc, source):
    """Refuse a document whose content is not what its writer's checksum says."""
    stated = doc.get('checksum')
    if stated is None:
        return                  # written before the checksum existed
    if stated != content_checksum(doc):
        raise CalibrationFileError(
            f'{source}: checksum does not match the content: the file changed after it was '
            'written (corrupt, or hand-edited); roll back to the previous calibration (magcal '
            'rollback) or recalibrate (magcal fit); to keep a deliberate hand edit, delete '
            'the checksum line')


def parse_calibration(text, source='calibration'):
    """Parse YAML text; returns (Calibration, doc)."""
    try:
        # libyaml's safe loader when PyYAML has it (the same documents, faster)
        doc = yaml.load(text, Loader=_SAFE_LOADER)  # noqa: S506 - a safe loader
    except yaml.YAMLError as exc:
        raise CalibrationFileError(f'{source}: not valid YAML (truncated or corrupt?): '
                                   f'{str(exc).splitlines()[0]}') from None
    return calibration_from_doc(doc, source), doc


def load_calibration(path):
    """Read and validate a calibration file; returns (Calibration, doc)."""
    path = os.fspath(path)
    try:
        with open(path, encoding='utf-8') as fh:
            text = fh.read()
    except OSError as exc:
        raise CalibrationFileError(
            f'cannot read calibration file {path}: {exc.strerror}') from None
    except UnicodeDecodeError:
        raise CalibrationFileError(f'{path}: not a text file (corrupt?)') from None
    if not text.strip():
        raise CalibrationFileError(f'{path}: file is empty (truncated write?)')
    return parse_calibration(text, path)


def save_calibration(path, doc, history=20, fsync=os.fsync):
    """
    Write a calibration document atomically, keep ``<path>.bak`` and a bounded history.

    ``<path>.history/`` keeps the last ``history`` calibrations (0: none) for :func:`rollback`.
    """
    text = dump_calibration(doc)
    parse_calibration(text, 'calibration to be written')          # never write a bad file
    atomic_write_text(path, text, backup=True, fsync=fsync)
    if history:
        hdir = os.fspath(path) + '.history'
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%dT%H%M%S.%fZ')
        atomic_write_text(os.path.join(hdir, f'calibration-{stamp}.yaml'), text, backup=False,
                          fsync=fsync)
        for old in list_history(path)[:-history]:
            os.unlink(old)
    return path


def list_history(path):
    """Calibration files in the history of ``path``, oldest first."""
    return sorted(glob.glob(os.path.join(os.fspath(path) + '.history', 'calibration-*.yaml')))


def active_history_index(path):
    """Index in :func:`list_history` of the newest entry the active file copies, or None."""
    def text(name):
        try:
            with open(name, encoding='utf-8') as fh:
                return fh.read()
        except (OSError, UnicodeDecodeError):
            return None
    active = text(path)
    hist = list_history(path)
    return None if active is None else next(
        (k for k in range(len(hist) - 1, -1, -1) if text(hist[k]) == active), None)


def rollback(path, steps=1):
    """
    Make the calibration ``steps`` back in the history the active one; returns its path.

    Steps count from the entry the active file copies (repeated rollbacks walk back); an
    active file in no entry counts as newer than every entry.
    """
    if int(steps) != steps or steps < 1:
        raise CalibrationFileError(f'steps must be an integer >= 1, got {steps!r}')
    hist = list_history(path)
    base = active_history_index(path)
    if base is None:
        base = len(hist)
    if base - steps < 0:
        raise CalibrationFileError(
            f'{path}: only {max(base, 0)} calibration(s) older than the active one in the '
            f'history ({len(hist)} kept), cannot go back {steps}')
    chosen = hist[base - steps]
    with open(chosen, encoding='utf-8') as fh:
        text = fh.read()
    parse_calibration(text, chosen)
    atomic_write_text(path, text, backup=True)
    return chosen
