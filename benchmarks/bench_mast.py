"""MAST benchmark: the paper's simulation (Table 2 analogue) and Monte Carlo uncertainty coverage.

Simela, Marshall & Daneshmend, section "Simulation Results": seven scanner positions in a
triangle between two beacons, Beacon 1 rotated by +10 (divergent), 0 (parallel) or -10 deg
(convergent), angular resolution 0.25 and 0.50 deg, beacon lengths 0.5-2.0 m.

Parts (all deterministic; seeds are fixed below):

1. ``table2``: one noisy scan (range noise 3 mm) per configuration
   3 wall configurations x 7 positions x 2 resolutions x 3 beacon lengths = 126 runs,
   printed like the paper's Table 2 (true/calculated position and azimuth, 95 % intervals,
   errors, Table 1 option).
2. ``coverage``: ``--trials`` (default 1000) Monte Carlo scans per configuration of a
   representative set; the fraction of trials whose true position lies inside the reported
   95 % ellipse and whose true azimuth lies inside the 95 % azimuth interval (target 93-97 %),
   plus RMS / 95th-percentile errors.
3. ``partial``: the same scenes with only the sub-optimal (single-panel) options 3-6 allowed.
4. ``beacon_survey``: beacon vertices given to MAST with 2 mm survey error; coverage with and
   without ``sigma_beacon_m`` stated.

Usage::

    python benchmarks/bench_mast.py                 # everything, writes benchmarks/results/mast/
    python benchmarks/bench_mast.py --trials 200    # quicker coverage
    python benchmarks/bench_mast.py --parts table2

Outputs ``benchmarks/results/mast/mast_benchmark.json`` and ``mast_benchmark.md``.
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
from scipy import stats

from minegeo._provenance import to_jsonable, versions
from minegeo.mast import (
    Beacon,
    MastParams,
    MastScenarioOptions,
    SegmentationParams,
    build_mast_world,
    locate_scanner,
)
from minegeo.survey import format_dms

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "mast"
CONFIGS = {"divergent": 10.0, "parallel": 0.0, "convergent": -10.0}
SIGMA_R = 0.003
#: Full-circle scans: the paper does not state a field of view, and with a 270 deg scanner the
#: beacon behind positions 6/7 falls in the blind sector (then MAST correctly reports it out of view).
FOV_DEG = 360.0

#: Monte Carlo set: (wall config, position, step deg, beacon length m, bearing sigma deg)
COVERAGE_SET = [
    ("parallel", 1, 0.25, 0.5, 0.0),
    ("parallel", 1, 0.50, 0.5, 0.0),
    ("divergent", 2, 0.25, 1.0, 0.0),
    ("divergent", 2, 0.50, 1.0, 0.0),
    ("convergent", 3, 0.25, 2.0, 0.0),
    ("convergent", 3, 0.50, 2.0, 0.0),
    ("parallel", 4, 0.25, 1.0, 0.0),
    ("parallel", 4, 0.50, 0.5, 0.0),
    ("divergent", 5, 0.25, 2.0, 0.0),
    ("convergent", 6, 0.50, 1.0, 0.0),
    ("parallel", 7, 0.25, 2.0, 0.0),
    ("parallel", 4, 0.25, 1.0, 0.01),
]


def _options(cfg, pos, step, length, sb=0.0):
    return MastScenarioOptions(
        position=pos, beacon1_rotation_deg=CONFIGS[cfg], angular_step_deg=step, beacon_length_m=length,
        sigma_range_m=SIGMA_R, sigma_bearing_deg=sb, fov_deg=FOV_DEG,
    )


def _errors(res, truth):
    x, y, az = truth
    return res.x_m - x, res.y_m - y, math.remainder(res.azimuth_deg - az, 360.0)


def _dms(deg):
    return format_dms(math.radians(deg % 360.0), 1, width_deg=3)


def run_table2(seed: int = 2026) -> list[dict]:
    rows = []
    k = 0
    for cfg in CONFIGS:
        for pos in range(1, 8):
            for step in (0.25, 0.5):
                for length in (0.5, 1.0, 2.0):
                    k += 1
                    o = _options(cfg, pos, step, length)
                    world = build_mast_world(o, np.random.default_rng([seed, k, 0]))
                    scan, _ = world.noisy_scan(np.random.default_rng([seed, k, 1]))
                    truth = o.truth_pose()
                    t0 = time.perf_counter()
                    res = locate_scanner(scan, world.beacons)
                    dt = time.perf_counter() - t0
                    row = {"config": cfg, "position": pos, "step_deg": step, "beacon_length_m": length,
                           "true_x": truth[0], "true_y": truth[1], "true_az_deg": truth[2], "status": res.status,
                           "reason": res.reason, "seconds": dt}
                    if res.ok:
                        ex, ey, ea = _errors(res, truth)
                        c = np.asarray(res.covariance)
                        row.update(
                            x=res.x_m, y=res.y_m, az_deg=res.azimuth_deg, ci95_x=1.96 * math.sqrt(c[0, 0]),
                            ci95_y=1.96 * math.sqrt(c[1, 1]), ci95_az_deg=res.azimuth_ci95_deg, err_x=ex, err_y=ey,
                            err_az_deg=ea, option=res.segmentation_option, icp_iterations=res.icp_iterations,
                            returns=res.details["returns_per_beacon"], sigma0=res.sigma0,
                        )
                    rows.append(row)
    return rows


def run_coverage(trials: int, seed: int = 7, options: tuple = (1, 2, 3, 4, 5, 6), cases=None) -> list[dict]:
    out = []
    params = MastParams(segmentation=SegmentationParams(options=options))
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        def tqdm(x, **_):
            return x
    for ci, (cfg, pos, step, length, sb) in enumerate(cases or COVERAGE_SET):
        o = _options(cfg, pos, step, length, sb)
        world = build_mast_world(o, np.random.default_rng([seed, ci]))
        truth = o.truth_pose()
        errs, in_ell, in_az, a95, ci_az, s0, opts = [], 0, 0, [], [], [], []
        fails: dict[str, int] = {}
        t0 = time.perf_counter()
        for k in tqdm(range(trials), desc=f"{cfg} pos{pos} {step} {length}m", file=sys.stderr, leave=False):
            scan, _ = world.noisy_scan(np.random.default_rng([seed, ci, k]))
            res = locate_scanner(scan, world.beacons, params)
            if not res.ok:
                key = res.reason.split(":")[0][:60]
                fails[key] = fails.get(key, 0) + 1
                continue
            ex, ey, ea = _errors(res, truth)
            # inside the *reported* ellipse95 (semi-axes a, b; azimuth of the major axis)?
            e95 = res.ellipse95
            t = math.radians(e95["orientation_deg"])
            u_ = -(ex * math.sin(t) + ey * math.cos(t))
            v_ = -(ex * math.cos(t) - ey * math.sin(t))
            in_ell += bool((u_ / e95["a_m"]) ** 2 + (v_ / e95["b_m"]) ** 2 <= 1.0)
            in_az += bool(abs(ea) <= res.azimuth_ci95_deg)
            errs.append((ex, ey, ea))
            a95.append(res.ellipse95["a_m"])
            ci_az.append(res.azimuth_ci95_deg)
            s0.append(res.sigma0)
            opts.append(res.segmentation_option)
        n = len(errs)
        e = np.array(errs).reshape(-1, 3)
        pe = np.hypot(e[:, 0], e[:, 1])
        out.append({
            "config": cfg, "position": pos, "step_deg": step, "beacon_length_m": length,
            "sigma_range_m": SIGMA_R, "sigma_bearing_deg": sb, "trials": trials, "solved": n, "failed": fails,
            "ellipse95_coverage": in_ell / n if n else None, "azimuth95_coverage": in_az / n if n else None,
            "rms_pos_err_mm": 1000 * float(np.sqrt(np.mean(pe**2))) if n else None,
            "p95_pos_err_mm": 1000 * float(np.percentile(pe, 95)) if n else None,
            "max_pos_err_mm": 1000 * float(pe.max()) if n else None,
            "rms_az_err_arcsec": 3600 * float(np.sqrt(np.mean(e[:, 2] ** 2))) if n else None,
            "p95_az_err_arcsec": 3600 * float(np.percentile(np.abs(e[:, 2]), 95)) if n else None,
            "mean_a95_mm": 1000 * float(np.mean(a95)) if n else None,
            "mean_az_ci95_arcsec": 3600 * float(np.mean(ci_az)) if n else None,
            "mean_sigma0": float(np.mean(s0)) if n else None,
            "options_used": {str(o_): int(c) for o_, c in zip(*np.unique(opts, return_counts=True), strict=True)},
            "seconds": time.perf_counter() - t0,
        })
        print(json.dumps(to_jsonable(out[-1])), file=sys.stderr)
    return out


def run_beacon_survey(trials: int, sigma_vertex_m: float = 0.002, seed: int = 13) -> list[dict]:
    """Coverage when the beacon vertices carry survey error, modelled or not (``sigma_beacon_m``)."""
    cfg, pos, step, length = "divergent", 2, 0.5, 1.0
    o = _options(cfg, pos, step, length)
    world = build_mast_world(o, np.random.default_rng([seed, 0]))
    truth = o.truth_pose()
    out = []
    for modelled in (0.0, sigma_vertex_m):
        params = MastParams(sigma_beacon_m=modelled)
        in_ell = in_az = n = 0
        pe = []
        for k in range(trials):
            rng = np.random.default_rng([seed, 1, k])
            scan, _ = world.noisy_scan(rng)
            surveyed = [Beacon(b.beacon_id, b.vertices_m + rng.normal(size=(4, 2)) * sigma_vertex_m)
                        for b in world.beacons]
            res = locate_scanner(scan, surveyed, params)
            if not res.ok:
                continue
            n += 1
            ex, ey, ea = _errors(res, truth)
            e95 = res.ellipse95
            t = math.radians(e95["orientation_deg"])
            u_ = -(ex * math.sin(t) + ey * math.cos(t))
            v_ = -(ex * math.cos(t) - ey * math.sin(t))
            in_ell += bool((u_ / e95["a_m"]) ** 2 + (v_ / e95["b_m"]) ** 2 <= 1.0)
            in_az += bool(abs(ea) <= res.azimuth_ci95_deg)
            pe.append(math.hypot(ex, ey))
        out.append({"config": cfg, "position": pos, "step_deg": step, "beacon_length_m": length,
                    "vertex_survey_sigma_m": sigma_vertex_m, "sigma_beacon_m_modelled": modelled,
                    "trials": trials, "solved": n, "ellipse95_coverage": in_ell / n, "azimuth95_coverage": in_az / n,
                    "rms_pos_err_mm": 1000 * float(np.sqrt(np.mean(np.square(pe))))})
        print(json.dumps(out[-1]), file=sys.stderr)
    return out


def binomial_band(p: float, n: int, level: float = 0.999) -> tuple[float, float]:
    lo, hi = stats.binom.interval(level, n, p)
    return lo / n, hi / n


def markdown(result: dict) -> str:
    L = ["# MAST benchmark results", ""]
    L.append(f"Range noise σ_r = {1000 * SIGMA_R:.0f} mm, wall roughness 5 mm, FOV {FOV_DEG:.0f}°, max range 30 m. "
             f"Generated by `python benchmarks/bench_mast.py` ({result['created_utc']}).")
    L.append("")
    if "table2" in result:
        rows = result["table2"]
        L += ["## Table 2 analogue (one scan per configuration)", ""]
        L.append("| cfg | pos | step ° | L m | true X | true Y | calc X | calc Y | 95% ± X mm | 95% ± Y mm | "
                 "err X mm | err Y mm | true Az | calc Az | 95% ± Az ″ | err Az ″ | opt |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            if r["status"] != "ok":
                L.append(f"| {r['config']} | {r['position']} | {r['step_deg']} | {r['beacon_length_m']} | "
                         f"{r['true_x']:.3f} | {r['true_y']:.3f} | FAILED: {r['reason'][:60]} |||||||||||")
                continue
            L.append(
                f"| {r['config']} | {r['position']} | {r['step_deg']:.2f} | {r['beacon_length_m']:.1f} | "
                f"{r['true_x']:.3f} | {r['true_y']:.3f} | {r['x']:.4f} | {r['y']:.4f} | {1000 * r['ci95_x']:.2f} | "
                f"{1000 * r['ci95_y']:.2f} | {1000 * r['err_x']:+.2f} | {1000 * r['err_y']:+.2f} | "
                f"{_dms(r['true_az_deg'])} | {_dms(r['az_deg'])} | {3600 * r['ci95_az_deg']:.0f} | "
                f"{3600 * r['err_az_deg']:+.0f} | {r['option']} |")
        ok = [r for r in rows if r["status"] == "ok"]
        L.append("")
        L += ["### Summary by resolution and beacon length", "",
              "| step ° | L m | solved | max pos err mm | RMS pos err mm | max az err ″ | RMS az err ″ | options |",
              "|---|---|---|---|---|---|---|---|"]
        for step in (0.25, 0.5):
            for length in (0.5, 1.0, 2.0):
                sel = [r for r in rows if r["step_deg"] == step and r["beacon_length_m"] == length]
                g = [r for r in sel if r["status"] == "ok"]
                if not g:
                    continue
                pe = np.array([math.hypot(r["err_x"], r["err_y"]) for r in g]) * 1000
                ae = np.abs([r["err_az_deg"] for r in g]) * 3600
                opts = sorted({r["option"] for r in g})
                L.append(f"| {step:.2f} | {length:.1f} | {len(g)}/{len(sel)} | {pe.max():.2f} | "
                         f"{np.sqrt(np.mean(pe**2)):.2f} | {ae.max():.0f} | {np.sqrt(np.mean(ae**2)):.0f} | {opts} |")
        L.append("")
        L.append(f"All configurations: {len(ok)}/{len(rows)} solved.")
        L.append("")
    for key, title in (("coverage", "Monte Carlo coverage of the 95 % ellipse and azimuth interval"),
                       ("partial", "Sub-optimal (single-panel) segmentation only: options 3-6")):
        if key not in result:
            continue
        cov = result[key]
        L += [f"## {title}", ""]
        if cov:
            n = cov[0]["trials"]
            lo, hi = binomial_band(0.95, n)
            L.append(f"{n} trials per configuration; a correct 95 % region covers the truth in "
                     f"{100 * lo:.1f}-{100 * hi:.1f} % of trials (binomial 99.9 % band).")
            L.append("")
        L.append("| cfg | pos | step ° | L m | σ_β ° | solved | ellipse cov. | azimuth cov. | RMS pos mm | "
                 "p95 pos mm | mean a95 mm | RMS az ″ | p95 az ″ | mean ±az95 ″ | mean σ0 | options |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in cov:
            if not r["solved"]:
                L.append(f"| {r['config']} | {r['position']} | {r['step_deg']} | {r['beacon_length_m']} | "
                         f"{r['sigma_bearing_deg']} | 0/{r['trials']} | {r['failed']} |||||||||")
                continue
            L.append(
                f"| {r['config']} | {r['position']} | {r['step_deg']:.2f} | {r['beacon_length_m']:.1f} | "
                f"{r['sigma_bearing_deg']} | {r['solved']}/{r['trials']} | {100 * r['ellipse95_coverage']:.1f} % | "
                f"{100 * r['azimuth95_coverage']:.1f} % | {r['rms_pos_err_mm']:.2f} | {r['p95_pos_err_mm']:.2f} | "
                f"{r['mean_a95_mm']:.2f} | {r['rms_az_err_arcsec']:.0f} | {r['p95_az_err_arcsec']:.0f} | "
                f"{r['mean_az_ci95_arcsec']:.0f} | {r['mean_sigma0']:.3f} | {r['options_used']} |")
        L.append("")
    if "beacon_survey" in result:
        rows = result["beacon_survey"]
        L += ["## Beacon survey error: stated or not", "",
              f"Beacon vertices perturbed by N(0, {1000 * rows[0]['vertex_survey_sigma_m']:.0f} mm) per coordinate "
              "in every trial (the surveyed coordinates given to MAST are wrong by that much); "
              f"{rows[0]['config']} position {rows[0]['position']}, {rows[0]['step_deg']}°, "
              f"{rows[0]['beacon_length_m']} m beacons, {rows[0]['trials']} trials.", "",
              "| sigma_beacon_m stated | solved | ellipse cov. | azimuth cov. | RMS pos mm |", "|---|---|---|---|---|"]
        for r in rows:
            L.append(f"| {r['sigma_beacon_m_modelled']} | {r['solved']}/{r['trials']} | "
                     f"{100 * r['ellipse95_coverage']:.1f} % | {100 * r['azimuth95_coverage']:.1f} % | "
                     f"{r['rms_pos_err_mm']:.2f} |")
        L.append("")
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--partial-trials", type=int, default=200)
    ap.add_argument("--parts", default="table2,coverage,partial,beacon_survey")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    import datetime as dt

    from minegeo.mast import _warmup

    result: dict = {"created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    "versions": versions(), "machine": platform.machine()}
    t0 = time.perf_counter()
    _warmup()
    result["compile_s"] = time.perf_counter() - t0
    if "table2" in parts:
        result["table2"] = run_table2()
    if "coverage" in parts:
        result["coverage"] = run_coverage(args.trials)
    if "partial" in parts:
        cases = [c for c in COVERAGE_SET if c[4] == 0.0][::2]
        result["partial"] = run_coverage(args.partial_trials, seed=11, options=(3, 4, 5, 6), cases=cases)
    if "beacon_survey" in parts:
        result["beacon_survey"] = run_beacon_survey(args.trials)
    result["total_s"] = time.perf_counter() - t0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = "" if parts == {"table2", "coverage", "partial", "beacon_survey"} else "_" + "_".join(sorted(parts))
    (out / f"mast_benchmark{suffix}.json").write_text(json.dumps(to_jsonable(result), indent=1) + "\n")
    md = markdown(result)
    (out / f"mast_benchmark{suffix}.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
