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
Progress bars of the long steps of ``magcal`` (reading, fitting, screening, the report).

One tqdm bar per step on stderr (never stdout): name, progress, time spent and left. Silent
with ``--quiet``, with ``--json``, and when stderr is not a terminal (a log, a pipe, a test).
"""
import sys


def wanted(quiet=False, json_out=False, stream=None):
    """Tell whether bars are drawn: not quiet, no JSON on stdout, stderr a terminal."""
    stream = sys.stderr if stream is None else stream
    return (not quiet and not json_out and bool(getattr(stream, 'isatty', lambda: False)()))


class Progress:
    """
    Progress of the steps of one command: ``progress(step, i, n, label)``.

    ``i`` of ``n`` parts of ``step`` done, ``label`` the part under way; :meth:`bar` gives a
    bar for a loop counting its own unit (bytes, messages). ``enabled=False``: all no-ops.
    """

    def __init__(self, enabled=True, stream=None):
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(enabled)
        self._bar = None
        self._step = None

    def __call__(self, step, i, n, label=''):
        """Report that ``i`` of ``n`` parts of ``step`` are done (``label``: the current one)."""
        if not self.enabled:
            return
        if self._bar is None or step != self._step or self._bar.total != n:
            self.close()
            self._bar = self.bar(step, total=n)
            self._step = step
        self._bar.set_postfix_str(str(label)[:40], refresh=False)
        self._bar.update(max(0, i - self._bar.n))
        if i >= n:
            self.close()

    def bar(self, step, total=None, unit='it', scale=False):
        """Return a tqdm bar named ``step`` (``total`` parts of ``unit``); none when silent."""
        from tqdm import tqdm
        return tqdm(total=total, desc=step, unit=unit, unit_scale=scale, file=self.stream,
                    disable=not self.enabled, leave=True, dynamic_ncols=True,
                    mininterval=0.2)

    def close(self):
        """Finish the bar of the current step."""
        if self._bar is not None:
            self._bar.close()
        self._bar = None
        self._step = None
