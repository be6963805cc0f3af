"""Benchmark: does the whole-map rival search turn exact twins into ``ambiguous`` without losing ``ok``?

Issue 15: a drift copied exactly onto another level cannot be told apart from the original by
a scan taken in it, yet the pipeline said ``ok`` whenever RANSAC proposed only one of the two
places. ``LocalizeParams.rival`` (:mod:`minegeo.localize.rivals`) searches the whole map
at the chosen attitude before an ``ok``. This script runs every scan twice, **before** (the
search off, ``rival=None``: the previous behaviour) and **after** (on, the default),
on study worlds of :func:`minegeo.synth.study.make_study_world`:

* an **exact-twin world** (``twins="exact"``: level 0 copied 25 m below, roughness and
  structures included): *twin* scans (the middle of a copied drift; the copy re-simulated and
  verified identical within 1 mm) -> count ``ok`` (must be 0 after), ``ambiguous`` with both
  placements listed (the truth and its twin each within ``SUCCESS_M`` of a listed candidate),
  other ``ambiguous``, ``failed``; and *mapped* scans (places without a copy: the decline);
* a **no-twin world** (``twins="none"``, same seed): *mapped* scans.

Each class: lengths 10 m and 20 m, levelled (z up, random heading; ``--levelled 3``) and
unlevelled (uniformly random rotation; the 6-DOF model), ``--n`` scans of each (default 5,
i.e. 20 per class), ZEB-REVO-like walk, 50 000 beams. Parameters: the CLI's own
``params_from_args`` for ``--profile fast`` (+ ``--levelled 3`` for levelled scans), seed 0.
Success = ``ok`` and the placed trajectory within ``SUCCESS_M`` of the truth (largest error
over its poses); wrong ok = ``ok`` and farther (for a twin scan, from both the truth and the
twin). Times: ``localize_scan`` wall time per scan, map prepared and every search structure
(including the rival search's occupancy) built beforehand, Numba compiled beforehand.

Usage::

    python benchmarks/bench_twins.py --out benchmarks/results/twins_2026-11-25      # ~2-4 min

Writes ``OUT.json`` (every run) and ``OUT.md`` (the tables in docs/localization.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

SUCCESS_M = 0.10
LENGTHS = (10.0, 20.0)


def _params(levelled: bool):
    """(PrepareParams, LocalizeParams) exactly as ``minegeo localize --profile fast [--levelled 3]`` builds them."""
    from minegeo.cli import build_parser
    from minegeo.cli.localize import params_from_args

    opts = ["--profile", "fast"] + (["--levelled", "3"] if levelled else [])
    args = build_parser(["localize"]).parse_args(["localize", "--map", "m", "--scan", "s", "--out", "o", *opts])
    return params_from_args(args)


def _err(T, T_true, pts) -> float:
    from minegeo.localize.pipeline import error_vs_truth

    return float(error_vs_truth(T, T_true, pts)["max_point_error_m"])


def _judge(r, sc) -> dict:
    """Status and errors of one result against the scan's truth (and twins)."""
    pts = np.asarray(sc.trajectory.poses)[:, :3, 3]
    e_true = _err(r.T_map_scan, sc.T_map_scan, pts)
    e_twin = min((_err(r.T_map_scan, T, pts) for T in sc.twins_T_map_scan), default=math.inf)
    listed = [np.asarray(h["T_map_scan"]) for h in (r.hypotheses or [])]
    near_true = min((_err(T, sc.T_map_scan, pts) for T in listed), default=math.inf)
    near_twin = min((_err(T, Tw, pts) for T in listed for Tw in sc.twins_T_map_scan), default=math.inf)
    rv = r.rival_search
    br = None if rv is None else rv.get("best_rival")
    return {"status": r.status, "reason": r.reason, "error_m": e_true, "error_to_twin_m": e_twin,
            "listed_nearest_truth_m": near_true, "listed_nearest_twin_m": near_twin,
            "n_listed": len(listed),
            "rival_ran": rv is not None,
            "rival_self_rank": None if rv is None else rv["self_rank"],
            "rival_margin": None if rv is None else rv["margin"],
            "rival_distance_m": None if br is None else br["distance_to_chosen_m"],
            "rival_score": None if br is None else br["plane_fitness"],
            "rival_score_level": None if br is None else br["score_level"],
            "rival_source": None if br is None else br["source"],
            "rival_covered": None if rv is None else rv["covered"],
            "rival_test": None if br is None else br["test_passed"],
            "rival_matched_ratio": None if br is None else br["matched_ratio"],
            "rival_s": None if rv is None else r.timings_s["rival_search"],
            "rival_timings_s": None if rv is None else {k: v for k, v in r.timings_s.items()
                                                        if k.startswith("rival_search")}}


def run(seed: int, n: int, log=print, rival_params=None, near: int = 0) -> list[dict]:
    import minegeo
    from minegeo.localize import localize_scan, prepare_map
    from minegeo.synth.study import make_study_world

    t0 = time.perf_counter()
    minegeo.warmup()
    log(f"warm-up (Numba cache): {time.perf_counter() - t0:.1f} s")
    records = []
    worlds = [("exact", ("twin", "mapped"), n), ("none", ("mapped",), n)] + ([("near", ("twin",), near)] if near else [])
    for twins, classes, n_w in worlds:
        t1 = time.perf_counter()
        sw = make_study_world(None, twins=twins, seed=seed)
        t_world = time.perf_counter() - t1
        log(f"world twins={twins} seed {seed}: {len(sw.map)} map points, {t_world:.1f} s")
        for levelled in (True, False):
            prep, lp = _params(levelled)
            if rival_params is not None:
                lp = dataclasses.replace(lp, rival=rival_params)
            t1 = time.perf_counter()
            pm = prepare_map(sw.map, prep)
            t_prep = time.perf_counter() - t1
            t1 = time.perf_counter()
            pm.build_indexes(lp)
            cp = lp.rival.search
            pm.occupancy(cp)
            pm.screen_target(cp.screen_voxel_size_m)
            if cp.screen_grid and cp.screen_voxel_size_m is not None:
                pm.screen_grid(cp.screen_voxel_size_m)
            t_idx = time.perf_counter() - t1
            configs = (("before", dataclasses.replace(lp, rival=None)), ("after", lp))
            for label in classes:
                for length in LENGTHS:
                    t1 = time.perf_counter()
                    scans = sw.draw_scans(n_w, length, label, levelled=levelled, seed=seed)
                    t_draw = time.perf_counter() - t1
                    for i, sc in enumerate(scans):
                        for name, q in configs:
                            t1 = time.perf_counter()
                            r = localize_scan(pm, sc.cloud, sc.trajectory, q, seed=0)
                            wall = time.perf_counter() - t1
                            rec = {"world": twins, "world_seed": seed, "class": sc.label, "length_m": length,
                                   "levelled": levelled, "index": i, "drift": sc.drift, "s_m": sc.s_m,
                                   "n_points": len(sc.cloud), "n_twins": len(sc.twins_T_map_scan),
                                   "config": name, "localize_s": wall, "map_prepare_s": t_prep,
                                   "map_indexes_s": t_idx, "draw_s": t_draw / max(1, n_w), **_judge(r, sc)}
                            records.append(rec)
                            log(f"{twins:5s} {sc.label:6s} {length:4.0f} m {'lev' if levelled else '6dof'} #{i} "
                                f"{name:6s} {rec['status']:9s} err {rec['error_m']:8.3f} twin "
                                f"{rec['error_to_twin_m']:8.3f} {wall:5.2f} s"
                                + ("" if not rec["rival_ran"] else
                                   f"  rival {rec['rival_s']:.2f} s self#{rec['rival_self_rank']} "
                                   f"margin {rec['rival_margin']:.3f} "
                                   f"at {rec['rival_distance_m'] if rec['rival_distance_m'] is None else round(rec['rival_distance_m'], 1)} m"))
    return records


def _f(v) -> float:
    return math.inf if v is None else float(v)  # JSON writes inf as null


def _good(r) -> bool:
    """ok and within SUCCESS_M of the truth (of the truth or its exact twin: the same scan)."""
    e = _f(r["error_m"]) if r["class"] != "twin" else min(_f(r["error_m"]), _f(r["error_to_twin_m"]))
    return r["status"] == "ok" and e < SUCCESS_M


def summarize(records: list[dict]) -> dict:
    out = {"twin": [], "ordinary": []}
    groups = sorted({(r["world"], r["class"], r["length_m"], r["levelled"]) for r in records},
                    key=lambda g: (g[1] != "twin", g[0], not g[3], g[2]))
    for world, cls, length, lev in groups + [(w, c, None, None) for w, c in sorted({(r["world"], r["class"])
                                                                                    for r in records})]:
        rs = [r for r in records if r["world"] == world and r["class"] == cls
              and (length is None or r["length_m"] == length) and (lev is None or r["levelled"] == lev)]
        row = {"world": world, "class": cls, "length_m": length, "levelled": lev,
               "n": len({(r["length_m"], r["levelled"], r["index"]) for r in rs})}
        for name in ("before", "after"):
            x = [r for r in rs if r["config"] == name]
            t = np.array([r["localize_s"] for r in x]) if x else np.zeros(1)
            amb = [r for r in x if r["status"] == "ambiguous"]
            both = [r for r in amb if _f(r["listed_nearest_truth_m"]) < SUCCESS_M
                    and _f(r["listed_nearest_twin_m"]) < SUCCESS_M]
            row[name] = {"ok": sum(r["status"] == "ok" for r in x), "ok_correct": sum(_good(r) for r in x),
                         "wrong_ok": sum(r["status"] == "ok" and not _good(r) for r in x),
                         "ambiguous": len(amb), "ambiguous_twin_listed": len(both),
                         "failed": sum(r["status"] == "failed" for r in x),
                         "median_s": float(np.median(t)), "max_s": float(t.max())}
        b = {(r["length_m"], r["levelled"], r["index"]): r for r in rs if r["config"] == "before"}
        add = np.array([r["localize_s"] - b[(r["length_m"], r["levelled"], r["index"])]["localize_s"]
                        for r in rs if r["config"] == "after"])
        rv = np.array([r["rival_s"] for r in rs if r["config"] == "after" and r["rival_ran"]])
        row["added_s_median"] = float(np.median(add)) if add.size else math.nan
        row["added_s_max"] = float(add.max()) if add.size else math.nan
        row["rival_s_median"] = float(np.median(rv)) if rv.size else math.nan
        row["rival_s_max"] = float(rv.max()) if rv.size else math.nan
        row["rival_runs"] = int(rv.size)
        margins = [r["rival_margin"] for r in rs if r["config"] == "after" and r["status"] == "ok"
                   and r["rival_margin"] is not None]
        row["ok_margin_min"] = float(min(margins)) if margins else math.nan
        row["self_not_found"] = sum(1 for r in rs if r["config"] == "after" and r["rival_ran"]
                                    and r["rival_self_rank"] is None)
        row["before_median_s"] = row["before"]["median_s"]
        (out["twin"] if cls in ("twin", "near_twin") else out["ordinary"]).append(row)
    return out


def _s(v) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.2f}"


def _g(row) -> str:
    if row["length_m"] is None:
        return "**all**"
    return f"{row['length_m']:.0f} m, {'levelled' if row['levelled'] else 'unlevelled (6-DOF)'}"


def markdown(summary: dict, seed: int, n: int) -> str:
    lines = [f"Study worlds `make_study_world(twins=..., seed={seed})` (small layout, 2 levels 25 m apart, "
             "map one VLP-16 frame every 10 m); ZEB-REVO-like walks, 50 000 beams; "
             f"{n} scans per length x frame; `--profile fast` (+ `--levelled 3` for levelled scans), seed 0; "
             "before = `rival=None`, after = the default. Success = `ok` within "
             f"{SUCCESS_M:.2f} m of the truth (or of its twin); twin listed = `ambiguous` with the truth and "
             f"the twin each within {SUCCESS_M:.2f} m of a listed candidate. Times: `localize_scan` wall s, "
             "map and its search structures prepared beforehand; shared 2-core machine.", "",
             "**Twins** (class `twin` of the exact-twin world; `near_twin`: world `twins=\"near\"`, same layout, "
             "other rock, which a scan can tell apart; `ok+correct` there = within 0.10 m of the truth):", "",
             "| world | scans | n | before: ok (ok+correct) / ambiguous (twin listed) / failed | after: ok (ok+correct) / "
             "ambiguous (twin listed) / failed | before / after: median s | after: max s | rival search median / "
             "max s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in summary["twin"]:
        b, a = r["before"], r["after"]
        lines.append(f"| {r['world']} | {_g(r)} | {r['n']} | {b['ok']} ({b['ok_correct']}) / {b['ambiguous']} "
                     f"({b['ambiguous_twin_listed']}) / {b['failed']} | {a['ok']} ({a['ok_correct']}) / "
                     f"{a['ambiguous']} ({a['ambiguous_twin_listed']}) / {a['failed']} | {b['median_s']:.2f} / "
                     f"{a['median_s']:.2f} | {a['max_s']:.2f} | {_s(r['rival_s_median'])} / {_s(r['rival_s_max'])} |")
    lines += ["", "**Ordinary mapped scans** (class `mapped`; in the exact-twin world: the decline, which has "
              "no copy):", "",
              "| world | scans | n | before: ok+correct / wrong ok / ambiguous / failed | after: ok+correct / "
              "wrong ok / ambiguous / failed | added s per scan median / max | rival search median / max s "
              "(runs) | before / after: median s | after: max s | smallest margin of an `ok` |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in summary["ordinary"]:
        b, a = r["before"], r["after"]
        lines.append(f"| {r['world']} | {_g(r)} | {r['n']} | {b['ok_correct']} / {b['wrong_ok']} / {b['ambiguous']} "
                     f"/ {b['failed']} | {a['ok_correct']} / {a['wrong_ok']} / {a['ambiguous']} / {a['failed']} | "
                     f"{r['added_s_median']:+.2f} / {r['added_s_max']:+.2f} | {_s(r['rival_s_median'])} / "
                     f"{_s(r['rival_s_max'])} ({r['rival_runs']}) | {b['median_s']:.2f} / {a['median_s']:.2f} | "
                     f"{a['max_s']:.2f} | {_s(r['ok_margin_min'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="study world seed (default 1)")
    ap.add_argument("--n", type=int, default=5, help="scans per length x frame and class (default 5)")
    ap.add_argument("--near", type=int, default=0,
                    help="also NEAR twin scans (world twins='near') per length x frame (default 0)")
    ap.add_argument("--out", default="benchmarks/results/twins", help="output stem: OUT.json and OUT.md")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    records = run(a.seed, a.n, near=a.near)
    summary = summarize(records)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from minegeo._provenance import to_jsonable, versions

    doc = {"seed": a.seed, "n": a.n, "success_threshold_m": SUCCESS_M, "summary": summary, "records": records,
           "wall_s": time.perf_counter() - t0, "machine": platform.platform(), "versions": versions()}
    out.with_suffix(".json").write_text(json.dumps(to_jsonable(doc), indent=1, allow_nan=True) + "\n")
    md = markdown(summary, a.seed, a.n)
    out.with_suffix(".md").write_text(md)
    print(md)
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
