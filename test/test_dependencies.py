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
Every third-party module the package imports is declared: in requirements.txt and package.xml.

The imports are read from the source (ast) of ``magcal_ros/`` and ``launch/``: ``import`` and
``from ... import`` at any depth (a lazy import inside a function counts), and the module named
by a string literal given to ``import_module`` or to the corrector's ``_optional``.  Each
top-level module outside the standard library is mapped to the distribution that installs it
(``importlib.metadata.packages_distributions()``), and :data:`DECLARED` gives, per
distribution, the requirement of requirements.txt that installs it and its rosdep key; both
must be declared.  A ROS package that the wheels do not provide (only an install of ROS has
it, and the code runs without it) is in :data:`ROS_ONLY` with its key, which package.xml must
list.  A pip key that rosdistro lacks must be defined in ``rosdep.yaml`` with the same pip
package.
"""

import ast
import importlib.metadata
import re
import sys
import xml.etree.ElementTree as ET

from ros_helpers import REPO_ROOT
import yaml

#: distribution (as installed) -> (the requirement of requirements.txt that installs it,
#: its rosdep key in package.xml).  Keys ending in -pip: rosdistro's python.yaml has
#: ``python3-rosbags-pip``; the others are in rosdep.yaml (:data:`OWN_PIP_KEYS`)
DECLARED = {
    'numpy': ('numpy', 'python3-numpy'),
    'scipy': ('scipy', 'python3-scipy'),
    'pyserial': ('pyserial', 'python3-serial'),
    'PyYAML': ('PyYAML', 'python3-yaml'),
    'matplotlib': ('matplotlib', 'python3-matplotlib'),
    'pillow': ('Pillow', 'python3-pil'),
    'tqdm': ('tqdm', 'python3-tqdm'),
    'jsonschema': ('jsonschema', 'python3-jsonschema'),
    'rosbags': ('rosbags', 'python3-rosbags-pip'),
    'ppigrf': ('ppigrf', 'python3-ppigrf-pip'),
    'zstandard': ('zstandard', 'python3-zstandard-pip'),
    'threadpoolctl': ('threadpoolctl', 'python3-threadpoolctl-pip'),
    'pymavlink': ('pymavlink', 'python3-pymavlink-pip'),
    'pyulog': ('pyulog', 'python3-pyulog-pip'),
    # the ROS 2 Jazzy wheels: each ROS package is its own distribution, installed by the
    # requirement named here; its rosdep key is the ROS package's name
    'ros-rclpy': ('ros-jazzy-rclpy', 'rclpy'),
    'ros-rcl-interfaces': ('ros-jazzy-rclpy', 'rcl_interfaces'),
    'ros-builtin-interfaces': ('ros-jazzy-rclpy', 'builtin_interfaces'),
    'ros-ament-index-python': ('ros-jazzy-rclpy', 'ament_index_python'),
    'ros-sensor-msgs': ('ros-jazzy-common-interfaces', 'sensor_msgs'),
    'ros-std-msgs': ('ros-jazzy-common-interfaces', 'std_msgs'),
    'ros-geometry-msgs': ('ros-jazzy-common-interfaces', 'geometry_msgs'),
    'ros-diagnostic-msgs': ('ros-jazzy-common-interfaces', 'diagnostic_msgs'),
    'ros-std-srvs': ('ros-jazzy-std-srvs', 'std_srvs'),
    # built from interfaces/ by scripts/build_interfaces.sh, not a requirement
    'magcal-interfaces': (None, 'magcal_interfaces'),
}
#: imported modules no wheel of requirements.txt installs (an install of ROS has them; the
#: package runs without them: a shim, or the feature is off) -> rosdep key
ROS_ONLY = {'diagnostic_updater': 'diagnostic_updater', 'tf2_ros': 'tf2_ros',
            'launch': 'launch', 'launch_ros': 'launch_ros'}
#: the pip keys rosdistro lacks, defined in rosdep.yaml
OWN_PIP_KEYS = {'python3-ppigrf-pip', 'python3-zstandard-pip', 'python3-threadpoolctl-pip',
                'python3-pymavlink-pip', 'python3-pyulog-pip'}


def imported_modules(paths):
    """Return {top-level module: sorted files importing it}, outside the standard library."""
    found = {}
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif (isinstance(node, ast.Call) and node.args
                  and isinstance(node.args[0], ast.Constant)
                  and isinstance(node.args[0].value, str)
                  and getattr(node.func, 'attr', getattr(node.func, 'id', None))
                  in ('import_module', '_optional')):
                names = [node.args[0].value]
            else:
                continue
            for name in names:
                found.setdefault(name.split('.')[0], set()).add(
                    str(path.relative_to(REPO_ROOT)))
    skip = set(sys.stdlib_module_names) | {'magcal_ros'}
    return {m: sorted(f) for m, f in found.items() if m not in skip}


def _normalise(name):
    return re.sub(r'[-_.]+', '-', name).lower()


def requirements():
    """Return the normalised names of requirements.txt's requirements."""
    names = set()
    for line in (REPO_ROOT / 'requirements.txt').read_text().splitlines():
        line = line.split('#')[0].strip()
        if line:
            names.add(_normalise(re.match(r'[A-Za-z0-9._-]+', line).group(0)))
    return names


def exec_depends():
    """Return package.xml's exec_depend keys."""
    root = ET.parse(REPO_ROOT / 'package.xml').getroot()
    return {e.text for e in root.findall('exec_depend')}


def undeclared(modules, distributions, required, keys):
    """
    Return the problems: one line per imported module whose dependency is not declared.

    modules: {module: files}; distributions: packages_distributions(); required: normalised
    requirement names; keys: package.xml's exec_depend keys.
    """
    problems = []
    for module, files in sorted(modules.items()):
        where = f'{module} (imported by {files[0]})'
        if module in ROS_ONLY:
            if ROS_ONLY[module] not in keys:
                problems.append(f'{where}: package.xml lacks {ROS_ONLY[module]}')
            continue
        dists = [d for d in distributions.get(module, []) if d in DECLARED]
        if not dists:
            problems.append(f'{where}: its distribution {distributions.get(module)} is not in '
                            'the table DECLARED of this test (add its requirement and key)')
            continue
        requirement, key = DECLARED[dists[0]]
        if requirement is not None and _normalise(requirement) not in required:
            problems.append(f'{where}: requirements.txt lacks {requirement}')
        if key not in keys:
            problems.append(f'{where}: package.xml lacks <exec_depend>{key}</exec_depend>')
    return problems


def _sources():
    return sorted((REPO_ROOT / 'magcal_ros').rglob('*.py')) + sorted(
        (REPO_ROOT / 'launch').glob('*.py'))


def test_every_third_party_import_is_declared_in_requirements_and_package_xml():
    modules = imported_modules(_sources())
    # the scan sees the imports it must: lazy ones, and the corrector's optional ones
    assert {'numpy', 'scipy', 'yaml', 'rosbags', 'ppigrf', 'zstandard', 'threadpoolctl',
            'jsonschema', 'tqdm', 'PIL', 'serial', 'rclpy', 'tf2_ros',
            'magcal_interfaces', 'launch'} <= set(modules)
    problems = undeclared(modules, importlib.metadata.packages_distributions(),
                          requirements(), exec_depends())
    assert problems == [], 'undeclared dependencies:\n' + '\n'.join(problems)


def test_a_missing_declaration_is_found():
    modules = {'zstandard': ['magcal_ros/io/compressed.py'], 'numpy': ['magcal_ros/cli.py']}
    dists = {'zstandard': ['zstandard'], 'numpy': ['numpy']}
    keys = {'python3-numpy', 'python3-zstandard-pip'}
    assert undeclared(modules, dists, {'numpy', 'zstandard'}, keys) == []
    assert undeclared(modules, dists, {'numpy'}, keys) == [
        'zstandard (imported by magcal_ros/io/compressed.py): requirements.txt lacks zstandard']
    assert undeclared(modules, dists, {'numpy', 'zstandard'}, {'python3-numpy'}) == [
        'zstandard (imported by magcal_ros/io/compressed.py): package.xml lacks '
        '<exec_depend>python3-zstandard-pip</exec_depend>']
    assert 'not in the table' in undeclared({'foo': ['x.py']}, {'foo': ['foo']}, set(), keys)[0]


def test_the_pip_keys_rosdistro_lacks_are_defined_in_rosdep_yaml():
    own = yaml.safe_load((REPO_ROOT / 'rosdep.yaml').read_text())
    assert set(own) == OWN_PIP_KEYS and OWN_PIP_KEYS <= exec_depends()
    for key, rule in own.items():
        (requirement,) = [r for r, k in DECLARED.values() if k == key]
        for osname in ('debian', 'ubuntu'):
            assert rule[osname]['pip']['packages'] == [requirement], key


def test_test_depends_are_declared():
    root = ET.parse(REPO_ROOT / 'package.xml').getroot()
    test_deps = {e.text for e in root.findall('test_depend')}
    assert {'python3-pytest', 'python3-pytest-timeout', 'python3-hypothesis',
            'ament_flake8', 'ament_pep257', 'ament_copyright'} <= test_deps
