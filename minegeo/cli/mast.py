"""``minegeo mast``: scanner position and azimuth from one 2D scan of two surveyed beacons (MAST)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from minegeo._params import arg_type

#: the parameter class whose field rules the options use (imported when an option is parsed)
_MAST = "minegeo.mast.pipeline:MastParams"

HELP = "position and azimuth of a 2D scanner from two wall beacons (MAST, Simela et al.)"


def add_arguments(parser) -> None:
    parser.add_argument("--scan", required=True, help="2D scan CSV with header bearing_deg,range_m (bearing clockwise)")
    parser.add_argument("--beacons", required=True, help="beacons CSV with header beacon_id,vertex,x_m,y_m")
    parser.add_argument("--out", required=True, help="output directory (result.json, report.html)")
    parser.add_argument("--sigma-range-m", type=arg_type(_MAST, "sigma_range_m"), default=None,
                        help="range noise of the scanner (m); default: '# sigma_range_m' line of the scan file")
    parser.add_argument("--sigma-bearing-deg", type=arg_type(_MAST, "sigma_bearing_deg"), default=None,
                        help="bearing noise (deg); default: from the scan file, else 0")
    parser.add_argument("--sigma-panel-m", type=arg_type(_MAST, "sigma_panel_m"), default=0.0,
                        help="extra per-return panel-line uncertainty (panel flatness), m")
    parser.add_argument("--sigma-beacon-m", type=arg_type(_MAST, "sigma_beacon_m"), default=0.0,
                        help="standard deviation of each surveyed beacon vertex coordinate (m); "
                             "propagated with full correlation")
    parser.add_argument("--ccw", action="store_true", help="bearings in the file are counter-clockwise")
    parser.add_argument("--min-beacons", type=arg_type(_MAST, "min_beacons"), default=2, help="beacons that must be seen (default 2)")
    parser.add_argument("--options", default="1,2,3,4,5,6",
                        help="segmentation options of the paper's Table 1 allowed (default 1,2,3,4,5,6)")
    parser.add_argument("--variance", choices=("aposteriori", "apriori"), default="aposteriori",
                        help="sigma0 scaling the covariance (default aposteriori)")
    parser.add_argument("--dxf", action="store_true",
                        help="also write DIR/mast.dxf for mine-planning CAD: station with its 95 %% ellipse and the "
                             "beacons on MINEGEO_* layers, mine-frame coordinates, z = 0 (needs minegeo[dxf])")


def _write_dxf(path: Path, res, beacons) -> dict:
    """``mast.dxf``: the station (ok only) with its 95 % ellipse, and the surveyed beacons (mine frame, z = 0)."""
    import math

    from minegeo.cli._dxf import dxf_record
    from minegeo.io.dxf import DxfDrawing

    dwg = DxfDrawing(frame="mine frame of the beacons (E, N; 2-D: z = 0)")
    for b in beacons:
        dwg.polyline3d("beacons", b.vertices_m, label=b.beacon_id)
    if res.ok:
        dwg.point("stations", (res.x_m, res.y_m, 0.0), label=f"MAST station, azimuth {res.azimuth_dms}")
        e = res.ellipse95 or {}
        if e.get("a_m") is not None:
            dwg.ellipse((res.x_m, res.y_m, 0.0), float(e["a_m"]), float(e["b_m"]), math.radians(e["orientation_deg"]))
    else:
        dwg.property("MINEGEO_NOT_PLACED", f"MAST station ({res.status}: no position)")
    return dxf_record(path, dwg.save(path))


def run(args) -> int:
    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.errors import InputError
    from minegeo.mast import MastParams, SegmentationParams, locate_scanner, read_beacons_csv, read_scan_csv
    from minegeo.report.mast_report import write_mast_report

    timer = StageTimer()
    try:
        options = tuple(int(o) for o in str(args.options).split(",") if o.strip())
    except ValueError:
        raise InputError(f"--options must be a comma list of 1-6, got {args.options!r}") from None
    params = MastParams(
        sigma_range_m=args.sigma_range_m,
        sigma_bearing_deg=args.sigma_bearing_deg,
        sigma_panel_m=args.sigma_panel_m,
        sigma_beacon_m=args.sigma_beacon_m,
        segmentation=SegmentationParams(options=options),
        min_beacons=args.min_beacons,
        variance=args.variance,
    )
    out = Path(args.out)
    if args.dxf:
        from minegeo.cli._dxf import require_dxf

        require_dxf()  # a missing ezdxf stops the run before any work
    with OutputTransaction("mast", inputs={"--scan": args.scan, "--beacons": args.beacons},
                           folders={"--out": out}) as tx:
        with timer("read"):
            scan = read_scan_csv(args.scan, counter_clockwise=args.ccw)
            beacons = read_beacons_csv(args.beacons)
        with timer("locate"):
            res = locate_scanner(scan, beacons, params)
        stage = tx.folder("--out")
        inputs = {"scan": input_record(args.scan), "beacons": input_record(args.beacons)}
        summary = res.summary()
        summary["parameters"] = asdict(params)
        summary["timings_s"] = {**timer.as_dict(), **run_timings(args)}
        summary["provenance"] = provenance(seed=None, origin=res.details.get("origin_m"),
                                           inputs=list(inputs.values()))
        if args.dxf:
            summary["dxf"] = _write_dxf(stage / "mast.dxf", res, beacons)
        write_json_atomic(stage / "result.json", summary)
        write_mast_report(res, beacons, stage, inputs, timings=summary["timings_s"])
        # exactly the files in the result folder, named at their final (committed) paths
        names = ", ".join(str(out / n) for n in sorted((f.name for f in stage.iterdir()),
                                                        key=lambda n: (n != "result.json", n)))
    if getattr(args, "quiet", False):  # -q: only warnings and errors (the result is in the files)
        return 0 if res.ok else 1
    if res.ok:
        print(f"x = {res.x_m:.4f} m  y = {res.y_m:.4f} m  azimuth = {res.azimuth_dms}  "
              f"(95% ellipse {1000 * res.ellipse95['a_m']:.1f} x {1000 * res.ellipse95['b_m']:.1f} mm, "
              f"azimuth ±{3600 * res.azimuth_ci95_deg:.0f}\", sigma0 {res.sigma0:.2f})")
        print(f"written: {names}")
        return 0
    print(f"minegeo mast: FAILED: {res.reason}")
    print(f"written: {names}")
    return 1
