"""Control stations in the pose graph vs a rigid fit vs no control, on a drifting synthetic drive.

Truth: the motion of ``minegeo synth --stream vehicle`` (``simulate_stream``: junctions-free loop
network, stop-and-go stations every ``--station-spacing-m``, every ``--control-every``-th a control
station) and its stations (:func:`minegeo.synth.stream.stream_stations`: surveyed with σ_h = 5 mm,
σ_v = 10 mm, the truth without noise). No sweeps are made: the odometry of a keyframe graph
(keyframes every ``--keyframe-s`` s of the true motion) is the true relative motion perturbed
per edge by ``ξ = bias + noise`` on the right (``Z = Z_true Exp(ξ)``), no loop closures:

* bias (drift): scale ``--scale-bias`` of the travelled translation, a yaw rate ``--yaw-bias`` and
  a pitch rate ``--pitch-bias`` (rad per metre travelled); the same on every edge;
* noise: random walk, σ_rot = ``--sigma-rot`` rad/√m, σ = ``--sigma-trans`` m/√m across the
  edge's motion and ``--sigma-along`` m/√m along it (LiDAR odometry in a drift is weakest along
  its axis) per edge (floors 1e-6 rad, 1e-5 m: edges standing still), seeded. The information of every edge is the inverse of this noise
  covariance: the bias is *not* modelled (as a real odometry's is not).

Measured: check-station errors (truth, not the surveyed coordinates) for (i) no control: the
SLAM map placed in the CRS by the true pose at the first control station (one set-up with a perfect
backsight: the best a single station gives); (ii) the rigid fit of all control stations; (iii) control
in the graph. Calibration: ``--mc`` runs with noise only (no bias), new seeds: fraction of check
stations whose true horizontal error lies inside the 95 % ellipse (``eᵀ C⁻¹ e ≤ χ²₂(0.95)``), and
(``coverage_95_v``) whose vertical error lies inside ``±1.96 σ_v``; with ``--resurvey`` each run draws
the stations' survey noise again (else the stream's one survey serves every run).

``--odometry slam-model``: the errors of minegeo's own SLAM noise model instead (what ``minegeo slam
--control`` assumes; its constants fitted on real SLAM runs of the simulator by
``benchmarks/bench_edge_covariance.py``): keyframes every ``--keyframe-s`` s, an edge errs by its floor
``w ~ N(0, F)`` (:func:`minegeo.slam.odometry.edge_covariance_floor` at the edge's true length, angle and
the keyframes' true angular rates, plus 1e-6 rad and 1e-5 m standing for GICP's own covariance) accumulated along the chain, ``y_{k+1} = y_k Z*_k Exp(w_k)``, and
each keyframe by its own pose noise, ``x_k = y_k Exp(n_k)``, ``n_k ~ N(0, Q_k)``
(:func:`minegeo.slam.odometry.keyframe_pose_noise`); the edges are ``x_k⁻¹ x_{k+1}`` with information
``F⁻¹`` and :func:`apply_control` gets ``pose_noise = Q`` as from a SLAM run. The bias, where drawn, is
added to ``w`` (scale, yaw and pitch rates as above).

Run: ``NUMBA_NUM_THREADS=1 python benchmarks/bench_control.py --out benchmarks/results/control_<date>.json``.
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

import numpy as np

from minegeo.io.stations import Stations
from minegeo.kernels.lie import se3_exp, se3_inverse, so3_log
from minegeo.slam.control import (
    ControlParams,
    apply_control,
    drift_states_needed,
    drift_states_test,
    interpolate_poses,
    station_points,
)
from minegeo.slam.odometry import OdometryParams, edge_covariance_floor, keyframe_pose_noise
from minegeo.synth.stream import StreamParams, simulate_stream, stream_stations

CHI2_2_95 = 5.991464547107979
CHI2_1_95 = 3.841458820694124


def truth(duration_s: float, spacing_m: float, control_every: int, seed: int, keyframe_s: float,
          station_keyframes: bool = False):
    """True keyframe times/poses (``T_world_sensor``), stations, ``T_crs_world`` (with ``rates_deg_s``,
    the true angular rate at each keyframe over ±0.05 s, and ``loops``, :func:`loop_pairs`) and path
    length. ``station_keyframes``: a keyframe at each station's middle time too (``--odometry
    slam-model``: in a SLAM run the station's variable is its stop frame's pose, with a registration
    error of its own; one interpolated between keyframes would carry a mix of theirs)."""
    st = simulate_stream(StreamParams(preset="vehicle", duration_s=duration_s, station_spacing_m=spacing_m,
                                      control_every=control_every, seed=seed))
    stations, tr = stream_stations(st)
    t = np.arange(st.frame_times[0], st.frame_times[-1] + 1e-9, keyframe_s)
    if station_keyframes:  # a keyframe at each station's middle time (its own pose noise, as a SLAM run's stop frame)
        t = np.union1d(t[np.min(np.abs(t[:, None] - stations.t_mid_s[None, :]), axis=1) > 0.05], stations.t_mid_s)
    R, p = st.curve.rotation_position(t)
    T = np.tile(np.eye(4), (t.size, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, p
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    Ra, _ = st.curve.rotation_position(t - 0.05)
    Rb, _ = st.curve.rotation_position(t + 0.05)
    tr = dict(tr, rates_deg_s=np.degrees([np.linalg.norm(so3_log(np.ascontiguousarray(a.T @ b))) for a, b in zip(Ra, Rb, strict=True)]) / 0.1,
              loops=loop_pairs(T, t))
    return t, T, stations, tr, length


# the median GICP covariance of the simulator's vehicle SLAM edges (benchmarks/bench_edge_covariance.py's
# edge records, seeds 1-4: chain and loop edges alike), σ per axis (ω, ρ; rad, m); part of every edge's error
GICP_SIGMA = np.array([4.3e-4, 1.15e-4, 3.7e-5, 8.4e-4, 3.0e-4, 1.0e-3])


def loop_pairs(T_true, times_s, radius_m: float = 1.0, min_gap_s: float = 60.0) -> np.ndarray:
    """Loop edges ``(i, j)``, ``i < j``: for each keyframe ``j`` the nearest earlier keyframe within
    ``radius_m`` (true positions) at least ``min_gap_s`` before it (the 2 km SLAM run accepted a loop on
    1162 of its 1292 keyframes, median distance 0.13 m, gaps from 68 s)."""
    from scipy.spatial import cKDTree

    p = T_true[:, :3, 3]
    tree = cKDTree(p)
    out = []
    for j, near in enumerate(tree.query_ball_point(p, radius_m)):
        near = [i for i in near if times_s[j] - times_s[i] >= min_gap_s]
        if near:
            out.append((min(near, key=lambda i: float(np.sum((p[i] - p[j]) ** 2))), j))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def slam_model_odometry(T_true, times_s, rates_deg_s, rng, scale_bias, yaw_bias, pitch_bias, params: OdometryParams,
                        loops: np.ndarray):
    """Chain and loop edges with the errors of minegeo's SLAM noise model (module docstring, ``--odometry
    slam-model``): edges, measurements, information ``(G + F)⁻¹`` (``G`` = :data:`GICP_SIGMA`²) and the
    keyframes' pose noise ``Q``. A loop edge measures the true relative pose of its keyframes with its own
    error ``w ~ N(0, G + F_loop)`` and theirs: ``Exp(−n_i) T*_i⁻¹ T*_j Exp(n_j) Exp(w)``."""
    k = T_true.shape[0]
    G = GICP_SIGMA**2
    Q = keyframe_pose_noise(rates_deg_s, params)
    n = np.sqrt(np.einsum("kii->ki", Q)) * rng.standard_normal((k, 6))  # Q diagonal
    En = [se3_exp(n[i]) for i in range(k)]
    Y = np.empty((k, 4, 4))
    Y[0] = T_true[0]
    Z, info = [], []
    for e in range(k - 1):
        Zt = se3_inverse(T_true[e]) @ T_true[e + 1]
        d = float(np.linalg.norm(Zt[:3, 3]))
        ang = float(np.degrees(np.linalg.norm(so3_log(np.ascontiguousarray(Zt[:3, :3])))))
        var = np.diag(edge_covariance_floor(d, ang, params, rates_deg_s=(rates_deg_s[e], rates_deg_s[e + 1]))) + G
        w = np.r_[0.0, pitch_bias * d, yaw_bias * d, scale_bias * Zt[:3, 3]] + np.sqrt(var) * rng.standard_normal(6)
        Y[e + 1] = Y[e] @ Zt @ se3_exp(w)
        Z.append(se3_inverse(Y[e] @ En[e]) @ Y[e + 1] @ En[e + 1])
        info.append(np.diag(1.0 / var))
    for i, j in loops:
        Zt = se3_inverse(T_true[i]) @ T_true[j]
        var = np.diag(edge_covariance_floor(0.0, 0.0, params, rates_deg_s=(rates_deg_s[i], rates_deg_s[j]), loop=True)) + G
        Z.append(se3_inverse(En[i]) @ Zt @ En[j] @ se3_exp(np.sqrt(var) * rng.standard_normal(6)))
        info.append(np.diag(1.0 / var))
    edges = np.r_[np.c_[np.arange(k - 1), np.arange(1, k)], loops].astype(np.int64)
    return edges, np.stack(Z), np.stack(info), Q


def slam_map(edges, Z, info) -> np.ndarray:
    """The SLAM map of the graph: :func:`minegeo.slam.posegraph.optimize_pose_graph` from the chained
    odometry, the first keyframe fixed at the identity (as ``minegeo slam``'s back end)."""
    from minegeo.io.g2o import PoseGraph
    from minegeo.slam.posegraph import optimize_pose_graph

    k = int(edges.max()) + 1
    chain_edges = edges[:, 1] == edges[:, 0] + 1
    P0 = chain(Z[chain_edges][:k - 1], np.eye(4))
    p = [3, 4, 5, 0, 1, 2]
    g = PoseGraph("SE3", np.arange(k, dtype=np.int64), P0, edges, Z, info[:, p][:, :, p], fixed=(0,))
    return optimize_pose_graph(g).graph.poses


def odometry(T_true, rng, scale_bias, yaw_bias, pitch_bias, sigma_rot, sigma_trans, sigma_along):
    """Chain edges ``(i, i+1)``: measurements with bias and noise, information (rotation first)."""
    k = T_true.shape[0]
    edges = np.c_[np.arange(k - 1), np.arange(1, k)]
    Z = np.empty((k - 1, 4, 4))
    info = np.zeros((k - 1, 6, 6))
    for e in range(k - 1):
        Zt = se3_inverse(T_true[e]) @ T_true[e + 1]
        d = float(np.linalg.norm(Zt[:3, 3]))
        sr = max(sigma_rot * np.sqrt(d), 1e-6)
        sc, sa = max(sigma_trans * np.sqrt(d), 1e-5), max(sigma_along * np.sqrt(d), 1e-5)
        u = Zt[:3, 3] / d if d > 1e-9 else np.array([1.0, 0.0, 0.0])
        C = np.zeros((6, 6))
        C[:3, :3] = sr**2 * np.eye(3)
        C[3:, 3:] = sc**2 * np.eye(3) + (sa**2 - sc**2) * np.outer(u, u)
        xi = np.r_[0.0, pitch_bias * d, yaw_bias * d, scale_bias * Zt[:3, 3]] + np.linalg.cholesky(C) @ rng.standard_normal(6)
        Z[e] = Zt @ se3_exp(xi)
        info[e] = np.linalg.inv(C)
    return edges, Z, info


def chain(Z, T0):
    P = np.empty((Z.shape[0] + 1, 4, 4))
    P[0] = T0
    for e in range(Z.shape[0]):
        P[e + 1] = P[e] @ Z[e]
    return P


def resurveyed(stations: Stations, tr, rng) -> Stations:
    """The stations surveyed again: the truth plus a new draw of their survey noise (σ_h, σ_v of each
    station), so that a Monte Carlo run draws every random input, not the odometry alone (with one fixed
    survey, the runs' check errors share its datum error and the coverage is conditional on it)."""
    from dataclasses import replace

    sig = np.c_[stations.sigma_h_m, stations.sigma_h_m, stations.sigma_v_m]
    enh = tr["enh_true"] - stations.origin_enh + sig * rng.standard_normal(sig.shape)
    return replace(stations, enh_local=enh)


def run_once(t, T_true, stations: Stations, tr, rng, drift, offset, crs,
             modes=("rigid", "similarity", "graph", "graph_drift"), slam_model: OdometryParams | None = None,
             resurvey: bool = False):
    """The modes on one odometry draw; returns errors at the check stations (truth). ``similarity``
    is the 7-parameter fit after SLAM (``minegeo slam --control-mode similarity``: rigid mode, the
    similarity model). ``slam_model``: the odometry of :func:`slam_model_odometry` with these
    constants (``drift[:3]`` its bias), its pose noise passed to :func:`apply_control`. ``resurvey``:
    the stations' surveyed coordinates drawn again from ``rng`` (:func:`resurveyed`)."""
    if resurvey:
        stations = resurveyed(stations, tr, rng)
    if slam_model is None:
        edges, Z, info = odometry(T_true, rng, *drift)
        Q = None
    else:
        edges, Z, info, Q = slam_model_odometry(T_true, t, tr["rates_deg_s"], rng, *drift[:3], slam_model, tr["loops"])
    P = chain(Z, np.eye(4)) if slam_model is None else slam_map(edges, Z, info)  # SLAM map frame = first keyframe
    T_cw = np.array(tr["T_crs_world"])
    true_local = tr["enh_true"] - stations.origin_enh
    # check stations between two control stations in time (the acceptance's); the others extrapolate
    tc = stations.t_mid_s[stations.is_control]
    chk = stations.is_check & (stations.t_mid_s > tc.min()) & (stations.t_mid_s < tc.max())
    out = {"n_check_between": int(chk.sum()), "n_check_outside": int((stations.is_check & ~chk).sum())}
    # (i) no control: placed by the first control station only (its surveyed point and the true
    # heading at it: what a surveyor gets from one set-up and a backsight)
    c0 = int(np.flatnonzero(stations.is_control)[0])
    T_s = interpolate_poses(t, P, stations.t_mid_s[c0:c0 + 1])[0]
    T_s_true = T_cw @ interpolate_poses(t, T_true, stations.t_mid_s[c0:c0 + 1])[0]
    G = T_s_true @ se3_inverse(T_s)
    pts = station_points(G @ interpolate_poses(t, P, stations.t_mid_s), offset) - stations.origin_enh
    out["none"] = pts[chk] - true_local[chk]
    for mode in modes:
        cp = (ControlParams(mode="rigid", model="similarity") if mode == "similarity"
              else ControlParams(mode=mode[:5], drift_states=mode == "graph_drift"))
        res = apply_control(t, P, edges, Z, info, stations, offset, crs, cp, pose_noise=Q)
        out[mode] = res.station_enh_local[chk] - true_local[chk]
        out[mode + "_outside"] = (res.station_enh_local - true_local)[stations.is_check & ~chk]
        out[mode + "_objective"] = (float(res.objective), float(res.drift_parameters))
        if mode == "similarity":
            out["similarity_scale"] = (float(res.scale), float(res.scale_std))
        if mode == "graph_drift":
            out["graph_drift_status"] = res.status
            out["graph_drift_cov"] = res.station_cov_enh[chk]
            out["graph_drift_sigma0"] = float(np.sqrt(res.global_chi2.statistic / max(res.global_chi2.dof, 1)))
        if mode == "graph":
            out["graph_needs_drift"] = drift_states_needed(res.global_chi2)
            out["graph_status"] = res.status
            out["graph_cov"] = res.station_cov_enh[chk]
            out["sigma0"] = float(np.sqrt(res.global_chi2.statistic / max(res.global_chi2.dof, 1)))
            out["flagged"] = list(res.stats.flagged_ids)
            out["class_passed"] = int(res.classes.passed.sum())
            out["misclosure_N_min"] = float(np.min(res.misclosure_ratio))
            out["iterations"] = res.optimisation.iterations
    if "graph" in modes and "graph_drift" in modes:
        # ControlParams(drift_states="auto"): the likelihood-ratio test of C6 (drift_states_test) on the two
        # solutions, as apply_control makes it (tests/slam/test_control_auto_lr.py checks the two agree);
        # "graph_auto_chi2" is the earlier rule (the plain graph's own chi-square test, upper tail)
        lr = drift_states_test(out["graph_objective"][0], *out["graph_drift_objective"], ControlParams().drift_alpha)
        out["lr"] = lr
        for name, take in (("graph_auto", lr["chosen"]), ("graph_auto_chi2", out["graph_needs_drift"])):
            pick = "graph_drift" if take else "graph"
            out[name], out[name + "_outside"] = out[pick], out[pick + "_outside"]
            out[name + "_cov"], out[name + "_drift"] = out[pick + "_cov"], pick == "graph_drift"
    return out


def _inside(e, C):
    """Whether each horizontal error ``e[:, :2]`` lies in its 95 % ellipse of ``C[:, :2, :2]``."""
    e = e[:, :2]
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(C[:, :2, :2]), e) <= CHI2_2_95


def noise_ate(sigma_rot, sigma_trans, sigma_along, runs=200) -> dict:
    """What the odometry noise model means as the SLAM benchmarks state it: mean aligned ATE RMSE
    (SE(3) Kabsch of the chained odometry onto the truth, every keyframe) of this noise over ``runs``
    draws on (i) the 20 s vehicle stream of ``benchmarks/bench_deskew.py`` (seed 1, keyframes every
    1 s; deskewed SLAM: 0.029 m = 0.071 % of 41.2 m, docs/slam.md) and (ii) a 506 m straight with a
    frame every 1 m (the "straight" sequence of bench_slam.py; SLAM odometry: 0.122 m)."""
    from minegeo.registration.estimation import kabsch

    st = simulate_stream(StreamParams(preset="vehicle", duration_s=20.0, seed=1))
    t = np.arange(st.frame_times[0], st.frame_times[-1] + 1e-9, 1.0)
    R, p = st.curve.rotation_position(t)
    Tv = np.tile(np.eye(4), (t.size, 1, 1))
    Tv[:, :3, :3], Tv[:, :3, 3] = R, p
    Ts = np.tile(np.eye(4), (507, 1, 1))
    Ts[:, 0, 3] = np.arange(507.0)
    out = {}
    for name, T in (("vehicle_20s", Tv), ("straight_506m", Ts)):
        length = float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())
        ate = []
        for r in range(runs):
            _, Z, _ = odometry(T, np.random.default_rng(r), 0.0, 0.0, 0.0, sigma_rot, sigma_trans, sigma_along)
            P = chain(Z, T[0])
            A = kabsch(P[:, :3, 3], T[:, :3, 3], allow_degenerate=True)
            q = P[:, :3, 3] @ A[:3, :3].T + A[:3, 3]
            ate.append(float(np.sqrt(np.mean(np.sum((q - T[:, :3, 3]) ** 2, axis=1)))))
        out[name] = {"path_m": length, "mean_aligned_ate_m": float(np.mean(ate)),
                     "percent_of_path": 100.0 * float(np.mean(ate)) / length, "runs": runs}
    return out


def rmse(e):
    h = np.hypot(e[:, 0], e[:, 1])
    return float(np.sqrt(np.mean(h**2))), float(np.sqrt(np.mean(e[:, 2] ** 2)))


def markdown(path) -> str:
    """The docs table (docs/survey.md, "Control in the pose graph") from a results file."""
    with open(path) as f:
        d = json.load(f)
    c = d["conditions"]
    lines = [f"<!-- generated by: python benchmarks/bench_control.py --markdown {path} -->",
             "| odometry drift | mode | check RMSE h (m) | check RMSE v (m) | max h (m) | max v (m) |",
             "|---|---|---|---|---|---|"]
    names = {"none": "no control (placed by the first control station, true heading)",
             "rigid": "rigid fit of the control stations",
             "similarity": "similarity fit of the control stations (7 parameters, scale estimated)",
             "graph": "control in the pose graph",
             "graph_drift": "control in the pose graph + drift states (C4)",
             "graph_auto": "automatic: drift states by the likelihood-ratio test (C6)",
             "graph_auto_chi2": "earlier automatic rule: drift states when the plain graph's χ² fails"}
    if not c.get("auto_rule", "").startswith("likelihood ratio"):  # a file of the earlier rule: its own name
        names["graph_auto"] = "automatic: drift states when the graph's χ² fails (C6)"
    for cname, tab in d["table"].items():
        for m, r in tab.items():
            lines.append(f"| {cname.replace('_', ' ')} | {names[m]} | {r['rmse_h_m']:.3f} | {r['rmse_v_m']:.3f} | "
                         f"{r['max_h_m']:.3f} | {r['max_v_m']:.3f} |")
    lines.append("")
    lines.append(f"Drive {c['path_length_m']:.0f} m, {c['keyframes']} keyframes, {c['control']} control and "
                 f"{c['check']} check stations ({next(iter(d['graph'].values()))['n_check_between']} between two controls, "
                 f"in the table), seed {c['seed']}.")
    if "calibration" in d:
        cal = d["calibration"]
        lines[-1] += (f" 95 % ellipse coverage at the check stations over {cal['runs']} runs "
                      f"({cal['check_points']} points, noise only): {100 * cal['coverage_95']:.1f} % "
                      f"(binomial s.e. {100 * cal['binomial_se']:.1f} %); with the drift states "
                      f"{100 * cal.get('coverage_95_drift_states', float('nan')):.1f} %.")
    if d.get("monte_carlo"):
        vert = "coverage_95_v" in next(iter(d["monte_carlo"].values()))["graph"]
        lines += ["", "| Monte Carlo | mode | 95 % ellipse coverage |" + (" 95 % vertical coverage |" if vert else "")
                  + " check RMSE h (m) | check RMSE v (m) |", "|---|---|---|---|---|" + ("---|" if vert else "")]
        for cname, r in d["monte_carlo"].items():
            for m in ("graph", "graph_drift", "graph_auto", "graph_auto_chi2"):
                if m not in r:
                    continue
                lines.append(f"| {cname.replace('_', ' ')}, {r['runs']} runs ({r['check_points']} check points) | "
                             f"{names[m]} | {100 * r[m]['coverage_95']:.1f} % | "
                             + (f"{100 * r[m]['coverage_95_v']:.1f} % | " if vert else "")
                             + f"{r[m]['rmse_h_m']:.3f} | {r[m]['rmse_v_m']:.3f} |")
        lines.append("")
        lines.append("Binomial s.e. of a coverage: " + ", ".join(
            f"{cname.replace('_', ' ')} {100 * r['binomial_se']:.1f} %" for cname, r in d["monte_carlo"].items())
            + "; the automatic choice took the drift states in " + ", ".join(
            f"{r['auto_chose_drift_states']} of {r['runs']} runs ({cname.replace('_', ' ')})"
            for cname, r in d["monte_carlo"].items()) + "" + "".join(
            f"; the earlier χ² rule in {r['auto_chi2_chose_drift_states']} ({cname.replace('_', ' ')})"
            for cname, r in d["monte_carlo"].items() if "auto_chi2_chose_drift_states" in r) + ".")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=1100.0)
    ap.add_argument("--spacing-m", type=float, default=100.0)
    ap.add_argument("--control-every", type=int, default=5)
    ap.add_argument("--keyframe-s", type=float, default=1.0)
    ap.add_argument("--scale-bias", type=float, default=0.005)
    ap.add_argument("--yaw-bias", type=float, default=2e-5)
    ap.add_argument("--pitch-bias", type=float, default=1e-5)
    ap.add_argument("--sigma-rot", type=float, default=2e-5)
    ap.add_argument("--sigma-trans", type=float, default=0.002)
    ap.add_argument("--sigma-along", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--mc", type=int, default=200)
    ap.add_argument("--mc-duration-s", type=float, default=1100.0)
    ap.add_argument("--conditions", nargs="+", choices=("bias", "noise_only"), default=["bias", "noise_only"],
                    help="which odometry conditions to run (default both)")
    ap.add_argument("--odometry", choices=("random-walk", "slam-model"), default="random-walk",
                    help="the odometry errors: the random walk of --sigma-* (default) or minegeo's SLAM noise model "
                         "(edge floor + keyframe pose noise, OdometryParams() defaults; the --sigma-* unused)")
    ap.add_argument("--resurvey", action="store_true",
                    help="Monte Carlo: draw the stations' survey noise again in every run (else one fixed survey)")
    ap.add_argument("--label", default="", help="recorded in the results file (what this run is)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--markdown", default=None, help="print the docs table of this results file and exit")
    ap.add_argument("--noise-ate", action="store_true",
                    help="only the aligned ATE this odometry noise gives on the SLAM benchmarks' paths (to --out)")
    a = ap.parse_args(argv)
    if a.markdown:
        print(markdown(a.markdown))
        return None
    if a.noise_ate:
        res = {"label": a.label, "date": datetime.date.today().isoformat(), "sigma_rot_rad_per_sqrt_m": a.sigma_rot,
               "sigma_trans_m_per_sqrt_m": a.sigma_trans, "sigma_along_m_per_sqrt_m": a.sigma_along,
               "ate": noise_ate(a.sigma_rot, a.sigma_trans, a.sigma_along)}
        print(json.dumps(res, indent=1))
        if a.out:
            with open(a.out, "w") as f:
                json.dump(res, f, indent=1)
        return res
    t0 = time.perf_counter()
    slam_model = OdometryParams() if a.odometry == "slam-model" else None
    offset = np.zeros(3)
    t, T_true, stations, tr, length = truth(a.duration_s, a.spacing_m, a.control_every, a.seed, a.keyframe_s,
                                            slam_model is not None)
    drift = (a.scale_bias, a.yaw_bias, a.pitch_bias, a.sigma_rot, a.sigma_trans, a.sigma_along)
    tables, graph_info = {}, {}
    conds = {k: v for k, v in {"bias": drift, "noise_only": (0.0, 0.0, 0.0) + drift[3:]}.items() if k in a.conditions}
    print(f"drive {length:.0f} m, {len(stations)} stations ({int(stations.is_control.sum())} control), "
          f"{t.size} keyframes", flush=True)
    modes_tab = ("none", "rigid", "similarity", "graph", "graph_drift", "graph_auto")
    for cname, dr in conds.items():
        one = run_once(t, T_true, stations, tr, np.random.default_rng(a.seed), dr, offset, tr["crs"],
                       slam_model=slam_model)
        table = {}
        for m in modes_tab:
            h, v = rmse(one[m])
            table[m] = {"rmse_h_m": h, "rmse_v_m": v, "max_h_m": float(np.max(np.hypot(one[m][:, 0], one[m][:, 1]))),
                        "max_v_m": float(np.max(np.abs(one[m][:, 2])))}
            if m != "none" and one[m + "_outside"].shape[0]:
                table[m]["rmse_h_outside_m"], table[m]["rmse_v_outside_m"] = rmse(one[m + "_outside"])
            print(f"  {cname:10s} {m:11s} RMSE h {h:.4f} m  v {v:.4f} m", flush=True)
        tables[cname] = table
        graph_info[cname] = {k: one[k] for k in ("graph_status", "sigma0", "graph_drift_sigma0", "graph_drift_status",
                                                 "graph_auto_drift", "graph_auto_chi2_drift", "lr", "flagged", "class_passed",
                                                 "misclosure_N_min", "iterations", "n_check_between",
                                                 "n_check_outside", "similarity_scale")}
    # Monte Carlo: new odometry draws (seeds [seed, 1000 + r]) under each condition; the information is
    # the true noise (the bias, where drawn, is not in it)
    t_mc = time.perf_counter()
    if a.mc:
        tm, Tm, sm, trm, len_mc = truth(a.mc_duration_s, a.spacing_m, a.control_every, a.seed, a.keyframe_s,
                                        slam_model is not None)
    mc = {}
    for cname, dr in conds.items():
        m_modes = ("graph", "graph_drift", "graph_auto", "graph_auto_chi2")
        inside, sq, sqv, total, sig0, n_auto, n_auto_chi2 = dict.fromkeys(m_modes, 0), dict.fromkeys(m_modes, 0.0), \
            dict.fromkeys(m_modes, 0.0), 0, [], 0, 0
        inside_v = dict.fromkeys(m_modes, 0)
        lr_runs = []
        for r in range(a.mc):
            o = run_once(tm, Tm, sm, trm, np.random.default_rng([a.seed, 1000 + r]), dr, offset, trm["crs"],
                         modes=("graph", "graph_drift"), slam_model=slam_model, resurvey=a.resurvey)
            for m in m_modes:
                e = o[m][:, :2]
                C = o[m + "_cov"][:, :2, :2]
                inside[m] += int((np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e) <= CHI2_2_95).sum())
                inside_v[m] += int((o[m][:, 2] ** 2 <= CHI2_1_95 * o[m + "_cov"][:, 2, 2]).sum())
                sq[m] += float(np.sum(e**2))
                sqv[m] += float(np.sum(o[m][:, 2] ** 2))
            total += o["graph"].shape[0]
            n_auto += int(o["graph_auto_drift"])
            n_auto_chi2 += int(o["graph_auto_chi2_drift"])
            sig0.append(o["sigma0"])
            lr_runs.append({"statistic": o["lr"]["statistic"], "dof": o["lr"]["dof"], "chosen": o["lr"]["chosen"],
                            "inside_plain": int(np.sum(_inside(o["graph"], o["graph_cov"]))),
                            "inside_drift": int(np.sum(_inside(o["graph_drift"], o["graph_drift_cov"]))),
                            "n": int(o["graph"].shape[0])})
            if (r + 1) % 20 == 0:
                print(f"  mc {cname} {r + 1}/{a.mc}: coverage " + ", ".join(f"{m} {inside[m] / total:.4f}" for m in m_modes)
                      + f"; auto chose drift states in {n_auto}", flush=True)
        if total:
            mc[cname] = {"runs": a.mc, "check_points": total, "binomial_se": float(np.sqrt(0.95 * 0.05 / total)),
                         "auto_chose_drift_states": n_auto, "auto_chi2_chose_drift_states": n_auto_chi2,
                         "mean_sigma0_graph": float(np.mean(sig0)), "lr_per_run": lr_runs,
                         **{m: {"coverage_95": inside[m] / total, "coverage_95_v": inside_v[m] / total, "rmse_h_m": float(np.sqrt(sq[m] / total)),
                                "rmse_v_m": float(np.sqrt(sqv[m] / total))} for m in m_modes}}
    res = {
        "label": a.label,
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                 cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip() or None,
        "date": datetime.date.today().isoformat(), "host": platform.node(), "python": sys.version.split()[0],
        "threads": os.environ.get("NUMBA_NUM_THREADS"), "load": os.getloadavg(),
        "conditions": {"duration_s": a.duration_s, "path_length_m": length, "stations": len(stations),
                       "control": int(stations.is_control.sum()), "check": int(stations.is_check.sum()),
                       "spacing_m": a.spacing_m, "control_every": a.control_every, "keyframe_s": a.keyframe_s,
                       "keyframes": int(t.size), "scale_bias": a.scale_bias, "yaw_bias_rad_per_m": a.yaw_bias,
                       "pitch_bias_rad_per_m": a.pitch_bias, "sigma_rot_rad_per_sqrt_m": a.sigma_rot,
                       "sigma_trans_m_per_sqrt_m": a.sigma_trans, "sigma_along_m_per_sqrt_m": a.sigma_along, "seed": a.seed,
                       "station_sigma_h_m": float(stations.sigma_h_m[0]),
                       "station_sigma_v_m": float(stations.sigma_v_m[0]), "loop_closures": 0,
                       "drift_prior": list(ControlParams().drift_prior), "drift_walk_per_sqrt_s": list(ControlParams().drift_walk),
                       "auto_rule": "likelihood ratio (drift_states_test, C6): vTPv (every factor) without minus with the drift states against chi2_f(0.95), f = 3n - tr(H^-1 H_walk) - tr(H^-1 H_prior) the drift parameters the data determine; graph_auto_chi2: the earlier rule, the plain graph failing the upper tail of its 95 % two-tailed chi-square test (drift_states_needed)",
                       "mc_duration_s": a.mc_duration_s, "odometry": a.odometry, "resurvey": a.resurvey,
                       "odometry_constants": ({f: getattr(slam_model, f) for f in OdometryParams.__dataclass_fields__
                                               if f.startswith(("edge_sigma", "keyframe_sigma"))}
                                              if slam_model is not None else None)},
        "table": tables,
        "graph": graph_info,
        "monte_carlo": mc,
        "seconds": time.perf_counter() - t0, "mc_seconds": time.perf_counter() - t_mc,
    }
    print(json.dumps({k: res[k] for k in ("table", "monte_carlo")}, indent=1))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=1, default=float)
    return res


if __name__ == "__main__":
    main()
