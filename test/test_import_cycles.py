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
The package has no import cycle between its modules (docs/design.md §6).

Every ``import`` and ``from ... import`` of a ``magcal_ros`` module, at module level or inside
a function (a lazy import still ties the two modules), is an edge of a graph whose nodes are
the package's source files; a package's ``__init__`` is the node of the package.  The graph
must have no strongly connected component of more than one file, so each folder of
``magcal_ros/core`` can be read on top of the ones it uses.
"""

import ast
import pathlib

from ros_helpers import REPO_ROOT
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

PKG = REPO_ROOT / 'magcal_ros'


def module_name(path):
    """Dotted name of a source file (a package's ``__init__.py`` is the package)."""
    parts = list(path.relative_to(REPO_ROOT).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def import_graph():
    """{module: set of magcal_ros modules it imports}, over every source file."""
    files = {module_name(p): p for p in PKG.rglob('*.py')}
    graph = {}
    for name, path in files.items():
        is_pkg = path.name == '__init__.py'
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ''
                if node.level:
                    anchor = name.split('.') if is_pkg else name.split('.')[:-1]
                    anchor = anchor[:len(anchor) - node.level + 1]
                    base = '.'.join(anchor + ([base] if base else []))
                # `from pkg import sub` names the submodule when it is one
                targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in files else base
                           for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in files:
                    target = target.rpartition('.')[0]
                if target and target != name:
                    deps.add(target)
        graph[name] = deps
    return graph


def cycles(graph):
    """Strongly connected components of more than one module, as sorted lists."""
    names = sorted(graph)
    index = {n: k for k, n in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    adj = csr_matrix(([1] * len(rows), (rows, cols)), shape=(len(names), len(names)))
    n, labels = connected_components(adj, directed=True, connection='strong')
    groups = [sorted(names[k] for k in range(len(names)) if labels[k] == c) for c in range(n)]
    return [g for g in groups if len(g) > 1]


def test_the_graph_sees_a_cycle_when_there_is_one():
    graph = {'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}
    assert cycles(graph) == [['a', 'b', 'c']]
    assert cycles({'a': {'b'}, 'b': set()}) == []


def test_the_graph_reads_lazy_and_relative_imports(tmp_path):
    graph = import_graph()
    # a module-level import and a lazy one inside a function are both edges
    assert 'magcal_ros.core.model.spec' in graph['magcal_ros.core.model.fitting']
    assert 'magcal_ros.core.geometry.tensor' in graph['magcal_ros.core.model.calibration']


def test_no_import_cycle_in_the_package():
    found = cycles(import_graph())
    assert found == [], 'import cycles (each a set of modules that import each other):\n' + \
        '\n'.join(' <-> '.join(c) for c in found)
