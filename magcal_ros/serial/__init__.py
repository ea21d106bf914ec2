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

r"""
Serial device protocols (pure parsers/encoders) and the pyserial transport (no rclpy).

:data:`PROTOCOLS` maps a name to its parser and encoder classes (more with
:func:`register_protocol`); :func:`make_parser` and :func:`make_encoder` build them from one
options dictionary, each side taking the options it uses; :func:`parse_options` reads that
dictionary from configuration text (ROS parameter strings, command lines, YAML).
"""
from dataclasses import dataclass
import inspect
import re

from magcal_ros.serial.ascii import AsciiEncoder, AsciiParser
from magcal_ros.serial.base import Encoder, Parser, ParserStats, Sample
from magcal_ros.serial.hmr2300 import (Hmr2300AsciiEncoder, Hmr2300AsciiParser,
                                       Hmr2300BinaryEncoder, Hmr2300BinaryParser)
from magcal_ros.serial.lemi025 import Lemi025Encoder, Lemi025Parser
import yaml

__all__ = ['Encoder', 'Parser', 'ParserStats', 'Protocol', 'PROTOCOLS', 'Sample',
           'DEFAULT_PROTOCOL', 'load_yaml', 'make_encoder', 'make_parser', 'parse_options',
           'parse_value', 'parser_options', 'register_protocol']

DEFAULT_PROTOCOL = 'ascii'


@dataclass(frozen=True)
class Protocol:
    """One registry entry: the :class:`Parser` and :class:`Encoder` classes, a line of help."""

    name: str
    parser: type
    encoder: type
    description: str


PROTOCOLS = {}


def register_protocol(name, parser, encoder, description=''):
    """Add (or replace) protocol ``name``: its Parser and Encoder subclasses, a line of help."""
    if not (isinstance(parser, type) and issubclass(parser, Parser)):
        raise ValueError(f'parser for {name!r} must be a Parser subclass, got {parser!r}')
    if not (isinstance(encoder, type) and issubclass(encoder, Encoder)):
        raise ValueError(f'encoder for {name!r} must be an Encoder subclass, got {encoder!r}')
    PROTOCOLS[name] = Protocol(name, parser, encoder, description)


register_protocol('ascii', AsciiParser, AsciiEncoder,
                  'configurable text lines, default "<x_nT>,<y_nT>,<z_nT>,<temp_C>\\r\\n"')
register_protocol('hmr2300_ascii', Hmr2300AsciiParser, Hmr2300AsciiEncoder,
                  'Honeywell HMR2300 ASCII output, 15000 counts/gauss')
register_protocol('hmr2300_binary', Hmr2300BinaryParser, Hmr2300BinaryEncoder,
                  'Honeywell HMR2300 7-byte binary frame (>hhh + CR)')
register_protocol('lemi025', Lemi025Parser, Lemi025Encoder,
                  'LEMI-025 style 32-byte packets with sync tag and CRC-16')


def _accepted(cls):
    """Keyword names accepted by ``cls`` and the ``__init__`` of its bases (via **kwargs)."""
    names = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get('__init__')
        if init is None:
            continue
        params = inspect.signature(init).parameters.values()
        names.update(p.name for p in params
                     if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name != 'self')
        if not any(p.kind == p.VAR_KEYWORD for p in params):
            break
    return names


def _lookup(protocol):
    try:
        return PROTOCOLS[protocol]
    except (KeyError, TypeError):
        raise ValueError(f'unknown serial protocol {protocol!r}; '
                         f'choose one of {sorted(PROTOCOLS)}') from None


def parser_options(protocol):
    """Return the sorted option names understood by ``protocol`` (parser or encoder side)."""
    entry = _lookup(protocol)
    return sorted(_accepted(entry.parser) | _accepted(entry.encoder))


def _build(protocol, side, options):
    known = parser_options(protocol)
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(f'unknown option(s) {unknown} for serial protocol {protocol!r}; '
                         f'known: {known}')
    cls = getattr(_lookup(protocol), side)
    mine = _accepted(cls)
    try:
        return cls(**{k: v for k, v in options.items() if k in mine})
    except TypeError as exc:
        raise ValueError(f'bad options for serial protocol {protocol!r}: {exc}') from None


def make_parser(protocol=DEFAULT_PROTOCOL, **options):
    """Build ``protocol``'s :class:`Parser` (ValueError: an unknown name or option, bad value)."""
    return _build(protocol, 'parser', options)


def make_encoder(protocol=DEFAULT_PROTOCOL, **options):
    """Build the :class:`Encoder` writing what :func:`make_parser` reads (the same rules)."""
    return _build(protocol, 'encoder', options)


_FLOAT_12 = re.compile(r'^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?'
                       r'|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$')


class _Loader(yaml.SafeLoader):
    """
    SafeLoader that also reads YAML 1.2 floats such as ``1e5``.

    PyYAML implements YAML 1.1, where ``1e5`` or ``1.0e5`` (no exponent sign) is a string;
    users write them as numbers: ``"{scale: 1e5}"`` gives ``{'scale': 100000.0}``.
    """


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
