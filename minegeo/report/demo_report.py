"""Self-contained HTML summary of ``minegeo demo``: each step, its time, its answer against the truth.

``OUT/report.html`` opens with the status banner (``OK`` when every step gave an ``ok`` result,
``WARNINGS`` when a step's result is ``warning`` or ``ambiguous``, ``FAILED`` when a step failed
or could not run), then one table row per step with a relative link to that step's own
``report.html`` (the folder can be moved or archived whole), and the parameters of the run.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import badge, esc, img_png, page, params_table, status_word, table

__all__ = ["demo_status", "demo_report_html", "write_demo_report", "plot_demo_png"]

_GOOD = {"OK": True, "PASSED": True, "WARNINGS": None, "AMBIGUOUS": False, "FAILED": False, "ERROR": False}


def demo_status(rows) -> tuple[str, str]:
    """Overall status word and reason of the demo from its step rows (see the module docstring)."""
    words = [(r["step"], status_word(r.get("status") or "error")) for r in rows]
    bad = [f"{s} {w}" for s, w in words if w in ("FAILED", "ERROR")]
    warn = [f"{s} {w}" for s, w in words if w in ("WARNINGS", "AMBIGUOUS")]
    n_ok = sum(1 for _, w in words if w in ("OK", "PASSED"))
    text = f"{n_ok} of {len(words)} steps ok" + (f"; {', '.join(bad + warn)}" if bad or warn else "")
    if not words:
        return "FAILED", "no step ran"
    if bad:
        return "FAILED", text
    if warn:
        return "WARNINGS", text
    return "OK", text


def plot_demo_png(p_true, p_slam, scans=(), origin=(0.0, 0.0)) -> bytes:
    """Plan view of the demo in EPSG:5186 (PNG bytes): the true drive, the georeferenced SLAM
    trajectory, and each localized scan's origin against its true origin.

    Parameters
    ----------
    p_true, p_slam : (n, 3) and (m, 3) array_like
        True drive positions and georeferenced SLAM positions (E, N, H in metres, CRS).
    scans : iterable of (name, est (3,), true (3,))
        Localized scans (``est`` None when the scan got no position).
    origin : (2,) array_like
        E, N subtracted for the axes (m).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    o = np.asarray(origin, dtype=np.float64)[:2]
    fig = Figure(figsize=(8.5, 6.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    t = np.asarray(p_true, dtype=np.float64)
    e = np.asarray(p_slam, dtype=np.float64)
    if len(t):
        ax.plot(t[:, 0] - o[0], t[:, 1] - o[1], "-", c="0.55", lw=2.5, label="true drive (synthetic truth)")
    if len(e):
        ax.plot(e[:, 0] - o[0], e[:, 1] - o[1], "-", c="tab:blue", lw=1.0, label="SLAM trajectory, georeferenced")
    first = True
    for name, est, true in scans:
        tr = np.asarray(true, dtype=np.float64)
        ax.plot(tr[0] - o[0], tr[1] - o[1], "s", mfc="none", mec="0.2", ms=8,
                label="scan origin, true" if first else None)
        if est is not None:
            es = np.asarray(est, dtype=np.float64)
            ax.plot(es[0] - o[0], es[1] - o[1], "x", c="tab:green", ms=8, mew=2,
                    label="scan origin, localized" if first else None)
        ax.annotate(name, (tr[0] - o[0], tr[1] - o[1]), xytext=(6, 6), textcoords="offset points", fontsize=8)
        first = False
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, color="0.92")
    ax.set_xlabel(f"E − {o[0]:.0f} m (EPSG:5186)")
    ax.set_ylabel(f"N − {o[1]:.0f} m (EPSG:5186)")
    ax.set_title("plan view: the drive, the SLAM trajectory and the localized scans in the grid")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def demo_report_html(rows, seed: int, total_s: float | None = None, parameters: dict | None = None,
                     plan_png: bytes | None = None, compile_s: float | None = None) -> str:
    """HTML text of the demo summary.

    Parameters
    ----------
    rows : list of dict
        One per step: ``step``, ``time_s`` (float or None), ``status`` (``ok``, ``warning``,
        ``ambiguous``, ``failed`` or ``error`` when the step could not run), ``result`` (text:
        the answer against the synthetic truth) and ``report`` (the step's ``report.html``
        relative to the demo folder, POSIX separators, or None).
    seed : int
    total_s : float, optional
        Wall time of the whole demo.
    parameters : dict, optional
        Parameters of the run (shown under "Parameters used").
    plan_png : bytes, optional
        The plan view (:func:`plot_demo_png`).
    compile_s : float, optional
        Seconds of this run spent compiling Numba kernels (0 when every kernel came from the cache).
    """
    status, text = demo_status(rows)
    body = []
    for r in rows:
        w = status_word(r.get("status") or "error")
        link = r.get("report")
        if link:
            link = str(link).replace("\\", "/")
            if ":" in link or link.startswith("/"):
                raise ValueError(f"step report links must be relative paths, got {link!r}")
        body.append([
            esc(r["step"]),
            "–" if r.get("time_s") is None else f"{r['time_s']:.1f} s",
            badge(w, _GOOD.get(w)),
            r.get("result", ""),
            f'<a href="{esc(link)}">{esc(link)}</a>' if link else "–",
        ])
    if total_s is not None:
        note = ("" if compile_s is None else
                f"of which {compile_s:.1f} s compiling numerical kernels (once; cached for later runs)")
        body.append(["<b>total</b>", f"{total_s:.1f} s", "", esc(note), ""])
    secs = [
        ("Steps", table(["step", "time", "status", "result against the synthetic truth", "step report"], body,
                        numeric=[1], raw_cols=[0, 2, 4])
         + "<p class=\"small\">Each link opens that step's own report (relative to this folder).</p>"),
        ("Plan view", img_png(plan_png, "plan view of the drive, the SLAM trajectory and the localized scans")
         if plan_png else "<p>No plan view: the SLAM or georef step did not give a georeferenced trajectory.</p>"),
        ("What the demo does", "<ol><li><b>synth</b>: a small synthetic mine with ground truth.</li>"
                               "<li><b>sequence</b>: VLP-16 frames of a vehicle driving a loop of the mine.</li>"
                               "<li><b>slam</b>: the map and trajectory built from those frames alone.</li>"
                               "<li><b>georef</b>: the SLAM map georeferenced into EPSG:5186 from control "
                               "points read off it.</li>"
                               "<li><b>mast</b>: a 2D scanner positioned from two wall beacons.</li>"
                               "<li><b>localize</b>: the local scans of the mapped drifts and their "
                               "trajectories placed in the georeferenced SLAM map (fast profile).</li></ol>"),
        ("Parameters used", params_table({"seed": seed, **(parameters or {})})),
    ]
    return page("minegeo demo", secs, subtitle=f"the whole chain on the built-in small synthetic mine, seed {seed}",
                status=status, status_text=text)


def write_demo_report(path, rows, seed: int, total_s: float | None = None, parameters: dict | None = None,
                      plan_png: bytes | None = None, compile_s: float | None = None) -> Path:
    """Write the demo summary (:func:`demo_report_html`) to ``path`` atomically and return the path."""
    return atomic_write_text(Path(path), demo_report_html(rows, seed, total_s, parameters, plan_png, compile_s))
