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
Imports inside the package: no cycle between modules, and core/'s folders in layers.

The graph: every ``import`` and ``from ... import`` of a ``magcal_ros`` module, absolute or
relative, at module level or inside a function (a lazy import still ties the two modules),
is an edge between the package's source files; a package's ``__init__`` is the node of the
package.  Checked on it (docs/design.md §6):

- no strongly connected component of more than one file (no import cycle);
- each folder of ``magcal_ros/core`` imports only the folders below it in §6's list, as the
  table :data:`ALLOWED` writes out (and the table is that list's order): no two folders
  import each other, and every folder of core/ has its place.

What the graph cannot see: a module named by a string at run time (``importlib``), and the
package ``__init__`` that Python runs before a submodule (only the submodule is an edge).
"""

import ast
import re

from ros_helpers import REPO_ROOT
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

PKG = REPO_ROOT / 'magcal_ros'

#: folder of magcal_ros/core -> the folders of magcal_ros/core it may import (those below it
#: in docs/design.md §6: live, discovery, data, model, papers, effects, geometry)
ALLOWED = {
    'live': {'discovery', 'data', 'model', 'papers', 'effects', 'geometry'},
    'discovery': {'data', 'model', 'papers', 'effects', 'geometry'},
    'data': {'model', 'papers', 'effects', 'geometry'},
    'model': {'papers', 'effects', 'geometry'},
    'papers': {'effects', 'geometry'},
    'effects': {'geometry'},
    'geometry': set(),
}


def module_name(path, root):
    """Return the dotted name of a source file under ``root`` (a package's ``__init__``: it)."""
    parts = list(path.relative_to(root).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def import_graph(pkg=PKG):
    """Return {module: set of the package's modules it imports}, over every source file."""
    files = {module_name(p, pkg.parent): p for p in pkg.rglob('*.py')}
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
    """Return the strongly connected components of more than one module (sorted lists)."""
    names = sorted(graph)
    index = {n: k for k, n in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    adj = csr_matrix(([1] * len(rows), (rows, cols)), shape=(len(names), len(names)))
    n, labels = connected_components(adj, directed=True, connection='strong')
    groups = [sorted(names[k] for k in range(len(names)) if labels[k] == c) for c in range(n)]
    return [g for g in groups if len(g) > 1]


def core_folder(module):
    """Return the folder of magcal_ros/core a module is in, or None."""
    parts = module.split('.')
    return parts[2] if len(parts) > 3 and parts[:2] == ['magcal_ros', 'core'] else None


def layer_violations(graph, allowed=ALLOWED):
    """Return 'importer -> imported' for each import between core folders ``allowed`` forbids."""
    out = []
    for a, deps in sorted(graph.items()):
        fa = core_folder(a)
        for b in sorted(deps):
            fb = core_folder(b)
            if fa and fb and fa != fb and fb not in allowed.get(fa, ()):
                out.append(f'{a} ({fa}) -> {b} ({fb})')
    return out


def test_the_graph_sees_a_cycle_when_there_is_one():
    graph = {'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}
    assert cycles(graph) == [['a', 'b', 'c']]
    assert cycles({'a': {'b'}, 'b': set()}) == []


def test_the_graph_reads_absolute_relative_and_lazy_imports(tmp_path):
    pkg = tmp_path / 'pkg'
    (pkg / 'sub').mkdir(parents=True)
    for name, text in {
            '__init__.py': '',
            'a.py': 'import os\nfrom . import b\n\n\ndef f():\n    from .sub import c\n',
            'b.py': 'from pkg.sub.c import g  # noqa\n',
            'sub/__init__.py': 'from .c import g\n',
            'sub/c.py': 'def g():\n    from ..a import f\n    import pkg.b\n',
            'sub/d.py': 'from .. import sub\nfrom ...outside import x\n'}.items():
        (pkg / name).write_text(text)
    assert import_graph(pkg) == {
        'pkg': set(),
        'pkg.a': {'pkg.b', 'pkg.sub.c'},            # module level, relative; lazy, relative
        'pkg.b': {'pkg.sub.c'},                     # absolute, to a submodule
        'pkg.sub': {'pkg.sub.c'},                   # relative in a package's __init__
        'pkg.sub.c': {'pkg.a', 'pkg.b'},            # lazy: two levels up; absolute
        'pkg.sub.d': {'pkg.sub'}}                   # a package from its parent; outside: none


def test_no_import_cycle_in_the_package():
    found = cycles(import_graph())
    assert found == [], 'import cycles (each a set of modules that import each other):\n' + \
        '\n'.join(' <-> '.join(c) for c in found)


def test_the_table_is_the_order_of_design_md():
    design = (REPO_ROOT / 'docs' / 'design.md').read_text()
    section = design[design.index('## §6'):design.index('## §7')]
    order = re.findall(r'^- `core/(\w+)/`', section, re.M)
    assert order == list(ALLOWED)
    assert ALLOWED == {f: set(order[k + 1:]) for k, f in enumerate(order)}
    folders = {p.name for p in (PKG / 'core').iterdir() if (p / '__init__.py').is_file()}
    assert folders == set(ALLOWED), f'folders of core/ not in §6: {folders ^ set(ALLOWED)}'


def test_core_folders_import_only_the_ones_below():
    assert layer_violations({'magcal_ros.core.model.x': {'magcal_ros.core.data.y',
                                                         'magcal_ros.core.effects.z'},
                             'magcal_ros.core.effects.z': set()}) == [
        'magcal_ros.core.model.x (model) -> magcal_ros.core.data.y (data)']
    found = layer_violations(import_graph())
    assert found == [], ('imports against the layers of docs/design.md §6 (move the code to '
                         'the layer it belongs to, or pass the value):\n' + '\n'.join(found))
