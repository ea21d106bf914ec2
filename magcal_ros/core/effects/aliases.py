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
``aux:aux_x``, ...) stays a term of the formula.  A driven token is evaluated by its
composition (:data:`.catalog.TOKENS`, the grammar's code) under its own parameter names and
reference values, so that every calibration file written before loads and corrects as
before; :func:`expansion` prints that composition.  Differences a user may notice: the
token's drift is referred to the first sample (the composition ``offset(t)`` to the mean),
``aux_poly`` and ``drift2`` are unscaled powers (``poly`` scales by the half range),
``nonlinearity`` has the degrees 2 and 3 only, ``field_rate`` is written with -tau (s).
The constant linear map and offset are the model's core, not compositions.
"""
from magcal_ros.core.effects.registry import make_catalog_effect

#: the tokens that are not compositions: what each stands for
CONSTANT = {
    'base': 'offset + scale + nonorthogonality + misalignment',
    'offset': 'offset(1)',
    'scale': 'the constant scale factors (paper 004 eq. 2, S)',
    'nonorthogonality': 'the constant non-orthogonality angles (paper 004 eq. 2, C_NO)',
    'misalignment': 'the constant orientation relative to sensor 1 (paper 004 eq. 3)',
    'soft_iron': 'the constant full linear map (paper 002, K = I + D)',
    'site_gradient': 'the constant gradient of the site, world frame (paper 004 eq. 1)',
}


def expansion(token):
    """
    Return the composition a legacy token stands for, e.g. 'offset(poly(aux_x, 2))@2'.

    None for a token that is no alias (a plug-in effect of its own).
    """
    core, _, where = str(token).strip().partition('@')
    scope = f'@{where}' if where else ''
    if core in CONSTANT:
        return CONSTANT[core] + (scope if core == 'offset' else '')
    eff = make_catalog_effect(core, 1)
    if not hasattr(eff, 'parts'):
        return None
    return ' + '.join(p.text + scope for p in eff.parts) + eff.comp.note
