"""The LiDAR edges' added noise in the LiDAR-inertial keyframe graph (``InertialParams.edge_sigma_deg``,
``edge_sigma_m``) against ATE, on the simulated 10 Hz streams of ``bench_stream_ate.py``.

Each stream (``minegeo synth OUT --stream P --stream-network N --duration-s D --seed K``, written once
into ``--work``) is run by ``minegeo slam --imu imu.csv`` once per noise pair, and once without
``--imu`` for reference. The pair is set through the CLI's own parameter function
(``minegeo.cli.slam.inertial_params`` wrapped to replace the two fields; the run's ``result.json``
records the parameters it used, which the script checks). Everything else is the CLI's default run.
ATE as ``bench_stream_ate.py`` computes it (unaligned: both trajectories in their first pose's
frame; aligned: SE(3) Umeyama), in m and % of the path.

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_inertial_edge_noise.py --work /tmp/edge_noise \\
        --json benchmarks/results/inertial_edge_noise_<date>.json --md benchmarks/results/inertial_edge_noise_<date>.md
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
from bench_realtime import _ate  # noqa: E402
from bench_stream_ate import SEQUENCES, _stream  # noqa: E402

#: (sequence of bench_stream_ate, seed), 20 s each
STREAMS = [("vehicle, loop 3.2 m", 1), ("vehicle, junctions 3.5 m", 1), ("handheld, loop 3.2 m", 1),
           ("drone, NIOSH 2.9 m", 1), ("drone, NIOSH 2.9 m", 4), ("drone, NIOSH 2.9 m", 2), ("drone, NIOSH 2.9 m", 3),
           ("drone, NIOSH 2.9 m", 5), ("vehicle, loop 3.2 m", 2), ("vehicle, junctions 3.5 m", 2),
           ("handheld, loop 3.2 m", 2)]
#: (edge_sigma_deg, edge_sigma_m); None: no IMU
PAIRS = [None, (0.2, 0.02), (0.1, 0.01), (0.05, 0.005), (0.02, 0.002)]

#: the CLI run with the two fields replaced in the parameters the CLI builds from its options
WRAPPER = """
import sys
from dataclasses import replace
import minegeo.cli.slam as s
from minegeo.cli import main
_orig = s.inertial_params
s.inertial_params = lambda args: (lambda p: None if p is None else replace(p, edge_sigma_deg={d!r}, edge_sigma_m={m!r}))(_orig(args))
sys.exit(main(sys.argv[1:]))
"""


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def run_slam_ate(stream: Path, run: Path, pair) -> dict:
    """``minegeo slam`` on ``stream/frames`` into ``run``: without the IMU (``pair`` None), with ``--imu``
    and the CLI's parameters (``"default"``), or with ``--imu`` and the edge noise ``pair = (deg, m)``
    (checked in the run's ``result.json``); its wall time and ATE (``bench_realtime._ate``)."""
    from minegeo.io.trajectory import read_trajectory

    args = ["--quiet", "slam", "--frames", str(stream / "frames"), "--out", str(run)]
    imu = ["--imu", str(stream / "imu.csv")]
    if pair is None:
        cmd = [sys.executable, "-m", "minegeo.cli", *args]
    elif pair == "default":
        cmd, pair = [sys.executable, "-m", "minegeo.cli", *args, *imu], None
    else:
        cmd = [sys.executable, "-c", WRAPPER.format(d=pair[0], m=pair[1]), *args, *imu]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    res = json.loads((run / "result.json").read_text())
    if pair is not None:
        got = res["inertial"]["edge_sigma_deg"] == pair[0] and res["inertial"]["edge_sigma_m"] == pair[1]
        if not got:
            raise SystemExit(f"{run}: result.json does not record edge_sigma_deg {pair[0]}, edge_sigma_m {pair[1]}")
    truth = read_trajectory(stream / "groundtruth.txt")
    est = read_trajectory(run / "trajectory.tum")
    return {"wall_s": wall, **_ate(est.times_s, est.poses, truth)}


def _commit() -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True).stdout.strip()


def commit_label(commit0: str) -> str:
    """The commit a run ended at, ``+dirty`` with uncommitted library changes, as ``start..end`` when it
    is not the commit ``commit0`` the run started at."""
    commit = _commit()
    if subprocess.run(["git", "status", "--porcelain", "--", "../minegeo"], capture_output=True, text=True,
                      cwd=HERE).stdout.strip():
        commit += "+dirty"
    return commit if commit.startswith(commit0) else f"{commit0}..{commit}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    up0 = os.getloadavg()
    commit0 = _commit()
    rows = []
    for seq, seed in STREAMS:
        carrier, network = SEQUENCES[seq]
        stream = _stream(a.work, carrier, network, 20.0, seed)
        for pair in PAIRS:
            tag = "no_imu" if pair is None else f"{pair[0]:g}deg_{pair[1]:g}m"
            r = run_slam_ate(stream, a.work / f"{stream.name}_{tag}", pair)
            label = "no IMU" if pair is None else f"{pair[0]:g}°, {1000 * pair[1]:g} mm"
            _log(f"{seq}, seed {seed} / {label}: {r['ate_unaligned_pct']:.3f} % unaligned")
            rows.append({"sequence": seq, "seed": seed, "edge_sigma": pair, "label": label, **r})
    meta = {"date": dt.date.today().isoformat(), "commit": commit_label(commit0), "duration_s": 20.0,
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "load_before": up0,
            "load_after": os.getloadavg(), "cpus": os.cpu_count(),
            "command": "python benchmarks/bench_inertial_edge_noise.py " + " ".join(argv or sys.argv[1:])}
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    a.md.write_text(_markdown(meta, rows))
    return 0


def _markdown(meta: dict, rows: list[dict]) -> str:
    labels = list(dict.fromkeys(r["label"] for r in rows))
    keys = list(dict.fromkeys((r["sequence"], r["seed"]) for r in rows))
    by = {(r["sequence"], r["seed"], r["label"]): r for r in rows}
    load = f"{meta['load_before'][0]:.1f}-{meta['load_after'][0]:.1f}"
    out = [f"*Results file `benchmarks/results/inertial_edge_noise_{meta['date']}.json`; measured {meta['date']}; "
           f"commit {meta['commit']}; threads {meta['numba_threads']} (Numba); 1-minute load {load} "
           f"({meta['cpus']}-core machine); 20 s streams at 10 Hz; `minegeo slam` deskewed, with `--imu` and the "
           "LiDAR edges' added noise of each column (rotation per axis, translation per axis).*", "",
           "Unaligned ATE RMSE, % of the path:", "",
           "| stream | path | " + " | ".join(labels) + " |", "|---|---|" + "---|" * len(labels)]
    lower = {lab: 0 for lab in labels}
    for seq, seed in keys:
        cells = [by[(seq, seed, lab)] for lab in labels]
        out.append(f"| {seq}, seed {seed} | {cells[0]['path_m']:.1f} m | "
                   + " | ".join(f"{c['ate_unaligned_pct']:.3f} %" for c in cells) + " |")
        base = by.get((seq, seed, "0.2°, 20 mm"))
        for lab, c in zip(labels, cells, strict=True):
            if base is not None and c["ate_unaligned_pct"] < base["ate_unaligned_pct"]:
                lower[lab] += 1
    med = {lab: float(np.median([by[(s, k, lab)]["ate_unaligned_pct"] for s, k in keys])) for lab in labels}
    out.append("| median | | " + " | ".join(f"{med[lab]:.3f} %" for lab in labels) + " |")
    out.append("| streams lower than 0.2°, 20 mm | | " + " | ".join(str(lower[lab]) for lab in labels) + " |")
    out += ["", "Aligned ATE RMSE, % of the path:", "", "| stream | " + " | ".join(labels) + " |",
            "|---|" + "---|" * len(labels)]
    for seq, seed in keys:
        out.append(f"| {seq}, seed {seed} | " + " | ".join(f"{by[(seq, seed, lab)]['ate_aligned_pct']:.3f} %"
                                                       for lab in labels) + " |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
