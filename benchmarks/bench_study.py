"""Acceptance study of issue 15: does ``minegeo localize`` say ``ok`` only when it is right, on
every kind of wall, and is its 95 % region honest?

Worlds (:func:`minegeo.synth.study.make_study_world`, seeds the tests do not use):

* **grid**: wall roughness 0.05 / 0.08 / 0.25 m (shotcrete-smooth to blasted) x scan length
  10 / 20 / 30 m x levelled (z up within an IMU error of ``--tilt-sigma-deg``, random heading;
  ``--levelled 3``) / unlevelled (uniformly random rotation: the CLI's default 6-DOF model);
  ``--n`` scans per cell, ZEB-REVO-like walks, 50 000 beams;
* **twins**: a world whose level 0 is copied exactly 25 m below (``twins="exact"``); scans of the
  middle of a copied drift (verified identical within 1 mm): must never be ``ok``, and
  ``ambiguous`` with the truth and the twin each within ``SUCCESS_M`` of a listed candidate;
* **unmapped**: a world with drifts the map does not hold (``unmapped=2``); scans of those
  drifts: must never be ``ok``.

The survey map: ``map_passes=4`` (a VLP-16 frame every 2.5 m of every drift, ~10^6 points), a
mobile-mapping density (Baek et al. 2022: 9.2 x 10^7 raw points); with one frame per 10 m the
correct placements of rough walls reach only 70-80 % plane fitness (docs/localization.md).

Parameters: the CLI's own ``params_from_args`` (``--profile fast``; ``--levelled 3`` for the
levelled cells), seed 0. Success = ``ok`` and every trajectory pose within ``SUCCESS_M`` of the
truth; wrong ok = ``ok`` and farther. Uncertainty: *coverage* = share of correct ``ok`` results
whose scan-origin error ``e`` lies inside the reported 95 % ellipsoid (``e^T P^-1 e <=
chi2_3(0.95) = 7.815``, ``P = position_cov_3x3``); *ratio* = median ``position_95_radius_m`` /
RMS scan-origin error of the cell. Times: ``localize_scan`` wall time with the map prepared and
its search structures built, Numba compiled beforehand; per-stage medians from ``timings_s``.

Usage::

    python benchmarks/bench_study.py --seed 21 --n 20 --out benchmarks/results/study_2026-11-25

Writes ``OUT.json`` (every run) and ``OUT.md`` (the tables of docs/localization.md).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_twins import _err, _params  # noqa: E402  (the CLI's own parameters)

SUCCESS_M = 0.10
CHI2_3_95 = 7.814727903251178
ROUGHNESS = (0.05, 0.08, 0.25)
LENGTHS = (10.0, 20.0, 30.0)
STAGES = ("downsample", "normals", "fpfh", "ransac", "correlative", "icp", "decision", "rival_search", "polish",
          "covariance", "gravity")


def _record(r, sc, wall: float, **meta) -> dict:
    pts = np.asarray(sc.trajectory.poses)[:, :3, 3]
    e = _err(r.T_map_scan, sc.T_map_scan, pts)
    e_twin = min((_err(r.T_map_scan, T, pts) for T in sc.twins_T_map_scan), default=math.inf)
    listed = [np.asarray(h["T_map_scan"]) for h in (r.hypotheses or [])]
    near_true = min((_err(T, sc.T_map_scan, pts) for T in listed), default=math.inf)
    near_twin = min((_err(T, Tw, pts) for T in listed for Tw in sc.twins_T_map_scan), default=math.inf)
    d_origin = np.asarray(r.T_map_scan)[:3, 3] - np.asarray(sc.T_map_scan)[:3, 3]
    maha = math.nan
    if r.position_cov_3x3 is not None:
        try:
            maha = float(d_origin @ np.linalg.solve(np.asarray(r.position_cov_3x3), d_origin))
        except np.linalg.LinAlgError:
            maha = math.inf
    return {**meta, "status": r.status, "reason": r.reason, "error_m": e, "error_to_twin_m": e_twin,
            "origin_error_m": float(np.linalg.norm(d_origin)), "origin_error_xyz_m": d_origin.tolist(),
            "mahalanobis2": maha, "position_95_radius_m": float(r.position_95_radius_m),
            "horizontal_95_radius_m": float(r.horizontal_95_radius_m),
            "position_sigma_m": np.asarray(r.position_sigma_m, dtype=float).tolist(),
            "listed_nearest_truth_m": near_true, "listed_nearest_twin_m": near_twin,
            "n_points": int(len(sc.cloud)), "localize_s": wall,
            "timings_s": {k: float(v) for k, v in r.timings_s.items() if isinstance(v, (int, float))},
            "gravity": getattr(r, "gravity", None)}


def _prepare(sw, levelled: bool):
    from minegeo.localize import prepare_map

    prep, lp = _params(levelled)
    t0 = time.perf_counter()
    pm = prepare_map(sw.map, prep)
    t_prep = time.perf_counter() - t0
    t0 = time.perf_counter()
    pm.build_indexes(lp)
    cp = lp.rival.search
    pm.occupancy(cp)
    pm.occupancy(lp.correlative.search)
    pm.screen_target(cp.screen_voxel_size_m)
    if cp.screen_grid and cp.screen_voxel_size_m is not None:
        pm.screen_grid(cp.screen_voxel_size_m)
    return pm, lp, t_prep, time.perf_counter() - t0


def run(seed: int, n: int, n_twins: int, n_unmapped: int, roughness=ROUGHNESS, lengths=LENGTHS,
        tilt_sigma_deg: float = 1.0, log=print) -> list[dict]:
    import minegeo
    from minegeo.localize import localize_scan
    from minegeo.synth.study import make_study_world

    t0 = time.perf_counter()
    minegeo.warmup()
    log(f"warm-up (Numba cache): {time.perf_counter() - t0:.1f} s")
    records: list[dict] = []

    def _go(sw, label, rough, length, levelled, count, pm, lp, t_prep, t_idx, group):
        scans = sw.draw_scans(count, length, label, levelled=levelled, seed=seed,
                              tilt_sigma_deg=tilt_sigma_deg if levelled else 0.0)
        for i, sc in enumerate(scans):
            t1 = time.perf_counter()
            r = localize_scan(pm, sc.cloud, sc.trajectory, lp, seed=0)
            wall = time.perf_counter() - t1
            rec = _record(r, sc, wall, group=group, cls=label, roughness_m=rough, length_m=length,
                          levelled=levelled, index=i, drift=sc.drift, n_twins=len(sc.twins_T_map_scan),
                          map_prepare_s=t_prep, map_indexes_s=t_idx)
            records.append(rec)
            log(f"{group:8s} r={rough} {length:4.0f} m {'lev ' if levelled else '6dof'} #{i:2d} {rec['status']:9s} "
                f"err {rec['error_m']:8.3f} r95 {rec['position_95_radius_m']:.3f} {wall:5.2f} s")

    for rough in roughness:
        sw = make_study_world(rough, twins="none", seed=seed, map_passes=4)
        for levelled in (True, False):
            pm, lp, t_prep, t_idx = _prepare(sw, levelled)
            for length in lengths:
                _go(sw, "mapped", rough, length, levelled, n, pm, lp, t_prep, t_idx, "grid")
    if n_twins:
        sw = make_study_world(None, twins="exact", seed=seed, map_passes=4)
        per = max(1, n_twins // 4)
        for levelled in (True, False):
            pm, lp, t_prep, t_idx = _prepare(sw, levelled)
            for length in (10.0, 20.0):
                _go(sw, "twin", None, length, levelled, per, pm, lp, t_prep, t_idx, "twins")
    if n_unmapped:
        sw = make_study_world(None, unmapped=2, seed=seed, map_passes=4)
        per = max(1, n_unmapped // 4)
        for levelled in (True, False):
            pm, lp, t_prep, t_idx = _prepare(sw, levelled)
            for length in (10.0, 20.0):
                _go(sw, "unmapped", None, length, levelled, per, pm, lp, t_prep, t_idx, "unmapped")
    return records


def _f(v) -> float:
    return math.inf if v is None else float(v)


def _good(r) -> bool:
    return r["status"] == "ok" and _f(r["error_m"]) < SUCCESS_M


def _cell(rs: list[dict]) -> dict:
    n = len(rs)
    good = [r for r in rs if _good(r)]
    t = np.array([r["localize_s"] for r in rs]) if rs else np.zeros(1)
    out = {"n": n, "ok_correct": len(good), "wrong_ok": sum(r["status"] == "ok" and not _good(r) for r in rs),
           "ambiguous": sum(r["status"] == "ambiguous" for r in rs),
           "failed": sum(r["status"] == "failed" for r in rs),
           "success": len(good) / n if n else math.nan,
           "median_s": float(np.median(t)), "max_s": float(t.max())}
    m = np.array([_f(r["mahalanobis2"]) for r in good])
    out["coverage"] = float(np.mean(m <= CHI2_3_95)) if good else math.nan
    out["coverage_ball"] = float(np.mean([r["origin_error_m"] <= r["position_95_radius_m"] for r in good])) \
        if good else math.nan
    e = np.array([r["origin_error_m"] for r in good])
    rad = np.array([r["position_95_radius_m"] for r in good])
    out["rms_origin_error_m"] = float(np.sqrt(np.mean(e ** 2))) if good else math.nan
    out["median_r95_m"] = float(np.median(rad)) if good else math.nan
    out["ratio_r95_rms"] = out["median_r95_m"] / out["rms_origin_error_m"] if good and out["rms_origin_error_m"] > 0 \
        else math.nan
    out["stages_median_s"] = {s: float(np.median([r["timings_s"].get(s, 0.0) for r in rs])) for s in STAGES} \
        if rs else {}
    return out


def summarize(records: list[dict]) -> dict:
    grid = []
    for rough in sorted({r["roughness_m"] for r in records if r["group"] == "grid"}):
        for lev in (True, False):
            for length in sorted({r["length_m"] for r in records if r["group"] == "grid"}):
                rs = [r for r in records if r["group"] == "grid" and r["roughness_m"] == rough
                      and r["levelled"] == lev and r["length_m"] == length]
                if rs:
                    grid.append({"roughness_m": rough, "levelled": lev, "length_m": length, **_cell(rs)})
    g = [r for r in records if r["group"] == "grid"]
    out = {"grid": grid, "grid_all": _cell(g) if g else None}
    tw = [r for r in records if r["group"] == "twins"]
    if tw:
        amb = [r for r in tw if r["status"] == "ambiguous"]
        both = [r for r in amb if _f(r["listed_nearest_truth_m"]) < SUCCESS_M
                and _f(r["listed_nearest_twin_m"]) < SUCCESS_M]
        out["twins"] = {**_cell(tw), "ok": sum(r["status"] == "ok" for r in tw), "ambiguous_twin_listed": len(both)}
    um = [r for r in records if r["group"] == "unmapped"]
    if um:
        out["unmapped"] = {**_cell(um), "ok": sum(r["status"] == "ok" for r in um)}
    return out


def _p(x) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{100 * x:.0f} %"


def _s(x, d=2) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{d}f}"


def markdown(summary: dict, meta: dict) -> str:
    L = [f"Study worlds `make_study_world(roughness, seed={meta['seed']}, map_passes=4)`; ZEB-REVO-like walks, "
         f"50 000 beams; {meta['n']} scans per cell; levelled = z up within |N(0, {meta['tilt_sigma_deg']} deg)|, "
         "`--levelled 3`; unlevelled = uniformly random rotation, the default 6-DOF model; `--profile fast`, seed 0. "
         f"Success = `ok` and every trajectory pose within {SUCCESS_M:.2f} m of the truth. Coverage = correct `ok` "
         "scans whose scan-origin error is inside the reported 95 % ball (`position_95_radius_m`) / inside the 95 % "
         "ellipsoid of `position_cov_3x3`; ratio = median 95 % radius / RMS "
         "scan-origin error. Times: `localize_scan` wall s per scan, map prepared; "
         f"{meta['machine']}.", "",
         "| roughness | frame | length | n | ok+correct | wrong ok | ambiguous | failed | success | coverage ball / ellipsoid | "
         "median r95 / RMS error | median r95 mm | RMS error mm | median / max s |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in summary["grid"]:
        L.append(f"| {c['roughness_m']:.2f} m | {'levelled' if c['levelled'] else 'unlevelled'} | "
                 f"{c['length_m']:.0f} m | {c['n']} | {c['ok_correct']} | {c['wrong_ok']} | {c['ambiguous']} | "
                 f"{c['failed']} | {_p(c['success'])} | {_p(c['coverage_ball'])} / {_p(c['coverage'])} | {_s(c['ratio_r95_rms'], 1)} | "
                 f"{_s(1000 * c['median_r95_m'], 1)} | {_s(1000 * c['rms_origin_error_m'], 1)} | "
                 f"{_s(c['median_s'])} / {_s(c['max_s'])} |")
    a = summary["grid_all"]
    if a:
        L.append(f"| **all** | | | {a['n']} | {a['ok_correct']} | {a['wrong_ok']} | {a['ambiguous']} | {a['failed']} | "
                 f"{_p(a['success'])} | {_p(a['coverage_ball'])} / {_p(a['coverage'])} | {_s(a['ratio_r95_rms'], 1)} | "
                 f"{_s(1000 * a['median_r95_m'], 1)} | {_s(1000 * a['rms_origin_error_m'], 1)} | "
                 f"{_s(a['median_s'])} / {_s(a['max_s'])} |")
    L += ["", "Median seconds per stage (`LocalizationResult.timings_s`):", "",
          "| roughness | frame | length | " + " | ".join(STAGES) + " | total |",
          "|---|---|---|" + "---|" * (len(STAGES) + 1)]
    for c in summary["grid"]:
        st = c["stages_median_s"]
        L.append(f"| {c['roughness_m']:.2f} m | {'levelled' if c['levelled'] else 'unlevelled'} | {c['length_m']:.0f} m | "
                 + " | ".join(_s(st.get(s, 0.0)) for s in STAGES) + f" | {_s(c['median_s'])} |")
    for key, title in (("twins", "Exact twins (level 0 copied 25 m below; scans of a copied drift)"),
                       ("unmapped", "Scans of drifts the map does not hold")):
        c = summary.get(key)
        if c:
            extra = (f", ambiguous with the truth and the twin listed: {c['ambiguous_twin_listed']}"
                     if key == "twins" else "")
            L += ["", f"**{title}**: {c['n']} scans (10 and 20 m, levelled and unlevelled): ok {c['ok']}, ambiguous "
                  f"{c['ambiguous']}{extra}, failed {c['failed']}; median {_s(c['median_s'])} s."]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=21, help="world and scan seed (default 21; tests use 0-7)")
    ap.add_argument("--n", type=int, default=20, help="scans per grid cell (default 20)")
    ap.add_argument("--twins", type=int, default=20, help="exact-twin scans (default 20)")
    ap.add_argument("--unmapped", type=int, default=20, help="scans of unmapped drifts (default 20)")
    ap.add_argument("--roughness", default=",".join(map(str, ROUGHNESS)))
    ap.add_argument("--lengths", default=",".join(str(int(x)) for x in LENGTHS))
    ap.add_argument("--tilt-sigma-deg", type=float, default=1.0)
    ap.add_argument("--out", default="benchmarks/results/study", help="output stem: OUT.json and OUT.md")
    ap.add_argument("--rescore", action="store_true",
                    help="re-summarize OUT.json (its records) into OUT.json / OUT.md without localizing again")
    a = ap.parse_args(argv)
    if a.rescore:
        out = Path(a.out)
        d = json.loads(out.with_suffix(".json").read_text())
        d["summary"] = summarize(d["records"])
        out.with_suffix(".json").write_text(json.dumps(d, indent=1))
        out.with_suffix(".md").write_text(markdown(d["summary"], d["meta"]))
        print(markdown(d["summary"], d["meta"]))
        return 0
    t0 = time.perf_counter()
    records = run(a.seed, a.n, a.twins, a.unmapped, tuple(float(x) for x in a.roughness.split(",")),
                  tuple(float(x) for x in a.lengths.split(",")), a.tilt_sigma_deg)
    summary = summarize(records)
    from minegeo._provenance import to_jsonable, versions

    meta = {"seed": a.seed, "n": a.n, "tilt_sigma_deg": a.tilt_sigma_deg, "wall_s": time.perf_counter() - t0,
            "machine": f"{platform.machine()}, {platform.python_version()}, 2 cores shared"}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(to_jsonable({"meta": meta, "versions": versions(),
                                                                "summary": summary, "records": records}), indent=1))
    out.with_suffix(".md").write_text(markdown(summary, meta))
    print(markdown(summary, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
