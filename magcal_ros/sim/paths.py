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
Where the simulated devices of a namespace live (the driver's default ports read this).

No heavy imports here: the driver imports this module at start-up.

:mod:`magcal_ros.sim.devices` creates the links; the driver's default ports point here, so a
simulator and a driver started in the same namespace meet without arguments.
"""

import os
import tempfile

#: ``/tmp/magcal_sim`` unless TMPDIR names another temporary directory
DEFAULT_DIR = os.path.join(tempfile.gettempdir(), 'magcal_sim')
#: namespace of every node started without a ``__ns`` remap (docs/design.md §3); the ROS
#: nodes take it from here (magcal_ros.ros.run), so the simulator and the driver agree
DEFAULT_NAMESPACE = '/magcal'


def device_dir(namespace=DEFAULT_NAMESPACE):
    """
    Folder of the simulated devices of a namespace: one array per namespace.

    ``/magcal`` (the default) -> :data:`DEFAULT_DIR`; ``/array2`` ->
    ``<DEFAULT_DIR>_array2``, so a simulator and a driver started in the same namespace meet
    on the same devices and two arrays never share them.
    """
    ns = '/' + namespace.strip('/') if namespace.strip('/') else '/'
    if ns == DEFAULT_NAMESPACE:
        return DEFAULT_DIR
    return DEFAULT_DIR + '_' + (ns.strip('/').replace('/', '_') or 'root')


#: link name prefix: sensor j is <dir>/<prefix>j
DEFAULT_PREFIX = 'fluxgate'
