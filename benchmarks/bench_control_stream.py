"""Survey control on a real SLAM run: a >= 2 km stop-and-go stream of motion-distorted sweeps.

Issue 30's accuracy acceptance measured end to end on the deskewed SLAM, not on a modelled odometry
(``bench_control.py`` chains the true motion perturbed by a random walk and makes no sweeps):

1. ``minegeo synth WORK/stream --stream vehicle --duration-s S --station-spacing-m 100
   --control-every 5 --seed 7``: 10 Hz VLP-16 sweeps smeared by the motion (per-point times), an
   IMU, ``stations.csv`` (surveyed, σ_h 5 mm, σ_v 8 mm) and ``stations_truth.csv``;
2. ``minegeo slam --frames WORK/stream/frames --control stations.csv --control-mode graph
   --drift-states auto --out WORK/slam_<imu>`` without and with ``--imu`` (one SLAM run each);
3. every control mode on the graph that run wrote (``keyframes.tum``, ``graph.g2o`` and the frame
   trajectory ``trajectory.tum``, all at full float64 precision): :func:`minegeo.slam.control.graph_inputs`
   and :func:`~minegeo.slam.control.apply_control` as ``minegeo slam`` calls them, for the plain
   graph (``--drift-states off``), the drift states (``on``), ``auto``, the rigid and the similarity
   fit (``--control-mode rigid|similarity``). The control modes change nothing before the graph
   (the SLAM front end sees only ``--control``'s edge-covariance floor), so one SLAM run per IMU
   condition serves every mode; the ``auto`` row recomputed here is checked against the run's own
   ``result.json`` (its check RMSE).
4. no control: the SLAM trajectory placed in the CRS by the true pose at the first control station
   (one set-up with a perfect backsight), as ``bench_control.py`` does;
5. the acceptance's blunder (:func:`blunder_case`): 0.5 m added to the E of the second control
   station, control in the graph with drift states off (the default) and auto: the w-tests flagged, the suspected blunders
   named, the check errors; then that station removed and the check errors again.

Measured at the check stations against ``stations_truth.csv`` (the truth, not the surveyed
coordinates): RMSE and max of the horizontal and vertical error, for the check stations between two
control stations in time (the acceptance's) and for all; σ̂0 = √(χ²/dof) of the adjustment; the
control stations flagged by the w-test and the suspected blunders; in graph modes the fraction of
check stations whose true horizontal error lies in its 95 % ellipse (one run: a handful of points,
not a calibration). Diagnostics of where the error comes from: the SLAM trajectory's aligned ATE;
the odometry's drift over each control interval (the SLAM poses between two consecutive control
stations, placed by the true pose at the first, compared with the truth at the second); the error
of the graph solution at the station stops and along the path (every graph variable).

Run (about 2 h of CPU for 1100 s; ``--reuse`` keeps a stream or SLAM run already in WORK)::

    NUMBA_NUM_THREADS=1 python benchmarks/bench_control_stream.py --work /tmp/control_stream \\
        --out benchmarks/results/control_stream_<date>.json --md benchmarks/results/control_stream_<date>.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

CHI2_2_95 = 5.991464547107979
MODES = {  # name: (ControlParams keywords, label)
    "graph": ({"mode": "graph", "drift_states": False}, "control in the pose graph (--drift-states off)"),
    "graph_drift": ({"mode": "graph", "drift_states": True}, "control in the pose graph + drift states (on)"),
    "graph_auto": ({"mode": "graph", "drift_states": "auto"}, "control in the pose graph, drift states auto"),
    "rigid": ({"mode": "rigid"}, "rigid fit of the control stations"),
    "similarity": ({"mode": "rigid", "model": "similarity"}, "similarity fit of the control stations (7 parameters)"),
}
NONE_LABEL = "no control (placed by the first control station, true pose)"


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _run(cmd: list[str], log: Path) -> dict:
    """Run ``cmd`` (the minegeo CLI) with 1 Numba thread; its output to ``log``; wall and CPU time."""
    env = {**os.environ, "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS", "1")}
    t0, c0 = time.perf_counter(), os.times()
    with open(log, "w") as f:
        p = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
    c1 = os.times()
    rec = {"cmd": " ".join(cmd), "exit": p.returncode, "wall_s": time.perf_counter() - t0,
           "cpu_s": (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)}
    if p.returncode != 0:
        raise SystemExit(f"{cmd[3]} failed (exit {p.returncode}), see {log}")
    return rec


def synth(work: Path, a) -> dict:
    out = work / "stream"
    if a.reuse and (out / "stations_truth.csv").is_file():
        log = work / "synth.log"  # the log of the run that made it (wall and CPU time), when kept
        return {"reused": str(out), "log": log.read_text().splitlines()[-6:] if log.is_file() else None}
    cmd = [sys.executable, "-m", "minegeo.cli", "synth", str(out), "--force", "--stream", "vehicle",
           "--duration-s", str(a.duration_s), "--station-spacing-m", str(a.spacing_m),
           "--control-every", str(a.control_every), "--seed", str(a.seed)]
    return _run(cmd, work / "synth.log")


def slam(work: Path, imu: bool, a) -> dict:
    out = work / ("slam_imu" if imu else "slam")
    if a.reuse and (out / "graph.g2o").is_file():
        log = work / (out.name + ".log")
        return {"reused": str(out), "log": log.read_text().splitlines()[-8:] if log.is_file() else None,
                **({"follow": json.loads((out / "follow.json").read_text())} if (out / "follow.json").is_file() else {})}
    s = work / "stream"
    cmd = [sys.executable, "-m", "minegeo.cli", "slam", "--frames", str(s / "frames"), "--control",
           str(s / "stations.csv"), "--control-mode", "graph", "--drift-states", "auto", "--out", str(out)]
    if imu:
        cmd += ["--imu", str(s / "imu.csv")]
    return _run(cmd, work / (out.name + ".log"))


def load_slam(out: Path):
    """The parts of a ``SlamResult`` that :func:`graph_inputs` reads, from the files ``minegeo slam``
    wrote (float64 at full precision: TUM with 17 digits, g2o by ``repr``)."""
    from minegeo.io import read_trajectory
    from minegeo.io.g2o import read_g2o

    tr, kf = read_trajectory(out / "trajectory.tum"), read_trajectory(out / "keyframes.tum")
    g = read_g2o(out / "graph.g2o")
    idx = np.searchsorted(tr.times_s, kf.times_s)
    if not np.array_equal(tr.times_s[idx], kf.times_s):
        raise RuntimeError(f"{out}: keyframe times not among the frame times")
    if not np.allclose(g.poses, kf.poses, atol=1e-9):
        raise RuntimeError(f"{out}: graph.g2o vertices differ from keyframes.tum")
    from dataclasses import fields

    from minegeo.slam.odometry import OdometryParams
    from minegeo.slam.pipeline import SlamParams

    rec = json.loads((out / "result.json").read_text())["parameters"]["odometry"]  # the keyframe noise of the run
    known = {f.name for f in fields(OdometryParams)}
    odo = OdometryParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in rec.items() if k in known})
    return SimpleNamespace(times_s=tr.times_s, poses=tr.poses, keyframes=idx, keyframe_poses=kf.poses, graph=g,
                           params=SlamParams(odometry=odo))


def read_truth(stream: Path):
    """``stations_truth.csv`` E N H (absolute), ``T_crs_world`` and the true trajectory (world frame)."""
    from minegeo.io import read_trajectory

    rows = [ln.split(",") for ln in (stream / "stations_truth.csv").read_text().splitlines()
            if ln and not ln.startswith("#")][1:]
    enh = np.array([[float(r[3]), float(r[4]), float(r[5])] for r in rows])
    meta = json.loads((stream / "result.json").read_text())
    return [r[0] for r in rows], enh, np.array(meta["stations"]["T_crs_world"]), read_trajectory(
        stream / "groundtruth.txt"), meta


def _err_stats(e: np.ndarray) -> dict:
    h = np.hypot(e[:, 0], e[:, 1])
    return {"rmse_h_m": float(np.sqrt(np.mean(h**2))), "rmse_v_m": float(np.sqrt(np.mean(e[:, 2] ** 2))),
            "max_h_m": float(h.max()), "max_v_m": float(np.abs(e[:, 2]).max()), "n": int(e.shape[0])}


def blunder_case(st, graph, offset, true_local, between, pose_noise=None, drift_states="auto") -> dict:
    """The acceptance's blunder on this SLAM run: 0.5 m added to the E of the second control station,
    control in the graph (``drift_states``: "auto", or False as ``minegeo slam``'s default): flagged by
    its w-test and named? Then the same station removed from the file: the check errors (the stations
    between two control stations, against the truth) with the remaining three control stations."""
    from dataclasses import replace as dc_replace

    from minegeo.slam.control import ControlParams, apply_control

    c = int(np.flatnonzero(st.is_control)[1])
    enh = st.enh_local.copy()
    enh[c, 0] += 0.5
    bad = dc_replace(st, enh_local=enh)
    p = ControlParams(mode="graph", drift_states=drift_states)
    r = apply_control(*graph, bad, offset, st.crs, p, pose_noise)
    e = r.station_enh_local - true_local
    keep = np.arange(len(st.ids)) != c
    sub = dc_replace(st, ids=tuple(np.asarray(st.ids)[keep]), t_start_s=st.t_start_s[keep], t_end_s=st.t_end_s[keep],
                     enh_local=st.enh_local[keep], sigma_h_m=st.sigma_h_m[keep], sigma_v_m=st.sigma_v_m[keep],
                     roles=tuple(np.asarray(st.roles, dtype=object)[keep]),
                     **({"lines": tuple(np.asarray(st.lines)[keep])} if getattr(st, "lines", None) else {}))
    r2 = apply_control(*graph, sub, offset, st.crs, p, pose_noise)
    e2 = r2.station_enh_local - true_local[keep]
    w = {f"{i} {comp}": float(v) for i, comp, v in r.stats.flagged}
    return {"station": st.ids[c], "drift_states": drift_states, "added_enh_m": [0.5, 0.0, 0.0], "status": str(r.status),
            "reason": r.reason,
            "flagged": list(r.stats.flagged_ids), "flagged_w": w, "suspected_blunders": list(r.blunders),
            "check_between_with_blunder": _err_stats(e[between]),
            "removed": {"control": int(sum(str(x) == "control" for x in sub.roles)), "status": str(r2.status),
                        "flagged": list(r2.stats.flagged_ids), "check_between": _err_stats(e2[between[keep]])}}


def evaluate(out: Path, stream: Path) -> dict:
    """Every mode on the SLAM run in ``out``; errors at the check stations against the truth."""
    from minegeo.io.stations import read_stations
    from minegeo.kernels.lie import se3_inverse
    from minegeo.registration.estimation import kabsch
    from minegeo.slam.control import (
        ControlParams,
        apply_control,
        graph_inputs,
        interpolate_poses,
        slam_pose_noise,
        station_points,
    )

    st = read_stations(stream / "stations.csv")
    ids, enh_true, T_cw, gt, meta = read_truth(stream)
    if list(ids) != list(st.ids):
        raise RuntimeError("stations.csv and stations_truth.csv list different stations")
    offset = np.asarray(meta["stations"]["station_offset_m"], dtype=np.float64)
    o = st.origin_enh
    true_local = enh_true - o
    T_cl = T_cw.copy()
    T_cl[:3, 3] -= o  # world -> local CRS frame
    res = load_slam(out)
    kt, kP, edges, Z, info = graph_inputs(res, st.t_mid_s)
    pose_noise = slam_pose_noise(res, kt)
    tc = st.t_mid_s[st.is_control]
    between = st.is_check & (st.t_mid_s > tc.min()) & (st.t_mid_s < tc.max())
    rec = {"frames": int(res.times_s.size), "keyframes": int(res.keyframes.size), "graph_variables": int(kt.size),
           "check_between": int(between.sum()), "check_all": int(st.is_check.sum()),
           "control": int(st.is_control.sum()), "modes": {}}
    # no control: placed by the true pose at the first control station
    c0 = int(np.flatnonzero(st.is_control)[0])
    T_slam = interpolate_poses(res.times_s, res.poses, st.t_mid_s)
    T_true_st = T_cl @ interpolate_poses(gt.times_s, gt.poses, st.t_mid_s)
    G = T_true_st[c0] @ se3_inverse(T_slam[c0])
    e = station_points(G @ T_slam, offset) - true_local
    rec["modes"]["none"] = {"label": NONE_LABEL, "check_between": _err_stats(e[between]),
                            "check_all": _err_stats(e[st.is_check]),
                            "errors_enh_m": {i: e[k].tolist() for k, i in enumerate(st.ids) if st.is_check[k]}}
    for name, (kw, label) in MODES.items():
        t0 = time.perf_counter()
        c = apply_control(kt, kP, edges, Z, info, st, offset, st.crs, ControlParams(**kw), pose_noise)
        e = c.station_enh_local - true_local
        m = {"label": label, "seconds": time.perf_counter() - t0, "status": str(c.status), "reason": c.reason,
             "check_between": _err_stats(e[between]), "check_all": _err_stats(e[st.is_check]),
             "sigma0": float(np.sqrt(c.global_chi2.statistic / max(c.global_chi2.dof, 1))),
             "chi2_dof": float(c.global_chi2.dof), "chi2_passed": c.global_chi2.passed,
             "flagged": list(c.stats.flagged_ids), "suspected_blunders": list(c.blunders),
             "drift_states": bool(c.drift_states), "drift_choice": c.drift_choice,
             "errors_enh_m": {i: e[k].tolist() for k, i in enumerate(st.ids) if st.is_check[k]},
             "control_residuals_enh_m": {i: e[k].tolist() for k, i in enumerate(st.ids) if st.is_control[k]}}
        if c.check is not None:  # as result.json states it: against the surveyed check coordinates
            m["check_vs_surveyed_m"] = [float(c.check.rmse_horizontal), float(c.check.rmse_vertical)]
        if c.similarity:
            m["scale"], m["scale_std"] = float(c.scale), float(c.scale_std)
        if c.station_cov_enh is not None:
            for sel, key in ((between, "coverage_between"), (st.is_check, "coverage_all")):
                ee, C = e[sel][:, :2], c.station_cov_enh[sel][:, :2, :2]
                inside = np.einsum("ni,nij,nj->n", ee, np.linalg.inv(C), ee) <= CHI2_2_95
                m[key] = {"inside": int(inside.sum()), "n": int(inside.size)}
            m["ellipse_a_m_check"] = {i: float(2.4477 * np.sqrt(np.linalg.eigvalsh(c.station_cov_enh[k][:2, :2])[-1]))
                                      for k, i in enumerate(st.ids) if st.is_check[k]}
            # where the graph solution errs: at the station stops and along the path (every variable)
            Tt = T_cl @ interpolate_poses(gt.times_s, gt.poses, np.clip(c.times_s, gt.times_s[0], gt.times_s[-1]))
            ev = c.poses[:, :3, 3] - Tt[:, :3, 3]
            m["path_error"] = _err_stats(ev)
            m["station_pose_error"] = _err_stats(c.poses[c.station_var, :3, 3] - Tt[c.station_var, :3, 3])
        rec["modes"][name] = m
    rec["blunder"] = blunder_case(st, (kt, kP, edges, Z, info), offset, true_local, between, pose_noise)
    rec["blunder_drift_off"] = blunder_case(st, (kt, kP, edges, Z, info), offset, true_local, between, pose_noise,
                                            drift_states=False)
    # the run's own result.json (same function, same inputs): its check RMSE must equal the auto row
    if (out / "result.json").is_file():
        rj = json.loads((out / "result.json").read_text())
        ck = rj["control"]["check"]
        rec["cli"] = {"control_status": rj["control"]["status"], "timings_s": rj.get("timings_s"),
                      "check_rmse_vs_surveyed_m": [ck["rmse_horizontal_m"], ck["rmse_vertical_m"]],
                      # the run solved on its in-memory poses, this on the files' (17 digits): equal to rounding
                      "difference_from_graph_auto_m": abs(ck["rmse_horizontal_m"]
                                                          - rec["modes"]["graph_auto"]["check_vs_surveyed_m"][0])}
    # SLAM alone: aligned ATE of the frames, and the odometry's drift over each control interval
    Tg = T_cl @ interpolate_poses(gt.times_s, gt.poses, res.times_s)
    A = kabsch(res.poses[:, :3, 3], Tg[:, :3, 3], allow_degenerate=True)
    q = res.poses[:, :3, 3] @ A[:3, :3].T + A[:3, 3]
    path = float(np.linalg.norm(np.diff(Tg[:, :3, 3], axis=0), axis=1).sum())
    ate = float(np.sqrt(np.mean(np.sum((q - Tg[:, :3, 3]) ** 2, axis=1))))
    rec["slam"] = {"path_m": path, "aligned_ate_m": ate, "aligned_ate_percent": 100 * ate / path}
    ctrl = np.flatnonzero(st.is_control)
    drift = []
    for a_, b_ in zip(ctrl[:-1], ctrl[1:], strict=True):
        Ga = T_true_st[a_] @ se3_inverse(T_slam[a_])
        d = (Ga @ T_slam[b_])[:3, 3] - T_true_st[b_][:3, 3]
        dist = float(np.linalg.norm(np.diff(Tg[(res.times_s >= st.t_mid_s[a_]) & (res.times_s <= st.t_mid_s[b_]), :3, 3],
                                            axis=0), axis=1).sum())
        drift.append({"from": st.ids[a_], "to": st.ids[b_], "path_m": dist, "error_enh_m": d.tolist(),
                      "error_h_m": float(np.hypot(d[0], d[1])), "error_v_m": float(abs(d[2]))})
    rec["slam"]["drift_per_control_interval"] = drift
    return rec


def markdown(d: dict) -> str:
    c = d["conditions"]
    lines = [f"# Survey control on a real SLAM run ({c['path_m']:.0f} m stop-and-go vehicle stream)", "",
             "| IMU | mode | check RMSE h (m) | check RMSE v (m) | max h (m) | max v (m) | σ̂0 | flagged control | "
             "95 % ellipse coverage |", "|---|---|---|---|---|---|---|---|---|"]
    for cond, r in d["runs"].items():
        for m in r["modes"].values():
            b = m["check_between"]
            cov = m.get("coverage_between")
            lines.append(f"| {cond} | {m['label']} | {b['rmse_h_m']:.3f} | {b['rmse_v_m']:.3f} | {b['max_h_m']:.3f} | "
                         f"{b['max_v_m']:.3f} | {m['sigma0']:.2f} | " if "sigma0" in m else
                         f"| {cond} | {m['label']} | {b['rmse_h_m']:.3f} | {b['rmse_v_m']:.3f} | {b['max_h_m']:.3f} | "
                         f"{b['max_v_m']:.3f} | – | ")
            if "sigma0" in m:
                lines[-1] += (", ".join(m["flagged"]) or "none") + " | " + (
                    f"{cov['inside']} of {cov['n']} |" if cov else "– |")
            else:
                lines[-1] += "– | – |"
    r0 = next(iter(d["runs"].values()))
    lines += ["", f"Drive {c['path_m']:.0f} m in {c['duration_s']:.0f} s, {c['frames']} sweeps at 10 Hz, "
              f"{r0['control']} control and {r0['check_all']} check stations every {c['spacing_m']:.0f} m "
              f"({r0['check_between']} between two control stations: the table), seed {c['seed']}; "
              "errors against stations_truth.csv." + (f" {d['note']}" if d.get("note") else "")]
    lines += ["", "| IMU | SLAM aligned ATE | drift over each control interval, h (m) | v (m) |", "|---|---|---|---|"]
    for cond, r in d["runs"].items():
        s = r["slam"]
        lines.append(f"| {cond} | {s['aligned_ate_m']:.3f} m ({s['aligned_ate_percent']:.3f} %) | "
                     + ", ".join(f"{x['error_h_m']:.3f}" for x in s["drift_per_control_interval"]) + " | "
                     + ", ".join(f"{x['error_v_m']:.3f}" for x in s["drift_per_control_interval"]) + " |")
    lines += ["", "| IMU | mode | error at the station stops h / v (m) | along the path (every variable) h / v (m) |",
              "|---|---|---|---|"]
    for cond, r in d["runs"].items():
        for m in r["modes"].values():
            if "path_error" in m:
                lines.append(f"| {cond} | {m['label']} | {m['station_pose_error']['rmse_h_m']:.3f} / "
                             f"{m['station_pose_error']['rmse_v_m']:.3f} | {m['path_error']['rmse_h_m']:.3f} / "
                             f"{m['path_error']['rmse_v_m']:.3f} |")
    lines += ["", "| IMU | drift states | 0.5 m added to the E of control station | status | flagged (w-test) | "
              "suspected blunders | check RMSE h / v with it (m) | that station removed: flagged, check RMSE h / v (m) |",
              "|---|---|---|---|---|---|---|---|"]
    for cond, r in d["runs"].items():
        for b in (r.get("blunder_drift_off"), r.get("blunder")):
            if not b:
                continue
            w = ", ".join(f"{k} {v:+.1f}" for k, v in b["flagged_w"].items()) or "none"
            ds = {False: "off (default)", True: "on"}.get(b.get("drift_states", "auto"), b.get("drift_states", "auto"))
            lines.append(f"| {cond} | {ds} | {b['station']} | {b['status']} | {w} | {', '.join(b['suspected_blunders']) or 'none'} | "
                         f"{b['check_between_with_blunder']['rmse_h_m']:.3f} / {b['check_between_with_blunder']['rmse_v_m']:.3f} | "
                         f"{', '.join(b['removed']['flagged']) or 'none'}; {b['removed']['check_between']['rmse_h_m']:.3f} / "
                         f"{b['removed']['check_between']['rmse_v_m']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="scratch folder (the stream and the SLAM runs; not the repo)")
    ap.add_argument("--duration-s", type=float, default=1100.0)
    ap.add_argument("--spacing-m", type=float, default=100.0)
    ap.add_argument("--control-every", type=int, default=5)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--imu", choices=("both", "off", "on"), default="both")
    ap.add_argument("--reuse", action="store_true", help="keep a stream or SLAM run already in --work")
    ap.add_argument("--note", default="", help="recorded in the results file (how this run was made)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--md", default=None)
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    up0 = _uptime()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    timings = {"synth": synth(work, a)}
    print(f"synth: {timings['synth']}", flush=True)
    runs = {}
    for imu in {"both": (False, True), "off": (False,), "on": (True,)}[a.imu]:
        cond = "with IMU" if imu else "LiDAR only"
        timings["slam " + cond] = slam(work, imu, a)
        print(f"slam ({cond}): {timings['slam ' + cond]}", flush=True)
        runs[cond] = evaluate(work / ("slam_imu" if imu else "slam"), work / "stream")
        for name, m in runs[cond]["modes"].items():
            b = m["check_between"]
            print(f"  {cond:10s} {name:11s} RMSE h {b['rmse_h_m']:.4f} v {b['rmse_v_m']:.4f} max h {b['max_h_m']:.4f}",
                  flush=True)
    meta = json.loads((work / "stream" / "result.json").read_text())
    d = {"note": a.note, "date": datetime.date.today().isoformat(), "commit": commit, "threads": os.environ.get("NUMBA_NUM_THREADS"),
         "uptime_before": up0, "uptime_after": _uptime(), "python": sys.version.split()[0],
         "command": "python benchmarks/bench_control_stream.py " + " ".join(sys.argv[1:] if argv is None else argv),
         "conditions": {"duration_s": a.duration_s, "spacing_m": a.spacing_m, "control_every": a.control_every,
                        "seed": a.seed, "frames": meta["n_frames"], "points": meta["n_points"],
                        "path_m": meta["motion_stats"]["path_length_m"], "lidar_hz": meta["params"]["lidar_hz"],
                        "station_sigma_h_m": meta["stations"]["sigma_h_m"],
                        "station_sigma_v_m": meta["stations"]["sigma_v_m"],
                        **({"assembled": meta["assembled"]} if "assembled" in meta else {})},
         "timings": timings, "runs": runs}
    for f in ("uptime_slam_start", "uptime_slam_end"):  # a driver that ran the SLAM runs apart (--reuse) keeps them
        if (work / (f + ".txt")).is_file():
            d[f] = (work / (f + ".txt")).read_text().strip()
    if a.out:
        Path(a.out).write_text(json.dumps(d, indent=1, default=float) + "\n")
    md = markdown(d)
    if a.md:
        Path(a.md).write_text(md)
    print(md)
    return d


if __name__ == "__main__":
    main()
