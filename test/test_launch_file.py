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
launch/magcal.launch.py and the node parameter files, checked without `launch` installed.

`launch`/`launch_ros` do not install from the package index, so the launch file is compiled,
its NODES table is checked against setup.py's console scripts and the config directory, and
``generate_launch_description()`` is run against stand-ins with the Jazzy signatures of
``launch_ros.actions.Node`` (keyword-only: executable, package, name, namespace, exec_name,
parameters, remappings, ros_arguments, arguments, plus ExecuteProcess/Action keywords) that
record what the file asks for.
"""
import ast
import os
import pathlib
import sys
import types

from magcal_ros.ros import params as prm
from magcal_ros.ros.learning import learning_specs
import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'magcal.launch.py'

#: keyword arguments of launch.actions.ExecuteProcess / launch.Action (Jazzy) that a Node
#: passes through **kwargs
EXECUTE_PROCESS_KWARGS = {
    'output', 'condition', 'respawn', 'respawn_delay', 'emulate_tty', 'sigterm_timeout',
    'sigkill_timeout', 'additional_env', 'cwd', 'name', 'prefix', 'shell', 'log_cmd',
    'on_exit', 'cached_output', 'env', 'output_format'}


def _console_scripts():
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entries = ast.literal_eval(node.value)['console_scripts']
            return dict(tuple(x.strip() for x in e.split('=')) for e in entries)
    raise AssertionError('setup.py has no entry_points')


def _nodes_table():
    tree = ast.parse(LAUNCH.read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', '') == 'NODES':
            return ast.literal_eval(node.value)
    raise AssertionError('launch file has no NODES table')


def test_launch_file_compiles():
    compile(LAUNCH.read_text(), str(LAUNCH), 'exec')


def test_executables_are_console_scripts_with_main():
    scripts = _console_scripts()
    nodes = _nodes_table()
    assert {n[0] for n in nodes} == {
        'fluxgate_sim', 'fluxgate_driver', 'calibration_node', 'corrector_node'}
    for executable, _, _ in nodes:
        assert executable in scripts, f'{executable} is not a console script in setup.py'
        module, func = scripts[executable].split(':')
        if not (ROOT / (module.replace('.', '/') + '.py')).exists():
            pytest.fail(f'{executable}: module {module} does not exist')
        src = (ROOT / (module.replace('.', '/') + '.py')).read_text()
        assert f'def {func}(args=None)' in src, f'{module} has no {func}(args=None)'


def test_config_files_exist_and_are_installed():
    for _, config, _ in _nodes_table():
        assert (ROOT / 'config' / config).is_file(), f'config/{config} missing'
    setup = (ROOT / 'setup.py').read_text()
    assert "glob('config/*.yaml')" in setup
    assert "glob('launch/*.launch.py')" in setup


@pytest.mark.parametrize('node_name, specs', [
    ('calibration_node', prm.calibration_specs() + learning_specs()),
    ('corrector_node', prm.corrector_specs()),
])
def test_parameter_files_match_declared_parameters(node_name, specs):
    doc = yaml.safe_load((ROOT / 'config' / node_name.replace('_node', '.yaml')).read_text())
    # '/**/name' matches the node in any namespace (a bare 'name' only in the root namespace)
    assert list(doc) == [f'/**/{node_name}']
    values = doc[f'/**/{node_name}']['ros__parameters']
    declared = {s.name: s for s in specs + [prm.N_SENSORS]}
    unknown = set(values) - set(declared)
    assert not unknown, f'{node_name}: parameters not declared by the node: {unknown}'
    for name, value in values.items():
        spec = declared[name]
        if isinstance(spec.default, tuple):
            assert isinstance(value, list)
        else:
            assert type(value) is type(spec.default), (name, value)
        if spec.check:
            assert spec.check(tuple(value) if isinstance(value, list) else value) is None
        if spec.limits is not None:
            assert spec.limits[0] <= value <= spec.limits[1], (name, value, spec.limits)
        # the shipped file keeps the documented defaults
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        assert value == default, f'{node_name}.{name}: {value!r} != default {default!r}'


def _stub_modules(share_dir):
    recorded = {'nodes': [], 'arguments': []}

    class Node:
        def __init__(self, *, executable, package=None, name=None, namespace=None,
                     exec_name=None, parameters=None, remappings=None, ros_arguments=None,
                     arguments=None, **kwargs):
            unknown = set(kwargs) - EXECUTE_PROCESS_KWARGS
            if unknown:
                raise TypeError(f'Node() got unexpected keyword arguments {unknown}')
            if parameters is not None and not isinstance(parameters, list):
                raise TypeError('parameters must be a list (launch_ros ensure_argument_type)')
            recorded['nodes'].append(dict(executable=executable, package=package, name=name,
                                          namespace=namespace, parameters=parameters,
                                          **kwargs))

    class DeclareLaunchArgument:
        def __init__(self, name, *, default_value=None, description=None, choices=None):
            recorded['arguments'].append((name, default_value))

    class LaunchConfiguration:
        def __init__(self, variable_name, *, default=None):
            self.variable_name = variable_name

    class OpaqueFunction:
        def __init__(self, *, function, args=None, kwargs=None):
            self.function = function

    class LaunchDescription:
        def __init__(self, initial_entities=None):
            self.entities = list(initial_entities or [])

    mods = {
        'launch': types.ModuleType('launch'),
        'launch.actions': types.ModuleType('launch.actions'),
        'launch.substitutions': types.ModuleType('launch.substitutions'),
        'launch_ros': types.ModuleType('launch_ros'),
        'launch_ros.actions': types.ModuleType('launch_ros.actions'),
        'ament_index_python': types.ModuleType('ament_index_python'),
        'ament_index_python.packages': types.ModuleType('ament_index_python.packages'),
    }
    mods['launch'].LaunchDescription = LaunchDescription
    mods['launch.actions'].DeclareLaunchArgument = DeclareLaunchArgument
    mods['launch.actions'].OpaqueFunction = OpaqueFunction
    mods['launch.substitutions'].LaunchConfiguration = LaunchConfiguration
    mods['launch_ros.actions'].Node = Node

    def get_package_share_directory(name):
        if name != 'magcal_ros':
            raise LookupError(name)
        return str(share_dir)
    mods['ament_index_python.packages'].get_package_share_directory = \
        get_package_share_directory
    return mods, recorded


class _Context:
    """What an OpaqueFunction reads of a launch context: the arguments as given."""

    def __init__(self, **given):
        self.launch_configurations = {'use_sim': 'true', 'namespace': 'magcal',
                                      'driver_params': '', 'calibration_file': ''}
        self.launch_configurations.update(given)


def _launch(monkeypatch, **given):
    """Run the launch file against the stand-ins; return (arguments, nodes by executable)."""
    mods, recorded = _stub_modules(ROOT)
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)
    ns = {'__file__': str(LAUNCH), '__name__': 'magcal_launch'}
    exec(compile(LAUNCH.read_text(), str(LAUNCH), 'exec'), ns)
    desc = ns['generate_launch_description']()
    (opaque,) = [e for e in desc.entities if hasattr(e, 'function')]
    opaque.function(_Context(**given))
    return dict(recorded['arguments']), {n['executable']: n for n in recorded['nodes']}


def test_generate_launch_description(monkeypatch, tmp_path):
    args, nodes = _launch(monkeypatch)
    assert args == {'use_sim': 'true', 'namespace': 'magcal', 'driver_params': '',
                    'calibration_file': ''}
    assert set(nodes) == {'fluxgate_sim', 'fluxgate_driver', 'calibration_node',
                          'corrector_node'}
    for exe, n in nodes.items():
        assert n['package'] == 'magcal_ros'
        assert n['namespace'] == 'magcal'
        (path,) = n['parameters']
        assert os.path.dirname(path) == os.path.join(str(ROOT), 'config')
        assert os.path.exists(path), f'{exe}: parameter file {path} missing'


def test_launch_arguments_select_files(monkeypatch, tmp_path):
    # real fluxgates: no simulator, and the simulator's ports are not loaded
    with pytest.raises(RuntimeError, match='use_sim:=false needs driver_params'):
        _launch(monkeypatch, use_sim='false')
    mine = tmp_path / 'driver.yaml'
    mine.write_text('/**/fluxgate_driver:\n  ros__parameters:\n    sensor1.port: /dev/ttyUSB0\n')
    cal = str(tmp_path / 'cal.yaml')
    _, nodes = _launch(monkeypatch, use_sim='false', driver_params=str(mine),
                       calibration_file=cal, namespace='array2')
    assert set(nodes) == {'fluxgate_driver', 'calibration_node', 'corrector_node'}
    assert nodes['fluxgate_driver']['parameters'] == [str(mine)]
    for exe in ('calibration_node', 'corrector_node'):
        assert nodes[exe]['parameters'][1] == {'calibration_file': cal}
        assert nodes[exe]['namespace'] == 'array2'
    with pytest.raises(RuntimeError, match='driver_params: no file'):
        _launch(monkeypatch, driver_params=str(tmp_path / 'missing.yaml'))
    # package name agrees with package.xml
    assert '<name>magcal_ros</name>' in (ROOT / 'package.xml').read_text()
