"""``minegeo posegraph IN.g2o --out OUT.g2o``: optimise a pose-graph file (the SLAM contract's cost).

Writes the optimised graph (every vertex at its optimised value, every edge as read) and, in
``--report DIR`` (default ``OUT.g2o.report``), ``result.json`` and ``report.html`` with the cost
before and after, the iterations, what was done with information matrices that are not positive
semi-definite, and a plan view.

Exit status: 0 converged (the stopping test held and the result passed its check); 1 a completed
run that is not converged (stopped at ``--max-iterations``, the line says how far from converged,
or a result that failed its check; both written with their status); 2 a user error, nothing
written: an unreadable or malformed file, an option value out of range, a self-loop edge, every
vertex fixed, a vertex that no edge with non-zero information ties to a fixed vertex (or whose
edges leave a direction of its pose free), or, with ``--indefinite-information refuse``, an edge
whose information matrix is not positive semi-definite.
"""

from __future__ import annotations

from pathlib import Path

from minegeo._params import arg_type

#: the parameter class whose field rules the options use
_PG = "minegeo.slam.posegraph:PoseGraphParams"
#: ``--max-iterations`` takes at most this many (the field takes any whole number >= 1)
MAX_ITERATIONS = 100000

HELP = "optimise a pose graph (g2o SE3/SE2) by Levenberg-Marquardt; report the cost before/after and iterations"


def add_arguments(parser) -> None:
    parser.add_argument("graph", help="pose graph in g2o format (VERTEX_SE3:QUAT/EDGE_SE3:QUAT or VERTEX_SE2/EDGE_SE2)")
    parser.add_argument("--out", required=True, help="optimised graph to write (g2o)")
    parser.add_argument("--report", default=None, help="folder for result.json and report.html (default OUT.report)")
    # defaults None: PoseGraphParams' own (not imported here: the parser is built for every verb; the
    # options' types check PoseGraphParams' field rules, importing it when an option is parsed)
    parser.add_argument("--max-iterations", type=arg_type(_PG, "max_iterations", le=MAX_ITERATIONS), default=None,
                        help="largest number of LM iterations (default: PoseGraphParams.max_iterations)")
    parser.add_argument("--robust", choices=("none", "huber", "cauchy"), default="none",
                        help="robust kernel on the whitened edge residual (default none: the contract cost)")
    parser.add_argument("--robust-scale", type=arg_type(_PG, "robust_scale"), default=1.0,
                        help="kernel width in standard deviations")
    parser.add_argument("--indefinite-information", choices=("gtsam", "refuse"), default="gtsam",
                        help="an edge information matrix that is not positive semi-definite: 'gtsam' (default) uses "
                             "the matrix GTSAM's readG2o uses (R^T R, R from the LLT stopped at its first "
                             "non-positive pivot) and reports how many; 'refuse' stops with exit 2 naming the first")


def run(args) -> int:
    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, input_record, provenance, write_json_atomic
    from minegeo.errors import InputError
    from minegeo.io.g2o import read_g2o, write_g2o
    from minegeo.report.slam_report import plot_posegraph_png, write_posegraph_report
    from minegeo.slam.posegraph import PoseGraphParams, optimize_pose_graph

    timer = StageTimer()
    given = {"max_iterations": args.max_iterations} if args.max_iterations is not None else {}
    params = PoseGraphParams(robust=args.robust, robust_scale=args.robust_scale,
                             indefinite_information=args.indefinite_information, **given)
    out = Path(args.out)
    report = Path(args.report) if args.report else out.with_name(out.name + ".report")
    with OutputTransaction("posegraph", inputs={"graph": args.graph}, files={"--out": out},
                           folders={"--report": report}) as tx:
        with timer("read"):
            graph = read_g2o(args.graph)
        with timer("optimise"):
            res = optimize_pose_graph(graph, params)
        if res.user_error:  # the graph leaves a vertex unconstrained: the user's input, nothing written
            raise InputError(res.reason)
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
