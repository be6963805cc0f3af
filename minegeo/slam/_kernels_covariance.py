"""Numba kernel of :mod:`minegeo.slam.frame_covariances`: PCA normals from given kNN lists.

Contiguous float64 arrays in, no checks."""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit_parallel, prange
from minegeo.kernels.eig3 import STATUS_OK, centred_covariance, jacobi_min3, store_normal


@njit_parallel
def plane_normals_from_lists(Q, idx, ratio):
    """PCA normals (n, 3; as the eigen-solve gives them, the consumer normalises) of the rows ``idx[i]`` of ``Q`` (covariance centred on the mean after
    differences from ``Q[idx[i, 0]]``, cyclic Jacobi: :func:`minegeo.kernels.eig3.centred_covariance`,
    :func:`~minegeo.kernels.eig3.jacobi_min3`); the zero vector where the neighbourhood has no surface
    model (:func:`minegeo.kernels.eig3.store_normal`'s status: coincident, or collinear when the middle
    eigenvalue is ``<= ratio`` times the largest)."""
    n, k = idx.shape
    N = np.zeros((n, 3))
    ev = np.empty((n, 3))
    status = np.empty(n, dtype=np.int8)
    for i in prange(n):  # independent per point
        c = centred_covariance(Q, idx[i], k, idx[i, 0])
        n0, n1, n2, l0, l1, l2 = jacobi_min3(c[0], c[1], c[2], c[3], c[4], c[5])
        store_normal(i, n0, n1, n2, l0, l1, l2, ratio, True, N, ev, status)
        if status[i] != STATUS_OK:
            N[i, 0] = N[i, 1] = N[i, 2] = 0.0
    return N
