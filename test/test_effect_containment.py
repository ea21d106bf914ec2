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
Effect code cannot end a node (issue 22, item 2).

Start-up: a plug-in is evaluated once on a context of only the signals it declares; one that
reads an undeclared signal is refused with one line naming the effect and the signal, exit
status 2, offline (``magcal --plugin``) and live (the nodes' ``plugins`` parameter), run as
executables.  Run time: an exception raised by effect code while a sample is corrected is
contained: that sensor's sample is not published (no residual in the calibration node), the
error is logged once per effect and counted on ``/diagnostics`` (ERROR, naming the effect),
the other sensors and the node go on; a calibrate call failing inside effect code answers
success=false naming the effect.  The plug-ins are in test/faulty_effects.py; the values of
the data fed are not under test here, only what is published and answered.
"""
import json
import pathlib
import subprocess

from diagnostic_msgs.msg import DiagnosticStatus
import faulty_effects
import injection
from magcal_ros.core import effects as fx
from magcal_ros.core.data.simulate import simulate
from magcal_ros.core.effects.safety import (culprit, EffectError, EffectErrors,
                                            probe_context, probe_effect)
from magcal_ros.core.live.corrector import LiveCorrector
from magcal_ros.core.model import Calibration, Model
from magcal_ros.io.calfile import calibration_to_doc, save_calibration
from magcal_ros.pipeline import cross_geometry
from magcal_ros.ros.calibration_node import CalibrationNode
from magcal_ros.ros.corrector_node import CorrectorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from ros_helpers import call_trigger, console_script, REPO_ROOT, spin_until, subprocess_env
from sim_feed import Feeder
from test_corrector_node import Probe

TEST_DIR = pathlib.Path(__file__).resolve().parent
SNEAKY_LINE = ("effect 'sneaky_heat' (faulty_effects) reads the signal 'temperature' but does "
               "not declare it (signals: 'time')")


@pytest.fixture(scope='module')
def fragile():
    """Register faulty_effects.Fragile (passes the start-up probe) for this module."""
    assert fx.load_plugin('faulty_effects:Fragile') == ['fragile']
    yield faulty_effects.Fragile
    faulty_effects.BROKEN['on'] = False
    fx.unregister_effect('fragile')


def fragile_calibration(path):
    """Write a calibration base + fragile@2 (identity, zero offsets, 3 nT noise) to path."""
    model = Model.from_spec('base,fragile@2', 4)
    cal = Calibration(model, model.default_params(), sigma_nt=np.full(4, 3.0))
    save_calibration(path, calibration_to_doc(cal, geometry=cross_geometry(0.5)), history=0)
    return path


# -- start-up ------------------------------------------------------------------------------

def test_probe_refuses_an_undeclared_signal_in_one_line():
    with pytest.raises(ValueError) as err:
        fx.load_plugin('faulty_effects')
    assert str(err.value).startswith(SNEAKY_LINE) and '\n' not in str(err.value)
    assert fx.effect_class('sneaky_heat') is None          # refused before registration

    # a built-in effect with its declaration taken away is caught the same way: the probe
    # looks at what the code reads, not at names
    class NoTemp(fx.effect_class('temperature')):
        signals = ()

    class NoAux(fx.TOKEN_CLASSES['aux']):
        signals = ()

    with pytest.raises(ValueError, match="reads the signal 'temperature'"):
        probe_effect(NoTemp)
    with pytest.raises(ValueError, match="reads the signal 'aux_current'"):
        probe_effect(NoAux)


def test_probe_accepts_every_built_in_effect_and_the_example():
    for name in fx.BUILTIN_EFFECTS:
        probe_effect(fx.effect_class(name))
    probe_effect(fx.TOKEN_CLASSES['aux'])
    # the context holds exactly the declared signals; has() says no to the others
    ctx = probe_context(('temperature', 'aux_pump'))
    assert ctx.has('temperature') and ctx.has('aux_pump') and ctx.has('time')
    assert not ctx.has('field_rate') and not ctx.has('aux_motor')
    assert ctx.subset(slice(0, 5)).temp.shape == (5,)


def _run(cmd, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60,
                          env=subprocess_env({'PYTHONPATH': f'{REPO_ROOT}:{TEST_DIR}'}), **kw)


def test_magcal_plugin_refused_with_exit_2(tmp_path):
    proc = _run(console_script('magcal') + ['simulate', '--out', str(tmp_path / 'x.csv'),
                                            '--n', '20', '--plugin', 'faulty_effects'])
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('magcal: error: ' + SNEAKY_LINE), lines
    assert not (tmp_path / 'x.csv').exists()


@pytest.mark.parametrize('executable', ['corrector_node', 'calibration_node'])
def test_node_plugin_refused_with_exit_2(executable, tmp_path, ros_namespace):
    proc = _run(console_script(executable) + [
        '--ros-args', '-r', f'__ns:={ros_namespace}', '-p', 'plugins:=[faulty_effects]',
        '-p', f'calibration_file:={tmp_path / "cal.yaml"}'])
    assert proc.returncode == 2, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith(f'{executable}: bad parameters: plugins: {SNEAKY_LINE}'), \
        proc.stderr


# -- run time ------------------------------------------------------------------------------

def test_live_corrector_names_the_effect(fragile, tmp_path):
    model = Model.from_spec('base,fragile@2', 4)
    live = LiveCorrector(Calibration(model, model.default_params()), 4)
    raw = np.array([100.0, 200.0, 300.0])
    np.testing.assert_allclose(live.correct(1, 0.0, raw), raw)       # identity, sensor 1
    with pytest.raises(EffectError) as err:
        live.correct(2, 0.0, raw)
    assert err.value.effect == 'fragile@2' and isinstance(err.value.error, IndexError)
    assert str(err.value).startswith('effect fragile@2 raised IndexError: ')
    errors = EffectErrors()
    assert errors.add(err.value) and not errors.add(err.value)       # logged once
    assert errors.counts() == {'fragile@2': 2}
    assert culprit(ValueError('not from an effect')) is None


def test_corrector_contains_an_effect_error(fragile, make_node, ros_node, ros_executor,
                                            ros_namespace, tmp_path, monkeypatch):
    path = fragile_calibration(tmp_path / 'cal.yaml')
    node = make_node(CorrectorNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path))])
    assert node.calibration is not None
    logged = []
    monkeypatch.setattr(node.get_logger(), 'error', logged.append)
    probe = Probe(ros_node, ros_namespace)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    data = injection.make(n=30, seed=3)
    feeder.feed(ros_executor, data, taken=lambda: node.received, temperature=False)
    spin_until(ros_executor, lambda: len(probe.corrected[3]) >= 30, 5.0, 'sensor 4')
    # sensor 2's samples are handled before sensor 3's and 4's: none was published
    assert [len(c) for c in probe.corrected] == [30, 0, 30, 30]
    assert node.received == 120                  # the node took every sample and lives on
    assert len(logged) == 1 and logged[0].startswith('effect fragile@2 raised IndexError'), \
        logged
    status = probe.last_status(ros_executor, since=len(probe.diagnostics))
    assert status.level == DiagnosticStatus.ERROR
    assert 'effect fragile@2 raised IndexError' in status.message
    values = {v.key: v.value for v in status.values}
    assert values['effect_errors fragile@2'] == '30' and values['effect_errors'] == '30'


def test_calibration_node_contains_an_effect_error(fragile, make_node, ros_node, ros_executor,
                                                   ros_namespace, tmp_path, monkeypatch):
    path = fragile_calibration(tmp_path / 'cal.yaml')
    node = make_node(CalibrationNode, namespace=ros_namespace, parameter_overrides=[
        Parameter('calibration_file', value=str(path)), Parameter('min_samples', value=12),
        Parameter('model', value=['base', 'fragile@2']),
        Parameter('report_dir', value=str(tmp_path / 'report'))])
    logged = []
    monkeypatch.setattr(node.get_logger(), 'error', logged.append)
    feeder = Feeder(ros_node)
    feeder.wait_for_subscribers(ros_executor)
    assert call_trigger(ros_node, ros_executor, 'calibration/start').success
    # a tumble covering every attitude in 3 s (the fit must get as far as the effect's code)
    data, _ = simulate(n_samples=300, rate_hz=100.0, trajectory='smooth', smooth_period_s=3.0,
                       seed=7)
    feeder.feed(ros_executor, data, taken=lambda: node._taken, temperature=False)
    # the residual of sensor 2 fails in effect code on every sample; the node collects on
    assert node.received.tolist() == [300] * 4
    status = node.residual_status()
    assert status.level == DiagnosticStatus.ERROR
    assert status.message.startswith('effect code failed: effect fragile@2 raised IndexError')
    assert {v.key: v.value for v in status.values}['effect_errors fragile@2'] == '300'
    assert len(logged) == 1
    # a calibrate call whose fit fails inside the effect answers success=false, naming it
    faulty_effects.BROKEN['on'] = True
    try:
        res = call_trigger(ros_node, ros_executor, 'calibration/calibrate')
    finally:
        faulty_effects.BROKEN['on'] = False
    assert not res.success
    payload = json.loads(res.message.splitlines()[-1])
    assert payload.get('effect') == 'fragile@2', res.message
    assert 'effect fragile@2 raised RuntimeError: fragile is broken' in res.message
    assert node.residual_status().level == DiagnosticStatus.ERROR
    assert len(logged) == 1                 # fragile@2 was logged already: counted only
