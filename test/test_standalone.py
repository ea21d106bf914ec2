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
The repository stands on its own (issue 22 item 1): its data are in it, nothing reads beside it.

The session-wide audit (test/open_audit_site/open_audit.py) fails a run in which the tests, a
README command or a benchmark opens a file under the repository's parent folder but outside
the repository; the tests here show that it does (in the pytest process and in a process it
starts) and that it passes a run that reads only the repository and the temporary directory.
The static check keeps the documents and scripts from naming a folder beside the clone.
"""
import gzip
import os
import pathlib
import re
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
SITE = REPO / 'test' / 'open_audit_site'
REAL = REPO / 'data' / 'real'

_NESTED_TEST = """
import subprocess
import sys

BESIDE = {beside!r}
INSIDE = {inside!r}


def test_reads():
    mode = {mode!r}
    if mode == 'in-process':
        with open(BESIDE) as fh:
            fh.read()
    elif mode == 'subprocess':
        subprocess.run([sys.executable, '-c', f'open({{BESIDE!r}}).read()'], check=True)
    else:
        open(INSIDE).read()
        subprocess.run([sys.executable, '-c', f'open({{INSIDE!r}}).read()'], check=True)
"""


def _nested_session(tmp_path, mode):
    """Run a made-up repository's pytest session with the audit; return (rc, output)."""
    parent = tmp_path / mode / 'parent'
    repo, beside, tmp = parent / 'repo', parent / 'shared', tmp_path / mode / 'tmp'
    for d in (repo, beside, tmp):
        d.mkdir(parents=True)
    (beside / 'recording.csv').write_text('t,s1_x,s1_y,s1_z\n')
    (repo / 'inside.csv').write_text('t,s1_x,s1_y,s1_z\n')
    (repo / 'test_reads.py').write_text(_NESTED_TEST.format(
        beside=str(beside / 'recording.csv'), inside=str(repo / 'inside.csv'), mode=mode))
    env = dict(os.environ, MAGCAL_TEST_OPEN_REPO=str(repo), TMPDIR=str(tmp),
               PYTHONPATH=os.pathsep.join([str(SITE), os.environ.get('PYTHONPATH', '')]))
    env.pop('MAGCAL_TEST_OPEN_LOG')                 # its own log, not this session's
    p = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider',
                        '-p', 'open_audit', 'test_reads.py'], cwd=repo, env=env,
                       capture_output=True, text=True, timeout=120)
    return p.returncode, p.stdout + p.stderr, beside / 'recording.csv'


@pytest.mark.parametrize('mode', ['in-process', 'subprocess'])
def test_the_audit_fails_a_session_that_reads_beside_the_repository(tmp_path, mode):
    rc, out, path = _nested_session(tmp_path, mode)
    assert rc == 1, out
    assert '1 passed' in out                        # the test itself passed: the audit failed it
    assert 'opened outside the repository' in out and str(path.resolve()) in out, out


def test_the_audit_passes_a_session_that_reads_only_the_repository(tmp_path):
    rc, out, _ = _nested_session(tmp_path, 'inside')
    assert rc == 0 and 'opened outside' not in out, out


def test_this_session_is_audited():
    """The hook is installed here and handed to every Python process the tests start."""
    assert os.environ.get('MAGCAL_TEST_OPEN_LOG')
    assert str(SITE) in os.environ['PYTHONPATH'].split(os.pathsep)
    code = 'import sys; print("open_audit" in sys.modules)'
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                       timeout=60)
    assert p.stdout.strip() == 'True', p.stderr


#: documents and scripts a user or a benchmark runs: none may name the folder beside the clone
_SCANNED = ['README.md', 'BENCHMARKS.md', 'CONTRIBUTING.md', 'Makefile', 'docs/**/*.md',
            'bench/**/*.py', 'scripts/*', 'test/**/*.py', 'examples/**/*', 'config/*',
            'launch/*']


def test_documents_and_scripts_do_not_name_the_parent_folder():
    pattern = re.compile(r'\.\./' + 'shared|' + r'\.\.[/\\]\.\.|/work/' + 'shared')
    hits = []
    for glob in _SCANNED:
        for path in sorted(REPO.glob(glob)):
            if path.is_file() and path.suffix not in ('.png', '.gz', '.zst'):
                for no, line in enumerate(path.read_text(errors='replace').splitlines(), 1):
                    if pattern.search(line):
                        hits.append(f'{path.relative_to(REPO)}:{no}: {line.strip()}')
    assert not hits, '\n'.join(hits)


def test_each_data_source_has_its_licence_and_provenance():
    sources = sorted(p for p in REAL.iterdir() if p.is_dir())
    assert [p.name for p in sources] == ['ck-accmag', 'dronekit-log171', 'methodic-copter46',
                                         'pyflightcoach-plane', 'pyulog-px4', 'roboto-px4',
                                         'sunsided-hmc5883l']
    for src in sources:
        assert (src / 'PROVENANCE.md').is_file()
        assert [p for p in src.iterdir() if p.name.startswith('LICENSE')], src
        prov = (src / 'PROVENANCE.md').read_text()
        for word in ('commit', 'Licence', 'Sensor', 'changed'):
            assert word in prov, (src.name, word)
    assert 'European Union Public Licence' in (REAL / 'sunsided-hmc5883l' /
                                               'LICENSE.md').read_text().replace('License',
                                                                                 'Licence')
    assert 'Apache License' in (REAL / 'ck-accmag' / 'LICENSE').read_text()
    recs = sorted((REAL / 'sunsided-hmc5883l').glob('*/*.csv.gz'))
    assert len(recs) == 13
    # the first row of the full sphere, as the source's .mat holds it (gauss x 1e5, nT)
    with gzip.open(REAL / 'sunsided-hmc5883l' / 'full-sphere' / 'full-sphere.csv.gz',
                   'rt') as fh:
        assert fh.readline().strip() == 't,s1_x,s1_y,s1_z,s1_temp'
        assert fh.readline().strip() == '0.000000,24128.440,-33761.468,-38899.083,24.7653'
