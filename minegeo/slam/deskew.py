"""Motion deskewing of a LiDAR sweep to its frame time, from a constant twist.

A spinning LiDAR measures each point at its own time while the sensor moves, so the raw sweep is
smeared by the motion. With the SLAM contract's conventions ("Sensor streams"): the frame time
``t_k`` is the time the frame's pose refers to, point ``i`` was measured at ``t_k + τ_i`` (``τ_i``
its per-point offset, s) and is given in the sensor frame at that time, ``p_i``.

With the sensor moving at a constant body twist ``ξ = (ω, v)`` over the sweep (rotation first;
rad/s and m/s, both expressed in the sensor frame), the sensor pose at ``t_k + τ`` is

    ``T_w_s(t_k + τ) = T_w_s(t_k) · exp(τ ξ)``,

so the point expressed in the sensor frame at the frame time is

    ``q_i = exp(τ_i ξ) · p_i = R(τ_i ω) p_i + J_l(τ_i ω) τ_i v``

(:mod:`minegeo.kernels.lie` conventions; ``J_l`` the SO(3) left Jacobian). This is the
constant-velocity deskewing of KISS-ICP (Vizzo et al. 2023, Sec. III-A), there done to the middle
of the sweep, here to the frame time (the sweep start for :mod:`minegeo.synth` streams).

The odometry's twist is :func:`twist_from_motion` of its last relative motion: with
``ΔT = T_w_s(t_a)⁻¹ T_w_s(t_b)`` over ``Δt = t_b − t_a``, ``ξ = Log(ΔT) / Δt``, which is exact for
a motion of constant body twist.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo.errors import InputError
from minegeo.kernels.lie import se3_log
from minegeo.slam._kernels_deskew import deskew_points_kernel

__all__ = ["deskew_points", "twist_from_motion"]


def twist_from_motion(delta: np.ndarray, dt_s: float) -> np.ndarray:
    """Body twist ``ξ = Log(ΔT) / Δt`` (rad/s, m/s; rotation first) of a relative motion.

    Parameters
    ----------
    delta : (4, 4) array
        ``ΔT = T_w_s(t_a)⁻¹ T_w_s(t_b)``: the pose at ``t_b`` in the sensor frame at ``t_a``.
    dt_s : float
        ``t_b − t_a`` (s, > 0).
    """
    D = np.ascontiguousarray(delta, dtype=np.float64)
    if D.shape != (4, 4) or not np.all(np.isfinite(D)):
        raise InputError(f"delta must be a finite 4x4 transform, got shape {D.shape}")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise InputError(f"dt_s must be a finite number of seconds > 0, got {dt_s!r}")
    return se3_log(D) / float(dt_s)


def deskew_points(points: np.ndarray, offsets_s: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Points of a sweep moved to the sensor frame at the frame time: ``q_i = exp(τ_i ξ) p_i``.

    Parameters
    ----------
    points : (n, 3) array
        ``p_i`` (m), each in the sensor frame at its own time ``t_k + τ_i``.
    offsets_s : (n,) array
        ``τ_i``, seconds after the frame time (finite).
    twist : (6,) array
        ``ξ = (ω, v)``: body angular rate (rad/s) then velocity (m/s), sensor frame, constant over
        the sweep (module docstring).

    Returns
    -------
    (n, 3) float64
        ``q_i`` in the sensor frame at the frame time (m). A zero twist returns the points unchanged.
    """
    P = np.ascontiguousarray(points, dtype=np.float64)
    tau = np.ascontiguousarray(offsets_s, dtype=np.float64).reshape(-1)
    xi = np.ascontiguousarray(twist, dtype=np.float64).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {P.shape}")
    if tau.shape[0] != P.shape[0]:
        raise InputError(f"offsets_s has {tau.shape[0]} values for {P.shape[0]} points")
    if xi.shape != (6,) or not np.all(np.isfinite(xi)):
        raise InputError(f"twist must be 6 finite numbers (rad/s, m/s), got {xi!r}")
    if not np.all(np.isfinite(tau)):
        raise InputError("offsets_s holds a NaN or infinite time")
    return deskew_points_kernel(P, tau, xi)  # writable or read-only (frames read from files) arrays alike
