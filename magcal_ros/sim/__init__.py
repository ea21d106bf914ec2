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

Served by the ROS node ``fluxgate_sim`` or ``python -m magcal_ros.sim``.  This module says
where a namespace's devices live, with no heavy import (the driver's default ports).
"""
import os
import tempfile

#: ``/tmp/magcal_sim`` unless TMPDIR names another temporary directory
DEFAULT_DIR = os.path.join(tempfile.gettempdir(), 'magcal_sim')
#: namespace of every node started without a ``__ns`` remap (docs/design.md §3)
DEFAULT_NAMESPACE = '/magcal'
#: link name prefix: sensor j is <dir>/<prefix>j
DEFAULT_PREFIX = 'fluxgate'


def device_dir(namespace=DEFAULT_NAMESPACE):
    """Folder of a namespace's devices: :data:`DEFAULT_DIR`, ``<DEFAULT_DIR>_array2`` ..."""
    name = namespace.strip('/')
    if '/' + name == DEFAULT_NAMESPACE:
        return DEFAULT_DIR
    return DEFAULT_DIR + '_' + (name.replace('/', '_') or 'root')
