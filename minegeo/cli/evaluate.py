"""``minegeo evaluate --est EST --gt GT --out DIR``: ATE and RPE of a trajectory, as evo computes them.

Trajectories in any format ``minegeo info`` reads (TUM, KITTI with ``--times``, CSV). Poses are
associated by time, the estimate is aligned by Umeyama SE(3) (Sim(3) with ``--scale``), and
``DIR/result.json`` + ``DIR/report.html`` hold the statistics, per axis, and plots.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

HELP = "absolute and relative trajectory error (ATE/RPE) of an estimate against ground truth, evo's definitions"


def add_arguments(parser) -> None:
    parser.add_argument("--est", required=True, help="estimated trajectory (TUM, KITTI, CSV)")
    parser.add_argument("--gt", required=True, help="ground-truth trajectory (TUM, KITTI, CSV)")
    parser.add_argument("--out", required=True, help="output folder (result.json, report.html)")
    parser.add_argument("--scale", action="store_true", help="Sim(3) alignment (correct the scale too)")
    parser.add_argument("--no-align", action="store_true", help="no alignment (both already in the same frame)")
    parser.add_argument("--max-diff", type=float, default=0.01, help="largest time difference of a match (s)")
    parser.add_argument("--delta", type=float, default=1.0, help="RPE pair distance (default 1)")
    parser.add_argument("--delta-unit", choices=("frames", "m"), default="frames", help="unit of --delta")


def _stats(s) -> dict:
    return asdict(s)


def run(args) -> int:
    import numpy as np

    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.io import read_trajectory
    from minegeo.report.slam_report import plot_evaluation_png, write_evaluate_report
    from minegeo.slam.evaluate import evaluate_trajectory

    timer = StageTimer()
    out = Path(args.out)
    with OutputTransaction("evaluate", inputs={"--est": args.est, "--gt": args.gt}, folders={"--out": out}) as tx:
        with timer("read"):
            est = read_trajectory(args.est)
            gt = read_trajectory(args.gt)
        with timer("evaluate"):
            ev = evaluate_trajectory(est, gt, scale=args.scale, max_diff_s=args.max_diff, rpe_delta=args.delta,
                                     rpe_unit=args.delta_unit, align=not args.no_align)
        result = {
            "n_matched": ev.n_matched, "T_gt_est": ev.T_gt_est.tolist(), "scale": ev.scale, "ate": _stats(ev.ate),
            "ate_axis": {a: _stats(s) for a, s in ev.ate_axis.items()}, "ate_rotation_deg": _stats(ev.ate_rotation_deg),
            "ate_percent_of_path": ev.ate_percent_of_path, "path_length_m": ev.path_length_m,
            "rpe_translation": _stats(ev.rpe_translation), "rpe_rotation_deg": _stats(ev.rpe_rotation_deg),
            "rpe_translation_percent": ev.rpe_translation_percent, "rpe_rotation_deg_per_m": ev.rpe_rotation_deg_per_m,
            "params": ev.params, "warnings": ev.warnings,
        }
        inputs = {"est": input_record(args.est), "gt": input_record(args.gt)}
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
        print(f"matched {ev.n_matched} poses; ATE RMSE {ev.ate.rmse:.4f} m ({ev.ate_percent_of_path:.3f} % of "
              f"{ev.path_length_m:.1f} m), RPE {ev.rpe_translation.rmse:.4f} m / {ev.rpe_rotation_deg.rmse:.4f} deg "
              f"RMSE per {args.delta:g} {args.delta_unit}")
        print(f"written: {out / 'result.json'}, {out / 'report.html'}")
    return 0
