"""The one place where Numba compilation options are set.

All kernels use ``from minegeo._jit import njit, prange`` (or ``njit_parallel``)
so that caching, fastmath (always off: it breaks bit reproducibility and IEEE
NaN handling) and error model are consistent across the package.
"""

from __future__ import annotations

import numba
from numba import prange

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
