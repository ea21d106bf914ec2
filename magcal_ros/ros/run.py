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
The one ``main`` of every node: init, spin until SIGINT/SIGTERM, clean shutdown, exit codes.

rclpy's own signal handler shuts the context down while a callback may still run (a
traceback and exit 1 on Ctrl-C, issue 12). Here SIGINT and SIGTERM only set a flag: the
executor finishes its callback, stops within :data:`SPIN_PERIOD_S`, the node is destroyed,
then the context; exit 0. Bad start-up input (a ``--ros-args`` rule rcl cannot parse, an
override of the wrong type such as ``-p field_nt:=48000``, a value a validator refuses) is
one line on stderr and exit 2.
"""
from contextlib import contextmanager, suppress
import os
import signal
import sys
import tempfile
import threading
from types import SimpleNamespace

from magcal_ros.runtime import limit_blas_threads
from magcal_ros.sim import DEFAULT_NAMESPACE  # noqa: F401 (the nodes' default namespace)
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions

#: longest time between a SIGINT/SIGTERM and the end of the spin loop when idle, s
SPIN_PERIOD_S = 0.1

#: environment variable choosing the executor: ``events`` (default where rclpy has it) or
#: ``single`` (rclpy's SingleThreadedExecutor)
EXECUTOR_VARIABLE = 'MAGCAL_EXECUTOR'
#: niceness added to the solve threads, so that the sample intake, the driver and the
#: corrector keep the CPU they need on a loaded machine
SOLVE_NICENESS = 5


def yield_cpu():
    """Lower the calling thread's CPU priority by :data:`SOLVE_NICENESS` (Linux; else no-op)."""
    if not sys.platform.startswith('linux'):   # elsewhere a tid is not a PRIO_PROCESS id
        return
    with suppress(OSError):
        tid = threading.get_native_id()
        now = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, now + SOLVE_NICENESS))


def make_executor(events=True, context=None):
    """
    Return the executor a node spins on, and its name (``'events'`` or ``'single'``).

    rclpy's EventsExecutor (``rclpy.experimental``, a third of the SingleThreadedExecutor's
    CPU per message: bench/executor.py) unless ``events`` is False (a node it cannot run: in
    Jazzy no coroutine callbacks), ``MAGCAL_EXECUTOR=single`` or rclpy lacks it.
    ``context``: the nodes' rclpy context (None: the default).
    """
    choice = os.environ.get(EXECUTOR_VARIABLE, 'events').strip().lower()
    if choice not in ('events', 'single'):
        raise ValueError(f'{EXECUTOR_VARIABLE}={choice!r}: use events or single')
    if choice == 'events' and events:
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            pass
        else:
            return EventsExecutor(context=context), 'events'
    return SingleThreadedExecutor(context=context), 'single'


def _one_line(exc):
    """Return the first line of an exception's message (rcl appends C file positions)."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.split(', at /')[0]


@contextmanager
def _stderr_held():
    """Hold what C code writes to fd 2 in ``.text`` (rcl logs its own copy of a parse error)."""
    held = SimpleNamespace(text='')
    sys.stderr.flush()
    with tempfile.TemporaryFile(mode='w+b') as file:
        saved = os.dup(2)
        os.dup2(file.fileno(), 2)
        try:
            yield held
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            file.seek(0)
            held.text = file.read().decode('utf-8', 'replace')


def spin_node(node_cls, name, args=None, events=True):
    """
    Create ``node_cls()``, spin it until SIGINT/SIGTERM or shutdown, clean up; return 0 or 2.

    ``node_cls``: a Node subclass (or a partial of one) that sets its default namespace
    (:data:`DEFAULT_NAMESPACE`); its ``finished`` event, if any, ends the spin when set.
    ``name``: the executable, in error messages; ``args``: the command line (None:
    ``sys.argv``); ``events``: as :func:`make_executor`. 2 is bad start-up input.
    """
    stop = threading.Event()
    limit_blas_threads()              # small linear algebra: BLAS threads only contend
    try:
        with _stderr_held() as held:
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except _rclpy.RCLError as exc:        # e.g. '-p field_nt' without ':=value'
        print(f'{name}: bad command line: {_one_line(exc)}', file=sys.stderr)
        return 2
    sys.stderr.write(held.text)
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        node = node_cls()
    except (ValueError, ParameterException) as exc:
        print(f'{name}: bad parameters: {_one_line(exc)}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        executor, _ = make_executor(events)
    except ValueError as exc:
        print(f'{name}: bad environment: {exc}', file=sys.stderr)
        node.destroy_node()
        rclpy.try_shutdown()
        return 2
    executor.add_node(node)
    try:
        finished = getattr(node, 'finished', None) or threading.Event()
        while not stop.is_set() and not finished.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_PERIOD_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
