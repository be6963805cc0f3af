"""Self-contained HTML summary of ``minegeo demo``: each step, its time, its answer against the truth.

``OUT/report.html`` opens with the status banner (``OK`` when every step gave an ``ok`` result,
``WARNINGS`` when a step's result is ``warning`` or ``ambiguous``, ``FAILED`` when a step failed
or could not run), then one table row per step with a relative link to that step's own
``report.html`` (the folder can be moved or archived whole), and the parameters of the run.
"""

from __future__ import annotations

from pathlib import Path

from minegeo._provenance import atomic_write_text
from minegeo.report._html import badge, esc, page, params_table, status_word, table

__all__ = ["demo_status", "demo_report_html", "write_demo_report"]

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


def demo_report_html(rows, seed: int, total_s: float | None = None, parameters: dict | None = None) -> str:
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
        body.append(["<b>total</b>", f"{total_s:.1f} s", "", "includes one-time Numba compilation on a fresh "
                     "install", ""])
    secs = [
        ("Steps", table(["step", "time", "status", "result against the synthetic truth", "step report"], body,
                        numeric=[1], raw_cols=[0, 2, 4])
         + "<p class=\"small\">Each link opens that step's own report (relative to this folder).</p>"),
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


def write_demo_report(path, rows, seed: int, total_s: float | None = None, parameters: dict | None = None) -> Path:
    """Write the demo summary (:func:`demo_report_html`) to ``path`` atomically and return the path."""
    return atomic_write_text(Path(path), demo_report_html(rows, seed, total_s, parameters))
