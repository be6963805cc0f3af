"""The up direction of an unlevelled scan from its own geometry (a minegeo addition).

Why
---
minegeo's levelled machinery (2-point heading + translation RANSAC and the whole-map
correlative 4-DOF search, :mod:`minegeo.localize.correlative`) needs the scan's z axis to be
up. A SLAM frame is usually the first sensor pose, tilted arbitrarily. A mine drift says
where up is through its shape: a flat floor, vertical walls, an arched roof. This module
estimates ``up`` in the scan frame from those cues, says how sure it is, and says what it
*cannot* know: on a straight ramp the floor is tilted about the drift's cross axis by the
unknown slope, so it also returns the residual-tilt range to search.

What each cue fixes (``a`` drift axis, ``c = up x a_h`` its horizontal cross axis, slope ``s``)
------------------------------------------------------------------------------------------------
Write a small error of ``up`` as a rotation ``(delta_along, delta_across)``: ``delta_along``
about ``c`` (tilts up towards the drift axis), ``delta_across`` about the drift axis.

=======================================  ======================  ======================================
cue                                      fixes ``delta_across``  fixes ``delta_along``
=======================================  ======================  ======================================
floor normal ``f = cos s up - sin s a_h``  yes (``f . c = 0``)     only if the floor is level (``s = 0``)
walls, straight drift (normals ``+-c``)  yes (``n . up = 0``)    no
walls of a curve, junction or face       yes                     yes, whatever the slope
drift axis ``a`` (normals are ``_|_ a``)  no                      only if the drift is level
=======================================  ======================  ======================================

So on a straight ramp nothing in the scan gives the slope: ``up`` is known up to a rotation
of the floor normal about ``c`` by ``s``; this module returns the floor-based estimate (the
level hypothesis), its statistical uncertainty, and the search range
``R(c, theta) up, theta in tilt_range_deg`` that contains the truth for slopes up to
``GravityParams.max_slope_deg``. Where the walls also fix ``delta_along`` (curves, junctions)
their own estimate is reported (``evidence.walls_slope_deg``, candidate ``"walls"``) but not
used: on rough rock it is off by several degrees (docs/localization.md).

Method
------
1. Area-uniform sample: at most ``max_points`` points drawn with probability inversely
   proportional to the local density (neighbours within ``density_radius_m``), in a canonical
   order (distance to the exactly summed centroid), so the result does not depend on the
   order of the points; PCA normals (:func:`minegeo.geometry.estimate_normals`).
2. Floor detection (no prior on up): the modes of the area density of the normals
   (:func:`minegeo.localize._kernels_gravity.normal_density`) that look like floors or walls
   are scored by the floor signature (:func:`_column_score`: flat below, arched above); the
   best is the floor, its sign from the arched roof.
3. Floor refinement: iteratively reweighted total least squares of the floor points, Tukey
   weights on the height residual (scale 7 MAD, at most ``floor_residual_scale_m``) and on
   the normal's tilt (``floor_max_tilt_deg``).
4. Walls: surfels above the floor whose normal is within ``wall_max_tilt_deg`` of horizontal
   (Tukey weights, scale 7 MAD of ``n . up``); Gauss-Newton on ``sum w (n . up)^2`` over
   ``delta_across`` (and, as evidence only, over both components when the wall normals spread
   in azimuth, ``min_wall_spread``).
5. Uncertainty: delete-one-block jackknife over ``n_blocks`` slices along the drift axis
   (rough rock is spatially correlated, so per-point least-squares covariances would be far
   too small): ``Sigma = (g - 1) / g sum_k (d_k - d_bar)(d_k - d_bar)^T``. The floor and wall
   estimates are fused with their jackknife covariances (information-weighted) and the fused
   estimator is jackknifed again. The 95 % region uses Hotelling's T^2 with ``g - 1`` degrees
   of freedom: ``r^2 = 2 (g - 1) / (g - 2) F_{2, g-2}(0.95)`` (12.0 for g = 8).

All angles in this module's results are in degrees unless the name says ``rad``; every vector
is in the frame of the input points (the *scan* frame).

Modules: this one holds :func:`estimate_up` (steps 1 and the assembly of the result); the floor and
wall cues, jackknife and fusion (steps 2-5) are in :mod:`minegeo.localize.gravity_cues`, the result
types and :func:`levelling_rotation` in :mod:`minegeo.localize.gravity_result` (importable here).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import InputError, TooFewPointsError
from minegeo.geometry.neighbors import NeighborIndex
from minegeo.geometry.normals import STATUS_OK, NormalParams, estimate_normals
from minegeo.localize import _kernels_gravity as KG
from minegeo.localize.gravity_cues import (
    _basis,
    _block_replicates,
    _drift_axis,
    _Floor,
    _floor,
    _from_tangent,
    _fuse,
    _Fusion,
    _no_floor_reason,
    _normal_modes,
    _Walls,
    _walls,
    _walls_alone,
    _WallsAlone,
)
from minegeo.localize.gravity_result import (
    STATUSES,
    UpCandidate,
    UpEstimate,
    UpEvidence,
    UpStatus,
    hotelling_r2_95,
    levelling_rotation,
)
from minegeo.localize.params import GravityParams

__all__ = ["GravityParams", "UpCandidate", "UpEvidence", "UpEstimate", "UpStatus", "estimate_up", "levelling_rotation",
           "hotelling_r2_95", "STATUSES"]

log = logging.getLogger(__name__)
_MIN_TOL_DEG = 1e-3  # floor of tilt_tolerance_deg (noise-free inputs give a zero jackknife spread)


# ---------------------------------------------------------------------------------------------- main

def _prepare(points, normals, p: GravityParams):
    """Validated points, area-uniform sample Q with weights W and unit normals N (canonical order)."""
    pts = as_points(points, "points", min_points=1)
    n = pts.shape[0]
    if n < p.min_points:
        raise TooFewPointsError(f"points has {n} point(s); estimating up needs at least {p.min_points}")
    nrm = None
    if normals is not None:
        nrm = as_points(normals, "normals", min_points=1)
        if nrm.shape[0] != n:
            raise InputError(f"normals must have one row per point ({n}), got {nrm.shape[0]}")
        ln = np.linalg.norm(nrm, axis=1)
        if np.any(ln < 0.5) or np.any(ln > 1.5):
            raise InputError("normals must be unit vectors (some rows have length < 0.5 or > 1.5)")
        nrm = nrm / ln[:, None]
    # canonical order: squared distance to the exactly summed centroid (independent of row order)
    cen = np.array([math.fsum(pts[:, k]) / n for k in range(3)])
    X = pts - cen
    d2 = np.einsum("ij,ij->i", X, X)
    order = np.lexsort((X[:, 2], X[:, 1], X[:, 0], d2))
    pts_c = np.ascontiguousarray(X[order])
    nrm_c = None if nrm is None else np.ascontiguousarray(nrm[order])
    cnt = NeighborIndex(pts_c).radius_counts(pts_c, p.density_radius_m).astype(np.float64)
    area = 1.0 / np.maximum(cnt, 1.0)
    valid = np.ones(n, dtype=bool)
    if nrm_c is None:
        nr = estimate_normals(pts_c, NormalParams(radius_m=p.normal_radius_m, max_nn=p.normal_max_nn),
                              orient_towards="none")
        nrm_c = nr.normals
        valid = nr.status == STATUS_OK
    if n > p.max_points:
        rng = np.random.default_rng(p.seed)
        pr = area / area.sum()
        pick = np.sort(rng.choice(n, size=p.max_points, replace=False, p=pr))
        Q, N, ok = pts_c[pick], nrm_c[pick], valid[pick]
        W = np.full(pick.size, 1.0)
    else:
        Q, N, ok, W = pts_c, nrm_c, valid, area.copy()
    W = np.where(ok, W, 0.0)
    if not W.sum() > 0:
        raise InputError("no usable normals: the cloud has no planar neighbourhoods")
    W = W / W.sum()
    return np.ascontiguousarray(Q), np.ascontiguousarray(N), np.ascontiguousarray(W), cen


def _failed(reason: str, p: GravityParams, cands=(), timings=None) -> UpEstimate:
    return UpEstimate(status=UpStatus.FAILED, reason=reason, up=None, tangent_basis=None, covariance_rad2=None,
                      covariance_3d_rad2=None, sigma_deg=math.nan, cone95_deg=math.nan, r95_squared=math.nan,
                      tilt_axis=None, tilt_range_deg=(math.nan, math.nan), tilt_tolerance_deg=math.nan,
                      candidates=tuple(cands), evidence=None, params=p, timings_s=dict(timings or {}))


def _evidence(Q: np.ndarray, W: np.ndarray, N: np.ndarray, up: np.ndarray, fl: _Floor, walls: _Walls,
              wa: _WallsAlone, r_floor: np.ndarray, ta2: np.ndarray, tc2: np.ndarray, ratio: float,
              g_eff: int) -> UpEvidence:
    """What the estimate rests on (floor and wall fit quality, axes, rival ratio)."""
    cu = N @ up
    ww = walls.weights if walls.weights is not None else np.zeros_like(W)
    wsum = float(ww.sum())
    vert = math.degrees(math.sqrt(float(ww @ np.arcsin(np.clip(cu, -1, 1)) ** 2) / wsum)) if wsum > 0 else math.nan
    fsum = float(fl.weights.sum())
    frms = math.sqrt(float(fl.weights @ r_floor ** 2) / fsum) if fsum > 0 else math.nan
    return UpEvidence(floor_fraction=float(fl.mass), floor_score=float(fl.score), void_fraction=float(fl.void),
                      floor_normal=fl.f.copy(), floor_rms_m=frms, wall_fraction=float(W[ww > 0].sum()),
                      wall_verticality_rms_deg=vert, wall_spread=walls.spread, walls_slope_deg=wa.slope_deg,
                      walls_slope_sigma_deg=wa.slope_sigma_deg, drift_axis=ta2.copy(), cross_axis=tc2.copy(),
                      rival_ratio=ratio, n_points_used=int(Q.shape[0]), n_blocks=g_eff)


def _candidates(up: np.ndarray, fl: _Floor, fu: _Fusion, sig: float, wa: _WallsAlone, spread: float,
                cands: list) -> list:
    """The estimate, the floor (level) hypothesis, the walls' (if any) and the rival modes."""
    f = fl.f
    out_c = [UpCandidate(up=up.copy(), source="estimate", score=float(fl.score), sigma_deg=sig,
                         note="floor (level hypothesis) and walls (across the drift)"),
             UpCandidate(up=f.copy(), source="floor", score=float(fl.score),
                         sigma_deg=math.degrees(math.sqrt(float(np.linalg.eigvalsh(fu.S_f)[-1]))),
                         note=f"floor normal alone: up if the floor is level (slab {fl.mass:.3f} of the area, "
                              f"{fl.void:.3f} above it)")]
    if wa.up is not None:
        out_c.append(UpCandidate(up=wa.up.copy(), source="walls", score=math.nan, sigma_deg=wa.sigma_deg,
                                 note=f"walls alone (seen in several directions, spread {spread:.2f}): "
                                      f"floor slope {wa.slope_deg:.1f} +- {wa.slope_sigma_deg:.1f} deg relative to them"))
    out_c += [c for c in cands if abs(float(c.up @ f)) < math.cos(math.radians(1.0))]
    return out_c


def _search_region(S: np.ndarray, g_eff: int, p: GravityParams) -> tuple:
    """1-sigma angle, 95 % cone, Hotelling ``r95^2``, residual-tilt range and tube half-width (deg).

    ``S`` is the fused jackknife covariance of ``(delta_along, delta_across)`` (rad^2) over
    ``g_eff`` blocks; returns ``(sigma, cone95, r95_squared, lo, hi, tolerance)``.
    """
    lam_max = float(np.linalg.eigvalsh(S)[-1])
    r2 = hotelling_r2_95(g_eff)
    sig = math.degrees(math.sqrt(max(lam_max, 0.0)))
    cone = math.degrees(math.sqrt(r2 * max(lam_max, 0.0)))
    kk = math.sqrt(r2)
    sa = math.degrees(math.sqrt(max(S[0, 0], 0.0)))
    sc = math.degrees(math.sqrt(max(S[1, 1], 0.0)))
    lo, hi = -p.max_slope_deg - kk * sa, p.max_slope_deg + kk * sa
    tol = max(kk * sc, _MIN_TOL_DEG)
    return sig, cone, r2, lo, hi, tol


def _status(up: np.ndarray, rivals: list, ratio: float, fl: _Floor, sig: float, p: GravityParams) -> tuple[UpStatus, str]:
    """``("ambiguous", why)`` when a distinct rival floor scores ``ambiguity_ratio`` of the floor's, else ``ok``."""
    if rivals and ratio >= p.ambiguity_ratio:
        r_ang = math.degrees(math.acos(min(1.0, float(rivals[0][1] @ up))))
        status, reason = UpStatus.AMBIGUOUS, (f"a second floor candidate {r_ang:.0f} deg away scores {ratio:.2f} of the "
                                       f"floor's (need < {p.ambiguity_ratio:g}); both are in candidates")
    else:
        status = UpStatus.OK
        reason = (f"floor {fl.mass:.0%} of the scan, up 1-sigma {sig:.2f} deg if the floor is level; "
                  f"a ramp of up to {p.max_slope_deg:g} deg is within tilt_range_deg")
    return status, reason


def estimate_up(points, normals=None, params: GravityParams | None = None) -> UpEstimate:
    """Estimate the up direction of a mine-drift scan from its floor and walls.

    Parameters
    ----------
    points : (n, 3) array_like of float
        The scan in its own frame (m), any orientation.
    normals : (n, 3) array_like of float, optional
        Unit normals of ``points`` (any sign). Default: PCA normals within
        ``params.normal_radius_m``.
    params : GravityParams, optional

    Returns
    -------
    UpEstimate
        ``up`` (scan frame), its covariance and 95 % cone under the level-floor hypothesis
        (or the walls' when they fix it), the residual-tilt search for ramps, the candidates
        and the evidence; ``status`` ``failed`` when the scan shows no floor (a lone plane, a
        vertical shaft, no void side) and ``ambiguous`` when a distinct rival floor scores
        almost as well (e.g. a flat roof as large as the floor).

    Raises
    ------
    InputError
        NaN/inf, wrong shapes, normals that are not unit vectors, bad parameters.
    TooFewPointsError
        Fewer than ``params.min_points`` points.

    Notes
    -----
    Deterministic: the same points (in any order) and ``params.seed`` give the same result;
    rotating the points rotates ``up`` (exactly up to floating point when the cloud has at
    most ``max_points`` points and the plane detection picks the same floor).
    """
    p = GravityParams() if params is None else params
    if not isinstance(p, GravityParams):
        raise InputError(f"params must be a GravityParams, got {type(p).__name__}")
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    Q, N, W, _ = _prepare(points, normals, p)
    timings["sample_and_normals"] = time.perf_counter() - t0

    # ---- floor detection: modes of the normals, each scored by the floor signature
    t1 = time.perf_counter()
    modes = _normal_modes(Q, W, N, p)
    timings["floor_detection"] = time.perf_counter() - t1
    cands = [UpCandidate(up=m[1].copy(), source="mode", score=float(m[0]), sigma_deg=math.nan,
                         note=f"normal mode; {m[2]:.0%} of the area in columns spanning a drift height")
             for m in modes]
    if not modes or modes[0][0] < p.min_floor_score:
        return _failed(_no_floor_reason(modes, p), p, cands, timings)
    fl, why = _floor(Q, W, N, modes, p)
    if fl is None:
        return _failed(why, p, cands, timings)
    f = fl.f

    # ---- drift axis and walls
    t2 = time.perf_counter()
    r_floor = Q @ f - fl.d
    axis = _drift_axis(Q, W, f)
    ta, tc = _basis(f, axis)
    walls = _walls(Q, W, N, r_floor, f, axis, p)
    timings["floor_and_walls"] = time.perf_counter() - t2

    # ---- jackknife over blocks along the drift, fusion
    t3 = time.perf_counter()
    rep_f, rep_w, rep_wa = _block_replicates(Q, W, N, fl, walls, axis, ta, tc, p)
    good = np.all(np.isfinite(rep_f), axis=1)
    if np.count_nonzero(good) < 4:
        return _failed("the floor is too small to estimate its uncertainty (fewer than 4 jackknife blocks hold it)",
                       p, cands, timings)
    fu = _fuse(rep_f, rep_w, good, walls.fit, f, ta, tc)
    S, g_eff = fu.S, fu.g_eff
    wa = _walls_alone(walls.fit_along, rep_wa, f, ta, tc)
    timings["jackknife"] = time.perf_counter() - t3

    up = _from_tangent(f, ta, tc, fu.d_hat)
    ta2, tc2 = _basis(up, axis)
    B = np.vstack([ta2, tc2])
    sig, cone, r2, lo, hi, tol = _search_region(S, g_eff, p)

    # ---- evidence, candidates, status
    rivals = [m for m in modes[1:] if math.degrees(math.acos(min(1.0, float(m[1] @ up)))) > p.min_rival_angle_deg]
    ratio = float(rivals[0][0] / fl.score) if rivals else 0.0
    ev_ = _evidence(Q, W, N, up, fl, walls, wa, r_floor, ta2, tc2, ratio, g_eff)
    out_c = _candidates(up, fl, fu, sig, wa, walls.spread, cands)
    status, reason = _status(up, rivals, ratio, fl, sig, p)
    timings["total"] = time.perf_counter() - t0
    log.debug("estimate_up: %s (%s)", status, reason)
    return UpEstimate(status=status, reason=reason, up=up, tangent_basis=B, covariance_rad2=S,
                      covariance_3d_rad2=B.T @ S @ B, sigma_deg=sig, cone95_deg=cone, r95_squared=r2,
                      tilt_axis=tc2.copy(), tilt_range_deg=(float(lo), float(hi)), tilt_tolerance_deg=float(tol),
                      candidates=tuple(out_c), evidence=ev_, params=p, timings_s=timings)


def _warmup() -> None:
    KG._warmup()
