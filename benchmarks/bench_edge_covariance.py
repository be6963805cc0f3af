"""Calibration of the pose graph's edge covariance (odometry and loop edges) on simulated 10 Hz streams.

For each simulated stop-and-go stream (``minegeo.synth.stream``: 10 Hz VLP-16 sweeps smeared by the
motion, 0.2° azimuth step, vehicle and handheld presets, several seeds) the SLAM runs as
``minegeo slam --control`` runs it (odometry to the local map, deskewed, loop closure) with the
floor constants at 0, so every edge carries GICP's own information ``Ω_G``. Each keyframe edge and
each accepted loop edge ``Z = T_i⁻¹ T_j`` is compared with the simulator's truth
``Z* = T*_i⁻¹ T*_j`` at the keyframes' frame times: ``e = Log(Z*⁻¹ Z)`` in (ω, ρ) order (the pose
graph's right perturbation), and its normalised squared error (NEES) ``eᵀ Σ⁻¹ e`` with
``Σ = Ω_G⁻¹ + F``, ``F`` the floor of :func:`minegeo.slam.odometry.edge_covariance_floor`; calibrated,
the NEES averages 6 (χ²(6)), the rotation block's and the translation block's 3 each.

The 14 floor constants (``EDGE_FLOOR_FIELDS``: path, turn and loop terms) are fitted jointly by
maximum likelihood on the ``fit`` seeds and checked on the ``check`` seeds (never the same streams).
``--control-seeds`` also runs the control adjustment (``slam --control``, graph mode) on 60 s vehicle
streams with stations 6 m apart, with GICP's information alone and with the floor: its global test and
the check stations' NEES against the truth.

Usage (1 thread; about 4 min of CPU per 200 s stream)::

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

from minegeo.kernels.lie import se3_log
from minegeo.slam.odometry import EDGE_FLOOR_FIELDS, OdometryParams, keyframe_rates_deg_s, run_odometry
from minegeo.slam.pipeline import SlamParams, run_backend
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

NAMES = EDGE_FLOOR_FIELDS
#: the odometry as ``minegeo slam --control`` runs a 10 Hz stream, with GICP's information alone
RAW = replace(OdometryParams(edge_covariance_floor=True, frame_target="submap"), **dict.fromkeys(NAMES, 0.0))


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


def neg_loglik(rec: dict, x: dict) -> float:
    C = rec["cov"] + floors(rec, x)
    _, logdet = np.linalg.slogdet(C)
    return float(0.5 * np.sum(logdet) + 0.5 * np.einsum("ni,ni->", rec["err"],
                                                        np.linalg.solve(C, rec["err"][..., None])[..., 0]))


START = {"edge_sigma_tilt_deg_per_sqrt_m": 0.1, "edge_sigma_tilt_deg_per_deg": 0.05, "edge_sigma_yaw_deg_per_sqrt_m": 0.03,
         "edge_sigma_trans_xy_m_per_sqrt_m": 0.005, "edge_sigma_trans_z_m_per_sqrt_m": 0.01,
         "edge_sigma_trans_z_m_per_deg": 0.001, "edge_sigma_tilt_deg_per_deg_s": 0.01, "edge_sigma_yaw_deg_per_deg_s": 0.01,
         "edge_sigma_trans_xy_m_per_deg_s": 0.001, "edge_sigma_trans_z_m_per_deg_s": 0.001, "loop_sigma_tilt_deg": 0.1,
         "loop_sigma_yaw_deg": 0.03, "loop_sigma_trans_xy_m": 0.005, "loop_sigma_trans_z_m": 0.01}


def fit(rec: dict) -> dict:
    """Maximum-likelihood floor constants: Powell then Nelder-Mead on their logarithms, from a fixed start."""
    from scipy.optimize import minimize

    def f(y):
        return neg_loglik(rec, dict(zip(NAMES, np.exp(np.clip(y, -25, 5)), strict=True)))

    y = np.log([START[k] for k in NAMES])
    y = minimize(f, y, method="Powell", options={"xtol": 1e-3, "ftol": 1e-7, "maxiter": 20000}).x
    y = minimize(f, y, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 20000,
                                                      "adaptive": True}).x
    # two significant digits; a constant the fit drives below 1e-6 (its lower clip is e⁻²⁵) is 0
    return {k: 0.0 if v < 1e-6 else float(f"{v:.2g}") for k, v in zip(NAMES, np.exp(np.clip(y, -25, 5)), strict=True)}


def concat(recs: list) -> dict:
    return {k: np.concatenate([r[k] for r in recs]) for k in recs[0]}


def by_kind(rec: dict, x: dict | None) -> dict:
    """NEES summaries of the odometry edges and the loop edges under the constants ``x`` (None: GICP alone)."""
    out = {}
    for name, sel in (("odometry", rec["kind"] < 2), ("loops", rec["kind"] == 2)):
        if not sel.any():
            continue
        cov = rec["cov"][sel] + (floors({k: v[sel] for k, v in rec.items()}, x) if x is not None else 0.0)
        out[name] = summary(nees(rec["err"][sel], cov))
    return out


def control_run(seed: int, duration_s: float, configs: dict) -> dict:
    """One 10 Hz stop-and-go vehicle stream with stations (6 m apart, every second a control, offset
    0 0 -0.6): the control adjustment in the graph (``slam --control``) per floor configuration: the
    global test statistic ``vᵀPv`` and its redundancy, and the check stations' 3D NEES ``dᵀ Σ⁻¹ d`` (d
    the error against the simulator's true station, Σ the adjustment's covariance)."""
    from minegeo.errors import MinegeoError
    from minegeo.slam.control import ControlParams, apply_control, graph_inputs
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
                              ControlParams(mode="graph"))
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


def _check_formula(rec: dict, x: dict) -> None:
    """The vectorised :func:`floors` equals the library's :func:`edge_covariance_floor` edge by edge."""
    from minegeo.slam.odometry import edge_covariance_floor

    p = replace(OdometryParams(), **x)
    F = floors(rec, x)
    for n in range(0, len(F), max(1, len(F) // 50)):
        G = edge_covariance_floor(rec["length_m"][n], rec["angle_deg"][n], p,
                                  rates_deg_s=(rec["rate_i"][n], rec["rate_j"][n]), loop=bool(rec["kind"][n] == 2))
        assert np.allclose(F[n], G, rtol=1e-12, atol=0.0), n


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
            if not f.exists():
                st, sweeps = simulate(preset, seed, a.duration_s)
                res = run_backend(run_odometry(sweeps, RAW), SlamParams(odometry=RAW))
                np.savez(f, **edge_records(res, st.curve.poses(st.frame_times)))
            recs[preset, seed] = dict(np.load(f))
            print(f"{preset} seed {seed}: {np.bincount(recs[preset, seed]['kind'], minlength=3)} edges "
                  "(chain, extra, loop)", flush=True)
    fit_rec = concat([recs[p, s] for p in a.presets for s in a.fit_seeds])
    fitted = fit(fit_rec)
    _check_formula(fit_rec, fitted)
    default = {k: getattr(OdometryParams(), k) for k in NAMES}
    out = {"conditions": {"threads": os.environ.get("NUMBA_NUM_THREADS"), "duration_s": a.duration_s, "lidar_hz": 10.0,
                          "azimuth_step_deg": 0.2, "station_spacing_m": 100.0, "odometry": "submap (local map)",
                          "fit_seeds": a.fit_seeds, "check_seeds": a.check_seeds, "presets": a.presets,
                          "uptime": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
                          "machine": platform.machine(),
                          "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                                   text=True).stdout.strip()},
           "fitted": fitted, "default": default, "streams": {}}
    for (preset, seed), r in recs.items():
        out["streams"][f"{preset}_seed{seed}"] = {
            "role": "fit" if seed in a.fit_seeds else "check", "uncalibrated": by_kind(r, None),
            "calibrated_default": by_kind(r, default), "calibrated_fitted": by_kind(r, fitted)}
    for role, seeds in (("fit", a.fit_seeds), ("check", a.check_seeds)):
        for preset in a.presets:
            r = concat([recs[preset, s] for s in seeds])
            out[f"{role}_{preset}"] = {"uncalibrated": by_kind(r, None), "calibrated_default": by_kind(r, default),
                                       "calibrated_fitted": by_kind(r, fitted)}
    if a.control_seeds:
        configs = {"uncalibrated": RAW, "calibrated_default": replace(RAW, **default)}
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
