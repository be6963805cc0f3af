"""Stage 3 of :func:`~minegeo.localize.localize_scan`: ICP of the hypotheses and their verification.

Every placement the pipeline considers (RANSAC's, the correlative search's, the rival search's)
goes through the same refinement (ICP, Sec. 2.4, [Baek2022 Eqs. 10-16]; GICP selectable) and
the same score, the point-to-plane agreement of :func:`verify`. This module holds that shared
machinery (:class:`VerifyContext`: the map target, the tolerances, the ICP settings and the
memo of fits already computed) and the stages built on it:

* :func:`coarse_pull_in`: a wide-gate point-to-plane ICP of the feature-level scan (minegeo);
* :func:`screen`: a capped ICP of a thinned feature-level scan, to rank many hypotheses cheaply;
* :func:`refine_candidates`: the full-resolution ICP of the leaders, verified;
* :func:`polish`: the tight-gate point-to-plane ICP of the chosen placement (minegeo).

All placements map the origin-subtracted scan ``D`` into the map's ``work`` frame
(:mod:`minegeo.localize.scan`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from pykdtree.kdtree import KDTree

from minegeo.geometry.se3 import invert, log_so3
from minegeo.localize.params import LocalizeParams
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.scan import ScanFeatures
from minegeo.registration.gicp import GICPParams, register_gicp
from minegeo.registration.icp import ICPParams, register_icp
from minegeo.registration.ransac import hypothesis_distance

__all__ = ["VerifyContext", "Candidate", "Refined", "Screening", "Polish", "verify", "surface_noise_m",
           "verify_context", "refine", "distinct", "coarse_pull_in", "screen", "refine_candidates", "polish",
           "STAGE_STEP_M", "STAGE_STEP_RAD"]

#: Step test of minegeo's own ICP stages (coarse pull-in, screening, polish): stop once an
#: update moves less than 0.1 mm and 1e-5 rad (see ``ICPParams.step_translation_m``).
STAGE_STEP_M, STAGE_STEP_RAD = 1e-4, 1e-5

log = logging.getLogger(__name__)


class Candidate(NamedTuple):
    """One hypothesis before ICP: ``T`` maps ``D`` into ``work``; RANSAC's fitness and inlier RMSE
    (m; the correlative search's refined score and NaN for its candidates)."""

    name: str
    T: np.ndarray
    fitness: float
    rmse_m: float


class Refined(NamedTuple):
    """A hypothesis after ICP and verification (``ic``: the ICP result; ``pf``, ``prm``, ``pff``:
    :func:`verify`'s plane fitness, plane RMSE (m) and fine fitness at ``ic.T_target_source``)."""

    name: str
    T0: np.ndarray
    fitness: float
    rmse_m: float
    ic: object
    pf: float
    prm: float
    pff: float


@dataclass(frozen=True)
class VerifyContext:
    """What every refinement and score of one localization shares (built by :func:`verify_context`).

    Attributes
    ----------
    p : LocalizeParams
    scan : ScanFeatures
    Qf, Nf : (m, 3) ndarray
        The map's ICP cloud and its normals (work frame).
    tree : KDTree
        Over ``Qf``.
    gate : float
        ICP pair gate and verification gate, m (``icp.max_correspondence_m``).
    tol, tol_fine : float, float or None
        Plane and fine tolerances of :func:`verify`, m (widened by the scan's noise).
    scan_noise : float
        The scan's surface noise ``σ_surf`` (m; NaN when not measured).
    amb_ratio, fine_ratio : float
        The ambiguity ratios at the two tolerances (the small scan's when ``scan.small_scan``).
    D_screen : (k, 3) ndarray
        Feature-level points of the screening ICP (at most ``icp.screen_max_points``).
    icp_p, icp_screen : ICPParams or None
        Full-resolution and screening ICP settings (point-to-point / point-to-plane).
    gicp_p, gicp_cov, gicp_index : optional
        GICP settings and the map's plane covariances and index (``icp.method == "gicp"``).
    memo : dict
        ICP results already computed, by (stage, candidate name, initial pose bytes).
    """

    p: LocalizeParams
    scan: ScanFeatures
    Qf: np.ndarray
    Nf: np.ndarray
    tree: object
    gate: float
    tol: float
    tol_fine: float | None
    scan_noise: float
    amb_ratio: float
    fine_ratio: float
    D_screen: np.ndarray
    icp_p: ICPParams | None = None
    icp_screen: ICPParams | None = None
    gicp_p: GICPParams | None = None
    gicp_cov: object = None
    gicp_index: object = None
    memo: dict = field(default_factory=dict)


def icp_params(p: LocalizeParams) -> ICPParams:
    """The paper's ICP (Table 3 gate, iterations and convergence; ``p.icp.method``)."""
    return ICPParams(max_correspondence_distance_m=float(p.icp.max_correspondence_m),
                     max_iterations=int(p.icp.max_iterations), relative_fitness=float(p.icp.relative_fitness),
                     relative_rmse=float(p.icp.relative_rmse), method=p.icp.method,
                     degeneracy_ratio_threshold=float(p.verify.degeneracy_ratio) if p.verify.degeneracy_ratio > 0 else 1e-12)


def plane_icp_params(gate_m: float, p: LocalizeParams) -> ICPParams:
    """Point-to-plane ICP settings of minegeo's extra stages (coarse pull-in, polish): the given
    gate, the paper's iteration cap, 1e-6 convergence or a step below ``STAGE_STEP_M`` /
    ``STAGE_STEP_RAD``, no degeneracy verdict (the decision's)."""
    return ICPParams(max_correspondence_distance_m=float(gate_m), max_iterations=int(p.icp.max_iterations),
                     relative_fitness=1e-6, relative_rmse=1e-6, method="point_to_plane",
                     degeneracy_ratio_threshold=1e-12, step_translation_m=STAGE_STEP_M,
                     step_rotation_rad=STAGE_STEP_RAD)


def verify(P: np.ndarray, T: np.ndarray, Q: np.ndarray, N: np.ndarray, tree, gate: float, tol: float,
           tol_fine: float | None = None):
    """Point-to-plane agreement of a placement: ``(plane_fitness, plane_rmse_m, fine_fitness)``.

    ``plane_fitness`` = fraction of the scan points whose nearest map point is within ``gate``
    **and** whose distance to that point's tangent plane, ``|(R p + t − q)·n_q|``, is below
    ``tol``; ``plane_rmse_m`` = RMS of those plane distances over the pairs within ``gate``.
    Unlike the point-to-point fitness it is not blurred by the map's point spacing.
    ``fine_fitness``: the same fraction with ``tol_fine`` (``plane_fitness`` when None;
    ``LocalizeParams.verify.fine_tolerance_m``).
    """
    X = P @ T[:3, :3].T + T[:3, 3]
    dist, idx = tree.query(X, k=1, distance_upper_bound=gate)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    m = idx < Q.shape[0]
    if not m.any():
        return 0.0, math.nan, 0.0
    j = idx[m]
    r = np.abs(np.einsum("ij,ij->i", X[m] - Q[j], N[j]))
    pf = float(np.count_nonzero(r < tol)) / P.shape[0]
    pff = pf if tol_fine is None else float(np.count_nonzero(r < tol_fine)) / P.shape[0]
    return pf, float(math.sqrt(float(np.mean(r * r)))), pff


def surface_noise_m(P: np.ndarray, k: int = 16, max_points: int = 20000) -> float:
    """Scan surface noise ``σ_surf`` (m): median of ``sqrt(λ_min)`` of the k-neighbour PCA ([Baek2022 Eq. 2]).

    Evaluated on an evenly strided subset of at most ``max_points`` points (deterministic);
    neighbours from the whole cloud. Independent of any placement in the map.
    """
    n = P.shape[0]
    if n < k + 1:
        return 0.0
    sub = P[:: max(1, n // max_points)]
    _, idx = KDTree(P).query(sub, k=k)
    N = P[np.asarray(idx, dtype=np.int64)]
    N = N - N.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", N, N) / k
    lam = np.linalg.eigvalsh(C)[:, 0]
    return float(np.median(np.sqrt(np.maximum(lam, 0.0))))


def _tolerances(p: LocalizeParams, scan_noise: float) -> tuple[float, float | None]:
    """Plane and fine tolerances of the verification (m), widened by the scan's noise
    (``verify.noise_factor``, ``verify.fine_noise_factor``)."""
    tol = float(p.verify.plane_tolerance_m)
    if p.verify.noise_factor > 0:
        tol = max(tol, float(p.verify.noise_factor) * scan_noise)
    tol_fine = None
    if p.verify.fine_tolerance_m is not None:
        tol_fine = float(p.verify.fine_tolerance_m)
        if p.verify.fine_noise_factor > 0 and math.isfinite(scan_noise):
            tol_fine = max(tol_fine, float(p.verify.fine_noise_factor) * scan_noise)
        tol_fine = min(tol_fine, tol)
    return tol, tol_fine


def verify_context(pm: PreparedMap, sf: ScanFeatures, p: LocalizeParams) -> VerifyContext:
    """The ICP settings, map target, tolerances and screening sample of one localization."""
    small_scan = sf.small_scan
    amb_ratio, fine_ratio = p.ambiguity.ratios(small_scan)
    kw: dict = {}
    if p.icp.method == "gicp":
        gicp_p = GICPParams(max_correspondence_distance_m=float(p.icp.max_correspondence_m),
                            max_iterations=int(p.icp.max_iterations),
                            degeneracy_ratio_threshold=float(p.verify.degeneracy_ratio) if p.verify.degeneracy_ratio > 0 else 1e-12)
        gicp_cov, gicp_index = pm.gicp_target(gicp_p)
        kw.update(gicp_p=gicp_p, gicp_cov=gicp_cov, gicp_index=gicp_index)
    else:
        icp_p = icp_params(p)
        # the screening (a minegeo stage) also stops once the pose stops moving, and after
        # icp_screen_max_iterations (not for a small scan: its rivals are decided on a narrower
        # margin, so an under-converged screen must not drop one); the full-resolution ICP
        # keeps the paper's convergence test
        icp_screen = replace(icp_p, step_translation_m=STAGE_STEP_M, step_rotation_rad=STAGE_STEP_RAD,
                             max_iterations=icp_p.max_iterations if small_scan else
                             min(icp_p.max_iterations, int(p.icp.screen_max_iterations)))
        kw.update(icp_p=icp_p, icp_screen=icp_screen)
    scan_noise = surface_noise_m(sf.icp_points) if p.verify.noise_factor > 0 else math.nan
    tol, tol_fine = _tolerances(p, scan_noise)
    # the screening ICP runs on at most icp_screen_max_points evenly spaced feature-level points
    # (a small scan: on all of them, as with the iteration cap)
    D = sf.feature_points
    n_scr = int(p.icp.screen_max_points)
    D_screen = D if small_scan or D.shape[0] <= n_scr else np.ascontiguousarray(
        D[np.unique(np.linspace(0, D.shape[0] - 1, n_scr).round().astype(np.int64))])
    return VerifyContext(p=p, scan=sf, Qf=pm.icp_points, Nf=pm.icp_normals, tree=pm.kdtree,
                         gate=float(p.icp.max_correspondence_m), tol=tol, tol_fine=tol_fine, scan_noise=scan_noise,
                         amb_ratio=amb_ratio, fine_ratio=fine_ratio, D_screen=D_screen, **kw)


def refine(ctx: VerifyContext, P_src: np.ndarray, T_init: np.ndarray, screening: bool = False):
    """The pipeline's ICP (or GICP) of ``P_src`` from ``T_init`` against the map's ICP cloud;
    ``screening``: the capped screening settings (ICP only)."""
    if ctx.gicp_p is not None:
        return register_gicp(P_src, ctx.Qf, T_init, ctx.gicp_p, target_covariances=ctx.gicp_cov,
                             target_index=ctx.gicp_index, check_target=False)
    return register_icp(P_src, ctx.Qf, T_init, ctx.icp_screen if screening else ctx.icp_p, target_normals=ctx.Nf,
                        target_index=ctx.tree, check_target=False)


def verify_at(ctx: VerifyContext, P: np.ndarray, T: np.ndarray):
    """:func:`verify` of ``P`` at ``T`` with the context's target and tolerances."""
    return verify(P, T, ctx.Qf, ctx.Nf, ctx.tree, ctx.gate, ctx.tol, ctx.tol_fine)


def refine_and_verify(ctx: VerifyContext, P: np.ndarray, T_init: np.ndarray, screening: bool = False):
    """``(icp_result, plane_fitness, plane_rmse_m, fine_fitness)`` of ``P`` refined from ``T_init``."""
    ic = refine(ctx, P, T_init, screening=screening)
    return (ic, *verify_at(ctx, P, ic.T_target_source))


def once(ctx: VerifyContext, stage: str, name: str, T: np.ndarray, fn: Callable):
    """ICP results of one candidate, computed once: the fallback re-evaluates RANSAC's
    candidates together with the correlative ones (deterministic, so reuse is exact)."""
    key = (stage, name, T.tobytes())
    if key not in ctx.memo:
        ctx.memo[key] = fn()
    return ctx.memo[key]


def distinct(Ta: np.ndarray, Tb: np.ndarray, centre: np.ndarray, p: LocalizeParams) -> bool:
    """Two placements are distinct hypotheses: the scan centroid moves more than
    ``ambiguity.distance_m`` or the rotation differs by more than ``ambiguity.angle_deg``."""
    dist, ang = hypothesis_distance(Ta, Tb, centre)
    return max(dist / p.ambiguity.distance_m, ang / p.ambiguity.angle_deg) > 1.0


def coarse_pull_in(ctx: VerifyContext, uniq: list) -> list[Candidate]:
    """Coarse pull-in (minegeo addition): RANSAC poses are often ~1 m off (4-DOF levelled
    hypotheses, 1 m voxels), beyond the 0.5 m ICP gate; a point-to-plane ICP of the feature-level
    scan with the wider gate ``icp.coarse_correspondence_m`` brings them into the fine ICP's basin
    first. Correlative candidates (already refined with gates down to 0.5 m) are kept as they are."""
    p, D = ctx.p, ctx.scan.feature_points
    if p.icp.coarse_correspondence_m is None or not uniq:
        return uniq
    coarse_p = plane_icp_params(p.icp.coarse_correspondence_m, p)
    return [Candidate(name, T0 if name.startswith("correlative") else once(
                ctx, "coarse", name, T0, lambda T0=T0: register_icp(D, ctx.Qf, T0, coarse_p, target_normals=ctx.Nf,
                                                                    target_index=ctx.tree,
                                                                    check_target=False).T_target_source),
                      rf, rrmse) for name, T0, rf, rrmse in uniq]


@dataclass(frozen=True)
class Screening:
    """Outcome of :func:`screen`: which candidates get the full-resolution ICP.

    Attributes
    ----------
    screened : list of tuple
        Per candidate ``(icp_result, plane_fitness, plane_rmse_m, fine_fitness)`` of the
        screening ICP (empty for a single candidate).
    fine_set : set of int
        Indices given the full-resolution ICP.
    same_place : set of int
        Indices dropped because the screening brought them onto a better-screened one.
    deferred : bool
        ``may_defer`` and the screening shows that this list cannot give an ``ok`` alone.
    """

    screened: list
    fine_set: set
    same_place: set
    deferred: bool = False


def screen(ctx: VerifyContext, uniq: list[Candidate], may_defer: bool) -> Screening:
    """The screening ICP of several candidates on the feature-level scan (cheap), and the short
    list for the full-resolution ICP: the leader and any candidate within the ambiguity ratio
    of its plane fitness, one per placement.

    ``may_defer``: the correlative fallback will follow if this list gives no ``ok``; when the
    screening already shows that it cannot (best screened plane fitness below
    ``verify.min_plane_fitness``) or that only the full-resolution ICP could separate distinct rivals,
    the result is ``deferred``: the fallback's evaluation refines the same candidates (memoised)
    if they still lead."""
    p = ctx.p
    if len(uniq) <= 1:
        return Screening(screened=[], fine_set={0} if uniq else set(), same_place=set())
    screened = [once(ctx, "screen", c[0], c[1], lambda T0=c[1]: refine_and_verify(ctx, ctx.D_screen, T0, True))
                for c in uniq]
    scores = [x[1] for x in screened]
    if may_defer and max(scores) < p.verify.min_plane_fitness:
        return Screening(screened=screened, fine_set=set(), same_place=set(), deferred=True)
    fine_set = {i for i, pf in enumerate(scores) if pf >= ctx.amb_ratio * max(scores)}
    fine_set.add(int(np.argmax(scores)))
    # candidates that the screening ICP brought to the same placement (within the
    # ambiguity distance and angle) are one hypothesis: only the best-screened of them
    # gets the full-resolution ICP (they could never be each other's rival)
    kept: list[int] = []
    for i in sorted(fine_set, key=lambda i: (-scores[i], i)):
        Ti = screened[i][0].T_target_source
        if all(distinct(Ti, screened[j][0].T_target_source, ctx.scan.centre, p) for j in kept):
            kept.append(i)
    same_place = fine_set - set(kept)
    fine_set = set(kept)
    log.debug("screened %d hypotheses: best plane fitness %.3f, %d distinct within ratio %.2f",
              len(scores), max(scores), len(fine_set), ctx.amb_ratio)
    # distinct rivals on the screen: the whole-map candidates may hold a clearly
    # better placement, and if they do not, the same rivals are refined there
    return Screening(screened=screened, fine_set=fine_set, same_place=same_place,
                     deferred=may_defer and len(fine_set) > 1)


def refine_candidates(ctx: VerifyContext, uniq: list[Candidate], scr: Screening) -> list[Refined]:
    """The full-resolution ICP and verification of the short-listed candidates; the others keep
    their screening scores (marked ``screened out`` in their name)."""
    refined = []
    for i, (name, T0, rf, rrmse) in enumerate(uniq):
        if i in scr.fine_set:
            # from the candidate's own pose, not the screened one: the feature-level ICP can
            # settle ~0.1 m off along a curved drift and the fine ICP then stays there
            # (curve flash scan, 12 m map: 0.117 m instead of 0.028 m)
            ic, pf, prm, pff = once(ctx, "fine", name, T0, lambda T0=T0: refine_and_verify(ctx, ctx.scan.icp_points, T0))
            refined.append(Refined(name, T0, rf, rrmse, ic, pf, prm, pff))
        else:  # screened out: keep the coarse ICP's score for the record
            ic, pf, prm, pff = scr.screened[i]
            why = ("screened out: same placement as a better-screened one" if i in scr.same_place
                   else "screened out on the coarse scan")
            refined.append(Refined(f"{name} ({why})", T0, rf, rrmse, ic, pf, prm, pff))
    return refined


@dataclass(frozen=True)
class Polish:
    """Outcome of :func:`polish`: ``ic`` the tight-gate ICP result, ``record`` the
    ``LocalizationResult.polish`` entry (``shift_6``: the pose shift ``(ω, t)`` about the placed
    scan origin, map axes, rad and m), ``applied`` whether the final pose comes from it."""

    ic: object
    record: dict
    applied: bool


def polish(ctx: VerifyContext, ic_best) -> Polish:
    """Point-to-plane ICP of the ICP-level scan from the chosen pose with the tight gate
    ``max(icp_polish_correspondence_m, 3 σ_surf)`` (minegeo addition, see ``LocalizeParams``);
    applied when it keeps at least 7 pairs and moves no scan point more than
    ``verify.max_pending_step_m``."""
    p, Dfine, scan_origin = ctx.p, ctx.scan.icp_points, ctx.scan.scan_origin
    pol_gate = float(p.icp.polish_correspondence_m)
    if math.isfinite(ctx.scan_noise):
        pol_gate = max(pol_gate, 3.0 * ctx.scan_noise)
    pol_p = plane_icp_params(pol_gate, p)
    ic_pol = register_icp(Dfine, ctx.Qf, ic_best.T_target_source, pol_p, target_normals=ctx.Nf, target_index=ctx.tree,
                          check_target=False)
    Ta, Tp = ic_best.T_target_source, ic_pol.T_target_source
    Pa = Dfine @ Ta[:3, :3].T + Ta[:3, 3]
    shift = float(np.sqrt(np.max(np.sum((Dfine @ Tp[:3, :3].T + Tp[:3, 3] - Pa) ** 2, axis=1))))
    applied = ic_pol.correspondences.shape[0] >= 7 and shift <= p.verify.max_pending_step_m
    # the same shift as a pose increment (ω, t) about the placed scan origin, map axes
    dT = Tp @ invert(Ta)
    o_a = Ta[:3, :3] @ (-scan_origin) + Ta[:3, 3]
    shift6 = np.r_[log_so3(dT[:3, :3]), dT[:3, :3] @ o_a + dT[:3, 3] - o_a]
    record = {"gate_m": pol_gate, "applied": bool(applied), "largest_shift_m": shift, "shift_6": shift6.tolist(),
              "iterations": int(ic_pol.iterations), "fitness": float(ic_pol.fitness),
              "inlier_rmse_m": float(ic_pol.inlier_rmse_m), "n_pairs": int(ic_pol.correspondences.shape[0])}
    return Polish(ic=ic_pol, record=record, applied=bool(applied))
