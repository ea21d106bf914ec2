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
The message package interfaces/magcal_interfaces builds with colcon as the README says.

A workspace is laid out as a ROS user does it: the repository as ``src/magcal_ros`` and a
link ``src/magcal_interfaces -> magcal_ros/interfaces/magcal_interfaces`` (colcon does not
look for a package inside another package's folder), then ``colcon build --packages-select
magcal_interfaces magcal_ros``.  Here ROS comes from wheels, so the build gets the same
CMake arguments as ``scripts/build_interfaces.sh`` (the wheels' include folder fix); on a
ROS install they are not needed.  The generated Python message is then imported from the
workspace's install folder and filled.
"""
import pathlib
import shutil
import subprocess
import sys
import sysconfig

import numpy
import pytest
from ros_helpers import REPO_ROOT, subprocess_env

_IGNORE = shutil.ignore_patterns('.venv', '.git', 'build', 'install', 'log', '__pycache__',
                                 '*.egg-info', '.pytest_cache', '.hypothesis')
PREFIX = pathlib.Path(sys.prefix)

CHECK = r"""
import sys
from magcal_interfaces.msg import GradientTensorStamped
import magcal_interfaces
m = GradientTensorStamped()
m.header.frame_id = 'magcal_array'
m.tensor = [float(k) for k in range(9)]
m.tensor_covariance = [0.0] * 81
assert len(m.tensor) == 9 and len(m.tensor_covariance) == 81
print(magcal_interfaces.__file__)
print(GradientTensorStamped.get_fields_and_field_types())
"""


@pytest.mark.timeout(600)
def test_colcon_builds_the_linked_interface_package(tmp_path):
    if shutil.which('cmake') is None:
        pytest.fail('cmake is needed to build magcal_interfaces (make setup needs it too)')
    src = tmp_path / 'ws' / 'src'
    shutil.copytree(REPO_ROOT, src / 'magcal_ros', ignore=_IGNORE, symlinks=True)
    (src / 'magcal_interfaces').symlink_to('magcal_ros/interfaces/magcal_interfaces')
    ws = tmp_path / 'ws'
    colcon = PREFIX / 'bin' / 'colcon'
    cmd = [str(colcon)] if colcon.exists() else [sys.executable, '-m', 'colcon']
    cmd += ['--log-base', str(ws / 'log'), 'build', '--base-paths', str(src),
            '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install'),
            '--packages-select', 'magcal_interfaces', 'magcal_ros',
            '--event-handlers', 'console_cohesion+', 'summary-',
            '--cmake-args', '-DBUILD_TESTING=OFF', f'-DPython3_EXECUTABLE={sys.executable}',
            f'-DCMAKE_PROJECT_INCLUDE={REPO_ROOT / "interfaces" / "ros_wheels_fix.cmake"}',
            f'-DMAGCAL_PYTHON_INCLUDE={sysconfig.get_paths()["include"]}',
            f'-DMAGCAL_NUMPY_INCLUDE={numpy.get_include()}']
    env = subprocess_env({'COLCON_HOME': str(ws / 'colcon_home'), 'PYTHONPATH': None,
                          'COLCON_DEFAULTS_FILE': None, 'AMENT_PREFIX_PATH': str(PREFIX),
                          'CMAKE_PREFIX_PATH': str(PREFIX)})
    result = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=540)
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    # both packages found: the linked one, and magcal_ros (not its nested interfaces folder)
    install = ws / 'install'
    assert (install / 'magcal_ros').is_dir() and (install / 'magcal_interfaces').is_dir()
    site = install / 'magcal_interfaces' / 'lib' / 'python3.11' / 'site-packages'
    assert (site / 'magcal_interfaces' / 'msg' / '_gradient_tensor_stamped.py').is_file()
    env = subprocess_env({'PYTHONPATH': str(site),
                          'LD_LIBRARY_PATH': str(install / 'magcal_interfaces' / 'lib')})
    out = subprocess.run([sys.executable, '-c', CHECK], env=env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    path, fields = out.stdout.strip().splitlines()
    assert path.startswith(str(site))                      # the workspace's build, not .venv's
    assert fields == str({'header': 'std_msgs/Header', 'tensor': 'double[9]',
                          'tensor_covariance': 'double[81]'})
