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
Run a Python module as ``python -m`` would and write its peak resident memory to a file.

    python bench/peak_rss.py OUT_FILE MODULE [ARGS...]

Writes the process's ``VmHWM`` (kB, /proc/self/status) to OUT_FILE when the module exits.
Why not ``ru_maxrss`` of ``wait4``: Linux carries a child's maximum RSS over ``exec`` from
the process it was forked from (with ``vfork``, the parent's whole peak), so a benchmark's
own memory shows in every child it measures; ``VmHWM`` belongs to the memory map the
executed program made itself.  Nothing but the standard library is imported here.
"""
import atexit
import runpy
import sys


def _write_hwm(path):
    with open('/proc/self/status') as fh:
        for line in fh:
            if line.startswith('VmHWM:'):
                with open(path, 'w') as out:
                    out.write(line.split()[1] + '\n')
                return


def main():
    """Run ``sys.argv[2]`` as ``__main__`` with the arguments after it."""
    out, module = sys.argv[1], sys.argv[2]
    atexit.register(_write_hwm, out)
    sys.argv = [module] + sys.argv[3:]
    runpy.run_module(module, run_name='__main__', alter_sys=True)


if __name__ == '__main__':
    main()
