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

Shutdown: rclpy's own signal handler shuts the context down from inside the signal, while a
callback may still be running; that callback's next ``publish`` then raises "publisher's
context is invalid" and a waiting executor "take_message" errors, i.e. a traceback and exit 1
on an ordinary Ctrl-C (issue 12). Here rclpy installs no signal handler: SIGINT and SIGTERM
only set a flag, the executor finishes the callback it is running, stops within
:data:`SPIN_PERIOD_S`, the node is destroyed (its threads stopped) while the context is
still valid, and only then the context is shut down. Exit status 0.

Bad start-up input is a user error, reported as one line on stderr with exit status 2 (as
the README promises): a ``--ros-args`` rule rcl cannot parse, a parameter override of the
wrong type (``-p field_nt:=48000``, an integer for a double; ``:=abc``), or a value the
node's validators refuse.
"""
import os
import signal
import sys
import tempfile
import threading

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


#: niceness added to the solve thread (calibrate, diagnose): on a loaded machine the sample
#: intake of this node, and the driver and corrector beside it, keep the CPU they need
#: while a solve takes what is left (a diagnosis beside a 4 x 1 kHz stream starved it)
SOLVE_NICENESS = 5


def yield_cpu():
    """Lower the calling thread's CPU priority by :data:`SOLVE_NICENESS` (Linux; else no-op)."""
    if not sys.platform.startswith('linux'):   # elsewhere a tid is not a PRIO_PROCESS id
        return
    try:
        tid = threading.get_native_id()
        now = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, now + SOLVE_NICENESS))
    except OSError:
        pass


def make_executor(events=True, context=None):
    """
    Return the executor a node spins on, and its name (``'events'`` or ``'single'``).

    rclpy's EventsExecutor (``rclpy.experimental``, in Jazzy's rclpy 7.1) dispatches from a
    C++ event queue; the SingleThreadedExecutor rebuilds its wait set in Python on every
    spin, which cost 3 x the CPU per message (bench/executor.py: 4 topics at 200 Hz, 220
    against 72 us per message). ``events=False`` for a node the EventsExecutor cannot run:
    in Jazzy it takes neither guard conditions nor coroutine (``async def``) callbacks, and
    the calibration node's services are coroutines. ``MAGCAL_EXECUTOR=single`` chooses the
    classic executor for every node; an rclpy without the EventsExecutor gets it too.
    ``context``: the rclpy context of the nodes it will spin (None: the default one).
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


class _stderr_held:
    """
    Hold what C code writes to file descriptor 2 (rcl logs its own copy of a parse error).

    ``text`` is what was written; the caller shows it only when it is not replacing it by
    its one-line message.
    """

    def __enter__(self):
        sys.stderr.flush()
        self._file = tempfile.TemporaryFile(mode='w+b')
        self._saved = os.dup(2)
        os.dup2(self._file.fileno(), 2)
        self.text = ''
        return self

    def __exit__(self, *exc):
        sys.stderr.flush()
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode('utf-8', 'replace')
        self._file.close()
        return False


def spin_node(node_cls, name, args=None, events=True):
    """
    Create ``node_cls()``, spin it until SIGINT/SIGTERM or shutdown, and clean up.

    Parameters
    ----------
    node_cls : callable
        A ``rclpy.node.Node`` subclass (or a partial of one) called with no argument; it
        sets its default namespace itself (:data:`DEFAULT_NAMESPACE`), which a ``__ns``
        remap overrides. A node with a ``finished`` event (``threading.Event``) ends the
        spin when it is set, as after a signal.
    name : str
        Executable name used in error messages.
    args : list of str, optional
        Command line (``sys.argv`` when None).
    events : bool
        Spin on the EventsExecutor where rclpy has it (:func:`make_executor`).

    Returns
    -------
    int
        0 after a signal or an external shutdown, 2 for bad start-up input.

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
        # a node may end its own run (fluxgate_sim after its duration): ``finished`` set
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
