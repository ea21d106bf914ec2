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
End to end with real processes: simulator, driver, calibration and corrector nodes.

fluxgate_sim -> fluxgate_driver -> calibration_node (and corrector_node) run as the installed
console scripts on real pseudo-terminals (the serial path a user's hardware takes), driven
from this test over ROS.

The live pipeline at the noise floor (calibrate on the tumbling array, then the corrected
total field and gradient tensor against the simulator's noise) is test_demo.py's
``make demo`` test: the same four processes, the same checks, run once in the suite.
Here: a recording the fit must refuse (a turntable, one rotation axis) leaves the previous
calibration file untouched.
"""
import json

from magcal_ros.core.data.simulate import simulate
from magcal_ros.io.calfile import save_calibration
from magcal_ros.pipeline import calibrate
from ros_helpers import call_trigger, console_script, spin_until, split_response as split
from std_msgs.msg import String

FIELD_NT = 50000.0
#: one sample per write, as a real device sends lines (see scripts/demo.py --sim-tick)
SIM_TICK = ['--tick', '0.01']


def start_pipeline(start_process, tmp_path, namespace, sim_args=(), calib_params=(),
                   corrector=True):
    """Start the simulator, the driver and the nodes; return the calibration file path."""
    sim_dir = tmp_path / 'sim'
    cal_file = tmp_path / 'calibration.yaml'
    ros = ['--ros-args', '-r', f'__ns:={namespace}']
    start_process(console_script('fluxgate_sim') + ['--dir', str(sim_dir)] + SIM_TICK
                  + list(sim_args), name='fluxgate_sim', ready='streaming')
    start_process(console_script('fluxgate_driver') + ros + [
        a for j in range(1, 5) for a in ('-p', f'sensor{j}.port:={sim_dir}/fluxgate{j}')],
        name='fluxgate_driver')
    start_process(console_script('calibration_node') + ros + [
        '-p', f'calibration_file:={cal_file}', '-p', f'report_dir:={tmp_path / "report"}']
        + [a for p in calib_params for a in ('-p', p)], name='calibration_node')
    if corrector:
        start_process(console_script('corrector_node') + ros + [
            '-p', f'calibration_file:={cal_file}'], name='corrector_node')
    return cal_file


def wait_for_sets(node, executor, n_sets, timeout_sec, need_ready=True):
    """Spin until calibration/status reports ``n_sets`` sets (and readiness); return it."""
    box = []
    sub = node.create_subscription(String, 'calibration/status',
                                   lambda m: box.append(json.loads(m.data)), 10)
    try:
        return spin_until(
            executor, lambda: box and box[-1]['sets'] >= n_sets
            and (box[-1]['ready'] or not need_ready) and box[-1], timeout_sec,
            f'{n_sets} sets' + (' and full coverage' if need_ready else ''))
    finally:
        node.destroy_subscription(sub)


def test_single_axis_rotation_is_refused(start_process, ros_node, ros_executor, ros_namespace,
                                         tmp_path):
    data, _ = simulate(n_samples=600, trajectory='smooth', smooth_period_s=6.0, seed=2)
    cal_file = tmp_path / 'calibration.yaml'
    save_calibration(cal_file, calibrate(data, 'base', field_nt=FIELD_NT).doc, history=0)
    before = cal_file.read_bytes()
    start_pipeline(start_process, tmp_path, ros_namespace,
                   sim_args=['--trajectory', 'turntable'],
                   calib_params=['min_samples:=300'], corrector=False)
    assert call_trigger(ros_node, ros_executor, 'calibration/start', timeout_sec=30.0).success
    status = wait_for_sets(ros_node, ros_executor, 400, 30.0, need_ready=False)
    assert set(status['coverage'].values()) == {'single axis'}
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=60.0)
    assert not resp.success
    lines, out = split(resp)
    head = ' '.join(lines[:2])         # a short first line, the reason on the next
    assert 'rotation about one axis only' in head
    assert 'rotate about another axis too' in head
    # the turntable turns about the sensors' z axis: the refusal names it
    assert 'normal (+0.00, +0.00, +1.00)' in head or 'normal (+0.00, +0.00, -1.00)' in head
    assert head.endswith('previous calibration stays active')
    assert cal_file.read_bytes() == before
