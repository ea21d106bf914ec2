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
The one parser of model formulas: :func:`parse` (docs/formulas.md).

::

    model    := term (('+' | ',') term)*
    term     := alias-token ['@' scope]                 base, temperature@2, step(300), ...
              | coupling '(' driver ')' ['@' scope]     offset(s(t, k=6))@2
              | 'drop(' t0 ',' t1 ')' ['@' J | '{' J (',' J)* '}']
                                                        leave [t0, t1] s out of the fit:
                                                        every sensor, or those of the scope
    driver   := factor ('*' factor)*
    factor   := name '(' arg (',' arg)* ')' | variable | '1'      arg := value | key '=' value
    scope    := J | each | alike | '{' J (',' J)* '}' | array

The command line (``--model``), the calibration node's ``model`` parameter, the
calibration file and ``magcal simulate --truth`` all read models through :func:`parse`.
:class:`Formula` prints canonical text (``str``): ``parse(str(f)) == f``.
"""
from dataclasses import dataclass
import re

from magcal_ros.core.effects import couplings as cp
from magcal_ros.core.effects import drivers as dv
from magcal_ros.core.effects.base import format_arg, parse_number
from magcal_ros.core.effects.catalog import BASE, make_catalog_effect
from magcal_ros.core.effects.couplings import ComposedEffect, FieldEffect
from magcal_ros.core.effects.drivers import FormulaError

_NAME = re.compile(r'^[A-Za-z_][A-Za-z0-9_.:]*$')
_OPEN, _CLOSE = '({', ')}'

__all__ = ['Formula', 'FormulaError', 'parse', 'parse_driver', 'Term']


def split_top(text, seps):
    """Split ``text`` at the characters ``seps`` outside parentheses and braces."""
    out, cur, depth = [], [], 0
    for ch in text:
        if ch in _OPEN:
            depth += 1
        elif ch in _CLOSE:
            depth -= 1
            if depth < 0:
                raise FormulaError(f'unbalanced {ch!r} in {text!r}')
        if ch in seps and depth == 0:
            out.append(''.join(cur))
            cur = []
        else:
            cur.append(ch)
    if depth:
        raise FormulaError(f'unbalanced "(" or "{{" in {text!r}: close every parenthesis')
    out.append(''.join(cur))
    return out


def _call(text):
    """'name(a, b)' -> ('name', 'a, b'); 'name' -> ('name', None)."""
    text = text.strip()
    if '(' not in text:
        return text, None
    name, _, rest = text.partition('(')
    if not rest.endswith(')'):
        raise FormulaError(f'{text!r}: expected name(arguments) with nothing after ")"')
    return name.strip(), rest[:-1]


def _arguments(inner, where):
    """Positional and keyword arguments of a factor, as strings."""
    args, kwargs = [], {}
    for part in split_top(inner, ','):
        part = part.strip()
        if not part:
            raise FormulaError(f'empty argument in {where!r}')
        key, eq, value = part.partition('=')
        if eq:
            kwargs[key.strip()] = value.strip()
        elif kwargs:
            raise FormulaError(f'{where!r}: positional argument {part!r} after a keyword')
        else:
            args.append(part)
    return args, kwargs


def parse_driver(text):
    """Return the :class:`~.drivers.Driver` of ``text`` ('s(t, k=6)', 'temperature * t')."""
    factors = []
    for part in split_top(text, '*'):
        part = part.strip()
        if not part:
            raise FormulaError(f'empty factor in driver {text!r}: write factor * factor')
        name, inner = _call(part)
        if inner is None:
            factors.append(dv.Constant() if name == '1' else dv.Variable(name))
            continue
        cls = dv.driver_class(name)
        if cls is None:
            raise FormulaError(
                f'unknown driver {name!r} in {part!r}: drivers are '
                f'{", ".join(d + "(...)" for d in dv.registered_drivers())}, a variable '
                '(t, temperature, aux_<name>, rate, lin) or 1')
        args, kwargs = _arguments(inner, part)
        factors.append(cls.from_args(args, kwargs))
    return factors[0] if len(factors) == 1 else dv.Product(factors)


@dataclass(frozen=True)
class Term:
    """One term of a formula."""

    #: canonical, pasteable text (``offset(s(t, k=6))@2``)
    text: str
    #: 'composed' (coupling(driver)), 'alias' (a catalog or plug-in token) or 'drop'
    kind: str
    #: ``text`` without the scope
    core: str
    #: coupling name and canonical driver text of a composed term
    coupling: str | None = None
    driver: str | None = None
    #: 'each', 'alike', 'array', 'J' (a sensor number) or '{J,J,...}'
    scope: str = 'each'
    #: channels the term reads (keys of ``base.SIGNALS`` or aux_<name>)
    signals: tuple = ()
    #: the composition a catalog token stands for (``offset(t)@2`` for ``drift@2``)
    expansion: str | None = None
    #: (t0, t1) s of a ``drop`` term, and the 1-based sensors it leaves out (None: every
    #: sensor and the attitude's observation)
    window: tuple | None = None
    dropped: tuple | None = None

    def sensors(self, n_sensors):
        """1-based sensors the term is on (all of them for each, alike, array)."""
        if self.scope in ('each', 'alike', 'array'):
            return list(range(1, n_sensors + 1))
        js = [int(j) for j in self.scope.strip('{}').split(',')]
        for j in js:
            if not 1 <= j <= n_sensors:
                raise FormulaError(f'{self.text!r}: sensor {j} does not exist (the data have '
                                   f'sensors 1..{n_sensors})')
        return js

    def __str__(self):
        return self.text


def _scope(text, where, field):
    s = text.strip().replace(' ', '')
    if field:
        if s not in ('', 'array'):
            raise FormulaError(f'{where!r}: field() is common to every sensor, its scope is '
                               'always the array: drop @' + s)
        return 'array'
    if s in ('', 'each', 'alike'):
        return s or 'each'
    if s.startswith('{') and s.endswith('}'):
        try:
            js = sorted({int(j) for j in s[1:-1].split(',')})
        except ValueError:
            js = []
        if not js:
            raise FormulaError(f'{where!r}: bad sensor set @{text}: write @{{1,3}}')
        return str(js[0]) if len(js) == 1 else '{' + ','.join(map(str, js)) + '}'
    if s.isdigit():
        return str(int(s))
    raise FormulaError(f'{where!r}: unknown scope @{text}: use @J (a sensor number), @each, '
                       '@alike, @{J,J,...} or (field only) @array')


def parse_term(text):
    """Return the :class:`Term` of one term's text."""
    raw = text.strip()
    if not raw:
        raise FormulaError('empty term: two separators in a row, or one at the end')
    parts = split_top(raw, '@')
    if len(parts) > 2:
        raise FormulaError(f'{raw!r}: more than one "@"')
    core_text, scope_text = parts[0].strip(), (parts[1] if len(parts) == 2 else '')
    if len(parts) == 2 and not scope_text.strip():
        raise FormulaError(f'{raw!r}: nothing after "@": give a sensor, each, alike or {{J,J}}')
    name, inner = _call(core_text)
    if not _NAME.match(name or ''):
        raise FormulaError(f'{raw!r}: {name!r} is not a term name: write coupling(driver), '
                           'a catalog token (base, temperature, step(300), ...) or drop(t0, t1)')
    if name == 'drop':
        return _drop_term(raw, inner, scope_text)
    ccls = cp.coupling_class(name)
    if inner is not None and ccls is not None:
        coupling = ccls()
        try:
            driver = parse_driver(inner)
        except FormulaError as exc:
            raise FormulaError(f'{raw!r}: {exc}') from None
        if driver.per_axis and not coupling.per_axis_ok:
            raise FormulaError(f'{raw!r}: {name}() takes a scalar driver; rate and lin are per '
                               'axis (use offset(...) or scale(...))')
        if driver.reads_lin and coupling.scope == 'array':
            raise FormulaError(f"{raw!r}: field() cannot follow lin (the sensor's own reading)")
        scope = _scope(scope_text, raw, coupling.scope == 'array')
        core = f'{name}({driver.text})'
        text_out = core if scope in ('each', 'array') else f'{core}@{scope}'
        return Term(text=text_out, kind='composed', core=core, coupling=name,
                    driver=driver.text, scope=scope, signals=tuple(driver.signals))
    return _alias_term(raw, core_text, scope_text)


def _drop_term(raw, inner, scope_text):
    """Return the term of ``drop(t0, t1)`` (every sensor) or ``drop(t0, t1)@J`` / ``@{J,K}``."""
    args, kw = _arguments(inner or '', raw) if inner is not None else ([], {})
    if inner is None or len(args) != 2 or kw:
        raise FormulaError(f'{raw!r}: drop takes two times in s, e.g. drop(120, 160)')
    t0, t1 = (parse_number(a, 'drop time [s]') for a in args)
    if not t1 > t0:
        raise FormulaError(f'{raw!r}: the end of the dropped window must follow its start')
    core = f'drop({format_arg(t0)}, {format_arg(t1)})'
    if not scope_text:
        return Term(text=core, kind='drop', core=core, scope='array', window=(t0, t1))
    given = scope_text.strip().replace(' ', '')
    if not (given.isdigit() or given.startswith('{')):
        raise FormulaError(f'{raw!r}: drop takes a sensor scope, @J or @{{J,K}} (without one '
                           'it leaves the window out for every sensor)')
    scope = _scope(scope_text, raw, False)
    return Term(text=f'{core}@{scope}', kind='drop', core=core, scope=scope, window=(t0, t1),
                dropped=tuple(int(j) for j in scope.strip('{}').split(',')))


def _alias_term(raw, core_text, scope_text):
    """Return the term of a catalog or plug-in token, validated by building its effect."""
    if core_text == 'base':
        core, eff = 'base', None
    else:
        try:
            eff = make_effect(core_text, 1)
        except ValueError as exc:
            raise FormulaError(
                f'{raw!r}: {exc}; or a composed term coupling(driver) with couplings '
                f'{", ".join(cp.registered_couplings())}') from None
        core = eff.label
    array = eff is not None and getattr(eff, 'scope', 'sensor') == 'array'
    if array and scope_text.strip():
        raise FormulaError(f'{raw!r}: {core} is one effect of the whole array: drop '
                           f'@{scope_text.strip()}')
    scope = 'array' if array else _scope(scope_text, raw, False)
    if scope == 'alike':
        raise FormulaError(f'{raw!r}: @alike shares one parameter set between sensors and is '
                           'for composed terms, e.g. offset(t)@alike')
    at = '' if scope in ('each', 'array') else f'@{scope}'
    expansion = (' + '.join(BASE) if eff is None else
                 eff.expansion(at) if hasattr(eff, 'expansion') else None)
    return Term(text=core + at, kind='alias', core=core, scope=scope,
                signals=tuple(eff.signals) if eff is not None else (), expansion=expansion)


@dataclass(frozen=True)
class Formula:
    """A parsed model: its terms, in order.  ``str(f)`` is canonical; ``parse(str(f)) == f``."""

    terms: tuple

    def __str__(self):
        return ' + '.join(t.text for t in self.terms)

    @property
    def drops(self):
        """Return the windows left out of the fit: (t0 s, t1 s, sensors as Term.dropped)."""
        return [(*t.window, t.dropped) for t in self.terms if t.kind == 'drop']

    def __add__(self, other):
        other = other if isinstance(other, Formula) else parse(other)
        return Formula(self.terms + other.terms)


def parse(text):
    """
    Parse a model formula: ``'base + offset(s(t, k=6))@2'`` -> :class:`Formula`.

    ``text`` may also be a list of terms (the node's ``model`` parameter, the calibration
    file's ``model``) or a Formula.  Raises :class:`FormulaError` (a ValueError) naming the
    bad part and what is allowed.
    """
    if isinstance(text, Formula):
        return text
    if isinstance(text, (list, tuple)):
        text = ' , '.join(str(t) for t in text)
    text = str(text)
    if not text.strip():
        raise FormulaError('empty model: give at least one term, e.g. --model base')
    return Formula(tuple(parse_term(p) for p in split_top(text, '+,')))


def composed_effect(term, sensor):
    """Return the :class:`ComposedEffect` (:class:`FieldEffect`) of a composed ``term``."""
    coupling = cp.coupling_class(term.coupling)()
    driver = parse_driver(term.driver)
    if coupling.scope == 'array':
        return FieldEffect(coupling, driver, sensor=0)
    return ComposedEffect(coupling, driver, sensor=sensor, shared=term.scope == 'alike')


def make_effect(token, sensor):
    """Create the effect of a term's core text on ``sensor``: a catalog token or a composition."""
    head = token.partition('(')[0].strip()
    if '(' in token and cp.coupling_class(head) is not None:
        return composed_effect(parse_term(token), sensor)
    return make_catalog_effect(token, sensor)
