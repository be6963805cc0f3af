"""Survey-style adjustment report (HTML, text) and result JSON of a network adjustment.

``report.html`` is the report (one self-contained file: inline CSS, the plan view embedded as a
``data:`` PNG, no scripts, no external resources); ``report.txt`` holds the same tables as text
for filing. The HTML page opens with the status banner (:func:`network_status`):

* ``FAILED`` — the χ² global test failed (the residuals do not fit the stated precisions) or
  the iteration did not converge;
* ``WARNINGS`` — the global test passed (or could not be made: no redundancy) but at least one
  observation is flagged by data snooping (w-test, τ-test or "no check");
* ``PASSED`` — the global test passed and no observation is flagged.

The plan view (:func:`plot_network_png`, needs matplotlib: ``pip install 'minegeo[report]'``)
shows the points (control points as triangles), the observation lines (flagged ones in red) and
the error ellipses of the adjusted points at the report's confidence level, exaggerated by a
stated round factor with a scale bar.

Section order follows what surveyors know from adjustment packages (STAR*NET, GNU Gama,
Ghilani's ADJUST): project and input → adjustment summary → statistics (σ̂0, χ² global test
PASSED/FAILED) → adjusted coordinates with corrections and standard deviations → orientation
unknowns → observations with residuals, redundancy numbers, standardised residuals (Baarda w),
τ and flags → absolute and relative error ellipses (standard and 95 %) → flagged observations.

Units in the report: coordinates m; corrections, standard deviations, distance residuals mm;
angular residuals and σ in arc-seconds (dms input) or mgon (gon input).
"""

from __future__ import annotations

import io
import math
from pathlib import Path

from minegeo._provenance import atomic_write_text, write_json_atomic
from minegeo.report._html import (
    NO_PLOT,
    badge,
    esc,
    img_png,
    kv_table,
    page,
    params_table,
    table,
    timings_html,
)
from minegeo.survey.angles import RHO_ARCSEC, format_dms, rad_to_gon

__all__ = ["network_result_dict", "network_status", "plot_network_png", "report_text", "report_html",
           "write_survey_report"]

_ANG = {"direction", "angle", "azimuth", "zenith_angle", "vertical_angle"}
_KIND_TITLE = {
    "distance": "Horizontal distances",
    "spatial_distance": "Slope distances",
    "direction": "Directions",
    "angle": "Horizontal angles",
    "azimuth": "Azimuths / grid bearings",
    "zenith_angle": "Zenith angles",
    "vertical_angle": "Vertical angles",
    "height_difference": "Levelled height differences",
    "trig_height_difference": "Trigonometric height differences",
    "baseline": "GNSS baselines (components)",
}


def _num(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)


def _ell(e):
    return None if e is None else e.as_dict()


def network_result_dict(res, parameters: dict | None = None, provenance: dict | None = None) -> dict:
    """JSON-ready dictionary of a :class:`~minegeo.survey.network.NetworkResult`.

    Keys: ``points`` {id: {x, y, h, sx_m, sy_m, sh_m, dx_m, dy_m, dh_m, fixed}}, ``sigma0``,
    ``sigma0_apriori``, ``variance_factor``, ``dof``, ``chi2_test`` {value, lower, upper, alpha,
    passed, verdict}, ``observations`` (each with residual, standardized_residual,
    redundancy_number, tau, flag), ``orientations``, ``ellipses`` {note, points {id: {standard,
    confidence_95}}, relative [...]}, ``network`` (name, source, dimension, datum), ``statistics``
    (counts, critical values), ``local_origin``, ``parameters``, ``provenance``.
    """
    lsq = res.lsq
    net = res.network
    pts = {}
    for pid, p in res.points.items():
        d = {"fixed": list(p.fixed)}
        for k in ("x", "y", "h", "sx_m", "sy_m", "sh_m", "dx_m", "dy_m", "dh_m"):
            v = getattr(p, k)
            if v is not None:
                d[k] = float(v)
        pts[pid] = d
    obs = []
    for o in res.observations:
        ob = o.obs
        ang = ob.kind in _ANG
        e = {
            "type": ob.kind,
            "station": ob.station,
            "target": ob.target,
            "line": ob.line,
            "unit": "rad" if ang else "m",
            "observed": _num(o.observed),
            "adjusted": _num(o.adjusted),
            "residual": _num(o.residual),
            "sigma": _num(o.sigma),
            "redundancy_number": _num(o.redundancy),
            "standardized_residual": _num(o.w),
            "tau": _num(o.tau),
            "flag": o.flag,
        }
        if ob.backsight:
            e["backsight"] = ob.backsight
        if o.component:
            e["component"] = o.component
        if ob.set_id is not None:
            e["set"] = ob.set_id
        if ang:
            e["residual_arcsec"] = _num(o.residual * RHO_ARCSEC)
            e["sigma_arcsec"] = _num(o.sigma * RHO_ARCSEC)
        else:
            e["residual_mm"] = _num(o.residual * 1000.0)
            e["sigma_mm"] = _num(o.sigma * 1000.0)
        obs.append(e)
    ell_pts = {
        pid: {"standard": _ell(p.ellipse_standard), "confidence_95": _ell(p.ellipse_95)}
        for pid, p in res.points.items()
        if p.ellipse_standard is not None
    }
    rel = [
        {"from": a, "to": b, "standard": _ell(e1), "confidence_95": _ell(e2)}
        for a, b, e1, e2 in res.relative_ellipses
    ]
    chi = lsq.chi2
    datum = {"type": net.datum.kind, "coordinates": [f"{a}{p}" for p, a in net.datum.coords]}
    if res.datum_defects:
        datum["defects_removed"] = list(res.datum_defects)
    return {
        "tool": "minegeo adjust",
        "network": {
            "name": net.name,
            "source": net.source,
            "dimension": net.dim,
            "datum": datum,
            "sigma0_in_file": net.sigma0_text,
            "unused_points": list(res.unused_points),
        },
        "points": pts,
        "sigma0": _num(lsq.sigma0),
        "sigma0_apriori": lsq.sigma0_apriori,
        "variance_factor": _num(lsq.sigma0_sq),
        "variance_used": lsq.variance_used,
        "dof": lsq.dof,
        "chi2_test": {
            "value": _num(chi.statistic),
            "lower": _num(chi.lower),
            "upper": _num(chi.upper),
            "alpha": chi.alpha,
            "passed": chi.passed,
            "verdict": chi.verdict,
        },
        "statistics": {
            "n_observations": len(lsq.v),
            "n_unknowns": len(lsq.x),
            "iterations": lsq.iterations,
            "converged": lsq.converged,
            "vtpv": lsq.vtwv,
            "w_critical": lsq.w_critical,
            "alpha_w": lsq.options.alpha_w,
            "tau_critical": _num(lsq.tau_critical),
            "alpha_tau": lsq.options.alpha_tau,
            "sum_redundancy": float(sum(lsq.redundancy)),
        },
        "orientations": [
            {
                "set": sid,
                "station": st,
                "orientation_deg": math.degrees(o),
                "orientation_dms": format_dms(o, 2),
                "std_arcsec": sd * RHO_ARCSEC,
            }
            for sid, (st, o, sd) in res.orientations.items()
        ],
        "observations": obs,
        "ellipses": {"note": _ellipse_note(res), "points": ell_pts, "relative": rel},
        "local_origin": res.local_origin,
        "parameters": parameters or {},
        "provenance": provenance or {},
    }


def _fmt(v, f):
    return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, f)


def _obs_rows(res):
    """Grouped rows: {kind: (headers, rows, flags)} with display units."""
    groups: dict = {}
    for o in res.observations:
        ob = o.obs
        kind = ob.kind
        ang = kind in _ANG
        gon = ang and ob.unit == "gon"
        if ang:
            if gon:
                obs_txt = f"{rad_to_gon(o.observed):.5f}"
                adj_txt = f"{rad_to_gon(o.adjusted):.5f}"
                res_txt = _fmt(rad_to_gon(o.residual) * 1000.0, ".3f")
                sig_txt = _fmt(rad_to_gon(o.sigma) * 1000.0, ".3f")
                unit = ("gon", "mgon")
            else:
                obs_txt = format_dms(o.observed, 1)
                adj_txt = format_dms(o.adjusted, 1)
                res_txt = _fmt(o.residual * RHO_ARCSEC, ".2f")
                sig_txt = _fmt(o.sigma * RHO_ARCSEC, ".2f")
                unit = ("dms", '"')
        else:
            obs_txt = f"{o.observed:.4f}"
            adj_txt = f"{o.adjusted:.4f}"
            res_txt = _fmt(o.residual * 1000.0, ".2f")
            sig_txt = _fmt(o.sigma * 1000.0, ".2f")
            unit = ("m", "mm")
        frm = f"{ob.backsight}" if kind == "angle" else ob.station
        tgt = ob.target if not o.component else f"{ob.target} {o.component}"
        at = ob.station if kind == "angle" else ""
        key = (kind, unit)
        row = [
            at,
            frm,
            ob.target,
            obs_txt,
            adj_txt,
            res_txt,
            sig_txt,
            _fmt(o.redundancy, ".3f"),
            _fmt(o.w, ".2f"),
            _fmt(o.tau, ".2f"),
            o.flag,
        ]
        if kind == "angle":
            row = [at, frm, tgt] + row[3:]
        else:
            row = [frm, tgt] + row[3:]
        groups.setdefault(key, []).append((row, bool(o.flag and o.flag != "weak r_i")))
    out = []
    for (kind, unit), rows in groups.items():
        first = ["at", "from", "to"] if kind == "angle" else ["from", "to"]
        headers = first + [
            f"observed [{unit[0]}]",
            f"adjusted [{unit[0]}]",
            f"v [{unit[1]}]",
            f"σ [{unit[1]}]",
            "r_i",
            "w",
            "τ",
            "flag",
        ]
        out.append(
            (_KIND_TITLE.get(kind, kind), headers, [r for r, _ in rows], [f for _, f in rows], len(first))
        )
    return out


#: Per network dimension: the coordinate columns (attribute, header) and the axis letters of the
#: shift ``d`` and standard deviation ``σ`` columns (attributes ``d<axis>_m`` and ``s<axis>_m``).
_COORD_COLUMNS = {
    1: ((("h", "H [m]"),), ("h",), ("H",)),
    2: ((("x", "E/x [m]"), ("y", "N/y [m]")), ("x", "y"), ("E", "N")),
    3: ((("x", "E/x [m]"), ("y", "N/y [m]"), ("h", "H/z [m]")), ("x", "y", "h"), ("E", "N", "H")),
}


def _coord_rows(res):
    """Headers and rows of the adjusted-coordinates table: the coordinates (m), shifts ``d`` and
    standard deviations ``σ`` (mm) per axis, in 2-D and 3-D the point error ``σP`` (mm;
    ``hypot(σx, σy)``, resp. ``sqrt(σx² + σy² + σh²)``), and the datum."""
    dim = res.network.dim
    coords, axes, names = _COORD_COLUMNS[min(dim, 3)]
    rows = []
    for pid, p in res.points.items():
        fx = "fixed: " + ",".join(p.fixed) if p.fixed else ""
        row = [pid] + [f"{getattr(p, c):.4f}" for c, _ in coords]
        row += [_fmt(getattr(p, f"d{a}_m") * 1000, ".2f") for a in axes]
        row += [_fmt(getattr(p, f"s{a}_m") * 1000, ".2f") for a in axes]
        if dim == 2:
            row.append(_fmt(math.hypot(p.sx_m, p.sy_m) * 1000, ".2f"))
        elif dim != 1:
            row.append(_fmt(math.sqrt(p.sx_m**2 + p.sy_m**2 + p.sh_m**2) * 1000, ".2f"))
        rows.append(row + [fx])
    headers = ["point"] + [h for _, h in coords] + [f"d{n} [mm]" for n in names] + [f"σ{n} [mm]" for n in names]
    return headers + ([] if dim == 1 else ["σP [mm]"]) + ["datum"], rows


def _confidence(res) -> float:
    """Confidence level of the report's ellipses (0.95 unless the run asked for another)."""
    for p in res.points.values():
        if p.ellipse_95 is not None:
            return float(p.ellipse_95.confidence)
    for _a, _b, _e1, e2 in res.relative_ellipses:
        return float(e2.confidence)
    return 0.95


def _ellipse_note(res) -> str:
    """How the confidence ellipses were scaled, at the confidence level actually used.

    ``res.ellipse_note`` states 95 %; for another ``--confidence`` the note is rebuilt from the
    ellipses' own scale ``k`` and basis.
    """
    conf = _confidence(res)
    if abs(conf - 0.95) < 1e-12:
        return res.ellipse_note
    e = next((p.ellipse_95 for p in res.points.values() if p.ellipse_95 is not None), None)
    if e is None:
        e = next((r[3] for r in res.relative_ellipses), None)
    if e is None:
        return res.ellipse_note
    note = f"{100 * conf:g}% ellipses scaled by k = {e.k:.4f} ({e.basis})"
    if res.datum_defects:
        note += f"; free-network datum removes: {', '.join(res.datum_defects)}"
    return note


def _is_flagged(o) -> bool:
    """Flagged by data snooping (w-test, τ-test) or unchecked ("no check"); "weak r_i" alone is not."""
    return bool(o.flag and o.flag != "weak r_i")


def network_status(res) -> tuple[str, str]:
    """Status word and reason of an adjustment, for the report's banner.

    Returns
    -------
    status : {"PASSED", "WARNINGS", "FAILED"}
        FAILED when the χ² global test failed or the iteration did not converge; WARNINGS when
        an observation is flagged (w-test, τ-test, "no check") or the global test could not be
        made (no redundancy); PASSED otherwise.
    reason : str
        One sentence with the numbers behind the word.
    """
    lsq = res.lsq
    chi = lsq.chi2
    flagged = [o for o in res.observations if _is_flagged(o)]
    fl = ""
    if flagged:
        worst = max(flagged, key=lambda o: abs(o.w) if math.isfinite(o.w) else -1.0)
        fl = (f"{len(flagged)} observation(s) flagged by data snooping, largest |w| {abs(worst.w):.2f}: "
              f"{worst.obs.kind} {worst.obs.label}" + (f" (line {worst.obs.line})" if worst.obs.line else ""))
    chi_txt = (f"χ² global test {chi.verdict} ({_fmt(chi.statistic, '.3f')} in [{_fmt(chi.lower, '.3f')}, "
               f"{_fmt(chi.upper, '.3f')}], σ̂0 = {_fmt(lsq.sigma0, '.3f')}, r = {lsq.dof})")
    if not lsq.converged:
        return "FAILED", f"the adjustment did not converge in {lsq.iterations} iterations; {chi_txt}"
    if chi.passed is False:
        return "FAILED", chi_txt + (f"; {fl}" if fl else "")
    if flagged:
        return "WARNINGS", f"{chi_txt}; {fl}"
    if chi.passed is None:
        return "WARNINGS", f"{chi_txt}: no observation is checked by another"
    return "PASSED", f"{chi_txt}; no observation flagged"


def _round_125(x: float) -> float:
    """Largest 1, 2 or 5 × 10^m not above ``x`` (``x`` > 0)."""
    dec = 10.0 ** math.floor(math.log10(x))
    return dec * max(m for m in (1.0, 2.0, 5.0) if m * dec <= x * (1 + 1e-12))


def plot_network_png(res) -> bytes | None:
    """Plan view of an adjusted network as PNG bytes (None without matplotlib or plan coordinates).

    Points labelled (control points with fixed plan coordinates as triangles), observation lines
    (grey; lines of flagged observations red), error ellipses of the adjusted points at the
    report's confidence level, exaggerated by a round factor ``k`` stated in the legend together
    with a scale bar (its length in metres and in millimetres of ellipse). Uses the
    object-oriented API (``Figure`` + Agg canvas; no global pyplot state) and writes no
    time-dependent metadata, so the same result gives the same bytes.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.lines import Line2D
        from matplotlib.patches import Ellipse
        from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
    except ImportError:
        return None
    pts = {pid: p for pid, p in res.points.items() if p.x is not None and p.y is not None}
    if res.network.dim < 2 or not pts:
        return None
    big = max(max(abs(p.x), abs(p.y)) for p in pts.values()) >= 1e5  # grid coordinates: plot reduced
    ox = float(res.local_origin.get("x", 0.0) or 0.0) if big else 0.0
    oy = float(res.local_origin.get("y", 0.0) or 0.0) if big else 0.0
    xy = {pid: (p.x - ox, p.y - oy) for pid, p in pts.items()}
    conf = _confidence(res)
    # observation lines, one per pair of points; red when any observation on it is flagged
    seg: dict = {}
    for o in res.observations:
        ob = o.obs
        pairs = [(ob.station, ob.target)]
        if ob.backsight:
            pairs.append((ob.station, ob.backsight))
        for a, b in pairs:
            if a in xy and b in xy and a != b:
                key = tuple(sorted((a, b)))
                seg[key] = seg.get(key, False) or _is_flagged(o)
    X = [v[0] for v in xy.values()]
    Y = [v[1] for v in xy.values()]
    span = max(max(X) - min(X), max(Y) - min(Y), 1e-3)
    adj = {pid: p for pid, p in pts.items() if p.ellipse_95 is not None and p.ellipse_95.semi_major_m > 0
           and not ({"x", "y"} <= set(p.fixed))}
    amax = max((p.ellipse_95.semi_major_m for p in adj.values()), default=0.0)
    k = _round_125(0.08 * span / amax) if amax > 0 else 1.0

    fig = Figure(figsize=(8.5, 7.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for (a, b), bad in sorted(seg.items(), key=lambda kv: kv[1]):
        ax.plot([xy[a][0], xy[b][0]], [xy[a][1], xy[b][1]], "-", color="tab:red" if bad else "0.6",
                lw=2.2 if bad else 0.9, zorder=2 if bad else 1)
    fixed = [pid for pid, p in pts.items() if {"x", "y"} <= set(p.fixed)]
    free = [pid for pid in pts if pid not in fixed]
    if fixed:
        ax.scatter([xy[p][0] for p in fixed], [xy[p][1] for p in fixed], marker="^", s=90, c="k", zorder=4)
    if free:
        ax.scatter([xy[p][0] for p in free], [xy[p][1] for p in free], marker="o", s=28, c="tab:blue", zorder=4)
    for pid, p in adj.items():
        e = p.ellipse_95
        ax.add_patch(Ellipse(xy[pid], 2 * k * e.semi_major_m, 2 * k * e.semi_minor_m,
                             angle=90.0 - math.degrees(e.azimuth_rad), fill=False, color="tab:blue", lw=1.6,
                             zorder=3))
    for pid, (x, y) in xy.items():
        ax.annotate(str(pid), (x, y), textcoords="offset points", xytext=(6, 6), fontsize=9, zorder=5)
    ax.set_aspect("equal", adjustable="box")
    pad = 0.08 * span + (k * amax if amax > 0 else 0.0)
    ax.set_xlim(min(X) - pad, max(X) + pad)
    ax.set_ylim(min(Y) - pad, max(Y) + pad)
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("E / x (m)" + (f" − {ox:.0f}" if ox else ""))
    ax.set_ylabel("N / y (m)" + (f" − {oy:.0f}" if oy else ""))
    ax.grid(True, color="0.92")
    bar = _round_125(span / 4.0)
    handles = [Line2D([], [], color="0.6", lw=0.9, label="observation")]
    if any(seg.values()):
        handles.append(Line2D([], [], color="tab:red", lw=2.2, label="flagged observation (data snooping)"))
    if fixed:
        handles.append(Line2D([], [], ls="", marker="^", ms=9, color="k", label="control point (fixed)"))
    if free:
        handles.append(Line2D([], [], ls="", marker="o", ms=6, color="tab:blue", label="adjusted point"))
    if adj:
        handles.append(Line2D([], [], color="tab:blue", lw=1.6,
                              label=f"{100 * conf:g} % error ellipse, exaggerated ×{k:g}"))
        handles.append(Line2D([], [], ls="", label=f"scale bar {bar:g} m = {1000 * bar / k:.3g} mm of ellipse"))
    ax.add_artist(AnchoredSizeBar(ax.transData, bar, f"{bar:g} m" + (f" (ellipses {1000 * bar / k:.3g} mm)"
                                                                       if adj else ""),
                                  "lower right", pad=0.6, sep=4, frameon=True, size_vertical=span / 300))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, fontsize=8,
              frameon=False)
    ax.set_title(f"{res.network.name or 'Network'}: plan view"
                 + (f", {100 * conf:g} % error ellipses ×{k:g}" if adj else ""))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None}, bbox_inches="tight")
    return buf.getvalue()


def _ellipse_cells(name: str, e1, e2) -> list:
    """One row of an ellipse table: the standard ellipse's semi-axes (mm) and azimuth (DMS), the
    confidence ellipse's semi-axes (mm) and its factor ``k``."""
    return [
        name,
        f"{e1.semi_major_m * 1000:.2f}",
        f"{e1.semi_minor_m * 1000:.2f}",
        format_dms(e1.azimuth_rad, 0),
        _fmt(e2.semi_major_m * 1000, ".2f"),
        _fmt(e2.semi_minor_m * 1000, ".2f"),
        _fmt(e2.k, ".4f"),
    ]


def _ellipse_rows(res):
    rows = [_ellipse_cells(pid, p.ellipse_standard, p.ellipse_95) for pid, p in res.points.items()
            if p.ellipse_standard is not None]
    rel = [_ellipse_cells(f"{a}-{b}", e1, e2) for a, b, e1, e2 in res.relative_ellipses]
    c = f"{100 * _confidence(res):g}%"
    headers = ["point", "a std [mm]", "b std [mm]", "azimuth of a", f"a {c} [mm]", f"b {c} [mm]", "k"]
    return headers, rows, rel


def _summary_items(res, inputs=None):
    lsq = res.lsq
    net = res.network
    counts: dict = {}
    for o in net.observations:
        counts[o.kind] = counts.get(o.kind, 0) + 1
    n_fixed = sum(1 for p in res.points.values() if p.fixed)
    items = [
        ("project", net.name or "(none)"),
        ("input", net.source),
        ("dimension", f"{net.dim}D"),
        (
            "datum",
            f"{net.datum.kind}: "
            + " ".join(f"{a}{p}" for p, a in net.datum.coords)
            + (f" (defects removed: {', '.join(res.datum_defects)})" if res.datum_defects else ""),
        ),
        (
            "points",
            f"{len(res.points)} in the adjustment ({n_fixed} with fixed coordinates)"
            + (f"; not observed: {', '.join(res.unused_points)}" if res.unused_points else ""),
        ),
        (
            "observations",
            ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in counts.items()) + f" ({len(lsq.v)} equations)",
        ),
        ("unknowns", str(len(lsq.x))),
        ("degrees of freedom r", str(lsq.dof)),
        ("iterations", f"{lsq.iterations} ({'converged' if lsq.converged else 'NOT converged'})"),
        ("local origin subtracted", ", ".join(f"{k}={v:.0f} m" for k, v in res.local_origin.items())),
    ]
    if inputs:
        for rec in inputs:
            items.append(("input sha256", f"{rec.get('sha256', '')}"))
    return items


def _stats_items(res):
    lsq = res.lsq
    chi = lsq.chi2
    return [
        ("reference std. deviation σ̂0 (a posteriori)", _fmt(lsq.sigma0, ".4f")),
        (
            "a-priori σ0",
            f"{lsq.sigma0_apriori:g} (observation σ are absolute; [Sigma0] in file: {res.network.sigma0_text or 'none'})",
        ),
        ("variance factor σ̂0²", _fmt(lsq.sigma0_sq, ".4f")),
        ("vᵀPv", f"{lsq.vtwv:.4f}"),
        (
            f"χ² global test (two-tailed, {100 * (1 - chi.alpha):.0f} %)",
            f"{_fmt(chi.statistic, '.3f')} in [{_fmt(chi.lower, '.3f')}, {_fmt(chi.upper, '.3f')}] → {chi.verdict}",
        ),
        (
            "covariances scaled with",
            "a-posteriori σ̂0" if lsq.variance_used == "aposteriori" else "a-priori σ0",
        ),
        ("w-test (Baarda) critical value", f"{lsq.w_critical:.2f} (α0 = {lsq.options.alpha_w})"),
        (
            "τ-test (Pope) critical value",
            f"{lsq.tau_critical:.2f} (α = {lsq.options.alpha_tau})"
            if math.isfinite(lsq.tau_critical)
            else "n/a (needs r ≥ 2)",
        ),
        ("Σ redundancy numbers", f"{sum(lsq.redundancy):.3f}"),
    ] + ([("ellipses", _ellipse_note(res))] if res.network.dim >= 2 else [])


def _text_table(headers, rows) -> list[str]:
    w = [len(h) for h in headers]
    for r in rows:
        for i, c in enumerate(r):
            w[i] = max(w[i], len(str(c)))
    line = "  ".join(h.ljust(w[i]) for i, h in enumerate(headers))
    out = [line, "-" * len(line)]
    for r in rows:
        out.append(
            "  ".join(str(c).rjust(w[i]) if i > 0 else str(c).ljust(w[i]) for i, c in enumerate(r)).rstrip()
        )
    return out


def report_text(res, inputs=None) -> str:
    """Plain-text adjustment report (see module docstring for the section order)."""
    L = ["MINEGEO SURVEY NETWORK ADJUSTMENT", "=" * 33, ""]
    sec = iter(range(1, 20))
    L += (
        [f"{next(sec)}. ADJUSTMENT SUMMARY", ""]
        + [f"  {k:<28} {v}" for k, v in _summary_items(res, inputs)]
        + [""]
    )
    L += [f"{next(sec)}. STATISTICS", ""] + [f"  {k:<44} {v}" for k, v in _stats_items(res)] + [""]
    h, rows = _coord_rows(res)
    L += [f"{next(sec)}. ADJUSTED COORDINATES (d = correction to the approximate value)", ""]
    L += ["  " + x for x in _text_table(h, rows)] + [""]
    if res.orientations:
        L += [f"{next(sec)}. ORIENTATION UNKNOWNS", ""]
        rows = [
            [f"{sid}", st, format_dms(o, 2), f"{sd * RHO_ARCSEC:.2f}"]
            for sid, (st, o, sd) in res.orientations.items()
        ]
        L += ["  " + x for x in _text_table(["set", "station", "orientation", 'σ ["]'], rows)] + [""]
    L += [f"{next(sec)}. OBSERVATIONS AND RESIDUALS (v = adjusted − observed; w = standardised residual)", ""]
    for title, headers, rows, _flags, _n in _obs_rows(res):
        L += [f"  {title}"] + ["  " + x for x in _text_table(headers, rows)] + [""]
    h, rows, rel = _ellipse_rows(res)
    if rows or rel:
        L += [f"{next(sec)}. ERROR ELLIPSES (" + _ellipse_note(res) + ")", ""]
        if rows:
            L += ["  Absolute"] + ["  " + x for x in _text_table(h, rows)] + [""]
        if rel:
            L += (
                ["  Relative (between observed pairs)"]
                + ["  " + x for x in _text_table(["pair"] + h[1:], rel)]
                + [""]
            )
    flagged = [o for o in res.observations if o.flag and o.flag != "weak r_i"]
    L += [f"{next(sec)}. FLAGGED OBSERVATIONS", ""]
    if flagged:
        for o in flagged:
            L.append(
                f"  {o.obs.kind} {o.obs.label} (line {o.obs.line}): w = {o.w:.2f}, τ = {_fmt(o.tau, '.2f')} [{o.flag}]"
            )
        i = res.lsq.suspected_blunder()
        if i is not None:
            L.append(
                f"  largest |w|: {res.lsq.obs_names[i]} — check it first (remove or re-measure, then re-adjust)"
            )
    else:
        L.append("  none (no standardised residual above the critical values)")
    L.append("")
    return "\n".join(L)


def _parameters_used(res, parameters: dict | None) -> dict:
    """Parameters of the run as the adjustment actually used them (options from the result)."""
    o = res.lsq.options
    used = {
        "variance (σ0 scaling the covariances)": o.variance,
        "confidence of the ellipses": _confidence(res),
        "alpha of the χ² global test": o.alpha_global,
        "alpha of the w-test (Baarda)": o.alpha_w,
        "alpha of the τ-test (Pope)": o.alpha_tau,
        "max iterations": o.max_iterations,
        "a-priori σ0": o.sigma0_apriori,
        "min redundancy number (weak r_i)": o.min_redundancy,
    }
    known = {"variance", "confidence", "alpha_global", "alpha_w", "alpha_tau", "max_iterations", "timings_s"}
    for k, v in (parameters or {}).items():
        if k not in known:
            used[k] = v
    return used


def report_html(res, inputs=None, parameters: dict | None = None, *, plot: bool = True) -> str:
    """Standalone HTML report: status banner, the sections of :func:`report_text` and the plan view.

    Parameters
    ----------
    res : NetworkResult
    inputs : list of dict, optional
        Input records (``path``, ``sha256``) from the provenance.
    parameters : dict, optional
        Parameters of the run (as recorded in ``result.json``); the options the adjustment used
        are read from ``res`` itself.
    plot : bool
        Draw the plan view (needs matplotlib; without it the report says so).
    """
    chi = res.lsq.chi2
    opts = res.lsq.options
    conf = _confidence(res)
    status, reason = network_status(res)
    secs = [("Adjustment summary", kv_table(_summary_items(res, inputs)))]
    stats = kv_table(_stats_items(res))
    secs.append((f"Statistics (χ² global test at α = {chi.alpha:g})",
                 f"<p>χ² global test: {badge(chi.verdict, chi.passed)}</p>" + stats))
    if res.network.dim >= 2:
        png = plot_network_png(res) if plot else None
        if png:
            fig = (f"<figure>{img_png(png, 'plan view of the network with error ellipses')}<figcaption>Plan "
                   f"view: control points ▲, adjusted points ●, observation lines (red: flagged by data "
                   f"snooping), {100 * conf:g} % error ellipses drawn exaggerated by the factor stated in "
                   "the legend; the scale bar gives metres and millimetres of ellipse.</figcaption></figure>")
        else:
            fig = f"<p>{esc(NO_PLOT)}</p>"
        secs.append((f"Plan view ({100 * conf:g} % error ellipses)", fig))
    h, rows = _coord_rows(res)
    secs.append(("Adjusted coordinates", table(h, rows, numeric=range(1, len(h) - 1))))
    if res.orientations:
        rows = [
            [f"{sid}", st, format_dms(o, 2), f"{sd * RHO_ARCSEC:.2f}"]
            for sid, (st, o, sd) in res.orientations.items()
        ]
        secs.append(
            ("Orientation unknowns", table(["set", "station", "orientation", 'σ ["]'], rows, numeric=[2, 3]))
        )
    parts = []
    for title, headers, rows, flags, n in _obs_rows(res):
        parts.append(
            f"<h3>{esc(title)}</h3>"
            + table(headers, rows, numeric=range(n, n + 7), row_classes=["flag" if f else "" for f in flags])
        )
    secs.append(
        (
            "Observations and residuals",
            "<p>v = adjusted − observed; w = Baarda standardised residual; τ = Pope.</p>" + "".join(parts),
        )
    )
    h, rows, rel = _ellipse_rows(res)
    if rows or rel:
        body = f"<p>{esc(_ellipse_note(res))}</p>"
        if rows:
            body += "<h3>Absolute</h3>" + table(h, rows, numeric=range(1, 7))
        if rel:
            body += "<h3>Relative</h3>" + table(["pair"] + h[1:], rel, numeric=range(1, 7))
        secs.append((f"Error ellipses (standard and {100 * conf:g} %)", body))
    flagged = [o for o in res.observations if _is_flagged(o)]
    if flagged:
        body = table(
            ["observation", "line", "w", "τ", "flag"],
            [
                [f"{o.obs.kind} {o.obs.label}", o.obs.line, f"{o.w:.2f}", _fmt(o.tau, ".2f"), o.flag]
                for o in flagged
            ],
            numeric=[1, 2, 3],
            row_classes=["flag"] * len(flagged),
        )
        i = res.lsq.suspected_blunder()
        if i is not None:
            body += (f"<p>Largest |w|: <b>{esc(res.lsq.obs_names[i])}</b> — check it first (remove or "
                     "re-measure, then re-adjust).</p>")
    else:
        body = "<p>None: no standardised residual above the critical values.</p>"
    secs.append((f"Flagged observations (w-test α0 = {opts.alpha_w:g}, τ-test α = {opts.alpha_tau:g})", body))
    secs.append(("Parameters used", params_table(_parameters_used(res, parameters))))
    if parameters and parameters.get("timings_s"):
        secs.append(("Run time (s; Numba compile time apart)", timings_html(parameters["timings_s"])))
    return page("Survey network adjustment", secs, subtitle=f"{res.network.name} — {res.network.source}",
                status=status, status_text=reason)


def write_survey_report(res, out_dir, parameters: dict | None = None, provenance: dict | None = None) -> dict:
    """Write ``result.json``, ``report.txt`` and ``report.html`` into ``out_dir`` (atomically).

    ``report.html`` is the report (status banner, tables, embedded plan view); ``report.txt`` the
    same tables as plain text for filing.

    Returns ``{"result": path, "report_txt": path, "report_html": path}``.
    """
    out = Path(out_dir)
    inputs = (provenance or {}).get("inputs")
    d = network_result_dict(res, parameters, provenance)
    p1 = write_json_atomic(out / "result.json", d)
    p2 = atomic_write_text(out / "report.txt", report_text(res, inputs))
    p3 = atomic_write_text(out / "report.html", report_html(res, inputs, parameters))
    return {"result": p1, "report_txt": p2, "report_html": p3}
