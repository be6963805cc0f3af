"""``minegeo evaluate --est EST --gt GT --out DIR``: ATE and RPE of a trajectory, as evo computes them.

Trajectories in any format ``minegeo info`` reads (TUM, KITTI, GeoSLAM, CSV). Poses are associated
by time (within ``--max-diff``); two KITTI files, which have no times, by index, and then they must
hold the same number of poses (as ``evo_ape kitti`` requires), unless ``--est-times``/``--gt-times``
give their times (the KITTI odometry ``times.txt`` layout), which matches them by time. A KITTI file
is never matched against a timed file without its times. The estimate is aligned by Umeyama SE(3)
(Sim(3) with ``--scale``; ``--no-align`` contradicts ``--scale``), and ``DIR/result.json`` +
``DIR/report.html`` hold the statistics, per axis, and plots.

Every option value is checked before any file is read: ``--max-diff`` positive finite seconds,
``--delta`` a whole number of frames from 1 (``--delta-unit frames``) or positive finite metres
(``m``).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

HELP = "absolute and relative trajectory error (ATE/RPE) of an estimate against ground truth, evo's definitions"


#: default largest time difference of a match (s), evo's ``--t_max_diff``
MAX_DIFF_S = 0.01


def add_arguments(parser) -> None:
    from minegeo.cli._argtypes import positive_float

    parser.add_argument("--est", required=True, help="estimated trajectory (TUM, KITTI, GeoSLAM, CSV)")
    parser.add_argument("--gt", required=True, help="ground-truth trajectory (TUM, KITTI, GeoSLAM, CSV)")
    parser.add_argument("--out", required=True, help="output folder (result.json, report.html)")
    parser.add_argument("--est-times", default=None, metavar="FILE",
                        help="times of a KITTI --est (one time in seconds per pose, KITTI times.txt): match by time")
    parser.add_argument("--gt-times", default=None, metavar="FILE",
                        help="times of a KITTI --gt (one time in seconds per pose, KITTI times.txt): match by time")
    parser.add_argument("--scale", action="store_true", help="Sim(3) alignment (correct the scale too)")
    parser.add_argument("--no-align", action="store_true", help="no alignment (both already in the same frame)")
    parser.add_argument("--max-diff", type=positive_float, default=None,
                        help=f"largest time difference of a match (s, default {MAX_DIFF_S:g})")
    parser.add_argument("--delta", type=positive_float, default=1.0,
                        help="RPE pair distance: a whole number of frames, or metres with --delta-unit m (default 1)")
    parser.add_argument("--delta-unit", choices=("frames", "m"), default="frames", help="unit of --delta")


def _stats(s) -> dict:
    return asdict(s)


def _check_options(args) -> None:
    """Option combinations that contradict, refused before any file is read."""
    from minegeo.errors import InputError
    from minegeo.slam.evaluate import MAX_DELTA_FRAMES

    if args.scale and args.no_align:
        raise InputError("--scale and --no-align contradict: --scale corrects the scale as part of the alignment "
                         "that --no-align turns off; give one of them")
    if args.delta_unit == "frames" and not (args.delta.is_integer() and args.delta <= MAX_DELTA_FRAMES):
        raise InputError(f"--delta {args.delta:g}: with --delta-unit frames the RPE pair distance is a whole number "
                         f"of frames from 1 to {MAX_DELTA_FRAMES} (or give metres with --delta-unit m)")


def _match(args, est, gt, est_fmt: str, gt_fmt: str) -> str:
    """``"time"``, or ``"index"`` for two KITTI files without times (same number of poses required)."""
    from minegeo.errors import InputError

    est_timed = est_fmt != "kitti" or args.est_times is not None
    gt_timed = gt_fmt != "kitti" or args.gt_times is not None
    if est_timed and gt_timed:
        return "time"
    if est_timed != gt_timed:
        name, opt, other = (args.gt, "--gt-times", args.est) if est_timed else (args.est, "--est-times", args.gt)
        raise InputError(f"{name} is a KITTI file (no times) and {other} has times: the poses cannot be matched; "
                         f"give the KITTI file's times with {opt} FILE (one time in seconds per pose)")
    if args.max_diff is not None:
        raise InputError("--max-diff matches poses by time, and the two KITTI files have none (they are matched by "
                         "index): drop --max-diff, or give their times with --est-times and --gt-times")
    if len(est) != len(gt):
        raise InputError(f"{args.est} holds {len(est)} poses and {args.gt} {len(gt)}: KITTI files have no times, so "
                         "pose k is matched with pose k and both must hold the same number of poses (as evo_ape "
                         "kitti requires); give their times with --est-times and --gt-times to match them by time")
    return "index"


def run(args) -> int:
    import numpy as np

    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.io.trajectory import read_trajectory, trajectory_format
    from minegeo.report.slam_report import plot_evaluation_png, write_evaluate_report
    from minegeo.slam.evaluate import evaluate_trajectory

    _check_options(args)
    timer = StageTimer()
    out = Path(args.out)
    named = {"--est": args.est, "--gt": args.gt, "--est-times": args.est_times, "--gt-times": args.gt_times}
    with OutputTransaction("evaluate", inputs=named, folders={"--out": out}) as tx:
        with timer("read"):
            est = read_trajectory(args.est, times=args.est_times)
            gt = read_trajectory(args.gt, times=args.gt_times)
            match = _match(args, est, gt, trajectory_format(args.est), trajectory_format(args.gt))
        with timer("evaluate"):
            ev = evaluate_trajectory(est, gt, scale=args.scale, max_diff_s=args.max_diff or MAX_DIFF_S,
                                     rpe_delta=args.delta, rpe_unit=args.delta_unit, align=not args.no_align,
                                     match=match)
        result = {
            "n_matched": ev.n_matched, "T_gt_est": ev.T_gt_est.tolist(), "scale": ev.scale, "ate": _stats(ev.ate),
            "ate_axis": {a: _stats(s) for a, s in ev.ate_axis.items()}, "ate_rotation_deg": _stats(ev.ate_rotation_deg),
            "ate_percent_of_path": ev.ate_percent_of_path, "path_length_m": ev.path_length_m,
            "rpe_translation": _stats(ev.rpe_translation), "rpe_rotation_deg": _stats(ev.rpe_rotation_deg),
            "rpe_translation_percent": ev.rpe_translation_percent, "rpe_rotation_deg_per_m": ev.rpe_rotation_deg_per_m,
            "params": ev.params, "warnings": ev.warnings,
        }
        inputs = {"est": input_record(args.est), "gt": input_record(args.gt)}
        for key, path in (("est_times", args.est_times), ("gt_times", args.gt_times)):
            if path is not None:
                inputs[key] = input_record(path)
        summary = {"command": "evaluate", "status": "ok", "result": result, "inputs": inputs,
                   "timings_s": {**timer.as_dict(), **run_timings(args)},
                   "provenance": provenance(seed=None, inputs=list(inputs.values()))}
        stage = tx.folder("--out")
        write_json_atomic(stage / "result.json", summary)
        idx_gt = ev.gt_index
        gt_xy = gt.poses[idx_gt, :2, 3] + gt.origin[:2]
        est_xy = gt_xy - ev.errors_m[:, :2]
        dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(gt.poses[idx_gt, :3, 3], axis=0), axis=1))]
        png = plot_evaluation_png(gt_xy, est_xy, dist, np.linalg.norm(ev.errors_m, axis=1))
        write_evaluate_report(stage / "report.html", summary, png)
    if not getattr(args, "quiet", False):
        how = "by time" if match == "time" else "by index (KITTI, no times)"
        print(f"matched {ev.n_matched} poses {how}; ATE RMSE {ev.ate.rmse:.4f} m ({ev.ate_percent_of_path:.3f} % of "
              f"{ev.path_length_m:.1f} m), RPE {ev.rpe_translation.rmse:.4f} m / {ev.rpe_rotation_deg.rmse:.4f} deg "
              f"RMSE per {args.delta:g} {args.delta_unit}")
        print(f"written: {out / 'result.json'}, {out / 'report.html'}")
    return 0
