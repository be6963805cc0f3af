"""``minegeo localize``: place a local scan (and its sensor trajectory) in a prior mine map and its CRS.

Writes ``DIR/result.json`` (status, reason, ``T_map_scan``, ``T_crs_scan``, scores, covariance,
timings, parameters, versions, seed, input hashes), ``DIR/trajectory_global.csv`` when a
trajectory is given and the result is ``ok``, and ``DIR/report.html``. **Only an ok result gives
coordinates**: for ``failed`` / ``ambiguous`` the pose fields of result.json are null and the
placements that were tried are under ``rejected_candidates`` (map frame, "NOT a position"), the
printout says FAILED / AMBIGUOUS, why, and lists those candidates as rejected, and the report's
first line is the status banner. Exit status 0 for ``ok``, 1 for ``ambiguous`` or ``failed``
(result.json says why), 2 for input errors (one stderr line; nothing is written, an earlier
result folder is left as it was: an unusable scan, empty, tiny or flat, is one).

Default ``--profile``: :data:`DEFAULT_PROFILE` (measured, docs/localization.md). A progress bar
on stderr names each step when stderr is a terminal (not with ``--quiet``); the printed time is
the whole command's, Numba compile time apart.

``--map`` takes a map file (plain, or georeferenced by ``minegeo georef`` with its sidecar) or a
prepared map (``.npz`` from ``minegeo prepare-map``). A map file is prepared in-process and the
result cached next to it as ``<map>.prepared-<hash12>.npz`` (``<hash12>`` = first 12 hex digits of
the parameter hash); the cache is reused only when the map's SHA-256 matches (``--no-cache`` to
disable).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

from minegeo._params import arg_type
from minegeo.cli._argtypes import MAX_COUNT, int_in_range
from minegeo.cli._common import StepBar, summary_lines_quiet, time_line, whole_run_timings

#: the parameter classes whose field rules the options use (imported when an option is parsed)
_LP, _ICP, _VERIFY = ("minegeo.localize.params:" + c for c in ("LocalizeParams", "IcpParams", "VerifyParams"))
_RANSAC = "minegeo.registration.ransac_params:RansacParams"
#: ``--levelled`` says the scan's z axis is up like the map's: a tilt allowance beyond 90 deg (an up
#: axis below the horizon) contradicts that, so the option takes at most 90 deg, where the library's
#: ``RansacParams.max_tilt_deg`` (a prior of any model) takes up to 180 deg
LEVELLED_MAX_DEG = 90.0
_MAX_TEXT = f"{MAX_COUNT:.0e}".replace("e+0", "e")  # the counts' cap in the help: "1e9"
#: ``IcpParams.method`` and ``CorrelativeStageParams.mode`` (tests check they equal the Literals)
ICP_CHOICES = ("point_to_point", "point_to_plane", "gicp")
CORRELATIVE_CHOICES = ("fallback", "always", "off")

log = logging.getLogger(__name__)

HELP = "globally localize a local scan (+ trajectory) in a prior map: FPFH + RANSAC + ICP (Baek et al. 2022)"

#: Default ``--profile`` of ``localize`` and ``prepare-map``: chosen by
#: ``benchmarks/bench_default_profile.py`` (success first, no wrong ``ok``, then time; on the 25
#: scans of ``minegeo synth --preset small`` seeds 0-4: fast 17/25 ok and correct in 0.5 s per
#: scan, table3 7/25 in 1.0 s, both 0 wrong ``ok``; docs/localization.md).
DEFAULT_PROFILE = "fast"
#: What each profile is, for ``--help``, the report and the printout.
PROFILE_TEXT = {
    "fast": "minegeo's measured default: voxel 1 m, normals 2 m, FPFH 5 m, 3-point RANSAC with mutual matches "
            "and always 1e6 draws, point-to-plane ICP",
    "table3": "the paper-faithful profile, Baek et al. 2022 Table 3 (voxel 0.5 m, normals 1 m, FPFH 2.5 m, 4-point RANSAC, "
              "point-to-point ICP; minegeo caps RANSAC at 4e6 draws instead of 4e8 and uses mutual matches)",
}


def add_arguments(parser) -> None:
    parser.add_argument("--map", required=True,
                        help="prior map: point cloud (georeferenced map_geo.ply with sidecar, or plain) or prepared .npz")
    parser.add_argument("--scan", required=True, help="local scan point cloud in its own frame")
    parser.add_argument("--trajectory", default=None, help="sensor trajectory of the scan (TUM/KITTI/CSV, scan frame)")
    parser.add_argument("--out", required=True, help="output directory (result.json, report.html, trajectory_global.csv)")
    parser.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=0, help="random seed (default 0)")
    add_profile_arguments(parser)
    parser.add_argument("--icp", default=None, choices=ICP_CHOICES,
                        help="ICP variant (table3 profile: point_to_point as the paper; fast: point_to_plane; "
                             "gicp: Generalized-ICP)")
    parser.add_argument("--ransac-max-iterations", type=arg_type(_RANSAC, "max_iterations", le=MAX_COUNT),
                        default=None,
                        help=f"RANSAC iteration cap, a whole number from 1 to {_MAX_TEXT} (table3 profile: 4e6, "
                             "the paper's Table 3 uses 4e8; fast: 1e6)")
    parser.add_argument("--ransac-runs", type=arg_type(_LP, "ransac_runs"), default=1,
                        help="independent RANSAC runs whose hypotheses are all verified by ICP (default 1)")
    parser.add_argument("--no-mutual-filter", action="store_true",
                        help="use every FPFH nearest neighbour as a putative match (the paper) instead of mutual ones")
    parser.add_argument("--ransac-min-iterations", type=arg_type(_RANSAC, "min_iterations", le=MAX_COUNT),
                        default=None,
                        help=f"RANSAC draws before Eq. 8 may stop the search, a whole number from 0 to {_MAX_TEXT} "
                             "(fast profile: 1e6; table3: 0 = Eq. 8 alone, as the paper)")
    parser.add_argument("--hypotheses", type=arg_type(_RANSAC, "n_hypotheses", le=MAX_COUNT), default=None,
                        metavar="K",
                        help="distinct RANSAC hypotheses verified by ICP per run, a whole number from 2 "
                             f"(default 2: best and runner-up) to {_MAX_TEXT}")
    parser.add_argument("--levelled", type=arg_type(_RANSAC, "max_tilt_deg", le=LEVELLED_MAX_DEG), default=None,
                        metavar="DEG",
                        help="the scan frame is levelled (z up, e.g. by the scanner's IMU) like the map: RANSAC "
                             "draws 2-point yaw+translation hypotheses and rejects placements tilting the "
                             "vertical by more than DEG degrees (e.g. 3; DEG in (0, 90]); ICP still refines all 6 DOF")
    parser.add_argument("--correlative", default=None, choices=CORRELATIVE_CHOICES,
                        help="with --levelled: the exhaustive 4-DOF correlative search of the whole map adds its "
                             "best placements when the RANSAC hypotheses fail (fallback, default), always, or never")
    parser.add_argument("--no-gravity-fallback", action="store_true",
                        help="without --levelled: do not retry a failed 6-DOF scan levelled by its own up direction "
                             "(floor, roof, walls; residual tilts up to 15 deg searched for ramps)")
    parser.add_argument("--fine-tolerance", type=arg_type(_VERIFY, "fine_tolerance_m", off=0.0), default=None,
                        metavar="M",
                        help="plane tolerance (m) of the fine agreement that tells smooth drifts apart (default "
                             "0.04, widened to 2 x the scan's surface noise); 0 turns it off")
    parser.add_argument("--polish", type=arg_type(_ICP, "polish_correspondence_m", off=0.0), default=None,
                        metavar="M",
                        help="gate (m) of the final tight point-to-plane polish of the chosen pose (default 0.25; "
                             "the gate used is max(M, 3 x the scan's surface noise)); 0 turns it off")
    parser.add_argument("--no-cache", action="store_true", help="do not read or write the prepared-map cache")
    parser.add_argument("--dxf", action="store_true",
                        help="also write DIR/placement.dxf for mine-planning CAD: scan origin, 95 %% ellipse and "
                             "trajectory on MINEGEO_* layers in CRS coordinates (ok results only; needs minegeo[dxf])")
    parser.add_argument("--drop-nonfinite", action="store_true",
                        help="drop scan points with NaN/inf coordinates (organised PCD/PLY files mark missing "
                             "returns that way) instead of refusing the file")


def add_profile_arguments(parser) -> None:
    """--profile / --voxel / --octree-level (shared with prepare-map)."""
    parser.add_argument("--profile", choices=("fast", "table3"), default=DEFAULT_PROFILE,
                        help=f"fast (default): {PROFILE_TEXT['fast']}; table3: {PROFILE_TEXT['table3']}. "
                             "Map and scan must use the same profile. Measured on the synthetic mine: fast 17/25 "
                             "scans ok and correct, table3 7/25 (docs/localization.md)")
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--voxel", type=arg_type(_LP, "scan_voxel_size_m"), default=None, metavar="M",
                   help="voxel size in m for map and scan (profile default: fast 1.0, table3 0.5); the normal and FPFH "
                        "radii scale with it (2x and 5x, the Table 3 ratios)")
    g.add_argument("--octree-level", type=arg_type(_LP, "scan_octree_level"), default=None, metavar="L",
                   help="octree subsampling level of the scan (Sec. 2.2, e.g. 6, 8, 10, 12) instead of a voxel "
                        "(localize) or of the map (prepare-map)")


def check_combinations(args) -> None:
    """Refuse options that contradict each other (an option that cannot act with the others given),
    before any file is read. Options missing from ``args`` (another verb's) count as not given."""
    from minegeo.errors import InputError

    levelled = getattr(args, "levelled", None) is not None
    lo, hi = getattr(args, "ransac_min_iterations", None), getattr(args, "ransac_max_iterations", None)
    if lo is not None and hi is not None and lo > hi:
        raise InputError(f"--ransac-min-iterations {lo} exceeds --ransac-max-iterations {hi}: the search would "
                         "stop at the cap before its stopping rule may act; lower the first or raise the second")
    if levelled and getattr(args, "no_gravity_fallback", False):
        raise InputError("--no-gravity-fallback applies to 6-DOF scans (without --levelled): a levelled scan has no "
                         "gravity fallback; drop one of the two options")
    if not levelled and getattr(args, "no_gravity_fallback", False) and getattr(args, "correlative", None) is not None:
        raise InputError("--correlative acts on levelled searches (--levelled, or the gravity fallback of a 6-DOF "
                         "scan), and --no-gravity-fallback without --levelled leaves none; drop one of the options")


def params_from_args(args):
    """(PrepareParams, LocalizeParams) from the CLI options (also used by ``prepare-map``)."""
    from dataclasses import replace

    from minegeo.localize.params import CorrelativeStageParams, FeatureParams, LocalizeParams, PrepareParams

    check_combinations(args)

    profile = getattr(args, "profile", None) or DEFAULT_PROFILE
    if profile == "fast":
        prep, lp = PrepareParams.fast(), LocalizeParams.fast()
    else:
        prep, lp = PrepareParams(), LocalizeParams()
    voxel = getattr(args, "voxel", None)  # checked by its type (LocalizeParams.scan_voxel_size_m's rule)
    if voxel is not None:
        feats = FeatureParams(normal_radius_m=2.0 * voxel, fpfh_radius_m=5.0 * voxel)
        prep = replace(prep, voxel_size_m=float(voxel), features=feats)
        lp = replace(lp, scan_voxel_size_m=float(voxel), features=feats)
    icp = getattr(args, "icp", None)
    runs = getattr(args, "ransac_runs", 1)
    if runs is None:
        runs = 1
    # the values were checked by the options' types (the fields' own rules, --levelled and the counts
    # with the options' own upper bounds; 0 = off for the optional ones)
    kw = {"ransac_runs": int(runs)}
    icp_kw, verify_kw = {}, {}
    if icp is not None:
        icp_kw["method"] = icp
    if getattr(args, "octree_level", None) is not None:
        kw["scan_octree_level"] = int(args.octree_level)
    corr = getattr(args, "correlative", None)
    if corr == "off":
        kw["correlative"] = None
    elif corr is not None:
        kw["correlative"] = replace(lp.correlative or CorrelativeStageParams(), mode=str(corr))
    polish = getattr(args, "polish", None)
    if polish is not None:
        icp_kw["polish_correspondence_m"] = float(polish) if float(polish) > 0.0 else None
    if getattr(args, "no_gravity_fallback", False):
        kw["gravity_fallback"] = None
    fine = getattr(args, "fine_tolerance", None)
    if fine is not None:
        verify_kw["fine_tolerance_m"] = float(fine) if float(fine) > 0.0 else None
    if icp_kw:
        kw["icp"] = replace(lp.icp, **icp_kw)
    if verify_kw:
        kw["verify"] = replace(lp.verify, **verify_kw)
    lp = replace(lp, **kw)
    rk = {}
    if getattr(args, "ransac_max_iterations", None) is not None:
        rk["max_iterations"] = int(args.ransac_max_iterations)
    if getattr(args, "no_mutual_filter", False):
        rk["mutual_filter"] = False
    if getattr(args, "ransac_min_iterations", None) is not None:
        rk["min_iterations"] = int(args.ransac_min_iterations)
    if getattr(args, "hypotheses", None) is not None:
        rk["n_hypotheses"] = int(args.hypotheses)
    if getattr(args, "levelled", None) is not None:
        rk.update(model="levelled", ransac_n=2, max_tilt_deg=float(args.levelled))
    if rk:
        lp = replace(lp, ransac=replace(lp.ransac, **rk))
    return prep, lp


def _write_trajectory_csv(path: Path, res) -> None:
    import numpy as np

    from minegeo._provenance import atomic_write_text
    from minegeo.io import matrix_to_quat

    tm = res.trajectory_map
    tg = res.trajectory_geo
    head = ["time_s", "x_map_m", "y_map_m", "z_map_m"]
    if tg is not None:
        head += ["E_m", "N_m", "H_m"]
    head += ["qx", "qy", "qz", "qw", "sigma_3d_m", "status"]
    lines = ["# sensor trajectory placed by minegeo localize (Baek et al. 2022, Eq. 18): "
             "T_map_sensor = T_map_scan * T_scan_sensor",
             f"# crs: {res.crs or 'none'}; status: {res.status}; quaternion = orientation in "
             + ("the CRS axes (geo frame)" if tg is not None else "map axes"),
             ",".join(head)]
    for i in range(len(tm.times_s)):
        row = [f"{tm.times_s[i]:.6f}"] + [f"{v:.4f}" for v in tm.poses[i, :3, 3]]
        R = tm.poses[i, :3, :3]
        if tg is not None:
            row += [f"{v:.4f}" for v in tg.poses[i, :3, 3] + tg.origin]
            R = tg.poses[i, :3, :3]
        q = matrix_to_quat(R, order="xyzw", atol=1e-3)
        row += [f"{v:.9f}" for v in q]
        s = res.trajectory_sigma_m[i] if res.trajectory_sigma_m is not None else np.inf
        row += [f"{s:.4f}" if np.isfinite(s) else "inf", res.status]
        lines.append(",".join(row))
    atomic_write_text(path, "\n".join(lines) + "\n")


def run(args) -> int:
    from minegeo._output import OutputTransaction

    out = Path(args.out)
    if args.seed < 0:
        from minegeo.errors import InputError

        raise InputError(f"--seed must be >= 0, got {args.seed}")
    prep, lp = params_from_args(args)
    if getattr(args, "dxf", False):
        from minegeo.cli._dxf import require_dxf

        require_dxf()  # a missing ezdxf stops the run before any work
    for name in ("map", "scan", "trajectory"):
        v = getattr(args, name)
        if v is not None and not Path(v).exists():
            from minegeo.errors import InputError

            raise InputError(f"--{name} {v} does not exist")
    inputs = {"--map": args.map, "--scan": args.scan, "--trajectory": args.trajectory}
    # the result folder is staged and replaces an earlier one only when this run ends without an
    # error: a user mistake leaves the earlier folder as it was and writes nothing
    with OutputTransaction("localize", inputs=inputs, folders={"--out": out}) as tx:
        n_idx = 3 + (3 if lp.ransac.model == "levelled" and lp.correlative is not None else 0) \
            + (1 if lp.icp.method == "gicp" else 0)
        with StepBar(args, "localize", total=2 + n_idx + 8 + 1) as bar:
            res, d, how = _run(args, prep, lp, tx.folder("--out"), out, bar)
    if not getattr(args, "quiet", False):
        d["timings_s"].update(whole_run_timings(args))  # after the commit: the whole command
        print_result(res, d, how, out)
    return 0 if res.status == "ok" else 1


def _run(args, prep, lp, stage: Path, out: Path, progress):
    from minegeo._provenance import input_record
    from minegeo.localize.prepared import cache_path, load_or_prepare

    t_start = time.perf_counter()
    inputs = [input_record(args.map), input_record(args.scan)]
    if args.trajectory:
        inputs.append(input_record(args.trajectory))

    # read and check the scan first: a user mistake there should not cost a map preparation
    progress("read scan")
    scan, traj, t_read = read_scan_inputs(args.scan, args.trajectory, lp,
                                          drop_nonfinite=bool(getattr(args, "drop_nonfinite", False)))
    progress("load map" if str(args.map).lower().endswith(".npz") else "load or prepare map")
    t0 = time.perf_counter()
    # the cache of a freshly prepared map is written below, once, with its search structures
    with summary_lines_quiet():
        pm, how = load_or_prepare(args.map, prep, use_cache=not args.no_cache, write_cache=False)
    t_map = time.perf_counter() - t0
    # the map's search structures (KD-trees, descriptor tree, occupancy bitmap): once per
    # process, timed apart from the scan's own localization
    index_s = pm.build_indexes(lp, progress=lambda name: progress(f"search structure {name}"))
    base = result_base(pm, how, t_map, index_s, profile=getattr(args, "profile", None) or DEFAULT_PROFILE,
                       inputs=inputs, seed=args.seed,
                       cache_file=None if (how == "prepared_file" or args.no_cache) else cache_path(args.map, prep))
    # an unusable scan (too few points, flat, degenerate) raises a typed error: exit 2, nothing written
    res, d = localize_and_write(stage, pm, scan, traj, lp, seed=args.seed, base=base, t_read=t_read, t_start=t_start,
                                run_timings=lambda: whole_run_timings(args), progress=progress)
    if how == "computed" and not args.no_cache:
        # only once the scan was usable: a run stopped by a user mistake leaves nothing new behind
        progress("write map cache")
        try:
            pm.save(cache_path(args.map, prep))
        except OSError as exc:
            log.warning("could not write the prepared-map cache: %s", exc)
    if getattr(args, "dxf", False):  # placement.dxf for CAD (coordinates only for ok), recorded in result.json
        from minegeo._provenance import write_json_atomic
        from minegeo.cli._dxf import write_localize_result_dxf

        d["dxf"] = write_localize_result_dxf(stage, d)
        write_json_atomic(stage / "result.json", d)
    return res, d, how


def read_scan_inputs(scan_path, trajectory_path, lp, *, drop_nonfinite: bool = False):
    """Read and check a scan (and its trajectory) for :func:`localize_and_write`.

    Returns ``(scan, trajectory or None, seconds)``; raises the typed errors of the readers and
    :class:`~minegeo.errors.TooFewPointsError` for a scan with fewer than ``lp.min_scan_points``
    points (shared by ``localize`` and ``localize-batch``)."""
    from minegeo.errors import TooFewPointsError
    from minegeo.io import read_point_cloud, read_trajectory

    t0 = time.perf_counter()
    scan = read_point_cloud(scan_path, drop_nonfinite=drop_nonfinite)
    if len(scan) < lp.min_scan_points:
        raise TooFewPointsError(f"the scan {scan_path} has only {len(scan)} points; at least {lp.min_scan_points} "
                                "are needed to localize it")
    traj = read_trajectory(trajectory_path, frame="scan") if trajectory_path else None
    return scan, traj, time.perf_counter() - t0


def result_base(pm, how: str, t_map: float, index_s: dict, *, profile: str, inputs: list, seed: int,
                cache_file=None) -> dict:
    """The run-level fields of ``result.json`` (profile, inputs, map preparation, versions, seed, and
    the command's options as ``provenance.arguments``: ``None`` in a localize-batch worker, whose
    batch records them in its ``batch_result.json``)."""
    from minegeo._provenance import arguments_provenance, versions

    return {
        "profile": profile,
        "inputs": inputs,
        "map_preparation": {"source": how, "seconds": t_map, "timings_s": index_s, "n_points": len(pm),
                            "params_hash": pm.params_hash,
                            "cache_file": None if cache_file is None else str(cache_file)},
        "versions": versions(),
        "seed": int(seed),
        "provenance": arguments_provenance(),
    }


def localize_and_write(stage: Path, pm, scan, traj, lp, *, seed: int, base: dict, t_read: float, t_start: float,
                       run_timings, progress=None):
    """Localize one scan in a loaded map and write its result folder's files into ``stage``.

    The per-scan work of ``minegeo localize``, shared with ``minegeo localize-batch`` so that both
    write the same ``result.json`` (up to its timings), ``report.html`` and
    ``trajectory_global.csv`` for the same map, scan, parameters and seed.

    Parameters
    ----------
    stage : Path
        Folder to write into (the staging folder of an :class:`~minegeo._output.OutputTransaction`).
    pm : PreparedMap
    scan, traj : PointCloud, Trajectory or None
        From :func:`read_scan_inputs`.
    lp : LocalizeParams
    seed : int
    base : dict
        :func:`result_base` (its ``map_preparation`` seconds become ``timings_s`` entries).
    t_read, t_start : float
        Seconds spent reading the inputs; ``time.perf_counter()`` when the run started.
    run_timings : callable
        Returns the run's ``wall_s``, ``compile_s``, ``work_s`` (added to ``timings_s``).
    progress : callable, optional
        ``progress(step)`` as each step starts.

    Returns
    -------
    (LocalizationResult, dict)
        The result and its ``result.json`` record.
    """
    from minegeo._provenance import write_json_atomic
    from minegeo.localize.pipeline import localize_scan
    from minegeo.report.localize_report import write_localize_report

    progress = progress or (lambda step: None)
    res = localize_scan(pm, scan, traj, lp, seed=seed, progress=progress)
    d = res.to_dict()
    timings = dict(d["timings_s"])
    timings["localize_total"] = timings.pop("total")
    timings["map_load_or_prepare"] = base["map_preparation"]["seconds"]
    timings["map_indexes"] = float(sum(base["map_preparation"]["timings_s"].values()))
    timings["read_inputs"] = t_read
    d["timings_s"] = timings
    d.update(base)
    # only an ok result is a position: no trajectory file otherwise (result.json says why)
    if res.status == "ok" and res.trajectory_map is not None:
        _write_trajectory_csv(stage / "trajectory_global.csv", res)
        d["trajectory_csv"] = "trajectory_global.csv"
    elif res.trajectory_map is not None:
        d["trajectory_csv"] = None
        d["trajectory_note"] = (f"no trajectory_global.csv: the localization is {res.status}, so no sensor pose "
                                "in the map or the CRS is known")
    d["timings_s"]["total"] = time.perf_counter() - t_start
    d["timings_s"].update(run_timings())  # wall_s, compile_s (Numba), work_s of the whole run
    progress("report")
    write_localize_report(stage / "report.html", res, pm, scan=scan, inputs=base["inputs"], extra=d)
    write_json_atomic(stage / "result.json", d)
    return res, d


#: What to do next after a ``failed`` / ``ambiguous`` result, for the printout.
NEXT_STEP = {
    "failed": "check that the scan lies inside the mapped area and that the map is current there; if it does, scan a "
              "longer section (20 m or more) that includes a distinctive feature (intersection, curve, structure) "
              "and run again; a scanner levelled by its IMU: add --levelled 3",
    "ambiguous": "scan a longer section that reaches a distinctive feature (intersection, curve, structure) so that "
                 "only one place fits, and run again",
}


def heading_text(res) -> str:
    """The scan's heading for the printout: azimuth of the scan x axis, clockwise from grid north
    (CRS), or its angle anticlockwise from the map x axis (map frame), degrees in [0, 360)."""
    if res.T_crs_scan is not None:
        R = res.T_crs_scan[:3, :3]
        return (f"heading {math.degrees(math.atan2(R[0, 0], R[1, 0])) % 360.0:.1f} deg (azimuth of the scan's x axis, "
                "clockwise from grid north)")
    R = res.T_map_scan[:3, :3]
    return (f"heading {math.degrees(math.atan2(R[1, 0], R[0, 0])) % 360.0:.1f} deg (the scan's x axis, anticlockwise "
            "from the map x axis)")


def position_line(res) -> str:
    """Position of the scan origin with its 95 % radius (:func:`minegeo.report.localize_report.position_text`)."""
    from minegeo.report.localize_report import position_text

    return position_text(res)


def fit_line(res) -> str:
    """One line of fit quality of an ``ok`` result: share of the scan on the map surface, ICP
    fitness and RMSE, and how far the best other place falls short."""
    pf = res.hypotheses[0]["plane_fitness"] if res.hypotheses else float("nan")
    txt = (f"fit: {100 * pf:.0f} % of the scan within {res.plane_tolerance_m:.3g} m of the map surface, "
           f"{100 * res.fitness:.0f} % matched by ICP, RMSE {res.inlier_rmse_m:.3f} m")
    rv = getattr(res, "rival_search", None) or {}
    b = rv.get("best_rival")
    if rv and b is None:
        txt += "; the whole-map search found no other place that fits"
    elif b is not None:
        txt += (f"; the best other place ({b['distance_to_chosen_m']:.0f} m away) fits {b['plane_fitness']:.2f} "
                f"against {b['chosen_plane_fitness']:.2f}")
    return txt


def _candidate_lines(res, limit: int = 3) -> list[str]:
    """Rejected candidates for the printout: map frame, each against the first ranked (#0) by the
    ranking criterion; labelled NOT a position."""
    from minegeo.localize.pipeline import rejected_candidates
    from minegeo.report.localize_report import rank_reason

    cands = rejected_candidates(res)
    if not cands:
        return ["  rejected candidates: none (no placement of the scan was proposed)"]
    hyps = {int(h["rank"]): h for h in res.hypotheses or []}
    lines = [f"  rejected candidates ({len(cands)}; NOT positions: where the scan origin would be if that "
             "placement were right, map frame x y z, m; ranked by fine agreement, then plane fitness):"]
    h0 = hyps.get(0)
    for c in cands[:limit]:
        x, y, z = c["origin_map_m"]
        h = hyps.get(c["rank"])
        if c["rank"] == 0 or h is None or h0 is None:
            why = "ranked first" if c["rank"] == 0 else ""
        else:
            why = (f"{c['distance_to_best_m']:.1f} m / {c['rotation_to_best_deg']:.1f} deg from #0, "
                   f"{rank_reason(h, h0)}")
        fine = f", fine agreement {h['fine_fitness']:.3f}" if h is not None else ""
        lines.append(f"    #{c['rank']} map x {x:.1f} y {y:.1f} z {z:.1f} (not a position; {why}): plane fitness "
                     f"{c['plane_fitness']:.3f}{fine}; {c['source']}")
    if len(cands) > limit:
        lines.append(f"    ... {len(cands) - limit} more in result.json -> rejected_candidates")
    return lines


def _rival_line(res) -> str | None:
    """The whole-map rival search's best rival (map frame, labelled NOT a position; printed for a
    failed / ambiguous result, an ok result's is in its fit line)."""
    rv = getattr(res, "rival_search", None)
    if not rv:
        return None
    b = rv.get("best_rival")
    tail = "" if rv.get("covered") else "; coverage incomplete, see result.json"
    if b is None:
        return f"  whole-map rival search at the chosen attitude: no other placement found{tail}"
    x, y, z = b["origin_map_m"]
    test = f"; passes the {b['test_passed']} test" if b.get("test_passed") else ""
    return (f"  best rival (NOT a position; {'rejected' if res.status == 'ok' else 'a rival'}; whole-map rival "
            f"search): map x {x:.1f} y {y:.1f} z {z:.1f}, {b['distance_to_chosen_m']:.1f} m / "
            f"{b['rotation_to_chosen_deg']:.1f} deg from {'the answer' if res.status == 'ok' else '#0'}, plane "
            f"fitness {b['plane_fitness']:.3f} vs {b['chosen_plane_fitness']:.3f} (margin {b['margin']:.2f}, "
            f"ambiguous at <= {1.0 / rv['ambiguity_ratio']:.2f}), support-matched {b['matched_ratio']:.2f} "
            f"(ambiguous at >= {rv['params']['matched_ratio']:g}){test}{tail}")


def print_result(res, d: dict, how: str, out: Path) -> None:
    """The stdout of ``minegeo localize``, for a surveyor.

    ``ok``: the status, the position of the scan origin (E N H in the CRS when the map is
    georeferenced, else map x y z) with its 95 % radius from the calibrated covariance, the
    heading, one line of fit quality, the files written and the time. ``failed`` / ``ambiguous``:
    the status, why, what to do next, the rejected candidates (map frame, NOT positions) and the
    files; **never a position**.
    """
    t = d["timings_s"]
    times = (f"time: scan {t['localize_total']:.2f} s (+ map {how} {t['map_load_or_prepare']:.2f} s, its search "
             f"structures {t['map_indexes']:.2f} s); run {time_line(t)}")
    profile = d.get("profile") or DEFAULT_PROFILE
    if res.status == "ok":
        print(f"OK: the scan is placed in the map (profile {profile})")
        print(f"  {position_line(res)}")
        print(f"  {heading_text(res)}")
        print(f"  {fit_line(res)}")
        files = [out / "result.json", out / "report.html"]
        if d.get("trajectory_csv"):
            files.append(out / "trajectory_global.csv")
        if d.get("dxf"):
            files.append(out / d["dxf"]["file"])
        print("  wrote " + ", ".join(str(f) for f in files))
        print(f"  {times}")
        return
    word = res.status.upper()
    print(f"{word}: {res.reason}")
    from minegeo.localize.pipeline import rejected_candidates

    print(f"  NO POSITION: the scan was not localized ({word}); result.json, report.html and this output give no "
          "coordinates of it" + (" (the candidates below were rejected)" if rejected_candidates(res) else ""))
    print(f"  next: {NEXT_STEP.get(res.status, 'see report.html')}")
    for line in _candidate_lines(res):
        print(line)
    rival = _rival_line(res)
    if rival:
        print(rival)
    extra = " (no trajectory_global.csv: written only for an ok result)" if res.trajectory_map is not None else ""
    print(f"  wrote {out / 'result.json'}, {out / 'report.html'}{extra}")
    print(f"  profile {profile}; {times}")
