"""Pose-graph benchmark: minegeo ``optimize_pose_graph`` vs GTSAM 4.3 Levenberg–Marquardt, side by side.

Cases
-----
* the standard files of ``shared/data/pose_graph_g2o``: parking-garage, sphere2500, torus3D, cubicle;
  both start from the file's vertices, the first pose held (minegeo: gauge; GTSAM: a prior of
  σ = 1e-9), cost ``F = ½ Σ rᵀΩr`` of slam_contract.md evaluated by each library on the
  between-edges. cubicle.g2o holds 5021 indefinite information matrices, which GTSAM cannot
  represent (``noiseModel.Gaussian.Information`` keeps the ``R`` of an LLᵀ factorisation that
  stops at the first non-positive pivot; ``RᵀR ≠ Ω``): both libraries are given GTSAM's ``RᵀR``,
  so both minimise the same cost (row ``cubicle (GTSAM's RᵀR)``).
* ``chain10k`` (``--synthetic``): a seeded synthetic SE(3) graph of 10,000 poses, ten laps of a
  rectangular 2 km mine circuit with a small grade, odometry edges (σ 0.1° / 0.2° yaw, 1 cm) and a
  loop edge every 10 poses to the pose one lap earlier (900 loops); start = odometry chained.

Settings
--------
GTSAM: ``LevenbergMarquardtParams`` defaults (λ₀ = 1e-5, factor 10, damping λI) with relative /
absolute error tolerances 1e-12 / 1e-14 and at most 500 iterations. minegeo:
``PoseGraphParams(max_iterations=500)`` (λ₀ = 1e-5, factor 10, damping λI, stop at a relative
decrease below 1e-10). The process is pinned to ``--threads`` cores (``os.sched_setaffinity``);
minegeo runs ``numba.set_num_threads(threads)`` (edge linearisation, residuals and retraction are
parallel; the block Cholesky is serial). The pip wheel of GTSAM 4.3 is built without TBB (no
``libtbb`` linked), so GTSAM runs on one thread whatever the setting; minegeo is also timed on one
thread for a like-for-like row. Times are medians of ``--repeats`` interleaved runs, the graph
already in memory (file reading excluded on both sides); minegeo's compile time is measured in a
fresh process with an empty ``NUMBA_CACHE_DIR`` (cold) and again with that cache filled.

Usage::

    python benchmarks/bench_posegraph.py --json OUT.json --md OUT.md [--threads 2] [--synthetic]
    python benchmarks/bench_posegraph.py --cli --threads 1 2 --json OUT.json --md OUT.md

``--cli``: what a user runs. For each standard file, as shipped and with no option, the whole
process ``minegeo posegraph FILE --out OUT`` (process time = user + system CPU of the child,
and wall time; optimiser time = ``timings_s.optimise`` of its result.json, wall), once per
``NUMBA_NUM_THREADS`` value; its exit status and status; the cost of the written graph evaluated
by GTSAM on the file's own factors (``readG2o``), against GTSAM's LM with its default parameters
(100 iterations, relative/absolute tolerance 1e-5) and run to convergence (1000 iterations,
1e-12 / 1e-14), both from the file's vertices with the first pose held by a σ = 1e-9 prior,
process time of ``optimize()`` (GTSAM's wheel is single-threaded). ``uptime`` load before and after.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's minegeo, not whatever copy is installed
SHARED = REPO.parent / "shared" / "data"
FILES = ("parking-garage.g2o", "sphere2500.g2o", "torus3D.g2o", "cubicle.g2o")
MAX_IT = 500

_COMPILE_SNIPPET = """
import time, numpy as np
t0 = time.perf_counter()
from minegeo.io.g2o import PoseGraph
from minegeo.slam.posegraph import optimize_pose_graph
t1 = time.perf_counter()
for kind, d in (("SE3", 4), ("SE2", 3)):
    n = 4
    poses = np.tile(np.eye(d), (n, 1, 1))
    for k in range(n):
        poses[k, 0, d - 1] = k
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    Z = np.stack([np.linalg.inv(poses[i]) @ poses[j] for i, j in edges])
    Z[:, 1, d - 1] += 0.01
    info = np.tile(np.eye(6 if d == 4 else 3), (4, 1, 1))
    optimize_pose_graph(PoseGraph(kind, np.arange(n), poses, edges, Z, info))
print(t1 - t0, time.perf_counter() - t1)
"""


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def compile_times(threads: int) -> dict:
    """Import and first-call time (s) of minegeo's pose-graph kernels: cold (empty cache), then cached."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "NUMBA_NUM_THREADS": str(threads),
               "PYTHONPATH": str(REPO)}
        for label in ("cold_empty_cache", "warm_cache"):
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", _COMPILE_SNIPPET], env=env, capture_output=True, text=True,
                                 check=True)
            imp, first = map(float, res.stdout.split())
            out[label] = {"import_s": imp, "first_calls_s": first, "process_s": time.perf_counter() - t0}
            _log(f"compile {label}: import {imp:.2f} s, first SE3+SE2 calls {first:.2f} s")
    return out


def gtsam_information(gtsam, graph):
    """The information matrices GTSAM uses (``RᵀR`` per factor), in the g2o file's (t, r) order."""
    R = np.stack([np.asarray(graph.at(k).noiseModel().R()) for k in range(graph.size())])
    p = np.argsort([3, 4, 5, 0, 1, 2])
    return np.einsum("eki,ekj->eij", R, R)[:, p][:, :, p]


def chain10k(seed: int = 0, laps: int = 10, per_lap: int = 1000):
    """The synthetic 10^4-pose SE(3) graph of the module docstring: (PoseGraph, truth poses)."""
    from minegeo.io.g2o import PoseGraph
    from minegeo.kernels.lie import se3_exp

    rng = np.random.default_rng(seed)
    side = per_lap // 4  # 2 m steps, 500 m sides
    truth = []
    for lap in range(laps):
        for k in range(per_lap):
            c, s = divmod(k, side)
            yaw = c * np.pi / 2
            corner = np.array([[0, 0], [500, 0], [500, 500], [0, 500]][c], float)
            xy = corner + 2.0 * s * np.array([np.cos(yaw), np.sin(yaw)])
            T = np.eye(4)
            T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
            T[:3, 3] = [xy[0], xy[1], 0.01 * s + 0.5 * lap]
            truth.append(T)
    truth = np.stack(truth)
    n = truth.shape[0]
    s_odo = np.r_[np.radians([0.1, 0.1, 0.2]), 0.01, 0.01, 0.01]
    s_loop = np.r_[np.radians([0.05] * 3), 0.02, 0.02, 0.02]
    pairs = [(k, k + 1) for k in range(n - 1)] + [(k, k + per_lap) for k in range(0, n - per_lap, 10)]
    Z, info = [], []
    for i, j in pairs:
        sig = s_odo if j == i + 1 else s_loop
        Z.append(np.linalg.inv(truth[i]) @ truth[j] @ se3_exp(rng.normal(size=6) * sig))
        info.append(np.diag(1.0 / np.r_[sig[3:], sig[:3]] ** 2))
    Z = np.stack(Z)
    poses = [truth[0]]
    for k in range(n - 1):
        poses.append(poses[-1] @ Z[k])
    g = PoseGraph("SE3", np.arange(n), np.stack(poses), np.asarray(pairs, dtype=np.int64), Z, np.stack(info))
    return g, truth


def to_gtsam(gtsam, g):
    """A GTSAM factor graph and initial values from an in-memory SE(3) PoseGraph (information as given)."""
    p = [3, 4, 5, 0, 1, 2]
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, T in enumerate(g.poses):
        initial.insert(k, gtsam.Pose3(T))
    for (i, j), Z, I in zip(g.edges.tolist(), g.measurements, g.information, strict=True):
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(Z), gtsam.noiseModel.Gaussian.Information(I[p][:, p])))
    return graph, initial


def run_gtsam(gtsam, graph, initial):
    between = gtsam.NonlinearFactorGraph(graph)
    full = gtsam.NonlinearFactorGraph(graph)
    key0 = min(initial.keys())
    full.add(gtsam.PriorFactorPose3(key0, initial.atPose3(key0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(MAX_IT)
    p.setRelativeErrorTol(1e-12)
    p.setAbsoluteErrorTol(1e-14)
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(full, initial, p)
    res = opt.optimize()
    dt = time.perf_counter() - t0
    return dt, {"cost_initial": between.error(initial), "cost_final": between.error(res),
                "iterations": int(opt.iterations()), "inner_iterations": None}


def run_minegeo(g, threads: int):
    import numba

    from minegeo.slam.posegraph import PoseGraphParams, optimize_pose_graph

    numba.set_num_threads(threads)
    t0 = time.perf_counter()
    r = optimize_pose_graph(g, PoseGraphParams(max_iterations=MAX_IT))
    dt = time.perf_counter() - t0
    return dt, {"cost_initial": r.cost_initial, "cost_final": r.cost_final, "iterations": r.iterations,
                "inner_iterations": len(r.history), "status": r.status}, r


def bench_case(name, g, gt_graph, gt_initial, threads, repeats, truth=None):
    import gtsam

    times = {"gtsam": [], "minegeo": [], "minegeo_1thread": []}
    out = {}
    for rep in range(repeats):
        dt, out["gtsam"] = run_gtsam(gtsam, gt_graph, gt_initial)
        times["gtsam"].append(dt)
        dt, out["minegeo"], res = run_minegeo(g, threads)
        times["minegeo"].append(dt)
        if threads > 1:
            dt, out["minegeo_1thread"], _ = run_minegeo(g, 1)
            times["minegeo_1thread"].append(dt)
        _log(f"{name} run {rep + 1}/{repeats}: gtsam {times['gtsam'][-1]:.2f} s, minegeo {times['minegeo'][-1]:.2f} s")
    med = {k: statistics.median(v) for k, v in times.items() if v}
    row = {"vertices": g.n_vertices, "edges": g.n_edges, "repeats": repeats, "median_s": med, "times_s": times, **out,
           "ratio_minegeo_over_gtsam": med["minegeo"] / med["gtsam"],
           "relative_cost_difference": (out["minegeo"]["cost_final"] - out["gtsam"]["cost_final"])
           / out["gtsam"]["cost_final"]}
    if "minegeo_1thread" in med:
        row["ratio_minegeo_1thread_over_gtsam"] = med["minegeo_1thread"] / med["gtsam"]
    if truth is not None:
        e = np.linalg.norm(res.graph.poses[:, :3, 3] - truth[:, :3, 3], axis=1)
        e0 = np.linalg.norm(g.poses[:, :3, 3] - truth[:, :3, 3], axis=1)
        row["position_rmse_m"] = {"start": float(np.sqrt(np.mean(e0**2))), "optimised": float(np.sqrt(np.mean(e**2)))}
    return row


def markdown(results: dict, meta: dict) -> str:
    c = meta["compile"]
    lines = [f"Pose-graph benchmark, {meta['date']}: minegeo vs GTSAM {meta['versions'].get('gtsam', '?')} LM, "
             f"same start, first pose held; {meta['threads']} core(s) (affinity), minegeo numba threads "
             f"{meta['threads']}, GTSAM single-threaded (wheel without TBB); medians of {meta['repeats']} "
             f"interleaved runs (torus3D and cubicle: {meta['slow_repeats']}); the machine was shared with other jobs (load average {meta['load_avg']}).", "",
             "| graph | poses / edges | F start | F GTSAM | F minegeo | rel. diff. | it. GTSAM | it. minegeo "
             "(trials) | GTSAM s | minegeo s | ratio | minegeo 1 thread s | ratio |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        gt, mg = r["gtsam"], r["minegeo"]
        one = r["median_s"].get("minegeo_1thread")
        lines.append(
            f"| {name} | {r['vertices']} / {r['edges']} | {gt['cost_initial']:.10g} | {gt['cost_final']:.10g} | "
            f"{mg['cost_final']:.10g} | {r['relative_cost_difference']:.1e} | {gt['iterations']} | "
            f"{mg['iterations']} ({mg['inner_iterations']}) | {r['median_s']['gtsam']:.2f} | "
            f"{r['median_s']['minegeo']:.2f} | {r['ratio_minegeo_over_gtsam']:.2f} | "
            + (f"{one:.2f} | {r['ratio_minegeo_1thread_over_gtsam']:.2f} |" if one is not None else "- | - |"))
    lines += ["", f"minegeo compile (fresh process, empty NUMBA_CACHE_DIR): import {c['cold_empty_cache']['import_s']:.2f} s"
              f" + first SE(3) and SE(2) calls {c['cold_empty_cache']['first_calls_s']:.2f} s; with the cache filled: "
              f"{c['warm_cache']['import_s']:.2f} s + {c['warm_cache']['first_calls_s']:.2f} s."]
    for name, r in results.items():
        if "position_rmse_m" in r:
            e = r["position_rmse_m"]
            lines.append(f"{name}: position RMSE to the truth {e['start']:.3f} m (odometry) -> {e['optimised']:.3f} m.")
    return "\n".join(lines)


def _gtsam_lm(gtsam, path: Path, iterations: int, rel_tol: float, abs_tol: float):
    graph, initial = gtsam.readG2o(str(path), True)
    between = gtsam.NonlinearFactorGraph(graph)
    key0 = min(initial.keys())
    graph.add(gtsam.PriorFactorPose3(key0, initial.atPose3(key0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(iterations)
    p.setRelativeErrorTol(rel_tol)
    p.setAbsoluteErrorTol(abs_tol)
    c0, w0 = time.process_time(), time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, p)
    res = opt.optimize()
    return {"cost": between.error(res), "cost_initial": between.error(initial), "iterations": int(opt.iterations()),
            "process_s": time.process_time() - c0, "wall_s": time.perf_counter() - w0}


def cli_rows(files, threads_list) -> dict:
    """The ``--cli`` measurements of the module docstring."""
    import json
    import resource

    import gtsam

    rows = {}
    for name in files:
        path = SHARED / "pose_graph_g2o" / name
        graph, _ = gtsam.readG2o(str(path), True)
        row = {"gtsam_default": _gtsam_lm(gtsam, path, 100, 1e-5, 1e-5),
               "gtsam_converged": _gtsam_lm(gtsam, path, 1000, 1e-12, 1e-14), "minegeo": {}}
        _log(f"{name}: GTSAM default {row['gtsam_default']}, converged {row['gtsam_converged']}")
        for t in threads_list:
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / "out.g2o"
                env = {**os.environ, "NUMBA_NUM_THREADS": str(t)}
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                w0 = time.perf_counter()
                proc = subprocess.run([sys.executable, "-m", "minegeo", "posegraph", str(path), "--out", str(out)],
                                      env=env, capture_output=True, text=True)
                wall = time.perf_counter() - w0
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                summary = json.loads((Path(tmp) / "out.g2o.report" / "result.json").read_text())
                _, values = gtsam.readG2o(str(out), True)
                f = graph.error(values)
            ref = row["gtsam_converged"]["cost"]
            row["minegeo"][str(t)] = {
                "exit": proc.returncode, "status": summary["status"], "reason": summary["reason"],
                "iterations": summary["result"]["iterations"],
                "information_changed": summary["result"].get("information_changed"),
                "cost_by_gtsam": f, "relative_to_gtsam_converged": (f - ref) / ref,
                "process_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
                "wall_s": wall, "optimise_s": summary["timings_s"].get("optimise")}
            _log(f"{name} threads {t}: {row['minegeo'][str(t)]}")
        rows[name] = row
    return rows


def cli_markdown(rows: dict, meta: dict) -> str:
    lines = [f"`minegeo posegraph FILE --out OUT` (files as shipped, no option) vs GTSAM {meta['gtsam']} LM, "
             f"{meta['date']}, commit {meta['commit']}; load (uptime) before: {meta['uptime_before']}; after: "
             f"{meta['uptime_after']}. 2-core machine shared with other jobs. Process = user + system CPU of the "
             "minegeo process (import, read, optimise, write, report); optimiser = wall time inside "
             "optimize_pose_graph; GTSAM = CPU of optimize() (single-threaded wheel). F by GTSAM = the written "
             "graph evaluated by GTSAM on the file's own factors; rel. = (F − F*) / F*, F* = GTSAM run to "
             "convergence.", "",
             "| graph | threads | exit | status | it. | F by GTSAM | rel. to F* | process s | optimiser s | "
             "GTSAM default: it., F, s | GTSAM converged: it., F*, s |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---|---|"]
    for name, r in rows.items():
        gd, gc = r["gtsam_default"], r["gtsam_converged"]
        for t, m in r["minegeo"].items():
            lines.append(f"| {name.removesuffix('.g2o')} | {t} | {m['exit']} | {m['status']} | {m['iterations']} | "
                         f"{m['cost_by_gtsam']:.10g} | {m['relative_to_gtsam_converged']:.1e} | {m['process_s']:.1f} | "
                         f"{m['optimise_s']:.1f} | {gd['iterations']}, {gd['cost']:.10g}, {gd['process_s']:.1f} | "
                         f"{gc['iterations']}, {gc['cost']:.10g}, {gc['process_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    ap.add_argument("--threads", type=int, nargs="+", default=[2])
    ap.add_argument("--cli", action="store_true", help="time the CLI process on the files as shipped (see docstring)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--slow-repeats", type=int, default=1, help="repeats for torus3D and cubicle (minutes each)")
    ap.add_argument("--files", nargs="*", default=list(FILES))
    ap.add_argument("--synthetic", action="store_true", help="also the 10^4-pose synthetic graph")
    a = ap.parse_args(argv)
    if a.cli:
        return _main_cli(a)
    a.threads = a.threads[0]
    os.environ.setdefault("NUMBA_NUM_THREADS", str(a.threads))
    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: a.threads])

    import gtsam

    from minegeo._provenance import atomic_write_text, to_jsonable, versions, write_json_atomic
    from minegeo.io.g2o import PoseGraph, non_psd_edges, read_g2o

    meta = {"date": time.strftime("%Y-%m-%d"), "threads": a.threads, "repeats": a.repeats,
            "slow_repeats": a.slow_repeats,
            "load_avg": ", ".join(f"{x:.1f}" for x in os.getloadavg()), "versions": versions()}
    meta["versions"]["gtsam"] = getattr(gtsam, "__version__", None) or _pkg_version("gtsam")
    meta["compile"] = compile_times(a.threads)
    run_minegeo(read_g2o(SHARED / "pose_graph_g2o" / "smallGrid3D.g2o"), a.threads)  # load the cache here
    results = {}
    for name in a.files:
        path = SHARED / "pose_graph_g2o" / name
        g = read_g2o(path)
        graph, initial = gtsam.readG2o(str(path), True)
        label = name.removesuffix(".g2o")
        if non_psd_edges(g).size:
            g = PoseGraph(g.kind, g.ids, g.poses, g.edges, g.measurements, gtsam_information(gtsam, graph), g.fixed)
            label += " (GTSAM's RᵀR)"
        reps = a.slow_repeats if name in ("torus3D.g2o", "cubicle.g2o") else a.repeats
        results[label] = bench_case(label, g, graph, initial, a.threads, reps)
    if a.synthetic:
        g, truth = chain10k()
        graph, initial = to_gtsam(gtsam, g)
        results["chain10k (synthetic)"] = bench_case("chain10k", g, graph, initial, a.threads, a.repeats, truth)
    meta["load_avg_end"] = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    md = markdown(results, meta)
    print(md)
    if a.json:
        write_json_atomic(a.json, to_jsonable({"meta": meta, "results": results}))
    if a.md:
        atomic_write_text(a.md, md + "\n")
    return 0


def _main_cli(a) -> int:
    from minegeo._provenance import atomic_write_text, to_jsonable, write_json_atomic

    up = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()  # noqa: E731
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "uptime_before": up(),
            "gtsam": _pkg_version("gtsam"), "threads": a.threads}
    rows = cli_rows(a.files, a.threads)
    meta["uptime_after"] = up()
    md = cli_markdown(rows, meta)
    print(md)
    if a.json:
        write_json_atomic(a.json, to_jsonable({"meta": meta, "results": rows}))
    if a.md:
        atomic_write_text(a.md, md + "\n")
    return 0


def _pkg_version(name: str):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001 - version lookup only
        return None


if __name__ == "__main__":
    raise SystemExit(main())
