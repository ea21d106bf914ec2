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
Protocol options from configuration text (ROS parameter strings, command lines, YAML).

PyYAML implements YAML 1.1, where ``1e5`` or ``1.0e5`` (no exponent sign) is a *string*;
users write them as numbers. The loader here also resolves those as floats (YAML 1.2 rule),
so ``"{scale: 1e5}"`` gives ``{'scale': 100000.0}``.
"""
import re

import yaml

_FLOAT_12 = re.compile(r'^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?'
                       r'|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$')


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2 floats such as ``1e5``."""


_Loader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_12,
                              list('-+0123456789.'))


def load_yaml(text):
    """Parse YAML text with YAML 1.2 floats; raise ValueError on a syntax error."""
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ValueError(f'not valid YAML: {exc}') from None


def parse_options(text):
    """
    Return the dict of protocol options given as a YAML mapping string (ValueError if not).

    e.g. ``"{columns: 'x,y,z,temp,time', scale: 1e5}"``; '' or None gives no options; a dict
    is returned as a copy.
    """
    if text is None or isinstance(text, dict):
        return dict(text or {})
    if not str(text).strip():
        return {}
    try:
        value = load_yaml(str(text))
    except ValueError as exc:
        raise ValueError(f'options must be a YAML mapping, e.g. "{{scale: 1.0e5}}": '
                         f'{exc}') from None
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ValueError(f'options must be a YAML mapping, e.g. "{{scale: 1.0e5}}", '
                         f'got {text!r}')
    return value


def parse_value(text):
    """Read one option value from a command line: int, float (also ``1e5``), else YAML."""
    text = str(text)
    if not text.strip():
        return ''
    try:
        return load_yaml(text)
    except ValueError:
        return text
