"""RANSAC sample check for levelled frames (4-DOF: yaw + translation); contiguous arrays in, no checks.

Status codes are those of :mod:`minegeo.registration._kernels_ransac`; the 4-DOF fit is
:func:`minegeo.kernels.rigid.yaw_fit`.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit
from minegeo.kernels.rigid import yaw_fit
from minegeo.registration._kernels_ransac import ST_DEGENERATE, ST_DISTANCE, ST_EDGE, ST_EVALUATED


@njit
def ransac_check_levelled_kernel(csrc, ctgt, samples, sim, dist_thr, min_spread_m2, distinct):
    """Prune and fit a batch of levelled RANSAC samples (rows of ``samples``, n >= 2); serial.

    0. if ``distinct``, a sample repeating a correspondence is rejected (ST_DEGENERATE);
    1. edge-length test ([Baek2022 Eq. 7]) on every pair of the sample: ``min(l_s, l_t) >= sim * max(l_s, l_t)``;
    2. yaw + translation by :func:`yaw_fit`; rejected (ST_DEGENERATE) if the horizontal spread
       of the source sample is below ``min_spread_m2`` (the yaw is undetermined);
    3. distance check ``|Rz p + t − q| <= dist_thr`` for every sampled pair.

    Returns ``status (B,)`` and ``T (B, 4, 4)``.
    """
    B = samples.shape[0]
    n = samples.shape[1]
    status = np.full(B, ST_EDGE, dtype=np.int64)
    Ts = np.zeros((B, 4, 4))
    P = np.empty((n, 3))
    Q = np.empty((n, 3))
    for h in range(B):
        bad = False
        if distinct:
            for a in range(n):
                for b in range(a + 1, n):
                    if samples[h, a] == samples[h, b]:
                        bad = True
            if bad:
                status[h] = ST_DEGENERATE
                continue
        for a in range(n):
            for k in range(3):
                P[a, k] = csrc[samples[h, a], k]
                Q[a, k] = ctgt[samples[h, a], k]
        for a in range(n):
            for b in range(a + 1, n):
                ls = math.sqrt((P[a, 0] - P[b, 0]) ** 2 + (P[a, 1] - P[b, 1]) ** 2 + (P[a, 2] - P[b, 2]) ** 2)
                lt = math.sqrt((Q[a, 0] - Q[b, 0]) ** 2 + (Q[a, 1] - Q[b, 1]) ** 2 + (Q[a, 2] - Q[b, 2]) ** 2)
                if min(ls, lt) < sim * max(ls, lt):
                    bad = True
        if bad:
            continue  # ST_EDGE
        T, spread = yaw_fit(P, Q)
        if spread < min_spread_m2:
            status[h] = ST_DEGENERATE
            continue
        Ts[h] = T
        ok = True
        for a in range(n):
            x = T[0, 0] * P[a, 0] + T[0, 1] * P[a, 1] + T[0, 3] - Q[a, 0]
            y = T[1, 0] * P[a, 0] + T[1, 1] * P[a, 1] + T[1, 3] - Q[a, 1]
            z = P[a, 2] + T[2, 3] - Q[a, 2]
            if x * x + y * y + z * z > dist_thr * dist_thr:
                ok = False
                break
        status[h] = ST_EVALUATED if ok else ST_DISTANCE
    return status, Ts


def _warmup() -> None:
    P = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, 0.5], [1.0, 4.0, -0.2]])
    yaw_fit(P, P + 1.0)
    ransac_check_levelled_kernel(P, P + 1.0, np.array([[0, 1], [1, 2]], dtype=np.int64), 0.9, 0.5, 0.25, True)
