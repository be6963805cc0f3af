"""``MAP.npz.report.html``: the report of ``minegeo prepare-map`` (self-contained, status first).

What a surveyor checks before localizing against a prepared map: which map file it came from
(path, SHA-256, point count, georeferencing and CRS), what was kept (downsampled feature points,
ICP points), the parameters it was prepared with (they must match the ones ``minegeo localize``
uses), a plan view of the feature points, and the run time with the Numba compile time apart.
"""

from __future__ import annotations

import io

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import NO_PLOT, esc, img_png, kv_table, page, params_table, table, timings_html

__all__ = ["plot_prepared_png", "prepare_report_html", "write_prepare_report"]


def plot_prepared_png(points_map: np.ndarray, max_points: int = 20000, seed: int = 0) -> bytes | None:
    """Plan view (x, y in the map frame, m) of the feature points coloured by height; None without matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    P = np.asarray(points_map, dtype=np.float64)
    if P.shape[0] > max_points:  # a seeded, evenly drawn subset keeps the figure light
        P = P[np.sort(np.random.default_rng(seed).choice(P.shape[0], max_points, replace=False))]
    fig = Figure(figsize=(8, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    sc = ax.scatter(P[:, 0], P[:, 1], c=P[:, 2], s=1.0, cmap="viridis", linewidths=0)
    fig.colorbar(sc, ax=ax, label="height z (m, map frame)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, map frame)")
    ax.set_ylabel("y (m, map frame)")
    ax.set_title("prepared map: feature points (plan view)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def prepare_report_html(record: dict, png: bytes | None = None) -> str:
    """HTML text of the report from the ``MAP.npz.json`` record written by ``minegeo prepare-map``."""
    src = (record.get("inputs") or [{}])[0]
    summary = [
        ("map file", src.get("path")),
        ("map SHA-256", src.get("sha256")),
        ("map points read", f"{record.get('n_points', 0):,}"),
        ("feature points kept (downsampled)", f"{record.get('n_down', 0):,}"),
        ("ICP points kept", f"{record.get('n_icp_points', 0):,}"),
        ("profile", record.get("profile")),
        ("georeferenced", "yes" if record.get("georeferenced") else "no (local map frame)"),
        ("CRS", record.get("crs") or "none"),
        ("work origin (m)", ", ".join(f"{v:.3f}" for v in np.asarray(record.get("work_origin", [0, 0, 0]), float))),
        ("parameter hash", record.get("params_hash")),
        ("prepared map written", record.get("out")),
    ]
    secs = [
        ("Summary", kv_table(summary)),
        ("Plan view", img_png(png, "feature points of the prepared map") if png else f"<p>{esc(NO_PLOT)}</p>"),
        ("Parameters used", params_table(record.get("params") or {})),
    ]
    timings = record.get("timings_s") or {}
    secs.append(("Run time (s; Numba compile time apart)", timings_html(timings)))
    structs = timings.get("search_structures") or {}
    if structs:
        secs.append(("Search structures stored (build time, s)",
                     table(["structure", "seconds"], [(k, f"{float(v):.3f}") for k, v in structs.items()], numeric=[1])))
    vers = record.get("versions") or {}
    secs.append(("Provenance", kv_table(sorted(vers.items()))))
    return page("Prepared map for localization", secs, subtitle=str(src.get("path", "")),
                status=str(record.get("status", "ok")),
                status_text=f"{record.get('n_down', 0):,} feature points, profile {record.get('profile')}")


def write_prepare_report(path, record: dict, points_map: np.ndarray | None = None):
    """Write the report atomically and return its path (plan view when matplotlib is available)."""
    png = plot_prepared_png(points_map) if points_map is not None and len(points_map) else None
    return atomic_write_text(path, prepare_report_html(record, png))
