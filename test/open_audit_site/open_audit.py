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
The suite reads nothing beside the repository: files opened outside it are found and fail.

Issue 22 item 1: the data the project's claims rest on live in the repository, so no test,
README command or benchmark may read a file from the repository's parent folder (such as a
``shared`` folder next to the clone) that a fresh clone does not have.  An audit hook
(:func:`sys.addaudithook`, event ``open``) records every file opened under the repository's
parent folder but outside the repository; the temporary directory, the Python environment
and system paths are allowed.

- In the pytest process: installed by :func:`pytest_sessionstart` (test/conftest.py calls it);
  :func:`pytest_sessionfinish` fails the session and lists the paths.
- In every Python process the tests start (the ``magcal`` CLI, the README's commands, the
  benchmarks, the ROS nodes): ``sitecustomize.py`` beside this file installs the same hook;
  the session puts this folder first on ``PYTHONPATH``.  All of them append to one log file
  (``MAGCAL_TEST_OPEN_LOG``), read at the end of the session.

``MAGCAL_TEST_OPEN_REPO`` (default: two folders above this file) names the repository; the
self-test in test/test_standalone.py points it at a made-up layout.
"""
import os
import sys
import tempfile

ENV_LOG = 'MAGCAL_TEST_OPEN_LOG'
#: the temporary folder of the session that made the log: its processes may get a TMPDIR of
#: their own (test_ros_user's user shell), and still write where the session's tests do
ENV_TMP = 'MAGCAL_TEST_OPEN_TMP'
ENV_REPO = 'MAGCAL_TEST_OPEN_REPO'

_state = {'busy': False, 'cache': {}, 'log': None, 'created': False}


def _under(path, root):
    return path == root or path.startswith(root.rstrip(os.sep) + os.sep)


def _roots():
    repo = os.path.realpath(os.environ.get(ENV_REPO) or os.path.join(
        os.path.dirname(os.path.abspath(__file__)), '..', '..'))
    allowed = [repo, os.path.realpath(tempfile.gettempdir())]
    if os.environ.get(ENV_TMP):
        allowed.append(os.path.realpath(os.environ[ENV_TMP]))
    allowed += [os.path.realpath(p) for p in {sys.prefix, sys.base_prefix, sys.exec_prefix}]
    # the interpreter's bytecode cache (PYTHONPYCACHEPREFIX: scripts/test_lanes.py puts it in
    # the temporary folder; a clone in /tmp found it beside the repository)
    if getattr(sys, 'pycache_prefix', None):
        allowed.append(os.path.realpath(sys.pycache_prefix))
    return os.path.dirname(repo), allowed


def outside(path, parent, allowed):
    """Return True if ``path`` (str) is under ``parent`` and under none of ``allowed``."""
    real = os.path.realpath(path)
    return _under(real, parent) and not any(_under(real, a) for a in allowed)


def install(log_path):
    """Install the audit hook: files opened outside the repository are appended to log_path."""
    parent, allowed = _roots()
    cache = _state['cache']
    _state['log'] = log_path

    def hook(event, args):
        if event != 'open' or _state['busy']:
            return
        path = args[0]
        if isinstance(path, int) or path is None:
            return
        _state['busy'] = True
        try:
            path = os.fsdecode(path)
            key = (path, os.getcwd()) if not os.path.isabs(path) else path
            bad = cache.get(key)
            if bad is None:
                # a tool probing for a file that is not there (flake8 and pydocstyle look for
                # setup.cfg, tox.ini, ... in every folder up to the root) reads nothing
                bad = cache[key] = outside(path, parent, allowed) and os.path.exists(path)
            if bad:
                line = f'{os.path.realpath(path)}\t{os.getpid()}\t{" ".join(sys.argv)[:200]}\n'
                fd = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
                try:
                    os.write(fd, line.encode('utf-8', 'replace'))
                finally:
                    os.close(fd)
        except Exception:                           # noqa: BLE001 - never break an open()
            pass
        finally:
            _state['busy'] = False

    sys.addaudithook(hook)


def install_from_env():
    """Install the hook when the test session asked for it (sitecustomize.py)."""
    log_path = os.environ.get(ENV_LOG)
    if log_path:
        install(log_path)


def violations(log_path):
    """Return {path: [process command lines]} recorded in ``log_path``."""
    out = {}
    try:
        with open(log_path, encoding='utf-8', errors='replace') as fh:
            for line in fh:
                path, _, rest = line.rstrip('\n').partition('\t')
                out.setdefault(path, []).append(rest.partition('\t')[2])
    except FileNotFoundError:
        pass
    return out


def pytest_sessionstart(session):
    """Install the hook here and, through PYTHONPATH, in every Python process started."""
    log_path = os.environ.get(ENV_LOG)
    if not log_path:                                # a parallel worker inherits the controller's
        fd, log_path = tempfile.mkstemp(prefix='magcal-open-audit-', suffix='.log')
        os.close(fd)
        os.environ[ENV_LOG] = log_path
        os.environ[ENV_TMP] = os.path.realpath(tempfile.gettempdir())
        _state['created'] = True
    here = os.path.dirname(os.path.abspath(__file__))
    paths = os.environ.get('PYTHONPATH', '').split(os.pathsep)
    if here not in paths:
        os.environ['PYTHONPATH'] = os.pathsep.join([here] + [p for p in paths if p])
    install(log_path)


def pytest_sessionfinish(session, exitstatus):
    """Fail the session if any process opened a file beside the repository."""
    log_path = _state['log']
    if not log_path:
        return
    found = violations(log_path)
    if _state['created']:
        try:
            os.unlink(log_path)
        except OSError:
            pass
    if not found:
        return
    tr = session.config.pluginmanager.get_plugin('terminalreporter')
    write = tr.write_line if tr is not None else (lambda s: print(s, file=sys.stderr))
    write(f'FAILED open audit: {len(found)} file(s) opened outside the repository '
          '(a fresh clone has nothing beside it; put the data in the repository):')
    for path, procs in sorted(found.items()):
        write(f'  {path}  (by {procs[0] or "this pytest process"})')
    session.exitstatus = 1
