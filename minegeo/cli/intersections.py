"""``minegeo intersections build --map MAP --out DB``: the intersection knowledge base of a prior map
(Liang et al. 2024, Sec. 3.2; ``docs/intersections.md``).

Writes ``DB`` (``.npz``), ``DB.json`` (result with provenance) and ``DB.html`` (plan view, similarity
matrices). A georeferenced map (``minegeo georef`` output with its sidecar) gives a base that carries
its CRS and origin. A map without intersections writes the base with status ``no_intersections`` and
exits 1 with the reason.
"""

from __future__ import annotations

import sys
from pathlib import Path

from minegeo._params import arg_type
from minegeo.cli._argtypes import int_in_range

#: the parameter classes whose field rules the options use (imported when an option is parsed)
_KB = "minegeo.semantic.knowledge:KBParams"
_SKELETON = "minegeo.semantic.skeleton:SkeletonParams"

HELP = "intersection knowledge base of a prior map (subcommand: build), for `minegeo track` (Liang et al. 2024)"


def add_arguments(parser) -> None:
    verb = parser.prog  # "minegeo intersections"

    class _ActionParser(type(parser)):
        """An action's parser: its one error line starts ``minegeo intersections: error:``, as the
        verb's other errors do (not ``minegeo intersections build: error:``)."""

        def error(self, message):  # noqa: D102 - argparse API
            self.exit(2, f"{verb}: error: {message} (see {self.prog} --help)\n")

    sub = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=_ActionParser, required=True)
    b = sub.add_parser("build", help="build the knowledge base of a map", description="build the intersection "
                       "knowledge base (invariant points, dense clouds, PWCV/CWC descriptors) of a prior map")
    b.add_argument("--map", required=True, help="prior map (PLY/PCD/LAS/XYZ, m, z up, one mine level); a "
                   "georeferenced map (with its .georef.json sidecar) gives a georeferenced base")
    b.add_argument("--out", required=True, help="knowledge base file (.npz)")
    b.add_argument("--report", default=None, help="report file (default: OUT.html)")
    b.add_argument("--json", default=None, help="result file (default: OUT.json)")
    b.add_argument("--cloud-radius", type=arg_type(_KB, "cloud_radius_m"), default=15.0, help="dense cloud radius per intersection "
                   "(m; default 15, at least the 12 m descriptor radius)")
    b.add_argument("--floor-cell", type=arg_type(_SKELETON, "floor_cell_m"), default=2.0, help="floor-height cell of the drift skeleton (m; "
                   "default 2); 1 for rough floors (bumps of 0.1 m RMS or more), see docs/intersections.md")
    b.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=0, help="recorded seed (the build draws no random numbers)")


def _read_map(path):
    """(points (n, 3) m, georef dict): a georeferenced map relative to its origin, else the file's points."""
    import numpy as np

    from minegeo.georef import load_georeferenced_map, sidecar_path
    from minegeo.io import read_point_cloud

    if sidecar_path(path).exists():
        cloud, geo = load_georeferenced_map(path)
        return cloud.points, {"crs": geo.crs, "origin_m": np.asarray(geo.origin, float).tolist()}
    cloud = read_point_cloud(path, origin="auto")
    o = np.asarray(cloud.origin if cloud.origin is not None else np.zeros(3), float)
    geo = {"crs": cloud.crs, "origin_m": o.tolist()} if (cloud.crs or np.any(o != 0)) else {}
    return cloud.points, geo


def run(args) -> int:
    from dataclasses import asdict, replace

    from minegeo._output import OutputTransaction, run_timings
    from minegeo._provenance import StageTimer, provenance, sha256_file, to_jsonable, write_json_atomic
    from minegeo.errors import InputError
    from minegeo.report.intersections_report import write_kb_report
    from minegeo.semantic import (
        DescriptorParams,
        KBParams,
        SkeletonParams,
        build_knowledge_base,
        similarity_matrix,
    )

    timer = StageTimer()
    out = Path(args.out)
    report = Path(args.report) if args.report else out.with_name(out.name + ".html")
    js = Path(args.json) if args.json else out.with_name(out.name + ".json")
    descriptor = DescriptorParams()
    if args.cloud_radius < descriptor.radius_m:
        raise InputError(f"--cloud-radius {args.cloud_radius:g} m is less than the descriptor radius "
                         f"({descriptor.radius_m:g} m): the dense cloud of an intersection must hold what its "
                         "descriptor saw, for the ICP verification of `minegeo track`")
    params = KBParams(SkeletonParams(floor_cell_m=args.floor_cell), descriptor, cloud_radius_m=args.cloud_radius)
    with OutputTransaction("intersections", inputs={"--map": args.map},
                           files={"--out": out, "--report": report, "--json": js}) as tx:
        with timer("read"):
            P, geo = _read_map(args.map)
        with timer("build"):
            kb = build_knowledge_base(P, params)
        kb = replace(kb, georef=geo)
        with timer("similarity"):
            S, M = (similarity_matrix(kb), similarity_matrix(kb, "cwc")) if len(kb) else (None, None)
        kb.save(tx.file("--out"))
        summary = {"command": "intersections build", "status": kb.status, "reason": kb.reason,
                   "parameters": to_jsonable(asdict(params)),
                   "inputs": {"map": str(args.map)},
                   "result": {"status": kb.status, "reason": kb.reason, "intersections": len(kb),
                              "map_points": int(P.shape[0]), "georef": geo,
                              "ids": kb.ids.tolist(), "degree": kb.degree.tolist(),
                              "invariant_points_m": kb.invariant_points.tolist(),
                              "clearance_m": kb.clearance_m.tolist(),
                              "similarity_pwcv": None if S is None else S.tolist(),
                              "similarity_cwc": None if M is None else M.tolist()},
                   "outputs": {"db": str(out), "report": str(report), "json": str(js)},
                   "timings_s": {**timer.as_dict(), **run_timings(args)},
                   "provenance": provenance(seed=args.seed, origin=geo.get("origin_m"),
                                            inputs=[{"path": str(args.map), "sha256": sha256_file(args.map)}])}
        write_json_atomic(tx.file("--json"), summary)
        write_kb_report(tx.file("--report"), summary, kb, S, M)
    if kb.status != "ok":
        print(f"minegeo intersections: {kb.status}: {kb.reason} (written: {out})", file=sys.stderr)
        return 1
    if not getattr(args, "quiet", False):
        print(f"{len(kb)} intersections (degrees {', '.join(map(str, kb.degree.tolist()))})"
              + (f", georeferenced ({geo.get('crs')})" if geo else ""))
        print(f"written: {out}, {js}, {report}")
    return 0
