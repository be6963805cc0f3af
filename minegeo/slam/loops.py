"""Loop closure by rules and GICP (Ren et al. 2019, Sec. 3.4.1).

For the newest keyframe ``k``, a candidate is an older keyframe ``j`` (index smaller) such that
the trajectory distance between them is above ``min_path_gap_m`` (it is a return, not the
recent past) and their Euclidean distance is below ``max_distance_m`` (they may see the same
place). The ``max_candidates`` nearest candidates are registered by GICP (``k`` into ``j``, from the
odometry's relative pose); the highest-scoring registration wins ("the highest GICP registration
score is selected as the final loop frame"). A loop is accepted only when its overlap reaches
``min_fitness``, its inlier RMSE stays below ``max_rmse_m`` and its correction of the odometry's
relative pose stays within its limits (a far jump is a wrong place that looked alike, rejected
rather than trusted). Every candidate tried is recorded with its scores and the reason it was
rejected: the loop list is an output.

Two additions to the paper's rules, for long loops (hundreds of metres, measured on the synthetic
2 km ablation, ``benchmarks/bench_slam.py``):

* the correction limit grows with the drift the odometry may have collected since the older
  keyframe: ``max(max_correction_m, max_correction_per_path · Δs)``, ``Δs`` the trajectory distance
  between the two keyframes (the angle limit stays ``max_correction_deg``);
* two keyframes a few metres apart along the same roadway overlap well but never exactly (the
  sensor sees the walls from another place), so a correct return can have an inlier RMSE of
  0.3-0.45 m with 0.3 m voxels. A registration with an RMSE up to ``confirmed_rmse_m`` is accepted
  when another candidate's registration of the same keyframe puts it at the same world pose
  (within ``consistency_m`` / ``consistency_deg``): a look-alike place along a repetitive drift is
  a single registration that no neighbour confirms.

The keyframe poses the candidates are searched and judged at are re-optimised (the whole keyframe
graph, :func:`minegeo.slam.pipeline.run_backend`) after an accepted loop whose correction of the
current poses exceeds ``reoptimise_m`` or ``reoptimise_deg``: the first loop of a return carries
the whole drift and moves every later keyframe with it, and the loops that follow along the same
return then correct the current poses by centimetres, far below the registration's reach, so
re-optimising after each of them (hundreds along a long revisit) moves the later keyframes' guesses
by no more than that.
The loops accepted in between are all in the next optimisation and in the final one. The default
limits, 0.1 m and 2°, lie above what loop registrations along a 3.2 m drift disagree with the just
optimised poses by (1-5 cm and 0.2-2.3° on the 2040 m stop-and-go stream of
``benchmarks/bench_control_stream.py``, where the first loop of a return corrects 0.4 m) and far
below the registration's reach (a 2° error moves a wall 10 m away by 0.35 m). On that stream the
keyframe graph is optimised 65 times instead of after each of the 1163 accepted loops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from minegeo._params import bounded, validate
from minegeo.geometry.se3 import compose, project, relative
from minegeo.slam.odometry import OdometryParams, PreparedFrame, register_frames

__all__ = ["LoopParams", "LoopCandidate", "find_loop", "loop_correction"]


@dataclass(frozen=True)
class LoopParams:
    """Rules and acceptance thresholds of loop closure (m, deg).

    ``max_correction_per_path`` (m of correction per m of trajectory between the keyframes) widens
    the translation limit for long loops; ``confirmed_rmse_m`` is the inlier RMSE a registration may
    reach when another candidate confirms it within ``consistency_m`` / ``consistency_deg``;
    ``reoptimise_m`` / ``reoptimise_deg``: an accepted loop whose measured relative pose differs
    from the current poses' by more than either re-optimises the keyframe graph before the next
    keyframe's candidates are searched (0 and 0: after every accepted loop) (see the module
    docstring).
    """

    min_path_gap_m: float = bounded(30.0, gt=0.0)
    max_distance_m: float = bounded(8.0, gt=0.0)
    max_candidates: int = bounded(3, ge=1, integer=True)
    min_fitness: float = bounded(0.5, ge=0.0, le=1.0)
    max_rmse_m: float = bounded(0.3, gt=0.0)
    max_correction_m: float = bounded(5.0, gt=0.0)
    max_correction_deg: float = bounded(45.0, gt=0.0)
    max_correction_per_path: float = bounded(0.02, gt=0.0)
    confirmed_rmse_m: float = bounded(0.45, gt=0.0)
    consistency_m: float = bounded(0.3, gt=0.0)
    consistency_deg: float = bounded(1.0, gt=0.0)
    reoptimise_m: float = bounded(0.1, ge=0.0)
    reoptimise_deg: float = bounded(2.0, ge=0.0)

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class LoopCandidate:
    """One loop candidate tried: keyframes ``i`` (older) and ``j`` (newer), scores, verdict."""

    i: int
    j: int
    distance_m: float
    fitness: float
    rmse_m: float
    accepted: bool
    reason: str
    T_i_j: np.ndarray
    information: np.ndarray


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0))))


def candidates(k: int, positions: np.ndarray, path_m: np.ndarray, params: LoopParams) -> np.ndarray:
    """Keyframe indices ``j < k`` meeting the three rules, nearest first (at most ``max_candidates``)."""
    j = np.arange(k)
    d = np.linalg.norm(positions[:k] - positions[k], axis=1)
    ok = (path_m[k] - path_m[:k] > params.min_path_gap_m) & (d < params.max_distance_m)
    j, d = j[ok], d[ok]
    return j[np.argsort(d, kind="stable")][: params.max_candidates]


def find_loop(k: int, poses: np.ndarray, path_m: np.ndarray, frames: list[PreparedFrame],
              params: LoopParams, odo: OdometryParams) -> list[LoopCandidate]:
    """Try the loop candidates of keyframe ``k``; at most one of the returned candidates is accepted.

    Parameters
    ----------
    k : int
        The newest keyframe.
    poses : (K, 4, 4)
        Keyframe poses ``T_world_keyframe`` (odometry or optimised).
    path_m : (K,)
        Trajectory distance of each keyframe from the start (m).
    frames : list of PreparedFrame
        The prepared keyframe clouds (sensor frame).
    """
    tried, world = [], []
    for j in candidates(k, poses[:, :3, 3], path_m, params):
        guess = relative(poses[j], poses[k])  # T_j_k from the odometry (re-projected onto SE(3))
        reg = register_frames(frames[k], frames[j], guess, odo, trusted_init=True)
        T_jk = project(reg.T)
        corr = relative(guess, T_jk)
        limit_m = max(params.max_correction_m, params.max_correction_per_path * float(path_m[k] - path_m[j]))
        reason = reg.reason
        if not reason and reg.fitness < params.min_fitness:
            reason = f"overlap {reg.fitness:.2f} below {params.min_fitness:.2f}"
        if not reason and reg.rmse_m > params.confirmed_rmse_m:
            reason = f"inlier RMSE {reg.rmse_m:.3f} m above {params.confirmed_rmse_m:.3f} m"
        if not reason and (np.linalg.norm(corr[:3, 3]) > limit_m
                           or _angle_deg(corr[:3, :3]) > params.max_correction_deg):
            reason = (f"corrects the odometry by {np.linalg.norm(corr[:3, 3]):.2f} m / {_angle_deg(corr[:3, :3]):.1f}"
                      f" deg: beyond the limits ({limit_m:.1f} m / {params.max_correction_deg:.0f} deg), "
                      "a look-alike place")
        tried.append(LoopCandidate(int(j), int(k), float(np.linalg.norm(poses[j, :3, 3] - poses[k, :3, 3])),
                                   reg.fitness, reg.rmse_m, False, reason, T_jk, reg.information))
        world.append(compose(poses[j], T_jk))  # where this registration puts keyframe k
    tried = _confirm(tried, world, params)
    good = [a for a, c in enumerate(tried) if not c.reason]
    if not good:
        return tried
    b = max(good, key=lambda a: (tried[a].fitness, -tried[a].rmse_m))  # the first of equal scores
    why = f"lower score than the loop to keyframe {tried[b].i}"
    return [replace(c, accepted=True) if a == b else replace(c, reason=why) if a in good else c
            for a, c in enumerate(tried)]


def loop_correction(c: LoopCandidate, poses: np.ndarray) -> tuple[float, float]:
    """How far the loop ``c`` corrects the keyframe poses ``poses``: the translation (m) and the
    rotation angle (deg) of ``(T_i⁻¹ T_j)⁻¹ Z_ij``, ``T`` the poses (``T_world_keyframe``) and ``Z_ij``
    the loop's measured ``T_i_j``."""
    corr = relative(relative(poses[c.i], poses[c.j]), c.T_i_j)
    return float(np.linalg.norm(corr[:3, 3])), _angle_deg(corr[:3, :3])


def _confirm(tried: list[LoopCandidate], world: list[np.ndarray], params: LoopParams) -> list[LoopCandidate]:
    """The candidates, those with an inlier RMSE above ``max_rmse_m`` that no other passing candidate
    confirms (the same world pose of the keyframe within ``consistency_m`` / ``consistency_deg``) rejected."""
    ok = [not c.reason for c in tried]
    out = list(tried)
    for a, c in enumerate(tried):
        if not ok[a] or c.rmse_m <= params.max_rmse_m:
            continue
        agree = [b for b in range(len(tried)) if b != a and ok[b]
                 and np.linalg.norm(world[a][:3, 3] - world[b][:3, 3]) <= params.consistency_m
                 and _angle_deg(world[a][:3, :3].T @ world[b][:3, :3]) <= params.consistency_deg]
        if not agree:
            out[a] = replace(c, reason=(f"inlier RMSE {c.rmse_m:.3f} m above {params.max_rmse_m:.3f} m and no other "
                                        "candidate confirms the pose"))
    return out
