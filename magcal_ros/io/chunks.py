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

:func:`open_record` returns a :class:`Record`: its size (bytes or messages, for progress)
and ``chunks()``, read again from the start at each call (:mod:`magcal_ros.core.data.reduce`
reads a long record twice).
"""
import os

from magcal_ros.io import csvio
from magcal_ros.io.atomic import atomic_write_text

#: epochs per chunk: ~10 MB of a 4-sensor CSV chunk as float64
CHUNK_ROWS = 65536


class Record:
    """A recording on disk, read in chunks (``chunks(rows)``); ``size`` in ``unit``."""

    def __init__(self, path, kind, size, unit):
        self.path, self.kind, self.size, self.unit = os.fspath(path), kind, size, unit

    def chunks(self, rows=CHUNK_ROWS, progress=None):
        """Yield Dataset pieces of at most ``rows`` epochs; ``progress(done)`` in ``unit``."""
        if self.kind == 'csv':
            return csvio.read_pieces(self.path, rows, progress)
        from magcal_ros.io.bag import bag_chunks
        return bag_chunks(self.path, rows, progress)


def open_record(path):
    """Return the :class:`Record` of a wide CSV file or a rosbag2 directory."""
    path = os.fspath(path)
    if os.path.isdir(path):
        from magcal_ros.io.bag import bag_message_count
        return Record(path, 'bag', bag_message_count(path), 'msg')
    return Record(path, 'csv', os.path.getsize(path), 'B')


def write_csv_chunks(path, pieces, comment=None):
    """
    Write consecutive Dataset ``pieces`` (the same columns) as one wide CSV, atomically.

    One piece in memory at a time.  Returns the number of epochs written.
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
