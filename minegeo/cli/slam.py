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
import sys
from pathlib import Path

from minegeo.cli._argtypes import float_in_range, int_in_range, nonnegative_int, positive_float

HELP = "LiDAR SLAM from a folder of frames: GICP odometry, loop closure, pose graph; trajectory + map (Ren et al. 2019)"

log = logging.getLogger(__name__)


def add_arguments(parser) -> None:
    parser.add_argument("--frames", required=True, help="folder of frames (PLY/PCD/LAS/XYZ or KITTI .bin), sensor frame; "
                        "times from times.txt or the file names")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--times", default=None, help="file of frame times (s), one per frame in name order "
                        "(default: FRAMES/times.txt, else the numbers in the file names)")
    parser.add_argument("--pattern", default=None, help='frame file-name pattern, e.g. "*.pcd" (default: every '
                        "point-cloud file in the folder)")
    parser.add_argument("--voxel", type=positive_float, default=0.3, help="odometry voxel size (m, default 0.3)")
    parser.add_argument("--max-distance", type=positive_float, default=1.0,
                        help="GICP correspondence gate (m, default 1.0)")
    parser.add_argument("--keyframe-distance", type=positive_float, default=2.0, help="keyframe distance threshold (m)")
    parser.add_argument("--keyframe-angle", type=float_in_range(0.0, 180.0, lo_open=True), default=10.0,
                        help="keyframe rotation threshold (deg, in (0, 180])")
    parser.add_argument("--keyframe-interval", type=positive_float, default=10.0, help="keyframe time threshold (s)")
    parser.add_argument("--loop-gap", type=positive_float, default=30.0, help="loop candidates: path gap above (m)")
    parser.add_argument("--loop-radius", type=positive_float, default=8.0,
                        help="loop candidates: distance below (m; less than --loop-gap)")
    parser.add_argument("--no-planes", action="store_true", help="no floor-plane landmarks in the pose graph "
                        "(default: floor planes of the keyframe sub-maps as nodes, Ren et al. 2019 Sec. 3.4.2)")
    parser.add_argument("--no-noise-removal", action="store_true", help="keep the roadway noise in the map "
                        "(default: points inside the roadway away from the fitted floor, walls and roof, e.g. "
                        "pedestrians, are removed section by section along the keyframe track, Ren et al. 2019 Sec. 3.5)")
    parser.add_argument("--map-voxel", type=positive_float, default=0.1, help="map voxel (m, default 0.1)")
    parser.add_argument("--no-deskew", action="store_true", help="do not deskew frames whose points carry times "
                        "(default: each such frame is moved to its frame time by the constant-velocity motion of the "
                        "odometry before registration; frames without times are never deskewed)")
    parser.add_argument("--deskew-iterations", type=int_in_range(0, 1), default=None,
                        help="1 (default): after registering a frame, deskew it again with its own estimated motion "
                        "and register once more; 0: one pass")
    parser.add_argument("--max-speed", type=positive_float, default=30.0,
                        help="plausible motion: a registration faster than this is rejected (m/s, default 30)")
    parser.add_argument("--max-angular-rate", type=positive_float, default=180.0,
                        help="plausible motion: a registration turning faster is rejected (deg/s, default 180)")
    parser.add_argument("--max-acceleration", type=positive_float, default=20.0,
                        help="plausible motion: a registration whose velocity changes faster than this against the "
                        "previous motion, beyond 0.1 m of registration scatter, is rejected (m/s^2, default 20)")
    parser.add_argument("--seed", type=nonnegative_int, default=0,
                        help="recorded seed (the run draws no random numbers)")


def _check_options(args) -> None:
    """Option combinations and paths, before any work.

    * ``--loop-radius`` must be below ``--loop-gap``: a candidate lies more than the gap along the
      path and less than the radius away, and the straight-line distance never exceeds the path
      distance, so with radius >= gap every keyframe one gap back on a straight drift would be a
      "loop" (no revisit at all).
    * ``--times`` must name a regular file (not a folder, FIFO or device).
    """
    from minegeo.errors import InputError

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


def _check_times(files) -> None:
    """The frame times as the run needs them (the frames reader checks order and finiteness; this
    adds the trajectory files' range, so that ``trajectory.tum`` can be read back): every time within
    ``±MAX_ABS_TIME`` s, hence every difference finite."""
    from minegeo.errors import InputError
    from minegeo.io._limits import MAX_ABS_TIME

    for k, f in enumerate(files):
        t = f.time_s
        if not abs(t) <= MAX_ABS_TIME:
            raise InputError(f"frame {f.path.name}: time {t!r} s is beyond ±{MAX_ABS_TIME:.0e} s, the range a "
                             "trajectory file holds (give times in seconds from a nearby epoch)")
        if k and not t > files[k - 1].time_s:
            raise InputError(f"frame {f.path.name}: time {t!r} s is not after the previous frame's "
                             f"{files[k - 1].time_s!r} s")


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
                         max_acceleration_m_s2=getattr(args, "max_acceleration", 20.0))
    return SlamParams(odometry=odo, loops=LoopParams(min_path_gap_m=args.loop_gap, max_distance_m=args.loop_radius),
                      map_voxel_m=args.map_voxel, use_planes=not getattr(args, "no_planes", False),
                      remove_noise=not getattr(args, "no_noise_removal", False))


def _frames(files, skipped: list, bar, min_points: int, with_times: bool = False):
    """Yield (time, points) of the readable frames, or with ``with_times`` (time, points, per-point
    offsets in s after the frame time, or None when the file holds no times); unreadable ones and
    frames with fewer than ``min_points`` points are recorded and skipped (the contract)."""
    from minegeo.errors import MinegeoError
    from minegeo.io.frames import read_frame

    for f in files:
        tau = None
        try:
            if with_times:
                tp = read_frame(f.path, with_times=True, time_s=f.time_s)
                pts, tau = tp.xyz, tp.t_offset_s
            else:
                pts = read_frame(f.path)
        except (MinegeoError, OSError) as exc:
            skipped.append({"frame": f.path.name, "reason": str(exc)})
            log.warning("frame %s skipped: %s", f.path.name, exc)
            bar.update(1)
            continue
        bar.update(1)
        if pts.shape[0] < min_points:
            skipped.append({"frame": f.path.name, "reason": f"{pts.shape[0]} points, fewer than {min_points}"})
            log.warning("frame %s skipped: %d points", f.path.name, pts.shape[0])
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
    with OutputTransaction("slam", inputs=inputs_named, folders={"--out": out}) as tx:
        files = list_frames(args.frames, times_file=args.times, pattern=args.pattern)
        _check_times(files)
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
                               params)
        except InputError:
            if files and len(skipped) == len(files):  # every frame skipped: say why, not "the sequence is empty"
                raise InputError(_all_skipped(args.frames, skipped)) from None
            raise
        finally:
            reg_log.setLevel(level)
        used = {f.path.name for f in files} - {s["frame"] for s in skipped}
        if res.times_s.size < 2:
            raise InputError(f"--frames {args.frames}: fewer than 2 readable frames")
        inputs = [{"path": str(f.path), "sha256": sha256_file(f.path)} for f in files]
        if args.times:
            inputs.append({"path": str(args.times), "sha256": sha256_file(args.times)})
        stage = tx.folder("--out")
        with timer("write"):
            _write_outputs(stage, res, sorted(used))
        summary = {
            "command": "slam", "status": "ok", "reason": "", "parameters": params.as_dict(),
            "result": {**res.summary(), "times_from": times_source(args.frames, args.times), "skipped_frames": skipped,
                       "frames_not_registered": [{"time_s": float(res.times_s[k]), "reason": r}
                                                 for k, r in enumerate(res.odometry.frame_reason) if r],
                       "low_observability_frames": [{"time_s": float(res.times_s[k]), "direction": w}
                                                    for k, w in enumerate(res.odometry.frame_weak) if w],
                       **_deskew_and_runaway(res.odometry)},
            "outputs": {n: str(out / n) for n in ("trajectory.tum", "keyframes.tum", "graph.g2o", "loops.csv", "map.ply",
                                                  "result.json", "report.html")},
            "module_timings_s": res.timings_s,
            "timings_s": {**timer.as_dict(), **run_timings(args)},
            "provenance": provenance(seed=args.seed, inputs=inputs),
        }
        write_json_atomic(stage / "result.json", summary)
        write_slam_report(stage / "report.html", summary, res)
    if not getattr(args, "quiet", False):
        s = summary["result"]
        print(f"{s['frames']} frames ({len(skipped)} skipped, {s['failed_frames']} not registered), {s['keyframes']} "
              f"keyframes, {s['loops_accepted']} loop(s) of {s['loop_candidates']} candidates, path "
              f"{s['path_length_m']:.1f} m, map {s['map_points']:,} points")
        held = s["motion_prior_stretches"]
        if held:
            where = ", ".join(f"frames {h['first_frame']}-{h['last_frame']} ({h['first_time_s']:.2f}-"
                              f"{h['last_time_s']:.2f} s)" for h in held[:5]) + (" ..." if len(held) > 5 else "")
            print(f"held by the motion prior alone: {len(held)} stretch(es), {s['motion_prior_held_s']:.2f} s: {where}")
        print(f"written: {out}/(trajectory.tum, keyframes.tum, graph.g2o, loops.csv, map.ply, result.json, report.html)")
    return 0
