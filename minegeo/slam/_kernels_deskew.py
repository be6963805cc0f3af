"""Numba kernel of the motion deskewing of a LiDAR sweep (:mod:`minegeo.slam.deskew` validates).

Contiguous float64 arrays in, no checks. Conventions as :mod:`minegeo.kernels.lie`: twists are
rotation first, ``ξ = (ω, v)`` (rad/s, m/s), ``exp(ξ) = [[exp(ω), J_l(ω) v], [0, 1]]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import types

from minegeo._jit import njit

#: Below this rotation angle (rad) the Rodrigues and Jacobian coefficients use their series
#: (as :data:`minegeo.kernels.lie.SMALL_ANGLE`; relative error < 1e-16).
_SMALL = 1e-4


_F2, _F1 = types.Array(types.float64, 2, "C"), types.Array(types.float64, 1, "C")
_RO2, _RO1 = types.Array(types.float64, 2, "C", readonly=True), types.Array(types.float64, 1, "C", readonly=True)


#: writable arrays, or read-only ones (frames read from files) without a copy
@njit([_F2(_F2, _F1, _F1), _F2(_RO2, _RO1, _F1)])
def deskew_points_kernel(points, offsets_s, twist):
    """``q_i = exp(τ_i ξ) p_i = R(φ_i) p_i + J_l(φ_i) τ_i v``, ``φ_i = τ_i ω`` for each point.

    With ``K = [φ]×``, ``θ = |φ|``: ``R = I + (sin θ/θ) K + ((1 − cos θ)/θ²) K²`` (Rodrigues) and
    ``J_l = I + ((1 − cos θ)/θ²) K + ((θ − sin θ)/θ³) K²`` [Sola2018 Eq. 145], applied as cross
    products (no 3×3 matrix per point); series below θ = 1e-4. Units: m, s, rad/s, m/s.
    """
    n = points.shape[0]
    out = np.empty((n, 3))
    # the coefficients of a point depend on its time only: consecutive points of one time (a firing of
    # all rings) reuse them (the same expressions per point, so the same bits as computing each anew)
    tau_prev = np.nan
    f0 = f1 = f2 = u0 = u1 = u2 = s = a = b = 0.0
    c0 = c1 = c2 = cc0 = cc1 = cc2 = 0.0
    for i in range(n):
        tau = offsets_s[i]
        if not (tau == tau_prev and math.copysign(1.0, tau) == math.copysign(1.0, tau_prev)):  # (±0 told apart)
            tau_prev = tau
            f0, f1, f2 = tau * twist[0], tau * twist[1], tau * twist[2]
            u0, u1, u2 = tau * twist[3], tau * twist[4], tau * twist[5]
            t2 = f0 * f0 + f1 * f1 + f2 * f2
            th = np.sqrt(t2)
            if th < _SMALL:
                s = 1.0 - t2 / 6.0
                a = 0.5 - t2 / 24.0
                b = 1.0 / 6.0 - t2 / 120.0
            else:
                s = np.sin(th) / th
                a = (1.0 - np.cos(th)) / t2
                b = (th - np.sin(th)) / (t2 * th)
            # K u, K K u
            c0, c1, c2 = f1 * u2 - f2 * u1, f2 * u0 - f0 * u2, f0 * u1 - f1 * u0
            cc0, cc1, cc2 = f1 * c2 - f2 * c1, f2 * c0 - f0 * c2, f0 * c1 - f1 * c0
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        # K p, K K p
        k0, k1, k2 = f1 * p2 - f2 * p1, f2 * p0 - f0 * p2, f0 * p1 - f1 * p0
        kk0, kk1, kk2 = f1 * k2 - f2 * k1, f2 * k0 - f0 * k2, f0 * k1 - f1 * k0
        out[i, 0] = p0 + s * k0 + a * kk0 + u0 + a * c0 + b * cc0
        out[i, 1] = p1 + s * k1 + a * kk1 + u1 + a * c1 + b * cc1
        out[i, 2] = p2 + s * k2 + a * kk2 + u2 + a * c2 + b * cc2
    return out
