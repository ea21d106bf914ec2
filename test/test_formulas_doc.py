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

"""docs/formulas.md: every example formula parses, fits and round-trips a calibration file."""
import pathlib
import re

import injection as inj
from magcal_ros.core.effects import parse
from magcal_ros.core.model import fit
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, parse_calibration
import numpy as np
import pytest

DOC = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'formulas.md'


def _block(heading, lang):
    text = DOC.read_text()
    sec = text[text.index(heading):]
    return re.search(rf'```{lang}\n(.*?)```', sec, re.S).group(1)


EXAMPLES = [ln.strip() for ln in _block('## Examples', 'text').splitlines() if ln.strip()]


@pytest.fixture(scope='module')
def data():
    d = inj.make(n=1500, seed=4)
    # the channels the examples name (a wrapped wheel angle, a motor current)
    d.aux['aux_wheel_angle'] = np.mod(2 * np.pi * 0.13 * d.t, 2 * np.pi)
    return d


def test_the_doc_has_its_examples():
    assert len(EXAMPLES) == 11 and all(e.startswith('base') for e in EXAMPLES)


@pytest.mark.parametrize('text', EXAMPLES)
def test_example_parses_fits_and_round_trips(text, data):
    f = parse(text)
    assert parse(str(f)) == f
    res = fit(data, text, inj.F_NT, check_identifiability=False, on_degenerate='flag')
    # the data hold none of these effects: the fit stays at the injected 3 nT noise
    assert res.success and np.all(np.abs(res.sigma_nt - inj.SIGMA_NT) < 0.3), res.sigma_nt
    cal, doc = parse_calibration(dump_calibration(calibration_to_doc(res.calibration)), text)
    assert parse(doc['model']) == parse(res.model.spec())
    np.testing.assert_array_equal(cal.params, res.params)


def test_python_snippet_runs_as_shown():
    code = _block('## Writing a term in Python', 'python')
    ns = {}
    exec(code, ns)                     # noqa: S102 - the documentation's own snippet
    f = ns['f']
    assert [t.text for t in f.terms] == ['base', 'offset(s(t, k=6))@2']
    t = f.terms[1]
    assert (t.coupling, t.driver, t.scope) == ('offset', 's(t, k=6)', '2')
    assert ns['Model'].from_spec([t.text], 4).n_params == 18
    assert ns['model'].n_params == 45 + 18
