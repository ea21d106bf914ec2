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
Today's model tokens as compositions coupling(driver) of the grammar (docs/formulas.md).

Every token accepted before the grammar (``base``, ``temperature@2``, ``step(300)``,
``aux:aux_x``, ...) stays a term of the formula.  It keeps its catalog class
(:mod:`.catalog`), its parameter names and its reference values, so that every calibration
file written before loads and corrects exactly as before; :func:`expansion` gives the
composition it is (test/test_grammar.py checks that the class and the composition give the
same change of the reading).  Differences a user may notice: the catalog's drift is
referred to the first sample (the composition ``offset(t)`` to the mean), ``aux_poly`` and
``drift2`` are unscaled powers (``poly`` scales by the half range), ``nonlinearity`` has the
degrees 2 and 3 only, ``field_rate`` is written with -tau (s).
"""
from magcal_ros.core.effects.registry import parse_token

#: token (or pattern) -> composition; {x}, {d}, {a} are the token's arguments
ALIASES = {
    'base': 'offset + scale + nonorthogonality + misalignment',
    'offset': 'offset(1)',
    'scale': 'the constant scale factors (paper 004 eq. 2, S)',
    'nonorthogonality': 'the constant non-orthogonality angles (paper 004 eq. 2, C_NO)',
    'misalignment': 'the constant orientation relative to sensor 1 (paper 004 eq. 3)',
    'soft_iron': 'the constant full linear map (paper 002, K = I + D)',
    'site_gradient': 'the constant gradient of the site, world frame (paper 004 eq. 1)',
    'temperature': 'offset(temperature) + scale(temperature)',
    'drift': 'offset(t)',
    'drift2': 'offset(poly(t, 2))',
    'aux': 'offset({x})',
    'aux_poly': 'offset(poly({x}, {d}))',
    'step': 'offset(step({a}))',
    'periodic': 'offset(sin({a}))',
    'lag': 'offset(lag({x}))',
    'field_rate': 'offset(rate)   (dB = -tau rate, tau in s)',
    'nonlinearity': 'offset(poly(lin, 3)) without the linear column (degrees 2 and 3)',
}


def expansion(token):
    """
    Return the composition a legacy token stands for, e.g. 'offset(poly(aux_x, 2))'.

    None for a token that is no alias (a plug-in effect of its own).
    """
    tok = str(token).strip()
    core, _, where = tok.partition('@')
    scope = f'@{where}' if where else ''
    if core.startswith('aux:'):
        return ALIASES['aux'].format(x=core[4:]) + scope
    name, args, _ = parse_token(core)
    pattern = ALIASES.get(name)
    if pattern is None:
        return None
    text = pattern.format(x=args[0] if args else '', d=args[1] if len(args) > 1 else '',
                          a=', '.join(args))
    if scope and '+' in text:
        return ' + '.join(f'{t.strip()}{scope}' for t in text.split('+'))
    return text + (scope if '(' in text else '')
