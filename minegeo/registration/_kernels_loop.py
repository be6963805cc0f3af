"""Numba kernels of the registration loop (:mod:`minegeo.registration.loop`; arrays in, no checks).

The loop asks, every iteration, for the *gated nearest neighbour* of each moved source point
``p``: the target point ``q_j`` with the lexicographically smallest ``(sq, j)`` among those with
``sq < d²``, ``sq = dx*dx + dy*dy + dz*dz`` (Open3D ``evaluate_registration``, oracle spec §8).
The answer is defined without reference to a search structure, so every exact search returns
the same bits.

The search is the warm-started KD-tree query of the kernel layer
(:func:`minegeo.kernels.kdtree.kd_nn_warm_serial` / ``kd_nn_warm_parallel``: the previous
partner's ``sq`` only tightens the initial bound, same answer). :func:`compact_matches` turns
the per-row answer into the correspondence list and the inlier sum in one pass.

Determinism: the sum uses the fixed chunking of :mod:`minegeo.kernels.chunks` (partials of
``CHUNK`` consecutive pairs, added serially in chunk order from 0.0), i.e. the bits of
``registration._kernels.sum_kernel`` on the gathered squared distances, whatever the thread count.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit
from minegeo.kernels.chunks import CHUNK

# ----------------------------------------------------------------------------- matches


@njit
def match_stats(idx, sq, m):
    """``(k, total)``: the number of rows with a partner (``idx[i] < m``) and the fixed-chunk sum of
    their ``sq`` (partials of ``CHUNK`` pairs added in chunk order from 0.0: the bits of
    ``registration._kernels.sum_kernel`` on the gathered ``sq[i]``)."""
    total = 0.0
    part = 0.0
    r = 0
    for i in range(idx.shape[0]):
        if idx[i] < m:
            part += sq[i]
            r += 1
            if r % CHUNK == 0:
                total = total + part
                part = 0.0
    if r % CHUNK != 0:
        total = total + part
    return r, total


@njit
def compact_matches(idx, sq, m):
    """``(corr (k, 2), total)``: the pairs ``(i, idx[i])`` with ``idx[i] < m`` in ascending ``i``
    and the sum of their ``sq`` (:func:`match_stats`)."""
    k, total = match_stats(idx, sq, m)
    corr = np.empty((k, 2), dtype=np.int64)
    r = 0
    for i in range(idx.shape[0]):
        j = idx[i]
        if j < m:
            corr[r, 0] = i
            corr[r, 1] = j
            r += 1
    return corr, total


def _warmup() -> None:
    """Compile the kernels of this module on tiny inputs."""
    compact_matches(np.array([0, 4, 2], dtype=np.int64), np.array([0.5, np.inf, 0.25]), 4)
