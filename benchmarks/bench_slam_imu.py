"""LiDAR-inertial SLAM (``minegeo slam --imu``) on simulated sensor streams: ATE with and without the IMU.

For each stream preset (vehicle, handheld, drone; ``minegeo synth OUT --stream P --duration-s D --seed S``,
written once into the work folder and reused) ``minegeo slam`` runs three times on the same frames:

* ``raw``: ``--no-deskew`` (the sweeps as recorded, smeared by the motion; no IMU);
* ``deskew, no IMU``: the default (constant-velocity deskewing, 2 passes);
* ``gyro front end only``: through the Python API, ``run_odometry(..., imu=GyroAid(imu))`` (gyro rotation
  guesses and gyro deskewing) then ``run_backend`` without the IMU (the LiDAR keyframe graph as without
  an IMU): what the odometry's use of the gyro does alone;
* ``deskew + IMU``: ``--imu imu.csv`` (the above, then IMU preintegration factors in the keyframe graph).

ATE RMSE against the stream's ``groundtruth.txt``: after SE(3) Umeyama alignment
(:func:`minegeo.slam.evaluate.evaluate_trajectory`, evo's definition) and without alignment (the truth
moved into the first sensor frame, the SLAM map frame), in m and % of the true path; the frames held
by the motion prior; with the IMU the largest error of the estimated gyro bias at the keyframes
against the simulator's record (``imu_truth.csv``); the wall time of each run.

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_slam_imu.py --duration-s 20 --presets vehicle handheld \\
        --work ~/.cache/minegeo_bench/slam_imu \\
        --json benchmarks/results/slam_imu_<date>.json --md benchmarks/results/slam_imu_<date>.md
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_deskew import run_cli, run_meta, stream_ate, synth_stream  # noqa: E402

MODES = {"raw": ["--no-deskew"], "deskew, no IMU": [], "gyro front end only": None, "deskew + IMU": ["--imu", "IMU"]}


def _front_end_only(stream: Path, run: Path, frame_target: str = "submap") -> float:
    """The gyro in the odometry only (Python API); writes ``trajectory.tum`` and the ``result.json`` fields
    :func:`_ate` reads. Returns the wall time (s)."""
    from minegeo.io import write_trajectory
    from minegeo.io.frames import iter_frames, list_frames
    from minegeo.io.imu import read_imu_csv
    from minegeo.io.types import Trajectory
    from minegeo.slam.inertial import GyroAid
    from minegeo.slam.odometry import OdometryParams, run_odometry
    from minegeo.slam.pipeline import SlamParams, run_backend

    t0 = time.perf_counter()
    p = SlamParams(odometry=OdometryParams(frame_target=frame_target))
    files = list_frames(stream / "frames")
    odo = run_odometry((((f.time_s, pts, tau) for f, pts, tau, _exc in iter_frames(files, True))), p.odometry,
                       imu=GyroAid(read_imu_csv(stream / "imu.csv")))
    res = run_backend(odo, p)
    run.mkdir(parents=True, exist_ok=True)
    write_trajectory(run / "trajectory.tum", Trajectory(res.times_s, res.poses, frame="map", body="sensor"))
    (run / "result.json").write_text(json.dumps({"result": {"frames": int(res.times_s.size),
                                                            "keyframes": int(res.keyframes.size),
                                                            "motion_prior_stretches": odo.held_stretches()}}))
    return time.perf_counter() - t0


def _ate(run: Path, stream: Path) -> dict:
    base, res = stream_ate(run, stream)
    out = {**base, "keyframes": res["keyframes"],
           "frames_held_by_prior": int(sum(h["frames"] for h in res["motion_prior_stretches"]))}
    if "inertial" in res:
        ine = res["inertial"]
        truth = np.loadtxt(stream / "imu_truth.csv", delimiter=",", skiprows=1)
        kt = np.array([k["time_s"] for k in ine["keyframes"]])
        b_true = truth[np.searchsorted(truth[:, 0], kt), 7:10]
        b_est = np.array([k["bias_gyro_rad_s"] for k in ine["keyframes"]])
        out.update(inertial_status=ine["status"], gyro_bias_true_max_rad_s=float(np.abs(b_true).max()),
                   gyro_bias_error_max_rad_s=float(np.abs(b_est - b_true).max()))
    return out


def _table(meta: dict, rows: list[dict]) -> list[str]:
    lines = [f"*Results file `benchmarks/results/slam_imu_{meta['date']}.json`; measured {meta['date']}, commit "
             f"{meta['commit']}, {meta['duration_s']:g} s streams at 10 Hz (seed {meta['seed']}), IMU 200 Hz "
             f"(ADIS16448 noise), Numba threads {meta['numba_threads']}, 1-minute load {meta['load_1min_start']:.1f} → "
             f"{meta['load_1min_end']:.1f} on {meta['cpus']} cores.*", "",
             "| stream | mode | ATE RMSE, aligned | ATE RMSE, unaligned | max error | frames held by the prior "
             "| gyro bias error (of) | wall |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["path_m"]
        bias = (f"{1e3 * r['gyro_bias_error_max_rad_s']:.2f} mrad/s ({1e3 * r['gyro_bias_true_max_rad_s']:.1f})"
                if "gyro_bias_error_max_rad_s" in r else "")
        lines.append(f"| {r['preset']} {p:.1f} m | {r['mode']} | {r['ate_aligned_m']:.3f} m "
                     f"({100 * r['ate_aligned_m'] / p:.3f} %) | {r['ate_unaligned_m']:.3f} m "
                     f"({100 * r['ate_unaligned_m'] / p:.3f} %) | {r['max_error_unaligned_m']:.3f} m | "
                     f"{r['frames_held_by_prior']} of {r['frames']} | {bias} | {r['wall_s']:.0f} s |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--presets", nargs="+", default=["vehicle", "handheld", "drone"])
    ap.add_argument("--work", type=Path, default=Path.home() / ".cache" / "minegeo_bench" / "slam_imu")
    ap.add_argument("--odometry", choices=("submap", "frame"), default="submap",
                    help="minegeo slam --odometry, and the front-end-only run's frame_target (a 10 Hz stream: submap)")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    rows = []
    for preset in a.presets:
        stream = synth_stream(a.work, preset, a.duration_s, a.seed)
        for mode, opts in MODES.items():
            run = a.work / f"{stream.name}_{mode.replace(',', '').replace('+', '').replace(' ', '_')}"
            if opts is None:
                wall, opts = _front_end_only(stream, run, a.odometry), ["(Python API)"]
            else:
                opts = [str(stream / "imu.csv") if o == "IMU" else o for o in opts]
                opts = [*opts, "--odometry", a.odometry]
                wall = run_cli(["slam", "--frames", str(stream / "frames"), "--out", str(run), *opts])
            rows.append({"preset": preset, "mode": mode, "options": opts, "wall_s": wall, **_ate(run, stream)})
            print(rows[-1], flush=True)
    meta = run_meta("bench_slam_imu.py", argv, load0, a.duration_s, a.seed)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    a.md.write_text("\n".join(_table(meta, rows)) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
