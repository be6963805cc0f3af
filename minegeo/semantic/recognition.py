"""Online intersection recognition of a keyframe against the knowledge base (Liang et al. 2024, Sec. 3.2).

Steps 1-9 of the paper's Sec. 3.2, for one keyframe (``docs/intersections.md``, "Online recognition
and tracking"):

1. **Preprocessing.** The current keyframe and its ``n_his`` predecessors are stacked in the current
   keyframe's frame [Liang2024 Eq. 20] and cropped to ``crop_radius_m``. The **ground plane** is a
   least-squares plane through the lowest points (two trimming passes); the cloud is levelled by its
   normal (frame ``L``: z up, same heading). **Walls** are the points ``wall_band_m`` above it; fewer
   than ``min_wall_points`` gives status ``no_walls``. A 16-ring LiDAR does not see the floor within
   ~5 m of itself, so the free space of every stacked keyframe is carved along its horizontal rays
   (virtual floor samples up to ``carve_margin_m`` before each azimuth's farthest wall return).
2. **Detection.** :func:`~minegeo.semantic.skeleton.drift_skeleton` of that cloud; the junction
   nearest to the sensor within ``max_junction_range_m`` is kept (else ``none``), its invariant point
   ``c`` (largest empty circle, z = floor) is the observation ``z`` (keyframe frame).
3.-5. **PWCV** of the stacked cloud around ``c`` against every knowledge-base PWCV (heading-invariant
   similarity, occlusion rule); the candidates are those ``>= pwcv_threshold`` (0.8). None: ``none``.
6. Several candidates: their **CWC** similarity decides; a runner-up within ``cwc_margin`` of the best
   (and not excluded by the odometry gate) gives ``ambiguous``.
7.-8. **Consecutive recognitions**: with a :class:`RecognitionState`, the same id must be the match
   of ``consecutive_required`` keyframes in a row (the paper's ``N_same = consecutive_required - 1``);
   until then the status is ``candidate``. The count restarts after a verification.
9. **Verification.** ICP (:func:`minegeo.registration.register_icp`, point-to-point) of the stacked
   cloud onto the intersection's dense cloud ``P^i`` from the pose implied by ``c -> C^i`` and the
   descriptor yaw (for a symmetric junction, the equally good shift nearest the predicted heading).
   ``rejected`` when the inlier RMS distance exceeds ``icp_max_distance_m`` or the overlap is below
   ``icp_min_fitness``, and ``rejected`` when the **observed point check** fails: the observed invariant
   point placed by the registered pose ``T_ICP`` (knowledge-base frame) must lie within the gate floor
   ``gate_m`` (m) of the matched intersection's point, ``|T_ICP z − C^i| ≤ gate_m`` (the ICP registers
   the whole stacked cloud and can fit the map around ``C^i`` from a junction detected metres away, a
   bend or a widening taken for a junction; the observation of a factor must be the junction it names,
   with or without a prediction); ``conflict`` when the matched intersection or the registered pose lies
   outside the gate of the odometry prediction (a nearly-alike intersection elsewhere in the mine). Only
   ``verified`` recognitions may become factors.

**The gate** (:class:`PredictionGate`) is a Mahalanobis gate around the predicted keyframe pose
``T̂`` with covariance ``Σ`` (6×6, ``(φ, ρ)``, right perturbation ``T = T̂ Exp(δ)``; the tracker's
factor-graph marginal). A world point ``x`` is within the gate of the point ``z`` of the keyframe when

``(x − T̂ z)ᵀ (J Σ Jᵀ + (g² / q) I)⁻¹ (x − T̂ z) ≤ q``,  ``J = R̂ [−hat(z), I]``,

``q`` the χ² quantile with 3 degrees of freedom at ``gate_probability`` (0.999: 16.27) and ``g`` the
floor ``gate_m``: without a covariance the gate is the sphere of radius ``g``, and it never shrinks
below that sphere (the floor stands for the error of the observed point itself). ``J`` is the first
order change of ``T̂ z`` under ``δ``. The same gate decides which look-alike candidates are
plausible (steps 6 and 9), refuses a match whose knowledge-base point lies outside it (even when it is
the only candidate), and refuses an ICP pose whose sensor position (``z = 0``) lies outside it. After
the ICP the pose is taken as known and the gate collapses to its floor: the observed point check of
step 9 (``|T_ICP z − C^i| ≤ RecognitionParams.gate_m``, always the parameter's floor, not a ``gate_m``
argument grown by a path-fraction gate: the ICP has removed the drift).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, group, validate
from minegeo._validate import as_points, as_transform, check_positive
from minegeo.errors import InputError, MinegeoError
from minegeo.geometry.se3 import compose, invert
from minegeo.semantic.descriptors import completeness, cwc, pwcv, similarity, stack_keyframes
from minegeo.semantic.knowledge import IntersectionKB
from minegeo.semantic.skeleton import SkeletonParams, drift_skeleton

__all__ = ["PredictionGate", "RecognitionParams", "RecognitionState", "Recognition", "RecognitionStatus",
           "recognise_keyframe",
           "level_and_carve", "STATUSES"]


class RecognitionStatus(StrEnum):
    """Status of a keyframe recognition (:attr:`Recognition.status`); each member is its string value.
    Only ``verified`` yields a factor."""

    #: no intersection in view (or none in the knowledge base)
    NONE = "none"
    #: too few wall points, or no drift skeleton
    NO_WALLS = "no_walls"
    #: matched, waiting for ``consecutive_required`` keyframes in a row
    CANDIDATE = "candidate"
    #: the descriptors do not single out one intersection
    AMBIGUOUS = "ambiguous"
    #: matched and verified by ICP: a factor
    VERIFIED = "verified"
    #: the ICP verification failed
    REJECTED = "rejected"
    #: verified by ICP but contradicting the odometry prediction
    CONFLICT = "conflict"


#: every status of a :class:`Recognition`; only ``verified`` yields a factor
STATUSES = tuple(RecognitionStatus)


@dataclass(frozen=True)
class RecognitionParams:
    """Parameters of :func:`recognise_keyframe` (lengths in m, angles in deg).

    Each numeric field declares its bounds in its metadata (:mod:`minegeo._params`): the same rule
    checks the dataclass, the ``minegeo track`` option that sets it (``--pwcv-threshold``,
    ``--n-his``, ``--consecutive``, ``--icp-max-distance``, ``--gate``) and its key in a ``--config``
    file; ``skeleton`` is a :class:`SkeletonParams` group (which checks itself).

    Attributes
    ----------
    pwcv_threshold : float
        ``epsilon_pwcv``: minimum PWCV similarity of a candidate (paper: 0.8).
    n_his : int
        ``N_his``: previous keyframes stacked with the current one [Liang2024 Eq. 20].
    consecutive_required : int
        Keyframes in a row that must match the same id before verification (paper's
        ``epsilon_same + 1``).
    cwc_margin : float
        Several PWCV candidates: a runner-up CWC within this of the best is ``ambiguous``.
    icp_max_distance_m : float
        ``epsilon_icp``: maximum inlier RMS distance after ICP. A correct match of a point-to-point ICP
        onto a map sampled every ``s`` has an RMS of about ``sqrt(s²/6 + σ_sensor² + σ_map²)`` (the
        RMS distance to the nearest sample of a square grid is ``s/√6``): 0.089 m for the 0.2 m map,
        3 cm sensor and 2 cm map noise of the synthetic networks. The default is 1.5 times that,
        0.135 m. A look-alike crossing with another roof height (X2 for X3) registers at 0.17 m:
        the walls fit, the roof does not. A coarser map needs a larger limit (CLI
        ``--icp-max-distance``).
    icp_min_fitness : float
        Minimum fraction of the stacked points within ``icp_gate_m`` of the dense cloud after ICP.
    icp_gate_m : float
        ICP correspondence gate of the final stage (the first stage uses three times this).
    gate_m : float
        Floor of the gate around the odometry prediction (m): the gate's radius without a covariance
        (see :class:`PredictionGate`); also the largest distance from the observed invariant point,
        placed by the verification's ICP pose, to the matched intersection's point (step 9).
    gate_probability : float
        Probability of the χ² (3 degrees of freedom) quantile of the Mahalanobis gate (0.999: 16.27).
    gate_yaw_deg : float
        Heading gate between the ICP pose and the prediction.
    crop_radius_m, max_junction_range_m : float
        Horizontal crop of the stacked cloud around the sensor; farthest junction kept.
    min_wall_points : int
        Fewer wall-band points: ``no_walls``.
    carve_margin_m, carve_step_m : float
        Free-space carving: stop this short of the wall return; sample spacing.
    icp_voxel_m : float
        Voxel of the stacked cloud for ICP.
    skeleton : SkeletonParams
        Detection parameters (as for the knowledge base).
    """

    pwcv_threshold: float = bounded(0.8, gt=0.0, le=1.0)
    n_his: int = bounded(5, ge=0, integer=True)
    consecutive_required: int = bounded(2, ge=1, integer=True)
    cwc_margin: float = bounded(0.02, ge=0.0)
    icp_max_distance_m: float = bounded(0.135, gt=0.0)
    icp_min_fitness: float = bounded(0.6, ge=0.0, le=1.0)
    icp_gate_m: float = bounded(0.5, gt=0.0)
    gate_m: float = bounded(3.0, gt=0.0)
    gate_probability: float = bounded(0.999, gt=0.0, lt=1.0)
    gate_yaw_deg: float = bounded(15.0, gt=0.0)
    crop_radius_m: float = bounded(20.0, gt=0.0)
    max_junction_range_m: float = bounded(8.0, gt=0.0)
    min_wall_points: int = bounded(200, ge=3, integer=True)
    carve_margin_m: float = bounded(0.5, ge=0.0)
    carve_step_m: float = bounded(0.2, gt=0.0)
    icp_voxel_m: float = bounded(0.2, gt=0.0)
    skeleton: SkeletonParams = group(SkeletonParams)

    def __post_init__(self):
        validate(self)


@dataclass
class RecognitionState:
    """Consecutive-recognition counter of steps 7-8 (mutable, one per run).

    Attributes
    ----------
    last_id : int
        Matched id of the previous keyframe (-1: none).
    streak : int
        Keyframes in a row matched to ``last_id`` (the paper's ``N_same + 1``).
    """

    last_id: int = -1
    streak: int = 0


@dataclass
class Recognition:
    """Outcome of :func:`recognise_keyframe` for one keyframe (mutable: the tracker revises the
    status of a recognition it holds; a status set as a string is stored as its
    :class:`RecognitionStatus` member, an unknown one is refused with ``ValueError``).

    Attributes
    ----------
    status : RecognitionStatus
        One of :data:`STATUSES`.
    reason : str
        Why (human-readable; empty for ``verified``).
    intersection_id : int
        Matched knowledge-base id (-1 when none).
    pwcv_scores : ndarray (k,)
        PWCV similarity to every knowledge-base intersection (empty when not computed).
    pwcv_score, cwc_score : float
        Scores of the match (NaN when not computed).
    candidates : tuple of int
        Ids with PWCV similarity >= the threshold.
    yaw_rad : float
        Descriptor yaw of the match (reference bearings to observed bearings, levelled frame).
    z_keyframe : ndarray (3,)
        Observed invariant point (m, keyframe frame); NaN when no junction was detected.
    completeness : float
        ``k_c / k_b`` of the observed PWCV against the match's [Liang2024 Eq. 32].
    icp_rms_m, icp_fitness : float
        Inlier RMS distance (m) and overlap of the verification ICP (NaN when not run).
    T_world_keyframe_icp : ndarray (4, 4) or None
        Keyframe pose in the knowledge-base frame registered by the ICP.
    prediction_error_m, prediction_yaw_error_deg : float
        ICP pose minus the odometry prediction (NaN without a prediction).
    observed_to_named_m : float
        ``|T_ICP z − C^i|`` (m, knowledge-base frame): the observed invariant point placed by the ICP
        pose, from the matched intersection's point (NaN when the ICP did not run). More than
        ``RecognitionParams.gate_m``: ``rejected``.
    streak : int
        Consecutive keyframes matched to this id (step 7).
    timings_s : dict
        Seconds per step (``preprocess``, ``detect``, ``descriptors``, ``verify``).
    """

    status: RecognitionStatus
    reason: str = ""
    intersection_id: int = -1
    pwcv_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pwcv_score: float = float("nan")
    cwc_score: float = float("nan")
    candidates: tuple = ()
    yaw_rad: float = float("nan")
    z_keyframe: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    completeness: float = float("nan")
    icp_rms_m: float = float("nan")
    icp_fitness: float = float("nan")
    T_world_keyframe_icp: np.ndarray | None = None
    prediction_error_m: float = float("nan")
    prediction_yaw_error_deg: float = float("nan")
    observed_to_named_m: float = float("nan")
    streak: int = 0
    timings_s: dict = field(default_factory=dict)

    def __setattr__(self, name, value):
        super().__setattr__(name, RecognitionStatus(value) if name == "status" else value)

    def summary(self) -> dict:
        """JSON-able summary (no arrays but the observed point and the ICP keyframe position, m, world)."""
        def f(v):
            return None if not np.isfinite(v) else float(v)

        return {"status": self.status, "reason": self.reason, "intersection_id": int(self.intersection_id),
                "pwcv_score": f(self.pwcv_score), "cwc_score": f(self.cwc_score),
                "candidates": [int(c) for c in self.candidates], "yaw_deg": f(math.degrees(self.yaw_rad)),
                "z_keyframe_m": [f(v) for v in self.z_keyframe], "completeness": f(self.completeness),
                "icp_rms_m": f(self.icp_rms_m), "icp_fitness": f(self.icp_fitness),
                "prediction_error_m": f(self.prediction_error_m),
                "prediction_yaw_error_deg": f(self.prediction_yaw_error_deg),
                "observed_to_named_m": f(self.observed_to_named_m), "streak": int(self.streak),
                "icp_position_m": (None if self.T_world_keyframe_icp is None
                                   else [float(v) for v in self.T_world_keyframe_icp[:3, 3]])}


class PredictionGate:
    """Mahalanobis gate around a predicted keyframe pose (module docstring, "The gate").

    Parameters
    ----------
    T_pred : array (4, 4)
        Predicted ``T_world_keyframe``.
    covariance : array (6, 6) or None
        Covariance of ``δ`` in ``T = T_pred Exp(δ)``, ``(φ, ρ)`` order (rad², m²). None: the sphere
        of radius ``floor_m``.
    floor_m : float
        Floor radius ``g`` (m).
    probability : float
        χ² (3 degrees of freedom) probability of the gate.
    """

    def __init__(self, T_pred, covariance, floor_m: float, probability: float = 0.999):
        from scipy.stats import chi2

        self.T = as_transform(T_pred, "T_world_kf_pred")
        self.cov = None if covariance is None else np.asarray(covariance, np.float64)
        if self.cov is not None and (self.cov.shape != (6, 6) or not np.all(np.isfinite(self.cov))):
            raise InputError(f"the prediction covariance must be a finite 6x6 matrix, got shape {self.cov.shape}")
        self.floor_m = check_positive(floor_m, "gate_m")
        self.probability = float(probability)
        self.limit = float(chi2.ppf(self.probability, 3))

    def point_covariance(self, z) -> np.ndarray:
        """Covariance (3×3, m², world) of ``T_pred z`` with the floor: ``J Σ Jᵀ + (g²/q) I``."""
        S = np.eye(3) * (self.floor_m**2 / self.limit)
        if self.cov is not None:
            z = np.asarray(z, np.float64)
            hz = np.array([[0.0, -z[2], z[1]], [z[2], 0.0, -z[0]], [-z[1], z[0], 0.0]])
            J = self.T[:3, :3] @ np.c_[-hz, np.eye(3)]
            S = S + J @ (0.5 * (self.cov + self.cov.T)) @ J.T
        return S

    def d2(self, z, x) -> float:
        """Squared Mahalanobis distance of the world point ``x`` from ``T_pred z``."""
        e = np.asarray(x, np.float64) - (self.T[:3, :3] @ np.asarray(z, np.float64) + self.T[:3, 3])
        return float(e @ np.linalg.solve(self.point_covariance(z), e))

    def inside(self, z, x) -> bool:
        """``x`` within the gate of ``T_pred z``."""
        return self.d2(z, x) <= self.limit

    def describe(self, z=(0.0, 0.0, 0.0)) -> str:
        """The gate in words: probability and the semi-axes (m) of its ellipsoid at ``T_pred z``."""
        ax = np.sqrt(np.maximum(np.linalg.eigvalsh(self.point_covariance(z)), 0.0) * self.limit)
        if self.cov is None:
            return f"{self.floor_m:.1f} m gate"
        return f"{100 * self.probability:g} % gate (semi-axes {ax[0]:.1f}, {ax[1]:.1f}, {ax[2]:.1f} m)"


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _yaw(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _ground_plane(P: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit normal (z > 0) and offset ``d`` of the floor plane ``n·p = d`` (m): least squares through
    the lowest points at 1.5-15 m range, trimmed twice (0.3 m, then 0.12 m). Level if too few."""
    r = np.hypot(P[:, 0], P[:, 1])
    Q = P[(r > 1.5) & (r < 15.0)]
    if Q.shape[0] < 30:
        Q = P
    z0 = float(np.quantile(Q[:, 2], 0.05))
    sel = np.abs(Q[:, 2] - z0) < 0.3
    n, d = np.array([0.0, 0.0, 1.0]), z0
    for tol in (0.3, 0.12):
        F = Q[sel]
        if F.shape[0] < 30:
            break
        A = np.c_[F[:, 0], F[:, 1], np.ones(F.shape[0])]
        a, b, c = np.linalg.lstsq(A, F[:, 2], rcond=None)[0]
        n = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1.0)
        d = c * n[2]
        sel = np.abs(Q @ n - d) < tol
    return n, float(d)


def _levelling(n: np.ndarray) -> np.ndarray:
    """Rotation ``R_L_k`` taking the floor normal ``n`` (keyframe frame) to +z with the least turn (no yaw)."""
    v = np.cross(n, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(v)), float(n[2])
    if s < 1e-12:
        return np.eye(3)
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1.0 - c) * K @ K


def level_and_carve(clouds: Sequence[np.ndarray], T_curr_his: Sequence[np.ndarray], params: RecognitionParams):
    """Step 1: stack [Liang2024 Eq. 20], crop, find the floor plane, level, carve the free space.

    Parameters
    ----------
    clouds : sequence of (n_i, 3) arrays
        Current keyframe (its sensor frame) then its predecessors (their frames).
    T_curr_his : sequence of (4, 4) arrays
        Pose of each predecessor in the current keyframe.

    Returns
    -------
    (ndarray (n, 3), ndarray (m, 3), ndarray (4, 4), int)
        The levelled real points (frame ``L``: origin at the current sensor, floor at z = 0, heading
        of the keyframe), the virtual floor samples, ``T_L_keyframe`` and the number of wall points.
    """
    S = stack_keyframes(clouds, T_curr_his)
    r = np.hypot(S[:, 0], S[:, 1])
    S = S[(r <= params.crop_radius_m) & (np.linalg.norm(S, axis=1) > 0.5)]
    if S.shape[0] < 3:
        return S, np.zeros((0, 3)), np.eye(4), 0
    n, d = _ground_plane(S)
    T = np.eye(4)
    T[:3, :3] = _levelling(n)
    T[2, 3] = -d                      # the plane n·p = d goes to z = 0
    L = S @ T[:3, :3].T + T[:3, 3]
    lo, hi = params.skeleton.wall_band_m
    wall = (L[:, 2] >= lo) & (L[:, 2] <= hi)
    origins = [np.zeros(3)] + [np.asarray(t, np.float64)[:3, 3] for t in T_curr_his]
    virt = []
    for o in origins:
        oL = T[:3, :3] @ o + T[:3, 3]
        W = L[wall] - oL
        rr = np.hypot(W[:, 0], W[:, 1])
        keep = rr > 1.0
        if not keep.any():
            continue
        az = np.floor((np.arctan2(W[keep, 1], W[keep, 0]) + np.pi) / (2 * np.pi) * 360).astype(np.int64) % 360
        far = np.zeros(360)
        np.maximum.at(far, az, rr[keep])
        b = np.flatnonzero(far > params.carve_margin_m)
        ang = (b + 0.5) * 2 * np.pi / 360 - np.pi
        for a, rmax in zip(ang, far[b] - params.carve_margin_m, strict=True):
            s = np.arange(0.0, rmax, params.carve_step_m)
            virt.append(np.c_[oL[0] + s * math.cos(a), oL[1] + s * math.sin(a), np.zeros(s.size)])
    V = np.concatenate(virt) if virt else np.zeros((0, 3))
    return np.ascontiguousarray(L), V, T, int(wall.sum())


def _pick_shift(sim, T_L_world_yaw_pred: float | None, period_tol: float = 0.03) -> float:
    """The descriptor yaw; for a symmetric junction (several shifts within ``period_tol`` of the best)
    the one nearest to the predicted yaw (``None``: the best)."""
    if T_L_world_yaw_pred is None:
        return sim.yaw_rad
    n = sim.scores.shape[0]
    good = np.flatnonzero(sim.scores >= sim.score - period_tol)
    frac = sim.yaw_rad - sim.shift * 2 * math.pi / n
    yaws = [_wrap(k * 2 * math.pi / n + frac) for k in good]
    return min(yaws, key=lambda y: abs(_wrap(y - T_L_world_yaw_pred)))


def _verify(L: np.ndarray, c_L: np.ndarray, yaw: float, kb: IntersectionKB, i: int, params: RecognitionParams):
    """ICP of the levelled stacked cloud onto ``P^i`` from ``c_L -> C^i`` and the yaw; ``T_world_L`` and the
    ICP result of the final (``icp_gate_m``) stage."""
    from minegeo.geometry import voxel_downsample
    from minegeo.registration import build_target_index
    from minegeo.registration.icp import ICPParams, register_icp

    R0 = _rz(-yaw)                    # observed = Rz(yaw) reference  =>  world = Rz(-yaw) observed
    T0 = np.eye(4)
    T0[:3, :3] = R0
    T0[:3, 3] = kb.invariant_points[i] - R0 @ c_L
    near = np.hypot(L[:, 0] - c_L[0], L[:, 1] - c_L[1]) <= kb.params.cloud_radius_m
    src = voxel_downsample(L[near], params.icp_voxel_m).points
    tgt = np.ascontiguousarray(kb.cloud(i))
    if src.shape[0] < 10 or tgt.shape[0] < 10:
        return T0, None
    index = build_target_index(tgt)
    res = register_icp(src, tgt, T0, ICPParams(3.0 * params.icp_gate_m, max_iterations=30), target_index=index,
                       check_target=False)
    res = register_icp(src, tgt, res.T_target_source, ICPParams(params.icp_gate_m, max_iterations=30),
                       target_index=index, check_target=False)
    return res.T_target_source, res


def _detect(clouds, T_his, params: RecognitionParams):
    """Steps 1-2: (status, reason, levelled points, T_L_keyframe, c_L or None); status None when a junction
    was detected (the matching decides)."""
    L, V, T_L_k, n_wall = level_and_carve(clouds, T_his, params)
    if n_wall < params.min_wall_points:
        return RecognitionStatus.NO_WALLS, (f"{n_wall} wall points between {params.skeleton.wall_band_m} m above the floor plane "
                            f"(fewer than {params.min_wall_points})"), L, T_L_k, None
    try:
        # the keyframe's free space is carved along its rays (V), dense; the footprint closing is for a map's
        # unsampled floor and roof, and on a keyframe it would bridge the openings the rays did not reach
        sk = drift_skeleton(np.concatenate([L, V]), replace(params.skeleton, fill_radius_m=0.0), complete_walls=False)
    except MinegeoError as exc:
        return RecognitionStatus.NO_WALLS, f"no drift skeleton: {exc}", L, T_L_k, None
    if sk.junction_xy.shape[0] == 0:
        return RecognitionStatus.NONE, "no intersection in view (the drift skeleton has no junction)", L, T_L_k, None
    dist = np.hypot(sk.junction_xy[:, 0], sk.junction_xy[:, 1])
    j = int(np.argmin(dist))
    if dist[j] > params.max_junction_range_m:
        return RecognitionStatus.NONE, (f"nearest junction {dist[j]:.1f} m away (more than {params.max_junction_range_m} m)"), \
            L, T_L_k, None
    c = np.r_[sk.junction_xy[j], sk.floor.height(sk.junction_xy[j:j + 1])[0]]
    return None, "", L, T_L_k, c


def _match(L, c_L, kb: IntersectionKB, params: RecognitionParams, yaw_pred_L):
    """Steps 3-6: (status, reason, id, pwcv scores, candidates, cwc score, similarity of the match, V_curr);
    status None when one intersection matched."""
    d = kb.params.descriptor
    V = pwcv(L, c_L, d)
    sims = [similarity(V, kb.pwcv[i]) for i in range(len(kb))]
    s = np.array([r.score for r in sims])
    cand = tuple(int(i) for i in np.flatnonzero(s >= params.pwcv_threshold))
    if not cand:
        return RecognitionStatus.NONE, (f"best PWCV similarity {s.max():.3f} below {params.pwcv_threshold} (not an intersection "
                        "of the knowledge base)"), -1, s, cand, float("nan"), None, V
    if len(cand) == 1:
        return None, "", cand[0], s, cand, float("nan"), sims[cand[0]], V
    M = cwc(L, c_L, d)                                        # step 6 (on the stacked cloud, [Liang2024 Eq. 20])
    cs = {i: similarity(M, kb.cwc[i]) for i in cand}
    order = sorted(cand, key=lambda i: -cs[i].score)
    best, second = order[0], order[1]
    if cs[best].score - cs[second].score < params.cwc_margin:
        return RecognitionStatus.AMBIGUOUS, (f"CWC similarity of ids {best} and {second}: {cs[best].score:.3f} and "
                             f"{cs[second].score:.3f} (margin {params.cwc_margin})"), best, s, cand, \
            cs[best].score, sims[best], V
    return None, "", best, s, cand, cs[best].score, sims[best], V


def recognise_keyframe(points_kf, history, kb: IntersectionKB, params: RecognitionParams | None = None, *,
                       T_world_kf_pred=None, gate_m: float | None = None, gate_cov=None,
                       state: RecognitionState | None = None) -> Recognition:
    """Recognise the intersection seen by a keyframe and verify it (steps 1-9 of Liang2024 Sec. 3.2).

    Parameters
    ----------
    points_kf : array_like (n, 3)
        Current keyframe points (m, its sensor frame, z roughly up).
    history : sequence of (points (m_i, 3), T_kf_his (4, 4))
        Previous keyframes (their own frames) with their poses in the current keyframe; the last
        ``params.n_his`` are stacked [Liang2024 Eq. 20].
    kb : IntersectionKB
    params : RecognitionParams, optional
    T_world_kf_pred : array_like (4, 4), optional
        Odometry prediction of the keyframe pose in the knowledge-base frame: resolves symmetric
        junctions' yaw and gates the verification (``conflict`` beyond the gate). None: no gate.
    gate_m : float, optional
        Floor of the gate (m); default ``params.gate_m``.
    gate_cov : array_like (6, 6), optional
        Covariance of the prediction (``(φ, ρ)``, right perturbation): the Mahalanobis gate of
        :class:`PredictionGate` at ``params.gate_probability``. None: the sphere of radius ``gate_m``.
    state : RecognitionState, optional
        Consecutive-recognition counter (updated in place). None: one keyframe is enough.

    Returns
    -------
    Recognition
    """
    params = params or RecognitionParams()
    t = {"preprocess": 0.0, "detect": 0.0, "descriptors": 0.0, "verify": 0.0}
    t0 = time.perf_counter()
    P = as_points(points_kf, "points_kf", min_points=0)
    hist = list(history)[-int(params.n_his):] if params.n_his else []
    T_pred = None if T_world_kf_pred is None else as_transform(T_world_kf_pred, "T_world_kf_pred")
    gate = None if T_pred is None else PredictionGate(T_pred, gate_cov, params.gate_m if gate_m is None else gate_m,
                                                      params.gate_probability)
    if kb.status != "ok" or len(kb) == 0:
        return Recognition(RecognitionStatus.NONE, f"the knowledge base holds no intersection ({kb.status})", timings_s=t)
    status, reason, L, T_L_k, c_L = _detect([P] + [h[0] for h in hist], [h[1] for h in hist], params)
    t["detect"] = time.perf_counter() - t0
    if state is not None and status:
        state.last_id, state.streak = -1, 0
    if status:
        return Recognition(status, reason, timings_s=t)
    z = np.linalg.solve(T_L_k, np.r_[c_L, 1.0])[:3]
    yaw_pred_L = None
    if T_pred is not None:                    # heading of the levelled frame L in the world, predicted
        T_wL = compose(T_pred, invert(T_L_k))
        yaw_pred_L = -_yaw(T_wL[:3, :3])       # descriptor yaw = -(yaw of L in the world)
    t1 = time.perf_counter()
    status, reason, i, s, cand, cscore, sim, V = _match(L, c_L, kb, params, yaw_pred_L)
    t["descriptors"] = time.perf_counter() - t1
    rec = Recognition(status or RecognitionStatus.CANDIDATE, reason, i, s, float(s[i]) if i >= 0 else float(np.max(s)), cscore, cand,
                      float("nan") if sim is None else sim.yaw_rad, z, timings_s=t)
    if i >= 0:
        rec.completeness = completeness(V, kb.pwcv[i])
    if status == "none":
        if state is not None:
            state.last_id, state.streak = -1, 0
        return rec
    if status == "ambiguous" and T_pred is None:
        if state is not None:
            state.last_id, state.streak = -1, 0
        return rec
    if state is not None:                     # steps 7-8
        state.streak = state.streak + 1 if state.last_id == i else 1
        state.last_id = i
        rec.streak = state.streak
        if state.streak < params.consecutive_required and status != "ambiguous":
            rec.reason = f"{state.streak} of {params.consecutive_required} consecutive keyframes matched id {i}"
            return rec
    t2 = time.perf_counter()
    _verify_step(rec, L, c_L, T_L_k, sim, kb, params, T_pred, yaw_pred_L, gate, cand)
    t["verify"] = time.perf_counter() - t2
    if state is not None and rec.status == "verified":
        state.streak = 0
    return rec


def _verify_step(rec: Recognition, L, c_L, T_L_k, sim, kb, params, T_pred, yaw_pred_L,
                 gate: PredictionGate | None, cand) -> None:
    """Step 9 (and, with a prediction, the resolution of an ``ambiguous`` match): fills ``rec`` in place."""
    ids = [rec.intersection_id]
    z = rec.z_keyframe
    if rec.status == "ambiguous":             # CWC did not decide: the odometry gate may (the one candidate in it)
        # 3-D gate: a look-alike on another level is not within it
        inside = [c for c in cand if gate.inside(z, kb.invariant_points[c])]
        if len(inside) != 1:
            rec.reason += f"; {len(inside)} of them within the {gate.describe(z)} of the prediction"
            return
        ids = inside
        rec.intersection_id = ids[0]
        sim = similarity(pwcv(L, c_L, kb.params.descriptor), kb.pwcv[ids[0]])
        rec.pwcv_score = float(sim.score)
    elif gate is not None:
        if not gate.inside(z, kb.invariant_points[rec.intersection_id]):   # even when the only candidate
            rec.status = RecognitionStatus.CONFLICT
            rec.reason = (f"intersection {rec.intersection_id} matched, but it lies outside the {gate.describe(z)} "
                          f"of the prediction (Mahalanobis distance "
                          f"{math.sqrt(gate.d2(z, kb.invariant_points[rec.intersection_id])):.1f}, limit "
                          f"{math.sqrt(gate.limit):.1f}): a nearly-alike intersection elsewhere")
            return
        # a factor only when the match is the one look-alike in the gate
        rivals = [int(c) for c in cand if c != rec.intersection_id and gate.inside(z, kb.invariant_points[c])]
        if rivals:
            rec.status = RecognitionStatus.AMBIGUOUS
            rec.reason = (f"intersection {rec.intersection_id} matched, but the look-alike candidate(s) "
                          f"{', '.join(map(str, rivals))} also lie within the {gate.describe(z)} of the prediction")
            return
    i = ids[0]
    yaw = _pick_shift(sim, yaw_pred_L)
    rec.yaw_rad = float(yaw)
    T_wL, res = _verify(L, c_L, yaw, kb, i, params)
    if res is None:
        rec.status, rec.reason = RecognitionStatus.REJECTED, "too few points for the ICP verification"
        return
    rec.icp_rms_m, rec.icp_fitness = float(res.inlier_rmse_m), float(res.fitness)
    T_wk = compose(T_wL, T_L_k)
    rec.T_world_keyframe_icp = T_wk
    if T_pred is not None:
        rec.prediction_error_m = float(np.linalg.norm(T_wk[:3, 3] - T_pred[:3, 3]))
        rec.prediction_yaw_error_deg = float(abs(math.degrees(_wrap(_yaw(T_wk[:3, :3]) - _yaw(T_pred[:3, :3])))))
    if not (rec.icp_rms_m <= params.icp_max_distance_m and rec.icp_fitness >= params.icp_min_fitness):
        rec.status = RecognitionStatus.REJECTED
        rec.reason = (f"ICP distance {rec.icp_rms_m:.3f} m (max {params.icp_max_distance_m}) and overlap "
                      f"{rec.icp_fitness:.2f} (min {params.icp_min_fitness}) against intersection {i}")
        return
    # the observed junction, placed by the ICP pose, must be the named one: the pose being known after the
    # ICP, the gate collapses to its floor (the error of the observed point itself)
    x_obs = T_wk[:3, :3] @ z + T_wk[:3, 3]
    rec.observed_to_named_m = float(np.linalg.norm(x_obs - kb.invariant_points[i]))
    if not rec.observed_to_named_m <= params.gate_m:
        rec.status = RecognitionStatus.REJECTED
        rec.reason = (f"the ICP fits intersection {i}, but it places the detected junction point "
                      f"{rec.observed_to_named_m:.1f} m from that intersection's point (more than the gate floor "
                      f"{params.gate_m:g} m): the detected junction is not intersection {i}")
        return
    if T_pred is not None and (not gate.inside(np.zeros(3), T_wk[:3, 3])
                               or rec.prediction_yaw_error_deg > params.gate_yaw_deg):
        rec.status = RecognitionStatus.CONFLICT
        rec.reason = (f"intersection {i} verified by ICP puts the keyframe {rec.prediction_error_m:.1f} m / "
                      f"{rec.prediction_yaw_error_deg:.0f} deg from the odometry prediction ({gate.describe()} / "
                      f"{params.gate_yaw_deg:.0f} deg): a nearly-alike intersection elsewhere")
        return
    rec.status, rec.reason = RecognitionStatus.VERIFIED, ""
