"""Human-readable report of a MAST scanner positioning (:func:`minegeo.mast.locate_scanner`).

Writes ``report.md`` (the numbers a surveyor checks: pose, covariance, 95 % ellipse,
azimuth interval, sigma0 and its chi-square test, beacons and panels identified, the
noise model) and, when matplotlib is installed, ``mast_plot.png`` with the scan in the
mine frame, the identified panel returns, the beacons and the 95 % error ellipse.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes, atomic_write_text

__all__ = ["write_mast_report", "mast_report_text", "plot_mast"]


def _f(v, fmt: str) -> str:
    return "n/a" if v is None else format(v, fmt)


def mast_report_text(result, inputs: dict | None = None, plot_name: str | None = None) -> str:
    """Markdown text of the report (see module docstring)."""
    d = result.details
    lines = ["# MAST scanner positioning report", ""]
    lines.append(f"**Status: {result.status.upper()}**" + (f" — {result.reason}" if result.reason else ""))
    lines.append("")
    if inputs:
        lines += ["## Inputs", ""]
        for k, rec in inputs.items():
            lines.append(f"- {k}: `{rec['path']}` (sha256 `{rec['sha256'][:16]}…`, {rec['size_bytes']} bytes)")
        lines.append("")
    nm = d.get("noise_model", {})
    lines += [
        "## Noise model used for the weights",
        "",
        f"- range σ_r = {_f(nm.get('sigma_range_m'), '.4f')} m, bearing σ_β = "
        f"{_f(nm.get('sigma_bearing_deg'), '.5f')}°, panel σ = {_f(nm.get('sigma_panel_m'), '.4f')} m, "
        f"beacon vertex σ = {_f(nm.get('sigma_beacon_m'), '.4f')} m",
        f"- returns in the scan: {d.get('n_returns')}, straight lines found: {d.get('n_lines')}",
        "",
    ]
    if result.ok:
        cov = np.asarray(result.covariance)
        e = result.ellipse95
        chi = d.get("chi2_global_test", {})
        lines += [
            "## Result (mine frame)",
            "",
            "| quantity | value | std. dev. |",
            "|---|---|---|",
            f"| Easting x | {result.x_m:.4f} m | {1000 * math.sqrt(cov[0, 0]):.2f} mm |",
            f"| Northing y | {result.y_m:.4f} m | {1000 * math.sqrt(cov[1, 1]):.2f} mm |",
            f"| Azimuth of scanner forward axis | {result.azimuth_deg:.6f}° = {result.azimuth_dms} | "
            f"{3600 * math.sqrt(cov[2, 2]):.1f}″ |",
            "",
            f"95 % error ellipse: a = {1000 * e['a_m']:.2f} mm, b = {1000 * e['b_m']:.2f} mm, major axis azimuth "
            f"{e['orientation_deg']:.1f}° ({d.get('ellipse95_basis')}).",
            f"95 % azimuth interval: ± {3600 * result.azimuth_ci95_deg:.1f}″.",
            "",
            "Covariance (x [m], y [m], azimuth [deg]) = σ0²·(BᵀWB)⁻¹ "
            f"({d.get('variance_used')} σ0):",
            "",
            "```",
            *(" ".join(f"{v: .6e}" for v in row) for row in cov),
            "```",
            "",
            f"σ0 = {result.sigma0:.3f} (dof {d.get('dof')}, {d.get('n_observations')} returns on beacon panels); "
            f"χ² global test {chi.get('statistic', float('nan')):.1f} in [{chi.get('lower', float('nan')):.1f}, "
            f"{chi.get('upper', float('nan')):.1f}]: {'PASSED' if chi.get('passed') else 'FAILED'}.",
            "",
            "## How it was found",
            "",
            f"- Segmentation option (paper Table 1) of the panel identification used: {result.segmentation_option} "
            f"(per beacon: {d.get('per_beacon_option')})",
            f"- Returns per beacon in the adjustment: {d.get('returns_per_beacon')}",
            f"- ICP iterations: {result.icp_iterations}, ICP RMS {1000 * d.get('icp', {}).get('rms_m', float('nan')):.2f} mm, "
            f"β_cum (scan→mine rotation, clockwise) = {d.get('beta_cum_deg', float('nan')):.4f}°",
            f"- Local origin subtracted for the computation: {list(np.asarray(d.get('origin_m')).tolist())}",
            "",
        ]
    hyps = d.get("hypotheses") or []
    if hyps:
        lines += ["## Beacon-id hypotheses aligned", "", "| assignment (cluster → beacon) | Helmert scale | returns explained | rejected |",
                  "|---|---|---|---|"]
        for h in hyps:
            lines.append(f"| {h.get('assignment')} | {_f(h.get('helmert_scale'), '.4f')} | {h.get('n_explained', '')} | "
                         f"{h.get('rejected', '')} |")
        lines.append("")
    if plot_name:
        lines += [f"![scan, identified panels and 95 % ellipse]({plot_name})", ""]
    lines += ["Method: Simela, Marshall & Daneshmend (MAST); see docs/mast.md for the equations and the deviations.", ""]
    return "\n".join(lines)


def plot_mast(result, beacons) -> bytes | None:
    """PNG bytes of the overview plot, or None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.patches import Ellipse
    except ImportError:
        return None
    a = result.arrays
    fig, axs = plt.subplots(2, 2, figsize=(12, 11))
    axes = [axs[0, 0], axs[0, 1]]
    ax = axes[0]
    if result.ok and "points_mine" in a:
        P = a["points_mine"]
        ax.plot(P[:, 0], P[:, 1], ".", ms=1.5, color="0.6", label="scan returns")
        used = a["used"]
        ax.plot(P[used, 0], P[used, 1], ".", ms=3, color="tab:red", label="returns on identified panels")
        ax.plot(result.x_m, result.y_m, "k^", ms=8, label="scanner")
        L = 1.0
        az = math.radians(result.azimuth_deg)
        ax.annotate("", xy=(result.x_m + L * math.sin(az), result.y_m + L * math.cos(az)),
                    xytext=(result.x_m, result.y_m), arrowprops={"arrowstyle": "->"})
    elif "points_scan" in a:
        P = a["points_scan"]
        ax.plot(P[:, 0], P[:, 1], ".", ms=1.5, color="0.6", label="scan (scanner frame)")
        for s, e in a.get("segments", []):
            ax.plot(P[[s, e], 0], P[[s, e], 1], "-", lw=1)
    for b in beacons:
        v = b.vertices_m
        ax.plot(v[:, 0], v[:, 1], "-", color="tab:blue", lw=2)
        ax.text(v[0, 0], v[0, 1], f" {b.beacon_id}", color="tab:blue")
    ax.set_aspect("equal")
    ax.set_xlabel("Easting x (m)")
    ax.set_ylabel("Northing y (m)")
    ax.set_title(f"MAST: {result.status}")
    ax.legend(loc="best", fontsize=8)
    ax2 = axes[1]
    if result.ok:
        e = result.ellipse95
        cov = np.asarray(result.covariance)
        ell = Ellipse((0, 0), 2000 * e["a_m"], 2000 * e["b_m"], angle=90.0 - e["orientation_deg"],
                      fill=False, color="tab:red", lw=2, label="95 % ellipse")
        ax2.add_patch(ell)
        sx, sy = 1000 * math.sqrt(cov[0, 0]), 1000 * math.sqrt(cov[1, 1])
        ax2.errorbar([0], [0], xerr=[sx], yerr=[sy], fmt="k+", label="±1σ")
        r = 1.2 * 1000 * e["a_m"]
        ax2.set_xlim(-r, r)
        ax2.set_ylim(-r, r)
        ax2.set_aspect("equal")
        ax2.set_xlabel("ΔEasting (mm)")
        ax2.set_ylabel("ΔNorthing (mm)")
        ax2.set_title(f"95 % ellipse a={1000 * e['a_m']:.2f} mm b={1000 * e['b_m']:.2f} mm; "
                      f"az {result.azimuth_dms} ± {3600 * result.azimuth_ci95_deg:.0f}″", fontsize=9)
        ax2.legend(loc="best", fontsize=8)
    else:
        ax2.text(0.05, 0.5, "no pose:\n" + result.reason, wrap=True, transform=ax2.transAxes, fontsize=9)
        ax2.set_axis_off()
    for k, axz in enumerate([axs[1, 0], axs[1, 1]]):
        if k >= len(beacons):
            axz.set_axis_off()
            continue
        b = beacons[k]
        v = b.vertices_m
        c = v.mean(axis=0)
        r = 0.75 * float(b.panel_lengths_m.sum())
        if result.ok and "points_mine" in a:
            P = a["points_mine"]
            near = np.hypot(P[:, 0] - c[0], P[:, 1] - c[1]) < 2 * r
            ax_p = P[near]
            axz.plot(ax_p[:, 0], ax_p[:, 1], ".", ms=3, color="0.6", label="returns")
            u = a["used"] & near
            axz.plot(P[u, 0], P[u, 1], ".", ms=5, color="tab:red", label="used in adjustment")
        axz.plot(v[:, 0], v[:, 1], "-o", color="tab:blue", lw=1.5, ms=4, label=f"{b.beacon_id} panels (surveyed)")
        for i in range(3):
            m = 0.5 * (v[i] + v[i + 1])
            axz.text(m[0], m[1], f" P{i + 1}", fontsize=8, color="tab:blue")
        axz.set_xlim(c[0] - r, c[0] + r)
        axz.set_ylim(c[1] - r, c[1] + r)
        axz.set_aspect("equal")
        axz.set_title(f"beacon {b.beacon_id}", fontsize=9)
        axz.legend(loc="best", fontsize=7)
        axz.ticklabel_format(useOffset=False, style="plain")
        axz.tick_params(axis="x", labelrotation=30)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def write_mast_report(result, beacons, outdir, inputs: dict | None = None) -> dict[str, Path]:
    """Write ``report.md`` (and ``mast_plot.png`` if matplotlib is available) into ``outdir``."""
    out = Path(outdir)
    paths: dict[str, Path] = {}
    png = plot_mast(result, beacons)
    if png is not None:
        paths["plot"] = atomic_write_bytes(out / "mast_plot.png", png)
    paths["report"] = atomic_write_text(out / "report.md", mast_report_text(result, inputs, "mast_plot.png" if png else None))
    return paths
