"""Intersection factor graph (Liang et al. 2024 Sec. 3): minegeo ``FactorGraph.optimize`` vs GTSAM 4.3 LM.

Case: a seeded synthetic drift trajectory of ``n`` keyframes (1 m steps, gentle turns and grade),
odometry factors between consecutive keyframes (σ 0.002 rad, 0.02 m), ``n / 25`` intersections beside
the track, each observed (σ 0.1 m) from every keyframe within 6 m, and a weak prior on the first
keyframe; start = the noisy odometry chained (drifting). The same factors in GTSAM:
``BetweenFactorPose3``, ``PriorFactorPose3`` and a Python ``CustomFactor`` per intersection
observation (its error and Jacobian from ``Pose3.transformFrom``), every noise model
``noiseModel.Gaussian.Information(Ω)``. GTSAM's LM: defaults (λ₀ = 1e-5, ×10, damping λI), relative /
absolute error tolerances 1e-12 / 1e-14; minegeo: ``PoseGraphParams(max_iterations=200)`` (same
λ₀, factor and damping). The Python callback of the CustomFactor costs GTSAM time a C++ factor
would not; the ``gtsam_between_only`` column times GTSAM on the relative and prior factors alone
for scale. The process is pinned to ``--threads`` cores; minegeo runs ``numba.set_num_threads``;
the GTSAM wheel has no TBB (one thread). Times: medians of ``--repeats`` interleaved runs, graph
built beforehand, minegeo compiled beforehand.

Usage::

    python benchmarks/bench_semantic_factors.py --json OUT.json --md OUT.md [--threads 2] [--sizes 200 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def build(n: int, seed: int):
    """The synthetic graph (minegeo ``FactorGraph``) and its true poses."""
    from minegeo.geometry.se3 import invert, se3_exp
    from minegeo.semantic.factors import FactorGraph

    rng = np.random.default_rng(seed)
    truth = [np.eye(4)]
    for _ in range(n - 1):
        truth.append(truth[-1] @ se3_exp(np.r_[rng.normal(scale=0.01, size=2), rng.normal(scale=0.06), 1.0,
                                               rng.normal(scale=0.02, size=2)]))
    truth = np.stack(truth)
    s_rot, s_tr, s_int = 0.002, 0.02, 0.1
    info_rel = np.diag(np.r_[np.full(3, 1 / s_rot**2), np.full(3, 1 / s_tr**2)])
    g = FactorGraph()
    Zs = [invert(truth[k]) @ truth[k + 1] @ se3_exp(np.r_[rng.normal(scale=s_rot, size=3),
                                                          rng.normal(scale=s_tr, size=3)]) for k in range(n - 1)]
    T = truth[0]
    g.add_keyframe(T)
    for Z in Zs:
        T = T @ Z
        g.add_keyframe(T)
    for k, Z in enumerate(Zs):
        g.add_relative(k, k + 1, Z, info_rel)
    g.add_prior(0, truth[0], np.eye(6) * 1e2)
    n_int = max(3, n // 25)
    for c, k0 in enumerate(np.linspace(5, n - 6, n_int).astype(int)):
        C = truth[k0][:3, :3] @ np.array([0.0, 3.0 * (-1) ** c, 1.0]) + truth[k0][:3, 3]
        for k in np.flatnonzero(np.linalg.norm(truth[:, :3, 3] - C, axis=1) < 6.0):
            Ti = invert(truth[k])
            g.add_intersection(int(k), Ti[:3, :3] @ C + Ti[:3, 3] + rng.normal(scale=s_int, size=3), C,
                               np.eye(3) / s_int**2, intersection_id=c)
    return g, truth


def _gtsam_err(z, C, this, values, jacobians):
    T = values.atPose3(this.keys()[0])
    Hp, Hz = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
    p = T.transformFrom(z, Hp, Hz)
    if jacobians is not None:
        jacobians[0] = -Hp
    return C - p


def gtsam_problem(gtsam, g, with_intersections=True):
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, T in enumerate(g.poses):
        values.insert(k, gtsam.Pose3(T))
    for i, j, Z, W in g.relative_factors():
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(Z), gtsam.noiseModel.Gaussian.Information(W)))
    for i, T, W in g.prior_factors():
        graph.add(gtsam.PriorFactorPose3(i, gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Information(W)))
    if with_intersections:
        for i, z, C, W, _ in g.intersection_factors():
            graph.add(gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Information(W), [i],
                                         partial(_gtsam_err, z.copy(), C.copy())))
    return graph, values


def gtsam_solve(gtsam, graph, values):
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(200)
    p.setRelativeErrorTol(1e-12)
    p.setAbsoluteErrorTol(1e-14)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, p)
    out = opt.optimize()
    return out, opt.iterations()


def run_case(n: int, seed: int, repeats: int) -> dict:
    import copy

    import gtsam

    from minegeo.semantic.factors import PoseGraphParams

    g0, truth = build(n, seed)
    graph, values = gtsam_problem(gtsam, g0)
    between, values_b = gtsam_problem(gtsam, g0, with_intersections=False)
    t_mg, t_gt, t_gb = [], [], []
    for _ in range(repeats):
        g = copy.deepcopy(g0)
        t0 = time.perf_counter()
        res = g.optimize(PoseGraphParams(max_iterations=200))
        t_mg.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        out, it_gt = gtsam_solve(gtsam, graph, values)
        t_gt.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        gtsam_solve(gtsam, between, values_b)
        t_gb.append(time.perf_counter() - t0)
    ref = np.stack([out.atPose3(k).matrix() for k in range(n)])
    f_gt = graph.error(out)
    return {"keyframes": n, "relative_factors": len(g0.relative_factors()), "intersection_factors": len(g0.intersection_factors()),
            "intersections": int(len(set(g0.intersection_ids().tolist()))), "seed": seed,
            "cost_initial_minegeo": res.cost_initial, "cost_initial_gtsam": graph.error(values),
            "cost_final_minegeo": res.cost_final, "cost_final_gtsam": f_gt,
            "relative_cost_difference": abs(res.cost_final - f_gt) / f_gt,
            "max_pose_difference": float(np.abs(res.poses - ref).max()),
            "max_position_error_vs_truth_m": float(np.linalg.norm(res.poses[:, :3, 3] - truth[:, :3, 3], axis=1).max()),
            "iterations_minegeo": res.iterations, "iterations_gtsam": it_gt,
            "time_minegeo_s": statistics.median(t_mg), "time_gtsam_s": statistics.median(t_gt),
            "time_gtsam_between_only_s": statistics.median(t_gb)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", type=int, nargs="+", default=[200, 1000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=18)
    a = ap.parse_args(argv)
    os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[: a.threads]))
    import numba

    numba.set_num_threads(a.threads)
    build(20, 0)[0].optimize()  # compile
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    _log(f"uptime before: {load}")
    rows = []
    for n in a.sizes:
        rows.append(run_case(n, a.seed + n, a.repeats))
        _log(json.dumps(rows[-1]))
    load_after = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    import gtsam

    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "threads": a.threads, "repeats": a.repeats,
            "uptime_before": load, "uptime_after": load_after, "numpy": np.__version__,
            "numba": numba.__version__, "gtsam": getattr(gtsam, "__version__", "4.3")}
    a.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    md = ["# Intersection factor graph: minegeo vs GTSAM", "",
          f"{meta['date']}, {a.threads} thread(s), median of {a.repeats}; load before: `{load}`, after: `{load_after}`.",
          "", "| keyframes | rel. / int. factors (intersections) | F start | F final minegeo | F final GTSAM | "
          "rel. diff | max pose diff | it. minegeo / GTSAM | minegeo s | GTSAM s | GTSAM between-only s |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['keyframes']} | {r['relative_factors']} / {r['intersection_factors']} ({r['intersections']}) | "
                  f"{r['cost_initial_minegeo']:.6g} | {r['cost_final_minegeo']:.10g} | {r['cost_final_gtsam']:.10g} | "
                  f"{r['relative_cost_difference']:.1e} | {r['max_pose_difference']:.1e} | "
                  f"{r['iterations_minegeo']} / {r['iterations_gtsam']} | {r['time_minegeo_s']:.4f} | "
                  f"{r['time_gtsam_s']:.4f} | {r['time_gtsam_between_only_s']:.4f} |")
    a.md.write_text("\n".join(md) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
