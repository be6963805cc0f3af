"""SLAM back end: loops judged at poses re-optimised after every accepted loop, or only after a large correction.

Runs the SLAM front end once on a sensor stream as ``minegeo slam --control`` runs it (pickled in
``--cache``, reused when present), then :func:`minegeo.slam.pipeline.run_backend` on that same
odometry with ``LoopParams(reoptimise_m, reoptimise_deg)`` = the default (0.1 m, 2°) and (0, 0)
(after every accepted loop); counts the keyframe-graph optimisations, the loops accepted, the
timings, and the aligned ATE (rigid Umeyama, every frame) against the stream's ``groundtruth.txt``.

Run (the stream of ``bench_control_stream.py``; about 10 min of front end, then 5-30 min per back end)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_backend_reoptimise.py --stream WORK/stream \\
        --cache /tmp/odo.pkl --out benchmarks/results/backend_reoptimise_<date>.json
"""

from __future__ import annotations

import argparse
import json
import logging
import pickle
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def front_end(stream: Path, cache: Path):
    """The odometry of ``minegeo slam --frames stream/frames --control stream/stations.csv`` (pickled)."""
    if cache.is_file():
        with open(cache, "rb") as f:
            d = pickle.load(f)
        return d["odo"], d["params"]
    from minegeo.cli import build_parser
    from minegeo.cli import slam as cs
    from minegeo.io.frames import list_frames
    from minegeo.slam.odometry import run_odometry

    args = build_parser().parse_args(["slam", "--frames", str(stream / "frames"), "--control",
                                      str(stream / "stations.csv"), "--out", "/nonexistent"])
    params = cs._params(args)
    files = list_frames(args.frames, args.times, args.pattern, args.lidar_topic)
    target, _ = cs.odometry_target(args.odometry, [f.time_s for f in files])
    params = replace(params, odometry=replace(params.odometry, frame_target=target))

    class _Bar:
        def update(self, k):
            pass

    odo = run_odometry(cs._frames(files, [], _Bar(), params.odometry.min_points, params.odometry.deskew),
                       params.odometry)
    with open(cache, "wb") as f:
        pickle.dump({"odo": odo, "params": params}, f, protocol=5)
    return odo, params


def back_end(odo, params, m, deg, gt) -> dict:
    from minegeo.slam import pipeline as pl

    if m is not None:
        params = replace(params, loops=replace(params.loops, reoptimise_m=m, reoptimise_deg=deg))
    calls, orig = [0], pl._optimise

    def counted(*a, **k):
        calls[0] += 1
        return orig(*a, **k)

    pl._optimise = counted
    try:
        t = time.perf_counter()
        res = pl.run_backend(odo, params)
        wall = time.perf_counter() - t
    finally:
        pl._optimise = orig
    idx = np.searchsorted(gt[:, 0], res.times_s - 1e-6)
    P, Q = res.poses[:, :3, 3], gt[idx, 1:4]
    mp, mq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    e = np.linalg.norm((P - mp) @ R.T + mq - Q, axis=1)
    return {"reoptimise_m": params.loops.reoptimise_m, "reoptimise_deg": params.loops.reoptimise_deg, "wall_s": wall,
            "optimisations": calls[0], "loops_accepted": int(sum(c.accepted for c in res.loops)),
            "loops_tried": len(res.loops), "ate_aligned_rmse_m": float(np.sqrt(np.mean(e ** 2))),
            "ate_max_m": float(e.max()), "path_m": float(np.linalg.norm(np.diff(Q, axis=0), axis=1).sum()),
            "status": str(res.optimisation.status) if res.optimisation else None,
            "timings": {k: round(v, 1) for k, v in res.timings_s.items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stream", required=True, type=Path)
    ap.add_argument("--cache", required=True, type=Path)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    logging.getLogger("minegeo.registration").setLevel(logging.ERROR)
    up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    odo, params = front_end(a.stream, a.cache)
    gt = np.loadtxt(a.stream / "groundtruth.txt")
    runs = [back_end(odo, params, None, None, gt), back_end(odo, params, 0.0, 0.0, gt)]
    d = {"date": time.strftime("%Y-%m-%d"), "threads": 1, "uptime_before": up,
         "uptime_after": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
         "keyframes": int(odo.keyframes.size), "frames": int(odo.times_s.size), "runs": runs}
    Path(a.out).write_text(json.dumps(d, indent=1) + "\n")
    print(json.dumps(d, indent=1))


if __name__ == "__main__":
    main()
