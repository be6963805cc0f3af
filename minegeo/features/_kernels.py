"""Numba kernels for FPFH (Rusu et al. 2009; Baek et al. 2022, Sec. 2.3.1, [Baek2022 Eqs. 3-6]).

Kernels take C-contiguous float64/int64 arrays and do no checking; the public
function :func:`minegeo.features.compute_fpfh` validates and documents.

Neighbourhood layout (shared with ``minegeo.geometry.Neighborhoods``): ``nbr_idx``
is ``(n, kmax)`` int64 padded with -1, ``nbr_sq`` the matching squared distances
(padded with inf) sorted ascending, ``counts`` the number of valid entries per
row; position 0 is the query point itself.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit, njit_parallel, prange

#: Bins per angular feature and descriptor length (3 x 11 = 33).
N_BINS = 11
N_FEATURES = 33
#: Weight modes for [Baek2022 Eq. 6]: 0 = 1/d (paper), 1 = 1/d^2 (Open3D and PCL).
WEIGHT_INVERSE_DISTANCE = 0
WEIGHT_OPEN3D = 1


@njit
def pair_features(p1, n1, p2, n2):
    """Darboux-frame pair features ``(f1, f2, f3, f4)`` of a query point and one neighbour.

    Open3D's ``ComputePairFeatures``: with ``d = p2 - p1`` the source of the frame
    is the point whose normal makes the smaller angle with the connecting line
    (swap rule); then ``u = n1'``, ``v = d' x u / |d' x u|``, ``w = u x v`` and

    * ``f1 = atan2(w . n2', u . n2')``  (theta, [Baek2022 Eq. 5]), in [-pi, pi]
    * ``f2 = v . n2'``                   (alpha, [Baek2022 Eq. 3]), in [-1, 1]
    * ``f3 = u . d' / |d'|``             (phi, [Baek2022 Eq. 4]), in [-1, 1]
    * ``f4 = |d|`` (unused in the histogram).

    Returns all zeros for coincident points or ``d' || u``.
    """
    dx = p2[0] - p1[0]
    dy = p2[1] - p1[1]
    dz = p2[2] - p1[2]
    f4 = math.sqrt(dx * dx + dy * dy + dz * dz)
    if f4 == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    a1 = (n1[0] * dx + n1[1] * dy + n1[2] * dz) / f4
    a2 = (n2[0] * dx + n2[1] * dy + n2[2] * dz) / f4
    if abs(a1) < abs(a2):
        ux, uy, uz = n2[0], n2[1], n2[2]
        mx, my, mz = n1[0], n1[1], n1[2]
        dx, dy, dz = -dx, -dy, -dz
        f3 = -a2
    else:
        ux, uy, uz = n1[0], n1[1], n1[2]
        mx, my, mz = n2[0], n2[1], n2[2]
        f3 = a1
    # v = d' x u
    vx = dy * uz - dz * uy
    vy = dz * ux - dx * uz
    vz = dx * uy - dy * ux
    vn = math.sqrt(vx * vx + vy * vy + vz * vz)
    if vn == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    vx /= vn
    vy /= vn
    vz /= vn
    # w = u x v
    wx = uy * vz - uz * vy
    wy = uz * vx - ux * vz
    wz = ux * vy - uy * vx
    f2 = vx * mx + vy * my + vz * mz
    f1 = math.atan2(wx * mx + wy * my + wz * mz, ux * mx + uy * my + uz * mz)
    return f1, f2, f3, f4


@njit_parallel
def spfh_kernel(points, normals, nbr_idx, counts, row0):
    """Simplified point feature histograms (SPFH) of points ``row0 .. row0 + m - 1``, ``(m, 33)``.

    Row r of the neighbour table belongs to point ``i = row0 + r``. For each point i with ``m = counts[i] > 1`` neighbours (self at position 0),
    every neighbour at positions 1..m-1 adds ``100 / (m - 1)`` to one bin of each
    of the three 11-bin blocks (theta, alpha, phi). Degenerate pairs give the zero
    feature and land in the middle bins (5, 16, 27), as in Open3D.
    """
    nrow = nbr_idx.shape[0]
    out = np.zeros((nrow, N_FEATURES))
    two_pi = 2.0 * math.pi
    for i in prange(nrow):
        m = counts[i]
        if m <= 1:
            continue
        inc = 100.0 / (m - 1)
        p1 = points[row0 + i]
        n1 = normals[row0 + i]
        for k in range(1, m):
            j = nbr_idx[i, k]
            f1, f2, f3, _f4 = pair_features(p1, n1, points[j], normals[j])
            h = int(math.floor(N_BINS * (f1 + math.pi) / two_pi))
            if h < 0:
                h = 0
            if h >= N_BINS:
                h = N_BINS - 1
            out[i, h] += inc
            h = int(math.floor(N_BINS * (f2 + 1.0) * 0.5))
            if h < 0:
                h = 0
            if h >= N_BINS:
                h = N_BINS - 1
            out[i, N_BINS + h] += inc
            h = int(math.floor(N_BINS * (f3 + 1.0) * 0.5))
            if h < 0:
                h = 0
            if h >= N_BINS:
                h = N_BINS - 1
            out[i, 2 * N_BINS + h] += inc
    return out


@njit_parallel
def fpfh_kernel(spfh, nbr_idx, nbr_sq, counts, weight_mode, row0):
    """FPFH of points ``row0 .. row0 + m - 1`` from the SPFH of all points, ``(m, 33)``.

    [Baek2022 Eq. 6] with per-block normalisation; row r of the neighbour table belongs to point
    ``i = row0 + r``.

    ``acc = sum_k SPFH_k / w_k`` over neighbours at positions 1.. with non-zero
    distance, where ``w_k = d_k^2`` (Open3D, ``weight_mode=1``) or ``w_k = d_k``
    ([Baek2022 Eq. 6], ``weight_mode=0``). Each 11-bin block of ``acc`` is scaled to
    sum to 100 (left at zero if its sum is zero), then ``SPFH_i`` is added.
    """
    nrow = nbr_idx.shape[0]
    out = np.zeros((nrow, N_FEATURES))
    for i in prange(nrow):
        m = counts[i]
        if m <= 1:
            continue
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(1, m):
            dist = nbr_sq[i, k]
            if dist == 0.0:
                continue
            if weight_mode == WEIGHT_INVERSE_DISTANCE:
                dist = math.sqrt(dist)
            j = nbr_idx[i, k]
            # three branch-free block loops; same operations and order as Open3D
            for b in range(N_BINS):
                val = spfh[j, b] / dist
                out[i, b] += val
                s0 += val
            for b in range(N_BINS, 2 * N_BINS):
                val = spfh[j, b] / dist
                out[i, b] += val
                s1 += val
            for b in range(2 * N_BINS, N_FEATURES):
                val = spfh[j, b] / dist
                out[i, b] += val
                s2 += val
        if s0 != 0.0:
            s0 = 100.0 / s0
        if s1 != 0.0:
            s1 = 100.0 / s1
        if s2 != 0.0:
            s2 = 100.0 / s2
        for b in range(N_BINS):
            out[i, b] = out[i, b] * s0 + spfh[row0 + i, b]
        for b in range(N_BINS, 2 * N_BINS):
            out[i, b] = out[i, b] * s1 + spfh[row0 + i, b]
        for b in range(2 * N_BINS, N_FEATURES):
            out[i, b] = out[i, b] * s2 + spfh[row0 + i, b]
    return out
