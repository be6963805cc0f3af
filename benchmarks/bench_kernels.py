"""Search-kernel benchmark: pykdtree vs minegeo's KD-tree (:mod:`minegeo.kernels.kdtree`).

For clouds of 1e4, 1e5 and 1e6 points (a synthetic tunnel-like surface: points on a noisy
cylinder wall, 1 m spacing scale) and 1 and 2 threads (set explicitly: ``OMP_NUM_THREADS`` for
pykdtree, ``numba.set_num_threads`` for the Numba tree; each thread count runs in its own
subprocess), times: tree build, kNN with k = 1 and k = 30, gated 1-NN (the ICP query, gate
0.5 m) and a radius search (count of points within r, r chosen for ~30 neighbours; pykdtree
has no radius search, so its row is kNN k = 30 with ``distance_upper_bound = r``). Queries: the
first min(n, 1e5) cloud points, shifted by 1 cm. Median of 3 runs after one warm-up.

Writes ``benchmarks/results/kernels.json`` and ``benchmarks/results/kernels.md``.

Usage: ``python benchmarks/bench_kernels.py [--sizes 10000 100000 1000000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    length = n / 400.0  # ~400 points per metre of a 2.25 m radius tunnel
    s = rng.uniform(0.0, length, n)
    a = rng.uniform(0.0, 2 * np.pi, n)
    r = 2.25 + rng.normal(0.0, 0.01, n)
    return np.ascontiguousarray(np.c_[s, r * np.cos(a), r * np.sin(a)])


def _median_time(fn, repeat: int) -> float:
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _worker(sizes, repeat: int, threads: int) -> list[dict]:
    import numba
    from pykdtree.kdtree import KDTree

    from minegeo.kernels import kdtree as KD

    numba.set_num_threads(threads)
    rows = []
    for n in sizes:
        res, nq = _time_size(n, repeat, KDTree, KD)
        for lib, ops in res.items():
            for op, t in ops.items():
                rows.append({"n": n, "queries": nq, "threads": threads, "library": lib, "op": op, "seconds": t})
    return rows


def _time_size(n: int, repeat: int, KDTree, KD) -> tuple[dict, int]:
    """Median times (s) per library and operation for one cloud size, and the number of queries."""
    Q = _cloud(n)
    P = np.ascontiguousarray(Q[: min(n, 100_000)] + 0.01)
    density = n / (n / 400.0 * 2 * np.pi * 2.25)  # points per m² of wall
    r = float(np.sqrt(30.0 / (np.pi * density)))
    t_py = KDTree(Q)
    t_mg = KD.GatedKDTree(Q)
    tree = t_mg.packed
    res = {
        "pykdtree": {
            "build": _median_time(lambda: KDTree(Q), repeat),
            "knn1": _median_time(lambda: t_py.query(P, k=1), repeat),
            "knn30": _median_time(lambda: t_py.query(P, k=30), repeat),
            "gated1": _median_time(lambda: t_py.query(P, k=1, distance_upper_bound=0.5), repeat),
            "radius": _median_time(lambda: t_py.query(P, k=30, distance_upper_bound=r), repeat),
        },
        "minegeo": {
            "build": _median_time(lambda: KD.GatedKDTree(Q), repeat),
            "knn1": _median_time(lambda: KD.kd_knn(P, tree, 1), repeat),
            "knn30": _median_time(lambda: KD.kd_knn(P, tree, 30), repeat),
            "gated1": _median_time(lambda: t_mg.query(P, 0.25), repeat),
            "radius": _median_time(lambda: KD.kd_radius_count(P, tree, r), repeat),
        },
    }
    # the two trees must agree (exact searches): same nearest distances
    d_py, _ = t_py.query(P, k=30)
    _, sq = KD.kd_knn(P, tree, 30)
    assert np.allclose(np.sqrt(sq), d_py, rtol=1e-6, atol=1e-9)
    return res, int(P.shape[0])


def _markdown(rows: list[dict]) -> str:
    ops = ["build", "knn1", "knn30", "gated1", "radius"]
    lines = ["| n | threads | library | " + " | ".join(f"{o} (ms)" for o in ops) + " |",
             "|---|---|---|" + "---|" * len(ops)]
    keys = sorted({(r["n"], r["threads"], r["library"]) for r in rows})
    for n, th, lib in keys:
        t = {r["op"]: r["seconds"] for r in rows if (r["n"], r["threads"], r["library"]) == (n, th, lib)}
        lines.append(f"| {n:.0e} | {th} | {lib} | " + " | ".join(f"{1e3 * t[o]:.1f}" for o in ops) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--worker", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        json.dump(_worker(a.sizes, a.repeat, a.worker), sys.stdout)
        return
    rows = []
    for th in a.threads:
        env = {**os.environ, "OMP_NUM_THREADS": str(th), "NUMBA_NUM_THREADS": str(max(a.threads))}
        out = subprocess.run([sys.executable, __file__, "--worker", str(th), "--repeat", str(a.repeat),
                              "--sizes", *map(str, a.sizes)], env=env, check=True, capture_output=True, text=True)
        rows += json.loads(out.stdout)
    RESULTS.mkdir(exist_ok=True)
    meta = {"cpu_count": os.cpu_count(), "load_avg": os.getloadavg(), "repeat": a.repeat}
    (RESULTS / "kernels.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    md = _markdown(rows)
    (RESULTS / "kernels.md").write_text(md)
    sys.stdout.write(md)


if __name__ == "__main__":
    main()
