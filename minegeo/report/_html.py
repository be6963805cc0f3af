"""Tiny dependency-free HTML helpers for minegeo reports (shared; use from any report module).

Usage::

    from minegeo.report._html import page, table, esc, kv_table
    body = [("Summary", kv_table([("sigma0", "1.02"), ("chi-square test", "PASSED")])),
            ("Points", table(["id", "E (m)"], [["A", "1000.000"]], numeric=[1]))]
    html = page("My report", body, subtitle="input.dat")

* :func:`esc` — HTML-escape any value (``None`` -> empty).
* :func:`num` — a number formatted with ``fmt``, or ``n/a`` (None, text, NaN, inf).
* :func:`table` — ``<table>`` from headers and rows; ``numeric`` column indices are right
  aligned in a monospace font; ``row_classes`` marks rows (``"flag"`` renders red).
* :func:`kv_table` — two-column key/value table.
* :func:`page` — full standalone page (inline CSS, no scripts, prints well) from
  ``[(section title, section html), ...]``; section titles become ``<h2>`` with anchors.
* :func:`badge` — coloured PASSED/FAILED style label (``ok=True/False/None``).
* :func:`status_banner` — the report's first line, ``STATUS: OK/FAILED/AMBIGUOUS ...`` (``page(status=...)``).
* :func:`img_png` — an embedded PNG figure (``data:`` URI).
* :func:`params_table` — "Parameters used" table from a (nested) mapping or dataclass.
* :func:`status_word` — a result's ``status`` (``ok``, ``warning``, ``failed`` ...) as a banner word.
* :data:`CSS` — the shared style sheet (for report modules that build their own page).
* :data:`NO_PLOT` — the sentence a report shows instead of a figure when matplotlib is missing.
"""

from __future__ import annotations

import html
import math
import re

__all__ = ["esc", "num", "table", "kv_table", "page", "badge", "status_banner", "img_png", "timings_html", "params_table",
           "status_word", "CSS", "NO_PLOT"]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{font-size:1.5em;border-bottom:2px solid #444;padding-bottom:.2em}
h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #bbb}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top}
th{background:#f0f0f0}
td.num{text-align:right;font-family:ui-monospace,Menlo,Consolas,monospace;white-space:nowrap}
tr.flag td{background:#fde8e8}
.badge{display:inline-block;padding:.1em .6em;border-radius:.3em;font-weight:bold;color:#fff}
.ok{background:#2e7d32}.bad{background:#c62828}.na{background:#777}
.sub{color:#555}
pre{background:#f7f7f7;padding:.6em;overflow-x:auto}
.status{font-size:1.6em;font-weight:bold;color:#fff;padding:.4em .6em;border-radius:.3em;margin:0 0 .6em 0}
.status.na{background:#b26a00}
figure{margin:.5em 0 1em 0}figcaption{color:#555;font-size:.9em}
.small{color:#555;font-size:.9em}tr.warn td{background:#fff4d6}
@media print{body{margin:0;max-width:none}}
"""


#: The shared style sheet (inline in every report).
CSS = _CSS

#: What a report says in place of a figure when matplotlib (the ``report`` extra) is missing.
NO_PLOT = "(no plot: matplotlib is not installed; pip install 'minegeo[report]')"


def esc(value) -> str:
    """HTML-escaped text of ``value`` (``None`` -> ``""``)."""
    return "" if value is None else html.escape(str(value), quote=True)


def num(value, fmt: str) -> str:
    """``value`` formatted with ``fmt``; ``"n/a"`` when it is not a finite number (None, text, NaN, inf)."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return "n/a"
    return "n/a" if not math.isfinite(f) else format(f, fmt)


def badge(text: str, ok: bool | None) -> str:
    """Coloured label: green when ``ok``, red when False, grey when None."""
    cls = "na" if ok is None else ("ok" if ok else "bad")
    return f'<span class="badge {cls}">{esc(text)}</span>'


def table(headers, rows, numeric=(), row_classes=None, raw_cols=()) -> str:
    """HTML table. ``numeric``: right-aligned monospace column indices; ``raw_cols``: cells already HTML."""
    num = set(numeric)
    raw = set(raw_cols)
    out = ["<table><thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in headers) + "</tr></thead><tbody>"]
    for i, row in enumerate(rows):
        cls = row_classes[i] if row_classes else ""
        cells = []
        for j, c in enumerate(row):
            txt = c if j in raw else esc(c)
            cells.append(f'<td class="num">{txt}</td>' if j in num else f"<td>{txt}</td>")
        out.append(
            f'<tr class="{esc(cls)}">' + "".join(cells) + "</tr>"
            if cls
            else "<tr>" + "".join(cells) + "</tr>"
        )
    out.append("</tbody></table>")
    return "\n".join(out)


def kv_table(items) -> str:
    """Two-column key/value table from ``[(key, value), ...]`` (values are escaped)."""
    return (
        "<table><tbody>"
        + "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in items)
        + "</tbody></table>"
    )


def _anchor(title: str) -> str:
    a = re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")
    return "status-section" if a == "status" else a  # id "status" is the banner's


#: Status words shown in the banner, and whether each is good (green), bad (red) or neither.
_STATUS_OK = {"OK": True, "PASSED": True, "WARNINGS": None, "AMBIGUOUS": False, "FAILED": False, "ERROR": False}


def status_banner(status: str, text: str = "") -> str:
    """The first line of every report: ``STATUS: OK`` / ``FAILED`` / ``AMBIGUOUS`` ... in a coloured band.

    The element carries ``id="status"`` and ``data-status="<STATUS>"`` so tests (and a browser)
    find it; a FAILED or AMBIGUOUS result is red and says so in capitals before anything else.
    """
    word = str(status).upper()
    ok = _STATUS_OK.get(word)
    cls = "na" if ok is None else ("ok" if ok else "bad")
    extra = f" — {esc(text)}" if text else ""
    return (f'<div id="status" class="status {cls}" data-status="{esc(word)}" role="status">'
            f"STATUS: {esc(word)}{extra}</div>")


def img_png(png: bytes | None, alt: str, width: str = "100%") -> str:
    """An embedded PNG (``data:`` URI, no external file); an empty string when ``png`` is None."""
    import base64

    if not png:
        return ""
    b64 = base64.b64encode(png).decode("ascii")
    return f'<img alt="{esc(alt)}" src="data:image/png;base64,{b64}" style="max-width:{esc(width)}">'


_STATUS_WORDS = {"ok": "OK", "passed": "PASSED", "warning": "WARNINGS", "warnings": "WARNINGS",
                 "ambiguous": "AMBIGUOUS", "failed": "FAILED", "error": "ERROR"}


def status_word(status) -> str:
    """Banner word of a result status: ``ok`` -> ``OK``, ``warning`` -> ``WARNINGS``, ``failed`` -> ``FAILED``.

    Unknown values are upper-cased unchanged.
    """
    s = str(status).strip()
    return _STATUS_WORDS.get(s.lower(), s.upper())


def _flat(prefix: str, value, out: list) -> None:
    import dataclasses

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        if not value:
            out.append((prefix, "{}"))
        for k, v in value.items():
            _flat(f"{prefix}.{k}" if prefix else str(k), v, out)
        return
    if isinstance(value, (list, tuple)):
        value = ", ".join(str(v) for v in value) if value else "(none)"
    elif value is None:
        value = "None (not given)"
    out.append((prefix, value))


def params_table(params, skip=()) -> str:
    """Key/value table of the parameters a run used (nested keys flattened as ``a.b``).

    Parameters
    ----------
    params : mapping or dataclass
        The parameters actually used (not the defaults).
    skip : iterable of str
        Top-level keys left out (e.g. ``"timings_s"``).
    """
    import dataclasses

    if dataclasses.is_dataclass(params) and not isinstance(params, type):
        params = dataclasses.asdict(params)
    rows: list = []
    for k, v in dict(params or {}).items():
        if k not in set(skip):
            _flat(str(k), v, rows)
    if not rows:
        return "<p>(none recorded)</p>"
    return kv_table(rows)


def page(title: str, sections, subtitle: str = "", *, status: str | None = None, status_text: str = "") -> str:
    """Standalone HTML page from ``[(section title, html), ...]`` with a table of contents.

    With ``status`` the page opens with :func:`status_banner` (before the title), so nobody can
    miss a FAILED or AMBIGUOUS result. The page has no scripts and no external resources.
    """
    toc = "".join(f'<li><a href="#{_anchor(t)}">{esc(t)}</a></li>' for t, _ in sections)
    body = "\n".join(f'<h2 id="{_anchor(t)}">{esc(t)}</h2>\n{h}' for t, h in sections)
    sub = f'<p class="sub">{esc(subtitle)}</p>' if subtitle else ""
    banner = status_banner(status, status_text) if status is not None else ""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{esc((str(status).upper() + ': ') if status is not None else '')}{esc(title)}</title>"
        f"<style>{_CSS}</style></head><body>\n"
        f"{banner}<h1>{esc(title)}</h1>{sub}<ol>{toc}</ol>\n{body}\n</body></html>\n"
    )


def timings_html(timings: dict | None) -> str:
    """The "Run time" table of a report: each stage (s) and the run's wall time with the Numba
    compile time apart (``wall_s``, ``compile_s``, ``work_s`` from :func:`minegeo._output.run_timings`).
    Empty string when ``timings`` is None."""
    if not timings:
        return ""
    run = {k: timings[k] for k in ("wall_s", "compile_s", "work_s") if k in timings}
    stages = [(k, v) for k, v in timings.items() if k not in run and isinstance(v, (int, float))]
    rows = [(k, f"{float(v):.3f}") for k, v in stages]
    if run:
        rows += [("whole run, wall clock", f"{float(run.get('wall_s', 0.0)):.3f}"),
                 ("  of it compiling Numba kernels (once; cached afterwards)", f"{float(run.get('compile_s', 0.0)):.3f}"),
                 ("  of it work", f"{float(run.get('work_s', 0.0)):.3f}")]
    return table(["stage", "seconds"], rows, numeric=[1])
