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
A recording read in chunks of epochs, in bounded memory (wide CSV and rosbag2).

``open_record(path)`` returns a :class:`Record`: its size (bytes or messages, for the
progress bar) and ``chunks()``, Dataset pieces of at most ``rows`` epochs in time order, read
again from the start at each call (a long record is read twice: to reduce it, then for the
residual statistics, :mod:`magcal_ros.core.data.reduce`).

The CSV pieces are the rows :func:`magcal_ros.io.csvio.read_csv` reads, with its checks and
messages: ``numpy.loadtxt`` parses a chunk, and one it cannot (an empty cell, a ``plane``
column, a bad number) is parsed by csvio's line parser, which names what is wrong and where.
Time must not decrease across chunks either.  The rosbag2 pieces come from
:func:`magcal_ros.io.bag.bag_chunks`.
"""
import os

from magcal_ros.io import csvio
from magcal_ros.io.atomic import atomic_write_text
import numpy as np

#: epochs per chunk: ~10 MB of a 4-sensor CSV chunk as float64
CHUNK_ROWS = 65536


class Record:
    """A recording on disk, read in chunks (``chunks(rows)``); ``size`` in ``unit``."""

    def __init__(self, path, kind, size, unit):
        self.path = os.fspath(path)
        self.kind = kind
        self.size = size
        self.unit = unit

    def chunks(self, rows=CHUNK_ROWS, progress=None):
        """Yield Dataset pieces of at most ``rows`` epochs; ``progress(done)`` in ``unit``."""
        if self.kind == 'csv':
            return csv_chunks(self.path, rows, progress)
        from magcal_ros.io.bag import bag_chunks
        return bag_chunks(self.path, rows, progress)


def open_record(path):
    """Return the :class:`Record` of a wide CSV file or a rosbag2 directory."""
    path = os.fspath(path)
    if os.path.isdir(path):
        from magcal_ros.io.bag import bag_message_count
        return Record(path, 'bag', bag_message_count(path), 'msg')
    return Record(path, 'csv', os.path.getsize(path), 'B')


def _data_lines(lines, start):
    """Return (line numbers, data lines) of ``lines`` (the first is line ``start + 1``)."""
    kept = [(no, ln) for no, ln in enumerate(lines, start=start + 1) if csvio.is_content(ln)]
    return np.array([no for no, _ in kept], int), [ln for _, ln in kept]


def csv_chunks(path, rows=CHUNK_ROWS, progress=None):
    """
    Yield the epochs of a wide CSV as Datasets of at most ``rows`` epochs, in file order.

    The same columns, values and errors as :func:`magcal_ros.io.csvio.read_csv`;
    ``progress(bytes_read)`` is called after each chunk.
    """
    path = os.fspath(path)
    from magcal_ros.io.compressed import CorruptArchiveError, open_text
    try:
        yield from _csv_chunks(path, rows, progress, open_text)
    except CorruptArchiveError as exc:
        raise csvio.CsvFormatError(str(exc)) from None
    except OSError as exc:
        raise csvio.CsvFormatError(f'cannot read {path}: {exc.strerror}') from exc


def _csv_chunks(path, rows, progress, open_text):
    with open_text(path, encoding='utf-8-sig') as fh:
        try:
            no, first = csvio.header_line(fh)
            if first is None:
                raise csvio.CsvFormatError(f'{path} has no header row')
            layout = csvio.parse_header(path, first)
            n_cols = len(layout[0])
            t_last = -np.inf
            n_read = 0
            hint = None
            while True:
                # whole lines of about ``rows`` rows (the first chunk: the header's length x
                # rows, then the mean length seen)
                lines = fh.readlines(hint or max(1, len(first)) * rows)
                if not lines:
                    break
                start, no = no, no + len(lines)
                arr = planes = None
                if layout[2] is None:
                    try:
                        arr = np.loadtxt(lines, delimiter=',', comments='#', ndmin=2)
                    except ValueError:
                        arr = None
                    if arr is not None and arr.shape[1] != n_cols:
                        arr = None
                if arr is not None and len(arr) == len(lines):
                    nos, data = np.arange(start + 1, no + 1), lines
                else:
                    nos, data = _data_lines(lines, start)
                    if arr is None or len(arr) != len(data):
                        arr, planes = csvio.parse_rows(path, layout, nos, data)
                if not len(data):
                    continue
                hint = max(1, sum(map(len, lines[:64])) // min(64, len(lines))) * rows
                piece = csvio.build_dataset(path, layout, arr, nos, data, planes)
                if piece.t[0] < t_last:
                    raise csvio.CsvFormatError(
                        f'{path}: column t must be finite and non-decreasing (line {nos[0]})')
                t_last = piece.t[-1]
                n_read += len(data)
                if progress is not None and hasattr(fh, 'buffer'):
                    progress(fh.buffer.tell())
                yield piece
        except UnicodeDecodeError as exc:
            raise csvio.CsvFormatError(f'{path} is not a text CSV file ({exc})') from exc
        if n_read == 0:
            raise csvio.CsvFormatError(f'{path}: no data rows (only the header)')


def write_csv_chunks(path, pieces, comment=None):
    """
    Write consecutive Dataset ``pieces`` (the same columns) as one wide CSV, atomically.

    One piece is formatted at a time (:func:`magcal_ros.io.csvio.format_csv`): memory is that
    of a piece, whatever the length of the record.  Returns the number of epochs written.
    """
    count = [0]

    def parts():
        for i, piece in enumerate(pieces):
            text = csvio.format_csv(piece, comment if i == 0 else None)
            if i:
                text = text.split('\n', 1)[1]          # the header once
            count[0] += piece.n_samples
            yield text
    from magcal_ros.io.compressed import compress_parts, compression
    atomic_write_text(path, compress_parts(path, parts()), backup=False,
                      binary=compression(path) is not None)
    return count[0]
