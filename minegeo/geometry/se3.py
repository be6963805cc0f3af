"""Rigid-motion helpers (SE(3)) in float64.

Frame naming: ``T_a_b`` maps coordinates expressed in frame *b* into frame *a*:
``p_a = R_a_b @ p_b + t_a_b``. Composition: ``T_a_c = T_a_b @ T_b_c``.
Rotation vectors use the axis-angle (so(3)) convention, angles in radians.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hat",
    "exp_so3",
    "log_so3",
    "exp_se3",
    "make_transform",
    "invert",
    "transform_points",
    "rotation_from_euler_xyz",
    "rotation_angle",
    "random_transform",
]


def hat(w) -> np.ndarray:
    """Skew-symmetric matrix ``[w]x`` with ``hat(w) @ v == cross(w, v)``."""
    wx, wy, wz = np.asarray(w, dtype=np.float64)
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def exp_so3(w) -> np.ndarray:
    """Rodrigues' formula: rotation matrix of the rotation vector ``w`` (rad)."""
    w = np.asarray(w, dtype=np.float64)
    th = float(np.linalg.norm(w))
    K = hat(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


def log_so3(R) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix; inverse of :func:`exp_so3` for angles < pi."""
    R = np.asarray(R, dtype=np.float64)
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return 0.5 * v
    if np.pi - th < 1e-6:
        # near pi: axis from the diagonal of (R + I) / 2
        B = (R + np.eye(3)) / 2.0
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(B[k, k])
        return axis * th
    return th / (2.0 * np.sin(th)) * v


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
    """Inverse of a rigid transform: ``T_b_a`` from ``T_a_b`` (exact, no general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


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
    return float(np.arccos(np.clip((np.trace(np.asarray(R)) - 1.0) / 2.0, -1.0, 1.0)))


def random_transform(rng: np.random.Generator, max_angle_rad: float = np.pi, max_translation: float = 1.0):
    """Random rigid transform: uniform axis, angle uniform in [0, max_angle], translation in a cube."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = rng.uniform(0.0, max_angle_rad)
    t = rng.uniform(-max_translation, max_translation, size=3)
    return make_transform(exp_so3(axis * ang), t)
