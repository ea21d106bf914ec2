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
The calibration node never installs a fit that did not converge (issue 10 item 4).

The solver is cut to 2 evaluations (pipeline.fit patched in-process): the node answers
success=false with the reason, writes no file and publishes nothing (until a good fit).
"""
from functools import partial

from magcal_ros import pipeline
from magcal_ros.core import model as model_mod
from magcal_ros.core.data.simulate import simulate
from magcal_ros.ros.calibration_node import RESULT_QOS
from ros_helpers import call_trigger, spin_until, split_response as split
from test_calibration_node import feed_and_calibrate, listen, start_node


def test_node_refuses_a_fit_that_did_not_converge(make_node, ros_node, ros_executor,
                                                  ros_namespace, tmp_path, monkeypatch):
    data, _ = simulate(n_samples=600, rate_hz=100.0, trajectory='smooth',
                       smooth_period_s=6.0, seed=7)
    monkeypatch.setattr(pipeline, 'fit', partial(model_mod.fit, max_nfev=2))
    results = listen(ros_node, 'calibration/result', RESULT_QOS)
    node = start_node(make_node, ros_namespace, tmp_path, min_samples=300)
    resp = feed_and_calibrate(node, ros_node, ros_executor, data)
    assert not resp.success
    lines, out = split(resp)
    # a long reason goes on the line after the short headline (what `ros2 service call` shows)
    assert lines[0] == 'not calibrated:'
    assert lines[1].startswith('the fit did not converge (maximum number of evaluations')
    assert lines[1].endswith('previous calibration stays active')
    assert out['converged'] is False
    assert not (tmp_path / 'cal' / 'calibration.yaml').exists()
    # the sentinel, not a fixed wait: the same data with the solver restored calibrate, and
    # the one calibration/result that arrives is that one (the refused fit published none)
    monkeypatch.undo()
    resp = call_trigger(ros_node, ros_executor, 'calibration/calibrate', timeout_sec=120.0)
    assert resp.success, resp.message
    spin_until(ros_executor, lambda: results, 5.0, 'the calibration/result of the good fit')
    assert len(results) == 1 and (tmp_path / 'cal' / 'calibration.yaml').exists()
