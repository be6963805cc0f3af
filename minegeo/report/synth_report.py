"""Self-contained HTML report of a synthetic mine written by ``minegeo synth``.

``report.html`` sits beside ``truth.json`` and shows what was generated and what the truth is:
the status banner, the world summary, a plan view (map points shaded by height, the local
scans' trajectories placed in the map with their start points, the GCPs; needs matplotlib,
``pip install 'minegeo[report]'``), the scans, the CRS placement (``T_crs_map``), the files with
their SHA-256 and the parameters used.

The page depends only on the folder's files and ``truth.json``: no clock times, no absolute
paths, and a figure rendered without time-dependent metadata, so ``minegeo synth`` with the
same preset and seed still writes byte-identical folders.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import NO_PLOT, esc, img_png, kv_table, page, params_table, table

__all__ = ["plot_synth_png", "synth_report_html", "write_synth_report"]

#: At most this many map points are drawn (every n-th point: deterministic, no random draw).
MAX_PLOT_POINTS = 40000


def _T(m) -> np.ndarray:
    return np.asarray(m, dtype=np.float64).reshape(4, 4)


def _scan_paths(folder: Path, truth: dict) -> list[tuple[str, np.ndarray]]:
    """Each scan's trajectory in the map frame, ``[(name, (m, 3) xyz), ...]`` (the start pose alone for a scan without a trajectory file)."""
    from minegeo.io import read_trajectory

    out = []
    for sc in truth.get("scans", []):
        T = _T(sc["T_map_scan"])
        if sc.get("trajectory"):  # written by the same synth run: an unreadable one is a bug, not hidden
            tr = read_trajectory(folder / sc["trajectory"], frame="scan")
            p = tr.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
        else:  # a scan without a trajectory file: its start pose from truth.json
            p = T[None, :3, 3]
        out.append((sc["name"], p))
    return out


def plot_synth_png(folder, truth: dict) -> bytes | None:
    """Plan view of the synthetic mine in the map frame, as PNG bytes (None without matplotlib).

    Map points (every n-th, at most :data:`MAX_PLOT_POINTS`) shaded by height, each local
    scan's trajectory placed with its true ``T_map_scan`` (start point marked and labelled)
    and the GCPs (triangles). Deterministic: no random subsampling, no time-dependent metadata.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    from minegeo.io import read_gcps, read_point_cloud

    folder = Path(folder)
    fig = Figure(figsize=(10, 8), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if truth.get("map", {}).get("file"):  # the map this synth run wrote (a MAST-only run has none)
        P = read_point_cloud(folder / truth["map"]["file"]).points
        step = max(1, -(-len(P) // MAX_PLOT_POINTS))
        P = P[::step]
        z0, z1 = float(P[:, 2].min()), float(P[:, 2].max())
        r = max(z1 - z0, 1.0)
        # every level visible: the lowest near black, the highest mid grey (not white)
        sc = ax.scatter(P[:, 0], P[:, 1], s=0.4, c=P[:, 2], cmap="Greys_r", vmin=z0 - 0.2 * r, vmax=z1 + 0.6 * r,
                        linewidths=0, rasterized=True)
        cb = fig.colorbar(sc, ax=ax, shrink=0.7, label="map point height z (m)")
        cb.ax.set_ylim(z0, z1)
    colours = ["tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink",
               "tab:olive", "tab:cyan"]
    for i, (name, p) in enumerate(_scan_paths(folder, truth)):
        c = colours[i % len(colours)]
        ax.plot(p[:, 0], p[:, 1], "-", color=c, lw=2, label=f"{name} trajectory")
        ax.plot(p[0, 0], p[0, 1], "o", color=c, ms=7, mec="k")
        ax.annotate(name, (p[0, 0], p[0, 1]), textcoords="offset points", xytext=(6, 6 if i % 2 == 0 else -16),
                    fontsize=9, color=c, fontweight="bold")
    if truth.get("gcps", {}).get("file"):  # the control points this synth run wrote
        g = read_gcps(folder / truth["gcps"]["file"])
        ax.scatter(g.local_xyz[:, 0], g.local_xyz[:, 1], marker="^", s=70, c="gold", edgecolors="k", zorder=4,
                   label="GCP")
        for gid, xy in zip(g.ids, g.local_xyz[:, :2], strict=True):
            ax.annotate(str(gid), tuple(xy), textcoords="offset points", xytext=(5, -10), fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("map x (m)")
    ax.set_ylabel("map y (m)")
    ax.set_title(f"Synthetic mine (preset {truth.get('preset')}, seed {truth.get('seed')}): plan view, map frame")
    ax.grid(True, color="0.92")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=4, fontsize=8, frameon=False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None}, bbox_inches="tight")
    return buf.getvalue()


def synth_report_html(folder, truth: dict, png: bytes | None = None) -> str:
    """HTML text of the report of the synthetic mine in ``folder`` (see the module docstring).

    Parameters
    ----------
    folder : path
        The synth output folder (read for the MAST scenario, if any; only relative names are shown).
    truth : dict
        The content of ``truth.json``.
    png : bytes, optional
        The plan view (:func:`plot_synth_png`).
    """
    folder = Path(folder)
    w = truth.get("world", {})
    n_scans = len(truth.get("scans", []))
    text = (f"synthetic mine written: preset {truth.get('preset')}, seed {truth.get('seed')}, "
            f"{w.get('total_length_m', 0):.0f} m of drifts, {n_scans} local scans; ground truth in truth.json")
    secs = [("Summary", kv_table([
        ("preset / seed", f"{truth.get('preset')} / {truth.get('seed')}"),
        ("drifts", f"{w.get('n_drifts')} ({w.get('total_length_m', 0):.0f} m: "
                   + ", ".join(f"{k} {v:.0f} m" for k, v in w.get("length_by_kind_m", {}).items()) + ")"),
        ("levels / loops / dead ends", f"{w.get('n_levels')} / {w.get('n_loops')} / {w.get('n_dead_ends')}"),
        ("intersections", ", ".join(f"{k} ×{v}" for k, v in w.get("intersections_by_type", {}).items())),
        ("ramp slopes", ", ".join(f"{s:.2f}°" for s in w.get("ramp_slopes_deg", []))),
        ("map", f"{truth['map']['file']}: {truth['map']['n_points']} points (map frame), survey trajectory "
                f"{truth['map']['trajectory']}"),
        ("GCPs", f"{truth['gcps']['file']}: {truth['gcps']['n']} control points in {truth.get('crs')} "
                 f"(σ {1000 * truth['gcps']['sigma_m']:.0f} mm)"),
    ]))]
    if png:
        secs.append(("Plan view", f"<figure>{img_png(png, 'plan view of the synthetic mine')}<figcaption>Map "
                                  "points shaded by height (both levels overlap in plan), local scan "
                                  "trajectories placed with their true T_map_scan (● start), GCPs ▲."
                                  "</figcaption></figure>"))
    else:
        secs.append(("Plan view", f"<p>{esc(NO_PLOT)}</p>"))
    rows = []
    for sc in truth.get("scans", []):
        t = _T(sc["T_map_scan"])[:3, 3]
        rows.append([sc["name"], sc["file"], sc["n_points"], sc["section"], f"{sc['length_m']:.0f}",
                     sc["sensor"]["model"], sc["carrier"], f"{t[0]:.3f}", f"{t[1]:.3f}", f"{t[2]:.3f}",
                     "yes" if sc.get("vehicle_moved_since_map") else "no"])
    secs.append(("Local scans", table(
        ["scan", "file", "points", "section", "length [m]", "sensor", "carrier", "start x [m]", "start y [m]",
         "start z [m]", "vehicle moved since map"], rows, numeric=[2, 4, 7, 8, 9])))
    T = _T(truth["T_crs_map"])
    cp = truth.get("crs_placement", {})
    o = truth.get("origin_enh", [0, 0, 0])
    secs.append(("Ground truth: map → CRS", kv_table([
        ("CRS", truth.get("crs")),
        ("recorded origin (E, N, H)", ", ".join(f"{v:.3f}" for v in o) + " m"),
        ("rotation of the map about the vertical", f"{cp.get('rotation_deg', float('nan')):.6f}°"),
        ("scale / grid scale factor at the site", f"{cp.get('scale')} / {cp.get('grid_scale_factor')}"),
        ("GCP σ", f"{1000 * cp.get('sigma_m', float('nan')):.1f} mm"),
        ("site (lat, lon)", f"{cp.get('lat_deg', float('nan')):.5f}°, {cp.get('lon_deg', float('nan')):.5f}°"),
    ]) + "<p>T<sub>crs_map</sub> (4×4):</p><pre>"
        + esc("\n".join(" ".join(f"{v: .6f}" for v in row) for row in T)) + "</pre>"))
    mast = folder / "mast" / "truth.json"
    if mast.is_file():
        m = json.loads(mast.read_text(encoding="utf-8"))
        secs.append(("MAST beacon scenario (mast/)", kv_table([
            ("files", "mast/scan.csv, mast/beacons.csv, mast/truth.json"),
            ("true scanner position", f"x = {m.get('x_m', float('nan')):.4f} m, y = {m.get('y_m', float('nan')):.4f} m"),
            ("true azimuth", f"{m.get('azimuth_deg', float('nan')):.6f}°"),
        ])))
    files = [[name, sha] for name, sha in sorted(truth.get("files_sha256", {}).items())]
    files += [["truth.json", "(ground truth; holds the hashes above)"], ["report.txt", "(text summary)"],
              ["report.html", "(this report)"]]
    secs.append(("Files", table(["file", "SHA-256"], files)))
    params = {"preset": truth.get("preset"), "seed": truth.get("seed"), "crs": truth.get("crs"),
              "gcps": truth["gcps"]["n"], "world": truth.get("world_params", {})}
    secs.append(("Parameters used", params_table(params)))
    secs.append(("Versions", kv_table(sorted((k, v) for k, v in truth.get("versions", {}).items()
                                             if k != "platform"))))
    return page("Synthetic mine", secs, subtitle="minegeo synth: map, local scans, trajectories, GCPs and truth",
                status="OK", status_text=text)


def write_synth_report(folder, truth: dict | None = None) -> Path:
    """Write ``folder/report.html`` for the synthetic mine in ``folder`` (``truth`` read from ``truth.json`` if None)."""
    folder = Path(folder)
    if truth is None:
        truth = json.loads((folder / "truth.json").read_text(encoding="utf-8"))
    png = plot_synth_png(folder, truth)
    return atomic_write_text(folder / "report.html", synth_report_html(folder, truth, png))
