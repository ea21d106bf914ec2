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

"""Transport tests on real pseudo-terminals: PtyDevice -> pyserial PortReader."""

import logging
import os
import threading
import time

from magcal_ros.serial import make_encoder, make_parser, Sample
from magcal_ros.serial.transport import PortReader, PtyDevice
import pytest
import serial


def wait_for(predicate, timeout=5.0, interval=0.01):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, 'timed out'
        time.sleep(interval)


class Collector:
    def __init__(self):
        self.items = []
        self.lock = threading.Lock()

    def __call__(self, sample, arrival):
        with self.lock:
            self.items.append((sample, arrival))

    def xs(self):
        with self.lock:
            return [s.field_nt[0] for s, _ in self.items]

    def __len__(self):
        with self.lock:
            return len(self.items)


@pytest.fixture
def link(tmp_path):
    return str(tmp_path / 'sim' / 'fluxgate1')


@pytest.fixture
def cleanup():
    things = []
    yield things
    for t in reversed(things):
        (t.stop if isinstance(t, PortReader) else t.close)()


def reader(port, callback, cleanup, protocol='ascii', **kwargs):
    kwargs.setdefault('backoff_min', 0.02)
    kwargs.setdefault('backoff_max', 0.2)
    r = PortReader(port, 115200, make_parser(protocol), callback, **kwargs)
    cleanup.append(r)
    return r.start()


def test_pty_device_links_and_replaces_stale_link(link, cleanup):
    os.makedirs(os.path.dirname(link))
    os.symlink('/nonexistent/pts/99', link)              # stale link from a crashed run
    dev = PtyDevice(link)
    cleanup.append(dev)
    assert os.path.islink(link) and os.readlink(link) == dev.slave_name
    assert dev.path == link and dev.plugged
    old = dev.slave_name
    dev.unplug()
    assert not os.path.lexists(link) and not dev.plugged
    assert dev.write(b'lost') == 0 and dev.bytes_dropped == 4
    dev.replug()
    assert os.readlink(link) == dev.slave_name and dev.plug_count == 2
    assert isinstance(old, str)


def test_pty_device_refuses_to_replace_a_regular_file(tmp_path):
    path = tmp_path / 'precious'
    path.write_text('data')
    with pytest.raises(ValueError, match='not a symlink'):
        PtyDevice(str(path))
    assert path.read_text() == 'data'


def test_pty_device_drops_output_when_nobody_reads(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)

    def flood():
        for _ in range(200):                  # 200 kB into a ~18 kB kernel buffer
            dev.write(b'x' * 1000)
    writer = threading.Thread(target=flood, daemon=True)
    writer.start()
    writer.join(30.0)                         # a hang detector, not a speed bound
    assert not writer.is_alive(), 'PtyDevice.write blocked with nobody reading'
    assert dev.bytes_written + dev.bytes_dropped == 200_000
    assert dev.flushes >= 5                   # stale unread output was discarded


def test_reader_receives_samples_in_order_with_arrival_stamps(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)
    got = Collector()
    r = reader(link, got, cleanup)
    wait_for(lambda: r.stats().state == 'open')
    enc = make_encoder('ascii')
    t0 = time.time()
    dev.write(enc.encode_many(Sample((float(k), 2.0, 3.0), 20.0) for k in range(5)))
    wait_for(lambda: len(got) == 5)
    time.sleep(0.3)                            # the device pauses
    t1 = time.time()
    dev.write(enc.encode_many(Sample((float(k), 2.0, 3.0), 20.0) for k in range(5, 10)))
    wait_for(lambda: len(got) == 10)
    assert got.xs() == list(range(10))
    stamps = [a for _, a in got.items]
    # stamped on arrival: the pause shows in the stamps (not t0 + i/rate)
    assert all(t0 <= a < t1 for a in stamps[:5]) and all(a >= t1 for a in stamps[5:])
    assert stamps == sorted(stamps)
    st = r.stats()
    assert st.samples == 10 and st.parse_errors == 0 and st.reconnects == 0
    assert st.path == link and st.bytes_in == len(enc.encode(got.items[0][0])) * 10


def test_start_and_stop_commands_reach_the_device(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)
    p = make_parser('hmr2300_binary', send_start=True, rate=50)
    r = PortReader(link, 9600, p, lambda s, a: None, backoff_min=0.02)
    cleanup.append(r)
    r.start()
    wait_for(lambda: r.stats().state == 'open')
    received = b''

    def got_start():
        nonlocal received
        received += dev.read()
        return received == b'*99B\r*99R=50\r*99C\r'

    wait_for(got_start)
    r.stop()
    assert not r.running and r.stats().state == 'stopped'
    wait_for(lambda: dev.read() == b'\x1b')    # ESC stops continuous output on close


def test_unplug_replug_mid_stream_recovers_and_counts(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)
    got = Collector()
    r = reader(link, got, cleanup)
    wait_for(lambda: r.stats().state == 'open')
    enc = make_encoder('ascii')
    k = 0

    def stream(n):
        nonlocal k
        for _ in range(n):
            dev.write(enc.encode(Sample((float(k), 0.0, 0.0), 20.0)))
            k += 1
            time.sleep(0.001)

    stream(100)
    wait_for(lambda: len(got) == 100)
    dev.unplug()
    stream(50)                                 # written into the void while unplugged
    wait_for(lambda: r.stats().disconnects == 1)
    assert r.stats().state in ('backoff', 'connecting')
    dev.replug()
    wait_for(lambda: r.stats().reconnects == 1 and r.stats().state == 'open')
    stream(100)
    wait_for(lambda: len(got) == 200)
    st = r.stats()
    assert got.xs() == list(range(100)) + list(range(150, 250))
    assert st.disconnects == 1 and st.reconnects == 1 and st.parse_errors == 0
    # the last error is the last thing that went wrong: the unplug, or a reopen attempt
    # made while the device was away (counted as an open failure)
    assert ('could not open' if st.open_failures else 'disconnected') in st.last_error, (
        st.open_failures, st.last_error)


def test_repeated_replug_at_1khz(link, cleanup):
    # 1 kHz in 10-sample chunks every 10 ms; three unplug/replug cycles
    dev = PtyDevice(link)
    cleanup.append(dev)
    got = Collector()
    r = reader(link, got, cleanup)
    wait_for(lambda: r.stats().state == 'open')
    enc = make_encoder('ascii')
    k = 0
    for cycle in range(3):
        t_end = time.monotonic() + 0.4
        while time.monotonic() < t_end:
            dev.write(enc.encode_many(Sample((float(k + i), 0.0, 0.0), 20.0)
                                      for i in range(10)))
            k += 10
            time.sleep(0.01)
        n = k
        wait_for(lambda: len(got) == n)
        dev.unplug()
        wait_for(lambda: r.stats().disconnects == cycle + 1)
        dev.replug()
        wait_for(lambda: r.stats().reconnects == cycle + 1 and r.stats().state == 'open')
    st = r.stats()
    xs = got.xs()
    assert st.reconnects == 3 and st.disconnects == 3
    assert xs == sorted(xs) and len(xs) == k and st.parse_errors == 0
    assert st.rate_hz >= 0.0


def test_alternative_path_after_replug(tmp_path, cleanup):
    primary = str(tmp_path / 'ttyFLUX0')
    dev = PtyDevice(primary)
    cleanup.append(dev)
    got = Collector()
    r = reader(primary, got, cleanup, alternatives=[str(tmp_path / 'ttyFLUX*')])
    wait_for(lambda: r.stats().state == 'open')
    enc = make_encoder('ascii')
    dev.write(enc.encode(Sample((1.0, 0.0, 0.0), 20.0)))
    wait_for(lambda: len(got) == 1)
    dev.unplug()
    dev.replug(str(tmp_path / 'ttyFLUX1'))      # the adapter comes back under a new name
    wait_for(lambda: r.stats().reconnects == 1 and r.stats().state == 'open')
    assert r.stats().path == str(tmp_path / 'ttyFLUX1')
    dev.write(enc.encode(Sample((2.0, 0.0, 0.0), 20.0)))
    wait_for(lambda: len(got) == 2)


def test_two_readers_never_share_a_device_through_alternatives(tmp_path, cleanup):
    a, b = PtyDevice(str(tmp_path / 'ttyA0')), PtyDevice(str(tmp_path / 'ttyA1'))
    cleanup += [a, b]
    ra = reader(str(tmp_path / 'ttyA0'), Collector(), cleanup)
    wait_for(lambda: ra.stats().state == 'open')
    # reader b's own path is missing; its glob also matches the device reader a holds
    rb = reader(str(tmp_path / 'missing'), Collector(), cleanup,
                alternatives=[str(tmp_path / 'ttyA*')])
    wait_for(lambda: rb.stats().state == 'open')
    assert rb.stats().path == str(tmp_path / 'ttyA1')


class _RecordedWaits(threading.Event):
    """A stop event whose waits are recorded and return at once (no wall clock)."""

    def __init__(self):
        super().__init__()
        self.delays = []

    def wait(self, timeout=None):
        self.delays.append(timeout)
        return self.is_set()


def test_backoff_grows_exponentially_to_the_cap(cleanup):
    calls = []

    def factory(path, baud, timeout):
        calls.append(path)
        if len(calls) >= 7:
            waits.set()                 # the loop ends after this failure's wait
        raise serial.SerialException(f'could not open port {path}')

    r = PortReader('/dev/does-not-exist', 9600, make_parser('ascii'), lambda s, a: None,
                   backoff_min=0.02, backoff_max=0.16, serial_factory=factory)
    waits = _RecordedWaits()
    r._stop = waits
    cleanup.append(r)
    r.start()
    wait_for(lambda: r.stats().state == 'stopped', timeout=5)
    # the delay asked before each retry: doubling from backoff_min, capped at backoff_max
    assert waits.delays == [0.02, 0.04, 0.08, 0.16, 0.16, 0.16, 0.16], waits.delays
    st = r.stats()
    assert st.open_failures == 7 and 'could not open' in st.last_error


def test_a_port_that_cannot_be_opened_is_logged_once_per_error(cleanup, caplog):
    """The driver's log says which port it cannot open (once, not at every retry)."""
    calls = []

    def factory(path, baud, timeout):
        calls.append(path)
        raise serial.SerialException(f'could not open port {path}')

    caplog.set_level(logging.WARNING, logger='magcal_ros.serial.transport')
    r = PortReader('/dev/does-not-exist', 9600, make_parser('ascii'), lambda s, a: None,
                   backoff_min=0.01, backoff_max=0.02, serial_factory=factory, name='sensor3')
    cleanup.append(r)
    r.start()
    wait_for(lambda: len(calls) >= 5, timeout=5)
    r.stop()
    msgs = [rec.getMessage() for rec in caplog.records]
    assert msgs == ['sensor3: cannot open /dev/does-not-exist: could not open port '
                    '/dev/does-not-exist; retrying every 0.02 s at most'], msgs


def test_callback_errors_do_not_kill_the_reader(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)
    seen = []

    def flaky(sample, arrival):
        seen.append(sample)
        if len(seen) == 1:
            raise RuntimeError('bug in a subscriber')

    r = reader(link, flaky, cleanup)
    wait_for(lambda: r.stats().state == 'open')
    dev.write(make_encoder('ascii').encode_many(Sample((1.0, 2.0, 3.0), 20.0)
                                                for _ in range(3)))
    wait_for(lambda: len(seen) == 3)
    assert r.running and r.stats().callback_errors == 1


def test_garbage_on_the_wire_is_counted_in_reader_stats(link, cleanup):
    dev = PtyDevice(link)
    cleanup.append(dev)
    got = Collector()
    r = reader(link, got, cleanup)
    wait_for(lambda: r.stats().state == 'open')
    dev.write(b'1,2,3,4\r\n\xff\xfe garbage\r\nnan,1,1,1\r\n5,6,7,8\r\n')
    wait_for(lambda: len(got) == 2)
    wait_for(lambda: r.stats().parse_errors == 2)
    assert r.stats().errors == {'malformed': 1, 'non_finite': 1}


@pytest.mark.parametrize('kwargs, match', [
    ({'port': ''}, 'port must be a non-empty'),
    ({'baudrate': -9600}, 'baudrate must be a positive integer'),
    ({'baudrate': 9600.5}, 'baudrate must be a positive integer'),
    ({'backoff_min': 1.0, 'backoff_max': 0.5}, 'backoff_max'),
    ({'backoff_min': 0}, 'backoff_min must be a finite positive'),
    ({'timeout': -1}, 'timeout must be a finite positive'),
    ({'callback': None}, 'callback must be callable'),
])
def test_reader_rejects_bad_settings(kwargs, match):
    args = {'port': '/dev/ttyUSB0', 'baudrate': 9600, 'parser': make_parser('ascii'),
            'callback': lambda s, a: None}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        PortReader(args.pop('port'), args.pop('baudrate'), args.pop('parser'),
                   args.pop('callback'), **args)
