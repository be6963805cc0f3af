"""Tracking with intersection factors: GICP odometry + online recognition + incremental factor graph
(Liang et al. 2024, Sec. 3; ``docs/intersections.md``, "Online recognition and tracking").

:func:`track` runs :func:`minegeo.slam.odometry.run_odometry` over the frames (it is a batch function:
there is no per-frame API), then replays its keyframes **in time order** as they would arrive:

* keyframe ``k`` enters the :class:`~minegeo.semantic.factors.FactorGraph` at the current estimate of
  ``k - 1`` composed with the odometry edge, with a relative-pose factor whose information is GICP's
  [Liang2024 Eqs. 15-18] (``OdometryResult.keyframe_information``, (φ, ρ) order) with a model-noise
  floor added to its covariance (:func:`odometry_edge_information`: GICP's own information claims
  millimetres where the odometry drifts by metres in a smooth drift);
* :func:`~minegeo.semantic.recognition.recognise_keyframe` runs on it with its ``n_his`` predecessors
  stacked [Liang2024 Eq. 20], the graph's current estimate as the prediction, and, with the map, the
  Mahalanobis gate of that prediction's covariance (:class:`~minegeo.semantic.recognition.PredictionGate`:
  χ² 3 degrees of freedom at ``RecognitionParams.gate_probability``, floored by ``gate_m``). The
  covariance is the graph's own: after each optimisation the marginal covariance of the newest keyframe
  (:meth:`~minegeo.semantic.factors.FactorGraph.marginal_covariance`, the ``H⁻¹`` block from the
  optimiser's Cholesky factor), then carried along each new odometry edge ``Z`` with its covariance
  ``Σ_Z`` (the inverse of the edge information below), ``Σ_k = Ad(Z⁻¹) Σ_{k-1} Ad(Z⁻¹)ᵀ + Σ_Z`` (right
  perturbation, first order): exactly the graph's marginal of the new keyframe when only the chain edge
  joins it, an upper bound when the odometry adds edges across keyframes. A recognition whose
  knowledge-base point or ICP pose lies outside the gate is a ``conflict``, a look-alike inside it
  makes the match ``ambiguous``, and one whose ICP pose places the observed invariant point more than
  ``RecognitionParams.gate_m`` (m) from the named point is ``rejected`` (the observed point check of
  :mod:`~minegeo.semantic.recognition`, step 9). Without the map (or with ``TrackParams.gate_drift_fraction`` set) the
  gate is the sphere ``gate_m + fraction · (path since the last verified recognition)``;
* a ``verified`` recognition adds an intersection factor (``z`` = the observed invariant point, ``C`` = the
  knowledge-base point, covariance ``Λ_I`` of :func:`~minegeo.semantic.factors.intersection_covariance`
  from the PWCV completeness [Liang2024 Eq. 32]; residual [Liang2024 Eq. 22]) and the graph is re-optimised from the previous
  optimum (warm start). Only verified recognitions make factors; every other status is recorded.
* frames between keyframes take the keyframes' correction interpolated in time (:func:`_frame_poses`).
* **No factor from a held keyframe**: a keyframe whose frame was not registered (a stretch held by the
  motion prior, or by the IMU when a registration disagreed with the gyro:
  :meth:`~minegeo.slam.odometry.OdometryResult.held_stretches`) adds no intersection or loop factor;
  a verified recognition there is recorded as ``rejected`` with the reason (:func:`_held_reason`).

**With an IMU** (``imu``, :class:`~minegeo.io.imu.ImuSamples`): the odometry takes the gyro as each
registration's rotation guess, deskews frames with per-point times by the gyro and rejects a
registration whose rotation disagrees with the gyro's (:mod:`minegeo.slam.inertial`); the keyframe
graph here has no IMU factors (the preintegration graph is :func:`minegeo.slam.pipeline.run_slam`'s).

**Map-registration factors** (``map_points``, the dense prior map the knowledge base was built
from; off without it): once the path since the last verified intersection (or the start) exceeds
``TrackParams.map_factor_after_m``, every ``map_factor_spacing_m`` of path the keyframe's stacked
cloud is registered to the map around its predicted pose (:mod:`~minegeo.semantic.mapfactor`: point-to-plane
ICP, the recognition's ICP checks and prediction gate) and, if accepted, enters the graph as a pose
factor whose information is zero along every direction the registration leaves free (the axis of a
straight drift), then the graph is re-optimised. They do not count as checks for
``unchecked_stretches`` (they may constrain only some directions); ``TrackResult.map_registrations``
lists every attempt.

**Start pose.** ``TrackParams.T_world_start`` (the first frame in the knowledge-base frame) holds keyframe
0 there. Without it the run is *unanchored*: the first verified recognition (ICP only, no gate) places
the keyframes so far by its registered pose, keyframe 0 is then held (gauge), and later recognitions are
gated.

**Without a map** (``use_map=False``, the paper's "Ours (no map)"): the knowledge base is built online.
A junction detected within ``online_add_range_m`` of the sensor, more than ``online_merge_m`` from every
entry, becomes an entry (its invariant point, stacked cloud and descriptors in the world frame of the
current estimate, remembered with its keyframe). An entry can be recognised only after
``revisit_min_path_m`` more metres of path (a re-visit, not the same pass); a verified re-visit adds a
relative-pose (loop) factor between the entry's keyframe and the current one from the ICP pose,
information ``diag(1/σ_φ², 1/σ_t²)`` with ``σ_t = intersection_sigma_m``, ``σ_φ = loop_sigma_deg``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, one_of, validate
from minegeo._validate import as_transform, internal_transform
from minegeo.errors import DegenerateGeometryError, InputError
from minegeo.geometry.se3 import compose, invert, relative
from minegeo.kernels.lie import se3_adjoint
from minegeo.semantic.descriptors import cwc, pwcv
from minegeo.semantic.factors import FactorGraph, intersection_covariance
from minegeo.semantic.knowledge import IntersectionKB, KBParams
from minegeo.semantic.mapfactor import map_registration_counts
from minegeo.semantic.recognition import (
    Recognition,
    RecognitionParams,
    RecognitionState,
    _detect,
    recognise_keyframe,
)
from minegeo.semantic.track_information import odometry_edge_information
from minegeo.slam.inertial import GyroAid
from minegeo.slam.odometry import OdometryParams, run_odometry

log = logging.getLogger(__name__)

__all__ = ["TRACK_ODOMETRY", "TrackParams", "TrackRecognition", "TrackResult", "TrackStatus", "track", "odometry_edge_information"]

#: the odometry settings of ``track`` that differ from ``OdometryParams()``'s (and ``minegeo slam``'s):
#: each frame's own GICP covariances and a 5-keyframe local map, as the flights of docs/intersections.md
#: were measured (see :class:`TrackParams` ``odometry``)
TRACK_ODOMETRY = {"covariance_frames": 1, "local_map_keyframes": 5}


@dataclass(frozen=True, eq=False)
class TrackParams:
    """Parameters of :func:`track` (lengths in m).

    Each numeric and choice field declares its rule in its metadata (:mod:`minegeo._params`): the same
    rule checks the dataclass, the ``minegeo track`` option that sets it (``--gate-drift``,
    ``--unchecked-path``) and its key in a ``--config`` file; ``odometry`` and ``recognition`` check
    themselves, ``T_world_start`` is checked as a rigid transform.

    Attributes
    ----------
    odometry : OdometryParams
        Default: frame-to-local-map GICP (``frame_target="submap"``): in long drifts frame-to-frame
        GICP with a VLP-16's sparse rings is biased towards no tilt change and no motion (see
        ``docs/intersections.md``, "Odometry").
    recognition : RecognitionParams
    T_world_start : array_like (4, 4), optional
        Pose of the first frame in the knowledge-base frame (None: unanchored until recognised).
    gate_drift_fraction : float or None
        With the map: None (default) gates each recognition by the covariance of its prediction (the
        Mahalanobis gate of the module docstring); a number replaces that by the sphere
        ``gate_m + gate_drift_fraction · (path since the last verified recognition)`` (m per m), which
        does not know how uncertain the prediction is: too wide after a recent anchor (look-alikes
        inside it leave the keyframe ``ambiguous``), too narrow after a long unanchored stretch.
    online_gate_drift_fraction : float
        The same without the map: the online base holds only the intersections seen so far, so an
        unseen look-alike cannot be ruled out and the gate stays narrow (0.05).
    intersection_sigma_m : float
        ``σ`` of :func:`~minegeo.semantic.factors.intersection_covariance` [Liang2024 Eq. 32].
    completeness_scaling : {"paper", "inverse"}
    same_place_m : float
        Two different ids verified within this of each other (world): ``conflict``.
    online_add_range_m, online_merge_m, revisit_min_path_m, loop_sigma_deg : float
        Without a map (see the module docstring).
    online_icp_max_distance_m : float
        ICP verification limit against the online base, whose clouds are keyframes downsampled at the
        odometry voxel ``v`` = 0.3 m with the sensor noise on both sides: 1.5 times
        ``sqrt(v²/6 + 2 · 0.03²)`` = 0.2 m (as ``RecognitionParams.icp_max_distance_m`` for the map).
    intersection_observation : {"icp", "detected"}
        The observation ``z`` of an intersection factor [Liang2024 Eq. 22]: ``"icp"`` (default) the base's
        invariant point put into the keyframe by the verification's ICP, ``"detected"`` the paper's
        invariant point detected in the keyframe. The detected point's height is the floor under it
        from a few laser rings and its position comes from a 0.25 m grid: on rough floors it lies
        0.1-0.3 m from the base's (corridor, 0.1 m rock: height error RMS 0.25 m with it).
    odometry_sigma_fraction, odometry_sigma_deg_per_m, odometry_sigma_mps : float
        Model-noise floor added to every odometry edge's covariance (see :func:`odometry_edge_information`):
        translation σ as a fraction of the edge length, rotation σ in degrees per metre of edge, and
        a velocity uncertainty (m/s) times the time the edge spans.
    unchecked_path_m : float
        A keyframe farther than this along the path (m) from every verified intersection (and, with
        ``T_world_start``, from the start) is placed by the odometry alone: such keyframes form the
        ``unchecked_stretches`` of the result, and any makes the status ``partial``. At the odometry's
        drift of about 1 % of the path the default (200 m) bounds such a position's error near 2 m.
    map_factor_after_m, map_factor_spacing_m : float
        With ``map_points``: map registrations start once the path since the last verified
        intersection (or the start) exceeds ``map_factor_after_m`` (m) and are ``map_factor_spacing_m``
        (m of path) apart.
    map_factor_sigma_m : float
        ``σ_floor`` (m) of :func:`~minegeo.semantic.mapfactor.map_registration_information`.
    map_factor_min_ratio : float
        A pose direction is constrained by a map registration when its eigenvalue of the normalised
        point-to-plane matrix is at least this fraction of the largest (else it gets no information).
    factor_test_probability : float
        After the last optimisation every intersection factor's ``eᵀΩe`` is tested against the χ²
        quantile with 3 degrees of freedom at this probability (0.999: 16.3); a factor beyond it
        disagrees with the odometry between its neighbours (a wrong recognition, or the odometry ran
        away) and makes the status ``inconsistent``.
    """

    odometry: OdometryParams = field(default_factory=lambda: OdometryParams(frame_target="submap", **TRACK_ODOMETRY))
    recognition: RecognitionParams = field(default_factory=RecognitionParams)
    T_world_start: object = None
    gate_drift_fraction: float | None = bounded(None, ge=0.0, optional=True)
    online_gate_drift_fraction: float = bounded(0.05, ge=0.0)
    intersection_sigma_m: float = bounded(0.2, gt=0.0)
    completeness_scaling: str = one_of("paper", ("paper", "inverse"))
    same_place_m: float = bounded(5.0, ge=0.0)
    online_add_range_m: float = bounded(3.0, ge=0.0)
    online_merge_m: float = bounded(10.0, ge=0.0)
    revisit_min_path_m: float = bounded(30.0, ge=0.0)
    loop_sigma_deg: float = bounded(1.0, ge=0.0)
    online_icp_max_distance_m: float = bounded(0.2, ge=0.0)
    odometry_sigma_fraction: float = bounded(0.05, ge=0.0)
    odometry_sigma_deg_per_m: float = bounded(0.1, ge=0.0)
    odometry_sigma_mps: float = bounded(0.1, ge=0.0)
    intersection_observation: str = one_of("icp", ("icp", "detected"))
    unchecked_path_m: float = bounded(200.0, gt=0.0)
    factor_test_probability: float = bounded(0.999, gt=0.0, lt=1.0)
    map_factor_after_m: float = bounded(50.0, ge=0.0)
    map_factor_spacing_m: float = bounded(10.0, gt=0.0)
    map_factor_sigma_m: float = bounded(0.2, gt=0.0)
    map_factor_min_ratio: float = bounded(0.02, gt=0.0, lt=1.0)

    def __post_init__(self):
        validate(self)
        if self.T_world_start is not None:
            as_transform(self.T_world_start, "T_world_start")

    def as_dict(self) -> dict:
        from dataclasses import asdict

        d = asdict(self)
        d["T_world_start"] = None if self.T_world_start is None else np.asarray(self.T_world_start).tolist()
        return d


@dataclass
class TrackRecognition:
    """One keyframe's recognition in a run: the :class:`Recognition`, its keyframe and time, and whether
    it became a factor."""

    keyframe: int
    frame: int
    time_s: float
    recognition: Recognition
    factor: bool = False

    def summary(self) -> dict:
        return {"keyframe": self.keyframe, "frame": self.frame, "time_s": self.time_s, "factor": self.factor,
                **self.recognition.summary()}


class TrackStatus(StrEnum):
    """Status of a :class:`TrackResult` (each member is its string value; :attr:`TrackResult.status`)."""

    OK = "ok"
    PARTIAL = "partial"
    INCONSISTENT = "inconsistent"
    NO_RECOGNITION = "no_recognition"
    UNANCHORED = "unanchored"
    NO_INTERSECTIONS = "no_intersections"


@dataclass(frozen=True)
class TrackResult:
    """Outcome of :func:`track`.

    Attributes
    ----------
    status : TrackStatus
        ``ok`` (factors, every one consistent, and no keyframe farther than
        ``TrackParams.unchecked_path_m`` of path from a verified intersection or the start pose);
        ``partial`` (consistent factors, but ``unchecked_stretches`` placed by the odometry alone);
        ``inconsistent`` (a factor fails the χ² test: ``inconsistent_factors``); ``no_recognition``
        (none verified; odometry only), ``unanchored`` (no start pose and nothing verified: poses in
        the first frame's frame) or ``no_intersections`` (the knowledge base has none; odometry only).
    reason : str
    times_s : ndarray (n,)
    poses : ndarray (n, 4, 4)
        ``T_world_frame`` of every frame after the last optimisation (world = knowledge-base frame).
    keyframes : ndarray (k,) int
        Frame index of each keyframe.
    keyframe_poses, keyframe_poses_online : ndarray (k, 4, 4)
        Final estimate, and the estimate right after each keyframe was processed (causal).
    recognitions : list of TrackRecognition
        Every keyframe's recognition (status ``none`` included).
    timings_s : dict
        Seconds per module: odometry, recognition steps, optimisation.
    use_map : bool
    odometry : OdometryResult
    online_points, online_keyframes : ndarray (e, 3), (e,)
        Without the map: the online base's invariant points (world) and the keyframe that created each
        entry (the entry's id is its row).
    n_optimisations : int
    map_registrations : list of MapRegistration
        Every map registration tried (``map_points`` given): keyframe, status (``factor``, ``rejected``,
        ``degenerate``), reason, constrained rank, ICP RMS and overlap.
    unchecked_stretches : list of dict
        Runs of keyframes farther than ``unchecked_path_m`` of path from every check (verified
        intersection, loop, start pose): first/last keyframe, frame and time, the path they span (m)
        and their largest path distance to a check (m).
    inconsistent_factors : list of dict
        Intersection factors beyond the χ² test after the last optimisation: keyframe, frame,
        intersection id, ``eᵀΩe`` and the residual's length (m).
    imu : dict or None
        With an IMU: the odometry's gyro bias at the end (rad/s, IMU axes) and the number of registered
        rotations it was estimated from (``result.imu`` of ``result.json``); None without one.
    """

    status: TrackStatus
    reason: str
    times_s: np.ndarray
    poses: np.ndarray
    keyframes: np.ndarray
    keyframe_poses: np.ndarray
    keyframe_poses_online: np.ndarray
    recognitions: list
    timings_s: dict
    use_map: bool = True
    odometry: object = None
    online_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    online_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_optimisations: int = 0
    imu: dict | None = None
    unchecked_stretches: list = field(default_factory=list)
    inconsistent_factors: list = field(default_factory=list)
    map_registrations: list = field(default_factory=list)

    def verified(self) -> list:
        """The recognitions that became factors."""
        return [r for r in self.recognitions if r.factor]

    def summary(self) -> dict:
        counts: dict[str, int] = {}
        for r in self.recognitions:
            counts[r.recognition.status] = counts.get(r.recognition.status, 0) + 1
        return {"status": self.status, "reason": self.reason, "frames": int(self.times_s.size),
                "keyframes": int(self.keyframes.size), "use_map": self.use_map, "status_counts": counts,
                "factors": len(self.verified()), "optimisations": self.n_optimisations,
                "recognised_ids": sorted({r.recognition.intersection_id for r in self.verified()}),
                "unchecked_stretches": self.unchecked_stretches, "inconsistent_factors": self.inconsistent_factors,
                **({} if not self.map_registrations else {"map_registrations": map_registration_counts(self.map_registrations)}),
                **({} if self.odometry is None else {"motion_prior_stretches": self.odometry.held_stretches()}),
                **({} if self.imu is None else {"imu": self.imu})}


class _OnlineKB:
    """Knowledge base grown from the run itself (``use_map=False``)."""

    def __init__(self, params: KBParams):
        self.params = params
        self.C, self.clouds, self.V, self.M, self.kf, self.path, self.T = [], [], [], [], [], [], []
        self.entry_of: dict = {}

    def add(self, C, cloud, kf: int, path_m: float, T_kf) -> None:
        d = self.params.descriptor
        self.C.append(C)
        self.clouds.append(cloud)
        self.V.append(pwcv(cloud, C, d))
        self.M.append(cwc(cloud, C, d))
        self.kf.append(kf)
        self.path.append(path_m)
        self.T.append(T_kf.copy())

    def view(self, path_m: float, min_gap_m: float) -> tuple[IntersectionKB, list]:
        """The entries made at least ``min_gap_m`` of path ago, as a knowledge base, and their indices."""
        idx = [i for i, p in enumerate(self.path) if path_m - p >= min_gap_m]
        d = self.params.descriptor
        k = len(idx)
        clouds = [self.clouds[i] for i in idx]
        off = np.r_[0, np.cumsum([len(c) for c in clouds])].astype(np.int64)
        kb = IntersectionKB("ok" if k else "no_intersections", "", np.arange(k, dtype=np.int64),
                            np.full(k, 3, np.int64), np.array([self.C[i] for i in idx]).reshape(k, 3),
                            np.zeros(k), off, np.concatenate(clouds) if k else np.zeros((0, 3)),
                            np.array([self.V[i] for i in idx]).reshape(k, d.n_sectors),
                            np.array([self.M[i] for i in idx]).reshape(k, d.n_bands, d.n_sectors), self.params, {})
        return kb, idx


def _frame_poses(odo, kf_poses: np.ndarray) -> np.ndarray:
    """Every frame placed by the keyframe correction interpolated in time.

    The correction of keyframe ``k`` is ``C_k = T_world_k T_odom_k⁻¹``; a frame at time ``t`` between
    keyframes ``k`` and ``k + 1`` gets ``C(t)`` (rotation by the SO(3) geodesic, translation linearly,
    ``α = (t − t_k) / (t_{k+1} − t_k)``) and ``T_world_f = C(t) T_odom_f``. Frames after the last keyframe
    keep its correction. A correction that the graph puts on one keyframe edge (e.g. where the
    odometry reported a false stop) is so spread over that edge's frames, not left at its end.
    """
    from minegeo.geometry.se3 import exp_so3, log_so3

    kf = odo.keyframes
    C = np.stack([compose(Tk, invert(To)) for Tk, To in zip(kf_poses, odo.poses[kf], strict=True)])
    t = odo.times_s
    out = np.empty_like(odo.poses)
    kf_of = np.searchsorted(kf, np.arange(t.size), side="right") - 1
    for f, k in enumerate(kf_of):
        Cf = C[k]
        if k + 1 < kf.size and f != kf[k]:
            a = (t[f] - t[kf[k]]) / max(t[kf[k + 1]] - t[kf[k]], 1e-12)
            Cf = np.eye(4)
            Cf[:3, :3] = C[k, :3, :3] @ exp_so3(a * log_so3(C[k, :3, :3].T @ C[k + 1, :3, :3]))
            Cf[:3, 3] = (1.0 - a) * C[k, :3, 3] + a * C[k + 1, :3, 3]
        out[f] = compose(Cf, odo.poses[f])
    return out


def _conflicting(rec: Recognition, T_world_kf: np.ndarray, done: list, same_place_m: float) -> str:
    """A reason when another id was verified at the same place (world estimate), else ''."""
    p = (T_world_kf @ np.r_[rec.z_keyframe, 1.0])[:3]
    for q, j in done:
        if j != rec.intersection_id and np.linalg.norm(p[:2] - q[:2]) < same_place_m:
            return (f"intersection {rec.intersection_id} verified where intersection {j} was verified before "
                    f"({np.linalg.norm(p[:2] - q[:2]):.1f} m apart)")
    return ""


def _held_reason(odo, frame: int) -> str:
    """Why keyframe frame ``frame`` gives no factor ("" when it was registered): it lies in a stretch held
    by the motion prior (or the IMU) alone, whose pose carries no registration."""
    if odo.frame_ok[frame]:
        return ""
    by = "the IMU (gyro rotation, constant-velocity translation)" if odo.imu_aided else "the motion prior alone"
    return (f"keyframe in a stretch held by {by} (frame {frame} not registered: {odo.frame_reason[frame]}): "
            "no factor")


def unchecked_stretches(path_m, checked, limit_m: float, keyframes, times_s) -> list:
    """Runs of keyframes whose path distance to every checked keyframe exceeds ``limit_m``.

    Keyframe ``k`` at path length ``s_k`` (m from the first keyframe) is unchecked when
    ``min_c |s_k − s_c| > limit_m`` over the checked keyframes ``c`` (every keyframe when none is).

    Parameters
    ----------
    path_m : ndarray (k,)
        Path length of each keyframe (m, non-decreasing).
    checked : sequence of int
        Keyframes a check places (verified intersection, loop, start pose).
    limit_m : float
    keyframes : ndarray (k,) int
        Frame index of each keyframe.
    times_s : ndarray (n,)
        Time of each frame (s).

    Returns
    -------
    list of dict
        ``first_keyframe``, ``last_keyframe``, ``first_frame``, ``last_frame``, ``first_time_s``,
        ``last_time_s``, ``path_m`` (path the run spans) and ``max_path_from_check_m``.
    """
    path_m = np.asarray(path_m, np.float64)
    n = path_m.size
    if len(checked):
        a = path_m[np.unique(np.asarray(checked, np.int64))]
        d = np.min(np.abs(path_m[:, None] - a[None, :]), axis=1)
    else:
        d = np.full(n, np.inf)
    out, k = [], 0
    while k < n:
        if d[k] <= limit_m:
            k += 1
            continue
        j = k
        while j + 1 < n and d[j + 1] > limit_m:
            j += 1
        fa, fb = int(keyframes[k]), int(keyframes[j])
        out.append({"first_keyframe": k, "last_keyframe": j, "first_frame": fa, "last_frame": fb,
                    "first_time_s": float(times_s[fa]), "last_time_s": float(times_s[fb]),
                    "path_m": float(path_m[j] - path_m[k]), "max_path_from_check_m": float(np.max(d[k:j + 1]))})
        k = j + 1
    return out


def track(frames: Iterable[tuple[float, np.ndarray]], kb: IntersectionKB | None, params: TrackParams | None = None,
          *, use_map: bool = True, progress=None, odometry=None, imu=None, map_points=None) -> TrackResult:
    """Track a LiDAR sequence with intersection factors (Liang et al. 2024, Sec. 3).

    Parameters
    ----------
    frames : iterable of (time_s, (m, 3) points)
        Frames in time order, points in the sensor frame (m), z roughly up.
    kb : IntersectionKB or None
        The knowledge base of the prior map (world = its frame). Not used with ``use_map=False``.
    params : TrackParams, optional
    use_map : bool
        True: recognise against ``kb`` ("ours (map)"); False: against the run's own online base
        ("ours (no map)", re-visits only).
    progress : callable, optional
        Called with the frame index after each odometry frame.
    odometry : OdometryResult, optional
        The result of :func:`~minegeo.slam.odometry.run_odometry` on these ``frames`` with
        ``params.odometry``, when already computed (``frames`` is then not read): a benchmark runs
        the odometry once for several methods.
    imu : ImuSamples or GyroAid, optional
        The IMU (:mod:`minegeo.slam.inertial`): gyro rotation guesses, gyro deskew and the IMU gate in
        the odometry. Its coverage of the frames is the caller's check
        (:func:`minegeo.slam.inertial.check_imu_for_frames`).
    map_points : array (N, 3), optional
        The dense prior map (m, world = the knowledge base's frame) for the map-registration factors
        (module docstring); None (default): none. Only with ``use_map=True``.

    Returns
    -------
    TrackResult
    """
    params = params or TrackParams()
    rp = params.recognition
    if use_map and kb is None:
        raise InputError("use_map=True needs a knowledge base (kb)")
    if map_points is not None and not use_map:
        raise InputError("map_points (map-registration factors) need use_map=True")
    t0 = time.perf_counter()
    aid = imu if imu is None or isinstance(imu, GyroAid) else GyroAid(imu)
    odo = run_odometry(frames, params.odometry, progress, imu=aid) if odometry is None else odometry
    timings = {"odometry": time.perf_counter() - t0, **{f"odometry_{k}": v for k, v in odo.timings_s.items()}}
    T_start = None if params.T_world_start is None else np.asarray(params.T_world_start, np.float64)
    if not use_map and T_start is None:
        T_start = np.eye(4)
    st = _State(odo, params, T_start, use_map)
    if map_points is not None:
        from minegeo.semantic.mapfactor import MapPrior

        tm = time.perf_counter()
        st.prior = MapPrior.from_points(map_points)
        timings["map_prepare"] = time.perf_counter() - tm
    online = None if use_map else _OnlineKB(kb.params if kb is not None else KBParams())
    usable = (not use_map) or (kb.status == "ok" and len(kb) > 0)
    state = RecognitionState()
    for k, f in enumerate(odo.keyframes):
        st.add_keyframe(k)
        hist = [(odo.keyframe_clouds[h], relative(st.T_odom(k), st.T_odom(h)))
                for h in range(max(0, k - rp.n_his), k)]
        tr = time.perf_counter()
        if not usable:
            rec = Recognition("none", f"the knowledge base holds no intersection ({kb.status})")
        elif use_map:
            rec = recognise_keyframe(odo.keyframe_clouds[k], hist, kb, rp, T_world_kf_pred=st.prediction(k),
                                     gate_m=st.gate(k), gate_cov=st.gate_covariance(k), state=state)
        else:
            rec = st.online_step(k, hist, online, state)
        for name, v in rec.timings_s.items():
            timings[f"recognition_{name}"] = timings.get(f"recognition_{name}", 0.0) + v
        timings["recognition"] = timings.get("recognition", 0.0) + time.perf_counter() - tr
        entry = TrackRecognition(k, int(f), float(odo.times_s[f]), rec)
        if rec.status == "verified":
            why = _conflicting(rec, st.pose_for_conflict(k, rec), st.done, params.same_place_m)
            if why:
                rec.status, rec.reason = "conflict", why
            elif _held_reason(odo, int(f)):
                rec.status, rec.reason = "rejected", _held_reason(odo, int(f))
            else:
                entry.factor = st.add_factor(k, rec, kb, online, timings)
        if st.prior is not None and not entry.factor:
            st.map_step(k, hist, timings)
        st.online_poses.append(st.current(k))
        st.recognitions.append(entry)
    res = st.result(use_map, usable, kb, online, timings)
    if aid is not None:
        res = replace(res, imu={"front_end_bias_gyro_rad_s": [float(x) for x in aid.bias_g],
                                "bias_updates": int(aid.n_updates)})
    return res


class _State:
    """The incremental graph of :func:`track` (keyframes in the odometry frame until anchored)."""

    def __init__(self, odo, params: TrackParams, T_start, use_map: bool = True):
        self.odo, self.params, self.use_map = odo, params, use_map
        self.g: FactorGraph | None = None
        self.T_world_odom = None if T_start is None else compose(T_start, invert(odo.poses[0]))
        self.path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(odo.poses[odo.keyframes, :3, 3], axis=0), axis=1))]
        self.last_anchor_path = 0.0
        self.done: list = []
        self.recognitions: list = []
        self.online_poses: list = []
        self.n_opt = 0
        self.cov = None          # covariance (6×6, (φ, ρ)) of the graph's newest keyframe
        self.cov_k = -1
        self.checked: list = [0] if T_start is not None else []   # keyframes a check places (start, factors)
        self.prior = None                  # MapPrior with map_points
        self.map_regs: list = []
        self.last_map_path = -np.inf
        if self.T_world_odom is not None:
            self._build(0)

    def T_odom(self, k: int) -> np.ndarray:
        return self.odo.poses[self.odo.keyframes[k]]

    def _build(self, upto: int) -> None:
        """Graph of keyframes 0..upto placed by ``T_world_odom``, keyframe 0 held."""
        g = FactorGraph()
        g.add_keyframe(compose(self.T_world_odom, self.T_odom(0)), fixed=True)
        self.cov, self.cov_k = np.zeros((6, 6)), 0
        for k in range(1, upto + 1):
            self._append(g, k)
        self.g = g

    def _append(self, g: FactorGraph, k: int) -> None:
        Z = self.odo.keyframe_edges[k - 1]
        g.add_keyframe(g.predict(k - 1, Z))
        p = self.params
        t = self.odo.times_s[self.odo.keyframes]
        info = odometry_edge_information(self.odo.keyframe_information[k - 1], Z, p.odometry_sigma_fraction,
                                         p.odometry_sigma_deg_per_m, t[k] - t[k - 1], p.odometry_sigma_mps)
        g.add_relative(k - 1, k, Z, info)
        if self.cov_k == k - 1:    # carried along the edge: Σ_k = Ad(Z⁻¹) Σ_{k-1} Ad(Z⁻¹)ᵀ + Ω⁻¹
            A = se3_adjoint(invert(Z))
            S = A @ self.cov @ A.T + np.linalg.inv(info)
            self.cov, self.cov_k = 0.5 * (S + S.T), k
        for i, j, Zij, I in self.odo.keyframe_extra_edges:  # across keyframes placed by the guess
            if j == k:
                g.add_relative(i, k, Zij, odometry_edge_information(
                    I, Zij, p.odometry_sigma_fraction, p.odometry_sigma_deg_per_m, t[k] - t[i], p.odometry_sigma_mps))

    def add_keyframe(self, k: int) -> None:
        if self.g is not None and k > 0:
            self._append(self.g, k)

    def prediction(self, k: int):
        """Keyframe ``k``'s pose in the graph (checked as an internal invariant, re-projected), or None."""
        return None if self.g is None else internal_transform(self.g.poses[k], f"graph pose of keyframe {k}")

    def current(self, k: int) -> np.ndarray:
        if self.g is not None:
            return self.g.poses[k]
        return self.T_odom(k)

    def gate(self, k: int) -> float:
        """Floor (covariance gate) or radius (path-fraction gate) of keyframe ``k``'s gate (m)."""
        p = self.params
        if self.gate_covariance(k) is not None:
            return p.recognition.gate_m
        frac = p.online_gate_drift_fraction if not self.use_map else (
            p.gate_drift_fraction if p.gate_drift_fraction is not None else 0.0)
        return p.recognition.gate_m + frac * (self.path[k] - self.last_anchor_path)

    def gate_covariance(self, k: int):
        """The graph's covariance of keyframe ``k``'s prediction for the Mahalanobis gate (with the map
        and ``gate_drift_fraction`` None), else None."""
        if not self.use_map or self.params.gate_drift_fraction is not None or self.g is None:
            return None
        if self.cov_k != k:
            raise AssertionError(f"internal error: prediction covariance of keyframe {self.cov_k}, not {k}")
        return self.cov

    def pose_for_conflict(self, k: int, rec: Recognition) -> np.ndarray:
        return self.g.poses[k] if self.g is not None else rec.T_world_keyframe_icp

    def add_factor(self, k: int, rec: Recognition, kb, online, timings: dict) -> bool:
        """Intersection factor (map) or loop factor (online base) for a verified recognition; re-optimise."""
        p = self.params
        if self.g is None:                    # unanchored: the first verification places the run
            self.T_world_odom = compose(rec.T_world_keyframe_icp, invert(self.T_odom(k)))
            self._build(k)
        if online is None:
            cov = intersection_covariance(max(rec.completeness, 1e-3), p.intersection_sigma_m,
                                          scaling=p.completeness_scaling)      # [Liang2024 Eq. 32]
            C = kb.invariant_points[rec.intersection_id]
            z = rec.z_keyframe
            if p.intersection_observation == "icp" and rec.T_world_keyframe_icp is not None:
                # where the verification's ICP (the keyframes' clouds on the base's dense cloud) puts the
                # base's invariant point in the keyframe: the detected point's own error (its floor height
                # from a few rings, its xy from a 0.25 m grid) stays out of the factor
                z = np.linalg.solve(rec.T_world_keyframe_icp, np.r_[C, 1.0])[:3]
            self.g.add_intersection(k, z, C, np.linalg.inv(cov), intersection_id=rec.intersection_id)
        else:
            e = online.entry_of[rec.intersection_id]
            Z = relative(online.T[e], rec.T_world_keyframe_icp)
            s_phi, s_t = math.radians(p.loop_sigma_deg), p.intersection_sigma_m
            self.g.add_relative(online.kf[e], k, Z, np.diag([s_phi**-2] * 3 + [s_t**-2] * 3))
        res = self._optimise(k, online is None, timings)
        self.checked += [k] if online is None else [k, online.kf[e]]
        self.last_anchor_path = self.path[k]
        self.done.append(((self.g.poses[k] @ np.r_[rec.z_keyframe, 1.0])[:3], rec.intersection_id))
        return res.status != "failed"

    def _optimise(self, k: int, covariance: bool, timings: dict):
        """Re-optimise from the previous optimum; then (``covariance``) keyframe ``k``'s marginal
        covariance for the next gate."""
        t0 = time.perf_counter()
        res = self.g.optimize(warm_start=True)
        if covariance and k == self.g.n_keyframes - 1:
            try:
                self.cov, self.cov_k = self.g.marginal_covariance(k), k
            except DegenerateGeometryError as exc:   # adding a factor only shrinks it: keep the carried one
                log.warning("keyframe %d: no marginal covariance after the optimisation (%s); the gate keeps the "
                            "prediction's covariance", k, exc)
        timings["optimisation"] = timings.get("optimisation", 0.0) + time.perf_counter() - t0
        self.n_opt += 1
        return res

    def map_step(self, k: int, hist, timings: dict) -> None:
        """A map registration of keyframe ``k`` when it is due (module docstring), its factor if accepted."""
        from minegeo.semantic.mapfactor import register_to_map
        from minegeo.semantic.recognition import PredictionGate

        p = self.params
        if (self.g is None or self.path[k] - self.last_anchor_path < p.map_factor_after_m
                or self.path[k] - self.last_map_path < p.map_factor_spacing_m
                or _held_reason(self.odo, int(self.odo.keyframes[k]))):
            return
        self.last_map_path = self.path[k]
        t0 = time.perf_counter()
        pts = np.concatenate([self.odo.keyframe_clouds[k]] + [c @ T[:3, :3].T + T[:3, 3] for c, T in hist])
        T_pred = self.prediction(k)
        rp = p.recognition
        cov = self.gate_covariance(k)
        gate = PredictionGate(T_pred, cov, rp.gate_m if cov is not None else self.gate(k), rp.gate_probability)
        reg = register_to_map(k, pts, T_pred, self.prior, rp, gate, p.map_factor_sigma_m, p.map_factor_min_ratio)
        timings["map_registration"] = timings.get("map_registration", 0.0) + time.perf_counter() - t0
        self.map_regs.append(reg)
        if reg.status == "factor":
            self.g.add_map_registration(k, reg.T_world_keyframe, reg.information)
            res = self._optimise(k, True, timings)
            if res.status == "failed":              # the factor stays in the graph; the estimate did not move
                reg.reason = f"the optimisation after it failed ({res.reason}); the estimate kept the previous optimum"

    def online_step(self, k: int, hist, online: _OnlineKB, state: RecognitionState) -> Recognition:
        """``use_map=False``: recognise re-visits of the online base, else maybe add a new entry."""
        rp = replace(self.params.recognition, icp_max_distance_m=self.params.online_icp_max_distance_m)
        conflict = None
        view, idx = online.view(self.path[k], self.params.revisit_min_path_m)
        online.entry_of = {i: e for i, e in enumerate(idx)}
        if len(view):
            rec = recognise_keyframe(self.odo.keyframe_clouds[k], hist, view, rp, T_world_kf_pred=self.prediction(k),
                                     gate_m=self.gate(k), state=state)
            if rec.status in ("verified", "candidate", "rejected", "ambiguous"):
                return rec
            if rec.status == "conflict":          # a look-alike of an entry, far from it: maybe a new entry
                conflict = rec
        t0 = time.perf_counter()
        status, reason, L, T_L_k, c_L = _detect([self.odo.keyframe_clouds[k]] + [h[0] for h in hist],
                                                [h[1] for h in hist], rp)
        rec = conflict or Recognition(status or "none", reason or "no re-visit of the online knowledge base",
                                      timings_s={"detect": time.perf_counter() - t0})
        if c_L is None or np.hypot(c_L[0], c_L[1]) > self.params.online_add_range_m:
            return rec
        T_wL = compose(self.g.poses[k], invert(T_L_k))
        C = T_wL[:3, :3] @ c_L + T_wL[:3, 3]
        if any(np.linalg.norm(C[:2] - q[:2]) < self.params.online_merge_m for q in online.C):
            return rec
        online.add(C, L @ T_wL[:3, :3].T + T_wL[:3, 3], k, self.path[k], self.g.poses[k])
        new = f"new online intersection {len(online.C) - 1} at ({C[0]:.1f}, {C[1]:.1f}) m"
        rec.reason = f"{rec.reason}; {new}" if conflict is not None else new
        return rec

    def result(self, use_map: bool, usable: bool, kb, online, timings: dict) -> TrackResult:
        odo = self.odo
        kf = np.stack([self.current(k) for k in range(odo.keyframes.size)])
        unchecked = self.unchecked_stretches()
        bad = self.inconsistent_factors() if self.g is not None else []
        if self.g is None:
            status, reason = "unanchored", "no start pose and no verified recognition: poses in the first frame's frame"
        elif not usable:
            status, reason = "no_intersections", f"the knowledge base holds no intersection ({kb.status}): odometry only"
        elif not self.n_opt:
            status, reason = "no_recognition", "no recognition was verified: odometry only"
        else:
            status, reason = self._checked_status(bad, unchecked)
        pts = np.array(online.C).reshape(-1, 3) if online is not None else np.zeros((0, 3))
        okf = np.array(online.kf if online is not None else [], np.int64)
        return TrackResult(TrackStatus(status), reason, odo.times_s, _frame_poses(odo, kf), odo.keyframes.copy(), kf,
                           np.stack(self.online_poses), self.recognitions, timings, use_map, odo, pts, okf,
                           self.n_opt, unchecked_stretches=unchecked, inconsistent_factors=bad,
                           map_registrations=self.map_regs)

    def unchecked_stretches(self) -> list:
        """Runs of keyframes farther than ``unchecked_path_m`` of path from every check."""
        return unchecked_stretches(self.path, self.checked, self.params.unchecked_path_m, self.odo.keyframes,
                                   self.odo.times_s)

    def inconsistent_factors(self) -> list:
        """Intersection factors whose ``eᵀΩe`` exceeds the χ²(3) quantile at the current estimate."""
        from scipy.stats import chi2

        limit = float(chi2.ppf(self.params.factor_test_probability, 3))
        q = self.g.whitened_squares()["intersection"]
        facts = self.g.intersection_factors()
        out = []
        for (kf, z, C, _info, iid), x in zip(facts, q, strict=True):
            if x > limit:
                T = self.g.poses[kf]
                e = float(np.linalg.norm(C - T[:3, :3] @ z - T[:3, 3]))
                out.append({"keyframe": int(kf), "frame": int(self.odo.keyframes[kf]), "intersection_id": int(iid),
                            "chi2": float(x), "chi2_limit": limit, "residual_m": e})
        return out

    def _checked_status(self, bad: list, st: list) -> tuple[str, str]:
        """``ok``, ``partial`` or ``inconsistent`` of a run with factors, from its inconsistent factors
        ``bad`` and unchecked stretches ``st`` [see TrackParams]."""
        if bad:
            worst = max(bad, key=lambda b: b["chi2"])
            return "inconsistent", (
                f"{len(bad)} intersection factor(s) disagree with the odometry between them beyond the χ² test "
                f"(p {self.params.factor_test_probability:g}): worst keyframe {worst['keyframe']} "
                f"(intersection {worst['intersection_id']}, residual {worst['residual_m']:.2f} m): a wrong "
                "recognition or a runaway odometry; positions not trusted")
        if st:
            n = sum(s["last_keyframe"] - s["first_keyframe"] + 1 for s in st)
            long = max(st, key=lambda s: s["path_m"])
            return "partial", (
                f"{n} of {self.odo.keyframes.size} keyframes in {len(st)} stretch(es) lie more than "
                f"{self.params.unchecked_path_m:g} m of path from every verified intersection"
                f"{' or the start pose' if self.params.T_world_start is not None else ''}: odometry only there, "
                f"unchecked (longest {long['path_m']:.0f} m, {long['first_time_s']:.1f}-{long['last_time_s']:.1f} s)")
        return "ok", ""
