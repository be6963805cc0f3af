"""Calibration of the pose graph's edge covariance and of the keyframes' own pose noise on simulated 10 Hz streams.

For each simulated stop-and-go stream (``minegeo.synth.stream``: 10 Hz VLP-16 sweeps smeared by the
motion, 0.2° azimuth step, vehicle and handheld presets, several seeds) the SLAM runs as
``minegeo slam --control`` runs it (odometry to the local map, deskewed, loop closure) with the
floor constants at 0, so every edge carries GICP's own information ``Ω_G``. Each keyframe edge and
each accepted loop edge ``Z = T_i⁻¹ T_j`` is compared with the simulator's truth
``Z* = T*_i⁻¹ T*_j`` at the keyframes' frame times: ``e = Log(Z*⁻¹ Z)`` in (ω, ρ) order (the pose
graph's right perturbation).

The model (:func:`minegeo.slam.odometry.edge_covariance_floor`, :func:`~minegeo.slam.odometry.keyframe_pose_noise`):
each keyframe's estimated pose is ``x_k = y_k Exp(n_k)`` (``y`` the truth, ``n_k ~ N(0, Q_k)`` its own
error), so ``e = w + n_j − Ad(Z*⁻¹) n_i`` with ``w ~ N(0, Ω_G⁻¹ + F)`` the edge's accumulating error.
The errors of all the edges of a stream are jointly Gaussian, ``E ~ N(0, W + A Q Aᵀ)`` (``A`` the
``+I``/``−Ad`` blocks); the 22 constants (``EDGE_FLOOR_FIELDS`` and ``KEYFRAME_NOISE_FIELDS``) are
fitted jointly by maximum likelihood of that distribution (:func:`joint_neg_loglik`: matrix
determinant lemma and Woodbury identity, a sparse LU of ``I + S AᵀW⁻¹A S``, ``S = Q^½``) on the
``fit`` seeds and checked on the ``check`` seeds (never the same streams). Reported: the NEES
``eᵀ Σ⁻¹ e`` of single edges (their marginal ``Σ = Ω_G⁻¹ + F + Q_j + Ad Q_i Adᵀ``) and of windows
of ``m`` consecutive odometry edges composed (the drift a chain of ``m`` edges accumulates, what
the control adjustment weighs between two stations); calibrated, it averages 6 (χ²(6)), the rotation
block's and the translation block's 3 each, at every ``m``.

``--control-seeds`` also runs the control adjustment (``slam --control``, graph mode) on 60 s vehicle
streams with stations 6 m apart, with GICP's information alone and with the model: its global test
and the check stations' NEES against the truth.

Usage (1 thread; about 4 min of CPU per 200 s stream, the fit a few minutes)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_edge_covariance.py --out benchmarks/results/edge_covariance.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from minegeo.kernels.lie import se3_adjoint, se3_exp, se3_log
from minegeo.slam.odometry import (
    EDGE_FLOOR_FIELDS,
    KEYFRAME_NOISE_FIELDS,
    OdometryParams,
    keyframe_pose_noise,
    keyframe_rates_deg_s,
    run_odometry,
)
from minegeo.slam.pipeline import SlamParams, run_backend
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

NAMES = EDGE_FLOOR_FIELDS + KEYFRAME_NOISE_FIELDS
#: the odometry as ``minegeo slam --control`` runs a 10 Hz stream, with GICP's information alone
RAW = replace(OdometryParams(edge_covariance_floor=True, frame_target="submap"), **dict.fromkeys(NAMES, 0.0))
#: the constants of the edge-only model (fitted 2026-11-30, edge_covariance_2026-11-30.json): no keyframe noise
EDGE_ONLY = {"edge_sigma_tilt_deg_per_sqrt_m": 0.065, "edge_sigma_tilt_deg_per_deg": 0.027,
             "edge_sigma_yaw_deg_per_sqrt_m": 0.0, "edge_sigma_trans_xy_m_per_sqrt_m": 0.0017,
             "edge_sigma_trans_z_m_per_sqrt_m": 0.0058, "edge_sigma_trans_z_m_per_deg": 0.0025,
             "edge_sigma_tilt_deg_per_deg_s": 0.014, "edge_sigma_yaw_deg_per_deg_s": 0.008,
             "edge_sigma_trans_xy_m_per_deg_s": 0.00079, "edge_sigma_trans_z_m_per_deg_s": 0.00096,
             "loop_sigma_tilt_deg": 0.12, "loop_sigma_yaw_deg": 0.0, "loop_sigma_trans_xy_m": 0.0048,
             "loop_sigma_trans_z_m": 0.01, **dict.fromkeys(KEYFRAME_NOISE_FIELDS, 0.0)}
#: the window lengths (consecutive odometry edges) of the chain NEES
WINDOWS = (1, 3, 10, 30, 60)


def simulate(preset: str, seed: int, duration_s: float, spacing_m: float | None = 100.0, control_every: int = 5,
             offset=(0.0, 0.0, 0.0)):
    """``(stream, sweeps)`` of one stop-and-go stream at 10 Hz (the simulator's defaults)."""
    st = simulate_stream(StreamParams(preset=preset, duration_s=duration_s, seed=seed, station_spacing_m=spacing_m,
                                      control_every=control_every, station_offset_m=offset))
    sweeps = ((t, P, tau) for t, P, tau, _r in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, st.frame_times,
                                                           st.lidar_seed))
    return st, sweeps


def edge_records(res, truth: np.ndarray) -> dict:
    """Per edge of the SLAM graph (odometry chain, extra, accepted loops) with GICP's information:
    error ``e = Log(Z*⁻¹ Z)`` (ω, ρ), covariance ``Ω_G⁻¹``, true length (m) and angle (deg), the
    keyframes' angular rates (deg/s) and the kind (0 chain, 1 extra, 2 loop)."""
    odo = res.odometry
    kf = odo.keyframes
    rates = keyframe_rates_deg_s(odo.times_s, odo.poses, kf)
    edges = [(a, a + 1, odo.keyframe_edges[a], odo.keyframe_information[a], 0) for a in range(len(kf) - 1)]
    edges += [(i, j, Z, Om, 1) for i, j, Z, Om in odo.keyframe_extra_edges]
    edges += [(c.i, c.j, c.T_i_j, c.information, 2) for c in res.loops if c.accepted]
    rec = {k: [] for k in ("err", "cov", "length_m", "angle_deg", "rate_i", "rate_j", "kind", "i", "j", "z_true")}
    for i, j, Z, Om, kind in edges:
        if np.trace(Om) < 1e-3:  # the negligible information of a guessed chain edge: no measurement
            continue
        Zt = np.linalg.inv(truth[kf[i]]) @ truth[kf[j]]
        rec["err"].append(se3_log(np.ascontiguousarray(np.linalg.inv(Zt) @ Z)))
        rec["cov"].append(np.linalg.inv(Om))
        rec["length_m"].append(float(np.linalg.norm(Z[:3, 3])))
        rec["angle_deg"].append(float(np.degrees(np.linalg.norm(se3_log(np.ascontiguousarray(Z))[:3]))))
        rec["rate_i"].append(rates[i])
        rec["rate_j"].append(rates[j])
        rec["kind"].append(kind)
        rec["i"].append(i)
        rec["j"].append(j)
        rec["z_true"].append(Zt)
    return {k: np.asarray(v) for k, v in rec.items()}


def floors(rec: dict, x: dict) -> np.ndarray:
    """The floor ``F`` of every edge for the constants ``x`` (name → value), vectorised; the same
    formula as :func:`minegeo.slam.odometry.edge_covariance_floor` (checked in :func:`main`)."""
    g = x.get
    L, th, loop = rec["length_m"], rec["angle_deg"], rec["kind"] == 2
    W = rec["rate_i"] ** 2 + rec["rate_j"] ** 2
    t2 = np.where(loop, g("loop_sigma_tilt_deg") ** 2,
                  g("edge_sigma_tilt_deg_per_sqrt_m") ** 2 * L + (g("edge_sigma_tilt_deg_per_deg") * th) ** 2)
    z2 = np.where(loop, g("loop_sigma_yaw_deg") ** 2, g("edge_sigma_yaw_deg_per_sqrt_m") ** 2 * L)
    h2 = np.where(loop, g("loop_sigma_trans_xy_m") ** 2, g("edge_sigma_trans_xy_m_per_sqrt_m") ** 2 * L)
    v2 = np.where(loop, g("loop_sigma_trans_z_m") ** 2,
                  g("edge_sigma_trans_z_m_per_sqrt_m") ** 2 * L + (g("edge_sigma_trans_z_m_per_deg") * th) ** 2)
    d2r = math.radians(1.0) ** 2
    F = np.zeros((len(L), 6, 6))
    F[:, 0, 0] = F[:, 1, 1] = d2r * (t2 + g("edge_sigma_tilt_deg_per_deg_s") ** 2 * W)
    F[:, 2, 2] = d2r * (z2 + g("edge_sigma_yaw_deg_per_deg_s") ** 2 * W)
    F[:, 3, 3] = F[:, 4, 4] = h2 + g("edge_sigma_trans_xy_m_per_deg_s") ** 2 * W
    F[:, 5, 5] = v2 + g("edge_sigma_trans_z_m_per_deg_s") ** 2 * W
    return F


def nees(err: np.ndarray, cov: np.ndarray) -> dict:
    """Full, rotation and translation NEES of errors (n, 6) under covariances (n, 6, 6), and the mean
    ``e²/σ²`` per axis (ω_x, ω_y, ω_z, ρ_x, ρ_y, ρ_z)."""
    full = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    rot = np.einsum("ni,ni->n", err[:, :3], np.linalg.solve(cov[:, :3, :3], err[:, :3, None])[..., 0])
    tra = np.einsum("ni,ni->n", err[:, 3:], np.linalg.solve(cov[:, 3:, 3:], err[:, 3:, None])[..., 0])
    return {"full": full, "rot": rot, "trans": tra, "axes": (err**2 / np.diagonal(cov, axis1=1, axis2=2)).mean(0)}


def summary(n: dict) -> dict:
    out = {"edges": int(len(n["full"]))}
    for k in ("full", "rot", "trans"):
        v = n[k]
        m = float(np.mean(v))
        se = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan")
        out[k] = {"mean": round(m, 3), "mean_95ci": [round(m - 1.96 * se, 3), round(m + 1.96 * se, 3)],
                  "median": round(float(np.median(v)), 3)}
    out["axes_mean_e2_over_s2"] = [round(float(a), 3) for a in n["axes"]]
    return out


def keyframe_noise(rates: np.ndarray, x: dict) -> np.ndarray:
    """The diagonal (k, 6) of each keyframe's own noise ``Q`` for the constants ``x``, vectorised; the
    same formula as :func:`minegeo.slam.odometry.keyframe_pose_noise` (checked in :func:`main`)."""
    g = x.get
    d2r, w2 = math.radians(1.0) ** 2, rates**2
    t = d2r * (g("keyframe_sigma_tilt_deg") ** 2 + g("keyframe_sigma_tilt_deg_per_deg_s") ** 2 * w2)
    z = d2r * (g("keyframe_sigma_yaw_deg") ** 2 + g("keyframe_sigma_yaw_deg_per_deg_s") ** 2 * w2)
    h = g("keyframe_sigma_trans_xy_m") ** 2 + g("keyframe_sigma_trans_xy_m_per_deg_s") ** 2 * w2
    v = g("keyframe_sigma_trans_z_m") ** 2 + g("keyframe_sigma_trans_z_m_per_deg_s") ** 2 * w2
    return np.stack([t, t, z, h, h, v], 1)


def prepare(rec: dict) -> dict:
    """A stream's records with the keyframes' rates (k,) and each edge's ``Ad(Z*⁻¹)``."""
    k = int(max(rec["i"].max(), rec["j"].max())) + 1
    rates = np.zeros(k)
    rates[rec["i"]], rates[rec["j"]] = rec["rate_i"], rec["rate_j"]
    ad = np.stack([se3_adjoint(np.ascontiguousarray(np.linalg.inv(Z))) for Z in rec["z_true"]])
    return {"rec": rec, "k": k, "rates": rates, "ad": ad}


def joint_neg_loglik(s: dict, x: dict) -> float:
    """``−log p(E)`` (without the constant) of a stream's edge errors ``E ~ N(0, W + A Q Aᵀ)``:
    ``log det(W + AQAᵀ) = log det W + log det M`` and ``Eᵀ(W + AQAᵀ)⁻¹E = EᵀW⁻¹E − bᵀ M⁻¹ b`` with
    ``M = I + S H S``, ``H = AᵀW⁻¹A``, ``b = S AᵀW⁻¹E``, ``S = Q^½`` (``Q`` may be singular)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    rec, k, i, j, ad = s["rec"], s["k"], s["rec"]["i"], s["rec"]["j"], s["ad"]
    C = rec["cov"] + floors(rec, x)
    Ci = np.linalg.inv(C)
    _, logdet = np.linalg.slogdet(C)
    Cie = np.einsum("nab,nb->na", Ci, rec["err"])
    adT_ci = np.einsum("nba,nbc->nac", ad, Ci)
    blocks = [(j, j, Ci), (i, i, adT_ci @ ad), (i, j, -adT_ci), (j, i, -Ci @ ad)]
    r6 = np.arange(6)
    rows = np.concatenate([(6 * a[:, None, None] + r6[None, :, None]).repeat(6, 2).reshape(-1) for a, _, _ in blocks])
    cols = np.concatenate([(6 * c[:, None, None] + r6[None, None, :]).repeat(6, 1).reshape(-1) for _, c, _ in blocks])
    S = np.sqrt(keyframe_noise(s["rates"], x)).reshape(-1)
    vals = np.concatenate([B.reshape(-1) for _, _, B in blocks]) * S[rows] * S[cols]
    M = sp.coo_matrix((vals, (rows, cols)), shape=(6 * k, 6 * k)).tocsc() + sp.identity(6 * k, format="csc")
    b = np.zeros((k, 6))
    np.add.at(b, j, Cie)
    np.add.at(b, i, -np.einsum("nba,nb->na", ad, Cie))
    b = S * b.reshape(-1)
    lu = spla.splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return 0.5 * (float(logdet.sum()) + float(np.log(np.abs(lu.U.diagonal())).sum())
                  + float(np.einsum("na,na->", rec["err"], Cie)) - float(b @ lu.solve(b)))


#: the start of the fit: the edge-only constants (``EDGE_ONLY``), a keyframe noise of 0.03° tilt, 0.01° yaw,
#: 3 mm, 0.01°, 0.001° and 3 mm per deg/s (a constant at 0 starts at 1e-5: the fit runs on logarithms)
START = {**{k: max(v, 1e-5) for k, v in EDGE_ONLY.items()}, **dict.fromkeys(KEYFRAME_NOISE_FIELDS, 0.003),
         "keyframe_sigma_tilt_deg": 0.03, "keyframe_sigma_yaw_deg": 0.01, "keyframe_sigma_tilt_deg_per_deg_s": 0.01,
         "keyframe_sigma_yaw_deg_per_deg_s": 0.001}


def fit(streams: list) -> dict:
    """Maximum-likelihood constants (:func:`joint_neg_loglik` summed over the streams): L-BFGS-B then
    Powell on their logarithms (bounded to [e⁻¹⁴, e²]), from a fixed start (the constants of the
    edge-only fit, a small keyframe noise)."""
    from scipy.optimize import minimize

    def f(y):
        x = dict(zip(NAMES, np.exp(y), strict=True))
        return sum(joint_neg_loglik(s, x) for s in streams)

    bounds = [(-14.0, 2.0)] * len(NAMES)
    y = minimize(f, np.log([START[k] for k in NAMES]), method="L-BFGS-B", bounds=bounds,
                 options={"maxiter": 300, "eps": 1e-4}).x
    y = minimize(f, y, method="Powell", bounds=bounds, options={"xtol": 1e-3, "ftol": 1e-8, "maxiter": 20000}).x
    # two significant digits; a constant the fit drives below 1e-5 is 0
    return {k: 0.0 if v < 1e-5 else float(f"{v:.2g}") for k, v in zip(NAMES, np.exp(y), strict=True)}


def concat(recs: list) -> dict:
    return {k: np.concatenate([r[k] for r in recs]) for k in recs[0]}


def by_kind(streams: list, x: dict | None) -> dict:
    """NEES summaries of the single odometry edges and loop edges (their marginal covariance, the
    keyframes' noise included) under the constants ``x`` (None: GICP alone)."""
    out = {}
    for name, kind in (("odometry", lambda k: k < 2), ("loops", lambda k: k == 2)):
        err, cov = [], []
        for s in streams:
            rec = s["rec"]
            sel = kind(rec["kind"])
            c = rec["cov"][sel]
            if x is not None:
                q = keyframe_noise(s["rates"], x)
                ad = s["ad"][sel]
                Qi, Qj = (np.einsum("na,ab->nab", q[rec[end][sel]], np.eye(6)) for end in ("i", "j"))
                c = c + floors({k: v[sel] for k, v in rec.items()}, x) + Qj + ad @ Qi @ np.swapaxes(ad, 1, 2)
            err.append(rec["err"][sel])
            cov.append(c)
        if sum(len(e) for e in err):
            out[name] = summary(nees(np.concatenate(err), np.concatenate(cov)))
    return out


def window_nees(streams: list, x: dict | None, m: int) -> dict:
    """NEES of ``m`` consecutive odometry edges composed: ``e = Log(Z*_w⁻¹ Z_w)`` of ``Z_w = Z_1 ⋯ Z_m``
    against ``Σ_w = Σ_e Ad(R_e⁻¹)(Ω_G⁻¹ + F)_e Ad(R_e⁻¹)ᵀ + Q_end + Ad(Z*_w⁻¹) Q_start Ad(Z*_w⁻¹)ᵀ``
    (``R_e`` the true motion after edge ``e``; the keyframes inside the window cancel)."""
    err, cov = [], []
    for s in streams:
        rec = s["rec"]
        ch = np.flatnonzero(rec["kind"] == 0)
        ch = ch[np.argsort(rec["i"][ch], kind="stable")]
        i = rec["i"][ch]
        F = rec["cov"][ch] + (floors({k: v[ch] for k, v in rec.items()}, x) if x is not None else 0.0)
        q = keyframe_noise(s["rates"], x) if x is not None else np.zeros((s["k"], 6))
        Zt = rec["z_true"][ch]
        Z = np.stack([Zt[n] @ se3_exp(np.ascontiguousarray(rec["err"][ch][n])) for n in range(ch.size)])
        for a in range(ch.size - m + 1):
            if not np.array_equal(i[a:a + m], np.arange(i[a], i[a] + m)):
                continue
            Zw, Ztw, R = np.eye(4), np.eye(4), np.eye(4)
            S = np.diag(q[i[a] + m])
            for n in range(a + m - 1, a - 1, -1):
                A = se3_adjoint(np.ascontiguousarray(np.linalg.inv(R)))
                S = S + A @ F[n] @ A.T
                R = Zt[n] @ R
            for n in range(a, a + m):
                Zw, Ztw = Zw @ Z[n], Ztw @ Zt[n]
            A = se3_adjoint(np.ascontiguousarray(np.linalg.inv(R)))
            err.append(se3_log(np.ascontiguousarray(np.linalg.inv(Ztw) @ Zw)))
            cov.append(S + A @ np.diag(q[i[a]]) @ A.T)
    return summary(nees(np.asarray(err), np.asarray(cov))) if err else {"edges": 0}


def control_run(seed: int, duration_s: float, configs: dict) -> dict:
    """One 10 Hz stop-and-go vehicle stream with stations (6 m apart, every second a control, offset
    0 0 -0.6): the control adjustment in the graph (``slam --control``) per floor configuration: the
    global test statistic ``vᵀPv`` and its redundancy, and the check stations' 3D NEES ``dᵀ Σ⁻¹ d`` (d
    the error against the simulator's true station, Σ the adjustment's covariance)."""
    from minegeo.errors import MinegeoError
    from minegeo.slam.control import ControlParams, apply_control, graph_inputs, slam_pose_noise
    from minegeo.synth.stream import stream_stations

    off = (0.0, 0.0, -0.6)
    st, sweeps = simulate("vehicle", seed, duration_s, spacing_m=6.0, control_every=2, offset=off)
    stations, truth = stream_stations(st)
    odo = run_odometry(sweeps, RAW)
    out = {"stations": len(stations.ids), "control": int(stations.is_control.sum())}
    enh_true_local = truth["enh_true"] - stations.origin_enh
    for name, p in configs.items():
        res = run_backend(odo, SlamParams(odometry=p))  # the back end floors the edges by p
        kt, kP, edges, Z, info = graph_inputs(res, stations.t_mid_s)
        try:
            c = apply_control(kt, kP, edges, Z, info, stations, np.array(off), stations.crs,
                              ControlParams(mode="graph"), slam_pose_noise(res, kt))
        except MinegeoError as exc:  # recorded, not hidden (e.g. the initial rigid fit of collinear stations)
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        chk = np.flatnonzero(stations.is_check)
        nees_chk = []
        if c.station_cov_enh is not None and c.check is not None:
            for n, k in enumerate(chk):  # estimated − true = (estimated − surveyed) + (surveyed − true)
                d = np.asarray(c.check.delta[n]) + stations.enh_local[k] - enh_true_local[k]
                nees_chk.append(float(d @ np.linalg.solve(np.asarray(c.station_cov_enh[k]), d)))
        out[name] = {"statistic": float(c.global_chi2.statistic), "dof": int(c.global_chi2.dof),
                     "passed": c.global_chi2.passed, "flagged": list(c.stats.flagged_ids) if c.stats else [],
                     "check_nees3": nees_chk}
    return out


def _check_formula(streams: list, x: dict) -> None:
    """The vectorised :func:`floors` and :func:`keyframe_noise` equal the library's
    :func:`edge_covariance_floor` and :func:`keyframe_pose_noise`, edge by edge and keyframe by keyframe."""
    from minegeo.slam.odometry import edge_covariance_floor

    p = replace(OdometryParams(), **x)
    for s in streams:
        rec = s["rec"]
        F = floors(rec, x)
        for n in range(0, len(F), max(1, len(F) // 50)):
            G = edge_covariance_floor(rec["length_m"][n], rec["angle_deg"][n], p,
                                      rates_deg_s=(rec["rate_i"][n], rec["rate_j"][n]), loop=bool(rec["kind"][n] == 2))
            assert np.allclose(F[n], G, rtol=1e-12, atol=0.0), n
        Q = keyframe_pose_noise(s["rates"], p)
        assert np.allclose(np.diagonal(Q, axis1=1, axis2=2), keyframe_noise(s["rates"], x), rtol=1e-12, atol=0.0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="benchmarks/results/edge_covariance.json")
    ap.add_argument("--duration-s", type=float, default=200.0)
    ap.add_argument("--fit-seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--check-seeds", type=int, nargs="+", default=[3])
    ap.add_argument("--presets", nargs="+", default=["vehicle", "handheld"])
    ap.add_argument("--cache", default="/tmp/edge_cov_cache", help="edge records per stream (npz), reused")
    ap.add_argument("--control-seeds", type=int, nargs="*", default=[],
                    help="also run the control adjustment (slam --control, graph) on 60 s vehicle streams of these seeds")
    ap.add_argument("--control-duration-s", type=float, default=60.0)
    a = ap.parse_args()
    os.makedirs(a.cache, exist_ok=True)
    t0 = time.perf_counter()
    recs = {}
    for preset in a.presets:
        for seed in a.fit_seeds + a.check_seeds:
            f = Path(a.cache) / f"{preset}_{seed}_{a.duration_s:g}_10hz.npz"
            if not f.exists() or "z_true" not in np.load(f).files:  # records of an older format: again
                st, sweeps = simulate(preset, seed, a.duration_s)
                res = run_backend(run_odometry(sweeps, RAW), SlamParams(odometry=RAW))
                np.savez(f, **edge_records(res, st.curve.poses(st.frame_times)))
            recs[preset, seed] = dict(np.load(f))
            print(f"{preset} seed {seed}: {np.bincount(recs[preset, seed]['kind'], minlength=3)} edges "
                  "(chain, extra, loop)", flush=True)
    prepared = {key: prepare(r) for key, r in recs.items()}
    fit_streams = [prepared[p, s] for p in a.presets for s in a.fit_seeds]
    t_fit = time.perf_counter()
    fitted = fit(fit_streams)
    t_fit = time.perf_counter() - t_fit
    _check_formula(fit_streams, fitted)
    default = {k: getattr(OdometryParams(), k) for k in NAMES}
    out = {"conditions": {"threads": os.environ.get("NUMBA_NUM_THREADS"), "duration_s": a.duration_s, "lidar_hz": 10.0,
                          "azimuth_step_deg": 0.2, "station_spacing_m": 100.0, "odometry": "submap (local map)",
                          "fit_seeds": a.fit_seeds, "check_seeds": a.check_seeds, "presets": a.presets,
                          "model": "edges: GICP + floor (accumulating); keyframes: own pose noise Q (joint ML)",
                          "uptime": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
                          "machine": platform.machine(), "fit_seconds": round(t_fit, 1),
                          "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                                   text=True).stdout.strip()},
           "fitted": fitted, "default": default, "edge_floor_only_2026_11_30": EDGE_ONLY,
           "neg_loglik_fit": {"fitted": round(sum(joint_neg_loglik(s, fitted) for s in fit_streams), 1),
                              "edge_floor_only": round(sum(joint_neg_loglik(s, EDGE_ONLY) for s in fit_streams), 1)},
           "streams": {}}
    models = {"uncalibrated": None, "edge_floor_only": EDGE_ONLY, "calibrated_default": default,
              "calibrated_fitted": fitted}
    for (preset, seed), s in prepared.items():
        out["streams"][f"{preset}_seed{seed}"] = {"role": "fit" if seed in a.fit_seeds else "check",
                                                  **{name: by_kind([s], x) for name, x in models.items()}}
    for role, seeds in (("fit", a.fit_seeds), ("check", a.check_seeds)):
        for preset in a.presets:
            ss = [prepared[preset, s] for s in seeds]
            out[f"{role}_{preset}"] = {name: by_kind(ss, x) for name, x in models.items()}
            out[f"{role}_{preset}"]["windows"] = {
                name: {str(m): window_nees(ss, x, m) for m in WINDOWS} for name, x in models.items() if x is not None}
            print(role, preset, {name: {m: w["full"]["mean"] for m, w in v.items()}
                                 for name, v in out[f"{role}_{preset}"]["windows"].items()}, flush=True)
    if a.control_seeds:
        configs = {"uncalibrated": RAW, "edge_floor_only": replace(RAW, **EDGE_ONLY),
                   "calibrated_default": replace(RAW, **default)}
        runs = {}
        for seed in a.control_seeds:
            f = Path(a.cache) / f"control_{seed}_{a.control_duration_s:g}_10hz.json"
            if not f.exists():
                f.write_text(json.dumps(control_run(seed, a.control_duration_s, configs)))
            runs[seed] = json.loads(f.read_text())
            print(f"control seed {seed}: {runs[seed]}", flush=True)
        out["control"] = {"runs": runs}
        runs = {k: r for k, r in runs.items() if all("error" not in r[n] for n in configs)}
        out["control"]["failed_runs"] = len(a.control_seeds) - len(runs)
        for name in configs:
            stat = sum(r[name]["statistic"] for r in runs.values())
            dof = sum(r[name]["dof"] for r in runs.values())
            chk = [x for r in runs.values() for x in r[name]["check_nees3"]]
            out["control"][name] = {
                "pooled_sigma0": round(float(np.sqrt(stat / max(dof, 1))), 3), "dof": dof,
                "chi2_passed": sum(bool(r[name]["passed"]) for r in runs.values()), "runs": len(runs),
                "runs_with_flagged_control": sum(bool(r[name]["flagged"]) for r in runs.values()),
                "check_nees3_mean": round(float(np.mean(chk)), 3) if chk else None, "check_stations": len(chk)}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "streams"}, indent=1))


if __name__ == "__main__":
    main()
