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

One seed is one draw of the world's rock relief, the carrier's sway and the range noise. With
``--demo-seeds`` instead of ``--frames``/``--truth`` the demo's own sequence (``minegeo demo``'s step
2: :func:`minegeo.synth.world.build_world` ``("small", seed)``, the loop ``DEMO_LOOP``, VLP-16 frames
at the demo's rate and azimuth step, simulated in memory by the same calls) is drawn for each seed
given and every value run on each; the summary gives, per value, the median and the spread of the
SLAM ATE over the seeds, and for each value against the first one the paired difference (mean and
its standard error over the seeds) and on how many seeds it is lower::

    NUMBA_NUM_THREADS=2 python benchmarks/bench_covariance_frames.py --demo-seeds $(seq 1 30) \
        --odometry frame --values 9 1 \
        --json benchmarks/results/covariance_frames_<date>_demo_seeds.json \
        --md benchmarks/results/covariance_frames_<date>_demo_seeds.md
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


def _demo_sequence(seed: int):
    """The frames and true poses of ``minegeo demo --seed SEED``'s step 2, in memory (its calls)."""
    from minegeo.cli.demo import AZIMUTH_STEP_DEG, FRAME_RATE_HZ
    from minegeo.synth.sensors import Velodyne16
    from minegeo.synth.sequence import DEMO_LOOP, route_path, simulate_sequence
    from minegeo.synth.world import build_world

    world = build_world("small", seed)
    path = route_path(world, DEMO_LOOP["drifts"], DEMO_LOOP["start_m"], DEMO_LOOP["end_m"])
    truth, frames = simulate_sequence(world, path, rate_hz=FRAME_RATE_HZ,
                                      sensor=Velodyne16(azimuth_step_deg=AZIMUTH_STEP_DEG), seed=seed)
    return [(float(t), P) for t, P in zip(truth.times_s, frames, strict=True)], truth


def _score(frames, gt, v: int, frame_target: str) -> dict:
    """The SLAM chain and its odometry with ``covariance_frames = v`` on ``frames``, scored against ``gt``."""
    from minegeo.io.types import Trajectory
    from minegeo.slam.evaluate import evaluate_trajectory
    from minegeo.slam.odometry import run_odometry
    from minegeo.slam.pipeline import SlamParams, run_backend

    base = SlamParams()
    p = replace(base, odometry=replace(base.odometry, covariance_frames=v, frame_target=frame_target))
    t0 = time.perf_counter()
    o = run_odometry(frames, p.odometry)  # the front end, scored alone, then the back end on it (run_slam's two steps)
    r = run_backend(o, p, odometry_s=time.perf_counter() - t0)
    wall = time.perf_counter() - t0
    est, od = Trajectory(r.times_s, r.poses), Trajectory(o.times_s, o.poses)
    ev, ev_a = evaluate_trajectory(est, gt, align=False), evaluate_trajectory(est, gt, align=True)
    eo, eo_a = evaluate_trajectory(od, gt, align=False), evaluate_trajectory(od, gt, align=True)
    return {"covariance_frames": v, "default": v == base.odometry.covariance_frames,
            "ate_rmse_m": float(ev.ate.rmse), "ate_max_m": float(ev.ate.max), "ate_aligned_m": float(ev_a.ate.rmse),
            "odometry_ate_m": float(eo.ate.rmse), "odometry_ate_aligned_m": float(eo_a.ate.rmse),
            "odometry_end_error_m": float(np.linalg.norm(o.poses[-1][:3, 3] - gt.poses[-1][:3, 3])),
            "keyframes": int(len(r.keyframes)), **_edge_errors(o, gt),
            "plane_nodes": None if r.planes is None else int(r.planes.n_planes), "wall_s": wall}


def _edge_errors(o, gt) -> dict:
    """RMS over the odometry's keyframe edges of the error of the later keyframe placed from the true
    earlier one by the edge, against its true pose, in the world frame: along the true horizontal step,
    across it (to its left) and vertical (m), and its rotation about the vertical (yaw, deg)."""
    kf, out = o.keyframes, []
    for i in range(len(kf) - 1):
        A, B = gt.poses[kf[i]], gt.poses[kf[i + 1]]
        T_est = A @ o.keyframe_edges[i]  # the later keyframe placed from the true earlier one by the edge
        e = T_est[:3, 3] - B[:3, 3]  # world frame
        step = B[:2, 3] - A[:2, 3]
        u = step / max(np.linalg.norm(step), 1e-9)
        R = T_est[:3, :3] @ B[:3, :3].T  # the rotation error in the world frame
        yaw = np.degrees(np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))
        out.append((e[:2] @ u, e[0] * -u[1] + e[1] * u[0], e[2], yaw))
    E = np.asarray(out).reshape(-1, 4)
    rms = np.sqrt(np.mean(E ** 2, axis=0)) if len(E) else np.full(4, np.nan)
    return {"edge_along_rms_m": float(rms[0]), "edge_across_rms_m": float(rms[1]), "edge_vertical_rms_m": float(rms[2]),
            "edge_yaw_rms_deg": float(rms[3])}


def _relative_to_first(truth):
    from minegeo.io.types import Trajectory

    return Trajectory(truth.times_s, np.einsum("ij,njk->nik", np.linalg.inv(truth.poses[0]), truth.poses))


def paired_stats(x, ref) -> dict:
    """Of a measure ``x`` over seeds and the same seeds' ``ref`` (paired by position): its median, min,
    max and RMS, and ``x − ref``'s mean, that mean's standard error and the seeds where ``x < ref``."""
    x, d = np.asarray(x, dtype=np.float64), np.asarray(x, dtype=np.float64) - np.asarray(ref, dtype=np.float64)
    return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max()),
            "rms": float(np.sqrt(np.mean(x ** 2))), "paired_difference_mean": float(d.mean()),
            "paired_difference_se": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan"),
            "seeds_lower_than_first": int(np.sum(d < 0))}


def _summary(rows: list[dict], values: list[int]) -> list[dict]:
    """Per value over the seeds, of each measure, :func:`paired_stats` against the first value."""
    first = {r["seed"]: r for r in rows if r["covariance_frames"] == values[0]}
    out = []
    for v in values:
        mine = {r["seed"]: r for r in rows if r["covariance_frames"] == v}
        seeds = sorted(mine)
        row = {"covariance_frames": v, "seeds": len(seeds)}
        for key in ("ate_rmse_m", "ate_aligned_m", "odometry_ate_m", "odometry_end_error_m", "edge_along_rms_m",
                    "edge_across_rms_m", "edge_vertical_rms_m", "edge_yaw_rms_deg", "plane_nodes"):
            row[key] = paired_stats([np.nan if mine[s][key] is None else mine[s][key] for s in seeds],
                                    [np.nan if first[s][key] is None else first[s][key] for s in seeds])
        out.append(row)
    return out


def main(argv=None) -> int:
    from minegeo.io import read_trajectory
    from minegeo.io.frames import iter_frames, list_frames

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", type=Path)
    src.add_argument("--demo-seeds", type=int, nargs="+", help="draw the demo's sequence with each of these seeds")
    ap.add_argument("--truth", type=Path, help="with --frames: TUM file of the true sensor poses at the frame times")
    ap.add_argument("--odometry", choices=("frame", "submap"), required=True)
    ap.add_argument("--values", type=int, nargs="+", default=[9, 1])
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.frames is not None and a.truth is None:
        ap.error("--frames needs --truth")

    up0, rows = _uptime(), []
    if a.frames is not None:
        gt = _relative_to_first(read_trajectory(a.truth))
        frames = [(float(f[0].time_s), f[1]) for f in iter_frames(list_frames(a.frames))]
        for v in a.values:
            rows.append(_score(frames, gt, v, a.odometry))
            print(rows[-1], flush=True)
        n_frames = len(frames)
    else:
        n_frames = {}
        for seed in a.demo_seeds:
            frames, truth = _demo_sequence(seed)
            n_frames[seed] = len(frames)
            for v in a.values:
                rows.append({"seed": seed, **_score(frames, _relative_to_first(truth), v, a.odometry)})
                print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    source = str(a.frames) if a.frames is not None else f"the demo's sequence, seeds {a.demo_seeds}"
    meta = {"date": dt.date.today().isoformat(), "commit": commit, "frames": source, "n_frames": n_frames,
            "truth": str(a.truth) if a.truth else "the simulator's poses", "frame_target": a.odometry,
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "unset"),
            "uptime_before": up0, "uptime_after": _uptime(),
            "command": "python benchmarks/bench_covariance_frames.py " + " ".join(argv or sys.argv[1:])}
    out = {"meta": meta, "rows": rows}
    if a.demo_seeds is not None:
        out["summary"] = _summary(rows, a.values)
    a.json.write_text(json.dumps(out, indent=2) + "\n")
    a.md.write_text("\n".join(_markdown(meta, rows, out.get("summary"), a.values)) + "\n")
    return 0


def _markdown(meta: dict, rows: list[dict], summary, values) -> list[str]:
    n = meta["n_frames"]
    what = f"{n} frames of `{meta['frames']}`" if isinstance(n, int) else f"{meta['frames']}"
    lines = [f"*{meta['date']}, commit {meta['commit']}, {what}, odometry '{meta['frame_target']}', "
             f"Numba threads {meta['numba_threads']}; load: `{meta['uptime_before']}` → `{meta['uptime_after']}`.*", ""]
    if summary is not None:
        lines += [f"Over {summary[0]['seeds']} seeds (estimate and truth in their first pose's frame, without alignment "
                  f"or SE(3)-aligned; the paired difference is against covariance_frames = {values[0]}, mean ± its "
                  "standard error):", "",
                  "| covariance_frames | measure | median (min-max) | RMS over seeds | paired difference | seeds lower |",
                  "|---|---|---|---|---|---|"]
        measures = (("ate_rmse_m", "SLAM ATE, no alignment"), ("ate_aligned_m", "SLAM ATE, aligned"),
                    ("odometry_ate_m", "odometry ATE, no alignment"),
                    ("odometry_end_error_m", "odometry error at the last frame"))
        for s in summary:
            for key, label in measures:
                a = s[key]
                lines.append(f"| {s['covariance_frames']} | {label} | {a['median']:.3f} m ({a['min']:.3f}-{a['max']:.3f}) "
                             f"| {a['rms']:.3f} m | {a['paired_difference_mean'] * 1e3:+.1f} ± "
                             f"{a['paired_difference_se'] * 1e3:.1f} mm | {a['seeds_lower_than_first']} of {s['seeds']} |")
        lines += ["", "The odometry's keyframe edges against the truth (RMS over a run's edges, median over the seeds; "
                  "along / across the true step and vertical, and yaw; in brackets the seeds on which it is lower "
                  f"than with covariance_frames = {values[0]}), and the floor plane nodes of the SLAM:", "",
                  "| covariance_frames | edge error along | across | vertical | yaw | plane nodes |",
                  "|---|---|---|---|---|---|"]
        for s in summary:
            cells = [f"{s[k]['median'] * 1e3:.1f} mm ({s[k]['seeds_lower_than_first']} lower)"
                     for k in ("edge_along_rms_m", "edge_across_rms_m", "edge_vertical_rms_m")]
            lines.append(f"| {s['covariance_frames']} | " + " | ".join(cells) + f" | {s['edge_yaw_rms_deg']['median']:.3f}° "
                         f"({s['edge_yaw_rms_deg']['seeds_lower_than_first']} lower) | {s['plane_nodes']['median']:g} "
                         f"({s['plane_nodes']['min']:g}-{s['plane_nodes']['max']:g}) |")
        lines += ["", "Per seed:", ""]
    seed_col = summary is not None
    lines += [("| seed " if seed_col else "") + "| covariance_frames | SLAM ATE RMSE, no alignment / max | SLAM ATE "
              "aligned | odometry ATE, no alignment / aligned | odometry error at the last frame | keyframes | "
              "keyframe edge error along / across / vertical | edge yaw | plane nodes | SLAM wall s |",
              "|---" * (11 if seed_col else 10) + "|"]
    for r in rows:
        lines.append((f"| {r['seed']} " if seed_col else "") +
                     f"| {r['covariance_frames']}{' (default)' if r['default'] else ''} | {r['ate_rmse_m']:.3f} / "
                     f"{r['ate_max_m']:.3f} m | {r['ate_aligned_m']:.3f} m | {r['odometry_ate_m']:.3f} / "
                     f"{r['odometry_ate_aligned_m']:.3f} m | {r['odometry_end_error_m']:.3f} m | {r['keyframes']} | "
                     f"{r['edge_along_rms_m'] * 1e3:.1f} / {r['edge_across_rms_m'] * 1e3:.1f} / "
                     f"{r['edge_vertical_rms_m'] * 1e3:.1f} mm | {r['edge_yaw_rms_deg']:.3f}° | {r['plane_nodes']} | "
                     f"{r['wall_s']:.1f} |")
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
