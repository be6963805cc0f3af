"""Trajectory evaluation: absolute (ATE) and relative (RPE) pose error, as evo computes them.

Conventions follow ``slam_contract.md`` and evo (``evo_ape``, ``evo_rpe``), so that the numbers agree
with evo on the same files:

* **Association** by timestamp (``match="time"``): every pose of the shorter trajectory is matched
  with the nearest time of the other within ``max_diff_s`` (default 10 ms; evo's
  ``matching_time_indices``); or by index (``match="index"``, poses without times such as KITTI's):
  pose k with pose k, and both trajectories must hold the same number of poses (evo's
  ``APE.process_data`` refuses different lengths: "trajectories must have same number of poses").
* **Inputs** pass the trajectory readers' check (:func:`minegeo.io.trajectory.time_problem`,
  :func:`~minegeo.io.trajectory.rotation_problem`): finite, strictly increasing times and proper
  rotations (evo's ``PoseTrajectory3D.check``: ascending unique stamps, SO(3) rotations); ``scale``
  requires ``align`` (the scale is part of the alignment); the RPE pair distance is a whole number of
  frames (evo: "delta must be integer for delta unit frames") or finite metres, and must give at least
  one pair (evo: "produced an empty index list").
* **ATE**: the estimate is aligned to the ground truth by Umeyama's least-squares rigid (SE(3)) or
  similarity (Sim(3), ``scale=True``) fit of the matched positions (:func:`minegeo.registration.umeyama`); the
  error of pose k is ``e_k = t_gt,k − (s R t_est,k + t)`` (m); statistics of ``|e_k|`` (evo's APE,
  translation part) and per axis, plus the rotation error angle of ``R_gt,kᵀ R R_est,k``.
* **RPE** over consecutive pose pairs ``(i, j)`` ``delta`` frames apart, or ``delta`` metres of
  ground-truth path apart (evo's ``filter_pairs_by_path`` with ``--pairs_from_reference``: the pairs
  do not depend on the estimate's noise):
  ``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`` [Sturm2012 Eq. 1]; translation error ``|t(E)|`` (m) and
  rotation error ``angle(R(E))`` (deg); also as % of the pair's path length and deg/m.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import InputError
from minegeo.io.trajectory import rotation_problem, time_problem
from minegeo.io.types import Trajectory
from minegeo.registration.estimation import umeyama

__all__ = ["ErrorStats", "TrajectoryEvaluation", "associate", "evaluate_trajectory", "error_stats", "MAX_DELTA_FRAMES"]

#: largest RPE pair distance in frames (a count above this is a typo; as ``minegeo.cli._argtypes.MAX_COUNT``)
MAX_DELTA_FRAMES = 10**9


@dataclass(frozen=True)
class ErrorStats:
    """Summary of an error series, as evo prints it (``sse`` = sum of squares)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    n: int


def error_stats(e: np.ndarray) -> ErrorStats:
    """:class:`ErrorStats` of a 1-D error series (evo's ``get_all_statistics``)."""
    e = np.asarray(e, dtype=np.float64)
    if e.size == 0:
        nan = float("nan")
        return ErrorStats(nan, nan, nan, nan, nan, nan, 0.0, 0)
    sse = float(np.dot(e, e))
    return ErrorStats(float(np.sqrt(np.mean(np.power(e, 2)))), float(np.mean(e)), float(np.median(e)),
                      float(np.std(e)), float(np.min(e)), float(np.max(e)), sse, int(e.size))


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """ATE and RPE of an estimated trajectory against a reference.

    Attributes
    ----------
    n_matched : int
        Poses associated by time.
    T_gt_est : (4, 4) float64
        The alignment applied to the estimate (``s R`` in the rotation block when ``scale``).
    scale : float
        Sim(3) scale (1 for SE(3)).
    ate : ErrorStats
        Position error after alignment (m).
    ate_axis : dict
        Per-axis :class:`ErrorStats` of the signed errors ``x``, ``y``, ``z`` (m).
    ate_rotation_deg : ErrorStats
        Rotation error angle after alignment (deg).
    ate_percent_of_path : float
        ATE RMSE as % of the ground-truth path length.
    rpe_translation, rpe_rotation_deg : ErrorStats
        RPE over the pose pairs (m, deg).
    rpe_translation_percent, rpe_rotation_deg_per_m : float
        Sums of the pair errors over the summed pair path lengths (%, deg/m).
    times_s : (n,) float64
        Matched reference times. ``errors_m``: per-pose ATE vectors (n, 3); ``gt_index``: the
        matched ground-truth pose indices.
    """

    n_matched: int
    T_gt_est: np.ndarray
    scale: float
    ate: ErrorStats
    ate_axis: dict
    ate_rotation_deg: ErrorStats
    ate_percent_of_path: float
    path_length_m: float
    rpe_translation: ErrorStats
    rpe_rotation_deg: ErrorStats
    rpe_translation_percent: float
    rpe_rotation_deg_per_m: float
    rpe_pairs: np.ndarray
    times_s: np.ndarray
    errors_m: np.ndarray
    gt_index: np.ndarray
    params: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)


def associate(t_ref: np.ndarray, t_est: np.ndarray, max_diff_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_ref, i_est)`` of the poses matched by nearest time within ``max_diff_s``.

    The shorter series is walked; for each of its times the nearest time of the other (ties to
    the earlier one) within ``max_diff_s`` is taken (evo's ``associate_trajectories``).
    """
    swap = t_est.size > t_ref.size
    short, long_ = (t_ref, t_est) if swap else (t_est, t_ref)
    if np.any(np.diff(long_) < 0):
        raise InputError("trajectory times must be increasing")
    i_s, i_l = [], []
    for k, t in enumerate(short):
        if t < long_[0] - max_diff_s or t > long_[-1] + max_diff_s:
            continue
        j = min(int(np.searchsorted(long_, t, side="right")), long_.size - 1)
        ub = long_[j] - t
        lb = t - long_[j - 1] if j > 0 else float("inf")
        if ub <= max_diff_s and ub < lb:
            best = j
        elif lb <= max_diff_s and lb <= ub:
            best = j - 1
        else:
            continue
        i_s.append(k)
        i_l.append(best)
    a, b = np.asarray(i_s, dtype=np.int64), np.asarray(i_l, dtype=np.int64)
    return (a, b) if swap else (b, a)


def _pairs(P_ref: np.ndarray, delta: float, unit: str) -> np.ndarray:
    if unit == "frames":
        ids = np.arange(0, P_ref.shape[0], int(delta))
    else:  # metres of reference path, consecutive pairs (evo filter_pairs_by_path)
        ids, path = [0], 0.0
        for i in range(1, P_ref.shape[0]):
            path += float(np.linalg.norm(P_ref[i, :3, 3] - P_ref[i - 1, :3, 3]))
            if path >= delta:
                ids.append(i)
                path = 0.0
        ids = np.asarray(ids)
    return np.stack([ids[:-1], ids[1:]], axis=1) if ids.size > 1 else np.zeros((0, 2), dtype=np.int64)


def _angle_deg(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def _rigid_inv(T):
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def _check_params(scale, max_diff_s, rpe_delta, rpe_unit, align, match) -> None:
    """Refuse parameters that are out of range or contradict each other (before any work)."""
    if rpe_unit not in ("frames", "m"):
        raise InputError(f"rpe_unit must be 'frames' or 'm', got {rpe_unit!r}")
    if match not in ("time", "index"):
        raise InputError(f"match must be 'time' or 'index', got {match!r}")
    try:
        d = float(rpe_delta)
    except (TypeError, ValueError):
        raise InputError(f"rpe_delta must be a number, got {rpe_delta!r}") from None
    if rpe_unit == "frames" and not (np.isfinite(d) and d.is_integer() and 1 <= d <= MAX_DELTA_FRAMES):
        raise InputError(f"rpe_delta {rpe_delta!r}: with rpe_unit 'frames' the pair distance is a whole number of "
                         f"frames from 1 to {MAX_DELTA_FRAMES}")
    if rpe_unit == "m" and not (np.isfinite(d) and d > 0):
        raise InputError(f"rpe_delta {rpe_delta!r}: with rpe_unit 'm' the pair distance is a positive finite number "
                         "of metres")
    if match == "time" and not (isinstance(max_diff_s, (int, float, np.floating)) and np.isfinite(max_diff_s)
                                and max_diff_s > 0):
        raise InputError(f"max_diff_s must be a positive finite number of seconds, got {max_diff_s!r}")
    if scale and not align:
        raise InputError("scale=True corrects the scale in the alignment, and align=False turns the alignment off: "
                         "they contradict")


def _check_trajectory(traj: Trajectory, name: str, timed: bool) -> None:
    if not isinstance(traj, Trajectory):
        raise InputError(f"{name} must be a Trajectory, got {type(traj).__name__}")
    problem = (time_problem(traj.times_s) if timed else None) or rotation_problem(traj.poses[:, :3, :3])
    if problem is not None:
        raise InputError(f"{name} pose {problem[0]}: {problem[1]}")


def evaluate_trajectory(est: Trajectory, gt: Trajectory, *, scale: bool = False, max_diff_s: float = 0.01,
                        rpe_delta: float = 1.0, rpe_unit: str = "frames", align: bool = True,
                        match: str = "time") -> TrajectoryEvaluation:
    """ATE and RPE of ``est`` against ``gt`` (see the module docstring for every formula).

    Parameters
    ----------
    est, gt : Trajectory
        Timestamped poses ``T_world_sensor`` (each in its own world frame when ``align``).
    scale : bool
        Sim(3) alignment (monocular-style scale drift) instead of SE(3).
    max_diff_s : float
        Largest time difference of an association (s), positive and finite (``match="time"``).
    rpe_delta : float
        Pair distance: a whole number of frames from 1 (``rpe_unit="frames"``) or positive finite
        metres of reference path (``"m"``).
    align : bool
        Umeyama alignment before ATE (False: the frames are already the same; ``scale`` needs it).
    match : {"time", "index"}
        Associate poses by nearest time, or pose k with pose k (same number of poses required; the
        times are then not used, as for KITTI files).

    Raises
    ------
    InputError
        A parameter out of range or contradicting another (``scale`` without ``align``), a trajectory
        whose times are not finite and strictly increasing or whose rotations are not proper (the
        pose is named), different lengths with ``match="index"``, fewer than 3 poses associated, or
        an RPE pair distance that gives no pair. (A straight ground-truth path is evaluated, with a
        warning: the alignment's rotation about the line is then undetermined.)
    """
    _check_params(scale, max_diff_s, rpe_delta, rpe_unit, align, match)
    if rpe_unit == "frames":
        rpe_delta = int(rpe_delta)
    _check_trajectory(est, "estimate", match == "time")
    _check_trajectory(gt, "ground truth", match == "time")
    if match == "index":
        if len(est) != len(gt):
            raise InputError(f"the estimate holds {len(est)} poses and the ground truth {len(gt)}: matched by index "
                             "(no times), both must hold the same number of poses")
        i_gt = i_est = np.arange(len(gt), dtype=np.int64)
    else:
        i_gt, i_est = associate(gt.times_s, est.times_s, max_diff_s)
    if i_gt.size < 3:
        raise InputError(f"only {i_gt.size} pose(s) of the estimate match the ground truth"
                         + (f" within {max_diff_s} s: check the time stamps (same clock and unit?)"
                            if match == "time" else ": at least 3 are needed"))
    Q = gt.poses[i_gt].copy()
    P = est.poses[i_est].copy()
    Q[:, :3, 3] += gt.origin  # positions in the trajectory's frame, its recorded local origin added
    P[:, :3, 3] += est.origin
    T = np.eye(4)
    s = 1.0
    warnings = []
    if align:
        ev_pos = np.linalg.eigvalsh(np.cov(Q[:, :3, 3].T))
        if ev_pos[1] <= 1e-10 * max(ev_pos[2], 1e-300):
            warnings.append("the ground-truth path is a straight line: the alignment's rotation about it is "
                            "undetermined (position errors are unaffected; the rotation error is not meaningful)")
        T, s = umeyama(P[:, :3, 3], Q[:, :3, 3], with_scale=scale, allow_degenerate=True)
        T, s = np.asarray(T, dtype=np.float64), float(s)
    Pa = np.einsum("ij,njk->nik", T, P)
    err = Q[:, :3, 3] - Pa[:, :3, 3]
    Ra = Pa[:, :3, :3] / s
    rot = _angle_deg(np.einsum("nji,njk->nik", Q[:, :3, :3], Ra))
    seg = np.linalg.norm(np.diff(Q[:, :3, 3], axis=0), axis=1)
    path = float(seg.sum())
    pairs = _pairs(Q, rpe_delta, rpe_unit)
    if pairs.shape[0] == 0:
        unit = "frames" if rpe_unit == "frames" else "m of ground-truth path"
        raise InputError(f"no pose pair is {rpe_delta:g} {unit} apart ({i_gt.size} matched poses, path "
                         f"{path:.3f} m): choose a smaller RPE pair distance")
    Pr = P.copy()
    Pr[:, :3, 3] *= s  # RPE on the scale-corrected estimate (evo_rpe -s); rigid alignment does not change RPE
    Qrel = np.einsum("nij,njk->nik", _rigid_inv(Q[pairs[:, 0]]), Q[pairs[:, 1]])
    Prel = np.einsum("nij,njk->nik", _rigid_inv(Pr[pairs[:, 0]]), Pr[pairs[:, 1]])
    E = np.einsum("nij,njk->nik", _rigid_inv(Qrel), Prel)
    et, er = np.linalg.norm(E[:, :3, 3], axis=1), _angle_deg(E[:, :3, :3])
    cum = np.r_[0.0, np.cumsum(seg)]
    plen = cum[pairs[:, 1]] - cum[pairs[:, 0]]
    tot = float(plen.sum())
    return TrajectoryEvaluation(
        n_matched=int(i_gt.size), T_gt_est=T, scale=s, ate=error_stats(np.linalg.norm(err, axis=1)),
        ate_axis={ax: error_stats(err[:, k]) for k, ax in enumerate("xyz")}, ate_rotation_deg=error_stats(rot),
        ate_percent_of_path=100.0 * error_stats(np.linalg.norm(err, axis=1)).rmse / path if path > 0 else float("nan"),
        path_length_m=path, rpe_translation=error_stats(et), rpe_rotation_deg=error_stats(er),
        rpe_translation_percent=100.0 * float(et.sum()) / tot if tot > 0 else float("nan"),
        rpe_rotation_deg_per_m=float(er.sum()) / tot if tot > 0 else float("nan"),
        rpe_pairs=pairs, times_s=gt.times_s[i_gt], errors_m=err, gt_index=i_gt, warnings=warnings,
        params={"scale": scale, "max_diff_s": max_diff_s if match == "time" else None, "rpe_delta": rpe_delta,
                "rpe_unit": rpe_unit, "align": align, "match": match},
    )
