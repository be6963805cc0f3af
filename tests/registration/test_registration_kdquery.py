"""The parallel gated KD-tree query (used from PARALLEL_QUERY_ROWS rows) equals the serial one and brute force."""

from __future__ import annotations

import numba
import numpy as np

from minegeo.kernels import kdtree as KD
from minegeo.kernels.chunks import PARALLEL_QUERY_ROWS


def test_parallel_query_equals_serial_and_brute_force(rng):
    Q = np.ascontiguousarray(rng.uniform(-5, 5, (3000, 3)))
    Q[1500:1510] = Q[:10]  # duplicates: ties go to the lowest index
    n = PARALLEL_QUERY_ROWS + 1001
    P = np.ascontiguousarray(rng.uniform(-5.5, 5.5, (n, 3)))
    P[:10] = Q[:10]
    tree = KD.GatedKDTree(Q)
    d2 = 0.4**2
    idx_s = np.empty(n, dtype=np.int64)
    sq_s = np.empty(n)
    KD.kd_nn_serial(P, tree.packed, d2, idx_s, sq_s)
    old = numba.get_num_threads()
    try:
        for threads in (1, old):
            numba.set_num_threads(threads)
            idx_p, sq_p = tree.query(P, d2)  # n >= PARALLEL_QUERY_ROWS: the prange driver
            assert np.array_equal(idx_p, idx_s) and np.array_equal(sq_p, sq_s)
    finally:
        numba.set_num_threads(old)
    # brute force: nearest strictly within the gate, lowest index on ties
    D = ((P[:, None, :] - Q[None, :, :]) ** 2).sum(axis=2)
    D[D >= d2] = np.inf
    j = np.argmin(D, axis=1)
    none = ~np.isfinite(D[np.arange(n), j])
    j[none] = Q.shape[0]
    assert np.array_equal(idx_s, j)
    assert np.all(idx_s[:10] == np.arange(10))
