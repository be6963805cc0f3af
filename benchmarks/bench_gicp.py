"""GICP benchmark: minegeo ``register_gicp`` vs Open3D 0.20 vs small_gicp on the same inputs.

Cases
-----
* ``small_gicp_pair``: the real LiDAR pair of ``shared/data/small_gicp_pair`` (known
  ``T_target_source``), 0.3 m voxel centroids (minegeo ``voxel_downsample``; the same arrays go
  to every library), gate 1 m, starts = the truth perturbed by up to ±0.5 m per axis and ±10°
  about a random axis (small_gicp's ``registration_test.cpp``), seeded.
* ``synthetic_tunnel`` (``--synthetic``): a 20 m VLP-16 scan of a regular drift section of the
  seeded synthetic mine (``minegeo.synth``) against the survey map cropped to 40 m around it,
  0.3 m voxels, gate 1 m, starts = truth perturbed by ±0.3 m / ±3°.

Variants (each timed end to end from the downsampled points: covariances + registration,
because Open3D and small_gicp compute their covariances inside the call)

* ``minegeo``: ``GICPParams(d)`` (default: step convergence test, cycle stop, "minegeo"
  covariances);
* ``minegeo_open3d``: ``GICPParams.open3d(d)`` (Open3D's covariances and loop);
* ``minegeo_cached``: default parameters with both clouds' covariances precomputed (what a
  prepared map and a cached previous frame give; registration only);
* ``minegeo_cached_pyloop``: ``minegeo_cached`` through the Python loop
  (``registration.loop.run_loop``, ``register_gicp(..., engine="python")``) instead of the one-kernel
  default loop: what the loop kernel saves;
* ``minegeo_sg_stop``: like for like with small_gicp's loop: its convergence test (step below
  0.1° **and** 1 mm) and its 20-iteration cap (``GICPParams(d, max_iterations=20,
  step_translation_m=1e-3, step_rotation_rad=radians(0.1))``), covariances computed in the call;
* ``open3d``: ``registration_generalized_icp`` (ε = 1e-3, criteria (1e-6, 1e-6, 30));
* ``small_gicp``: ``estimate_covariances`` (k = 20) on both + ``KdTree`` + ``align('GICP')``
  with its default convergence (0.1°, 1 mm, 20 iterations).

Timings are steady-state medians over ``--repeats`` interleaved runs (the machine is shared:
interleaving gives every library the same load). Each timed call is preceded by ``--idle-ms``
(default 50) of sleep: the three libraries use three different OpenMP runtimes, and a runtime
keeps its worker threads spinning for a while after a parallel region, so without the gap a call
runs against the previous library's spinning threads on the same 2 cores (measured at 2 threads:
small_gicp 19.5 ms right after minegeo, 13.9 ms after the gap; minegeo's default 20.3 vs 15.0 ms).
The gap measures each library as it runs in an application that uses only it. minegeo's compile / cache-load time is the
first call in this process and is reported separately. Accuracy: rotation (rad) and
translation (m) error to the known answer; agreement of ``minegeo_open3d`` with Open3D and of
``minegeo`` with small_gicp.

Usage::

    python benchmarks/bench_gicp.py --json OUT.json --md OUT.md [--synthetic] [--threads 2 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))  # this checkout's minegeo, not whatever copy is installed
from bench_registration import write_results  # noqa: E402

SHARED = REPO.parent / "shared" / "data"

VARIANTS = ("minegeo", "minegeo_sg_stop", "minegeo_open3d", "minegeo_cached", "minegeo_cached_pyloop", "open3d",
            "small_gicp")


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _rot_trans(A, B):
    """(rotation angle rad, translation m) of ``B⁻¹ A``."""
    dR = B[:3, :3].T @ A[:3, :3]
    v = [dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]
    ang = float(np.arctan2(np.linalg.norm(v) / 2, (np.trace(dR) - 1) / 2))
    return ang, float(np.linalg.norm(A[:3, 3] - B[:3, 3]))


def _starts(T, n, seed, max_t, max_deg):
    from minegeo.geometry.se3 import exp_so3

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        D = np.eye(4)
        D[:3, :3] = exp_so3(axis * np.radians(rng.uniform(-max_deg, max_deg)))
        D[:3, 3] = rng.uniform(-max_t, max_t, size=3)
        out.append(D @ T)
    return out


def pair_data():
    from minegeo.geometry import voxel_downsample
    from minegeo.io.pointcloud import read_point_cloud

    d = SHARED / "small_gicp_pair"
    src = voxel_downsample(read_point_cloud(d / "source.ply").points, 0.3).points
    tgt = voxel_downsample(read_point_cloud(d / "target.ply").points, 0.3).points
    return np.ascontiguousarray(src), np.ascontiguousarray(tgt), np.loadtxt(d / "T_target_source.txt")


def tunnel_data(seed: int):
    from minegeo.geometry import voxel_downsample
    from minegeo.synth import Velodyne16, build_map, build_world, local_scan

    world = build_world("small", seed=seed)
    cloud = build_map(world, seed=seed, spacing_m=4.0)
    scan, _, T_map_scan = local_scan(world, "regular", 20.0, Velodyne16(azimuth_step_deg=0.4), seed=seed + 1,
                                     max_rays=60_000)
    centre = T_map_scan[:3, :3] @ scan.points.mean(axis=0) + T_map_scan[:3, 3]
    m = cloud.points[np.linalg.norm(cloud.points - centre, axis=1) < 40.0]
    src = voxel_downsample(scan.points, 0.3).points
    tgt = voxel_downsample(m, 0.3).points
    return np.ascontiguousarray(src), np.ascontiguousarray(tgt), T_map_scan


def run_case(name, src, tgt, T_true, starts, d, threads, repeats, idle_s=0.05):
    import open3d as o3d
    import small_gicp as sg

    from minegeo.registration import GICPParams, estimate_gicp_covariances, register_gicp

    reg = o3d.pipelines.registration
    prm = GICPParams(d)
    prm_o3d = GICPParams.open3d(d)
    prm_sg = GICPParams(d, max_iterations=20, step_translation_m=1e-3, step_rotation_rad=float(np.radians(0.1)))

    def v_minegeo(T0):
        r = register_gicp(src, tgt, T0, prm)
        return r.T_target_source, r.iterations, r.fitness

    def v_minegeo_sg_stop(T0):
        r = register_gicp(src, tgt, T0, prm_sg)
        return r.T_target_source, r.iterations, r.fitness

    def v_minegeo_open3d(T0):
        r = register_gicp(src, tgt, T0, prm_o3d)
        return r.T_target_source, r.iterations, r.fitness

    covs = (estimate_gicp_covariances(src, prm), estimate_gicp_covariances(tgt, prm))

    def v_minegeo_cached(T0):
        r = register_gicp(src, tgt, T0, prm, source_covariances=covs[0], target_covariances=covs[1])
        return r.T_target_source, r.iterations, r.fitness

    def v_minegeo_cached_pyloop(T0):
        r = register_gicp(src, tgt, T0, prm, source_covariances=covs[0], target_covariances=covs[1], engine="python")
        return r.T_target_source, r.iterations, r.fitness

    def v_open3d(T0):
        ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
        pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
        o = reg.registration_generalized_icp(ps, pt, d, T0, reg.TransformationEstimationForGeneralizedICP(epsilon=1e-3),
                                             reg.ICPConvergenceCriteria(1e-6, 1e-6, 30))
        return np.asarray(o.transformation), None, o.fitness

    def v_small_gicp(T0):
        ps, pt = sg.PointCloud(src), sg.PointCloud(tgt)
        ts = sg.KdTree(ps, num_threads=threads)
        tt = sg.KdTree(pt, num_threads=threads)
        sg.estimate_covariances(ps, ts, num_neighbors=20, num_threads=threads)
        sg.estimate_covariances(pt, tt, num_neighbors=20, num_threads=threads)
        o = sg.align(pt, ps, tt, init_T_target_source=T0, registration_type="GICP",
                     max_correspondence_distance=d, num_threads=threads)
        return np.asarray(o.T_target_source), o.iterations, o.num_inliers / len(src)

    fns = {"minegeo": v_minegeo, "minegeo_sg_stop": v_minegeo_sg_stop, "minegeo_open3d": v_minegeo_open3d, "minegeo_cached": v_minegeo_cached,
           "minegeo_cached_pyloop": v_minegeo_cached_pyloop, "open3d": v_open3d, "small_gicp": v_small_gicp}
    from minegeo.registration import gicp as G

    prange_rows = [G._parallel_rows(G.PARALLEL_SEARCH_ROWS)]  # from the thread count (speed only, same bits)
    per_start = []
    times = {v: [] for v in VARIANTS}
    for k, T0 in enumerate(starts):
        res = {}
        for v in VARIANTS:
            fns[v](T0)  # warm (caches, allocators)
        for _ in range(repeats):
            for v in VARIANTS:  # interleaved
                time.sleep(idle_s)  # the previous library's OpenMP threads stop spinning
                t0 = time.perf_counter()
                T, it, fit = fns[v](T0)
                times[v].append(time.perf_counter() - t0)
                res[v] = (T, it, fit)
        row = {"start": k, "start_error_to_truth": dict(zip(("rot_rad", "trans_m"), _rot_trans(T0, T_true), strict=True))}
        for v in VARIANTS:
            T, it, fit = res[v]
            row[v] = {"error_to_truth": dict(zip(("rot_rad", "trans_m"), _rot_trans(T, T_true), strict=True)),
                      "iterations": it, "fitness": fit}
        row["agreement_minegeo_open3d_vs_open3d"] = dict(zip(
            ("rot_rad", "trans_m"), _rot_trans(res["minegeo_open3d"][0], res["open3d"][0]), strict=True))
        row["agreement_minegeo_vs_small_gicp"] = dict(zip(
            ("rot_rad", "trans_m"), _rot_trans(res["minegeo"][0], res["small_gicp"][0]), strict=True))
        per_start.append(row)
        _log(f"{name} start {k}: done")
    med = {v: statistics.median(times[v]) for v in VARIANTS}
    prange_rows.append(G._parallel_rows(G.PARALLEL_SEARCH_ROWS))
    summary = {
        "minegeo_prange_from_rows_start_end": prange_rows,
        "n_source": len(src), "n_target": len(tgt), "gate_m": d, "starts": len(starts), "repeats": repeats,
        "idle_before_each_call_s": idle_s,
        "median_s": med,
        "min_s": {v: min(times[v]) for v in VARIANTS},
        "ratio_vs_open3d": {v: med[v] / med["open3d"] for v in VARIANTS},
        "ratio_vs_small_gicp": {v: med[v] / med["small_gicp"] for v in VARIANTS},
        "max_error_to_truth": {v: {"rot_rad": max(r[v]["error_to_truth"]["rot_rad"] for r in per_start),
                                   "trans_m": max(r[v]["error_to_truth"]["trans_m"] for r in per_start)}
                               for v in VARIANTS},
        "max_agreement_minegeo_open3d_vs_open3d": {
            q: max(r["agreement_minegeo_open3d_vs_open3d"][q] for r in per_start) for q in ("rot_rad", "trans_m")},
        "max_agreement_minegeo_vs_small_gicp": {
            q: max(r["agreement_minegeo_vs_small_gicp"][q] for r in per_start) for q in ("rot_rad", "trans_m")},
        "per_start": per_start,
    }
    return summary


def markdown(results: dict, meta: dict) -> str:
    lines = [f"GICP benchmark ({meta['threads']} thread(s), medians of {meta['repeats']} interleaved runs per "
             f"start, {meta.get('idle_ms', 0):g} ms idle before each call; minegeo compile/cache-load "
             f"{meta['compile_s']:.2f} s, first call, excluded). Load before / "
             f"after: `{meta.get('uptime_before', '?')}` / `{meta.get('uptime_after', '?')}` (2 cores shared "
             "with other workers).", ""]
    for case, s in results.items():
        if case == "meta":
            continue
        lines += [f"**{case}**: source {s['n_source']} pts, target {s['n_target']} pts, gate {s['gate_m']} m, "
                  f"{s['starts']} starts; minegeo ran its kernels in prange from "
                  f"{'/'.join(str(r) for r in s['minegeo_prange_from_rows_start_end'])} rows (start/end of the case; "
                  "from the thread count: 2048 with two or more Numba threads)", "",
                  "| variant | median time per registration (ms) | min (ms) | / Open3D | / small_gicp | "
                  "max rot. error to truth (°) | max transl. error to truth (m) | iterations per start |",
                  "|---|---:|---:|---:|---:|---:|---:|---|"]
        for v in VARIANTS:
            e = s["max_error_to_truth"][v]
            its = ",".join("?" if r[v]["iterations"] is None else str(r[v]["iterations"]) for r in s["per_start"])
            lines.append(f"| {v} | {1e3 * s['median_s'][v]:.1f} | {1e3 * s['min_s'][v]:.1f} | "
                         f"{s['ratio_vs_open3d'][v]:.2f} | "
                         f"{s['ratio_vs_small_gicp'][v]:.2f} | {np.degrees(e['rot_rad']):.4f} | {e['trans_m']:.4f} | "
                         f"{its} |")
        a, b = s["max_agreement_minegeo_open3d_vs_open3d"], s["max_agreement_minegeo_vs_small_gicp"]
        lines += ["", f"minegeo_open3d vs Open3D: max {a['rot_rad']:.1e} rad, {a['trans_m']:.1e} m; "
                  f"minegeo (default) vs small_gicp: max {b['rot_rad']:.1e} rad, {b['trans_m']:.1e} m.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="write results JSON here")
    ap.add_argument("--md", type=Path, default=None, help="write the markdown table here")
    ap.add_argument("--threads", type=int, nargs="+", default=[2],
                    help="thread counts (each case runs once per count, every library with that many)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--synthetic", action="store_true", help="also run the synthetic tunnel case")
    ap.add_argument("--idle-ms", type=float, default=50.0,
                    help="sleep before each timed call so the previous library's OpenMP threads stop spinning "
                         "(default 50; 0 = back to back)")
    a = ap.parse_args(argv)

    import os

    import open3d as o3d

    from minegeo._provenance import versions

    uptime_before = os.popen("uptime").read().strip()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    t_all = time.perf_counter()

    # compile / cache-load time: the first GICP calls of this process (both covariance modes)
    from minegeo.registration import GICPParams, register_gicp

    P = np.random.default_rng(0).normal(size=(64, 3))
    t0 = time.perf_counter()
    register_gicp(P, P, np.eye(4), GICPParams(1.0, max_iterations=2))
    register_gicp(P, P, np.eye(4), GICPParams.open3d(1.0, max_iterations=2))
    compile_s = time.perf_counter() - t0
    _log(f"minegeo first calls (compile or cache load): {compile_s:.2f} s")

    results = {}
    run_threads = []
    for nt in a.threads:
        numba.set_num_threads(min(nt, numba.config.NUMBA_NUM_THREADS))
        threads = numba.get_num_threads()
        o3d.utility.set_max_threads(threads)
        run_threads.append(threads)
        src, tgt, T = pair_data()
        results[f"small_gicp_pair_threads{threads}"] = run_case(
            "small_gicp_pair", src, tgt, T, [T @ np.eye(4)] + _starts(T, a.starts - 1, a.seed, 0.5, 10.0),
            1.0, threads, a.repeats, a.idle_ms / 1e3)
        if a.synthetic:
            t0 = time.perf_counter()
            src, tgt, T = tunnel_data(a.seed)
            _log(f"synthetic tunnel: scan {len(src)} pts, map crop {len(tgt)} pts ({time.perf_counter() - t0:.1f} s)")
            results[f"synthetic_tunnel_threads{threads}"] = run_case(
                "synthetic_tunnel", src, tgt, T, _starts(T, a.starts, a.seed + 1, 0.3, 3.0), 1.0, threads, a.repeats,
                a.idle_ms / 1e3)
    threads = ",".join(str(t) for t in run_threads)
    meta = {"threads": threads, "seed": a.seed, "repeats": a.repeats, "starts": a.starts, "compile_s": compile_s,
            "idle_ms": a.idle_ms,
            "total_s": time.perf_counter() - t_all, "versions": versions(), "uptime_before": uptime_before,
            "uptime_after": os.popen("uptime").read().strip()}
    meta["versions"]["open3d"] = o3d.__version__
    try:
        from importlib.metadata import version

        meta["versions"]["small_gicp"] = version("small_gicp")
    except Exception:  # noqa: BLE001 - version lookup only
        pass
    write_results(results, meta, markdown, a.json, a.md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
