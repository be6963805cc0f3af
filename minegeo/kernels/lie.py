"""SO(3), SE(3) and SE(2): exponential and logarithm, hat/vee, Jacobians, adjoint (Numba).

Conventions (the package's, :mod:`minegeo.geometry.se3`):

* ``T_a_b`` maps coordinates of frame *b* into frame *a*, ``p_a = R p_b + t``; composition
  ``T_a_c = T_a_b T_b_c``.
* Rotation vectors ``φ`` (rad) are axis-angle, ``θ = |φ|``; ``hat(φ) v = φ × v``.
* SE(3) tangent vectors are ordered **rotation first**, ``ξ = (φ, ρ)`` (rad, m), as the
  parameters of the ICP / GICP normal equations; ``exp(ξ) = [[exp(φ), J_l(φ) ρ], [0, 1]]``.
* SE(2) tangent vectors are ``(θ, ρ_x, ρ_y)`` (rad, m).
* Left Jacobian ``J_l``: ``exp(ξ + δ) ≈ exp(J_l(ξ) δ) exp(ξ)``; right Jacobian
  ``J_r(ξ) = J_l(-ξ)``: ``exp(ξ + δ) ≈ exp(ξ) exp(J_r(ξ) δ)``.
* Adjoint: ``T exp(ξ) T⁻¹ = exp(Ad(T) ξ)``, ``Ad(T) = [[R, 0], [hat(t) R, R]]`` for the
  rotation-first order.

Formulas: Solà, Deray, Atchuthan (2018), *A micro Lie theory for state estimation in
robotics*, App. B (SO(3): [Sola2018 Eqs. 143-146] for ``J_r``, ``J_r⁻¹``, ``J_l``, ``J_l⁻¹``),
App. C (SE(2)) and App. D (SE(3)); Barfoot (2017), *State Estimation for Robotics*, Sec. 7.1
(the SE(3) Jacobian's coupling block ``Q``, [Barfoot2017 Eq. 7.86], here for ``(φ, ρ)``).
Below ``θ < SMALL_ANGLE`` the coefficients use their Taylor series (relative error < 1e-16).

One code, two runtimes: :mod:`minegeo.geometry.se3` (the public, validated face) runs these
functions' Python source under NumPy (``kernel.py_func``), njit callers run them compiled. The
results agree to rounding; they are not bit-identical, because NumPy's ``arccos`` is a SIMD
(SVML) loop and its small matrix products call BLAS (with FMA), whereas Numba uses libm and
its own products. The public face keeps NumPy's bits (they enter published outputs); for the
same reason :func:`minegeo.geometry.se3.invert` keeps its NumPy/BLAS expression next to the
loop of :func:`se3_inverse`.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit

__all__ = [
    "SMALL_ANGLE", "hat", "vee", "so3_exp", "so3_log", "so3_angle", "so3_left_jacobian",
    "so3_left_jacobian_inv", "so3_right_jacobian", "so3_right_jacobian_inv", "so3_project", "se3_project",
    "se3_inverse", "se3_exp",
    "se3_log", "se3_adjoint", "se3_left_jacobian", "se3_left_jacobian_inv", "se3_right_jacobian",
    "se3_right_jacobian_inv", "se2_exp", "se2_log", "se2_adjoint", "se2_right_jacobian_inv",
]

#: Below this rotation angle (rad) the Jacobian coefficients use their Taylor series.
SMALL_ANGLE = 1e-4


@njit
def hat(w):
    """Skew-symmetric ``[w]x`` (3, 3) with ``hat(w) @ v == cross(w, v)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


@njit
def vee(W):
    """Inverse of :func:`hat`: ``(W[2,1], W[0,2], W[1,0])`` of a skew-symmetric ``W``."""
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


@njit
def so3_exp(w):
    """Rotation matrix of the rotation vector ``w`` (rad), Rodrigues' formula.

    ``R = I + (sin θ / θ) [w]x + ((1 - cos θ) / θ²) [w]x²`` (Solà 2018, App. B), second-order
    series ``I + [w]x + [w]x² / 2`` below ``θ = 1e-8``.
    """
    th = np.linalg.norm(w)
    K = hat(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


@njit
def so3_angle(R):
    """Rotation angle (rad, in [0, π]) of a rotation matrix: ``arccos((tr R - 1) / 2)``."""
    c = ((R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0
    return np.arccos(min(max(c, -1.0), 1.0))


@njit
def so3_log(R):
    """Rotation vector (rad) of a rotation matrix; inverse of :func:`so3_exp` for angles < π.

    ``φ = θ / (2 sin θ) vee(R - Rᵀ)``; ``vee(R - Rᵀ) / 2`` below ``θ = 1e-8``; within 1e-6 of π
    the axis comes from the largest diagonal entry of ``(R + I) / 2``.
    """
    c = ((R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0  # so3_angle, inlined (one runtime per call)
    th = np.arccos(min(max(c, -1.0), 1.0))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return 0.5 * v
    if np.pi - th < 1e-6:
        B = (R + np.eye(3)) / 2.0
        k = 0
        for j in range(1, 3):
            if B[j, j] > B[k, k]:
                k = j
        axis = B[:, k] / np.sqrt(B[k, k])
        return axis * th
    return th / (2.0 * np.sin(th)) * v


@njit
def _so3_coeffs(w):
    """``(θ, a, b)`` with ``a = (1 - cos θ) / θ²``, ``b = (θ - sin θ) / θ³`` (series when small)."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = np.sqrt(t2)
    if th < SMALL_ANGLE:
        return th, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    return th, (1.0 - np.cos(th)) / t2, (th - np.sin(th)) / (t2 * th)


@njit
def so3_left_jacobian(w):
    """``J_l(w) = I + ((1 - cos θ)/θ²) [w]x + ((θ - sin θ)/θ³) [w]x²`` ([Sola2018 Eq. 145])."""
    _, a, b = _so3_coeffs(w)
    K = hat(w)
    return np.eye(3) + a * K + b * (K @ K)


@njit
def so3_right_jacobian(w):
    """``J_r(w) = J_l(-w) = I - a [w]x + b [w]x²`` ([Sola2018 Eq. 143])."""
    return so3_left_jacobian(-w)


@njit
def so3_left_jacobian_inv(w):
    """``J_l⁻¹(w) = I - [w]x / 2 + (1/θ² - (1 + cos θ)/(2 θ sin θ)) [w]x²`` ([Sola2018 Eq. 146]).

    Singular at ``θ = 2π k``, k ≠ 0 (use rotation vectors with θ < π).
    """
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = np.sqrt(t2)
    if th < SMALL_ANGLE:
        c = 1.0 / 12.0 + t2 / 720.0
    else:
        c = 1.0 / t2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))
    K = hat(w)
    return np.eye(3) - 0.5 * K + c * (K @ K)


@njit
def so3_right_jacobian_inv(w):
    """``J_r⁻¹(w) = J_l⁻¹(-w)`` ([Sola2018 Eq. 144])."""
    return so3_left_jacobian_inv(-w)


@njit
def so3_project(R):
    """Nearest rotation matrix to the 3x3 ``R`` in the Frobenius norm (the orthogonal polar factor).

    ``R = U Σ Vᵀ`` (SVD), ``R' = U diag(1, 1, det(U Vᵀ)) Vᵀ`` (Higham 1986, *Computing the polar
    decomposition*; Horn, Hilden, Negahdaripour 1988 for the det = +1 constraint). For an ``R``
    that has drifted from SO(3) by ``ε = ‖RᵀR − I‖`` after chained products, ``‖R' − R‖ ≈ ε / 2``
    and ``‖R'ᵀR' − I‖`` is at rounding level (about 1e-15). Meant for drift, not for repairing
    arbitrary matrices: the caller decides what "drifted" means.
    """
    U, _, Vt = np.linalg.svd(np.ascontiguousarray(R))
    Q = U @ Vt
    if np.linalg.det(Q) < 0.0:
        for r in range(3):
            U[r, 2] = -U[r, 2]
        Q = U @ Vt
    return Q


@njit
def se3_project(T):
    """``T`` (4x4) re-projected onto SE(3): rotation block :func:`so3_project`, translation kept,
    last row ``[0, 0, 0, 1]``.

    The one re-projection of the package: every product, inversion and interpolation of poses that
    is chained (odometry, pose graph inputs, tracking, localization) goes through it (via
    :func:`minegeo.geometry.se3.compose` / :func:`~minegeo.geometry.se3.relative` /
    :func:`~minegeo.geometry.se3.project`), so rounding cannot accumulate across thousands of
    frames. Float64; a non-finite ``T`` gives a non-finite result (callers check).
    """
    out = np.eye(4)
    out[:3, :3] = so3_project(np.ascontiguousarray(T[:3, :3]))
    for r in range(3):
        out[r, 3] = T[r, 3]
    return out


@njit
def se3_inverse(T):
    """Inverse of a rigid transform: ``T_b_a`` from ``T_a_b`` (``[[Rᵀ, -Rᵀ t], [0, 1]]``)."""
    Ti = np.eye(4)
    for r in range(3):
        for c in range(3):
            Ti[r, c] = T[c, r]
        Ti[r, 3] = -(T[0, r] * T[0, 3] + T[1, r] * T[1, 3] + T[2, r] * T[2, 3])
    return Ti


@njit
def se3_exp(xi):
    """4x4 transform ``exp(ξ)`` of ``ξ = (φ, ρ)``: ``[[exp(φ), J_l(φ) ρ], [0, 1]]`` (Solà 2018, App. D)."""
    phi = xi[:3].copy()
    rho = xi[3:6].copy()
    T = np.eye(4)
    T[:3, :3] = so3_exp(phi)
    T[:3, 3] = so3_left_jacobian(phi) @ rho
    return T


@njit
def se3_log(T):
    """``ξ = (φ, ρ)`` with ``exp(ξ) = T``: ``φ = log(R)``, ``ρ = J_l(φ)⁻¹ t`` (angles < π)."""
    phi = so3_log(T[:3, :3].copy())
    out = np.empty(6)
    out[:3] = phi
    out[3:6] = so3_left_jacobian_inv(phi) @ T[:3, 3].copy()
    return out


@njit
def se3_adjoint(T):
    """6x6 adjoint ``[[R, 0], [hat(t) R, R]]`` (rotation-first order): ``T exp(ξ) T⁻¹ = exp(Ad ξ)``."""
    R = T[:3, :3].copy()
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = hat(T[:3, 3].copy()) @ R
    return A


@njit
def _se3_q(phi, rho):
    """Coupling block ``Q(φ, ρ)`` of the SE(3) left Jacobian ([Barfoot2017 Eq. 7.86]).

    ``Q = ½ P + a (F P + P F + F P F) + b (F F P + P F F - 3 F P F)
    + c (F P F F + F F P F)`` with ``F = hat(φ)``, ``P = hat(ρ)``,
    ``a = (θ - sin θ)/θ³``, ``b = (θ² + 2 cos θ - 2)/(2 θ⁴)``, ``c = (2θ - 3 sin θ + θ cos θ)/(2 θ⁵)``.
    """
    t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    th = np.sqrt(t2)
    if th < SMALL_ANGLE:
        a = 1.0 / 6.0 - t2 / 120.0
        b = 1.0 / 24.0 - t2 / 720.0
        c = 1.0 / 120.0 - t2 / 2520.0
    else:
        s = np.sin(th)
        co = np.cos(th)
        a = (th - s) / (t2 * th)
        b = (t2 + 2.0 * co - 2.0) / (2.0 * t2 * t2)
        c = (2.0 * th - 3.0 * s + th * co) / (2.0 * t2 * t2 * th)
    F = hat(phi)
    P = hat(rho)
    FP = F @ P
    PF = P @ F
    FPF = FP @ F
    FF = F @ F
    return 0.5 * P + a * (FP + PF + FPF) + b * (FF @ P + PF @ F - 3.0 * FPF) + c * (FPF @ F + FF @ PF)


@njit
def se3_left_jacobian(xi):
    """6x6 left Jacobian of SE(3) at ``ξ = (φ, ρ)``: ``[[J_l(φ), 0], [Q(φ, ρ), J_l(φ)]]``."""
    phi = xi[:3].copy()
    rho = xi[3:6].copy()
    J = so3_left_jacobian(phi)
    out = np.zeros((6, 6))
    out[:3, :3] = J
    out[3:, 3:] = J
    out[3:, :3] = _se3_q(phi, rho)
    return out


@njit
def se3_left_jacobian_inv(xi):
    """Inverse of :func:`se3_left_jacobian`: ``[[J⁻¹, 0], [-J⁻¹ Q J⁻¹, J⁻¹]]``."""
    phi = xi[:3].copy()
    rho = xi[3:6].copy()
    Ji = so3_left_jacobian_inv(phi)
    out = np.zeros((6, 6))
    out[:3, :3] = Ji
    out[3:, 3:] = Ji
    out[3:, :3] = -(Ji @ _se3_q(phi, rho) @ Ji)
    return out


@njit
def se3_right_jacobian(xi):
    """6x6 right Jacobian ``J_r(ξ) = J_l(-ξ)``."""
    return se3_left_jacobian(-xi)


@njit
def se3_right_jacobian_inv(xi):
    """``J_r⁻¹(ξ) = J_l⁻¹(-ξ)``."""
    return se3_left_jacobian_inv(-xi)


@njit
def se2_exp(xi):
    """3x3 homogeneous transform of ``ξ = (θ, ρ_x, ρ_y)``: ``[[R(θ), V(θ) ρ], [0, 1]]``.

    ``V(θ) = [[sin θ/θ, -(1 - cos θ)/θ], [(1 - cos θ)/θ, sin θ/θ]]`` (Solà 2018, App. C), series
    below ``SMALL_ANGLE``.
    """
    th = xi[0]
    c = np.cos(th)
    s = np.sin(th)
    if abs(th) < SMALL_ANGLE:
        A = 1.0 - th * th / 6.0
        B = th / 2.0 - th * th * th / 24.0
    else:
        A = s / th
        B = (1.0 - c) / th
    T = np.eye(3)
    T[0, 0] = c
    T[0, 1] = -s
    T[1, 0] = s
    T[1, 1] = c
    T[0, 2] = A * xi[1] - B * xi[2]
    T[1, 2] = B * xi[1] + A * xi[2]
    return T


@njit
def se2_log(T):
    """``ξ = (θ, ρ_x, ρ_y)`` with ``se2_exp(ξ) = T``, ``θ = atan2(R10, R00)`` in (-π, π]."""
    th = np.arctan2(T[1, 0], T[0, 0])
    if abs(th) < SMALL_ANGLE:
        A = 1.0 - th * th / 6.0
        B = th / 2.0 - th * th * th / 24.0
    else:
        A = np.sin(th) / th
        B = (1.0 - np.cos(th)) / th
    d = A * A + B * B
    out = np.empty(3)
    out[0] = th
    out[1] = (A * T[0, 2] + B * T[1, 2]) / d
    out[2] = (-B * T[0, 2] + A * T[1, 2]) / d
    return out


@njit
def se2_adjoint(T):
    """3x3 adjoint of SE(2) for ``ξ = (θ, ρ_x, ρ_y)``: ``[[1, 0, 0], [t_y, R], [-t_x, R]]``
    (``T exp(ξ) T⁻¹ = exp(Ad ξ)``; [Sola2018 Eq. 159] reordered rotation-first)."""
    A = np.zeros((3, 3))
    A[0, 0] = 1.0
    A[1, 0] = T[1, 2]
    A[2, 0] = -T[0, 2]
    A[1:, 1:] = T[:2, :2]
    return A


@njit
def se2_right_jacobian_inv(xi):
    """Inverse right Jacobian of SE(2) at ``ξ = (θ, ρ_x, ρ_y)`` ([Sola2018 Eq. 163] reordered
    rotation-first: ``J_r = [[1, 0], [c, M]]``, so ``J_r⁻¹ = [[1, 0], [-M⁻¹c, M⁻¹]]``)."""
    th, r1, r2 = xi[0], xi[1], xi[2]
    t2 = th * th
    if abs(th) < SMALL_ANGLE:
        a = 1.0 - t2 / 6.0            # sin θ / θ
        b = th / 2.0 - t2 * th / 24.0  # (1 - cos θ) / θ
        p = th / 6.0                   # (θ - sin θ) / θ²
        q = 0.5 - t2 / 24.0            # (1 - cos θ) / θ²
    else:
        s, c = np.sin(th), np.cos(th)
        a, b = s / th, (1.0 - c) / th
        p, q = (th - s) / t2, (1.0 - c) / t2
    # M = [[a, b], [-b, a]], c = (p r1 - q r2, q r1 + p r2)
    det = a * a + b * b
    out = np.zeros((3, 3))
    out[0, 0] = 1.0
    out[1, 1] = a / det
    out[1, 2] = -b / det
    out[2, 1] = b / det
    out[2, 2] = a / det
    c1 = p * r1 - q * r2
    c2 = q * r1 + p * r2
    out[1, 0] = -(out[1, 1] * c1 + out[1, 2] * c2)
    out[2, 0] = -(out[2, 1] * c1 + out[2, 2] * c2)
    return out
