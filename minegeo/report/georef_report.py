"""Self-contained HTML report of a map georeferencing (:func:`minegeo.georef.georeference`).

``report.html`` holds everything a surveyor checks, in one file that can be mailed or archived.
It opens with the status banner (``OK``, ``WARNINGS`` or ``FAILED`` from ``result.status``, with
the reason), then: inputs with SHA-256, the CRS (name, EPSG code, units, official axis order,
recorded local origin), the model equation and rotation convention, the parameters with
standard deviations (rotations in radians, arc-seconds and DMS; scale in ppm), ``T_crs_map``,
σ0 with its χ² test (PASSED/FAILED), the per-GCP residual table with w-test flags, the grid
scale factors, every warning, the parameters the run used, and — when matplotlib is installed
(``pip install 'minegeo[report]'``) — a plan view of the GCPs with their residual vectors
embedded as a base64 PNG (no external files, no scripts).
"""

from __future__ import annotations

import html
import io
import math

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.report._html import (
    CSS,
    NO_PLOT,
    img_png,
    num,
    params_table,
    status_banner,
    status_word,
    timings_html,
)

__all__ = ["georef_report_html", "plot_georef_png", "write_georef_report"]

# the shared report style, then this report's tables: numbers right-aligned, class 'l' left
_CSS = CSS + """
td,th{text-align:right}td.l,th.l{text-align:left}tr.flag td{background:#fde2e2}tr.warn td{background:#fff4d6}
code,pre{font-family:ui-monospace,Consolas,monospace;font-size:.92em}
"""


def _asdict(params) -> dict:
    import dataclasses

    return dataclasses.asdict(params) if dataclasses.is_dataclass(params) else dict(params)


def _e(x) -> str:
    return html.escape(str(x))


def plot_georef_png(result, cloud_geo=None, max_cloud_points: int = 20000, seed: int = 0) -> bytes | None:
    """Plan view (E, N) of the GCPs with exaggerated residual vectors, as PNG bytes.

    Returns None when matplotlib is not installed (the report then says so). Uses the
    object-oriented API (``Figure`` + Agg canvas): no global pyplot state is touched.
    ``cloud_geo`` (a georeferenced cloud in the ``geo`` frame) is drawn as a light footprint,
    subsampled to ``max_cloud_points`` with ``np.random.default_rng(seed)``.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    o = np.asarray(result.origin, dtype=np.float64)
    en = np.asarray(result.gcp_crs_enh, dtype=np.float64)[:, :2] - o[:2]
    v = np.asarray(result.residuals_m, dtype=np.float64)[:, :2]
    fig = Figure(figsize=(7.5, 6.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if cloud_geo is not None and len(cloud_geo) > 0:
        pts = cloud_geo.points
        if len(pts) > max_cloud_points:
            idx = np.sort(np.random.default_rng(seed).choice(len(pts), max_cloud_points, replace=False))
            pts = pts[idx]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c="0.75", linewidths=0, label="map (georeferenced)")
    span = float(np.max(np.ptp(en, axis=0))) if len(en) > 1 else 1.0
    vmax = float(np.max(np.linalg.norm(v, axis=1))) if len(v) else 0.0
    k = 1.0
    if vmax > 0:
        # a round exaggeration factor (1, 2, 5 x 10^m) making the longest vector ~15-35 % of the span
        raw = 0.3 * span / vmax
        dec = 10.0 ** math.floor(math.log10(raw))
        k = dec * max(m for m in (1.0, 2.0, 5.0) if m * dec <= raw)
    flagged = np.asarray(result.blunder, dtype=bool) | np.array([bool(f) for f in result.flags])
    ax.scatter(en[~flagged, 0], en[~flagged, 1], marker="^", s=50, c="tab:blue", label="GCP", zorder=3)
    if flagged.any():
        ax.scatter(en[flagged, 0], en[flagged, 1], marker="^", s=70, c="tab:red", label="GCP flagged", zorder=3)
    if vmax > 0:
        ax.quiver(
            en[:, 0], en[:, 1], v[:, 0] * k, v[:, 1] * k, angles="xy", scale_units="xy", scale=1,
            color="tab:red", width=0.004, zorder=4,
        )
    for gid, (e, nn) in zip(result.gcp_ids, en, strict=True):
        ax.annotate(str(gid), (e, nn), textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"E − {o[0]:.0f} m")
    ax.set_ylabel(f"N − {o[1]:.0f} m")
    ax.set_title(f"GCP residuals (fitted − observed), vectors ×{k:g}; max {vmax * 1000:.1f} mm")
    ax.grid(True, color="0.9")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _head(r, word: str, ci: dict) -> list[str]:
    """Page head: status banner, title and the result's warnings."""
    if r.reason:
        text = r.reason
    else:
        text = (f"σ0 = {num(r.sigma0, '.3f')}, χ² test {r.chi2.get('verdict', 'n/a')}, RMS horizontal "
                f"{num(r.rms_m.get('horizontal', float('nan')) * 1000, '.1f')} mm over {r.n_gcps} GCPs")
    out: list[str] = [
        "<!DOCTYPE html>",
        f"<html lang='en'><head><meta charset='utf-8'><title>{_e(word)}: minegeo georeferencing report</title>",
        f"<style>{_CSS}</style></head><body>",
        status_banner(word, text),
        "<h1>Georeferencing of the map into " + _e(ci.get("name") or r.crs) + "</h1>",
    ]
    if r.warnings:
        out.append("<ul>" + "".join(f"<li>{_e(w)}</li>" for w in r.warnings) + "</ul>")
    return out


def _files_section(inputs: dict | None, outputs: dict | None) -> list[str]:
    """Inputs (with SHA-256) and outputs."""
    out: list[str] = []
    if inputs:
        out.append("<h2>Inputs</h2><table><tr><th class='l'>role</th><th class='l'>file</th><th class='l'>SHA-256</th><th>bytes</th></tr>")
        for k, rec in inputs.items():
            out.append(
                f"<tr><td class='l'>{_e(k)}</td><td class='l'><code>{_e(rec.get('path'))}</code></td>"
                f"<td class='l'><code>{_e(rec.get('sha256'))}</code></td><td>{_e(rec.get('size_bytes'))}</td></tr>"
            )
        out.append("</table>")
    if outputs:
        out.append("<h2>Outputs</h2><ul>" + "".join(f"<li>{_e(k)}: <code>{_e(v)}</code></li>" for k, v in outputs.items()) + "</ul>")
    return out


def _crs_section(r, ci: dict) -> list[str]:
    """The CRS table: name, units and axis order, area of use, local origin, grid factors."""
    o = r.origin
    out = [
        "<h2>Coordinate reference system</h2><table>",
        f"<tr><th class='l'>CRS</th><td class='l'>{_e(r.crs)} — {_e(ci.get('name'))} (EPSG {_e(ci.get('epsg'))}, {_e(ci.get('kind'))})</td></tr>",
        f"<tr><th class='l'>units / official axis order</th><td class='l'>{_e(ci.get('units'))} / {_e(ci.get('axis_order'))} "
        "(minegeo files always use E, N, H)</td></tr>",
        f"<tr><th class='l'>area of use</th><td class='l'>{_e(ci.get('area_of_use'))}</td></tr>",
        f"<tr><th class='l'>recorded local origin</th><td class='l'>E {o[0]:.3f}, N {o[1]:.3f}, H {o[2]:.3f} m "
        "(geo = CRS − origin; computations use geo coordinates)</td></tr>",
    ]
    gf = r.grid_factors
    if gf:
        out.append(
            f"<tr><th class='l'>grid factors at GCP centroid</th><td class='l'>point scale k = {gf['point_scale_factor']:.9f}, "
            f"height factor R/(R+h) = {gf['height_factor']:.9f}, combined = {gf['combined_factor']:.9f} "
            f"({gf['combined_ppm']:+.1f} ppm) at lat {gf['lat_deg']:.5f}°, lon {gf['lon_deg']:.5f}°</td></tr>"
        )
    out.append("</table>")
    return out


def _parameter_table(r) -> list[str]:
    """The model sentence and the table of the transformation parameters with standard deviations."""
    sd = r.translation_std_m
    rs = r.rotation_std_arcsec
    conv = "position vector (EPSG 9606)" if r.convention == "position_vector" else "coordinate frame (EPSG 9607)"
    out = [
        "<h2>Model and parameters</h2>",
        f"<p><b>{'3D similarity, 7 parameters' if r.model == 'similarity' else '3D rigid, 6 parameters (s = 1)'}</b>: "
        "X<sub>CRS</sub> = T + s·R·x<sub>map</sub>, weighted least squares (Gauss–Markov), "
        f"rotation convention <b>{conv}</b>: R = exp([ω]×) with ω the position-vector rotation vector"
        + ("" if r.convention == "position_vector" else "; reported rotations are −ω")
        + ". Residuals v = fitted − observed.</p>",
        "<p class='small'>r<sub>E</sub>, r<sub>N</sub>, r<sub>H</sub>: components of the rotation vector (for small "
        "angles the EPSG rotations about E, N, H). Their standard deviations are those of small rotations about the "
        "E, N, H axes at the solution.</p>",
        "<table><tr><th class='l'>parameter</th><th>value</th><th>std. dev.</th></tr>",
        f"<tr><td class='l'>T<sub>E</sub></td><td>{r.translation_m[0]:.4f} m</td><td>{sd[0] * 1000:.2f} mm</td></tr>",
        f"<tr><td class='l'>T<sub>N</sub></td><td>{r.translation_m[1]:.4f} m</td><td>{sd[1] * 1000:.2f} mm</td></tr>",
        f"<tr><td class='l'>T<sub>H</sub></td><td>{r.translation_m[2]:.4f} m</td><td>{sd[2] * 1000:.2f} mm</td></tr>",
    ]
    for j, ax in enumerate("ENH"):
        out.append(
            f"<tr><td class='l'>r<sub>{ax}</sub></td><td>{r.rotation_rad[j]:.9f} rad = "
            f"{r.rotation_arcsec[j]:.4f}″ = {_e(r.rotation_dms[j])}</td><td>{rs[j]:.3f}″</td></tr>"
        )
    if r.model == "similarity":
        out.append(
            f"<tr><td class='l'>scale s</td><td>{r.scale:.10f} (ds = {r.ds_ppm:+.2f} ppm)</td>"
            f"<td>{r.scale_std * 1e6:.2f} ppm</td></tr>"
        )
    else:
        out.append("<tr><td class='l'>scale s</td><td>1 (fixed)</td><td>—</td></tr>")
    out.append("</table>")
    return out


def _scale_and_angles(r) -> list[str]:
    """The scale test (similarity), the equivalent Euler angles and ``T_crs_map``."""
    gf = r.grid_factors
    eu = r.euler_zyx_rad
    out: list[str] = []
    if r.model == "similarity" and r.scale_std > 0:
        zs = abs(r.scale - 1.0) / r.scale_std
        gtxt = ""
        if gf:
            zg = abs(r.scale - gf["combined_factor"]) / r.scale_std
            gtxt = (
                f" Against the grid's combined factor ({gf['combined_ppm']:+.1f} ppm): |s − k·R/(R+h)|/σ<sub>s</sub> = "
                f"{zg:.2f}."
            )
        out.append(
            f"<p>Scale test: |s − 1|/σ<sub>s</sub> = {zs:.2f} ({'significant' if zs > 1.96 else 'not significant'} "
            "at 95 %; if not significant, the 6-parameter rigid model is an option)." + gtxt + "</p>"
        )
    out += [
        f"<p>Equivalent angles R = Rz(yaw)·Ry(pitch)·Rx(roll): roll {_e(r.euler_zyx_dms[0])}, pitch "
        f"{_e(r.euler_zyx_dms[1])}, <b>yaw {_e(r.euler_zyx_dms[2])}</b> ({math.degrees(eu[2]):.6f}°, rotation of the "
        "map about the vertical, counter-clockwise from map x to grid east).</p>",
        "<p>T<sub>crs_map</sub> (4×4; top-left block s·R"
        + (", not a rigid transform when s ≠ 1" if r.model == "similarity" else "")
        + "):</p><pre>"
        + "\n".join(" ".join(f"{v: .12f}" if abs(v) < 1e4 else f"{v: .6f}" for v in row) for row in r.T_crs_map)
        + "</pre>",
    ]
    return out


def _statistics_section(r) -> list[str]:
    """Adjustment statistics: σ0 and its χ² test, w-test critical value, RMS residuals, geometry."""
    chi = r.chi2
    verdict = chi.get("verdict", "n/a")
    rms = r.rms_m
    return [
        "<h2>Adjustment statistics</h2><table>",
        f"<tr><th class='l'>GCPs / observations / unknowns / dof</th><td>{r.n_gcps} / {3 * r.n_gcps} / "
        f"{7 if r.model == 'similarity' else 6} / {r.dof}</td></tr>",
        f"<tr><th class='l'>σ0 (a posteriori, 1 expected)</th><td>{num(r.sigma0, '.4f')}</td></tr>",
        f"<tr><th class='l'>χ² test vᵀWv = {num(chi.get('statistic'), '.3f')} in "
        f"[{num(chi.get('lower'), '.3f')}, {num(chi.get('upper'), '.3f')}] (α = {num(chi.get('alpha'), 'g')})</th>"
        f"<td><b>{_e(verdict)}</b></td></tr>",
        f"<tr><th class='l'>parameter covariance scaled with</th><td>{_e(r.variance_used)} σ0</td></tr>",
        f"<tr><th class='l'>w-test critical value (α = {r.params.blunder_alpha:g})</th><td>{r.w_critical:.3f}</td></tr>",
        f"<tr><th class='l'>RMS residual horizontal / height / 3D</th><td>{rms['horizontal'] * 1000:.2f} / "
        f"{rms['height'] * 1000:.2f} / {rms['3d'] * 1000:.2f} mm</td></tr>",
        f"<tr><th class='l'>rotation-free scale check (unit rule)</th><td>{num(r.scale_estimate_spread, '.8f')}</td></tr>",
        f"<tr><th class='l'>GCP geometry (σ2/σ1 of map coordinates)</th><td>{num(r.geometry_ratio, '.3f')}</td></tr>",
        "</table>",
    ]


def _gcp_section(r) -> list[str]:
    """The per-GCP table: coordinates, residuals, σ, w-test values, redundancy numbers, flags."""
    out = [
        "<h2>Ground control points</h2>",
        "<table><tr><th class='l'>id</th><th>x map</th><th>y map</th><th>z map</th><th>E</th><th>N</th><th>H</th>"
        "<th>v<sub>E</sub> mm</th><th>v<sub>N</sub> mm</th><th>v<sub>H</sub> mm</th><th>σ<sub>E,N,H</sub> mm</th>"
        "<th>w<sub>E</sub></th><th>w<sub>N</sub></th><th>w<sub>H</sub></th><th>min r<sub>i</sub></th><th class='l'>flags</th></tr>",
    ]
    for i, gid in enumerate(r.gcp_ids):
        cls = " class='flag'" if r.blunder[i] else (" class='warn'" if r.flags[i] else "")
        x = r.gcp_local_xyz[i]
        X = r.gcp_crs_enh[i]
        v = r.residuals_m[i] * 1000
        s = r.sigma_used_m[i] * 1000
        w = r.w[i]
        out.append(
            f"<tr{cls}><td class='l'>{_e(gid)}</td><td>{x[0]:.3f}</td><td>{x[1]:.3f}</td><td>{x[2]:.3f}</td>"
            f"<td>{X[0]:.3f}</td><td>{X[1]:.3f}</td><td>{X[2]:.3f}</td>"
            f"<td>{v[0]:+.1f}</td><td>{v[1]:+.1f}</td><td>{v[2]:+.1f}</td>"
            f"<td>{s[0]:.1f}, {s[1]:.1f}, {s[2]:.1f}</td>"
            f"<td>{num(w[0], '+.2f')}</td><td>{num(w[1], '+.2f')}</td><td>{num(w[2], '+.2f')}</td>"
            f"<td>{num(np.min(r.redundancy[i]), '.2f')}</td><td class='l'>{_e(r.flags[i])}</td></tr>"
        )
    out.append("</table>")
    out.append(
        "<p class='small'>w = Baarda's standardised residual (a-priori σ0 = 1); a GCP is flagged when a "
        "coordinate has |w| above the critical value; the largest is the suspected blunder (remove it and "
        "re-run). r<sub>i</sub> = redundancy number (&lt; 0.1: the coordinate is barely checked by the others).</p>"
    )
    return out


def _tail(r, png: bytes | None, provenance: dict | None, timings: dict | None) -> list[str]:
    """Plan view, parameters used, run time and provenance, and the end of the page."""
    out = ["<h2>Plan view</h2>"]
    if png:
        out.append(img_png(png, "GCP residual vectors"))
    else:
        out.append(f"<p>{_e(NO_PLOT)}</p>")
    out.append("<h2>Parameters used</h2>")
    out.append(params_table({"crs": r.crs, **({} if r.params is None else _asdict(r.params))}))
    if timings:
        out.append("<h2>Run time (s; Numba compile time apart)</h2>")
        out.append(timings_html(timings))
    if provenance:
        vers = provenance.get("versions", {})
        out.append(
            "<h2>Provenance</h2><p class='small'>"
            + _e(", ".join(f"{k} {v}" for k, v in vers.items()))
            + f"<br>created {_e(provenance.get('created_utc', ''))}</p>"
        )
    out.append("</body></html>")
    return out


def georef_report_html(
    result,
    inputs: dict | None = None,
    png: bytes | None = None,
    outputs: dict | None = None,
    provenance: dict | None = None,
    timings: dict | None = None,
) -> str:
    """The HTML text of the report (see the module docstring); ``timings`` adds the run-time table."""
    r = result
    ci = r.as_dict()["crs_info"]
    out = _head(r, status_word(r.status), ci)
    out += _files_section(inputs, outputs)
    out += _crs_section(r, ci)
    out += _parameter_table(r)
    out += _scale_and_angles(r)
    out += _statistics_section(r)
    out += _gcp_section(r)
    out += _tail(r, png, provenance, timings)
    return "\n".join(out) + "\n"


def write_georef_report(
    path, result, inputs: dict | None = None, cloud_geo=None, outputs: dict | None = None, provenance: dict | None = None,
    timings: dict | None = None,
):
    """Write ``report.html`` (atomically) and return its path; the plot is embedded when possible."""
    png = plot_georef_png(result, cloud_geo=cloud_geo)
    return atomic_write_text(path, georef_report_html(result, inputs=inputs, png=png, outputs=outputs,
                                                      provenance=provenance, timings=timings))
