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
Layer boundaries: everything outside magcal_ros.ros imports without rclpy or *_msgs.

Each top-level part of the package other than ``ros`` (``core``, ``io``, ``serial``, ``cli``,
``units``, ``report`` ... discovered with pkgutil, so new modules are covered) is imported
with all its submodules in a fresh interpreter; afterwards ``sys.modules`` must hold no
rclpy, no ROS message or service package and no rosidl runtime.
"""

import ast
import functools
import json
import pathlib
import pkgutil
import sys

import pytest
from ros_helpers import REPO_ROOT, run_concurrently, subprocess_env

# Run in a fresh interpreter: import ``target`` and, if it is a subpackage, all its submodules
# one by one, recording which import first brought a ROS module in. The top package itself is
# imported alone (its subpackages are separate targets, and ``ros`` is allowed rclpy).
CHECK = r"""
import importlib, json, pkgutil, sys, traceback

def ros_modules():
    out = set()
    for name in sys.modules:
        top = name.split('.')[0]
        if (top in ('rclpy', 'rpyutils', 'builtin_interfaces') or top.endswith('_msgs')
                or top.endswith('_srvs') or top.startswith('rosidl')):
            out.add(top)
    return out

target = sys.argv[1]
report = {'imported': [], 'offenders': {}, 'errors': {}}

def visit(name):
    before = ros_modules()
    try:
        module = importlib.import_module(name)
    except BaseException:
        report['errors'][name] = traceback.format_exc(limit=3)
        return None
    report['imported'].append(name)
    new = sorted(ros_modules() - before)
    if new:
        report['offenders'][name] = new
    return module

module = visit(target)
if module is not None and hasattr(module, '__path__') and target != 'magcal_ros':
    for info in pkgutil.walk_packages(module.__path__, prefix=target + '.',
                                      onerror=lambda n: report['errors'].setdefault(n, 'walk')):
        visit(info.name)
print(json.dumps(report))
"""


def _ros_free_targets():
    """Top-level modules/packages of magcal_ros other than ``ros``, plus the package."""
    pkg_dir = REPO_ROOT / 'magcal_ros'
    names = sorted(info.name for info in pkgutil.iter_modules([str(pkg_dir)]))
    return ['magcal_ros'] + [f'magcal_ros.{n}' for n in names if n != 'ros']


#: the ROS layer's conversions: the detector must see rclpy there (test_the_check_detects_rclpy)
ROS_TARGET = 'magcal_ros.ros.conversions'


@functools.lru_cache(maxsize=None)
def _reports():
    """
    Run the check on every target, each in its own fresh interpreter, side by side.

    The interpreters are independent and only their reports are read, so they run at once
    (run_concurrently) instead of one after the other; each test reads its own.
    """
    targets = _ros_free_targets() + [ROS_TARGET]
    return run_concurrently({t: ([sys.executable, '-c', CHECK, t], subprocess_env())
                             for t in targets}, timeout_sec=120, cwd=REPO_ROOT)


def _check(target):
    result = _reports()[target]
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_the_layers_named_in_the_design_are_covered():
    targets = _ros_free_targets()
    for layer in ('core', 'io', 'serial', 'cli'):
        assert f'magcal_ros.{layer}' in targets
    assert 'magcal_ros.ros' not in targets


@pytest.mark.parametrize('target', _ros_free_targets())
def test_layer_imports_no_ros(target):
    report = _check(target)
    assert report['errors'] == {}, 'modules that failed to import:\n' + '\n'.join(
        f'{k}: {v}' for k, v in report['errors'].items())
    assert report['offenders'] == {}, (
        f'these modules import ROS packages (allowed only under magcal_ros/ros/): '
        f'{report["offenders"]}')
    # every module file under a package was actually imported
    path = REPO_ROOT / pathlib.Path(*target.split('.'))
    if path.is_dir() and target != 'magcal_ros':
        files = {p for p in path.rglob('*.py') if '__pycache__' not in p.parts}
        expected = {'.'.join(p.relative_to(REPO_ROOT).with_suffix('').parts).removesuffix(
            '.__init__') for p in files}
        assert expected <= set(report['imported'])


def test_the_check_detects_rclpy():
    # the ROS layer does import rclpy: the detector is not blind
    report = _check(ROS_TARGET)
    assert report['errors'] == {}
    assert 'rclpy' in report['offenders'][ROS_TARGET]
    assert 'sensor_msgs' in report['offenders'][ROS_TARGET]


# -- private names stay in their module ------------------------------------------------------

def _is_private(name):
    return name.startswith('_') and not (name.startswith('__') and name.endswith('__'))


def private_reaches(source, package_root=REPO_ROOT):
    """
    Return where ``source`` uses another magcal_ros module's private names.

    Two forms: ``from magcal_ros.x import _name`` and ``alias._name`` where ``alias`` is a
    magcal_ros module (``import magcal_ros.x as alias``, ``from magcal_ros import x as
    alias``).  Returns a list of (line, text).
    """
    tree = ast.parse(source)
    modules = {}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or '').split('.')[0] == 'magcal_ros':
            for a in node.names:
                if _is_private(a.name):
                    out.append((node.lineno, f'from {node.module} import {a.name}'))
                    continue
                sub = package_root / pathlib.Path(*f'{node.module}.{a.name}'.split('.'))
                if sub.with_suffix('.py').is_file() or sub.is_dir():
                    modules[a.asname or a.name] = f'{node.module}.{a.name}'
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split('.')[0] == 'magcal_ros':
                    modules[a.asname or 'magcal_ros'] = a.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and _is_private(node.attr)
                and isinstance(node.value, ast.Name) and node.value.id in modules):
            out.append((node.lineno, f'{node.value.id}.{node.attr} '
                                     f'({modules[node.value.id]})'))
    return sorted(out)


def test_no_module_reaches_into_another_modules_private_names():
    found = []
    for top in ('magcal_ros', 'bench'):
        for path in sorted((REPO_ROOT / top).rglob('*.py')):
            for line, text in private_reaches(path.read_text()):
                found.append(f'{path.relative_to(REPO_ROOT)}:{line}: {text}')
    assert not found, ('private names used across modules (make them public, with a '
                       'docstring, or keep the use inside the module):\n' + '\n'.join(found))


def test_the_private_name_check_sees_both_forms():
    source = ('from magcal_ros.core.model import fit, _hidden\n'
              'from magcal_ros.core import effects as fx\n'
              'import magcal_ros.core.model.engine as eng\n'
              'x = fx._REGISTRY, eng._cache, fx.make_effect, fx.__name__\n')
    assert [t for _, t in private_reaches(source)] == [
        'from magcal_ros.core.model import _hidden',
        'eng._cache (magcal_ros.core.model.engine)',
        'fx._REGISTRY (magcal_ros.core.effects)']
