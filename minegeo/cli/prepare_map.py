"""``minegeo prepare-map``: downsample a prior map and compute its normals and FPFH once.

Writes the prepared map (``.npz``, no pickles: arrays + JSON metadata with format version,
parameters and their hash, the map's georeferencing and SHA-256) and ``<out>.json`` (a short
record with timings and versions). ``minegeo localize --map PREPARED.npz`` then only pays for
the scan; asking it for other parameters than the file's is an error.
"""

from __future__ import annotations

import time
from pathlib import Path

HELP = "prepare a prior map for localization once (downsample, normals, FPFH -> .npz)"


def add_arguments(parser) -> None:
    parser.add_argument("--map", required=True, help="map point cloud (georeferenced map_geo.ply with sidecar, or plain)")
    parser.add_argument("--out", required=True, help="prepared map to write (.npz)")
    from minegeo.cli.localize import add_profile_arguments

    add_profile_arguments(parser)
    parser.add_argument("--icp-voxel", type=float, default=0.1,
                        help="voxel of the ICP target copy of the map, m (default 0.1; 0 = every point)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")


def run(args) -> int:
    from dataclasses import replace

    from minegeo._output import OutputTransaction
    from minegeo._provenance import input_record, sha256_file, versions, write_json_atomic
    from minegeo.cli._common import StepBar, summary_lines_quiet, time_line, whole_run_timings
    from minegeo.cli.localize import DEFAULT_PROFILE, params_from_args
    from minegeo.errors import InputError
    from minegeo.localize.prepared import load_map_cloud, prepare_map

    out = Path(args.out)
    if not out.name.lower().endswith(".npz"):
        raise InputError(f"--out must end in .npz, got {out.name}")
    if not Path(args.map).exists():
        raise InputError(f"--map {args.map} does not exist")
    prep, _ = params_from_args(argparse_defaults(args))
    if args.octree_level is not None:
        prep = replace(prep, voxel_size_m=None, octree_level=int(args.octree_level))
    icp_voxel = None if args.icp_voxel is not None and args.icp_voxel <= 0 else args.icp_voxel
    prep = replace(prep, icp_voxel_size_m=icp_voxel)
    record = out.with_name(out.name + ".json")
    report = out.with_name(out.name + ".report.html")
    profile = getattr(args, "profile", None) or DEFAULT_PROFILE
    with OutputTransaction("prepare-map", inputs={"--map": args.map},
                           files={"--out": out, "its record": record, "its report": report}, overwrite_files=bool(args.force)) as tx, \
            StepBar(args, "prepare-map", total=1 + 1 + 4 + 6 + 1) as bar, summary_lines_quiet():
        t0 = time.perf_counter()
        bar("read map")
        cloud, g = load_map_cloud(args.map)
        t_read = time.perf_counter() - t0
        bar("SHA-256 of the map file")
        t0 = time.perf_counter()
        source = {"path": str(args.map), "sha256": sha256_file(args.map), "n_points": len(cloud.points),
                  "georeferenced": g is not None}
        t_hash = time.perf_counter() - t0
        pm = prepare_map(cloud, prep, georef=g, source=source, progress=bar)
        # the search structures every localization would otherwise build (those of levelled scans'
        # whole-map search included) are stored in the file too
        _, lp = params_from_args(argparse_defaults(args))
        lp = replace(lp, ransac=replace(lp.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0))
        index_s = pm.build_indexes(lp, progress=lambda name: bar(f"search structure {name}"))
        bar("write")
        t0 = time.perf_counter()
        pm.save(tx.file("--out"))
        t_save = time.perf_counter() - t0
        rec = {"status": "ok", "out": str(out), "profile": profile, "n_points": len(cloud.points), "n_down": len(pm),
               "n_icp_points": int(pm.icp_points.shape[0]), "params": prep, "params_hash": pm.params_hash,
               "crs": pm.crs, "georeferenced": g is not None, "work_origin": pm.work_origin,
               "timings_s": {"read": t_read, "sha256": t_hash, **pm.timings_s, "search_structures": index_s,
                             "write": t_save, **whole_run_timings(args)},
               "inputs": [input_record(args.map)],
               "versions": versions()}
        write_json_atomic(tx.file("its record"), rec)
        from minegeo._provenance import to_jsonable
        from minegeo.report.prepare_report import write_prepare_report

        write_prepare_report(tx.file("its report"), to_jsonable(rec), pm.points_map())
    if not getattr(args, "quiet", False):
        # measured after the commit, from the start of the process: the time the user waited
        rt = whole_run_timings(args)
        pt = rec["timings_s"]
        steps = (f"read {t_read:.1f} s, SHA-256 {t_hash:.1f} s, downsample + normals + FPFH + ICP target {pt.get('total', 0.0):.1f} s, "
                 f"search structures {sum(index_s.values()):.1f} s, write {t_save:.1f} s")
        print(f"prepared {args.map} (profile {profile}): {len(cloud.points)} -> {len(pm)} points ({prep.describe()}), "
              f"{pm.icp_points.shape[0]} ICP points; wrote {out}, {record.name}, {report.name}")
        print(f"  {time_line(rt)}; {steps}")
    return 0


def argparse_defaults(args):
    """The localize option namespace that ``params_from_args`` expects (voxel only)."""
    import argparse

    return argparse.Namespace(profile=args.profile, voxel=args.voxel, octree_level=None, icp=None, ransac_runs=1,
                              ransac_max_iterations=None, no_mutual_filter=False)
