"""``minegeo slam --frames DIR --out OUT``: map and trajectory from LiDAR frames alone (Ren et al. 2019).

Files, frame order, times and outputs as fixed by the SLAM contract (``slam_contract.md``):
``OUT/trajectory.tum`` (every used frame), ``keyframes.tum``, ``graph.g2o`` (optimised),
``loops.csv`` (i, j, fitness, rmse, accepted, reason), ``map.ply``, ``result.json`` and
``report.html`` (plan view, loops, per-module timing table). Frames that cannot be read or hold too
few points are reported and skipped; the run goes on.
"""

from __future__ import annotations

import logging
import stat
import statistics
import sys
from dataclasses import asdict, replace
from pathlib import Path

from minegeo._params import arg_type
from minegeo.cli._argtypes import finite_float, nonnegative_int, positive_float
from minegeo.cli._imu import add_imu_arguments, check_imu, inertial_params, read_imu

#: the parameter class whose field rules the odometry options use (imported when an option is parsed)
_ODO = "minegeo.slam.odometry_model:OdometryParams"
_LOOPS = "minegeo.slam.loops:LoopParams"
_CONTROL = "minegeo.slam.control:ControlParams"
_SLAM = "minegeo.slam.pipeline:SlamParams"
#: ``--keyframe-angle``: the rotation between two poses is at most 180 deg, so a larger threshold
#: would never act; the option takes (0, 180] where ``OdometryParams.keyframe_angle_deg`` takes any
#: angle > 0 (every value from 180 up behaves the same there)
KEYFRAME_ANGLE_MAX_DEG = 180.0

HELP = "LiDAR SLAM from a folder of frames: GICP odometry, loop closure, pose graph; trajectory + map (Ren et al. 2019)"

log = logging.getLogger(__name__)

#: what holds a flagged stretch (summary line): without and with --imu
_HELD_BY = ("the motion prior alone", "the IMU (gyro rotation, constant-velocity translation)")


def add_arguments(parser) -> None:
    parser.add_argument("--frames", required=True, help="folder of frames (PLY/PCD/LAS/XYZ or KITTI .bin), sensor frame; "
                        "times from times.txt or the file names; or a ROS bag (.bag, ROS 2 folder, .mcap/.db3): its "
                        "PointCloud2 messages, timed by their header stamps")
    parser.add_argument("--lidar-topic", "--points-topic", dest="lidar_topic", default=None, metavar="TOPIC",
                        help="the bag's sensor_msgs/PointCloud2 topic (default: the only one; `minegeo info BAG` "
                        "lists them)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--times", default=None, help="file of frame times (s), one per frame in name order "
                        "(default: FRAMES/times.txt, else the numbers in the file names)")
    parser.add_argument("--pattern", default=None, help='frame file-name pattern, e.g. "*.pcd" (default: every '
                        "point-cloud file in the folder)")
    parser.add_argument("--voxel", type=arg_type(_ODO, "voxel_size_m"), default=0.3,
                        help="odometry voxel size (m, > 0, default 0.3)")
    parser.add_argument("--max-distance", type=arg_type(_ODO, "max_correspondence_distance_m"), default=1.0,
                        help="GICP correspondence gate (m, > 0, default 1.0)")
    parser.add_argument("--keyframe-distance", type=arg_type(_ODO, "keyframe_distance_m"), default=2.0,
                        help="keyframe distance threshold (m, > 0, default 2)")
    parser.add_argument("--keyframe-angle", type=arg_type(_ODO, "keyframe_angle_deg", le=KEYFRAME_ANGLE_MAX_DEG),
                        default=10.0, help="keyframe rotation threshold (deg, in (0, 180], default 10)")
    parser.add_argument("--keyframe-interval", type=arg_type(_ODO, "keyframe_interval_s"), default=10.0,
                        help="keyframe time threshold (s, > 0, default 10)")
    parser.add_argument("--loop-gap", type=arg_type(_LOOPS, "min_path_gap_m"), default=30.0,
                        help="loop candidates: path gap above (m, > 0)")
    parser.add_argument("--loop-radius", type=arg_type(_LOOPS, "max_distance_m"), default=8.0,
                        help="loop candidates: distance below (m; less than --loop-gap)")
    parser.add_argument("--no-planes", action="store_true", help="no floor-plane landmarks in the pose graph "
                        "(default: floor planes of the keyframe sub-maps as nodes, Ren et al. 2019 Sec. 3.4.2)")
    parser.add_argument("--no-noise-removal", action="store_true", help="keep the roadway noise in the map "
                        "(default: points inside the roadway away from the fitted floor, walls and roof, e.g. "
                        "pedestrians, are removed section by section along the keyframe track, Ren et al. 2019 Sec. 3.5)")
    parser.add_argument("--map-voxel", type=arg_type(_SLAM, "map_voxel_m"), default=0.1,
                        help="map voxel (m, > 0, default 0.1)")
    parser.add_argument("--no-deskew", action="store_true", help="do not deskew frames whose points carry times "
                        "(default: each such frame is moved to its frame time by the constant-velocity motion of the "
                        "odometry before registration; frames without times are never deskewed)")
    parser.add_argument("--deskew-iterations", type=arg_type(_ODO, "deskew_iterations"), default=None,
                        help="1 (default): after registering a frame, deskew it again with its own estimated motion "
                        "and register once more; 0: one pass")
    parser.add_argument("--odometry", choices=("auto", "submap", "frame"), default="auto",
                        help="what each frame registers to: 'submap' the local map of the last keyframes, 'frame' "
                        "the previous frame (Ren2019 Eq. 7; keyframes refined against the local map); 'auto' "
                        f"(default): submap for a sensor stream (median frame interval up to {STREAM_INTERVAL_S:g} s), "
                        "frame for a log of keyframes farther apart")
    parser.add_argument("--max-speed", type=arg_type(_ODO, "max_speed_m_s"), default=30.0,
                        help="plausible motion: a registration faster than this is rejected (m/s, > 0, default 30)")
    parser.add_argument("--max-angular-rate", type=arg_type(_ODO, "max_angular_rate_deg_s"), default=180.0,
                        help="plausible motion: a registration turning faster is rejected (deg/s, > 0, default 180)")
    parser.add_argument("--max-acceleration", type=arg_type(_ODO, "max_acceleration_m_s2"), default=20.0,
                        help="plausible motion: a registration whose velocity changes faster than this against the "
                        "previous motion, beyond 0.1 m of registration scatter, is rejected (m/s^2, > 0, default 20)")
    parser.add_argument("--seed", type=nonnegative_int, default=0,
                        help="recorded seed (the run draws no random numbers)")
    add_imu_arguments(parser, "gyro rotation guesses, deskewing and a gate on each registration, IMU preintegration "
                      "factors in the keyframe graph")
    g = parser.add_argument_group("survey control (docs/survey.md, 'Control in the pose graph')")
    g.add_argument("--control", default=None, metavar="STATIONS.csv",
                   help="stations CSV (id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role): control stations put the "
                   "trajectory and map into the CRS, check stations are withheld and compared")
    g.add_argument("--crs", default=None, help="CRS of the stations, e.g. EPSG:5186 (default: the file's '# crs:' line)")
    g.add_argument("--station-offset", nargs=3, type=finite_float, default=None, metavar=("X", "Y", "Z"),
                   help="surveyed point in the sensor frame (m, default 0 0 0)")
    g.add_argument("--control-mode", choices=("rigid", "similarity", "graph"), default=None,
                   help="graph (default): position factors in the pose graph; rigid: one rigid fit (6 parameters) "
                   "after SLAM; similarity: one 7-parameter fit after SLAM, the scale estimated with its sigma "
                   "(needs 3 control stations not on one line; no drift states)")
    g.add_argument("--dxf", default=None, metavar="FILE.dxf",
                   help="also draw the stations (control and check on separate layers), their residual vectors and "
                   "95 %% ellipses (exaggerated) and the trajectory, in the CRS, into this DXF")
    g.add_argument("--dxf-exaggeration", type=positive_float, default=None, metavar="X",
                   help="exaggeration of the DXF's residual vectors and ellipses (default: 1, 2 or 5 x 10^k, the "
                   "longest vector at most 5 %% of the drawing)")
    g.add_argument("--drift-states", choices=("off", "on", "auto"), default=None,
                   help="graph mode: estimate a systematic odometry drift (scale, pitch and yaw rate per metre) as a "
                   "random walk on every graph variable; off (default), on, or auto: only when the data show a drift "
                   "(likelihood-ratio test of the graph with against without them; its ellipses are not calibrated "
                   "for a drift near the test's detection limit, docs/survey.md)")
    g.add_argument("--drift-walk", nargs=3, type=positive_float, default=None, metavar=("SCALE", "PITCH", "YAW"),
                   help="random-walk standard deviations of the drift states per sqrt(s) between graph variables "
                   "(scale/sqrt(s), rad/m/sqrt(s), rad/m/sqrt(s); default 2e-5 1e-7 1e-7)")
    g.add_argument("--drift-prior", nargs=3, type=positive_float, default=None, metavar=("SCALE", "PITCH", "YAW"),
                   help="a-priori standard deviations of a constant drift (scale, rad/m, rad/m; default 0.02 1e-4 1e-4)")
    g.add_argument("--class-constant", type=arg_type(_CONTROL, "class_c"), default=None, metavar="C_MM",
                   help="ICSM SP1 class constant c of the check stations' class test, r = c (d + 0.2) mm with d in "
                   "km (mm, default 50: Class D underground; 30 C, 15 B, 7.5 A)")


def _check_options(args) -> None:
    """Option combinations and paths, before any work.

    * ``--loop-radius`` must be below ``--loop-gap``: a candidate lies more than the gap along the
      path and less than the radius away, and the straight-line distance never exceeds the path
      distance, so with radius >= gap every keyframe one gap back on a straight drift would be a
      "loop" (no revisit at all).
    * ``--times`` must name a regular file (not a folder, FIFO or device).
    """
    from minegeo.errors import InputError

    if getattr(args, "control", None) is None:
        for opt, name in (("control_mode", "--control-mode"), ("station_offset", "--station-offset"), ("crs", "--crs"),
                          ("dxf", "--dxf"), ("dxf_exaggeration", "--dxf-exaggeration"),
                          ("drift_states", "--drift-states"), ("drift_walk", "--drift-walk"),
                          ("drift_prior", "--drift-prior"), ("class_constant", "--class-constant")):
            if getattr(args, opt, None) is not None:
                raise InputError(f"{name} needs --control STATIONS.csv (the stations it applies to)")
    _check_drift_options(args)
    if getattr(args, "dxf_exaggeration", None) is not None and getattr(args, "dxf", None) is None:
        raise InputError("--dxf-exaggeration needs --dxf FILE.dxf (the drawing it applies to)")
    if getattr(args, "no_deskew", False) and getattr(args, "deskew_iterations", None) is not None:
        raise InputError(f"--deskew-iterations {args.deskew_iterations} contradicts --no-deskew (no deskewing, no "
                         "deskewing passes): give one of them")
    if args.loop_radius >= args.loop_gap:
        raise InputError(f"--loop-radius {args.loop_radius:g} m must be less than --loop-gap {args.loop_gap:g} m "
                         "(otherwise any stretch of straight drift one gap long counts as a loop)")
    if args.times is not None:
        p = Path(args.times)
        try:
            mode = p.stat().st_mode
        except FileNotFoundError:
            raise InputError(f"--times {args.times}: no such file") from None
        except OSError as exc:
            raise InputError(f"--times {args.times}: cannot be read ({exc.strerror or exc})") from None
        if stat.S_ISDIR(mode):
            raise InputError(f"--times {args.times} is a folder: name the file of frame times (one time in s per "
                             "line), e.g. FOLDER/times.txt")
        if not stat.S_ISREG(mode):
            raise InputError(f"--times {args.times} is not a regular file (a FIFO, socket or device): name a file "
                             "of frame times")


def _check_drift_options(args) -> None:
    """The drift-state options' combinations (``InputError``): drift states are graph-mode variables, so
    ``--drift-states on|auto`` contradicts ``--control-mode rigid`` and ``similarity``; ``--drift-walk``/``--drift-prior``
    shape drift states, so they need ``--drift-states on`` or ``auto``."""
    from minegeo.errors import InputError

    ds, mode = getattr(args, "drift_states", None), getattr(args, "control_mode", None)
    if ds in ("on", "auto") and mode in ("rigid", "similarity"):
        raise InputError(f"--drift-states {ds} contradicts --control-mode {mode} (drift states are variables of the "
                         f"pose graph; a {mode} fit has none): use --control-mode graph, or leave --drift-states out")
    for opt, name in (("drift_walk", "--drift-walk"), ("drift_prior", "--drift-prior")):
        if getattr(args, opt, None) is not None and ds not in ("on", "auto"):
            raise InputError(f"{name} needs --drift-states on or auto (it shapes the drift states"
                             + (", which --drift-states off leaves out)" if ds == "off" else ", off by default)"))


def control_params(args, mode: str):
    """:class:`~minegeo.slam.control.ControlParams` of the survey-control options (``mode`` from
    ``--control-mode``, default graph; ``similarity`` is rigid mode with the 7-parameter model): drift states off/on/auto → False/True/"auto", their walk and
    prior (library defaults when not given), the class constant c (mm, default 50 = Class D)."""
    from minegeo.slam.control import ControlParams

    ds = {None: False, "off": False, "on": True, "auto": "auto"}[getattr(args, "drift_states", None)]
    kw = {"mode": "rigid", "model": "similarity"} if mode == "similarity" else {"mode": mode}
    kw["drift_states"] = ds
    if getattr(args, "drift_walk", None) is not None:
        kw["drift_walk"] = tuple(float(v) for v in args.drift_walk)
    if getattr(args, "drift_prior", None) is not None:
        kw["drift_prior"] = tuple(float(v) for v in args.drift_prior)
    if getattr(args, "class_constant", None) is not None:
        kw["class_c"] = float(args.class_constant)
    return ControlParams(**kw)


def _check_times(files) -> None:
    """The frame times as the run needs them (the frames reader checks order and finiteness; this
    adds the trajectory files' range, so that ``trajectory.tum`` can be read back): every time within
    ``±MAX_ABS_TIME`` s, hence every difference finite."""
    from minegeo.errors import InputError
    from minegeo.io.limits import MAX_ABS_TIME

    for k, f in enumerate(files):
        t = f.time_s
        if not abs(t) <= MAX_ABS_TIME:
            raise InputError(f"frame {f.name}: time {t!r} s is beyond ±{MAX_ABS_TIME:.0e} s, the range a "
                             "trajectory file holds (give times in seconds from a nearby epoch)")
        if k and not t > files[k - 1].time_s:
            raise InputError(f"frame {f.name}: time {t!r} s is not after the previous frame's "
                             f"{files[k - 1].time_s!r} s")


#: ``--odometry auto``: frames at most this far apart (median, s) are a sensor stream, registered to the local map
STREAM_INTERVAL_S = 0.25


def odometry_target(choice: str, times_s) -> tuple[str, str]:
    """``(frame_target, why)`` of ``--odometry`` ``choice`` for frames at ``times_s`` (s).

    ``auto`` takes ``"submap"`` (each frame to the local map of the last keyframes) when the median
    frame interval is at most :data:`STREAM_INTERVAL_S` (a 4-20 Hz sensor stream: frame-to-frame GICP
    with a spinning LiDAR's rings is biased towards no motion, 0.73 % against 0.08 % of the path on
    the simulated 10 Hz junctions drive, benchmarks/results/stream_ate_*), else ``"frame"`` (a log of
    keyframes seconds and metres apart: MulRan Riverside02, whose 11 m steps the local map once
    matched 49 deg off, benchmarks/results/mulran_*)."""
    if choice != "auto":
        return choice, "--odometry " + choice
    t = [float(x) for x in times_s]
    med = statistics.median([t[i + 1] - t[i] for i in range(len(t) - 1)]) if len(t) > 1 else float("inf")
    if med <= STREAM_INTERVAL_S:
        return "submap", f"auto: median frame interval {med:.3g} s <= {STREAM_INTERVAL_S:g} s (a sensor stream)"
    return "frame", f"auto: median frame interval {med:.3g} s > {STREAM_INTERVAL_S:g} s (a log of keyframes)"


def _params(args):
    from minegeo.slam.loops import LoopParams
    from minegeo.slam.odometry import OdometryParams
    from minegeo.slam.pipeline import SlamParams

    odo = OdometryParams(voxel_size_m=args.voxel, max_correspondence_distance_m=args.max_distance,
                         keyframe_distance_m=args.keyframe_distance, keyframe_angle_deg=args.keyframe_angle,
                         keyframe_interval_s=args.keyframe_interval, deskew=not getattr(args, "no_deskew", False),
                         deskew_iterations=1 if getattr(args, "deskew_iterations", None) is None
                         else args.deskew_iterations,
                         max_speed_m_s=getattr(args, "max_speed", 30.0),
                         max_angular_rate_deg_s=getattr(args, "max_angular_rate", 180.0),
                         max_acceleration_m_s2=getattr(args, "max_acceleration", 20.0),
                         edge_covariance_floor=getattr(args, "control", None) is not None)
    return SlamParams(odometry=odo, loops=LoopParams(min_path_gap_m=args.loop_gap, max_distance_m=args.loop_radius),
                      map_voxel_m=args.map_voxel, use_planes=not getattr(args, "no_planes", False),
                      remove_noise=not getattr(args, "no_noise_removal", False))


def _frames(files, skipped: list, bar, min_points: int, with_times: bool = False):
    """Yield (time, points) of the readable frames, or with ``with_times`` (time, points, per-point
    offsets in s after the frame time, or None when the file holds no times); unreadable ones and
    frames with fewer than ``min_points`` points are recorded and skipped (the contract)."""
    from minegeo.io.frames import iter_frames

    for f, pts, tau, exc in iter_frames(files, with_times):
        bar.update(1)
        if exc is not None:
            skipped.append({"frame": f.name, "reason": str(exc)})
            log.warning("frame %s skipped: %s", f.name, exc)
            continue
        if pts.shape[0] < min_points:
            skipped.append({"frame": f.name, "reason": f"{pts.shape[0]} points, fewer than {min_points}"})
            log.warning("frame %s skipped: %d points", f.name, pts.shape[0])
            continue
        yield (f.time_s, pts) if tau is None else (f.time_s, pts, tau)


def _all_skipped(frames_dir, skipped: list[dict]) -> str:
    """The message when no frame could be used: how many, and the first reasons."""
    first = "; ".join(f"{s['frame']}: {s['reason']}" for s in skipped[:2])
    more = f" (and {len(skipped) - 2} more)" if len(skipped) > 2 else ""
    return f"--frames {frames_dir}: none of the {len(skipped)} frames can be used ({first}{more})"


def _write_outputs(stage: Path, res, files_used: list[str]) -> None:
    import numpy as np

    from minegeo._provenance import atomic_write_text
    from minegeo.io import PointCloud, write_point_cloud, write_trajectory
    from minegeo.io.g2o import write_g2o
    from minegeo.io.types import Trajectory

    write_trajectory(stage / "trajectory.tum", Trajectory(res.times_s, res.poses, frame="map", body="sensor"))
    write_trajectory(stage / "keyframes.tum", Trajectory(res.times_s[res.keyframes], res.keyframe_poses,
                                                         frame="map", body="sensor"))
    write_g2o(stage / "graph.g2o", res.graph)
    rows = ["i,j,fitness,rmse_m,accepted,reason"]
    for c in res.loops:
        reason = c.reason.replace('"', "'")
        rows.append(f'{c.i},{c.j},{c.fitness:.6f},{c.rmse_m:.6f},{int(c.accepted)},"{reason}"')
    atomic_write_text(stage / "loops.csv", "\n".join(rows) + "\n")
    write_point_cloud(stage / "map.ply", PointCloud(points=np.ascontiguousarray(res.map_points)))
    atomic_write_text(stage / "frames_used.txt", "\n".join(files_used) + "\n")


def _deskew_and_runaway(odo) -> dict:
    """result.json: whether deskewing ran and the twist each frame was deskewed with, and the
    stretches held by the constant-velocity motion prior (no silent runaway)."""
    held = odo.held_stretches()
    d = odo.deskewed
    s = odo.summary()
    return {
        "deskew": {"ran": bool(d.any()), "frames_deskewed": int(d.sum()), "frames": int(d.size),
                   "enabled": bool(odo.params.deskew), "iterations": int(odo.params.deskew_iterations),
                   "convention": "q = exp(tau xi) p: xi = (omega rad/s, v m/s), sensor frame, constant over the "
                                 "sweep; tau = point time after the frame time (s); poses at the frame time",
                   "per_frame": [{"frame": k, "time_s": float(odo.times_s[k]),
                                  "twist_rad_s_m_s": [float(x) for x in odo.deskew_twist[k]]}
                                 for k in range(d.size) if d[k]]},
        "motion_prior_stretches": held,
        "motion_prior_held_s": s["held_s_total"],
        "min_constraint_ratio": s["min_constraint_ratio"],
    }


def _read_control(args):
    """``(stations, offset, crs, mode)`` of the survey-control options, or None without ``--control``
    (read and checked before any work: the CRS given twice must agree)."""
    from minegeo.errors import InputError
    from minegeo.georef.crs import same_crs
    from minegeo.io.stations import parse_station_offset, read_stations

    if args.control is None:
        return None
    st = read_stations(args.control)
    if args.crs and st.crs and not same_crs(args.crs, st.crs):
        raise InputError(f"--crs {args.crs} contradicts the '# crs: {st.crs}' line of --control {args.control}: "
                         "give one CRS")
    crs = args.crs or st.crs
    if not crs:
        raise InputError(f"--control {args.control}: no CRS (give --crs EPSG:... or a '# crs:' line in the file)")
    from minegeo.errors import CRSError
    from minegeo.georef.crs import validate_crs

    try:
        validate_crs(crs)  # a projected grid in metres (CRSError names a geographic or geocentric CRS)
    except CRSError as exc:
        where = f"--crs {args.crs}" if args.crs else f"the '# crs:' line of --control {args.control}"
        raise CRSError(f"{where}: {exc}") from None
    if getattr(args, "dxf", None) is not None:
        from minegeo.io.dxf import ezdxf_module

        ezdxf_module()  # the dxf extra, before any work
    offset = parse_station_offset(args.station_offset if args.station_offset is not None else (0.0, 0.0, 0.0))
    mode = args.control_mode or "graph"
    n_ctrl = int(st.is_control.sum())
    if n_ctrl < 3:
        raise InputError(f"--control {args.control}: {n_ctrl} control station(s); the {mode} mode needs at least 3 "
                         "not on one line (make more stations control, or add stations)")
    from minegeo.slam.control import check_control_geometry

    check_control_geometry(st, mode, f"--control {args.control}: ")
    return st, offset, crs, mode


def _map_corrected(map_points, var_xyz_map, C):
    """Map points (map frame) into the local CRS frame: each point moved by the correction ``C`` (k, 4, 4)
    of the graph variable nearest to it in the map frame (rigid mode: one correction for all)."""
    import numpy as np
    from scipy.spatial import cKDTree

    if map_points.shape[0] == 0:
        return np.zeros((0, 3))
    _, near = cKDTree(var_xyz_map).query(map_points)
    return np.einsum("nij,nj->ni", C[near, :3, :3], map_points) + C[near, :3, 3]


#: LAS resolution of ``map_crs.las`` (m): 1 mm, below the survey's σ and the map voxel; with the
#: offset at the map's whole-km origin the 32-bit integers hold ±2147 km
MAP_LAS_SCALE_M = 0.001


def _write_map_las(stage: Path, cloud, fit, extra: dict) -> dict:
    """``map_crs.laz`` (``.las`` when laspy has no LAZ backend) beside ``map_crs.ply``: LAS 1.4, point
    format 6, the CRS as an OGC WKT VLR, integer coordinates ``X = round((E − offset) / scale)`` with
    ``scale`` :data:`MAP_LAS_SCALE_M` and ``offset`` the PLY's recorded origin (whole km), and its
    georef sidecar. Without the ``las`` extra: no file, a one-line warning, ``written: False``."""
    from minegeo.errors import OptionalDependencyError
    from minegeo.georef.sidecar import write_georeferenced_map
    from minegeo.io.types import PointCloud

    try:
        import laspy

        name = "map_crs.laz" if laspy.LazBackend.detect_available() else "map_crs.las"
    except ImportError:
        log.warning("map_crs.las not written: laspy is not installed (pip install 'minegeo[las]'); the map in the "
                    "CRS is map_crs.ply with its sidecar")
        return {"written": False, "reason": "laspy is not installed (the 'las' extra)"}
    las_cloud = PointCloud(points=cloud.points, origin=cloud.origin, crs=cloud.crs, frame=cloud.frame,
                           metadata={"las_scale": MAP_LAS_SCALE_M})
    try:
        write_georeferenced_map(stage / name, las_cloud, fit, extra=extra)
    except OptionalDependencyError as exc:
        log.warning("%s not written: %s; the map in the CRS is map_crs.ply with its sidecar", name, exc)
        return {"written": False, "reason": str(exc)}
    return {"written": True, "file": name, "scale_m": [MAP_LAS_SCALE_M] * 3,
            "offset_m": [float(v) for v in fit.origin], "crs_vlr": "OGC WKT (LAS 1.4, record 2112)",
            "coordinates": "E N H = X * scale + offset (ASPRS LAS 1.4 R15 Sec. 2.4)"}


def _write_map_crs(stage: Path, res, c, graph, st, offset, crs, mode) -> dict:
    """The map in the CRS: ``map_crs.ply`` (geo = CRS − origin) with its sidecar (the rigid fit of the
    control stations), and the same points as LAS/LAZ with the CRS's WKT (:func:`_write_map_las`);
    returns the record of the LAS in result.json."""
    import numpy as np

    from minegeo.georef import GeorefParams, georeference
    from minegeo.georef.sidecar import write_georeferenced_map
    from minegeo.io import PointCloud
    from minegeo.io.types import ControlPoints
    from minegeo.slam.control import interpolate_poses, station_points

    kt, kP, var_map = graph
    o = c.origin_enh
    if c.similarity:  # one similarity for every point: s R p + T
        local = np.asarray(res.map_points, dtype=np.float64) @ c.T_local_map[:3, :3].T + c.T_local_map[:3, 3]
    else:
        C = c.poses @ np.linalg.inv(var_map)
        local = _map_corrected(np.asarray(res.map_points, dtype=np.float64), var_map[:, :3, 3], C)
    ctrl = st.is_control
    pts_map = station_points(interpolate_poses(kt, kP, st.t_mid_s), offset)
    sig = np.c_[st.sigma_h_m, st.sigma_h_m, st.sigma_v_m][ctrl]
    glog = logging.getLogger("minegeo.georef")
    level = glog.level
    glog.setLevel(logging.ERROR)  # the same fit apply_control ran and logged: not twice on the terminal
    try:
        fit = georeference(ControlPoints(ids=[i for i, k in zip(st.ids, ctrl, strict=True) if k], local_xyz=pts_map[ctrl],
                                         crs_enh=st.enh[ctrl], sigma_enh_m=sig, crs=crs),
                           crs, GeorefParams(model="similarity" if c.similarity else "rigid", max_sigma0=1e12))
    finally:
        glog.setLevel(level)
    geo = local + (o - np.asarray(fit.origin, dtype=np.float64))
    write_georeferenced_map(stage / "map_crs.ply", PointCloud(points=np.ascontiguousarray(geo), origin=fit.origin,
                                                              crs=crs, frame="geo"), fit,
                            extra={"slam_control": {
                                "mode": mode, "points": "p_crs = T_crs_map p_map (the similarity fit of the control "
                                "stations)" if c.similarity else "each map point moved by the correction of the graph "
                                "variable nearest to it (graph mode: non-rigid; T_crs_map is the rigid fit of the "
                                "control stations, for reference)"}})
    return _write_map_las(stage, PointCloud(points=np.ascontiguousarray(geo), origin=fit.origin, crs=crs,
                                            frame="geo"), fit, extra={"slam_control": {"mode": mode, "points": "as map_crs.ply"}})


def _control_outputs(stage: Path, res, ctrl_in, params, dxf_path: Path | None = None,
                     dxf_exaggeration: float | None = None) -> tuple[dict, dict]:
    """Apply the control to the SLAM result and write the CRS deliverables (and the DXF at ``dxf_path``);
    returns the ``control`` record of result.json and the plot data of the report."""
    import numpy as np

    from minegeo._provenance import atomic_write_text
    from minegeo.io import write_trajectory
    from minegeo.io.types import Trajectory
    from minegeo.slam.control import apply_control, graph_inputs, interpolate_poses, slam_pose_noise

    st, offset, crs, mode = ctrl_in
    kt, kP, edges, Z, info = graph_inputs(res, st.t_mid_s)
    c = apply_control(kt, kP, edges, Z, info, st, offset, crs, params, slam_pose_noise(res, kt))
    var_map = interpolate_poses(kt, kP, c.times_s)  # the variables' map poses before the correction
    P_local = c.transform(res.times_s, res.poses, c.times_s, var_map)
    o = c.origin_enh
    write_trajectory(stage / "trajectory_crs.tum",
                     Trajectory(res.times_s, P_local, frame="local CRS (origin added back in the CSV)", body="sensor"))
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(P_local[:, :3, :3]).as_quat()  # x y z w
    enh = P_local[:, :3, 3] + o
    rows = ["t,E,N,H,qx,qy,qz,qw"] + [f"{t:.6f},{e[0]:.4f},{e[1]:.4f},{e[2]:.4f},{qq[0]:.9f},{qq[1]:.9f},{qq[2]:.9f},"
                                      f"{qq[3]:.9f}" for t, e, qq in zip(res.times_s, enh, q, strict=True)]
    atomic_write_text(stage / "trajectory_crs.csv", "\n".join(rows) + "\n")
    # stations
    chk = st.is_check
    w = np.full((len(st), 3), np.nan)
    w[st.is_control] = c.stats.w
    flagged = {f[0] for f in c.stats.flagged}
    ell = {}
    for k, i in enumerate(np.flatnonzero(chk)):
        if k < len(c.ellipses_check):
            ell[i] = c.ellipses_check[k]
    hdr = ("id,role,E,N,H,E_est,N_est,H_est,dE,dN,dH,horizontal,d3,w_max,flagged,ellipse95_a_m,ellipse95_b_m,"
           "ellipse95_azimuth_deg")
    lines = [hdr]
    for i, sid in enumerate(st.ids):
        s_enh, e_enh = st.enh[i], c.station_enh_local[i] + o
        d = c.station_enh_local[i] - st.enh_local[i]
        wm = np.nanmax(np.abs(w[i])) if np.isfinite(w[i]).any() else np.nan
        el = ell.get(i)
        el_s = (f"{el.semi_major_m:.4f},{el.semi_minor_m:.4f},{np.degrees(el.azimuth_rad):.2f}" if el is not None
                else ",,")
        lines.append(f"{sid},{st.roles[i]},{s_enh[0]:.4f},{s_enh[1]:.4f},{s_enh[2]:.4f},{e_enh[0]:.4f},{e_enh[1]:.4f},"
                     f"{e_enh[2]:.4f},{d[0]:.4f},{d[1]:.4f},{d[2]:.4f},{np.hypot(d[0], d[1]):.4f},"
                     f"{np.linalg.norm(d):.4f},{'' if np.isnan(wm) else f'{wm:.3f}'},{int(sid in flagged)},{el_s}")
    atomic_write_text(stage / "stations_result.csv", "\n".join(lines) + "\n")
    map_rec = _write_map_crs(stage, res, c, (kt, kP, var_map), st, offset, crs, mode)
    rec = control_record(c, st, offset, crs, mode)
    rec["map_las"] = map_rec
    if dxf_path is not None:
        from minegeo.io.dxf import write_control_dxf

        cov = c.station_cov_enh
        d = write_control_dxf(dxf_path, ids=st.ids, is_control=st.is_control, surveyed_enh=st.enh,
                              estimated_enh=c.station_enh_local + o, cov_enh=cov, trajectory_enh=enh, crs=crs,
                              exaggeration=dxf_exaggeration, flagged=[f[0] for f in c.stats.flagged])
        rec["dxf"] = {"layers": d["layers"], "exaggeration": d["exaggeration"], "ellipses": d["ellipses"]}
    plot = {"enh": enh, "origin": o, "stations_enh": st.enh, "est_enh": c.station_enh_local + o,
            "is_control": st.is_control, "ids": st.ids, "ellipses": ell}
    return rec, plot


def _control_parameters(p) -> dict:
    """``parameters.control`` of result.json: the :class:`~minegeo.slam.control.ControlParams` the run used."""
    return {"mode": "similarity" if p.model == "similarity" else p.mode, "drift_states": {False: "off", True: "on", "auto": "auto"}[p.drift_states],
            "drift_walk_per_sqrt_s": [float(v) for v in p.drift_walk], "drift_prior": [float(v) for v in p.drift_prior],
            "class_constant_mm": float(p.class_c), "snooping": bool(p.snooping)}


def control_record(c, st, offset, crs, mode) -> dict:
    """The ``control`` record of result.json (and of the report's "Survey control" section) of a
    :class:`~minegeo.slam.control.ControlResult` ``c`` of the stations ``st``: mode, status and reason
    (the flagged stations named), σ0, χ² test, w-test flags, control residuals, check errors and RMSE,
    class test, misclosure ratios."""
    import numpy as np

    o = c.origin_enh
    chi = c.global_chi2
    rec = {
        "mode": mode, "status": c.status, "reason": c.reason, "crs": crs, "origin_enh": o.tolist(),
        "station_offset_m": offset.tolist(), "source": str(st.source), "note": c.keyframe_note,
        "drift_states": bool(c.drift_states), "drift_states_choice": c.drift_choice,
        "uncertainty_note": c.uncertainty_note,
        "sigma0": float(np.sqrt(chi.statistic / chi.dof)) if chi.dof else None,
        "chi2_test": {"statistic": float(chi.statistic), "dof": int(chi.dof), "alpha": float(chi.alpha),
                      "lower": float(chi.lower), "upper": float(chi.upper), "passed": chi.passed,
                      "verdict": chi.verdict},
        "flagged": [{"id": f[0], "component": f[1], "w": float(f[2])} for f in c.stats.flagged],
        "suspected_blunders": list(c.blunders), "still_flagged_after_snooping": list(c.unresolved),
        "control_residuals": [{"id": sid, "v_enh_m": c.stats.v[k].tolist()} for k, sid in enumerate(c.stats.ids)],
        "check": None if c.check is None else {
            "rmse_horizontal_m": float(c.check.rmse_horizontal), "rmse_vertical_m": float(c.check.rmse_vertical),
            "rmse_3d_m": float(c.check.rmse_3d),
            "stations": [{"id": sid, "delta_enh_m": c.check.delta[k].tolist(), "horizontal_m": float(c.check.horizontal[k]),
                          "d3_m": float(c.check.d3[k]),
                          "misclosure_ratio": float(c.misclosure_ratio[k]) if k < c.misclosure_ratio.size else None}
                         for k, sid in enumerate(c.check.ids)]},
        "class_test": None if c.classes is None else {
            "c": float(c.classes.c), "ids": list(c.classes.ids), "nearest_control": list(c.classes.nearest_control),
            "distance_m": c.classes.distance_m.tolist(), "allowed_mm": c.classes.allowed_mm.tolist(),
            "relative_error_mm": c.classes.relative_error_mm.tolist(),
            "passed": [bool(x) for x in c.classes.passed]},
        "misclosure_ratio": [float(x) for x in c.misclosure_ratio],
        "station_covariance_enh_m2": None if c.station_cov_enh is None else {
            sid: np.asarray(c.station_cov_enh[i]).tolist() for i, sid in enumerate(st.ids)},
    }
    if c.similarity:
        rec["scale"] = {"scale": float(c.scale), "scale_ppm": float((c.scale - 1.0) * 1e6),
                        "sigma_ppm": float(c.scale_std * 1e6), "sigma": "a posteriori (scaled by sigma0)",
                        "dof": int(chi.dof), "T_local_map": np.asarray(c.T_local_map).tolist(),
                        "definition": "p_local = T_local_map p_map = s R p_map + T; E N H = p_local + origin_enh"}
    return rec


def _side_inputs(args, imu) -> list[dict]:
    """The input records (path, SHA-256) of the times file, the IMU (a bag's SHA-256 is its frames') and
    its noise file."""
    from minegeo._provenance import sha256_file

    out = [{"path": str(args.times), "sha256": sha256_file(args.times)}] if args.times else []
    if imu is not None:
        out.append({"path": str(args.imu), "sha256": sha256_file(args.imu) if Path(args.imu).is_file() else None})
        if getattr(args, "imu_noise", None):
            out.append({"path": str(args.imu_noise), "sha256": sha256_file(args.imu_noise)})
    return out


def run(args) -> int:
    from tqdm import tqdm

    from minegeo._output import OutputTransaction, progress_enabled, run_timings
    from minegeo._provenance import StageTimer, provenance, sha256_file, write_json_atomic
    from minegeo.errors import InputError
    from minegeo.io.frames import list_frames, times_source
    from minegeo.report.slam_report import write_slam_report
    from minegeo.slam.pipeline import run_slam

    timer = StageTimer()
    params = _params(args)
    out = Path(args.out)
    inputs_named = {"--frames": args.frames, **({"--times": args.times} if args.times else {})}
    _check_options(args)
    ctrl_in = _read_control(args)
    if ctrl_in is not None:
        ctrl_params = control_params(args, ctrl_in[3])
        inputs_named["--control"] = args.control
    dxf_out = {"--dxf": args.dxf} if getattr(args, "dxf", None) else {}
    imu = read_imu(args)
    inertial = inertial_params(args)
    inputs_named.update({"--imu": args.imu} if imu is not None else {})
    inputs_named.update({"--imu-noise": args.imu_noise} if getattr(args, "imu_noise", None) else {})
    with OutputTransaction("slam", inputs=inputs_named, folders={"--out": out}, files=dxf_out) as tx:
        files = list_frames(args.frames, args.times, args.pattern, args.lidar_topic)
        if len(files) < 2:  # before any compiled work (a first run compiles for a minute before its first frame)
            raise InputError(f"--frames {args.frames}: fewer than 2 readable frames")
        _check_times(files)
        check_imu(imu, files, args)
        target, target_why = odometry_target(getattr(args, "odometry", "auto"), [f.time_s for f in files])
        params = replace(params, odometry=replace(params.odometry, frame_target=target))
        if ctrl_in is not None and files:
            from minegeo.slam.control import check_station_frames

            check_station_frames(ctrl_in[0], [f.time_s for f in files], f"the frames of --frames {args.frames}")
        skipped: list[dict] = []
        bar = tqdm(total=len(files), desc="slam", unit="frame", file=sys.stderr, disable=not progress_enabled(args))
        # each registration's warnings (weak direction, 2-cycle) are recorded per frame in
        # result.json; on the terminal they would be one line per frame
        reg_log = logging.getLogger("minegeo.registration")
        level = reg_log.level
        reg_log.setLevel(logging.ERROR)
        try:
            with bar, timer("slam"):
                res = run_slam(_frames(files, skipped, bar, params.odometry.min_points, params.odometry.deskew),
                               params, imu=imu, inertial=inertial)
        except InputError:
            if files and len(skipped) == len(files):  # every frame skipped: say why, not "the sequence is empty"
                raise InputError(_all_skipped(args.frames, skipped)) from None
            raise
        finally:
            reg_log.setLevel(level)
        used = {f.name for f in files} - {s["frame"] for s in skipped}
        if res.times_s.size < 2:
            raise InputError(f"--frames {args.frames}: fewer than 2 readable frames")
        inputs = files.inputs() + _side_inputs(args, imu)
        stage = tx.folder("--out")
        with timer("write"):
            _write_outputs(stage, res, sorted(used))
        control_rec = control_plot = None
        if ctrl_in is not None:
            inputs.append({"path": str(args.control), "sha256": sha256_file(args.control)})
            from minegeo.slam.control import check_station_frames

            # the frames the run used (unreadable ones skipped): a station must not fall in a gap they leave
            check_station_frames(ctrl_in[0], res.times_s, f"the frames of --frames {args.frames} the run could use")
            with timer("control"):
                control_rec, control_plot = _control_outputs(stage, res, ctrl_in, ctrl_params,
                                                             tx.file("--dxf") if dxf_out else None,
                                                             getattr(args, "dxf_exaggeration", None))
        summary = {
            "command": "slam", "status": "ok", "reason": "",
            "parameters": {**params.as_dict(), **({"control": _control_parameters(ctrl_params)} if ctrl_in is not None
                                                  else {})},
            "result": {**res.summary(), "times_from": times_source(args.frames, args.times), "skipped_frames": skipped,
                       "frames_not_registered": [{"time_s": float(res.times_s[k]), "reason": r}
                                                 for k, r in enumerate(res.odometry.frame_reason) if r],
                       "low_observability_frames": [{"time_s": float(res.times_s[k]), "direction": w}
                                                    for k, w in enumerate(res.odometry.frame_weak) if w],
                       "odometry_target": {"frame_target": target, "chosen_by": target_why},
                       **_deskew_and_runaway(res.odometry)},
            "outputs": {n: str(out / n) for n in ("trajectory.tum", "keyframes.tum", "graph.g2o", "loops.csv", "map.ply",
                                                  "result.json", "report.html")},
            **({"control": control_rec} if control_rec is not None else {}),
            **({"imu_noise": asdict(inertial.noise), "inertial": asdict(inertial)} if inertial is not None else {}),
            "module_timings_s": res.timings_s,
            "timings_s": {**timer.as_dict(), **run_timings(args)},
            "provenance": provenance(seed=args.seed, inputs=inputs),
        }
        if control_rec is not None:
            summary["outputs"].update({n: str(out / n) for n in ("trajectory_crs.tum", "trajectory_crs.csv",
                                                                 "stations_result.csv", "map_crs.ply",
                                                                 "map_crs.ply.georef.json")})
            if control_rec["map_las"]["written"]:
                las = control_rec["map_las"]["file"]
                summary["outputs"].update({las: str(out / las), f"{las}.georef.json": str(out / f"{las}.georef.json")})
            if dxf_out:
                summary["outputs"]["dxf"] = str(args.dxf)
        write_json_atomic(stage / "result.json", summary)
        write_slam_report(stage / "report.html", summary, res, control_plot)
    if not getattr(args, "quiet", False):
        _print_summary(summary, out, args, skipped, imu, control_rec, dxf_out)
    return 0


def _print_summary(summary: dict, out: Path, args, skipped: list, imu, control_rec, dxf_out: dict) -> None:
    """The run's lines on stdout (frames, IMU graph, held stretches, control, files written)."""
    s = summary["result"]
    print(f"{s['frames']} frames ({len(skipped)} skipped, {s['failed_frames']} not registered), {s['keyframes']} "
          f"keyframes, {s['loops_accepted']} loop(s) of {s['loop_candidates']} candidates, path "
          f"{s['path_length_m']:.1f} m, map {s['map_points']:,} points")
    print(f"odometry: each frame to the {'local map' if s['odometry_target']['frame_target'] == 'submap' else 'previous frame'}"
          f" ({s['odometry_target']['chosen_by']})")
    held = s["motion_prior_stretches"]
    if "inertial" in s:
        ine = s["inertial"]
        print(f"IMU keyframe graph: {ine['status']}{': ' + ine['reason'] if ine['status'] == 'failed' else ''}; gyro "
              f"bias at the last keyframe {[round(x, 5) for x in ine['keyframes'][-1]['bias_gyro_rad_s']]} rad/s")
    if held:
        where = ", ".join(f"frames {h['first_frame']}-{h['last_frame']} ({h['first_time_s']:.2f}-"
                          f"{h['last_time_s']:.2f} s)" for h in held[:5]) + (" ..." if len(held) > 5 else "")
        print(f"held by {_HELD_BY[imu is not None]}: {len(held)} stretch(es), {s['motion_prior_held_s']:.2f} s: {where}")
    if control_rec is not None:
        c = control_rec
        chk = c["check"]
        print(f"control ({c['mode']}, {c['crs']}): {c['status']}{': ' + c['reason'] if c['reason'] else ''}"
              + ("" if chk is None else f"; check RMSE h {chk['rmse_horizontal_m']:.3f} m, v "
                                        f"{chk['rmse_vertical_m']:.3f} m")
              + (f"; scale {c['scale']['scale_ppm']:+.1f} +- {c['scale']['sigma_ppm']:.1f} ppm" if "scale" in c else ""))
        if c["drift_states_choice"] is not None:
            ch = c["drift_states_choice"]
            print(f"drift states (auto): {'taken' if ch['chosen'] else 'not taken'} (likelihood ratio "
                  f"{ch['statistic']:.2f}, critical {ch['critical']:.2f} on {ch['dof']:.2f} degrees of freedom); "
                  f"note: {c['uncertainty_note']}")
        las = c["map_las"]
        print(f"written: {out}/(trajectory_crs.tum, trajectory_crs.csv, stations_result.csv, map_crs.ply"
              + (f", {las['file']})" if las["written"] else ")")
              + (f"; {args.dxf} (residuals and ellipses x{c['dxf']['exaggeration']:g})" if dxf_out else ""))
        if not las["written"]:
            print(f"note: no map_crs.las: {las['reason']} (pip install 'minegeo[las]')")
    print(f"written: {out}/(trajectory.tum, keyframes.tum, graph.g2o, loops.csv, map.ply, result.json, report.html)")
