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

One BLAS thread. The linear algebra here is small or tall-skinny: a 2000 x 10 SVD for the
coverage in every status message, P x P solves, products with a few columns. With
OpenBLAS' default of one thread per core, each such call starts and spins the other
threads: on this project's 2-core machine with a second process busy, a 2000 x 10 SVD took
36 ms of CPU against 0.4 ms on one thread (BENCHMARKS.md, "One BLAS thread per process"),
and a live node spent a fifth of a core on its status alone. The library's fit and
diagnosis already limit BLAS around themselves
(:func:`magcal_ros.core.model.solvers.single_threaded_blas`); this does it once for the
whole process. A user who sets ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or
``MKL_NUM_THREADS`` keeps that setting.
"""
import os

#: environment variables by which a user chooses the BLAS threads themselves
THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')

_limits = None


def limit_blas_threads():
    """
    Run BLAS on one thread for the rest of this process, unless the user chose otherwise.

    Returns
    -------
    str
        What was done, for a log line: ``'1 thread'``, ``'as OPENBLAS_NUM_THREADS=...'``, or
        ``'unchanged (threadpoolctl not installed)'``.

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
    # the limit reaches only libraries already loaded: numpy's OpenBLAS now; scipy's
    # own OpenBLAS, loaded later (or never: a driver or a simulator needs none of it,
    # and importing scipy.linalg only to limit it cost a node ~0.3 s of CPU at every
    # start), reads the variable when it loads. Processes started from here inherit
    # it, and run on one thread as they would anyway.
    import numpy  # noqa: F401
    _limits = threadpool_limits(limits=1, user_api='blas')
    os.environ['OPENBLAS_NUM_THREADS'] = '1'
    return '1 thread'
