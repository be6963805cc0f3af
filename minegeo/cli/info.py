"""``minegeo info FILE``: what is in a point-cloud, trajectory or control-point file.

Prints format, point count, bounds, attributes with dtypes, CRS, recorded origin, file
size and SHA-256. ``--json OUT`` also writes the summary with provenance (versions,
input hash) atomically. A file that cannot be read gives one line on stderr and exit 2.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HELP = "summarise a point-cloud / trajectory / control-point file: counts, bounds, attributes, CRS"

_TRAJ_SUFFIXES = (".tum", ".kitti")


def add_arguments(parser) -> None:
    parser.add_argument("file", metavar="FILE", help="point cloud (ply pcd las laz xyz txt csv pts 3d e57 zip), "
                        "trajectory (--kind trajectory) or GCP CSV (--kind gcp)")  # fmt: skip
    parser.add_argument("--format", default=None, help="file format if the suffix does not tell (e.g. pcd, tum)")
    parser.add_argument(
        "--kind",
        choices=("auto", "cloud", "trajectory", "gcp"),
        default="auto",
        help="what the file holds (default: point cloud, or trajectory for .tum/.kitti)",
    )
    parser.add_argument("--json", metavar="OUT", default=None, help="also write the summary as JSON ('-' = stdout)")


def _fmt_vec(v) -> str:
    return "(" + ", ".join(f"{x:.4f}" for x in v) + ")" if v is not None else "-"


def _trajectory_info(path: Path, fmt) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.io.trajectory import read_trajectory

    tr = read_trajectory(path, format=fmt)
    pos = tr.positions + tr.origin
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1) if len(tr) > 1 else np.zeros(0)
    return {
        "path": str(path),
        "kind": "trajectory",
        "poses": len(tr),
        "time_start_s": float(tr.times_s[0]),
        "time_end_s": float(tr.times_s[-1]),
        "duration_s": float(tr.times_s[-1] - tr.times_s[0]),
        "length_m": float(steps.sum()),
        "bounds_min": pos.min(axis=0).tolist(),
        "bounds_max": pos.max(axis=0).tolist(),
        "crs": tr.crs,
        "size_bytes": path.stat().st_size,
        "sha256": sha256_file(path),
    }


def _gcp_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.io.gcp import read_gcps

    g = read_gcps(path)
    return {
        "path": str(path),
        "kind": "gcp",
        "points": len(g),
        "ids": g.ids,
        "crs": g.crs,
        "bounds_min": g.crs_enh.min(axis=0).tolist(),
        "bounds_max": g.crs_enh.max(axis=0).tolist(),
        "local_bounds_min": g.local_xyz.min(axis=0).tolist(),
        "local_bounds_max": g.local_xyz.max(axis=0).tolist(),
        "sigma_enh_m_median": np.median(g.sigma_enh_m, axis=0).tolist(),
        "size_bytes": path.stat().st_size,
        "sha256": sha256_file(path),
    }


def _print_e57_scans(meta: dict) -> None:
    """The scans of an E57 file and their poses (scan frame -> file frame)."""
    from minegeo.io._quat import matrix_to_quat

    scans = meta["e57_scans"]
    extra = f"; {meta['e57_invalid_dropped']:,} invalid returns dropped" if meta.get("e57_invalid_dropped") else ""
    print(f"scans     {len(scans)} (points merged into the file frame by each scan's pose{extra})")
    for s in scans:
        T = np.asarray(s["T_file_scan"], dtype=np.float64)
        q = matrix_to_quat(T[:3, :3], order="wxyz", atol=1e-3)
        print(f"  #{s['index']} {s['name']!r}: {s['points']:,} points ({s['coordinates']}), position "
              f"{_fmt_vec(T[:3, 3])}, rotation wxyz ({', '.join(f'{v:.6f}' for v in q)}), guid {s['guid']}")


def _print_cloud(info: dict) -> None:
    print(f"file      {info['path']}")
    enc = f" ({info['encoding']})" if info.get("encoding") else ""
    print(f"format    {info['format']}{enc}")
    print(f"points    {info['points']:,}")
    print(f"min       {_fmt_vec(info['bounds_min'])}")
    print(f"max       {_fmt_vec(info['bounds_max'])}")
    print(f"extent    {_fmt_vec(info['extent'])}")
    print(f"units     {info['units']}")
    print(f"crs       {info['crs'] or 'none (local frame)'}")
    if any(info["recorded_origin"]) and "las_offset" not in info["metadata"]:
        print(f"origin    {_fmt_vec(info['recorded_origin'])} (recorded in the file)")
    meta = info["metadata"]
    if "las_scale" in meta:
        print(f"las       scale {meta['las_scale']} offset {meta['las_offset']} point format {meta['las_point_format']}")
    if "e57_scans" in meta:
        _print_e57_scans(meta)
    if info["attributes"]:
        print("fields")
        for k, a in info["attributes"].items():
            rng = ""
            if a.get("min") is not None:
                rng = f"  {a['min']:.6g} .. {a['max']:.6g}"
            print(f"  {k:<20} {a['dtype']:<8} {'x'.join(map(str, a['shape']))}{rng}")
    else:
        print("fields    x y z only")
    print(f"size      {info['size_bytes']:,} bytes")
    print(f"sha256    {info['sha256']}")


def run(args) -> int:
    from minegeo._output import OutputTransaction, check_outputs
    from minegeo._provenance import provenance, to_jsonable, write_json_atomic
    from minegeo.io.pointcloud import cloud_info

    path = Path(args.file)
    if not path.exists():
        raise FileNotFoundError(2, "no such file", str(path))
    out_json = args.json if args.json and args.json != "-" else None
    # an output never equals or lies inside an input: checked before the file is even read
    check_outputs({"FILE": path}, files={"--json": out_json})
    kind = args.kind
    if kind == "auto":
        kind = "trajectory" if path.suffix.lower() in _TRAJ_SUFFIXES else "cloud"
    if kind == "cloud":
        info = cloud_info(path, format=args.format)
        info["kind"] = "cloud"
    elif kind == "trajectory":
        info = _trajectory_info(path, args.format)
    else:
        info = _gcp_info(path)
    if args.json != "-":
        if kind == "cloud":
            _print_cloud(info)
        else:
            for k, v in info.items():
                if k != "ids":
                    print(f"{k:<14} {v}")
    if args.json:
        doc = {
            "verb": "info",
            "parameters": {"file": str(path), "format": args.format, "kind": kind},
            "result": info,
            "provenance": provenance(seed=None, origin=None, inputs=[{"path": str(path), "sha256": info["sha256"],
                                                                      "size_bytes": info["size_bytes"]}]),
        }  # fmt: skip
        if args.json == "-":
            json.dump(to_jsonable(doc), sys.stdout, indent=2)
            print()
        else:
            with OutputTransaction("info", inputs={"FILE": path}, files={"--json": out_json}) as tx:
                write_json_atomic(tx.file("--json"), doc)
            print(f"wrote     {args.json}")
    return 0
