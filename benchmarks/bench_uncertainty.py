"""Benchmark: calibration of the reported pose uncertainty of ``localize_scan`` by Monte Carlo.

Many scans of the synthetic mine (random places, sensors, range-noise levels and lengths, several
worlds, i.e. several independent map realisations) are localized; for every ``ok`` result the
uncertainty of the final pose is recomputed with :func:`minegeo.localize.uncertainty.pose_uncertainty`
for each estimator (formal, cluster-robust, jackknife at several block sizes) from the same pairs
the pipeline uses (every ICP source point with its nearest ``prepared.icp_points`` partner within
the ICP gate, at the final pose), and the actual error of the scan origin (against the synthetic
truth) is compared with the reported 95 % regions:

* ``ball``: ``|e| <= position_95_radius_m`` (the number the pipeline reports);
* ``plan``: ``|e_xy| <= horizontal_95_radius_m``;
* ``ell3``: ``eᵀ Σ_tt⁻¹ e <= χ²₃(0.95)`` (the 95 % ellipsoid: checks the shape too);
* ``ell6``: the full 6-D pose (rotation and translation) against ``χ²₆(0.95) = 12.59``.

A calibrated estimator covers 95 % (the ball and plan circle over-cover by construction when the
ellipsoid is elongated). Usage::

    python benchmarks/bench_uncertainty.py --quick --out bench_out/uncertainty      # a few minutes
    nice -n 5 python benchmarks/bench_uncertainty.py --out bench_out/uncertainty    # the study

Writes ``results.json`` (every scan, every estimator) and ``table.md``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

CHI2_6D_95 = 12.591587243743977
SECTIONS = ("irregular_roof", "curve", "regular", "sump", "intersection")
SENSORS = ("zebrevo", "velodyne16", "flash")
NOISES = (None, 0.01, 0.03, 0.06)  # range-noise sigma override (None = the sensor's default)
LENGTHS = (10.0, 20.0, 30.0)


def _sensor(name: str, noise):
    from minegeo.synth import FlashSensor, Velodyne16, ZebRevo

    s = {"zebrevo": ZebRevo, "velodyne16": Velodyne16, "flash": FlashSensor}[name]()
    if noise is not None:
        s = replace(s, range_noise_sigma_m=float(noise))
    return s


def estimators(cluster_sizes, map_floors=()) -> dict:
    """Name -> UncertaintyParams of every estimator compared (the default is ``cluster``)."""
    from minegeo.localize.uncertainty import UncertaintyParams

    d = {"formal": UncertaintyParams(method="formal", add_pending_step=False)}
    default = UncertaintyParams()
    d[f"{default.method} {default.cluster_size_m:g} m (default)"] = default
    for h in cluster_sizes:
        for m in ("cluster", "jackknife"):
            name = f"{m} {h:g} m"
            if not (m == default.method and h == default.cluster_size_m):
                d[name] = UncertaintyParams(method=m, cluster_size_m=float(h))
    for floor in map_floors:
        d[f"{default.method} {default.cluster_size_m:g} m + map floor {1e3 * floor:g} mm"] = replace(
            default, map_sigma_m=float(floor))
    return d


def final_pairs(prepared, scan_points: np.ndarray, T_work_D: np.ndarray, lp, gate_m: float | None = None):
    """Replicates the pipeline's final ICP pairs: the ICP source (scan voxel centroids at
    ``lp.scan_icp_voxel_size_m``) placed by the final pose, each point with its nearest map ICP point
    when closer than the gate (``gate_m``, default the ICP gate; the polish gate when the pipeline
    polished the pose). Returns ``(P_work, corr)``."""
    from minegeo.geometry import voxel_downsample

    P = np.asarray(scan_points, dtype=np.float64)
    D = P if lp.scan_icp_voxel_size_m is None else voxel_downsample(P, float(lp.scan_icp_voxel_size_m)).points
    Pw = D @ T_work_D[:3, :3].T + T_work_D[:3, 3]
    gate = float(lp.icp.max_correspondence_m if gate_m is None else gate_m)
    dist, idx = prepared.kdtree.query(Pw, k=1, distance_upper_bound=gate)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    m = (idx < prepared.icp_points.shape[0]) & (dist * dist < gate * gate)
    return Pw, np.column_stack([np.flatnonzero(m), idx[m]]).astype(np.int64)


def evaluate(unc, e6: np.ndarray) -> dict:
    """Coverage indicators of one estimate for the true error ``e6 = (ω, t)``."""
    from minegeo.localize.uncertainty import CHI2_3D_95

    et = e6[3:]
    C = unc.covariance_6x6
    if C is None:
        return {"degenerate": True}
    Ct = C[3:, 3:]
    return {"degenerate": False, "r95_m": unc.position_95_radius_m, "h95_m": unc.horizontal_95_radius_m,
            "err_m": float(np.linalg.norm(et)), "err_xy_m": float(np.linalg.norm(et[:2])),
            "m2_3": float(et @ np.linalg.solve(Ct, et)), "m2_6": float(e6 @ np.linalg.solve(C, e6)),
            "sigma3_m": float(math.sqrt(np.trace(Ct))), "inflation": unc.inflation, "n_clusters": unc.n_clusters,
            "in_ball": bool(np.linalg.norm(et) <= unc.position_95_radius_m),
            "in_plan": bool(np.linalg.norm(et[:2]) <= unc.horizontal_95_radius_m),
            "in_ell3": bool(et @ np.linalg.solve(Ct, et) <= CHI2_3D_95),
            "in_ell6": bool(e6 @ np.linalg.solve(C, e6) <= CHI2_6D_95)}


def with_shift(unc, delta: np.ndarray):
    """``unc`` with ``δ δᵀ`` added to its covariance (``δ`` = the polish's pose shift, (ω, t))."""
    from minegeo.localize.uncertainty import radii_95

    if unc.covariance_6x6 is None:
        return unc
    C = unc.covariance_6x6 + np.outer(delta, delta)
    pos = C[3:, 3:]
    r95, h95 = radii_95(pos)
    return replace(unc, covariance_6x6=C, position_cov_3x3=pos, position_95_radius_m=r95, horizontal_95_radius_m=h95)


def summarise(records: list, names) -> list[dict]:
    rows = []
    for name in names:
        ev = [r["estimators"][name] for r in records if name in r["estimators"]]
        ev = [e for e in ev if not e["degenerate"]]
        n = len(ev)
        if n == 0:
            continue

        def frac(key, ev=ev, n=n):
            return sum(e[key] for e in ev) / n

        rows.append({"estimator": name, "n": n, "ball": frac("in_ball"), "plan": frac("in_plan"),
                     "ell3": frac("in_ell3"), "ell6": frac("in_ell6"),
                     "median_err_over_sigma": float(np.median([e["err_m"] / e["sigma3_m"] for e in ev])),
                     "median_err_over_r95": float(np.median([e["err_m"] / e["r95_m"] for e in ev])),
                     "rms_mahalanobis_3": float(math.sqrt(np.mean([e["m2_3"] for e in ev]) / 3.0)),
                     "median_r95_m": float(np.median([e["r95_m"] for e in ev])),
                     "median_err_m": float(np.median([e["err_m"] for e in ev])),
                     "median_inflation": float(np.nanmedian([e["inflation"] for e in ev]))
                     if any(np.isfinite(e["inflation"]) for e in ev) else math.nan})
    return rows


def _binom_ci(p: float, n: int) -> float:
    return 1.96 * math.sqrt(max(p * (1 - p), 0.25 / max(n, 1)) / max(n, 1))


def table_md(rows: list[dict], records: list, meta: dict) -> str:
    n_all = len(records)
    n_ok = sum(r["status"] == "ok" for r in records)
    lines = [f"Scans: {n_all} localized, {n_ok} `ok` (only `ok` results are scored); worlds {meta['worlds']}, "
             f"profile `{meta['profile']}`; {meta['elapsed_s']:.0f} s.", "",
             "| estimator | n | ball (3-D r95) | plan (2-D h95) | 95 % ellipsoid | 6-D | median err/σ₃ᴰ | "
             "median err/r95 | RMS Mahalanobis/√3 | median r95 (mm) | median err (mm) | median inflation |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ci = _binom_ci(r["ball"], r["n"])
        lines.append(f"| {r['estimator']} | {r['n']} | {100 * r['ball']:.1f} % (±{100 * ci:.1f}) | "
                     f"{100 * r['plan']:.1f} % | {100 * r['ell3']:.1f} % | {100 * r['ell6']:.1f} % | "
                     f"{r['median_err_over_sigma']:.2f} | {r['median_err_over_r95']:.2f} | "
                     f"{r['rms_mahalanobis_3']:.2f} | {1e3 * r['median_r95_m']:.1f} | {1e3 * r['median_err_m']:.1f} | "
                     f"{r['median_inflation']:.1f} |")
    lines += ["", "σ₃ᴰ = √tr(Σ_tt); a calibrated Gaussian gives median err/σ₃ᴰ ≈ 0.9 (isotropic), RMS Mahalanobis/√3 "
              "= 1, and 95 % in every coverage column (± is the 95 % binomial interval of the ball column).", ""]
    ok = [r for r in records if r["status"] == "ok" and math.isfinite(r.get("pipeline_r95_m", math.inf))]
    if ok:
        def cover(rs):
            return f"{sum(r['err_m'] <= r['pipeline_r95_m'] for r in rs)}/{len(rs)}"

        weak = [r for r in ok if r.get("pipeline_weak_term")]
        lines += [f"What `result.json` reports (`position_95_radius_m`, every `ok` scan, weak directions included): "
                  f"covers {cover(ok)} ({100 * np.mean([r['err_m'] <= r['pipeline_r95_m'] for r in ok]):.1f} %); "
                  f"with the weak-axis polish term added {cover(weak)}, the others {cover([r for r in ok if r not in weak])}; "
                  f"median radius {1e3 * np.median([r['pipeline_r95_m'] for r in ok]):.1f} mm.", ""]
    # breakdown of the default by sensor and noise
    default = next((r["estimator"] for r in rows if "default" in r["estimator"]), None)
    if default:
        lines += [f"Breakdown of `{default}` and `formal` (ball coverage):", "",
                  "| group | n | formal | default |", "|---|---|---|---|"]
        groups = {}
        for rec in records:
            if rec["status"] != "ok":
                continue
            for key in (f"sensor {rec['sensor']}", f"noise {rec['noise'] if rec['noise'] is not None else 'default'}",
                        f"length {rec['length_m']:g} m"):
                groups.setdefault(key, []).append(rec)
        for key in sorted(groups):
            recs = groups[key]
            vals = []
            for name in ("formal", default):
                ev = [r["estimators"][name] for r in recs if not r["estimators"][name]["degenerate"]]
                vals.append(f"{100 * np.mean([e['in_ball'] for e in ev]):.0f} %" if ev else "-")
            lines.append(f"| {key} | {len(recs)} | {vals[0]} | {vals[1]} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one world, 16 scans (a few minutes)")
    ap.add_argument("--worlds", default="0,1,2", help="world seeds (each an independent map realisation)")
    ap.add_argument("--scans", type=int, default=60, help="scans per world")
    ap.add_argument("--profile", default="fast", choices=("fast", "table3"))
    ap.add_argument("--cluster-sizes", default="1,2,4,8", help="block edges (m) of the compared estimators")
    ap.add_argument("--map-floors", default="0.002", help="map_sigma_m values (m) added to the default as extra rows")
    ap.add_argument("--max-rays", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_out/uncertainty")
    ap.add_argument("--levelled", type=float, default=None, metavar="DEG",
                    help="re-express every scan in a levelled frame (0.3 deg IMU error) and localize it with the "
                         "levelled 2-point model and the correlative fallback (as `minegeo localize --levelled DEG`)")
    args = ap.parse_args(argv)
    if args.quick:
        args.worlds, args.scans, args.cluster_sizes = "0", 16, "2,4"

    from minegeo._provenance import atomic_write_text, versions, write_json_atomic
    from minegeo.geometry.se3 import log_so3
    from minegeo.localize import LocalizeParams, PrepareParams, localize_scan, prepare_map
    from minegeo.localize.uncertainty import pose_uncertainty
    from minegeo.synth import build_map, build_world, local_scan

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    worlds = [int(w) for w in args.worlds.split(",") if w != ""]
    est = estimators([float(h) for h in args.cluster_sizes.split(",") if h],
                     [float(f) for f in args.map_floors.split(",") if f])
    lp = LocalizeParams.fast() if args.profile == "fast" else LocalizeParams()
    if args.levelled is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_localization import level_scan

        lp = replace(lp, ransac=replace(lp.ransac, model="levelled", ransac_n=2, max_tilt_deg=float(args.levelled)))
    records: list[dict] = []
    t_start = time.perf_counter()
    t_unc = []
    meta = {"worlds": worlds, "profile": args.profile, "levelled_deg": args.levelled, "scans_per_world": args.scans, "max_rays": args.max_rays,
            "seed": args.seed, "estimators": {k: vars(v) if hasattr(v, "__dict__") else str(v) for k, v in est.items()}}
    for ws in worlds:
        world = build_world("small", ws)
        cloud = build_map(world, seed=ws + 1)
        prepared = prepare_map(cloud, PrepareParams.fast() if args.profile == "fast" else PrepareParams())
        rng = np.random.default_rng([args.seed, ws])
        L = np.array([d.length_m for d in world.drifts])
        for j in range(args.scans):
            if rng.integers(0, 3) == 0:
                sec = SECTIONS[int(rng.integers(0, len(SECTIONS)))]
            else:
                k = int(rng.choice(len(L), p=L / L.sum()))
                sec = {"drift": k, "s_m": float(rng.uniform(0.0, L[k]))}
            sen = SENSORS[int(rng.integers(0, len(SENSORS)))]
            noise = NOISES[int(rng.integers(0, len(NOISES)))]
            length = LENGTHS[int(rng.integers(0, len(LENGTHS)))]
            sseed = int(rng.integers(0, 2**31 - 1))
            rec = {"world": ws, "scan": j, "section": sec, "sensor": sen, "noise": noise, "length_m": length,
                   "scan_seed": sseed, "estimators": {}}
            try:
                c, tr, T_true = local_scan(world, sec, length, _sensor(sen, noise), seed=sseed,
                                           kind="handheld" if sen == "flash" else "walk", max_rays=args.max_rays)
                if args.levelled is not None:
                    c, tr, T_true = level_scan(c, tr, T_true, np.random.default_rng(sseed), 0.3)
                r = localize_scan(prepared, c, tr, lp, seed=args.seed)
            except Exception as exc:  # typed errors (tiny scan, section not in this world): not scored
                rec.update(status="error", reason=f"{type(exc).__name__}: {exc}")
                records.append(rec)
                continue
            rec.update(status=r.status, reason=r.reason, pipeline_r95_m=r.position_95_radius_m,
                       pipeline_weak_term=bool((r.uncertainty or {}).get("weak_axis_polish_term", False)))
            e6 = np.r_[log_so3(r.T_map_scan[:3, :3] @ T_true[:3, :3].T), r.T_map_scan[:3, 3] - T_true[:3, 3]]
            rec["err_m"] = float(np.linalg.norm(e6[3:]))
            rec["rot_err_deg"] = float(np.degrees(np.linalg.norm(e6[:3])))
            if r.status == "ok" and r.icp is not None:
                T = r.icp.T_target_source  # work frame <- (scan - scan origin)
                so = np.asarray(c.origin, dtype=np.float64)
                gate = None
                if r.polish is not None and r.polish["applied"]:  # the final pose is the polished one
                    T = r.T_map_scan.copy()
                    T[:3, 3] = T[:3, 3] + T[:3, :3] @ so - prepared.work_origin
                    gate = r.polish["gate_m"]
                Pw, corr = final_pairs(prepared, c.points, T, lp, gate)
                o_work = T[:3, :3] @ (-so) + T[:3, 3]
                rec["n_pairs"] = int(corr.shape[0])
                shift6 = np.asarray(r.polish["shift_6"]) if r.polish is not None and r.polish["applied"] else None
                rec["polish_shift_6"] = None if shift6 is None else shift6.tolist()
                for name, prm in est.items():
                    t0 = time.perf_counter()
                    u = pose_uncertainty(Pw, prepared.icp_points, prepared.icp_normals, corr, o_work, prm)
                    t_unc.append((name, time.perf_counter() - t0))
                    rec["estimators"][name] = evaluate(u, e6)
                    if "default" in name:  # the polish term on every scan (the pipeline adds it on weak ones only)
                        rec["estimators"][name + " + polish shift on all"] = evaluate(
                            with_shift(u, shift6 if shift6 is not None else np.zeros(6)), e6)
            records.append(rec)
            dflt = next(iter(k for k in est if "default" in k))
            ev = rec["estimators"].get(dflt, {})
            print(f"[w{ws} {j + 1}/{args.scans}] {r.status:9s} {sen:10s} noise {noise} {length:4.0f} m  "
                  f"err {1e3 * rec['err_m']:8.1f} mm  r95 formal {1e3 * r.position_95_radius_m:6.1f} / default "
                  f"{1e3 * ev.get('r95_m', math.nan):6.1f} mm", file=sys.stderr, flush=True)
    meta["elapsed_s"] = time.perf_counter() - t_start
    rows = summarise(records, list(est) + [k + " + polish shift on all" for k in est if "default" in k])
    times = {}
    for name, t in t_unc:
        times.setdefault(name, []).append(t)
    meta["pose_uncertainty_median_s"] = {k: float(np.median(v)) for k, v in times.items()}
    write_json_atomic(out / "results.json", {"meta": meta, "summary": rows, "records": records,
                                             "versions": versions()})
    md = table_md(rows, records, meta)
    atomic_write_text(out / "table.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
