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
Helpers and fixtures for magcal_ros's ROS tests (rclpy's own pattern, no launch_testing).

Import what you need in a test module::

    from ros_helpers import call_trigger, console_script, spin_until, wait_for_messages

The fixtures below are registered for every test by ``test/conftest.py``; use them by name:

``ros_context``
    A fresh, initialised :class:`rclpy.context.Context` per test (no signal handlers, so
    Ctrl+C still reaches pytest), shut down after the test.
``ros_executor``
    A :class:`~rclpy.executors.SingleThreadedExecutor` bound to ``ros_context``. Tests that
    need a ``MultiThreadedExecutor`` create one with ``context=ros_context``.
``ros_namespace``
    A namespace unique to the test (``/t_<test name>_<n>``), so tests never see each
    other's topics even when they share a domain.
``make_node``
    Factory ``make_node(NodeClass_or_name, *args, **kwargs)``: creates a node in
    ``ros_context`` (``context=`` is injected), adds it to ``ros_executor`` and destroys it
    after the test. A string creates a plain node in ``ros_namespace``.
``ros_node``
    A plain probe node in ``ros_namespace``, already added to ``ros_executor``.
``start_process``
    Factory ``start_process(cmd, name=None, env=None, cwd=None, ready=None,
    ready_timeout_sec=30.0)`` -> :class:`ManagedProcess`: runs ``cmd`` (a list, e.g.
    ``console_script('fluxgate_sim') + ['--rate', '50']`` or
    ``python_module('magcal_ros.cli', 'simulate')``) in a new session with the test
    session's ROS environment, output to ``<tmp_path>/<name>.log``. Stopped after the test
    (SIGINT, then SIGTERM, then SIGKILL); when the test fails, the tail of every log is added
    to the failure report.

Waiting is always bounded: :func:`spin_until` spins the executor until a predicate holds and
raises ``AssertionError`` naming what it waited for. Services are called with
``call_async`` plus spinning (:func:`call_trigger`), never with ``Client.call()``.
"""

import ctypes
import itertools
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import time
import weakref

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

#: Repository root (the directory holding package.xml).
REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]

#: Default bound for waits in these helpers, s.
DEFAULT_TIMEOUT_SEC = 10.0

_LOG_TAIL_CHARS = 20000
_PR_SET_PDEATHSIG = 1
try:
    _LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith('linux') else None
except OSError:   # pragma: no cover - no libc handle; processes then rely on the finalizers
    _LIBC = None

# Every ManagedProcess still alive, for the end-of-session safety net.
_LIVE_PROCESSES = weakref.WeakSet()
# Per-test list of processes (item.stash), read by conftest's report hook.
PROCESSES_KEY = pytest.StashKey()
_name_counter = itertools.count(1)


# -- waiting ----------------------------------------------------------------------------------

def _describe(predicate):
    return getattr(predicate, '__qualname__', None) or repr(predicate)


def spin_until(executor, predicate, timeout_sec=DEFAULT_TIMEOUT_SEC, message=None,
               period_sec=0.05):
    """
    Spin ``executor`` until ``predicate()`` is truthy; fail after ``timeout_sec``.

    Parameters
    ----------
    executor : rclpy.executors.Executor
        Executor holding the nodes whose callbacks must run.
    predicate : callable
        Called with no argument before each spin.
    timeout_sec : float, optional
        Upper bound on the wait, s.
    message : str, optional
        What is being waited for, used in the failure message.
    period_sec : float, optional
        Longest single ``spin_once`` wait, s.

    Returns
    -------
    object
        The predicate's (truthy) value, so ``msg = spin_until(ex, lambda: box.get('m'))``.

    Raises
    ------
    AssertionError
        If the predicate is still falsy at the deadline.

    """
    deadline = time.monotonic() + timeout_sec
    while True:
        value = predicate()
        if value:
            return value
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            raise AssertionError(
                f'timed out after {timeout_sec:.1f} s waiting for '
                f'{message or _describe(predicate)}')
        executor.spin_once(timeout_sec=min(period_sec, remaining))


def spin_for(executor, duration_sec):
    """Spin ``executor`` for ``duration_sec`` seconds (e.g. to check nothing arrives)."""
    deadline = time.monotonic() + duration_sec
    while (remaining := deadline - time.monotonic()) > 0.0:
        executor.spin_once(timeout_sec=min(0.05, remaining))


def _ensure_in_executor(node, executor):
    """Add ``node`` to ``executor`` if missing; return True when it was added here."""
    if node in executor.get_nodes():
        return False
    executor.add_node(node)
    return True


def wait_for_messages(node, executor, msg_type, topic, count=1,
                      timeout_sec=DEFAULT_TIMEOUT_SEC, qos=10, predicate=None):
    """
    Subscribe to ``topic`` and return the first ``count`` messages received.

    Parameters
    ----------
    node : rclpy.node.Node
        Node to subscribe with (added to ``executor`` for the wait if it is not in it).
    executor : rclpy.executors.Executor
        Executor to spin.
    msg_type : type
        Message class, e.g. ``sensor_msgs.msg.MagneticField``.
    topic : str
        Topic name (relative names resolve in the node's namespace).
    count : int, optional
        Number of messages to collect.
    timeout_sec : float, optional
        Upper bound on the wait, s.
    qos : int or rclpy.qos.QoSProfile, optional
        Subscription QoS (depth, or a profile such as ``qos_profile_sensor_data``).
    predicate : callable, optional
        Only messages for which ``predicate(msg)`` is true are kept.

    Returns
    -------
    list
        ``count`` messages in arrival order.

    Raises
    ------
    AssertionError
        If fewer than ``count`` messages arrive in time.

    """
    received = []

    def on_msg(msg):
        if predicate is None or predicate(msg):
            received.append(msg)

    sub = node.create_subscription(msg_type, topic, on_msg, qos)
    added = _ensure_in_executor(node, executor)
    try:
        spin_until(executor, lambda: len(received) >= count, timeout_sec,
                   message=f'{count} message(s) on {sub.topic_name}')
    finally:
        node.destroy_subscription(sub)
        if added:
            executor.remove_node(node)
    return received[:count]


def split_response(response):
    """(summary lines, JSON payload) of a node's Trigger response: a human summary, then JSON."""
    summary, _, payload = response.message.partition('\n{')
    return summary.splitlines(), json.loads('{' + payload)


#: spin time after a new client sees its server, before the first request (see call_trigger)
DISCOVERY_GRACE_S = 0.3

# node -> {resolved service name: [client, reply writers of the server that last answered]}
_TRIGGER_CLIENTS = weakref.WeakKeyDictionary()


def _reply_writers(node, full_name):
    """Return the GIDs of the response writers of service ``full_name`` (the servers)."""
    infos = node.get_publishers_info_by_topic(f'rr{full_name}Reply', no_mangle=True)
    return frozenset(bytes(info.endpoint_gid) for info in infos)


def call_trigger(node, executor, service_name, timeout_sec=30.0):
    """
    Call a ``std_srvs/srv/Trigger`` service with ``call_async`` and bounded spinning.

    The client is kept for the next call of the same service from the same node. A new
    client, or one whose server is not the one that answered it last (another response
    writer, e.g. a restarted node), first spins :data:`DISCOVERY_GRACE_S`; a client its
    server has answered before is matched both ways already and calls at once.

    Parameters
    ----------
    node : rclpy.node.Node
        Node that creates the client (added to ``executor`` for the call if missing).
    executor : rclpy.executors.Executor
        Executor to spin; it must also run the server if the server is in this process.
    service_name : str
        Service name (relative names resolve in the node's namespace).
    timeout_sec : float, optional
        Upper bound for the service to appear plus the call to complete, s.

    Returns
    -------
    std_srvs.srv.Trigger.Response
        The response (``success``, ``message``); the caller checks ``success``.

    Raises
    ------
    AssertionError
        If the service does not appear or does not answer in time.

    """
    deadline = time.monotonic() + timeout_sec
    full_name = node.resolve_service_name(service_name)
    clients = _TRIGGER_CLIENTS.setdefault(node, {})
    if full_name not in clients:
        clients[full_name] = [node.create_client(Trigger, service_name), None]
    entry = clients[full_name]
    client = entry[0]
    added = _ensure_in_executor(node, executor)
    try:
        spin_until(executor, client.service_is_ready, timeout_sec,
                   message=f'service {full_name} to become available')
        writers = _reply_writers(node, full_name)
        if not writers or writers != entry[1]:
            # The client sees the server before the server has discovered the client's
            # response reader; Fast DDS's server waits only 100 ms for it and then drops the
            # response ("failed to send response (timeout)"). A short spin lets discovery
            # finish both ways.
            grace = time.monotonic() + DISCOVERY_GRACE_S
            while time.monotonic() < grace:
                executor.spin_once(timeout_sec=0.05)
        future = client.call_async(Trigger.Request())
        spin_until(executor, future.done, max(deadline - time.monotonic(), 0.1),
                   message=f'the response of {full_name}')
        exc = future.exception()
        if exc is not None:
            raise exc
        entry[1] = writers
        return future.result()
    finally:
        if added:
            executor.remove_node(node)


# -- processes --------------------------------------------------------------------------------

def subprocess_env(extra=None):
    """
    Return the environment for a child process of the tests.

    It is this process's environment (so the loopback DDS profile, RMW and ROS_DOMAIN_ID set
    by conftest are inherited), with unbuffered Python output, no colour codes in ROS logs,
    the repository first on ``PYTHONPATH`` (so ``python -m magcal_ros...`` works without an
    install), and ``extra`` applied last (a value of None removes the variable).
    """
    env = dict(os.environ)
    env['PYTHONUNBUFFERED'] = '1'
    env['RCUTILS_COLORIZED_OUTPUT'] = '0'
    env.setdefault('MPLBACKEND', 'Agg')
    paths = [str(REPO_ROOT)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p]
    env['PYTHONPATH'] = os.pathsep.join(dict.fromkeys(paths))
    for key, value in (extra or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = str(value)
    return env


def _entry_points_from_setup_py():
    text = (REPO_ROOT / 'setup.py').read_text(encoding='utf-8')
    return {m.group(1): (m.group(2), m.group(3)) for m in re.finditer(
        r"'\s*([A-Za-z0-9_]+)\s*=\s*([A-Za-z0-9_.]+):([A-Za-z0-9_]+)\s*'", text)}


def console_script(name):
    """
    Return the command (list) that runs the console script ``name``.

    The installed script next to this interpreter (``.venv/bin/<name>`` after ``make setup``)
    is preferred, so tests run what a user runs. Without an install, the entry point from
    setup.py is called through this interpreter.

    Raises
    ------
    ValueError
        If ``name`` is not a console script of setup.py.

    """
    installed = pathlib.Path(sys.executable).parent / name
    if installed.is_file() and os.access(installed, os.X_OK):
        return [str(installed)]
    entry_points = _entry_points_from_setup_py()
    if name not in entry_points:
        raise ValueError(f'{name!r} is not a console script of setup.py '
                         f'(known: {sorted(entry_points)})')
    module, func = entry_points[name]
    code = f'import sys; from {module} import {func}; sys.exit({func}())'
    return [sys.executable, '-c', code]


def python_module(module, *args):
    """Return the command (list) ``python -m module args...`` with this interpreter."""
    return [sys.executable, '-m', module, *map(str, args)]


def _die_with_parent():
    # Runs in the child between fork and exec: SIGTERM it if the test process dies, so a
    # crashed or killed pytest leaves no node running (Linux only).
    if _LIBC is not None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class ManagedProcess:
    """
    A child process in its own session, output in a log file, stopped by escalation.

    Parameters
    ----------
    cmd : list of str
        Command and arguments.
    log_path : str or pathlib.Path
        File receiving stdout and stderr (overwritten).
    name : str, optional
        Label for reports; defaults to the command's base name.
    env : dict, optional
        Full environment; defaults to :func:`subprocess_env`.
    cwd : str or pathlib.Path, optional
        Working directory.

    Attributes
    ----------
    popen : subprocess.Popen
    name : str
    log_path : pathlib.Path
    signals_sent : list of str
        Signals :meth:`stop` had to send ('SIGINT', 'SIGTERM', 'SIGKILL').

    """

    def __init__(self, cmd, log_path, name=None, env=None, cwd=None):
        self.cmd = [str(c) for c in cmd]
        self.name = name or pathlib.Path(self.cmd[0]).name
        self.log_path = pathlib.Path(log_path)
        self.signals_sent = []
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, 'wb') as log:
            self.popen = subprocess.Popen(
                self.cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                env=subprocess_env() if env is None else env, cwd=cwd,
                start_new_session=True, preexec_fn=_die_with_parent)
        _LIVE_PROCESSES.add(self)

    @property
    def pid(self):
        """Process id (also the process-group id)."""
        return self.popen.pid

    @property
    def returncode(self):
        """Exit status, None while running (negative: killed by that signal)."""
        return self.popen.poll()

    def running(self):
        """Return True while the process has not exited."""
        return self.popen.poll() is None

    def read_log(self):
        """Return everything the process printed so far (stdout and stderr)."""
        try:
            return self.log_path.read_text(encoding='utf-8', errors='replace')
        except FileNotFoundError:
            return ''

    def log_tail(self, max_chars=_LOG_TAIL_CHARS):
        """Return the last ``max_chars`` characters of the log."""
        text = self.read_log()
        return text if len(text) <= max_chars else '...\n' + text[-max_chars:]

    def wait_for_log(self, pattern, timeout_sec=30.0):
        """
        Wait until the log matches regex ``pattern``; return the match.

        Raises
        ------
        AssertionError
            If the process exits first or the pattern does not appear in time; the message
            includes the log tail.

        """
        regex = re.compile(pattern, re.MULTILINE)
        deadline = time.monotonic() + timeout_sec
        while True:
            match = regex.search(self.read_log())
            if match:
                return match
            if not self.running():
                raise AssertionError(
                    f'{self.name} exited with {self.returncode} before printing '
                    f'{pattern!r}; log:\n{self.log_tail(4000)}')
            if time.monotonic() > deadline:
                raise AssertionError(
                    f'{self.name} did not print {pattern!r} within {timeout_sec:.1f} s; '
                    f'log:\n{self.log_tail(4000)}')
            time.sleep(0.05)

    def wait(self, timeout_sec):
        """Wait for the process to exit; return its exit status, None on timeout."""
        try:
            return self.popen.wait(timeout=timeout_sec)
        except subprocess.TimeoutExpired:
            return None

    def _signal_group(self, sig):
        try:
            os.killpg(self.popen.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def stop(self, sigint_timeout_sec=5.0, sigterm_timeout_sec=3.0):
        """
        Stop the process: SIGINT, then SIGTERM, then SIGKILL, each to its process group.

        Safe to call more than once. Leftover members of the group (children the process
        started) are killed once the process itself has exited.

        Returns
        -------
        int
            Exit status (0 after a clean shutdown on SIGINT; negative if killed by a signal).

        """
        for sig, wait_sec in ((signal.SIGINT, sigint_timeout_sec),
                              (signal.SIGTERM, sigterm_timeout_sec),
                              (signal.SIGKILL, 10.0)):
            if not self.running():
                break
            self.signals_sent.append(sig.name)
            self._signal_group(sig)
            self.wait(wait_sec)
        self._signal_group(signal.SIGKILL)
        _LIVE_PROCESSES.discard(self)
        return self.popen.wait()

    def describe(self):
        """One line: name, pid, state, signals needed, log path."""
        code = self.returncode
        state = 'running' if code is None else f'exit {code}'
        sent = f', signals sent {self.signals_sent}' if self.signals_sent else ''
        return f'{self.name} (pid {self.pid}, {state}{sent}), log {self.log_path}'

    def __repr__(self):
        return f'<ManagedProcess {self.describe()}>'


def run_concurrently(commands, timeout_sec=60.0, max_running=None, cwd=None):
    """
    Run independent short-lived commands side by side; return each one's result.

    For tests that start one process per case and only read how it ended (exit status and
    output): the processes are the same as with :func:`subprocess.run`, one per command, but
    up to ``max_running`` of them run at once, so the cores are not idle while each one
    imports its modules. Not for commands that compute (fits, benchmarks): numpy's OpenBLAS
    runs a thread per core in each process, and side by side they were slower than one
    after the other (test_cli's exit codes 5.3 s -> 8.9 s).

    Parameters
    ----------
    commands : dict
        ``key -> (cmd, env)``: the command (list) and its full environment (None: this
        process's); stdin is closed.
    timeout_sec : float, optional
        Bound on each process, counted from its own start, s.
    max_running : int, optional
        Most processes at once; default the number of CPUs plus one.
    cwd : str or pathlib.Path, optional
        Working directory of every process.

    Returns
    -------
    dict
        ``key -> subprocess.CompletedProcess`` with text ``stdout`` and ``stderr``.

    Raises
    ------
    subprocess.TimeoutExpired
        If a process outlives ``timeout_sec`` (every process still running is killed).

    """
    import tempfile
    limit = max_running or (os.cpu_count() or 1) + 1
    waiting = list(commands.items())
    running = {}                    # key -> (Popen, deadline, stdout file, stderr file)
    results = {}
    try:
        while waiting or running:
            while waiting and len(running) < limit:
                key, (cmd, env) = waiting.pop(0)
                out, err = tempfile.TemporaryFile(), tempfile.TemporaryFile()
                proc = subprocess.Popen([str(c) for c in cmd], stdin=subprocess.DEVNULL,
                                        stdout=out, stderr=err, env=env, cwd=cwd,
                                        preexec_fn=_die_with_parent)
                running[key] = (proc, time.monotonic() + timeout_sec, out, err)
            for key, (proc, deadline, out, err) in list(running.items()):
                if proc.poll() is None:
                    if time.monotonic() > deadline:
                        raise subprocess.TimeoutExpired(proc.args, timeout_sec)
                    continue
                texts = []
                for f in (out, err):
                    f.seek(0)
                    texts.append(f.read().decode('utf-8', errors='replace'))
                    f.close()
                results[key] = subprocess.CompletedProcess(proc.args, proc.returncode, *texts)
                del running[key]
            time.sleep(0.01)
    finally:
        for proc, _, out, err in running.values():
            proc.kill()
            proc.wait()
            out.close()
            err.close()
    return results


def stop_all_processes():
    """Stop every :class:`ManagedProcess` still running (end-of-session safety net)."""
    for proc in list(_LIVE_PROCESSES):
        proc.stop(sigint_timeout_sec=2.0, sigterm_timeout_sec=2.0)


def attach_process_logs(item, report):
    """Add the log tail of each process the test started to a failed ``report``."""
    if not report.failed:
        return
    for proc in item.stash.get(PROCESSES_KEY, []):
        report.sections.append((f'process {proc.describe()}', proc.log_tail()))


# -- bound sockets (loopback checks) ----------------------------------------------------------

def _hex_ip(hex_addr):
    raw = bytes.fromhex(hex_addr)
    if len(raw) == 4:
        return '.'.join(str(b) for b in raw[::-1])
    words = [raw[i:i + 4][::-1] for i in range(0, 16, 4)]
    return ':'.join(b''.join(words)[i:i + 2].hex() for i in range(0, 16, 2))


def bound_inet_sockets(pid):
    """
    List the IPv4/IPv6 sockets of process ``pid`` with their local address (Linux /proc).

    Parameters
    ----------
    pid : int
        Process id.

    Returns
    -------
    list of tuple
        ``(protocol, local_ip, local_port)`` with protocol in ``udp, udp6, tcp, tcp6``;
        IPv6 addresses as eight uncompressed hex groups.

    """
    inodes = set()
    fd_dir = pathlib.Path(f'/proc/{pid}/fd')
    for fd in fd_dir.iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith('socket:['):
            inodes.add(target[8:-1])
    sockets = []
    for proto in ('udp', 'udp6', 'tcp', 'tcp6'):
        table = pathlib.Path(f'/proc/{pid}/net/{proto}')
        if not table.exists():
            continue
        for line in table.read_text().splitlines()[1:]:
            fields = line.split()
            if len(fields) > 9 and fields[9] in inodes:
                ip_hex, port_hex = fields[1].split(':')
                sockets.append((proto, _hex_ip(ip_hex), int(port_hex, 16)))
    return sockets


# -- fixtures (registered in conftest.py) -----------------------------------------------------

@pytest.fixture
def ros_context():
    """Provide a fresh initialised rclpy Context for one test; shut it down afterwards."""
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


@pytest.fixture
def ros_executor(ros_context):
    """Provide a SingleThreadedExecutor bound to ``ros_context``."""
    executor = SingleThreadedExecutor(context=ros_context)
    try:
        yield executor
    finally:
        executor.shutdown(timeout_sec=5.0)


@pytest.fixture
def ros_namespace(request):
    """
    Return a namespace unique to this test and process, e.g. ``/t_test_corrector_3_p4711``.

    The process id keeps two test runs apart even when their ROS_DOMAIN_IDs (PID-derived,
    scripts/ros_env.sh) collide: the same test of two runs never shares topics.
    """
    stem = re.sub(r'[^A-Za-z0-9]+', '_', request.node.name).strip('_')[:60].strip('_')
    return f'/t_{stem}_{next(_name_counter)}_p{os.getpid()}'


@pytest.fixture
def make_node(ros_context, ros_executor, ros_namespace):
    """Return a factory creating nodes in ``ros_context``, spun by ``ros_executor``."""
    nodes = []

    def _make(factory, *args, **kwargs):
        if isinstance(factory, str):
            kwargs.setdefault('namespace', ros_namespace)
            node = rclpy.create_node(factory, *args, context=ros_context, **kwargs)
        else:
            kwargs.setdefault('context', ros_context)
            node = factory(*args, **kwargs)
            if not isinstance(node, Node):
                raise ValueError(f'make_node: {factory!r} did not return an rclpy Node')
        ros_executor.add_node(node)
        nodes.append(node)
        return node

    yield _make
    for node in reversed(nodes):
        ros_executor.remove_node(node)
        node.destroy_node()


@pytest.fixture
def ros_node(make_node):
    """Provide a plain node ``test_probe`` in ``ros_namespace``, added to ``ros_executor``."""
    return make_node('test_probe')


@pytest.fixture
def start_process(request, tmp_path):
    """Return a factory starting managed child processes, each stopped after the test."""
    procs = request.node.stash.setdefault(PROCESSES_KEY, [])

    def _start(cmd, name=None, env=None, cwd=None, ready=None, ready_timeout_sec=30.0):
        label = name or pathlib.Path(str(cmd[0])).name
        stem = re.sub(r'[^A-Za-z0-9_.-]+', '_', label)
        proc = ManagedProcess(cmd, tmp_path / f'{stem}_{len(procs) + 1}.log', name=label,
                              env=env, cwd=cwd)
        procs.append(proc)
        request.addfinalizer(proc.stop)
        if ready is not None:
            proc.wait_for_log(ready, ready_timeout_sec)
        return proc

    return _start
