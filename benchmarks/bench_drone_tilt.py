"""Where the drone's tilt error comes from: the same sweeps deskewed four ways, LiDAR odometry only.

The 60 s drone flight of ``bench_stream_ate.py`` (``minegeo synth OUT --stream drone --stream-network
NIOSH --duration-s 60 --seed 1``: 2.9 m drifts, 10 Hz motion-distorted sweeps, each point's time
``τ ∈ [0, 0.1)`` s after its frame time) registered by :func:`minegeo.slam.odometry.run_odometry`
(each frame to the local map, ``frame_target="submap"``, as ``minegeo slam`` runs a 10 Hz stream;
no loops, no pose graph) after one of four treatments of the sweeps:

* ``estimated``: minegeo's own deskewing (the constant twist of the odometry, then of the frame's
  own registration), as ``minegeo slam`` does;
* ``truth``: every point moved by the *true* motion at its own time, ``q = T(t)⁻¹ T(t + τ) p``, with
  ``T(t + τ)`` integrated from the true body rate and world velocity of ``imu_truth.csv`` (200 Hz,
  interpolated linearly between samples), anchored at the frame's true pose: a perfect deskew;
* ``true constant twist``: the constant twist of the true motion from the previous frame time to this
  one (what a perfect odometry would hand to minegeo's deskewing);
* ``raw``: the sweeps as recorded, no deskewing.

Measured: unaligned ATE (first pose on the truth) as RMSE and % of the path, the worst error, and the
rotation error (rotation vector of ``R_trueᵀ R_est``, degrees) at 8, 15, 30 s and at the end.

Run: ``NUMBA_NUM_THREADS=1 python benchmarks/bench_drone_tilt.py --work DIR --out benchmarks/results/drone_tilt_<date>``
(the stream is simulated into ``DIR`` when it is not there).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_realtime import load_frames  # noqa: E402
from bench_stream_ate import _stream  # noqa: E402

from minegeo.slam.deskew import deskew_points, twist_from_motion  # noqa: E402
from minegeo.slam.odometry import OdometryParams, run_odometry  # noqa: E402

MODES = ("estimated", "truth", "true constant twist", "raw")


def _true_relative(t: float, pose_t: np.ndarray, imu: np.ndarray):
    """``(offsets (n,), rotation vectors (n, 3), positions (n, 3))`` of ``T(t)⁻¹ T(t + τ)`` at the truth
    IMU samples within 0.15 s of ``t`` (one of them at ``t``)."""
    m = (imu[:, 0] >= t - 0.15) & (imu[:, 0] <= t + 0.15)
    ts, w, v = imu[m, 0], imu[m, 1:4], imu[m, 13:16]
    i0 = int(np.argmin(np.abs(ts - t)))
    if abs(ts[i0] - t) > 1e-6:
        raise SystemExit(f"no truth IMU sample at the frame time {t}")
    n = ts.size
    R = np.empty((n, 3, 3))
    P = np.zeros((n, 3))
    R[i0] = np.eye(3)
    for i in range(i0 + 1, n):
        R[i] = R[i - 1] @ Rotation.from_rotvec(w[i - 1] * (ts[i] - ts[i - 1])).as_matrix()
        P[i] = P[i - 1] + v[i - 1] * (ts[i] - ts[i - 1])
    for i in range(i0 - 1, -1, -1):
        R[i] = R[i + 1] @ Rotation.from_rotvec(-w[i] * (ts[i + 1] - ts[i])).as_matrix()
        P[i] = P[i + 1] - v[i] * (ts[i + 1] - ts[i])
    return ts - t, Rotation.from_matrix(R).as_rotvec(), P @ pose_t[:3, :3]


def _frames(mode: str, frames, G: np.ndarray, gt_t: np.ndarray, imu: np.ndarray):
    out = []
    for k, (t, P, tau) in enumerate(frames):
        j = int(np.searchsorted(gt_t, t - 1e-9))
        if abs(gt_t[j] - t) > 1e-6:
            raise SystemExit(f"frame {k}: no truth pose at {t}")
        if mode == "estimated":
            out.append((t, P, tau))
        elif mode == "raw" or (mode == "true constant twist" and k == 0):
            out.append((t, P))
        elif mode == "true constant twist":
            out.append((t, deskew_points(P, tau, twist_from_motion(np.linalg.inv(G[j - 1]) @ G[j], gt_t[j] - gt_t[j - 1]))))
        else:
            off, rv, pos = _true_relative(t, G[j], imu)
            i = np.clip(np.searchsorted(off, tau) - 1, 0, off.size - 2)
            a = ((tau - off[i]) / (off[i + 1] - off[i]))[:, None]
            out.append((t, Rotation.from_rotvec(rv[i] * (1 - a) + rv[i + 1] * a).apply(P) + pos[i] * (1 - a) + pos[i + 1] * a))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder of the simulated stream (made when missing)")
    ap.add_argument("--out", type=Path, required=True, help="results path without extension (.json and .md written)")
    a = ap.parse_args()
    stream = _stream(a.work, "drone", "niosh", 60.0, 1)
    frames, truth = load_frames(stream)
    G, gt_t = np.asarray(truth.poses), np.asarray(truth.times_s)
    imu = np.loadtxt(stream / "imu_truth.csv", delimiter=",", skiprows=1)
    path = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    load0 = os.getloadavg()
    rows = {}
    for mode in MODES:
        t0 = time.perf_counter()
        odo = run_odometry(_frames(mode, frames, G, gt_t, imu), OdometryParams(frame_target="submap"))
        E = odo.poses
        G0 = np.linalg.inv(G[0]) @ G[: len(E)]
        err = np.linalg.norm(G0[:, :3, 3] - E[:, :3, 3], axis=1)
        rmse = float(np.sqrt(np.mean(err ** 2)))
        rot = {f"{gt_t[i] - gt_t[0]:.0f} s": np.degrees(Rotation.from_matrix(G0[i, :3, :3].T @ E[i, :3, :3]).as_rotvec()).round(3).tolist()
               for i in (80, 150, 300, len(E) - 1)}
        rows[mode] = {"rmse_m": rmse, "rmse_pct": 100 * rmse / path, "max_m": float(err.max()),
                      "frames_not_registered": int((~odo.frame_ok).sum()), "rotation_error_deg": rot,
                      "seconds": time.perf_counter() - t0}
        print(mode, json.dumps(rows[mode]), flush=True)
    commit = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    rec = {"date": datetime.date.today().isoformat(), "commit": commit, "python": platform.python_version(),
           "threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "load_start": load0, "load_end": os.getloadavg(),
           "stream": stream.name, "path_m": path, "frames": len(frames), "rows": rows}
    a.out.with_suffix(".json").write_text(json.dumps(rec, indent=1) + "\n")
    md = [f"# Drone tilt: the 60 s NIOSH flight's sweeps deskewed four ways, odometry only ({rec['date']})", "",
          f"{len(frames)} frames, {path:.1f} m of path; commit {commit}; NUMBA_NUM_THREADS={rec['threads']}; "
          f"load {load0[0]:.1f} at the start, {rec['load_end'][0]:.1f} at the end.", "",
          "| sweeps | unaligned RMSE (m) | % of path | max (m) | frames not registered | rotation error (deg) at 8 / 15 / 30 s / end |",
          "|---|---|---|---|---|---|"]
    for mode, r in rows.items():
        md.append(f"| {mode} | {r['rmse_m']:.3f} | {r['rmse_pct']:.3f} % | {r['max_m']:.2f} | {r['frames_not_registered']} | "
                  + " / ".join(str(v) for v in r["rotation_error_deg"].values()) + " |")
    a.out.with_suffix(".md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
