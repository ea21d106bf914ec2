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
The registry of named effects (catalog and plug-ins) and the token helpers.

Effects, couplings and drivers each have a :class:`.base.Registry` (docs/plugins.md).
Plug-ins are imported only at start-up (``magcal --plugin``, the nodes' ``plugins``
parameter), never from a model or a calibration file.
"""
import importlib
import sys

from magcal_ros.core.effects.attitude_ref import AttitudeFull, AttitudeReference
from magcal_ros.core.effects.base import Effect, Registry
from magcal_ros.core.effects.catalog import (AxisMap, Misalignment, NonOrthogonality, Offset,
                                             Scale, SiteGradient, SoftIron, TOKEN_CLASSES)

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
    Import ``module`` or ``module:Class`` and register the classes it names; return the names.

    A module may list ``MAGCAL_EFFECTS``, ``MAGCAL_COUPLINGS`` and ``MAGCAL_DRIVERS``, or
    call the ``register_*`` functions itself; ``module:Class`` registers that one class.
    Each effect class is first probed on its declared signals
    (:func:`magcal_ros.core.effects.safety.probe_effect`): one that reads an undeclared
    signal, or fails, is refused (ValueError naming the effect and the signal).
    """
    from magcal_ros.core.effects import couplings, drivers
    from magcal_ros.core.effects.safety import probe_effect   # here: it imports the package
    mod_name, _, attr = ref.partition(':')
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as exc:
        raise ValueError(f'cannot import effect plugin {ref!r}: {exc}') from exc
    classes = [getattr(mod, attr)] if attr else [
        c for key in ('MAGCAL_EFFECTS', 'MAGCAL_COUPLINGS', 'MAGCAL_DRIVERS')
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


def parse_token(token):
    """'step(120,300)@2' -> ('step', ('120', '300'), 2); 'drift' -> ('drift', (), None)."""
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
    """Return the names :func:`load_plugin` registers for each of ``refs``, in order."""
    return [name for ref in refs or () for name in load_plugin(ref)]


def _loaded_effect_name(ref):
    """
    Return the registered name of the effect class ``module:Class`` of a loaded plug-in.

    Never imports: a model token or a calibration document (which may come from a ROS
    parameter write or message) must not run code.
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
    """Create the catalog effect ``token`` ('offset', 'aux:aux_motor_current', 'step(300)')."""
    if '(' in token:
        name, args, _ = parse_token(token)
        cls = EFFECTS.get(name)
        if cls is None:
            raise ValueError(f'unknown effect {name!r} in {token!r}; known effects: '
                             f'{", ".join(registered_effects())}')
        return cls.from_args(args, sensor)
    if token.startswith('aux:'):
        return TOKEN_CLASSES['aux'](sensor=sensor, args=(token[4:],))
    if EFFECTS.get(token) is None and ':' in token:
        token = _loaded_effect_name(token)
    cls = EFFECTS.get(token)
    if cls is None:
        raise ValueError(f'unknown effect {token!r}; known effects: '
                         f'{", ".join(registered_effects())}')
    if cls.usage is not None:
        raise ValueError(f'effect {token!r} needs arguments: {cls.usage}')
    return cls(sensor=sensor)
