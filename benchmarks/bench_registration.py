"""Registration pipeline benchmark: minegeo vs Open3D 0.20 on the same seeded synthetic mine.

Stages: ``voxel``, ``octree``, ``normals``, ``fpfh``, ``ransac``, ``icp_point_to_point``,
``icp_point_to_plane``. Each stage reports steady-state seconds for both libraries (minimum
over repeats after a warm-up call), the ratio minegeo/Open3D, an accuracy/agreement figure and
minegeo's compile (or cache-load) time. Both libraries use the same thread count
(``--threads``, default 2: ``numba.set_num_threads`` and ``open3d.utility.set_max_threads``).

The data: ``minegeo.synth`` builds a seeded mine (``build_world``), a survey map of it
(``build_map``, the global cloud) and a local scan of a drift section (``local_scan``) with its
ground-truth ``T_map_scan``. The map is voxel-downsampled; the stages run on those clouds with

* the *paper* parameters of Baek et al. (2022) Table 3 (voxel 0.5 m; normals r = 1 m,
  max_nn = 1000; FPFH r = 2.5 m, max_nn = 1000; RANSAC distance 2.5 m, edge 0.9, n = 4;
  ICP d = 0.5 m, 30 iterations, relative RMSE 1e-6), and
* a *light* set (voxel v; normals Hybrid(2v, 30); FPFH Hybrid(5v, 100); RANSAC 1.5v, n = 3;
  ICP d = v), Open3D's tutorial defaults.

Stage functions for voxel/octree/normals come from ``benchmarks/stages_geometry.py`` and for
FPFH/RANSAC from ``benchmarks/stages_features.py``; when one is missing the stage is reported
as skipped with the reason.

RANSAC success is a rate, so it is measured over several drift sections (``SECTIONS_QUICK`` /
``SECTIONS_FULL``: straight, curved, junction, ...) times several seeds (``--ransac-seeds``), both
libraries with the same budget (100,000 iterations, confidence 0.999), checkers and feature
matching inside the timed call. Its ``minegeo_s`` / ``open3d_s`` are median seconds per call
(interleaved runs), ``ratio`` their quotient; minegeo's own mode (distinct samples + refit) is
run too and reported as ``minegeo_mode_success``. Success = within 5 degrees and max(1 m, 2 d)
of the section's ground truth.

Usage::

    python benchmarks/bench_registration.py --quick --json OUT.json   # light set, small, < 5 min
    python benchmarks/bench_registration.py --json OUT.json --md OUT.md  # full size, both sets

The JSON is ``{stage: {"minegeo_s", "open3d_s", "ratio", "agreement", ...}}`` (light set; the
paper set, when run, is under the key ``"paper"``) plus ``"meta"``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
import traceback
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))  # this checkout's minegeo, not whatever copy is installed

STAGES = ("voxel", "octree", "normals", "fpfh", "ransac", "icp_point_to_point", "icp_point_to_plane")

#: Baek et al. 2022, Table 3.
PAPER = {
    "voxel_m": 0.5, "normal_radius_m": 1.0, "normal_max_nn": 1000, "fpfh_radius_m": 2.5, "fpfh_max_nn": 1000,
    "ransac_distance_m": 2.5, "ransac_n": 4, "edge": 0.9, "icp_distance_m": 0.5, "icp_iterations": 30,
    "icp_relative_rmse": 1e-6,
}


def light_params(v: float) -> dict:
    """Open3D tutorial defaults for voxel size ``v`` (metres)."""
    return {
        "voxel_m": v, "normal_radius_m": 2 * v, "normal_max_nn": 30, "fpfh_radius_m": 5 * v, "fpfh_max_nn": 100,
        "ransac_distance_m": 1.5 * v, "ransac_n": 3, "edge": 0.9, "icp_distance_m": v, "icp_iterations": 30,
        "icp_relative_rmse": 1e-6,
    }


def _o3d(threads: int):
    import open3d as o3d

    o3d.utility.set_max_threads(int(threads))
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def write_results(results: dict, meta: dict, markdown, json_path, md_path) -> None:
    """``results["meta"] = meta``; print ``markdown(results, meta)``, write ``results`` to ``json_path`` and
    the Markdown to ``md_path`` (each atomically, when given), and log the total time."""
    from minegeo._provenance import atomic_write_text, to_jsonable, write_json_atomic

    results["meta"] = meta
    md = markdown(results, meta)
    print(md)
    if json_path:
        write_json_atomic(json_path, to_jsonable(results))
    if md_path:
        atomic_write_text(md_path, md + "\n")
    _log(f"total {meta['total_s']:.1f} s")


def _skip(reason: str) -> dict:
    return {"minegeo_s": None, "open3d_s": None, "ratio": None, "agreement": None, "skipped": reason}


def _import_stage(module: str, name: str):
    try:
        return getattr(importlib.import_module(module), name), None
    except Exception as exc:  # stage module not there (yet) or broken: report, keep going
        return None, f"{module}.{name} unavailable: {type(exc).__name__}: {exc}"


# ----------------------------------------------------------------------------- data


#: Drift sections scanned for the RANSAC success rate (``minegeo.synth.local_scan`` starts).
SECTIONS_QUICK = ("regular", "curve", "intersection")
SECTIONS_FULL = ("regular", "curve", "irregular_roof", "sump", "intersection")


def make_data(quick: bool, seed: int, threads: int) -> dict:
    """Seeded synthetic mine: map (raw), local scans (scan frames) of several sections and their truths.

    ``scan`` / ``T_map_scan`` are the "regular" drift section (used by every stage); ``scans``
    holds ``{section: (points, T_map_scan)}`` for the RANSAC success rate.
    """
    from minegeo.synth import Velodyne16, build_map, build_world, local_scan

    t0 = time.perf_counter()
    world = build_world("small", seed=seed)
    cloud = build_map(world, seed=seed, spacing_m=8.0 if quick else 4.0)
    max_rays = 40_000 if quick else 150_000
    scans = {}
    for k, section in enumerate(SECTIONS_QUICK if quick else SECTIONS_FULL):
        scan, _, T = local_scan(world, section, 20.0, Velodyne16(azimuth_step_deg=0.4), seed=seed + 1 + k,
                                max_rays=max_rays)
        scans[section] = (np.ascontiguousarray(scan.points), T)
    _log(f"synthetic mine: map {len(cloud.points)} pts, scans {[len(v[0]) for v in scans.values()]} pts "
         f"({time.perf_counter() - t0:.1f} s)")
    return {"map": np.ascontiguousarray(cloud.points), "scan": scans["regular"][0],
            "T_map_scan": scans["regular"][1], "scans": scans, "build_s": time.perf_counter() - t0}


# ----------------------------------------------------------------------------- ICP stage


def _rot_trans_diff(A, B):
    dR = A[:3, :3].T @ B[:3, :3]
    ang = float(np.arctan2(np.linalg.norm([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2,
                           (np.trace(dR) - 1) / 2))
    return ang, float(np.linalg.norm(A[:3, 3] - B[:3, 3]))


def bench_icp(src, tgt, tgt_normals, T_init, T_true, method, d, iterations, rel_rmse, threads, repeats=3):
    """ICP, both libraries, same start/parameters/target normals.

    ``agreement`` = ``{"rot_rad", "trans_m"}``: difference between minegeo's and Open3D's final
    transforms (acceptance: <= 1e-6 each); also reported: error of each to the ground truth,
    fitness, RMSE, iterations and minegeo's degeneracy verdict.
    """
    from minegeo.registration import ICPParams, register_icp

    o3d = _o3d(threads)
    reg = o3d.pipelines.registration
    src = np.ascontiguousarray(src)
    tgt = np.ascontiguousarray(tgt)
    prm = ICPParams(d, max_iterations=iterations, relative_fitness=1e-6, relative_rmse=rel_rmse, method=method)
    t0 = time.perf_counter()
    register_icp(src[:50], src[:50], np.eye(4), ICPParams(d, max_iterations=2, method=method),
                 target_normals=tgt_normals[:50] if method == "point_to_plane" else None)
    compile_s = time.perf_counter() - t0
    nrm = tgt_normals  # point-to-point uses them only for the degeneracy analysis (Open3D ignores them)
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    pt.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(tgt_normals))
    est = reg.TransformationEstimationPointToPoint() if method == "point_to_point" else \
        reg.TransformationEstimationPointToPlane()
    crit = reg.ICPConvergenceCriteria(1e-6, rel_rmse, iterations)
    # interleaved runs (the machine is shared: both libraries see the same load); minimum of each
    best_m = best_o = np.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        r = register_icp(src, tgt, T_init, prm, target_normals=nrm)
        best_m = min(best_m, time.perf_counter() - t0)
        t0 = time.perf_counter()
        o = reg.registration_icp(ps, pt, d, T_init, est, crit)
        best_o = min(best_o, time.perf_counter() - t0)
    To = np.asarray(o.transformation)
    rot, tr = _rot_trans_diff(r.T_target_source, To)
    e_m = _rot_trans_diff(r.T_target_source, T_true)
    e_o = _rot_trans_diff(To, T_true)
    return {
        "minegeo_s": best_m, "open3d_s": best_o, "ratio": best_m / best_o,
        "agreement": {"rot_rad": rot, "trans_m": tr},
        "compile_s": compile_s, "threads": threads, "n_source": len(src), "n_target": len(tgt),
        "minegeo_error_to_truth": {"rot_rad": e_m[0], "trans_m": e_m[1]},
        "open3d_error_to_truth": {"rot_rad": e_o[0], "trans_m": e_o[1]},
        "fitness": [r.fitness, o.fitness], "inlier_rmse_m": [r.inlier_rmse_m, o.inlier_rmse],
        "iterations": r.iterations, "converged": r.converged, "degenerate": r.degenerate,
        "degeneracy_ratio": r.degeneracy_ratio, "status": r.status,
        "timings_s": r.timings_s,
    }


def _ransac_summary(per: dict) -> dict:
    """Pool the per-section RANSAC runs: median seconds per call, success over all seeds x sections."""
    m_t = np.concatenate([r["per_run_s"]["minegeo"] for r in per.values()])
    o_t = np.concatenate([r["per_run_s"]["open3d"] for r in per.values()])
    m_ok = np.concatenate([r["success"]["minegeo"] for r in per.values()])
    o_ok = np.concatenate([r["success"]["open3d"] for r in per.values()])
    own_ok = np.concatenate([r["minegeo_mode"]["success"] for r in per.values()])
    own_t = np.concatenate([r["minegeo_mode"]["per_run_s"] for r in per.values()])
    first = next(iter(per.values()))
    return {
        "minegeo_s": float(np.median(m_t)), "open3d_s": float(np.median(o_t)),
        "ratio": float(np.median(m_t) / np.median(o_t)),
        "ratio_total": float(m_t.sum() / o_t.sum()),
        "ratio_per_run_median": float(np.median(m_t / o_t)),
        "agreement": {"minegeo_success": float(m_ok.mean()), "open3d_success": float(o_ok.mean()),
                      "minegeo_successes": int(m_ok.sum()), "open3d_successes": int(o_ok.sum()),
                      "runs": int(m_ok.size), "minegeo_mode_success": float(own_ok.mean()),
                      "minegeo_mode_successes": int(own_ok.sum())},
        "minegeo_mode_s": float(np.median(own_t)),
        "compile_s": float(first["compile_s"]), "threads": first["threads"], "budget": first["budget"],
        "seeds_per_section": first["seeds"], "sections": list(per), "success_rule": first["success_rule"],
        "per_section": {k: {"minegeo_success": r["agreement"]["minegeo_success"],
                            "open3d_success": r["agreement"]["open3d_success"],
                            "minegeo_mode_success": float(np.mean(r["minegeo_mode"]["success"])),
                            "minegeo_median_s": float(np.median(r["per_run_s"]["minegeo"])),
                            "open3d_median_s": float(np.median(r["per_run_s"]["open3d"])),
                            "n_source": r["n_source"]} for k, r in per.items()},
        "runs": per,
    }


# ----------------------------------------------------------------------------- one parameter set


def run_set(data: dict, p: dict, threads: int, repeats: int, seeds: int, budget: int, quick: bool,
            only=None) -> dict:
    from minegeo.geometry import NormalParams, estimate_normals, voxel_downsample
    from minegeo.geometry.se3 import random_transform

    out: dict = {}
    v = p["voxel_m"]
    M = voxel_downsample(data["map"], v).points
    S = voxel_downsample(data["scan"], v).points
    _log(f"voxel {v} m: map {len(M)} pts, scan {len(S)} pts")
    # normals on both clouds (minegeo's; the same arrays are given to both libraries downstream)
    npar = NormalParams(radius_m=p["normal_radius_m"], max_nn=p["normal_max_nn"])
    NM = estimate_normals(M, npar).normals
    NS = estimate_normals(S, npar).normals

    def stage(name, fn):
        if only and name not in only:
            return
        _log(f"stage {name} ...")
        t0 = time.perf_counter()
        try:
            out[name] = fn()
        except Exception as exc:
            out[name] = _skip(f"failed: {type(exc).__name__}: {exc}")
            traceback.print_exc()
        _log(f"stage {name} done in {time.perf_counter() - t0:.1f} s: ratio {out[name].get('ratio')}")

    bench_voxel, why = _import_stage("stages_geometry", "bench_voxel")
    stage("voxel", (lambda: bench_voxel(data["map"], v, repeats)) if bench_voxel else (lambda: _skip(why)))
    bench_octree, why = _import_stage("stages_geometry", "bench_octree")
    stage("octree", (lambda: bench_octree(data["map"], 8 if quick else 10, repeats)) if bench_octree
          else (lambda: _skip(why)))
    bench_normals, why = _import_stage("stages_geometry", "bench_normals")
    stage("normals", (lambda: bench_normals(M, p["normal_radius_m"], p["normal_max_nn"], repeats))
          if bench_normals else (lambda: _skip(why)))
    bench_fpfh, why = _import_stage("stages_features", "bench_fpfh")
    stage("fpfh", (lambda: bench_fpfh(M, NM, p["fpfh_radius_m"], p["fpfh_max_nn"], max(1, repeats - 1)))
          if bench_fpfh else (lambda: _skip(why)))

    # scan source frame: move the scan far from the map frame by the truth (source = scan frame)
    T_true = data["T_map_scan"]
    bench_ransac, why = _import_stage("stages_features", "bench_ransac")
    if bench_ransac is not None and (not only or "ransac" in only):
        def ransac():
            from minegeo.features import FPFHParams, compute_fpfh
            from minegeo.registration.ransac import RansacParams

            fp = FPFHParams(p["fpfh_radius_m"], p["fpfh_max_nn"], "open3d")
            ft = compute_fpfh(M, NM, fp).features
            prm = RansacParams.open3d_compatible(p["ransac_distance_m"], ransac_n=p["ransac_n"],
                                                 edge_length_similarity=p["edge"])
            # minegeo's own mode (distinct samples, refit), same budget and confidence, for the success rate
            own = RansacParams(distance_threshold_m=p["ransac_distance_m"], ransac_n=p["ransac_n"],
                               edge_length_similarity=p["edge"], max_validations=None, mode="minegeo")
            per = {}
            for section, (raw, T_sec) in data["scans"].items():
                Ssec = S if section == "regular" else voxel_downsample(raw, v).points
                Nsec = NS if section == "regular" else estimate_normals(Ssec, npar).normals
                fs = compute_fpfh(Ssec, Nsec, fp).features
                per[section] = bench_ransac(Ssec, M, fs, ft, prm, range(seeds), budget, T_true=T_sec,
                                            success_deg=5.0, success_m=max(1.0, 2 * p["ransac_distance_m"]),
                                            minegeo_mode_params=own)
                a = per[section]["agreement"]
                _log(f"  ransac {section}: {len(Ssec)} pts, success {a['minegeo_success']:.2f} "
                     f"(mode minegeo {np.mean(per[section]['minegeo_mode']['success']):.2f}) vs "
                     f"{a['open3d_success']:.2f}, time ratio {per[section]['ratio']:.2f}")
            return _ransac_summary(per)
        stage("ransac", ransac)
    else:
        stage("ransac", lambda: _skip(why))

    # ICP starts from the truth perturbed like a RANSAC answer (2 degrees, 0.3 m)
    rng = np.random.default_rng(1234)
    T_init = data["T_map_scan"] @ random_transform(rng, np.radians(2.0), 0.3)
    for method in ("point_to_point", "point_to_plane"):
        stage(f"icp_{method}", lambda m=method: bench_icp(
            S, M, NM, T_init, T_true, m, p["icp_distance_m"], p["icp_iterations"], p["icp_relative_rmse"],
            threads, max(5, repeats)))
    out["_sizes"] = {"map_points": int(len(M)), "scan_points": int(len(S))}
    return out


# ----------------------------------------------------------------------------- report


def _fmt(x, spec=".3f"):
    return "—" if x is None else format(x, spec)


def _agreement_text(stage: str, r: dict) -> str:
    a = r.get("agreement")
    if a is None:
        return r.get("skipped", "—")
    if stage.startswith("icp"):
        e = r["minegeo_error_to_truth"]
        return (f"Δ vs Open3D {a['rot_rad']:.1e} rad / {a['trans_m']:.1e} m; "
                f"to truth {e['rot_rad']:.1e} rad / {e['trans_m']:.3f} m; {r['iterations']} its, {r['status']}")
    if stage == "ransac" and isinstance(a, dict):
        if "runs" not in a:
            return f"success {a['minegeo_success']:.2f} (minegeo) vs {a['open3d_success']:.2f} (Open3D)"
        sec = "; ".join(f"{k} {v['minegeo_success']:.2f}/{v['minegeo_mode_success']:.2f}/{v['open3d_success']:.2f}"
                        for k, v in r.get("per_section", {}).items())
        n = a["runs"]
        return (f"success {a['minegeo_successes']}/{n} (minegeo, Open3D mode) and "
                f"{a['minegeo_mode_successes']}/{n} (minegeo mode, {r['minegeo_mode_s']:.2f} s/call) vs "
                f"{a['open3d_successes']}/{n} (Open3D); {r['seeds_per_section']} seeds x {len(r['sections'])} "
                f"sections, budget {r['budget']} its; per section (Open3D mode/minegeo mode/Open3D): {sec}; "
                f"median of per-run time ratios {r['ratio_per_run_median']:.2f}")
    if stage == "fpfh":
        return f"max rel. L1 {a:.1e}"
    if stage == "normals":
        return f"{a:.4f} of normals within 1e-6 rad"
    if stage in ("voxel", "octree"):
        return f"{a:.4f} identical"
    return str(a)


#: Acceptance ratios minegeo / Open3D. ICP (issue 16, the one registration loop): <= 0.8 with the same
#: thread count on both sides (the loop's warm-started, evenly split query and the ~2x faster private
#: KD-tree build; measured 0.74-0.79 on the 2-core machine at load ~2.5, before 1.01-1.06).
TARGETS = {"normals": 0.8, "fpfh": 0.8, "icp_point_to_point": 0.8, "icp_point_to_plane": 0.8, "ransac": 0.5}


def markdown(results: dict, meta: dict) -> str:
    lines = []
    sets = [("light", results)] + ([("paper (Table 3)", results["paper"])] if "paper" in results else [])
    for label, res in sets:
        sz = res.get("_sizes", {})
        lines.append(f"**{label}** — map {sz.get('map_points')} pts, scan {sz.get('scan_points')} pts "
                     f"(after voxel downsampling), {meta['threads']} threads\n")
        lines.append("| stage | minegeo s | Open3D s | ratio | target | compile s | agreement / accuracy |")
        lines.append("|---|---|---|---|---|---|---|")
        for st in STAGES:
            r = res.get(st, _skip("not run"))
            tgt = TARGETS.get(st)
            ok = ""
            if tgt is not None and r.get("ratio") is not None:
                ok = " ✓" if r["ratio"] <= tgt else " ✗ miss"
            lines.append(f"| {st} | {_fmt(r.get('minegeo_s'), '.4f')} | {_fmt(r.get('open3d_s'), '.4f')} | "
                         f"{_fmt(r.get('ratio'), '.2f')}{ok} | {'≤ ' + str(tgt) if tgt else '—'} | "
                         f"{_fmt(r.get('compile_s'), '.2f')} | {_agreement_text(st, r)} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small light-set run (< 5 min)")
    ap.add_argument("--json", type=Path, default=None, help="write results JSON here")
    ap.add_argument("--md", type=Path, default=None, help="write the markdown table here")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--only", default="", help="comma-separated subset of stages: " + ",".join(STAGES))
    ap.add_argument("--ransac-seeds", type=int, default=None,
                    help="RANSAC seeds per section (default 10 quick, 6 full light, 10 full paper)")
    a = ap.parse_args(argv)

    from minegeo._provenance import versions

    only = {x.strip() for x in a.only.split(",") if x.strip()}
    if only - set(STAGES):
        ap.error(f"unknown stage(s) {sorted(only - set(STAGES))}; choose from {', '.join(STAGES)}")
    numba.set_num_threads(min(a.threads, numba.config.NUMBA_NUM_THREADS))
    threads = numba.get_num_threads()
    _o3d(threads)
    t_all = time.perf_counter()
    warm = {}
    for mod in ("minegeo.geometry", "minegeo.features", "minegeo.registration"):
        t0 = time.perf_counter()
        try:
            importlib.import_module(mod)._warmup()
            warm[mod] = time.perf_counter() - t0
        except Exception as exc:  # another package's warm-up problem must not stop the benchmark
            warm[mod] = f"warm-up failed: {type(exc).__name__}: {exc}"
        _log(f"warm-up {mod}: {warm[mod]}")
    data = make_data(a.quick, a.seed, threads)
    repeats = a.repeats or (2 if a.quick else 3)
    if a.quick:
        results = run_set(data, light_params(0.4), threads, repeats, seeds=a.ransac_seeds or 10, budget=100_000,
                          quick=True, only=only)
    else:
        results = run_set(data, light_params(0.2), threads, repeats, seeds=a.ransac_seeds or 6, budget=100_000, quick=False,
                          only=only)
        results["paper"] = run_set(data, PAPER, threads, repeats, seeds=a.ransac_seeds or 10, budget=100_000, quick=False,
                                   only=only)
    meta = {"quick": a.quick, "threads": threads, "seed": a.seed, "repeats": repeats,
            "map_raw_points": int(len(data["map"])), "scan_raw_points": int(len(data["scan"])),
            "data_build_s": data["build_s"], "warmup_s": warm, "total_s": time.perf_counter() - t_all,
            "versions": versions()}
    try:
        import open3d

        meta["versions"]["open3d"] = open3d.__version__
    except ImportError:
        pass
    write_results(results, meta, markdown, a.json, a.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
