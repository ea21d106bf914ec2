#!/usr/bin/env python3

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
The magcal_ros main job, end to end on the simulated array (README "Demo").

Starts ``fluxgate_sim`` (simulated fluxgates on pseudo-terminals), ``fluxgate_driver``,
``calibration_node`` and ``corrector_node`` as separate processes, calls
``calibration/start``, shows the collection progress while the simulated array tumbles,
calls ``calibration/calibrate``, then records the raw and corrected streams and prints the
total-field and gradient-tensor errors before and after correction (RMS and max, per
sensor and per component) next to the noise-propagated floor, and the calibration node's
live residual (``calibration/residual``) next to its floor. Figures (PNG) and a JSON
summary go to ``--out`` (default ``./demo_out``). Every process is stopped at the end; the
exit status is 0 only if everything worked and the corrected errors are at the floor.

Run it through ``scripts/demo.sh``, which sources ``scripts/ros_env.sh`` (loopback-only DDS
profile and a private ROS_DOMAIN_ID). The simulated field is uniform (no gradient), so the
true tensor is zero and the true total field is ``--field-nt``.
"""
import argparse
import ctypes
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
NAMESPACE = '/magcal'
N_SENSORS = 4
#: corrected errors must stay within this factor of the noise-propagated floor
ACCEPT_FACTOR = 1.5


def _ensure_ros_env():
    """Keep DDS on loopback even without scripts/demo.sh (before rclpy loads); one BLAS thread."""
    profile = str(ROOT / 'config' / 'fastdds_loopback.xml')
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', profile)
    os.environ.setdefault('FASTDDS_DEFAULT_PROFILES_FILE', profile)
    os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'
    os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    from magcal_ros.runtime import limit_blas_threads
    limit_blas_threads()              # this process' analysis, as the nodes do (runtime.py)


def executable(name):
    """Command that runs console script ``name`` (venv bin, PATH, or ``python -m``)."""
    here = pathlib.Path(sys.executable).parent / name
    if here.exists():
        return [str(here)]
    found = shutil.which(name)
    if found:
        return [found]
    module = {'fluxgate_sim': 'magcal_ros.ros.sim_node',
              'fluxgate_driver': 'magcal_ros.ros.driver_node',
              'calibration_node': 'magcal_ros.ros.calibration_node',
              'corrector_node': 'magcal_ros.ros.corrector_node'}[name]
    return [sys.executable, '-m', module]


#: libc's prctl, looked up here: the forked child (``preexec_fn``) only calls it
_PRCTL = ctypes.CDLL(None).prctl if sys.platform.startswith('linux') else None
_PR_SET_PDEATHSIG = 1


def _die_with_parent():
    """
    In the forked child: SIGTERM it when the demo dies (Linux ``PR_SET_PDEATHSIG``).

    The nodes run in sessions of their own (a Ctrl-C reaches the demo, which stops them in
    order); a demo killed outright (SIGKILL, a test's timeout) left them streaming for good.
    """
    if _PRCTL is not None:
        _PRCTL(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


#: the wait before a client's first request, once it sees its service, s: Fast DDS's server
#: drops a response (after 100 ms) when it has not yet discovered the client's response
#: reader, and the call never returns (the loop demo's first calibration/start, in the suite
#: under load, 2026-11-28); test/ros_helpers.call_trigger waits 0.3 s in the tests' process
FIRST_CALL_GRACE_S = 1.0


def wait_future(fut, timeout_s, what):
    """Wait for ``fut`` (its node spun by another thread); its result, or TimeoutError."""
    deadline = time.monotonic() + timeout_s
    while not fut.done():
        if time.monotonic() > deadline:
            raise TimeoutError(f'{what} did not answer within {timeout_s} s')
        time.sleep(0.05)
    return fut.result()


def call_service(client, request, timeout_s, what):
    """
    Call ``client`` (its node spun by another thread); return the response.

    The first call of a client waits :data:`FIRST_CALL_GRACE_S` after the service appears.
    Raises TimeoutError when the service does not appear, or does not answer, in
    ``timeout_s`` s each.
    """
    if not client.wait_for_service(timeout_sec=timeout_s):
        raise TimeoutError(f'service {what} not available after {timeout_s} s')
    if not getattr(client, 'magcal_answered', False):
        time.sleep(FIRST_CALL_GRACE_S)
    response = wait_future(client.call_async(request), timeout_s, what)
    client.magcal_answered = True
    return response


class Processes:
    """The demo's child processes, each logging to <out>/logs/<name>.log."""

    def __init__(self, log_dir):
        self.log_dir = pathlib.Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs = {}

    def start(self, name, args):
        """Start ``name`` (a console script) with ``args``; return the Popen."""
        cmd = executable(name) + list(args)
        log = open(self.log_dir / f'{name}.log', 'w')
        env = dict(os.environ, PYTHONUNBUFFERED='1')
        env['PYTHONPATH'] = os.pathsep.join(
            [str(ROOT)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p])
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True, preexec_fn=_die_with_parent)
        log.close()
        self.procs[name] = proc
        return proc

    def dead(self):
        """Names and exit codes of the processes that stopped on their own."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def stop_all(self, timeout_s=10.0):
        """SIGINT every process, then SIGTERM/SIGKILL stragglers; return exit codes."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        for p in self.procs.values():
            for sig in (None, signal.SIGTERM, signal.SIGKILL):
                if sig is not None and p.poll() is None:
                    p.send_signal(sig)
                try:
                    p.wait(timeout=max(0.5, deadline - time.monotonic()))
                    break
                except subprocess.TimeoutExpired:
                    continue
        return {n: p.returncode for n, p in self.procs.items()}

    def tail(self, name, lines=15):
        """Last lines of a process log."""
        path = self.log_dir / f'{name}.log'
        if not path.exists():
            return ''
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:])


class Recorder:
    """rclpy client: services, status, raw/corrected/gradient streams (thread-safe)."""

    def __init__(self, rclpy, context):
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import MagneticField
        from std_msgs.msg import Float64MultiArray, String
        from std_srvs.srv import Trigger

        from magcal_ros.ros.conversions import msg_to_field_nt, msg_to_residual_nt, \
            msg_to_tensor, stamp_to_seconds
        from magcal_ros.ros.run import make_executor
        self._to_nt, self._to_tensor, self._sec = msg_to_field_nt, msg_to_tensor, \
            stamp_to_seconds
        self._to_residual = msg_to_residual_nt
        self.Trigger = Trigger
        self.node = Node('magcal_demo', namespace=NAMESPACE, context=context)
        self.lock = threading.Lock()
        self.recording = False
        self.status = None
        self.raw_count = np.zeros(N_SENSORS, int)
        self.raw = [[] for _ in range(N_SENSORS)]
        self.corrected = [[] for _ in range(N_SENSORS)]
        self.gradient = []
        self.residual = []              # calibration/residual: (scalar (S,), vector (S,)) nT
        self.frames = set()             # frame_id of the corrected fields and the gradient
        reliable = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
        n = self.node
        for j in range(N_SENSORS):
            # reliable like the rest: the floor is estimated from the differences of the raw
            # series, and samples a best-effort queue of 5 dropped under load left gaps that
            # raised it (3.5-3.75 nT for the simulator's 3 nT, 2026-11-22)
            n.create_subscription(MagneticField, f'sensor{j + 1}/raw', self._stream(j, 'raw'),
                                  reliable)
            n.create_subscription(MagneticField, f'sensor{j + 1}/corrected',
                                  self._stream(j, 'corrected'), reliable)
        n.create_subscription(Float64MultiArray, 'gradient', self._on_gradient, reliable)
        n.create_subscription(Float64MultiArray, 'calibration/residual', self._on_residual,
                              reliable)
        n.create_subscription(String, 'calibration/status', self._on_status, 10)
        self.clients = {k: n.create_client(Trigger, f'calibration/{k}')
                        for k in ('start', 'calibrate', 'diagnose')}
        # ten streams at 100 Hz: the EventsExecutor takes them for a third of the CPU of the
        # SingleThreadedExecutor (bench/executor.py), CPU the nodes under test keep
        self.executor, _ = make_executor(True, context)
        self.executor.add_node(n)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _stream(self, j, kind):
        def cb(msg):
            with self.lock:
                if kind == 'raw':
                    self.raw_count[j] += 1
                if self.recording:
                    getattr(self, kind)[j].append(
                        (self._sec(msg.header.stamp), *self._to_nt(msg)))
                    if kind == 'corrected':
                        self.frames.add(msg.header.frame_id)
        return cb

    def _on_residual(self, msg):
        with self.lock:
            if self.recording:
                self.residual.append(self._to_residual(msg))

    def _on_gradient(self, msg):
        with self.lock:
            if self.recording:
                self.gradient.append(self._to_tensor(msg))

    def _on_status(self, msg):
        with self.lock:
            self.status = json.loads(msg.data)

    def call(self, name, timeout_s):
        """Call a Trigger service; returns the response or raises TimeoutError."""
        return call_service(self.clients[name], self.Trigger.Request(), timeout_s,
                            f'calibration/{name}')

    def _spin(self):
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def close(self):
        """Stop spinning and destroy the node."""
        # the spin thread ends first: shutting the executor down under a running spin raised
        # InvalidHandle in that thread ('cannot use Destroyable because destruction was
        # requested') at the end of some runs
        self._stop.set()
        self.thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()


def shut_down(client, rclpy, context, procs, sim_dir, failures):
    """
    Close ``client`` (if any) and ROS, stop every process, remove the simulator's folder.

    A process that had stopped by itself is added to ``failures`` with the tail of its log;
    the exit codes are printed. Shared by the demo and the loop demo (``finally``).
    """
    if client is not None:
        client.close()
    rclpy.try_shutdown(context=context)
    died = procs.dead()
    codes = procs.stop_all()
    shutil.rmtree(sim_dir, ignore_errors=True)
    for name, code in died.items():
        failures.append(f'{name} stopped by itself with exit code {code}:\n{procs.tail(name)}')
    print(f'stopped all processes (exit codes {codes})')


def _wait(predicate, timeout_s, what, procs):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        dead = procs.dead()
        if dead:
            raise RuntimeError(f'process(es) stopped while waiting for {what}: {dead}')
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout_s} s waiting for {what}')
        time.sleep(0.1)


def _rms(x, axis=None):
    return np.sqrt(np.mean(np.square(x), axis=axis))


def analyse(rec, field_nt, baseline_m, tolerance_s):
    """Errors before/after correction and their floors (all nT, nT/m)."""
    from magcal_ros.core.data.noise import noise_floor
    from magcal_ros.core.geometry.tensor import cross_positions, tensor_lstsq, tensor_noise_floor
    from magcal_ros.core.live.sync import StampMatcher

    with rec.lock:
        raw = [np.array(r) for r in rec.raw]
        cor = [np.array(c) for c in rec.corrected]
        grad = np.array(rec.gradient)
    for name, arrs in (('raw', raw), ('corrected', cor)):
        for j, a in enumerate(arrs):
            if len(a) < 50:
                raise RuntimeError(f'only {len(a)} {name} samples of sensor {j + 1} recorded')
    if len(grad) < 50:
        raise RuntimeError(f'only {len(grad)} gradient tensors recorded')
    # noise per axis of each sensor from high-order differences of its raw series
    sigma = np.array([noise_floor(r[:, 1:]) for r in raw])
    positions = cross_positions(baseline_m)
    out = {'field_nt': field_nt, 'noise_sigma_nt': sigma.tolist(), 'sensors': {}}
    for j in range(N_SENSORS):
        before = np.linalg.norm(raw[j][:, 1:], axis=1) - field_nt
        after = np.linalg.norm(cor[j][:, 1:], axis=1) - field_nt
        out['sensors'][str(j + 1)] = {
            'total_field_rms_before_nt': float(_rms(before)),
            'total_field_max_before_nt': float(np.abs(before).max()),
            'total_field_rms_after_nt': float(_rms(after)),
            'total_field_max_after_nt': float(np.abs(after).max()),
            # white noise sigma per axis gives about sigma on the magnitude
            'total_field_floor_nt': float(sigma[j]),
            'samples': int(len(after)),
        }
    # uncorrected tensor from stamp-matched raw sets (the corrector does the same with
    # corrected samples and publishes it on `gradient`)
    matcher = StampMatcher(N_SENSORS, tolerance_s)
    sets = []
    events = sorted(((r[0], j, r[1:]) for j in range(N_SENSORS) for r in raw[j]),
                    key=lambda e: (e[0], e[1]))
    for t, j, b in events:
        sets.extend(items for _, _, items in matcher.add(j, t, b))
    raw_sets = np.transpose(np.array(sets), (1, 0, 2))           # (S, N, 3)
    g_before, _ = tensor_lstsq(raw_sets, positions)
    floor = tensor_noise_floor(sigma, positions)
    out['tensor'] = {
        'rms_before_nt_per_m': _rms(g_before, 0).tolist(),
        'max_before_nt_per_m': np.abs(g_before).max(0).tolist(),
        'rms_after_nt_per_m': _rms(grad, 0).tolist(),
        'max_after_nt_per_m': np.abs(grad).max(0).tolist(),
        'floor_nt_per_m': floor.tolist(),
        'rms_before_all_nt_per_m': float(_rms(g_before)),
        'rms_after_all_nt_per_m': float(_rms(grad)),
        'floor_all_nt_per_m': float(_rms(floor)),
        'tensors_after': int(len(grad)),
        'tensors_before': int(len(g_before)),
    }
    # the calibration node's own live check (calibration/residual, one message per set)
    with rec.lock:
        residual = list(rec.residual)
        out['corrected_frame_ids'] = sorted(rec.frames)
    if len(residual) < 50:
        raise RuntimeError(f'only {len(residual)} calibration/residual messages recorded')
    scalar = np.array([r[0] for r in residual])                  # (M, S) nT
    vector = np.array([r[1] for r in residual])
    var = sigma ** 2
    # |b_j - mean of the others|: 3 axes of noise variance sigma_j^2 + sum_k sigma_k^2/(S-1)^2
    vector_floor = np.sqrt(3 * (var + (var.sum() - var) / (N_SENSORS - 1) ** 2))
    out['live_residual'] = {
        'sets': int(len(residual)),
        'scalar_rms_nt': {str(j + 1): float(v) for j, v in enumerate(_rms(scalar, 0))},
        'scalar_floor_nt': {str(j + 1): float(v) for j, v in enumerate(sigma)},
        'vector_rms_nt': {str(j + 1): float(v) for j, v in enumerate(_rms(vector, 0))},
        'vector_floor_nt': {str(j + 1): float(v) for j, v in enumerate(vector_floor)},
    }
    series = {'raw': raw, 'cor': cor, 'grad': grad, 'g_before': g_before}
    return out, series


def print_report(res):
    """Human-readable before/after tables."""
    print('\nTotal-field error |B| - F per sensor (nT):')
    print(f'  {"sensor":>6} {"RMS before":>11} {"max before":>11} {"RMS after":>10} '
          f'{"max after":>10} {"floor":>7} {"after/floor":>11}')
    for j, s in res['sensors'].items():
        print(f'  {j:>6} {s["total_field_rms_before_nt"]:11.1f} '
              f'{s["total_field_max_before_nt"]:11.1f} {s["total_field_rms_after_nt"]:10.2f} '
              f'{s["total_field_max_after_nt"]:10.2f} {s["total_field_floor_nt"]:7.2f} '
              f'{s["total_field_rms_after_nt"] / s["total_field_floor_nt"]:11.2f}')
    t = res['tensor']
    print('\nGradient tensor error G_ik (true tensor: 0), nT/m, RMS before -> after '
          '(noise floor) [max after]:')
    for i in range(3):
        cells = []
        for k in range(3):
            cells.append(f'{t["rms_before_nt_per_m"][i][k]:8.1f} -> '
                         f'{t["rms_after_nt_per_m"][i][k]:5.2f} '
                         f'({t["floor_nt_per_m"][i][k]:5.2f}) '
                         f'[{t["max_after_nt_per_m"][i][k]:5.1f}]')
        print('  ' + ' | '.join(cells))
    print(f'  all components: RMS {t["rms_before_all_nt_per_m"]:.1f} -> '
          f'{t["rms_after_all_nt_per_m"]:.2f} nT/m, floor {t["floor_all_nt_per_m"]:.2f} nT/m '
          f'(improvement x{t["rms_before_all_nt_per_m"] / t["rms_after_all_nt_per_m"]:.0f})')
    r = res['live_residual']
    print(f'\nLive residual of the calibration node (calibration/residual, {r["sets"]} sets), '
          'RMS (floor), nT:')
    for kind in ('scalar', 'vector'):
        print(f'  {kind:>6}: ' + ', '.join(
            f'{j}: {v:.2f} ({r[kind + "_floor_nt"][j]:.2f})'
            for j, v in r[kind + '_rms_nt'].items()))
    print(f'corrected fields in frame {", ".join(res["corrected_frame_ids"])}')


def write_figures(res, series, out_dir):
    """PNG figures of the errors before/after; returns the paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    field = res['field_nt']
    paths = []
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    t0 = min(r[0, 0] for r in series['raw'])
    for j in range(N_SENSORS):
        r, c = series['raw'][j], series['cor'][j]
        axes[0].plot(r[:, 0] - t0, np.linalg.norm(r[:, 1:], axis=1) - field, lw=0.8,
                     label=f'sensor {j + 1}')
        axes[1].plot(c[:, 0] - t0, np.linalg.norm(c[:, 1:], axis=1) - field, lw=0.6,
                     label=f'sensor {j + 1}')
    floor = np.mean(res['noise_sigma_nt'])
    axes[1].axhspan(-floor, floor, color='0.85', label=f'+-noise ({floor:.1f} nT)')
    axes[0].set_title('total-field error before correction (raw)')
    axes[1].set_title('after correction (corrector_node)')
    for ax in axes:
        ax.set_ylabel('|B| - F (nT)')
        # outside the axes: inside, it hid the largest raw errors
        ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
        ax.grid(alpha=0.3)
    axes[1].set_xlabel('time (s)')
    fig.tight_layout()
    paths.append(os.path.join(out_dir, 'total_field_error.png'))
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    t = res['tensor']
    before = np.array(t['rms_before_nt_per_m']).ravel()
    after = np.array(t['rms_after_nt_per_m']).ravel()
    floor_t = np.array(t['floor_nt_per_m']).ravel()
    labels = [f'G{"xyz"[i]}{"xyz"[k]}' for i in range(3) for k in range(3)]
    x = np.arange(9)
    fig, ax = plt.subplots(figsize=(10, 4.5))
    ax.bar(x - 0.27, before, 0.27, label='before (raw)')
    ax.bar(x, after, 0.27, label='after (corrected)')
    ax.bar(x + 0.27, floor_t, 0.27, label='noise floor', color='0.6')
    ax.set_yscale('log')
    ax.set_xticks(x, labels)
    ax.set_ylabel('RMS error (nT/m)')
    ax.set_title('gradient tensor components: RMS error (true tensor 0)')
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0))
    ax.grid(axis='y', alpha=0.3, which='both')
    fig.tight_layout()
    paths.append(os.path.join(out_dir, 'tensor_rms.png'))
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(3, 3, figsize=(11, 7), sharex=True)
    gb, ga = series['g_before'], series['grad']
    for i in range(3):
        for k in range(3):
            ax = axes[i, k]
            ax.plot(np.arange(len(gb)) / len(gb), gb[:, i, k], lw=0.6, label='before')
            ax.plot(np.arange(len(ga)) / len(ga), ga[:, i, k], lw=0.6, label='after')
            ax.set_title(labels[3 * i + k], fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.supxlabel('fraction of the recording')
    fig.supylabel('nT/m')
    fig.tight_layout()
    paths.append(os.path.join(out_dir, 'tensor_components.png'))
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def parse_args(argv=None):
    """Command line of the demo."""
    p = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog='scripts/demo.sh --site-gradient [GXX,GXY,GXZ,GYY,GYZ]: '
                                       'an offline before/after of a site gradient instead '
                                       '(scripts/demo_site_gradient.py; add --help for its '
                                       'options); scripts/demo.sh --loop [--seed N]: '
                                       'the workbench loop live, a hidden effect diagnosed '
                                       'and removed through ROS (scripts/demo_loop.py; '
                                       '--loop --help for its options)')
    p.add_argument('--out', default='demo_out', help='output directory (default ./demo_out)')
    p.add_argument('--collect-s', type=float, default=30.0,
                   help='seconds of rotation data to collect (default 30: about 3000 sets, '
                        "by when the simulator's smooth trajectory has covered the attitudes); "
                        'collection goes on past it until calibration/status says ready, at '
                        'most --max-collect-s')
    p.add_argument('--max-collect-s', type=float, default=120.0,
                   help='longest collection, s (default 120): calibrate then even if the '
                        'status is not ready (the reply says why if it refuses)')
    p.add_argument('--record-s', type=float, default=15.0,
                   help='seconds of corrected stream to record afterwards (default 15)')
    p.add_argument('--model', default='base', help='model to fit (default base)')
    p.add_argument('--field-nt', type=float, default=50000.0,
                   help='field magnitude of the simulator and the reference, nT')
    p.add_argument('--seed', type=int, default=0, help='simulator seed')
    p.add_argument('--sim-tick', type=float, default=0.01,
                   help='write period of fluxgate_sim, s (default 0.01 = one sample per '
                        'write at 100 Hz, like a real device; the driver stamps samples on '
                        'arrival, so several samples per write would share a stamp)')
    p.add_argument('--diagnose', action='store_true',
                   help='also call calibration/diagnose after calibrating (ranks the effects '
                        'missing from the model; writes an HTML report to <out>/report)')
    p.add_argument('--no-check', action='store_true',
                   help='do not fail when the corrected errors exceed 1.5x the floor')
    return p.parse_args(argv)


def main(argv=None):
    """Run the demo; returns the exit status."""
    args = parse_args(argv)
    _ensure_ros_env()
    out_dir = os.path.abspath(args.out)
    os.makedirs(out_dir, exist_ok=True)
    sim_dir = tempfile.mkdtemp(prefix='magcal_demo_sim_')
    cal_file = os.path.join(out_dir, 'calibration.yaml')
    print(f'magcal_ros demo: ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}, output in {out_dir}')

    import rclpy
    from rclpy.context import Context

    procs = Processes(os.path.join(out_dir, 'logs'))
    context = Context()
    rclpy.init(context=context)
    rec = None
    failures = []
    try:
        ros = ['--ros-args', '-r', f'__ns:={NAMESPACE}']
        procs.start('fluxgate_sim', ['--dir', sim_dir, '--seed', str(args.seed),
                                     '--field-nt', str(args.field_nt),
                                     '--tick', str(args.sim_tick)])
        ports = [os.path.join(sim_dir, f'fluxgate{j}') for j in range(1, N_SENSORS + 1)]
        _wait(lambda: all(os.path.exists(p) for p in ports), 15, 'the simulated ports', procs)
        procs.start('fluxgate_driver', ros + [a for j, p in enumerate(ports, 1)
                                              for a in ('-p', f'sensor{j}.port:={p}')])
        procs.start('calibration_node', ros + [
            '--params-file', str(ROOT / 'config' / 'calibration.yaml'),
            '-p', f'calibration_file:={cal_file}',
            '-p', f'report_dir:={os.path.join(out_dir, "report")}',
            '-p', f'field_nt:={args.field_nt}',
            '-p', f'model:={json.dumps(args.model.split(","))}'])
        procs.start('corrector_node', ros + [
            '--params-file', str(ROOT / 'config' / 'corrector.yaml'),
            '-p', f'calibration_file:={cal_file}'])
        print('started fluxgate_sim, fluxgate_driver, calibration_node, corrector_node '
              f'(logs in {procs.log_dir})')
        rec = Recorder(rclpy, context)
        _wait(lambda: rec.clients['start'].service_is_ready(), 30, 'calibration_node', procs)
        _wait(lambda: np.all(rec.raw_count > 10), 30, 'raw samples of all sensors', procs)
        print(f'raw data flowing ({rec.raw_count.tolist()} samples so far)')

        resp = rec.call('start', 10)
        print(f'calibration/start: {resp.message.splitlines()[0]}')
        if not resp.success:
            raise RuntimeError(f'calibration/start refused: {resp.message}')
        t0 = time.monotonic()
        next_print = 0.0
        told = False
        # the set duration, then on until calibration/status says ready (enough sets and
        # attitude coverage), at most --max-collect-s
        while ((elapsed := time.monotonic() - t0) < args.collect_s
               or (not (rec.status or {}).get('ready') and elapsed < args.max_collect_s)):
            if procs.dead():
                raise RuntimeError(f'process(es) stopped during collection: {procs.dead()}')
            if elapsed >= args.collect_s and not told:
                print('  calibration/status not ready yet: collecting on until it is (at most '
                      f'{args.max_collect_s:.0f} s)', flush=True)
                told = True
            if elapsed >= next_print:
                st = rec.status or {}
                cov = ' '.join(f'{j}:{v if isinstance(v, str) else v["status"]}'
                               for j, v in st.get('coverage', {}).items())
                bar = '#' * min(30, int(30 * elapsed / args.collect_s))
                print(f'  [{bar:<30}] {elapsed:5.1f}/{args.collect_s:.0f} s  sets '
                      f'{st.get("sets", 0):6d}  coverage {cov or "-"}', flush=True)
                next_print += 5.0
            time.sleep(0.2)
        st = rec.status or {}
        print(f'  collected {st.get("sets", 0)} sets; raw samples received per sensor '
              f'{st.get("samples_received")}; incomplete sets dropped '
              f'{st.get("incomplete_sets_dropped")}')
        missing = st.get('missing', [])
        if missing:
            print('  status reports missing: ' + '; '.join(missing))

        print('calling calibration/calibrate ...')
        resp = rec.call('calibrate', 180)
        summary, _, payload = resp.message.partition('\n{')
        print('\n'.join('  ' + line for line in summary.splitlines()))
        if not resp.success:
            raise RuntimeError('calibration/calibrate failed')
        cal_summary = json.loads('{' + payload)

        if args.diagnose:
            print('calling calibration/diagnose (is anything missing from the model?) ...')
            resp = rec.call('diagnose', 600)
            summary, _, _ = resp.message.partition('\n{')
            print('\n'.join('  ' + line for line in summary.splitlines()))
            if not resp.success:
                raise RuntimeError('calibration/diagnose failed')

        time.sleep(1.0)          # corrector picks up calibration/result
        with rec.lock:
            rec.recording = True
        print(f'recording raw, corrected and gradient streams for {args.record_s:.0f} s ...')
        time.sleep(args.record_s)
        with rec.lock:
            rec.recording = False
        res, series = analyse(rec, args.field_nt, 0.5, 0.005)
        res['calibration'] = cal_summary
        # calibration/status at the end of the collection (sets, drops per sensor)
        res['collection'] = {k: st.get(k) for k in ('sets', 'incomplete_sets_dropped',
                                                    'samples_received')}
        print_report(res)
        figures = write_figures(res, series, out_dir)
        with open(os.path.join(out_dir, 'summary.json'), 'w') as fh:
            json.dump(res, fh, indent=2)
        print(f'\nfigures: {", ".join(figures)}\nsummary: {out_dir}/summary.json\n'
              f'calibration file: {cal_file}')
        t = res['tensor']
        if t['rms_after_all_nt_per_m'] > ACCEPT_FACTOR * t['floor_all_nt_per_m']:
            failures.append(f'tensor RMS after correction {t["rms_after_all_nt_per_m"]:.2f} '
                            f'nT/m exceeds {ACCEPT_FACTOR} x floor '
                            f'{t["floor_all_nt_per_m"]:.2f} nT/m')
        live = res['live_residual']
        for j, v in live['scalar_rms_nt'].items():
            if v > ACCEPT_FACTOR * live['scalar_floor_nt'][j]:
                failures.append(f'sensor {j}: live residual (calibration/residual) {v:.2f} nT '
                                f'exceeds {ACCEPT_FACTOR} x noise '
                                f'{live["scalar_floor_nt"][j]:.2f} nT')
        for j, s in res['sensors'].items():
            if s['total_field_rms_after_nt'] > ACCEPT_FACTOR * s['total_field_floor_nt']:
                failures.append(f'sensor {j}: total-field RMS after correction '
                                f'{s["total_field_rms_after_nt"]:.2f} nT exceeds '
                                f'{ACCEPT_FACTOR} x noise {s["total_field_floor_nt"]:.2f} nT')
        if args.no_check:
            failures = [f'(not checked) {f}' for f in failures]
            for f in failures:
                print(f)
            failures = []
    except (RuntimeError, TimeoutError, ValueError) as exc:
        failures.append(str(exc))
    except KeyboardInterrupt:
        failures.append('interrupted')
    finally:
        shut_down(rec, rclpy, context, procs, sim_dir, failures)
    if failures:
        print('\nDEMO FAILED:\n- ' + '\n- '.join(failures), file=sys.stderr)
        return 1
    print('\ndemo OK: corrected total field and tensor are at the noise floor')
    return 0


if __name__ == '__main__':
    sys.exit(main())
