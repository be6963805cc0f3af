"""Whole-map rival search at the chosen attitude: can another placement explain the scan as well?

Why
---
Mines repeat their level layouts: a drift copied onto the level below is, for a scan taken in
it, *indistinguishable* from the original. The pipeline's ambiguity test (docs/localization.md,
*Never a silent wrong pose*) compared only the placements that RANSAC and, when it runs, the
correlative search had proposed; a copy that neither proposed was never compared, and the
result would come out ``ok`` on a coin flip (an exact twin 25-40 m below was ``ok`` in 2 of 3
tries). Before a result is ``ok``, :func:`search_rivals` looks for such a placement over the
*whole* map, explicitly, and the pipeline (:func:`minegeo.localize.localize_scan`) makes the
result ``ambiguous`` when one explains the scan nearly as well.

Method
------
Let ``T = [R | t]`` be the chosen placement (``T_work_scan`` of the origin-subtracted scan
``D``). Rotating the scan by ``R`` puts it in the chosen attitude: ``D' = R D`` is levelled
exactly as the chosen placement has it (``R = Rz(ψ) R_tilt``: tilt and heading are both taken
out), and heading 0 of the search grid *is* the chosen heading. The exhaustive correlative
4-DOF search (:func:`minegeo.localize.correlative.correlative_candidates`, Olson 2009's
correlative scan matching over the map's floor anchors) then scores, over the whole map,

    ``p ↦ Rz(ψ) (R p − q) + a``  for every floor anchor ``a`` and every ``ψ = k · yaw_step``

(``q`` a *pivot*: a scan floor point), i.e. every placement of the chosen placement's
**attitude class** (same tilt, any heading on the grid, anywhere a scanner can stand), and
refines the best ones by 4-DOF Gauss-Newton against the map. A candidate ``T_c`` of that
search maps ``D'``, so it maps ``D`` by ``T_c · [R | 0]``.

*Pivots.* A placement is on the grid only up to the distance between where it puts the pivot
and the nearest anchor, which on a sparse survey map reaches metres (the floor under the pivot
may not be mapped at all). The first pivot (every heading) is the scan floor point that the
chosen placement puts nearest to an anchor, so the chosen placement itself is on the grid;
``translation_pivots`` more floor points, spread over the scan (farthest-point order), are
scored with the chosen heading ± ``translation_headings`` grid steps: a *translated copy* of
the chosen placement (a repeated level or drift) is on the grid when its map has floor under
any of them.

*Witness and coverage.* The chosen placement is the search's witness
(``correlative_candidates(witness=...)``): at every stage of the cascade (grid bins,
screening, refinement, distinct selection) its own score ``s`` is found, and the stage keeps
every placement scoring at least ``s − cover_slack`` (up to ``cover_max_factor`` × its usual
size); ``coverage["covered"]`` records whether it could.

*Checks.* Every candidate farther than ``distinct_m`` / ``distinct_deg`` from ``T`` is
pre-checked without ICP, with the pipeline's own verification (plane fitness of the
feature-level scan, and the support-matched comparison below, against the chosen placement's
own at its converged pose). The candidates are already refined at the chosen attitude, so a
screening ICP adds little (in the cases looked at, plane fitness before and after it within
0.02).
Those within reach of either ambiguity test — pre-check ``≥ precheck_ratio`` × the chosen
placement's, or support-matched ``≥ precheck_matched_ratio`` — get the pipeline's
full-resolution ICP and verification (at most ``max_fine_icp``, closest first).

*Ambiguity tests* (:func:`rival_test`), for a rival still distinct from ``T`` after its ICP:

1. plane fitness ``≥ ambiguity_ratio ×`` the chosen placement's (the pipeline's test); or
2. **support-matched**: on the scan points that have a map point within the ICP gate at *both*
   placements (at least ``min_common_fraction`` of them), the rival's fraction within the plane
   tolerance is ``≥ matched_ratio ×`` the chosen placement's. A survey map covers two copies
   of a drift differently (other survey positions, occlusions): on the study worlds 6 of 80
   exact twins reached only 0.83-0.89 of the original's plane fitness, while on the points both
   maps cover every twin agreed 0.98-1.01 as well; the best *other* placements of 49 ordinary
   ``ok`` scans reached 0.46-0.89 support-matched, near twins (same layout, other rock)
   0.62-0.81 (docs/localization.md). A point the map does not cover at one place says nothing
   against that place; a point it covers but off the surface does.

Guarantee
---------
**What is covered.** Every (floor anchor × heading of the ``yaw_step_deg`` grid aligned with the
chosen heading) placement at the chosen attitude, pivoted on the first pivot, and every (anchor
× heading within ± ``translation_headings`` steps of the chosen one) placement pivoted on each
further pivot, is scored — exhaustively (the seed only picks the scan's sample points), so the
search is deterministic. When ``covered`` holds, every placement that scores within
``cover_slack`` of the chosen placement's own score at every stage of the cascade is refined and
pre-checked, and every distinct one within reach of an ambiguity test is verified by the same
full-resolution ICP and plane fitness as the pipeline's own candidates. A translated copy of the
chosen drift (an exact twin) scores like the chosen placement wherever its map has floor under a
pivot; it is then verified, and the result is ``ambiguous`` with both placements listed.

**What it cannot see.** (a) a rival at another tilt (a copy rotated out of the chosen
attitude, e.g. a drift repeated on a ramp of another slope): the scan is not re-tilted; (b) a
rival whose heading is off the grid by more than the 4-DOF refinement recovers (about ±1.5°;
only rivals that are not translations of the chosen placement); (c) a rival with no mapped floor
within the refinement's reach of any pivot's landing point; (d) a rival that loses more than
``cover_slack`` against the chosen placement at some stage of the cascade, or whose pre-check
stays below both bars (thresholds measured on the study worlds), or that the caps cut
(``covered`` false: recorded, with a warning); (e) anything the map does not hold. When the
search does not recover the chosen placement itself (``self_found`` false) its ranking argument
does not hold; the pipeline says so in a warning.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from minegeo.localize.correlative import MapOccupancy, correlative_candidates
from minegeo.localize.params import CorrelativeParams, RivalParams
from minegeo.registration.ransac import hypothesis_distance

__all__ = ["RivalParams", "RivalCandidate", "RivalSearch", "search_rivals", "attitude", "matched_support",
           "rival_test"]

#: What the search covers, written into ``result.json`` (``rival_search.guarantee``).
GUARANTEE = ("scored over the whole map at the chosen placement's tilt: every floor anchor x every heading of the "
             "{yaw:g} deg grid aligned with the chosen heading, and every anchor x the chosen heading +-{th} steps "
             "for {np} more pivots (translated copies); every placement within {slack:g} of the chosen placement's "
             "own score at each stage of the cascade was refined and pre-checked (covered: {cov}), and those within "
             "reach of an ambiguity test verified with the same ICP and plane fitness. Not covered: rivals at "
             "another tilt, rivals without mapped floor under a pivot, rivals losing more than the slack at some stage")

#: Placement types kept in ``RivalCandidate.stage``.
STAGES = ("self", "precheck", "fine")


@dataclass
class RivalCandidate:
    """One placement returned by the whole-map search (poses map the origin-subtracted scan ``D``
    into the work frame).

    Attributes
    ----------
    rank : int
        1-based rank among the search's candidates (best refined search score first).
    T_search : (4, 4) ndarray
        The search's placement (4-DOF refined at the chosen attitude, before any ICP).
    search_fraction : float
        Its refined search score (fraction of the refinement points within the tolerance).
    distance_m, rotation_deg : float
        Scan-centre distance (m) and rotation angle (deg) from the chosen placement, before ICP.
    is_self : bool
        Within ``distinct_m`` / ``distinct_deg`` of the chosen placement (the search found it).
    precheck, pre_common_fraction, pre_matched_ratio : float
        At ``T_search``, feature-level scan: plane fitness, and the support-matched comparison
        with the chosen placement (:func:`matched_support`); NaN for ``is_self``.
    T_final : (4, 4) ndarray or None
        After the full-resolution ICP (None when not given it).
    plane_fitness, plane_rmse_m, fine_fitness, icp_fitness, icp_inlier_rmse_m : float
        Verification of ``T_final`` (NaN without it); ``fine_fitness`` at the pipeline's fine
        tolerance (``LocalizeParams.verify.fine_tolerance_m``; = ``plane_fitness`` when off).
    icp_iterations : int
        Of the full-resolution ICP (0 without it).
    common_fraction, matched_ratio : float
        Support-matched comparison of ``T_final`` with the chosen placement, ICP-level points
        (NaN without it).
    final_distance_m, final_rotation_deg : float
        Distance / rotation of ``T_final`` (else of ``T_search``) from the chosen placement.
    distinct : bool
        Farther than the ambiguity distance / angle from the chosen placement (after the ICP
        when it ran: a rival that ICP brings back onto the chosen placement is not a rival).
    stage : str
        ``"self"`` (the chosen placement found again), ``"precheck"`` (pre-checked, out of reach
        of both tests or cut by ``max_fine_icp``), ``"fine"`` (full-resolution ICP and
        verification).
    """

    rank: int
    T_search: np.ndarray
    search_fraction: float
    distance_m: float
    rotation_deg: float
    is_self: bool
    precheck: float = math.nan
    pre_common_fraction: float = math.nan
    pre_matched_ratio: float = math.nan
    T_final: np.ndarray | None = None
    plane_fitness: float = math.nan
    plane_rmse_m: float = math.nan
    fine_fitness: float = math.nan
    icp_fitness: float = math.nan
    icp_inlier_rmse_m: float = math.nan
    icp_iterations: int = 0
    common_fraction: float = math.nan
    matched_ratio: float = math.nan
    final_distance_m: float = math.nan
    final_rotation_deg: float = math.nan
    distinct: bool = False
    stage: str = ""


@dataclass(frozen=True)
class RivalSearch:
    """Outcome of :func:`search_rivals` (see the module docstring for what it covers).

    Attributes
    ----------
    candidates : list of RivalCandidate
        The search's candidates, best search score first (the chosen placement's own included,
        ``is_self``).
    self_rank : int or None
        Rank of the first candidate within ``distinct_m`` / ``distinct_deg`` of the chosen
        placement; None when the search did not recover it.
    tilt_deg, heading_deg : float
        The chosen attitude ``R = Rz(ψ) R_tilt``: the angle of ``R_tilt`` (deg; between the
        scan's up and the map's z) and ``ψ`` (deg, map frame).
    precheck_self : float
        The chosen placement's own pre-check (feature-level plane fitness at its converged pose).
    n_anchors, n_yaw, n_sample, n_pivots : int
        Grid size (``n_anchors · n_yaw`` placements on the first pivot), scan sample size,
        pivots used.
    n_fine_cut : int
        Rivals within reach of a test that the ``max_fine_icp`` cap left without the
        full-resolution ICP (0 normally).
    coverage : dict or None
        The witness coverage of the cascade (``CorrelativeResult.coverage``) and ``n_fine_cut``.
    reason : str
        Why the search produced no candidate (empty otherwise).
    params : RivalParams
    timings_s : dict
        ``search`` (with its parts under ``search_parts``), ``precheck``, ``fine``, ``total`` (s).
    """

    candidates: list
    self_rank: int | None
    tilt_deg: float
    heading_deg: float
    precheck_self: float
    n_anchors: int
    n_yaw: int
    n_sample: int
    n_pivots: int
    n_fine_cut: int
    coverage: dict | None
    reason: str
    params: RivalParams
    timings_s: dict = field(default_factory=dict)

    @property
    def self_found(self) -> bool:
        return self.self_rank is not None

    @property
    def covered(self) -> bool:
        return bool(self.coverage and self.coverage.get("covered") and self.n_fine_cut == 0)

    def guarantee(self) -> str:
        p = self.params
        return GUARANTEE.format(yaw=p.search.yaw_step_deg, th=p.translation_headings, np=max(0, self.n_pivots - 1),
                                slack=p.cover_slack, cov="yes" if self.covered else "NO")

    def to_dict(self, to_map: Callable[[np.ndarray], np.ndarray] | None = None) -> dict:
        """JSON record without the times (equal inputs, equal record); ``to_map(T_work_scan) ->
        T_map_scan`` converts the poses (map frame)."""
        conv = (lambda T: T) if to_map is None else to_map

        def _c(c: RivalCandidate) -> dict:
            return {"rank": c.rank, "stage": c.stage, "is_self": c.is_self, "search_fraction": c.search_fraction,
                    "distance_to_chosen_m": c.distance_m, "rotation_to_chosen_deg": c.rotation_deg,
                    "precheck_plane_fitness": c.precheck, "precheck_common_fraction": c.pre_common_fraction,
                    "precheck_matched_ratio": c.pre_matched_ratio, "plane_fitness": c.plane_fitness,
                    "fine_fitness": c.fine_fitness,
                    "plane_rmse_m": c.plane_rmse_m, "icp_fitness": c.icp_fitness,
                    "icp_inlier_rmse_m": c.icp_inlier_rmse_m, "icp_iterations": c.icp_iterations,
                    "common_fraction": c.common_fraction, "matched_ratio": c.matched_ratio,
                    "final_distance_to_chosen_m": c.final_distance_m,
                    "final_rotation_to_chosen_deg": c.final_rotation_deg, "distinct": c.distinct,
                    "T_map_scan": conv(c.T_final if c.T_final is not None else c.T_search)}

        return {"self_rank": self.self_rank, "self_found": self.self_found, "covered": self.covered,
                "tilt_deg": self.tilt_deg, "heading_deg": self.heading_deg, "precheck_self": self.precheck_self,
                "n_anchors": self.n_anchors, "n_yaw": self.n_yaw, "n_placements": self.n_anchors * self.n_yaw,
                "n_sample": self.n_sample, "n_pivots": self.n_pivots, "n_fine_cut": self.n_fine_cut,
                "coverage": self.coverage, "reason": self.reason, "guarantee": self.guarantee(),
                "candidates": [_c(c) for c in self.candidates], "params": asdict(self.params)}


def matched_support(best: tuple, other: tuple, fine_scale: float | None = None) -> tuple[float, float]:
    """Support-matched comparison of two placements of the same scan points.

    Parameters
    ----------
    best, other : (supported, on_plane[, on_fine]) tuples of (n,) bool arrays
        Per scan point: a map point within the ICP gate (``supported``) and, in addition,
        within the plane tolerance of that point's tangent plane (``on_plane``), as in the
        pipeline's plane fitness; ``on_fine``: within the fine tolerance
        (``LocalizeParams.verify.fine_tolerance_m``).
    fine_scale : float, optional
        Both placements are converged (after ICP): ``matched_ratio`` is the smaller of the
        ratio at the plane tolerance and ``fine_scale`` × the ratio at the fine tolerance (when
        the masks hold it), so the test passes only when the rival matches at both
        (``fine_scale = ambiguity_ratio / fine_ratio`` > 1: the fine level is noisier, measured
        0.90 for an exact twin whose two copies the map covers differently, 0.6 for another
        smooth drift). Not for pre-checks: a placement before ICP is a few cm off, and the
        fine level would hide a true twin there.

    Returns
    -------
    common_fraction : float
        Fraction of the points supported at both placements.
    matched_ratio : float
        ``mean(on_plane_other | both) / mean(on_plane_best | both)`` over those points (0 when
        there are none; inf when the chosen placement has none on the plane there).
    """
    both = best[0] & other[0]
    n = int(np.count_nonzero(both))
    if n == 0:
        return 0.0, 0.0
    a = float(np.count_nonzero(best[1] & both)) / n
    b = float(np.count_nonzero(other[1] & both)) / n
    ratio = b / a if a > 0 else math.inf
    if fine_scale is not None and len(best) > 2 and len(other) > 2:
        af = float(np.count_nonzero(best[2] & both)) / n
        bf = float(np.count_nonzero(other[2] & both)) / n
        ratio = min(ratio, float(fine_scale) * bf / af if af > 0 else math.inf)
    return n / both.size, ratio


def rival_test(chosen_plane_fitness: float, plane_fitness: float, common_fraction: float, matched_ratio: float,
               ambiguity_ratio: float, params: RivalParams, *, chosen_fine_fitness: float | None = None,
               fine_fitness: float | None = None, fine_ratio: float | None = None) -> str:
    """Which ambiguity test a distinct, fully verified rival passes: ``"plane fitness"``,
    ``"support-matched"`` or ``""`` (module docstring, *Ambiguity tests*).

    With ``fine_fitness`` and ``chosen_fine_fitness`` (the agreement at the pipeline's fine
    tolerance), the plane-fitness test also needs ``fine_fitness >= fine_ratio ×
    chosen_fine_fitness`` (``fine_ratio`` defaults to ``ambiguity.ratio``); ``matched_ratio``
    should then be :func:`matched_support` with ``fine_scale = ambiguity_ratio / fine_ratio``.
    """
    fine_ok = True
    if fine_fitness is not None and chosen_fine_fitness is not None and math.isfinite(fine_fitness) \
            and math.isfinite(chosen_fine_fitness):
        fr = float(ambiguity_ratio if fine_ratio is None else fine_ratio)
        fine_ok = fine_fitness >= fr * chosen_fine_fitness
    if plane_fitness >= float(ambiguity_ratio) * chosen_plane_fitness and fine_ok:
        return "plane fitness"
    if common_fraction >= float(params.min_common_fraction) and matched_ratio >= float(params.matched_ratio):
        return "support-matched"
    return ""


def attitude(R: np.ndarray) -> tuple[float, float]:
    """``(tilt_deg, heading_deg)`` of a rotation ``R = Rz(ψ) R_tilt`` (scan → map).

    ``R_tilt`` is the smallest rotation taking the scan's up direction ``u = Rᵀ e_z`` onto
    ``e_z``; the tilt is its angle, ``arccos(R₃₃)``, and ``ψ = atan2((R R_tiltᵀ)₂₁, (R R_tiltᵀ)₁₁)``.
    """
    R = np.asarray(R, dtype=np.float64)
    u = R[2, :]  # R^T e_z: the map's up in scan coordinates
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(u[2])))))
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        Rt = np.eye(3) if u[2] > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = axis / s
        ang = math.atan2(s, float(u[2]))
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        Rt = np.eye(3) + math.sin(ang) * K + (1.0 - math.cos(ang)) * (K @ K)
    Rz = R @ Rt.T
    return tilt, math.degrees(math.atan2(Rz[1, 0], Rz[0, 0]))


def _pivots(Dr: np.ndarray, Nr: np.ndarray, ref_xy, t_best: np.ndarray, anchors: np.ndarray, sp: CorrelativeParams,
            n_extra: int, n_head: int):
    """Grid pivots of the rival search (``grid_references`` of the correlative search).

    The search pivots a placement on a scan floor point set onto a map floor anchor, so a
    placement is on the grid only up to the distance between where it puts the pivot and the
    nearest anchor (up to metres on a sparse survey map, where the floor under the pivot may be
    unmapped). First pivot (every heading): among the scan's floor points within the sample
    radius of the reference, the one that the chosen placement puts nearest to an anchor, so the
    chosen placement itself is on the grid. Then ``n_extra`` more floor points spread over the
    same area (farthest-point order from the first), each with the chosen heading ± ``n_head``
    grid steps only: a translated copy of the chosen placement is on the grid when its map has
    floor under *any* of the pivots.
    """
    from pykdtree.kdtree import KDTree

    up = math.cos(math.radians(sp.anchor_max_tilt_deg))
    floor = np.flatnonzero(Nr[:, 2] >= up)
    if floor.size == 0 or anchors.shape[0] == 0:
        return None  # the search reports why
    xy = np.asarray(ref_xy, dtype=np.float64)[:2]
    r0 = Dr[floor[np.argmin(np.sum((Dr[floor, :2] - xy) ** 2, axis=1))]]
    cand = floor[np.sum((Dr[floor, :2] - r0[:2]) ** 2, axis=1) <= float(sp.sample_radius_m) ** 2]
    d, _ = KDTree(np.ascontiguousarray(anchors)).query(np.ascontiguousarray(Dr[cand] + t_best), k=1)
    first = int(cand[int(np.argmin(d))])
    n_yaw = int(round(360.0 / float(sp.yaw_step_deg)))
    heads = np.unique(np.arange(-n_head, n_head + 1) % n_yaw)
    out = [(Dr[first].copy(), None)]
    dmin = np.sum((Dr[cand, :2] - Dr[first, :2]) ** 2, axis=1)
    for _ in range(min(n_extra, cand.size - 1)):
        j = int(np.argmax(dmin))
        if dmin[j] <= 0.0:
            break
        out.append((Dr[cand[j]].copy(), heads))
        dmin = np.minimum(dmin, np.sum((Dr[cand, :2] - Dr[cand[j], :2]) ** 2, axis=1))
    return out


def _precheck(others: list, T_best: np.ndarray, support: Callable) -> float:
    """The pipeline's verification of the feature-level scan at every candidate (``precheck``,
    ``pre_common_fraction``, ``pre_matched_ratio`` set in place), against the chosen placement's
    own at its converged pose (one batched query); returns the latter (NaN without candidates)."""
    pre_self = math.nan
    if others:
        masks = support([T_best] + [c.T_search for c in others], "feature")
        pre_self = float(np.mean(masks[0][1]))
        for c, mk in zip(others, masks[1:], strict=True):
            c.precheck = float(np.mean(mk[1]))
            c.pre_common_fraction, c.pre_matched_ratio = matched_support(masks[0], mk)
    return pre_self


def _verify_rivals(todo: list, T_best: np.ndarray, centre: np.ndarray, ambiguity_distance_m: float,
                   ambiguity_angle_deg: float, support: Callable, fine: Callable, fine_scale: float | None) -> None:
    """The pipeline's full-resolution ICP (from each candidate's own pose) and verification of the
    candidates ``todo``, set in place (``T_final``, scores, distance to the chosen placement,
    ``distinct``, support-matched comparison; ``stage = "fine"``)."""
    if todo:
        sup_self = support([T_best], "fine")[0]
    for c in todo:
        ic, pf, prm, *pff = fine(c.T_search)
        Tf = np.asarray(ic.T_target_source, dtype=np.float64)
        c.T_final, c.plane_fitness, c.plane_rmse_m = Tf, float(pf), float(prm)
        c.fine_fitness = float(pff[0]) if pff else float(pf)
        c.icp_fitness, c.icp_inlier_rmse_m, c.icp_iterations = float(ic.fitness), float(ic.inlier_rmse_m), \
            int(ic.iterations)
        c.final_distance_m, c.final_rotation_deg = hypothesis_distance(Tf, T_best, centre)
        c.distinct = c.final_distance_m > ambiguity_distance_m or c.final_rotation_deg > ambiguity_angle_deg
        c.common_fraction, c.matched_ratio = matched_support(sup_self, support([Tf], "fine")[0],
                                                             fine_scale=fine_scale)
        c.stage = "fine"


def search_rivals(occupancy: MapOccupancy, D: np.ndarray, Nd: np.ndarray, T_best: np.ndarray, *,
                  params: RivalParams, seed: int, centre: np.ndarray, ambiguity_distance_m: float,
                  ambiguity_angle_deg: float,
                  support: Callable[[list, str], list],
                  fine: Callable[[np.ndarray], tuple[object, float, float]],
                  reference_point: np.ndarray | None = None, refine_target=None, screen_target=None,
                  screen_grid=None, fine_scale: float | None = None) -> RivalSearch:
    """Whole-map search for placements at the chosen attitude that explain the scan nearly as well.

    Parameters
    ----------
    occupancy : MapOccupancy
        The map's occupancy and floor anchors (work frame), ``PreparedMap.occupancy(params.search)``.
    D, Nd : (n, 3) float64
        The feature-level scan points relative to the scan origin (scan axes, m) and their
        void-oriented unit normals.
    T_best : (4, 4) ndarray
        The chosen placement ``T_work_scan`` of ``D`` (its attitude is searched).
    params : RivalParams
    seed : int
        Picks the search's scan sample (as in the correlative search).
    centre : (3,) ndarray
        Scan point (``D`` frame, m) whose placed position measures the distance between two
        placements (the pipeline's ``centre``, the mean of ``D``).
    ambiguity_distance_m, ambiguity_angle_deg : float
        A rival must be farther than this distance (m) or angle (deg) from the chosen placement
        (the pipeline's ``ambiguity.distance_m`` / ``ambiguity.angle_deg``).
    support : callable ``([T, ...], level) -> [(supported, on_plane), ...]``
        The pipeline's verification as per-point masks at each ``T`` (:func:`matched_support`),
        on the feature-level points (``level="feature"``; their mean of ``on_plane`` is the
        plane fitness) or on the ICP-level points (``"fine"``).
    fine : callable ``T -> (icp_result, plane_fitness, plane_rmse_m[, fine_fitness])``
        The pipeline's full-resolution ICP from ``T`` and its verification.
    fine_scale : float, optional
        Passed to :func:`matched_support` for the converged rivals (the fine agreement level).
    reference_point : (3,) ndarray, optional
        Where the scanner was (``D`` frame, m), e.g. the middle of its trajectory.
    refine_target, screen_target, screen_grid
        As for :func:`~minegeo.localize.correlative.correlative_candidates` (the map's ICP cloud and
        its KD-tree, the thinned screening cloud and its lookup grid).

    Returns
    -------
    RivalSearch
        Every candidate with the stage it reached. The decision (``ambiguous`` when a distinct
        verified rival passes :func:`rival_test`) is the pipeline's.
    """
    t_all = time.perf_counter()
    sp = params.search
    T_best = np.asarray(T_best, dtype=np.float64)
    R = T_best[:3, :3]
    tilt, heading = attitude(R)
    # the scan in the chosen attitude: heading 0 of the grid is the chosen heading
    Dr = np.ascontiguousarray(D @ R.T)
    Nr = np.ascontiguousarray(Nd @ R.T)
    ref = np.median(D, axis=0) if reference_point is None else np.asarray(reference_point, dtype=np.float64)
    ref_xy = (R @ ref)[:2]
    A = np.eye(4)
    A[:3, :3] = R
    W = np.eye(4)  # the chosen placement of the rotated scan: no rotation left, its translation
    W[:3, 3] = T_best[:3, 3]
    t0 = time.perf_counter()
    pivots = _pivots(Dr, Nr, ref_xy, T_best[:3, 3], occupancy.anchors, sp, int(params.translation_pivots),
                     int(params.translation_headings))
    corr = correlative_candidates(occupancy, Dr, Nr, sp, seed=seed, reference_xy=ref_xy, refine_target=refine_target,
                                  screen_target=screen_target, screen_grid=screen_grid, grid_references=pivots,
                                  witness=W, cover_slack=float(params.cover_slack),
                                  cover_max_factor=float(params.cover_max_factor))
    timings = {"search": time.perf_counter() - t0, "search_parts": dict(corr.timings_s)}
    cands: list[RivalCandidate] = []
    self_rank = None
    for k, (Tc, frac) in enumerate(corr.candidates):
        T = Tc @ A
        dist, ang = hypothesis_distance(T, T_best, centre)
        is_self = dist <= sp.distinct_m and ang <= sp.distinct_deg
        if is_self and self_rank is None:
            self_rank = k + 1
        cands.append(RivalCandidate(rank=k + 1, T_search=T, search_fraction=float(frac), distance_m=dist,
                                    rotation_deg=ang, is_self=is_self, stage="self" if is_self else "precheck",
                                    final_distance_m=dist, final_rotation_deg=ang,
                                    distinct=dist > ambiguity_distance_m or ang > ambiguity_angle_deg))
    others = [c for c in cands if not c.is_self]

    # 1. pre-check without ICP: the pipeline's verification of the feature-level scan at every candidate,
    #    against the chosen placement's own at its converged pose (one batched query)
    t0 = time.perf_counter()
    pre_self = _precheck(others, T_best, support)
    timings["precheck"] = time.perf_counter() - t0

    # 2. full-resolution ICP (from the candidate's own pose, as the pipeline does) and verification of every
    #    rival within reach of an ambiguity test, closest first
    t0 = time.perf_counter()

    def _reach(c) -> float:
        r = c.precheck / (float(params.precheck_ratio) * pre_self) if pre_self > 0 else 0.0
        if c.pre_common_fraction >= float(params.min_common_fraction) and math.isfinite(c.pre_matched_ratio):
            r = max(r, c.pre_matched_ratio / float(params.precheck_matched_ratio))
        return r

    within = sorted((c for c in others if c.distinct and _reach(c) >= 1.0), key=lambda c: (-_reach(c), c.rank))
    n_cut = max(0, len(within) - int(params.max_fine_icp))
    todo = within[: int(params.max_fine_icp)]
    _verify_rivals(todo, T_best, centre, ambiguity_distance_m, ambiguity_angle_deg, support, fine, fine_scale)
    timings["fine"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    cov = None if corr.coverage is None else {**corr.coverage, "n_fine_cut": n_cut}
    return RivalSearch(candidates=cands, self_rank=self_rank, tilt_deg=tilt, heading_deg=heading,
                       precheck_self=pre_self, n_anchors=corr.n_anchors, n_yaw=corr.n_yaw, n_sample=corr.n_sample,
                       n_pivots=0 if pivots is None else len(pivots), n_fine_cut=n_cut, coverage=cov,
                       reason=corr.reason, params=params, timings_s=timings)
