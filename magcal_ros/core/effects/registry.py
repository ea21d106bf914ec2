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
The registry of named effects (catalog and plug-ins) and the legacy token helpers.

A plug-in module defines :class:`~magcal_ros.core.effects.base.Effect` subclasses and
registers them (:func:`register_effect`, or ``MAGCAL_EFFECTS = [...]``); a plug-in coupling
or driver of the grammar registers with :func:`magcal_ros.core.effects.couplings.
register_coupling` / :func:`magcal_ros.core.effects.drivers.register_driver`
(docs/plugins.md); the three registries are one mechanism, :class:`.names.Registry`.
Plug-ins are imported only at start-up (``magcal --plugin``, the nodes'
``plugins`` parameter), never from a model or a calibration file.
"""
import importlib
import sys

from magcal_ros.core.effects.attitude_ref import AttitudeFull, AttitudeReference
from magcal_ros.core.effects.base import Effect
from magcal_ros.core.effects.catalog import (aux_effect, AxisMap, Misalignment,
                                             NonOrthogonality, Offset, Scale, SiteGradient,
                                             SoftIron, TOKEN_CLASSES)
from magcal_ros.core.effects.names import Registry

# -- registry -------------------------------------------------------------------------------

#: the named effects (catalog and plug-ins)
EFFECTS = Registry(Effect, 'effect', 'magcal_ros.core.effects.Effect')
register_effect = EFFECTS.register
unregister_effect = EFFECTS.unregister
#: the Effect class registered as a name (without arguments), or None
effect_class = EFFECTS.get

for _cls in (AxisMap, Scale, NonOrthogonality, Misalignment, SoftIron, Offset,
             *(TOKEN_CLASSES[n] for n in ('temperature', 'drift', 'drift2', 'nonlinearity',
                                          'field_rate', 'step', 'periodic', 'lag', 'aux_poly')),
             SiteGradient, AttitudeReference, AttitudeFull):
    register_effect(_cls)

#: names of the effects that ship with the library
BUILTIN_EFFECTS = EFFECTS.seal_builtin()

#: the model of paper 004 (offset, scale, nonorthogonality, misalignment)
BASE = ('offset', 'scale', 'nonorthogonality', 'misalignment')


def registered_effects():
    """Names of all registered effects (plus 'aux:<column>')."""
    return EFFECTS.names() + ['aux:<column>']


def needs_args(name):
    """Tell whether the registered effect ``name`` is only written with arguments."""
    cls = EFFECTS.get(name)
    return cls is not None and cls.usage is not None


def load_plugin(ref):
    """
    Import ``module`` or ``module:Class`` and register the classes it names.

    A module may define ``MAGCAL_EFFECTS = [Cls, ...]`` (named effects),
    ``MAGCAL_COUPLINGS`` and ``MAGCAL_DRIVERS`` (the grammar's couplings and driver factors,
    :mod:`.couplings`, :mod:`.drivers`), or call the ``register_*`` functions itself;
    ``module:Class`` registers that one class, whichever of the three it is.  Returns the
    list of registered names.

    Each effect class is evaluated once on a context holding only the signals it declares
    (:func:`magcal_ros.core.effects.safety.probe_effect`) before it is registered: one that
    reads an undeclared signal, or fails, is refused (ValueError, one line naming the effect
    and the signal).  Couplings and drivers are not probed on their own.
    """
    from magcal_ros.core.effects import couplings, drivers
    from magcal_ros.core.effects.safety import probe_effect   # here: it imports the package
    mod_name, _, attr = ref.partition(':')
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ValueError(f'cannot import effect plugin {ref!r}: {exc}') from exc
    if attr:
        classes = [getattr(mod, attr)]
    else:
        classes = [c for key in ('MAGCAL_EFFECTS', 'MAGCAL_COUPLINGS', 'MAGCAL_DRIVERS')
                   for c in getattr(mod, key, [])]
    names = []
    for cls in classes:
        registry = next((r for r in (couplings.COUPLINGS, drivers.DRIVERS)
                         if isinstance(cls, type) and issubclass(cls, r.base)), EFFECTS)
        if registry.get(cls.name) is not cls:
            if registry is EFFECTS and isinstance(cls, type) and issubclass(cls, Effect):
                probe_effect(cls, ref)
            registry.register(cls)
        names.append(cls.name)
    return names


def split_spec(spec):
    """
    Tokens of a comma-separated model spec; commas inside ``name(a, b)`` do not split.

    'base,step(120,300)@2, periodic(0.23)' -> ['base', 'step(120,300)@2', 'periodic(0.23)'].
    """
    out, depth, cur = [], 0, []
    for ch in str(spec):
        if ch == '(':
            depth += 1
        elif ch == ')':
            depth -= 1
            if depth < 0:
                raise ValueError(f'unbalanced ")" in model {spec!r}')
        if ch == ',' and depth == 0:
            out.append(''.join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    if depth:
        raise ValueError(f'unbalanced "(" in model {spec!r}')
    out.append(''.join(cur).strip())
    return [t for t in out if t]


def parse_token(token):
    """
    'step(120,300)@2' -> ('step', ('120', '300'), 2); 'drift' -> ('drift', (), None).

    The sensor is None when the token has no ``@j`` (the effect on every sensor).
    """
    tok = token.strip()
    name, at, where = tok.rpartition('@') if tok.rfind('@') > tok.rfind(')') else (tok, '', '')
    sensor = None
    if at:
        try:
            sensor = int(where)
        except ValueError:
            raise ValueError(f'bad sensor in {token!r}: expected name@<sensor number>') from None
    name = name.strip()
    args = ()
    if '(' in name:
        if not name.endswith(')'):
            raise ValueError(f'bad effect {token!r}: expected name(arguments)@sensor')
        name, _, inner = name[:-1].partition('(')
        args = tuple(a.strip() for a in inner.split(','))
        if any(not a for a in args):
            raise ValueError(f'empty argument in {token!r}')
        name = name.strip()
    return name, args, sensor


def load_plugins(refs):
    """
    Load every plug-in of ``refs`` and return the registered names.

    :func:`load_plugin` for each of ``refs`` (``--plugin``, a node's ``plugins``); the
    registered names, in order.
    """
    return [name for ref in refs or () for name in load_plugin(ref)]


def _loaded_effect_name(ref):
    """
    Return the registered name of the effect class ``module:Class`` of a loaded plug-in.

    Never imports: a model token or a calibration document (which may come from a ROS
    parameter write or message) must not run code; plug-ins are loaded beforehand by
    :func:`load_plugin` (``magcal --plugin``, the nodes' start-up parameter ``plugins``).
    """
    mod_name, _, attr = ref.partition(':')
    module = sys.modules.get(mod_name)
    cls = getattr(module, attr, None) if module is not None and attr else None
    name = getattr(cls, 'name', None)
    if name is None or EFFECTS.get(name) is not cls:
        raise ValueError(f'effect {ref!r} is not loaded: plug-in effects are imported only at '
                         'start-up (magcal --plugin MODULE, ROS start-up parameter plugins), '
                         'never from a model or a calibration file')
    return name


def make_catalog_effect(token, sensor):
    """
    Create the catalog effect ``token`` ('offset', 'aux:aux_motor_current', 'step(300)', ...).

    A composed term ``coupling(driver)`` is the grammar's: :func:`.formula.make_effect` builds
    both (this module sits below the grammar and imports none of it).
    """
    if '(' in token:
        name, args, _ = parse_token(token)
        cls = EFFECTS.get(name)
        if cls is None:
            raise ValueError(f'unknown effect {name!r} in {token!r}; known effects: '
                             f'{", ".join(registered_effects())}')
        return cls.from_args(args, sensor)
    if token.startswith('aux:'):
        return aux_effect(token[4:], sensor)
    if EFFECTS.get(token) is None and ':' in token:
        token = _loaded_effect_name(token)
    cls = EFFECTS.get(token)
    if cls is None:
        raise ValueError(f'unknown effect {token!r}; known effects: '
                         f'{", ".join(registered_effects())}')
    if cls.usage is not None:
        raise ValueError(f'effect {token!r} needs arguments: {cls.usage}')
    return cls(sensor=sensor)
