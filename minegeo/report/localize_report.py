"""Self-contained HTML report of a global localization (``minegeo localize``).

One page a surveyor can file. Its first line is the status banner (``STATUS: OK`` /
``FAILED`` / ``AMBIGUOUS`` with the reason, :func:`minegeo.report._html.status_banner`). For an
``ok`` result: the scan origin in the map and the CRS with its uncertainty, a plan view (map +
placed scan + trajectory, embedded PNG), the verified hypotheses, the residuals of the final
fit and the trajectory in the CRS. For a ``failed`` or ``ambiguous`` result **no position is
shown anywhere**: the placements that were tried are listed as *rejected candidates* (map
frame, labelled "not a position") and the plan view marks them as such. Then the parameters
actually used (profile and effective values), the run time with Numba compile time apart,
and the input hashes.
"""

from __future__ import annotations

import base64
import io
import math
from dataclasses import asdict

import numpy as np

from minegeo._provenance import atomic_write_text, to_jsonable
from minegeo.report._html import badge, esc, kv_table, num, page, table

__all__ = ["map_plot_points", "plan_axis_labels", "plot_localization_png", "localize_report_html", "write_localize_report"]

_STATUS_TEXT = {
    "ok": "The scan was placed in the map; no competing placement fits nearly as well and the geometry "
          "constrains all six pose directions. The coordinates below can be used with the stated uncertainty.",
    "ambiguous": "NO POSITION. A placement fits, but it is NOT unique: another placement fits almost as well (a "
                 "repeated drift), or the geometry leaves a direction unconstrained (e.g. a straight "
                 "featureless drift), or the fit did not settle. The competing placements are listed below as "
                 "rejected candidates, not positions. Re-scan a longer section including a distinctive feature "
                 "(intersection, curve, structure).",
    "failed": "NO POSITION. No placement of the scan fits the map well enough. The scan may be outside the mapped "
              "area, the drift may have changed since mapping, or the scan is too short or too noisy. The "
              "placements that were tried are listed below as rejected candidates, not positions.",
}


def _frame_xy(g, pts_map: np.ndarray):
    """Plan coordinates for plotting: geo frame (CRS − origin) if georeferenced (``g``), else map."""
    if g is not None:
        from minegeo.georef import map_to_crs

        return map_to_crs(pts_map, g, allow_failed=True)
    return pts_map


def map_plot_points(prepared, max_map_points: int, seed: int = 0) -> np.ndarray:
    """The map points (map frame, m) drawn under a plan view: all of them, or ``max_map_points``
    rows chosen without replacement by a generator seeded ``seed`` (kept in file order)."""
    M = prepared.points_map()
    if M.shape[0] > max_map_points:
        M = M[np.sort(np.random.default_rng(seed).choice(M.shape[0], max_map_points, replace=False))]
    return M


def plan_axis_labels(ax, g) -> None:
    """Axis labels of a plan view drawn by :func:`_frame_xy`: ``E − E0 m``, ``N − N0 m`` with the
    georeference's origin when ``g`` is given, else the map frame's ``x``, ``y`` (m)."""
    if g is not None:
        ax.set_xlabel(f"E − {g.origin[0]:.0f} m")
        ax.set_ylabel(f"N − {g.origin[1]:.0f} m")
    else:
        ax.set_xlabel("x map (m)")
        ax.set_ylabel("y map (m)")


def label_offsets(xy, min_sep: float, step_pt: float = 10.0) -> list[tuple[float, float]]:
    """Text offsets (points) for the labels of the points ``xy`` (n, 2) so that labels do not overlap.

    Deterministic: label ``i`` sits ``(4, 4 + step_pt * j)`` points from its point, ``j`` the
    number of earlier points closer than ``min_sep`` (data units) to it, so the labels of nearby
    points (e.g. two candidates 0.1 m apart) are stacked in their order and far ones keep (4, 4).
    """
    P = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = []
    for i in range(P.shape[0]):
        j = int(np.count_nonzero(np.hypot(*(P[:i] - P[i]).T) < min_sep)) if i else 0
        out.append((4.0, 4.0 + step_pt * j))
    return out


def plot_localization_png(res, prepared, max_map_points: int = 40000, seed: int = 0) -> bytes | None:
    """Plan view as PNG bytes (None without matplotlib).

    ``ok``: map (grey), placed scan and trajectory, overview and detail. ``failed`` /
    ``ambiguous``: the map and the scan origin of each rejected candidate, marked ``x`` and
    numbered, titled "rejected candidates — NOT positions", in the map frame as their table;
    no placed scan, no trajectory.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    g = prepared.georef_result
    M = map_plot_points(prepared, max_map_points, seed)
    ok = res.status == "ok"
    if not ok:  # the rejected candidates are drawn in the map frame, as their table
        g = None
    Mx = _frame_xy(g, M)
    fig = Figure(figsize=(11, 5.2) if ok else (7.5, 5.2), dpi=100)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)] if ok else [fig.add_subplot(1, 1, 1)]
    if ok:
        S = res.scan_points_down if res.scan_points_down is not None else np.zeros((0, 3))
        T = res.T_map_scan
        Sx = _frame_xy(g, S @ T[:3, :3].T + T[:3, 3])
    for k, ax in enumerate(axes):
        ax.scatter(Mx[:, 0], Mx[:, 1], s=0.15, c="0.7", linewidths=0)
        ax.scatter([], [], s=12, c="0.7", label="map (downsampled)")  # legend proxy
        if ok:
            ax.scatter(Sx[:, 0], Sx[:, 1], s=0.6, c="tab:green", linewidths=0)
            ax.scatter([], [], s=12, c="tab:green", label="scan placed (ok)")
            if res.trajectory_map is not None:
                P = _frame_xy(g, res.trajectory_map.poses[:, :3, 3])
                ax.plot(P[:, 0], P[:, 1], "-", c="tab:blue", lw=1.2, label="sensor trajectory")
                ax.plot(P[0, 0], P[0, 1], "o", c="tab:blue", ms=4)
            o = _frame_xy(g, T[:3, 3].reshape(1, 3))[0]
            ax.plot(o[0], o[1], "k+", ms=10, mew=1.5, label="scan origin")
        else:
            from minegeo.localize.pipeline import rejected_candidates

            cands = rejected_candidates(res)
            if cands:  # map frame, as the rejected-candidates table (never CRS coordinates)
                C = np.array([c["origin_map_m"] for c in cands])
                ax.plot(C[:, 0], C[:, 1], "x", c="tab:red", ms=9, mew=2,
                        label="rejected candidates (NOT positions)")
                sep = 0.04 * float(max(np.ptp(Mx[:, 0]), np.ptp(Mx[:, 1]), 1.0)) if len(Mx) else 1.0
                for c, xy, off in zip(cands, C, label_offsets(C[:, :2], sep), strict=True):
                    ax.annotate(f"#{c['rank']}", xy[:2], xytext=off, textcoords="offset points", fontsize=8,
                                color="tab:red")
            ax.set_title(f"{res.status.upper()}: rejected candidates — NOT positions (map frame)")
        if ok and k == 1 and Sx.shape[0]:
            c = Sx[:, :2].mean(axis=0)
            r = max(float(np.max(np.ptp(Sx[:, :2], axis=0))) * 0.75, 5.0)
            ax.set_xlim(c[0] - r, c[0] + r)
            ax.set_ylim(c[1] - r, c[1] + r)
            ax.set_title("detail")
        elif ok:
            ax.set_title("overview")
        ax.set_aspect("equal", adjustable="box" if k == 1 else "datalim")
        ax.grid(True, color="0.92")
        plan_axis_labels(ax, g)
    axes[0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def describe_params(p, map_params) -> str:
    """The effective parameters of a run in one line (downsampling, features, RANSAC, ICP, checks)."""
    r = p.ransac
    f = p.features
    mp = map_params
    scan_ds = p.describe_downsampling()
    map_ds = mp.describe() if mp is not None and hasattr(mp, "describe") else "n/a"
    model = f"levelled, tilt <= {r.max_tilt_deg:g} deg" if r.model == "levelled" else r.model
    ransac = (f"RANSAC {r.ransac_n}-point ({model}), "
              f"{'mutual' if r.mutual_filter else 'all'} FPFH matches, ε_distance {r.distance_threshold_m:g} m, "
              f"edge similarity {r.edge_length_similarity:g}, draws: Eq. 8 with floor {int(r.min_iterations):,} "
              f"and cap {int(r.max_iterations):,}, "
              f"{r.max_validations} validations, {r.n_hypotheses} hypotheses x {p.ransac_runs} run(s)")
    icp = (f"ICP {p.icp.method}, gate {p.icp.max_correspondence_m:g} m, <= {p.icp.max_iterations} iterations, "
           f"ICP clouds {num(p.scan_icp_voxel_size_m, 'g')} m (scan) / "
           f"{num(getattr(mp, 'icp_voxel_size_m', None), 'g')} m (map) voxels; polish "
           + (f"{p.icp.polish_correspondence_m:g} m" if p.icp.polish_correspondence_m is not None else "off"))
    corr = f"correlative search {'off' if p.correlative is None else p.correlative.mode}" if r.model == "levelled" else "no correlative search (not levelled)"
    return (f"scan {scan_ds}, map {map_ds}; normals r {f.normal_radius_m:g} m, FPFH r {f.fpfh_radius_m:g} m; "
            f"{ransac}; {icp}; {corr}; ok needs plane fitness >= {p.verify.min_plane_fitness:g}, "
            f"ICP fitness >= {p.verify.min_fitness:g}, no rival >= {p.ambiguity.ratio:g} x the best")


#: the LocalizeParams groups listed field by field (``icp.method``) in the report
_FLAT_GROUPS = ("icp", "verify", "ambiguity")


def _flat_params(p) -> dict:
    """``asdict(p)`` with the groups of :data:`_FLAT_GROUPS` spread into ``group.field`` keys."""
    out = {}
    for k, v in asdict(p).items():
        if k in _FLAT_GROUPS and isinstance(v, dict):
            out.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        else:
            out[k] = v
    return out


def profile_label(p, map_params, profile: str | None) -> str:
    """Which profile the parameters are: exactly a named one, or that profile with overrides (named)."""
    from minegeo.localize import LocalizeParams, PrepareParams

    named = {"fast": (LocalizeParams.fast(), PrepareParams.fast()),
             "table3": (LocalizeParams(), PrepareParams())}
    text = {"fast": "minegeo's fast profile (the measured CLI default, not the paper's values)",
            "table3": "Baek et al. 2022 Table 3 (paper-faithful profile; RANSAC capped at 4e6 draws instead of 4e8, "
                      "mutual FPFH matches)"}
    if profile not in named:
        return "library parameters (no CLI profile)"
    lp0, mp0 = named[profile]
    diff = [k for k, v in _flat_params(p).items() if _flat_params(lp0)[k] != v]
    if map_params is not None:
        diff += [f"map.{k}" for k, v in asdict(map_params).items() if asdict(mp0).get(k) != v]
    if not diff:
        return f"profile {profile}: {text[profile]}"
    return f"profile {profile} with changed {', '.join(diff)} (so not exactly {text[profile].split(' (')[0]})"


def _uncertainty_text(u: dict | None) -> str:
    """One paragraph, in plain words, saying where the uncertainty above comes from (the
    estimator, then each part added to it; the machine-readable names are in result.json)."""
    if not u:
        return "No uncertainty: the fit leaves a direction of the pose unconstrained."
    method = u.get("method")
    base = "How sure the position is: from how well the scan's points lie on the map's surfaces in the final fit"
    if method == "jackknife":
        txt = (f"{base}, measured by leaving out one of {u.get('n_clusters')} blocks of "
               f"{num(u.get('cluster_size_used_m'), 'g')} m at a time (neighbouring points err together; this is "
               f"{num(u.get('inflation'), '.1f')}x the textbook least-squares value in position, and never below it; "
               "delete-one-block jackknife)")
    elif method == "cluster":
        txt = (f"{base}, measured over {u.get('n_clusters')} blocks of {num(u.get('cluster_size_used_m'), 'g')} m "
               "(cluster-robust), never below the textbook least-squares value")
    else:
        txt = (f"{base}, textbook least-squares value σ²(JᵀJ)⁻¹ (every point assumed to err independently: "
               "optimistic)")
    if u.get("params", {}).get("add_pending_step") and "pending_step" not in (u.get("model_terms") or {}):
        txt += "; it includes the last correction the fit had not yet applied"
    if u.get("weak_axis_polish_term"):
        txt += ("; and the shift of the final polish along the weakly constrained direction (the position there "
                "depends on how far apart matched points may be)")
    dt = u.get("data_term") or {}
    terms = u.get("model_terms") or {}
    if dt.get("position_95_radius_m") is not None:
        txt += (f". The scan's fit alone gives a 95 % radius of {num(dt.get('position_95_radius_m'), '.4f')} m "
                f"(weakest-to-strongest constraint ratio {num(dt.get('information_ratio'), '.2e')})")
    if terms:
        from minegeo.localize.uncertainty import MODEL_TERM_TEXT

        txt += "; added to it (RMS of the position, m): " + "; ".join(
            f"{v.get('meaning') or MODEL_TERM_TEXT.get(k, k)}: {num(v.get('position_rms_m'), '.4f')}"
            for k, v in terms.items())
    return txt + (". It does not include the map's own error or the georeferencing error (see the georef report; "
                  "docs/uncertainty.md).")


def _mat(T) -> str:
    if T is None:
        return "n/a"
    return "<pre>" + esc("\n".join(" ".join(f"{v:14.6f}" for v in row) for row in np.asarray(T))) + "</pre>"


#: How the verified hypotheses are ranked (:func:`minegeo.localize.decision.hypothesis_records`).
RANKING = ("ranked fully refined first (a candidate screened out on the coarse scan last), then by fine agreement "
           "(share of the scan within the fine tolerance of the map surface), plane fitness, ICP fitness")


def rank_reason(h: dict, h0: dict) -> str:
    """Why the verified hypothesis ``h`` ranks below ``h0`` (ranked first), by the ranking's own
    criterion (:data:`RANKING`): the first key that differs at the printed 3 decimals."""
    if "screened out" in h["source"] and "screened out" not in h0["source"]:
        return "screened out on the coarse scan"
    for key, name in (("fine_fitness", "fine agreement"), ("plane_fitness", "plane fitness"),
                      ("icp_fitness", "ICP fitness")):
        if f"{h[key]:.3f}" != f"{h0[key]:.3f}":
            return f"{name} {h[key]:.3f} vs {h0[key]:.3f} of #0"
    return "fits as well as #0 to 3 decimals"


def _rejected_section(res) -> str:
    """Table of the rejected candidates of a failed / ambiguous result (map frame, not positions),
    each against #0 by the ranking criterion."""
    from minegeo.localize.pipeline import rejected_candidates

    cands = rejected_candidates(res)
    if not cands:
        why = res.ransac.reason if res.ransac is not None else ""
        return f"<p>No candidate placement was proposed ({esc(why)}).</p>"
    hyps = {int(h["rank"]): h for h in res.hypotheses or []}
    h0 = hyps.get(0)
    rows = []
    for c in cands:
        h = hyps.get(c["rank"])
        why = "ranked first" if c["rank"] == 0 else (rank_reason(h, h0) if h is not None and h0 is not None else "")
        rows.append([c["rank"], c["source"], "NOT a position: " + "  ".join(f"{v:.1f}" for v in c["origin_map_m"]),
                     num(c["distance_to_best_m"], ".1f"), num(c["rotation_to_best_deg"], ".1f"),
                     num(h["fine_fitness"] if h is not None else None, ".3f"), num(c["plane_fitness"], ".3f"),
                     num(c["icp_fitness"], ".3f"), num(c["icp_inlier_rmse_m"], ".3f"), why])
    sec = ("<p><b>These placements were tried and rejected; none of them is the position of the scan.</b> "
           "The map-frame location is where the scan origin would be if that placement were right; it is given "
           "to show how far apart the candidates are (a repeated drift), never to be used. The table and the plan "
           f"view below are both in the map frame (x, y, z of the prior map, m). The candidates are {RANKING}.</p>")
    sec += table(["#", "candidate", "scan origin if this were right (map frame x y z, m)", "from #0 m",
                  "from #0 °", "fine agreement", "plane fitness", "ICP fitness", "ICP RMSE m", "below #0 by"], rows,
                 numeric=range(3, 9))
    sec += (f"<p class='sub'>An ok result needs plane fitness >= {res.params.verify.min_plane_fitness:g} and no distinct "
            f"rival reaching {res.params.ambiguity.ratio:g} x #0's (plane tolerance "
            f"{num(res.plane_tolerance_m, '.3f')} m).</p>")
    return sec


def _rival_section(res) -> str | None:
    """The whole-map rival search (``res.rival_search``): its guarantee, the best rival (map frame,
    NOT a position), the margin and the placements it checked."""
    rv = getattr(res, "rival_search", None)
    if not rv:
        return None
    b = rv.get("best_rival")
    rows = [("what was searched", rv.get("guarantee", "")),
            ("chosen attitude: tilt / heading (°)", f"{num(rv.get('tilt_deg'), '.2f')} / {num(rv.get('heading_deg'), '.2f')}"),
            ("placements scored", f"{rv.get('n_placements')} on the first pivot ({rv.get('n_anchors')} floor anchors x "
                                  f"{rv.get('n_yaw')} headings), {rv.get('n_pivots')} pivots"),
            ("chosen placement found again by the search", f"rank {rv['self_rank']}" if rv.get("self_found")
             else "NO (the guarantee does not hold for this scan)"),
            ("coverage of the cascade", "complete" if rv.get("covered") else "INCOMPLETE (caps reached)"),
            ("time (s)", num(res.timings_s.get("rival_search"), ".2f"))]
    if b is None:
        rows.append(("best rival", "none: no other placement was found"))
    else:
        rows += [("best rival (NOT a position"
                  + ("; rejected)" if res.status == "ok" else ")"),
                  "scan origin if it were right, map frame: " + "  ".join(f"{v:.1f}" for v in b["origin_map_m"])),
                 ("its distance / rotation from the " + ("answer" if res.status == "ok" else "best"),
                  f"{num(b['distance_to_chosen_m'], '.1f')} m / {num(b['rotation_to_chosen_deg'], '.1f')} °"),
                 (f"plane fitness, rival vs chosen ({b['score_level']} level)",
                  f"{num(b['plane_fitness'], '.3f')} vs {num(b['chosen_plane_fitness'], '.3f')}"),
                 ("margin (chosen / rival; ambiguous at <= "
                  f"{num(1.0 / rv['ambiguity_ratio'], '.2f')})", num(b["margin"], ".3f")),
                 (f"support-matched ratio on the {num(100 * b['common_fraction'], '.0f')} % of points the map "
                  f"covers at both (ambiguous at >= {rv['params']['matched_ratio']:g})", num(b["matched_ratio"], ".3f")),
                 ("source / test passed", f"{b['source']} / {b.get('test_passed') or 'none'}")]
    sec = kv_table(rows)
    crow = [[c["rank"], c["stage"], num(c["final_distance_to_chosen_m"], ".1f"),
             num(c["final_rotation_to_chosen_deg"], ".1f"), num(c["precheck_plane_fitness"], ".3f"),
             num(c["precheck_matched_ratio"], ".3f"), num(c["plane_fitness"], ".3f"), num(c["matched_ratio"], ".3f")]
            for c in rv.get("candidates", []) if c["stage"] != "self"]
    if crow:
        sec += table(["#", "stage", "from chosen m", "from chosen °", "pre-check plane fitness",
                      "pre-check support-matched", "plane fitness after ICP", "support-matched after ICP"], crow,
                     numeric=range(2, 8))
    sec += ("<p class='sub'>Before an ok result, the exhaustive correlative search looks over the whole map at the "
            "chosen placement's tilt for another placement that explains the scan nearly as well (e.g. a copy "
            "of the drift on another level); its placements are checked with the same ICP and verification as "
            "the hypotheses (docs/localization.md, <i>Rival search</i>).</p>")
    return sec


def _timings_section(tim: dict) -> str:
    """Run time (wall, Numba compile apart) then the stages."""
    rows = []
    if "wall_s" in tim:
        wall = tim.get("process_wall_s", tim["wall_s"])
        rows.append(("whole run, wall clock", f"{num(wall, '.2f')} s"))
        rows.append(("  of which compiling Numba kernels (one-time; cached for later runs)",
                     f"{num(tim.get('compile_s'), '.2f')} s"))
        if "startup_s" in tim:
            rows.append(("  of which Python start-up and imports", f"{num(tim['startup_s'], '.2f')} s"))
        rows.append(("  work (run clock minus compiling)", f"{num(tim.get('work_s'), '.2f')} s"))
    head = kv_table(rows) if rows else ""
    skip = {"wall_s", "compile_s", "work_s", "startup_s", "process_wall_s"}
    return head + table(["stage", "seconds"], [[k, num(v, ".3f")] for k, v in tim.items() if k not in skip],
                        numeric=[1])


def _status_section(res) -> str:
    """Badge, reason, what the status means, and the warnings."""
    head = (f"<p>{badge(res.status.upper(), {'ok': True, 'failed': False, 'ambiguous': False}.get(res.status))} "
            f"{esc(res.reason)}</p><p>{esc(_STATUS_TEXT[res.status])}</p>")
    if res.warnings:
        head += "<ul>" + "".join(f"<li>{esc(w)}</li>" for w in res.warnings) + "</ul>"
    return head


def _result_section(res) -> str:
    """The placed scan (``ok`` only): origin in the map and the CRS, uncertainty, fit, transforms."""
    rows = [("frame of T_map_scan", "map frame of the prior map before georeferencing (p_map = R p_scan + t)")]
    t = res.T_map_scan[:3, 3]
    rows.append(("scan origin, map frame (m)", f"{t[0]:.3f}  {t[1]:.3f}  {t[2]:.3f}"))
    if res.T_crs_scan is not None:
        c = res.T_crs_scan[:3, 3]
        rows.append((f"scan origin, CRS {res.crs} (E N H, m)", f"{c[0]:.3f}  {c[1]:.3f}  {c[2]:.3f}"))
    s = res.position_sigma_m
    rows.append(("1σ of the scan origin x, y, z (m)", "  ".join(num(v, ".4f") for v in s)))
    rows.append(("95 % radius 3-D (m)", f"{num(res.position_95_radius_m, '.4f')}  (ball holding the origin with probability 0.95 under the covariance)"))
    rows.append(("95 % radius horizontal (m)",
                 f"{num(res.horizontal_95_radius_m, '.4f')}  (circle holding it with probability 0.95 in plan)"))
    rows.append(("σ of one residual (m)", num(res.sigma_m, ".4f")))
    rows.append(("final fitness / inlier RMSE (Eq. 19)",
                 f"{num(res.fitness, '.4f')} / {num(res.inlier_rmse_m, '.4f')} m"))
    rows.append(("scan points: read / features / ICP", f"{res.n_scan_points} / {res.n_scan_down} / {res.n_scan_icp}"))
    sec = kv_table(rows)
    sec += f"<p class='sub'>{esc(_uncertainty_text(res.uncertainty))}</p>"
    sec += "<h3>T_map_scan</h3>" + _mat(res.T_map_scan)
    if res.T_crs_scan is not None:
        sec += f"<h3>T_crs_scan (full {esc(res.crs)} coordinates)</h3>" + _mat(res.T_crs_scan)
    return sec


def _plan_view_section(res, prepared, ok: bool) -> tuple[str, str]:
    """The embedded plan view (or the note that matplotlib is missing), with its title."""
    png = plot_localization_png(res, prepared, seed=res.seed)
    if png is None:
        return ("Plan view", "<p>matplotlib is not installed: no plot.</p>")
    b64 = base64.b64encode(png).decode("ascii")
    return ("Plan view" if ok else "Plan view of the rejected candidates",
            f'<img alt="plan view" style="max-width:100%" src="data:image/png;base64,{b64}">')


def _hypotheses_section(res, ok: bool) -> str:
    """The verified hypotheses, the RANSAC summary and the final ICP's degeneracy check."""
    hrows = []
    for h in res.hypotheses:
        hrows.append([h["rank"], h["source"], num(h["ransac_fitness"], ".3f"), num(h["ransac_inlier_rmse_m"], ".3f"),
                      num(h["icp_fitness"], ".3f"), num(h["icp_inlier_rmse_m"], ".3f"), num(h["plane_fitness"], ".3f"),
                      num(h["plane_rmse_m"], ".3f"), num(h["distance_to_chosen_m"], ".2f"),
                      num(h["rotation_to_chosen_deg"], ".2f")])
    r = res.ransac
    ref = "chosen" if ok else "#0"
    sec = table(["rank", "hypothesis", "RANSAC fitness", "RANSAC RMSE m", "ICP fitness", "ICP RMSE m",
                 "plane fitness", "plane RMSE m", f"distance to {ref} m", f"rotation to {ref} °"], hrows,
                numeric=range(2, 10))
    if r is not None:
        sec += kv_table([
            ("RANSAC iterations / validations", f"{r.iterations} / {r.n_validations} ({r.status})"),
            ("putative FPFH correspondences", int(r.correspondences.shape[0])),
            ("runner-up score ratio / distance", f"{num(r.ambiguity_ratio, '.3f')} / {num(r.second_best_distance_m, '.1f')} m"),
        ])
    if res.icp is not None:
        ic = res.icp
        sec += kv_table([
            ("ICP method / iterations / converged", f"{res.params.icp.method} / {ic.iterations} / {ic.converged}"),
            ("constraint eigenvalue ratio (degenerate below "
             f"{res.params.verify.degeneracy_ratio:g})", num(ic.degeneracy_ratio, ".4f")),
            ("degeneracy", ic.degeneracy_reason or "none"),
        ])
    return sec


def _residuals_section(res) -> str:
    """Percentiles of the point-to-plane residuals of the final ICP pairs."""
    a = np.abs(res.residuals_m)
    q = np.percentile(a, [50, 68.3, 90, 95, 99])
    sec = table(["pairs", "mean |r| m", "median", "68.3 %", "90 %", "95 %", "99 %", "max"],
                [[a.size, num(a.mean(), ".4f")] + [num(v, ".4f") for v in q] + [num(a.max(), ".4f")]],
                numeric=range(0, 8))
    sec += "<p class='sub'>Point-to-plane residuals |(R p + t − q)·n| of the final ICP pairs (gate " \
           f"{res.params.icp.max_correspondence_m:g} m).</p>"
    return sec


def _trajectory_section(res) -> str:
    """Up to 15 poses of the sensor trajectory in the map and the CRS, with their 1σ."""
    tm = res.trajectory_map
    n = len(tm.times_s)
    pick = sorted(set(np.linspace(0, n - 1, min(n, 15)).round().astype(int).tolist()))
    trows = []
    for i in pick:
        p_i = tm.poses[i, :3, 3]
        row = [f"{tm.times_s[i]:.2f}", f"{p_i[0]:.3f}", f"{p_i[1]:.3f}", f"{p_i[2]:.3f}"]
        if res.trajectory_geo is not None:
            e = res.trajectory_geo.poses[i, :3, 3] + res.trajectory_geo.origin
            row += [f"{e[0]:.3f}", f"{e[1]:.3f}", f"{e[2]:.3f}"]
        s_i = res.trajectory_sigma_m[i] if res.trajectory_sigma_m is not None else math.inf
        row.append(num(s_i, ".4f"))
        trows.append(row)
    hdr = ["t (s)", "x map", "y map", "z map"] + (["E", "N", "H"] if res.trajectory_geo is not None else []) \
        + ["1σ 3-D m"]
    return (f"<p>{n} poses; {len(pick)} shown (all in trajectory_global.csv).</p>"
            + table(hdr, trows, numeric=range(len(hdr))))


def _parameters_section(res, prepared, profile) -> tuple[str, str]:
    """Title and table of the parameters used: profile, effective values, every field."""
    p = res.params
    label = profile_label(p, prepared.params, profile)
    prow = [("profile", label), ("effective values", describe_params(p, prepared.params))]
    prow += [(k, v) for k, v in to_jsonable(_flat_params(p)).items() if k not in ("features", "ransac")]
    prow += [(f"features.{k}", v) for k, v in to_jsonable(asdict(p.features)).items()]
    prow += [(f"ransac.{k}", v) for k, v in to_jsonable(asdict(p.ransac)).items()]
    prow += [(f"map.{k}", v) for k, v in to_jsonable(asdict(prepared.params)).items() if k != "features"]
    prow.append(("seed", res.seed))
    return (f"Parameters used ({label.split(':')[0].split(' (')[0]}; {p.describe_downsampling()}, "
            f"FPFH r {p.features.fpfh_radius_m:g} m, {p.ransac.ransac_n}-point RANSAC, {p.icp.method} ICP)",
            kv_table(prow))


def localize_report_html(res, prepared, *, inputs=None, extra: dict | None = None) -> str:
    """The report page as a string (see the module docstring: no position unless ``ok``)."""
    extra = extra or {}
    ok = res.status == "ok"
    sections = [("Status", _status_section(res))]
    if ok:
        sections.append(("Result", _result_section(res)))
    else:
        sections.append((f"Rejected candidates ({res.status.upper()}: NOT positions)", _rejected_section(res)))
    sections.append(_plan_view_section(res, prepared, ok))
    sections.append(("Hypotheses verified (multi-hypothesis ICP)", _hypotheses_section(res, ok)))
    rsec = _rival_section(res)
    if rsec is not None:
        sections.append(("Whole-map rival search (is there another place that fits?)", rsec))
    if ok and res.residuals_m is not None and res.residuals_m.size:
        sections.append(("Residuals of the final fit", _residuals_section(res)))
    if ok and res.trajectory_map is not None:
        sections.append(("Sensor trajectory in the map / CRS (Eq. 18)", _trajectory_section(res)))
    elif res.trajectory_map is not None:
        sections.append(("Sensor trajectory", f"<p>Not placed: the localization is {esc(res.status.upper())}, so no "
                                              "sensor pose is known (no trajectory_global.csv is written).</p>"))
    sections.append(_parameters_section(res, prepared, extra.get("profile")))
    tim = extra.get("timings_s", res.timings_s)
    sections.append(("Run time (s, wall clock; Numba compile time apart)", _timings_section(tim)))
    irows = [[i.get("path"), i.get("sha256"), i.get("size_bytes")] for i in (inputs or [])]
    vers = extra.get("versions") or {}
    sections.append(("Inputs and provenance", table(["file", "SHA-256", "bytes"], irows)
                     + kv_table([(k, v) for k, v in vers.items()])))
    return page("minegeo localize — global localization report", sections,
                subtitle=f"status {res.status}; CRS {res.crs or 'none'}; seed {res.seed}",
                status=res.status,
                status_text=(f"{position_text(res)} — {res.reason}" if ok and res.position_95_radius_m is not None
                             else res.reason))


def position_text(res) -> str:
    """Position of the scan origin with its 95 % radius: E N H in the CRS when the map is
    georeferenced, else map x y z (metres)."""
    if res.T_crs_scan is not None:
        e, n, h = res.T_crs_scan[:3, 3]
        where = f"{res.crs}: E {e:.3f}  N {n:.3f}  H {h:.3f} m"
    else:
        x, y, z = res.T_map_scan[:3, 3]
        where = f"map frame (not georeferenced): x {x:.3f}  y {y:.3f}  z {z:.3f} m"
    return f"position of the scan origin, {where}; 95 % radius {res.position_95_radius_m:.3f} m"


def write_localize_report(path, res, prepared, *, scan=None, inputs=None, extra: dict | None = None):
    """Write :func:`localize_report_html` to ``path`` atomically."""
    return atomic_write_text(path, localize_report_html(res, prepared, inputs=inputs, extra=extra))
