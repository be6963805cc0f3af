"""LiDAR odometry by GICP between consecutive frames and consecutive keyframes (Ren et al. 2019, Sec. 3.3).

* Each frame is prepared once (voxel downsampling, GICP covariances [Ren2019 Eqs. 2-3], a search
  tree) and serves as the source of its own registration, then as the target of the next one.
* Frame-to-frame GICP gives ``ΔT_{t-1,t}`` (current frame into the previous one) from a
  constant-velocity initial guess (the previous motion; when the time step differs from the
  previous one by more than 25 %, as in keyframe logs, also the previous motion scaled to the time
  step, and the better overlap wins); the pose is chained,
  ``T_t = T_{t-1} ΔT_{t-1,t}`` [Ren2019 Eq. 7].
* A frame becomes a keyframe when, relative to the last keyframe,
  ``ΔT = T_{k-1}⁻¹ T_k = [[ΔR, Δs], [0, 1]]`` [Ren2019 Eq. 8] has ``|Δs|`` above a distance,
  ``arccos((tr ΔR − 1)/2)`` above an angle, or the time since the last keyframe above an interval.
  Its pose is then refined by GICP against the last keyframe from the chained relative pose, and
  the refined relative pose is the keyframe edge of the pose graph.
* ``frame_target="submap"`` (frame to local map, not in the paper): each frame registers to the
  local map of the last ``local_map_keyframes`` keyframes (built as the keyframe refinement's sub-map), from
  the previous pose moved by the constant velocity; a keyframe's edge is that registration and the
  sub-map is rebuilt at each new keyframe. A frame that fails against the sub-map is registered to
  the previous frame instead (flagged in ``frame_weak``), and a keyframe made from such a frame starts
  a fresh sub-map; a keyframe placed by the guess (no registration) never enters the sub-map, so the
  frames after a short gap register to the sub-map from before it, and a long gap cannot keep the run
  lost. With a VLP-16's sparse rings, frame-to-frame GICP
  under-reads tilt changes (the floor rings move with the sensor); see ``docs/slam.md``.
* A frame that fails to register (too few points, low overlap) is flagged with the reason and
  placed by the constant-velocity guess; the run goes on. A registration with a weakly observed
  direction (e.g. along a straight smooth drift), or one still creeping along it when the
  iterations run out, is kept and flagged as low observability: its information matrix carries the
  weakness into the pose graph.
* Frames whose points carry times (``(time_s, points, offsets_s)``) are deskewed to their frame
  time before registration (:mod:`minegeo.slam.deskew`, ``q = exp(τ ξ) p``) by the body twist of the
  last registered motion, then once more by the twist of their own registered motion
  (``deskew_iterations``); the pose of a frame is the sensor pose at its frame time.
* No silent runaway: a registration whose motion since the last registered frame exceeds
  ``max_speed_m_s`` or ``max_angular_rate_deg_s``, whose velocity changes against the previous
  motion by more than ``max_acceleration_m_s2`` (with ``motion_noise_m`` of registration noise), or whose normalised constraint ratio is below
  ``min_constraint_ratio`` (degenerate geometry) is rejected: the frame is held by the
  constant-velocity prior, flagged (:meth:`OdometryResult.held_stretches`), and the next frame
  registers to the last registered one. With an IMU, a registration whose rotation since the last
  registered frame disagrees with the gyro's beyond ``θ_tol + n_σ √3 σ_θ``
  (:meth:`minegeo.slam.inertial.GyroAid.disagreement`) is rejected too, and a rejected frame is held
  by the gyro's rotation and the constant-velocity translation.
* The sensor translation is checked on its own (:mod:`minegeo.slam.observability`): when the
  rotation-marginalised translation information has ``λ_min / λ_max`` below
  ``translation_observability_ratio`` and the surface patches of both frames (ring lines left out)
  have theirs below ``surface_observability_ratio`` (a straight featureless drift, where GICP
  matches laser ring to laser ring and would report a stop), the motion along that axis is taken
  from the registration's initial guess (the constant-velocity prior) and the frame is flagged with
  the axis.

Poses stay on SE(3): every product, inverse and relative pose of the chain is
:func:`minegeo.geometry.se3.compose` / :func:`~minegeo.geometry.se3.relative` (re-projected onto
SE(3)), so thousands of chained frames keep orthonormal rotations to rounding (about 1e-15), and
a registration's initial guess is passed as the package's own transform (``trusted_init``: a
non-rigid one is an :class:`~minegeo.errors.InternalError`, a bug, never "your input").

Edge information: GICP's Gauss–Newton matrix ``H`` is for a left perturbation in the target frame,
parameters (ω, t); the pose graph perturbs on the right, so GICP's information is
``Ω_G = Ad(Z)ᵀ H Ad(Z) / σ²`` with ``σ`` GICP's a-posteriori scale (floored at ``sigma_floor_m``).
It treats every point as an independent measurement and is over-confident (on synthetic streams the
keyframe edges' normalised squared errors average several hundred instead of 6). ``OdometryResult``
keeps ``Ω_G``; with ``edge_covariance_floor`` the back end's pose graph
(:func:`minegeo.slam.pipeline.keyframe_graph`) gives each edge ``(Ω_G⁻¹ + F)⁻¹`` with the covariance
floor ``F`` of :func:`edge_covariance_floor`, fitted against the simulator's truth.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numba
import numpy as np

from minegeo.errors import InputError
from minegeo.geometry import voxel_downsample
from minegeo.geometry.se3 import compose, project, relative
from minegeo.io.limits import MAX_ABS_TIME
from minegeo.kernels.lie import se3_adjoint, se3_exp, se3_log
from minegeo.registration import build_target_index, register_gicp
from minegeo.registration.gicp import gicp_covariances_on_tree
from minegeo.slam.deskew import deskew_points, twist_from_motion
from minegeo.slam.frame_covariances import covariances_with_history
from minegeo.slam.observability import keep_prior_along, translation_observability
from minegeo.slam.odometry_model import (  # the parameters, records and result, re-exported
    EDGE_FLOOR_FIELDS,
    KEYFRAME_NOISE_FIELDS,
    OdometryParams,
    OdometryResult,
    PreparedFrame,
    Registration,
    edge_covariance_floor,
    floored_information,
    keyframe_pose_noise,
    keyframe_rates_deg_s,
)

__all__ = ["OdometryParams", "PreparedFrame", "OdometryResult", "prepare_frame", "register_frames", "run_odometry",
           "edge_covariance_floor", "floored_information", "keyframe_rates_deg_s", "EDGE_FLOOR_FIELDS",
           "KEYFRAME_NOISE_FIELDS", "keyframe_pose_noise"]

log = logging.getLogger(__name__)


def prepare_frame(points: np.ndarray, time_s: float, params: OdometryParams) -> PreparedFrame:
    """Downsample a frame (voxel centroids) and estimate its GICP covariances once.

    The covariances are those of :func:`minegeo.registration.estimate_gicp_covariances`, from
    the kNN of the frame's own search tree (built once, for both)."""
    P = voxel_downsample(np.asarray(points, dtype=np.float64), params.voxel_size_m).points
    if P.shape[0] < params.min_points:
        return PreparedFrame(float(time_s), P, np.zeros((P.shape[0], 3, 3)), None)
    index = build_target_index(P)
    C, N, ev, status = gicp_covariances_on_tree(P, params.gicp(), index, with_surface=True)
    return PreparedFrame(float(time_s), P, C, index, None, (N, ev, status))


def _frame_item(item) -> tuple[float, np.ndarray, np.ndarray | None]:
    """``(time_s, points, per-point offsets or None)`` of one input frame: ``(time_s, points)`` or
    ``(time_s, points, offsets_s)`` (offsets in s after the frame time, one per point)."""
    if len(item) == 2:
        return item[0], item[1], None
    t, pts, tau = item
    if tau is not None:
        tau = np.asarray(tau, dtype=np.float64).reshape(-1)
        n = np.asarray(pts).shape[0]
        if tau.shape[0] != n:
            raise InputError(f"frame at t = {t!r} s: {tau.shape[0]} point times for {n} points")
    return t, pts, tau


def _prepared_frames(frames: Iterable, params: OdometryParams):
    """``(time_s, PreparedFrame or None, seconds spent preparing, (points, offsets) or None)`` of
    every frame in order.

    A frame to be deskewed (per-point offsets and ``params.deskew``) is yielded raw, ``(points,
    offsets)`` with no PreparedFrame: its deskewing needs the motion of the registration before it.
    Every other frame is prepared here. With two or more Numba threads the next frame is read and
    prepared in a worker thread (one Numba thread there) while the caller registers the current one:
    the kernels release the GIL, so the two run on two cores without a barrier per kernel. The
    frames are the same either way.
    """
    it = iter(frames)

    def job():
        item = next(it, None)
        if item is None:
            return None
        t, pts, tau = _frame_item(item)
        if tau is not None and params.deskew:
            return t, None, 0.0, (np.asarray(pts, dtype=np.float64), tau)
        t0 = time.perf_counter()
        cur = prepare_frame(pts, t, params)
        return t, cur, time.perf_counter() - t0, None

    if numba.get_num_threads() < 2:
        while (r := job()) is not None:
            yield r
        return

    def job_one_thread():
        numba.set_num_threads(1)  # this worker's own kernels; the caller's count is unchanged
        return job()

    with ThreadPoolExecutor(1, thread_name_prefix="minegeo-odometry") as ex:
        fut = ex.submit(job_one_thread)
        while (r := fut.result()) is not None:
            fut = ex.submit(job_one_thread)
            yield r


def register_frames(source: PreparedFrame, target: PreparedFrame, T_init: np.ndarray,
                    params: OdometryParams, *, trusted_init: bool = False) -> Registration:
    """GICP of ``source`` into ``target`` from ``T_init``; a verdict and the edge information.

    ``T_init`` (target ← source) is the caller's input, checked as such by :func:`register_gicp`
    (a proper rigid transform to 1e-6, else :class:`~minegeo.errors.InputError`), unless
    ``trusted_init``: the odometry and loop closure pass the transforms they composed themselves
    (:func:`minegeo.geometry.se3.compose`), checked as an internal invariant (off SE(3) by more than
    1e-9 is :class:`~minegeo.errors.InternalError`, a bug)."""
    if source.index is None or target.index is None:
        n = min(source.points.shape[0], target.points.shape[0])
        return Registration(T_init, False, f"too few points after downsampling ({n} < {params.min_points})",
                            0.0, float("nan"), np.zeros((6, 6)))
    res = register_gicp(source.points, target.points, T_init, params.gicp(), source_covariances=source.covariances,
                        target_covariances=target.covariances, target_index=target.index, check_target=False,
                        trusted_init=trusted_init)
    reason = ""
    if res.fitness < params.min_fitness:
        reason = f"overlap {res.fitness:.2f} below {params.min_fitness:.2f}"
    weak = res.degeneracy_reason if res.degenerate else ""
    T = res.T_target_source
    obs = translation_observability(res.information_6x6, params.translation_observability_ratio)
    if obs.weak and not reason and min(source.surface(), target.surface()) < params.surface_observability_ratio:
        # e.g. a straight featureless drift: keep the prior along the free axis
        T = keep_prior_along(T, T_init, obs.axis)
        weak = (weak + "; " if weak else "") + obs.describe()
    if not res.converged and not reason:  # still creeping (a weak direction): better than a guess, flagged
        weak = (weak + "; " if weak else "") + f"not converged in {res.iterations} iterations"
    sigma = max(float(res.sigma_m), params.sigma_floor_m)
    A = se3_adjoint(np.ascontiguousarray(T))
    info = A.T @ res.information_6x6 @ A / sigma**2
    return Registration(T, not reason, reason, float(res.fitness), float(res.inlier_rmse_m),
                        0.5 * (info + info.T), weak, bool(res.converged), float(res.degeneracy_ratio))


def _register_with_retries(cur: PreparedFrame, prev: PreparedFrame, guess: np.ndarray,
                           params: OdometryParams, still: np.ndarray | None = None) -> Registration:
    """GICP from the constant-velocity guess; when that fails (e.g. a sharp turn at a junction, where
    the previous motion is a poor guess), again from no motion, then coarse-to-fine with a gate
    ``coarse_gate_factor`` times wider from both guesses; the best overlap that passes wins. A
    result farther than the wide gate from the constant-velocity guess fails as implausible (the
    vehicle cannot change its speed by that much between two frames: a wrong minimum). ``still`` is
    the "no motion" pose of ``cur`` in ``prev``'s frame (identity for the previous frame; the previous
    frame's pose for a local map)."""
    still = np.eye(4) if still is None else still
    reg = _plausible(register_frames(cur, prev, guess, params, trusted_init=True), guess, params)
    if (reg.ok and (reg.converged or reg.fitness >= params.unconverged_retry_fitness)) \
            or cur.index is None or prev.index is None:
        return reg
    coarse = replace(params, max_correspondence_distance_m=params.max_correspondence_distance_m
                     * params.coarse_gate_factor)
    tries = [reg, register_frames(cur, prev, still, params, trusted_init=True)]
    for T0 in (guess, still):
        c = register_frames(cur, prev, T0, coarse, trusted_init=True)
        tries.append(register_frames(cur, prev, c.T, params, trusted_init=True))
    good = [r for r in (_plausible(r, guess, params) for r in tries) if r.ok]
    if not good or max(r.fitness for r in good) < params.unconverged_retry_fitness:
        # a sharp turn (a junction): the heading changed more than the gate can follow
        for yaw in params.turn_retry_yaw_deg:
            c = math.radians(yaw)
            Rz = np.eye(4)
            Rz[:2, :2] = [[math.cos(c), -math.sin(c)], [math.sin(c), math.cos(c)]]
            T0 = compose(Rz, guess)
            T0[:3, 3] = guess[:3, 3]  # the yaw turns the rotation only
            r = register_frames(cur, prev, register_frames(cur, prev, T0, coarse, trusted_init=True).T, params,
                                trusted_init=True)
            r = _plausible(r, guess, params)
            if r.ok:
                good.append(r)
    return max(good, key=lambda r: r.fitness) if good else reg


def _plausible(reg: Registration, guess: np.ndarray, params: OdometryParams) -> Registration:
    """``reg``, failed when its translation is more than ``coarse_gate_factor`` correspondence gates
    from the guess's."""
    d = float(np.linalg.norm(reg.T[:3, 3] - guess[:3, 3]))
    limit = params.coarse_gate_factor * params.max_correspondence_distance_m
    if reg.ok and d > limit:
        return replace(reg, ok=False, reason=f"{d:.2f} m from the constant-velocity guess (more than {limit:.2f} m: "
                                             "a wrong minimum)")
    return reg


def _keyframe_submap(kf_clouds: list, kf_poses: list, params: OdometryParams, size: int | None = None) -> PreparedFrame:
    """The last ``size`` (default ``keyframe_submap_size``) keyframe clouds in the frame of the last
    keyframe, as one prepared target (voxel centroids, covariances, tree): the laser rings of several
    keyframes interleave, so the covariances describe the surfaces rather than the ring lines."""
    n = min(params.keyframe_submap_size if size is None else size, len(kf_clouds))
    parts = []
    for P, T in zip(kf_clouds[-n:], kf_poses[-n:], strict=True):
        A = relative(kf_poses[-1], T)
        parts.append(P @ A[:3, :3].T + A[:3, 3])
    return prepare_frame(np.concatenate(parts), 0.0, params)


def _register_to_submap(cur: PreparedFrame, prev: PreparedFrame, submap: PreparedFrame, T_sub: np.ndarray,
                        T_prev: np.ndarray, velocity: np.ndarray, scaled: np.ndarray | None,
                        params: OdometryParams) -> tuple[Registration, np.ndarray, bool]:
    """Frame to local map (``frame_target="submap"``): ``(registration, pose, registered to the previous
    frame instead)``. The guesses are the previous pose ``T_prev`` (in the local map's frame ``T_sub``)
    moved by the constant velocity (and by the time-scaled one), and not moved. When the local map
    fails (e.g. it holds keyframes placed by the guess), the previous frame is tried; when that fails
    too, the frame is placed by the constant velocity."""
    still = relative(T_sub, T_prev)
    reg = _register_with_retries(cur, submap, compose(still, velocity), params, still)
    if scaled is not None:
        alt = _register_with_retries(cur, submap, compose(still, scaled), params, still)
        if alt.ok and (not reg.ok or alt.fitness > reg.fitness):
            reg = alt
    if reg.ok:
        return reg, compose(T_sub, reg.T), False
    alt = _register_with_retries(cur, prev, velocity, params)
    if alt.ok:
        alt = replace(alt, weak=(alt.weak + "; " if alt.weak else "")
                      + f"registered to the previous frame (the local map failed: {reg.reason})")
        return alt, compose(T_prev, alt.T), True
    return reg, compose(T_prev, velocity), False


def _time_scaled_guess(velocity: np.ndarray, dt: float, velocity_dt: float) -> np.ndarray | None:
    """The previous motion scaled to this frame's time step, ``Exp((Δt/Δt_prev) Log(ΔT_prev))``, or
    None when the two steps agree within 25 % (frames at a steady rate: the previous motion is the
    guess as it is) or there is no previous motion yet."""
    if not velocity_dt > 0 or not dt > 0 or abs(dt / velocity_dt - 1.0) <= 0.25:
        return None
    return project(se3_exp(np.ascontiguousarray((dt / velocity_dt) * se3_log(np.ascontiguousarray(velocity)))))


def _keyframe_due(dT: np.ndarray, dt: float, params: OdometryParams) -> bool:
    """[Ren2019 Eq. 8]: distance |Δs|, angle arccos((tr ΔR − 1)/2) or time above its threshold."""
    angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dT[:3, :3]) - 1.0) / 2.0))))
    return (np.linalg.norm(dT[:3, 3]) > params.keyframe_distance_m or angle > params.keyframe_angle_deg
            or dt > params.keyframe_interval_s)


def _check_time(k: int, t, times: list) -> None:
    """Frame ``k``'s time: a finite number of seconds within ``±MAX_ABS_TIME`` (the trajectory
    files' limit, so the outputs read back; every difference of two such times, e.g. the keyframe
    interval, is then finite) and after the previous frame's."""
    try:
        tf = float(t)
    except (TypeError, ValueError):
        raise InputError(f"frame {k}: time {t!r} is not a number of seconds") from None
    if not (math.isfinite(tf) and abs(tf) <= MAX_ABS_TIME):
        raise InputError(f"frame {k}: time {t!r} s is not finite or beyond ±{MAX_ABS_TIME:.0e} s "
                         "(the trajectory file's limit)")
    if times and not tf > times[-1]:
        raise InputError(f"frame {k}: time {tf!r} s is not after the previous frame's {times[-1]!r} s")


def _scaled_motion(velocity: np.ndarray, dt: float, velocity_dt: float) -> np.ndarray:
    """The constant-velocity motion over ``dt``: ``Exp((Δt/Δt_v) Log(ΔT_v))`` (identity without a
    previous motion)."""
    if not velocity_dt > 0:
        return np.eye(4)
    return project(se3_exp(np.ascontiguousarray((dt / velocity_dt) * se3_log(np.ascontiguousarray(velocity)))))


def _implausible(reg: Registration, motion: np.ndarray, dt: float, v_prev_w: np.ndarray | None, velocity_dt: float,
                 R_from: np.ndarray, params: OdometryParams) -> str:
    """Why a registration is not a plausible motion ("" when it is): the motion ``motion`` (the pose
    in the sensor frame of the last registered frame, ``dt`` s earlier, whose world rotation is
    ``R_from``) against the speed, angular rate and acceleration bounds, and the registration's
    constraint ratio against ``min_constraint_ratio`` (degenerate geometry).

    speed ``|Δt| / dt``; angular rate ``arccos((tr ΔR − 1)/2) / dt``; acceleration: rejected when
    ``|v − v_prev| > a_max (dt + dt_prev)/2 + 2 motion_noise_m / dt`` with the world velocities
    ``v = R_from Δt / dt`` and ``v_prev`` of the previous motion (not checked before there is one)."""
    if reg.constraint_ratio < params.min_constraint_ratio:
        return (f"degenerate geometry: constraint ratio {reg.constraint_ratio:.2e} below "
                f"{params.min_constraint_ratio:.0e} (the registration does not fix the pose)")
    speed = float(np.linalg.norm(motion[:3, 3])) / dt
    if speed > params.max_speed_m_s:
        return f"implausible motion: speed {speed:.1f} m/s above {params.max_speed_m_s:g} m/s"
    angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(motion[:3, :3]) - 1.0) / 2.0))))
    if angle / dt > params.max_angular_rate_deg_s:
        return (f"implausible motion: angular rate {angle / dt:.0f} deg/s above "
                f"{params.max_angular_rate_deg_s:g} deg/s")
    if v_prev_w is not None and velocity_dt > 0:
        v = R_from @ motion[:3, 3] / dt
        dv = float(np.linalg.norm(v - v_prev_w))
        mid = 0.5 * (dt + velocity_dt)
        if dv > params.max_acceleration_m_s2 * mid + 2.0 * params.motion_noise_m / dt:
            return (f"implausible motion: velocity change {dv:.1f} m/s in {mid:.3f} s ({dv / mid:.0f} m/s²) above "
                    f"{params.max_acceleration_m_s2:g} m/s² with {params.motion_noise_m:g} m of registration noise")
    return ""


def _checked(reg: Registration, pose, k: int, t: float, poses: list, times: list, last_ok: int, v_prev_w,
             velocity_dt: float, params: OdometryParams, aid=None) -> Registration:
    """``reg`` (frame ``k`` at ``t``, placed at ``pose``), rejected when :func:`_implausible` says its
    motion since the last registered frame ``last_ok`` is implausible or, with an IMU (``aid``),
    :func:`_imu_disagreement` says its rotation disagrees with the gyro's."""
    if not reg.ok:  # nothing registered: nothing to check (and no pose to check it at)
        return reg
    motion = relative(poses[last_ok], pose)
    why = (_implausible(reg, motion, t - times[last_ok], v_prev_w, velocity_dt, poses[last_ok][:3, :3], params)
           or _imu_disagreement(aid, motion, times[last_ok], t))
    if why:
        log.info("frame %d (t = %.3f s) rejected: %s; held by the %s", k, t, why,
                 "gyro rotation and constant-velocity translation" if aid is not None else "constant-velocity prior")
        return replace(reg, ok=False, reason=why)
    return reg


def _imu_disagreement(aid, motion: np.ndarray, t_from: float, t: float) -> str:
    """Why a registered motion ``motion`` (``T(t_from)⁻¹ T(t)``) disagrees with the IMU ("" when it
    agrees or without an IMU): its rotation is farther from the gyro's than the bound of
    :meth:`minegeo.slam.inertial.GyroAid.disagreement`, ``θ_tol + n_σ √3 σ_θ``."""
    if aid is None:
        return ""
    theta, bound = aid.disagreement(t_from, t, motion[:3, :3])
    if theta <= bound:
        return ""
    return (f"IMU disagreement: registered rotation {math.degrees(theta):.2f} deg from the gyro's over "
            f"{t - t_from:.3f} s (bound {math.degrees(bound):.2f} deg)")


def _refine_keyframe(cur, last_kf, kf_clouds, kf_poses, rel, T_kf, reg, pose, k: int, last_registered,
                     v_prev_w, velocity_dt: float, params: OdometryParams, gate=(None, 0.0, 0.0)):
    """Keyframe-to-keyframe refinement of a new keyframe ``cur`` (relative pose ``rel`` to the last
    keyframe at ``T_kf``): ``(rel, information, pose)``, the refined ones when the refinement
    converged to a plausible motion since the last registered frame (``last_registered``: its pose
    and the time since it) that agrees with the IMU (``gate = (GyroAid or None, t_from, t)``,
    :func:`_imu_disagreement`), else the chained relative pose with the frame-to-frame information."""
    target = last_kf if params.keyframe_submap_size <= 1 else _keyframe_submap(kf_clouds, kf_poses, params)
    ref = register_frames(cur, target, rel, params, trusted_init=True)
    why = ""
    if ref.ok:
        T_last, dt_last = last_registered
        motion = relative(T_last, compose(T_kf, project(ref.T)))
        why = _implausible(ref, motion, dt_last, v_prev_w, velocity_dt, T_last[:3, :3], params) \
            or _imu_disagreement(gate[0], motion, gate[1], gate[2])
    if ref.ok and not why:
        rel = project(ref.T)
        return rel, ref.information, compose(T_kf, rel)
    log.info("keyframe %d refinement failed (%s); chained odometry kept", k, why or ref.reason)
    return rel, (reg.information if reg.ok else np.eye(6) * 1e-6), pose


def _result(times, poses, rows, kf, extra, timings, params, imu_aided: bool = False) -> OdometryResult:
    """The :class:`OdometryResult` of :func:`run_odometry`'s per-frame ``rows`` (ok, reason,
    fitness, weak, deskewed, twist, constraint ratio) and keyframe lists ``kf`` (indices, edges,
    information, clouds, covariances)."""
    if not times:
        raise InputError("no frames: the sequence is empty")
    ok, reasons, fitness, weak, deskewed, twists, cratio = (list(c) for c in zip(*rows, strict=True))
    kf_idx, kf_edges, kf_info, kf_clouds, kf_covs = kf
    return OdometryResult(
        times_s=np.asarray(times), poses=np.stack(poses), frame_ok=np.asarray(ok, dtype=bool), frame_reason=reasons,
        frame_weak=weak, fitness=np.asarray(fitness), keyframes=np.asarray(kf_idx, dtype=np.int64),
        keyframe_edges=np.stack(kf_edges) if kf_edges else np.zeros((0, 4, 4)),
        keyframe_information=np.stack(kf_info) if kf_info else np.zeros((0, 6, 6)),
        keyframe_clouds=kf_clouds, keyframe_covariances=kf_covs, params=params, timings_s=timings,
        keyframe_extra_edges=extra, deskewed=np.asarray(deskewed, dtype=bool),
        deskew_twist=np.asarray(twists, dtype=np.float64).reshape(-1, 6), constraint_ratio=np.asarray(cratio, dtype=np.float64),
        imu_aided=imu_aided,
    )


def _register_step(cur, k: int, t: float, prev, prev_k: int, submap, T_sub, poses, times, velocity,
                   velocity_dt: float, params: OdometryParams):
    """One registration of frame ``k`` (time ``t``): ``(registration, pose or None when not
    registered, registered to the previous frame instead of the local map)``."""
    if params.frame_target == "submap":
        # `times` holds this frame's time already: the step from the previous frame (pose poses[-1]) is t - times[-2]
        return _register_to_submap(cur, prev, submap, T_sub, poses[-1], velocity,
                                   _time_scaled_guess(velocity, t - times[-2], velocity_dt), params)
    if prev_k == k - 1:
        reg = _register_with_retries(cur, prev, velocity, params)  # [Ren2019 Eq. 7]: ΔT_{t-1,t}
        scaled = _time_scaled_guess(velocity, t - prev.time_s, velocity_dt)
        if scaled is not None:  # irregular frame times (keyframe logs, dropped frames): same speed, not same step
            alt = _register_with_retries(cur, prev, scaled, params)
            if alt.ok and (not reg.ok or alt.fitness > reg.fitness):
                reg = alt
    else:  # frames since `prev` were held by the prior: the constant-velocity motion since `prev`
        reg = _register_with_retries(cur, prev, _scaled_motion(velocity, t - prev.time_s, velocity_dt), params)
    return reg, (compose(poses[prev_k], reg.T) if reg.ok else None), False


def _deskew_prepare(raw, twist, t: float, params: OdometryParams, aid=None):
    """``(frame, seconds, twist)``: the raw points ``raw = (points, offsets)`` deskewed by the body twist
    ``twist`` (rad/s, m/s) and prepared at frame time ``t``. With an IMU (``aid``,
    :class:`minegeo.slam.inertial.GyroAid`) each point is rotated by the gyro-integrated rotation at its
    own time and moved by the twist's velocity; the twist returned then holds the mean gyro rate."""
    t0 = time.perf_counter()
    if aid is None:
        return prepare_frame(deskew_points(raw[0], raw[1], twist), t, params), time.perf_counter() - t0, twist
    tau = np.asarray(raw[1], dtype=np.float64)
    used = np.r_[aid.mean_rate(t + float(tau.min()), t + float(tau.max())), twist[3:]] if tau.size else twist
    frame = prepare_frame(aid.deskew(raw[0], tau, t, twist[3:]), t, params)
    return frame, time.perf_counter() - t0, used


def _deskewed(raw, T_from, T_to, dt: float, t: float, params: OdometryParams, aid=None, covs=None):
    """``(frame, twist, seconds)``: ``raw`` deskewed by the body twist of the motion ``T_from -> T_to``
    over ``dt`` seconds (:func:`_deskew_prepare`); with ``covs`` (:class:`_CovarianceHistory`) its
    covariances among the last frames' points, at ``T_to``."""
    t0 = time.perf_counter()
    frame, _, twist = _deskew_prepare(raw, twist_from_motion(relative(T_from, T_to), dt), t, params, aid)
    return (frame if covs is None else covs.at(frame, T_to)), twist, time.perf_counter() - t0


def _guesses(raw, velocity: np.ndarray, velocity_dt: float, poses: list, times: list, t: float):
    """``(twist, T_guess)`` of the frame at time ``t``: the body twist of the last registered motion
    ``velocity`` over ``velocity_dt`` (zero without point times or a motion) to deskew it by, and its
    pose guessed by that motion scaled to the time since the last frame (None for the first frame)."""
    twist = twist_from_motion(velocity, velocity_dt) if raw is not None and velocity_dt > 0 else np.zeros(6)
    return twist, (compose(poses[-1], _scaled_motion(velocity, t - times[-1], velocity_dt)) if poses else None)


def start_velocity(times_s, positions_m) -> np.ndarray:
    """Velocity (m/s) of the least-squares line through the positions of the frames after the first.

    ``v = Σ (τ_i − τ̄)(p_i − p̄) / Σ (τ_i − τ̄)²`` over the frames at ``τ_i = t_i − t_0`` (the slope of
    ``p(τ) = x_0 + v τ``). The first frame deskewed by it (:func:`run_odometry`, ``start_deskew_window_s``)
    anchors the local map the frames after it are registered to: an error of its earlier deskewing
    shifts them all alike, which moves ``x_0``, not ``v``.

    Parameters
    ----------
    times_s : (n,) array
        Frame times (s); n ≥ 2, not all equal.
    positions_m : (n, 3) array
        The frames' positions (m), in the first frame's sensor frame at its frame time (the odometry's
        frame): the velocity is then the body velocity of the first sweep.

    Returns
    -------
    (3,) float64
    """
    tau = np.asarray(times_s, dtype=np.float64)
    P = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    d = tau - tau.mean()
    return (d @ (P - P.mean(axis=0))) / float(d @ d)


def _first_row(cur: PreparedFrame, raw, twist) -> list:
    """The first frame's row (:func:`_result`): registered by definition unless it has too few points."""
    return [cur.index is not None, "" if cur.index is not None else "too few points", 1.0, "", raw is not None,
            twist, 1.0]


def _start_redeskew(raw, frames, keyframes, last_kf, local, to_submap: bool, params: OdometryParams, aid):
    """The first frame deskewed again from its raw points ``raw`` by its rotation rate as before (the first
    motion's, or the gyro's) and the velocity :func:`start_velocity` of the registered frames since, put in
    place of its cloud in the keyframes, as the last keyframe and in the local map when it still is in them.

    ``frames = (times, poses, rows)`` (its row gets the twist used), ``keyframes = (indices, clouds,
    covariances)`` (changed in place), ``local = (clouds, poses, local map)``. Returns ``(seconds, last
    keyframe, local map clouds, local map)``."""
    t0 = time.perf_counter()
    times, poses, rows = frames
    kf_idx, kf_clouds, kf_covs = keyframes
    sub_clouds, sub_poses, submap = local
    ok = [i for i in range(1, len(poses)) if rows[i][0]]
    if len(ok) < 2:
        return time.perf_counter() - t0, last_kf, sub_clouds, submap
    v = start_velocity([times[i] for i in ok], [poses[i][:3, 3] for i in ok])
    first, _, rows[0][5] = _deskew_prepare(raw, np.r_[np.asarray(rows[0][5], dtype=np.float64)[:3], v], times[0],
                                           params, aid)
    if first.index is not None:
        if to_submap and sub_clouds and sub_clouds[0] is kf_clouds[0]:
            sub_clouds = [first.points] + sub_clouds[1:]
            submap = first if len(sub_clouds) == 1 else _keyframe_submap(sub_clouds, sub_poses, params,
                                                                         params.local_map_keyframes)
        kf_clouds[0], kf_covs[0] = first.points, first.covariances
        last_kf = first if kf_idx == [0] else last_kf
    return time.perf_counter() - t0, last_kf, sub_clouds, submap


def _first_pass(cur, raw, twist, t: float, params: OdometryParams, aid, covs, T_guess):
    """``(frame, frame with its own covariances, seconds, twist)``: the frame for its first registration: ``raw`` deskewed by the
    constant-velocity twist ``twist`` of the last registered motion (:func:`_deskew_prepare`), else the
    prepared ``cur``; its covariances among the last frames' points at its guessed pose ``T_guess``
    (:class:`_CovarianceHistory`; None for the first frame). The first pass needs them as much as the
    second: on the 20 s junctions stream, the first pass on the frame's own covariances (the second on
    the history's) ended at 0.29 % of the path against 0.07 % with both on the history's."""
    t0 = time.perf_counter()
    if raw is not None:
        cur, _, twist = _deskew_prepare(raw, twist, t, params, aid)
    return covs.at(cur, T_guess), cur, time.perf_counter() - t0, twist


def _retaken(own, cur, reg, pose, via, covs, register, kt, motion_args):
    """``(frame, registration, pose, via_prev)``: of the registration ``reg`` (at ``pose``, of ``cur``
    whose covariances were taken at a guess far from ``pose``, or rejected) and the registration of the frame on its
    own covariances ``own`` followed by one on the history's covariances taken at that pose, the one
    with the higher overlap (fitness). At a sharp turn of frames 1 m apart (bench_slam's ramp, a 44°
    step guessed as 30°) the covariances at the guess put the history 14° off and the registration
    settled 7° and 1.7 m wrong at overlap 0.69; on its own covariances it found the turn (0.99). An
    accepted ``reg`` is replaced only by an overlap higher by :attr:`_CovarianceHistory.RETAKE_OVERLAP`:
    along a road (MulRan's keyframes, speed changing between them) minima metres apart overlap alike,
    and the higher of two such was 3.3 m wrong at keyframe 33."""
    reg_o, pose_o, via_o = register(own, *kt)
    if not (reg_o.ok and pose_o is not None):
        return cur, reg, pose, via
    best = (own, _checked(reg_o, pose_o, *motion_args), pose_o, via_o)
    cur3 = covs.at(own, pose_o)
    reg3, pose3, via3 = register(cur3, *kt, pose_o)  # from the pose its covariances were taken at
    if reg3.ok and pose3 is not None:
        r3 = _checked(reg3, pose3, *motion_args)
        if r3.ok and r3.fitness >= best[1].fitness:
            best = (cur3, r3, pose3, via3)
    better = not reg.ok or pose is None or best[1].fitness > reg.fitness + covs.RETAKE_OVERLAP
    return best if best[1].ok and better else (cur, reg, pose, via)


class _CovarianceHistory:
    """The points and poses of the last ``covariance_frames - 1`` registered frames, and the GICP
    covariances of a new frame among them (:func:`minegeo.slam.frame_covariances.covariances_with_history`).
    """

    #: rotation (deg) and translation (m) between a frame's guess and its registration above which the
    #: frame is registered again from its own covariances (:func:`_retaken`)
    RETAKE_DEG, RETAKE_M = 0.5, 0.1
    #: the overlap (fraction of the frame's points) by which a registration taken again must exceed an
    #: accepted one to replace it
    RETAKE_OVERLAP = 0.1

    def __init__(self, params: OdometryParams):
        self.params, self.frames = params, []

    def at(self, cur: PreparedFrame, T_cur: np.ndarray | None) -> PreparedFrame:
        """``cur`` (taken at the pose ``T_cur``, ``T_world_sensor``) with its covariances from the
        kNN of its points among its own and the history's (moved into its frame); ``cur`` itself
        without a history, a pose or a search index (too few points)."""
        if T_cur is None or not self.frames or cur.index is None:
            return cur
        parts = []
        for P, T in self.frames:
            A = relative(T_cur, T)
            parts.append(P @ A[:3, :3].T + A[:3, 3])
        C = covariances_with_history(cur.points, np.concatenate(parts), self.params.gicp(), self.params.voxel_size_m)
        return replace(cur, covariances=C)

    def moved(self, T_guess: np.ndarray | None, T_reg: np.ndarray) -> bool:
        """Whether a frame registered at ``T_reg`` lies so far from the guess ``T_guess`` its covariances
        were taken at that they are in doubt (:func:`_retaken`): more than :attr:`RETAKE_DEG` of rotation
        or :attr:`RETAKE_M` of translation apart (with a history to take them from). At 10 m range 0.5°
        is 9 cm, a third of the default voxel: the history's points then no longer lie on the frame's
        surfaces."""
        if T_guess is None or not self.frames:
            return False
        D = relative(T_guess, T_reg)
        ang = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(D[:3, :3])) - 1.0) / 2.0))))
        return ang > self.RETAKE_DEG or float(np.linalg.norm(D[:3, 3])) > self.RETAKE_M

    def push(self, cur: PreparedFrame, pose: np.ndarray) -> None:
        """Keep the registered frame ``cur`` at ``pose`` (the oldest leaves)."""
        n = self.params.covariance_frames - 1
        if n > 0 and cur.index is not None:
            self.frames = (self.frames + [(cur.points, pose)])[-n:]


def _held_step(aid, velocity: np.ndarray, velocity_dt: float, t_prev: float, t: float) -> np.ndarray:
    """The motion of a frame not registered, from the previous frame at ``t_prev``: the constant
    velocity (time-scaled when the step changed), its rotation from the gyro with an IMU."""
    if aid is not None:
        return _guess(aid, velocity, velocity_dt, t_prev, t)
    step = _time_scaled_guess(velocity, t - t_prev, velocity_dt)
    return velocity if step is None else step


def _reference_motion(aid, velocity: np.ndarray, velocity_dt: float, T_ref: np.ndarray, t_ref: float, t: float,
                      start: np.ndarray | None):
    """``(motion, seconds)`` the registration of the frame at ``t`` starts from, from the reference frame
    (at pose ``T_ref``, time ``t_ref``): the constant velocity (with an IMU its rotation the gyro's since
    ``t_ref``, :func:`_guess`), or the move to the pose ``start`` (``T_world_sensor``) when given."""
    if start is not None:
        return relative(T_ref, start), t - t_ref
    return (velocity, velocity_dt) if aid is None else (_guess(aid, velocity, velocity_dt, t_ref, t), t - t_ref)


def _guess(aid, velocity: np.ndarray, velocity_dt: float, t_from: float, t: float) -> np.ndarray:
    """The motion from ``t_from`` to ``t``: the constant velocity's (:func:`_scaled_motion`), its rotation
    from the gyro with an IMU (:meth:`minegeo.slam.inertial.GyroAid.guess`)."""
    return aid.guess(_scaled_motion(velocity, t - t_from, velocity_dt), t_from, t)


def _submap_keyframe_information(reg, via_prev: bool, sub_kf: int, n_kf: int, T_sub, pose):
    """``(information, extra edge or None)`` of a keyframe registered to the local map: when the
    keyframes since ``sub_kf`` were placed by the guess, the registration measures ``T_sub⁻¹ T``,
    not the relative pose to the (guessed) last keyframe: an extra edge ``(sub_kf, n_kf, T_sub⁻¹ T,
    information)`` carries it and the chain edge gets a negligible information."""
    info = reg.information if reg.ok else np.eye(6) * 1e-6
    if reg.ok and not via_prev and sub_kf != n_kf - 1:
        return np.eye(6) * 1e-6, (sub_kf, n_kf, relative(T_sub, pose), info)
    return info, None


def _next_submap(sub_clouds, sub_poses, cur, pose, via_prev: bool, params: OdometryParams):
    """The local map's keyframes with the registered keyframe ``cur`` added: ``(clouds, poses,
    local map)``; one registered to the previous frame (the local map failed) starts a fresh local map."""
    n = params.local_map_keyframes
    sub_clouds = ([] if via_prev else sub_clouds[-(n - 1):] if n > 1 else []) + [cur.points]
    sub_poses = ([] if via_prev else sub_poses[-(n - 1):] if n > 1 else []) + [pose]
    return sub_clouds, sub_poses, _keyframe_submap(sub_clouds, sub_poses, params, n)


def run_odometry(frames: Iterable, params: OdometryParams | None = None, progress=None, imu=None) -> OdometryResult:
    """GICP odometry over a sequence of frames, deskewed when their points carry times.

    Parameters
    ----------
    frames : iterable of (time_s, (m, 3) points) or (time_s, (m, 3) points, (m,) offsets_s)
        Frames in time order, points in the sensor frame (m), per-point offsets in seconds after the
        frame time (or None). With offsets and ``params.deskew`` each frame is deskewed to its frame
        time by the body twist ``ξ = Log(T_a⁻¹ T_b) / (t_b − t_a)`` of the last registered motion
        (:func:`minegeo.slam.deskew.deskew_points`), then (``deskew_iterations = 1``) by its own.
    params : OdometryParams, optional
    progress : callable, optional
        Called with the frame index after each frame.
    imu : GyroAid, optional
        :class:`minegeo.slam.inertial.GyroAid`: rotation guesses and deskewing from the gyro.

    Returns
    -------
    OdometryResult
    """
    params = params or OdometryParams()
    t_prep = t_f2f = t_kf = 0.0
    times, poses, rows = [], [], []  # rows: (ok, reason, fitness, weak, deskewed, twist, constraint ratio)
    kf_idx, kf_edges, kf_info, kf_clouds, kf_covs = [], [], [], [], []
    prev = last_kf = submap = None
    prev_k = last_ok = 0  # frame index of `prev` and of the last registered frame
    to_submap = params.frame_target == "submap"
    sub_clouds, sub_poses = [], []  # the keyframes the local map is made of (registered ones only)
    T_sub, sub_kf = np.eye(4), 0  # pose and keyframe number of the local map's frame (its last keyframe)
    extra, covs = [], _CovarianceHistory(params)  # keyframe edges (i, j, T_i⁻¹ T_j, Ω) to an older keyframe's local map
    # the last registered motion, its world velocity (m/s), the first frame's raw points until a motion is
    # known and until it is deskewed again (start_deskew_window_s)
    velocity, velocity_dt, v_prev_w, first_raw, start = np.eye(4), 0.0, None, None, None

    def register(cur: PreparedFrame, k: int, t: float, start: np.ndarray | None = None):
        j = k - 1 if to_submap else prev_k  # the reference frame of the guess
        m, m_dt = _reference_motion(imu, velocity, velocity_dt, poses[j], times[j], t, start)
        return _register_step(cur, k, t, prev, prev_k, submap, T_sub, poses, times, m, m_dt, params)
    for k, (t, cur, dt_prep, raw) in enumerate(_prepared_frames(frames, params)):
        _check_time(k, t, times)
        twist, T_guess = _guesses(raw, velocity, velocity_dt, poses, times, t)
        cur, own, dt1, twist = _first_pass(cur, raw, twist, t, params, imu, covs, T_guess)
        t_prep += dt_prep + dt1
        times.append(float(t))
        if prev is None:
            first_raw, start = raw, (raw if raw is not None and params.start_deskew_window_s > 0 else None)
            poses.append(np.eye(4))
            rows.append(_first_row(cur, raw, twist))
            kf_idx, kf_clouds, kf_covs = [0], [cur.points], [cur.covariances]
            prev = last_kf = submap = cur
            sub_clouds, sub_poses = [cur.points], [np.eye(4)]
            continue
        t0, T_kf = time.perf_counter(), poses[kf_idx[-1]]
        reg, pose, via_prev = register(cur, k, t)
        if first_raw is not None and reg.ok and pose is not None and prev_k == 0:
            # the first frame had no motion to deskew by: both by the first one, then register again
            first, twist0, dt1 = _deskewed(first_raw, poses[0], pose, t - times[0], times[0], params, imu)
            if raw is not None:
                cur, twist, dt2 = _deskewed(raw, poses[0], pose, t - times[0], t, params, imu)
                dt1 += dt2
            t_prep += dt1
            if first.index is not None:
                prev = last_kf = first
                kf_clouds[0], kf_covs[0], rows[0][5] = first.points, first.covariances, twist0
                if to_submap:
                    submap, sub_clouds = first, [first.points]
                reg0, pose0, via0 = register(cur, k, t)
                if reg0.ok and pose0 is not None:
                    reg, pose, via_prev = reg0, pose0, via0
        first_raw = None
        motion_args = (k, t, poses, times, last_ok, v_prev_w, velocity_dt, params, imu)
        reg = _checked(reg, pose, *motion_args)  # an implausible first pass does not seed the second
        if own is not cur and (not reg.ok or pose is None or covs.moved(T_guess, pose)):  # covariances in doubt
            cur, reg, pose, via_prev = _retaken(own, cur, reg, pose, via_prev, covs, register, (k, t), motion_args)
        if raw is not None and params.deskew_iterations and reg.ok and pose is not None:
            # deskew again with this frame's own motion (from the last registered frame to it)
            cur2, twist2, dt1 = _deskewed(raw, poses[last_ok], pose, t - times[last_ok], t, params, imu, covs)
            t_prep += dt1
            reg2, pose2, via2 = register(cur2, k, t)
            if reg2.ok and pose2 is not None:
                cur, reg, pose, via_prev, twist = cur2, _checked(reg2, pose2, *motion_args), pose2, via2, twist2
        t_f2f += time.perf_counter() - t0
        if not reg.ok:
            via_prev = False
            log.info("frame %d (t = %.3f s) not registered: %s; placed by constant velocity", k, t, reg.reason)
            pose = compose(poses[-1], _held_step(imu, velocity, velocity_dt, times[-2], t))
        rows.append([reg.ok, reg.reason, reg.fitness, reg.weak, raw is not None, twist,
                     reg.constraint_ratio if cur.index is not None and prev.index is not None else float("nan")])
        rel, t0 = relative(T_kf, pose), time.perf_counter()
        if _keyframe_due(rel, t - times[kf_idx[-1]], params):
            if to_submap:  # the registration already was to the local map of the last keyframes
                info, edge = _submap_keyframe_information(reg, via_prev, sub_kf, len(kf_idx), T_sub, pose)
                extra += [edge] if edge is not None else []
            else:
                rel, info, pose = _refine_keyframe(cur, last_kf, kf_clouds, [poses[i] for i in kf_idx], rel, T_kf,
                                                   reg, pose, k, (poses[last_ok], t - times[last_ok]), v_prev_w,
                                                   velocity_dt, params, (imu, times[last_ok], t))
            for lst, v in zip((kf_idx, kf_edges, kf_info, kf_clouds, kf_covs), (k, rel, info, cur.points,
                                                                                cur.covariances), strict=True):
                lst.append(v)
            last_kf = cur
            if to_submap and cur.index is not None and reg.ok:
                sub_clouds, sub_poses, submap = _next_submap(sub_clouds, sub_poses, cur, pose, via_prev, params)
                T_sub, sub_kf = pose, len(kf_idx) - 1
            t_kf += time.perf_counter() - t0
        poses.append(pose)
        if reg.ok:
            covs.push(cur, pose)
            velocity, velocity_dt = relative(poses[last_ok], poses[-1]), t - times[last_ok]
            v_prev_w = (poses[-1][:3, 3] - poses[last_ok][:3, 3]) / velocity_dt
            if imu is not None:  # the registered rotation measures the gyro bias
                imu.update(times[last_ok], t, velocity[:3, :3])
            last_ok = k
        if start is not None and reg.ok and t - times[0] >= params.start_deskew_window_s:
            dt1, last_kf, sub_clouds, submap = _start_redeskew(start, (times, poses, rows), (kf_idx, kf_clouds, kf_covs),
                                                               last_kf, (sub_clouds, sub_poses, submap), to_submap, params, imu)
            t_prep, start = t_prep + dt1, None
        if to_submap:
            prev = cur if cur.index is not None else prev
        elif cur.index is not None and reg.ok:  # a frame held by the prior is no registration target
            prev, prev_k = cur, k
        if progress is not None:
            progress(k)
    return _result(times, poses, rows, (kf_idx, kf_edges, kf_info, kf_clouds, kf_covs), extra,
                   {"prepare": t_prep, "frame_to_frame": t_f2f, "keyframe_refine": t_kf}, params, imu is not None)
