"""Calibration of the odometry's keyframe-edge covariance by Monte Carlo on synthetic streams.

For each simulated stop-and-go stream (``minegeo.synth.stream``, vehicle and handheld presets, several
seeds) the GICP odometry runs with the default :class:`~minegeo.slam.odometry.OdometryParams`; each
keyframe edge ``Z = T_i⁻¹ T_j`` (chain and extra edges) is compared with the simulator's truth
``Z* = T*_i⁻¹ T*_j`` at the keyframes' frame times: ``e = Log(Z*⁻¹ Z)`` in (ω, ρ) order (the pose
graph's right perturbation), and its normalised squared error (NEES) ``eᵀ Ω e`` with the information
``Ω`` the edge carries; calibrated, the NEES averages 6 (χ²(6)), the rotation block's
``e_ωᵀ Σ_ωω⁻¹ e_ω`` and the translation block's 3 each.

The edges are recorded with the uncalibrated GICP information too (``OdometryParams`` with the floors
at 0), so the floor constants of :class:`~minegeo.slam.odometry.OdometryParams` (``EDGE_FLOOR_FIELDS``) are fitted by maximum likelihood on the ``fit`` seeds and checked on the
``check`` seeds (never the same streams).

Usage (1 thread; about 4 min of CPU per 8 streams of 30 s at 5 Hz)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_edge_covariance.py --out benchmarks/results/edge_covariance.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from minegeo.kernels.lie import se3_log
from minegeo.slam.odometry import (
    EDGE_FLOOR_FIELDS,
    OdometryParams,
    edge_covariance_floor,
    floored_information,
    run_odometry,
)
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream


def simulate(preset: str, seed: int, duration_s: float, hz: float = 5.0, azimuth_deg: float = 0.4,
             spacing_m: float | None = 6.0):
    """``(sweeps, truth poses at the frame times)`` of one stop-and-go stream."""
    st = simulate_stream(StreamParams(preset=preset, duration_s=duration_s, lidar_hz=hz, azimuth_step_deg=azimuth_deg,
                                      seed=seed, station_spacing_m=spacing_m, control_every=2))
    ft = st.frame_times
    sweeps = [(t, P, tau) for t, P, tau, _r in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                            st.lidar_seed)]
    return sweeps, st.curve.poses(ft)


def edge_records(odo, truth: np.ndarray) -> dict:
    """Per keyframe edge: error ``e = Log(Z*⁻¹ Z)`` (ω, ρ), information, true length (m) and angle (deg)."""
    kf = odo.keyframes
    edges = [(a, a + 1, odo.keyframe_edges[a], odo.keyframe_information[a]) for a in range(len(kf) - 1)]
    edges += list(odo.keyframe_extra_edges)
    err, info, length, angle = [], [], [], []
    for i, j, Z, Om in edges:
        if np.trace(Om) < 1e-3:  # the negligible information of a guessed chain edge: no measurement
            continue
        Zt = np.linalg.inv(truth[kf[i]]) @ truth[kf[j]]
        err.append(se3_log(np.ascontiguousarray(np.linalg.inv(Zt) @ Z)))
        info.append(Om)
        length.append(float(np.linalg.norm(Zt[:3, 3])))
        angle.append(float(np.degrees(np.linalg.norm(se3_log(np.ascontiguousarray(Zt))[:3]))))
    return {"err": np.array(err).reshape(-1, 6), "info": np.array(info).reshape(-1, 6, 6),
            "length_m": np.array(length), "angle_deg": np.array(angle)}


def nees(err: np.ndarray, cov: np.ndarray) -> dict:
    """Full, rotation and translation NEES of errors (n, 6) under covariances (n, 6, 6)."""
    full = np.array([e @ np.linalg.solve(C, e) for e, C in zip(err, cov, strict=True)])
    rot = np.array([e[:3] @ np.linalg.solve(C[:3, :3], e[:3]) for e, C in zip(err, cov, strict=True)])
    tra = np.array([e[3:] @ np.linalg.solve(C[3:, 3:], e[3:]) for e, C in zip(err, cov, strict=True)])
    return {"full": full, "rot": rot, "trans": tra}


def summary(n: dict) -> dict:
    out = {"edges": int(len(n["full"]))}
    for k, v in n.items():
        m = float(np.mean(v))
        se = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan")
        out[k] = {"mean": round(m, 3), "mean_95ci": [round(m - 1.96 * se, 3), round(m + 1.96 * se, 3)],
                  "median": round(float(np.median(v)), 3)}
    return out


def calibrated_cov(rec: dict, params: OdometryParams) -> np.ndarray:
    """The edges' covariance with the floor model of ``params`` added to the GICP part."""
    return np.array([np.linalg.inv(Om) + edge_covariance_floor(L, A, params)
                     for Om, L, A in zip(rec["info"], rec["length_m"], rec["angle_deg"], strict=True)])


def neg_loglik(rec: dict, params: OdometryParams) -> float:
    C = calibrated_cov(rec, params)
    e = rec["err"]
    sign, logdet = np.linalg.slogdet(C)
    return float(0.5 * np.sum(logdet) + 0.5 * np.sum([x @ np.linalg.solve(c, x) for x, c in zip(e, C, strict=True)]))


NAMES = EDGE_FLOOR_FIELDS


def fit(rec: dict, base: OdometryParams) -> OdometryParams:
    """Maximum-likelihood floor constants (Nelder-Mead on their logarithms, from a fixed start)."""
    from scipy.optimize import minimize

    def params_of(x):
        return replace(base, **{k: float(np.exp(v)) for k, v in zip(NAMES, x, strict=True)})

    x0 = np.log([0.1, 0.1, 0.01, 0.003, 0.01, 0.005])
    r = minimize(lambda x: neg_loglik(rec, params_of(np.clip(x, -20, 5))), x0, method="Nelder-Mead",
                 options={"xatol": 1e-3, "fatol": 1e-4, "maxiter": 2000})
    return params_of(np.clip(r.x, -20, 5))


def concat(recs: list) -> dict:
    return {k: np.concatenate([r[k] for r in recs]) for k in recs[0]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="benchmarks/results/edge_covariance.json")
    ap.add_argument("--duration-s", type=float, default=30.0)
    ap.add_argument("--fit-seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--check-seeds", type=int, nargs="+", default=[3, 4])
    ap.add_argument("--presets", nargs="+", default=["vehicle", "handheld"])
    ap.add_argument("--cache", default="/tmp/edge_cov_cache")
    ap.add_argument("--azimuth-deg", type=float, default=0.4, help="azimuth step of the simulated VLP-16 (deg)")
    ap.add_argument("--control-seeds", type=int, nargs="*", default=[],
                    help="also run the control adjustment (slam --control, graph) on 60 s vehicle streams of these seeds")
    ap.add_argument("--control-duration-s", type=float, default=60.0)
    a = ap.parse_args()
    os.makedirs(a.cache, exist_ok=True)
    raw_params = replace(OdometryParams(edge_covariance_floor=True), **dict.fromkeys(NAMES, 0.0))
    t0 = time.perf_counter()
    recs = {}
    for preset in a.presets:
        for seed in a.fit_seeds + a.check_seeds:
            az = "" if a.azimuth_deg == 0.4 else f"_az{a.azimuth_deg:g}"
            f = Path(a.cache) / f"{preset}_{seed}_{a.duration_s:g}{az}.npz"
            if f.exists():
                recs[preset, seed] = dict(np.load(f))
                continue
            sweeps, truth = simulate(preset, seed, a.duration_s, azimuth_deg=a.azimuth_deg)
            odo = run_odometry(iter(sweeps), raw_params)
            recs[preset, seed] = edge_records(odo, truth)
            np.savez(f, **recs[preset, seed])
            print(f"{preset} seed {seed}: {len(recs[preset, seed]['err'])} edges", flush=True)
    fit_rec = concat([recs[p, s] for p in a.presets for s in a.fit_seeds])
    fitted = fit(fit_rec, OdometryParams(edge_covariance_floor=True))
    default = OdometryParams(edge_covariance_floor=True)
    out = {"conditions": {"threads": os.environ.get("NUMBA_NUM_THREADS"), "duration_s": a.duration_s, "lidar_hz": 5.0,
                          "azimuth_step_deg": a.azimuth_deg, "station_spacing_m": 6.0, "fit_seeds": a.fit_seeds,
                          "check_seeds": a.check_seeds, "uptime": subprocess.run(["uptime"], capture_output=True,
                                                                                 text=True).stdout.strip(),
                          "machine": platform.machine(),
                          "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                                   text=True).stdout.strip()},
           "fitted": {k: getattr(fitted, k) for k in NAMES}, "default": {k: getattr(default, k) for k in NAMES},
           "fitted_per_preset": {}, "streams": {}}
    for preset in a.presets:
        f1 = fit(concat([recs[preset, s] for s in a.fit_seeds]), OdometryParams(edge_covariance_floor=True))
        out["fitted_per_preset"][preset] = {k: getattr(f1, k) for k in NAMES}
    for (preset, seed), r in recs.items():
        role = "fit" if seed in a.fit_seeds else "check"
        raw = summary(nees(r["err"], np.linalg.inv(r["info"])))
        cal = summary(nees(r["err"], calibrated_cov(r, default)))
        out["streams"][f"{preset}_seed{seed}"] = {"role": role, "uncalibrated": raw, "calibrated_default": cal,
                                                  "median_length_m": round(float(np.median(r["length_m"])), 3)}
    for role, seeds in (("fit", a.fit_seeds), ("check", a.check_seeds)):
        for preset in a.presets:
            r = concat([recs[preset, s] for s in seeds])
            out[f"{role}_{preset}"] = {"uncalibrated": summary(nees(r["err"], np.linalg.inv(r["info"]))),
                                       "calibrated_default": summary(nees(r["err"], calibrated_cov(r, default)))}
    if a.control_seeds:
        configs = {"uncalibrated": raw_params, "calibrated_default": default}
        runs = {}
        for seed in a.control_seeds:
            f = Path(a.cache) / f"control_{seed}_{a.control_duration_s:g}.json"
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



def refloored(odo, params: OdometryParams):
    """``odo`` with its keyframe (and extra) edges' information refloored from GICP's (floors at 0 in
    ``odo``) by the floor of ``params``, each by its own edge's translation and rotation."""
    def fl(Z, Om):
        if np.trace(Om) < 1e-3:
            return Om
        ang = float(np.degrees(np.linalg.norm(se3_log(np.ascontiguousarray(Z))[:3])))
        return floored_information(Om, edge_covariance_floor(float(np.linalg.norm(Z[:3, 3])), ang, params))
    info = np.array([fl(Z, Om) for Z, Om in zip(odo.keyframe_edges, odo.keyframe_information, strict=True)])
    extra = [(i, j, Z, fl(Z, Om)) for i, j, Z, Om in odo.keyframe_extra_edges]
    return replace(odo, keyframe_information=info.reshape(-1, 6, 6), keyframe_extra_edges=extra)


def control_run(seed: int, duration_s: float, configs: dict) -> dict:
    """One stop-and-go vehicle stream with stations (6 m apart, every second a control, offset 0 0 -0.6):
    the control adjustment in the graph (``slam --control``) per floor configuration: the global
    test statistic ``vᵀPv`` and its redundancy, and the check stations' 3D NEES ``dᵀ Σ⁻¹ d`` (d the
    error against the simulator's true station, Σ the adjustment's covariance)."""
    from minegeo.errors import MinegeoError
    from minegeo.slam.control import ControlParams, apply_control, graph_inputs
    from minegeo.slam.pipeline import SlamParams, run_backend
    from minegeo.synth.stream import stream_stations

    off = (0.0, 0.0, -0.6)
    sp = StreamParams(preset="vehicle", duration_s=duration_s, lidar_hz=5.0, azimuth_step_deg=0.4, seed=seed,
                      station_spacing_m=6.0, control_every=2, station_offset_m=off)
    st = simulate_stream(sp)
    stations, truth = stream_stations(st)
    sweeps = [(t, P, tau) for t, P, tau, _r in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, st.frame_times,
                                                            st.lidar_seed)]
    odo = run_odometry(iter(sweeps), replace(OdometryParams(edge_covariance_floor=True), **dict.fromkeys(NAMES, 0.0)))
    out = {"stations": len(stations.ids), "control": int(stations.is_control.sum())}
    enh_true_local = truth["enh_true"] - stations.origin_enh
    for name, p in configs.items():
        res = run_backend(refloored(odo, p), SlamParams(odometry=p))
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


if __name__ == "__main__":
    main()
