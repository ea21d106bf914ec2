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

"""Atomic file replacement: temporary file in the same directory, fsync, rename."""
import contextlib
import os
import shutil
import tempfile


def atomic_write_text(path, text, backup=True, fsync=os.fsync, binary=None):
    """
    Write ``text`` to ``path`` so that readers see the old or the new file, never a mix.

    ``text``: str, bytes, or an iterable of str (of bytes with ``binary``) written in turn.
    ``backup`` keeps ``<path>.bak``; on failure the original stays.  ``fsync`` injectable.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', suffix='.tmp',
                               dir=directory)
    try:
        binary = isinstance(text, bytes) if binary is None else binary
        with os.fdopen(fd, 'wb' if binary else 'w',
                       **({} if binary else {'encoding': 'utf-8'})) as fh:
            for part in ([text] if isinstance(text, (str, bytes)) else text):
                fh.write(part)
            fh.flush()
            fsync(fh.fileno())
        if backup and os.path.exists(path):
            shutil.copy2(path, path + '.bak')
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):          # the rename made durable, where it can be
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
