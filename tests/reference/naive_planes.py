"""Naive twin of the roadway-plane pieces (:mod:`minegeo.slam.planes`): plain Python loops, the
plane transformed as a homogeneous 4-vector, residuals from explicit trigonometry and
finite-difference Jacobians under the same retractions. Slow and obviously right."""

from __future__ import annotations

import math

import numpy as np
from reference.naive_posegraph import exp as se3_exp_naive


def tangent_basis(n):
    """The same basis as the kernel (Duff et al. 2017 revision of Frisvad), written out."""
    s = 1.0 if n[2] >= 0 else -1.0
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    b1 = np.array([1.0 + s * n[0] ** 2 * a, s * b, -s * n[0]])
    b2 = np.array([b, s + n[1] ** 2 * a, -n[1]])
    return np.column_stack([b1, b2])


def retract_plane(plane, delta):
    n = plane[:3] + tangent_basis(plane[:3]) @ delta[:2]
    return np.r_[n / np.linalg.norm(n), plane[3] + delta[2]]


def plane_to_sensor(plane_world, T_world_sensor):
    """``π_s = Tᵀ π_w``: ``π_wᵀ [p_w; 1] = π_wᵀ T [p_s; 1] = 0`` (no formula from the paper used)."""
    return T_world_sensor.T @ plane_world


def plane_through(p0, p1, p2, up):
    n = np.cross(p1 - p0, p2 - p0)
    n = n / np.linalg.norm(n)
    if n @ up < 0:
        n = -n
    return np.r_[n, -(n @ p0)]


def ransac_counts(P, samples, up, cos_max_tilt, threshold):
    """Per-sample inlier counts (``-1`` degenerate, ``-2`` too steep), loop by loop."""
    out = []
    for i, j, k in samples:
        a, b = P[j] - P[i], P[k] - P[i]
        c = np.cross(a, b)
        if np.linalg.norm(c) <= 1e-9 * np.linalg.norm(a) * np.linalg.norm(b) or np.linalg.norm(c) == 0:
            out.append(-1)
            continue
        pl = plane_through(P[i], P[j], P[k], up)
        if pl[:3] @ up < cos_max_tilt:
            out.append(-2)
            continue
        out.append(sum(1 for p in P if abs(pl[:3] @ p + pl[3]) <= threshold))
    return np.array(out)


def residual(T, plane_world, meas):
    """``q_t(π') − q_t(π_t)``: azimuth/elevation of ``n_s`` in the frame (n_t, b1, b2), and ``d_s − d_t``."""
    ps = plane_to_sensor(plane_world, T)
    ns = ps[:3]
    B = tangent_basis(meas[:3])
    u0, u1, u2 = meas[:3] @ ns, B[:, 0] @ ns, B[:, 1] @ ns
    return np.array([math.atan2(u1, u0), math.atan2(u2, math.hypot(u0, u1)), ps[3] - meas[3]])


def numeric_jacobians(T, plane, meas, h=1e-6):
    """Central differences under ``T ← T·Exp(δ)`` (SciPy expm) and ``π ← retract_plane(π, δ)``."""
    Jp, Jl = np.zeros((3, 6)), np.zeros((3, 3))
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        Jp[:, k] = (residual(T @ se3_exp_naive(e), plane, meas) - residual(T @ se3_exp_naive(-e), plane, meas)) / (2 * h)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        Jl[:, k] = (residual(T, retract_plane(plane, e), meas) - residual(T, retract_plane(plane, -e), meas)) / (2 * h)
    return Jp, Jl
