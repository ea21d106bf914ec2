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

"""Tests of magcal_ros.serial.parse_options (protocol options from configuration text)."""

import math

from magcal_ros.serial import load_yaml, make_parser, parse_options, parse_value
import pytest


def test_yaml_12_floats_are_numbers():
    # PyYAML alone (YAML 1.1) returns the string '1e5' here
    assert parse_options('{scale: 1e5, a: 1.0e5, b: -2E-3, c: 1.0e+5, d: .5}') == \
        {'scale': 1e5, 'a': 1e5, 'b': -2e-3, 'c': 1e5, 'd': 0.5}
    assert math.isinf(load_yaml('.inf'))
    # and the parser built from them works in the unit the option states (nT per gauss)
    p = make_parser('ascii', **parse_options("{scale: 1e5, columns: 'x,y,z'}"))
    assert p.feed(b'0.5,-0.25,0.125\n')[0].field_nt == (50000.0, -25000.0, 12500.0)


def test_strings_stay_strings():
    assert parse_options("{columns: 'x,y,z,temp', start_command: '*99C', h: x}") == \
        {'columns': 'x,y,z,temp', 'start_command': '*99C', 'h': 'x'}
    assert parse_options('{terminator: "\\r\\n"}') == {'terminator': '\r\n'}


def test_empty_and_dict_inputs():
    assert parse_options('') == {} and parse_options(None) == {} and parse_options('  ') == {}
    src = {'scale': 2.0}
    out = parse_options(src)
    assert out == src and out is not src


@pytest.mark.parametrize('text', ['[1, 2]', 'just text', '{a: [1, 2}'])
def test_non_mappings_are_refused(text):
    with pytest.raises(ValueError, match='options must be a YAML mapping'):
        parse_options(text)


def test_parse_value_for_command_lines():
    assert [parse_value(v) for v in ('1e5', '3', 'x,y,z', '[1, 2]', '', 'true')] == \
        [1e5, 3, 'x,y,z', [1, 2], '', True]
    assert parse_value('{a: [1') == '{a: [1'          # not YAML: kept as text
