"""Deskewing in ``minegeo slam`` on simulated sensor streams: ATE with and without it.

For each stream preset (vehicle, handheld, drone; ``minegeo synth OUT --stream P --duration-s D --seed S``,
written once into the work folder and reused) ``minegeo slam`` runs three times on the same frames:

* ``raw``: ``--no-deskew`` (the sweeps as recorded, smeared by the motion);
* ``deskew, 1 pass``: ``--deskew-iterations 0`` (deskewed by the constant-velocity twist of the last
  registered motion, as KISS-ICP does);
* ``deskew, 2 passes`` (the default): deskewed again by the twist of the frame's own registered motion.

ATE RMSE against the stream's ``groundtruth.txt``: after SE(3) Umeyama alignment
(:func:`minegeo.slam.evaluate.evaluate_trajectory`, evo's definition) and without alignment (the truth
moved into the first sensor frame, the SLAM map frame), in m and % of the true path; the frames held
by the motion prior (rejected registrations) and the wall time of each run.

Usage::

    python benchmarks/bench_deskew.py --duration-s 20 --work ~/.cache/minegeo_bench/deskew \\
        --json benchmarks/results/deskew_<date>.json --md benchmarks/results/deskew_<date>.md
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

MODES = {"raw": ["--no-deskew"], "deskew, 1 pass": ["--deskew-iterations", "0"], "deskew, 2 passes (default)": []}


def run_cli(args: list[str]) -> float:
    """Wall time (s) of ``python -m minegeo.cli --quiet ARGS`` (a failed run raises)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "minegeo.cli", "--quiet", *args], check=True)
    return time.perf_counter() - t0


def synth_stream(work: Path, preset: str, duration_s: float, seed: int) -> Path:
    """The folder of ``minegeo synth --stream PRESET --duration-s D --seed S`` in ``work``, written once
    (reused when its ``groundtruth.txt`` is there)."""
    stream = work / f"{preset}_{duration_s:g}s_seed{seed}"
    if not (stream / "groundtruth.txt").is_file():
        run_cli(["synth", str(stream), "--stream", preset, "--duration-s", f"{duration_s:g}", "--seed", str(seed),
                 "--force"])
    return stream


def stream_ate(run: Path, stream: Path) -> tuple[dict, dict]:
    """ATE of ``run/trajectory.tum`` against ``stream/groundtruth.txt``: ``path_m``, ``ate_aligned_m``
    (SE(3) Umeyama, evo's definition), ``ate_unaligned_m`` and ``max_error_unaligned_m`` (the truth moved
    into the first sensor frame), ``frames``; and the ``result`` of ``run/result.json``."""
    from minegeo.io.trajectory import read_trajectory
    from minegeo.slam.evaluate import evaluate_trajectory

    est = read_trajectory(run / "trajectory.tum")
    gt = read_trajectory(stream / "groundtruth.txt")
    aligned = float(evaluate_trajectory(est, gt).ate.rmse)
    G = np.einsum("ij,njk->nik", np.linalg.inv(gt.poses[0]), gt.poses)
    e = np.linalg.norm(est.poses[:, :3, 3] - G[:, :3, 3], axis=1)
    path = float(np.linalg.norm(np.diff(gt.poses[:, :3, 3], axis=0), axis=1).sum())
    res = json.loads((run / "result.json").read_text())["result"]
    return {"path_m": path, "ate_aligned_m": aligned, "ate_unaligned_m": float(np.sqrt(np.mean(e ** 2))),
            "max_error_unaligned_m": float(e.max()), "frames": res["frames"]}, res


def run_meta(script: str, argv, load0: float, duration_s: float, seed: int) -> dict:
    """The results file's ``meta``: date, commit (``+dirty`` when minegeo/ has changes), stream length and
    seed, Numba threads, 1-minute load at the start and now, cores, the command line of ``script``."""
    here = Path(__file__).parent
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=here).stdout.strip()
    if subprocess.run(["git", "status", "--porcelain", "--", "../minegeo"], capture_output=True, text=True,
                      cwd=here).stdout.strip():
        commit += "+dirty"
    return {"date": dt.date.today().isoformat(), "commit": commit, "duration_s": duration_s, "seed": seed,
            "numba_threads": os.environ.get("NUMBA_NUM_THREADS", "default"), "load_1min_start": load0,
            "load_1min_end": os.getloadavg()[0], "cpus": os.cpu_count(),
            "command": f"python benchmarks/{script} " + " ".join(argv if argv is not None else sys.argv[1:])}


def _ate(run: Path, stream: Path) -> dict:
    base, res = stream_ate(run, stream)
    return {**base, "frames_held_by_prior": int(sum(h["frames"] for h in res["motion_prior_stretches"])),
            "frames_deskewed": res["deskew"]["frames_deskewed"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--presets", nargs="+", default=["vehicle", "handheld", "drone"])
    ap.add_argument("--work", type=Path, default=Path.home() / ".cache" / "minegeo_bench" / "deskew")
    ap.add_argument("--odometry", choices=("auto", "submap", "frame"), default="auto",
                    help="minegeo slam --odometry (auto, the CLI's default: the local map on these 10 Hz streams)")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    rows = []
    for preset in a.presets:
        stream = synth_stream(a.work, preset, a.duration_s, a.seed)
        for mode, opts in MODES.items():
            run = a.work / f"{stream.name}_{'_'.join(mode.replace(',', '').split()[:3])}"
            opts = [*opts, "--odometry", a.odometry]
            wall = run_cli(["slam", "--frames", str(stream / "frames"),
                         "--out", str(run), *opts])
            rows.append({"preset": preset, "mode": mode, "options": opts, "wall_s": wall, **_ate(run, stream)})
            print(rows[-1], flush=True)
    meta = run_meta("bench_deskew.py", argv, load0, a.duration_s, a.seed)
    commit = meta["commit"]
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = [f"*{meta['date']}, commit {commit}, {a.duration_s:g} s streams at 10 Hz (seed {a.seed}), Numba threads "
             f"{meta['numba_threads']}, 1-minute load {load0:.1f} → {meta['load_1min_end']:.1f} on {meta['cpus']} "
             "cores.*", "",
             "| stream | mode | ATE RMSE, aligned | ATE RMSE, unaligned | max error | frames held by the prior | wall |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["path_m"]
        lines.append(f"| {r['preset']} {p:.1f} m | {r['mode']} | {r['ate_aligned_m']:.3f} m "
                     f"({100 * r['ate_aligned_m'] / p:.3f} %) | {r['ate_unaligned_m']:.3f} m "
                     f"({100 * r['ate_unaligned_m'] / p:.3f} %) | {r['max_error_unaligned_m']:.3f} m | "
                     f"{r['frames_held_by_prior']} of {r['frames']} | {r['wall_s']:.0f} s |")
    a.md.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
