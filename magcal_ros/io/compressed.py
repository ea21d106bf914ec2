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
Text files read through gzip or Zstandard when their name says so (``.gz``, ``.zst``).

Decompressed as it is read; a corrupt or truncated archive raises
:class:`CorruptArchiveError` (one line: the file, the format, what to do).
"""
import contextlib
import gzip
import io
import os
import zlib

#: file-name endings (lower case) and the compression they mean
SUFFIXES = {'.gz': 'gzip', '.zst': 'zstd'}


class CorruptArchiveError(ValueError):
    """A compressed file cannot be decompressed (corrupt, truncated or not that format)."""


def compression(path):
    """Return 'gzip', 'zstd' or None from the file name's last suffix (case-insensitive)."""
    return SUFFIXES.get(os.path.splitext(os.fspath(path))[1].lower())


def compress_text(path, text):
    """``text`` as UTF-8 bytes compressed as the name of ``path`` says, else unchanged."""
    kind = compression(path)
    if kind == 'gzip':
        return gzip.compress(text.encode('utf-8'), mtime=0)
    if kind == 'zstd':
        import zstandard
        return zstandard.ZstdCompressor(level=10).compress(text.encode('utf-8'))
    return text


def compress_parts(path, parts):
    """Yield str ``parts`` compressed as one stream as ``path``'s name says (plain: as is)."""
    kind = compression(path)
    if kind is None:
        yield from parts
        return
    if kind == 'gzip':
        z = zlib.compressobj(9, zlib.DEFLATED, 31)        # wbits 31: the gzip container
    else:
        import zstandard
        z = zstandard.ZstdCompressor(level=10).compressobj()
    for part in parts:
        out = z.compress(part.encode('utf-8'))
        if out:
            yield out
    yield z.flush()


class _ZstdReader(io.RawIOBase):
    """
    A Zstandard file's decompressed bytes, frame after frame.

    EOFError at a frame cut short (as gzip), where zstandard's ``stream_reader`` ends quietly.
    """

    _CHUNK = 1 << 17

    def __init__(self, path):
        try:
            import zstandard
        except ImportError:                          # pragma: no cover - a requirement
            raise CorruptArchiveError(
                f'{path}: reading .zst needs the zstandard package (pip install zstandard, '
                'see requirements.txt), or decompress it first (zstd -d)') from None
        self._dctx = zstandard.ZstdDecompressor()
        self._raw = open(path, 'rb')
        self._obj = None                             # the frame being decompressed
        self._pending = b''                          # compressed bytes not yet fed
        self._out = b''                              # decompressed bytes not yet returned

    def readable(self):
        return True

    def close(self):
        if not self.closed:
            self._raw.close()
        super().close()

    def readinto(self, buf):
        while not self._out:
            if not self._fill():
                return 0
        n = min(len(buf), len(self._out))
        buf[:n] = self._out[:n]
        self._out = self._out[n:]
        return n

    def _fill(self):
        """Decompress more into self._out; False at the clean end of the file."""
        if not self._pending:
            self._pending = self._raw.read(self._CHUNK)
            if not self._pending:
                if self._obj is not None and not self._obj.eof:
                    raise EOFError('the file ends inside a Zstandard frame')
                return False
        if self._obj is None or self._obj.eof:
            self._obj = self._dctx.decompressobj()
        data, self._pending = self._pending, b''
        self._out = self._obj.decompress(data)
        if self._obj.eof:
            self._pending = self._obj.unused_data
        return True


@contextlib.contextmanager
def open_text(path, encoding='utf-8', errors='strict'):
    """
    Open ``path`` for reading text (a context manager), decompressing ``.gz`` or ``.zst``.

    A decompression error inside the ``with`` block becomes :class:`CorruptArchiveError`.
    """
    path = os.fspath(path)
    kind = compression(path)
    if kind == 'gzip':
        fh = gzip.open(path, 'rt', encoding=encoding, errors=errors)
        bad = (gzip.BadGzipFile, EOFError, zlib.error)
    elif kind == 'zstd':
        fh = io.TextIOWrapper(io.BufferedReader(_ZstdReader(path)), encoding=encoding,
                              errors=errors)
        import zstandard                             # imported by _ZstdReader: no cost
        bad = (zstandard.ZstdError, EOFError)
    else:
        fh = open(path, encoding=encoding, errors=errors)
        bad = ()
    with fh:
        try:
            yield fh
        except bad as exc:
            tool = {'gzip': 'gzip -t', 'zstd': 'zstd -t'}[kind]
            raise CorruptArchiveError(
                f'{path}: the {kind} archive is corrupt or truncated ({exc}); check it with '
                f'`{tool} {os.path.basename(path)}` and copy or export it again, or name it '
                f'without the {os.path.splitext(path)[1]} suffix if it is not compressed'
            ) from None
