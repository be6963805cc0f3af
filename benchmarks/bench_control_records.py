"""Calibration of the control adjustment's check-station ellipses on real SLAM errors of simulated streams.

``benchmarks/bench_control.py --odometry slam-model`` draws the odometry's errors from minegeo's own
noise model: it tests the adjustment's propagation, not the model. Here the errors are those of the
SLAM itself: the edge records of ``benchmarks/bench_edge_covariance.py`` (its ``--cache``; one
``minegeo slam --control`` odometry and loop closure per simulated 200 s, 10 Hz stop-and-go stream,
GICP's information, the measured edge ``Z``, the truth ``Z*`` and the keyframes' angular rates).
For each stream:

* the SLAM graph as ``minegeo slam --control`` builds it: every recorded edge (chain, extra, accepted
  loops) with its measurement and the floored information ``(Ω_G⁻¹ + F)⁻¹``
  (:func:`minegeo.slam.odometry.edge_covariance_floor` at the recorded length, angle and rates), the
  keyframes' pose noise :func:`minegeo.slam.odometry.keyframe_pose_noise` at their rates; the map
  optimised from the chained edges (:func:`minegeo.slam.posegraph.optimize_pose_graph`, keyframe 0 fixed);
* the truth: the keyframes' true poses chained from the records' ``Z*`` (keyframe 0 at the identity);
* station layouts on keyframes by distance along the true path: a control station every
  ``--control-spacing-m`` from ``--first-m`` (surveyed with σ_h 5 mm, σ_v 10 mm, seeded noise), a check
  station every ``--check-spacing-m`` between the first and the last control (not on a control), each on
  the nearest keyframe turning at most ``--max-rate-deg-s`` (a station is a stop, not a turn; here it
  is a moving keyframe, a harder case than a stop frame); one layout per start in ``--first-m`` (they
  share the stream's errors: not independent); the survey noise drawn per layout;
* :func:`minegeo.slam.control.apply_control` (graph mode, defaults) with the pose noise; at each check
  station the error against the truth, inside the 95 % horizontal ellipse (``eᵀC⁻¹e ≤ χ²₂``) and the
  95 % vertical interval (``e_v² ≤ χ²₁ σ_v²``).

The keyframe index stands for its time (the records keep no times; a station on a keyframe needs none,
and the drift states are off by default). The streams' own stops at their stations play no part.
Diagnostics: ``--drift-states``, ``--loop-inflation`` (every loop's covariance times a factor),
``--extra-sigma-xy-m`` (a station noise beyond the keyframe's own, carried by the control factors and
the stations, not the edges), ``--constants`` (another fit's constants).

Records missing from ``--cache`` are made as ``bench_edge_covariance.py`` makes them (about 4 min of
CPU per stream). Usage (1 thread; seconds per stream once the records exist)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_control_records.py --cache /tmp/edge_cov_cache \\
        --streams vehicle:3-12 --control-spacing-m 120 --check-spacing-m 20 --first-m 0 10 20 30 40 50 \\
        --out benchmarks/results/control_records_vehicle.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

from minegeo.io.g2o import PoseGraph
from minegeo.io.stations import Stations
from minegeo.kernels.lie import se3_exp
from minegeo.slam.control import ControlParams, apply_control
from minegeo.slam.odometry import OdometryParams, edge_covariance_floor, keyframe_pose_noise
from minegeo.slam.posegraph import optimize_pose_graph

CHI2_2_95 = 5.991464547107979
CHI2_1_95 = 3.841458820694124
ORIGIN = np.array([500000.0, 4000000.0, 100.0])
CRS = "EPSG:32633"


def largest_component(rec: dict) -> dict:
    """The records of the largest connected part of the graph, keyframes renumbered in order (an
    odometry edge without a measurement is not recorded: the handheld streams' graphs fall apart there)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    i, j = rec["i"].astype(np.int64), rec["j"].astype(np.int64)
    k = int(max(i.max(), j.max())) + 1
    _, lab = connected_components(coo_matrix((np.ones(i.size), (i, j)), shape=(k, k)), directed=False)
    big = np.bincount(lab).argmax()
    keep_kf = np.flatnonzero(lab == big)
    new = np.full(k, -1)
    new[keep_kf] = np.arange(keep_kf.size)
    keep = lab[i] == big
    out = {key: v[keep] for key, v in rec.items()}
    out["i"], out["j"] = new[i[keep]], new[j[keep]]
    return out


def stream_graph(rec: dict, params: OdometryParams, loop_inflation: float = 1.0):
    """``(truth, edges, Z, info, Q, rates)`` of one stream's records (module docstring; its largest connected part)."""
    rec = largest_component(rec)
    i, j, kind = rec["i"].astype(np.int64), rec["j"].astype(np.int64), rec["kind"]
    k = int(max(i.max(), j.max())) + 1
    Z = np.einsum("eab,ebc->eac", rec["z_true"], np.stack([se3_exp(e) for e in rec["err"]]))
    rates = np.zeros(k)
    rates[i], rates[j] = rec["rate_i"], rec["rate_j"]
    info = np.empty((i.size, 6, 6))
    for e in range(i.size):
        F = edge_covariance_floor(rec["length_m"][e], rec["angle_deg"][e], params,
                                  rates_deg_s=(rec["rate_i"][e], rec["rate_j"][e]), loop=bool(kind[e] == 2))
        C = (rec["cov"][e] + F) * (loop_inflation if kind[e] == 2 else 1.0)
        info[e] = np.linalg.inv(0.5 * (C + C.T))
    # truth: breadth first over the edges (any path gives the same poses: Z* is exact)
    truth = np.full((k, 4, 4), np.nan)
    truth[0] = np.eye(4)
    adj = [[] for _ in range(k)]
    for e in range(i.size):
        adj[i[e]].append((j[e], rec["z_true"][e]))
        adj[j[e]].append((i[e], np.linalg.inv(rec["z_true"][e])))
    todo = deque([0])
    while todo:
        a = todo.popleft()
        for b, Zab in adj[a]:
            if np.isnan(truth[b, 0, 0]):
                truth[b] = truth[a] @ Zab
                todo.append(b)
    if np.isnan(truth[:, 0, 0]).any():
        raise ValueError("the records' graph is not connected")
    return truth, np.c_[i, j], Z, info, keyframe_pose_noise(rates, params), rates


def slam_map(truth, edges, Z, info) -> np.ndarray:
    """The SLAM map: the graph optimised from the chained (spanning-tree) measurements, keyframe 0 fixed."""
    k = truth.shape[0]
    P0 = np.full((k, 4, 4), np.nan)
    P0[0] = np.eye(4)
    for _ in range(k):  # chain along edges whose start is known (the chain, gaps bridged by extra edges)
        for (a, b), Zab in zip(edges, Z, strict=True):
            if not np.isnan(P0[a, 0, 0]) and np.isnan(P0[b, 0, 0]):
                P0[b] = P0[a] @ Zab
        if not np.isnan(P0[:, 0, 0]).any():
            break
    p = [3, 4, 5, 0, 1, 2]  # (ω, ρ) → g2o's (t, r)
    g = PoseGraph("SE3", np.arange(k, dtype=np.int64), P0, edges.astype(np.int64), Z, info[:, p][:, :, p], fixed=(0,))
    return optimize_pose_graph(g).graph.poses


def layout(truth, first_m, control_m, check_m, rates_deg_s, max_rate_deg_s):
    """Keyframe indices of the control and check stations by true path distance: at each distance the
    nearest keyframe whose angular rate is at most ``max_rate_deg_s`` (a station is where the scanner
    stands still, not a turn)."""
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))]
    ok = np.flatnonzero(rates_deg_s <= max_rate_deg_s)

    def at(d):
        return int(ok[np.argmin(np.abs(s[ok] - d))])

    ctrl = sorted({at(d) for d in np.arange(first_m, s[-1] + 1e-9, control_m)})
    if len(ctrl) < 3:
        return ctrl, []
    chk = [at(d) for d in np.arange(s[ctrl[0]] + check_m, s[ctrl[-1]] - 1e-9, check_m)]
    chk = sorted(set(chk) - set(ctrl))
    return ctrl, chk


def run_layout(truth, edges, Z, info, Q, P, ctrl, chk, rng, pose_noise: bool, drift_states=False):
    """One control adjustment: errors, covariances and σ̂0 at the check stations."""
    idx = np.r_[ctrl, chk].astype(np.int64)
    order = np.argsort(idx)
    idx = idx[order]
    roles = np.array(["control"] * len(ctrl) + ["check"] * len(chk))[order]
    true_local = truth[idx, :3, 3]
    sig_h, sig_v = 0.005, 0.010
    noise = rng.standard_normal((idx.size, 3)) * [sig_h, sig_h, sig_v]
    surveyed = true_local + np.where((roles == "control")[:, None], noise, 0.0)
    t = np.arange(truth.shape[0], dtype=np.float64)
    st = Stations(ids=tuple(f"K{int(x):04d}" for x in idx), t_start_s=t[idx], t_end_s=t[idx],
                  enh_local=surveyed, origin_enh=ORIGIN, sigma_h_m=np.full(idx.size, sig_h),
                  sigma_v_m=np.full(idx.size, sig_v), roles=tuple(roles), crs=CRS)
    res = apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, ControlParams(mode="graph", drift_states=drift_states),
                        pose_noise=Q if pose_noise else None)
    m = roles == "check"
    e = res.station_enh_local[m] - true_local[m]
    C = res.station_cov_enh[m]
    dof = max(res.global_chi2.dof, 1)
    return e, C, float(np.sqrt(res.global_chi2.statistic / dof)), str(res.status)


def markdown(path) -> str:
    """The docs table of a results file (docs/survey.md, "Calibration of the ellipses")."""
    with open(path) as fh:
        d = json.load(fh)
    c = d["conditions"]
    lines = [f"<!-- generated by: python benchmarks/bench_control_records.py --markdown {path} -->",
             "| streams | station covariance | check points (layouts) | 95 % ellipse coverage (h) | 95 % coverage (v) "
             "| mean NEES h (2) / v (1) | check RMSE h / v (m) | mean σ̂0 |", "|---|---|---|---|---|---|---|---|"]
    names = {"pose_noise": "graph + keyframe pose noise (`minegeo slam --control`)",
             "edges_only": "graph, edges' information alone"}
    for key, r in d["summary"].items():
        preset, _, model = key.partition("_")
        lines.append(f"| {preset}, {r['streams']} × {c['duration_s']:g} s | {names[model]} | {r['check_points']} "
                     f"({r['layouts']}) | {100 * r['coverage_95_h']:.1f} % | {100 * r['coverage_95_v']:.1f} % | "
                     f"{r['mean_nees_h']:.2f} / {r['mean_nees_v']:.2f} | {r['rmse_h_m']:.3f} / {r['rmse_v_m']:.3f} | "
                     f"{r['mean_sigma0']:.2f} |")
    per = {}
    for row in d["rows"]:
        if row.get("pose_noise") and "nees_h" in row:
            per.setdefault((row["preset"], row["seed"]), []).extend(row["nees_h"])
    lines += ["", f"Stations: a control every {c['control_spacing_m']:g} m of path, a check every "
              f"{c['check_spacing_m']:g} m between, on keyframes turning at most {c['max_rate_deg_s']:g} deg/s; "
              f"layouts starting at {', '.join(f'{x:g}' for x in c['starts_m'])} m (they share a stream's errors); "
              f"drift states {c['drift_states']}; constants: {c['constants']}. Horizontal coverage per stream "
              "(graph + keyframe pose noise): " + ", ".join(
                  f"{p} {s} {100 * np.mean(np.asarray(q) <= CHI2_2_95):.0f} %" for (p, s), q in sorted(per.items())) + "."]
    return "\n".join(lines)


def parse_streams(specs):
    out = []
    for s in specs:
        preset, seeds = s.split(":")
        for part in seeds.split(","):
            a, _, b = part.partition("-")
            out += [(preset, n) for n in range(int(a), int(b or a) + 1)]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/edge_cov_cache", help="bench_edge_covariance.py's edge records (PRESET_SEED_200_10hz.npz)")
    ap.add_argument("--streams", nargs="+", default=["vehicle:1-12"], help="PRESET:SEEDS, e.g. vehicle:1-4,7")
    ap.add_argument("--duration-s", type=float, default=200.0)
    ap.add_argument("--control-spacing-m", type=float, default=250.0)
    ap.add_argument("--check-spacing-m", type=float, default=40.0)
    ap.add_argument("--first-m", type=float, nargs="+", default=[0.0, 20.0, 40.0, 60.0, 80.0], dest="starts")
    ap.add_argument("--max-rate-deg-s", type=float, default=3.0,
                    help="stations only on keyframes turning at most this fast (deg/s, the records' rates)")
    ap.add_argument("--drift-states", choices=("off", "on", "auto"), default="off",
                    help="ControlParams.drift_states of the adjustment (the keyframe index stands for seconds)")
    ap.add_argument("--constants", default=None,
                    help="a bench_edge_covariance.py results file: its fitted constants instead of OdometryParams()'s")
    ap.add_argument("--loop-inflation", type=float, default=1.0,
                    help="a diagnostic: every loop edge's covariance times this (1: as minegeo slam builds it)")
    ap.add_argument("--extra-sigma-xy-m", type=float, default=0.0,
                    help="a diagnostic: added (in quadrature) to every keyframe's pose noise along its sensor x and y "
                         "(the control factors and the stations carry it, the edges do not)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default=None)
    ap.add_argument("--markdown", default=None, help="print the docs table of this results file and exit")
    a = ap.parse_args(argv)
    if a.markdown:
        print(markdown(a.markdown))
        return None
    params = OdometryParams()
    if a.constants:  # the fitted constants of a bench_edge_covariance.py results file
        from dataclasses import replace

        with open(a.constants) as fh:
            params = replace(params, **json.load(fh)["fitted"])
    t0 = time.perf_counter()
    rows = []
    for preset, seed in parse_streams(a.streams):
        f = Path(a.cache) / f"{preset}_{seed}_{a.duration_s:g}_10hz.npz"
        if not f.exists():  # the records as bench_edge_covariance.py makes them (about 4 min of CPU per stream)
            sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
            import bench_edge_covariance as bec

            from minegeo.slam.odometry import run_odometry
            from minegeo.slam.pipeline import SlamParams, run_backend

            os.makedirs(a.cache, exist_ok=True)
            st, sweeps = bec.simulate(preset, seed, a.duration_s)
            res = run_backend(run_odometry(sweeps, bec.RAW), SlamParams(odometry=bec.RAW))
            np.savez(f, **bec.edge_records(res, st.curve.poses(st.frame_times)))
        truth, edges, Z, info, Q, rates = stream_graph(dict(np.load(f)), params, a.loop_inflation)
        Q = Q.copy()
        Q[:, 3, 3] += a.extra_sigma_xy_m**2  # a candidate term: station noise beyond the keyframe's own
        Q[:, 4, 4] += a.extra_sigma_xy_m**2
        P = slam_map(truth, edges, Z, info)
        for start in a.starts:
            ctrl, chk = layout(truth, start, a.control_spacing_m, a.check_spacing_m, rates, a.max_rate_deg_s)
            if len(ctrl) < 3 or not chk:
                continue
            for pn in (True, False):
                rng = np.random.default_rng([a.seed, seed, int(start)])
                try:
                    e, C, s0, status = run_layout(truth, edges, Z, info, Q, P, ctrl, chk, rng, pn,
                                                  {"off": False, "on": True, "auto": "auto"}[a.drift_states])
                except Exception as exc:  # a refused layout (collinear control): recorded, not counted
                    rows.append({"preset": preset, "seed": seed, "start_m": start, "pose_noise": pn,
                                 "refused": f"{type(exc).__name__}: {exc}"})
                    continue
                q_h = np.einsum("ni,nij,nj->n", e[:, :2], np.linalg.inv(C[:, :2, :2]), e[:, :2])
                q_v = e[:, 2] ** 2 / C[:, 2, 2]
                rows.append({"preset": preset, "seed": seed, "start_m": start, "pose_noise": pn,
                             "control": len(ctrl), "check": len(chk), "sigma0": s0, "status": status,
                             "nees_h": q_h.tolist(), "nees_v": q_v.tolist(),
                             "err_h_m": np.hypot(e[:, 0], e[:, 1]).tolist(), "err_v_m": e[:, 2].tolist()})
        r = [x for x in rows if x["preset"] == preset and x["seed"] == seed and x["pose_noise"] and "nees_h" in x]
        if r:
            qh = np.concatenate([x["nees_h"] for x in r])
            qv = np.concatenate([x["nees_v"] for x in r])
            print(f"{preset} {seed}: {len(r)} layouts, {qh.size} checks, inside h {np.mean(qh <= CHI2_2_95):.3f} "
                  f"v {np.mean(qv <= CHI2_1_95):.3f}, σ̂0 {np.mean([x['sigma0'] for x in r]):.2f}", flush=True)
    summary = {}
    for preset in sorted({x["preset"] for x in rows}):
        for pn in (True, False):
            r = [x for x in rows if x["preset"] == preset and x["pose_noise"] == pn and "nees_h" in x]
            if not r:
                continue
            qh = np.concatenate([x["nees_h"] for x in r])
            qv = np.concatenate([x["nees_v"] for x in r])
            # per stream, the first layout alone: independent errors
            first = [x for x in r if x["start_m"] == min(y["start_m"] for y in r if y["seed"] == x["seed"])]
            qh1 = np.concatenate([x["nees_h"] for x in first])
            qv1 = np.concatenate([x["nees_v"] for x in first])
            summary[f"{preset}_{'pose_noise' if pn else 'edges_only'}"] = {
                "streams": len({x["seed"] for x in r}), "layouts": len(r), "check_points": int(qh.size),
                "coverage_95_h": float(np.mean(qh <= CHI2_2_95)), "coverage_95_v": float(np.mean(qv <= CHI2_1_95)),
                "mean_nees_h": float(np.mean(qh)), "mean_nees_v": float(np.mean(qv)),
                "first_layout_check_points": int(qh1.size),
                "first_layout_coverage_95_h": float(np.mean(qh1 <= CHI2_2_95)),
                "first_layout_coverage_95_v": float(np.mean(qv1 <= CHI2_1_95)),
                "mean_sigma0": float(np.mean([x["sigma0"] for x in r])),
                "rmse_h_m": float(np.sqrt(np.mean(np.concatenate([x["err_h_m"] for x in r]) ** 2))),
                "rmse_v_m": float(np.sqrt(np.mean(np.concatenate([x["err_v_m"] for x in r]) ** 2))),
                "refused_layouts": sum(1 for x in rows if x["preset"] == preset and x["pose_noise"] == pn
                                       and "refused" in x)}
    res = {"commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                    cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip() or None,
           "date": datetime.date.today().isoformat(), "host": platform.node(), "python": sys.version.split()[0],
           "threads": os.environ.get("NUMBA_NUM_THREADS"), "load": os.getloadavg(),
           "conditions": {"streams": a.streams, "duration_s": a.duration_s, "control_spacing_m": a.control_spacing_m,
                          "check_spacing_m": a.check_spacing_m, "max_rate_deg_s": a.max_rate_deg_s,
                          "drift_states": a.drift_states, "loop_inflation": a.loop_inflation,
                          "extra_sigma_xy_m": a.extra_sigma_xy_m, "constants": a.constants or "OdometryParams() defaults",
                          "starts_m": a.starts, "seed": a.seed,
                          "station_sigma_h_m": 0.005, "station_sigma_v_m": 0.010},
           "summary": summary, "rows": rows, "seconds": time.perf_counter() - t0}
    print(json.dumps(summary, indent=1))
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(res, fh, indent=1)
    return res


if __name__ == "__main__":
    main()
