"""``minegeo prepare-map``: downsample a prior map and compute its normals and FPFH once.

Writes the prepared map (``.npz``, no pickles: arrays + JSON metadata with format version,
parameters and their hash, the map's georeferencing and SHA-256) and ``<out>.json`` (a short
record with timings and versions). ``minegeo localize --map PREPARED.npz`` then only pays for
the scan; asking it for other parameters than the file's is an error.

The map is read in chunks (``--chunk-points``), twice (bounds, then downsampling), so memory is
the downsampled map plus one chunk whatever the map's size; ``--max-memory-gb`` sets a ceiling on
the estimated peak (:func:`minegeo.localize.prepared.prepare_map_file`).
"""

from __future__ import annotations

import time
from pathlib import Path

from minegeo.cli._argtypes import nonnegative_float, positive_float, positive_int

HELP = "prepare a prior map for localization once (downsample, normals, FPFH -> .npz)"


def add_arguments(parser) -> None:
    parser.add_argument("--map", required=True, help="map point cloud (georeferenced map_geo.ply with sidecar, or plain)")
    parser.add_argument("--out", required=True, help="prepared map to write (.npz)")
    from minegeo.cli.localize import add_profile_arguments

    add_profile_arguments(parser)
    parser.add_argument("--icp-voxel", type=nonnegative_float, default=0.1,
                        help="voxel of the ICP target copy of the map, m (default 0.1; 0 = every point)")
    parser.add_argument("--chunk-points", type=positive_int, default=None,
                        help="points read per chunk (default 2097152); the map is read twice in chunks "
                             "(bounds, then downsampling), so memory is the downsampled map plus one chunk")
    parser.add_argument("--max-memory-gb", type=positive_float, default=None,
                        help="ceiling on the estimated peak memory, GB: the chunk shrinks to fit, and the run stops "
                             "with an error (exit 2) before exceeding it (default: no ceiling)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")


def run(args) -> int:
    from dataclasses import replace

    from minegeo._output import OutputTransaction
    from minegeo._provenance import (
        arguments_provenance,
        input_record,
        sha256_file,
        versions,
        write_json_atomic,
    )
    from minegeo.cli._common import StepBar, summary_lines_quiet, time_line, whole_run_timings
    from minegeo.cli.localize import DEFAULT_PROFILE, params_from_args
    from minegeo.errors import InputError
    from minegeo.localize.prepared import is_georeferenced, prepare_map_file

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
    if args.chunk_points is not None and args.chunk_points < 1:
        raise InputError(f"--chunk-points must be a positive integer, got {args.chunk_points}")
    if args.max_memory_gb is not None and not args.max_memory_gb > 0:
        raise InputError(f"--max-memory-gb must be a positive number, got {args.max_memory_gb}")
    if icp_voxel is None and args.max_memory_gb is not None:
        raise InputError("--icp-voxel 0 keeps every map point in memory and cannot be read in chunks: "
                         "give --icp-voxel > 0 or drop --max-memory-gb")
    record = out.with_name(out.name + ".json")
    report = out.with_name(out.name + ".report.html")
    profile = getattr(args, "profile", None) or DEFAULT_PROFILE
    with OutputTransaction("prepare-map", inputs={"--map": args.map},
                           files={"--out": out, "its record": record, "its report": report}, overwrite_files=bool(args.force)) as tx, \
            StepBar(args, "prepare-map", total=1 + 1 + 4 + 6 + 1) as bar, summary_lines_quiet():
        t0 = time.perf_counter()
        bar("SHA-256 of the map file")
        source = {"path": str(args.map), "sha256": sha256_file(args.map), "georeferenced": is_georeferenced(Path(args.map))}
        t_hash = time.perf_counter() - t0
        with ByteBar(args) as bytes_bar:
            pm = prepare_map_file(args.map, prep, chunk_points=args.chunk_points, max_memory_gb=args.max_memory_gb,
                                  source=source, progress=bar, read_progress=bytes_bar)
        n_points = int(pm.source["n_points"])
        g = pm.georef
        t_read = pm.timings_s.get("downsample", 0.0) + pm.source["streaming"]["bounds_pass_s"]
        # the search structures every localization would otherwise build (those of levelled scans'
        # whole-map search included) are stored in the file too
        _, lp = params_from_args(argparse_defaults(args))
        lp = replace(lp, ransac=replace(lp.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0))
        index_s = pm.build_indexes(lp, progress=lambda name: bar(f"search structure {name}"))
        bar("write")
        t0 = time.perf_counter()
        pm.save(tx.file("--out"))
        t_save = time.perf_counter() - t0
        rec = {"verb": "prepare-map", "status": "ok", "out": str(out), "profile": profile, "n_points": n_points, "n_down": len(pm),
               "n_icp_points": int(pm.icp_points.shape[0]), "params": prep, "params_hash": pm.params_hash,
               "crs": pm.crs, "georeferenced": g is not None, "work_origin": pm.work_origin,
               "streaming": pm.source["streaming"],
               "timings_s": {"read": t_read, "sha256": t_hash, **pm.timings_s, "search_structures": index_s,
                             "write": t_save, **whole_run_timings(args)},
               "inputs": [input_record(args.map)],
               "versions": versions(), "provenance": arguments_provenance()}
        write_json_atomic(tx.file("its record"), rec)
        from minegeo._provenance import to_jsonable
        from minegeo.report.prepare_report import write_prepare_report

        write_prepare_report(tx.file("its report"), to_jsonable(rec), pm.points_map())
    if not getattr(args, "quiet", False):
        # measured after the commit, from the start of the process: the time the user waited
        rt = whole_run_timings(args)
        pt = rec["timings_s"]
        steps = (f"read + downsample (2 chunked passes) {t_read:.1f} s, SHA-256 {t_hash:.1f} s, normals + FPFH + ICP target {pt.get('total', 0.0) - t_read:.1f} s, "
                 f"search structures {sum(index_s.values()):.1f} s, write {t_save:.1f} s")
        print(f"prepared {args.map} (profile {profile}): {n_points} -> {len(pm)} points ({prep.describe()}), "
              f"{pm.icp_points.shape[0]} ICP points; wrote {out}, {record.name}, {report.name}")
        print(f"  {time_line(rt)}; {steps}")
    return 0


class ByteBar:
    """A tqdm bar of the bytes read by the two chunked passes over the map (stderr; off with
    ``--quiet`` or when stderr is not a terminal, like :class:`~minegeo.cli._common.StepBar`).
    Called as ``bar(pass_number, bytes_read, size_bytes)``."""

    def __init__(self, args):
        from minegeo._output import progress_enabled

        self._bar = None
        self._enabled = progress_enabled(args)

    def __call__(self, pass_no: int, done: int, size: int) -> None:
        if not self._enabled:
            return
        if self._bar is None:
            import sys

            from tqdm import tqdm

            self._bar = tqdm(total=2 * size, desc="read map", unit="B", unit_scale=True, file=sys.stderr, leave=False,
                             dynamic_ncols=True, position=1)
        self._bar.set_description_str(f"read map (pass {pass_no}/2: {'bounds' if pass_no == 1 else 'downsample'})")
        self._bar.update((pass_no - 1) * size + done - self._bar.n)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        return False


def argparse_defaults(args):
    """The localize option namespace that ``params_from_args`` expects (voxel only)."""
    import argparse

    return argparse.Namespace(profile=args.profile, voxel=args.voxel, octree_level=None, icp=None, ransac_runs=1,
                              ransac_max_iterations=None, no_mutual_filter=False)
