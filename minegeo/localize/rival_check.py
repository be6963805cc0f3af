"""Stage 4a of :func:`~minegeo.localize.localize_scan`: no ``ok`` before the whole-map rival search.

Around an ``ok`` decision, :func:`rival_check` runs :func:`~minegeo.localize.rivals.search_rivals`
(the exhaustive correlative search at the chosen attitude) with the pipeline's own ICP and
verification (:mod:`minegeo.localize.verification`), pools its verified rivals with the pipeline's
own distinct hypotheses, and applies :func:`~minegeo.localize.rivals.rival_test` (plane fitness
at both tolerances, or the support-matched ratio). :func:`check_rivals` adds the one switch: a
rival that fits clearly better than the first choice is verified like every candidate and, if
it wins, searched around in turn (once).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from minegeo.localize.decision import Decision, DecisionStatus, evaluate
from minegeo.localize.hypotheses import reference_point
from minegeo.localize.prepared import PreparedMap
from minegeo.localize.rivals import RivalSearch, matched_support, rival_test, search_rivals
from minegeo.localize.run_context import RunContext
from minegeo.localize.scan import from_map, to_map
from minegeo.localize.verification import Candidate, VerifyContext, refine_and_verify

__all__ = ["RivalCheck", "rival_check", "check_rivals", "REJECTED_RIVAL"]

#: Label of the best rival of an ``ok`` result (``result.json`` ``rival_search.best_rival.note``).
REJECTED_RIVAL = ("NOT a position: the strongest other placement of the scan, checked and rejected by the "
                  "whole-map rival search (kept to show the margin)")


@dataclass(frozen=True)
class RivalCheck:
    """Outcome of :func:`rival_check`: the new ``status`` / ``reason``, the
    ``LocalizationResult.rival_search`` ``record`` (no times), the hypotheses with the search's
    verified rivals appended (``hyps``) and the warnings it raised."""

    status: DecisionStatus
    reason: str
    record: dict
    hyps: list
    warnings: list


def _masks(ctx: VerifyContext, P: np.ndarray, Ts: list) -> list:
    """Per point of ``P`` at each placement: map point within the gate, within the plane
    tolerance of its tangent plane and within the fine tolerance (the numbers of
    :func:`~minegeo.localize.verification.verify`, one KD-tree query)."""
    Qf, Nf, tol, tol_fine = ctx.Qf, ctx.Nf, ctx.tol, ctx.tol_fine
    n = P.shape[0]
    X = np.concatenate([P @ T[:3, :3].T + T[:3, 3] for T in Ts])
    _, idx = ctx.tree.query(X, k=1, distance_upper_bound=ctx.gate)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    sup = idx < Qf.shape[0]
    r = np.full(X.shape[0], np.inf)
    j = idx[sup]
    r[sup] = np.abs(np.einsum("ij,ij->i", X[sup] - Qf[j], Nf[j]))
    on = r < tol
    on_f = r < (tol if tol_fine is None else tol_fine)
    return [(sup[k * n:(k + 1) * n], on[k * n:(k + 1) * n], on_f[k * n:(k + 1) * n]) for k in range(len(Ts))]


def _search(ctx: VerifyContext, pm: PreparedMap, Tb: np.ndarray, trajectory, fine_scale, run: RunContext) -> RivalSearch:
    """:func:`~minegeo.localize.rivals.search_rivals` around ``Tb`` with the pipeline's ICP and
    verification (its draws from ``run.stage_seed("rivals")``); its map structures and parts timed into
    ``run.timings`` (``rival_search_*``)."""
    timings = run.timings
    p, sf = ctx.p, ctx.scan
    rp = p.rival
    cp = rp.search
    t0 = time.perf_counter()
    occ = pm.occupancy(cp)
    screen_target = pm.screen_target(cp.screen_voxel_size_m)
    screen_grid = (pm.screen_grid(cp.screen_voxel_size_m)
                   if cp.screen_grid and cp.screen_voxel_size_m is not None else None)
    timings["rival_search_map_structures"] = time.perf_counter() - t0

    def _support(Ts, level):
        return _masks(ctx, sf.feature_points if level == "feature" else sf.icp_points, Ts) if Ts else []

    rs = search_rivals(occ, sf.feature_points, sf.feature_normals, Tb, params=rp, seed=run.stage_seed("rivals"), centre=sf.centre,
                       ambiguity_distance_m=float(p.ambiguity.distance_m),
                       ambiguity_angle_deg=float(p.ambiguity.angle_deg), support=_support,
                       fine=lambda T: refine_and_verify(ctx, sf.icp_points, T),
                       reference_point=reference_point(trajectory, sf.scan_origin),
                       refine_target=(pm.target_index(), ctx.Qf, ctx.Nf), screen_target=screen_target,
                       screen_grid=screen_grid, fine_scale=fine_scale)
    parts = rs.timings_s.get("search_parts", {})
    timings["rival_search_grid"] = parts.get("setup", 0.0) + parts.get("score", 0.0) + parts.get("select", 0.0)
    timings["rival_search_refine"] = parts.get("refine", 0.0)
    timings["rival_search_checks"] = sum(rs.timings_s.get(k, 0.0) for k in ("precheck", "fine"))
    return rs


def _rival_hypotheses(rs: RivalSearch, hyps: list, tm) -> list:
    """The search's fully verified rivals as hypothesis records (source ``"rival search #k"``)."""
    out = []
    for c in rs.candidates:
        if c.stage != "fine":
            continue
        out.append({
            "rank": len(hyps) + len(out), "source": f"rival search #{c.rank}" + (
                "" if c.distinct else " (ICP brought it onto the chosen placement)"),
            "ransac_fitness": math.nan, "ransac_inlier_rmse_m": math.nan, "icp_fitness": c.icp_fitness,
            "icp_inlier_rmse_m": c.icp_inlier_rmse_m, "icp_iterations": c.icp_iterations,
            "plane_fitness": c.plane_fitness, "plane_rmse_m": c.plane_rmse_m, "fine_fitness": c.fine_fitness,
            "distance_to_chosen_m": c.final_distance_m, "rotation_to_chosen_deg": c.final_rotation_deg,
            "common_fraction": c.common_fraction, "matched_ratio": c.matched_ratio,
            "T_map_scan": tm(c.T_final)})
    return out


def _pool(ctx: VerifyContext, rs: RivalSearch, own_hyps: list, Tb: np.ndarray, chosen: tuple, fine_scale, tm, fm):
    """Every distinct scored placement other than the chosen one: the search's (at the deepest
    stage it reached) and the pipeline's own fully verified hypotheses (support-matched against
    the chosen one too: their records gain ``common_fraction`` and ``matched_ratio``)."""
    p = ctx.p
    pf_best, pff_best = chosen
    pool = []
    for c in rs.candidates:
        if c.stage == "fine" and c.distinct:
            pool.append({"source": f"rival search #{c.rank}", "score_level": "full", "T_map_scan": tm(c.T_final),
                         "plane_fitness": c.plane_fitness, "chosen_plane_fitness": pf_best,
                         "fine_fitness": c.fine_fitness, "chosen_fine_fitness": pff_best,
                         "common_fraction": c.common_fraction, "matched_ratio": c.matched_ratio,
                         "distance_to_chosen_m": c.final_distance_m, "rotation_to_chosen_deg": c.final_rotation_deg})
        elif c.stage == "precheck" and c.distinct:
            pool.append({"source": f"rival search #{c.rank}", "score_level": "pre-check",
                         "T_map_scan": tm(c.T_search), "plane_fitness": c.precheck,
                         "chosen_plane_fitness": rs.precheck_self, "fine_fitness": math.nan,
                         "chosen_fine_fitness": math.nan, "common_fraction": c.pre_common_fraction,
                         "matched_ratio": c.pre_matched_ratio, "distance_to_chosen_m": c.distance_m,
                         "rotation_to_chosen_deg": c.rotation_deg})
    own = [h for h in own_hyps[1:] if "screened out" not in h["source"]
           and (h["distance_to_chosen_m"] > p.ambiguity.distance_m or h["rotation_to_chosen_deg"] > p.ambiguity.angle_deg)]
    if own:
        m = _masks(ctx, ctx.scan.icp_points, [Tb] + [fm(h["T_map_scan"]) for h in own])
        for h, mk in zip(own, m[1:], strict=True):
            frac, ratio = matched_support(m[0], mk, fine_scale=fine_scale)
            h["common_fraction"], h["matched_ratio"] = frac, ratio
            pool.append({"source": h["source"], "score_level": "full", "T_map_scan": np.asarray(h["T_map_scan"]),
                         "plane_fitness": h["plane_fitness"], "chosen_plane_fitness": pf_best,
                         "fine_fitness": h["fine_fitness"], "chosen_fine_fitness": pff_best,
                         "common_fraction": frac, "matched_ratio": ratio,
                         "distance_to_chosen_m": h["distance_to_chosen_m"],
                         "rotation_to_chosen_deg": h["rotation_to_chosen_deg"]})
    return pool


def _rank_pool(ctx: VerifyContext, pool: list, pf_best: float, pff_best: float) -> None:
    """Score every pooled rival in place (``margin``, ``test_passed``, ``closeness``: how close to
    either test, 1 = on a threshold) and sort the pool, the rival closest to a test first."""
    rp = ctx.p.rival
    amb_ratio, fine_ratio = ctx.amb_ratio, ctx.fine_ratio
    for b in pool:
        b["margin"] = (b["chosen_plane_fitness"] / b["plane_fitness"]) if b["plane_fitness"] > 0 else math.inf
        b["test_passed"] = rival_test(pf_best, b["plane_fitness"], b["common_fraction"], b["matched_ratio"],
                                      amb_ratio, rp, chosen_fine_fitness=pff_best,
                                      fine_fitness=b["fine_fitness"], fine_ratio=fine_ratio) \
            if b["score_level"] == "full" else ""
        # how close to either test (1 = on a threshold)
        closeness = b["plane_fitness"] / (amb_ratio * b["chosen_plane_fitness"]) if b["chosen_plane_fitness"] > 0 else 0
        if math.isfinite(b["fine_fitness"]) and b["chosen_fine_fitness"] > 0:  # both tolerances must pass
            closeness = min(closeness, b["fine_fitness"] / (fine_ratio * b["chosen_fine_fitness"]))
        if b["common_fraction"] >= rp.min_common_fraction and math.isfinite(b["matched_ratio"]):
            closeness = max(closeness, b["matched_ratio"] / rp.matched_ratio)
        b["closeness"] = float(closeness)
    pool.sort(key=lambda b: (not b["test_passed"], -b["closeness"], b["source"]))


def _record(ctx: VerifyContext, rs: RivalSearch, best_r: dict | None, pf_best: float, pff_best: float, tm) -> dict:
    """``LocalizationResult.rival_search``: the search's record, the ratios and the best rival."""
    rp = ctx.p.rival
    amb_ratio = ctx.amb_ratio
    record = {**rs.to_dict(tm), "ambiguity_ratio": amb_ratio, "chosen_plane_fitness": pf_best,
              "fine_ambiguity_ratio": ctx.fine_ratio, "chosen_fine_fitness": pff_best,
              "fine_tolerance_m": ctx.tol_fine,
              "margin": best_r["margin"] if best_r else math.inf,
              "matched_ratio": best_r["matched_ratio"] if best_r else math.nan,
              "margin_note": ("margin = chosen / best rival plane fitness, both scored the same way (score_level: "
                              "'full' = after the full-resolution ICP, 'pre-check' = feature-level points, the rival "
                              "at the search's refined placement without ICP, for rivals out of reach of both tests "
                              "there); the result is "
                              f"ambiguous when a fully verified rival reaches the ambiguity ratio (margin <= "
                              f"{1.0 / amb_ratio:.3f}) or, on the points the map covers at both placements (common "
                              f"fraction >= {rp.min_common_fraction:g}), {rp.matched_ratio:g} of the chosen "
                              "placement's agreement (matched_ratio); best_rival = the rival closest to either test"),
              "best_rival": None}
    if best_r is not None:
        T = best_r["T_map_scan"]
        record["best_rival"] = {"note": REJECTED_RIVAL, **best_r, "origin_map_m": T[:3, 3].tolist()}
    return record


def _coverage_warnings(rs: RivalSearch) -> list[str]:
    """What the search could not guarantee for this scan."""
    if not rs.self_found:
        return ["the whole-map rival search did not recover the chosen placement itself among its "
                f"{len(rs.candidates)} candidates ({rs.reason or 'ranked lower'}): its guarantee does not hold "
                "for this scan"]
    if not rs.covered:
        return ["the whole-map rival search kept fewer placements than reach the chosen placement's own "
                "score minus its slack at some stage (caps; result.json rival_search.coverage): a rival "
                "scoring like the chosen placement may not have been checked"]
    return []


def _verdict(ctx: VerifyContext, best_r: dict | None, reason: str, pf_best: float, pff_best: float) -> tuple[DecisionStatus, str]:
    """``("ambiguous", why)`` when the best pooled rival passes a test, else ``("ok", reason + margin)``."""
    rp = ctx.p.rival
    amb_ratio, fine_ratio = ctx.amb_ratio, ctx.fine_ratio
    if best_r is not None and best_r["test_passed"]:
        b = best_r
        how = (f"plane fitness {b['plane_fitness']:.3f} vs {pf_best:.3f}, fine agreement {b['fine_fitness']:.3f} vs "
               f"{pff_best:.3f}, ratios >= {amb_ratio:g} / {fine_ratio:.3g}"
               f"{' for a small scan' if ctx.scan.small_scan else ''}" if b["test_passed"] == "plane fitness" else
               f"on the {100 * b['common_fraction']:.0f} % of scan points that the map covers at both places, its "
               f"share on the map surface is {b['matched_ratio']:.2f} of the chosen placement's, >= "
               f"{rp.matched_ratio:g}; plane fitness {b['plane_fitness']:.3f} vs {pf_best:.3f} only because the map "
               "covers the two places differently")
        where = ("the whole-map rival search at the chosen attitude" if b["source"].startswith("rival")
                 else "the hypotheses")
        return DecisionStatus.AMBIGUOUS, (
            f"another placement {b['distance_to_chosen_m']:.1f} m / {b['rotation_to_chosen_deg']:.1f} deg away, found "
            f"by {where}, fits almost as well ({how}): the scan cannot tell the two places apart (a repeated drift "
            "or level); extend the scan past a distinctive feature")
    if best_r is None:
        return DecisionStatus.OK, reason + "; whole-map rival search at its attitude: no other placement found"
    return DecisionStatus.OK, reason + (
        f"; best rival (whole-map search at its attitude and the hypotheses) "
        f"{best_r['distance_to_chosen_m']:.1f} m away, plane fitness {best_r['plane_fitness']:.3f} against "
        f"{best_r['chosen_plane_fitness']:.3f} ({best_r['score_level']} level; margin {best_r['margin']:.2f}, "
        f"ambiguous at <= {1.0 / amb_ratio:.2f}; support-matched {best_r['matched_ratio']:.2f}, ambiguous "
        f"at >= {rp.matched_ratio:g})")


def rival_check(ctx: VerifyContext, pm: PreparedMap, dec: Decision, trajectory, run: RunContext) -> RivalCheck:
    """The whole-map rival search around the ``ok`` decision ``dec``.

    ``ambiguous`` when a distinct, fully verified placement other than the chosen one (the
    search's or the pipeline's own hypotheses) passes :func:`~minegeo.localize.rivals.rival_test`;
    otherwise ``ok`` with the best rival and the margin added to the reason. The record holds no
    times (equal inputs give an equal record); the times go to ``run.timings`` (``rival_search_*``).
    """
    sf = ctx.scan
    pf_best, pff_best = float(dec.best.pf), float(dec.best.pff)
    fine_scale = ctx.amb_ratio / ctx.fine_ratio if ctx.tol_fine is not None else None
    Tb = dec.ic_best.T_target_source
    rs = _search(ctx, pm, Tb, trajectory, fine_scale, run)

    def tm(T):
        return to_map(T, sf.scan_origin, pm.work_origin)

    def fm(T):
        return from_map(T, sf.scan_origin, pm.work_origin)

    hyps = dec.hyps + _rival_hypotheses(rs, dec.hyps, tm)
    pool = _pool(ctx, rs, dec.hyps, Tb, (pf_best, pff_best), fine_scale, tm, fm)
    _rank_pool(ctx, pool, pf_best, pff_best)
    best_r = pool[0] if pool else None
    record = _record(ctx, rs, best_r, pf_best, pff_best, tm)
    status, reason = _verdict(ctx, best_r, dec.reason, pf_best, pff_best)
    return RivalCheck(status=status, reason=reason, record=record, hyps=hyps, warnings=_coverage_warnings(rs))


def check_rivals(ctx: VerifyContext, pm: PreparedMap, dec: Decision, r0, trajectory,
                 run: RunContext) -> tuple[Decision, dict]:
    """Stage 4a: the rival check of an ``ok`` decision, and its one switch.

    When the search finds a placement that fits better than the first choice, by so much at the
    fine level that the first choice would not be *its* rival, it is verified with the pipeline's
    own candidates and, if it wins there, searched around in turn (once; it never switches back).
    Returns the decision (status and reason after the check) and the rival record; appends to
    ``run.warnings`` and ``run.timings`` (``rival_search``, ``rival_switch``).
    """
    warnings, timings = run.warnings, run.timings
    run.announce("rival search")
    t0 = time.perf_counter()
    rc = rival_check(ctx, pm, dec, trajectory, run)
    warnings.extend(rc.warnings)
    timings["rival_search"] = time.perf_counter() - t0
    out = replace(dec, status=rc.status, reason=rc.reason, hyps=rc.hyps)
    record = rc.record
    b = (record or {}).get("best_rival")
    pf0, pff0 = float(dec.best.pf), float(dec.best.pff)
    amb_ratio, fine_ratio = ctx.amb_ratio, ctx.fine_ratio
    if (rc.status == "ambiguous" and ctx.tol_fine is not None and b is not None and b.get("score_level") == "full"
            and b["plane_fitness"] >= amb_ratio * pf0 and b["fine_fitness"] * fine_ratio > pff0):
        t0 = time.perf_counter()
        T_r = from_map(b["T_map_scan"], ctx.scan.scan_origin, pm.work_origin)
        first = (f"{b['distance_to_chosen_m']:.1f} m from the first choice, plane fitness {b['plane_fitness']:.3f} "
                 f"vs {pf0:.3f}, fine agreement {b['fine_fitness']:.3f} vs {pff0:.3f}")
        ev2 = evaluate(ctx, list(dec.uniq) + [Candidate("rival search: fits better than the first choice", T_r,
                                                        math.nan, math.nan)], r0, pm.work_origin)
        if ev2.status == "ok" and ev2.best[0].startswith("rival search"):
            warnings.extend(ev2.warnings)
            rc2 = rival_check(ctx, pm, ev2, trajectory, run)
            warnings.extend(rc2.warnings)
            out = replace(ev2, status=rc2.status, reason=rc2.reason, hyps=rc2.hyps)
            record = rc2.record
            warnings.append(f"the whole-map rival search found a placement that fits better than the first "
                            f"choice ({first}); it was verified like every candidate and chosen")
        timings["rival_switch"] = time.perf_counter() - t0
    return out, record
