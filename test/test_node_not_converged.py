"""The calibration node never installs a fit that did not converge (issue 10 item 4).

The solver is cut to 2 evaluations (pipeline.fit patched in-process): the node answers
success=false with the reason, writes no file and publishes nothing.
"""
from functools import partial

from magcal_ros import pipeline
from magcal_ros.core import model as model_mod
from magcal_ros.core.simulate import simulate
from magcal_ros.ros.calibration_node import RESULT_QOS
from ros_helpers import spin_for, split_response as split
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
    assert lines[0].startswith('not calibrated: the fit did not converge (maximum number of '
                               'evaluations')
    assert lines[0].endswith('previous calibration stays active')
    assert out['converged'] is False
    assert not (tmp_path / 'cal' / 'calibration.yaml').exists()
    spin_for(ros_executor, 0.3)
    assert results == []
