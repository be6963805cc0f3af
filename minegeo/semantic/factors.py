"""The intersection factor graph of Liang et al. (2024), Sec. 3: keyframe poses, LiDAR relative-pose
factors and intersection position factors, solved by Levenberg–Marquardt on SE(3).

Frames and conventions
----------------------
* A pose is ``T_world_keyframe`` (4×4), ``p_world = R p_keyframe + t`` (m); the world frame is the
  frame of the intersection knowledge base.
* Tangent vectors are ordered rotation first, ``δ = (φ, ρ)`` (rad, m), perturbations on the right,
  ``T ← T · Exp(δ)``: the convention of :mod:`minegeo.slam.posegraph` and of GTSAM's ``Pose3``. The
  paper writes ``ξ = (ρ, φ)`` and perturbs on the left; :func:`relative_jacobians_left` and
  :func:`intersection_jacobians_paper` give its forms, and the right-perturbation Jacobians the
  solver uses are those times the chart change (``δ_left = Ad(T) δ_right``).
* Information matrices are in the residual's order: (rotation, translation) for relative factors,
  world (x, y, z) for intersection factors.

Factors
-------
* Relative pose ``(i, j, Z_ij)``, ``Z_ij`` the registered ``T_i⁻¹ T_j`` (keyframe j in keyframe i):
  ``r = Log(Z_ij⁻¹ T_i⁻¹ T_j)`` [Liang2024 Eq. 11]. The paper's ``T_i^j`` of [Liang2024 Eq. 10]
  is written as ``(T_j^W)⁻¹ T_i^W``, but only its inverse ``T_i⁻¹ T_j`` makes the residual of
  [Liang2024 Eq. 11] vanish at the truth: that is the measurement here. The residual and its
  Jacobians are :func:`minegeo.optim.factors.between_terms` (GTSAM's ``BetweenFactorPose3``).
* Intersection position ``(i, z, C)``, ``z`` the intersection's invariant point observed in keyframe
  i (m, keyframe frame), ``C`` its position in the knowledge base (m, world frame):
  ``e = C − t_i − R_i z`` [Liang2024 Eq. 22] (:mod:`minegeo.semantic._kernels`). The paper also
  lists ``z`` among the variables [Liang2024 Eq. 23]; here it is a measurement, and its
  Jacobian ``−R_i`` [Liang2024 Eq. 28] serves only to propagate its covariance.
* Pose prior ``(i, T_prior)``: ``r = Log(T_prior⁻¹ T_i)`` (GTSAM's ``PriorFactorPose3``,
  :class:`minegeo.optim.factors.PriorFactors`).
* Map registration ``(i, T_map)``: the same residual ``r = Log(T_map⁻¹ T_i)``, ``T_map`` the keyframe's
  pose registered to the prior map (:mod:`minegeo.semantic.mapfactor`), with a positive
  *semi*-definite information: zero along the pose directions the registration does not constrain.

The graph is solved by the one optimiser, :func:`minegeo.optim.lm.levenberg_marquardt` (block normal
equations, damping, stopping rule and result check shared with :mod:`minegeo.slam.posegraph`).

The cost is ``F = ½ Σ rᵀ Ω r + ½ Σ eᵀ Ω e``, the contract cost of ``slam_contract.md``, equal to
GTSAM's ``NonlinearFactorGraph.error(values)`` for the same factors (the paper's objective
[Liang2024 Eq. 7] is ``2F``).

Covariances
-----------
:func:`relative_pose_information` / :func:`relative_pose_covariance` implement
[Liang2024 Eqs. 15-18] exactly for matched point pairs, and :func:`intersection_covariance`
implements [Liang2024 Eqs. 29-32]; their docstrings state where the paper is ambiguous and what is
done instead.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from minegeo.errors import DegenerateGeometryError, InputError
from minegeo.kernels.lie import hat, se3_adjoint, se3_inverse, se3_right_jacobian_inv
from minegeo.optim import (
    BetweenFactors,
    FactorGroup,
    FactorProblem,
    LMStatus,
    PriorFactors,
    Values,
    between_terms,
    levenberg_marquardt,
    quadratic_cost,
)
from minegeo.semantic import _kernels as KS
from minegeo.slam.posegraph import PoseGraphParams

__all__ = [
    "FactorGraph", "FactorGraphResult", "PoseGraphParams", "descriptor_completeness",
    "intersection_covariance", "intersection_jacobians_paper", "intersection_terms",
    "point_pair_information", "relative_jacobians_left", "relative_pose_covariance",
    "relative_pose_information", "relative_terms",
]

log = logging.getLogger(__name__)

GAUGES = ("hold_first", "error")


# ------------------------------------------------------------------ validation


def _pose(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"{name} must be a finite 4x4 rigid transform, got shape {T.shape}")
    R = T[:3, :3]
    if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
            and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise InputError(f"{name} is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return np.ascontiguousarray(T)


def _vector3(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"{name} must be a finite 3-vector (m), got shape {v.shape}")
    return np.ascontiguousarray(v)


def _information(W, k: int, name: str) -> np.ndarray:
    """A finite, symmetric, positive-definite k×k information matrix (else :class:`InputError`)."""
    W = np.asarray(W, dtype=np.float64)
    if W.shape != (k, k) or not np.all(np.isfinite(W)):
        raise InputError(f"{name} must be a finite {k}x{k} information matrix, got shape {W.shape}")
    scale = max(float(np.abs(W).max()), 1e-300)
    if not np.allclose(W, W.T, rtol=0.0, atol=1e-9 * scale):
        raise InputError(f"{name} is not symmetric")
    if np.linalg.eigvalsh(W)[0] <= 1e-14 * scale:
        raise InputError(f"{name} is not positive definite (smallest eigenvalue {np.linalg.eigvalsh(W)[0]:.3g})")
    return np.ascontiguousarray(0.5 * (W + W.T))


def _points(P, name: str) -> np.ndarray:
    P = np.asarray(P, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or not np.all(np.isfinite(P)):
        raise InputError(f"{name} must be a finite (N, 3) array of points (m), got shape {P.shape}")
    return np.ascontiguousarray(P)


# ------------------------------------------------------------------ single-factor terms


def relative_terms(T_i, T_j, Z_ij):
    """Residual and right-perturbation Jacobians of one relative-pose factor [Liang2024 Eq. 11].

    Parameters
    ----------
    T_i, T_j : ndarray (4, 4)
        ``T_world_keyframe`` of keyframes i and j.
    Z_ij : ndarray (4, 4)
        Measured ``T_i⁻¹ T_j`` (keyframe j in keyframe i).

    Returns
    -------
    r : ndarray (6,)
        ``Log(Z⁻¹ T_i⁻¹ T_j)`` as ``(φ, ρ)`` (rad, m).
    J_i, J_j : ndarray (6, 6)
        ``∂r/∂δ_i = −J_r⁻¹(r) Ad(T_j⁻¹ T_i)``, ``∂r/∂δ_j = J_r⁻¹(r)`` for ``T ← T Exp(δ)``.
    """
    poses = np.ascontiguousarray(np.stack([_pose(T_i, "T_i"), _pose(T_j, "T_j")]))
    r, Ji, Jj = between_terms("SE3", poses, np.array([[0, 1]], dtype=np.int64), _pose(Z_ij, "Z_ij")[None].copy())
    return r[0], Ji[0], Jj[0]


def relative_jacobians_left(T_i, T_j, Z_ij):
    """The paper's left-perturbation Jacobians [Liang2024 Eqs. 12-14], rotation-first order.

    With ``T ← Exp(δ) T``: ``∂r/∂δ_i = −J_r⁻¹(r) Ad(T_j⁻¹)`` [Liang2024 Eq. 13] and
    ``∂r/∂δ_j = J_r⁻¹(r) Ad(T_j⁻¹)`` [Liang2024 Eq. 14]. They equal the right-perturbation
    Jacobians of :func:`relative_terms` times ``Ad(T)⁻¹`` (``δ_left = Ad(T) δ_right``). The paper
    orders ``ξ = (ρ, φ)``; here both rows and columns are ``(φ, ρ)``.

    Returns
    -------
    J_i, J_j : ndarray (6, 6)
    """
    r = relative_terms(T_i, T_j, Z_ij)[0]
    B = se3_right_jacobian_inv.py_func(r) @ se3_adjoint.py_func(se3_inverse.py_func(_pose(T_j, "T_j")))
    return -B, B


def intersection_terms(T_world_keyframe, z, C):
    """Residual and right-perturbation Jacobian of one intersection factor [Liang2024 Eq. 22].

    Parameters
    ----------
    T_world_keyframe : ndarray (4, 4)
    z : ndarray (3,)
        Intersection invariant point observed in the keyframe (m, keyframe frame).
    C : ndarray (3,)
        Its position in the knowledge base (m, world frame).

    Returns
    -------
    e : ndarray (3,)
        ``C − t − R z`` (m, world frame).
    J : ndarray (3, 6)
        ``[R hat(z), −R]`` with respect to ``δ = (φ, ρ)`` of ``T ← T Exp(δ)``.
    """
    r, J = np.empty((1, 3)), np.empty((1, 3, 6))
    KS.intersection_terms(_pose(T_world_keyframe, "T_world_keyframe")[None].copy(), np.zeros(1, dtype=np.int64),
                          _vector3(z, "z")[None].copy(), _vector3(C, "C")[None].copy(), r, J)
    return r[0], J[0]


def intersection_jacobians_paper(T_world_keyframe, z):
    """The paper's Jacobians of ``e = C − t − R z``: rotation by a left perturbation
    ``R ← Exp(φ) R`` and translation additively ``t ← t + δt``.

    Returns
    -------
    d_phi : ndarray (3, 3)
        ``hat(R z)`` [Liang2024 Eq. 26].
    d_t : ndarray (3, 3)
        ``−I`` [Liang2024 Eq. 27].
    d_z : ndarray (3, 3)
        ``−R``, with respect to the observation ``z`` [Liang2024 Eq. 28].
    """
    T = _pose(T_world_keyframe, "T_world_keyframe")
    R = T[:3, :3]
    return hat.py_func(R @ _vector3(z, "z")), -np.eye(3), -R.copy()


# ------------------------------------------------------------------ covariances


def _axis_covariance(sigma, name: str) -> np.ndarray:
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,))
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise InputError(f"{name} must be positive and finite (m), got {sigma!r}")
    return np.diag(s * s)


def _hats(P: np.ndarray) -> np.ndarray:
    """``hat(p)`` (N, 3, 3) of every row of ``P``."""
    out = np.zeros((P.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -P[:, 2], P[:, 1], -P[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = P[:, 2], -P[:, 1], P[:, 0]
    return out


def point_pair_information(points_a, points_b, T_a_b, cov_a, cov_b) -> np.ndarray:
    """Information (6×6, ``(φ, ρ)`` order) of ``T_a_b`` from matched points, ``Σ Hᵀ Λ⁻¹ H``.

    Pair ``m``: ``p_a ≈ T_a_b p_b``; residual ``d = T_a_b p_b − p_a`` (m, frame a), Jacobian
    ``H = [−R hat(p_b), R]`` for ``T_a_b ← T_a_b Exp(δ)``, covariance ``Λ = Σ_a + R Σ_b Rᵀ`` (each
    point's noise in its own frame). This is the Gauss–Newton information of the point-to-point
    registration at its optimum; its inverse is the covariance of ``δ``, hence of the pose.

    Parameters
    ----------
    points_a, points_b : ndarray (N, 3)
        Matched points (m) in frames a and b.
    T_a_b : ndarray (4, 4)
    cov_a, cov_b : ndarray (3, 3)
        Point noise covariance (m²) in frames a and b.

    Returns
    -------
    ndarray (6, 6)
        Information, 1/rad² and 1/m² blocks.
    """
    Pa, Pb = _points(points_a, "points_a"), _points(points_b, "points_b")
    if Pa.shape != Pb.shape:
        raise InputError(f"matched point arrays differ in shape: {Pa.shape} vs {Pb.shape}")
    T = _pose(T_a_b, "T_a_b")
    R = T[:3, :3]
    Lam_inv = np.linalg.inv(np.asarray(cov_a, dtype=np.float64) + R @ np.asarray(cov_b, dtype=np.float64) @ R.T)
    H = np.empty((Pb.shape[0], 3, 6))
    H[:, :, :3] = -np.einsum("ij,njk->nik", R, _hats(Pb))
    H[:, :, 3:] = R
    return np.einsum("nki,kl,nlj->ij", H, Lam_inv, H)


def relative_pose_information(points_i, points_j, Z_ij, sigma_xyz_m) -> np.ndarray:
    """Information (6×6, ``(φ, ρ)``) of a relative-pose factor from its matched feature points
    [Liang2024 Eqs. 15-18].

    Pair ``m``: ``p_i ≈ Z_ij p_j`` ([Liang2024 Eq. 15], written from j into i), ``H`` the Jacobian
    of that projection [Liang2024 Eq. 17], ``Ω = Σ Hᵀ Λ⁻¹ H`` [Liang2024 Eq. 16] with the LiDAR
    noise ``diag(σx², σy², σz²)`` on each point. The pair's covariance is
    ``Λ = Σ + R Σ Rᵀ``: the paper's ``Λ_L = diag(2σx², 2σy², 2σz²)`` [Liang2024 Eq. 18] is this
    exactly when ``σx = σy = σz`` or ``R = I`` (and an approximation otherwise).

    The paper calls Ω a covariance but uses it as ``Σ HᵀΛ⁻¹H``, an information matrix (it grows
    with the number of pairs); here it is the information, and :func:`relative_pose_covariance`
    its inverse. [Liang2024 Eq. 19] adds these matrices along the odometry to get a keyframe's
    accumulated covariance starting from zero; that is not a factor's weight (information
    does not add along a chain of relative poses) and is not implemented: each factor gets its own
    pair information, and the graph yields the keyframes' marginal covariances.

    Parameters
    ----------
    points_i, points_j : ndarray (N, 3)
        Matched feature points (m) in keyframes i and j (N ≥ 3, not collinear).
    Z_ij : ndarray (4, 4)
        Registered ``T_i⁻¹ T_j``.
    sigma_xyz_m : float or array (3,)
        LiDAR noise σ along the sensor's x, y, z axes (m).

    Returns
    -------
    ndarray (6, 6)
    """
    S = _axis_covariance(sigma_xyz_m, "sigma_xyz_m")
    return point_pair_information(points_i, points_j, Z_ij, S, S)


def relative_pose_covariance(points_i, points_j, Z_ij, sigma_xyz_m) -> np.ndarray:
    """Covariance (6×6, ``(φ, ρ)``, rad² / m²) of ``Z_ij``: the inverse of
    :func:`relative_pose_information` [Liang2024 Eqs. 15-18].

    Raises
    ------
    DegenerateGeometryError
        Fewer than 3 pairs or collinear points (the information is singular).
    """
    W = relative_pose_information(points_i, points_j, Z_ij, sigma_xyz_m)
    return _inverse_pd(W, "the matched points do not determine the relative pose (fewer than 3 or collinear)")


def _inverse_pd(W: np.ndarray, why: str) -> np.ndarray:
    ev = np.linalg.eigvalsh(W)
    if ev[0] <= 1e-12 * max(ev[-1], 1e-300):
        raise DegenerateGeometryError(why)
    out = np.linalg.inv(W)
    return 0.5 * (out + out.T)


def descriptor_completeness(k_c: int, k_b: int) -> float:
    """``k_c / k_b``: nonzero wall-contour dimensions of the PWCV descriptor seen from the keyframe
    (``k_c``) over those of the knowledge-base descriptor (``k_b``) [Liang2024 Eq. 32].

    From two descriptors directly: :func:`minegeo.semantic.descriptors.completeness` (capped at 1;
    0 when nothing is seen, which :func:`intersection_covariance` rejects)."""
    try:
        ok = float(k_c) == int(k_c) and float(k_b) == int(k_b) and int(k_c) > 0 and int(k_b) > 0
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(f"k_c and k_b must be positive integers, got {k_c!r}, {k_b!r}")
    return float(k_c) / float(k_b)


def intersection_covariance(completeness: float, base_sigma_m: float, *, scaling: str = "paper",
                            points_keyframe=None, points_map=None, T_world_keyframe=None, z=None) -> np.ndarray:
    """Covariance (3×3, m², world frame) of an intersection factor's residual [Liang2024 Eqs. 29-32].

    The noise of a matched point is ``Λ_I = s σ² I₃`` [Liang2024 Eq. 32], with ``σ = base_sigma_m``
    and ``s = k_c / k_b`` (``scaling="paper"``, literally the paper: a *less* complete descriptor
    gets a *smaller* noise) or ``s = k_b / k_c`` (``scaling="inverse"``: less complete, larger noise).

    * Without matched points the residual's covariance is ``Λ_I`` itself.
    * With the keyframe's points matched to the knowledge base's (``points_keyframe[m] ≈
      T⁻¹ points_map[m]``, [Liang2024 Eq. 29]) the pose information is
      ``Ω = Σ Qᵀ Λ_I⁻¹ Q`` [Liang2024 Eqs. 30-31] (:func:`point_pair_information` with the
      knowledge-base points noise-free), a 6×6 matrix: the paper pairs it with the 3-vector
      residual of [Liang2024 Eq. 22] without saying how. Here it is propagated to the residual,
      ``Σ_e = J Ω⁻¹ Jᵀ`` with ``J = [R hat(z), −R]`` (:func:`intersection_terms`): the covariance of
      the observed invariant point ``T z`` in the world given the registration's pose uncertainty.

    Parameters
    ----------
    completeness : float
        ``k_c / k_b`` (:func:`descriptor_completeness`), > 0.
    base_sigma_m : float
        Base noise σ (m) of a complete descriptor's match.
    scaling : {"paper", "inverse"}
    points_keyframe, points_map : ndarray (N, 3), optional
        Matched points (m) in the keyframe and in the world (knowledge base).
    T_world_keyframe : ndarray (4, 4), optional
        Needed with the points: the registered pose.
    z : ndarray (3,), optional
        Needed with the points: the observed invariant point (m, keyframe frame).

    Returns
    -------
    ndarray (3, 3)
    """
    c = float(completeness)
    if not (np.isfinite(c) and c > 0):
        raise InputError(f"completeness must be a positive ratio k_c/k_b, got {completeness!r}")
    if not (np.isfinite(base_sigma_m) and base_sigma_m > 0):
        raise InputError(f"base_sigma_m must be positive (m), got {base_sigma_m!r}")
    if scaling not in ("paper", "inverse"):
        raise InputError(f"scaling must be 'paper' or 'inverse', got {scaling!r}")
    lam = base_sigma_m**2 * (c if scaling == "paper" else 1.0 / c) * np.eye(3)  # [Liang2024 Eq. 32]
    if points_keyframe is None and points_map is None:
        return lam
    if T_world_keyframe is None or z is None or points_keyframe is None or points_map is None:
        raise InputError("with matched points, points_keyframe, points_map, T_world_keyframe and z are all needed")
    W = point_pair_information(points_map, points_keyframe, T_world_keyframe, np.zeros((3, 3)), lam)
    Sigma = _inverse_pd(W, "the matched intersection points do not determine the pose (fewer than 3 or collinear)")
    J = intersection_terms(T_world_keyframe, z, np.zeros(3))[1]
    out = J @ Sigma @ J.T
    return 0.5 * (out + out.T)


# ------------------------------------------------------------------ the graph


@dataclass(frozen=True)
class FactorGraphResult:
    """Outcome of :meth:`FactorGraph.optimize`.

    Attributes
    ----------
    poses : ndarray (n, 4, 4)
        Optimised ``T_world_keyframe`` (the start poses when ``status == "failed"``).
    status : LMStatus
        ``converged``, ``max_iterations`` or ``failed`` (the optimiser's status).
    reason : str
    cost_initial, cost_final : float
        ``F = ½ Σ rᵀΩr + ½ Σ eᵀΩe`` (no robust kernel) before and after; GTSAM's ``graph.error``.
    iterations : int
        Linearisations performed.
    history : list of dict
        Per damping trial: iteration, cost, lambda, accepted, largest step component.
    held : tuple of int
        Keyframes held at their start value: the ones added with ``fixed=True`` and, with
        ``gauge="hold_first"``, the first keyframe of every component the factors do not anchor.
    params : PoseGraphParams
    timings_s : dict
    """

    poses: np.ndarray
    status: LMStatus
    reason: str
    cost_initial: float
    cost_final: float
    iterations: int
    history: list = field(default_factory=list)
    held: tuple = ()
    params: PoseGraphParams = field(default_factory=PoseGraphParams)
    timings_s: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"status": self.status, "reason": self.reason, "cost_initial": self.cost_initial,
                "cost_final": self.cost_final, "iterations": self.iterations, "held": list(self.held),
                "params": asdict(self.params)}


@dataclass
class _Arrays:
    """The graph as contiguous arrays for the kernels."""

    edges: np.ndarray        # (m, 2) int64: relative factors
    Z: np.ndarray            # (m, 4, 4)
    info: np.ndarray         # (m, 6, 6), (φ, ρ) order
    prior_kf: np.ndarray     # (p,) int64
    prior_T: np.ndarray      # (p, 4, 4)
    prior_info: np.ndarray   # (p, 6, 6)
    kf: np.ndarray           # (q,) int64: keyframe of each intersection factor
    z: np.ndarray            # (q, 3) keyframe frame
    C: np.ndarray            # (q, 3) world frame
    info_int: np.ndarray     # (q, 3, 3)


class IntersectionFactors(FactorGroup):
    """Intersection position factors ``e = C − t_i − R_i z`` [Liang2024 Eq. 22] as a unary factor
    group of :mod:`minegeo.optim` (Jacobian ``[R hat(z), −R]``, [Liang2024 Eqs. 22, 26-27])."""

    def __init__(self, kf, z, C, information):
        self.variables = np.ascontiguousarray(kf, dtype=np.int64).reshape(-1, 1)
        self.kf = np.ascontiguousarray(self.variables[:, 0])
        self.z, self.C, self.information = z, C, information

    def residuals(self, values: Values) -> np.ndarray:
        e = np.empty((self.kf.shape[0], 3))
        KS.intersection_residuals(values.poses, self.kf, self.z, self.C, e)
        return e

    def linearize(self, values: Values) -> tuple:
        q = self.kf.shape[0]
        e, J = np.empty((q, 3)), np.empty((q, 3, 6))
        KS.intersection_terms(values.poses, self.kf, self.z, self.C, e, J)
        return e, (J,)


class FactorGraph:
    """Keyframe poses with relative-pose, intersection and prior factors [Liang2024 Eq. 7].

    Keyframes are numbered in the order they are added (0, 1, ...). Incremental use: add the new
    keyframe (its start pose, e.g. the previous optimum composed with the odometry,
    :meth:`predict`), its factors, and call :meth:`optimize`, which starts from the previous
    optimum (``warm_start=True``) or from the poses given when the keyframes were added.

    Examples
    --------
    >>> g = FactorGraph()
    >>> a = g.add_keyframe(np.eye(4))
    >>> b = g.add_keyframe(g.predict(a, Z_ab))                       # doctest: +SKIP
    >>> g.add_relative(a, b, Z_ab, np.eye(6) * 1e4)                  # doctest: +SKIP
    >>> g.add_intersection(b, z, C, np.eye(3) * 100, intersection_id=7)  # doctest: +SKIP
    >>> res = g.optimize()                                           # doctest: +SKIP
    """

    def __init__(self):
        self._initial: list[np.ndarray] = []
        self._estimate: list[np.ndarray] = []
        self._fixed: list[bool] = []
        self._rel: list[tuple] = []
        self._prior: list[tuple] = []
        self._int: list[tuple] = []
        self._map: list[tuple] = []

    # -- building
    @property
    def n_keyframes(self) -> int:
        return len(self._initial)

    @property
    def poses(self) -> np.ndarray:
        """Current estimate ``T_world_keyframe`` (n, 4, 4): the last optimum, or the start poses."""
        return np.stack(self._estimate) if self._estimate else np.zeros((0, 4, 4))

    def add_keyframe(self, T_world_keyframe, *, fixed: bool = False) -> int:
        """Add a keyframe with its start pose; ``fixed=True`` holds it there. Returns its index."""
        T = _pose(T_world_keyframe, "T_world_keyframe")
        self._initial.append(T.copy())
        self._estimate.append(T.copy())
        self._fixed.append(bool(fixed))
        return self.n_keyframes - 1

    def predict(self, i: int, Z_ij) -> np.ndarray:
        """Start pose of a new keyframe j: the current estimate of keyframe i times ``Z_ij``."""
        return self._estimate[self._index(i, "predict")] @ _pose(Z_ij, "Z_ij")

    def _index(self, i, what: str) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= int(i) < self.n_keyframes:
            raise InputError(f"{what} references keyframe {i!r}, but the graph has keyframes 0..{self.n_keyframes - 1}")
        return int(i)

    def add_relative(self, i: int, j: int, Z_ij, information) -> None:
        """Relative-pose factor ``r = Log(Z_ij⁻¹ T_i⁻¹ T_j)`` [Liang2024 Eq. 11].

        Parameters
        ----------
        i, j : int
            Keyframe indices (distinct).
        Z_ij : ndarray (4, 4)
            Measured ``T_i⁻¹ T_j`` (keyframe j in keyframe i).
        information : ndarray (6, 6)
            Positive definite, ``(φ, ρ)`` order (1/rad², 1/m²), e.g. :func:`relative_pose_information`.
        """
        i, j = self._index(i, "a relative factor"), self._index(j, "a relative factor")
        if i == j:
            raise InputError(f"a relative factor needs two different keyframes, got {i} twice")
        self._rel.append((i, j, _pose(Z_ij, "Z_ij"), _information(information, 6, "relative information")))

    def add_intersection(self, i: int, z, C, information, intersection_id: int = -1) -> None:
        """Intersection position factor ``e = C − t_i − R_i z`` [Liang2024 Eq. 22].

        Parameters
        ----------
        i : int
            Keyframe index.
        z : ndarray (3,)
            Invariant point of the intersection observed in keyframe i (m, keyframe frame).
        C : ndarray (3,)
            Its position in the knowledge base (m, world frame).
        information : ndarray (3, 3)
            Positive definite (1/m², world frame), e.g. the inverse of :func:`intersection_covariance`.
        intersection_id : int
            The knowledge base's id of the intersection (kept for reports).
        """
        i = self._index(i, "an intersection factor")
        self._int.append((i, _vector3(z, "z"), _vector3(C, "C"), _information(information, 3, "intersection information"),
                          int(intersection_id)))

    def add_prior(self, i: int, T_prior, information) -> None:
        """Pose prior ``r = Log(T_prior⁻¹ T_i)`` (GTSAM's ``PriorFactorPose3``), information ``(φ, ρ)``."""
        i = self._index(i, "a prior")
        self._prior.append((i, _pose(T_prior, "T_prior"), _information(information, 6, "prior information")))

    def add_map_registration(self, i: int, T_map, information) -> None:
        """Map-registration factor ``r = Log(T_map⁻¹ T_i)`` (a pose prior whose information may be singular).

        Parameters
        ----------
        i : int
            Keyframe index.
        T_map : ndarray (4, 4)
            ``T_world_keyframe`` registered to the prior map.
        information : ndarray (6, 6)
            Symmetric positive *semi*-definite, ``(φ, ρ)`` order (1/rad², 1/m², right perturbation at
            ``T_map``), e.g. :func:`minegeo.semantic.mapfactor.map_registration_information`: a direction
            the registration does not constrain carries zero information (the graph's other factors
            must constrain it; the factor never anchors a component on its own).
        """
        i = self._index(i, "a map-registration factor")
        W = np.asarray(information, dtype=np.float64)
        if W.shape != (6, 6) or not np.all(np.isfinite(W)):
            raise InputError(f"map-registration information must be a finite 6x6 matrix, got shape {W.shape}")
        scale = max(float(np.abs(W).max()), 1e-300)
        if not np.allclose(W, W.T, rtol=0.0, atol=1e-9 * scale):
            raise InputError("map-registration information is not symmetric")
        if np.linalg.eigvalsh(0.5 * (W + W.T))[0] < -1e-9 * scale:
            raise InputError("map-registration information is not positive semi-definite")
        self._map.append((i, _pose(T_map, "T_map"), np.ascontiguousarray(0.5 * (W + W.T))))

    @property
    def n_factors(self) -> dict:
        out = {"relative": len(self._rel), "intersection": len(self._int), "prior": len(self._prior)}
        if self._map:
            out["map"] = len(self._map)
        return out

    def map_factors(self) -> list[tuple]:
        """Every map-registration factor as ``(i, T_map, information)`` (copies)."""
        return [(i, T.copy(), W.copy()) for i, T, W in self._map]

    def relative_factors(self) -> list[tuple]:
        """Every relative factor as ``(i, j, Z_ij, information)`` (copies), in the order added."""
        return [(i, j, Z.copy(), W.copy()) for i, j, Z, W in self._rel]

    def intersection_factors(self) -> list[tuple]:
        """Every intersection factor as ``(i, z, C, information, intersection_id)`` (copies)."""
        return [(i, z.copy(), C.copy(), W.copy(), cid) for i, z, C, W, cid in self._int]

    def prior_factors(self) -> list[tuple]:
        """Every prior as ``(i, T_prior, information)`` (copies)."""
        return [(i, T.copy(), W.copy()) for i, T, W in self._prior]

    def set_estimate(self, poses) -> None:
        """Replace the current estimate (the next warm start) by ``poses`` (n, 4, 4) ``T_world_keyframe``."""
        P = np.asarray(poses, dtype=np.float64)
        if P.shape != (self.n_keyframes, 4, 4):
            raise InputError(f"poses must have shape {(self.n_keyframes, 4, 4)}, got {P.shape}")
        self._estimate = [_pose(T, f"poses[{k}]").copy() for k, T in enumerate(P)]

    def intersection_ids(self) -> np.ndarray:
        """The knowledge-base id of every intersection factor, in the order added."""
        return np.array([f[4] for f in self._int], dtype=np.int64)

    # -- arrays, cost, gauge
    def _arrays(self) -> _Arrays:
        q, p = len(self._int), len(self._prior)
        return _Arrays(
            np.ascontiguousarray(np.asarray([(i, j) for i, j, _, _ in self._rel], dtype=np.int64).reshape(-1, 2)),
            np.ascontiguousarray(np.asarray([f[2] for f in self._rel], dtype=np.float64).reshape(-1, 4, 4)),
            np.ascontiguousarray(np.asarray([f[3] for f in self._rel], dtype=np.float64).reshape(-1, 6, 6)),
            np.array([f[0] for f in self._prior], dtype=np.int64),
            np.ascontiguousarray(np.asarray([f[1] for f in self._prior], dtype=np.float64).reshape(p, 4, 4)),
            np.ascontiguousarray(np.asarray([f[2] for f in self._prior], dtype=np.float64).reshape(p, 6, 6)),
            np.array([f[0] for f in self._int], dtype=np.int64),
            np.ascontiguousarray(np.asarray([f[1] for f in self._int], dtype=np.float64).reshape(q, 3)),
            np.ascontiguousarray(np.asarray([f[2] for f in self._int], dtype=np.float64).reshape(q, 3)),
            np.ascontiguousarray(np.asarray([f[3] for f in self._int], dtype=np.float64).reshape(q, 3, 3)))

    def _groups(self) -> list:
        """The factors as groups of :mod:`minegeo.optim` over the keyframe poses."""
        a = self._arrays()
        m = len(self._map)
        return [BetweenFactors(a.edges, a.Z, a.info), PriorFactors(a.prior_kf, a.prior_T, a.prior_info),
                IntersectionFactors(a.kf, a.z, a.C, a.info_int),
                PriorFactors(np.array([f[0] for f in self._map], dtype=np.int64),
                             np.asarray([f[1] for f in self._map], dtype=np.float64).reshape(m, 4, 4),
                             np.asarray([f[2] for f in self._map], dtype=np.float64).reshape(m, 6, 6))]

    def _problem(self, held, params) -> FactorProblem:
        return FactorProblem(self.n_keyframes, 6, self._groups(), held, params,
                             labels=lambda v: (f"keyframe {v}", int(v)), hint=" (a keyframe no factor constrains?)")

    def cost(self, poses=None) -> float:
        """``F = ½ Σ rᵀΩr + ½ Σ eᵀΩe`` at ``poses`` (default: the current estimate); GTSAM's ``graph.error``."""
        P = self.poses if poses is None else np.asarray(poses, dtype=np.float64)
        if P.shape != (self.n_keyframes, 4, 4) or not np.all(np.isfinite(P)):
            raise InputError(f"poses must be finite with shape {(self.n_keyframes, 4, 4)}, got {P.shape}")
        V = Values(np.ascontiguousarray(P))
        total = 0.0
        for g in self._groups():
            if g.variables.shape[0]:
                total += quadratic_cost(g.residuals(V), g.information)
        return total

    def whitened_squares(self, poses=None) -> dict:
        """Every factor's squared Mahalanobis residual ``rᵀΩr`` at ``poses`` (default: the current
        estimate), by kind: ``{"relative": (m,), "prior": (p,), "intersection": (q,), "map": (r,)}`` in
        the order added (a map factor's ``rᵀΩr`` counts only its constrained directions). At the optimum of a graph whose information matrices are right, each is a χ² variate
        with the residual's dimension (6, 6, 3) less its share of the fitted parameters."""
        P = self.poses if poses is None else np.asarray(poses, dtype=np.float64)
        V = Values(np.ascontiguousarray(P))
        out = {}
        for name, g in zip(("relative", "prior", "intersection", "map"), self._groups(), strict=True):
            r = g.residuals(V) if g.variables.shape[0] else np.zeros((0, 3))
            out[name] = np.einsum("ei,eij,ej->e", r, g.information, r) if r.shape[0] else np.zeros(0)
        return out

    def _components(self) -> tuple[int, np.ndarray]:
        """Connected components of the keyframes under the relative factors (labels)."""
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        n = self.n_keyframes
        e = np.asarray([(i, j) for i, j, _, _ in self._rel], dtype=np.int64).reshape(-1, 2)
        adj = sp.coo_matrix((np.ones(e.shape[0]), (e[:, 0], e[:, 1])), shape=(n, n))
        return connected_components(adj, directed=False)

    def gauge(self, mode: str = "hold_first") -> tuple[int, ...]:
        """Keyframes to hold so that every component of the graph is anchored in the world.

        A component (keyframes joined by relative factors) is anchored by a held keyframe, a prior,
        or intersection factors whose knowledge-base points ``C`` span a plane (three or more
        non-collinear points fix all six degrees of freedom; one point, or points on a line, leave a
        rotation free). ``mode="hold_first"`` holds the first keyframe of every other component at
        its current pose (with intersection factors on one or two points this is a constraint, not
        only a gauge); ``mode="error"`` raises :class:`DegenerateGeometryError` naming it.

        Returns
        -------
        tuple of int
            The held keyframes (the ``fixed`` ones and those added for the gauge).
        """
        if mode not in GAUGES:
            raise InputError(f"gauge must be one of {GAUGES}, got {mode!r}")
        n_comp, label = self._components()
        anchored = np.zeros(n_comp, dtype=bool)
        anchored[label[[i for i, _, _ in self._prior]]] = True
        anchored[label[np.flatnonzero(self._fixed)]] = True
        for c in np.flatnonzero(~anchored):
            pts = np.asarray([f[2] for f in self._int if label[f[0]] == c]).reshape(-1, 3)
            if pts.shape[0] >= 3:
                s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
                anchored[c] = s[1] > 1e-6 * max(s[0], 1.0)
        held = [k for k in range(self.n_keyframes) if self._fixed[k]]
        for c in np.flatnonzero(~anchored):
            first = int(np.flatnonzero(label == c)[0])
            if mode == "error":
                raise DegenerateGeometryError(
                    f"keyframes {first}.. form a component that no prior, held keyframe or set of three "
                    f"non-collinear intersections anchors in the world: its position or rotation is free "
                    f"(add a prior, join it by a relative factor, or use gauge='hold_first')")
            held.append(first)
        return tuple(sorted(set(held)))

    def marginal_covariance(self, i: int, params: PoseGraphParams | None = None,
                            gauge: str = "hold_first") -> np.ndarray:
        """Marginal covariance (6×6, ``(φ, ρ)``, rad² / m², right perturbation ``T ← T Exp(δ)``) of
        keyframe ``i`` at the current estimate: the ``i`` block of ``H⁻¹``, ``H = Σ Jᵀ w Ω J`` the
        undamped Gauss–Newton information of every factor (robust weights ``w`` of ``params``) with the
        held keyframes of :meth:`gauge` removed.

        Computed by six solves with the optimiser's block Cholesky factor of ``H``
        (:class:`minegeo.optim.BlockSystem`, fill-reducing order), ``H x = e_c`` for the unit vectors
        of ``i``'s block; never a dense inverse. A held keyframe has covariance zero.

        Raises
        ------
        DegenerateGeometryError
            ``H`` is singular (a direction no factor constrains).
        """
        from minegeo.optim import SINGULAR_PIVOT

        params = params or PoseGraphParams()
        i = self._index(i, "marginal_covariance")
        if not (self._rel or self._int or self._prior or self._map):
            raise InputError("the factor graph has no factors: no covariance")
        problem = self._problem(self.gauge(gauge), params)
        values = Values(np.ascontiguousarray(self.poses))
        system = problem.linearize(values, problem.evaluate(values))
        c = int(system.col[i])
        if c < 0:
            return np.zeros((6, 6))
        Lx = system.cholesky(0.0, False, SINGULAR_PIVOT)
        if Lx is None:
            raise DegenerateGeometryError(
                f"the information matrix of the factor graph is singular at keyframe "
                f"{int(system.block_vertex[system.failed_block])}: no marginal covariance")
        out = np.empty((6, 6))
        for a in range(6):
            b = np.zeros(system.n_cols)
            b[c + a] = 1.0
            out[:, a] = system.solve_factored(Lx, b)[c:c + 6]
        return 0.5 * (out + out.T)

    # -- solving
    def optimize(self, params: PoseGraphParams | None = None, *, warm_start: bool = True,
                 gauge: str = "hold_first") -> FactorGraphResult:
        """Minimise ``F`` by Levenberg–Marquardt on SE(3) (:func:`minegeo.optim.lm.levenberg_marquardt`).

        Parameters
        ----------
        params : PoseGraphParams, optional
            Iterations, damping, tolerances and robust kernel (applied to every factor's whitened
            residual), as for :func:`minegeo.slam.posegraph.optimize_pose_graph`.
        warm_start : bool
            Start from the current estimate (the previous optimum, new keyframes at their start
            pose); else from the poses given to :meth:`add_keyframe`.
        gauge : {"hold_first", "error"}
            What to do with components no factor anchors in the world (:meth:`gauge`).

        Returns
        -------
        FactorGraphResult
            The current estimate is set to its poses unless ``status == "failed"``.
        """
        params = params or PoseGraphParams()
        t0 = time.perf_counter()
        if self.n_keyframes == 0 or not (self._rel or self._int or self._prior or self._map):
            raise InputError("the factor graph has no keyframes or no factors: nothing to optimise")
        held = self.gauge(gauge)
        start = np.ascontiguousarray(np.stack(self._estimate if warm_start else self._initial))
        out = levenberg_marquardt(self._problem(held, params), Values(start), params)
        poses = out.values.poses.copy()
        if out.status != "failed":
            self._estimate = [p.copy() for p in poses]
        return FactorGraphResult(poses, out.status, out.reason, out.cost_initial, out.cost_final, out.iterations,
                                 out.history, held, params, {"total": time.perf_counter() - t0})
