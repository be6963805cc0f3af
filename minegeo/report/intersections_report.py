"""``report.html`` of ``minegeo intersections build`` and ``minegeo track`` (self-contained, status first).

build: the knowledge base in plan view (map points, invariant points with ids and degrees) and the PWCV
and CWC similarity matrices (Liang et al. 2024, Fig. 16).
track: the plan view (knowledge-base intersections, trajectory, recognised intersections), the
recognitions table with times and scores, with ``--truth`` the error map (trajectory coloured by
position error, as the paper's Fig. 10), the similarity matrix, per-module timings.
"""

from __future__ import annotations

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import esc, img_png, kv_table, page, params_table, table, timings_html
from minegeo.report.slam_report import _figure, _png

__all__ = ["plot_kb_png", "plot_similarity_png", "plot_track_png", "write_kb_report", "write_track_report"]


def plot_kb_png(kb, map_xy: np.ndarray | None = None, max_points: int = 40000) -> bytes | None:
    """Plan view of the knowledge base: dense-cloud points (grey), invariant points (red) with ids."""
    fig = _figure(size=(9, 6))
    if fig is None:
        return None
    ax = fig.add_subplot(1, 1, 1)
    P = kb.cloud_points if map_xy is None else map_xy
    if len(P):
        step = max(1, len(P) // max_points)
        ax.plot(P[::step, 0], P[::step, 1], ",", color="0.6")
        ax.plot([], [], "s", color="0.6", ms=5, label="prior map" if map_xy is not None else
                "prior map (dense clouds of the intersections)")
    C = kb.invariant_points
    ax.plot(C[:, 0], C[:, 1], "o", color="tab:red", ms=6, label="invariant points")
    for i, c in enumerate(C):
        ax.annotate(f"{i} (deg {kb.degree[i]})", c[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, base frame)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    return _png(fig)


def plot_similarity_png(S: np.ndarray, M: np.ndarray) -> bytes | None:
    """PWCV and CWC similarity matrices side by side (values printed when small)."""
    fig = _figure(size=(10, 4.5))
    if fig is None or S.size == 0:
        return None
    for k, (A, title) in enumerate(((S, "PWCV similarity"), (M, "CWC similarity"))):
        ax = fig.add_subplot(1, 2, k + 1)
        im = ax.imshow(A, vmin=0, vmax=1, cmap="viridis")
        if A.shape[0] <= 12:
            for (i, j), v in np.ndenumerate(A):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=7, color="w" if v < 0.6 else "k")
        ax.set_title(title)
        ax.set_xlabel("intersection id")
        ax.set_ylabel("intersection id")
        fig.colorbar(im, ax=ax, fraction=0.046)
    return _png(fig)


def plot_track_png(kb, xy: np.ndarray, recognised: np.ndarray, err_m: np.ndarray | None) -> bytes | None:
    """Plan view: KB intersections, trajectory (coloured by position error when given: the error map)
    and the recognised intersections (observed invariant points, world frame)."""
    fig = _figure(size=(10, 6))
    if fig is None:
        return None
    ax = fig.add_subplot(1, 1, 1)
    if kb is not None and len(kb):
        P = kb.cloud_points[:: max(1, len(kb.cloud_points) // 30000)]
        ax.plot(P[:, 0], P[:, 1], ",", color="0.75")
        ax.plot([], [], "s", color="0.75", ms=5, label="prior map (points around the base's intersections)")
        ax.plot(kb.invariant_points[:, 0], kb.invariant_points[:, 1], "s", mfc="none", color="k", ms=8,
                label="knowledge-base intersections")
        for i, c in enumerate(kb.invariant_points):
            ax.annotate(str(i), c[:2], textcoords="offset points", xytext=(6, 6), fontsize=8)
    if err_m is None:
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.0, label="trajectory")
    else:
        sc = ax.scatter(xy[:, 0], xy[:, 1], c=err_m, s=6, cmap="jet", label="trajectory (colour: position error)")
        fig.colorbar(sc, ax=ax, label="position error (m)")
    if len(recognised):
        ax.plot(recognised[:, 0], recognised[:, 1], "x", color="tab:red", ms=9, mew=2, label="recognised (factors)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, base frame)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    return _png(fig)


def _matrix_table(S: np.ndarray) -> str:
    return table(["id", *map(str, range(S.shape[0]))], [[i, *(f"{v:.3f}" for v in row)] for i, row in enumerate(S)],
                 numeric=range(S.shape[0] + 1))


def write_kb_report(path, summary: dict, kb, S: np.ndarray, M: np.ndarray):
    """Write the ``intersections build`` report."""
    r = summary["result"]
    ok = r["status"] == "ok"
    rows = [[i, kb.degree[i], *(f"{v:.3f}" for v in kb.invariant_points[i]), f"{kb.clearance_m[i]:.2f}",
             int(kb.cloud_offsets[i + 1] - kb.cloud_offsets[i])] for i in range(len(kb))]
    sections = [("Result", kv_table([("status", r["status"]), ("reason", r["reason"] or "-"),
                                     ("intersections", r["intersections"]), ("map points", r["map_points"]),
                                     ("georeferenced", r["georef"] or "no"),
                                     ("written", summary["outputs"]["db"])])),
                ("Plan view", img_png(plot_kb_png(kb), "knowledge base in plan view")),
                ("Intersections", table(["id", "degree", "x (m)", "y (m)", "z (m)", "clearance (m)", "cloud points"],
                                        rows, numeric=range(7)))]
    if len(kb):
        sections += [("Similarity matrices (Fig. 16)", img_png(plot_similarity_png(S, M), "similarity matrices")
                      + "<h3>PWCV</h3>" + _matrix_table(S) + "<h3>CWC</h3>" + _matrix_table(M))]
    sections += [("Parameters", params_table(summary["parameters"])), ("Timings", timings_html(summary["timings_s"]))]
    html = page("minegeo intersections build", sections, subtitle=esc(summary["inputs"]["map"]),
                status="ok" if ok else "failed", status_text=f"{r['status']}: {r['reason']}" if not ok else "")
    return atomic_write_text(path, html)


def write_track_report(path, summary: dict, res, kb, S: np.ndarray | None, err_m: np.ndarray | None):
    """Write the ``track`` report (plan/error map, recognitions, similarity matrix, timings)."""
    r = summary["result"]
    ok = r["status"] == "ok"
    verified = res.verified()
    rec_xy = np.array([(res.keyframe_poses[v.keyframe] @ np.r_[v.recognition.z_keyframe, 1.0])[:3]
                       for v in verified]).reshape(-1, 3)
    plan = plot_track_png(kb, res.poses[:, :3, 3], rec_xy, err_m)
    rows = [[f"{e.time_s:.3f}", e.keyframe, e.recognition.status, e.recognition.intersection_id,
             "" if not np.isfinite(e.recognition.pwcv_score) else f"{e.recognition.pwcv_score:.3f}",
             "" if not np.isfinite(e.recognition.cwc_score) else f"{e.recognition.cwc_score:.3f}",
             "" if not np.isfinite(e.recognition.icp_rms_m) else f"{e.recognition.icp_rms_m:.3f}",
             "yes" if e.factor else "", e.recognition.reason]
            for e in res.recognitions if e.recognition.status != "none"]
    items = [("status", r["status"]), ("reason", r["reason"] or "-"), ("frames / keyframes",
             f"{r['frames']} / {r['keyframes']}"), ("mode", "with map" if r["use_map"] else "without map (online base)"),
             ("intersection factors", r["factors"]), ("recognised ids", ", ".join(map(str, r["recognised_ids"])) or "-"),
             ("statuses", ", ".join(f"{k}: {v}" for k, v in sorted(r["status_counts"].items())))]
    if "map_registrations" in r:  # --map: registrations to the prior map and the factors they gave, by rank
        m = r["map_registrations"]
        items += [("map factors / registrations tried", f"{m['factors']} / {m['tried']}"
                   + (" (" + ", ".join(f"{k}: {v}" for k, v in sorted(m["by_status"].items())) + "; factor rank "
                      + (", ".join(f"{k}: {v}" for k, v in sorted(m["factor_rank"].items())) or "-") + ")"
                      if m["tried"] else ""))]
    if "truth" in r:
        items += [("position error RMSE / max", f"{r['truth']['rmse_m']:.3f} / {r['truth']['max_m']:.3f} m")]
    sections = [("Result", kv_table(items)),
                ("Plan view" + (" and error map" if err_m is not None else ""), img_png(plan, "plan view")),
                ("Recognitions", table(["time (s)", "keyframe", "status", "id", "PWCV", "CWC", "ICP RMS (m)",
                                        "factor", "reason"], rows, numeric=(0, 1, 3, 4, 5, 6)) if rows
                 else "<p>No keyframe saw an intersection.</p>")]
    held = r.get("motion_prior_stretches") or []
    hrows = [[f"{h['first_frame']}–{h['last_frame']}", f"{h['first_time_s']:.3f}–{h['last_time_s']:.3f}",
              f"{h['held_s']:.3f}", "IMU (gyro rotation)" if h.get("held_by") == "imu" else "motion prior",
              "; ".join(h["reasons"])] for h in held]
    sections.append(("Stretches held without registration (no factor from their keyframes)",
                     table(["frames", "times (s)", "held for (s)", "held by", "reason"], hrows, numeric=(2,))
                     if hrows else "<p>Every frame after the first was registered.</p>"))
    un = r.get("unchecked_stretches") or []
    urows = [[f"{u['first_keyframe']}–{u['last_keyframe']}", f"{u['first_frame']}–{u['last_frame']}",
              f"{u['first_time_s']:.3f}–{u['last_time_s']:.3f}", f"{u['path_m']:.1f}", f"{u['max_path_from_check_m']:.1f}"]
             for u in un]
    limit = summary["parameters"].get("unchecked_path_m")
    sections.append((f"Stretches placed by the odometry alone (more than {limit} m of path from every check)",
                     table(["keyframes", "frames", "times (s)", "path (m)", "farthest from a check (m)"], urows,
                           numeric=(3, 4)) if urows
                     else "<p>Every keyframe lies within that path distance of a verified intersection"
                          " (or the start pose).</p>"))
    bad = r.get("inconsistent_factors") or []
    if bad:
        brows = [[b["keyframe"], b["frame"], b["intersection_id"], f"{b['chi2']:.1f}", f"{b['chi2_limit']:.1f}",
                  f"{b['residual_m']:.2f}"] for b in bad]
        sections.append(("Intersection factors failing the χ² test (positions not trusted)",
                         table(["keyframe", "frame", "id", "eᵀΩe", "limit", "residual (m)"], brows,
                               numeric=(0, 1, 2, 3, 4, 5))))
    if S is not None and S.size:
        sections.append(("Knowledge-base similarity matrix (PWCV)", _matrix_table(S)))
    sections += [("Time per module", timings_html(summary["module_timings_s"])),
                 ("Parameters", params_table(summary["parameters"])), ("Timings", timings_html(summary["timings_s"]))]
    html = page("minegeo track", sections, subtitle=esc(summary["inputs"]["frames"]),
                status="ok" if ok else "failed", status_text="" if ok else f"{r['status']}: {r['reason']}")
    return atomic_write_text(path, html)
