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
The demos' processes end with the demo, however it ends (scripts/demo.py ``Processes``).

A loop demo killed by a test's timeout once left its simulator, driver and calibration node
streaming for a quarter of an hour, and the next runs shared the machine with them.
"""
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
import demo
procs = demo.Processes(sys.argv[2])
p = procs.start('fluxgate_sim', ['--dir', sys.argv[3], '--sensors', '1'])
print(p.pid, flush=True)
time.sleep(120)
"""


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (not reaped by its new parent yet) has ended too
    with open(f'/proc/{pid}/stat') as fh:
        return fh.read().split(') ')[-1][0] != 'Z'


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='PR_SET_PDEATHSIG: Linux')
def test_a_demo_killed_outright_takes_its_processes_with_it(tmp_path):
    demo = subprocess.Popen([sys.executable, '-c', CHILD, str(ROOT / 'scripts'),
                             str(tmp_path / 'logs'), str(tmp_path / 'dev')],
                            stdout=subprocess.PIPE, text=True)
    node = int(demo.stdout.readline())
    # the simulator runs (its link appears), in a session of its own
    deadline = time.monotonic() + 30.0
    while not os.path.lexists(tmp_path / 'dev' / 'fluxgate1'):
        assert time.monotonic() < deadline, (tmp_path / 'logs' / 'fluxgate_sim.log').read_text()
        time.sleep(0.05)
    assert os.getsid(node) == node != os.getsid(demo.pid)
    demo.send_signal(signal.SIGKILL)               # no finally, no shut_down
    demo.wait(10)
    deadline = time.monotonic() + 15.0
    while _alive(node):
        assert time.monotonic() < deadline, 'the simulator outlived the demo'
        time.sleep(0.05)
    # it was told to stop (SIGTERM), not killed: it removed its device link
    deadline = time.monotonic() + 5.0
    while os.path.lexists(tmp_path / 'dev' / 'fluxgate1'):
        assert time.monotonic() < deadline, 'the device link stayed'
        time.sleep(0.05)
