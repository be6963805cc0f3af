"""Map-registration factors: a keyframe registered to the prior map, in the directions it constrains.

Between verified intersections the tracker of :mod:`minegeo.semantic.tracking` holds the keyframes by
the odometry alone. In a long dead end flown in and back out, that is hundreds of metres of drift
nothing checks. The prior map (the dense cloud the knowledge base was built from) is there, so every
``TrackParams.map_factor_spacing_m`` of path the keyframe's stacked cloud is registered to it around
its predicted pose, and the registration enters the factor graph as a pose factor
(:meth:`~minegeo.semantic.factors.FactorGraph.add_map_registration`) with an information that is
**zero along every direction the registration does not constrain**: in a straight, smooth drift the
motion along the drift is free (the walls slide along themselves), and the factor says nothing about it.

Frames: ``T_world_keyframe`` maps the keyframe frame (sensor at the keyframe, m) into the map (world)
frame; the pose perturbation is on the right, ``T = T_map Exp(δ)``, ``δ = (φ, ρ)`` (rad, m), the
convention of :mod:`minegeo.semantic.factors`.

Registration (:func:`register_to_map`): the stacked cloud (keyframe and its ``n_his`` predecessors,
as for the recognition), voxel-downsampled at ``RecognitionParams.icp_voxel_m``, point-to-plane ICP
(:func:`minegeo.registration.icp.register_icp`, Low 2004) on the map with PCA normals, from the
predicted pose, correspondence gate ``3 · icp_gate_m`` then ``icp_gate_m``; accepted with the
recognition's ICP checks (inlier RMS ``≤ icp_max_distance_m``, overlap ``≥ icp_min_fitness``) and its
prediction gate (the registered position inside the Mahalanobis gate of the prediction's covariance,
the heading within ``gate_yaw_deg``).

Information (:func:`map_registration_information`): with the matched source points ``p_i`` (keyframe
frame) and the map normals ``m_i = R_mapᵀ n_i`` (rotated into the keyframe frame), the point-to-plane
Jacobian of ``r_i = n_iᵀ (T p_i − q_i)`` for the right perturbation is ``J_i = [(p_i × m_i)ᵀ, m_iᵀ]``,
``H = Σ J_iᵀ J_i``. With ``L = sqrt(mean |p_i|²)`` (m) and ``D = diag(L, L, L, 1, 1, 1)`` the
dimensionless ``C = D⁻¹ H D⁻¹ / k`` (``k`` pairs; rotations as metres of surface displacement at
``L``; Gelfand et al. 2003) has eigenpairs ``(λ_j, v_j)``. A direction is *constrained* when
``λ_j ≥ min_ratio · λ_max``; on those alone

``Ω = D (Σ_j w_j v_j v_jᵀ) D``,  ``w_j = 1 / (σ_rms² / (k λ_j) + σ_floor²)``,

``σ_rms`` the ICP's inlier RMS (m) and ``σ_floor`` (m) the model-noise floor (map error, roughness,
correlated residuals: the ICP's own ``σ²/(kλ)`` claims millimetres). The unconstrained directions
get exactly zero. minegeo's formula; not in Liang et al. (2024).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import InputError

__all__ = ["MapPrior", "MapRegistration", "map_registration_counts", "map_registration_information", "register_to_map"]


def map_registration_information(points_kf, normals_kf, sigma_rms_m: float, sigma_floor_m: float,
                                 min_ratio: float) -> tuple[np.ndarray, dict]:
    """Information (6×6, ``(φ, ρ)``, right perturbation) of a point-to-plane registration, zero along
    its unconstrained directions (module docstring, "Information").

    Parameters
    ----------
    points_kf : array (k, 3)
        Matched source points in the keyframe frame (m).
    normals_kf : array (k, 3)
        Unit normals of their map matches, rotated into the keyframe frame.
    sigma_rms_m : float
        Residual RMS of the registration (m).
    sigma_floor_m : float
        Model-noise floor ``σ_floor`` (m, > 0).
    min_ratio : float
        A direction is constrained when its eigenvalue of ``C`` is at least this times the largest.

    Returns
    -------
    information : ndarray (6, 6)
        Symmetric positive semi-definite, rank = the number of constrained directions.
    info : dict
        ``rank``, ``eigenvalues`` (ascending, of ``C``), ``ratio`` (smallest / largest), ``L_m``,
        ``free`` (the unconstrained directions in words).
    """
    P = np.asarray(points_kf, np.float64).reshape(-1, 3)
    N = np.asarray(normals_kf, np.float64).reshape(-1, 3)
    if P.shape != N.shape:
        raise InputError(f"points_kf {P.shape} and normals_kf {N.shape} differ in shape")
    if not (sigma_floor_m > 0 and math.isfinite(sigma_floor_m)):
        raise InputError(f"sigma_floor_m must be finite and > 0, got {sigma_floor_m!r}")
    k = P.shape[0]
    if k == 0:
        return np.zeros((6, 6)), {"rank": 0, "eigenvalues": [0.0] * 6, "ratio": 0.0, "L_m": 0.0,
                                  "free": "everything (no correspondences)"}
    J = np.concatenate([np.cross(P, N), N], axis=1)             # (k, 6): [(p × m)ᵀ, mᵀ]
    H = J.T @ J
    L = float(np.sqrt(np.mean(np.einsum("ij,ij->i", P, P))))
    d = np.array([L] * 3 + [1.0] * 3) if L > 0 else np.ones(6)
    C = H / d[:, None] / d[None, :] / k
    lam, V = np.linalg.eigh(0.5 * (C + C.T))
    lam = np.maximum(lam, 0.0)
    keep = lam >= min_ratio * lam[-1] if lam[-1] > 0 else np.zeros(6, bool)
    W = np.zeros((6, 6))
    free = []
    for j in range(6):
        v = V[:, j]
        if keep[j]:
            w = 1.0 / (sigma_rms_m**2 / (k * lam[j]) + sigma_floor_m**2)
            W += w * np.outer(v, v)
        else:
            rot, tra = np.linalg.norm(v[:3]), np.linalg.norm(v[3:])
            a = v[3:] / tra if tra >= rot else v[:3] / rot
            free.append(f"{'translation along' if tra >= rot else 'rotation about'} "
                        f"({a[0]:+.2f}, {a[1]:+.2f}, {a[2]:+.2f})")
    W = d[:, None] * W * d[None, :]
    return 0.5 * (W + W.T), {"rank": int(keep.sum()), "eigenvalues": lam.tolist(),
                             "ratio": float(lam[0] / lam[-1]) if lam[-1] > 0 else 0.0, "L_m": L,
                             "free": "; ".join(free)}


@dataclass
class MapPrior:
    """The prior map for registration: points (m, world), PCA unit normals and the search index.

    Build with :meth:`from_points` (normals by :func:`minegeo.geometry.normals.estimate_normals`,
    kNN 30).
    """

    points: np.ndarray
    normals: np.ndarray
    index: object = field(repr=False)

    @classmethod
    def from_points(cls, points) -> MapPrior:
        from minegeo.geometry.normals import estimate_normals
        from minegeo.registration import build_target_index

        P = np.ascontiguousarray(np.asarray(points, np.float64))
        if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 10 or not np.all(np.isfinite(P)):
            raise InputError(f"the prior map must be a finite (N >= 10, 3) array of points (m), got shape {P.shape}")
        N = np.ascontiguousarray(estimate_normals(P).normals, dtype=np.float64)
        return cls(P, N, build_target_index(P))


@dataclass
class MapRegistration:
    """One keyframe's registration to the prior map.

    Attributes
    ----------
    keyframe : int
    status : str
        ``factor`` (added to the graph), ``rejected`` (an ICP check or the gate failed) or
        ``degenerate`` (no direction constrained).
    reason : str
    T_world_keyframe : ndarray (4, 4) or None
        The registered pose.
    information : ndarray (6, 6) or None
        :func:`map_registration_information` (``(φ, ρ)``, right perturbation at the registered pose).
    rank : int
        Constrained directions.
    rms_m, fitness : float
        ICP inlier RMS (m) and overlap.
    prediction_error_m : float
        ``|t_map − t_pred|`` (m).
    """

    keyframe: int
    status: str
    reason: str = ""
    T_world_keyframe: np.ndarray | None = None
    information: np.ndarray | None = None
    rank: int = 0
    rms_m: float = float("nan")
    fitness: float = float("nan")
    prediction_error_m: float = float("nan")
    free: str = ""

    def summary(self) -> dict:
        return {"keyframe": self.keyframe, "status": self.status, "reason": self.reason, "rank": self.rank,
                "rms_m": self.rms_m, "fitness": self.fitness, "prediction_error_m": self.prediction_error_m,
                "free": self.free}


def _yaw(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def register_to_map(keyframe: int, points_kf, T_pred, prior: MapPrior, rp, gate, sigma_floor_m: float,
                    min_ratio: float) -> MapRegistration:
    """Register the stacked cloud ``points_kf`` (keyframe frame, m) to ``prior`` from ``T_pred``
    (module docstring, "Registration"); the result's information by :func:`map_registration_information`.

    Parameters
    ----------
    keyframe : int
    points_kf : array (n, 3)
    T_pred : array (4, 4)
        Predicted ``T_world_keyframe``.
    prior : MapPrior
    rp : RecognitionParams
        ``icp_voxel_m``, ``icp_gate_m``, ``icp_max_distance_m``, ``icp_min_fitness``, ``gate_yaw_deg``.
    gate : PredictionGate or None
        The prediction's Mahalanobis gate (None: no gate).
    sigma_floor_m, min_ratio : float
        As in :func:`map_registration_information`.
    """
    from minegeo.geometry import voxel_downsample
    from minegeo.registration.icp import ICPParams, register_icp

    src = voxel_downsample(np.asarray(points_kf, np.float64), rp.icp_voxel_m).points
    if src.shape[0] < 50:
        return MapRegistration(keyframe, "rejected", f"{src.shape[0]} points after downsampling (< 50)")
    T = np.asarray(T_pred, np.float64)
    for g in (3.0 * rp.icp_gate_m, rp.icp_gate_m):
        res = register_icp(src, prior.points, T, ICPParams(g, max_iterations=30, method="point_to_plane"),
                           target_normals=prior.normals, target_index=prior.index, check_target=False,
                           trusted_init=True)
        T = res.T_target_source
    out = MapRegistration(keyframe, "rejected", T_world_keyframe=T, rms_m=float(res.inlier_rmse_m),
                          fitness=float(res.fitness),
                          prediction_error_m=float(np.linalg.norm(T[:3, 3] - np.asarray(T_pred)[:3, 3])))
    if not (out.rms_m <= rp.icp_max_distance_m and out.fitness >= rp.icp_min_fitness):
        out.reason = (f"ICP distance {out.rms_m:.3f} m (max {rp.icp_max_distance_m}) and overlap {out.fitness:.2f} "
                      f"(min {rp.icp_min_fitness})")
        return out
    dyaw = abs(math.degrees(math.remainder(_yaw(T[:3, :3]) - _yaw(np.asarray(T_pred)[:3, :3]), 2 * math.pi)))
    if gate is not None and (not gate.inside(np.zeros(3), T[:3, 3]) or dyaw > rp.gate_yaw_deg):
        out.reason = (f"the registered pose lies {out.prediction_error_m:.1f} m / {dyaw:.0f} deg from the prediction "
                      f"(outside its {gate.describe()} / {rp.gate_yaw_deg:.0f} deg)")
        return out
    corr = res.correspondences
    Pk = src[corr[:, 0]]
    Nk = prior.normals[corr[:, 1]] @ T[:3, :3]                   # rows R^T n_i: normals in the keyframe frame
    W, info = map_registration_information(Pk, Nk, out.rms_m, sigma_floor_m, min_ratio)
    out.rank, out.free = info["rank"], info["free"]
    if info["rank"] == 0:
        out.status, out.reason = "degenerate", "the registration constrains no pose direction"
        return out
    out.status, out.information = "factor", W
    return out


def map_registration_counts(regs: list) -> dict:
    """Map registrations (:class:`MapRegistration`) by status, and the factors by the rank of the directions
    they constrain: ``{"tried", "factors", "by_status", "factor_rank"}``."""
    out: dict = {"tried": len(regs), "factors": 0, "by_status": {}, "factor_rank": {}}
    for r in regs:
        out["by_status"][r.status] = out["by_status"].get(r.status, 0) + 1
        if r.status == "factor":
            out["factors"] += 1
            out["factor_rank"][str(r.rank)] = out["factor_rank"].get(str(r.rank), 0) + 1
    return out
