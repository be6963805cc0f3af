"""Stages 3-4 of :func:`~minegeo.localize.localize_scan`: verify a list of hypotheses and decide.

:func:`evaluate` runs the ICP stages of :mod:`minegeo.localize.verification` on a candidate list
and :func:`decide` turns the verified hypotheses into ``ok`` / ``ambiguous`` / ``failed`` by the
rules of the :mod:`minegeo.localize.pipeline` module docstring (plane fitness, ICP fitness, inlier
RMSE ([Baek2022 Eq. 19]), a distinct rival at both tolerances). The whole-map rival search
(:mod:`minegeo.localize.rival_check`) and the covariance checks
(:mod:`minegeo.localize.covariance`) come after it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from minegeo.localize.hypotheses import CorrelativeHypotheses, Hypotheses, correlative_hypotheses
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.run_context import RunContext
from minegeo.localize.scan import to_map
from minegeo.localize.verification import (
    Candidate,
    Refined,
    VerifyContext,
    coarse_pull_in,
    refine_candidates,
    screen,
)
from minegeo.registration.ransac import hypothesis_distance

__all__ = ["Decision", "DecisionStatus", "evaluate", "decide", "hypothesis_records", "verify_and_decide"]


class DecisionStatus(StrEnum):
    """Status of a :class:`Decision`: the three of :class:`~minegeo.localize.result.LocalizeStatus`
    and ``deferred``; each member is its string value."""

    OK = "ok"
    AMBIGUOUS = "ambiguous"
    FAILED = "failed"
    #: the screening showed that this candidate list alone gives no ``ok``: the correlative fallback follows
    DEFERRED = "deferred"


@dataclass(frozen=True)
class Decision:
    """Outcome of :func:`evaluate` on one candidate list.

    Attributes
    ----------
    status : DecisionStatus
        ``ok``, ``ambiguous``, ``failed`` or ``deferred`` (the screening showed that
        this list alone gives no ``ok``: the correlative fallback follows).
    reason : str
    weak : str
        The chosen fit's weak direction (judged after the covariance), or "".
    hyps : list of dict
        The verified hypotheses, chosen first (``LocalizationResult.hypotheses``).
    best : Refined or None
        The chosen hypothesis.
    uniq : list of Candidate
        The candidate list after the coarse pull-in.
    refined : list of Refined
    warnings : list of str
    t_icp, t_decision : float
        Seconds of the ICP stages and of the decision.
    """

    status: DecisionStatus
    reason: str = ""
    weak: str = ""
    hyps: list = field(default_factory=list)
    best: Refined | None = None
    uniq: list = field(default_factory=list)
    refined: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    t_icp: float = 0.0
    t_decision: float = 0.0

    @property
    def ic_best(self):
        """The chosen hypothesis's ICP result (None without one)."""
        return self.best.ic if self.best is not None else None


def evaluate(ctx: VerifyContext, uniq: list[Candidate], r0, work_origin: np.ndarray,
             may_defer: bool = False) -> Decision:
    """Steps 3-4 on a candidate list: coarse pull-in, screening, full-resolution ICP, decision.

    ``r0`` is the (first) RANSAC result (its reason and runner-up score enter the decision);
    ``may_defer``: see :func:`~minegeo.localize.verification.screen` (the result is then
    ``Decision("deferred")`` with only ``t_icp`` set).
    """
    t0 = time.perf_counter()
    uniq = coarse_pull_in(ctx, uniq)
    scr = screen(ctx, uniq, may_defer)
    if scr.deferred:
        return Decision(status=DecisionStatus.DEFERRED, t_icp=time.perf_counter() - t0)
    refined = refine_candidates(ctx, uniq, scr)
    t_icp = time.perf_counter() - t0
    t0 = time.perf_counter()
    dec = decide(ctx, refined, r0, work_origin)
    return replace(dec, uniq=uniq, t_icp=t_icp, t_decision=time.perf_counter() - t0)


def hypothesis_records(ctx: VerifyContext, refined: list[Refined], work_origin: np.ndarray):
    """The verified hypotheses ranked (fully refined first, then by fine agreement, plane fitness,
    ICP fitness) as ``LocalizationResult.hypotheses`` entries, and the chosen one."""
    if not refined:
        return [], None
    # fully refined hypotheses first (screened-out ones lost on the coarse scan already), then
    # by the fine agreement (verify_fine_tolerance_m; = the plane fitness when off)
    order = sorted(range(len(refined)),
                   key=lambda i: ("screened out" in refined[i][0], -refined[i][7], -refined[i][5],
                                  -refined[i][4].fitness, i))
    best = refined[order[0]]
    Tb = best[4].T_target_source
    hyps = []
    for rank, i in enumerate(order):
        name, T0, rf, rrmse, ic, pf, prm, pff = refined[i]
        dist, ang = hypothesis_distance(ic.T_target_source, Tb, ctx.scan.centre)
        hyps.append({
            "rank": rank, "source": name, "ransac_fitness": rf, "ransac_inlier_rmse_m": rrmse,
            "icp_fitness": ic.fitness, "icp_inlier_rmse_m": ic.inlier_rmse_m, "icp_iterations": ic.iterations,
            "plane_fitness": pf, "plane_rmse_m": prm, "fine_fitness": pff,
            "distance_to_chosen_m": dist, "rotation_to_chosen_deg": ang,
            "T_map_scan": to_map(ic.T_target_source, ctx.scan.scan_origin, work_origin),
        })
    return hyps, best


def _failure(ctx: VerifyContext, best: Refined) -> str:
    """Why the chosen hypothesis fails the absolute thresholds, or "" when it passes them."""
    p = ctx.p
    f, e, pf_best = best.ic.fitness, best.ic.inlier_rmse_m, best.pf
    if pf_best < p.verify.min_plane_fitness:
        return (f"the first-ranked placement (#0) has only {100 * pf_best:.0f} % of the scan points within "
                f"{ctx.tol:.3g} m of the map surface (need {100 * p.verify.min_plane_fitness:.0f} %; "
                f"ICP fitness {f:.3f}): no placement matches the drift's shape — the scan is probably not in "
                "the mapped area, the map changed there, or the right place was not found")
    if f < p.verify.min_fitness:
        return (f"the first-ranked placement (#0) explains only {100 * f:.0f} % of the scan points within "
                f"{p.icp.max_correspondence_m:g} m of the map (need {100 * p.verify.min_fitness:.0f} %): the scan is "
                "probably not in the mapped area, or the map changed there")
    if e > p.verify.max_inlier_rmse_m:
        return (f"the inlier RMSE {e:.3f} m exceeds {p.verify.max_inlier_rmse_m:g} m: the scan does not fit the map "
                "closely enough")
    return ""


def decide(ctx: VerifyContext, refined: list[Refined], r0, work_origin: np.ndarray) -> Decision:
    """The decision on verified hypotheses (module docstring of :mod:`minegeo.localize.pipeline`):
    ``failed`` without a hypothesis or below an absolute threshold, ``ambiguous`` when a distinct
    hypothesis reaches the ambiguity ratio at both tolerances, else ``ok`` (the weak-direction
    verdict is left to the covariance stage)."""
    p = ctx.p
    hyps, best = hypothesis_records(ctx, refined, work_origin)
    warnings: list[str] = []
    if best is None:
        return Decision(status=DecisionStatus.FAILED, reason=f"RANSAC found no placement of the scan in the map ({r0.reason})",
                        hyps=hyps, refined=refined, warnings=warnings)
    ic_best = best.ic
    f, e = ic_best.fitness, ic_best.inlier_rmse_m
    pf_best, pff_best = best.pf, best.pff
    amb_ratio, fine_ratio = ctx.amb_ratio, ctx.fine_ratio
    rivals = [h for h in hyps[1:] if "screened out" not in h["source"] and (
              h["distance_to_chosen_m"] > p.ambiguity.distance_m or h["rotation_to_chosen_deg"] > p.ambiguity.angle_deg)
              and h["plane_fitness"] >= amb_ratio * pf_best and h["fine_fitness"] >= fine_ratio * pff_best]
    status, reason, weak = DecisionStatus.OK, _failure(ctx, best), ""
    if reason:
        status = DecisionStatus.FAILED
    elif rivals:
        h = rivals[0]
        status = DecisionStatus.AMBIGUOUS
        reason = (f"another placement {h['distance_to_chosen_m']:.1f} m / {h['rotation_to_chosen_deg']:.1f} deg "
                  f"away fits almost as well (plane fitness {h['plane_fitness']:.3f} vs {pf_best:.3f}, fine "
                  f"agreement {h['fine_fitness']:.3f} vs {pff_best:.3f}, ratios >= "
                  f"{amb_ratio:g} / {fine_ratio:.3g}{' for a small scan' if ctx.scan.small_scan else ''}): the drift "
                  "repeats itself; "
                  "extend the scan past a distinctive feature")
    if status == "ok" and ic_best.degeneracy_ratio < p.verify.degeneracy_ratio:
        # decided after the covariance: a weak direction matters only if it leaves the pose uncertain
        weak = (ic_best.degeneracy_reason or
                f"eigenvalue ratio {ic_best.degeneracy_ratio:.2e} < {p.verify.degeneracy_ratio:g}")
    if status == "ok":
        reason = (f"ICP fitness {f:.3f}, inlier RMSE {e:.3f} m, plane fitness {pf_best:.3f}; "
                  + (f"{len(hyps) - 1} other hypothesis(es) verified, none of them elsewhere reaching "
                     f"{amb_ratio:g} x its plane fitness and {fine_ratio:.3g} x its fine agreement"
                     if len(hyps) > 1 else "no competing hypothesis found by RANSAC"))
    if r0.ambiguity_ratio >= p.ambiguity.ratio and not (status == "ambiguous" and rivals):
        warnings.append(f"RANSAC's runner-up scored {r0.ambiguity_ratio:.2f} of the best; ICP verification "
                        "separated them")
    return Decision(status=status, reason=reason, weak=weak, hyps=hyps, best=best, refined=refined,
                    warnings=warnings)


def verify_and_decide(ctx: VerifyContext, pm: PreparedMap, hy: Hypotheses, trajectory,
                      run: RunContext) -> tuple[Decision, CorrelativeHypotheses | None]:
    """Stages 3-4 with the correlative search of a levelled scan (``LocalizeParams.correlative``).

    ``"always"``: its candidates join RANSAC's before the verification. ``"fallback"``: RANSAC's
    candidates are verified first (allowed to defer) and the search runs when they give no
    ``ok``, or always for a small scan (whose result is always confirmed against the whole map);
    RANSAC's and the search's candidates are then verified together. Returns the decision and
    the search's outcome (None when it did not run); ``icp`` and ``decision`` seconds go to
    ``run.timings``.
    """
    p = ctx.p
    uniq = hy.candidates
    # correlative 4-DOF search (minegeo addition, levelled scans only): proposes places that
    # FPFH + RANSAC cannot (few or no correct descriptor matches); see correlative.py
    use_corr = p.ransac.model == "levelled" and p.correlative is not None
    corr = None
    if use_corr and p.correlative.mode == "always":
        corr = correlative_hypotheses(ctx, pm, uniq, trajectory, run)
        uniq = corr.candidates
    fallback = use_corr and p.correlative.mode == "fallback"
    confirm = fallback and ctx.scan.small_scan
    # a small scan's result is always confirmed against the whole map: no need to decide twice
    if not confirm:
        run.announce("ICP verification")
    dec = Decision(status=DecisionStatus.DEFERRED) if confirm else evaluate(ctx, uniq, hy.r0, pm.work_origin, may_defer=fallback)
    if fallback and (dec.status != "ok" or confirm):
        t_first = dec.t_icp + dec.t_decision
        corr = correlative_hypotheses(ctx, pm, uniq, trajectory, run)
        run.announce("ICP verification")
        dec = evaluate(ctx, corr.candidates, hy.r0, pm.work_origin)
        dec = replace(dec, t_icp=dec.t_icp + t_first)
    run.timings["icp"] = dec.t_icp
    run.timings["decision"] = dec.t_decision
    return dec, corr
