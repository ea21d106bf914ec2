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
Nothing is imported or overwritten from the network (issue 12 item 2).

Plug-in effects load only from the read-only start-up parameter ``plugins`` of both nodes; a
calibration document or a model parameter naming a module is refused without importing it
(checked with a module that writes a file when it is imported); output paths are read-only;
bad start-up values end the process with one line on stderr and exit status 2.
"""
import copy
import sys

from diagnostic_msgs.msg import DiagnosticArray
from magcal_ros.core import effects as fx
from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.calfile import calibration_to_doc, dump_calibration, load_calibration
from magcal_ros.pipeline import cross_geometry
from magcal_ros.ros.calibration_node import CalibrationNode, RESULT_QOS
from magcal_ros.ros.conversions import field_nt_to_msg
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import (console_script, REPO_ROOT, run_concurrently, spin_until, subprocess_env)
from sensor_msgs.msg import MagneticField
from sim_feed import Feeder
from std_msgs.msg import String

#: a plug-in module that leaves a trace when it is imported
EVIL = """
import pathlib
pathlib.Path({marker!r}).write_text('imported')
"""

WHEEL = {'ax': 10.0, 'ay': -8.0, 'az': 6.0, 'bx': 4.0, 'by': 12.0, 'bz': -6.0}     # nT


@pytest.fixture
def evil_module(tmp_path, monkeypatch):
    """Put a module ``h5_evil_plugin`` on sys.path whose import writes ``<tmp>/imported``."""
    marker = tmp_path / 'imported'
    (tmp_path / 'h5_evil_plugin.py').write_text(EVIL.format(marker=str(marker)))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield marker
    sys.modules.pop('h5_evil_plugin', None)


@pytest.fixture
def wheel_unloaded():
    """Leave the registry without the example's 'wheel' effect after the test."""
    yield
    if fx.effect_class('wheel') is not None:
        fx.unregister_effect('wheel')
    sys.modules.pop('my_effect', None)


def _doc_with_effect(name, model_token):
    """Return the simulator's true calibration plus one additive effect ``name`` on sensor 3."""
    _, simulator = simulate(n_samples=50, rate_hz=100.0, trajectory='smooth', seed=3)
    doc = copy.deepcopy(calibration_to_doc(simulator.truth, geometry=cross_geometry(0.5)))
    doc['model'] = list(doc['model']) + [model_token]
    doc['sensors'][2]['effects'].append({
        'name': name, 'label': name, 'refs': {'t0_s': 0.0, 'frequency_hz': 0.25},
        'params': {k: {'value': v, 'unit': 'nT', 'stderr': 0.0} for k, v in WHEEL.items()}})
    return doc


def _diag_message(ros_node, ros_executor, predicate):
    box = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', box.append, 10)

    def found():
        for arr in box:
            for st in arr.status:
                if 'corrector_node' in st.name and predicate(st.message):
                    return st.message
        return None
    return spin_until(ros_executor, found, 10.0, 'the corrector diagnostics')


def test_calibration_message_naming_a_module_is_refused_without_importing_it(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, evil_module):
    make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(tmp_path / 'none.yaml'))])
    pub = ros_node.create_publisher(String, 'calibration/result', RESULT_QOS)
    pub.publish(String(data=dump_calibration(_doc_with_effect('h5_evil_plugin:Evil',
                                                              'h5_evil_plugin:Evil@3'))))
    msg = _diag_message(ros_node, ros_executor, lambda m: 'refused the calibration' in m)
    assert 'is not loaded' in msg and 'plugins' in msg
    assert not evil_module.exists(), 'the message made the node import a module'
    assert 'h5_evil_plugin' not in sys.modules


def test_model_parameter_naming_a_module_is_refused_without_importing_it(
        make_node, ros_namespace, tmp_path, evil_module):
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(tmp_path / 'cal.yaml'))])
    for model in (['base', 'h5_evil_plugin:Evil@1'], ['base', 'h5_evil_plugin:Evil'],
                  ['base', 'os:getcwd@1']):
        res = node.set_parameters([Parameter('model', value=model)])[0]
        assert not res.successful and 'is not loaded' in res.reason, res.reason
    assert not evil_module.exists()
    assert 'h5_evil_plugin' not in sys.modules
    assert node.get_parameter('model').value == ['base']


def test_plugin_effect_calibration_works_in_the_corrector(
        make_node, ros_node, ros_executor, ros_namespace, tmp_path, monkeypatch, wheel_unloaded):
    monkeypatch.syspath_prepend(str(REPO_ROOT / 'examples'))
    doc = _doc_with_effect('wheel', 'wheel@3')
    path = tmp_path / 'cal.yaml'
    path.write_text(dump_calibration(doc))
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)),
        Parameter('plugins', value=['my_effect'])])
    assert node.refusal is None and node.calibration is not None
    assert node.describe_parameter('plugins').read_only
    # the additive wheel term is removed from sensor 3 before A^-1: two raw samples equal to
    # the wheel's own field at t (computed here by hand) plus the offset correct to zero
    corrected = []
    ros_node.create_subscription(MagneticField, 'sensor3/corrected', corrected.append, 10)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    cal, _ = load_calibration(path)          # the plug-in is loaded now (by the node)
    a_inv, offset = cal.correction_matrix(3), cal.offset(3)
    for t in (1.0, 2.0):
        w = 2 * np.pi * 0.25 * t
        wheel = np.array([WHEEL[f'a{c}'] * np.cos(w) + WHEEL[f'b{c}'] * np.sin(w)
                          for c in 'xyz'])
        raw = offset + wheel + np.linalg.solve(a_inv, [100.0, 200.0, 300.0])
        feeder.raw[2].publish(field_nt_to_msg(raw, stamp=t, frame_id='fluxgate3'))
    spin_until(ros_executor, lambda: len(corrected) >= 2, 10.0, 'two corrected samples')
    for msg in corrected:
        b = np.array([msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z]) * 1e9
        np.testing.assert_allclose(b, [100.0, 200.0, 300.0], atol=1e-6)


def test_without_the_plugin_the_corrector_refuses_the_calibration(
        make_node, ros_namespace, tmp_path):
    path = tmp_path / 'cal.yaml'
    path.write_text(dump_calibration(_doc_with_effect('wheel', 'wheel@3')))
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    assert node.calibration is None and "unknown effect 'wheel'" in node.refusal


BAD_START_UP_EXES = ['calibration_node', 'corrector_node']
BAD_START_UP_VALUES = [
    ('field_nt:=48000', 'field_nt'),               # an integer for a double
    ('field_nt:=abc', 'field_nt'),
    ('plugins:=[no_such_module_h5]', 'cannot import effect plugin'),
    ("plugins:=['os.path:no_such_class']", 'no_such_class'),
    ('stamp_tolerance_s:=-1.0', 'stamp_tolerance_s'),
    ('-p', 'bad command line'),
]


def _bad_start_up_case(exe, override, match):
    """Return (command-line arguments, expected text) of one bad start-up case."""
    if exe == 'corrector_node' and override.startswith('field_nt'):
        override = 'diagnostics_period_s:=' + override.split(':=')[1]
        match = 'diagnostics_period_s'
    args = ['--ros-args', '-p', override] if override != '-p' else ['--ros-args', '-p',
                                                                    'field_nt']
    return args, match


@pytest.fixture(scope='module')
def bad_start_up_runs(tmp_path_factory):
    """
    Run every bad start-up case, each its own process with its own ROS_HOME, side by side.

    Each process ends at start-up and the tests read only how it ended, so they are started
    together (run_concurrently) instead of one after the other.
    """
    commands = {}
    for exe in BAD_START_UP_EXES:
        for override, match in BAD_START_UP_VALUES:
            args, _ = _bad_start_up_case(exe, override, match)
            home = tmp_path_factory.mktemp('ros_home')
            commands[exe, override] = (console_script(exe) + args,
                                       subprocess_env({'ROS_HOME': str(home)}))
    return run_concurrently(commands, timeout_sec=60)


@pytest.mark.parametrize('exe', BAD_START_UP_EXES)
@pytest.mark.parametrize('override, match', BAD_START_UP_VALUES)
def test_bad_start_up_values_give_one_line_and_exit_2(exe, override, match, bad_start_up_runs):
    _, match = _bad_start_up_case(exe, override, match)
    proc = bad_start_up_runs[exe, override]
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(exe + ': ') and match in lines[0], lines
