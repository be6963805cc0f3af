"""ATE of ``minegeo slam`` on motion-distorted 10 Hz streams against KISS-ICP on the same frames.

Issue 29's acceptance table: per sequence, ``minegeo slam`` (the CLI, default parameters otherwise)

* ``raw``: ``--no-deskew`` (the sweeps as recorded, smeared by the motion);
* ``deskewed``: the default (constant-velocity deskewing, two passes; docs/slam.md "Deskewing");
* ``deskewed + IMU``: ``--imu imu.csv`` (gyro-aided odometry, IMU gate, preintegration graph);
* ``deskewed by the truth`` (an oracle, ``--modes``): each sweep deskewed before the run by the simulator's
  motion over it, the constant body twist ``Log(T*_k⁻¹ T*_{k+1}) / Δt`` from the true poses at its frame
  time and the next (the last sweep by the motion into it), written with every point's time 0
  (``<stream>/frames_truth_deskewed``) and run as ``minegeo slam --frames``: the same passes as the
  ``deskewed`` row (its deskewing then moves nothing), so the row is the error left to the registration
  when the deskewing is right, what separates the deskew's share of a row from the rest;

and **KISS-ICP** (``KissICP.register_frame(points, times)``, its own deskewing from the same per-point
times, configuration of ``benchmarks/bench_realtime.py``: ``kiss_config``), as it ships (voxel
``max_range / 100`` = 1.0 m) and with a voxel of 0.25 m, the size a user would set for 3 m drifts. ATE RMSE unaligned (both
trajectories and the truth in their first pose's frame) and SE(3)-aligned, in m and % of the path,
with the functions of ``bench_realtime.py`` (minegeo's poses at the frame times; KISS-ICP's at the
end of each sweep, where it deskews to, against the truth interpolated there).

Sequences (``minegeo synth OUT --stream CARRIER --stream-network NET --duration-s D --seed S``): a vehicle
on the loop network (3.2 m drifts) and on the junctions network (3.5 m), a drone in the NIOSH layout
(2.9 m drifts, the shared data's edge list), a handheld walk on the loop, and a vehicle on the three
paths of the paper world (``build_world("paper", 1)``, 4.5 m drifts; docs/synth.md "Paper-world
streams"): ``paper-ring`` (the 100 m ring roadway once round and 15 m on, 114 m), ``paper-straight``
(the L1 main drift, 505 m) and ``paper-ramp`` (251 m, 25 m down the 7 degree ramp). The vehicle starts
from rest at 1 s, so ``--duration-s`` D covers about 3 (D - 3) m; the paths last 41.8, 172.1 and
88.7 s (a longer D is refused). A paper-world sweep costs about 0.7 s to cast (about 7 s per second
of stream on one core).

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_stream_ate.py --duration-s 20 \\
        --json benchmarks/results/stream_ate_<date>.json --md benchmarks/results/stream_ate_<date>.md
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_realtime import _ate, kiss_config, load_frames, run_kiss  # noqa: E402

NIOSH = HERE.parent.parent / "shared" / "data" / "subt_tunnel_niosh_mine" / "ex_edgelist.csv"
#: name -> (carrier preset, --stream-network)
SEQUENCES = {"vehicle, loop 3.2 m": ("vehicle", "loop"), "vehicle, junctions 3.5 m": ("vehicle", "junctions"),
             "drone, NIOSH 2.9 m": ("drone", "niosh"), "handheld, loop 3.2 m": ("handheld", "loop"),
             "vehicle, paper ring": ("vehicle", "paper-ring"), "vehicle, paper straight": ("vehicle", "paper-straight"),
             "vehicle, paper ramp": ("vehicle", "paper-ramp")}
MODES = {"raw": ["--no-deskew"], "deskewed": [], "deskewed + IMU": ["--imu", "IMU"], "deskewed by the truth": ["TRUTH"]}
#: KISS-ICP runs: label -> voxel size (m); None = as it ships (max_range / 100 = 1.0 m at 100 m range)
KISS_VOXELS = {"KISS-ICP (its deskewing), voxel 1.0 m as shipped": None,
               "KISS-ICP (its deskewing), voxel 0.25 m for 3 m drifts": 0.25}


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _cli(args: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "minegeo.cli", "--quiet", *args], check=True)
    return time.perf_counter() - t0


def _stream(work: Path, carrier: str, network: str, duration_s: float, seed: int) -> Path:
    d = work / f"{carrier}_{network}_{duration_s:g}s_seed{seed}"
    if not (d / "groundtruth.txt").is_file():
        _log(f"simulating {d.name} ...")
        net = str(NIOSH) if network == "niosh" else network
        _cli(["synth", str(d), "--stream", carrier, "--stream-network", net, "--duration-s", f"{duration_s:g}",
              "--seed", str(seed), "--force"])
    return d


def _truth_deskewed(stream: Path, frames: list, truth) -> Path:
    """``stream/frames_truth_deskewed``: each sweep deskewed by the true constant twist over it (see the
    module's ``deskewed by the truth``), PLY with every point's ``time`` 0, and ``times.txt``; written once."""
    from minegeo.io import PointCloud
    from minegeo.io.pointcloud import write_point_cloud
    from minegeo.slam.control_graph import interpolate_poses
    from minegeo.slam.deskew import deskew_points, twist_from_motion

    out = stream / "frames_truth_deskewed"
    if (out / "times.txt").is_file():
        return out
    tmp = stream / "frames_truth_deskewed.part"
    tmp.mkdir(exist_ok=True)
    t = np.asarray([f[0] for f in frames])
    G = interpolate_poses(truth.times_s, truth.poses, t)
    for k, (_, pts, tau) in enumerate(frames):
        a, b = (k, k + 1) if k + 1 < len(frames) else (k - 1, k)
        twist = twist_from_motion(np.linalg.inv(G[a]) @ G[b], t[b] - t[a])
        write_point_cloud(tmp / f"{k:06d}.ply", PointCloud(deskew_points(pts, tau, twist),
                                                          attributes={"time": np.zeros(len(pts))}))
    (tmp / "times.txt").write_text("".join(f"{x:.9f}\n" for x in t))
    tmp.rename(out)
    return out


def _minegeo(stream: Path, run: Path, opts: list[str], times: np.ndarray, truth, frames=None) -> dict:
    from minegeo.io.trajectory import read_trajectory

    opts = [str(stream / "imu.csv") if o == "IMU" else o for o in opts]
    src = stream / "frames"
    if "TRUTH" in opts:
        src, opts = _truth_deskewed(stream, frames, truth), [o for o in opts if o != "TRUTH"]
    wall = _cli(["slam", "--frames", str(src), "--out", str(run), *opts])
    est = read_trajectory(run / "trajectory.tum")
    if est.times_s.size != times.size or np.abs(est.times_s - times).max() > 1e-6:
        raise SystemExit(f"{run}: the trajectory's times are not the frames'")
    res = json.loads((run / "result.json").read_text())["result"]
    return {"options": opts, "wall_s": wall, **_ate(times, est.poses, truth),
            "frames_held": int(sum(h["frames"] for h in res["motion_prior_stretches"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=list(SEQUENCES))
    ap.add_argument("--modes", nargs="+", default=[m for m in MODES if m != "deskewed by the truth"], choices=list(MODES),
                    help="minegeo's rows (default: raw, deskewed, deskewed + IMU; the oracle on request)")
    ap.add_argument("--no-kiss", action="store_true", help="minegeo's rows only (no KISS-ICP rows)")
    ap.add_argument("--work", type=Path, default=Path.home() / ".cache" / "minegeo_bench" / "stream_ate")
    ap.add_argument("--kiss-threads", type=int, default=1)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    ap.add_argument("--odometry", choices=("auto", "submap", "frame"), default=None,
                    help="minegeo slam --odometry (default: the CLI's default, auto)")
    ap.add_argument("--kiss-from", type=Path, default=None, metavar="RESULTS.json",
                    help="take the KISS-ICP rows from an earlier run of this script on the same streams (same "
                         "duration and seed; KISS-ICP is not run again): minegeo's rows only are measured")
    a = ap.parse_args(argv)
    kiss_old = None
    if a.kiss_from is not None:
        old = json.loads(a.kiss_from.read_text())
        if (old["meta"]["duration_s"], old["meta"]["seed"]) != (a.duration_s, a.seed):
            raise SystemExit(f"--kiss-from {a.kiss_from}: other streams (duration {old['meta']['duration_s']} s, "
                             f"seed {old['meta']['seed']})")
        kiss_old = old
    a.work.mkdir(parents=True, exist_ok=True)
    up0 = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    commit0 = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=HERE).stdout.strip()
    rows = []
    for name in a.sequences:
        carrier, network = SEQUENCES[name]
        stream = _stream(a.work, carrier, network, a.duration_s, a.seed)
        frames, truth = load_frames(stream)
        times = np.asarray([f[0] for f in frames])
        for mode, opts in ((m, MODES[m]) for m in a.modes):
            run = a.work / f"{stream.name}_{mode.replace(' + ', '_').replace(' ', '_')}"
            opts = opts + (["--odometry", a.odometry] if a.odometry else [])
            rows.append({"sequence": name, "mode": mode, **_minegeo(stream, run, opts, times, truth, frames),
                         "odometry_target": json.loads((run / "result.json").read_text())["result"]
                         ["odometry_target"]["frame_target"]})
            _log(f"{name} / {mode}: {rows[-1]['ate_aligned_pct']:.3f} % aligned")
        end = times + np.asarray([float(f[2].max()) for f in frames])
        keep = end <= truth.times_s[-1]  # KISS-ICP's pose time (the sweep's end) inside the truth
        for label, voxel in ({} if a.no_kiss else KISS_VOXELS).items():
            if kiss_old is not None:
                (r,) = [r for r in kiss_old["rows"] if r["sequence"] == name and r["mode"] == label]
                rows.append({**r, "from": str(a.kiss_from)})
                continue
            t0 = time.perf_counter()
            _, poses = run_kiss(frames, a.kiss_threads, voxel)
            rows.append({"sequence": name, "mode": label, "wall_s": time.perf_counter() - t0,
                         **_ate(end[keep], poses[keep], truth), "frames_held": None})
            _log(f"{name} / {label}: {rows[-1]['ate_aligned_pct']:.3f} % aligned")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=HERE).stdout.strip()
    if subprocess.run(["git", "status", "--porcelain", "--", "../minegeo"], capture_output=True, text=True,
                      cwd=HERE).stdout.strip():
        commit += "+dirty"
    from importlib.metadata import version

    numba_threads = os.environ.get("NUMBA_NUM_THREADS", "default")
    meta = {"date": dt.date.today().isoformat(), "commit": commit if commit.startswith(commit0) else f"{commit0}..{commit}",
            "duration_s": a.duration_s, "seed": a.seed, "numba_threads": numba_threads, "kiss_threads": a.kiss_threads,
            "threads": f"{numba_threads} for minegeo (Numba), {a.kiss_threads} for KISS-ICP",
            "kiss_icp_version": version("kiss-icp"), "kiss_config": repr(kiss_config(a.kiss_threads)),
            "uptime_before": up0, "uptime_after": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
            "cpus": os.cpu_count(),
            "kiss_rows_from": None if kiss_old is None else {"file": str(a.kiss_from), "commit": kiss_old["meta"]["commit"],
                                                              "date": kiss_old["meta"]["date"]},
            "command": "python benchmarks/bench_stream_ate.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    a.md.write_text(markdown({"meta": meta, "rows": rows}))
    return 0


def markdown(d: dict) -> str:
    m = d["meta"]
    L = [f"*{m['date']}, commit {m['commit']}, {m['duration_s']:g} s streams at 10 Hz (seed {m['seed']}); minegeo "
         f"Numba threads {m['numba_threads']}, KISS-ICP {m['kiss_icp_version']} max_num_threads {m['kiss_threads']}; "
         f"load: `{m['uptime_before']}` → `{m['uptime_after']}`; {m['cpus']} cores"
         + ("" if not m.get("kiss_rows_from") else f"; KISS-ICP rows from `{m['kiss_rows_from']['file']}` (same "
            f"streams, commit {m['kiss_rows_from']['commit']}, {m['kiss_rows_from']['date']})") + ".*", "",
         "| sequence | path | mode | odometry | ATE RMSE, aligned | ATE RMSE, unaligned | max error (unaligned) | frames held |",
         "|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        held = "" if r["frames_held"] is None else str(r["frames_held"])
        target = {"submap": "to the local map", "frame": "frame to frame"}.get(r.get("odometry_target"), "")
        L.append(f"| {r['sequence']} | {r['path_m']:.1f} m | {r['mode']} | {target} | {r['ate_aligned_m']:.3f} m "
                 f"({r['ate_aligned_pct']:.3f} %) | {r['ate_unaligned_m']:.3f} m ({r['ate_unaligned_pct']:.3f} %) | "
                 f"{r['ate_max_m']:.3f} m | {held} |")
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
