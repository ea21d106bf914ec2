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
Process-wide settings of magcal_ros' executables (the ``magcal`` command, the nodes, demos).

One BLAS thread: the linear algebra here is small or tall-skinny, and extra threads only
spin (BENCHMARKS.md, "One BLAS thread per process"); a user's choice of threads is kept.
"""
import os

#: environment variables by which a user chooses the BLAS threads themselves
THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')

_limits = None


def limit_blas_threads():
    """
    Run BLAS on one thread for the rest of this process, unless the user chose otherwise.

    Returns what was done, for a log line: ``'1 thread'``, ``'as OPENBLAS_NUM_THREADS=...'``
    or ``'unchanged (threadpoolctl not installed)'``.
    """
    global _limits
    if _limits is not None:
        return '1 thread'
    chosen = [f'{k}={os.environ[k]}' for k in THREAD_VARIABLES if os.environ.get(k)]
    if chosen:
        return 'as ' + ', '.join(chosen)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:                   # pragma: no cover - a declared dependency
        return 'unchanged (threadpoolctl not installed)'
    # the limit reaches numpy's OpenBLAS now; scipy's, loaded later or never (importing it
    # only to limit it cost a node ~0.3 s at start), and child processes read the variable
    import numpy  # noqa: F401
    _limits = threadpool_limits(limits=1, user_api='blas')
    os.environ['OPENBLAS_NUM_THREADS'] = '1'
    return '1 thread'
