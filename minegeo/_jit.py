"""The one place where Numba compilation options are set.

All kernels use ``from minegeo._jit import njit, prange`` (or ``njit_parallel``)
so that caching, fastmath (always off: it breaks bit reproducibility and IEEE
NaN handling) and error model are consistent across the package.
"""

from __future__ import annotations

import os

# The OpenMP threads of Numba's "omp" threading layer (GNU libgomp) sleep when a parallel region ends
# instead of spinning for the next one (libgomp's default spins ~300,000 iterations): on a machine
# whose cores are shared, the spinning thread takes the core the other thread of the next region
# needs. SLAM front end per 10 Hz sweep at 2 threads on the shared 2-core machine (load 12-18), median
# CPU 73-94 ms spinning (benchmarks/results/realtime_2026-11-29_serial_t2.md), 21-22 ms passive
# (realtime_2026-11-29.md); wall 286-587 ms -> 90-125 ms. The price, on an idle machine: a single GICP
# registration 22-24 ms instead of 15-17 ms (a wake-up per parallel region), SLAM's wall time per sweep
# unchanged (benchmarks/results/omp_wait_2026-11-30/README.md, with spin counts in between). Read by
# libgomp when it loads (the first parallel kernel, or numba.set_num_threads); a user's own
# OMP_WAIT_POLICY or GOMP_SPINCOUNT wins (GOMP_SPINCOUNT=300000: libgomp's spinning). Same bits either way.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
from numba import prange  # noqa: E402

__all__ = ["njit", "njit_parallel", "prange", "NJIT_OPTIONS", "NJIT_PARALLEL_OPTIONS"]

#: Options for serial kernels. ``fastmath`` stays off for reproducibility.
NJIT_OPTIONS = {"cache": True, "fastmath": False, "nogil": True, "error_model": "numpy"}
#: Options for kernels whose outer loop is an independent ``prange``.
NJIT_PARALLEL_OPTIONS = {**NJIT_OPTIONS, "parallel": True}


def njit(*args, **kwargs):
    """``numba.njit`` with minegeo's options (serial). Usable bare or with a signature."""
    opts = {**NJIT_OPTIONS, **kwargs}
    if len(args) == 1 and callable(args[0]) and not kwargs:
        return numba.njit(**opts)(args[0])
    return numba.njit(*args, **opts)


def njit_parallel(*args, **kwargs):
    """``numba.njit(parallel=True)`` with minegeo's options; use ``prange`` for the outer loop."""
    opts = {**NJIT_PARALLEL_OPTIONS, **kwargs}
    if len(args) == 1 and callable(args[0]) and not kwargs:
        return numba.njit(**opts)(args[0])
    return numba.njit(*args, **opts)
