"""``minegeo demo``: the whole chain on the built-in small synthetic mine, from LiDAR frames to grid coordinates.

Steps (each CLI step through the same verb a surveyor would run, so the demo exercises the real
contracts and writes the real reports):

1. ``minegeo synth``   - generate the small mine: local scans, trajectories, control points (40, on
   the drift walls), truth. Its survey ``map.ply`` (assembled with the true poses) is not used.
2. ``sequence``        - a vehicle drives a 114 m loop of the mine (main drift, crosscut, parallel
   drift, crosscut, back through the X junction; junction turns on 3 m arcs) with a VLP-16 (2 degree
   azimuth step, 16 rings); one frame every 0.5 s (1.25 m) at the true poses, written to
   ``OUT/sequence/frames/`` (binary PLY, ``times.txt``), the true poses to ``OUT/sequence/truth.tum``
   (world frame, for the comparison only). See docs/demo.md.
3. ``minegeo slam``    - map and trajectory from those frames alone: ``OUT/slam/map.ply`` in the
   SLAM frame (origin: the first sensor pose). Its trajectory is compared with the truth (ATE,
   no alignment).
4. ``minegeo georef``  - georeference the SLAM map into EPSG:5186. The control points come from
   the synthetic survey (grid coordinates with 5 mm noise); their map coordinates are *read off the
   SLAM map*: each target is seen from the nearest frame and placed by SLAM's estimate of that
   frame (:func:`minegeo.synth.sequence.pick_gcps_in_map`), so they carry the SLAM error; targets
   outside the mapped drifts are left out. The true world-to-SLAM transform is never given to it.
5. ``minegeo mast``    - position a 2D scanner from wall beacons (synthetic MAST scenario).
6. ``minegeo localize`` - place the local scans that lie in the mapped drifts, and their
   trajectories, in the georeferenced SLAM map (``--profile fast``, the CLI default).

A summary table compares every answer with the synthetic ground truth (the localized scans in
EPSG:5186 against ``T_crs_map · T_map_scan`` of the truth); it is printed and written to
``OUT/report.html`` (:mod:`minegeo.report.demo_report`) with a relative link to each step's own
``report.html``, and to ``OUT/result.json``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from minegeo.cli import _common
from minegeo.cli._argtypes import int_in_range

HELP = "run the whole chain (frames -> SLAM map -> georeference -> localize) on the small synthetic mine"

log = logging.getLogger(__name__)

#: the demo's fixed choices (recorded in result.json)
N_GCPS = 40
FRAME_RATE_HZ = 2.0
AZIMUTH_STEP_DEG = 2.0
#: stated std. dev. of a target read off the SLAM map (georef --sigma-local-m): the RMS of the
#: a-posteriori sigma of the SLAM-map control points over seeds 1-4 (sub-map odometry; sigma0 with
#: 0.012 m: 0.96, 1.17, 1.30, 0.59, so seed 4's chi-square test rightly flags it as pessimistic)
SIGMA_PICK_M = 0.012
MAX_SCAN_GAP_M = 4.0  # a scan is localized when its whole true trajectory is this close to the drive


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="minegeo-demo", help="output directory (default ./minegeo-demo)")
    parser.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=1, help="random seed (default 1)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing demo directory")
    parser.add_argument("--no-background-compile", action="store_true",
                        help="do not compile the mast/localize kernels in a second process while the first "
                             "steps run (the default on a fresh install, where it saves ~40 s on two cores)")


def _run_verb(argv: list[str]) -> int:
    from minegeo.cli import main

    return main(["-q", *argv])


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _err_m(T_est, T_true) -> tuple[float, float]:
    from minegeo.geometry.se3 import rotation_angle

    T_est, T_true = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    # remove a similarity scale before comparing rotations (polar decomposition)
    U, _, Vt = np.linalg.svd(T_est[:3, :3])
    T_est = T_est.copy()
    T_est[:3, :3] = U @ Vt
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    dr = float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])))
    return dt, dr


def run(args) -> int:
    from minegeo._output import output_lock
    from minegeo.errors import InputError

    out = Path(args.out)
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not args.force:
        raise InputError(f"{out} exists and is not empty; use --force or another --out")
    # one demo at a time per folder; each step below stages and commits its own result folder
    with output_lock("demo", "--out", out):
        return _run(args, out)


def _row(step: str, t0: float | None, status: str, result: str, report: Path | None, out: Path) -> dict:
    """One summary row; ``report`` is linked relative to ``out`` when the step wrote it."""
    rel = report.relative_to(out).as_posix() if report is not None and report.is_file() else None
    return {"step": step, "time_s": None if t0 is None else time.perf_counter() - t0, "status": status,
            "result": result, "report": rel}


class _Rows(list):
    """The summary rows; each appended row advances the demo's progress bar."""

    def __init__(self, bar):
        super().__init__()
        self.bar = bar

    def append(self, row) -> None:
        super().append(row)
        self.bar.set_postfix_str(str(row.get("step", "")))
        self.bar.update(1)


def _run(args, out: Path) -> int:
    import sys

    from tqdm import tqdm

    from minegeo._output import progress_enabled

    with tqdm(total=7, desc="demo", unit="step", file=sys.stderr, disable=not progress_enabled(args)) as bar:
        return _steps(args, out, _Rows(bar))


def _synth(args, out: Path, rows) -> dict | None:
    """Step 1: the synthetic mine (``OUT/mine``); its truth.json, or None when the verb failed."""
    t0 = time.perf_counter()
    mine = out / "mine"
    argv = ["synth", str(mine), "--preset", "small", "--seed", str(args.seed), "--gcps", str(N_GCPS)]
    if args.force:
        argv.append("--force")
    if _run_verb(argv) != 0:
        return None
    rows.append(_row("synth", t0, "ok", f"small mine written to {mine}", mine / "report.html", out))
    return _json(mine / "truth.json")


def _sequence(args, out: Path, rows) -> dict:
    """Step 2: the VLP-16 frames of the demo loop (``OUT/sequence``); the true trajectory and path."""
    from minegeo.io import write_trajectory
    from minegeo.synth.sensors import Velodyne16
    from minegeo.synth.sequence import DEMO_LOOP, route_path, simulate_sequence, write_frames
    from minegeo.synth.world import build_world

    t0 = time.perf_counter()
    world = build_world("small", args.seed)
    path = route_path(world, DEMO_LOOP["drifts"], DEMO_LOOP["start_m"], DEMO_LOOP["end_m"])
    truth, frames = simulate_sequence(world, path, rate_hz=FRAME_RATE_HZ,
                                      sensor=Velodyne16(azimuth_step_deg=AZIMUTH_STEP_DEG), seed=args.seed)
    seq = out / "sequence"
    if seq.is_dir():  # an earlier demo's (--force): the frames folder is read whole
        shutil.rmtree(seq)
    write_frames(seq / "frames", truth.times_s, frames)
    write_trajectory(seq / "truth.tum", truth, format="tum")
    length = float(np.linalg.norm(np.diff(truth.poses[:, :3, 3], axis=0), axis=1).sum())
    n_pts = sum(f.shape[0] for f in frames)
    rows.append(_row("sequence", t0, "ok", f"{len(frames)} VLP-16 frames ({AZIMUTH_STEP_DEG:g} deg azimuth step, "
                     f"{FRAME_RATE_HZ:g} Hz, {n_pts:,} points) along a {length:.0f} m loop, in "
                     f"{seq.name}/frames", None, out))
    return {"truth": truth, "frames": seq / "frames", "n_frames": len(frames), "length_m": length}


def _slam(args, out: Path, rows, seq: dict) -> dict | None:
    """Step 3: ``minegeo slam`` on the frames; its result.json (with the ATE against the truth) or None."""
    from minegeo.io import read_trajectory
    from minegeo.io.types import Trajectory
    from minegeo.slam.evaluate import evaluate_trajectory

    t0 = time.perf_counter()
    dest = out / "slam"
    rc = _run_verb(["slam", "--frames", str(seq["frames"]), "--out", str(dest), "--seed", str(args.seed)])
    if rc != 0 or not (dest / "result.json").is_file():
        rows.append(_row("slam", None, "failed", f"failed (exit {rc})", dest / "report.html", out))
        return None
    s = _json(dest / "result.json")
    res = s["result"]
    truth = seq["truth"]
    T0inv = np.linalg.inv(truth.poses[0])  # evaluation only: the truth in the SLAM frame
    gt = Trajectory(truth.times_s, np.einsum("ij,njk->nik", T0inv, truth.poses))
    ev = evaluate_trajectory(read_trajectory(dest / "trajectory.tum"), gt, align=False)
    s["ate_rmse_m"], s["ate_max_m"] = float(ev.ate.rmse), float(ev.ate.max)
    rows.append(_row("slam", t0, str(s.get("status")),
                     f"{res['frames']} frames, {res['keyframes']} keyframes, {res['loops_accepted']} loop(s) "
                     f"accepted, map {res['map_points']:,} points; trajectory vs truth (no alignment) "
                     f"ATE RMSE {ev.ate.rmse:.3f} m, max {ev.ate.max:.3f} m", dest / "report.html", out))
    return s


def _georef(args, out: Path, rows, truth: dict, seq: dict, slam: dict | None) -> dict | None:
    """Step 4: control points read off the SLAM map, then ``minegeo georef`` of ``OUT/slam/map.ply``."""
    from minegeo.errors import InputError
    from minegeo.io import read_gcps, read_point_cloud, read_trajectory, write_gcps
    from minegeo.synth.sequence import pick_gcps_in_map

    geo_dir = out / "georef"
    if slam is None:
        rows.append(_row("georef", None, "failed", "no SLAM map to georeference", None, out))
        return None
    t0 = time.perf_counter()
    slam_map = out / "slam" / "map.ply"
    gcps = read_gcps(out / "mine" / "gcps.csv")
    cloud = read_point_cloud(slam_map)
    est = read_trajectory(out / "slam" / "trajectory.tum")
    try:
        picked, pick_rows = pick_gcps_in_map(gcps, seq["truth"], est, cloud.points + np.asarray(cloud.origin))
    except InputError as exc:  # fewer than 3 targets in the mapped drifts
        rows.append(_row("georef", None, "failed", str(exc), None, out))
        return None
    gcp_file = out / "gcps_slam.csv"
    write_gcps(gcp_file, picked)
    geo_map = out / "map_geo.ply"
    rc = _run_verb(["georef", "--map", str(slam_map), "--gcps", str(gcp_file), "--crs", "EPSG:5186",
                    "--sigma-local-m", str(SIGMA_PICK_M), "--out", str(geo_map), "--report", str(geo_dir),
                    "--force"])
    info = {"map": str(slam_map), "gcps": str(gcp_file), "n_gcps": len(picked.ids), "gcps_picked": pick_rows,
            "map_geo": str(geo_map) if rc == 0 else None}
    if rc != 0 or not (geo_dir / "result.json").is_file():
        rows.append(_row("georef", None, "failed", f"failed (exit {rc})", geo_dir / "report.html", out))
        return info
    g = _json(geo_dir / "result.json")
    T_est = g.get("T_crs_map") or g.get("result", {}).get("T_crs_map")
    rms, worst = _placement_error(T_est, est, seq["truth"], np.asarray(truth["T_crs_map"]))
    if T_est is not None:  # for the demo report's plan view (not written to result.json)
        T = np.asarray(T_est, dtype=float)
        seq["plan_slam_crs"] = est.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
        Tm = np.asarray(truth["T_crs_map"], dtype=float)
        seq["plan_true_crs"] = seq["truth"].poses[:, :3, 3] @ Tm[:3, :3].T + Tm[:3, 3]
    sigma0 = g.get("result", {}).get("sigma0", float("nan"))
    info.update(status=g.get("status"), sigma0=sigma0, trajectory_error_rms_m=rms, trajectory_error_max_m=worst)
    rows.append(_row("georef", t0, str(g.get("status")),
                     f"SLAM map with {len(picked.ids)} control points read off it: status {g.get('status')}, "
                     f"sigma0 {sigma0:.3f}; georeferenced SLAM trajectory vs truth in EPSG:5186 RMS {rms:.3f} m, "
                     f"max {worst:.3f} m", geo_dir / "report.html", out))
    return info


def _placement_error(T_crs_slam, est, truth, T_crs_map) -> tuple[float, float]:
    """RMS and largest distance (m) between the georeferenced SLAM positions and the true ones in the grid."""
    if T_crs_slam is None:
        return float("nan"), float("nan")
    T = np.asarray(T_crs_slam, dtype=float)
    k = np.searchsorted(truth.times_s, est.times_s).clip(0, len(truth.times_s) - 1)
    p_est = est.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    p_true = truth.poses[k, :3, 3] @ T_crs_map[:3, :3].T + T_crs_map[:3, 3]
    d = np.linalg.norm(p_est - p_true, axis=1)
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def _mast(args, out: Path, rows) -> None:
    """Step 5: MAST beacon positioning of a 2D scanner."""
    from minegeo.mast.scenario import write_mast_scenario

    t0 = time.perf_counter()
    mast_in = out / "mast_scenario"
    paths = write_mast_scenario(mast_in, seed=args.seed)
    rc = _run_verb(["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]),
                    "--out", str(out / "mast")])
    m = _json(out / "mast" / "result.json") if (out / "mast" / "result.json").exists() else {}
    mt = _json(paths["truth"])
    if m.get("status") == "ok":
        dpos = float(np.hypot(m["x"] - mt["x_m"], m["y"] - mt["y_m"]))
        daz = (m["azimuth_deg"] - mt["azimuth_deg"] + 180.0) % 360.0 - 180.0
        rows.append(_row("mast", t0, "ok",
                         f"x {m['x']:.4f} y {m['y']:.4f} az {m['azimuth_dms']}; vs truth "
                         f"{dpos * 1000:.2f} mm / {abs(daz) * 3600:.1f}\"; 95% ellipse "
                         f"a={m['ellipse95']['a_m'] * 1000:.2f} mm", out / "mast" / "report.html", out))
    else:
        rows.append(_row("mast", None, str(m.get("status") or "failed"),
                         f"status {m.get('status')}: {m.get('reason')} (exit {rc})", out / "mast" / "report.html", out))


def _scans_in_map(truth: dict, mine: Path, drive: np.ndarray) -> list[dict]:
    """The synthetic scans whose whole true trajectory stays within ``MAX_SCAN_GAP_M`` of the drive."""
    from scipy.spatial import cKDTree

    from minegeo.io import read_trajectory

    tree = cKDTree(drive)
    keep = []
    for sc in truth.get("scans", []):
        if not sc.get("trajectory"):
            continue
        tr = read_trajectory(mine / sc["trajectory"])
        pos = tr.poses[:, :3, 3] @ np.asarray(sc["T_map_scan"])[:3, :3].T + np.asarray(sc["T_map_scan"])[:3, 3]
        if float(tree.query(pos)[0].max()) <= MAX_SCAN_GAP_M:
            keep.append(sc)
    return keep


def _localize(args, out: Path, rows, truth: dict, scans: list[dict], geo: dict | None) -> None:
    """Step 6: ``minegeo localize`` of each scan in the georeferenced SLAM map; errors in the grid."""
    mine = out / "mine"
    T_crs_map = np.asarray(truth["T_crs_map"])
    geo_map = None if geo is None or not geo.get("map_geo") else Path(geo["map_geo"])
    plan_scans = geo.setdefault("_plan_scans", []) if geo is not None else []
    for sc in scans:
        name = Path(sc["file"]).stem
        if geo_map is None or not geo_map.exists():
            rows.append(_row(f"localize {name}", None, "failed", "no georeferenced map", None, out))
            continue
        t0 = time.perf_counter()
        dest = out / "localize" / name
        argv = ["localize", "--map", str(geo_map), "--scan", str(mine / sc["file"]), "--out", str(dest),
                "--seed", str(args.seed), "--profile", "fast"]
        if sc.get("trajectory"):
            argv += ["--trajectory", str(mine / sc["trajectory"])]
        rc = _run_verb(argv)
        res = dest / "result.json"
        if not res.exists():
            rows.append(_row(f"localize {name}", None, "failed", f"failed (exit {rc})", None, out))
            continue
        r = _json(res)
        txt = f"status {r['status']}"
        if r.get("T_crs_scan") is not None and r.get("inlier_rmse_m") is not None:
            dt, dr = _err_m(r["T_crs_scan"], T_crs_map @ np.asarray(sc["T_map_scan"]))
            txt += f", inlier RMSE {r['inlier_rmse_m']:.3f} m, vs truth in EPSG:5186 {dt:.3f} m / {dr:.2f} deg"
            r["error_m"], r["error_deg"] = dt, dr
        T_true = T_crs_map @ np.asarray(sc["T_map_scan"])
        T_got = r.get("T_crs_scan") if r["status"] == "ok" else None
        plan_scans.append((name, None if T_got is None else np.asarray(T_got)[:3, 3], T_true[:3, 3]))
        if r["status"] != "ok":
            txt += f" ({r.get('reason')})"
        rows.append(_row(f"localize {name}", t0, str(r["status"]), txt, dest / "report.html", out))


#: compiled in a second process while synth, sequence, slam and georef run (on a fresh install)
BACKGROUND_MODULES = ("minegeo.mast", "minegeo.localize")
#: kernels whose cache entries mean the background compilation has nothing to do
BACKGROUND_SENTINELS = (("minegeo.mast._kernels", "_grow_segments"),
                        ("minegeo.localize._kernels", "refine_placements_4dof"))


def _steps(args, out: Path, rows) -> int:
    from minegeo import _background_warmup

    t_start = time.perf_counter()
    why = ("disabled (--no-background-compile)" if args.no_background_compile
           else _background_warmup.reason_not_to_start(BACKGROUND_SENTINELS))
    bg = None if why else _background_warmup.launch(BACKGROUND_MODULES)
    compile_rec = {"modules": list(BACKGROUND_MODULES), "status": why or "could not start (see the log)"}
    try:
        truth = _synth(args, out, rows)
        if truth is None:
            return 1
        seq = _sequence(args, out, rows)
        slam = _slam(args, out, rows, seq)
        geo = _georef(args, out, rows, truth, seq, slam)
        if bg is not None:  # mast and localize load the kernels the second process compiled
            compile_rec = bg.merge()
        _mast(args, out, rows)
        scans = _scans_in_map(truth, out / "mine", seq["truth"].poses[:, :3, 3])
        _localize(args, out, rows, truth, scans, geo)
    finally:
        if bg is not None:
            bg.cancel()
    return _finish(args, out, rows, t_start, seq, slam, geo, scans, compile_rec)


def _compile_text(rec: dict) -> str:
    """One line on the second process that compiled the mast/localize kernels."""
    txt = f"{', '.join(rec['modules'])}: {rec['status']}"
    if "seconds" in rec:
        txt += (f" ({rec['seconds']:.1f} s in the second process, {rec['waited_s']:.1f} s waited for, "
                f"{rec['functions_copied']} kernels copied into this cache)")
    return txt


def _finish(args, out: Path, rows, t_start: float, seq: dict, slam: dict | None, geo: dict | None,
            scans: list[dict], compile_rec: dict) -> int:
    """The demo's report.html, result.json and the printed table."""
    from minegeo._output import run_timings
    from minegeo._provenance import arguments_provenance, versions, write_json_atomic
    from minegeo.report.demo_report import plot_demo_png, write_demo_report

    plan_scans = geo.pop("_plan_scans", []) if geo is not None else []
    plan = None
    if "plan_slam_crs" in seq:
        origin = np.floor(seq["plan_true_crs"][0, :2] / 100.0) * 100.0
        plan = plot_demo_png(seq["plan_true_crs"], seq["plan_slam_crs"], plan_scans, origin)
    total = time.perf_counter() - t_start
    names = [Path(sc["file"]).stem for sc in scans]
    report = write_demo_report(out / "report.html", rows, args.seed, total,
                               {"preset": "small", "crs": "EPSG:5186", "localize profile": "fast",
                                "sequence": f"VLP-16, {AZIMUTH_STEP_DEG:g} deg azimuth step, {FRAME_RATE_HZ:g} Hz, "
                                            f"{seq['n_frames']} frames, {seq['length_m']:.0f} m loop",
                                "map": "slam/map.ply (SLAM frame), georeferenced from control points read off it",
                                "localized scans": ", ".join(names) or "none (in the mapped drifts)",
                                "background compilation": _compile_text(compile_rec)},
                               plan_png=plan, compile_s=run_timings(args)["compile_s"])
    params = {"preset": "small", "crs": "EPSG:5186", "localize_profile": "fast", "localized_scans": names,
              "n_gcps_surveyed": N_GCPS, "sigma_pick_m": SIGMA_PICK_M,
              "sequence": {"frames": seq["n_frames"], "length_m": seq["length_m"], "rate_hz": FRAME_RATE_HZ,
                           "azimuth_step_deg": AZIMUTH_STEP_DEG, "folder": str(seq["frames"])}}
    slam_rec = None if slam is None else {
        "map": str(out / "slam" / "map.ply"), "map_points": slam["result"]["map_points"],
        "frames": slam["result"]["frames"], "keyframes": slam["result"]["keyframes"],
        "loops_accepted": slam["result"]["loops_accepted"], "ate_rmse_m": slam["ate_rmse_m"],
        "ate_max_m": slam["ate_max_m"]}
    write_json_atomic(out / "result.json", {
        "command": "demo", "status": "ok" if all(r.get("status") == "ok" for r in rows) else "warnings",
        "seed": int(args.seed), "steps": list(rows), "parameters": params, "slam": slam_rec, "georef": geo,
        "timings_s": {"total": total, **run_timings(args)}, "versions": versions(),
        "background_compilation": compile_rec, "provenance": arguments_provenance(),
    })
    w = max(len(r["step"]) for r in rows)
    print(f"\nminegeo demo (seed {args.seed}) - outputs in {out}/")
    print(f"{'step':<{w}}  {'time':>7}  result")
    for r in rows:
        t = "-" if r["time_s"] is None else f"{r['time_s']:.1f} s"
        print(f"{r['step']:<{w}}  {t:>7}  {r['result']}")
    print(f"{'total':<{w}}  {total:6.1f}s  ({_common.compile_note(args)})")
    print(f"report: {report}")
    return 0
