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
Shared helpers of the benchmarks: machine description, JSON results, text tables, ROS env.

Every benchmark is one seeded command that writes ``bench/results/<name>.json`` (machine,
settings, results) and prints a short table.  Nothing here imports rclpy.
"""
import datetime
import json
import os
import platform
import subprocess
import sys
import time

from magcal_ros.core.data.plain import jsonable  # noqa: F401 (re-exported for the benches)
import numpy as np
# what the fit imports at its first call, imported here, outside every timed region (the
# benches imported them through the diagnosis package before the fit stopped importing it)
import scipy.linalg  # noqa: F401
import scipy.optimize  # noqa: F401
import scipy.spatial.transform  # noqa: F401

BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
REPO_DIR = os.path.dirname(BENCH_DIR)
RESULTS_DIR = os.path.join(BENCH_DIR, 'results')

if REPO_DIR not in sys.path:
    sys.path.insert(0, REPO_DIR)


def _cpu_model():
    try:
        with open('/proc/cpuinfo') as fh:
            for line in fh:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or 'unknown'


def _mem_total_gib():
    try:
        with open('/proc/meminfo') as fh:
            for line in fh:
                if line.startswith('MemTotal'):
                    return round(int(line.split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    return None


def _git_commit():
    try:
        out = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=REPO_DIR,
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _blas_threads():
    """Return the OpenBLAS thread setting from the environment ('default' when unset)."""
    for key in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        if os.environ.get(key):
            return f'{key}={os.environ[key]}'
    return 'default'


def machine_info():
    """Describe the machine and software the benchmark ran on (a dict)."""
    import scipy
    info = {
        'cpu_model': _cpu_model(),
        'cpu_count': os.cpu_count(),
        'memory_gib': _mem_total_gib(),
        'platform': platform.platform(),
        'python': platform.python_version(),
        'numpy': np.__version__,
        'scipy': scipy.__version__,
        'blas_threads': _blas_threads(),
        'load_average_1min_at_start': os.getloadavg()[0],
        'git_commit': _git_commit(),
        'date_utc': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
    }
    from importlib.metadata import PackageNotFoundError, version
    for pkg in ('rclpy', 'threadpoolctl'):
        try:
            info[pkg] = version(pkg)
        except PackageNotFoundError:
            info[pkg] = None
    return info


def write_result(name, settings, results, tables, out_dir=None, started=None):
    """
    Write ``<out_dir>/<name>.json`` and return its path.

    Parameters
    ----------
    name : str
        Benchmark name (file stem).
    settings : dict
        Command-line settings (seeds, sizes, ...).
    results : dict
        The figures.
    tables : list of str
        The printed tables (kept in the JSON for BENCHMARKS.md).
    out_dir : str, optional
        Folder of the result (default bench/results).
    started : float, optional
        ``time.perf_counter()`` at the start: the JSON then has the wall time.

    """
    out_dir = out_dir or RESULTS_DIR
    os.makedirs(out_dir, exist_ok=True)
    doc = {'benchmark': name, 'machine': machine_info(), 'settings': settings,
           'results': results, 'tables': tables}
    if started is not None:
        doc['wall_time_s'] = time.perf_counter() - started
    path = os.path.join(out_dir, f'{name}.json')
    tmp = path + '.tmp'
    with open(tmp, 'w') as fh:
        json.dump(jsonable(doc), fh, indent=1, allow_nan=False)
        fh.write('\n')
    os.replace(tmp, path)
    return path


def table(headers, rows, title=None):
    """Plain-text (Markdown) table; floats get 3 significant digits unless preformatted."""
    def fmt(v):
        if v is None:
            return '-'
        if isinstance(v, (float, np.floating)):
            if not np.isfinite(v):
                return 'inf' if v > 0 else '-'
            if v == 0:
                return '0'
            a = abs(v)
            if a >= 1e5 or a < 1e-3:
                return f'{v:.3g}'
            if a >= 100:
                return f'{v:.0f}'
            return f'{v:.3g}'
        return str(v)
    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max(len(str(h)), *(len(c[i]) for c in cells)) if cells else len(str(h))
              for i, h in enumerate(headers)]
    lines = []
    if title:
        lines.append(f'**{title}**')
        lines.append('')
    lines.append('| ' + ' | '.join(str(h).ljust(w) for h, w in zip(headers, widths)) + ' |')
    lines.append('|' + '|'.join('-' * (w + 2) for w in widths) + '|')
    for c in cells:
        lines.append('| ' + ' | '.join(v.ljust(w) for v, w in zip(c, widths)) + ' |')
    return '\n'.join(lines)


def add_common_args(parser):
    """--out-dir option shared by every benchmark."""
    parser.add_argument('--out-dir', default=RESULTS_DIR,
                        help='directory of the JSON result (default bench/results)')
    return parser


# -- ROS environment (loopback only) --------------------------------------------------------

FASTDDS_PROFILE = os.path.join(REPO_DIR, 'config', 'fastdds_loopback.xml')


def ros_env(domain_id=None):
    """
    Environment for ROS processes of a benchmark: loopback Fast DDS profile, own domain.

    DDS stays on this machine: shared memory plus UDPv4 on 127.0.0.1 only, unicast
    discovery (config/fastdds_loopback.xml), and a private ROS_DOMAIN_ID.
    """
    if not os.path.exists(FASTDDS_PROFILE):
        raise FileNotFoundError(f'missing {FASTDDS_PROFILE}: the loopback DDS profile is '
                                'required so that no traffic leaves this machine')
    env = dict(os.environ)
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = FASTDDS_PROFILE
    env['FASTDDS_DEFAULT_PROFILES_FILE'] = FASTDDS_PROFILE
    env['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SYSTEM_DEFAULT'
    env.pop('ROS_STATIC_PEERS', None)
    env.pop('ROS_LOCALHOST_ONLY', None)
    if domain_id is None:
        # the per-run domain of scripts/ros_env.sh / test/conftest.py when set, else our own
        domain_id = os.environ.get('ROS_DOMAIN_ID') or 102 + (os.getpid() % 100)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['PYTHONPATH'] = REPO_DIR + os.pathsep + env.get('PYTHONPATH', '')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def _die_with_parent():
    """preexec_fn: SIGTERM this child when the benchmark process dies (Linux prctl)."""
    import ctypes
    import signal
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except OSError:
        pass


def popen(cmd, **kwargs):
    """subprocess.Popen that cannot outlive the benchmark (parent-death signal)."""
    return subprocess.Popen(cmd, preexec_fn=_die_with_parent, **kwargs)


def cpu_seconds(pid):
    """User + system CPU time of a process (and its threads), s, from /proc/<pid>/stat."""
    with open(f'/proc/{pid}/stat') as fh:
        parts = fh.read().rsplit(')', 1)[1].split()
    ticks = os.sysconf('SC_CLK_TCK')
    return (int(parts[11]) + int(parts[12])) / ticks


def stop_process(proc, timeout=5.0):
    """SIGINT, then SIGTERM, then SIGKILL a subprocess we started; returns its exit code."""
    import signal
    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, timeout),
                      (signal.SIGKILL, timeout)):
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            break
        try:
            return proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue
    return proc.poll()
