"""First-use (cold Numba cache) cost of every ``minegeo`` verb on its small documented example.

Each verb runs as its own process (``python -m minegeo VERB ...``) with a **fresh, empty**
``NUMBA_CACHE_DIR`` (a temporary folder). minegeo's kernels are ``cache=True`` (``minegeo/_jit.py``);
Numba's first cache locator is the user-provided ``NUMBA_CACHE_DIR``, so the warm cache in the
checkout's ``__pycache__`` folders is neither read nor written: every kernel the verb needs is compiled
in that run, exactly as on a fresh install.

Per verb it records:

* ``wall_s``           what the user waits (process start to exit);
* ``compile_s``        Numba compile seconds of the run as the verb's own ``result.json`` states them
                       (``timings_s.compile_s``), where the verb writes one;
* ``cpu_s``            user + system CPU seconds of the child process and its children
                       (``resource.getrusage(RUSAGE_CHILDREN)`` difference). Numba compiles on one
                       thread, so on a shared machine this is the comparable column (wall time
                       grows with the load, CPU time hardly does);
* ``functions`` / ``signatures``  number of cached functions (``*.nbi`` index files) and compiled
                       specialisations (``*.nbc`` data files) the run left in its fresh cache;
* ``load_before`` / ``load_after``  the 1-minute load average (``os.getloadavg``) around the run;
* the commit, ``NUMBA_NUM_THREADS`` and the machine's CPU count for the whole file.

Inputs: ``minegeo synth`` (small preset, seed 0, with the MAST scene) run first as the ``synth`` row
itself; the survey network and the pose graph from the shared data (``MINEGEO_SHARED_DATA`` or
``../shared/data``); the demo's frames and true trajectory for ``slam`` and ``evaluate``; a small
drift network and a drive through it (``tests/semantic/_netsim.py``, made with the normal cache before
the timed runs) for ``intersections build`` and ``track``.

Usage::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_first_use.py --label before    # ~15-30 min on 2 loaded cores
    python benchmarks/bench_first_use.py --verbs posegraph evaluate --label probe
    python benchmarks/bench_first_use.py --markdown benchmarks/results/first_use_A_before.json \
        benchmarks/results/first_use_B_after.json                            # the docs table

Writes ``benchmarks/results/first_use_<date>_<label>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VERBS = ("synth", "info", "adjust", "mast", "georef", "prepare-map", "localize", "localize-batch",
         "posegraph", "demo", "slam", "evaluate", "intersections build", "track", "warmup")


def _shared() -> Path:
    return Path(os.environ.get("MINEGEO_SHARED_DATA", ROOT.parent / "shared" / "data"))


def _commit() -> str:
    try:
        c = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "minegeo"], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip()
        return c + ("+dirty(minegeo/)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _commands(w: Path) -> dict[str, list[str]]:
    """The documented small example of each verb, with paths in the work folder ``w``."""
    mine = w / "mine"
    shared = _shared()
    net = shared / "krumm_gama_adjustment_examples" / "2D" / "Ghilani15_5_Angle_fix.dat"
    g2o = shared / "pose_graph_g2o" / "smallGrid3D.g2o"
    start = (w / "track_in" / "start.txt").read_text().split() if (w / "track_in" / "start.txt").is_file() else []
    return {
        "synth": ["synth", str(mine), "--preset", "small", "--seed", "0", "--mast"],
        "info": ["info", str(mine / "map.ply")],
        "adjust": ["adjust", str(net), "--out", str(w / "adjust")],
        "mast": ["mast", "--scan", str(mine / "mast" / "scan.csv"), "--beacons", str(mine / "mast" / "beacons.csv"),
                 "--out", str(w / "mast")],
        "georef": ["georef", "--map", str(mine / "map.ply"), "--gcps", str(mine / "gcps.csv"), "--crs", "EPSG:5186",
                   "--out", str(w / "map_geo.ply"), "--report", str(w / "georef")],
        "prepare-map": ["prepare-map", "--map", str(w / "map_geo.ply"), "--out", str(w / "map_geo.prepared.npz")],
        "localize": ["localize", "--map", str(w / "map_geo.prepared.npz"), "--scan",
                     str(mine / "scans" / "scan_00.ply"), "--trajectory", str(mine / "trajectories" / "scan_00.txt"),
                     "--out", str(w / "loc"), "--seed", "0"],
        "localize-batch": ["localize-batch", "--map", str(w / "map_geo.prepared.npz"), "--scans", str(mine / "scans"),
                           "--out", str(w / "batch"), "--workers", "2", "--seed", "0"],
        "posegraph": ["posegraph", str(g2o), "--out", str(w / "pg" / "o.g2o")],
        "demo": ["demo", "--out", str(w / "demo")],
        "slam": ["slam", "--frames", str(w / "demo" / "sequence" / "frames"), "--out", str(w / "slam"),
                 "--seed", "1"],
        "evaluate": ["evaluate", "--est", str(w / "slam" / "trajectory.tum"),
                     "--gt", str(w / "demo" / "sequence" / "truth.tum"), "--out", str(w / "eval")],
        "intersections build": ["intersections", "build", "--map", str(w / "track_in" / "map.ply"),
                                "--out", str(w / "kb.npz")],
        "track": ["track", "--frames", str(w / "track_in" / "frames"), "--db", str(w / "kb.npz"),
                  "--out", str(w / "track"), "--start", *start, "--truth", str(w / "track_in" / "truth.tum")],
        "warmup": ["warmup"],
    }


#: where each verb's own result.json is (relative to the work folder)
RESULT_JSON = {
    "adjust": "adjust/result.json", "mast": "mast/result.json", "georef": "georef/result.json",
    "localize": "loc/result.json", "localize-batch": "batch/result.json", "posegraph": "pg/o.g2o.report/result.json",
    "demo": "demo/result.json", "slam": "slam/result.json", "evaluate": "eval/result.json",
    "intersections build": "kb.npz.json", "track": "track/result.json", "synth": "mine/result.json",
}


def _make_track_inputs(w: Path) -> None:
    """A drift network map, a drive through its X crossing, the true trajectory and the start pose
    (the inputs of ``tests/semantic/test_semantic_cli.py``), made with the normal (warm) cache."""
    d = w / "track_in"
    if (d / "start.txt").is_file():
        return
    code = r"""
import sys, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(sys.argv[2]) / "tests" / "semantic"))
from _netsim import drive
from minegeo.io import PointCloud, write_point_cloud
from minegeo.synth.network import DriftNetwork, network_cloud
d = Path(sys.argv[1]); (d / "frames").mkdir(parents=True)
nodes = [(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)]
edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]
net = DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))
write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
frames, truth = drive(net, [(-14.0, 0.0), (10.0, 0.0)], step_m=1.2, seed=3)
for k, (_, P) in enumerate(frames):
    write_point_cloud(d / "frames" / f"{k:06d}.ply", PointCloud(points=P))
(d / "frames" / "times.txt").write_text("".join(f"{t:.6f}\n" for t, _ in frames))
from scipy.spatial.transform import Rotation
with open(d / "truth.tum", "w") as fh:
    for (t, _), T in zip(frames, truth):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        fh.write(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) + "\n")
T = truth[0]
yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
(d / "start.txt").write_text(" ".join(f"{v:.6f}" for v in (*T[:3, 3], yaw)))
"""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NUMBA_CACHE_DIR", None)
    subprocess.run([sys.executable, "-c", code, str(d), str(ROOT)], check=True, env=env)


def _run_one(verb: str, argv: list[str], w: Path, threads: str | None, timeout: float) -> dict:
    cache = Path(tempfile.mkdtemp(prefix="numba_cold_", dir=w))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT)}
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = threads
    load0 = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "minegeo", *argv], env=env, cwd=w, capture_output=True, text=True,
                           timeout=timeout)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as exc:
        rc, out, err = "timeout", str(exc.stdout or ""), str(exc.stderr or "")
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load1 = os.getloadavg()[0]
    nbi = sorted(cache.rglob("*.nbi"))
    nbc = sorted(cache.rglob("*.nbc"))
    rec = {"verb": verb, "argv": argv, "exit": rc, "wall_s": round(wall, 2),
           "cpu_s": round((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), 2),
           "functions": len(nbi), "signatures": len(nbc), "load_before": round(load0, 2),
           "load_after": round(load1, 2), "compile_s": None,
           "stderr_tail": err.strip().splitlines()[-6:], "stdout_tail": out.strip().splitlines()[-4:]}
    per_module: dict[str, int] = {}
    for f in nbc:
        mod = f.name.split(".")[0] if not f.parent.name else f"{f.parent.name}/{f.name.split('.')[0]}"
        per_module[mod] = per_module.get(mod, 0) + 1
    rec["signatures_per_file"] = dict(sorted(per_module.items(), key=lambda kv: -kv[1]))
    m = [ln for ln in err.splitlines() if "s of this run was one-time Numba compilation" in ln]
    if m:  # the CLI's own compile line (verbs without a result.json of their own)
        try:
            rec["compile_s_line"] = float(m[-1].split(": ", 1)[1].split(" s ", 1)[0])
        except (IndexError, ValueError):
            pass
    rj = RESULT_JSON.get(verb)
    if rj and (w / rj).is_file():
        try:
            t = json.loads((w / rj).read_text()).get("timings_s", {})
            if "compile_s" in t:
                rec["compile_s"] = round(float(t["compile_s"]), 2)
        except (OSError, ValueError, AttributeError):
            pass
    shutil.rmtree(cache, ignore_errors=True)
    return rec


def run(args) -> Path:
    w = Path(args.work).resolve() if args.work else Path(tempfile.mkdtemp(prefix="first_use_"))
    w.mkdir(parents=True, exist_ok=True)
    verbs = args.verbs or list(VERBS)
    if {"adjust", "posegraph"} & set(verbs) and not _shared().is_dir():
        raise SystemExit(f"bench_first_use: the shared data is not at {_shared()} (set MINEGEO_SHARED_DATA): "
                         "adjust and posegraph read their inputs from it")
    if "track" in verbs or "intersections build" in verbs:
        _make_track_inputs(w)
    threads = os.environ.get("NUMBA_NUM_THREADS")
    args.uptime_before = _uptime()
    rows = []
    for verb in verbs:
        argv = _commands(w)[verb]
        print(f"[{time.strftime('%H:%M:%S')}] {verb}: {' '.join(argv)}", file=sys.stderr, flush=True)
        rec = _run_one(verb, argv, w, threads, args.timeout)
        rows.append(rec)
        _write(args, threads, w, rows)  # after every verb: a stopped run keeps what it measured
        print(f"    exit {rec['exit']}  wall {rec['wall_s']} s  cpu {rec['cpu_s']} s  compile {rec['compile_s']} s  "
              f"{rec['functions']} functions / {rec['signatures']} signatures  load {rec['load_before']}->"
              f"{rec['load_after']}", file=sys.stderr, flush=True)
    return _write(args, threads, w, rows)


def _write(args, threads, w: Path, rows: list[dict]) -> Path:
    date = _dt.date.today().isoformat()
    doc = {"label": args.label, "date": date, "commit": getattr(args, "commit", None) or _commit(), "numba_num_threads": threads or "default",
           "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
           "numba": __import__("numba").__version__, "work": str(w), "rows": rows,
           "uptime_before": getattr(args, "uptime_before", None), "uptime_last": _uptime(),
           "conditions": "each verb in its own process with an empty NUMBA_CACHE_DIR; cpu_s = child user+sys "
                         "CPU (load-insensitive proxy of compile work); load = 1-min load average"}
    out = Path(args.out_dir) / f"first_use_{date}_{args.label}"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    out.with_suffix(".md").write_text(markdown([doc]) + "\n")
    return out


def _fmt(v, nd=1) -> str:
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def markdown(docs: list[dict]) -> str:
    """One table: a row per verb, for each results file its CPU s, wall s, compile s, signatures, load."""
    head = "| verb |" + "".join(f" {d['label']}: CPU s | wall s | compile s | kernels (fn/sig) | load |"
                                for d in docs)
    sep = "|---|" + "---:|---:|---:|---:|---|" * len(docs)
    lines = [" ; ".join(f"**{d['label']}**: commit {d['commit']}, {d['date']}, NUMBA_NUM_THREADS="
                        f"{d['numba_num_threads']}, {d['cpu_count']} CPUs, Numba {d['numba']}" for d in docs), "",
             head, sep]
    by = [{r["verb"]: r for r in d["rows"]} for d in docs]
    verbs = [v for v in VERBS if any(v in b for b in by)]
    for v in verbs:
        cells = []
        for b in by:
            r = b.get(v)
            if r is None:
                cells.append(" - | - | - | - | - |")
                continue
            bad = "" if r["exit"] in (0, 1) else f" (exit {r['exit']})"
            comp = r["compile_s"] if r.get("compile_s") is not None else r.get("compile_s_line")
            cells.append(f" {_fmt(r['cpu_s'])}{bad} | {_fmt(r['wall_s'])} | {_fmt(comp)} | "
                         f"{r['functions']}/{r['signatures']} | {r['load_before']:.1f}-{r['load_after']:.1f} |")
        lines.append(f"| `{v}` |" + "".join(cells))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--label", default="run")
    ap.add_argument("--work", default=None, help="work folder (default: a new temporary folder)")
    ap.add_argument("--verbs", nargs="+", default=None, choices=VERBS, metavar="VERB",
                    help=f"subset, in this order (default all: {', '.join(VERBS)})")
    ap.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--commit", default=None,
                    help="what code ran, when not the checkout's HEAD (e.g. a copy with a change)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per verb")
    ap.add_argument("--markdown", nargs="+", default=None, metavar="JSON",
                    help="print the table of these results files (before/after) and exit")
    args = ap.parse_args(argv)
    if args.markdown:
        print(markdown([json.loads(Path(p).read_text()) for p in args.markdown]))
        return 0
    np.seterr(all="ignore")
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
