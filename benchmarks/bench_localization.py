"""Benchmark: global localization on the synthetic mine vs ground truth (Baek et al. 2022, Sec. 3-4).

Reproduces the paper's study with known answers: six section types (irregular roof, curve,
intersection, regular, railings/structures, noisy), scan lengths 10/20/30 m, three sensor
models (ZEB-REVO-like, VLP-16-like, iPad-like flash) and scan octree levels 6/8/10/12, for
minegeo (Table 3 profile and fast profile) and Open3D's pipeline with the paper's parameters
on the same scans. Per run: status, error of the sensor trajectory placed in the map (max over
poses, against truth), inlier RMSE and time per stage.

Usage::

    python benchmarks/bench_localization.py --preset paper --out bench_out/localization
    # reduced sweep (what docs/localization.md reports when the full one is too slow here):
    python benchmarks/bench_localization.py --preset paper --reduced --out bench_out/localization

Writes ``results.json`` (every run) and ``table.md`` (aggregated, minegeo vs Open3D side by side).
Open3D is only used here (never inside minegeo).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SECTIONS = {  # name in the table -> (synth section, noise sigma override)
    "irregular roof": ("irregular_roof", None),
    "curve": ("curve", None),
    "intersection": ("intersection", None),
    "regular": ("regular", None),
    "railings": ("sump", None),
    "noisy": ("regular", 0.08),
}


def _sensor(name: str, noise):
    from minegeo.synth import FlashSensor, Velodyne16, ZebRevo

    # flash: 48 x 36 px per frame (the iPad Pro LiDAR projects 576 dots; its depth map is
    # upsampled), so that the --max-rays budget spans the whole walk instead of 2-5 full frames
    s = {"zebrevo": ZebRevo, "velodyne16": Velodyne16,
         "flash": lambda: FlashSensor(width_px=48, height_px=36)}[name]()
    if noise is not None:
        s = replace(s, range_noise_sigma_m=float(noise))
    return s


def level_scan(cloud, traj, T_map_scan, rng, tilt_error_deg: float):
    """Re-express a synthetic scan in a levelled frame (z up), as an IMU-levelled SLAM output.

    ``T_map_scan = [Rz(yaw) R_tilt | t]``: the scan is rotated by ``L = E R_tilt`` where ``E`` is a
    random tilt error of |N(0, tilt_error_deg)| about a random horizontal axis (the IMU's
    levelling error). Returns (cloud, trajectory, T_map_levelled) with the same map placement.
    """
    from minegeo.geometry.se3 import exp_so3
    from minegeo.io.types import PointCloud, Trajectory

    R = T_map_scan[:3, :3]
    yaw = math.atan2(R[1, 0], R[0, 0])
    cz, sz = math.cos(yaw), math.sin(yaw)
    L = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]]).T @ R
    ax = rng.normal(size=2)
    ax = np.r_[ax / np.linalg.norm(ax), 0.0]
    L = exp_so3(ax * math.radians(tilt_error_deg * abs(rng.normal()))) @ L
    Lh = np.eye(4)
    Lh[:3, :3] = L
    out = PointCloud(np.ascontiguousarray(cloud.points @ L.T), frame="scan")
    poses = np.einsum("ij,njk->nik", Lh, traj.poses)
    tr = Trajectory(times_s=traj.times_s, poses=poses, frame=traj.frame, body=traj.body)
    return out, tr, T_map_scan @ np.linalg.inv(Lh)


def _kind(sensor: str) -> str:
    return "handheld" if sensor == "flash" else "walk"


def plan(reduced: bool, octree_levels=(6, 8, 10, 12)) -> list[dict]:
    """List of runs: dict(section, length_m, sensor, octree_level or None, study)."""
    runs = []
    sensors = ("zebrevo", "velodyne16", "flash")
    lengths = (10.0, 20.0, 30.0)
    for sec in SECTIONS:
        for length in lengths:
            for sen in sensors if not reduced or length == 20.0 else ("zebrevo",):
                runs.append({"section": sec, "length_m": length, "sensor": sen, "octree_level": None,
                             "study": "length/sensor"})
        for lv in octree_levels:
            runs.append({"section": sec, "length_m": 20.0, "sensor": "zebrevo", "octree_level": lv,
                         "study": "octree"})
    return runs


# ----------------------------------------------------------------------------- Open3D pipeline
class Open3DPipeline:
    """Open3D 0.20 with the paper's Table 3 (voxel 0.5, normals r 1 / 1000, FPFH r 2.5 / 1000,
    RANSAC n 4 + EdgeLength 0.9 + Distance 2.5, confidence 0.999, ICP p2p 0.5 m / 30 it / 1e-6)."""

    def __init__(self, map_points: np.ndarray, max_iterations: int, voxel: float = 0.5, icp_voxel: float | None = 0.1):
        import open3d as o3d

        self.o3d = o3d
        self.voxel = voxel
        self.max_iterations = int(max_iterations)
        t0 = time.perf_counter()
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(map_points))
        # ICP target: the paper uses the whole map; Open3D rebuilds its KD-tree over the target in every
        # registration_icp call (~10 s for the 1.6e7-point paper map), so like minegeo it gets 0.1 m voxels
        self.full = pc if icp_voxel is None else pc.voxel_down_sample(icp_voxel)
        self.down, self.fpfh = self._features(pc)
        self.prep_s = time.perf_counter() - t0

    def _features(self, pc):
        o3d = self.o3d
        d = pc.voxel_down_sample(self.voxel)
        d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel, max_nn=1000))
        f = o3d.pipelines.registration.compute_fpfh_feature(
            d, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel, max_nn=1000))
        return d, f

    def run(self, scan_points: np.ndarray, seed: int) -> dict:
        o3d = self.o3d
        reg = o3d.pipelines.registration
        o3d.utility.random.seed(int(seed))
        t = {}
        t0 = time.perf_counter()
        sc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan_points))
        sd, sf = self._features(sc)
        t["features"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = reg.registration_ransac_based_on_feature_matching(
            sd, self.down, sf, self.fpfh, False, 2.5, reg.TransformationEstimationPointToPoint(False), 4,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(2.5)],
            reg.RANSACConvergenceCriteria(self.max_iterations, 0.999))
        t["ransac"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        ic = reg.registration_icp(sc, self.full, 0.5, r.transformation, reg.TransformationEstimationPointToPoint(),
                                  reg.ICPConvergenceCriteria(1e-6, 1e-6, 30))
        t["icp"] = time.perf_counter() - t0
        t["total"] = sum(t.values())
        return {"T": np.asarray(ic.transformation), "fitness": float(ic.fitness), "rmse": float(ic.inlier_rmse),
                "ransac_fitness": float(r.fitness), "timings": t}


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper", choices=("small", "paper"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_out/localization")
    ap.add_argument("--reduced", action="store_true", help="other sensors only at 20 m (fewer runs)")
    ap.add_argument("--max-rays", type=int, default=150_000, help="beams cast per scan (synth thinning)")
    ap.add_argument("--profiles", default="table3,fast", help="minegeo profiles to run (table3, fast)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--ransac-max-iterations", type=int, default=4_000_000,
                    help="RANSAC cap for minegeo table3 and Open3D (the paper's 4e8 would run for hours)")
    ap.add_argument("--limit", type=int, default=None, help="only the first N runs (smoke test)")
    ap.add_argument("--octree-levels", default="6,8,10,12",
                    help="scan octree levels of the octree study (levels 10 and 12 keep nearly every point of a "
                         "20 m scan: minutes per run)")
    ap.add_argument("--levelled", type=float, default=None, metavar="DEG",
                    help="scans in an IMU-levelled frame (levelling error |N(0, --imu-error-deg)|) and minegeo "
                         "told so (RansacParams model='levelled', 2-point yaw+translation samples, "
                         "max_tilt_deg = DEG); Open3D gets the same levelled scans")
    ap.add_argument("--imu-error-deg", type=float, default=0.3)
    ap.add_argument("--hypotheses", type=int, default=None, help="RansacParams.n_hypotheses for minegeo")
    ap.add_argument("--select", default=None, metavar="EXPR",
                    help="keep only the runs for which this Python expression over the run's fields is true, "
                         "e.g. \"octree_level in (None, 6, 8)\" (scan seeds stay those of the whole plan)")
    ap.add_argument("--merge", nargs="+", default=None, metavar="RESULTS_JSON",
                    help="merge the results of earlier runs of the same plan (e.g. minegeo-only and "
                         "Open3D-only) by scan into one table in --out, and exit")
    ap.add_argument("--map-cache", default=None,
                    help="PLY file holding the synthetic map: read if it exists, else built and written there "
                         "(the paper preset's map takes ~15-30 min to build)")
    ap.add_argument("--survey-passes", type=int, default=1,
                    help="interleaved passes of the map survey: 1 = one VLP-16 frame every 12 m on the paper "
                         "preset, 2 = every 6 m (synth.dataset.build_survey_map; the cache must match)")
    ap.add_argument("--study", default="all", choices=("all", "length", "octree"),
                    help="length/sensor runs, octree-level runs, or both")
    args = ap.parse_args(argv)
    if args.merge:
        return _merge(args)

    from minegeo.localize import LocalizeParams, PrepareParams, localize_scan, prepare_map
    from minegeo.localize.pipeline import error_vs_truth
    from minegeo.synth import build_world, local_scan
    from minegeo.synth.dataset import build_survey_map

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    world = build_world(args.preset, args.seed)
    if args.map_cache and Path(args.map_cache).exists():
        from minegeo.io import read_point_cloud

        cloud = read_point_cloud(args.map_cache)
    else:
        cloud = build_survey_map(world, seed=args.seed + 1, passes=args.survey_passes)
        if args.map_cache:
            from minegeo.io import write_point_cloud

            write_point_cloud(args.map_cache, cloud)
    t_world = time.perf_counter() - t0
    print(f"world + map: {len(cloud)} points, {t_world:.0f} s", file=sys.stderr, flush=True)

    profiles = [p for p in args.profiles.split(",") if p]
    prepared, prep_s = {}, {}
    for prof in profiles:
        t0 = time.perf_counter()
        pp = PrepareParams.fast() if prof == "fast" else PrepareParams()
        prepared[prof] = prepare_map(cloud, pp)
        prep_s[prof] = time.perf_counter() - t0
        print(f"prepared {prof}: {len(prepared[prof])} points, {prep_s[prof]:.1f} s", file=sys.stderr, flush=True)
    o3p = None
    if not args.no_open3d:
        try:
            o3p = Open3DPipeline(cloud.points, args.ransac_max_iterations)
            prep_s["open3d"] = o3p.prep_s
            print(f"prepared open3d: {o3p.prep_s:.1f} s", file=sys.stderr, flush=True)
        except ImportError:
            print("open3d not installed: skipping its pipeline", file=sys.stderr)

    # warm-up (compilation) timed separately
    t0 = time.perf_counter()
    import minegeo

    minegeo.warmup() if hasattr(minegeo, "warmup") else None
    t_warm = time.perf_counter() - t0
    # the maps' per-process search structures (KD-trees, descriptor tree, occupancy bitmap),
    # built before the first scan so that its time is the scan's alone
    for prof, pm in prepared.items():
        lp0 = LocalizeParams.fast() if prof == "fast" else LocalizeParams()
        if args.levelled is not None:
            lp0 = replace(lp0, ransac=replace(lp0.ransac, model="levelled", ransac_n=2, max_tilt_deg=float(args.levelled)))
        t0 = time.perf_counter()
        pm.build_indexes(lp0)
        prep_s[f"{prof}_indexes"] = time.perf_counter() - t0

    runs = plan(args.reduced, tuple(int(v) for v in args.octree_levels.split(",")))
    if args.study != "all":
        runs = [r for r in runs if (r["study"] == "octree") == (args.study == "octree")]
    if args.limit:
        runs = runs[: args.limit]
    rng = np.random.default_rng(args.seed)
    for run in runs:  # seeds drawn for the whole plan first: --select keeps the same scans
        run["scan_seed"] = int(rng.integers(0, 2**31 - 1))
    if args.select:
        runs = [r for r in runs if eval(args.select, {}, dict(r))]  # noqa: S307 (benchmark filter)
    records = []
    for k, run in enumerate(runs):
        sec, noise = SECTIONS[run["section"]]
        sseed = run["scan_seed"]
        t0 = time.perf_counter()
        try:
            c, tr, T_true = local_scan(world, sec, run["length_m"], _sensor(run["sensor"], noise), seed=sseed,
                                       kind=_kind(run["sensor"]), max_rays=args.max_rays)
        except Exception as exc:  # section not available in this world
            print(f"skip {run}: {exc}", file=sys.stderr)
            continue
        if args.levelled is not None:
            c, tr, T_true = level_scan(c, tr, T_true, np.random.default_rng(sseed), args.imu_error_deg)
        t_scan = time.perf_counter() - t0
        traj_pts = tr.poses[:, :3, 3]
        rec = dict(run, n_points=len(c), t_synth_s=t_scan, results={})
        for prof in profiles:
            lp = LocalizeParams.fast() if prof == "fast" else LocalizeParams(
                ransac=replace(LocalizeParams().ransac, max_iterations=args.ransac_max_iterations))
            if run["octree_level"] is not None:
                lp = replace(lp, scan_octree_level=int(run["octree_level"]))
            if args.levelled is not None:
                lp = replace(lp, ransac=replace(lp.ransac, model="levelled", ransac_n=2,
                                                max_tilt_deg=float(args.levelled)))
            if args.hypotheses is not None:
                lp = replace(lp, ransac=replace(lp.ransac, n_hypotheses=int(args.hypotheses)))
            try:
                r = localize_scan(prepared[prof], c, tr, lp, seed=args.seed)
                e = error_vs_truth(r.T_map_scan, T_true, traj_pts)
                rec["results"][prof] = {"status": r.status, "reason": r.reason, "traj_err_m": e["max_point_error_m"],
                                        "rot_err_deg": e["rotation_deg"], "inlier_rmse_m": r.inlier_rmse_m,
                                        "fitness": r.fitness, "n_down": r.n_scan_down,
                                        "ransac_iterations": r.ransac.iterations,
                                        "pos95_m": r.position_95_radius_m, "timings": r.timings_s}
            except Exception as exc:  # typed errors (tiny/flat scan) count as failed
                rec["results"][prof] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}",
                                        "traj_err_m": math.inf, "timings": {}}
        if o3p is not None:
            pts = c.points
            if run["octree_level"] is not None:
                from minegeo.geometry import octree_downsample

                pts = octree_downsample(pts, int(run["octree_level"])).points
            o = o3p.run(pts, args.seed)
            e = error_vs_truth(o["T"], T_true, traj_pts)
            rec["results"]["open3d"] = {"status": "n/a", "traj_err_m": e["max_point_error_m"],
                                        "rot_err_deg": e["rotation_deg"], "inlier_rmse_m": o["rmse"],
                                        "fitness": o["fitness"], "timings": o["timings"]}
        records.append(rec)
        line = " ".join(f"{p}:{v['status']}/{v['traj_err_m']:.3f}m/{v['timings'].get('total', float('nan')):.1f}s"
                        for p, v in rec["results"].items())
        print(f"[{k + 1}/{len(runs)}] {run['section']:14s} {run['length_m']:4.0f} m {run['sensor']:10s} "
              f"oct {run['octree_level']} n={len(c)}  {line}", file=sys.stderr, flush=True)
        _write(out, args, records, prep_s, t_world, t_warm, len(cloud))
    _write(out, args, records, prep_s, t_world, t_warm, len(cloud))
    print((out / "table.md").read_text())
    return 0


def _merge(args) -> int:
    """Join the per-scan results of several runs of the same plan (same preset, seed, options)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    merged: dict = {}
    prep_s: dict = {}
    head = None
    for f in args.merge:
        d = json.loads(Path(f).read_text())
        head = head or d
        prep_s.update(d["prep_s"])
        for r in d["records"]:
            key = (r["section"], r["length_m"], r["sensor"], r["octree_level"], r["study"], r["scan_seed"])
            if key in merged:
                merged[key]["results"].update(r["results"])
            else:
                merged[key] = r
    records = list(merged.values())
    _write(out, args, records, prep_s, head["t_world_s"], head["t_warmup_s"], head["n_map_points"])
    print((out / "table.md").read_text())
    return 0


def _agg(recs, prof):
    res = [r["results"][prof] for r in recs if prof in r["results"]]
    if not res:
        return None
    n = len(res)
    err = np.array([x["traj_err_m"] for x in res], dtype=float)
    good = err < 0.10
    if prof == "open3d":
        ok = np.ones(n, dtype=bool)  # Open3D has no status: every answer is "ok"
    else:
        ok = np.array([x["status"] == "ok" for x in res])
    tt = [x["timings"] for x in res]

    def med(key):
        v = [t.get(key) for t in tt if t.get(key) is not None]
        return float(np.median(v)) if v else math.nan

    rm = [x.get("inlier_rmse_m") for x in res if x.get("inlier_rmse_m") is not None and ok[res.index(x)]]
    return {"n": n, "ok_correct": int(np.sum(ok & good)), "ok_wrong": int(np.sum(ok & (err > 0.5))),
            "ok_total": int(ok.sum()), "median_err_ok_m": float(np.median(err[ok & np.isfinite(err)]))
            if np.any(ok & np.isfinite(err)) else math.nan,
            "median_rmse_m": float(np.median(rm)) if rm else math.nan,
            "t_features": (med("downsample") + med("normals") + med("fpfh")) if prof != "open3d" else med("features"),
            "t_ransac": med("ransac"), "t_icp": med("icp"), "t_total": med("total")}


def _write(out: Path, args, records, prep_s, t_world, t_warm, n_map) -> None:
    profs = []
    for r in records:
        for p in r["results"]:
            if p not in profs:
                profs.append(p)
    (out / "results.json").write_text(json.dumps({"args": vars(args), "prep_s": prep_s, "t_world_s": t_world,
                                                  "t_warmup_s": t_warm, "n_map_points": n_map,
                                                  "records": records}, indent=1, default=float))
    lines = [f"Preset `{args.preset}`, seed {args.seed}, map {n_map} points; map preparation (s): "
             + ", ".join(f"{k} {v:.1f}" for k, v in prep_s.items()) + f"; warm-up/compile {t_warm:.1f} s.", "",
             "ok+correct = status ok and trajectory error < 0.10 m; ok+wrong = status ok and error > 0.5 m "
             "(Open3D has no status, so every Open3D answer counts as ok). Times are medians (s, wall).", ""]
    groups = [("all", None, None, None)]
    groups += [(sec, "section", sec, "length/sensor") for sec in SECTIONS]
    groups += [(f"{int(L)} m", "length_m", L, "length/sensor") for L in (10.0, 20.0, 30.0)]
    groups += [(sen, "sensor", sen, "length/sensor") for sen in ("zebrevo", "velodyne16", "flash")]
    groups += [(f"octree {lv}", "octree_level", lv, "octree") for lv in (6, 8, 10, 12)]
    head = "| group | n | " + " | ".join(f"{p} ok+correct | {p} ok+wrong | {p} med err m | {p} RMSE m | "
                                         f"{p} t feat/RANSAC/ICP/total s" for p in profs) + " |"
    lines += [head, "|" + "---|" * (2 + 5 * len(profs))]
    for name, key, val, study in groups:
        rs = [r for r in records if key is None or (r[key] == val and r["study"] == study)]
        if not rs:
            continue
        cells = [name, str(len(rs))]
        for p in profs:
            a = _agg(rs, p)
            if a is None:
                cells += ["-"] * 5
                continue
            cells += [f"{a['ok_correct']}/{a['n']} ({100 * a['ok_correct'] / a['n']:.0f} %)", str(a["ok_wrong"]),
                      f"{a['median_err_ok_m']:.3f}", f"{a['median_rmse_m']:.3f}",
                      f"{a['t_features']:.2f}/{a['t_ransac']:.2f}/{a['t_icp']:.2f}/{a['t_total']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    (out / "table.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
