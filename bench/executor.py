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
CPU per received message of rclpy's two executors, side by side (magcal_ros/ros/run.py).

A publisher process sends ``sensor_msgs/MagneticField`` on 4 topics at ``--rate`` Hz each
(the cross's four raw streams); a subscriber process spins a node with those 4
subscriptions and a 1 s timer (as the corrector has) on the SingleThreadedExecutor or the
EventsExecutor for ``--duration`` s and reports its own CPU time (user + system, of the
whole process) and the messages it received. The two executors alternate ``--repeats``
times in one run; read their ratio (absolute figures depend on the machine and its load).

    python bench/executor.py
    python bench/executor.py --rate 100 --duration 2 --repeats 1      # tiny
"""
import argparse
import json
import os
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import common  # noqa: E402

CHILD = r"""
import json, os, sys, time
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import MagneticField
role, executor, rate, duration = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
rclpy.init()
node = Node(f'bench_executor_{role}_{os.getpid()}')
topics = [f'/bench_executor/sensor{j}/raw' for j in range(1, 5)]
if role == 'pub':
    pubs = [node.create_publisher(MagneticField, t, 100) for t in topics]
    t0, k = time.monotonic(), 0
    # until the parent stops it, once the subscriber has measured (at most a minute)
    while time.monotonic() - t0 < duration + 60.0:
        for p in pubs:
            p.publish(MagneticField())
        k += 1
        time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
    sys.exit(0)
got = [0]
def cb(msg):
    got[0] += 1
for t in topics:
    node.create_subscription(MagneticField, t, cb, 100)
node.create_timer(1.0, lambda: None)
from magcal_ros.ros.run import make_executor
os.environ['MAGCAL_EXECUTOR'] = executor
ex, name = make_executor()
assert name == executor, (name, executor)
ex.add_node(node)
# discovery: measure from the first message on, plus half a second (not after a fixed
# time: a process that started slowly on a busy machine once measured nothing)
deadline = time.monotonic() + 30.0
while not got[0] and time.monotonic() < deadline:
    ex.spin_once(timeout_sec=0.1)
settle = time.monotonic() + 0.5
while time.monotonic() < settle:
    ex.spin_once(timeout_sec=0.1)
n0, c0 = got[0], time.process_time()
t0 = time.monotonic()
while time.monotonic() - t0 < duration:
    ex.spin_once(timeout_sec=0.1)
print(json.dumps({'messages': got[0] - n0, 'cpu_s': time.process_time() - c0,
                  'wall_s': time.monotonic() - t0}))
"""


def one(executor, rate, duration, env):
    """Run one publisher/subscriber pair; return the subscriber's figures."""
    pub = common.popen([sys.executable, '-c', CHILD, 'pub', executor, str(rate),
                        str(duration)], env=env, stdout=subprocess.DEVNULL)
    try:
        out = subprocess.run([sys.executable, '-c', CHILD, 'sub', executor, str(rate),
                              str(duration)], env=env, capture_output=True, text=True,
                             timeout=duration + 60, check=True).stdout
    finally:
        common.stop_process(pub)
    return json.loads(out.strip().splitlines()[-1])


def main():
    """Alternate the two executors; write bench/results/executor.json."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--rate', type=float, default=200.0, help='Hz per topic (4 topics)')
    ap.add_argument('--duration', type=float, default=10.0, help='s measured per run')
    ap.add_argument('--repeats', type=int, default=3)
    common.add_common_args(ap)
    args = ap.parse_args()
    started = time.perf_counter()
    env = common.ros_env()
    runs = []
    for rep in range(args.repeats):
        for executor in ('single', 'events'):
            r = one(executor, args.rate, args.duration, env)
            r.update(executor=executor, repeat=rep)
            runs.append(r)
            print(r, flush=True)
    rows = []
    per = {}
    for executor in ('single', 'events'):
        rs = [r for r in runs if r['executor'] == executor]
        msgs = sum(r['messages'] for r in rs)
        cpu = sum(r['cpu_s'] for r in rs)
        per[executor] = cpu / msgs * 1e6 if msgs else float('nan')
        rows.append([executor, msgs, round(cpu, 2), round(per[executor], 1),
                     f'{100 * cpu / sum(r["wall_s"] for r in rs):.1f}'])
    ratio = per['single'] / per['events']
    tab = common.table(['executor', 'messages', 'CPU s', 'CPU us per message',
                        'CPU % of a core'], rows,
                       f'4 topics at {args.rate:g} Hz, {args.repeats} x {args.duration:g} s '
                       f'each (single / events: {ratio:.2f} x)')
    print(tab)
    path = common.write_result('executor', vars(args),
                               {'runs': runs, 'us_per_message': per, 'ratio': ratio},
                               [tab], args.out_dir, started)
    print(f'wrote {path}')


if __name__ == '__main__':
    main()
