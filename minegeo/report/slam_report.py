"""``report.html`` of ``minegeo slam``, ``minegeo posegraph`` and ``minegeo evaluate`` (self-contained, status first).

slam: counts, the plan view of map, trajectory and accepted loops, the time per module (as the
paper's Table 2), skipped frames, parameters.

posegraph: the graph file, the cost before and after (the contract cost ``F = ½ Σ rᵀΩr``), the
iterations and their costs, a plan view of the poses before and after with the edges, timings.
evaluate: ATE and RPE statistics (evo's), per-axis errors, the alignment, plots of both paths and of
the error along the path.
"""

from __future__ import annotations

import io

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import esc, img_png, kv_table, page, params_table, table, timings_html

__all__ = ["plot_posegraph_png", "posegraph_report_html", "write_posegraph_report", "plot_evaluation_png",
           "evaluate_report_html", "write_evaluate_report", "plot_slam_png", "slam_report_html", "write_slam_report"]


def _figure(n: int = 1, size=(9, 5)):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _xy(poses: np.ndarray) -> np.ndarray:
    return poses[:, :2, -1]


def plot_posegraph_png(before: np.ndarray, after: np.ndarray, edges: np.ndarray, max_edges: int = 20000) -> bytes | None:
    """Plan view (x, y of each pose) before and after, loop edges (|i − j| > 1) drawn thin."""
    fig = _figure(size=(11, 5))
    if fig is None:
        return None
    loops = edges[np.abs(edges[:, 0] - edges[:, 1]) > 1][:max_edges]
    for k, (poses, title) in enumerate(((before, "before (initial values)"), (after, "after optimisation"))):
        ax = fig.add_subplot(1, 2, k + 1)
        xy = _xy(poses)
        if loops.size:
            seg = np.stack([xy[loops[:, 0]], xy[loops[:, 1]]], axis=1)
            from matplotlib.collections import LineCollection

            ax.add_collection(LineCollection(seg, colors="tab:orange", linewidths=0.3, alpha=0.5, label="loop edges"))
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=0.6, label="poses in id order")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(title)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(loc="best", fontsize=8)
    return _png(fig)


def posegraph_report_html(summary: dict, png: bytes | None) -> str:
    res = summary["result"]
    ok = res["status"] == "converged"
    status = "ok" if ok else "failed"
    overview = kv_table([
        ("graph file", summary["inputs"]["graph"]["path"]),
        ("SHA-256", summary["inputs"]["graph"]["sha256"]),
        ("pose type", summary["graph"]["kind"]),
        ("vertices / edges", f"{summary['graph']['vertices']:,} / {summary['graph']['edges']:,}"),
        ("vertices chained from odometry (no VERTEX line)", f"{summary['graph']['chained']:,}"),
        ("fixed vertices (gauge)", ", ".join(map(str, res["fixed_ids"]))),
        ("edges with an information matrix not positive semi-definite", f"{res['non_psd_edges']:,}"),
        ("information used for them", res.get("information_rule", "as given")),
        ("cost before, F = ½ Σ rᵀΩr", f"{res['cost_initial']:.10g}"),
        ("cost after", f"{res['cost_final']:.10g}"),
        ("iterations", res["iterations"]),
        ("stopped because", res["reason"]),
        ("optimised graph written", summary["outputs"].get("graph")),
    ])
    hist = table(["iteration", "cost", "λ", "accepted", "largest step"],
                 [[h["iteration"], f"{h['cost']:.10g}", f"{h['lambda']:.1e}", "yes" if h["accepted"] else "no",
                   f"{h['step']:.3e}"] for h in res["history"]], numeric=(0, 1, 2, 4))
    cost = ("<p>Residual of an edge: r = Log(Z⁻¹ T_i⁻¹ T_j), rotation first; the file's information matrix "
            "is permuted to that order. This is GTSAM's BetweenFactor cost on a file read by readG2o "
            "(slam_contract.md). Levenberg–Marquardt on the Lie algebra, right perturbations, sparse normal "
            "equations.</p>")
    sections = [("Result", overview), ("Cost", cost), ("Plan view", img_png(png, "poses before and after")),
                ("Iterations", hist), ("Parameters", params_table(res["params"])),
                ("Timings", timings_html(summary.get("timings_s")))]
    return page("minegeo posegraph", sections, subtitle=esc(summary["inputs"]["graph"]["path"]), status=status,
                status_text=f"{res['status']}: {res['reason']}")


def write_posegraph_report(path, summary: dict, png: bytes | None):
    return atomic_write_text(path, posegraph_report_html(summary, png))


def plot_evaluation_png(gt_xy: np.ndarray, est_xy: np.ndarray, dist_m: np.ndarray, err_m: np.ndarray) -> bytes | None:
    """Both paths in plan view (estimate aligned) and the position error along the path."""
    fig = _figure(size=(11, 4.5))
    if fig is None:
        return None
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(gt_xy[:, 0], gt_xy[:, 1], "-", color="k", lw=1.0, label="ground truth")
    ax.plot(est_xy[:, 0], est_xy[:, 1], "-", color="tab:red", lw=0.8, label="estimate (aligned)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("plan view")
    ax = fig.add_subplot(1, 2, 2)
    ax.plot(dist_m, err_m, "-", color="tab:red", lw=0.8)
    ax.set_xlabel("distance along the ground-truth path (m)")
    ax.set_ylabel("position error after alignment (m)")
    ax.set_title("ATE along the path")
    return _png(fig)


def _stats_rows(stats: dict, unit: str):
    return [[name, *(f"{stats[name][k]:.6g}" for k in ("rmse", "mean", "median", "std", "min", "max")),
             stats[name]["n"], unit] for name in stats]


def evaluate_report_html(summary: dict, png: bytes | None) -> str:
    r = summary["result"]
    overview = kv_table([
        ("estimate", summary["inputs"]["est"]["path"]),
        ("ground truth", summary["inputs"]["gt"]["path"]),
        ("poses matched by time", f"{r['n_matched']:,} (within {r['params']['max_diff_s']} s)"),
        ("alignment", ("Sim(3)" if r["params"]["scale"] else "SE(3)") + " Umeyama" if r["params"]["align"] else "none"),
        ("scale", f"{r['scale']:.9g}"),
        ("ground-truth path length", f"{r['path_length_m']:.3f} m"),
        ("ATE RMSE", f"{r['ate']['rmse']:.6g} m ({r['ate_percent_of_path']:.4g} % of the path)"),
        ("RPE translation RMSE", f"{r['rpe_translation']['rmse']:.6g} m ({r['rpe_translation_percent']:.4g} %)"),
        ("RPE rotation RMSE", f"{r['rpe_rotation_deg']['rmse']:.6g} deg ({r['rpe_rotation_deg_per_m']:.4g} deg/m)"),
        *(("warning", w) for w in r.get("warnings", [])),
    ])
    heads = ["error", "RMSE", "mean", "median", "std", "min", "max", "n", "unit"]
    ate = table(heads, _stats_rows({"ATE |e|": r["ate"], **{f"ATE {a} (signed)": r["ate_axis"][a] for a in "xyz"}}, "m")
                + _stats_rows({"rotation after alignment": r["ate_rotation_deg"]}, "deg"), numeric=range(1, 8))
    rpe = table(heads, _stats_rows({"RPE translation": r["rpe_translation"]}, "m")
                + _stats_rows({"RPE rotation": r["rpe_rotation_deg"]}, "deg"), numeric=range(1, 8))
    method = ("<p>ATE: e_k = t_gt,k − (s R t_est,k + t) after the Umeyama (1991) least-squares fit of the matched "
              "positions. RPE: E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j) over consecutive pairs "
              f"{esc(r['params']['rpe_delta'])} {esc(r['params']['rpe_unit'])} apart on the ground truth; "
              "the same definitions as evo's evo_ape / evo_rpe (pairs from the reference).</p>")
    sections = [("Result", overview), ("Plots", img_png(png, "paths and error along the path")), ("ATE", ate),
                ("RPE", rpe), ("Method", method), ("Timings", timings_html(summary.get("timings_s")))]
    return page("minegeo evaluate", sections, status="ok", status_text=f"ATE RMSE {r['ate']['rmse']:.4g} m")


def write_evaluate_report(path, summary: dict, png: bytes | None):
    return atomic_write_text(path, evaluate_report_html(summary, png))


def plot_slam_png(map_points: np.ndarray, poses: np.ndarray, kf_poses: np.ndarray, loops: list,
                  max_points: int = 60000, seed: int = 0) -> bytes | None:
    """Plan view: map points (grey, by height), the trajectory, keyframes and accepted loops (red)."""
    fig = _figure(size=(10, 7))
    if fig is None:
        return None
    ax = fig.add_subplot(1, 1, 1)
    P = np.asarray(map_points)
    if P.shape[0] > max_points:  # a seeded, evenly drawn subset keeps the figure light
        P = P[np.sort(np.random.default_rng(seed).choice(P.shape[0], max_points, replace=False))]
    if P.shape[0]:
        sc = ax.scatter(P[:, 0], P[:, 1], c=P[:, 2], s=0.3, cmap="Greys", linewidths=0)
        fig.colorbar(sc, ax=ax, label="map height z (m)")
    xy = _xy(poses)
    ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.0, label="trajectory")
    kxy = _xy(kf_poses)
    ax.plot(kxy[:, 0], kxy[:, 1], ".", color="tab:blue", ms=3, label="keyframes")
    first = True
    for c in loops:
        if c.accepted:
            ax.plot([kxy[c.i, 0], kxy[c.j, 0]], [kxy[c.i, 1], kxy[c.j, 1]], "-", color="tab:red", lw=1.5,
                    label="accepted loop" if first else None)
            first = False
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, map frame = first sensor frame)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("map and trajectory (plan view)")
    return _png(fig)


def slam_report_html(summary: dict, png: bytes | None, extra: list | None = None) -> str:
    r = summary["result"]
    overview = kv_table([
        ("frames used / skipped / not registered", f"{r['frames']} / {len(r['skipped_frames'])} / {r['failed_frames']}"),
        ("frames with a weakly observed direction", r["weak_frames"]),
        ("keyframes", r["keyframes"]),
        ("loop candidates tried / accepted", f"{r['loop_candidates']} / {r['loops_accepted']}"),
        ("path length", f"{r['path_length_m']:.2f} m"),
        ("map points", f"{r['map_points']:,}"),
        ("pose graph", "—" if r["pose_graph"] is None else
         f"{r['pose_graph']['status']}: cost {r['pose_graph']['cost_initial']:.6g} → {r['pose_graph']['cost_final']:.6g} "
         f"in {r['pose_graph']['iterations']} iterations"),
        *([("IMU (LiDAR-inertial keyframe graph)", _inertial_text(r["inertial"]))] if r.get("inertial") else []),
    ])
    mt = summary.get("module_timings_s", {})
    n = max(r["frames"], 1)
    rows = [[name, f"{mt.get(key, 0.0):.3f}", f"{1000 * mt.get(key, 0.0) / n:.1f}"] for name, key in (
        ("frame preparation (downsampling, covariances)", "odometry_prepare"),
        ("odometry, frame to frame (GICP)", "odometry_frame_to_frame"),
        ("odometry, keyframe to keyframe (GICP)", "odometry_keyframe_refine"),
        ("loop detection and verification", "loop_closure"), ("pose-graph optimisation", "pose_graph"),
        ("map (noise removal included)", "map"), ("of it: roadway noise removal", "map_noise"), ("total", "total"))]
    timing = table(["module", "total s", "per frame ms"], rows, numeric=(1, 2))
    skipped = table(["frame", "reason"], [[s["frame"], s["reason"]] for s in r["skipped_frames"]]) \
        if r["skipped_frames"] else "<p>none</p>"
    sections = [("Result", overview), ("Map and trajectory", img_png(png, "plan view of the map and trajectory")),
                *(extra or []), ("Motion distortion and implausible motion", _motion_html(r)),
                ("Time per module (cf. Ren et al. 2019, Table 2)", timing), ("Skipped frames", skipped),
                ("Parameters", params_table(summary["parameters"])), ("Timings", timings_html(summary.get("timings_s")))]
    held = r.get("motion_prior_stretches") or []
    note = (f"; trajectory held by {_held_by(held)} in {len(held)} stretch(es), "
            f"{r.get('motion_prior_held_s', 0.0):.2f} s" if held else "")
    return page("minegeo slam", sections, status="ok",
                status_text=f"{r['frames']} frames, {r['keyframes']} keyframes, {r['loops_accepted']} loop(s){note}")


def _held_by(held: list) -> str:
    """What held the flagged stretches: the IMU (``held_by == "imu"``, with --imu) or the motion prior alone."""
    return ("the IMU (gyro rotation, constant-velocity translation)" if any(h.get("held_by") == "imu" for h in held)
            else "the motion prior alone")


def _inertial_text(ine: dict) -> str:
    """The IMU graph's status and the first and last keyframes' gyro bias (rad/s), the gravity in the map."""
    bg = [k["bias_gyro_rad_s"] for k in ine["keyframes"]]
    return (f"{ine['status']}: gyro bias {np.round(bg[0], 5).tolist()} → {np.round(bg[-1], 5).tolist()} rad/s, gravity "
            f"in the map frame {np.round(ine['gravity_map_m_s2'], 3).tolist()} m/s² (per keyframe in result.json)")


def _motion_html(r: dict) -> str:
    """Deskewing (whether it ran, on how many frames) and the stretches held by the motion prior."""
    d = r.get("deskew") or {}
    if d.get("ran"):
        tw = np.array([f["twist_rad_s_m_s"] for f in d.get("per_frame", [])]).reshape(-1, 6)
        speed = np.linalg.norm(tw[:, 3:], axis=1) if tw.size else np.zeros(1)
        rate = np.degrees(np.linalg.norm(tw[:, :3], axis=1)) if tw.size else np.zeros(1)
        text = (f"<p>Deskewed {d['frames_deskewed']} of {d['frames']} frames to their frame time "
                f"({d.get('iterations', 0) + 1} pass(es); {esc(d.get('convention', ''))}). Twist used: speed up to "
                f"{speed.max():.2f} m/s, angular rate up to {rate.max():.1f} deg/s (per frame in result.json).</p>")
    elif d.get("enabled"):
        text = "<p>Not deskewed: the frames carry no per-point times.</p>"
    else:
        text = "<p>Not deskewed (--no-deskew).</p>"
    held = r.get("motion_prior_stretches") or []
    if not held:
        return text + "<p>Every frame after the first was registered: no stretch held by the motion prior alone.</p>"
    rows = [[f"{h['first_frame']}–{h['last_frame']}", h["frames"], f"{h['first_time_s']:.3f}–{h['last_time_s']:.3f}",
             f"{h['held_s']:.3f}", "; ".join(h["reasons"])] for h in held]
    imu = _held_by(held) != "the motion prior alone"
    by, why = (_held_by(held), "implausible or against the IMU") if imu else ("the constant-velocity motion prior alone",
                                                                            "implausible")
    return (text + f"<p><b>Held by {by}</b> (registration failed or rejected as "
            f"{why}): {len(held)} stretch(es), {r.get('motion_prior_held_s', 0.0):.3f} s in total.</p>"
            + table(["frames", "count", "times (s)", "held for (s, since the last registered frame)", "reason"],
                    rows, numeric=(1, 3)))


def plot_control_png(plot: dict, exaggeration: float | None = None) -> bytes | None:
    """Plan view in the CRS (origin subtracted): trajectory, control (triangles) and check stations
    (circles), residual vectors (estimated − surveyed) exaggerated so the largest is 10 % of the
    extent, and the 95 % ellipses at the check stations at the same exaggeration."""
    fig = _figure(size=(10, 7))
    if fig is None:
        return None
    ax = fig.add_subplot(1, 1, 1)
    o = np.asarray(plot["origin"], dtype=np.float64)
    tr = np.asarray(plot["enh"]) - o
    sv = np.asarray(plot["stations_enh"]) - o
    es = np.asarray(plot["est_enh"]) - o
    ctrl = np.asarray(plot["is_control"], dtype=bool)
    d = es - sv
    ext = max(float(np.ptp(np.r_[tr[:, :2], sv[:, :2]], axis=0).max()), 1.0)
    big = max(float(np.hypot(d[:, 0], d[:, 1]).max()), 1e-6) if d.size else 1e-6
    x = exaggeration or 0.1 * ext / big
    ax.plot(tr[:, 0], tr[:, 1], "-", color="0.4", lw=1.0, label="trajectory")
    ax.plot(sv[ctrl, 0], sv[ctrl, 1], "^", color="tab:blue", ms=8, label="control station")
    ax.plot(sv[~ctrl, 0], sv[~ctrl, 1], "o", mfc="none", color="tab:red", ms=8, label="check station")
    for i in range(sv.shape[0]):
        ax.annotate("", xy=(sv[i, 0] + x * d[i, 0], sv[i, 1] + x * d[i, 1]), xytext=(sv[i, 0], sv[i, 1]),
                    arrowprops={"arrowstyle": "->", "color": "tab:blue" if ctrl[i] else "tab:red"})
        ax.annotate(plot["ids"][i], (sv[i, 0], sv[i, 1]), textcoords="offset points", xytext=(5, 5), fontsize=8)
    u = np.linspace(0.0, 2.0 * np.pi, 73)
    for i, el in plot["ellipses"].items():
        az = el.azimuth_rad  # clockwise from north: major axis direction (sin az, cos az) in (E, N)
        a, b = x * el.semi_major_m, x * el.semi_minor_m
        ma, mi = np.array([np.sin(az), np.cos(az)]), np.array([np.cos(az), -np.sin(az)])
        pts = sv[i, :2] + np.outer(a * np.cos(u), ma) + np.outer(b * np.sin(u), mi)
        ax.plot(pts[:, 0], pts[:, 1], "-", color="tab:red", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel(f"E − {o[0]:.0f} (m)")
    ax.set_ylabel(f"N − {o[1]:.0f} (m)")
    ax.set_title(f"Survey control: residual vectors and 95 % ellipses × {x:.0f}")
    ax.legend(loc="best", fontsize=8)
    return _png(fig)


def control_html(rec: dict, png: bytes | None) -> str:
    """The "Survey control" section: statistics table, check stations, plan view."""
    chi = rec["chi2_test"]
    chk = rec.get("check") or {}
    ratios = [r for r in rec.get("misclosure_ratio", []) if np.isfinite(r)]
    cls = rec.get("class_test")
    kv = kv_table([
        ("mode", rec["mode"]), ("status", f"{rec['status']} {rec['reason']}".strip()), ("CRS", rec["crs"]),
        ("origin E N H (m)", " ".join(f"{v:.0f}" for v in rec["origin_enh"])),
        ("station offset (sensor frame, m)", " ".join(f"{v:g}" for v in rec["station_offset_m"])),
        *([("scale (similarity)", f"{rec['scale']['scale_ppm']:+.1f} ± {rec['scale']['sigma_ppm']:.1f} ppm "
                                  f"(σ {rec['scale']['sigma']})")] if "scale" in rec else []),
        ("σ0", "—" if rec["sigma0"] is None else f"{rec['sigma0']:.3f}"),
        ("χ² test", f"{chi['verdict']}: {chi['statistic']:.3f}, dof {chi['dof']}, "
                    f"[{chi['lower']:.3f}, {chi['upper']:.3f}]"),
        ("flagged control stations (w-test)", ", ".join(f"{f['id']} {f['component']} w={f['w']:.2f}"
                                                         for f in rec["flagged"]) or "none"),
        ("check RMSE horizontal / vertical", "—" if not chk else
         f"{chk['rmse_horizontal_m']:.4f} m / {chk['rmse_vertical_m']:.4f} m"),
        ("class test", "—" if cls is None else f"{sum(cls['passed'])} of {len(cls['passed'])} check stations pass "
                                               f"(c = {cls['c']:g} mm)"),
        ("worst misclosure ratio", f"1:{min(ratios):,.0f}" if ratios else "—"),
        ("uncertainty", rec.get("uncertainty_note") or "—"),
    ])
    rows = [[s["id"], *(f"{v:.4f}" for v in s["delta_enh_m"]), f"{s['horizontal_m']:.4f}", f"{s['d3_m']:.4f}"]
            for s in chk.get("stations", [])]
    tab = table(["check station", "dE m", "dN m", "dH m", "horizontal m", "3D m"], rows, numeric=(1, 2, 3, 4, 5)) \
        if rows else "<p>no check stations</p>"
    return kv + tab + img_png(png, "plan view in the CRS: stations, residual vectors and ellipses")


def write_slam_report(path, summary: dict, res, control_plot: dict | None = None) -> None:
    png = plot_slam_png(res.map_points, res.poses, res.keyframe_poses, res.loops)
    html = slam_report_html(summary, png)
    if control_plot is not None and summary.get("control"):
        sec = control_html(summary["control"], plot_control_png(control_plot))
        html = slam_report_html(summary, png, extra=[("Survey control", sec)])
    atomic_write_text(path, html)
