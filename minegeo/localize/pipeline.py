"""Global localization of a local scan in a prior (georeferenced) mine map (Baek et al. 2022, Sec. 2).

Pipeline (:func:`localize_scan`), each stage timed:

1. ``downsample`` the scan (Sec. 2.2: voxel size or octree level), ``normals`` ([Baek2022 Eq. 2]),
   ``fpfh`` ([Baek2022 Eqs. 3-6]) with the map's :class:`~minegeo.localize.prepared.FeatureParams`;
2. ``ransac``: FPFH correspondences + RANSAC with edge-length pruning ([Baek2022 Eqs. 7-9]), Table 3
   parameters, via :func:`minegeo.registration.ransac.register_ransac`;
3. ``icp``: every *distinct* RANSAC hypothesis (the best one and the runner-up, optionally
   more from extra RANSAC runs) is refined by ICP (Sec. 2.4, [Baek2022 Eqs. 10-16]; point-to-point as
   in the paper, point-to-plane selectable; GICP is not available yet). The refined
   hypothesis with the highest ICP fitness wins (multi-hypothesis verification: mine drifts
   repeat themselves, and a RANSAC score alone can prefer a look-alike drift);
4. ``decision``: ``status`` = ``ok`` / ``ambiguous`` / ``failed`` with the reason (below); an
   ``ok`` decision is first checked by the whole-map rival search (``LocalizeParams.rival``);
5. ``covariance``: ``Σ = σ² (JᵀJ)⁻¹`` of the final fit and the 95 % position uncertainty of
   the scan origin;
6. ``trajectory``: the sensor trajectory moved into the map and the CRS ([Baek2022 Eq. 18]):
   ``T_map_sensor(τ) = T_map_scan · T_scan_sensor(τ)``.

Frames
------
``scan``  the local scan's own frame (its first sensor pose, as SLAM gives it).
``map``   the prior map's frame before georeferencing — for a map written by
          ``minegeo georef`` the frame of the map file it was made from (the ``map`` of
          ``T_crs_map``). **``T_map_scan`` always refers to this frame**:
          ``p_map = R p_scan + t``.
``geo``   CRS coordinates minus the georeferencing origin; ``T_geo_scan`` is obtained with
          :func:`~minegeo.georef.pose_to_crs` (the position goes through the
          similarity, the orientation only through its rotation, so the pose stays rigid).
``crs``   full projected coordinates = ``geo`` + origin (only added when printing).

Modules (one per stage, each a pure function of its inputs and a typed result)
-------------------------------------------------------------------------------
:mod:`~minegeo.localize.params` (every ``*Params``), :mod:`~minegeo.localize.scan` (1: features,
frames), :mod:`~minegeo.localize.hypotheses` (2: RANSAC, correlative search),
:mod:`~minegeo.localize.verification` (3: ICP, screening, plane agreement, polish),
:mod:`~minegeo.localize.decision` (4: the decision), :mod:`~minegeo.localize.rival_check`
(4a), :mod:`~minegeo.localize.covariance` (5), :mod:`~minegeo.localize.placement` (6),
:mod:`~minegeo.localize.fallback` (the gravity fallback), :mod:`~minegeo.localize.result`
(:class:`LocalizationResult` and its JSON record). This module only runs them in order.

Decision rules (all thresholds in :class:`LocalizeParams`)
----------------------------------------------------------
``failed``     RANSAC found no hypothesis; or the chosen placement's verification score (fraction
               of scan points within ``verify.plane_tolerance_m`` of the map's tangent planes)
               is below ``verify.min_plane_fitness``; or the best ICP fitness (fraction of scan points
               with a map point within the ICP gate) is below ``verify.min_fitness``; or its inlier
               RMSE ([Baek2022 Eq. 19]) exceeds ``verify.max_inlier_rmse_m``.
``ambiguous``  another refined hypothesis placing the scan more than ``ambiguity.distance_m``
               (or ``ambiguity.angle_deg``) away reaches ``ambiguity.ratio`` × the best ICP
               fitness (a look-alike drift); or, before an ``ok``, the **whole-map rival
               search** at the chosen attitude (``LocalizeParams.rival``, :mod:`minegeo.localize.rivals`)
               finds a placement that reaches that ratio or, on the scan points the map covers
               at both places, fits as well (``RivalParams.matched_ratio``: an exact copy of the
               drift on another level); or the ICP constraint matrix is degenerate
               (smallest / largest eigenvalue of the normalised point-to-plane constraint
               matrix < ``verify.degeneracy_ratio``, e.g. sliding along a straight featureless drift).
``ok``         otherwise; ``rival_search`` then names the best rival and the margin.
"""

from __future__ import annotations

import logging
import math
import time

from minegeo.errors import InputError
from minegeo.io.types import Trajectory
from minegeo.localize._progress import ProgressFn
from minegeo.localize.covariance import judge_fit, pose_covariance
from minegeo.localize.decision import verify_and_decide
from minegeo.localize.fallback import gravity_fallback
from minegeo.localize.hypotheses import ransac_hypotheses
from minegeo.localize.params import LocalizeParams
from minegeo.localize.placement import place
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.result import (
    ANSWER_FIELDS,
    CHI2_2D_95,
    CHI2_3D_95,
    STATUSES,
    LocalizationResult,
    LocalizeStatus,
    error_vs_truth,
    rejected_candidates,
)
from minegeo.localize.rival_check import check_rivals
from minegeo.localize.run_context import RunContext
from minegeo.localize.scan import scan_features, to_map
from minegeo.localize.verification import polish, verify_context

__all__ = ["LocalizeParams", "LocalizationResult", "LocalizeStatus", "localize_scan", "CHI2_3D_95", "CHI2_2D_95", "STATUSES",
           "ANSWER_FIELDS", "rejected_candidates", "error_vs_truth"]

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- main
def localize_scan(prepared_map: PreparedMap, scan_cloud, trajectory: Trajectory | None = None,
                  params: LocalizeParams | None = None, seed: int = 0, *,
                  progress: ProgressFn | None = None) -> LocalizationResult:
    """Find where a local scan (and its sensor trajectory) lies in a prepared prior map.

    Parameters
    ----------
    prepared_map : PreparedMap
        From :func:`~minegeo.localize.prepared.prepare_map` / ``PreparedMap.load``; its
        feature parameters must equal ``params.features``.
    scan_cloud : PointCloud or (n, 3) array_like
        The local scan in its own frame (m).
    trajectory : Trajectory, optional
        Sensor poses ``T_scan_sensor`` in the scan frame (as written by a SLAM system and by
        ``minegeo synth``); moved into the map and the CRS with [Baek2022 Eq. 18].
    params : LocalizeParams, optional
        Defaults to Baek et al. (2022) Table 3 plus the decision thresholds.
    seed : int
        Seeds every random choice (RANSAC sampling); equal inputs and seed give
        bit-identical results.
    progress : callable, optional
        ``progress(step)`` is called when each step starts (``"downsample"``, ``"normals"``,
        ``"FPFH"``, ``"RANSAC"``, ``"ICP verification"``, ``"correlative search"`` and
        ``"rival search"`` when they run, ``"polish"``, ``"uncertainty"``, ``"trajectory"``), e.g. to drive a progress bar
        (:mod:`minegeo.localize._progress`). Nothing is printed by this function.

    Returns
    -------
    LocalizationResult
        Never a silent wrong pose: check ``status`` (``ok`` / ``ambiguous`` / ``failed``) and
        ``reason``. Only an ``ok`` result carries an answer; for the others ``T_map_scan`` and
        its uncertainty describe the best *rejected* candidate (``to_dict`` writes them under
        ``rejected_candidates``, never as the pose).

    Notes
    -----
    **Degeneracy is reported once, where it matters.** Every ICP of every candidate (screening,
    full resolution, rivals) analyses its own constraint matrix, and a weak direction of a
    *rejected or rival* candidate says nothing about the answer; :func:`~minegeo.registration.register_icp`
    and ``register_gicp`` return the flag (``degenerate``, ``degeneracy_reason``) and log it at DEBUG
    level only, the caller deciding what to tell. The chosen fit's weak direction is judged once,
    after the covariance: if its 95 % displacement over the scan exceeds
    ``verify.max_weak_displacement_95_m`` the result is ``ambiguous`` and ``reason`` says so;
    otherwise it does not change the answer (the covariance, hence the 95 % radius, already
    contains it) and it is a note in ``warnings`` (result.json and the report), not a logged
    warning. The outcome itself is logged at DEBUG level: the caller reports ``status``.

    Raises
    ------
    TooFewPointsError
        Empty scan, or fewer than ``params.min_scan_points`` points after downsampling.
    DegenerateGeometryError
        The downsampled scan is collinear or planar (its pose cannot be determined).
    InputError
        Feature parameters differ from the prepared map's, bad shapes or parameters.
    """
    p = LocalizeParams() if params is None else params
    if not isinstance(p, LocalizeParams):
        raise InputError(f"params must be a LocalizeParams, got {type(p).__name__}")
    if not isinstance(prepared_map, PreparedMap):
        raise InputError(f"prepared_map must be a PreparedMap, got {type(prepared_map).__name__}")
    prepared_map.check_params(p.features)
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise InputError(f"seed must be an integer >= 0, got {seed!r}")
    seed = int(seed)
    res = _localize_scan(prepared_map, scan_cloud, trajectory, p, seed, progress)
    if res.status in ("failed", "ambiguous") and p.gravity_fallback is not None and p.ransac.model == "rigid":
        res = gravity_fallback(prepared_map, scan_cloud, trajectory, p, seed, progress, res, _localize_scan)
    return res


def _localize_scan(pm: PreparedMap, scan_cloud, trajectory, p: LocalizeParams, seed: int,
                   progress: ProgressFn | None) -> LocalizationResult:
    """One pass of the pipeline (arguments already checked): the stages of the module docstring."""
    t_all = time.perf_counter()
    run = RunContext(seed=seed, progress=progress)
    timings, warnings = run.timings, run.warnings
    features = scan_features(scan_cloud, p, run)  # 1. downsample, normals, FPFH
    hypotheses = ransac_hypotheses(pm, features, p, run)  # 2. RANSAC
    ctx = verify_context(pm, features, p)
    dec, corr = verify_and_decide(ctx, pm, hypotheses, trajectory, run)  # 3-4. ICP, decision
    warnings.extend(dec.warnings)
    rival_record = None
    if p.rival is not None and dec.status == "ok" and dec.ic_best is not None:
        # 4a. whole-map rival search at the chosen attitude (minegeo addition): no `ok`
        #     before it is established that no other placement explains the scan nearly as well
        dec, rival_record = check_rivals(ctx, pm, dec, hypotheses.r0, trajectory, run)
    pol, ic_final = None, dec.ic_best  # pose and covariance; the reported ICP statistics stay the decision's
    if p.icp.polish_correspondence_m is not None and dec.ic_best is not None:
        # 4b. polish (minegeo addition): point-to-plane with a tight gate from the chosen pose
        run.announce("polish")
        t0 = time.perf_counter()
        pol = polish(ctx, dec.ic_best)
        if pol.applied:
            ic_final = pol.ic
        else:
            warnings.append(f"the tight-gate polish would move the scan by {pol.record['largest_shift_m']:.3f} m (> "
                            f"{p.verify.max_pending_step_m:g} m) or left too few pairs: not applied")
        timings["polish"] = time.perf_counter() - t0
    # 5. covariance (about the scan origin, work frame) and the checks that use it
    run.announce("uncertainty")
    t0 = time.perf_counter()
    pose_cov = pose_covariance(ctx, ic_final, pol)
    status, reason = LocalizeStatus(dec.status), dec.reason  # a decision is never "deferred" here
    if ic_final is not None:
        status, reason = judge_fit(status, reason, dec.weak, pose_cov, p, warnings)
    timings["covariance"] = time.perf_counter() - t0
    T_map_scan = to_map(pose_cov.T_work_scan, features.scan_origin, pm.work_origin)
    # 6. trajectory and CRS ([Baek2022 Eq. 18])
    run.announce("trajectory")
    t0 = time.perf_counter()
    placement = place(T_map_scan, pm, trajectory, pose_cov.cov)
    warnings.extend(placement.warnings)
    timings["trajectory"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    # the caller reports the outcome (the CLI prints it once); see Notes of localize_scan
    log.debug("localization %s: %s", status, reason)
    ic_best, r0 = dec.ic_best, hypotheses.r0
    return LocalizationResult(
        status=status, reason=reason, T_map_scan=T_map_scan, T_geo_scan=placement.T_geo_scan, T_crs_scan=placement.T_crs_scan,
        fitness=float(ic_best.fitness) if ic_best is not None else 0.0,
        inlier_rmse_m=float(ic_best.inlier_rmse_m) if ic_best is not None else math.nan,
        ransac=r0, icp=ic_best, hypotheses=dec.hyps, covariance_6x6=pose_cov.cov, sigma_m=pose_cov.sigma,
        position_cov_3x3=pose_cov.pos_cov, position_sigma_m=pose_cov.pos_sigma, position_95_radius_m=pose_cov.r95,
        horizontal_95_radius_m=pose_cov.h95, pending_step_m=pose_cov.pending, trajectory_map=placement.trajectory_map,
        trajectory_geo=placement.trajectory_geo, trajectory_sigma_m=placement.trajectory_sigma_m, crs=placement.crs,
        georef_origin=placement.georef_origin, displacement_95_m=pose_cov.disp95, uncertainty=pose_cov.unc_record,
        plane_tolerance_m=ctx.tol, scan_noise_m=ctx.scan_noise, n_scan_points=int(features.points.shape[0]),
        n_scan_down=int(features.feature_points.shape[0]), n_scan_icp=int(features.icp_points.shape[0]), params=p, map_params=pm.params,
        seed=seed, timings_s=timings, warnings=warnings,
        ransac_T_map_scan=to_map(r0.T_target_source, features.scan_origin, pm.work_origin),
        scan_points_down=features.feature_points + features.scan_origin, residuals_m=pose_cov.residuals,
        correlative=None if corr is None else corr.record(p), polish=None if pol is None else pol.record,
        rival_search=rival_record,
    )
