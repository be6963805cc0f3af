"""Fixed chunking of reductions over rows (thread-count independent summation order).

The rows are cut into chunks of ``CHUNK`` consecutive rows, each chunk's partial sums are
computed independently (``prange`` over chunks), and the partials are then added serially in
chunk order. The floating-point summation order therefore depends only on the number of rows,
never on the number of threads, so results are bit-identical on 1 or N threads.
"""

from __future__ import annotations

from minegeo._jit import njit

__all__ = ["CHUNK", "n_chunks", "by_size", "PARALLEL_QUERY_ROWS", "QUERY_TASK_ROWS"]

#: Rows per reduction chunk (fixed so that summation order is thread-count independent).
CHUNK = 1024

#: Nearest-neighbour queries cost ~1 µs per row (a tree descent), so the query drivers switch to
#: ``prange`` from this many rows. Measured on the idle 2-core machine (the ICP stages of
#: benchmarks/bench_registration.py): serial queries made minegeo's ICP 1.15-1.42x Open3D's
#: time, parallel queries from 4096 rows bring it below 1.
PARALLEL_QUERY_ROWS = 1 << 12

#: Rows per task of the parallel 1-NN query drivers. Each row is independent (no reduction), so
#: the rows are cut finer than the reductions' ``CHUNK``: 4,761 queries are 38 tasks shared
#: evenly by 2 threads instead of 5 chunks split 3:2. Per-row results: any split gives the same bits.
QUERY_TASK_ROWS = 128


@njit
def n_chunks(m):
    """Number of ``CHUNK``-row chunks covering ``m`` rows (0 for m = 0)."""
    return (m + CHUNK - 1) // CHUNK


def by_size(rows, threshold, serial, parallel):
    """The driver of a kernel for ``rows`` rows: its ``prange`` form ``parallel`` from ``threshold``
    rows on, else ``serial``.

    Chosen from the problem size only, never from the machine's load. A kernel's two drivers run
    the same row or chunk bodies in the same order (fixed chunks), so either gives the same bits.
    """
    return parallel if rows >= threshold else serial
