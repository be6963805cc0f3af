"""The shared Numba kernel layer of minegeo (contiguous float64/int64 arrays in, no checks).

One place for the numerical building blocks that several packages use; the public, validated,
documented functions live in the packages (``geometry``, ``registration``, ``localize``,
``survey``) and call these kernels. ``docs/kernels.md`` lists every kernel, its equation tag and
its naive twin in ``tests/reference/naive_kernels.py``.

Modules
-------
chunks
    Fixed chunking of reductions (``CHUNK``, :func:`~minegeo.kernels.chunks.n_chunks`): the
    summation order depends on the number of rows only, never on the thread count.
hashgrid
    Open-addressing hash table of int64 keys (Fibonacci hashing, linear probing).
kdtree
    Sliding-midpoint 3-D KD-tree: build, gated 1-NN, exact kNN, radius search.
eig3
    3x3 symmetric eigen-solvers (closed form, Jacobi) and neighbourhood PCA.
rigid
    Umeyama / Kabsch rigid and similarity fits (from points and from moments) and the 4-DOF
    yaw fit.
lie
    SO(3), SE(3) and SE(2) exponential and logarithm, hat/vee, Jacobians, adjoint.

The submodules are imported explicitly (``from minegeo.kernels import kdtree``); importing this
package compiles nothing.
"""

__all__ = ["chunks", "hashgrid", "kdtree", "eig3", "rigid", "lie"]
