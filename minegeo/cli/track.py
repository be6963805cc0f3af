"""``minegeo track --frames DIR --db DB --out OUT``: LiDAR tracking with intersection factors
(Liang et al. 2024; ``docs/intersections.md``, "Online recognition and tracking").

Frames are read as ``minegeo slam`` reads them. ``--start`` and ``--truth`` are in the base's map
frame (the frame of the map the base was built from) or, with ``--start-frame crs`` /
``--truth-frame crs``, in the CRS of a georeferenced base (``p_map = p_crs - origin``, the origin the
base records). Writes ``OUT/trajectory.tum`` (every frame, base
frame), ``keyframes.tum``, ``trajectory_crs.tum`` (when the base is georeferenced: ``p + origin``),
``recognitions.csv`` (every keyframe that saw an intersection: time, status, id, scores), ``result.json``
(provenance) and ``report.html`` (plan view / error map, recognitions, similarity matrix, timings).
``--map MAP`` (the dense prior map, e.g. the cloud the base was built from, read as ``minegeo intersections
build`` reads its map, georeferencing sidecar included) adds map-registration factors
(:mod:`minegeo.semantic.mapfactor`): a keyframe far from every verified intersection is registered
to the map by point-to-plane ICP, information only in the directions the registration constrains;
their counts are in ``result.json`` (``result.map_registrations``) and the report.
``--imu IMU.csv`` (read and checked as ``minegeo slam`` does, :mod:`minegeo.cli._imu`) puts the gyro in the
odometry: rotation guesses, deskewing of frames with per-point times, the IMU gate on each registration.
Exit status 0 when the run is ``ok`` (intersection factors, each consistent with the odometry by its
χ² test, and every keyframe within ``--unchecked-path`` metres of path of a verified intersection or
the start pose); 1 with one line on stderr for ``partial`` (stretches placed by the odometry alone,
listed in result.json and the report), ``inconsistent`` (a factor fails its χ² test: a wrong
recognition or a runaway odometry), ``no_recognition``, ``no_intersections`` or ``unanchored``
(outputs written, odometry-only poses); 2 for a user mistake (one line, no traceback).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import asdict, replace
from pathlib import Path

from minegeo._params import arg_type
from minegeo.cli._argtypes import (
    finite_float,
    int_in_range,
)
from minegeo.cli._imu import add_imu_arguments, check_imu, inertial_params, read_imu

#: the parameter class whose field rules the odometry options use (imported when an option is parsed)
_ODO = "minegeo.slam.odometry_model:OdometryParams"
_REC = "minegeo.semantic.recognition:RecognitionParams"
_TRACK = "minegeo.semantic.tracking:TrackParams"
HELP = "LiDAR tracking with intersection recognition against a knowledge base (Liang et al. 2024)"


def add_arguments(parser) -> None:
    parser.add_argument("--frames", required=True, help="folder of frames or ROS bag, as for `minegeo slam`")
    parser.add_argument("--lidar-topic", "--points-topic", dest="lidar_topic", default=None, metavar="TOPIC",
                        help="the bag's sensor_msgs/PointCloud2 topic (default: the only one)")
    parser.add_argument("--db", required=True, help="knowledge base of `minegeo intersections build`")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--times", default=None, help="file of frame times (s) (default FRAMES/times.txt or names)")
    parser.add_argument("--pattern", default=None, help='frame file-name pattern, e.g. "*.pcd"')
    parser.add_argument("--truth", default=None, help="ground-truth TUM trajectory (in --truth-frame): error map + "
                        "RMSE")
    parser.add_argument("--truth-frame", choices=("map", "crs"), default=None,
                        help="frame of --truth: map (default; the frame of the map the base was built from) or crs "
                        "(CRS grid E N H; a georeferenced base: p_map = p_crs - origin)")
    parser.add_argument("--start", type=finite_float, nargs=4, metavar=("X", "Y", "Z", "YAW_DEG"), default=None,
                        help="pose of the first frame (m, deg; yaw counter-clockwise from +x / grid east) in "
                        "--start-frame; default: unanchored until the first verified recognition")
    parser.add_argument("--start-frame", choices=("map", "crs"), default=None,
                        help="frame of --start: map (default; the frame of the map the base was built from) or crs "
                        "(CRS grid E N H; a georeferenced base: p_map = p_crs - origin)")
    parser.add_argument("--map", default=None, metavar="MAP",
                        help="dense prior map (PLY/PCD/LAS/XYZ, m; the cloud the base was built from, in the same "
                        "frame: a georeferenced map with its .georef.json sidecar, or coordinates in the base's map "
                        "frame): adds map-registration factors, a keyframe more than 50 m of path from a verified "
                        "intersection registered to the map by ICP (every 10 m of path), constraining only the "
                        "directions the drift's walls fix; not with --no-map")
    parser.add_argument("--no-map", action="store_true", help="ignore the base's intersections: recognise "
                        "re-visits of an online base built from the run (the paper's 'no map')")
    parser.add_argument("--pwcv-threshold", type=arg_type(_REC, "pwcv_threshold"), default=0.8,
                        help="PWCV similarity threshold, in (0, 1] (default 0.8)")
    parser.add_argument("--n-his", type=arg_type(_REC, "n_his"), default=5,
                        help="previous keyframes stacked with the current one (Eq. 20; 0 = the current one alone)")
    parser.add_argument("--consecutive", type=arg_type(_REC, "consecutive_required"), default=2,
                        help="consecutive keyframes matching the same id")
    parser.add_argument("--icp-max-distance", type=arg_type(_REC, "icp_max_distance_m"), default=None, help="ICP verification RMS limit "
                        "against the base (m; default 0.135 for a map sampled every 0.2 m, see "
                        "docs/intersections.md); not with --no-map")
    parser.add_argument("--gate", type=arg_type(_REC, "gate_m"), default=3.0, help="odometry gate at an anchor (m)")
    parser.add_argument("--gate-drift", type=arg_type(_TRACK, "gate_drift_fraction"), default=None, help="gate growth per metre of path "
                        "since the last verified recognition against the base, instead of the default gate from the "
                        "covariance of the prediction; not with --no-map")
    parser.add_argument("--odometry", choices=("submap", "frame"), default="submap",
                        help="odometry target of each frame: the local map of the last 5 keyframes (default) or "
                        "the previous frame (Ren2019 Eq. 7)")
    parser.add_argument("--unchecked-path", type=arg_type(_TRACK, "unchecked_path_m"), default=200.0, metavar="M",
                        help="a keyframe farther than M metres of path from every verified intersection (and the "
                             "start pose) is odometry only: listed, and the status is 'partial' (default 200)")
    parser.add_argument("--voxel", type=arg_type(_ODO, "voxel_size_m"), default=0.3, help="odometry voxel size (m, > 0)")
    parser.add_argument("--keyframe-distance", type=arg_type(_ODO, "keyframe_distance_m"), default=2.0,
                        help="keyframe distance threshold (m)")
    parser.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=0,
                        help="recorded seed (the run draws no random numbers)")
    add_imu_arguments(parser, "gyro rotation guesses, deskewing by the gyro (frames with per-point times) and a "
                      "gate on each registration in the odometry; a keyframe held by the IMU gives no factor")


def _check_combinations(args) -> None:
    """Refuse options that contradict each other (before any file is read)."""
    from minegeo.errors import InputError

    for opt, frame, value in (("--start", "start_frame", args.start), ("--truth", "truth_frame", args.truth)):
        if getattr(args, frame, None) is not None and value is None:
            raise InputError(f"--{frame.replace('_', '-')} gives the frame of {opt}, which is not given: give "
                             f"{opt} or drop --{frame.replace('_', '-')}")
    if args.no_map and getattr(args, "map", None) is not None:
        raise InputError("--map adds factors in the base's map frame, whose intersections --no-map ignores (an "
                         "online base from the run): drop one of the two options")
    if args.no_map:
        given = [name for name, v in (("--icp-max-distance", args.icp_max_distance),
                                      ("--gate-drift", args.gate_drift)) if v is not None]
        if given:
            raise InputError(f"{given[0]} applies to recognitions against the base's intersections, which --no-map "
                             "ignores (the online base has its own limits): drop one of the two options")


def _check_frames(args, kb) -> None:
    """Refuse a pose or truth given in the CRS for a base that carries no CRS (before any tracking)."""
    from minegeo.errors import InputError

    geo = kb.georef or {}
    for opt, frame in (("--start", args.start_frame), ("--truth", args.truth_frame)):
        if frame == "crs" and not (geo.get("crs") and geo.get("origin_m") is not None):
            raise InputError(f"{opt} is given in the CRS (--{opt[2:]}-frame crs) but the base {args.db} is not "
                             "georeferenced (it was built from a map without a CRS): give it in the map frame, or "
                             "build the base from the georeferenced map (`minegeo georef` output)")


#: a junction of the base counts as inside the --map extent within this margin (m) of its bounding box
_MAP_MARGIN_M = 5.0


def _read_prior_map(path, kb, db):
    """The points (n, 3) of ``--map`` in the base's map frame (m), checked before any tracking.

    Read as ``minegeo intersections build`` reads its map (:func:`minegeo.cli.intersections._read_map`:
    a georeferenced map relative to its origin, a file with large coordinates relative to an automatic
    origin), then moved to the base's frame: ``p_base = p + origin_map - origin_base`` (a base
    without origin: ``origin_base = 0``); a map that records no origin is taken as given in the base's
    map frame. Refused (``InputError``):
    fewer than 10 points, a CRS other than the base's, or an extent (bounding box grown by
    :data:`_MAP_MARGIN_M`) that holds none of the base's junctions (a map in another frame).
    """
    import numpy as np

    from minegeo.cli.intersections import _read_map
    from minegeo.errors import InputError
    from minegeo.georef.crs import same_crs

    f = Path(path)
    if f.is_dir():
        raise InputError(f"--map {path} is a folder: name the map file (PLY/PCD/LAS/XYZ)")
    if not f.exists():
        raise InputError(f"--map {path}: No such file (name the map the base was built from)")
    if not f.is_file():
        raise InputError(f"--map {path} is not a regular file (a device, pipe or socket): name the map file")
    P, geo = _read_map(path)
    P = np.asarray(P, np.float64)
    if P.ndim != 2 or P.shape[0] < 10:
        raise InputError(f"--map {path}: holds {P.shape[0] if P.ndim == 2 else 0} point(s); the map-registration "
                         "factors need the dense prior map (at least 10 points)")
    if not np.all(np.isfinite(P)):
        raise InputError(f"--map {path}: has NaN or inf coordinates")
    kgeo = kb.georef or {}
    if geo.get("crs") and kgeo.get("crs") and not same_crs(str(geo["crs"]), str(kgeo["crs"])):
        raise InputError(f"--map {path} is in CRS {geo['crs']} but the base {db} is in {kgeo['crs']}: give the map "
                         "the base was built from")
    if geo.get("origin_m") is not None:  # the map's coordinates are p + origin_map; the base's p + origin_base
        P = P + (np.asarray(geo["origin_m"], float) - np.asarray(kgeo.get("origin_m") or np.zeros(3), float))
    J = np.asarray(kb.invariant_points, float).reshape(-1, 3)
    if J.shape[0]:
        lo, hi = P.min(0) - _MAP_MARGIN_M, P.max(0) + _MAP_MARGIN_M
        if not np.any(np.all((J >= lo) & (J <= hi), axis=1)):
            raise InputError(f"--map {path}: its extent (x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}, "
                             f"z {lo[2]:.1f}..{hi[2]:.1f} m in the base's frame, {_MAP_MARGIN_M:g} m margin) holds "
                             f"none of the base's {J.shape[0]} junctions: it is not in the base's frame (give the map "
                             "the base was built from)")
    return P


def _to_map(args, kb, T):
    """A pose of --start (4x4) from its frame to the base's map frame: ``p_map = p_crs - origin``."""
    import numpy as np

    if args.start_frame == "crs":
        T = T.copy()
        T[:3, 3] -= np.asarray(kb.georef["origin_m"], float)
    return T


def _params(args):
    import numpy as np

    from minegeo.semantic.recognition import RecognitionParams
    from minegeo.semantic.tracking import TRACK_ODOMETRY, TrackParams
    from minegeo.slam.odometry import OdometryParams

    T = None
    if args.start is not None:
        x, y, z, yaw = args.start
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        T = np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1]], float)
    rec = RecognitionParams(pwcv_threshold=args.pwcv_threshold, n_his=args.n_his,
                            consecutive_required=args.consecutive, gate_m=args.gate,
                            **({} if args.icp_max_distance is None else {"icp_max_distance_m": args.icp_max_distance}))
    odo = OdometryParams(voxel_size_m=args.voxel, keyframe_distance_m=args.keyframe_distance,
                         frame_target=getattr(args, "odometry", "submap"), **TRACK_ODOMETRY)
    return TrackParams(odo, rec, T_world_start=T, unchecked_path_m=getattr(args, "unchecked_path", 200.0),
                       **({} if args.gate_drift is None else {"gate_drift_fraction": args.gate_drift}))


def _truth_errors(truth_path, res, origin=None, tr=None):
    """Position error (m) of every frame against the truth at the same time (nearest within 0.05 s);
    ``origin`` (3,): the truth is in the CRS and ``p_map = p_crs - origin``. ``tr``: the truth already
    read (:func:`minegeo.io.read_trajectory`, before the run, so a bad file stops it before any work)."""
    import numpy as np

    from minegeo.errors import InputError
    from minegeo.io import read_trajectory

    tr = read_trajectory(truth_path) if tr is None else tr
    if origin is not None:
        P = tr.poses.copy()
        P[:, :3, 3] -= np.asarray(origin, float) - np.asarray(tr.origin if tr.origin is not None else np.zeros(3))
        tr = replace(tr, poses=P)
    j = np.clip(np.searchsorted(tr.times_s, res.times_s), 1, len(tr.times_s) - 1)
    j = np.where(np.abs(tr.times_s[j - 1] - res.times_s) < np.abs(tr.times_s[j] - res.times_s), j - 1, j)
    ok = np.abs(tr.times_s[j] - res.times_s) <= 0.05
    if not ok.any():
        raise InputError(f"--truth {truth_path}: no pose within 0.05 s of a frame time")
    err = np.full(res.times_s.size, np.nan)
    err[ok] = np.linalg.norm(res.poses[ok, :3, 3] - tr.poses[j[ok], :3, 3], axis=1)
    return err


def _write(stage: Path, res, kb) -> list[str]:
    import numpy as np

    from minegeo._provenance import atomic_write_text
    from minegeo.io import write_trajectory
    from minegeo.io.types import Trajectory

    names = ["trajectory.tum", "keyframes.tum", "recognitions.csv"]
    write_trajectory(stage / "trajectory.tum", Trajectory(res.times_s, res.poses, frame="map", body="sensor"))
    write_trajectory(stage / "keyframes.tum", Trajectory(res.times_s[res.keyframes], res.keyframe_poses,
                                                         frame="map", body="sensor"))
    geo = kb.georef if kb is not None else {}
    if geo.get("origin_m") is not None and geo.get("crs") and res.status != "unanchored":
        P = res.poses.copy()
        P[:, :3, 3] += np.asarray(geo["origin_m"], float)
        write_trajectory(stage / "trajectory_crs.tum", Trajectory(res.times_s, P, frame=str(geo["crs"]), body="sensor"))
        names.append("trajectory_crs.tum")
    rows = ["time_s,keyframe,status,intersection_id,pwcv,cwc,icp_rms_m,icp_fitness,completeness,factor,reason"]
    for e in res.recognitions:
        r = e.recognition
        if r.status == "none":
            continue
        reason = r.reason.replace('"', "'")
        rows.append(f"{e.time_s:.6f},{e.keyframe},{r.status},{r.intersection_id},{r.pwcv_score:.6f},"
                    f"{r.cwc_score:.6f},{r.icp_rms_m:.6f},{r.icp_fitness:.6f},{r.completeness:.6f},{int(e.factor)},"
                    f'"{reason}"')
    atomic_write_text(stage / "recognitions.csv", "\n".join(rows) + "\n")
    return names


class _Collect(logging.Handler):
    """Keeps the odometry's per-frame notes (INFO and above: frames held by the motion prior,
    frames not registered) for result.json, whatever the run's verbosity."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record) -> None:  # noqa: D102 - logging API
        self.messages.append(record.getMessage())


def run(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from minegeo._output import OutputTransaction, progress_enabled, run_timings
    from minegeo._provenance import StageTimer, provenance, sha256_file, write_json_atomic
    from minegeo.cli.slam import _frames
    from minegeo.errors import InputError
    from minegeo.io.frames import list_frames, times_source
    from minegeo.report.intersections_report import write_track_report
    from minegeo.semantic import IntersectionKB, similarity_matrix
    from minegeo.semantic.mapfactor import map_registration_counts
    from minegeo.semantic.tracking import track

    timer = StageTimer()
    _check_combinations(args)
    params = _params(args)
    out = Path(args.out)
    named = {"--frames": args.frames, "--db": args.db, **({"--map": args.map} if args.map else {}),
             **({"--times": args.times} if args.times else {}),
             **({"--truth": args.truth} if args.truth else {}), **({"--imu": args.imu} if args.imu else {}),
             **({"--imu-noise": args.imu_noise} if getattr(args, "imu_noise", None) else {})}
    imu = read_imu(args)
    inertial = inertial_params(args)
    from minegeo.io import read_trajectory
    from minegeo.slam.inertial import GyroAid

    truth = read_trajectory(args.truth) if args.truth else None  # a bad truth file: one line before any work

    with OutputTransaction("track", inputs=named, folders={"--out": out}) as tx:
        kb = IntersectionKB.load(args.db)
        _check_frames(args, kb)
        if params.T_world_start is not None:
            params = replace(params, T_world_start=_to_map(args, kb, params.T_world_start))
        # the keyframes' drift skeleton uses the base's own skeleton parameters (floor cell, wall band)
        params = replace(params, recognition=replace(params.recognition, skeleton=kb.params.skeleton))
        # the dense prior map (map-registration factors): read and checked before any frame is
        prior = _read_prior_map(args.map, kb, args.db) if args.map else None
        files = list_frames(args.frames, args.times, args.pattern, args.lidar_topic)
        if len(files) < 2:  # before any compiled work (a first run compiles for a minute before its first frame)
            raise InputError(f"--frames {args.frames}: fewer than 2 readable frames")
        check_imu(imu, files, args)
        skipped: list[dict] = []
        bar = tqdm(total=len(files), desc="track", unit="frame", file=sys.stderr, disable=not progress_enabled(args))
        reg_log = logging.getLogger("minegeo.registration")
        level = reg_log.level
        reg_log.setLevel(logging.ERROR)
        # the odometry's per-frame notes (a frame held by the motion prior) go to result.json, not stderr
        odo_log, held = logging.getLogger("minegeo.slam.odometry"), _Collect()
        odo_prop, odo_level = odo_log.propagate, odo_log.level
        odo_log.addHandler(held)
        odo_log.propagate = False
        odo_log.setLevel(logging.INFO)  # recorded also under -q (the notes never reach stderr)
        try:
            with bar, timer("track"):
                # per-point times (the gyro deskew) only with --imu: without it the frames are as before
                res = track(_frames(files, skipped, bar, params.odometry.min_points, imu is not None), kb, params,
                            use_map=not args.no_map, imu=None if imu is None else GyroAid(imu, inertial),
                            map_points=prior)
        finally:
            reg_log.setLevel(level)
            odo_log.removeHandler(held)
            odo_log.propagate = odo_prop
            odo_log.setLevel(odo_level)
        if res.times_s.size < 2:
            raise InputError(f"--frames {args.frames}: fewer than 2 readable frames")
        err = (_truth_errors(args.truth, res, kb.georef["origin_m"] if args.truth_frame == "crs" else None, truth)
               if args.truth else None)
        stage = tx.folder("--out")
        with timer("write"):
            names = _write(stage, res, kb)
        S = similarity_matrix(kb) if len(kb) else None
        result = {**res.summary(), "times_from": times_source(args.frames, args.times), "skipped_frames": skipped,
                  "odometry_notes": held.messages,
                  # with --map: the map registrations by status and the factors by rank (zeros included)
                  **({"map_registrations": map_registration_counts(res.map_registrations)} if prior is not None else {}),
                  "georef": kb.georef, "recognitions": [e.summary() for e in res.recognitions
                                                        if e.recognition.status != "none"]}
        if err is not None:
            e = err[np.isfinite(err)]
            result["truth"] = {"rmse_m": float(np.sqrt(np.mean(e**2))), "max_m": float(e.max()),
                               "mean_m": float(e.mean()), "n": int(e.size)}
        inputs = files.inputs()
        inputs += [{"path": str(p), "sha256": sha256_file(p)}
                   for p in (args.db, args.map, args.times, args.truth, args.imu, getattr(args, "imu_noise", None))
                   if p and Path(p).is_file()]
        summary = {"command": "track", "status": res.status, "reason": res.reason, "parameters": params.as_dict(),
                   "inputs": {"frames": str(args.frames), "db": str(args.db),
                              **({"map": str(args.map)} if args.map else {})}, "result": result,
                   "outputs": {n: str(out / n) for n in [*names, "result.json", "report.html"]},
                   **({"imu_noise": asdict(inertial.noise), "inertial": asdict(inertial)} if inertial is not None else {}),
                   "module_timings_s": res.timings_s, "timings_s": {**timer.as_dict(), **run_timings(args)},
                   "provenance": provenance(seed=args.seed, origin=kb.georef.get("origin_m"), inputs=inputs)}
        write_json_atomic(stage / "result.json", summary)
        write_track_report(stage / "report.html", summary, res, kb, S, err)
    if not getattr(args, "quiet", False):
        s = summary["result"]
        print(f"{s['frames']} frames, {s['keyframes']} keyframes, status {res.status}; {s['factors']} intersection "
              f"factor(s), ids {s['recognised_ids']}"
              + (f"; {s['map_registrations']['factors']} map factor(s) of {s['map_registrations']['tried']} "
                 "map registration(s)" if "map_registrations" in s else "") + (f"; position error RMSE {result['truth']['rmse_m']:.2f} m"
                                                        if err is not None else ""))
        print(f"written: {out}/({', '.join([*names, 'result.json', 'report.html'])})")
    if res.status != "ok":
        print(f"minegeo track: {res.status}: {res.reason} (written: {out})", file=sys.stderr)
        return 1
    return 0
