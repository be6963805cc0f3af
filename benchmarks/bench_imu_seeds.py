"""Does the IMU lower the ATE of ``minegeo slam``? The same 20 s stream with and without ``--imu``, over
many seeds (draws of the route, the sway, the rock, the range and IMU noise), paired by seed.

One 20 s run is one draw: the unaligned ATE of the same code moves by tenths of a percent of the path
with the last bits of its input (docs/index.md, "Reproducibility"). This script answers the question
in distribution. Each stream is ``minegeo synth OUT --stream P --stream-network N --duration-s 20 --seed K``
(written once into ``--work``, the names of ``bench_stream_ate.py``). It is run by ``minegeo slam``
deskewed, without and with ``--imu imu.csv``, everything else the CLI's default. ATE as
``bench_stream_ate.py`` computes it (unaligned: both trajectories in their first pose's frame;
aligned: SE(3) Umeyama), in % of the path. Per sequence: median, RMS and range of each, and the paired
difference IMU − LiDAR only (mean ± standard error over the seeds, seeds where the IMU is lower).

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_imu_seeds.py --sequence "vehicle, loop 3.2 m" --seeds 1-10 \\
        --work /tmp/imu_seeds --json benchmarks/results/imu_seeds_<date>_vehicle.json --md ....md
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_covariance_frames import paired_stats  # noqa: E402
from bench_inertial_edge_noise import _commit, commit_label, run_slam_ate  # noqa: E402
from bench_stream_ate import SEQUENCES, _stream  # noqa: E402


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(a)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", choices=list(SEQUENCES), required=True)
    ap.add_argument("--seeds", type=_seeds, default=_seeds("1-10"), help="first-last, e.g. 1-10")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    load0, commit0 = os.getloadavg(), _commit()
    carrier, network = SEQUENCES[a.sequence]
    rows = []
    for seed in a.seeds:
        stream = _stream(a.work, carrier, network, 20.0, seed)
        r = {"seed": seed}
        for imu in (False, True):
            key = "imu" if imu else "lidar"
            ate = run_slam_ate(stream, a.work / f"{stream.name}_{key}", "default" if imu else None)
            r["path_m"] = ate["path_m"]
            r[f"{key}_unaligned_pct"], r[f"{key}_aligned_pct"] = ate["ate_unaligned_pct"], ate["ate_aligned_pct"]
        print(f"[{time.strftime('%H:%M:%S')}] {a.sequence}, seed {seed}: {r['lidar_unaligned_pct']:.3f} -> "
              f"{r['imu_unaligned_pct']:.3f} % unaligned", file=sys.stderr, flush=True)
        rows.append(r)
    summary = {f"{k}_{m}": paired_stats([r[f"{k}_{m}_pct"] for r in rows], [r[f"lidar_{m}_pct"] for r in rows])
               for k in ("lidar", "imu") for m in ("unaligned", "aligned")}
    meta = {"date": dt.date.today().isoformat(), "commit": commit_label(commit0),
            "sequence": a.sequence, "seeds": a.seeds, "duration_s": 20.0,
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "load_before": load0,
            "load_after": os.getloadavg(), "cpus": os.cpu_count(),
            "command": "python benchmarks/bench_imu_seeds.py " + " ".join(argv or sys.argv[1:])}
    a.json.write_text(json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=1) + "\n")
    a.md.write_text(_markdown(meta, summary, rows))
    return 0


def _markdown(meta: dict, summary: dict, rows: list[dict]) -> str:
    n = len(rows)
    out = [f"# `minegeo slam` without and with `--imu`: {meta['sequence']}, 20 s, seeds {meta['seeds'][0]}-{meta['seeds'][-1]}", "",
           "| ATE (% of the path) | median | min-max | RMS over the seeds | IMU − LiDAR only (mean ± s.e.) | seeds lower with the IMU |",
           "|---|---|---|---|---|---|"]
    for m in ("unaligned", "aligned"):
        for k, label in (("lidar", "LiDAR only"), ("imu", "with the IMU")):
            s = summary[f"{k}_{m}"]
            diff = (f"{s['paired_difference_mean']:+.3f} ± {s['paired_difference_se']:.3f}" if k == "imu" else "")
            lower = f"{s['seeds_lower_than_first']} of {n}" if k == "imu" else ""
            out.append(f"| {m}, {label} | {s['median']:.3f} | {s['min']:.3f}-{s['max']:.3f} | {s['rms']:.3f} | {diff} | {lower} |")
    out += ["", "| seed | path | unaligned, LiDAR only | unaligned, with the IMU | aligned, LiDAR only | aligned, with the IMU |",
            "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['seed']} | {r['path_m']:.1f} m | {r['lidar_unaligned_pct']:.3f} % | {r['imu_unaligned_pct']:.3f} % | "
                   f"{r['lidar_aligned_pct']:.3f} % | {r['imu_aligned_pct']:.3f} % |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
