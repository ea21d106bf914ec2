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
Load generator / receiver of the live benchmark (rclpy; one role per process).

``--role pub``: publishes synthetic raw samples on ``sensor{j}/raw``
(sensor_msgs/MagneticField, reliable, depth 100: the driver's QoS) for every sensor at
``--rate`` Hz each, starting at the absolute time ``--t0`` (``time.time()`` clock), one
sample per sensor every 1/rate s (or bursts of several every ``--tick`` s); each message
carries its sequence number in ``header.frame_id`` and its publish time in
``header.stamp``.  Reports the messages published whose stamp lies in the measurement
window [t0 + warmup, t0 + warmup + duration).

``--role sub``: receives ``sensor{j}/<topic-in>`` (serialized, no deserialization: the
receiver must not be the bottleneck) and reports, for the messages stamped in the window,
the number received, the output rate and the latency (receive time - stamp) percentiles.

``--role both`` does both in one process.  Each process prints ``READY`` once its endpoints
are matched, and one JSON line at the end.
"""
import argparse
import json
import os
import struct
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import MagneticField

PUB_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE)
SUB_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE)
#: little-endian CDR after the 4-byte encapsulation: stamp.sec int32, stamp.nanosec uint32,
#: frame_id length uint32 (including the terminating NUL), then the characters
_HEAD = struct.Struct('<iII')
#: a plausible field per sensor, T (about 50 000 nT)
FIELD_T = np.array([[2.0e-5, -1.0e-5, 4.4e-5], [2.1e-5, -0.9e-5, 4.4e-5],
                    [1.9e-5, -1.1e-5, 4.5e-5], [2.0e-5, -1.0e-5, 4.3e-5]])


def _percentiles(lat_s):
    if len(lat_s) == 0:
        return None
    q = np.percentile(lat_s, [50, 90, 99, 100]) * 1e3
    return {'p50': float(q[0]), 'p90': float(q[1]), 'p99': float(q[2]), 'max': float(q[3]),
            'n': int(len(lat_s))}


def _sleep_until(t_abs):
    while True:
        d = t_abs - time.time()
        if d <= 0:
            return
        time.sleep(min(d, 0.05))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--role', choices=('pub', 'sub', 'both'), default='both')
    ap.add_argument('--ns', default='/bench')
    ap.add_argument('--n-sensors', type=int, default=4)
    ap.add_argument('--rate', type=float, default=100.0, help='Hz per sensor')
    ap.add_argument('--t0', default=None,
                    help='absolute start time (time.time()), or "stdin": read it from a line '
                    'of standard input after READY; default: 1 s after matching')
    ap.add_argument('--duration', type=float, default=10.0, help='measured window, s')
    ap.add_argument('--warmup', type=float, default=2.0, help='published but not measured, s')
    ap.add_argument('--tick', type=float, default=0.0,
                    help='publish in bursts every tick s (0: one sample per sensor per 1/rate)')
    ap.add_argument('--drain', type=float, default=1.0, help='wait for stragglers, s')
    ap.add_argument('--match-timeout', type=float, default=30.0)
    ap.add_argument('--topic-in', default='corrected', help='received topic suffix')
    ap.add_argument('--gradient', action='store_true',
                    help='sub: also subscribe gradient and gradient_stamped (counted), as a '
                    'user of the tensor does: the corrector matches sets only then')
    args = ap.parse_args(argv)
    # hard bound on this process's life, whatever happens to its parent or to DDS
    life = args.match_timeout + 30.0 + args.warmup + args.duration + args.drain + 30.0
    watchdog = threading.Timer(life, os._exit, args=(3,))
    watchdog.daemon = True
    watchdog.start()

    rclpy.init()
    node = Node(f'bench_load_{args.role}', namespace=args.ns)
    s = args.n_sensors
    do_pub = args.role in ('pub', 'both')
    do_sub = args.role in ('sub', 'both')
    cap = int(args.rate * (args.duration + args.warmup + 10)) + 1000
    recv_t = [np.full(cap, np.nan) for _ in range(s)]      # receive time by sequence number
    recv_stamp = [np.full(cap, np.nan) for _ in range(s)]
    extra = [0] * s
    arrival_no = [0] * s

    def make_cb(j):
        rt, rs = recv_t[j], recv_stamp[j]

        def cb(data):
            now = time.time()
            sec, nsec, ln = _HEAD.unpack_from(data, 4)
            try:
                k = int(data[16:16 + ln - 1])
            except ValueError:
                # no sequence number (the corrector writes the array frame into frame_id,
                # the driver the sensor frame): number by arrival
                k = arrival_no[j] % cap
                arrival_no[j] += 1
                rt[k] = rs[k] = np.nan
            if 0 <= k < cap and rt[k] != rt[k]:          # first arrival of k (nan check)
                rt[k] = now
                rs[k] = sec + 1e-9 * nsec
            else:
                extra[j] += 1
        return cb

    subs = [node.create_subscription(MagneticField, f'sensor{j}/{args.topic_in}',
                                     make_cb(j - 1), SUB_QOS, raw=True)
            for j in range(1, s + 1)] if do_sub else []
    n_gradient = [0]
    if do_sub and args.gradient:
        from std_msgs.msg import Float64MultiArray

        def count(_):
            n_gradient[0] += 1
        subs.append(node.create_subscription(Float64MultiArray, 'gradient', count, SUB_QOS,
                                             raw=True))
        try:
            from magcal_interfaces.msg import GradientTensorStamped
            node.create_subscription(GradientTensorStamped, 'gradient_stamped', count,
                                     SUB_QOS, raw=True)
        except ImportError:
            pass
    pubs = [node.create_publisher(MagneticField, f'sensor{j}/raw', PUB_QOS)
            for j in range(1, s + 1)] if do_pub else []
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()

    deadline = time.monotonic() + args.match_timeout
    while time.monotonic() < deadline:
        if all(x.get_publisher_count() > 0 for x in subs) and all(
                p.get_subscription_count() > 0 for p in pubs):
            break
        time.sleep(0.05)
    else:
        print(json.dumps({'error': f'{args.role}: endpoints not matched within '
                          f'{args.match_timeout} s'}), flush=True)
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
        return 1
    print('READY', flush=True)
    if args.t0 == 'stdin':
        t0 = float(sys.stdin.readline())
    else:
        t0 = float(args.t0) if args.t0 is not None else time.time() + 1.0
    t_meas0 = t0 + args.warmup
    t_stop = t_meas0 + args.duration
    out = {'role': args.role, 'rate_hz': args.rate, 'n_sensors': s,
           'duration_s': args.duration, 'warmup_s': args.warmup}

    if do_pub:
        msgs = []
        for j in range(s):
            m = MagneticField()
            m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z = FIELD_T[j % 4]
            msgs.append(m)
        pub_t = np.full(cap, np.nan)
        sent = 0
        _sleep_until(t0)
        period = args.tick if args.tick > 0 else 1.0 / args.rate
        next_tick = time.time()
        lag_max = 0.0
        while True:
            now = time.time()
            if now >= t_stop:
                break
            due = min(cap, int((now - t0) * args.rate) + 1)
            while sent < due:
                stamp = time.time()
                sec = int(stamp)
                nsec = int((stamp - sec) * 1e9)
                for j in range(s):
                    m = msgs[j]
                    m.header.stamp.sec = sec
                    m.header.stamp.nanosec = nsec
                    m.header.frame_id = str(sent)
                    pubs[j].publish(m)
                pub_t[sent] = stamp
                sent += 1
            lag_max = max(lag_max, time.time() - (t0 + due / args.rate))
            next_tick += period
            delay = next_tick - time.time()
            if delay > 0:
                time.sleep(delay)
            else:
                next_tick = time.time()
        win = np.flatnonzero((pub_t >= t_meas0) & (pub_t < t_stop))
        out.update(published=int(len(win) * s), offered_rate_hz=args.rate * s,
                   publish_rate_hz=len(win) * s / args.duration,
                   publish_lag_max_ms=lag_max * 1e3, seq_window=[int(win.min()), int(win.max())]
                   if len(win) else None)
    if do_sub:
        _sleep_until(t_stop + args.drain)
        got, lats, in_win = 0, [], 0
        for j in range(s):
            st = recv_stamp[j]
            sel = (st >= t_meas0) & (st < t_stop)
            got += int(sel.sum())
            lats.append(recv_t[j][sel] - st[sel])
            rt = recv_t[j]
            in_win += int(((rt >= t_meas0) & (rt < t_stop)).sum())
        lat = np.concatenate(lats)
        if args.gradient:
            out['gradient_messages'] = n_gradient[0]
        out.update(received=got, output_rate_hz=in_win / args.duration,
                   duplicates_or_unknown=int(sum(extra)), latency_ms=_percentiles(lat))
        if do_pub:
            out['loss'] = 1.0 - got / out['published'] if out['published'] else None
    print(json.dumps(out), flush=True)
    executor.shutdown(timeout_sec=2.0)
    spin.join(2.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
