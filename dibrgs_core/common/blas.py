"""numpy's and scipy's BLAS on one thread.

The library's numpy matrix products are small-sided: points or pixels times a 3x3 or 3x4 camera
matrix, memory-bound however many rows they have. OpenBLAS (numpy's and scipy's wheels each bundle
one) still splits them over every core, and its workers then spin for a while before sleeping,
taking the cores from torch's own threads. Measured on 2 cores (docs/benchmarks.md, "BLAS on one
thread"): building 96 pseudo views took 15.7 s of wall time and 31.0 s of CPU with OpenBLAS's two
threads (half of it kernel time, in the spinning workers' ``sched_yield``), 16.2 s and 16.2 s with
one. Torch's threads (``--threads``) are separate and unaffected.

Process-wide, set by the commands that compute (``commands.options.apply_compute``) and by the
benchmarks that time them, never on import. A user's own ``OPENBLAS_NUM_THREADS``,
``MKL_NUM_THREADS``, ``BLIS_NUM_THREADS`` or ``OMP_NUM_THREADS`` is left alone.
"""
from __future__ import annotations

import os
from typing import Mapping

#: Environment variables by which a user chooses BLAS threads themselves.
USER_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS", "OMP_NUM_THREADS")

_choice = "the BLAS libraries' defaults (single_thread_blas was not called)"


def single_thread_blas(environ: Mapping[str, str] = os.environ) -> str:
    """Limit the BLAS libraries numpy and scipy load to one thread (see the module docstring);
    returns what was done, for the log."""
    global _choice
    mine = [k for k in USER_VARIABLES if k in environ]
    if mine:
        _choice = f"the user's {' / '.join(mine)}"
        return _choice
    import numpy  # noqa: F401  (threadpoolctl changes only libraries already loaded)
    import scipy.linalg  # noqa: F401  (scipy's wheels bundle their own OpenBLAS)

    try:
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError:  # an environment set up before it was a dependency: slower, not wrong
        _choice = "the BLAS libraries' defaults (threadpoolctl is not installed: pip install threadpoolctl)"
        return _choice

    threadpool_limits(limits=1, user_api="blas")
    libs = sorted({f"{i['internal_api']} {i['num_threads']}" for i in threadpool_info() if i["user_api"] == "blas"})
    _choice = f"one thread ({', '.join(libs) or 'no BLAS library loaded'})"
    return _choice


def blas_policy() -> str:
    """What :func:`single_thread_blas` did in this process."""
    return _choice
