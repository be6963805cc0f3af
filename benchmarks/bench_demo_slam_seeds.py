"""The demo's SLAM step over many draws of its sequence, run by two (or more) versions of the code.

``minegeo demo`` scores one draw (``--seed 1``) of its 114 m loop: the world's rock relief, the
carrier's sway and the range noise all come from the seed, and the SLAM trajectory error (ATE RMSE
without alignment, both in their first pose's frame) moves by centimetres from draw to draw. One
draw cannot say whether a change made the SLAM better or worse; this script draws the demo's
sequence for every seed given, with the present code (``minegeo demo``'s step 2:
:func:`bench_covariance_frames._demo_sequence`), writes it as the frames folder the demo writes,
runs ``python -m minegeo.cli slam --frames F --out O --seed S`` on it with each source tree given
(``PYTHONPATH`` set to the tree: e.g. a ``git worktree`` of an older commit, and this clone) and scores
each trajectory as the demo does. The summary gives, per tree, the median, range and RMS over the
seeds and, against the first tree, the paired difference (mean ± its standard error over the seeds)
and on how many seeds it is lower.

Usage (the code of 2026-11-29, ``6db6ec7``, against the present)::

    git worktree add /tmp/minegeo-6db6ec7 6db6ec7
    python benchmarks/bench_demo_slam_seeds.py --seeds $(seq 1 30) --work /tmp/demo_seeds \\
        --trees 6db6ec7=/tmp/minegeo-6db6ec7 HEAD=. \\
        --json benchmarks/results/demo_slam_seeds_<date>.json --md benchmarks/results/demo_slam_seeds_<date>.md

Each ``minegeo slam`` runs with ``NUMBA_NUM_THREADS=1`` (the first run of a tree compiles its kernels
into that tree's Numba cache; the scores do not depend on it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from bench_covariance_frames import _demo_sequence, _relative_to_first, _uptime, paired_stats


def _commit(tree: Path) -> str:
    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=tree)
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                           text=True, cwd=tree).stdout.strip()
    return r.stdout.strip() + ("+dirty" if dirty else "")


def _run_slam(tree: Path, frames: Path, out: Path, seed: int) -> int:
    env = dict(os.environ, PYTHONPATH=str(tree.resolve()), NUMBA_NUM_THREADS="1")
    with open(out.parent / f"{out.name}.log", "w") as log:
        return subprocess.run([sys.executable, "-m", "minegeo.cli", "slam", "--frames", str(frames), "--out", str(out),
                               "--seed", str(seed)], env=env, cwd="/", stdout=log, stderr=subprocess.STDOUT).returncode


def _score(trajectory: Path, gt) -> tuple[float, float]:
    from minegeo.io import read_trajectory
    from minegeo.slam.evaluate import evaluate_trajectory

    ev = evaluate_trajectory(read_trajectory(trajectory), gt, align=False)
    return float(ev.ate.rmse), float(ev.ate.max)


def main(argv=None) -> int:
    from minegeo.io import write_trajectory
    from minegeo.synth.sequence import write_frames

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--trees", nargs="+", required=True, help="NAME=DIR: source trees to run (the first is the reference)")
    ap.add_argument("--work", type=Path, required=True, help="folder for the frames and the runs (made)")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    a = ap.parse_args(argv)
    trees = []
    for spec in a.trees:
        name, sep, d = spec.partition("=")
        if not sep or not Path(d, "minegeo", "__init__.py").is_file():
            ap.error(f"--trees {spec!r}: NAME=DIR with DIR a minegeo source tree")
        trees.append((name, Path(d)))
    up0, rows = _uptime(), []
    for seed in a.seeds:
        frames, truth = _demo_sequence(seed)
        d = a.work / f"seed{seed}"
        if not (d / "frames").is_dir():
            write_frames(d / "frames", truth.times_s, [P for _, P in frames])
            write_trajectory(d / "truth.tum", truth, format="tum")
        gt = _relative_to_first(truth)
        row = {"seed": seed, "frames": len(frames),
               "path_m": float(np.linalg.norm(np.diff(truth.poses[:, :3, 3], axis=0), axis=1).sum())}
        for name, tree in trees:
            out = d / name
            rc = 0 if (out / "trajectory.tum").is_file() else _run_slam(tree, d / "frames", out, seed)
            row[name] = dict(zip(("ate_rmse_m", "ate_max_m"), _score(out / "trajectory.tum", gt), strict=True)) \
                if rc == 0 else {"failed": rc}
        rows.append(row)
        print(row, flush=True)
    names = [n for n, _ in trees]
    ok = [r for r in rows if all("ate_rmse_m" in r[n] for n in names)]  # a failed run is listed, not scored
    summary = {"seeds_scored": len(ok), "seeds_failed": [r["seed"] for r in rows if r not in ok]}
    for n in names:
        s = paired_stats([r[n]["ate_rmse_m"] for r in ok], [r[names[0]]["ate_rmse_m"] for r in ok])
        summary[n] = {(k if k == "seeds_lower_than_first" else k + "_m"): v for k, v in s.items()}
    here = _commit(Path(__file__).parent)
    meta = {"date": dt.date.today().isoformat(), "trees": {n: {"dir": str(t), "commit": _commit(t)} for n, t in trees},
            "commit": here, "simulated_by": here, "seeds": a.seeds, "numba_threads": 1,
            "uptime_before": up0, "uptime_after": _uptime(),
            "command": "python benchmarks/bench_demo_slam_seeds.py " + " ".join(argv or sys.argv[1:])}
    a.json.write_text(json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=2) + "\n")
    code = ", ".join(f"{n} = {v['commit']}" for n, v in meta["trees"].items())
    lines = [f"*{meta['date']}; the demo's sequence (114 m loop, VLP-16 at 2 Hz, 2° azimuth step) drawn with seeds "
             f"{a.seeds[0]}-{a.seeds[-1]} ({len(a.seeds)} draws) by commit {meta['simulated_by']}; `minegeo slam` of "
             f"each tree ({code}), Numba threads 1; load: `{up0}` → `{meta['uptime_after']}`.*", "",
             f"SLAM ATE RMSE without alignment over the seeds; paired difference against {names[0]} (mean ± its "
             "standard error):", "",
             "| code | median | min-max | RMS over seeds | paired difference | seeds lower |", "|---|---|---|---|---|---|"]
    for n in names:
        s = summary[n]
        lines.append(f"| {n} ({meta['trees'][n]['commit']}) | {s['median_m']:.3f} m | {s['min_m']:.3f}-{s['max_m']:.3f} m "
                     f"| {s['rms_m']:.3f} m | {s['paired_difference_mean_m'] * 1e3:+.1f} ± "
                     f"{s['paired_difference_se_m'] * 1e3:.1f} mm | {s['seeds_lower_than_first']} of {len(ok)} |")
    if summary["seeds_failed"]:
        lines += ["", f"Failed (not in the summary): seeds {summary['seeds_failed']}."]
    lines += ["", "Per seed (ATE RMSE / max, m):", "", "| seed | path | " + " | ".join(names) + " |",
              "|---|---|" + "---|" * len(names)]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['path_m']:.1f} m | " + " | ".join(
            f"{r[n]['ate_rmse_m']:.3f} / {r[n]['ate_max_m']:.3f}" if "ate_rmse_m" in r[n] else f"failed ({r[n]['failed']})"
            for n in names) + " |")
    a.md.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
