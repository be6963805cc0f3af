"""The gravity fallback of :func:`~minegeo.localize.localize_scan` (``LocalizeParams.gravity_fallback``).

A 6-DOF scan that the pipeline cannot place (``failed``, or ``ambiguous``) is levelled by its own
up estimate (:func:`~minegeo.localize.gravity.estimate_up`: floor, roof, walls) and localized
again with the levelled machinery (2-point heading + translation RANSAC and the whole-map
correlative search). With ``R`` the levelling rotation (``p_lev = R p_scan``,
:func:`~minegeo.localize.gravity.levelling_rotation`) and the levelled run's ``T_map_lev``:
``T_map_scan = T_map_lev · [R | 0]``. The covariance (map axes, about the scan origin, which
``R`` fixes) and the placed trajectory (map frame) carry over unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from minegeo.errors import MinegeoError
from minegeo.io.types import PointCloud, Trajectory
from minegeo.localize._progress import ProgressFn, announce
from minegeo.localize.gravity import estimate_up, levelling_rotation
from minegeo.localize.gravity_result import _rotate
from minegeo.localize.params import LocalizeParams
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.result import LocalizationResult
from minegeo.localize.scan import scan_points
from minegeo.registration.ransac import hypothesis_distance

__all__ = ["gravity_fallback", "tilt_schedule", "six_dof_rival", "rebase"]

log = logging.getLogger(__name__)

#: One localization attempt: ``attempt(prepared_map, scan_cloud, trajectory, params, seed, progress)``.
Attempt = Callable[..., LocalizationResult]


def tilt_schedule(est, tilt: float) -> tuple[list[float], float, float]:
    """Residual tilts (deg) of the levelled attempts and the estimate's tilt range ``(lo, hi)``.

    A straight ramp's floor is tilted about the drift's cross axis by the unknown slope: up is
    rotated about ``est.tilt_axis`` by 0, ±2 tilt, ±4 tilt, ... within ``est.tilt_range_deg``
    widened by ``tilt``.
    """
    thetas = [0.0]
    lo, hi = (float(est.tilt_range_deg[0]), float(est.tilt_range_deg[1])) if est.tilt_axis is not None else (0.0, 0.0)
    k = 1
    while 2.0 * tilt * k <= max(-lo, hi) + tilt:
        for sgn in (1.0, -1.0):
            th = sgn * 2.0 * tilt * k
            if lo - tilt <= th <= hi + tilt:
                thetas.append(th)
        k += 1
    return thetas, lo, hi


def _levelled_inputs(scan_cloud, P_raw: np.ndarray, org: np.ndarray, trajectory, R: np.ndarray, R4: np.ndarray):
    """The scan and its trajectory re-expressed in the levelled frame (a rotation about the scan
    frame's origin)."""
    if isinstance(scan_cloud, PointCloud):
        cloud_l = PointCloud(points=P_raw @ R.T, origin=R @ org)
    else:
        cloud_l = np.ascontiguousarray(P_raw @ R.T)
    traj_l = trajectory
    if isinstance(trajectory, Trajectory):
        traj_l = replace(trajectory, poses=np.einsum("ij,njk->nik", R4, np.asarray(trajectory.poses)),
                         origin=R @ np.asarray(trajectory.origin, dtype=np.float64))
    return cloud_l, traj_l


@dataclass(frozen=True)
class _Levelled:
    """The levelled attempts: the last result, its ``R4`` (``p_lev = R4 p``), per attempt its tilt,
    status and reason, and seconds."""

    res: LocalizationResult
    R4: np.ndarray
    attempts: list
    attempt_s: list


def _levelled_attempts(attempt: Attempt, pm: PreparedMap, scan_cloud, scan_xyz: tuple, trajectory,
                       p: LocalizeParams, seed: int, progress, est, tilt: float, thetas: list) -> _Levelled:
    """Localize the levelled scan at each residual tilt in turn; the first non-failed wins.
    ``scan_xyz`` is :func:`~minegeo.localize.scan.scan_points` of ``scan_cloud``."""
    P_raw, org = scan_xyz
    p_l = replace(p, ransac=replace(p.ransac, model="levelled", ransac_n=2, max_tilt_deg=min(90.0, tilt),
                                    normal_angle_threshold_rad=None), gravity_fallback=None)
    attempts: list[dict] = []
    attempt_s: list[float] = []  # seconds per levelled attempt -> timings_s["gravity_attempt_k"]
    res_l = R4 = None
    for th in thetas:
        up = np.asarray(est.up, dtype=np.float64)
        if th != 0.0:
            ax = np.asarray(est.tilt_axis, dtype=np.float64)
            up = _rotate(up, ax / np.linalg.norm(ax), math.radians(th))  # up tilted about the cross axis
        R = levelling_rotation(up)
        R4 = np.eye(4)
        R4[:3, :3] = R
        cloud_l, traj_l = _levelled_inputs(scan_cloud, P_raw, org, trajectory, R, R4)
        res_l = attempt(pm, cloud_l, traj_l, p_l, seed, progress)
        attempts.append({"tilt_about_cross_axis_deg": th, "status": res_l.status, "reason": res_l.reason})
        attempt_s.append(float(res_l.timings_s.get("total", math.nan)))
        if res_l.status != "failed":
            break
    return _Levelled(res=res_l, R4=R4, attempts=attempts, attempt_s=attempt_s)


def _keep_6dof(res_6dof: LocalizationResult, rec: dict, lev: _Levelled, t0: float, warning: str) -> LocalizationResult:
    """The 6-DOF result, with the fallback's record, times and a warning."""
    res_6dof.timings_s["gravity"] = time.perf_counter() - t0
    res_6dof.timings_s.update({f"gravity_attempt_{k}": v for k, v in enumerate(lev.attempt_s)})
    res_6dof.warnings.append(warning)
    return replace(res_6dof, gravity=rec)


def gravity_fallback(pm: PreparedMap, scan_cloud, trajectory, p: LocalizeParams, seed: int,
                     progress: ProgressFn | None, res_6dof: LocalizationResult,
                     attempt: Attempt) -> LocalizationResult:
    """``LocalizeParams.gravity_fallback``: level a failed (or ambiguous) 6-DOF scan by its own up
    estimate and localize it again with ``attempt`` (one pass of the pipeline) in the levelled
    frame; the result in the original scan frame (module docstring). An ambiguous 6-DOF result is
    replaced only by an ``ok`` that none of the 6-DOF run's own verified placements rivals."""
    t0 = time.perf_counter()
    P_raw, org = scan_points(scan_cloud)
    announce(progress, "gravity")
    try:
        est = estimate_up(P_raw + org, params=p.gravity_fallback.estimate)
    except MinegeoError as e:  # too few points for the estimate: keep the 6-DOF answer
        log.debug("gravity fallback: no up estimate (%s)", e)
        return res_6dof
    t_est = time.perf_counter() - t0
    rec = {"status": est.status, "reason": est.reason, "cone95_deg": float(est.cone95_deg),
           "up_scan": None if est.up is None else np.asarray(est.up).tolist()}  # no times in the record (equal inputs, equal record): see timings_s
    if est.status != "ok" or est.up is None:
        res_6dof.timings_s["gravity"] = t_est
        res_6dof.warnings.append(f"gravity fallback not tried: up estimate {est.status} ({est.reason})")
        return res_6dof
    tilt = max(float(p.gravity_fallback.tilt_deg), float(est.cone95_deg)) if math.isfinite(est.cone95_deg) \
        else float(p.gravity_fallback.tilt_deg)
    thetas, lo, hi = tilt_schedule(est, tilt)
    lev = _levelled_attempts(attempt, pm, scan_cloud, (P_raw, org), trajectory, p, seed, progress, est, tilt,
                             thetas)
    res_l, R4 = lev.res, lev.R4
    rec.update({"levelled_status": res_l.status, "levelled_reason": res_l.reason, "tilt_tolerance_deg": tilt,
                "R_levelled_scan": R4[:3, :3].tolist(), "attempts": lev.attempts,
                "tilt_range_deg": [lo, hi], "six_dof_status": res_6dof.status})
    if res_6dof.status == "ambiguous" and res_l.status != "failed":
        # an ambiguous 6-DOF result is replaced only by an ``ok`` that none of the 6-DOF run's own
        # verified placements rivals (the same two-level test, against the levelled answer)
        rival = six_dof_rival(res_6dof, rebase(res_l, R4), p, P_raw.mean(axis=0) + org) if res_l.status == "ok" else None
        if res_l.status != "ok" or rival is not None:
            why = (f"the levelled search says {res_l.status}" if res_l.status != "ok" else
                   f"its answer has a rival among the 6-DOF placements ({rival})")
            return _keep_6dof(res_6dof, rec, lev, t0, f"gravity fallback: levelled by the scan's own up estimate; "
                                                      f"{why}: the result stays ambiguous")
    if res_l.status == "failed":
        return _keep_6dof(res_6dof, rec, lev, t0,
                          f"gravity fallback: levelled by the scan's own up estimate (95 % cone "
                          f"{est.cone95_deg:.1f} deg; residual tilts {', '.join(f'{a:g}' for a in thetas)} "
                          f"deg tried), the levelled search failed too ({res_l.reason})")
    out = rebase(res_l, R4)
    out.timings_s["gravity"] = t_est
    out.timings_s.update({f"gravity_attempt_{k}": v for k, v in enumerate(lev.attempt_s)})
    out.timings_s["six_dof_attempt"] = float(res_6dof.timings_s.get("total", math.nan))
    out.timings_s["total"] = time.perf_counter() - t0 + float(res_6dof.timings_s.get("total", 0.0))
    first = "found no placement" if res_6dof.status == "failed" else "could not tell places apart"
    out.warnings.insert(0, f"the 6-DOF search {first} ({res_6dof.reason}); this result levels the scan "
                           f"by its own up direction (floor/roof/walls, 95 % cone {est.cone95_deg:.1f} deg) and "
                           f"searches heading and position (tilt tolerance {tilt:.1f} deg, residual tilt "
                           f"{lev.attempts[-1]['tilt_about_cross_axis_deg']:g} deg about the drift's cross axis)")
    return replace(out, gravity=rec)


def six_dof_rival(res_6dof, res_ok, p: LocalizeParams, centre: np.ndarray) -> str | None:
    """A verified placement of the 6-DOF run that is a rival of ``res_ok``'s answer (both in the
    original scan frame; ``centre`` the scan's centroid in that frame), by the pipeline's
    two-level plane test; None when there is none."""
    hyps_ok = res_ok.hypotheses or []
    if not hyps_ok:
        return "no verified placement"
    pf_a, pff_a = float(hyps_ok[0]["plane_fitness"]), float(hyps_ok[0].get("fine_fitness", hyps_ok[0]["plane_fitness"]))
    amb, fine = p.ambiguity.ratios(res_ok.n_scan_down < int(p.ambiguity.small_scan_below_points))
    for h in res_6dof.hypotheses or []:
        if "screened out" in h["source"]:
            continue
        dist, ang = hypothesis_distance(res_ok.T_map_scan, h["T_map_scan"], centre)
        if dist <= p.ambiguity.distance_m and ang <= p.ambiguity.angle_deg:
            continue
        pff = float(h.get("fine_fitness", h["plane_fitness"]))
        if float(h["plane_fitness"]) >= amb * pf_a and pff >= fine * pff_a:
            return (f"{dist:.1f} m / {ang:.1f} deg away, plane fitness {h['plane_fitness']:.3f} vs {pf_a:.3f}, fine "
                    f"agreement {pff:.3f} vs {pff_a:.3f}")
    return None


def rebase(res, R4: np.ndarray):
    """A levelled-frame result expressed for the original scan frame: every ``T_*_scan`` pose
    (the answer, the hypotheses, the rival search) right-multiplied by ``R4`` (``p_lev = R4 p``)."""
    def conv(obj, key=""):
        if isinstance(obj, dict):
            return {k: conv(v, k) for k, v in obj.items()}
        if isinstance(obj, list):
            return [conv(v, key) for v in obj]
        if key.startswith("T_") and key.endswith("_scan") and obj is not None:
            a = np.asarray(obj, dtype=np.float64)
            if a.shape == (4, 4):
                return a @ R4
        return obj

    kw = {}
    for f in ("T_map_scan", "T_geo_scan", "T_crs_scan", "ransac_T_map_scan"):
        v = getattr(res, f, None)
        if v is not None:
            kw[f] = np.asarray(v, dtype=np.float64) @ R4
    kw["hypotheses"] = conv(res.hypotheses) if res.hypotheses is not None else None
    if getattr(res, "rival_search", None) is not None:
        kw["rival_search"] = conv(res.rival_search)
    return replace(res, **kw)
