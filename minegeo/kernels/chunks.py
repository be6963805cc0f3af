"""Fixed chunking of reductions over rows (thread-count independent summation order).

The rows are cut into chunks of ``CHUNK`` consecutive rows, each chunk's partial sums are
computed independently (``prange`` over chunks), and the partials are then added serially in
chunk order. The floating-point summation order therefore depends only on the number of rows,
never on the number of threads, so results are bit-identical on 1 or N threads.
"""

from __future__ import annotations

from minegeo._jit import njit

__all__ = ["CHUNK", "n_chunks", "PARALLEL_QUERY_ROWS"]

#: Rows per reduction chunk (fixed so that summation order is thread-count independent).
CHUNK = 1024

#: Nearest-neighbour queries cost ~1 µs per row (a tree descent), so the query drivers switch to
#: ``prange`` from this many rows. Measured on the idle 2-core machine (the ICP stages of
#: benchmarks/bench_registration.py): serial queries made minegeo's ICP 1.15-1.42x Open3D's
#: time, parallel queries from 4096 rows bring it below 1.
PARALLEL_QUERY_ROWS = 1 << 12


@njit
def n_chunks(m):
    """Number of ``CHUNK``-row chunks covering ``m`` rows (0 for m = 0)."""
    return (m + CHUNK - 1) // CHUNK
