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
Test-session setup: loopback-only DDS, a per-run ROS_DOMAIN_ID, and the ROS fixtures.

pytest imports this file before any test module, so the environment below is in place
before rclpy is imported or creates a DDS participant anywhere in the session, and it is
inherited by every process the tests start:

- ``FASTRTPS_DEFAULT_PROFILES_FILE`` and ``FASTDDS_DEFAULT_PROFILES_FILE``: the absolute path
  of ``config/fastdds_loopback.xml`` (shared memory + UDPv4 on 127.0.0.1, no multicast).
- ``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT`` so the profile is used unchanged,
  ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``; ``ROS_LOCALHOST_ONLY`` and ``ROS_STATIC_PEERS``
  are removed.
- ``ROS_DOMAIN_ID``: chosen per run (per pytest-xdist worker) in 1..101, starting from the
  PID (spread by the worker's index) and skipping domains
  whose Fast DDS ports are already bound on this machine, so parallel runs do not meet.
  Set ``MAGCAL_TEST_ROS_DOMAIN_ID`` to force one.

Every file opened by the session or a Python process it starts under the repository's parent
folder but outside the repository fails the session (``open_audit_site/open_audit.py``).

rclpy is required: if it cannot be imported the session errors out (it is not skipped);
``make setup`` installs it.
"""

import fcntl
import os
import pathlib
import socket
import sys
import tempfile

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
PROFILE = REPO_ROOT / 'config' / 'fastdds_loopback.xml'

# Fast DDS well-known ports (RTPS 2.x defaults): PB + DG * domain + offset + PG * participant.
_PB, _DG, _PG, _D0, _D1 = 7400, 250, 2, 0, 10


def _domain_in_use(domain_id, participants=4):
    """Return True if a Fast DDS participant of ``domain_id`` seems to run on this machine."""
    ports = [_PB + _DG * domain_id + _D0]
    ports += [_PB + _DG * domain_id + _D1 + _PG * p for p in range(participants)]
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind(('127.0.0.1', port))
            except OSError:
                return True
    return False


#: open lock files of the domains this process claimed (held until it exits)
_CLAIMS = {}


def _claim(domain_id):
    """
    Claim ``domain_id`` for this process with an exclusive lock file; False if it is taken.

    The ports of a domain are bound only once its first participant starts, so processes
    choosing at the same moment (the lanes' pytest-xdist workers, started together) could
    all see a domain free: two live tests shared one (a loop demo run's calibration
    reached the README test's corrector). The lock is the kernel's (``flock``): it goes with
    the process, however it ends.
    """
    if domain_id in _CLAIMS:            # this process's already: not a free one
        return False
    path = os.path.join(tempfile.gettempdir(), f'magcal_ros_domain_{domain_id}.lock')
    fh = open(path, 'a')
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        return False
    _CLAIMS[domain_id] = fh
    return True


def pick_domain_id(seed=None):
    """
    Return a ROS domain id in 1..101 free on this machine, starting from ``seed``.

    Free: no DDS ports of it bound and not claimed by another process of the suite
    (:func:`_claim`, which this call makes for the domain it returns).
    """
    start = (os.getpid() if seed is None else seed) % 101
    for k in range(101):
        domain_id = 1 + (start + k) % 101
        if not _domain_in_use(domain_id) and _claim(domain_id):
            return domain_id
    raise RuntimeError('every ROS domain id 1..101 has DDS ports bound on this machine; '
                       'stop stale ROS processes or set MAGCAL_TEST_ROS_DOMAIN_ID')


def _configure_ros_environment():
    if not PROFILE.is_file():
        raise RuntimeError(f'loopback DDS profile missing: {PROFILE}')
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(PROFILE)
    os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] = str(PROFILE)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'
    os.environ['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    os.environ.pop('ROS_STATIC_PEERS', None)
    forced = os.environ.get('MAGCAL_TEST_ROS_DOMAIN_ID')
    # pytest-xdist workers (gw0, gw1, ...) start side by side: each from its own PID, spread
    # by its index so that two never probe the same free domain at once
    # and the lanes of scripts/test_lanes.py (MAGCAL_TEST_LANE) start side by side too
    worker = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')[2:]
    lane = os.environ.get('MAGCAL_TEST_LANE', '0')
    seed = (os.getpid() + 31 * (int(worker) if worker.isdigit() else 0)
            + 43 * (int(lane) if lane.isdigit() else 0))
    os.environ['ROS_DOMAIN_ID'] = str(int(forced) if forced else pick_domain_id(seed))
    os.environ.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
    os.environ.setdefault('MPLBACKEND', 'Agg')


_configure_ros_environment()


def _limit_blas_threads():
    """Run BLAS as magcal's executables do (runtime.py): three workers on two cores."""
    from magcal_ros.runtime import limit_blas_threads
    limit_blas_threads()


_limit_blas_threads()

try:
    import rclpy  # noqa: E402,F401  (after the environment is set)
except ImportError as exc:  # a missing rclpy is a failure, never a skip
    raise ImportError(
        f'rclpy (ROS 2 Jazzy) cannot be imported by {sys.executable}: {exc}. '
        'Run `make setup` and the tests with `make test` (or .venv/bin/python -m pytest).'
    ) from exc

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / 'open_audit_site'))
import open_audit  # noqa: E402,I100  (files opened beside the repository fail the session)
import ros_helpers  # noqa: E402
from ros_helpers import (  # noqa: E402,F401  (fixtures registered for every test)
    make_node, ros_context, ros_executor, ros_namespace, ros_node, start_process)


def pytest_sessionstart(session):
    open_audit.pytest_sessionstart(session)


def pytest_report_header(config):
    return (f'ROS: domain {os.environ["ROS_DOMAIN_ID"]}, '
            f'{os.environ["RMW_IMPLEMENTATION"]}, profile {PROFILE}')


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    ros_helpers.attach_process_logs(item, outcome.get_result())


def pytest_sessionfinish(session, exitstatus):
    ros_helpers.stop_all_processes()
    open_audit.pytest_sessionfinish(session, exitstatus)


#: live files whose pipelines judge their own timing (sets lost, latency under a burst): the
#: main job at 4 x 100 Hz and the corrector's 4 x 1 kHz burst. Marked ``solo``: `make test`
#: runs them one at a time once the other live tests have ended (scripts/test_lanes.py);
#: beside another live pipeline the main job lost 2.4 % of its sets and the burst's median
#: latency was 149 ms against a bound of 31 (2026-11-27).
SOLO_FILES = frozenset({'test_demo.py', 'test_reliability_load.py'})

#: test files whose pipelines of ROS processes stream real-time data and judge it against the
#: noise: `make test` (scripts/test_lanes.py) runs them in the live lane, two at a time at
#: most, beside the rest (which runs on pytest-xdist workers at the idle CPU policy)
LIVE_FILES = frozenset({
    'test_calibration_node.py', 'test_calibration_residual.py', 'test_corrector_node.py',
    'test_demo.py', 'test_demo_loop.py', 'test_driver_node.py', 'test_e2e.py',
    'test_field_rate_live.py', 'test_geometry_e2e.py', 'test_geometry_nodes.py',
    'test_planar_node.py', 'test_reliability_calibration.py', 'test_reliability_driver.py',
    'test_reliability_load.py', 'test_ros_user.py', 'test_sim_node.py',
    'test_site_gradient_ros.py'})


def pytest_configure(config):
    config.addinivalue_line('markers', 'live: a live ROS pipeline judged against the noise '
                            '(conftest.LIVE_FILES, or marked one by one; `make test` runs '
                            'these in its live lane, two at a time at most)')
    config.addinivalue_line('markers', 'solo: a live pipeline that judges its own timing '
                            '(conftest.SOLO_FILES; `make test` runs these one at a time, '
                            'with no other live test beside them)')


#: the files that take longest, slowest first (wall time in `make test`, 2026-11-27: the loop
#: demo 179 s, test_workbench_loop 130 s ... test_interfaces 17 s). They are collected first
#: and, with ``--no-loadscope-reorder`` (scripts/test_lanes.py), handed to the xdist workers
#: first, so that the lanes do not end with one worker on a long file and the other idle:
#: pytest-xdist otherwise orders the files by their number of tests, which put flake8 and
#: the colcon build (one test each, 20 and 17 s) at the batch lane's very end
SLOWEST_FIRST = (
    'test_demo_loop.py', 'test_workbench_loop.py', 'test_discovery_cases.py',
    'test_bench_smoke.py', 'test_ros_user.py', 'test_reliability_persistence.py',
    'test_geometry_e2e.py', 'test_findings.py', 'test_attitude_aided.py',
    'test_learning.py', 'test_user_loop.py', 'test_demo_learn.py', 'test_magfit_compare.py',
    'test_calibration_node.py',
    'test_diagnose.py', 'test_planar_node.py', 'test_readme_commands.py',
    'test_diagnose_screen.py', 'test_long_records.py', 'test_import_boundaries.py',
    'test_live_pairing.py', 'test_reliability_driver.py', 'test_real_sunsided.py',
    'test_flake8.py', 'test_reliability_calibration.py', 'test_report.py',
    'test_interfaces.py')
_RANK = {name: k for k, name in enumerate(SLOWEST_FIRST)}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in LIVE_FILES:
            item.add_marker(pytest.mark.live)
        if item.path.name in SOLO_FILES:
            item.add_marker(pytest.mark.solo)
    # slowest files first, the rest in their order (a stable sort keeps each file's own)
    items[:] = sorted(items, key=lambda item: _RANK.get(item.path.name, len(_RANK)))
