"""Self-contained HTML report of a global localization (``minegeo localize``).

One page a surveyor can file: the status and its explanation, the scan origin in the map and
the CRS with its uncertainty, a plan view (map + placed scan + trajectory, embedded PNG), the
verified hypotheses, the residuals of the final fit, the trajectory in the CRS, the
parameters, timings and input hashes.
"""

from __future__ import annotations

import base64
import io
import math
from dataclasses import asdict

import numpy as np

from minegeo._provenance import atomic_write_text, to_jsonable
from minegeo.report._html import badge, esc, kv_table, page, table

__all__ = ["plot_localization_png", "localize_report_html", "write_localize_report"]

_STATUS_TEXT = {
    "ok": "The scan was placed in the map; no competing placement fits nearly as well and the geometry "
          "constrains all six pose directions. The coordinates below can be used with the stated uncertainty.",
    "ambiguous": "A placement was found but it is NOT unique: another placement fits almost as well (a "
                 "repeated drift), or the geometry leaves a direction unconstrained (e.g. a straight "
                 "featureless drift). Do not use the coordinates without independent confirmation; re-scan a "
                 "longer section including a distinctive feature (intersection, curve, structure).",
    "failed": "No placement of the scan fits the map well enough. The scan may be outside the mapped area, "
              "the drift may have changed since mapping, or the scan is too short or too noisy. The pose "
              "shown (if any) is the best attempt only and must not be used.",
}


def _n(v, fmt: str) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return "n/a"
    return "n/a" if not math.isfinite(f) else format(f, fmt)


def _frame_xy(g, pts_map: np.ndarray):
    """Plan coordinates for plotting: geo frame (CRS − origin) if georeferenced (``g``), else map."""
    if g is not None:
        from minegeo.localize.georef import map_to_crs

        return map_to_crs(pts_map, g, allow_failed=True)
    return pts_map


def plot_localization_png(res, prepared, max_map_points: int = 40000, seed: int = 0) -> bytes | None:
    """Plan view of map (grey), placed scan (status colour) and trajectory, as PNG bytes (None without matplotlib)."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    g = prepared.georef_result
    M = prepared.points_map()
    if M.shape[0] > max_map_points:
        idx = np.sort(np.random.default_rng(seed).choice(M.shape[0], max_map_points, replace=False))
        M = M[idx]
    S = res.scan_points_down if res.scan_points_down is not None else np.zeros((0, 3))
    T = res.T_map_scan
    Sm = S @ T[:3, :3].T + T[:3, 3]
    Mx = _frame_xy(g, M)
    Sx = _frame_xy(g, Sm)
    colour = {"ok": "tab:green", "ambiguous": "tab:orange", "failed": "tab:red"}[res.status]
    fig = Figure(figsize=(11, 5.2), dpi=100)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)]
    for k, ax in enumerate(axes):
        ax.scatter(Mx[:, 0], Mx[:, 1], s=0.15, c="0.7", linewidths=0)
        ax.scatter(Sx[:, 0], Sx[:, 1], s=0.6, c=colour, linewidths=0)
        ax.scatter([], [], s=12, c="0.7", label="map (downsampled)")  # legend proxies
        ax.scatter([], [], s=12, c=colour, label=f"scan placed ({res.status})")
        if res.trajectory_map is not None:
            P = _frame_xy(g, res.trajectory_map.poses[:, :3, 3])
            ax.plot(P[:, 0], P[:, 1], "-", c="tab:blue", lw=1.2, label="sensor trajectory")
            ax.plot(P[0, 0], P[0, 1], "o", c="tab:blue", ms=4)
        o = _frame_xy(g, T[:3, 3].reshape(1, 3))[0]
        ax.plot(o[0], o[1], "k+", ms=10, mew=1.5, label="scan origin")
        if k == 1 and Sx.shape[0]:
            c = Sx[:, :2].mean(axis=0)
            r = max(float(np.max(np.ptp(Sx[:, :2], axis=0))) * 0.75, 5.0)
            ax.set_xlim(c[0] - r, c[0] + r)
            ax.set_ylim(c[1] - r, c[1] + r)
            ax.set_title("detail")
        else:
            ax.set_title("overview")
        ax.set_aspect("equal", adjustable="box" if k == 1 else "datalim")
        ax.grid(True, color="0.92")
        if g is not None:
            ax.set_xlabel(f"E − {g.origin[0]:.0f} m")
            ax.set_ylabel(f"N − {g.origin[1]:.0f} m")
        else:
            ax.set_xlabel("x map (m)")
            ax.set_ylabel("y map (m)")
    axes[0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _uncertainty_text(u: dict | None) -> str:
    """One paragraph saying which covariance estimator the numbers above come from."""
    if not u:
        return "No covariance: the fit leaves a pose direction unconstrained."
    method = u.get("method")
    base = ("Uncertainty: covariance of the final point-to-plane fit about the scan origin, from the "
            "final ICP pairs")
    if method == "jackknife":
        txt = (f"{base}, by the delete-one-block jackknife over {u.get('n_clusters')} blocks of "
               f"{_n(u.get('cluster_size_used_m'), 'g')} m (neighbouring residuals are correlated; it is "
               f"{_n(u.get('inflation'), '.1f')}x the formal σ²(JᵀJ)⁻¹ in position), never below the formal one")
    elif method == "cluster":
        txt = (f"{base}, cluster-robust over {u.get('n_clusters')} blocks of "
               f"{_n(u.get('cluster_size_used_m'), 'g')} m, never below the formal σ²(JᵀJ)⁻¹")
    else:
        txt = f"{base}, formal σ²(JᵀJ)⁻¹ (independent residuals assumed: optimistic)"
    if u.get("params", {}).get("add_pending_step"):
        txt += "; plus the remaining Gauss-Newton step"
    if u.get("weak_axis_polish_term"):
        txt += ("; plus the polish's pose shift along the weakly constrained direction (the estimate depends "
                "on the correspondence gate there)")
    return txt + ". It excludes the map's own error and the georeferencing error (docs/uncertainty.md)."


def _mat(T) -> str:
    if T is None:
        return "n/a"
    return "<pre>" + esc("\n".join(" ".join(f"{v:14.6f}" for v in row) for row in np.asarray(T))) + "</pre>"


def localize_report_html(res, prepared, *, inputs=None, extra: dict | None = None) -> str:
    """The report page as a string."""
    extra = extra or {}
    sections = []
    head = (f"<p>{badge(res.status.upper(), {'ok': True, 'failed': False}.get(res.status))} "
            f"{esc(res.reason)}</p><p>{esc(_STATUS_TEXT[res.status])}</p>")
    if res.warnings:
        head += "<ul>" + "".join(f"<li>{esc(w)}</li>" for w in res.warnings) + "</ul>"
    sections.append(("Status", head))

    rows = [("frame of T_map_scan", "map frame of the prior map before georeferencing (p_map = R p_scan + t)")]
    t = res.T_map_scan[:3, 3]
    rows.append(("scan origin, map frame (m)", f"{t[0]:.3f}  {t[1]:.3f}  {t[2]:.3f}"))
    if res.T_crs_scan is not None:
        c = res.T_crs_scan[:3, 3]
        rows.append((f"scan origin, CRS {res.crs} (E N H, m)", f"{c[0]:.3f}  {c[1]:.3f}  {c[2]:.3f}"))
    s = res.position_sigma_m
    rows.append(("1σ of the scan origin x, y, z (m)", "  ".join(_n(v, ".4f") for v in s)))
    rows.append(("95 % radius 3-D (m)", f"{_n(res.position_95_radius_m, '.4f')}  (= sqrt(7.815 λmax), χ²₃)"))
    rows.append(("95 % radius horizontal (m)", f"{_n(res.horizontal_95_radius_m, '.4f')}  (= sqrt(5.991 λmax), χ²₂)"))
    rows.append(("σ of one residual (m)", _n(res.sigma_m, ".4f")))
    rows.append(("final fitness / inlier RMSE (Eq. 19)", f"{_n(res.fitness, '.4f')} / {_n(res.inlier_rmse_m, '.4f')} m"))
    rows.append(("scan points: read / features / ICP", f"{res.n_scan_points} / {res.n_scan_down} / {res.n_scan_icp}"))
    sec = kv_table(rows)
    sec += f"<p class='sub'>{esc(_uncertainty_text(res.uncertainty))}</p>"
    sec += "<h3>T_map_scan</h3>" + _mat(res.T_map_scan)
    if res.T_crs_scan is not None:
        sec += f"<h3>T_crs_scan (full {esc(res.crs)} coordinates)</h3>" + _mat(res.T_crs_scan)
    sections.append(("Result", sec))

    png = plot_localization_png(res, prepared, seed=res.seed)
    if png is None:
        sections.append(("Plan view", "<p>matplotlib is not installed: no plot.</p>"))
    else:
        b64 = base64.b64encode(png).decode("ascii")
        sections.append(("Plan view", f'<img alt="plan view" style="max-width:100%" src="data:image/png;base64,{b64}">'))

    hrows = []
    for h in res.hypotheses:
        hrows.append([h["rank"], h["source"], _n(h["ransac_fitness"], ".3f"), _n(h["ransac_inlier_rmse_m"], ".3f"),
                      _n(h["icp_fitness"], ".3f"), _n(h["icp_inlier_rmse_m"], ".3f"), _n(h["plane_fitness"], ".3f"),
                      _n(h["plane_rmse_m"], ".3f"), _n(h["distance_to_chosen_m"], ".2f"),
                      _n(h["rotation_to_chosen_deg"], ".2f")])
    r = res.ransac
    sec = table(["rank", "hypothesis", "RANSAC fitness", "RANSAC RMSE m", "ICP fitness", "ICP RMSE m",
                 "plane fitness", "plane RMSE m", "distance to chosen m", "rotation to chosen °"], hrows,
                numeric=range(2, 10))
    if r is not None:
        sec += kv_table([
            ("RANSAC iterations / validations", f"{r.iterations} / {r.n_validations} ({r.status})"),
            ("putative FPFH correspondences", int(r.correspondences.shape[0])),
            ("runner-up score ratio / distance", f"{_n(r.ambiguity_ratio, '.3f')} / {_n(r.second_best_distance_m, '.1f')} m"),
        ])
    if res.icp is not None:
        ic = res.icp
        sec += kv_table([
            ("ICP method / iterations / converged", f"{res.params.icp_method} / {ic.iterations} / {ic.converged}"),
            ("constraint eigenvalue ratio (degenerate below "
             f"{res.params.degeneracy_ratio:g})", _n(ic.degeneracy_ratio, ".4f")),
            ("degeneracy", ic.degeneracy_reason or "none"),
        ])
    sections.append(("Hypotheses verified (multi-hypothesis ICP)", sec))

    if res.residuals_m is not None and res.residuals_m.size:
        a = np.abs(res.residuals_m)
        q = np.percentile(a, [50, 68.3, 90, 95, 99])
        sec = table(["pairs", "mean |r| m", "median", "68.3 %", "90 %", "95 %", "99 %", "max"],
                    [[a.size, _n(a.mean(), ".4f")] + [_n(v, ".4f") for v in q] + [_n(a.max(), ".4f")]],
                    numeric=range(0, 8))
        sec += "<p class='sub'>Point-to-plane residuals |(R p + t − q)·n| of the final ICP pairs (gate " \
               f"{res.params.icp_max_correspondence_m:g} m).</p>"
        sections.append(("Residuals of the final fit", sec))

    if res.trajectory_map is not None:
        tm = res.trajectory_map
        n = len(tm.times_s)
        pick = sorted(set(np.linspace(0, n - 1, min(n, 15)).round().astype(int).tolist()))
        trows = []
        for i in pick:
            p = tm.poses[i, :3, 3]
            row = [f"{tm.times_s[i]:.2f}", f"{p[0]:.3f}", f"{p[1]:.3f}", f"{p[2]:.3f}"]
            if res.trajectory_geo is not None:
                e = res.trajectory_geo.poses[i, :3, 3] + res.trajectory_geo.origin
                row += [f"{e[0]:.3f}", f"{e[1]:.3f}", f"{e[2]:.3f}"]
            s_i = res.trajectory_sigma_m[i] if res.trajectory_sigma_m is not None else math.inf
            row.append(_n(s_i, ".4f"))
            trows.append(row)
        hdr = ["t (s)", "x map", "y map", "z map"] + (["E", "N", "H"] if res.trajectory_geo is not None else []) + ["1σ 3-D m"]
        sections.append(("Sensor trajectory in the map / CRS (Eq. 18)",
                         f"<p>{n} poses; {len(pick)} shown (all in trajectory_global.csv).</p>"
                         + table(hdr, trows, numeric=range(len(hdr)))))

    p = res.params
    prow = [(k, v) for k, v in to_jsonable(asdict(p)).items() if k not in ("features", "ransac")]
    prow += [(f"features.{k}", v) for k, v in to_jsonable(asdict(p.features)).items()]
    prow += [(f"ransac.{k}", v) for k, v in to_jsonable(asdict(p.ransac)).items()]
    prow += [(f"map.{k}", v) for k, v in to_jsonable(asdict(prepared.params)).items() if k != "features"]
    prow.append(("seed", res.seed))
    sections.append(("Parameters (Baek et al. 2022 Table 3 defaults)", kv_table(prow)))
    tim = extra.get("timings_s", res.timings_s)
    sections.append(("Timings (s, wall clock)", table(["stage", "seconds"], [[k, _n(v, ".3f")] for k, v in tim.items()],
                                                   numeric=[1])))
    irows = [[i.get("path"), i.get("sha256"), i.get("size_bytes")] for i in (inputs or [])]
    vers = extra.get("versions") or {}
    sections.append(("Inputs and provenance", table(["file", "SHA-256", "bytes"], irows)
                     + kv_table([(k, v) for k, v in vers.items()])))
    return page("minegeo localize — global localization report", sections,
                subtitle=f"status {res.status}; CRS {res.crs or 'none'}; seed {res.seed}")


def write_localize_report(path, res, prepared, *, scan=None, inputs=None, extra: dict | None = None):
    """Write :func:`localize_report_html` to ``path`` atomically."""
    return atomic_write_text(path, localize_report_html(res, prepared, inputs=inputs, extra=extra))
