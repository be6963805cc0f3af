"""SLAM trajectory error against the number of frames the GICP covariances are taken among.

``OdometryParams.covariance_frames`` (docs/slam.md, "Odometry and loop closure"): each frame's GICP
covariances come from its own points and those of the ``covariance_frames - 1`` registered frames
before it (9 by default, made for 10 Hz sensor streams). This script runs the SLAM chain
(:func:`minegeo.slam.pipeline.run_slam`'s two steps, default ``SlamParams`` otherwise) on one frames folder for
each value given and scores the frame trajectory against a truth TUM file without alignment (both in
their first pose's frame, as ``minegeo demo`` scores its SLAM step) and SE(3)-aligned, and the
odometry alone (:func:`minegeo.slam.odometry.run_odometry`, the same front end) the same way and by its
error at the last frame, so the default can be compared
with the one-frame covariances on inputs it was not made for (e.g. the demo's sparse 2 Hz frames).

Usage (the demo's frames: ``minegeo demo --out demo`` first)::

    NUMBA_NUM_THREADS=2 python benchmarks/bench_covariance_frames.py --frames demo/sequence/frames \\
        --truth demo/sequence/truth.tum --odometry frame --values 9 1 \\
        --json benchmarks/results/covariance_frames_<date>_demo.json --md benchmarks/results/covariance_frames_<date>_demo.md

``--odometry`` is the frame target ``minegeo slam --odometry auto`` picks for the folder (``frame``
for frames more than 0.25 s apart, ``submap`` otherwise; the ``result.json`` of a ``minegeo slam``
run on it records it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main(argv=None) -> int:
    from minegeo.io import read_trajectory
    from minegeo.io.frames import iter_frames, list_frames
    from minegeo.io.types import Trajectory
    from minegeo.slam.evaluate import evaluate_trajectory
    from minegeo.slam.odometry import run_odometry
    from minegeo.slam.pipeline import SlamParams, run_backend

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=Path, required=True)
    ap.add_argument("--truth", type=Path, required=True, help="TUM file of the true sensor poses at the frame times")
    ap.add_argument("--odometry", choices=("frame", "submap"), required=True)
    ap.add_argument("--values", type=int, nargs="+", default=[9, 1])
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)

    truth = read_trajectory(a.truth)
    gt = Trajectory(truth.times_s, np.einsum("ij,njk->nik", np.linalg.inv(truth.poses[0]), truth.poses))
    frames = [(float(f[0].time_s), f[1]) for f in iter_frames(list_frames(a.frames))]
    base = SlamParams()
    up0, rows = _uptime(), []
    for v in a.values:
        p = replace(base, odometry=replace(base.odometry, covariance_frames=v, frame_target=a.odometry))
        t0 = time.perf_counter()
        o = run_odometry(frames, p.odometry)  # the front end, scored alone, then the back end on it (run_slam's two steps)
        r = run_backend(o, p, odometry_s=time.perf_counter() - t0)
        wall = time.perf_counter() - t0
        est, od = Trajectory(r.times_s, r.poses), Trajectory(o.times_s, o.poses)
        ev, ev_a = evaluate_trajectory(est, gt, align=False), evaluate_trajectory(est, gt, align=True)
        eo, eo_a = evaluate_trajectory(od, gt, align=False), evaluate_trajectory(od, gt, align=True)
        rows.append({"covariance_frames": v, "default": v == base.odometry.covariance_frames,
                     "ate_rmse_m": float(ev.ate.rmse), "ate_max_m": float(ev.ate.max),
                     "ate_aligned_m": float(ev_a.ate.rmse),
                     "odometry_ate_m": float(eo.ate.rmse), "odometry_ate_aligned_m": float(eo_a.ate.rmse),
                     "odometry_end_error_m": float(np.linalg.norm(o.poses[-1][:3, 3] - gt.poses[-1][:3, 3])),
                     "keyframes": int(len(r.keyframes)), "wall_s": wall})
        print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    meta = {"date": dt.date.today().isoformat(), "commit": commit, "frames": str(a.frames), "n_frames": len(frames),
            "truth": str(a.truth), "frame_target": a.odometry, "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "unset"),
            "uptime_before": up0, "uptime_after": _uptime(),
            "command": "python benchmarks/bench_covariance_frames.py " + " ".join(argv or sys.argv[1:])}
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = [f"*{meta['date']}, commit {commit}, {len(frames)} frames of `{a.frames}`, odometry '{a.odometry}', "
             f"Numba threads {meta['numba_threads']}; load: `{up0}` → `{meta['uptime_after']}`.*", "",
             "| covariance_frames | SLAM ATE RMSE, no alignment / max | SLAM ATE aligned | odometry ATE, no alignment "
             "/ aligned | odometry error at the last frame | keyframes | SLAM wall s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['covariance_frames']}{' (default)' if r['default'] else ''} | {r['ate_rmse_m']:.3f} / "
                     f"{r['ate_max_m']:.3f} m | {r['ate_aligned_m']:.3f} m | {r['odometry_ate_m']:.3f} / "
                     f"{r['odometry_ate_aligned_m']:.3f} m | {r['odometry_end_error_m']:.3f} m | {r['keyframes']} | "
                     f"{r['wall_s']:.1f} |")
    a.md.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
