"""Numba kernels of :mod:`minegeo.localize.gravity` (contiguous float64 arrays in, no checks).

:func:`normal_density` is a Hough transform of surface orientations: for every axis of a
half-sphere grid, the area of the surfels whose normal lies in a cone around it (floors and
walls are its modes).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit_parallel, prange


@njit_parallel
def normal_density(N, W, D, cos_t, out):
    """Area of the surfels whose (unsigned) normal lies within ``acos(cos_t)`` of each axis.

    Parameters
    ----------
    N : (m, 3) float64
        Unit normals (any sign).
    W : (m,) float64
        Area weights.
    D : (k, 3) float64
        Unit axes.
    cos_t : float
        Cosine of the cone radius.
    out : (k,) float64
        Summed weights per axis.
    """
    for k in prange(D.shape[0]):
        s = 0.0
        for i in range(N.shape[0]):
            c = N[i, 0] * D[k, 0] + N[i, 1] * D[k, 1] + N[i, 2] * D[k, 2]
            if c > cos_t or -c > cos_t:
                s += W[i]
        out[k] = s


def _warmup() -> None:
    N = np.random.default_rng(0).normal(size=(50, 3))
    N /= np.linalg.norm(N, axis=1)[:, None]
    W = np.full(50, 1.0 / 50)
    out = np.empty(3)
    normal_density(N, W, np.eye(3), 0.9, out)
