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
Driver parsing rate per protocol, against a bare pyserial read loop on the same pty.

For every registered protocol (:data:`magcal_ros.serial.PROTOCOLS`):

- ``parser``: :meth:`Parser.feed` alone on the encoded byte stream in 4 KiB chunks
  (no I/O): samples/s;
- ``bare``: a bare pyserial loop ``ser.read(max(1, ser.in_waiting))`` that discards the
  bytes, reading a pseudo-terminal that a separate writer process fills as fast as the
  reader drains it: bytes/s, expressed as frames/s of the protocol;
- ``reader``: :class:`magcal_ros.serial.transport.PortReader` with the protocol's parser
  on the same kind of pty, samples delivered to a counting callback: samples/s.
  ``reader / bare`` is the share of the raw serial throughput the parsing path keeps.

Then the whole driver node at 4 x 1 kHz: ``fluxgate_sim`` (pseudo-terminals, default ASCII
protocol, 1 kHz per sensor) feeding ``fluxgate_driver`` (4 serial ports, publishing
``sensor{j}/raw``); a receiver (bench/live_load.py) counts what arrives.  Reported: the
driver's CPU use (% of one core) over the window, its publish rate and the stamp-to-receive
latency.  DDS on loopback only (config/fastdds_loopback.xml), private domain.

    python bench/driver_rate.py
    python bench/driver_rate.py --samples 2000 --node-duration 2      # tiny
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tty

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402
from magcal_ros.serial import make_encoder, make_parser, PROTOCOLS, Sample  # noqa: E402
from magcal_ros.serial.transport import PortReader  # noqa: E402
import numpy as np  # noqa: E402
import serial  # noqa: E402

PY = sys.executable
LOAD = os.path.join(common.BENCH_DIR, 'live_load.py')

_WRITER = r"""
import os, sys
fd = int(sys.argv[1]); path = sys.argv[2]; reps = int(sys.argv[3])
blob = open(path, 'rb').read()
os.set_blocking(fd, True)
for _ in range(reps):
    view = memoryview(blob)
    while view:
        n = os.write(fd, view)
        view = view[n:]
"""


def encoded_stream(protocol, n, seed=0):
    """(bytes, samples) of n samples of a tumbling 50 000 nT field in ``protocol``."""
    rng = np.random.default_rng(seed)
    enc = make_encoder(protocol)
    d = rng.normal(size=(n, 3))
    d = 50000.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(0, 3, (n, 3))
    temps = 25.0 + rng.normal(0, 0.1, n)
    chunks = []
    for k in range(n):
        s = Sample(field_nt=tuple(float(v) for v in d[k]), temp_c=float(temps[k]),
                   device_time=k * 1e-3)
        chunks.append(enc.encode(s))
    return b''.join(chunks), n


def parser_rate(protocol, blob, n, repeat=3, chunk=4096):
    """Samples/s of Parser.feed on ``chunk``-byte chunks (best of ``repeat``)."""
    best = 0.0
    got = 0
    for _ in range(repeat):
        p = make_parser(protocol)
        t0 = time.perf_counter()
        got = 0
        for i in range(0, len(blob), chunk):
            got += len(p.feed(blob[i:i + chunk]))
        dt = time.perf_counter() - t0
        best = max(best, got / dt)
    return best, got


class _Pty:
    """A raw pty whose master a writer subprocess fills with ``reps`` copies of a file."""

    def __init__(self, blob_path, reps):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.proc = common.popen([PY, '-c', _WRITER, str(self.master), blob_path,
                                  str(reps)], pass_fds=(self.master,),
                                 stderr=subprocess.DEVNULL)

    def close(self):
        common.stop_process(self.proc, timeout=2.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def bare_rate(blob_path, total_bytes, reps, timeout_s=60.0):
    """Bytes/s of a bare pyserial read loop on a pty being filled by another process."""
    pty = _Pty(blob_path, reps)
    try:
        ser = serial.Serial(pty.path, 115200, timeout=0.05)
        got = 0
        t0 = None
        deadline = time.monotonic() + timeout_s
        while got < total_bytes and time.monotonic() < deadline:
            data = ser.read(max(1, ser.in_waiting))
            if data and t0 is None:
                t0 = time.perf_counter()
            got += len(data)
        dt = time.perf_counter() - t0
        ser.close()
        return got / dt, got
    finally:
        pty.close()


def reader_rate(protocol, blob_path, reps, timeout_s=120.0):
    """
    Samples/s of PortReader + parser on a pty being filled by another process.

    Measured from the first to the last delivered sample; the run ends when the writer has
    finished and no sample arrived for 0.5 s.  (The byte stream repeats, so a protocol that
    checks the device time or a packet counter rejects a few frames at each repetition:
    counted as parse errors.)
    """
    pty = _Pty(blob_path, reps)
    count = [0]
    first = [None]
    last = [None]

    def cb(sample, arrival):
        now = time.perf_counter()
        if first[0] is None:
            first[0] = now
        last[0] = now
        count[0] += 1

    reader = PortReader(pty.path, 115200, make_parser(protocol), cb, name='bench')
    try:
        reader.start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            time.sleep(0.1)
            if pty.proc.poll() is not None and last[0] is not None and \
                    time.perf_counter() - last[0] > 0.5:
                break
        st = reader.stats()
    finally:
        reader.stop()
        pty.close()
    if first[0] is None or last[0] <= first[0]:
        return 0.0, count[0], st.parse_errors
    return count[0] / (last[0] - first[0]), count[0], st.parse_errors


def driver_node_cpu(args, env, tmp):
    """CPU use and output rate of fluxgate_driver fed by fluxgate_sim at 4 x rate."""
    simdir = os.path.join(tmp, 'sim')
    procs = []
    out = {'rate_hz_per_sensor': args.node_rate}
    logs = [open(os.path.join(tmp, 'sim.log'), 'w'), open(os.path.join(tmp, 'driver.log'), 'w')]
    try:
        sim = common.popen([PY, '-m', 'magcal_ros.sim', '--dir', simdir,
                                '--rate', str(args.node_rate)], env=env, stdout=logs[0],
                           stderr=subprocess.STDOUT)
        procs.append(sim)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not all(
                os.path.exists(os.path.join(simdir, f'fluxgate{j}')) for j in range(1, 5)):
            time.sleep(0.1)
        ports = []
        for j in range(1, 5):
            ports += ['-p', f'sensor{j}.port:={os.path.join(simdir, f"fluxgate{j}")}']
        drv = common.popen([PY, '-m', 'magcal_ros.ros.driver_node', '--ros-args', '-r',
                                '__ns:=/bench'] + ports, env=env, stdout=logs[1],
                           stderr=subprocess.STDOUT)
        procs.append(drv)
        rcv = common.popen([PY, LOAD, '--role', 'sub', '--ns', '/bench', '--topic-in', 'raw',
                            '--rate', str(args.node_rate), '--duration',
                            str(args.node_duration), '--warmup', str(args.node_warmup),
                            '--t0', 'stdin'],
                           env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           stderr=subprocess.DEVNULL, text=True)
        procs.append(rcv)
        line = ''
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and rcv.poll() is None:
            line = rcv.stdout.readline()
            if line.strip() == 'READY' or line.startswith('{'):
                break
        if line.strip() != 'READY':
            out['error'] = f'receiver did not match the driver: {line.strip()[:200]}'
            return out
        t0 = time.time() + 0.2
        rcv.stdin.write(f'{t0}\n')
        rcv.stdin.flush()
        time.sleep(max(0.0, t0 + args.node_warmup - time.time()))
        watched = (('driver', drv), ('sim', sim), ('receiver', rcv))
        c0 = {k: common.cpu_seconds(p.pid) for k, p in watched}
        w0 = time.time()
        time.sleep(args.node_duration)
        c1 = {k: common.cpu_seconds(p.pid) for k, p in watched}
        wall = time.time() - w0
        out['cpu_percent'] = {k: 100.0 * (c1[k] - c0[k]) / wall for k in c0}
        so, _ = rcv.communicate(timeout=30)
        js = [ln for ln in so.splitlines() if ln.startswith('{')]
        r = json.loads(js[-1]) if js else {'error': 'receiver gave no result'}
        if 'error' in r:
            out['error'] = r['error']
        else:
            out.update(received=r['received'], output_rate_hz=r['received'] / args.node_duration,
                       expected_rate_hz=4 * args.node_rate, latency_ms=r['latency_ms'])
        return out
    finally:
        for p in reversed(procs):
            common.stop_process(p)
        for f in logs:
            f.close()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--samples', type=int, default=20000, help='encoded samples per protocol')
    ap.add_argument('--pty-mbytes', type=float, default=8.0,
                    help='bytes written through the pty per protocol and loop, MB')
    ap.add_argument('--protocols', nargs='+', default=sorted(PROTOCOLS))
    ap.add_argument('--node-rate', type=float, default=1000.0, help='Hz per sensor')
    ap.add_argument('--node-duration', type=float, default=10.0, help='s')
    ap.add_argument('--node-warmup', type=float, default=2.0, help='s before the window')
    ap.add_argument('--no-node', action='store_true', help='skip the driver-node run')
    ap.add_argument('--domain-id', type=int, default=None)
    common.add_common_args(ap)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    res = {'protocols': {}}
    rows = []
    with tempfile.TemporaryDirectory(prefix='magcal_bench_drv_') as tmp:
        for proto in args.protocols:
            blob, n = encoded_stream(proto, args.samples)
            path = os.path.join(tmp, f'{proto}.bin')
            with open(path, 'wb') as fh:
                fh.write(blob)
            frame = len(blob) / n
            reps = max(1, int(np.ceil(args.pty_mbytes * 1e6 / len(blob))))
            p_rate, p_n = parser_rate(proto, blob, n)
            p64, _ = parser_rate(proto, blob, n, chunk=65536)
            b_rate, _ = bare_rate(path, len(blob) * reps, reps)
            r_rate, r_n, r_err = reader_rate(proto, path, reps)
            res['protocols'][proto] = {
                'bytes_per_frame': frame, 'parser_samples_per_s': p_rate, 'parser_samples': p_n,
                'parser_64k_samples_per_s': p64,
                'bare_bytes_per_s': b_rate, 'bare_frames_per_s': b_rate / frame,
                'reader_samples_per_s': r_rate, 'reader_samples': r_n,
                'reader_parse_errors': r_err, 'reader_over_bare': r_rate / (b_rate / frame)}
            rows.append([proto, f'{frame:.1f}', p_rate, p64, b_rate / frame, r_rate,
                         f'{r_rate / (b_rate / frame):.2f}', r_err])
            print(f'  {proto}: parser {p_rate:.0f}/s, bare {b_rate / frame:.0f} frames/s, '
                  f'reader {r_rate:.0f}/s', flush=True)
        tables = [common.table(
            ['protocol', 'bytes/frame', 'parser samples/s (4 KiB feeds)', '(64 KiB feeds)',
             'bare pyserial frames/s',
             'PortReader samples/s', 'reader/bare', 'parse errors'], rows,
            title='Serial parsing rate (one sensor, pty, no ROS)')]
        if not args.no_node:
            env = common.ros_env(args.domain_id)
            node = driver_node_cpu(args, env, tmp)
            res['driver_node'] = node
            lat = node.get('latency_ms') or {}
            cpu = node.get('cpu_percent') or {}
            tables.append(common.table(
                ['driver at', 'published msg/s', 'expected', 'driver CPU %', 'sim CPU %',
                 'p50 ms', 'p99 ms', 'note'],
                [[f'4 x {args.node_rate:g} Hz', node.get('output_rate_hz'),
                  node.get('expected_rate_hz'), cpu.get('driver'), cpu.get('sim'),
                  lat.get('p50'), lat.get('p99'), node.get('error', '')]],
                title='fluxgate_driver fed by fluxgate_sim (ASCII), CPU % of one core'))
    for t in tables:
        print()
        print(t)
    path = common.write_result('driver_rate', vars(args), res, tables, args.out_dir, started)
    print(f'\nwrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
