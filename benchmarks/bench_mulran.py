"""MulRan Riverside02 keyframes: minegeo's GICP odometry against the SC-PGO reference (issue 17).

Data: ``../shared/data/mulran_riverside02_keyframes`` (100 real Ouster OS1-64 keyframe sweeps,
13k points each, 0.6-14.2 m apart at irregular times, 403 m of riverside road; reference poses from
FAST-LIO2 + SC-PGO, trusted to "decimetres and a few tenths of a degree", x/y more than z). Every
frame is made a keyframe (``keyframe_interval_s=0.1`` < the smallest time step, 0.2 s).

Variants (``minegeo.slam.odometry.run_odometry``):

* ``defaults``: minegeo's voxel 0.3 m and gate 1 m (the parameters of ``tests/slam/test_slam_mulran.py``);
* ``wide_gate``: voxel 1 m (about max range / 100) and gate 6 m, wide enough for the 5-6 m error of
  the previous-motion initial guess at keyframes 31-32;
* ``cli``: ``minegeo slam`` (the whole chain: odometry, floor planes, pose graph, map) with the
  ``wide_gate`` parameters, on a folder laid out as the SLAM contract wants it (the scans and
  ``times.txt`` side by side, symlinked into a temporary folder); its ``trajectory.tum`` is compared.

For each: the relative pose of every consecutive pair against the reference's (translation
difference in the reference's gravity-aligned world frame, split horizontal / vertical; rotation
angle, split heading / tilt), its distribution (median, p90, p95, max), the pairs beyond the trust
bounds of the test (0.30 m, 0.5 deg) with the scan check of the test (GICP from the reference's
pose, and the median nearest-neighbour gap of the raw points within 50 m under each pose), the
path lengths and their ratio, the per-frame time (odometry wall time / frames, and per module).
Cross-checks of the per-pair errors: evo's RPE (delta 1 frame, ``pairs_from_reference``) and
``minegeo.slam.evaluate.evaluate_trajectory`` on the same trajectory. The two reference files
(FAST-LIO2 odometry, SC-PGO) are also compared with each other.

Usage::

    python benchmarks/bench_mulran.py --json benchmarks/results/mulran_2026-11-25.json \\
        --md benchmarks/results/mulran_2026-11-25.md

Another commit measured by this same script (``--code``: a checkout of it, e.g. a git worktree)::

    git worktree add ../minegeo-f04d4e1 f04d4e1
    NUMBA_NUM_THREADS=2 python benchmarks/bench_mulran.py --code ../minegeo-f04d4e1 --json J --md M
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: the checkout whose minegeo is measured: this one, or ``--code PATH`` (another checkout, e.g. an older
#: commit in a git worktree, measured by this same script); its path goes first on sys.path in main()
CODE = REPO
DATA = REPO.parent / "shared" / "data" / "mulran_riverside02_keyframes"

TRUST_T_M, TRUST_ROT_DEG = 0.30, 0.5  # as tests/slam/test_slam_mulran.py
GAP_RANGE_M = 50.0
QUANTILES = (50, 90, 95, 100)


def shown(text) -> str:
    """``text`` with this machine's folder above the repository written as ``..`` (as the docs cite data)."""
    return str(text).replace(str(REPO.parent), "..")


def read_kitti_poses(path) -> np.ndarray:
    rows = np.loadtxt(path, dtype=np.float64).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    T[:, :3, :] = rows
    return T


def relative(poses: np.ndarray) -> np.ndarray:
    return np.einsum("nij,njk->nik", np.linalg.inv(poses[:-1]), poses[1:])


def rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of (n, 3, 3) rotations (angles below 180°)."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    a = np.arccos(c)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.where(a > 1e-12, a / (2.0 * np.sin(np.maximum(a, 1e-12))), 0.5)
    return w * s[:, None]


def pair_errors(est: np.ndarray, ref: np.ndarray) -> dict:
    """Per consecutive pair: translation difference (world frame of the reference: horizontal =
    x/y, vertical = z) and rotation difference ``ΔR_ref⁻¹ ΔR_est`` (angle; heading = its world-z
    component, tilt = the rest)."""
    Ze, Zr = relative(est), relative(ref)
    Rw = ref[:-1, :3, :3]
    d = np.einsum("nij,nj->ni", Rw, Ze[:, :3, 3] - Zr[:, :3, 3])
    w = np.einsum("nij,nj->ni", Rw, rotvec(np.einsum("nji,njk->nik", Zr[:, :3, :3], Ze[:, :3, :3])))
    return {"translation_m": np.linalg.norm(d, axis=1), "horizontal_m": np.linalg.norm(d[:, :2], axis=1),
            "vertical_m": np.abs(d[:, 2]), "rotation_deg": np.degrees(np.linalg.norm(w, axis=1)),
            "heading_deg": np.degrees(np.abs(w[:, 2])), "tilt_deg": np.degrees(np.linalg.norm(w[:, :2], axis=1))}


def distribution(err: dict) -> dict:
    return {k: dict(zip(("median", "p90", "p95", "max"), (float(x) for x in np.percentile(v, QUANTILES)), strict=True))
            for k, v in err.items()}


def path_length(poses: np.ndarray, dims=3) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :dims, 3], axis=0), axis=1).sum())


def scan_gap_m(source, target, T) -> float:
    from scipy.spatial import cKDTree

    P = source[np.linalg.norm(source, axis=1) < GAP_RANGE_M]
    return float(np.median(cKDTree(target).query(P @ T[:3, :3].T + T[:3, 3])[0]))


def beyond_trust(frames, ref, est, err, params) -> list[dict]:
    """The pairs beyond the trust bounds, with the test's scan check."""
    from minegeo.slam.odometry import prepare_frame, register_frames

    Ze, Zr = relative(est), relative(ref)
    out = []
    for i in np.flatnonzero((err["translation_m"] > TRUST_T_M) | (err["rotation_deg"] > TRUST_ROT_DEG)):
        src, tgt = frames[i + 1][1], frames[i][1]
        fit = register_frames(prepare_frame(src, 0.0, params), prepare_frame(tgt, 0.0, params), Zr[i], params).T
        fe = pair_errors(np.stack([np.eye(4), fit]), np.stack([np.eye(4), Ze[i]]))
        out.append({"keyframe": int(i) + 1, "translation_m": float(err["translation_m"][i]),
                    "rotation_deg": float(err["rotation_deg"][i]),
                    "reference_step_m": float(np.linalg.norm(Zr[i, :3, 3])),
                    "gicp_from_reference_to_minegeo_m": float(fe["translation_m"][0]),
                    "gicp_from_reference_to_minegeo_deg": float(fe["rotation_deg"][0]),
                    "scan_gap_reference_m": scan_gap_m(src, tgt, Zr[i]), "scan_gap_minegeo_m": scan_gap_m(src, tgt, Ze[i])})
    return out


def cross_checks(times, est, ref, err) -> dict:
    """evo's RPE and minegeo's evaluate on the same trajectory (delta 1 frame)."""
    from minegeo.io.types import Trajectory
    from minegeo.slam.evaluate import evaluate_trajectory

    out = {}
    ev = evaluate_trajectory(Trajectory(times, est), Trajectory(times, ref), rpe_delta=1, rpe_unit="frames")
    out["minegeo_evaluate"] = {"rpe_translation_rmse_m": ev.rpe_translation.rmse,
                               "rpe_translation_max_m": ev.rpe_translation.max,
                               "rpe_rotation_rmse_deg": ev.rpe_rotation_deg.rmse,
                               "rpe_translation_percent": ev.rpe_translation_percent,
                               "ate_rmse_m": ev.ate.rmse, "ate_max_m": ev.ate.max}
    own_rmse = float(np.sqrt(np.mean(err["translation_m"] ** 2)))
    out["own_rpe_translation_rmse_m"] = own_rmse
    try:
        from evo.core import metrics
        from evo.core.trajectory import PoseTrajectory3D
    except ImportError as exc:
        out["evo"] = f"not importable: {exc}"
        return out
    r, e = (PoseTrajectory3D(poses_se3=list(P), timestamps=np.asarray(times)) for P in (ref, est))
    res = {}
    for name, rel in (("translation_m", metrics.PoseRelation.translation_part),
                      ("rotation_deg", metrics.PoseRelation.rotation_angle_deg)):
        rpe = metrics.RPE(rel, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False, pairs_from_reference=True)
        rpe.process_data((r, e))
        res[name] = {"rmse": float(rpe.get_statistic(metrics.StatisticsType.rmse)),
                     "median": float(rpe.get_statistic(metrics.StatisticsType.median)),
                     "max": float(rpe.get_statistic(metrics.StatisticsType.max)),
                     "max_abs_diff_to_own_per_pair": float(np.max(np.abs(np.asarray(rpe.error) - err[name])))}
    out["evo_rpe"] = res
    return out


def run_variant(name, frames, ref, params) -> dict:
    from minegeo.slam.odometry import run_odometry

    t0 = time.perf_counter()
    odo = run_odometry(frames, params)
    wall = time.perf_counter() - t0
    err = pair_errors(odo.poses, ref)
    n = len(frames)
    return {"name": name, "params": {k: getattr(params, k) for k in ("voxel_size_m", "max_correspondence_distance_m",
                                                                   "gicp_max_iterations", "keyframe_interval_s", "frame_target")},
            "poses": odo.poses, "err": err, "distribution": distribution(err),
            "within_trust": int(((err["translation_m"] <= TRUST_T_M) & (err["rotation_deg"] <= TRUST_ROT_DEG)).sum()),
            "pairs": int(err["translation_m"].size), "keyframes": int(odo.keyframes.size),
            "failed_frames": int((~odo.frame_ok).sum()),
            "flagged_frames": {int(k): w for k, w in enumerate(odo.frame_weak) if w},
            "path_m": path_length(odo.poses), "path_horizontal_m": path_length(odo.poses, 2),
            "time_per_frame_s": wall / n, "module_per_frame_s": {k: v / n for k, v in odo.timings_s.items()},
            "beyond_trust": beyond_trust(frames, ref, odo.poses, err, params)}


def run_cli(times, params) -> dict:
    """``minegeo slam`` on a contract-layout folder (symlinks), with the given odometry parameters."""
    from minegeo.cli import main
    from minegeo.io.frames import list_frames
    from minegeo.io.trajectory import read_trajectory

    notes = {}
    try:  # the data folder as it is: times.txt beside pose .txt files that --frames takes for XYZ frames
        list_frames(DATA)
        notes["data_root_as_frames"] = "accepted"
    except Exception as exc:  # noqa: BLE001 - recorded, it is the finding
        notes["data_root_as_frames"] = shown(f"{type(exc).__name__}: {exc}")
    notes["scans_folder_times"] = [f.time_s for f in list_frames(DATA / "scans")][:4]
    with tempfile.TemporaryDirectory() as tmp:
        frames_dir, out = Path(tmp) / "frames", Path(tmp) / "out"
        frames_dir.mkdir()
        for f in sorted((DATA / "scans").glob("*.pcd")):
            (frames_dir / f.name).symlink_to(f)
        (frames_dir / "times.txt").symlink_to(DATA / "times.txt")
        args = ["-q", "slam", "--frames", str(frames_dir), "--out", str(out), "--voxel", str(params.voxel_size_m),
                "--max-distance", str(params.max_correspondence_distance_m), "--keyframe-interval",
                str(params.keyframe_interval_s)]
        t0 = time.perf_counter()
        rc = main(args)
        wall = time.perf_counter() - t0
        traj = read_trajectory(out / "trajectory.tum")
        import json

        result = json.loads((out / "result.json").read_text())
    assert np.allclose(traj.times_s, times, atol=1e-6), "trajectory times are not the times.txt times"
    return {"command": "minegeo " + " ".join(a if "/" not in a else Path(a).name for a in args), "exit": rc,
            "wall_s": wall, "poses": traj.poses, "module_timings_s": result.get("module_timings_s", {}),
            "summary": {k: result["result"].get(k) for k in ("frames", "keyframes", "failed_frames", "weak_frames",
                                                             "path_length_m", "planes", "pose_graph")},
            "layout_notes": notes}


def git_state() -> dict:
    def git(*a):
        return subprocess.run(["git", *a], cwd=CODE, capture_output=True, text=True).stdout.strip()

    return {"commit": git("rev-parse", "HEAD"), "dirty_files": git("status", "--porcelain", "--", "minegeo").splitlines()}


def fmt_table(dist: dict) -> list[str]:
    rows = ["| error | median | p90 | p95 | max |", "|---|---|---|---|---|"]
    for k, v in dist.items():
        f = "{:.3f}" if k.endswith("_m") else "{:.2f}"
        rows.append(f"| {k} | " + " | ".join(f.format(v[q]) for q in ("median", "p90", "p95", "max")) + " |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    ap.add_argument("--md", required=True)
    ap.add_argument("--no-cli", action="store_true", help="skip the minegeo slam run")
    ap.add_argument("--frame-target", choices=("frame", "submap"), default="frame",
                    help="OdometryParams.frame_target of both variants (what each frame registers to; default frame)")
    ap.add_argument("--code", default=str(REPO),
                    help="root of the checkout whose minegeo is measured (default: this one); its commit is recorded")
    a = ap.parse_args(argv)
    global CODE
    CODE = Path(a.code).resolve()
    if "minegeo" in sys.modules:
        raise SystemExit("bench_mulran: minegeo was imported before --code took effect")
    sys.path.insert(0, str(CODE))  # that checkout's minegeo, not whatever copy is installed

    import numba

    from minegeo._provenance import atomic_write_text, to_jsonable, versions, write_json_atomic
    from minegeo.io.frames import read_frame
    from minegeo.slam.odometry import OdometryParams

    times = np.loadtxt(DATA / "times.txt")
    t0 = time.perf_counter()
    frames = [(float(t), read_frame(f)) for t, f in zip(times, sorted((DATA / "scans").glob("*.pcd")), strict=True)]
    read_s = time.perf_counter() - t0
    ref = read_kitti_poses(DATA / "optimized_poses_scpgo.txt")
    fastlio = read_kitti_poses(DATA / "odom_poses_fastlio2.txt")
    ref_path = path_length(ref)

    ft = a.frame_target
    variants = {"defaults": OdometryParams(keyframe_interval_s=0.1, frame_target=ft),
                "wide_gate": OdometryParams(voxel_size_m=1.0, max_correspondence_distance_m=6.0, keyframe_interval_s=0.1,
                                            frame_target=ft)}
    runs = []
    for name, p in variants.items():
        print(f"running {name} ...", file=sys.stderr)
        runs.append(run_variant(name, frames, ref, p))
    for r in runs:
        r["path_ratio"] = r["path_m"] / ref_path
        r["cross_checks"] = cross_checks(times, r["poses"], ref, r["err"])
    cli = None
    if not a.no_cli:
        print("running minegeo slam ...", file=sys.stderr)
        cli = run_cli(times, variants["wide_gate"])
        cerr = pair_errors(cli["poses"], ref)
        cli.update(distribution=distribution(cerr), path_m=path_length(cli["poses"]),
                   path_ratio=path_length(cli["poses"]) / ref_path,
                   within_trust=int(((cerr["translation_m"] <= TRUST_T_M) & (cerr["rotation_deg"] <= TRUST_ROT_DEG)).sum()),
                   max_difference_to_wide_gate_odometry=distribution(pair_errors(cli["poses"], runs[1]["poses"])))
    ref_internal = distribution(pair_errors(fastlio, ref))
    steps = np.linalg.norm(relative(ref)[:, :3, 3], axis=1)
    dts = np.diff(times)

    rec = {
        "data": shown(DATA), "frames": len(frames), "read_s": read_s,
        "reference": {"file": "optimized_poses_scpgo.txt", "path_m": ref_path, "path_horizontal_m": path_length(ref, 2),
                      "step_m": {"min": float(steps.min()), "median": float(np.median(steps)), "max": float(steps.max())},
                      "time_step_s": {"min": float(dts.min()), "median": float(np.median(dts)), "max": float(dts.max())},
                      "fastlio2_vs_scpgo_relative": ref_internal, "fastlio2_path_m": path_length(fastlio)},
        "trust_bounds": {"translation_m": TRUST_T_M, "rotation_deg": TRUST_ROT_DEG},
        "variants": [{k: v for k, v in r.items() if k not in ("poses", "err")} for r in runs],
        "cli": None if cli is None else {k: v for k, v in cli.items() if k != "poses"},
        "git": git_state(), "code": shown(CODE), "versions": versions(),
        "numba_threads": int(numba.config.NUMBA_NUM_THREADS),
        "numba_num_threads_env": os.environ.get("NUMBA_NUM_THREADS"), "load_average_1_5_15": list(os.getloadavg()),
        "command": shown(("NUMBA_NUM_THREADS=" + os.environ["NUMBA_NUM_THREADS"] + " "
                          if "NUMBA_NUM_THREADS" in os.environ else "")
                         + "python benchmarks/bench_mulran.py " + " ".join(argv if argv is not None else sys.argv[1:])),
        "cpu_count": os.cpu_count(),
    }
    write_json_atomic(a.json, to_jsonable(rec))

    md = ["# MulRan Riverside02 keyframes: minegeo odometry against the SC-PGO reference", "",
          f"Generated by `benchmarks/bench_mulran.py` at commit `{rec['git']['commit'][:10]}`"
          + (f" with {len(rec['git']['dirty_files'])} modified file(s) under minegeo/ (other workers' edits)"
             if rec["git"]["dirty_files"] else "") + f". 100 keyframes, every one a keyframe of the odometry. Load average at the end of the run "
          f"{rec['load_average_1_5_15'][0]:.1f} on {rec['cpu_count']} cores (shared machine: times are upper bounds).", "",
          f"Reference: path {ref_path:.2f} m ({path_length(ref, 2):.2f} m horizontal); steps {steps.min():.2f}-"
          f"{steps.max():.2f} m (median {np.median(steps):.2f} m); time steps {dts.min():.2f}-{dts.max():.2f} s. "
          f"Trust bounds of the test: {TRUST_T_M} m, {TRUST_ROT_DEG} deg per pair.", ""]
    for r in runs:
        p = r["params"]
        md += [f"## `{r['name']}`: voxel {p['voxel_size_m']} m, gate {p['max_correspondence_distance_m']} m, "
               f"each frame to the {'local map' if p['frame_target'] == 'submap' else 'previous frame'}", "",
               *fmt_table(r["distribution"]), "",
               f"- within trust: {r['within_trust']} of {r['pairs']} pairs; frames failed: {r['failed_frames']}; "
               f"flagged: {len(r['flagged_frames'])}",
               f"- path {r['path_m']:.2f} m vs {ref_path:.2f} m: ratio **{r['path_ratio']:.4f}**",
               f"- time per frame {r['time_per_frame_s'] * 1e3:.0f} ms ("
               + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in r["module_per_frame_s"].items())
               + "; module times can overlap: the next frame may be prepared in a worker thread)"]
        cc = r["cross_checks"]
        if isinstance(cc.get("evo_rpe"), dict):
            e = cc["evo_rpe"]
            md.append(f"- evo RPE (1 frame): translation RMSE {e['translation_m']['rmse']:.4f} m, max "
                      f"{e['translation_m']['max']:.3f} m, rotation RMSE {e['rotation_deg']['rmse']:.3f} deg; per pair "
                      f"equal to this table's to {max(e['translation_m']['max_abs_diff_to_own_per_pair'], e['rotation_deg']['max_abs_diff_to_own_per_pair']):.1e}; "
                      f"minegeo evaluate RPE RMSE {cc['minegeo_evaluate']['rpe_translation_rmse_m']:.4f} m (evo turns the "
                      "reference's 6-digit rotations, orthonormal to 1e-6 only, into quaternions: hence the 1e-6 level)")
        if r["beyond_trust"]:
            md += ["", "| keyframe | ref step m | Δt m | Δrot deg | GICP from ref → minegeo m / deg | gap ref m | gap minegeo m |",
                   "|---|---|---|---|---|---|---|"]
            md += [f"| {b['keyframe']} | {b['reference_step_m']:.2f} | {b['translation_m']:.3f} | {b['rotation_deg']:.3f} | "
                   f"{b['gicp_from_reference_to_minegeo_m']:.3f} / {b['gicp_from_reference_to_minegeo_deg']:.3f} | "
                   f"{b['scan_gap_reference_m']:.3f} | {b['scan_gap_minegeo_m']:.3f} |" for b in r["beyond_trust"]]
        md.append("")
    if cli is not None:
        md += ["## `minegeo slam` (CLI, `wide_gate` parameters, planes and pose graph on)", "", f"`{cli['command']}`", "",
               *fmt_table(cli["distribution"]), "",
               f"- within trust: {cli['within_trust']} of 99; path ratio **{cli['path_ratio']:.4f}**; wall {cli['wall_s']:.1f} s; "
               f"largest difference to the plain odometry: {cli['max_difference_to_wide_gate_odometry']['translation_m']['max']:.3f} m, "
               f"{cli['max_difference_to_wide_gate_odometry']['rotation_deg']['max']:.3f} deg",
               f"- data folder itself as `--frames`: {cli['layout_notes']['data_root_as_frames']}",
               f"- `--frames scans/`: times from the names, {cli['layout_notes']['scans_folder_times']} ... (not times.txt)", ""]
    md += ["## The two reference files against each other (FAST-LIO2 odometry vs SC-PGO)", "",
           *fmt_table(ref_internal), ""]
    atomic_write_text(a.md, "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
