"""Numba kernel of :mod:`minegeo.slam.frame_covariances`: plane-like GICP covariances from given kNN lists.

Contiguous float64 arrays in, no checks."""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit_parallel, prange
from minegeo.kernels.eig3 import centred_covariance, jacobi_min3


@njit_parallel
def plane_covariances_from_lists(Q, idx, eps, ratio):
    """``C_i = I − (1 − ε) n_i n_iᵀ`` (n, 3, 3) with ``n_i`` the PCA normal (two-pass covariance centred
    on the mean, cyclic Jacobi: :func:`minegeo.kernels.eig3.centred_covariance`,
    :func:`~minegeo.kernels.eig3.jacobi_min3`) of the rows ``idx[i]`` of ``Q``; ``I`` when the
    neighbourhood is coincident or collinear (middle eigenvalue ``<= ratio`` times the largest)."""
    n, k = idx.shape
    C = np.zeros((n, 3, 3))
    for i in prange(n):  # independent per point
        c = centred_covariance(Q, idx[i], k, idx[i, 0])
        n0, n1, n2, l0, l1, l2 = jacobi_min3(c[0], c[1], c[2], c[3], c[4], c[5])
        C[i, 0, 0] = C[i, 1, 1] = C[i, 2, 2] = 1.0
        if l2 > 0.0 and l1 > ratio * l2:
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            n0 /= nn
            n1 /= nn
            n2 /= nn
            f = 1.0 - eps
            C[i, 0, 0] -= f * n0 * n0
            C[i, 1, 1] -= f * n1 * n1
            C[i, 2, 2] -= f * n2 * n2
            C[i, 0, 1] = C[i, 1, 0] = -f * n0 * n1
            C[i, 0, 2] = C[i, 2, 0] = -f * n0 * n2
            C[i, 1, 2] = C[i, 2, 1] = -f * n1 * n2
    return C
