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
What the ament_lint tests check: the package's own source, not build products.

ROS packages call the linters on the package folder ('.').  Here that folder also holds
what ``make setup`` and colcon build inside it (``build/`` with generated message code,
``install/``, ``log/``) and the output of ``make demo``: the lint tests are given the
repository's top-level entries instead, every one that holds a file the linter reads.
"""
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: generated, never linted (colcon's and make's build trees, make demo's output)
GENERATED = frozenset({'build', 'install', 'log', 'demo_out'})
#: the file name endings ament_copyright checks (ament_copyright.main)
COPYRIGHT_EXTENSIONS = ('.c', '.cc', '.cpp', '.cxx', '.h', '.hh', '.hpp', '.hxx', '.cmake',
                        '.py')


def _skipped(path):
    return path.name[0] in '._' or path.name in GENERATED


def source_files(extensions=('.py',)):
    """
    List the files with one of ``extensions`` under the repository, as the linters walk it.

    Folders starting with '.' or '_' are skipped (as ament_flake8, ament_pep257 and
    ament_copyright skip them), and so are the generated top-level folders.

    Parameters
    ----------
    extensions : tuple of str
        File name endings, with the dot.

    Returns
    -------
    list of pathlib.Path
        Sorted absolute paths.

    """
    out = []
    stack = [p for p in ROOT.iterdir() if not _skipped(p)]
    while stack:
        path = stack.pop()
        if path.is_dir():
            stack.extend(p for p in path.iterdir() if p.name[0] not in '._')
        elif path.suffix in extensions:
            out.append(path)
    return sorted(out)


def lint_paths(extensions=('.py',)):
    """
    List the top-level entries of the repository holding files with ``extensions``.

    The entries (folders and files) as absolute paths, to pass to a linter's ``main``;
    ``extensions`` as in :func:`source_files`.
    """
    tops = {ROOT / f.relative_to(ROOT).parts[0] for f in source_files(extensions)}
    return [str(p) for p in sorted(tops)]
