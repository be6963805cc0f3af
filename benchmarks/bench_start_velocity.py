"""How far off is the velocity the first sweep of a stream is deskewed by?

The first frame of a stream has no motion before it: ``run_odometry`` deskews it by the first registered
motion (frame 0 to frame 1), and it anchors the local map the frames of the next seconds register to.
With ``OdometryParams.start_deskew_window_s = 0.5`` (0, off, by default) it is deskewed again, once the frames of
that window are registered, by the velocity of the least-squares line through their positions
(``minegeo.slam.odometry.start_velocity``). This script measures both velocities against the
simulator's: for each stream (``minegeo synth OUT --stream P --stream-network N --seed K`` as
``bench_stream_ate.py`` names them, its first 11 sweeps cast by ``minegeo.synth.stream.iter_sweeps``),
``run_odometry`` (each frame to the local map, the CLI's target for streams) with the window 0 and with
the default, without and with the IMU (``GyroAid`` on the stream's noisy IMU). The error is the norm of
the deskew twist's velocity (``OdometryResult.deskew_twist[0][3:]``) less the body velocity of the
simulator's continuous curve over the sweep, ``Log(T(t_0)⁻¹ T(t_0 + 0.1 s)) / 0.1 s`` (m/s).

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_start_velocity.py --seeds 1-10 \\
        --json benchmarks/results/start_velocity_<date>.json --md benchmarks/results/start_velocity_<date>.md
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_inertial_edge_noise import _commit, commit_label  # noqa: E402
from bench_stream_ate import NIOSH  # noqa: E402

#: (label, preset, network) of the streams: the 20 s sequences of bench_imu_seeds
STREAMS = (("vehicle, loop 3.2 m", "vehicle", "loop"), ("handheld, loop 3.2 m", "handheld", "loop"),
           ("drone, NIOSH 2.9 m", "drone", "niosh"))


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(a)]


def measure(preset: str, network: str, seed: int) -> dict:
    """The first sweep's deskew velocity error (m/s), window 0 and default, without and with the IMU."""
    from minegeo.io.imu import ImuSamples
    from minegeo.slam.deskew import twist_from_motion
    from minegeo.slam.inertial import GyroAid
    from minegeo.slam.odometry import OdometryParams, run_odometry
    from minegeo.synth.flight import NetworkWorld
    from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

    st = simulate_stream(StreamParams(preset=preset, network=str(NIOSH) if network == "niosh" else network,
                                      duration_s=20.0, seed=seed))
    ft = st.frame_times[:11]
    sweeps = [(t, P, tau) for t, P, tau, _ring in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                               st.lidar_seed)]
    T0, T1 = st.curve.poses(np.array([ft[0], ft[0] + 0.1]))
    v_true = twist_from_motion(np.linalg.inv(T0) @ T1, 0.1)[3:]
    out = {"seed": seed, "true_speed_m_s": float(np.linalg.norm(v_true))}
    window = 0.5  # the window measured (OdometryParams.start_deskew_window_s is 0, off, by default)
    for imu in (False, True):
        for key, w in (("first_motion", 0.0), ("line", window)):
            aid = GyroAid(ImuSamples(st.imu.t, st.imu.gyro, st.imu.accel)) if imu else None
            r = run_odometry(iter(sweeps), OdometryParams(frame_target="submap", start_deskew_window_s=w), imu=aid)
            out[f"{'imu' if imu else 'lidar'}_{key}_m_s"] = float(np.linalg.norm(r.deskew_twist[0][3:] - v_true))
    return out


def _stats(x) -> dict:
    x = np.asarray(x, dtype=np.float64)
    return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=_seeds, default=_seeds("1-10"), help="first-last, e.g. 1-10")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)

    load0, commit0 = os.getloadavg(), _commit()
    rows = []
    for label, preset, network in STREAMS:
        for seed in a.seeds:
            r = {"sequence": label, **measure(preset, network, seed)}
            print(f"[{time.strftime('%H:%M:%S')}] {label}, seed {seed}: LiDAR {r['lidar_first_motion_m_s']:.3f} -> "
                  f"{r['lidar_line_m_s']:.3f}, IMU {r['imu_first_motion_m_s']:.3f} -> {r['imu_line_m_s']:.3f} m/s",
                  file=sys.stderr, flush=True)
            rows.append(r)
    keys = ("lidar_first_motion_m_s", "lidar_line_m_s", "imu_first_motion_m_s", "imu_line_m_s")
    summary = {label: {k: _stats([r[k] for r in rows if r["sequence"] == label]) for k in keys}
               for label, _, _ in STREAMS}
    meta = {"date": dt.date.today().isoformat(), "commit": commit_label(commit0), "seeds": a.seeds,
            "start_deskew_window_s": 0.5,
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "load_before": load0,
            "load_after": os.getloadavg(), "cpus": os.cpu_count(),
            "command": "python benchmarks/bench_start_velocity.py " + " ".join(argv or sys.argv[1:])}
    a.json.write_text(json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=1) + "\n")
    out = [f"# The first sweep's deskew velocity error (m/s), seeds {a.seeds[0]}-{a.seeds[-1]}", "",
           "| stream | LiDAR only: first motion | LiDAR only: line | with the IMU: first motion | with the IMU: line |",
           "|---|---|---|---|---|"]
    for label, _, _ in STREAMS:
        s = summary[label]
        out.append(f"| {label} | " + " | ".join(f"{s[k]['median']:.3f} ({s[k]['min']:.3f}-{s[k]['max']:.3f})"
                                               for k in keys) + " |")
    a.md.write_text("\n".join(out) + "\n\nMedian (min-max) over the seeds.\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
