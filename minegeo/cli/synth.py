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

from minegeo.cli._argtypes import finite_float, float_in_range, int_in_range, nonnegative_int, positive_float

HELP = "write a seeded synthetic mine: map, local scans, trajectories, GCPs and truth.json"


def add_arguments(parser) -> None:
    parser.add_argument("outdir", metavar="OUTDIR", help="output directory (created; must be empty unless --force)")
    parser.add_argument("--preset", choices=("small", "paper"), default="small",
                        help="small: ~0.6 km, seconds (tests); paper: ~7 km, map ~1e7 points (benchmarks)")
    parser.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=0, help="random seed (default 0)")
    parser.add_argument("--force", action="store_true",
                        help="replace a non-empty OUTDIR as a whole (everything in it is deleted)")
    parser.add_argument("--gcps", type=int_in_range(3, 100_000), default=10, help="number of ground control points (default 10)")
    parser.add_argument("--crs", default="EPSG:5186", help="CRS of the control points (default EPSG:5186)")
    parser.add_argument("--mast", action="store_true",
                        help="also write a MAST beacon scenario (2D scan.csv, beacons.csv, truth.json) "
                             "into OUTDIR/mast/ (see docs/mast.md)")
    parser.add_argument("--mast-only", action="store_true",
                        help="write only the MAST beacon scenario into OUTDIR (no mine)")
    parser.add_argument("--flight", action="store_true",
                        help="also write a drone flight through level 0 (small preset) into OUTDIR/flight/: VLP-16 "
                             "frames and times as `minegeo track` reads them, the true trajectory in the map frame "
                             "(truth.tum) and in the CRS (truth_crs.tum), and start.txt (docs/intersections.md)")
    g = parser.add_argument_group("study options (docs/synth.md, 'Study worlds'; default: the preset as is)")
    g.add_argument("--roughness-m", type=positive_float, default=None, metavar="M",
                   help="std (m) of the wall-bump field, e.g. 0.05 / 0.08 (shotcrete-like) or 0.25 (blasted); "
                        "the preset's own is 0.064")
    g.add_argument("--lining", choices=("blasted", "shotcrete"), default=None,
                   help="roughness spectrum preset (std 0.25 / 0.065 m unless --roughness-m)")
    g.add_argument("--twins", choices=("none", "exact", "near"), default="none",
                   help="repeat level 0 on every level: exact copies (same rock and structures) or near copies "
                        "(same layout, independent rock)")
    g.add_argument("--unmapped", type=nonnegative_int, default=0, metavar="N",
                   help="add N headings that exist in the world but not in map.ply")
    s = parser.add_argument_group("sensor stream (docs/synth.md, 'Sensor streams'): raw motion-distorted sweeps "
                                  "with per-point times and an IMU, instead of the mine")
    s.add_argument("--stream", choices=("vehicle", "handheld", "drone"), default=None,
                   help="write a sensor stream of this carrier into OUTDIR (frames/ with times.txt, imu.csv, "
                        "imu_truth.csv, groundtruth.txt, result.json)")
    s.add_argument("--duration-s", type=positive_float, default=None, metavar="S", help="stream length (default 5 s)")
    s.add_argument("--lidar-hz", type=float_in_range(5.0, 20.0), default=None, metavar="HZ",
                   help="sweeps per second (default 10)")
    s.add_argument("--imu-hz", type=float_in_range(50.0, 1000.0), default=None, metavar="HZ",
                   help="IMU rate (default 200)")
    s.add_argument("--stream-network", default=None, metavar="NET",
                   help="loop (3.2 m drifts, default), junctions (3.5 m), an edge list CSV (NIOSH layout, 2.9 m) or "
                        "a path of the paper world (build_world('paper', 1), 4.5 m drifts): paper-ring (114 m), "
                        "paper-straight (505 m), paper-ramp (251 m, 25 m down)")
    s.add_argument("--drift-width-m", type=float_in_range(2.0, 10.0), default=None, metavar="M",
                   help="drift width of the stream network (default: the network's own)")
    s.add_argument("--station-spacing-m", type=float_in_range(6.0, 100_000.0), default=None, metavar="M",
                   help="stop-and-go survey stations every M m of path: the carrier stands still a few seconds on "
                        "each; writes stations.csv (surveyed, in --crs) and stations_truth.csv (docs/survey.md)")
    s.add_argument("--control-every", type=int_in_range(1, 100_000), default=None, metavar="K",
                   help="every K-th station (the first included) is a control station, the others check stations "
                        "(default 5: with 100 m spacing, control every 500 m)")
    s.add_argument("--station-offset", type=finite_float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="surveyed point of a station in the sensor frame (m; default 0 0 0), as minegeo slam "
                        "--station-offset")


def run(args) -> int:
    from minegeo.errors import InputError

    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    if args.mast_only:  # options that only shape the mine, which --mast-only does not write
        given = [o for o, v in (("--mast", args.mast), ("--flight", getattr(args, "flight", False)),
                                ("--roughness-m", args.roughness_m is not None),
                                ("--lining", args.lining is not None), ("--twins", args.twins != "none"),
                                ("--unmapped", args.unmapped != 0)) if v]
        if given:
            raise InputError(f"--mast-only writes the MAST scenario alone, no mine: {given[0]} has nothing to act on; "
                             "drop one of the two options")
    stream_params = _stream_params(args)  # None without --stream; raises InputError for a contradiction
    out = Path(args.outdir)
    # Validate every option before any work is done, so a mistake costs nothing and
    # leaves no half-written OUTDIR.
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise InputError(f"{out} is not empty; use --force to overwrite")
    if not args.mast_only and stream_params is None:
        if args.gcps < 3:
            raise InputError(f"--gcps: need at least 3 control points, got {args.gcps}")
        from minegeo.georef import validate_crs
        from minegeo.synth.dataset import crs_origin

        validate_crs(args.crs)  # a projected CRS in metres, as minegeo georef needs (not degrees)
        crs_origin(args.crs)  # raises CRSError for an unknown or unsuitable CRS
        if args.unmapped < 0:
            raise InputError(f"--unmapped must be >= 0, got {args.unmapped}")
        if args.roughness_m is not None and not args.roughness_m > 0:
            raise InputError(f"--roughness-m must be > 0, got {args.roughness_m}")
        from minegeo.synth.dataset import study_params

        study_params(args.preset, _study_options(args))  # raises InputError for a bad study option
        if getattr(args, "flight", False) and (args.preset != "small" or _study_options(args)):
            raise InputError("--flight flies the small preset's own mine (its route names its drifts): it does not "
                             "go with --preset paper or a study option; drop one of the two")
    from minegeo._output import OutputTransaction

    with OutputTransaction("synth", folders={"OUTDIR": out}, replace="any" if args.force else "result") as tx:
        return _write(args, tx.folder("OUTDIR"), out)


def _record_run(stage: Path, seed: int, kind: str, record: str) -> None:
    """The run's record ``result.json`` (kind, the data record it wrote, provenance with the options,
    so that ``minegeo synth OUTDIR --config result.json`` repeats the run); for a stream, whose
    ``result.json`` is its data record, the provenance is added to it. The data files stay byte-identical
    for the same options and seed; only this record carries the run's time."""
    import json

    from minegeo._provenance import provenance, write_json_atomic

    rec_path = stage / "result.json"
    rec = json.loads(rec_path.read_text()) if record == "result.json" else {
        "verb": "synth", "status": "ok", "kind": kind, "seed": int(seed), "record": record}
    rec["provenance"] = provenance(seed=int(seed))
    write_json_atomic(rec_path, rec)


def _write(args, stage, out) -> int:
    if args.mast_only:
        rc = _write_mast(stage, args.seed, out)
        _record_run(stage, args.seed, "MAST scenario", "truth.json")
    elif getattr(args, "stream", None):
        rc = _write_stream(args, stage, out)
        _record_run(stage, args.seed, "sensor stream", "result.json")
    else:
        rc = _write_mine(args, stage, out)
        _record_run(stage, args.seed, "mine", "truth.json")
    return rc


def _write_mine(args, stage, out) -> int:
    from tqdm import tqdm

    from minegeo._output import progress_enabled
    from minegeo.synth.dataset import SCAN_PLANS, write_world

    steps = 4 + len(SCAN_PLANS[args.preset])
    with tqdm(total=steps, desc=f"synth {args.preset}", unit="step", file=sys.stderr,
              disable=not progress_enabled(args)) as bar:

        def progress(name: str) -> None:
            bar.set_postfix_str(name)
            bar.update(1)

        truth = write_world(stage, args.preset, args.seed, force=True, n_gcps=args.gcps,
                            crs=args.crs, progress=progress, options=_study_options(args))
    w = truth["world"]
    print(f"wrote {out}: preset {args.preset}, seed {args.seed}")
    if "roughness" in w:
        print(f"  wall roughness: std {w['roughness']['wall_roughness_std_m']:.3f} m")
    if "repeat_levels" in w:
        print(f"  repeated levels: {w['repeat_levels']['mode']} copies, offset {w['repeat_levels']['offset_m']} m")
    if "unmapped_drifts" in w:
        print(f"  unmapped (in the world, not in map.ply): {', '.join(w['unmapped_drifts'])}")
    print(f"  world: {w['n_drifts']} drifts, {w['total_length_m']:.0f} m, {w['n_levels']} levels, "
          f"{w['n_loops']} loops, intersections {w['intersections_by_type']}, ramp slope(s) "
          + ", ".join(f"{s:.2f} deg" for s in w["ramp_slopes_deg"]))
    print(f"  map.ply: {truth['map']['n_points']} points")
    for s in truth["scans"]:
        print(f"  {s['file']}: {s['n_points']} points ({s['section']}, {s['length_m']:.0f} m, "
              f"{s['sensor']['model']}, {s['carrier']})")
    print(f"  gcps.csv: {truth['gcps']['n']} control points in {truth['crs']}; truth.json, report.txt")
    rc = _write_mast(stage / "mast", args.seed, out / "mast") if args.mast else 0
    if getattr(args, "flight", False):
        _write_flight(stage / "flight", args.seed, truth, out / "flight")
    from minegeo.report.synth_report import write_synth_report

    write_synth_report(stage, truth)
    print(f"  report: {out / 'report.html'}")
    return rc


def _study_options(args) -> dict:
    """The study options given on the command line (only those changed from their defaults)."""
    opts: dict = {}
    if getattr(args, "roughness_m", None) is not None:
        opts["wall_roughness_m"] = float(args.roughness_m)
    if getattr(args, "lining", None) is not None:
        opts["lining"] = args.lining
    if getattr(args, "twins", "none") != "none":
        opts["repeat_levels"] = args.twins
    if getattr(args, "unmapped", 0):
        opts["unmapped_headings"] = int(args.unmapped)
    return opts


def _write_mast(outdir, seed: int, final) -> int:
    """Write a MAST beacon scenario (2D scan, beacons, truth) with :func:`minegeo.mast.scenario.write_mast_scenario`."""
    from minegeo.mast.scenario import write_mast_scenario

    paths = write_mast_scenario(outdir, seed=seed)
    print(f"wrote MAST scenario (seed {seed}): " + ", ".join(str(Path(final) / Path(p).name) for p in paths.values()))
    return 0


def _stream_params(args):
    """The :class:`~minegeo.synth.stream.StreamParams` of ``--stream`` (None without it), checked before any work."""
    from minegeo.errors import InputError

    spacing = getattr(args, "station_spacing_m", None)
    opts = {"--duration-s": args.duration_s, "--lidar-hz": args.lidar_hz, "--imu-hz": args.imu_hz,
            "--stream-network": args.stream_network, "--drift-width-m": args.drift_width_m,
            "--station-spacing-m": spacing}
    for o, v in (("--control-every", getattr(args, "control_every", None)),
                 ("--station-offset", getattr(args, "station_offset", None))):
        if v is not None and spacing is None:
            raise InputError(f"{o} shapes the survey stations of a stream: give --stream and --station-spacing-m "
                             "with it")
    if not args.stream:
        given = [k for k, v in opts.items() if v is not None]
        if given:
            raise InputError(f"{given[0]} shapes a sensor stream: give --stream vehicle|handheld|drone with it")
        return None
    other = [o for o, v in (("--mast", args.mast), ("--mast-only", args.mast_only),
                            ("--flight", getattr(args, "flight", False)),
                            ("--roughness-m", args.roughness_m is not None), ("--lining", args.lining is not None),
                            ("--twins", args.twins != "none"), ("--unmapped", args.unmapped != 0),
                            ("--preset", args.preset != "small"), ("--gcps", args.gcps != 10),
                            ("--crs", args.crs != "EPSG:5186" and spacing is None)) if v]
    if other:
        raise InputError(f"--stream writes a sensor stream in a drift network, not the mine: {other[0]} has nothing "
                         "to act on; drop one of the two options")
    from minegeo.synth.imu import ImuParams
    from minegeo.synth.stream import StreamParams

    net = args.stream_network or "loop"
    from minegeo.synth.stream_paper import PAPER_NETWORKS

    if net not in ("loop", "junctions", *PAPER_NETWORKS) and not Path(net).is_file():
        raise InputError(f"--stream-network: {net} is neither loop, junctions, {', '.join(PAPER_NETWORKS)} nor an "
                         "edge list file")
    station = {}
    if spacing is not None:
        from minegeo.georef import validate_crs
        from minegeo.io.stations import parse_station_offset
        from minegeo.synth.dataset import crs_origin

        validate_crs(args.crs)  # a projected CRS in metres
        crs_origin(args.crs)
        station = {"station_spacing_m": spacing, "control_every": getattr(args, "control_every", None) or 5,
                   "station_offset_m": tuple(parse_station_offset(getattr(args, "station_offset", None) or
                                                                  [0.0, 0.0, 0.0])), "crs": args.crs}
    return StreamParams(preset=args.stream, duration_s=args.duration_s or 5.0, lidar_hz=args.lidar_hz or 10.0,
                        azimuth_step_deg=0.02 * (args.lidar_hz or 10.0), imu=ImuParams(rate_hz=args.imu_hz or 200.0),
                        network=net, width_m=args.drift_width_m, seed=args.seed, **station)


def _write_stream(args, stage, out) -> int:
    """Write the sensor stream of ``--stream`` (:func:`minegeo.synth.stream.write_stream`)."""
    from minegeo.synth.stream import write_stream

    rec = write_stream(stage, _stream_params(args))
    m = rec["motion_stats"]
    print(f"wrote {out}: {args.stream} stream, seed {args.seed}: {rec['n_frames']} sweeps at "
          f"{rec['params']['lidar_hz']:g} Hz ({rec['n_points']} points), {rec['n_imu']} IMU samples at "
          f"{rec['params']['imu']['rate_hz']:g} Hz")
    print(f"  path {m['path_length_m']:.1f} m, speed up to {m['max_speed_mps']:.2f} m/s, angular rate up to "
          f"{m['max_angular_rate_dps']:.0f} deg/s, tilt up to {m['max_tilt_deg']:.1f} deg")
    if "stations" in rec:
        s = rec["stations"]
        print(f"  stations.csv: {s['n']} station{'' if s['n'] == 1 else 's'} ({s['control']} control, {s['check']} check) every "
              f"{s['spacing_m']:g} m of path, {s['still_s']:g} s still on each, in {s['crs']}; stations_truth.csv")
    return 0


def _write_flight(folder: Path, seed: int, truth: dict, final: Path) -> None:
    """The drone flight of :func:`minegeo.synth.flight.mine_flight` as ``minegeo track`` reads it.

    ``frames/`` (binary PLY per frame, sensor frame, ``times.txt``), ``truth.tum`` (``T_map_sensor``,
    map frame = the frame of ``map.ply``), ``truth_crs.tum`` (``T_crs_map T_map_sensor``, CRS grid
    coordinates E, N, H) and ``start.txt`` (the first pose as ``x y z yaw_deg`` in both frames, yaw
    counter-clockwise from the frame's +x / grid east).
    """
    import numpy as np

    from minegeo._provenance import atomic_write_text
    from minegeo.io import write_trajectory
    from minegeo.io.types import Trajectory
    from minegeo.synth.flight import mine_flight
    from minegeo.synth.sequence import write_frames
    from minegeo.synth.world import build_world

    tr, frames = mine_flight(build_world("small", seed), seed=seed)
    write_frames(folder / "frames", tr.times_s, frames)
    write_trajectory(folder / "truth.tum", tr, format="tum")
    T_crs_map = np.asarray(truth["T_crs_map"], float)
    crs = Trajectory(tr.times_s, np.einsum("ij,njk->nik", T_crs_map, tr.poses), frame=str(truth["crs"]), body="sensor")
    write_trajectory(folder / "truth_crs.tum", crs, format="tum")

    def pose(T):
        return (f"{T[0, 3]:.3f} {T[1, 3]:.3f} {T[2, 3]:.3f} "
                f"{np.degrees(np.arctan2(T[1, 0], T[0, 0])):.3f}")

    lines = [f"map {pose(tr.poses[0])}", f"crs {pose(crs.poses[0])}"]
    atomic_write_text(folder / "start.txt", "# first pose: frame x y z yaw_deg (yaw counter-clockwise from +x / "
                      "grid east)\n" + "\n".join(lines) + "\n")
    length = float(np.linalg.norm(np.diff(tr.poses[:, :3, 3], axis=0), axis=1).sum())
    print(f"  flight/: {len(frames)} VLP-16 frames over {length:.0f} m ({tr.times_s[-1]:.0f} s), truth.tum (map), "
          f"truth_crs.tum ({truth['crs']})")
    print(f"  flight start (x y z yaw_deg): map {pose(tr.poses[0])}; crs {pose(crs.poses[0])}")
