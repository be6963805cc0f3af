"""Information of the tracker's odometry edges (:func:`odometry_edge_information`): GICP's information
with a model-noise floor (:mod:`minegeo.semantic.tracking` uses it for every keyframe edge)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["odometry_edge_information"]


def odometry_edge_information(information, Z, sigma_fraction: float, sigma_deg_per_m: float, dt_s: float = 0.0,
                              sigma_mps: float = 0.0) -> np.ndarray:
    """Information (6×6, (φ, ρ)) of an odometry edge with a model-noise floor.

    GICP's information (``OdometryResult.keyframe_information``, the sum of the matched points'
    ``Hᵀ Λ⁻¹ H`` [Liang2024 Eqs. 15-18]) only holds the sensor noise of the matched points. It ignores
    what dominates the drift in a smooth, self-similar drift: ring-to-ring matches, the
    constant-velocity prior along an unobserved axis, and unmodelled geometry. It claims millimetres per
    2 m edge where the odometry drifts by centimetres. Used as is, it leaves an intersection factor no
    weight against the chain. The edge covariance is therefore

    ``Σ = Ω_GICP⁻¹ + diag(σ_φ² I₃, σ_t² I₃)``,
    ``σ_t² = (sigma_fraction · max(|t|, 0.1 m))² + (sigma_mps · Δt)²``,
    ``σ_φ = sigma_deg_per_m · π/180 · max(|t|, 0.1 m)``,

    and the information is ``Σ⁻¹`` (minegeo's model-noise floor; not in the paper). The time term is the
    dead-reckoning part: along an axis the geometry does not observe, the odometry's motion is a
    constant-velocity prior (or a false stop when GICP matches laser ring to laser ring), whose error
    grows with the time the edge spans, not with the distance it claims. A non-positive-definite
    ``Ω_GICP`` (a failed edge) counts as no information (only the floor remains).

    Parameters
    ----------
    information : array (6, 6)
        GICP information of the edge, (φ, ρ) order.
    Z : array (4, 4)
        The edge's relative pose (its translation length sets the floor).
    sigma_fraction, sigma_deg_per_m : float
        Floor parameters (all 0: the GICP information, symmetrised and floored at 1e-9).
    dt_s, sigma_mps : float
        Time spanned by the edge (s) and the velocity uncertainty (m/s) of the time term.
    """
    W = 0.5 * (np.asarray(information, np.float64) + np.asarray(information, np.float64).T)
    lam, V = np.linalg.eigh(W)
    lam = np.maximum(lam, 1e-9)
    d = max(float(np.linalg.norm(np.asarray(Z, np.float64)[:3, 3])), 0.1)
    s_t = math.hypot(sigma_fraction * d, sigma_mps * max(float(dt_s), 0.0))
    s_phi = math.radians(sigma_deg_per_m) * d
    if s_t <= 0 and s_phi <= 0:
        return (V * lam) @ V.T
    S = (V / lam) @ V.T + np.diag([s_phi**2] * 3 + [s_t**2] * 3)
    out = np.linalg.inv(S)
    return 0.5 * (out + out.T)
