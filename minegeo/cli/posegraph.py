"""``minegeo posegraph IN.g2o --out OUT.g2o``: optimise a pose-graph file (the SLAM contract's cost).

Writes the optimised graph (every vertex at its optimised value, every edge as read) and, in
``--report DIR`` (default ``OUT.g2o.report``), ``result.json`` and ``report.html`` with the cost
before and after, the iterations and a plan view. Exit status 0 when the optimiser converged,
1 when it stopped at the iteration limit or failed (the reason is printed and recorded).
"""

from __future__ import annotations

from pathlib import Path

HELP = "optimise a pose graph (g2o SE3/SE2) by Levenberg-Marquardt; report the cost before/after and iterations"


def add_arguments(parser) -> None:
    parser.add_argument("graph", help="pose graph in g2o format (VERTEX_SE3:QUAT/EDGE_SE3:QUAT or VERTEX_SE2/EDGE_SE2)")
    parser.add_argument("--out", required=True, help="optimised graph to write (g2o)")
    parser.add_argument("--report", default=None, help="folder for result.json and report.html (default OUT.report)")
    parser.add_argument("--max-iterations", type=int, default=100, help="largest number of LM iterations (default 100)")
    parser.add_argument("--robust", choices=("none", "huber", "cauchy"), default="none",
                        help="robust kernel on the whitened edge residual (default none: the contract cost)")
    parser.add_argument("--robust-scale", type=float, default=1.0, help="kernel width in standard deviations")


def run(args) -> int:
    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.io.g2o import read_g2o, write_g2o
    from minegeo.report.slam_report import plot_posegraph_png, write_posegraph_report
    from minegeo.slam.posegraph import PoseGraphParams, optimize_pose_graph

    timer = StageTimer()
    params = PoseGraphParams(max_iterations=args.max_iterations, robust=args.robust, robust_scale=args.robust_scale)
    out = Path(args.out)
    report = Path(args.report) if args.report else out.with_name(out.name + ".report")
    with OutputTransaction("posegraph", inputs={"graph": args.graph}, files={"--out": out},
                           folders={"--report": report}) as tx:
        with timer("read"):
            graph = read_g2o(args.graph)
        with timer("optimise"):
            res = optimize_pose_graph(graph, params)
        with timer("write"):
            write_g2o(tx.file("--out"), res.graph)
        inputs = {"graph": input_record(args.graph)}
        summary = {
            "command": "posegraph",
            "status": res.status,
            "reason": res.reason,
            "graph": {"kind": graph.kind, "vertices": graph.n_vertices, "edges": graph.n_edges,
                      "chained": len(graph.chained_ids), "fixed": list(graph.fixed)},
            "result": {**res.summary(), "history": res.history},
            "outputs": {"graph": str(out), "result_json": str(report / "result.json"),
                        "report_html": str(report / "report.html")},
            "inputs": inputs,
            "timings_s": {**timer.as_dict(), **res.timings_s, **run_timings(args)},
            "provenance": provenance(seed=None, inputs=list(inputs.values())),
        }
        stage = tx.folder("--report")
        write_json_atomic(stage / "result.json", summary)
        with timer("report"):
            png = plot_posegraph_png(graph.poses, res.graph.poses, graph.edges)
        write_posegraph_report(stage / "report.html", summary, png)
    if not getattr(args, "quiet", False):
        print(f"{graph.kind} graph: {graph.n_vertices} vertices, {graph.n_edges} edges; cost "
              f"{res.cost_initial:.10g} -> {res.cost_final:.10g} in {res.iterations} iterations ({res.status}: "
              f"{res.reason})")
        print(f"written: {out}, {report / 'result.json'}, {report / 'report.html'}")
    return 0 if res.status == "converged" else 1
