"""Every 10 Hz sweep in real time? minegeo's SLAM front end and KISS-ICP per frame, deskewed, same frames.

Issue 29, deliverable 6: SLAM on every sweep of a 10 Hz VLP-16-like sensor, with deskewing, at a
median under 50 ms and a 95th percentile under 100 ms per frame on 2 cores.

Frames: ``minegeo synth OUT --stream P --duration-s D --seed S`` (vehicle, handheld, drone; 10 Hz
VLP-16 sweeps, 28 800 beams each, every point with its own time), written once into ``--work`` and
read once into memory by :func:`minegeo.io.frames.iter_frames` (as ``minegeo slam --frames`` reads
them; copied into writable arrays); both libraries then get the very same arrays (points in m, per-point times in s after the
frame time).

Measured in one process, per stream, ``--repeats`` runs alternating the order of the two libraries:

* **minegeo front end**: :func:`minegeo.slam.odometry.run_odometry` with the default
  ``OdometryParams`` (what ``minegeo slam`` runs per frame: deskew by the last motion, voxel
  downsampling, GICP covariances and search tree, frame-to-frame GICP with its retries and the
  motion checks, the second deskew pass and its registration, keyframe decision and keyframe
  refinement). Per frame: the wall time (``time.perf_counter``) and CPU time between two calls of
  its progress callback, the CPU of the calling thread (``time.thread_time``) and of the whole
  process (``time.process_time``: the Numba worker threads too). The first frame has no callback
  of its own: frames 0 and 1 are reported together apart (``first_two_frames_ms``) and left out of
  the statistics.
* **minegeo back end** (apart): :func:`minegeo.slam.pipeline.run_backend` on that odometry (floor
  planes, loop closure, pose graph, map), total and per keyframe.
* **KISS-ICP**: ``KissICP.register_frame(points, times)`` (kiss-icp 1.x, configuration printed) with
  its own constant-velocity deskewing (``data.deskew = True``) from the same per-point times; per
  frame the same three clocks around the call.

Thread counts are set on both sides and recorded: ``numba.set_num_threads(T)`` for minegeo (the
process starts with ``NUMBA_NUM_THREADS`` >= T) and ``registration.max_num_threads = T`` for
KISS-ICP (its TBB preprocessing and registration). One untimed warm-up per library first (Numba's
on-disk cache loaded; compile time is not part of a frame).

Statistics: per frame the minimum over the repeats (the machine is shared: the minimum is the
least disturbed run), then the median, 95th percentile and maximum over the frames; the medians of
each run are recorded too. ``uptime`` before and after. ATE as a sanity column (no alignment, both
trajectories and the truth in their first pose's frame; and SE(3)-aligned): minegeo's poses refer
to the frame time (the sweep start); KISS-ICP 1.3 deskews to the END of the sweep (a point at the
frame's last time is left as it is, one at its first time moved by the whole last motion; checked
on three points in ``kiss_icp.preprocess.Preprocessor``), so its poses are compared with the truth
interpolated at each frame's last point time (:func:`minegeo.slam.control.interpolate_poses`).

Usage::

    NUMBA_NUM_THREADS=2 python benchmarks/bench_realtime.py --threads 2 --duration-s 20 --repeats 3 \\
        --json benchmarks/results/realtime_<date>.json --md benchmarks/results/realtime_<date>.md
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's minegeo

#: The target of issue 29, deliverable 6 (ms per frame).
TARGET_MEDIAN_MS, TARGET_P95_MS = 50.0, 100.0


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def make_stream(work: Path, preset: str, duration_s: float, seed: int) -> Path:
    """The stream folder of ``minegeo synth --stream preset`` (simulated once, then reused)."""
    stream = work / f"{preset}_{duration_s:g}s_seed{seed}"
    if not (stream / "groundtruth.txt").is_file():
        _log(f"simulating {stream.name} ...")
        subprocess.run([sys.executable, "-m", "minegeo.cli", "--quiet", "synth", str(stream), "--stream", preset,
                        "--duration-s", f"{duration_s:g}", "--seed", str(seed), "--force"], check=True)
    return stream


def load_frames(stream: Path):
    """``[(t, points (m, 3), offsets (m,))]`` as ``minegeo slam --frames`` reads them, and the truth."""
    from minegeo.io.frames import iter_frames, list_frames
    from minegeo.io.trajectory import read_trajectory

    frames = []
    for f, pts, tau, exc in iter_frames(list_frames(stream / "frames"), True):
        if exc is not None or tau is None:
            raise SystemExit(f"{f.name}: {exc or 'no per-point times'}")
        # writable copies (a file's arrays are read-only, and KISS-ICP's binding refuses those)
        frames.append((float(f.time_s), np.array(pts, dtype=np.float64), np.array(tau, dtype=np.float64)))
    return frames, read_trajectory(stream / "groundtruth.txt")


class _Clocks:
    """Wall, process CPU and thread CPU stamps (s)."""

    def __init__(self):
        self.rows = []

    def stamp(self, *_):
        self.rows.append((time.perf_counter(), time.process_time(), time.thread_time()))

    def per_frame_ms(self) -> np.ndarray:
        return 1e3 * np.diff(np.asarray(self.rows), axis=0)


def run_minegeo(frames, frame_target: str = "submap"):
    """``(per-frame ms (n-1, 3): wall, process CPU, thread CPU of frames 1..n-1 (row 0 holds frames 0+1),
    OdometryResult)``; ``frame_target`` as ``minegeo slam --odometry`` (``submap``: what it runs on a 10 Hz
    stream)."""
    from minegeo.slam.odometry import OdometryParams, run_odometry

    clk = _Clocks()
    clk.stamp()
    odo = run_odometry(frames, OdometryParams(frame_target=frame_target), progress=clk.stamp)
    return clk.per_frame_ms(), odo


def kiss_config(threads: int):
    """KISS-ICP configuration, every field set here; its own deskewing on."""
    from kiss_icp.config import KISSConfig

    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = 100.0, 0.5, True
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0  # its default rule
    cfg.mapping.max_points_per_voxel = 20
    cfg.registration.max_num_iterations, cfg.registration.convergence_criterion = 500, 1e-4
    cfg.registration.max_num_threads = int(threads)
    cfg.adaptive_threshold.fixed_threshold = None
    cfg.adaptive_threshold.initial_threshold, cfg.adaptive_threshold.min_motion_th = 2.0, 0.1
    return cfg


def run_kiss(frames, threads: int, voxel_m: float | None = None):
    """``(per-frame ms (n, 3), poses (n, 4, 4))`` of KISS-ICP (deskewed to the end of each sweep);
    ``voxel_m``: its map voxel size (m), None for its default rule (``max_range / 100``)."""
    from kiss_icp.kiss_icp import KissICP

    cfg = kiss_config(threads)
    if voxel_m is not None:
        cfg.mapping.voxel_size = float(voxel_m)
    icp = KissICP(cfg)
    ms, poses = np.zeros((len(frames), 3)), np.zeros((len(frames), 4, 4))
    for k, (_, pts, tau) in enumerate(frames):
        a = (time.perf_counter(), time.process_time(), time.thread_time())
        icp.register_frame(pts, tau)
        b = (time.perf_counter(), time.process_time(), time.thread_time())
        ms[k] = 1e3 * (np.asarray(b) - np.asarray(a))
        poses[k] = icp.last_pose
    return ms, poses


def _ate(times, poses, truth) -> dict:
    """ATE RMSE (m, % of path) unaligned (both in their first pose's frame) and SE(3)-aligned, of
    ``poses`` at ``times`` against the truth interpolated there."""
    from minegeo.io.types import Trajectory
    from minegeo.slam.control import interpolate_poses
    from minegeo.slam.evaluate import evaluate_trajectory

    G = interpolate_poses(truth.times_s, truth.poses, times)
    G = np.einsum("ij,njk->nik", np.linalg.inv(G[0]), G)
    E = np.einsum("ij,njk->nik", np.linalg.inv(poses[0]), poses)
    path = float(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).sum())
    e = np.linalg.norm(E[:, :3, 3] - G[:, :3, 3], axis=1)
    ali = evaluate_trajectory(Trajectory(np.asarray(times), E), Trajectory(np.asarray(times), G), match="index")
    return {"path_m": path, "ate_unaligned_m": float(np.sqrt(np.mean(e ** 2))), "ate_max_m": float(e.max()),
            "ate_aligned_m": float(ali.ate.rmse), "ate_unaligned_pct": 100 * float(np.sqrt(np.mean(e ** 2))) / path,
            "ate_aligned_pct": 100 * float(ali.ate.rmse) / path}


def _stats(ms: np.ndarray) -> dict:
    return {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)), "max_ms": float(ms.max()),
            "mean_ms": float(ms.mean())}


def bench_stream(stream: Path, a) -> dict:
    from minegeo.slam.odometry import OdometryParams, run_odometry
    from minegeo.slam.pipeline import SlamParams, run_backend

    frames, truth = load_frames(stream)
    n = len(frames)
    _log(f"{stream.name}: {n} frames, {np.mean([f[1].shape[0] for f in frames]):.0f} points each; warm-up")
    run_odometry(frames[:3], OdometryParams(frame_target=a.odometry))  # untimed: Numba's cache loaded, every kernel of the path dispatched once
    run_kiss(frames[:3], a.threads)
    mg_runs, ks_runs, run_medians = [], [], []
    odo = k_poses = None
    for r in range(a.repeats):
        for lib in (("minegeo", "kiss") if r % 2 == 0 else ("kiss", "minegeo")):
            if lib == "minegeo":
                ms, odo = run_minegeo(frames, a.odometry)
                mg_runs.append(ms)
            else:
                ms, k_poses = run_kiss(frames, a.threads)
                ks_runs.append(ms)
        run_medians.append({"minegeo_wall_ms": float(np.median(mg_runs[-1][1:, 0])),
                            "kiss_wall_ms": float(np.median(ks_runs[-1][2:, 0])), "uptime": _uptime()})
        _log(f"{stream.name}: repeat {r + 1}/{a.repeats}: {run_medians[-1]}")
    mg, ks = np.min(np.stack(mg_runs), axis=0), np.min(np.stack(ks_runs), axis=0)
    t0 = time.perf_counter()
    slam = run_backend(odo, SlamParams(odometry=OdometryParams(frame_target=a.odometry)), odometry_s=0.0)
    backend_s = time.perf_counter() - t0
    n_kf = int(odo.keyframes.size)
    times = np.asarray([f[0] for f in frames])
    end = np.asarray([float(f[2].max()) for f in frames])
    keep = times + end <= truth.times_s[-1]  # KISS-ICP's pose time (the sweep's end) inside the truth
    bt = slam.timings_s
    return {
        "stream": stream.name, "frames": n, "points_per_frame": float(np.mean([f[1].shape[0] for f in frames])),
        "keyframes": n_kf, "frames_held_by_prior": int((~odo.frame_ok).sum()),
        "minegeo": {k: _stats(mg[1:, i]) for i, k in enumerate(("wall", "process_cpu", "thread_cpu"))}
        | {"first_two_frames_ms": mg[0].tolist(),
           "odometry_stage_totals_s_last_run": dict(odo.timings_s)},
        "kiss_icp": {k: _stats(ks[2:, i]) for i, k in enumerate(("wall", "process_cpu", "thread_cpu"))}
        | {"first_two_frames_ms": (ks[0] + ks[1]).tolist()},
        "backend": {"total_s": backend_s, "per_keyframe_ms": 1e3 * backend_s / max(n_kf, 1),
                    "stages_s": {k: float(bt[k]) for k in ("floor_planes", "loop_closure", "pose_graph", "map_noise",
                                                           "map")},
                    "loops_accepted": sum(bool(c.accepted) for c in slam.loops)},
        "ate": {"minegeo_front_end": _ate(times, odo.poses, truth), "minegeo_slam": _ate(times, slam.poses, truth),
                "kiss_icp": _ate((times + end)[keep], k_poses[keep], truth)},
        "run_medians": run_medians,
    }


def markdown(out: dict) -> str:
    m = out["meta"]
    L = [f"*{m['date']}, commit {m['commit']}, {m['duration_s']:g} s streams at 10 Hz (seed {m['seed']}), "
         f"threads: minegeo Numba {m['numba_threads']} ({m['numba_threading_layer']} layer, OMP_WAIT_POLICY "
         f"{m.get('omp_wait_policy', '?')}), KISS-ICP max_num_threads {m['kiss_threads']}; "
         f"minegeo odometry: each frame to the {'local map' if m.get('odometry', 'frame') == 'submap' else 'previous frame'}; "
         f"{m['repeats']} alternating runs, per frame the minimum over the runs; {m['cpus']} cores shared with "
         f"other jobs: uptime before `{m['uptime_before']}`, after `{m['uptime_after']}`.*", "",
         "| stream | per frame (ms) | minegeo wall: median / p95 / max | minegeo CPU (process) median / p95 "
         "| KISS-ICP wall: median / p95 / max | KISS-ICP CPU (process) median / p95 | ATE unaligned: minegeo "
         "front end / SLAM / KISS-ICP |", "|---|---|---|---|---|---|---|"]
    for s in out["streams"]:
        g, k, a = s["minegeo"], s["kiss_icp"], s["ate"]
        L.append(f"| {s['stream']} ({a['minegeo_slam']['path_m']:.1f} m, {s['frames']} sweeps, {s['keyframes']} "
                 f"keyframes) | {s['points_per_frame']:.0f} points "
                 f"| {g['wall']['median_ms']:.1f} / {g['wall']['p95_ms']:.1f} / {g['wall']['max_ms']:.1f} "
                 f"| {g['process_cpu']['median_ms']:.1f} / {g['process_cpu']['p95_ms']:.1f} "
                 f"| {k['wall']['median_ms']:.1f} / {k['wall']['p95_ms']:.1f} / {k['wall']['max_ms']:.1f} "
                 f"| {k['process_cpu']['median_ms']:.1f} / {k['process_cpu']['p95_ms']:.1f} "
                 f"| {a['minegeo_front_end']['ate_unaligned_pct']:.3f} % / {a['minegeo_slam']['ate_unaligned_pct']:.3f} "
                 f"% / {a['kiss_icp']['ate_unaligned_pct']:.3f} % |")
    L += ["", "| stream | minegeo back end total | per keyframe | loops accepted | frames held by the prior |",
          "|---|---|---|---|---|"]
    for s in out["streams"]:
        b = s["backend"]
        L.append(f"| {s['stream']} | {b['total_s']:.2f} s | {b['per_keyframe_ms']:.0f} ms | {b['loops_accepted']} "
                 f"| {s['frames_held_by_prior']} |")
    ok = all(s["minegeo"]["wall"]["median_ms"] < TARGET_MEDIAN_MS and s["minegeo"]["wall"]["p95_ms"] < TARGET_P95_MS
             for s in out["streams"])
    L += ["", f"Target (median < {TARGET_MEDIAN_MS:g} ms and p95 < {TARGET_P95_MS:g} ms per frame, wall, minegeo): "
          f"{'met' if ok else 'NOT met'} on every stream in this run.", "",
          "KISS-ICP configuration: `" + m["kiss_config"] + "`", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--presets", nargs="+", default=["vehicle", "handheld", "drone"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--odometry", choices=("submap", "frame"), default="submap",
                    help="what each frame registers to (minegeo slam --odometry; a 10 Hz stream: submap)")
    ap.add_argument("--work", type=Path, default=Path.home() / ".cache" / "minegeo_bench" / "realtime")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    a = ap.parse_args(argv)
    if int(os.environ.get("NUMBA_NUM_THREADS", "0") or 0) < a.threads:
        raise SystemExit(f"start with NUMBA_NUM_THREADS={a.threads} (or more) to measure {a.threads} thread(s)")
    import numba

    import minegeo._jit  # noqa: F401  (before set_num_threads loads libgomp: its OMP_WAIT_POLICY default)

    numba.set_num_threads(a.threads)
    _log(f"threads: minegeo numba.get_num_threads() = {numba.get_num_threads()}, KISS-ICP max_num_threads = "
         f"{kiss_config(a.threads).registration.max_num_threads}")
    a.work.mkdir(parents=True, exist_ok=True)
    streams = [make_stream(a.work, p, a.duration_s, a.seed) for p in a.presets]
    up0 = _uptime()
    res = [bench_stream(s, a) for s in streams]
    from importlib.metadata import version

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=REPO).stdout.strip()
    if subprocess.run(["git", "status", "--porcelain", "--", "minegeo/slam", "minegeo/registration"],
                      capture_output=True, text=True, cwd=REPO).stdout.strip():
        commit += "+dirty"
    meta = {"date": dt.date.today().isoformat(), "commit": commit, "duration_s": a.duration_s, "seed": a.seed,
            "repeats": a.repeats, "numba_threads": numba.get_num_threads(), "numba_threading_layer":
            numba.threading_layer(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "libgomp default (spin)"),
            "kiss_threads": a.threads, "odometry": a.odometry,
            "threads": f"{numba.get_num_threads()} for minegeo (Numba), {a.threads} for KISS-ICP",
            "kiss_config": repr(kiss_config(a.threads)),
            "kiss_icp_version": version("kiss-icp"), "cpus": os.cpu_count(), "uptime_before": up0,
            "uptime_after": _uptime(), "target_ms": {"median": TARGET_MEDIAN_MS, "p95": TARGET_P95_MS},
            "command": "python benchmarks/bench_realtime.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    out = {"meta": meta, "streams": res}
    md = markdown(out)
    print(md)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    if a.md:
        a.md.write_text(md + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
