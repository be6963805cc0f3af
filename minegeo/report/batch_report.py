"""Self-contained HTML reports of ``minegeo localize-batch``.

* :func:`write_batch_report`: ``OUT/report.html``, the batch summary. Status banner (``OK``
  when every scan is ``ok``, ``FAILED`` when none is, ``WARNINGS`` otherwise), status counts,
  a plan view of every placed scan over the map (origins numbered as in the table; failed and
  ambiguous scans have no position and are not drawn), and one table row per scan with a
  relative link to its own ``report.html``.
* :func:`write_scan_failure_report`: ``OUT/<scan>/report.html`` of a scan that could not be
  localized at all (unreadable, empty, not a point cloud, worker died): the ``FAILED`` banner
  and the reason (a scan that was localized gets ``minegeo localize``'s own report).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import (
    NO_PLOT,
    badge,
    esc,
    img_png,
    kv_table,
    num,
    page,
    params_table,
    status_word,
    table,
)

__all__ = ["batch_status", "plot_batch_png", "batch_report_html", "write_batch_report", "write_scan_failure_report"]


def batch_status(counts: dict) -> tuple[str, str]:
    """Banner word and text from the status counts (``ok``, ``ambiguous``, ``failed``)."""
    n = sum(counts.values())
    text = f"{counts.get('ok', 0)} of {n} scans ok, {counts.get('ambiguous', 0)} ambiguous, " \
           f"{counts.get('failed', 0)} failed"
    if n and counts.get("ok", 0) == n:
        return "OK", text
    if not counts.get("ok", 0):
        return "FAILED", text
    return "WARNINGS", text


def plot_batch_png(rows, prepared, max_map_points: int = 40000) -> bytes | None:
    """Plan view (PNG bytes; None without matplotlib): the map in grey and the origin of every
    ``ok`` scan, numbered by its row in the table."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    from minegeo.report.localize_report import _frame_xy, label_offsets, map_plot_points, plan_axis_labels

    g = prepared.georef_result
    M = map_plot_points(prepared, max_map_points)
    Mx = _frame_xy(g, M)
    fig = Figure(figsize=(9, 6.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(Mx[:, 0], Mx[:, 1], s=0.15, c="0.7", linewidths=0)
    ax.scatter([], [], s=12, c="0.7", label="map (downsampled)")
    placed = [(k, np.asarray(r["T_map_scan"], dtype=np.float64)) for k, r in enumerate(rows, 1)
              if r.get("T_map_scan") is not None]
    if placed:
        O = _frame_xy(g, np.array([T[:3, 3] for _, T in placed]))
        X = _frame_xy(g, np.array([T[:3, 3] + 4.0 * T[:3, 0] for _, T in placed]))
        ax.plot(O[:, 0], O[:, 1], "o", c="tab:green", ms=5, label="scan origin (ok)")
        sep = 0.04 * float(max(np.ptp(Mx[:, 0]), np.ptp(Mx[:, 1]), 1.0)) if len(Mx) else 1.0
        for (k, _), o, x, off in zip(placed, O, X, label_offsets(O[:, :2], sep, step_pt=9.0), strict=True):
            ax.plot([o[0], x[0]], [o[1], x[1]], "-", c="tab:green", lw=1.0)
            ax.annotate(str(k), o[:2], xytext=off, textcoords="offset points", fontsize=7, color="tab:green")
    ax.set_title(f"{len(placed)} of {len(rows)} scans placed (ok); line: scan x axis")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, color="0.92")
    plan_axis_labels(ax, g)
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def batch_report_html(record: dict, rows, prepared) -> str:
    """HTML text of the batch summary (``record``: the ``batch_result.json`` record)."""
    status, text = batch_status(record["counts"])
    crs = record.get("frame") == "crs"
    frame = "CRS " + str(record.get("crs")) if crs else "map frame"
    xyz = ["E", "N", "H"] if crs else ["x", "y", "z"]
    body = []
    for k, r in enumerate(rows, 1):
        w = status_word(r["status"])
        link = f"{r['folder']}/report.html"
        body.append([str(k), Path(r["scan"]).name, badge(w, {"OK": True}.get(w, False)), r["reason"],
                     num(r["E"], ".3f"), num(r["N"], ".3f"), num(r["H"], ".3f"), num(r["heading"], ".2f"),
                     num(r["radius95_m"], ".3f"), num(r["time_s"], ".2f"), "yes" if r.get("resumed") else "",
                     f'<a href="{esc(link)}">{esc(link)}</a>'])
    counts = record["counts"]
    png = plot_batch_png(rows, prepared)
    t = record.get("timings_s") or {}
    secs = [
        ("Status counts", kv_table([("ok (placed)", counts.get("ok", 0)), ("ambiguous (no position)",
                                                                           counts.get("ambiguous", 0)),
                                    ("failed (no position)", counts.get("failed", 0)),
                                    ("taken from an earlier run (resumed)", record.get("n_resumed", 0)),
                                    ("run now", record.get("n_run", 0)),
                                    ("wall time of this run", f"{t.get('wall_s', 0.0):.1f} s"),
                                    ("scans per minute (scans run now)",
                                     num(record.get("scans_per_minute"), ".1f"))])),
        ("Plan view", (img_png(png, "plan view of the placed scans") if png else f"<p>{esc(NO_PLOT)}</p>")
         + f"<p class=\"small\">Coordinates in the {esc(frame)}. Only <b>ok</b> scans have a position; "
           "ambiguous and failed scans are not drawn.</p>"),
        ("Scans", table(["#", "scan", "status", "reason", *xyz, "heading (deg)", "95 % radius (m)", "time (s)",
                         "resumed", "scan report"], body, numeric=[0, 4, 5, 6, 7, 8, 9], raw_cols=[2, 11])
         + f"<p class=\"small\">{', '.join(xyz)}: the scan origin "
           + ("in the CRS; heading: azimuth of the scan's x axis, degrees clockwise from grid north"
              if crs else "in the map frame (the map is not georeferenced); heading: azimuth of the scan's x axis, "
                          "degrees clockwise from the map's +y")
           + ". Each link opens the scan's own report (as minegeo localize writes it).</p>"),
        ("Parameters used", params_table({"seed": record.get("seed"), "profile": record.get("profile"),
                                          "workers": record.get("workers"), "scheduler": record.get("scheduler"),
                                          "localize": record["params"]["localize"]})),
    ]
    return page("minegeo localize-batch", secs, subtitle=f"{len(rows)} scans in {record['inputs'][0]['path']}",
                status=status, status_text=text)


def write_batch_report(path, record: dict, rows, prepared) -> Path:
    """Write :func:`batch_report_html` to ``path`` atomically."""
    return atomic_write_text(Path(path), batch_report_html(record, rows, prepared))


def write_scan_failure_report(path, record: dict) -> Path:
    """Write the FAILED report of a scan that could not be localized (``record``: its result.json)."""
    err = record.get("error") or {}
    inp = record.get("inputs") or []
    secs = [
        ("Why", f"<p><b>NO POSITION.</b> {esc(record.get('reason'))}</p>"
                + kv_table([("error kind", err.get("kind")), ("error type", err.get("type")),
                            ("what happens on the next run", "redone" if err.get("kind") == "crash" else
                             "kept (redone only when the scan file changes)")])),
        ("Inputs", table(["input", "path", "SHA-256"], [[str(k), r.get("path"), r.get("sha256") or "n/a"]
                                                        for k, r in zip(("map", "scan"), inp, strict=False)])),
        ("Parameters used", params_table({"seed": record.get("seed"), "profile": record.get("profile"),
                                          "localize": (record.get("params") or {}).get("localize")})),
    ]
    return atomic_write_text(Path(path), page("minegeo localize-batch: scan", secs,
                                              subtitle=str(inp[1].get("path")) if len(inp) > 1 else "",
                                              status="FAILED", status_text=str(record.get("reason"))[:300]))
