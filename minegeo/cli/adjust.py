"""``minegeo adjust NETWORK --out DIR``: least-squares adjustment of a survey network.

NETWORK is a text file in the Krumm/GNU Gama example format (``[Coordinates]``, ``[Datum]``,
``[Distances]``, ``[Angles,dms,s]``, ``[Directions]``, ``[LevelledHeightDifferences]``, …; see
``docs/survey.md``) or the equivalent JSON (``.json``). Writes ``DIR/result.json`` (points with
standard deviations, σ̂0, dof, χ² test, observations with residuals / standardised residuals /
redundancy numbers / flags, ellipses, parameters, versions, input sha256),
``DIR/report.txt`` and ``DIR/report.html``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from minegeo._provenance import StageTimer, provenance
from minegeo.cli._argtypes import open_unit_interval, positive_int
from minegeo.errors import InputError

HELP = "adjust a survey network (Krumm/Gama text or JSON) by least squares: coordinates, sigma0, chi-square, residuals, ellipses"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("network", help="network file: Krumm/Gama text format (.dat) or JSON (.json)")
    parser.add_argument(
        "--out", required=True, help="output directory (result.json, report.txt, report.html)"
    )
    parser.add_argument(
        "--variance",
        choices=("aposteriori", "apriori"),
        default="aposteriori",
        help="scale covariances with the estimated sigma0 (default, like adjustment packages) or the a-priori sigma0 = 1",
    )
    parser.add_argument(
        "--confidence", type=open_unit_interval, default=0.95, help="confidence level of the ellipses (default 0.95)"
    )
    parser.add_argument(
        "--alpha",
        type=open_unit_interval,
        default=0.05,
        help="significance of the two-tailed chi-square test (default 0.05)",
    )
    parser.add_argument(
        "--alpha-w", type=open_unit_interval, default=0.001, help="significance of Baarda's w-test (default 0.001 -> 3.29)"
    )
    parser.add_argument(
        "--alpha-tau", type=open_unit_interval, default=0.05, help="overall significance of Pope's tau-test (default 0.05)"
    )
    parser.add_argument("--max-iterations", type=positive_int, default=50, help="Gauss-Newton iterations (default 50)")
    parser.add_argument(
        "--dxf", action="store_true",
        help="also write DIR/adjusted.dxf for mine-planning CAD: adjusted and fixed points with names and their "
             "confidence ellipses on MINEGEO_* layers, network coordinates (needs minegeo[dxf])",
    )


def _write_dxf(stage: Path, res, confidence: float) -> Path:
    """``adjusted.dxf`` (points, names, confidence ellipses), recorded under ``"dxf"`` in the staged result.json."""
    import json

    from minegeo._provenance import write_json_atomic
    from minegeo.cli._dxf import dxf_record
    from minegeo.io.dxf import DxfDrawing

    pct = f"{100.0 * confidence:.4g}".replace(".", "_")
    dwg = DxfDrawing(frame="network coordinates (x = E, y = N, z = h; 0 when the network has no heights)",
                     ellipse_layer=f"ELLIPSE{pct}")
    skipped = []
    for pid, p in res.points.items():
        if p.x is None or p.y is None:  # a levelling-only point has no plan position to draw
            skipped.append(pid)
            continue
        at = (p.x, p.y, p.h if p.h is not None else 0.0)
        free = [a for a in ("x", "y", "z") if a not in p.fixed and (a != "z" or p.h is not None)]
        dwg.point("adjusted_points" if free else "fixed_points", at, label=pid)
        e = p.ellipse_95
        if e is not None:
            dwg.ellipse(at, e.semi_major_m, e.semi_minor_m, e.azimuth_rad)
    if skipped:
        dwg.property("MINEGEO_NOT_DRAWN", "; ".join(skipped) + " (no plan coordinates)")
    path = stage / "adjusted.dxf"
    rec = dxf_record(path, dwg.save(path))
    rec["confidence"] = confidence
    rj = stage / "result.json"
    d = json.loads(rj.read_text(encoding="utf-8"))
    d["dxf"] = rec
    write_json_atomic(rj, d)
    return path


def run(args) -> int:
    from minegeo.io.network import read_network
    from minegeo.report.survey_report import write_survey_report
    from minegeo.survey.lsq import LSQOptions
    from minegeo.survey.network import adjust_network

    path = Path(args.network)
    if not path.is_file():
        raise FileNotFoundError(2, "network file not found", str(path))
    if not 0 < args.confidence < 1:
        raise InputError(f"--confidence must be between 0 and 1, got {args.confidence}")
    from minegeo._output import OutputTransaction, run_timings

    out = Path(args.out)
    if args.dxf:
        from minegeo.cli._dxf import require_dxf

        require_dxf()  # a missing ezdxf stops the run before any work
    with OutputTransaction("adjust", inputs={"NETWORK": path}, folders={"--out": out}) as tx:
        timer = StageTimer()
        with timer("read"):
            net = read_network(path)
        opts = LSQOptions(
            variance=args.variance,
            alpha_global=args.alpha,
            alpha_w=args.alpha_w,
            alpha_tau=args.alpha_tau,
            max_iterations=args.max_iterations,
        )
        with timer("adjust"):
            res = adjust_network(net, opts, confidence=args.confidence)
        params = {
            "variance": args.variance,
            "confidence": args.confidence,
            "alpha_global": args.alpha,
            "alpha_w": args.alpha_w,
            "alpha_tau": args.alpha_tau,
            "max_iterations": args.max_iterations,
            "timings_s": {**timer.as_dict(), **run_timings(args)},
        }
        prov = provenance(seed=None, origin=res.local_origin, inputs=[path])
        staged = write_survey_report(res, tx.folder("--out"), params, prov)
        if args.dxf:
            staged["dxf"] = _write_dxf(tx.folder("--out"), res, args.confidence)
    paths = {k: out / Path(v).name for k, v in staged.items()}
    if getattr(args, "quiet", False):  # -q: only warnings and errors (the result is in the files)
        return 0
    lsq = res.lsq
    chi = lsq.chi2
    print(f"adjusted {len(res.points)} point(s) from {len(lsq.v)} observation equation(s); dof = {lsq.dof}")
    print(
        f"sigma0 = {lsq.sigma0:.4f}; chi-square test {chi.verdict} ({chi.statistic:.3f} in [{chi.lower:.3f}, {chi.upper:.3f}])"
    )
    flagged = [o for o in res.observations if o.flag and o.flag != "weak r_i"]
    if flagged:
        print(f"{len(flagged)} observation(s) flagged by data snooping; see {paths['report_html']}")
    print("wrote " + ", ".join(str(v) for v in paths.values()))
    return 0
