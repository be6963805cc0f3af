"""Numba kernel of the gyro deskewing of a LiDAR sweep (:meth:`minegeo.slam.inertial.GyroAid.deskew`
validates and prepares its inputs).

Contiguous float64 arrays in, no checks. Rotations as :mod:`minegeo.kernels.lie` (Rodrigues).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit

#: below this rotation angle (rad) the Rodrigues coefficients use their series (relative error < 1e-16)
_SMALL = 1e-4


@njit("float64[:, ::1](float64[:, ::1], float64[::1], float64[::1], float64[:, :, ::1], float64[:, ::1], "
      "float64[::1])")
def gyro_deskew_kernel(points, times, knots_t, M, w, v_offsets):
    """``q_i = M_j Exp(ω_j (s_i − t_j)) p_i + τ_i v`` for each point.

    ``s_i = times[i]`` is the point's time, ``j`` the knot interval holding it (``knots_t[j] ≤ s_i``,
    clamped to the first and last interval), ``M_j = R(t)ᵀ R(t_j)`` the rotation from the knot to the
    frame time, ``ω_j`` the (LiDAR-axes, bias-free) rate over the interval. ``v_offsets`` holds
    ``(v_x, v_y, v_z, t)``: the velocity (m/s, sensor frame at the frame time) and the frame time
    ``t`` (``τ_i = s_i − t``). ``Exp(φ) p = p + (sin θ/θ) φ×p + ((1 − cos θ)/θ²) φ×(φ×p)`` as cross
    products (series below θ = 1e-4). Units: m, s, rad/s.
    """
    n = points.shape[0]
    m = w.shape[0]
    out = np.empty((n, 3))
    t = v_offsets[3]
    for i in range(n):
        s_i = times[i]
        lo, hi = 0, m - 1
        while lo < hi:  # the last knot interval starting at or before s_i
            mid = (lo + hi + 1) // 2
            if knots_t[mid] <= s_i:
                lo = mid
            else:
                hi = mid - 1
        j = lo
        d = s_i - knots_t[j]
        f0, f1, f2 = w[j, 0] * d, w[j, 1] * d, w[j, 2] * d
        t2 = f0 * f0 + f1 * f1 + f2 * f2
        th = np.sqrt(t2)
        if th < _SMALL:
            sc = 1.0 - t2 / 6.0
            a = 0.5 - t2 / 24.0
        else:
            sc = np.sin(th) / th
            a = (1.0 - np.cos(th)) / t2
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        k0, k1, k2 = f1 * p2 - f2 * p1, f2 * p0 - f0 * p2, f0 * p1 - f1 * p0
        kk0, kk1, kk2 = f1 * k2 - f2 * k1, f2 * k0 - f0 * k2, f0 * k1 - f1 * k0
        y0, y1, y2 = p0 + sc * k0 + a * kk0, p1 + sc * k1 + a * kk1, p2 + sc * k2 + a * kk2
        tau = s_i - t
        for r in range(3):
            out[i, r] = M[j, r, 0] * y0 + M[j, r, 1] * y1 + M[j, r, 2] * y2 + tau * v_offsets[r]
    return out
