"""Rigid-motion helpers (SE(3)) in float64.

Frame naming: ``T_a_b`` maps coordinates expressed in frame *b* into frame *a*:
``p_a = R_a_b @ p_b + t_a_b``. Composition: ``T_a_c = T_a_b @ T_b_c``.
Rotation vectors use the axis-angle (so(3)) convention, angles in radians.

This is the public, NumPy face of the Lie-group kernels :mod:`minegeo.kernels.lie`:
:func:`hat`, :func:`exp_so3`, :func:`log_so3` and :func:`rotation_angle` run the kernels'
Python source under NumPy (``kernel.py_func``: the same code, NumPy's bits); the SE(3)
exponential/logarithm, the Jacobians, the adjoint and SE(2) are the compiled kernels.
"""

from __future__ import annotations

import numpy as np

from minegeo.kernels import lie

__all__ = [
    "hat",
    "vee",
    "exp_so3",
    "log_so3",
    "exp_se3",
    "se3_exp",
    "se3_log",
    "se3_adjoint",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "se3_left_jacobian",
    "se3_left_jacobian_inv",
    "se3_right_jacobian",
    "se3_right_jacobian_inv",
    "se2_exp",
    "se2_log",
    "make_transform",
    "invert",
    "project",
    "compose",
    "relative",
    "orthonormality_error",
    "transform_points",
    "rotation_from_euler_xyz",
    "rotation_angle",
    "random_transform",
]


def _vec(v, n: int) -> np.ndarray:
    a = np.ascontiguousarray(v, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"expected a vector of {n} values, got shape {a.shape}")
    return a


def _mat(M, n: int) -> np.ndarray:
    a = np.ascontiguousarray(M, dtype=np.float64)
    if a.shape != (n, n):
        raise ValueError(f"expected a ({n}, {n}) matrix, got shape {a.shape}")
    return a


def hat(w) -> np.ndarray:
    """Skew-symmetric matrix ``[w]x`` with ``hat(w) @ v == cross(w, v)``."""
    return lie.hat.py_func(_vec(w, 3))


def vee(W) -> np.ndarray:
    """Inverse of :func:`hat`: the vector ``w`` of a skew-symmetric ``W``."""
    return lie.vee.py_func(_mat(W, 3))


def exp_so3(w) -> np.ndarray:
    """Rodrigues' formula: rotation matrix of the rotation vector ``w`` (rad) (:func:`minegeo.kernels.lie.so3_exp`)."""
    return lie.so3_exp.py_func(_vec(w, 3))


def log_so3(R) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix; inverse of :func:`exp_so3` for angles < pi
    (:func:`minegeo.kernels.lie.so3_log`)."""
    return lie.so3_log.py_func(_mat(R, 3))


def exp_se3(xi) -> np.ndarray:
    """4x4 transform from a 6-vector ``(wx, wy, wz, tx, ty, tz)`` (rotation first, translation applied as is)."""
    xi = np.asarray(xi, dtype=np.float64)
    return make_transform(exp_so3(xi[:3]), xi[3:6])


def make_transform(R=None, t=None) -> np.ndarray:
    """4x4 homogeneous transform from rotation ``R`` (3x3) and translation ``t`` (3,)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def invert(T) -> np.ndarray:
    """Inverse of a rigid transform: ``T_b_a`` from ``T_a_b`` (exact, no general matrix inverse).

    NumPy/BLAS expression of :func:`minegeo.kernels.lie.se3_inverse` (kept: its BLAS product
    rounds differently from the kernel's loop, and its bits enter published outputs)."""
    T = np.asarray(T, dtype=np.float64)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def project(T) -> np.ndarray:
    """``T`` re-projected onto SE(3): nearest rotation (Frobenius) of its rotation block, translation
    kept, last row ``[0, 0, 0, 1]`` (:func:`minegeo.kernels.lie.se3_project`, under NumPy).

    No validation: for transforms the package made itself (chained products that drifted by
    rounding). Validate user input with :func:`minegeo._validate.as_transform` first.
    """
    return lie.se3_project.py_func(np.asarray(T, dtype=np.float64))


def compose(*Ts) -> np.ndarray:
    """Product ``T_1 @ T_2 @ ... @ T_n`` of rigid transforms, re-projected onto SE(3) (:func:`project`).

    ``T_a_c = compose(T_a_b, T_b_c)``. Every chained pose of the SLAM, tracking and localization
    code is composed here, so the rotation stays orthonormal to rounding (about 1e-15) however long
    the chain (``tests/kernels/test_kernels_manifold.py`` chains 10^5 relative poses).
    """
    if not Ts:
        return np.eye(4)
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return project(out)


def relative(T_w_a, T_w_b) -> np.ndarray:
    """``T_a_b = T_w_a⁻¹ T_w_b`` (the pose of *b* in *a*), by :func:`invert` (exact form, no general
    inverse or solve), re-projected onto SE(3)."""
    return compose(invert(T_w_a), T_w_b)


def orthonormality_error(T) -> float:
    """``‖RᵀR − I‖_F`` of the rotation block of ``T`` (4x4 or 3x3): how far it has left SO(3)."""
    A = np.asarray(T, dtype=np.float64)
    R = A[:3, :3]
    return float(np.linalg.norm(R.T @ R - np.eye(3)))


def transform_points(T, points) -> np.ndarray:
    """Apply ``T`` (4x4) to ``points`` (n, 3): ``R p + t``."""
    T = np.asarray(T, dtype=np.float64)
    P = np.asarray(points, dtype=np.float64)
    return P @ T[:3, :3].T + T[:3, 3]


def rotation_from_euler_xyz(rx, ry, rz) -> np.ndarray:
    """``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (rad): roll about x, then pitch about y, then yaw about z."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def rotation_angle(R) -> float:
    """Rotation angle (rad, in [0, pi]) of a rotation matrix, e.g. of ``R_est.T @ R_true``."""
    return float(lie.so3_angle.py_func(_mat(R, 3)))


def random_transform(rng: np.random.Generator, max_angle_rad: float = np.pi, max_translation: float = 1.0):
    """Random rigid transform: uniform axis, angle uniform in [0, max_angle], translation in a cube."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = rng.uniform(0.0, max_angle_rad)
    t = rng.uniform(-max_translation, max_translation, size=3)
    return make_transform(exp_so3(axis * ang), t)


# ----------------------------------------------------------------------------- Lie-group kernels
# Compiled kernels of minegeo.kernels.lie; tangent vectors rotation first: ξ = (φ rad, ρ m).


def se3_exp(xi) -> np.ndarray:
    """SE(3) exponential ``[[exp(φ), J_l(φ) ρ], [0, 1]]`` of ``ξ = (φ, ρ)`` (rad, m).

    Unlike :func:`exp_se3` (which applies ``ρ`` as the translation), this is the group
    exponential used by Gauss-Newton / pose-graph updates.
    """
    return lie.se3_exp(_vec(xi, 6))


def se3_log(T) -> np.ndarray:
    """SE(3) logarithm ``ξ = (φ, ρ)`` of a 4x4 rigid transform (rotation angle < pi)."""
    return lie.se3_log(_mat(T, 4))


def se3_adjoint(T) -> np.ndarray:
    """6x6 adjoint ``[[R, 0], [hat(t) R, R]]`` of ``T`` (rotation-first order)."""
    return lie.se3_adjoint(_mat(T, 4))


def so3_left_jacobian(w) -> np.ndarray:
    """Left Jacobian ``J_l(w)`` of SO(3) (3x3)."""
    return lie.so3_left_jacobian(_vec(w, 3))


def so3_left_jacobian_inv(w) -> np.ndarray:
    """Inverse left Jacobian of SO(3) (3x3; singular at angles 2πk, k ≠ 0)."""
    return lie.so3_left_jacobian_inv(_vec(w, 3))


def so3_right_jacobian(w) -> np.ndarray:
    """Right Jacobian ``J_r(w) = J_l(-w)`` of SO(3) (3x3)."""
    return lie.so3_right_jacobian(_vec(w, 3))


def so3_right_jacobian_inv(w) -> np.ndarray:
    """Inverse right Jacobian of SO(3) (3x3)."""
    return lie.so3_right_jacobian_inv(_vec(w, 3))


def se3_left_jacobian(xi) -> np.ndarray:
    """Left Jacobian of SE(3) at ``ξ = (φ, ρ)`` (6x6)."""
    return lie.se3_left_jacobian(_vec(xi, 6))


def se3_left_jacobian_inv(xi) -> np.ndarray:
    """Inverse left Jacobian of SE(3) (6x6)."""
    return lie.se3_left_jacobian_inv(_vec(xi, 6))


def se3_right_jacobian(xi) -> np.ndarray:
    """Right Jacobian of SE(3) ``J_r(ξ) = J_l(-ξ)`` (6x6)."""
    return lie.se3_right_jacobian(_vec(xi, 6))


def se3_right_jacobian_inv(xi) -> np.ndarray:
    """Inverse right Jacobian of SE(3) (6x6)."""
    return lie.se3_right_jacobian_inv(_vec(xi, 6))


def se2_exp(xi) -> np.ndarray:
    """SE(2) exponential: 3x3 homogeneous transform of ``ξ = (θ rad, ρ_x m, ρ_y m)``."""
    return lie.se2_exp(_vec(xi, 3))


def se2_log(T) -> np.ndarray:
    """SE(2) logarithm ``(θ, ρ_x, ρ_y)`` of a 3x3 homogeneous transform, ``θ`` in (-π, π]."""
    return lie.se2_log(_mat(T, 3))
