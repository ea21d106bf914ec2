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

"""The executables run BLAS on one thread unless the user chose (magcal_ros/runtime.py)."""
import json
import os
import subprocess
import sys

import pytest

#: what a fresh process reports: BLAS threads after limit_blas_threads(), as JSON
PROBE = ('import json; from magcal_ros.runtime import limit_blas_threads; '
         'said = limit_blas_threads(); import numpy, scipy.linalg; '
         'from threadpoolctl import threadpool_info; '
         'print(json.dumps([said, [p["num_threads"] for p in threadpool_info() '
         'if p["user_api"] == "blas"]]))')


def _probe(env_extra, nproc_threads=None):
    env = {k: v for k, v in os.environ.items()
           if k not in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')}
    env.update(env_extra)
    out = subprocess.run([sys.executable, '-c', PROBE], env=env, capture_output=True,
                         text=True, timeout=60, check=True).stdout
    return json.loads(out)


def test_one_blas_thread_by_default():
    said, threads = _probe({})
    assert said == '1 thread'
    assert threads and all(n == 1 for n in threads), threads


@pytest.mark.parametrize('var', ['OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS'])
def test_a_users_choice_is_kept(var):
    said, threads = _probe({var: '2'})
    assert said == f'as {var}=2'
    # OpenBLAS reads OPENBLAS_NUM_THREADS, else OMP_NUM_THREADS, at load: 2, not our 1
    assert threads and all(n == 2 for n in threads), threads


def test_the_cli_and_the_nodes_call_it():
    """The two entry points of every executable (magcal's main, the nodes' spin_node)."""
    import inspect

    from magcal_ros import cli
    from magcal_ros.ros import run
    assert 'limit_blas_threads()' in inspect.getsource(cli.main)
    assert 'limit_blas_threads()' in inspect.getsource(run.spin_node)


def test_executor_choice(monkeypatch):
    """The nodes' executor (ros/run.py): events by default, single on request or when told."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from magcal_ros.ros.run import EXECUTOR_VARIABLE, make_executor
    rclpy.init()
    try:
        monkeypatch.delenv(EXECUTOR_VARIABLE, raising=False)
        ex, name = make_executor()
        assert name == 'events' and not isinstance(ex, SingleThreadedExecutor)
        ex.shutdown()
        # the calibration node: coroutine services, which the EventsExecutor cannot run
        ex, name = make_executor(events=False)
        assert name == 'single' and isinstance(ex, SingleThreadedExecutor)
        monkeypatch.setenv(EXECUTOR_VARIABLE, 'single')
        ex, name = make_executor()
        assert name == 'single' and isinstance(ex, SingleThreadedExecutor)
        monkeypatch.setenv(EXECUTOR_VARIABLE, 'fast')
        with pytest.raises(ValueError, match="MAGCAL_EXECUTOR='fast': use events or single"):
            make_executor()
    finally:
        rclpy.try_shutdown()
