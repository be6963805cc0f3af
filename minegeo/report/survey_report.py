"""Survey-style adjustment report (text, HTML) and result JSON of a network adjustment.

Section order follows what surveyors know from adjustment packages (STAR*NET, GNU Gama,
Ghilani's ADJUST): project and input → adjustment summary → statistics (σ̂0, χ² global test
PASSED/FAILED) → adjusted coordinates with corrections and standard deviations → orientation
unknowns → observations with residuals, redundancy numbers, standardised residuals (Baarda w),
τ and flags → absolute and relative error ellipses (standard and 95 %) → flagged observations.

Units in the report: coordinates m; corrections, standard deviations, distance residuals mm;
angular residuals and σ in arc-seconds (dms input) or mgon (gon input).
"""

from __future__ import annotations

import math
from pathlib import Path

from minegeo._provenance import atomic_write_text, write_json_atomic
from minegeo.report._html import badge, esc, kv_table, page, table
from minegeo.survey.angles import RHO_ARCSEC, format_dms, rad_to_gon

__all__ = ["network_result_dict", "report_text", "report_html", "write_survey_report"]

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
        "ellipses": {"note": res.ellipse_note, "points": ell_pts, "relative": rel},
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


def _coord_rows(res):
    dim = res.network.dim
    rows = []
    for pid, p in res.points.items():
        fx = "fixed: " + ",".join(p.fixed) if p.fixed else ""
        if dim == 1:
            rows.append([pid, f"{p.h:.4f}", _fmt(p.dh_m * 1000, ".2f"), _fmt(p.sh_m * 1000, ".2f"), fx])
        elif dim == 2:
            sp = math.hypot(p.sx_m, p.sy_m)
            rows.append(
                [
                    pid,
                    f"{p.x:.4f}",
                    f"{p.y:.4f}",
                    _fmt(p.dx_m * 1000, ".2f"),
                    _fmt(p.dy_m * 1000, ".2f"),
                    _fmt(p.sx_m * 1000, ".2f"),
                    _fmt(p.sy_m * 1000, ".2f"),
                    _fmt(sp * 1000, ".2f"),
                    fx,
                ]
            )
        else:
            sp = math.sqrt(p.sx_m**2 + p.sy_m**2 + p.sh_m**2)
            rows.append(
                [
                    pid,
                    f"{p.x:.4f}",
                    f"{p.y:.4f}",
                    f"{p.h:.4f}",
                    _fmt(p.dx_m * 1000, ".2f"),
                    _fmt(p.dy_m * 1000, ".2f"),
                    _fmt(p.dh_m * 1000, ".2f"),
                    _fmt(p.sx_m * 1000, ".2f"),
                    _fmt(p.sy_m * 1000, ".2f"),
                    _fmt(p.sh_m * 1000, ".2f"),
                    _fmt(sp * 1000, ".2f"),
                    fx,
                ]
            )
    if dim == 1:
        headers = ["point", "H [m]", "dH [mm]", "σH [mm]", "datum"]
    elif dim == 2:
        headers = [
            "point",
            "E/x [m]",
            "N/y [m]",
            "dE [mm]",
            "dN [mm]",
            "σE [mm]",
            "σN [mm]",
            "σP [mm]",
            "datum",
        ]
    else:
        headers = [
            "point",
            "E/x [m]",
            "N/y [m]",
            "H/z [m]",
            "dE [mm]",
            "dN [mm]",
            "dH [mm]",
            "σE [mm]",
            "σN [mm]",
            "σH [mm]",
            "σP [mm]",
            "datum",
        ]
    return headers, rows


def _ellipse_rows(res):
    rows = []
    for pid, p in res.points.items():
        e1, e2 = p.ellipse_standard, p.ellipse_95
        if e1 is None:
            continue
        rows.append(
            [
                pid,
                f"{e1.semi_major_m * 1000:.2f}",
                f"{e1.semi_minor_m * 1000:.2f}",
                format_dms(e1.azimuth_rad, 0),
                _fmt(e2.semi_major_m * 1000, ".2f"),
                _fmt(e2.semi_minor_m * 1000, ".2f"),
                _fmt(e2.k, ".4f"),
            ]
        )
    rel = []
    for a, b, e1, e2 in res.relative_ellipses:
        rel.append(
            [
                f"{a}-{b}",
                f"{e1.semi_major_m * 1000:.2f}",
                f"{e1.semi_minor_m * 1000:.2f}",
                format_dms(e1.azimuth_rad, 0),
                _fmt(e2.semi_major_m * 1000, ".2f"),
                _fmt(e2.semi_minor_m * 1000, ".2f"),
                _fmt(e2.k, ".4f"),
            ]
        )
    headers = ["point", "a std [mm]", "b std [mm]", "azimuth of a", "a 95% [mm]", "b 95% [mm]", "k"]
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
    ] + ([("ellipses", res.ellipse_note)] if res.network.dim >= 2 else [])


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
        L += [f"{next(sec)}. ERROR ELLIPSES (" + res.ellipse_note + ")", ""]
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


def report_html(res, inputs=None) -> str:
    """Standalone HTML report with the same sections as :func:`report_text`."""
    chi = res.lsq.chi2
    secs = [("Adjustment summary", kv_table(_summary_items(res, inputs)))]
    stats = kv_table(_stats_items(res))
    secs.append(("Statistics", f"<p>χ² global test: {badge(chi.verdict, chi.passed)}</p>" + stats))
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
        body = f"<p>{esc(res.ellipse_note)}</p>"
        if rows:
            body += "<h3>Absolute</h3>" + table(h, rows, numeric=range(1, 7))
        if rel:
            body += "<h3>Relative</h3>" + table(["pair"] + h[1:], rel, numeric=range(1, 7))
        secs.append(("Error ellipses", body))
    flagged = [o for o in res.observations if o.flag and o.flag != "weak r_i"]
    if flagged:
        body = table(
            ["observation", "line", "w", "τ", "flag"],
            [
                [f"{o.obs.kind} {o.obs.label}", o.obs.line, f"{o.w:.2f}", _fmt(o.tau, ".2f"), o.flag]
                for o in flagged
            ],
            numeric=[1, 2, 3],
        )
    else:
        body = "<p>None: no standardised residual above the critical values.</p>"
    secs.append(("Flagged observations", body))
    return page("Survey network adjustment", secs, subtitle=f"{res.network.name} — {res.network.source}")


def write_survey_report(res, out_dir, parameters: dict | None = None, provenance: dict | None = None) -> dict:
    """Write ``result.json``, ``report.txt`` and ``report.html`` into ``out_dir`` (atomically).

    Returns ``{"result": path, "report_txt": path, "report_html": path}``.
    """
    out = Path(out_dir)
    inputs = (provenance or {}).get("inputs")
    d = network_result_dict(res, parameters, provenance)
    p1 = write_json_atomic(out / "result.json", d)
    p2 = atomic_write_text(out / "report.txt", report_text(res, inputs))
    p3 = atomic_write_text(out / "report.html", report_html(res, inputs))
    return {"result": p1, "report_txt": p2, "report_html": p3}
