"""``minegeo synth OUTDIR``: write a seeded synthetic mine (map, local scans, trajectories, GCPs, truth).

The output depends only on ``--preset`` and ``--seed``: running it twice gives
byte-identical files (no clock times or absolute paths are written). ``truth.json``
holds the ground truth (``T_crs_map``, ``T_map_scan`` per scan, sensors, sections,
intersections) with the SHA-256 of every other file; ``report.txt`` a short summary and
``report.html`` the report (truth summary, plan view of the mine and the scan positions;
:mod:`minegeo.report.synth_report`). ``--mast-only`` writes the MAST scenario files only.
"""

from __future__ import annotations

import sys
from pathlib import Path

HELP = "write a seeded synthetic mine: map, local scans, trajectories, GCPs and truth.json"


def add_arguments(parser) -> None:
    parser.add_argument("outdir", metavar="OUTDIR", help="output directory (created; must be empty unless --force)")
    parser.add_argument("--preset", choices=("small", "paper"), default="small",
                        help="small: ~0.6 km, seconds (tests); paper: ~7 km, map ~1e7 points (benchmarks)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--force", action="store_true",
                        help="replace a non-empty OUTDIR as a whole (everything in it is deleted)")
    parser.add_argument("--gcps", type=int, default=10, help="number of ground control points (default 10)")
    parser.add_argument("--crs", default="EPSG:5186", help="CRS of the control points (default EPSG:5186)")
    parser.add_argument("--mast", action="store_true",
                        help="also write a MAST beacon scenario (2D scan.csv, beacons.csv, truth.json) "
                             "into OUTDIR/mast/ (see docs/mast.md)")
    parser.add_argument("--mast-only", action="store_true",
                        help="write only the MAST beacon scenario into OUTDIR (no mine)")


def run(args) -> int:
    from minegeo.errors import InputError

    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    out = Path(args.outdir)
    # Validate every option before any work is done, so a mistake costs nothing and
    # leaves no half-written OUTDIR.
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise InputError(f"{out} is not empty; use --force to overwrite")
    if not args.mast_only:
        if args.gcps < 3:
            raise InputError(f"--gcps: need at least 3 control points, got {args.gcps}")
        from minegeo.localize.crs import validate_crs
        from minegeo.synth.dataset import _crs_origin

        validate_crs(args.crs)  # a projected CRS in metres, as minegeo georef needs (not degrees)
        _crs_origin(args.crs)  # raises CRSError for an unknown or unsuitable CRS
    from minegeo._output import OutputTransaction

    with OutputTransaction("synth", folders={"OUTDIR": out}, replace="any" if args.force else "result") as tx:
        return _write(args, tx.folder("OUTDIR"), out)


def _write(args, stage, out) -> int:
    from tqdm import tqdm

    from minegeo._output import progress_enabled
    from minegeo.synth.dataset import SCAN_PLANS, write_world

    if args.mast_only:
        return _write_mast(stage, args.seed, out)
    steps = 4 + len(SCAN_PLANS[args.preset])
    with tqdm(total=steps, desc=f"synth {args.preset}", unit="step", file=sys.stderr,
              disable=not progress_enabled(args)) as bar:

        def progress(name: str) -> None:
            bar.set_postfix_str(name)
            bar.update(1)

        truth = write_world(stage, args.preset, args.seed, force=True, n_gcps=args.gcps,
                            crs=args.crs, progress=progress)
    w = truth["world"]
    print(f"wrote {out}: preset {args.preset}, seed {args.seed}")
    print(f"  world: {w['n_drifts']} drifts, {w['total_length_m']:.0f} m, {w['n_levels']} levels, "
          f"{w['n_loops']} loops, intersections {w['intersections_by_type']}, ramp slope(s) "
          + ", ".join(f"{s:.2f} deg" for s in w["ramp_slopes_deg"]))
    print(f"  map.ply: {truth['map']['n_points']} points")
    for s in truth["scans"]:
        print(f"  {s['file']}: {s['n_points']} points ({s['section']}, {s['length_m']:.0f} m, "
              f"{s['sensor']['model']}, {s['carrier']})")
    print(f"  gcps.csv: {truth['gcps']['n']} control points in {truth['crs']}; truth.json, report.txt")
    rc = _write_mast(stage / "mast", args.seed, out / "mast") if args.mast else 0
    from minegeo.report.synth_report import write_synth_report

    write_synth_report(stage, truth)
    print(f"  report: {out / 'report.html'}")
    return rc


def _write_mast(outdir, seed: int, final) -> int:
    """Write a MAST beacon scenario (2D scan, beacons, truth) with :func:`minegeo.mast.scenario.write_mast_scenario`."""
    from minegeo.mast.scenario import write_mast_scenario

    paths = write_mast_scenario(outdir, seed=seed)
    print(f"wrote MAST scenario (seed {seed}): " + ", ".join(str(Path(final) / Path(p).name) for p in paths.values()))
    return 0
