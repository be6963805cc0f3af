"""``minegeo info FILE``: what a file holds, told from its content, and a summary of it.

:func:`detect_kind` looks at the first bytes of the file (never its name alone): a point cloud
(PLY, PCD, LAS/LAZ, E57, zip, xyz text), control points (a CSV header naming ``id x y z E N H``),
a trajectory (TUM: 8 numbers a line with a unit quaternion and rising times; KITTI: 12 with an
orthonormal rotation; CSV/GeoSLAM: a header naming the quaternion), a g2o pose graph
(``VERTEX_*`` / ``EDGE_*`` records), a prepared map or an intersection base (``.npz`` archives
told apart by their members), a minegeo ``result.json``, control/check stations of a SLAM run (header
``id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role``), a ROS bag (a ROS 1 ``.bag``, a ROS 2 bag
folder or ``.mcap``/``.db3`` file: topics with type, count, rate, time span, PointCloud2 fields and
time field) or an IMU CSV (header ``t,gx,gy,gz,ax,ay,az``). ``--kind`` forces the kind. For a point
cloud it prints format, point count, bounds, attributes with dtypes, CRS, recorded origin, the
per-point time field and the span of its offsets; for
the other kinds their own summary; always the file size and SHA-256. ``--json OUT`` also writes
the summary with provenance (versions, input hash) atomically. A file that cannot be read gives
one line on stderr and exit 2.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HELP = ("tell what a file holds (point cloud, control points, trajectory, g2o pose graph, prepared map, "
        "intersection base, result.json, ROS bag, IMU CSV, stations CSV) and summarise it: counts, bounds, attributes, CRS, "
        "topics, times")

_TRAJ_SUFFIXES = (".tum", ".kitti")
#: ``--kind`` values (``auto``: :func:`detect_kind`).
KINDS = ("auto", "cloud", "gcp", "trajectory", "posegraph", "prepared_map", "intersection_base", "result", "bag",
         "imu", "stations")
#: What each kind is called in the printout.
KIND_TEXT = {
    "cloud": "point cloud",
    "gcp": "control points (GCP CSV)",
    "trajectory": "trajectory",
    "posegraph": "pose graph (g2o)",
    "prepared_map": "prepared map (minegeo prepare-map)",
    "intersection_base": "intersection base (minegeo intersections build)",
    "result": "minegeo result record (result.json)",
    "bag": "ROS bag",
    "imu": "IMU samples (IMU CSV)",
    "stations": "control and check stations (stations CSV)",
}
#: header names that mark an IMU CSV (t,gx,gy,gz,ax,ay,az)
_IMU_NAMES = {"gx", "gy", "gz", "ax", "ay", "az"}
#: Bytes read to tell the kind.
_SNIFF_BYTES = 65536
_TRAJ_FORMATS = ("tum", "kitti", "geoslam")


def add_arguments(parser) -> None:
    parser.add_argument("file", metavar="FILE", help="point cloud (ply pcd las laz xyz txt csv pts 3d e57 zip), "
                        "trajectory (TUM, KITTI, CSV), GCP CSV, g2o pose graph, prepared map or intersection base "
                        "(.npz), result.json, ROS bag (.bag file or ROS 2 folder), IMU CSV, stations CSV")  # fmt: skip
    parser.add_argument("--format", default=None, help="file format if the suffix does not tell (e.g. pcd, tum)")
    parser.add_argument(
        "--kind",
        choices=KINDS,
        default="auto",
        help="what the file holds (default auto: told from the content); a value forces it",
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


def _sniff_head(path: Path) -> bytes | None:
    """The first :data:`_SNIFF_BYTES` of a regular file, else None (a FIFO or device is never
    opened here: the reader of the kind refuses it)."""
    import os
    import stat

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        with open(path, "rb") as fh:
            return fh.read(_SNIFF_BYTES)
    except OSError:
        return None


def _npz_kind(path: Path) -> str | None:
    """``prepared_map`` / ``intersection_base`` from the member names of an ``.npz`` archive."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (OSError, zipfile.BadZipFile, ValueError):
        return None
    if {"meta.npy", "points.npy", "features.npy", "icp_points.npy"} <= names:
        return "prepared_map"
    if {"meta.npy", "cloud_points.npy", "invariant_points.npy"} <= names:
        return "intersection_base"
    return None


def _numbers(line: str) -> list[float] | None:
    """The numbers of a text line (comma, semicolon or white space), or None if one is not a number."""
    delim = "," if "," in line else (";" if ";" in line else None)
    toks = [t.strip() for t in line.split(delim)] if delim else line.split()
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        return None
    return vals if vals and all(np.isfinite(vals)) else None


def _numeric_trajectory(rows: list[list[float]]) -> str | None:
    """``tum`` when every row has 8 numbers, rising times and a unit quaternion (|q| within 1e-3
    of 1); ``kitti`` when every row has 12 numbers whose 3x3 rotation is orthonormal (1e-3)."""
    n = len(rows[0])
    if any(len(r) != n for r in rows):
        return None
    A = np.asarray(rows, dtype=np.float64)
    if n == 8:
        q = np.linalg.norm(A[:, 4:8], axis=1)
        if np.all(np.abs(q - 1.0) < 1e-3) and np.all(np.diff(A[:, 0]) > 0):
            return "tum"
    if n == 12:
        R = A.reshape(-1, 3, 4)[:, :, :3]
        err = np.abs(np.einsum("kji,kjl->kil", R, R) - np.eye(3)).max()
        if err < 1e-3:
            return "kitti"
    return None


def _text_kind(path: Path, head: bytes) -> tuple[str, str | None, str]:
    """Kind, format hint and why, from the first lines of a text file."""
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    lines = text.splitlines()
    if len(head) == _SNIFF_BYTES and lines:
        lines = lines[:-1]  # the last line may be cut
    body = [ln.strip() for ln in lines if ln.strip() and not ln.strip().startswith(("#", "//"))]
    if not body:
        return "cloud", None, "no data lines"
    first = body[0]
    if first.startswith("{"):
        return "result", None, "a JSON object"
    word = first.split()[0].upper()
    if word.startswith(("VERTEX_SE", "EDGE_SE")) or word == "FIX":
        return "posegraph", None, f"g2o records ({word})"
    if _numbers(first) is None:  # a header line
        delim = "," if "," in first else (";" if ";" in first else ("\t" if "\t" in first else None))
        names = [t.strip().lower() for t in (first.split(delim) if delim else first.split())]
        from minegeo.io.gcp import is_gcp_header
        from minegeo.io.stations import is_stations_header

        if is_stations_header(names) or {"t_start", "t_end"} <= set(names):
            return "stations", None, "a header naming id, t_start, t_end, E N H, sigmas and role"
        if is_gcp_header(names):
            return "gcp", None, "a header naming id, local x y z and E N H"
        if "qw" in names or "q0" in names:
            return "trajectory", None, "a header naming a quaternion"
        if set(names) & _IMU_NAMES and not {"x", "y", "z"} <= set(names):
            return "imu", None, "a header naming gyro/accelerometer columns"
        return "cloud", None, "a header without quaternion or control-point columns"
    rows = []
    for ln in body[:200]:
        r = _numbers(ln)
        if r is None:
            break
        rows.append(r)
    fmt = _numeric_trajectory(rows)
    if fmt == "tum":
        return "trajectory", "tum", "8 numbers a line: rising times and unit quaternions (TUM)"
    if fmt == "kitti":
        return "trajectory", "kitti", "12 numbers a line: orthonormal rotations (KITTI)"
    return "cloud", None, f"{len(rows[0]) if rows else 0} numbers a line"


def detect_kind(path) -> tuple[str, str | None, str]:
    """What a file holds, from its content: ``(kind, format hint or None, why)``.

    ``kind`` is one of :data:`KINDS` (not ``auto``). Binary signatures first (PLY, PCD, LAS,
    E57, zip/npz: a prepared map or an intersection base by its members, else a zipped cloud),
    then the first data lines of a text file (:func:`_text_kind`). A file that is not regular
    (FIFO, device) or unreadable is called a point cloud by its name (``.tum``/``.kitti``: a
    trajectory), and its reader gives the error.
    """
    p = Path(path)
    from minegeo.io.bag import bag_kind

    bk = bag_kind(p)
    if bk is not None:
        return "bag", None, {"ros1": "ROS 1 bag signature", "ros2": "a ROS 2 bag folder (metadata.yaml)",
                             "ros2-mcap": "MCAP signature", "ros2-sqlite3": "a ROS 2 sqlite3 storage file"}[bk]
    head = _sniff_head(p)
    if head is None or not head:
        if p.suffix.lower() in _TRAJ_SUFFIXES:
            return "trajectory", None, "its suffix"
        return "cloud", None, "its suffix" if head is None else "an empty file"
    if head.startswith(b"PK\x03\x04"):
        k = _npz_kind(p)
        return (k, None, "its archive members") if k else ("cloud", None, "a zip archive")
    for magic, fmt in ((b"ply", "PLY"), (b"LASF", "LAS"), (b"ASTM-E57", "E57")):
        if head.startswith(magic):
            return "cloud", None, f"{fmt} signature"
    if head.lstrip().startswith((b"# .PCD", b"VERSION")) or b"\nDATA " in head[:4096]:
        return "cloud", None, "PCD header"
    if b"\x00" in head[:4096]:
        return "cloud", None, "binary content"
    if p.suffix.lower() in _TRAJ_SUFFIXES:
        return "trajectory", None, "its suffix"
    return _text_kind(p, head)


def _posegraph_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.io.g2o import read_g2o

    g = read_g2o(path)
    pos = g.poses[:, :-1, -1]
    return {"path": str(path), "kind": "posegraph", "pose_type": g.kind, "vertices": g.n_vertices,
            "edges": g.n_edges, "fixed": list(g.fixed), "chained_vertices": len(g.chained_ids),
            "bounds_min": pos.min(axis=0).tolist() if len(pos) else None,
            "bounds_max": pos.max(axis=0).tolist() if len(pos) else None,
            "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _prepared_map_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.localize.prepared import PreparedMap, profile_name

    pm = PreparedMap.load(path)
    P = pm.points_map()
    return {"path": str(path), "kind": "prepared_map", "points": len(pm), "icp_points": int(pm.icp_points.shape[0]),
            "profile": profile_name(pm.params) or "values of no profile (e.g. --voxel)",
            "voxel_size_m": pm.params.voxel_size_m, "crs": pm.crs, "work_origin": pm.work_origin.tolist(),
            "bounds_min_map": P.min(axis=0).tolist(), "bounds_max_map": P.max(axis=0).tolist(),
            "params_hash": pm.params_hash, "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _intersection_base_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.semantic.knowledge import IntersectionKB

    kb = IntersectionKB.load(path)
    return {"path": str(path), "kind": "intersection_base", "intersections": len(kb), "status": kb.status,
            "reason": kb.reason, "crs": (kb.georef or {}).get("crs"),
            "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _result_info(path: Path) -> dict:
    """A minegeo result record: its status and reason (never a position: see its report)."""
    from minegeo._provenance import sha256_file
    from minegeo.errors import FileFormatError
    from minegeo.io.jsonio import MAX_JSON_BYTES, load_json_text
    from minegeo.io.limits import read_file_bytes

    raw = read_file_bytes(path, max_bytes=MAX_JSON_BYTES, what="result.json")
    d = load_json_text(raw, path, allow_nonfinite=True)  # minegeo writes inf radii as Infinity
    if not isinstance(d, dict) or not ({"status", "verb", "provenance", "versions"} & set(d)):
        raise FileFormatError(path, "a JSON file but not a minegeo result record (no status, verb or provenance)")
    return {"path": str(path), "kind": "result", "verb": d.get("verb"), "status": d.get("status"),
            "reason": d.get("reason"), "profile": d.get("profile"), "crs": d.get("crs"), "seed": d.get("seed"),
            "inputs": [i.get("path") for i in d.get("inputs") or [] if isinstance(i, dict)],
            "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _bag_info(path: Path) -> dict:
    from minegeo.io.bag import bag_summary

    return bag_summary(path)


def _imu_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.io.imu import read_imu_csv

    imu = read_imu_csv(path)
    t = imu.t_s
    dt = np.diff(t)
    return {"path": str(path), "kind": "imu", "samples": len(imu), "frame": imu.frame,
            "time_start_s": float(t[0]), "time_end_s": float(t[-1]), "duration_s": float(t[-1] - t[0]),
            "rate_hz": imu.rate_hz, "largest_gap_s": float(dt.max()) if dt.size else None,
            "gyro_rad_s_mean": imu.gyro_rad_s.mean(axis=0).tolist(),
            "accel_m_s2_mean": imu.accel_m_s2.mean(axis=0).tolist(),
            "accel_norm_m_s2_median": float(np.median(np.linalg.norm(imu.accel_m_s2, axis=1))),
            "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _stations_info(path: Path) -> dict:
    from minegeo._provenance import sha256_file
    from minegeo.io.stations import read_stations

    st = read_stations(path)
    enh = st.enh
    ctrl = st.is_control
    dwell = st.t_end_s - st.t_start_s
    return {"path": str(path), "kind": "stations", "stations": len(st), "control": int(ctrl.sum()),
            "check": int((~ctrl).sum()), "ids": list(st.ids), "control_ids": [i for i, c in zip(st.ids, ctrl, strict=True) if c],
            "check_ids": [i for i, c in zip(st.ids, ctrl, strict=True) if not c], "crs": st.crs,
            "origin_enh": st.origin_enh.tolist(),
            "bounds_min": enh.min(axis=0).tolist(), "bounds_max": enh.max(axis=0).tolist(),
            "time_start_s": float(st.t_start_s.min()), "time_end_s": float(st.t_end_s.max()),
            "dwell_s_min": float(dwell.min()), "dwell_s_max": float(dwell.max()),
            "sigma_h_m_median": float(np.median(st.sigma_h_m)), "sigma_v_m_median": float(np.median(st.sigma_v_m)),
            "size_bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _print_bag(info: dict) -> None:
    print(f"file      {info['path']}")
    print(f"format    {info['bag_format']}")
    print(f"messages  {info['messages']:,} on {len(info['topics'])} topic(s) (times: log/record time, s)")
    for t in info["topics"]:
        rate = f"{t['rate_hz']:.3f} Hz" if t["rate_hz"] else "-"
        span = (f"{t['t_start_s']:.6f} .. {t['t_end_s']:.6f} s ({t['t_end_s'] - t['t_start_s']:.3f} s)"
                if t["t_start_s"] is not None else "no messages")
        print(f"  {t['name']}  {t['msgtype']}  {t['count']:,} msgs  {rate}  {span}")
        if t["frame_id"] is not None:
            print(f"    frame_id {t['frame_id']!r}")
        if t["fields"]:
            print("    fields   " + " ".join(f"{n}:{d}@{o}" + (f"x{c}" if c != 1 else "") for n, d, o, c in t["fields"]))
            tf = t["time_field"]
            print("    time     " + (f"per-point field {tf!r} (offsets from the header stamp)" if tf else
                                     "no per-point time field (time, t, timestamp, offset_time)"))
    print(f"size      {info['size_bytes']:,} bytes")
    print(f"sha256    {info['sha256']}")


def _print_e57_scans(meta: dict) -> None:
    """The scans of an E57 file and their poses (scan frame -> file frame)."""
    from minegeo.io import matrix_to_quat

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
    pt = info.get("point_times")
    if pt:
        if pt["min_s"] is None:
            print(f"times     field {pt['field']!r} ({pt['dtype']}): {pt['problem']}")
        else:
            print(f"times     field {pt['field']!r} ({pt['dtype']}, {pt['encoding']}): {pt['min_s']:.9g} .. "
                  f"{pt['max_s']:.9g} s (span {pt['span_s']:.6g} s)")
            if pt["problem"]:
                print(f"          warning: {pt['problem']}")
    print(f"size      {info['size_bytes']:,} bytes")
    print(f"sha256    {info['sha256']}")


def resolve_kind(path: Path, kind: str, fmt: str | None) -> tuple[str, str | None, str]:
    """``(kind, format, how it was told)``: ``--kind`` when given; with ``--format`` a trajectory
    format (tum, kitti, geoslam) means a trajectory and any other a point cloud; else
    :func:`detect_kind`."""
    if kind != "auto":
        return kind, fmt, "--kind"
    if fmt is not None:
        return ("trajectory" if str(fmt).lower() in _TRAJ_FORMATS else "cloud"), fmt, "--format"
    k, f, why = detect_kind(path)
    return k, f, f"detected: {why}"


_READERS = {"gcp": _gcp_info, "posegraph": _posegraph_info, "prepared_map": _prepared_map_info,
            "intersection_base": _intersection_base_info, "result": _result_info, "bag": _bag_info,
            "imu": _imu_info, "stations": _stations_info}


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
    kind, fmt, how = resolve_kind(path, args.kind, args.format)
    if kind == "cloud":
        info = cloud_info(path, format=fmt)
        info["kind"] = "cloud"
    elif kind == "trajectory":
        info = _trajectory_info(path, fmt)
    else:
        info = _READERS[kind](path)
    info["kind_text"] = f"{KIND_TEXT[kind]} ({how})"
    if args.json != "-":
        print(f"{'kind':<14} {info['kind_text']}")
        if kind == "cloud":
            _print_cloud(info)
        elif kind == "bag":
            _print_bag(info)
        else:
            for k, v in info.items():
                if k not in ("ids", "kind", "kind_text"):
                    print(f"{k:<14} {'-' if v is None else v}")
    if args.json:
        doc = {
            "verb": "info",
            "parameters": {"file": str(path), "format": args.format, "kind": kind, "kind_asked": args.kind},
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
