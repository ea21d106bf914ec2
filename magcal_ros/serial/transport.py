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
Serial transport: a reconnecting pyserial reader thread and a pseudo-terminal device.

:class:`PortReader` reads one port into a parser, hands each sample to a callback with its
arrival time, and reopens a lost device with exponential backoff (also at alternative
paths).  :class:`PtyDevice` plays the device on a pseudo-terminal, with
:meth:`~PtyDevice.unplug` and :meth:`~PtyDevice.replug` for a cable pulled and put back.
"""
import collections
import contextlib
from dataclasses import dataclass
import fcntl
import glob
import logging
import os
import termios
import threading
import time
import tty

from magcal_ros.serial.base import check_positive
import serial

_LOG = logging.getLogger(__name__)

# realpath -> id of the PortReader of this process that has it open (never two on one)
_CLAIMED = {}
_CLAIMED_LOCK = threading.Lock()

STATE_CONNECTING = 'connecting'
STATE_OPEN = 'open'
STATE_BACKOFF = 'backoff'
STATE_STOPPED = 'stopped'


@dataclass(frozen=True)
class PortStats:
    """
    Snapshot of a :class:`PortReader`.

    ``path`` the one open (None when closed); ``state`` 'connecting', 'open', 'backoff' or
    'stopped'; ``rate_hz`` samples/s over the last ``rate_window`` s; ``parse_errors``,
    ``errors``, ``bytes_dropped`` the parser's; ``callback_errors`` exceptions of the
    callback (logged); ``last_error`` '' if none; ``seconds_since_data`` None before data.
    """

    name: str
    port: str
    path: str | None
    state: str
    rate_hz: float
    samples: int
    bytes_in: int
    parse_errors: int
    errors: dict
    bytes_dropped: int
    reconnects: int
    disconnects: int
    open_failures: int
    callback_errors: int
    last_error: str
    seconds_since_data: float | None


class PortReader:
    """
    Background thread reading one serial port into a parser, reconnecting on loss.

    ``port`` the device path, ``baudrate`` bit/s; ``parser`` a :class:`~magcal_ros.serial.Parser`
    (its ``start_command`` written after every open, ``stop_command`` before a clean close);
    ``callback(sample, arrival_time)``, the ``clock()`` (s) when its bytes arrived;
    ``alternatives`` glob patterns of other paths; ``timeout`` of a read, s; ``backoff_min``,
    ``backoff_max`` the waits between reopens, s; ``serial_factory`` as ``serial.Serial``.
    """

    def __init__(self, port, baudrate, parser, callback, *, alternatives=(), timeout=0.05,
                 backoff_min=0.1, backoff_max=5.0, name=None, rate_window=2.0,
                 serial_factory=None, clock=time.time):
        if not isinstance(port, str) or not port:
            raise ValueError(f'port must be a non-empty device path, got {port!r}')
        try:
            baud = int(baudrate)
        except (TypeError, ValueError):
            baud = 0
        if baud <= 0 or baud != baudrate:
            raise ValueError(f'baudrate must be a positive integer (bit/s), got {baudrate!r}')
        if not callable(callback):
            raise ValueError('callback must be callable as callback(sample, arrival_time)')
        if isinstance(alternatives, str):
            alternatives = [alternatives]
        self.port = port
        self.baudrate = baud
        self.parser = parser
        self.callback = callback
        self.alternatives = tuple(str(a) for a in alternatives)
        self.timeout = check_positive('timeout', timeout, 'number of seconds')
        self.backoff_min = check_positive('backoff_min', backoff_min, 'number of seconds')
        self.backoff_max = check_positive('backoff_max', backoff_max, 'number of seconds')
        if self.backoff_max < self.backoff_min:
            raise ValueError(f'backoff_max ({backoff_max}) must be >= backoff_min '
                             f'({backoff_min})')
        self.rate_window = check_positive('rate_window', rate_window, 'number of seconds')
        self.name = name or port
        self._factory = serial_factory or serial.Serial
        self._clock = clock
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = self._path = self._last_data = self._rate_origin = None
        self._state = STATE_CONNECTING
        self._samples = self._bytes = self._reconnects = self._disconnects = 0
        self._open_failures = self._callback_errors = 0
        self._last_error = ''
        self._ever_opened = False
        self._arrivals = collections.deque()   # (arrival time, samples) within rate_window

    # -- public ----------------------------------------------------------------------
    def start(self):
        """Start the reader thread (returns immediately); returns self."""
        if self._thread is not None:
            raise RuntimeError(f'PortReader {self.name} already started')
        self._thread = threading.Thread(target=self._run, name=f'PortReader-{self.name}',
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout=2.0):
        """Stop the thread, write the parser's stop command if open, close the port."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._state = STATE_STOPPED

    @property
    def running(self):
        """Tell whether the reader thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def stats(self):
        """Return a :class:`PortStats` snapshot (thread safe)."""
        now = self._clock()
        with self._lock:
            pstats = self.parser.stats.copy()
            self._prune(now)
            in_window = sum(n for _, n in self._arrivals)
            rate = 0.0 if self._rate_origin is None else in_window / min(
                self.rate_window, max(now - self._rate_origin, 1e-3))
            return PortStats(
                name=self.name, port=self.port, path=self._path, state=self._state,
                rate_hz=rate, samples=self._samples, bytes_in=self._bytes,
                parse_errors=pstats.total_errors, errors=dict(pstats.errors),
                bytes_dropped=pstats.bytes_dropped, reconnects=self._reconnects,
                disconnects=self._disconnects, open_failures=self._open_failures,
                callback_errors=self._callback_errors, last_error=self._last_error,
                seconds_since_data=None if self._last_data is None else now - self._last_data)

    # -- thread ----------------------------------------------------------------------
    def _prune(self, now):
        while self._arrivals and self._arrivals[0][0] < now - self.rate_window:
            self._arrivals.popleft()

    def _candidates(self):
        found = [p for pattern in self.alternatives for p in sorted(glob.glob(pattern))]
        return list(dict.fromkeys([self.port] + found))       # in order, without repeats

    def _open(self):
        """Try every candidate path; return (serial object, path, realpath) or None."""
        for path in self._candidates():
            real = os.path.realpath(path)
            with _CLAIMED_LOCK:
                if _CLAIMED.setdefault(real, id(self)) != id(self):
                    continue                    # open by another reader of this process
            try:
                ser = self._factory(path, self.baudrate, timeout=self.timeout)
            except (serial.SerialException, OSError, ValueError) as exc:
                self._release(real)
                self._open_failures += 1
                self._last_error = f'open {path}: {exc}'
                continue
            return ser, path, real
        return None

    def _release(self, real):
        with _CLAIMED_LOCK:
            if _CLAIMED.get(real) == id(self):
                del _CLAIMED[real]

    def _run(self):
        delay = self.backoff_min
        logged = None           # the open error last logged (each new one is logged once)
        while not self._stop.is_set():
            self._state = STATE_CONNECTING
            opened = self._open()
            if opened is None:
                if self._last_error != logged and not self._stop.is_set():
                    logged = self._last_error
                    _LOG.warning('%s: cannot %s; retrying every %g s at most',
                                 self.name, logged or f'open {self.port}: no free candidate path',
                                 self.backoff_max)
            else:
                ser, path, real = opened
                with self._lock:
                    self.parser.reset()  # partial frames and the device clock: the old link's
                    self._path = path
                    self._reconnects += self._ever_opened
                    self._ever_opened = True
                    self._rate_origin = self._clock()
                    self._arrivals.clear()
                _LOG.info('%s: opened %s', self.name, path)
                logged = None
                if self._serve(ser):
                    delay = self.backoff_min
                self._close(ser, real)
            if opened is None or not self._stop.is_set():
                self._state = STATE_BACKOFF
                self._stop.wait(delay)
                delay = min(2.0 * delay, self.backoff_max)
        self._state = STATE_STOPPED

    def _serve(self, ser):
        """Read until stop or error; return True if any data arrived."""
        got_data = False
        try:
            if self.parser.start_command:
                ser.write(self.parser.start_command)
            self._state = STATE_OPEN
            while not self._stop.is_set():
                data = ser.read(max(1, ser.in_waiting))
                if not data:
                    continue
                arrival = self._clock()
                got_data = True
                with self._lock:
                    samples = self.parser.feed(data)
                    self._bytes += len(data)
                    self._samples += len(samples)
                    self._last_data = arrival
                    if samples:
                        self._arrivals.append((arrival, len(samples)))
                        self._prune(arrival)
                for sample in samples:
                    self._deliver(sample, arrival)
            if self.parser.stop_command:
                ser.write(self.parser.stop_command)
        except (serial.SerialException, OSError, termios.error) as exc:
            with self._lock:
                self._disconnects += 1
                self._last_error = f'{self._path}: {exc}'
            if not self._stop.is_set():         # not the close of a deliberate stop
                _LOG.warning('%s: lost %s (%s); reopening with backoff', self.name,
                             self._path, exc)
        return got_data

    def _deliver(self, sample, arrival):
        try:
            self.callback(sample, arrival)
        except Exception:  # noqa: B902 - the reader thread must survive a faulty callback
            self._callback_errors += 1
            _LOG.exception('%s: sample callback failed', self.name)

    def _close(self, ser, real):
        try:
            ser.close()
        except (serial.SerialException, OSError, termios.error) as exc:
            _LOG.debug('%s: close failed: %s', self.name, exc)
        self._release(real)
        with self._lock:
            self._path = None


def _atomic_symlink(target, link_path):
    """Point ``link_path`` at ``target`` atomically, replacing a stale symlink."""
    if os.path.lexists(link_path) and not os.path.islink(link_path):
        raise ValueError(f'{link_path} exists and is not a symlink; refusing to replace it')
    directory = os.path.dirname(os.path.abspath(link_path))
    os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f'.{os.path.basename(link_path)}.{os.getpid()}.tmp')
    if os.path.lexists(tmp):
        os.unlink(tmp)
    os.symlink(target, tmp)
    os.replace(tmp, link_path)


class PtyDevice:
    """
    A simulated serial device on a raw-mode pseudo-terminal, thread safe.

    The slave is symlinked to ``link_path`` (a stale symlink replaced, another file refused).
    :meth:`write` never blocks: with nobody reading, unread output is flushed (counted in
    :attr:`flushes`); bytes written while unplugged count in :attr:`bytes_dropped`.
    """

    def __init__(self, link_path=None):
        self._lock = threading.RLock()   # write/read vs unplug/replug from other threads
        self.link_path = link_path
        self.master = self.slave = self.slave_name = None
        self.bytes_written = self.bytes_dropped = self.flushes = self.plug_count = 0
        self.plug()

    @property
    def plugged(self):
        """Tell whether the pseudo-terminal exists."""
        return self.master is not None

    @property
    def path(self):
        """Return the path a reader should open (the link, or the slave name without one)."""
        return self.link_path or self.slave_name

    def plug(self, link_path=None):
        """Create a new pseudo-terminal (and link); ``link_path`` overrides the path."""
        with self._lock:
            if self.plugged:
                raise RuntimeError('PtyDevice is already plugged; call unplug() first')
            if link_path is not None:
                self.link_path = link_path
            master, slave = os.openpty()
            try:
                tty.setraw(slave)
                flags = fcntl.fcntl(master, fcntl.F_GETFL)
                fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
                name = os.ttyname(slave)
                if self.link_path:
                    _atomic_symlink(name, self.link_path)
            except BaseException:
                os.close(master)
                os.close(slave)
                raise
            self.master, self.slave, self.slave_name = master, slave, name
            self.plug_count += 1

    def unplug(self):
        """Close the pseudo-terminal (readers see an I/O error) and remove the link."""
        with self._lock:
            if self.link_path and os.path.islink(self.link_path):
                if os.readlink(self.link_path) == self.slave_name:
                    os.unlink(self.link_path)
            for fd in (self.master, self.slave):
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self.master = self.slave = None

    def replug(self, link_path=None):
        """Unplug (if plugged) and plug a fresh pseudo-terminal, optionally at a new path."""
        with self._lock:
            self.close()
            self.plug(link_path)

    def write(self, data):
        """Send bytes to the reader; return how many were accepted (0 while unplugged)."""
        data = bytes(data)
        with self._lock:
            if not self.plugged:
                self.bytes_dropped += len(data)
                return 0
            sent = 0
            for attempt in range(2):
                try:
                    sent += os.write(self.master, data[sent:])
                except BlockingIOError:
                    pass
                if sent == len(data):
                    break
                if attempt == 0:
                    # nobody reads: flush, and write the chunk again whole (a frame boundary)
                    termios.tcflush(self.slave, termios.TCIFLUSH)
                    self.flushes += 1
                    sent = 0
            self.bytes_written += sent
            self.bytes_dropped += len(data) - sent
            return sent

    def read(self, size=4096):
        """Return bytes the reader wrote to the device (commands), b'' if none."""
        with self._lock:
            if not self.plugged:
                return b''
            try:
                return os.read(self.master, size)
            except OSError:         # nothing to read (EAGAIN) or no reader attached (EIO)
                return b''

    def close(self):
        """Unplug for good."""
        with self._lock:
            if self.plugged:
                self.unplug()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
