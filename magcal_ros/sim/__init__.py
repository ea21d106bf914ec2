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
Simulated serial fluxgates on pseudo-terminals, without ROS (:mod:`magcal_ros.sim.devices`).

The ROS node ``fluxgate_sim`` (:mod:`magcal_ros.ros.sim_node`) serves these devices; scripts
and tests may use :class:`FluxgateSim` directly, or run ``python -m magcal_ros.sim``.
"""

import importlib

from magcal_ros.sim.paths import DEFAULT_DIR, DEFAULT_NAMESPACE, DEFAULT_PREFIX, device_dir

#: names served by :mod:`magcal_ros.sim.devices`, imported on first use (it loads the
#: simulator, numpy and scipy; the driver only needs :func:`device_dir`)
_FROM_DEVICES = ('DEFAULTS', 'FluxgateSim', 'load_config', 'parse_gradient', 'parse_option',
                 'parse_unplug', 'resolve_settings', 'Unplug')

__all__ = ['DEFAULT_DIR', 'DEFAULT_NAMESPACE', 'DEFAULT_PREFIX', 'device_dir', *_FROM_DEVICES]


def __getattr__(name):
    """Return a name of :mod:`magcal_ros.sim.devices`, importing it on first use (PEP 562)."""
    if name in _FROM_DEVICES:
        return getattr(importlib.import_module('magcal_ros.sim.devices'), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
