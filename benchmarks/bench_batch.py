"""Benchmark: ``minegeo localize-batch`` throughput on 1 and 2 Dask workers, and bit-identity with
one-by-one ``minegeo localize``.

50 synthetic scans: the 5 scans of ``minegeo synth --preset small --seed S`` (irregular roof, X
intersection, curve, regular drift, railings), each in 10 scan frames (copy 0 as written, copies
1-9 moved by a random rigid motion: yaw uniform in [0, 360) deg, tilt up to 3 deg, shift up to
50 m; a scan's own frame is arbitrary, so each copy is a new localization problem with known
truth ``T_map_scan_copy = T_map_scan @ G^-1``). The map is prepared once (``prepare-map
--profile fast``).

For each worker count the batch runs as a user runs it (``python -m minegeo localize-batch
... --workers N`` in a fresh process, fresh ``--out``): wall time of the whole command (Python
start-up, the local cluster's start, every worker's Numba cache load, the summary and its
report included) and the batch's own rate (``batch_result.json``: scans / seconds of
``run_batch``). Then every scan is localized one by one with ``minegeo localize`` (in this process
through ``minegeo.cli.main``, the CLI's code path, same ``--seed``) and its ``result.json`` is
compared with the batch's in its JSON text without ``VOLATILE_FIELDS`` (timings and the batch
record); the first 5 scans also as separate processes, for the per-scan cost of a shell loop.

Usage::

    python benchmarks/bench_batch.py --work bench_out/batch --out benchmarks/results/batch_2026-11-25

Writes ``OUT.json`` and ``OUT.md``; records ``uptime`` before and after (the machine is shared).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's minegeo, not whatever copy is installed

FAST = ["--profile", "fast"]
SUCCESS_M = 0.10
WRONG_M = 1.0


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "n/a"


def _rot(yaw_deg: float, tilt_deg: float, axis_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    a = np.radians(axis_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(a), np.sin(a), 0.0]))
    return (tilt * Rotation.from_euler("z", yaw_deg, degrees=True)).as_matrix()


def make_scans(work: Path, seed: int, copies: int) -> tuple[Path, Path, dict]:
    """World, prepared map and ``copies`` moved copies of each of its scans; ``{file: T_map_scan truth}``."""
    from minegeo.cli import main
    from minegeo.io import PointCloud, read_point_cloud, write_point_cloud
    from minegeo.synth import write_world

    mine = work / "mine"
    if not (mine / "truth.json").exists():
        write_world(mine, "small", seed)
    prep = work / "map.npz"
    if not prep.exists():
        assert main(["-q", "prepare-map", "--map", str(mine / "map.ply"), "--out", str(prep), *FAST]) == 0
    truth = json.loads((mine / "truth.json").read_text(encoding="utf-8"))
    scans = work / "scans"
    scans.mkdir(exist_ok=True)
    rng = np.random.default_rng(1000 + seed)
    out = {}
    for s in truth["scans"]:
        T = np.asarray(s["T_map_scan"], dtype=np.float64)
        pts = read_point_cloud(mine / s["file"]).points
        for j in range(copies):
            G = np.eye(4)
            if j:
                G[:3, :3] = _rot(rng.uniform(0, 360), rng.uniform(0, 3), rng.uniform(0, 360))
                G[:3, 3] = rng.uniform(-50, 50, 3)
            f = scans / f"{s['name']}_c{j}.ply"
            if not f.exists():
                write_point_cloud(f, PointCloud(points=pts @ G[:3, :3].T + G[:3, 3]), binary=True)
            out[f.name] = T @ np.linalg.inv(G)
    return prep, scans, out


def run_batch_cli(prep: Path, scans: Path, out: Path, workers: int, seed: int) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "minegeo", "-q", "localize-batch", "--map", str(prep), "--scans",
                        str(scans), "--out", str(out), "--workers", str(workers), "--seed", str(seed), *FAST],
                       capture_output=True, text=True, env=env, timeout=3600)
    wall = time.perf_counter() - t0
    if r.returncode not in (0, 1):
        raise RuntimeError(f"localize-batch exited {r.returncode}: {r.stderr[-2000:]}")
    rec = json.loads((out / "batch_result.json").read_text(encoding="utf-8"))
    return {"workers": workers, "wall_s": wall, "scans_per_minute_wall": 60.0 * rec["n_run"] / wall,
            "batch_s": rec["timings_s"]["batch"], "scans_per_minute_batch": rec["scans_per_minute"],
            "n_run": rec["n_run"], "counts": rec["counts"]}


def score(out: Path, truth: dict) -> dict:
    """``ok`` results: within their own 95 % radius of the truth, within 0.10 m, or at another place (> 1 m)."""
    ok = within95 = within10 = wrong = 0
    worst = 0.0
    for name, T in truth.items():
        d = json.loads((out / Path(name).stem / "result.json").read_text(encoding="utf-8"))
        if d["status"] == "ok":
            ok += 1
            err = float(np.linalg.norm(np.asarray(d["T_map_scan"])[:3, 3] - T[:3, 3]))
            within95 += err <= float(d["position_95_radius_m"])
            within10 += err < SUCCESS_M
            wrong += err > WRONG_M
            worst = max(worst, err)
    return {"ok": ok, "ok_within_95_radius": within95, "ok_within_0.10_m": within10, "wrong_place_ok": wrong,
            "worst_ok_error_m": worst}


def one_by_one(prep: Path, scans: Path, batch_out: Path, seed: int, work: Path, n_subprocess: int) -> dict:
    from minegeo.cli import main
    from minegeo.localize.batch import comparable_record

    files = sorted(scans.iterdir())
    same, differ = 0, []
    t0 = time.perf_counter()
    for f in files:
        one = work / "one_by_one" / f.stem
        main(["-q", "localize", "--map", str(prep), "--scan", str(f), "--out", str(one), "--seed", str(seed), *FAST])
        a = json.loads((batch_out / f.stem / "result.json").read_text(encoding="utf-8"))
        b = json.loads((one / "result.json").read_text(encoding="utf-8"))
        if json.dumps(comparable_record(a)) == json.dumps(comparable_record(b)):
            same += 1
        else:
            differ.append(f.stem)
    t_in = time.perf_counter() - t0
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    for f in files[:n_subprocess]:
        subprocess.run([sys.executable, "-m", "minegeo", "-q", "localize", "--map", str(prep), "--scan", str(f),
                        "--out", str(work / "one_by_one_proc" / f.stem), "--seed", str(seed), *FAST],
                       capture_output=True, env=env, timeout=600)
    t_proc = (time.perf_counter() - t0) / max(n_subprocess, 1)
    return {"n": len(files), "identical": same, "different": differ, "in_process_s": t_in,
            "in_process_scans_per_minute": 60.0 * len(files) / t_in, "subprocess_s_per_scan": t_proc,
            "subprocess_scans_per_minute": 60.0 / t_proc}


def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="bench_out/batch")
    ap.add_argument("--out", default=f"benchmarks/results/batch_{time.strftime('%Y-%m-%d')}")
    ap.add_argument("--synth-seed", type=int, default=7)
    ap.add_argument("--copies", type=int, default=10, help="copies of each of the 5 scans (default 10: 50 scans)")
    ap.add_argument("--seed", type=int, default=0, help="localize --seed of every scan")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--subprocess-scans", type=int, default=5)
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    import minegeo

    minegeo.warmup()
    up0 = _uptime()
    prep, scans, truth = make_scans(work, a.synth_seed, a.copies)
    runs = []
    for w in (int(x) for x in a.workers.split(",")):
        out = work / f"out_w{w}"
        if out.exists():
            import shutil

            shutil.rmtree(out)
        r = run_batch_cli(prep, scans, out, w, a.seed)
        r["score"] = score(out, truth)
        r["uptime_after"] = _uptime()
        runs.append(r)
        print(json.dumps(r))
    ref = work / f"out_w{runs[0]['workers']}"
    ident = one_by_one(prep, scans, ref, a.seed, work, a.subprocess_scans)
    same_between = all(
        json.dumps(json.loads((work / f"out_w{r['workers']}" / f.stem / "result.json").read_text())["T_map_scan"])
        == json.dumps(json.loads((ref / f.stem / "result.json").read_text())["T_map_scan"])
        for r in runs for f in sorted(scans.iterdir()))
    res = {"date": time.strftime("%Y-%m-%d %H:%M"), "n_scans": len(truth), "synth_seed": a.synth_seed,
           "seed": a.seed, "runs": runs, "one_by_one": ident, "poses_equal_across_worker_counts": same_between,
           "uptime_before": up0, "uptime_after": _uptime(), "cpus": os.cpu_count(),
           "python": platform.python_version()}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out + ".json").write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    Path(a.out + ".md").write_text(markdown(res), encoding="utf-8")
    print(markdown(res))
    return 0


def markdown(res: dict) -> str:
    lines = [f"`minegeo localize-batch` on {res['n_scans']} synthetic scans (5 scans of `minegeo synth --preset small "
             f"--seed {res['synth_seed']}` x 10 scan frames), `--profile fast --seed {res['seed']}`, "
             f"{res['cpus']} CPUs, {res['date']}.",
             "",
             "| workers | command wall (s) | scans/min (whole command) | scans/min (batch, cluster start incl.) | ok | "
             "ok within its 95 % radius | ok within 0.10 m | ok at another place (> 1 m) | worst ok error (m) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in res["runs"]:
        s = r["score"]
        lines.append(f"| {r['workers']} | {r['wall_s']:.1f} | {r['scans_per_minute_wall']:.1f} | "
                     f"{r['scans_per_minute_batch']:.1f} | {s['ok']} | {s['ok_within_95_radius']} | "
                     f"{s['ok_within_0.10_m']} | {s['wrong_place_ok']} | {s['worst_ok_error_m']:.3f} |")
    o = res["one_by_one"]
    lines += ["",
              f"One by one: `minegeo localize` in one process {o['in_process_scans_per_minute']:.1f} scans/min "
              f"(map loaded per scan, as the CLI does); as separate processes (a shell loop) "
              f"{o['subprocess_scans_per_minute']:.1f} scans/min ({o['subprocess_s_per_scan']:.2f} s per scan).",
              f"Bit-identity: {o['identical']} of {o['n']} batch `result.json` equal to one-by-one `localize` in their "
              "JSON text without the timings and the batch record"
              + (f" (different: {', '.join(o['different'])})" if o["different"] else "")
              + f"; poses equal between worker counts: {res['poses_equal_across_worker_counts']}.",
              f"Load: before `{res['uptime_before']}`; after `{res['uptime_after']}`."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main_())
