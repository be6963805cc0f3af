"""Self-contained HTML report of a MAST scanner positioning (:func:`minegeo.mast.locate_scanner`).

``report.html`` — one file to mail or archive (inline CSS, the plot embedded as a ``data:`` PNG,
no scripts, no external resources). It opens with the status banner (``OK``, or ``FAILED``
with the reason), then the numbers a surveyor checks: pose with standard deviations, 95 %
error ellipse and azimuth interval, covariance, σ0 and its χ² test, beacons and panels
identified, the beacon-id hypotheses, the overview plot (:func:`plot_mast`: scan in the mine
frame, returns used, beacons and the 95 % ellipse; needs matplotlib,
``pip install 'minegeo[report]'``), the noise model and the parameters the run used.
"""

from __future__ import annotations

import io
import math
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
    timings_html,
)

__all__ = ["write_mast_report", "mast_report_html", "plot_mast"]


def mast_report_html(result, beacons=(), inputs: dict | None = None, png: bytes | None = None,
                     timings: dict | None = None) -> str:
    """HTML text of the report (see the module docstring).

    Parameters
    ----------
    result : MastResult
    beacons : sequence of Beacon
        The surveyed beacons (listed in the report).
    inputs : dict, optional
        ``{role: input record}`` (``path``, ``sha256``, ``size_bytes``).
    png : bytes, optional
        The overview plot (:func:`plot_mast`); without it the report says why there is none.
    """
    d = result.details
    status = status_word(result.status)
    if result.ok:
        e = result.ellipse95
        text = (f"x = {result.x_m:.4f} m, y = {result.y_m:.4f} m, azimuth {result.azimuth_dms}; 95 % ellipse "
                f"{1000 * e['a_m']:.1f} × {1000 * e['b_m']:.1f} mm, σ0 = {num(result.sigma0, '.2f')}")
    else:
        text = result.reason or "no pose"
    secs = []
    if inputs:
        secs.append(("Inputs", table(["role", "file", "SHA-256", "bytes"],
                                     [[k, rec.get("path"), rec.get("sha256"), rec.get("size_bytes")]
                                      for k, rec in inputs.items()], numeric=[3])))
    if result.ok:
        cov = np.asarray(result.covariance)
        e = result.ellipse95
        chi = d.get("chi2_global_test", {})
        passed = chi.get("passed")
        secs.append(("Result (mine frame)", table(
            ["quantity", "value", "std. dev."],
            [["Easting x", f"{result.x_m:.4f} m", f"{1000 * math.sqrt(cov[0, 0]):.2f} mm"],
             ["Northing y", f"{result.y_m:.4f} m", f"{1000 * math.sqrt(cov[1, 1]):.2f} mm"],
             ["Azimuth of the scanner forward axis", f"{result.azimuth_deg:.6f}° = {result.azimuth_dms}",
              f"{3600 * math.sqrt(cov[2, 2]):.1f}″"]], numeric=[1, 2])))
        secs.append(("Uncertainty (95 %)", kv_table([
            ("95 % error ellipse", f"a = {1000 * e['a_m']:.2f} mm, b = {1000 * e['b_m']:.2f} mm, major axis "
                                   f"azimuth {e['orientation_deg']:.1f}° ({d.get('ellipse95_basis')})"),
            ("95 % azimuth interval", f"± {3600 * result.azimuth_ci95_deg:.1f}″"),
            ("covariance", f"σ0²·(BᵀWB)⁻¹ with the {d.get('variance_used')} σ0; units x [m], y [m], azimuth [deg]"),
        ]) + "<pre>" + esc("\n".join(" ".join(f"{v: .6e}" for v in row) for row in cov)) + "</pre>"))
        secs.append(("Statistics", f"<p>χ² global test: {badge('PASSED' if passed else 'FAILED', bool(passed))}</p>"
                     + kv_table([
                         ("σ0 (a posteriori)", num(result.sigma0, ".3f")),
                         ("degrees of freedom", d.get("dof")),
                         ("returns on beacon panels", d.get("n_observations")),
                         ("χ² statistic", f"{num(chi.get('statistic'), '.1f')} in [{num(chi.get('lower'), '.1f')}, "
                                          f"{num(chi.get('upper'), '.1f')}]"),
                     ])))
    secs.append(("Plot", f"<figure>{img_png(png, 'scan, identified panels and 95 % ellipse')}<figcaption>Top "
                         "left: scan in the mine frame, returns used (red), beacons (blue), scanner and its "
                         "forward axis; top right: 95 % error ellipse (mm); bottom: each beacon's panels "
                         "with the returns used.</figcaption></figure>" if png else f"<p>{esc(NO_PLOT)}</p>"))
    if result.ok:
        secs.append(("How it was found", kv_table([
            ("segmentation option (paper Table 1)", f"{result.segmentation_option} (per beacon: "
                                                    f"{d.get('per_beacon_option')})"),
            ("returns per beacon in the adjustment", d.get("returns_per_beacon")),
            ("ICP", f"{result.icp_iterations} iterations, RMS "
                    f"{num(1000 * d.get('icp', {}).get('rms_m', float('nan')), '.2f')} mm"),
            ("β_cum (scan → mine rotation, clockwise)", f"{num(d.get('beta_cum_deg'), '.4f')}°"),
            ("local origin subtracted for the computation", str(np.asarray(d.get("origin_m")).tolist())),
        ])))
    hyps = d.get("hypotheses") or []
    if hyps:
        secs.append(("Beacon-id hypotheses aligned", table(
            ["assignment (cluster → beacon)", "Helmert scale", "returns explained", "rejected"],
            [[h.get("assignment"), num(h.get("helmert_scale"), ".4f"), h.get("n_explained", ""), h.get("rejected", "")]
             for h in hyps], numeric=[1, 2])))
    if beacons:
        rows = []
        for b in beacons:
            for i, v in enumerate(np.asarray(b.vertices_m)):
                rows.append([b.beacon_id, i, f"{v[0]:.4f}", f"{v[1]:.4f}"])
        secs.append(("Beacons (surveyed)", table(["beacon", "vertex", "x [m]", "y [m]"], rows, numeric=[1, 2, 3])))
    nm = d.get("noise_model", {})
    secs.append(("Noise model used for the weights", kv_table([
        ("range σ_r", f"{num(nm.get('sigma_range_m'), '.4f')} m"),
        ("bearing σ_β", f"{num(nm.get('sigma_bearing_deg'), '.5f')}°"),
        ("panel σ", f"{num(nm.get('sigma_panel_m'), '.4f')} m"),
        ("beacon vertex σ", f"{num(nm.get('sigma_beacon_m'), '.4f')} m"),
        ("returns in the scan / straight lines found", f"{d.get('n_returns')} / {d.get('n_lines')}"),
    ])))
    secs.append(("Parameters used", params_table(result.params) if result.params is not None
                 else "<p>(not recorded)</p>"))
    if timings:
        secs.append(("Run time (s; Numba compile time apart)", timings_html(timings)))
    secs.append(("Method", "<p>Simela, Marshall &amp; Daneshmend (MAST); see docs/mast.md for the equations and "
                           "the deviations.</p>"))
    return page("MAST scanner positioning", secs, subtitle="position and azimuth of a 2D scanner from wall beacons",
                status=status, status_text=text)


def plot_mast(result, beacons) -> bytes | None:
    """PNG bytes of the 4-panel overview plot, or None without matplotlib.

    Uses the object-oriented API (``Figure`` + Agg canvas): no global pyplot state or backend
    is touched, and no time-dependent metadata is written.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Ellipse
    except ImportError:
        return None
    a = result.arrays
    fig = Figure(figsize=(12, 11))
    FigureCanvasAgg(fig)
    axs = fig.subplots(2, 2)
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
        axz.set_xlabel("Easting x (m)", fontsize=8)
        axz.set_ylabel("Northing y (m)", fontsize=8)
        axz.legend(loc="best", fontsize=7)
        axz.ticklabel_format(useOffset=False, style="plain")
        axz.tick_params(axis="x", labelrotation=30)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    return buf.getvalue()


def write_mast_report(result, beacons, outdir, inputs: dict | None = None,
                      timings: dict | None = None) -> dict[str, Path]:
    """Write ``report.html`` (plot embedded when matplotlib is available) into ``outdir``.

    Returns ``{"report": path}``: exactly the files written.
    """
    out = Path(outdir)
    png = plot_mast(result, beacons)
    return {"report": atomic_write_text(out / "report.html", mast_report_html(result, beacons, inputs, png, timings))}
