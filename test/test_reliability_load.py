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
The corrector under a 10x burst of input: bounded latency and memory afterwards.

Three processes, as a user runs them: ``corrector_node`` (the console script, with a
calibration file), a load process (this file run as a script: ``--load``) that publishes
``sensor{1..4}/raw`` like the driver (reliable, depth 100) and receives
``sensor{j}/corrected``, and the test, which samples the corrector's resident memory
(``VmRSS`` in ``/proc/<pid>/status``) four times a second.

Schedule (rate per sensor; nominal is the driver's default 100 Hz): 100 Hz for 3 s, 1000 Hz
for 6 s (10x, 4000 messages/s in), 100 Hz for 3 s, 1000 Hz for 6 s again, 100 Hz for 3 s.
Each phase is as long as its figures need: a 1 kHz queue of 25 fills in 25 ms, so 6 s of
burst are 240 times the time to saturate and hold 24 000 input messages (a leak shows
against that count, below); 3 s at 100 Hz give 1 200 latencies per nominal phase (its median
and 90th percentile) and the 2 s of memory samples the comparison takes (8 of them).
Each message carries its publish time in the stamp (unique, increasing), which the
corrector copies to its output; the load process keeps the sequence number of each stamp,
so it measures loss, order and latency per phase: the corrector's (the DDS source timestamp
of its output - the input's publish time) and the delivered one (this process's middleware
reception time - publish time).

The corrector consumes its inputs with the sensor-data QoS (best effort, keep last 25): when
it cannot keep up, the oldest queued samples are dropped, so the queue, and with it the
latency, stays bounded, and nothing accumulates in memory.
"""
import argparse
import json
import os
import struct
import sys
import threading
import time

import numpy as np

#: (rate per sensor Hz, duration s) of each phase
SCHEDULE = [(100.0, 3.0), (1000.0, 6.0), (100.0, 3.0), (1000.0, 6.0), (100.0, 3.0)]
N_SENSORS = 4
#: the corrector's input queue per sensor (magcal_ros.ros.calibration_node.SENSOR_QOS: keep
#: the last 25, a quarter second of 100 Hz), as the module docstring states it
QUEUE_DEPTH = 25

# -- the load process (publisher + receiver) ------------------------------------------------

#: little-endian CDR after the 4-byte encapsulation: stamp sec, nanosec
_HEAD = struct.Struct('<iI')


def _load_main(argv):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import MagneticField

    ap = argparse.ArgumentParser()
    ap.add_argument('--load', action='store_true')
    ap.add_argument('--ns', required=True)
    ap.add_argument('--schedule', required=True, help='JSON list of [rate_hz, duration_s]')
    args = ap.parse_args(argv)
    schedule = json.loads(args.schedule)

    rclpy.init()
    node = Node('load', namespace=args.ns)
    # as the driver publishes: reliable, keep last 100
    pub_qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE)
    pubs = [node.create_publisher(MagneticField, f'sensor{j}/raw', pub_qos)
            for j in range(1, N_SENSORS + 1)]
    cap = int(sum(r * d for r, d in schedule)) + 100
    # per sensor and input sequence number: when the corrector published its output (the
    # DDS source timestamp of the corrected message), and when this process's middleware
    # received it (its reception timestamp), s since the epoch.  Neither waits for this
    # process's Python executor, which shares the interpreter with the 4 kHz publishing
    # loop and fell behind on slow moments of the shared machine: measured at the
    # callback, the burst's median latency once read 317 ms where the corrector's was
    # within its bound (2026-11-27).
    out_t = np.full((N_SENSORS, cap), np.nan)
    recv_t = np.full((N_SENSORS, cap), np.nan)
    arrival = np.full((N_SENSORS, cap), -1)        # the order in which they were taken
    extra = [0]
    seq_of = {}                         # stamp (sec, nanosec) -> sequence number

    def make_cb(j):
        row, rrow, arow = out_t[j], recv_t[j], arrival[j]
        count = [0]

        def cb(data, info):
            k = seq_of[_HEAD.unpack_from(data, 4)]
            if row[k] == row[k]:
                extra[0] += 1               # a duplicate (nan != nan marks "not yet")
            else:
                row[k] = info['source_timestamp'] * 1e-9
                rrow[k] = info['received_timestamp'] * 1e-9
                arow[k] = count[0]
                count[0] += 1
        return cb

    sub_qos = QoSProfile(depth=5000, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE)
    subs = [node.create_subscription(MagneticField, f'sensor{j}/corrected', make_cb(j - 1),
                                     sub_qos, raw=True) for j in range(1, N_SENSORS + 1)]
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    deadline = time.monotonic() + 30.0
    while not (all(s.get_publisher_count() > 0 for s in subs)
               and all(p.get_subscription_count() > 0 for p in pubs)):
        if time.monotonic() > deadline:
            print(json.dumps({'error': 'the corrector was not discovered in 30 s'}), flush=True)
            return 1
        time.sleep(0.05)
    # the corrector is the only subscriber of the raw topics here
    qos = [info.qos_profile for info in node.get_subscriptions_info_by_topic(
        node.resolve_topic_name('sensor1/raw'))]
    print('READY', flush=True)

    msgs = []
    for j in range(N_SENSORS):
        m = MagneticField()
        m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z = 2.0e-5, -1.0e-5, 4.4e-5
        m.header.frame_id = 'fluxgate'
        msgs.append(m)
    pub_t = np.full(cap, np.nan)
    phases = []
    seq = 0
    t_phase = time.time() + 0.5
    for rate, duration in schedule:
        t_end = t_phase + duration
        first = seq
        while True:
            now = time.time()
            if now >= t_end:
                break
            due = int((now - t_phase) * rate) + 1
            while seq - first < due:
                stamp = max(time.time(), pub_t[seq - 1] + 1e-6 if seq else 0.0)
                sec = int(stamp)
                nsec = int((stamp - sec) * 1e9)
                seq_of[(sec, nsec)] = seq
                for j, m in enumerate(msgs):
                    m.header.stamp.sec = sec
                    m.header.stamp.nanosec = nsec
                    pubs[j].publish(m)
                pub_t[seq] = stamp
                seq += 1
            time.sleep(max(0.0, min(0.002, t_phase + (seq - first) / rate - time.time())))
        phases.append({'rate_hz': rate, 't0': t_phase, 't1': t_end, 'seq0': first,
                       'seq1': seq})
        t_phase = t_end
    time.sleep(1.0)                            # stragglers

    out = {'phases': [], 'duplicates': extra[0],
           'subscription_qos': [{'reliability': q.reliability.name, 'history': q.history.name,
                                 'depth': q.depth} for q in qos]}
    for ph in phases:
        s0, s1 = ph['seq0'], ph['seq1']
        lat = out_t[:, s0:s1] - pub_t[None, s0:s1]
        delivered = recv_t[:, s0:s1] - pub_t[None, s0:s1]
        got = np.isfinite(lat)
        # latency in the phase after its first 0.5 s (queues left by the previous phase
        # drain then), and in that first 0.5 s separately
        settled = (pub_t[s0:s1] >= ph['t0'] + 0.5)[None] & got
        early = (pub_t[s0:s1] < ph['t0'] + 0.5)[None] & got
        last_s = (pub_t[s0:s1] >= ph['t1'] - 1.0)[None] & got
        # in sequence order, the outputs were taken and published in increasing order
        order = [bool(np.all(np.diff(arrival[j, s0:s1][got[j]]) > 0)) and
                 bool(np.all(np.diff(out_t[j, s0:s1][got[j]]) >= 0)) for j in range(N_SENSORS)]

        def pct(x):
            if not x.size:
                return None
            return {k: float(v) * 1e3 for k, v in zip(
                ('p50', 'p90', 'p99', 'max'), np.percentile(x, [50, 90, 99, 100]))}

        out['phases'].append(dict(
            ph, published=int((s1 - s0) * N_SENSORS), received=int(got.sum()),
            received_per_sensor=got.sum(axis=1).tolist(), in_order=all(order),
            latency_ms=pct(lat[settled]), latency_first_500ms_ms=pct(lat[early]),
            latency_last_s_ms=pct(lat[last_s]), received_last_s=int(last_s.sum()),
            delivered_ms=pct(delivered[settled]),
            last_received=[int(np.flatnonzero(got[j])[-1]) + s0 if got[j].any() else None
                           for j in range(N_SENSORS)]))
    print(json.dumps(out), flush=True)
    executor.shutdown(timeout_sec=2.0)
    spinner.join(2.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__' and '--load' in sys.argv:
    sys.exit(_load_main(sys.argv[1:]))


# -- the test ----------------------------------------------------------------------------------

def rss_kib(pid):
    """Resident set size of process ``pid`` in KiB (``VmRSS`` of /proc/<pid>/status)."""
    with open(f'/proc/{pid}/status', encoding='ascii') as fh:
        for line in fh:
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    raise RuntimeError(f'no VmRSS for pid {pid}')


def test_corrector_under_a_10x_burst(start_process, ros_namespace, tmp_path):
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.io.calfile import calibration_to_doc, save_calibration
    from magcal_ros.pipeline import cross_geometry
    from ros_helpers import console_script

    _, sim = simulate(n_samples=2, seed=1)
    path = tmp_path / 'cal.yaml'
    save_calibration(path, calibration_to_doc(sim.truth, geometry=cross_geometry(0.5)),
                     history=0)
    corrector = start_process(console_script('corrector_node') + [
        '--ros-args', '-r', f'__ns:={ros_namespace}', '-p', f'calibration_file:={path}'],
        name='corrector_node', ready='using the calibration from')
    load = start_process([sys.executable, os.path.abspath(__file__), '--load', '--ns',
                          ros_namespace, '--schedule', json.dumps(SCHEDULE)],
                         name='load', ready='READY', ready_timeout_sec=40.0)
    samples = []                                 # (time.time(), VmRSS KiB)
    t_stop = time.time() + sum(d for _, d in SCHEDULE) + 5.0
    while time.time() < t_stop and load.running():
        samples.append((time.time(), rss_kib(corrector.pid)))
        time.sleep(0.25)
    assert load.wait(30) == 0, load.read_log()
    result = json.loads(load.read_log().strip().splitlines()[-1])
    assert corrector.running(), corrector.read_log()
    rss = np.array(samples)
    ph = result['phases']

    def rss_at_end(p):
        """Median VmRSS over the last 2 s of phase ``p`` (KiB)."""
        sel = (rss[:, 0] > ph[p]['t1'] - 2.0) & (rss[:, 0] <= ph[p]['t1'])
        return float(np.median(rss[sel, 1]))

    before, after1, after2 = rss_at_end(0), rss_at_end(2), rss_at_end(4)
    report = {'rss_mib': [round(x / 1024, 2) for x in (before, after1, after2)],
              'backlog_s': [round((b['published'] - b['received']) * (b['t1'] - b['t0'])
                                  / b['received'], 2) for b in (ph[1], ph[3])],
              'phases': [{k: p[k] for k in ('rate_hz', 'published', 'received', 'latency_ms',
                                            'latency_first_500ms_ms', 'latency_last_s_ms',
                                            'delivered_ms')}
                         for p in ph],
              'subscription_qos': result['subscription_qos']}
    print('\nload:', json.dumps(report))

    # the corrector takes its inputs with the sensor-data QoS: best effort, keep last
    assert result['subscription_qos'] and all(
        q['reliability'] == 'BEST_EFFORT' for q in result['subscription_qos'])
    assert result['duplicates'] == 0
    for p in ph:
        assert p['in_order'], p                  # never an old sample after a newer one
    base, burst1, nominal1, burst2, nominal2 = ph
    # at the nominal rate (almost) nothing is lost: 10 % allows a stall of ~0.6 s of the
    # corrector on a shared machine (the 25-deep queue holds 0.25 s of a 100 Hz stream)
    for p in (base, nominal1, nominal2):
        assert p['received'] >= 0.9 * p['published'], p
    # during a burst the corrector keeps working on the newest samples (the oldest queued
    # are dropped): each sensor's output reaches the burst's last second, and the latency
    # there stays bounded
    for p in (burst1, burst2):
        assert all(last is not None and last >= p['seq1'] - p['rate_hz'] for last in
                   p['last_received']), p
        assert p['received'] > 0.1 * p['published'], p
    # The latency is the corrector's: from the input's publish to the corrector's publish of
    # its output (DDS source timestamp), so this process's own receiving is not in it.
    # The bounds follow from the queue, not from the latencies under test: a sample
    # waits behind at most QUEUE_DEPTH samples of each of the N_SENSORS subscriptions, taken
    # at the rate the corrector took them in the burst's last second (at most its capacity),
    # so the wait is at most drain_ms(burst) (30-50 ms at load 15, where 24-28 ms were
    # measured with the queue full). Delivery without any queue (DDS, Python scheduling on
    # the shared machine) is this run's baseline phase, its 90th percentile the allowance
    # for that jitter when compared with a median. A queue keeping every sample gives its
    # backlog's age instead (2.5 s at the burst's end with a 5000-deep queue, checked).

    def drain_ms(burst):
        return 1e3 * N_SENSORS * QUEUE_DEPTH / burst['received_last_s']   # in 1 s

    jitter = base['latency_ms']['p90']
    for p in (burst1, burst2):
        assert p['latency_last_s_ms']['p50'] < jitter + drain_ms(p), (drain_ms(p), p)
    # after the burst: the leftover queue is served within drain_ms, so the phase's first
    # 0.5 s has a median within it, and what follows (drain_ms well below 0.5 s) is delivery
    # alone: its median within the baseline's jitter plus, at most, one queue's drain. The
    # alternative is a backlog kept (seconds, above); on its own the baseline's p90 is no
    # bound for another phase's median: on a quiet machine it is a millisecond or two, and
    # the median of a phase moves with the load beside it (1.00 ms in the baseline, 1.54 ms
    # after the burst against a p90 of 1.53 ms, 2026-11-27, nothing live beside it). Not the
    # 99th percentiles: stalls of the shared machine (p99 44-176 ms, max 116-192 ms in every
    # phase at load 15, the baseline's included) are no property of the corrector.
    for burst, p in ((burst1, nominal1), (burst2, nominal2)):
        assert drain_ms(burst) < 500.0, (drain_ms(burst), burst)
        assert p['latency_first_500ms_ms']['p50'] < jitter + drain_ms(burst), (drain_ms(burst), p)
        assert p['latency_ms']['p50'] < jitter + drain_ms(burst), (jitter, drain_ms(burst), p)
    # memory: a second identical burst must not grow it: 2 MiB is what a leak of 90 bytes
    # per input message would add (24 000 per burst; one leaked MagneticField with its
    # header and covariance is several hundred bytes); the first burst may fill allocator
    # pools once (DDS history caches, Python free lists): bounded by 16 MiB
    assert after2 - after1 < 2 * 1024, report
    assert after1 - before < 16 * 1024, report
