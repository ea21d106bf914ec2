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
Packaging: magcal_ros builds with colcon as an ament_python package.

The install holds what ``ros2 run`` / ``ros2 launch`` need (docs/design.md §3).

A copy of the package source is built with the colcon from this environment into a temporary
workspace (no writes to the repository). This is the slow test of the suite (about 10 s).
"""

import configparser
import os
import pathlib
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest
from ros_helpers import REPO_ROOT, subprocess_env

PACKAGE = 'magcal_ros'
# Console scripts of docs/design.md §3 plus the offline tool (docs/design.md §2).
EXECUTABLES = ('fluxgate_driver', 'calibration_node', 'corrector_node', 'fluxgate_sim',
               'magcal')
# What colcon must not see in the copy: environments, caches, other workspaces' output.
_IGNORE = shutil.ignore_patterns('.venv', '.git', 'build', 'install', 'log', '__pycache__',
                                 '*.egg-info', '.pytest_cache', '.hypothesis')


def test_package_xml_is_ament_python_format_3():
    root = ET.parse(REPO_ROOT / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == PACKAGE
    assert root.findtext('license') == 'Apache-2.0'
    assert root.find('export').findtext('build_type') == 'ament_python'
    exec_deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'sensor_msgs', 'std_msgs', 'std_srvs', 'diagnostic_msgs',
            'python3-numpy', 'python3-scipy', 'python3-serial', 'python3-yaml'} <= exec_deps


def test_setup_cfg_puts_scripts_where_ros2_run_looks():
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(REPO_ROOT / 'setup.cfg')
    assert cfg['develop']['script_dir'] == f'$base/lib/{PACKAGE}'
    assert cfg['install']['install_scripts'] == f'$base/lib/{PACKAGE}'


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    """Build a copy of the package with colcon; return the install prefix of the package."""
    ws = tmp_path_factory.mktemp('colcon_ws')
    src = ws / 'src' / PACKAGE
    shutil.copytree(REPO_ROOT, src, ignore=_IGNORE, symlinks=True)
    colcon = pathlib.Path(sys.executable).parent / 'colcon'
    cmd = [str(colcon)] if colcon.exists() else [sys.executable, '-m', 'colcon']
    cmd += ['--log-base', str(ws / 'log'), 'build', '--base-paths', str(ws / 'src'),
            '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install'),
            '--event-handlers', 'console_cohesion+', 'summary-']
    env = subprocess_env({'COLCON_HOME': str(ws / 'colcon_home'), 'PYTHONPATH': None,
                          'COLCON_DEFAULTS_FILE': None})
    result = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=150)
    assert result.returncode == 0, f'colcon build failed:\n{result.stdout}\n{result.stderr}'
    return ws / 'install' / PACKAGE


@pytest.mark.timeout(180)
def test_colcon_build_installs_index_manifest_config_and_executables(colcon_install):
    share = colcon_install / 'share'
    marker = share / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
    assert marker.is_file(), 'ament index marker missing: ros2 would not find the package'
    assert (share / PACKAGE / 'package.xml').is_file()

    config_src = {p.name for p in (REPO_ROOT / 'config').glob('*.yaml')}
    config_src |= {p.name for p in (REPO_ROOT / 'config').glob('*.xml')}
    config_installed = {p.name for p in (share / PACKAGE / 'config').iterdir()}
    assert config_src == config_installed
    assert any(name.endswith('.yaml') for name in config_installed), 'no parameter file'
    assert 'fastdds_loopback.xml' in config_installed

    launch_src = {p.name for p in (REPO_ROOT / 'launch').glob('*.launch.py')}
    if launch_src:
        assert launch_src == {p.name for p in (share / PACKAGE / 'launch').iterdir()}

    lib = colcon_install / 'lib' / PACKAGE
    for exe in EXECUTABLES:
        path = lib / exe
        assert path.is_file(), f'{path} missing: `ros2 run {PACKAGE} {exe}` would fail'
        assert os.access(path, os.X_OK), f'{path} is not executable'
        first_line = path.read_text().splitlines()[0]
        assert first_line.startswith('#!') and 'python' in first_line

    # the installed Python package is importable from the install prefix, and an installed
    # executable runs from there as `ros2 run` would start it (install/setup.sh's PYTHONPATH)
    site = list(colcon_install.glob('lib/python3*/site-packages'))
    assert len(site) == 1 and (site[0] / PACKAGE / 'units.py').is_file()
    result = subprocess.run([str(lib / 'magcal'), '--help'], cwd=colcon_install,
                            env=subprocess_env({'PYTHONPATH': str(site[0])}),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert 'usage' in result.stdout.lower() and 'fit' in result.stdout
    where = subprocess.run([sys.executable, '-c', 'import magcal_ros; print(magcal_ros.__file__)'],
                           cwd=colcon_install, env=subprocess_env({'PYTHONPATH': str(site[0])}),
                           capture_output=True, text=True, timeout=60)
    assert pathlib.Path(where.stdout.strip()).is_relative_to(site[0]), where
    # the real recordings (data/, test data) are the repository's, never installed as code
    installed = [p.relative_to(colcon_install) for p in colcon_install.rglob('*')]
    assert not [p for p in installed if p.name.endswith(('.csv', '.csv.gz', '.csv.zst'))
                or 'real' in p.parts or 'sunsided-hmc5883l' in p.parts], installed
