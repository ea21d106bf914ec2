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
Citations of docs/design.md and docs/papers.md point at existing sections.

Every citation of docs/design.md and docs/papers.md in the repository points at a section
that exists, and the background files of the development (never shipped) are not cited.
Every page of docs/ that the package's source (docstrings and comments) or docs/ cites, as
``docs/NAME.md`` or as a Markdown link ``(NAME.md)`` between two pages of docs/, exists.
"""
import pathlib
import re
import subprocess

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _tracked_text():
    files = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    for f in files:
        path = ROOT / f
        if path.suffix in ('.py', '.md', '.yaml', '.csv', '.xml', '.cfg', '.txt', '') and \
                path.is_file():
            try:
                yield f, path.read_text()
            except UnicodeDecodeError:
                continue


def test_citations_point_at_existing_sections():
    design = (ROOT / 'docs' / 'design.md').read_text()
    papers = (ROOT / 'docs' / 'papers.md').read_text()
    sections = set(re.findall(r'^## (§\d+)', design, re.M))
    paper_ids = set(re.findall(r'^## Paper (\d{3})$', papers, re.M))
    assert sections >= {'§1', '§2', '§3', '§4', '§5'} and paper_ids == {'000', '002', '004'}
    seen = 0
    for name, text in _tracked_text():
        for sec in re.findall(r'design\.md (§\d+)', text):
            assert sec in sections, f'{name} cites docs/design.md {sec}, which does not exist'
            seen += 1
        for pid in re.findall(r'papers\.md(?:, |#)paper[ -](\d{3})', text):
            assert pid in paper_ids, f'{name} cites paper {pid}, not in docs/papers.md'
            seen += 1
        for missing in (stem + '.md' for stem in ('DESIGN', 'SEEDS', 'API', 'STYLE')):
            assert missing not in text, f'{name} cites {missing}, which is not in the repository'
    assert seen > 30


def cited_doc_pages(name, text):
    """Return the docs/ pages a file cites: ``docs/NAME.md``, and links ``](NAME.md)`` in docs/."""
    pages = set(re.findall(r'\bdocs/([\w-]+\.md)', text))
    if name.startswith('docs/'):
        pages |= set(re.findall(r'\]\(([\w-]+\.md)(?:#[\w-]*)?\)', text))
    return pages


def test_cited_doc_pages_exist():
    assert cited_doc_pages('docs/a.md', 'see docs/formula.md and [f](plugins.md#x)') == \
        {'formula.md', 'plugins.md'}
    existing = {p.name for p in (ROOT / 'docs').glob('*.md')}
    cited = 0
    for name, text in _tracked_text():
        if name.endswith('.py') and name.startswith('magcal_ros/') or \
                name.startswith('docs/') and name.endswith('.md'):
            for page in cited_doc_pages(name, text):
                assert page in existing, f'{name} cites docs/{page}, which does not exist'
                cited += 1
    assert cited > 50
