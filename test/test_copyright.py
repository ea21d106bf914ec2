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
ament_copyright, as in a package made by ``ros2 pkg create``, or its check written out.

ament_copyright is not on the package index: on a ROS install it runs itself; elsewhere
the test checks what it checks (ament_copyright.main and .parser): every source file
starts, after an optional shebang or coding line, with a comment block holding a
``Copyright <years> <holder>`` line followed by the Apache-2.0 file header of
ament_copyright's template, compared with the formatting (comment marks, line breaks,
spaces) removed; and, at a repository root, LICENSE and CONTRIBUTING.md hold the license.
"""
import re

from lint_targets import COPYRIGHT_EXTENSIONS, lint_paths, ROOT, source_files
import pytest

try:
    from ament_copyright.main import main
except ImportError:
    main = None

#: ament_copyright's Apache-2.0 file header after the copyright line
APACHE2_HEADER = """
Licensed under the Apache License, Version 2.0 (the "License");
you may not use this file except in compliance with the License.
You may obtain a copy of the License at

    http://www.apache.org/licenses/LICENSE-2.0

Unless required by applicable law or agreed to in writing, software
distributed under the License is distributed on an "AS IS" BASIS,
WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
See the License for the specific language governing permissions and
limitations under the License.
"""
#: a sentence of each repository file's Apache-2.0 template in ament_copyright
REPOSITORY_FILE_TEXT = {
    'LICENSE': 'TERMS AND CONDITIONS FOR USE, REPRODUCTION, AND DISTRIBUTION',
    'CONTRIBUTING.md': 'Any contribution that you make to this repository will be under the '
                       'Apache 2 License',
}
#: ament_copyright.parser.get_copyright_information_regex, per line
COPYRIGHT_LINE = re.compile(r'^\s*copyright(?:\s+\(c\))?\s+\d{4}(?:-\d{4})?'
                            r'(?:,\s*\d{4}(?:-\d{4})?)*,?\s+\S', re.IGNORECASE)


def _flat(text):
    return ' '.join(text.split())


def _repository_files():
    """LICENSE and CONTRIBUTING.md, checked by ament_copyright at a repository root."""
    if not (ROOT / '.git').exists():
        return []
    return [str(ROOT / 'LICENSE'), str(ROOT / 'CONTRIBUTING.md')]


def header_problem(text):
    """
    Check the copyright and license header of a source file as ament_copyright does.

    Parameters
    ----------
    text : str
        The file's content.

    Returns
    -------
    str or None
        What is wrong, None when the header is there.

    """
    lines = text.lstrip('\ufeff').splitlines()
    if not lines:
        return None                      # ament_copyright: 'file empty' is no error
    i = 0
    while i < len(lines) and (lines[i].startswith('#!') or (
            lines[i].startswith('#') and ('coding:' in lines[i] or 'coding=' in lines[i]))):
        i += 1
    while i < len(lines) and not lines[i].strip():
        i += 1
    block = []
    while i < len(lines) and lines[i].startswith('#'):
        block.append(lines[i][2:])
        i += 1
    for k, line in enumerate(block):
        if COPYRIGHT_LINE.match(line):
            if _flat(APACHE2_HEADER) in _flat('\n'.join(block[k + 1:])):
                return None
            return 'copyright notice without the Apache-2.0 header below it'
    return 'could not find copyright notice'


@pytest.mark.copyright
@pytest.mark.linter
def test_copyright():
    paths = lint_paths(COPYRIGHT_EXTENSIONS) + _repository_files()
    if main is not None:
        rc = main(argv=paths)
        assert rc == 0, 'Found errors'
        return
    errors = []
    for path in source_files(COPYRIGHT_EXTENSIONS):
        problem = header_problem(path.read_text(encoding='utf-8'))
        if problem:
            errors.append(f'{path.relative_to(ROOT)}: {problem}')
    for name in _repository_files():
        path = ROOT / name
        if not path.is_file() or REPOSITORY_FILE_TEXT[path.name] not in _flat(
                path.read_text(encoding='utf-8')):
            errors.append(f'{path.name}: missing, or not for the Apache License, Version 2.0')
    assert not errors, f'{len(errors)} files without copyright and license:\n' + \
        '\n'.join(errors)


def test_header_check_finds_what_ament_copyright_refuses():
    """The written-out check refuses a file without header, or with another license."""
    header = (ROOT / 'test' / 'lint_targets.py').read_text(encoding='utf-8')
    assert header_problem(header) is None
    assert header_problem('#!/usr/bin/env python3\n\n' + header) is None
    assert header_problem('') is None
    assert header_problem('"""No header."""\n') == 'could not find copyright notice'
    mit = '# Copyright 2026 Someone\n#\n# Permission is hereby granted, free of charge\n'
    assert header_problem(mit) == 'copyright notice without the Apache-2.0 header below it'
    cut = '\n'.join(header.splitlines()[:8]) + '\n'
    assert header_problem(cut) == 'copyright notice without the Apache-2.0 header below it'
