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
Every command the README (and the docs' shell blocks) shows is run by a test.

``RUN_BY`` names, for every command line of a ``bash``/``sh`` block in README.md and
docs/*.md, the test that runs it. A command nobody runs fails
``test_every_shown_command_is_run_by_a_test``, so the README cannot grow an untested command.
"as written": the test runs the line itself in a shell; "driven": the ROS install's ``ros2``
CLI is not in this repository's wheels, so the test does what the line does through rclpy or
the launch API (the test's docstring says how).

The offline blocks are run here as written, in a temporary directory that has the layout
they need (``scripts/``, ``config/``, ``.venv`` and ``examples/`` linked from the
repository), so their output files do not land in the checkout.
"""
import argparse
import json
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]

#: (pattern of a shown command line, the test that runs it, how)
RUN_BY = [
    (r'make demo$', 'test_demo.py::test_make_demo_reaches_the_noise_floor', 'as written'),
    (r'make test$', 'test_demo.py::test_readme_starts_with_make_demo_and_make_test',
     'make -n (CI runs it; the suite cannot run itself)'),
    (r'scripts/demo\.sh --loop$',
     'test_demo_loop.py::test_loop_closes_for_three_hidden_terms', 'as written'),
    (r'scripts/demo\.sh --learn$', 'test_demo_learn.py::test_learn_demo_as_written',
     'as written'),
    (r'scripts/demo\.sh --site-gradient$',
     'test_demo_site_gradient.py::test_readme_site_gradient_demo', 'as written'),
    (r'source scripts/ros_env\.sh$', 'test_readme_commands.py::test_offline_block_as_written',
     'as written'),
    (r'magcal (simulate|fit|diagnose|report) sim\.csv|magcal simulate --out sim\.csv',
     'test_readme_commands.py::test_offline_block_as_written', 'as written'),
    (r'magcal (simulate --out turn\.csv|fit turn\.csv)',
     'test_readme_commands.py::test_degenerate_example_as_written', 'as written'),
    (r'magcal (fit|check) .*data/real/sunsided',
     'test_real_sunsided.py::test_readme_check_commands', 'as written'),
    (r'magcal fit data/real/dronekit-log171/',
     'test_vehicle_logs_real.py::test_readme_vehicle_log_command', 'as written'),
    (r'magcal fit test/data/paper002_table2\.csv',
     'test_fit_methods.py::test_readme_command_as_written', 'as written'),
    (r'magcal (simulate --out site\.csv|fit site\.csv)',
     'test_site_gradient.py::test_readme_commands', 'as written'),
    (r'colcon build --packages-select magcal_ros && source install/setup\.bash$',
     'test_packaging.py::test_colcon_build_installs_index_manifest_config_and_executables',
     'driven (colcon build of a copy)'),
    (r'ros2 launch magcal_ros magcal\.launch\.py',
     'test_launch_file.py::test_generate_launch_description', 'driven (launch API)'),
    (r'magcal fit .*--planar$', 'test_planar_node.py::test_readme_planar_commands',
     'as written'),
    (r'ros2 run magcal_ros \w+ --ros-args --params-file config/robot_planar\.yaml$',
     'test_planar_node.py::test_readme_robot_block_as_written',
     'as written (console scripts, a namespace of its own)'),
    (r'ros2 (run (?!.*(geometry_|robot_planar))|service call|'
     r'topic echo /magcal/calibration/status|'
     r'param set)|'
     r'ros2 topic echo /magcal/gradient$',
     'test_ros_user.py::test_readme_ros_commands_work_with_defaults', 'driven (rclpy)'),
    (r'ros2 run magcal_ros \w+ --ros-args --params-file config/geometry_8\.yaml$',
     'test_geometry_e2e.py::test_geometry_end_to_end_at_the_noise_floor',
     'as written (console scripts; each shipped geometry file, its own namespace)'),
    (r'ros2 topic echo /magcal/gradient_stamped',
     'test_corrector_node.py::test_corrects_to_the_true_field_and_publishes_the_gradient',
     'driven (rclpy subscriber)'),
    (r'cd ~/ros2_ws/src && ln -s|cd ~/ros2_ws && colcon build|source install/setup\.bash$',
     'test_interfaces.py::test_colcon_builds_the_linked_interface_package',
     'driven (colcon build of the linked package)'),
    # BENCHMARKS.md: the full runs take minutes to an hour; every benchmark runs in the suite
    # with smaller settings (test_bench_smoke), the rendering of the results as written
    (r'make bench$', 'test_readme_commands.py::test_benchmarks_doc_make_bench_and_report',
     'make -n (the full run takes ~16 min)'),
    (r'python bench/run_all\.py', 'test_bench_smoke.py::test_accuracy',
     'each benchmark it runs, with smaller settings (test_bench_smoke)'),
    (r'python bench/(accuracy|papers|live|driver_rate|real_data|solve_time)\.py',
     'test_bench_smoke.py::test_{0}', 'smaller settings'),
    (r'python bench/report\.py',
     'test_readme_commands.py::test_benchmarks_doc_make_bench_and_report',
     'with --print (in place it rewrites BENCHMARKS.md): the file holds what it renders'),
    (r'export PYTHONPATH=\$PWD/examples|magcal (simulate|diagnose|fit|report) .*my_effect',
     'test_readme_commands.py::test_plugins_doc_block_as_written', 'as written'),
]


def shown_commands(path):
    """
    Return the command lines of the ``bash``/``sh`` blocks of ``path``.

    Command lines of the ``bash``/``sh`` blocks of ``path``: continuations joined,
    comments and a trailing ``&`` cut, blank lines skipped.
    """
    text = path.read_text()
    out = []
    for block in re.findall(r'```(?:bash|sh)\n(.*?)```', text, flags=re.S):
        for line in block.replace('\\\n', ' ').splitlines():
            line = re.split(r'\s#\s|^#', line)[0].strip().rstrip('&').strip()
            if line:
                out.append(re.sub(r'\s+', ' ', line))
    return out


def _documents():
    return [REPO / 'README.md', REPO / 'BENCHMARKS.md'] + sorted((REPO / 'docs').glob('*.md'))


def test_every_shown_command_is_run_by_a_test():
    seen = 0
    for doc in _documents():
        for line in shown_commands(doc):
            hits = [(test.format(*m.groups()), how) for pat, test, how in RUN_BY
                    for m in [re.search(pat, line)] if m]
            assert hits, f'{doc.name}: no test runs the shown command {line!r} (add one)'
            seen += 1
            for test, _ in hits:
                fname, func = test.split('::')
                assert re.search(rf'^def {func}\(', (REPO / 'test' / fname).read_text(),
                                 re.M), f'{test} (for {line!r}) does not exist'
    assert seen > 30


def _layout(tmp_path, *names):
    """Make a working directory with the repository's ``names`` linked in it."""
    for name in names:
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


def run_block(lines, cwd, timeout=600):
    """Run ``lines`` in one bash (set -e) in ``cwd``; return each command's output."""
    script = ['set -e']
    for i, line in enumerate(lines):
        script += [f'echo "@@cmd {i}"', f'echo "@@cmd {i}" >&2', line]
    p = subprocess.run(['bash', '-c', '\n'.join(script)], cwd=cwd, capture_output=True,
                       text=True, timeout=timeout, env=dict(os.environ))
    assert p.returncode == 0, (p.stdout[-3000:], p.stderr[-3000:])
    outs = re.split(r'^@@cmd \d+\n', p.stdout, flags=re.M)[1:]
    errs = re.split(r'^@@cmd \d+\n', p.stderr, flags=re.M)[1:]
    assert len(outs) == len(lines)
    return list(zip(lines, outs, errs))


def _block_with(path, first):
    (block,) = [b for b in re.findall(r'```(?:bash|sh)\n(.*?)```', path.read_text(), re.S)
                if first in b]
    return [ln for ln in block.replace('\\\n', ' ').splitlines()
            if ln.strip() and not ln.lstrip().startswith('#')]


@pytest.mark.timeout(600)
def test_offline_block_as_written(tmp_path):
    """
    Run the README "Offline" block as written.

    README "Offline": simulate a hidden temperature term on sensor 2, fit the base model
    (a missing effect is warned about), diagnose it (verdict temperature@2), fit with it
    (sensor 2 down to the noise floor), report.
    """
    lines = _block_with(REPO / 'README.md', 'magcal simulate --out sim.csv')
    assert lines[0].startswith('source scripts/ros_env.sh')
    cwd = _layout(tmp_path, 'scripts', 'config', '.venv')
    results = run_block(lines, cwd)
    by_cmd = {line.split('#')[0].strip(): (out, err) for line, out, err in results}

    fit_base = next(v for k, v in by_cmd.items() if k.startswith('magcal fit sim.csv --model '
                                                                 'base --field-nt'))
    assert 'warning [missing_effect]: sensor 2' in fit_base[0] + fit_base[1]
    assert (cwd / 'calibration.yaml').exists()
    diag = next(v for k, v in by_cmd.items() if k.startswith('magcal diagnose'))
    assert re.search(r'^verdict: .*temperature@2', diag[0], re.M), diag[0][-2000:]
    fit_json = next(v for k, v in by_cmd.items() if '--json' in k)
    doc = json.loads(fit_json[0])
    floor = doc['noise_floor_nt']
    # simulate's default noise is 3 nT per axis; 3000 epochs: an RMS scatters by ~1.3 %
    assert abs(floor / 3.0 - 1.0) < 0.05
    assert doc['scalar_rms_nt']['2'] < 1.1 * floor
    assert (cwd / 'report' / 'index.html').exists()


@pytest.mark.timeout(600)
def test_plugins_doc_block_as_written(tmp_path):
    """
    Run the block of docs/plugins.md as written.

    docs/plugins.md: a wheel plug-in (examples/my_effect.py) simulated on sensor 3,
    diagnosed (verdict wheel@3), fitted (sensor 3 down to the 3 nT floor), reported.
    """
    lines = _block_with(REPO / 'docs' / 'plugins.md', 'export PYTHONPATH=$PWD/examples')
    cwd = _layout(tmp_path, 'examples', '.venv')
    lines = [f'PATH={REPO / ".venv" / "bin"}:$PATH'] + lines
    results = run_block(lines, cwd)
    diag = next(out for line, out, _ in results if line.startswith('magcal diagnose'))
    assert re.search(r'^verdict: .*wheel@3', diag, re.M), diag[-2000:]
    fit = next(out for line, out, _ in results if line.startswith('magcal fit'))
    rms3 = float(re.search(r'sensor 3: scalar RMS\s+([\d.]+) nT', fit).group(1))
    assert rms3 < 1.1 * 3.0, fit
    assert (cwd / 'cal.yaml').exists() and (cwd / 'report' / 'index.html').exists()


def test_degenerate_example_as_written(tmp_path):
    """README: the turntable example is refused (exit 2) with the message the README shows."""
    text = (REPO / 'README.md').read_text()
    m = re.search(r'```bash\n(magcal simulate --out turn\.csv.*?)```\n```\n(.*?)```', text,
                  flags=re.S)
    lines = [ln for ln in m.group(1).splitlines() if ln.strip()]
    shown = ' '.join(m.group(2).split())
    cwd = _layout(tmp_path, 'scripts', 'config', '.venv')
    p = subprocess.run(['bash', '-c', 'source scripts/ros_env.sh && ' + lines[0]], cwd=cwd,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    p = subprocess.run(['bash', '-c', 'source scripts/ros_env.sh && ' + lines[1]], cwd=cwd,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    err = p.stderr.strip().splitlines()
    assert len(err) == 1, err                   # one line, as the README says
    # the README wraps the line: the words are the same
    assert ' '.join(err[0].split()) == shown, (err[0], shown)


def test_benchmarks_doc_make_bench_and_report():
    """
    Check BENCHMARKS.md against `make bench` and bench/report.py.

    BENCHMARKS.md: `make bench` runs bench/run_all.py in the project environment, and
    `python bench/report.py` would leave the file as it is: its results section is what the
    result files in bench/results render to (nobody edited it by hand or forgot to render).
    """
    dry = subprocess.run(['make', '-n', '-o', '.venv/.magcal_setup_stamp', 'bench'], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert dry.returncode == 0 and 'bench/run_all.py' in dry.stdout, dry.stdout + dry.stderr
    p = subprocess.run([sys.executable, 'bench/report.py', '--print'], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    sys.path.insert(0, str(REPO / 'bench'))
    try:
        import report
    finally:
        sys.path.pop(0)
    text = (REPO / 'BENCHMARKS.md').read_text()
    block = text.split(report.BEGIN, 1)[1].split(report.END, 1)[0]
    assert block.strip() == p.stdout.strip(), 'BENCHMARKS.md differs from bench/report.py'


def test_design_synopsis_matches_the_command_line():
    """
    Match the synopsis of docs/design.md §2 against the command line.

    docs/design.md §2's synopsis names every subcommand, and every option it shows exists
    (`magcal <command> --help`, the parser users meet).
    """
    text = (REPO / 'docs' / 'design.md').read_text()
    synopsis = re.search(r'## §2 .*?```\n(.*?)```', text, flags=re.S).group(1)
    shown = {}
    cmd = None
    for line in synopsis.splitlines():
        m = re.match(r'magcal (\w+)', line)
        cmd = m.group(1) if m else cmd
        shown.setdefault(cmd, set()).update(re.findall(r'(?<![\w-])--[a-z][a-z-]*', line))
    from magcal_ros.cli import build_parser
    top = subprocess.run([sys.executable, '-m', 'magcal_ros.cli', '--help'],
                         capture_output=True, text=True, timeout=60).stdout
    commands = re.search(r'\{([a-z,]+)\}', top).group(1).split(',')
    assert sorted(shown) == sorted(commands)
    # each command's help from the parser `magcal` builds, in this process (a process per
    # command costs ~0.6 s each)
    subparsers = next(a for a in build_parser()._actions
                      if isinstance(a, argparse._SubParsersAction)).choices
    assert sorted(subparsers) == sorted(commands)
    for command, options in shown.items():
        help_text = subparsers[command].format_help()
        for option in options:
            assert re.search(rf'{option}\b', help_text), f'magcal {command} has no {option}'
        if command not in ('simulate', 'rollback'):
            assert '--unit' in help_text, command      # as the paragraph below it says


@pytest.fixture
def doc_plugin():
    """Register the effect class of docs/plugins.md, as written, for one test."""
    from magcal_ros.core import effects as fx
    import types
    code = re.findall(r'```python\n(.*?)```', (REPO / 'docs' / 'plugins.md').read_text(),
                      flags=re.S)[0]
    module = types.ModuleType('doc_plugin')
    exec(compile(code, 'docs/plugins.md', 'exec'), module.__dict__)
    names = []
    for cls in module.MAGCAL_EFFECTS:
        fx.register_effect(cls)
        names.append(cls.name)
    yield names
    for n in names:                     # keep the registry as other tests expect it
        fx.unregister_effect(n)


def test_plugins_doc_example_effect_as_written(doc_plugin):
    """
    Fit the example effect of docs/plugins.md as written.

    docs/plugins.md's example class (a heater's field going as sqrt(power)) fits the
    coupling it describes. The data: a simulated array whose heater power is switched by
    hand here, and sensor 2's raw readings given v (sqrt(P) - mean sqrt(P)), written here
    (not through the model), with v = (6, -4, 5) nT/sqrt(W).
    """
    from magcal_ros.core.data.simulate import simulate
    from magcal_ros.core.model import fit
    assert doc_plugin == ['heater_current']
    data, _ = simulate(n_samples=3000, rate_hz=10, trajectory='smooth', seed=11)
    rng = np.random.default_rng(5)
    t = data.t - data.t[0]
    third = t[-1] / 3
    power = np.where(t < third, 0.0, np.where(t < 2 * third, 16.0, 4.0))      # W
    power = power + rng.uniform(0.0, 1.0, t.size)
    data.aux['aux_heater_power'] = power
    v = np.array([6.0, -4.0, 5.0])                                             # nT/sqrt(W)
    i = np.sqrt(power)
    data.raw[1] += (i - i.mean())[:, None] * v
    without = fit(data, 'base', field_nt=50000.0)
    res = fit(data, 'base,heater_current@2', field_nt=50000.0)
    # 3 nT noise: without the effect sensor 2 is far above it, with it at it (10 %)
    assert without.scalar_rms_nt[2] > 2 * 3.0
    assert res.scalar_rms_nt[2] < 1.1 * 3.0
    rows = [r for r in res.param_table() if r['effect'].startswith('heater_current')]
    got = np.array([r['value'] for r in rows])
    se = np.array([r['stderr'] for r in rows])
    assert [r['unit'] for r in rows] == ['nT/sqrt(W)'] * 3
    assert np.all(np.abs(got - v) < 4 * se), (got, se)
