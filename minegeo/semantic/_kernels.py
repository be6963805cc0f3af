"""Numba kernels of the intersection factor graph (Liang et al. 2024, Sec. 3.2).

Contiguous float64 arrays in, no checks (:mod:`minegeo.semantic.factors` validates). Poses are
``T_world_keyframe`` (4×4); tangent vectors are ordered rotation first, ``δ = (φ, ρ)`` (rad, m),
and perturbations are on the right, ``T ← T · Exp(δ)``, as in :mod:`minegeo.optim` and
GTSAM's ``Pose3``. To first order the right perturbation moves ``R ← R (I + hat(φ))`` and
``t ← t + R ρ``.

Intersection position factor of keyframe ``i`` observing intersection ``I`` at ``z`` (m, keyframe
frame), knowledge-base position ``C`` (m, world frame), residual [Liang2024 Eq. 22]

.. math::

    e_I = C - t_i - R_i z,

and its Jacobian with respect to the right perturbation of ``T_i``:
``∂e/∂φ = R_i hat(z)`` (the paper's left-perturbation result ``hat(R_i z)`` [Liang2024 Eq. 26]
times ``∂φ_left/∂φ_right = R_i``), ``∂e/∂ρ = −R_i`` (the paper's ``−I`` [Liang2024 Eq. 27] times
``∂t/∂ρ = R_i``).
"""

from __future__ import annotations

from minegeo._jit import njit


@njit
def intersection_terms(poses, kf, z, C, r, J):
    """Fill ``r`` (m, 3) and ``J`` (m, 3, 6) of every intersection factor [Liang2024 Eqs. 22, 26-27].

    Serial: a factor is a few dozen flops, less than the launch of a parallel loop.

    ``kf[e]`` is the pose row of factor ``e``; ``r[e] = C[e] − t − R z[e]`` (m, world frame),
    ``J[e] = [R hat(z[e]), −R]`` with respect to ``δ = (φ, ρ)`` of ``T ← T Exp(δ)``.
    """
    for e in range(kf.shape[0]):
        T = poses[kf[e]]
        zx, zy, zz = z[e, 0], z[e, 1], z[e, 2]
        for a in range(3):
            R0, R1, R2 = T[a, 0], T[a, 1], T[a, 2]
            r[e, a] = C[e, a] - T[a, 3] - (R0 * zx + R1 * zy + R2 * zz)
            # (R hat(z))[a, :] = row a of R times hat(z) = (R1 zz − R2 zy, R2 zx − R0 zz, R0 zy − R1 zx)
            J[e, a, 0] = R1 * zz - R2 * zy
            J[e, a, 1] = R2 * zx - R0 * zz
            J[e, a, 2] = R0 * zy - R1 * zx
            J[e, a, 3] = -R0
            J[e, a, 4] = -R1
            J[e, a, 5] = -R2


@njit
def intersection_residuals(poses, kf, z, C, r):
    """Residuals only, ``r[e] = C[e] − t − R z[e]`` [Liang2024 Eq. 22] (cost of a trial step)."""
    for e in range(kf.shape[0]):
        T = poses[kf[e]]
        for a in range(3):
            r[e, a] = C[e, a] - T[a, 3] - (T[a, 0] * z[e, 0] + T[a, 1] * z[e, 1] + T[a, 2] * z[e, 2])
