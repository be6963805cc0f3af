"""Per-frame odometry time of ``minegeo.slam`` on simulated VLP-16 frames, with KISS-ICP beside it.

Frames: the ring of the synthetic small mine (``tests/slam/test_slam_ring.py``: world "small" seed 1,
main drift → crosscut → parallel drift → crosscut → back along the start, trajectory "drive" seed 3),
one VLP-16 rotation every 0.1 s (10 Hz, real time), azimuth step 0.2° (a real VLP-16 at 10 Hz,
28,800 rays) and 0.4° (14,400 rays). ``--seconds`` limits the drive (the simulation costs ~1.5 s per
0.2° frame); the frames are cached in ``--cache`` (npz) so reruns and the fresh-process compile probe
read them instead of simulating again.

Measured per variant, ``--repeats`` interleaved runs (the 2-core machine is shared with other
workers: interleaving gives both libraries the same load; the per-frame time is the median over the
runs, then the median and the 95th percentile over frames):

* ``minegeo``: :func:`minegeo.slam.pipeline.run_slam` with ``SlamParams()`` (voxel 0.3 m, GICP gate
  1 m, keyframes every 2 m / 10° / 10 s); per-frame odometry time = the time between two calls of
  the progress callback (voxel downsampling, covariances, search tree, frame-to-frame GICP with its
  retries, keyframe refinement); per-module totals from ``res.timings_s``.
* ``kiss_icp``: ``KissICP.register_frame`` (kiss-icp 1.3) per frame on the same points, configured
  explicitly (printed): range 0.5-100 m as the sensor model, no deskew (the simulated frames are
  taken at one pose), voxel 1 m (its default ``max_range / 100``), its adaptive threshold,
  ``max_num_threads`` = the thread count.

Compile time: a fresh process (``--compile-probe``) imports minegeo and runs the odometry on the first
frames; with Numba's cache on disk this is the cache-load time a user sees on every start. It is
reported apart from the steady-state numbers.

Usage::

    python benchmarks/bench_odometry.py --threads 2 --json OUT.json --md OUT.md [--seconds 12] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's minegeo, not whatever copy is installed

#: Ren et al. 2019, Table 2 (i7-8700): mean time per frame / per loop / per optimisation (ms).
PAPER_TABLE2_MS = {"gicp_odometry": 51.0, "plane_extraction": 10.0, "loop_detection": 114.0, "graph_optimisation": 15.0}
RATE_HZ = 10.0


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def make_frames(step_deg: float, seconds: float, cache: Path | None):
    """``(frames [(t, points)], truth poses (n, 4, 4) relative to the first)`` of the ring at 10 Hz."""
    path = None if cache is None else cache / f"ring_vlp16_{step_deg:g}deg_{seconds:g}s.npz"
    if path is not None and path.exists():
        z = np.load(path)
        ts, truth, counts = z["times"], z["truth"], z["counts"]
        pts = np.split(z["points"], np.cumsum(counts)[:-1])
        return [(float(t), p) for t, p in zip(ts, pts, strict=True)], truth
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    drifts = {d.name: d.centreline for d in world.drifts}
    parts = [drifts["main_L0_001"], drifts["main_L0_002"], drifts["crosscut_L0_006"],
             drifts["parallel_L0_009"][::-1], drifts["crosscut_L0_005"][::-1], drifts["main_L0_001"]]
    ring = np.concatenate([p if k == 0 else p[1:] for k, p in enumerate(parts)])
    traj = make_trajectory(world, "drive", path=ring, seed=3)
    ts = np.arange(0.0, min(traj.times_s[-1], seconds), 1.0 / RATE_HZ)
    P = interpolate_poses(traj, ts)
    sensor = Velodyne16(azimuth_step_deg=step_deg, rotation_rate_hz=RATE_HZ)
    frames = []
    for k, (t, T) in enumerate(zip(ts, P, strict=True)):
        frames.append((float(t), simulate_scan(world, sensor, T, seed=k).points))
        if k % 25 == 0:
            _log(f"simulated {k + 1}/{len(ts)} frames ({step_deg:g}°)")
    truth = np.einsum("ij,njk->nik", np.linalg.inv(P[0]), P)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, times=ts, truth=truth, counts=np.array([f[1].shape[0] for f in frames]),
                 points=np.concatenate([f[1] for f in frames]))
    return frames, truth


def run_minegeo(frames):
    """``(per-frame odometry times s, res.timings_s, SlamResult)`` of one ``run_slam``."""
    from minegeo.slam.pipeline import SlamParams, run_slam

    stamps = []
    t0 = time.perf_counter()
    res = run_slam(frames, SlamParams(), progress=lambda k: stamps.append(time.perf_counter()))
    # frame 0 is only prepared (no progress call); frame k >= 1 ends at stamps[k - 1]
    per = np.diff(np.concatenate([[t0], stamps]))
    return per, dict(res.timings_s), res


def kiss_config(threads: int):
    from kiss_icp.config import KISSConfig

    cfg = KISSConfig()
    cfg.data.max_range = 100.0
    cfg.data.min_range = 0.5
    cfg.data.deskew = False
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0
    cfg.mapping.max_points_per_voxel = 20
    cfg.registration.max_num_iterations = 500
    cfg.registration.convergence_criterion = 1e-4
    cfg.registration.max_num_threads = int(threads)
    return cfg


def run_kiss(frames, threads: int):
    """``(per-frame times s, poses (n, 4, 4))`` of KISS-ICP."""
    from kiss_icp.kiss_icp import KissICP

    odo = KissICP(kiss_config(threads))
    per, poses = [], []
    for _, pts in frames:
        t0 = time.perf_counter()
        odo.register_frame(np.ascontiguousarray(pts), np.zeros(pts.shape[0]))
        per.append(time.perf_counter() - t0)
        poses.append(np.array(odo.last_pose))
    return np.asarray(per), np.stack(poses)


def _ate(poses, truth):
    from minegeo.io.types import Trajectory
    from minegeo.slam.evaluate import evaluate_trajectory

    ts = np.arange(len(truth)) / RATE_HZ
    e = evaluate_trajectory(Trajectory(ts, poses), Trajectory(ts, truth), align=False)
    return {"ate_rmse_m": float(e.ate.rmse), "ate_max_m": float(e.ate.max), "path_m": float(e.path_length_m)}


def compile_probe(step: float, seconds: float, cache: Path, threads: int, numba_cache: str | None = None) -> dict:
    """Fresh process: import + first odometry frames (Numba compile or cache load), then steady.

    ``numba_cache``: a Numba cache directory for the probe (an empty one measures the compile from
    scratch, as after a fresh install); None uses the usual cache (the cache-load time of every start).
    """
    code = (
        "import sys, time, json, numba\n"
        f"sys.path.insert(0, {str(REPO)!r}); sys.path.insert(0, {str(REPO / 'benchmarks')!r})\n"
        f"numba.set_num_threads({threads})\n"
        "t0 = time.perf_counter()\n"
        "import minegeo.slam.odometry as O\n"
        "t_import = time.perf_counter() - t0\n"
        "from bench_odometry import make_frames\n"
        f"frames, _ = make_frames({step!r}, {seconds!r}, __import__('pathlib').Path({str(cache)!r}))\n"
        "t1 = time.perf_counter(); O.run_odometry(frames[:3]); first = time.perf_counter() - t1\n"
        "t2 = time.perf_counter(); O.run_odometry(frames[:3]); again = time.perf_counter() - t2\n"
        "print(json.dumps({'import_s': t_import, 'first_3_frames_s': first, 'again_3_frames_s': again}))\n"
    )
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = numba_cache
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _stats(per_frame_s) -> dict:
    a = 1e3 * np.asarray(per_frame_s)
    return {"median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)), "max_ms": float(a.max()),
            "mean_ms": float(a.mean())}


def bench_step(step: float, seconds: float, a) -> dict:
    frames, truth = make_frames(step, seconds, a.cache)
    n = len(frames)
    _log(f"{step:g}°: {n} frames, {np.mean([f[1].shape[0] for f in frames]):.0f} points per frame")
    mg_runs, kiss_runs, mods, res = [], [], [], None
    for r in range(a.repeats):
        for lib in (("minegeo", "kiss") if r % 2 == 0 else ("kiss", "minegeo")):  # interleaved
            if lib == "minegeo":
                per, tim, res = run_minegeo(frames)
                mg_runs.append(per)
                mods.append(tim)
            else:
                per, kiss_poses = run_kiss(frames, a.threads)
                kiss_runs.append(per)
        _log(f"{step:g}°: repeat {r + 1}/{a.repeats} done")
    mg = np.median(np.stack(mg_runs), axis=0)[1:]  # frame 0 is only prepared
    ks = np.median(np.stack(kiss_runs), axis=0)[1:]
    mod_med = {k: float(statistics.median(m[k] for m in mods)) for k in mods[0]}
    n_kf = int(res.keyframes.size)
    n_loops = len(res.loops)
    return {
        "azimuth_step_deg": step, "frames": n, "points_per_frame": float(np.mean([f[1].shape[0] for f in frames])),
        "keyframes": n_kf, "loop_candidates": n_loops, "loops_accepted": sum(bool(c.accepted) for c in res.loops),
        "minegeo_per_frame": _stats(mg), "kiss_icp_per_frame": _stats(ks),
        "minegeo_modules_total_s": mod_med,
        "minegeo_modules_ms": {
            "odometry_per_frame": 1e3 * mod_med["odometry"] / (n - 1),
            "odometry_prepare_per_frame": 1e3 * mod_med["odometry_prepare"] / n,
            "odometry_frame_to_frame_per_frame": 1e3 * mod_med["odometry_frame_to_frame"] / (n - 1),
            "odometry_keyframe_refine_per_keyframe": 1e3 * mod_med["odometry_keyframe_refine"] / max(n_kf - 1, 1),
            "floor_planes_per_keyframe": 1e3 * mod_med["floor_planes"] / n_kf,
            "loop_closure_per_keyframe": 1e3 * mod_med["loop_closure"] / n_kf,
            "pose_graph_per_optimisation": 1e3 * mod_med["pose_graph"],
            "map_total": 1e3 * (mod_med["map"] + mod_med["map_noise"]),
        },
        "accuracy": {"minegeo_odometry": _ate(res.odometry.poses, truth), "minegeo_slam": _ate(res.poses, truth),
                     "kiss_icp": _ate(kiss_poses, truth)},
        "frames_failed": int((~res.odometry.frame_ok).sum()),
    }


def markdown(out: dict) -> str:
    m = out["meta"]
    L = [f"Odometry benchmark: simulated VLP-16 at {RATE_HZ:g} Hz on the synthetic ring, {m['threads']} thread(s), "
         f"medians of {m['repeats']} interleaved runs. Load before / after: `{m['uptime_before']}` / "
         f"`{m['uptime_after']}` (2 cores shared with other workers).", ""]
    L += ["KISS-ICP configuration: `" + m["kiss_config"] + "`", ""]
    for s in out["steps"]:
        mg, ks, mm = s["minegeo_per_frame"], s["kiss_icp_per_frame"], s["minegeo_modules_ms"]
        L += [f"**{s['azimuth_step_deg']:g}° azimuth step**: {s['frames']} frames ({s['points_per_frame']:.0f} points "
              f"each), {s['keyframes']} keyframes, {s['loop_candidates']} loop candidate(s), "
              f"{s['loops_accepted']} accepted, {s['frames_failed']} failed frame(s)", "",
              "| per frame | median ms | p95 ms | max ms |", "|---|---:|---:|---:|",
              f"| minegeo odometry (prepare + GICP + keyframe refinement) | {mg['median_ms']:.1f} | {mg['p95_ms']:.1f} | "
              f"{mg['max_ms']:.1f} |",
              f"| KISS-ICP `register_frame` | {ks['median_ms']:.1f} | {ks['p95_ms']:.1f} | {ks['max_ms']:.1f} |", "",
              "| module (Ren 2019 Table 2 row) | minegeo ms | paper ms (i7-8700) | unit |", "|---|---:|---:|---|",
              f"| laser odometry (GICP) | {mm['odometry_per_frame']:.1f} | {PAPER_TABLE2_MS['gicp_odometry']:.0f} | "
              "mean per frame |",
              f"| ↳ prepare (voxel, covariances, tree; with 2+ threads in a worker thread, overlapping the "
              f"GICP of the previous frame) | {mm['odometry_prepare_per_frame']:.1f} | – | mean per frame |",
              f"| ↳ frame-to-frame GICP | {mm['odometry_frame_to_frame_per_frame']:.1f} | – | mean per frame |",
              f"| ↳ keyframe refinement | {mm['odometry_keyframe_refine_per_keyframe']:.1f} | – | per keyframe |",
              f"| plane extraction | {mm['floor_planes_per_keyframe']:.1f} | {PAPER_TABLE2_MS['plane_extraction']:.0f} | "
              "per keyframe (paper: per frame) |",
              f"| loop detection + GICP verification | {mm['loop_closure_per_keyframe']:.1f} | "
              f"{PAPER_TABLE2_MS['loop_detection']:.0f} | per keyframe (paper: per loop) |",
              f"| pose-graph optimisation | {mm['pose_graph_per_optimisation']:.1f} | "
              f"{PAPER_TABLE2_MS['graph_optimisation']:.0f} | per optimisation (minegeo: one, at the end) |",
              f"| map (noise removal + voxel) | {mm['map_total']:.1f} | – | total |", ""]
        acc = s["accuracy"]
        L += ["Accuracy, no alignment: " + "; ".join(
            f"{k} ATE RMSE {v['ate_rmse_m']:.3f} m (max {v['ate_max_m']:.3f} m)" for k, v in acc.items())
            + f"; path {acc['minegeo_odometry']['path_m']:.1f} m.", ""]
    for kind, what in (("cold", "empty Numba cache: compile from scratch, as after an install"),
                       ("cached", "Numba cache on disk: every later start")):
        c = m.get("compile_probe", {}).get(kind)
        if c:
            L += [f"Fresh process, {what}: import {c['import_s']:.2f} s, first 3 frames "
                  f"{c['first_3_frames_s']:.2f} s, the same 3 frames again {c['again_3_frames_s']:.2f} s "
                  f"(compile or cache load ≈ {c['first_3_frames_s'] - c['again_3_frames_s']:.2f} s).", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=float, nargs="+", default=[0.2, 0.4], help="azimuth steps (deg)")
    ap.add_argument("--seconds", type=float, nargs="+", default=[12.0, 41.0],
                    help="length of the drive per azimuth step (s of the ring, 41 s = the whole ring; one value: all)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/minegeo_bench_odometry"))
    ap.add_argument("--frames-only", action="store_true", help="simulate and cache the frames, then stop")
    a = ap.parse_args(argv)

    import numba

    numba.set_num_threads(min(a.threads, numba.config.NUMBA_NUM_THREADS))
    a.threads = numba.get_num_threads()
    secs = dict(zip(a.steps, a.seconds if len(a.seconds) == len(a.steps) else a.seconds[:1] * len(a.steps),
                    strict=True))
    if a.frames_only:
        for s in a.steps:
            make_frames(s, secs[s], a.cache)
        return 0
    from minegeo._provenance import atomic_write_text, to_jsonable, versions, write_json_atomic

    up0 = os.popen("uptime").read().strip()
    for s in a.steps:
        make_frames(s, secs[s], a.cache)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="numba_cold_") as cold:
        probe = {"cold": compile_probe(a.steps[0], secs[a.steps[0]], a.cache, a.threads, cold)}
    probe["cached"] = compile_probe(a.steps[0], secs[a.steps[0]], a.cache, a.threads)
    _log(f"compile probe: {probe}")
    steps = [bench_step(s, secs[s], a) for s in a.steps]
    from importlib.metadata import version

    meta = {"threads": a.threads, "repeats": a.repeats, "seconds": secs, "rate_hz": RATE_HZ,
            "uptime_before": up0, "uptime_after": os.popen("uptime").read().strip(), "compile_probe": probe,
            "kiss_config": repr(kiss_config(a.threads)), "paper_table2_ms": PAPER_TABLE2_MS, "versions": versions()}
    meta["versions"]["kiss_icp"] = version("kiss-icp")
    out = {"meta": meta, "steps": steps}
    md = markdown(out)
    print(md)
    if a.json:
        write_json_atomic(a.json, to_jsonable(out))
    if a.md:
        atomic_write_text(a.md, md + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
