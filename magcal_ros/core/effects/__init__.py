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
Physical error terms ("effects") of a vector magnetometer, and the grammar that composes them.

An effect is a *coupling* applied to a *driver* on a *scope* (docs/formulas.md); the names
below are re-exported from the modules of this package.
"""
from magcal_ros.core.effects.base import (  # noqa: F401 - re-exported
    decompose_linear, Effect, first_order_lag, misalignment_angles,
    misalignment_matrix, NONLINEARITY_FULL_SCALE_NT, nonorthogonality_matrix, raw_rate,
    rot_r1, rot_r2, rot_r3, rq_positive, SensorContext, SIGNALS, upper_to_scale_nonorth)
from magcal_ros.core.effects.catalog import (  # noqa: F401 - re-exported
    axis_map_args, AXIS_NAMES, AxisMap, BASE, BUILTIN_EFFECTS, effect_class, load_plugin,
    load_plugins, Misalignment, needs_args, NonOrthogonality, Offset, parse_token,
    register_effect, registered_effects, Scale, SiteGradient, SoftIron, TOKEN_CLASSES,
    TokenEffect, TOKENS, unregister_effect)
from magcal_ros.core.effects.couplings import (  # noqa: F401 - re-exported
    Coupling, register_coupling, unregister_coupling)
from magcal_ros.core.effects.drivers import (  # noqa: F401 - re-exported
    Driver, register_driver, unregister_driver)
from magcal_ros.core.effects.formula import make_effect, parse  # noqa: F401 - re-exported
