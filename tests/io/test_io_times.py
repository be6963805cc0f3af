"""Per-point times of PLY/PCD/LAS frames (minegeo.io.times, read_points, read_frame, info).

The files are written here by hand (header text + NumPy bytes), not by minegeo's writers, so the
expected values are the ones written: float fields read back as float64 of the stored value,
unsigned integer fields as ``ns / 1e9``.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_extra

from minegeo.errors import FileFormatError
from minegeo.io.frames import read_frame
from minegeo.io.pointcloud import cloud_info, read_point_cloud, read_points
from minegeo.io.times import OFFSET_RANGE_S, TIME_FIELDS, TimedPoints

PLY_TYPES = {"f4": "float", "f8": "double", "u4": "uint", "u2": "ushort", "u1": "uchar", "i4": "int"}
PCD_TYPES = {"f4": ("F", 4), "f8": ("F", 8), "u4": ("U", 4), "u8": ("U", 8), "u2": ("U", 2), "u1": ("U", 1), "i4": ("I", 4)}


def _cloud(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-20, 20, size=(n, 3))


def _times(code: str, n: int, seed=1):
    """Stored time values of dtype ``code`` within a 0.1 s sweep (ns for unsigned integers)."""
    rng = np.random.default_rng(seed)
    if code[0] == "f":
        return rng.uniform(0.0, 0.1, n).astype(code)
    if code in ("u1", "u2"):
        return rng.integers(0, np.iinfo(code).max, n).astype(code)
    return rng.integers(0, 100_000_000, n).astype(code)


def write_ply(path, xyz, fields: dict, encoding="binary_little_endian"):
    """PLY with double x y z and the given (name -> array) properties."""
    cols = [("x", xyz[:, 0].astype("f8")), ("y", xyz[:, 1].astype("f8")), ("z", xyz[:, 2].astype("f8"))]
    cols += [(k, np.asarray(v)) for k, v in fields.items()]
    head = ["ply", f"format {encoding} 1.0", f"element vertex {len(xyz)}"]
    head += [f"property {PLY_TYPES[v.dtype.str[1:]]} {k}" for k, v in cols]
    head.append("end_header")
    data = ("\n".join(head) + "\n").encode()
    if encoding == "ascii":
        rows = [" ".join(repr(float(v[i])) if v.dtype.kind == "f" else str(int(v[i])) for _, v in cols)
                for i in range(len(xyz))]
        data += ("\n".join(rows) + "\n").encode()
    else:
        e = "<" if encoding == "binary_little_endian" else ">"
        rec = np.empty(len(xyz), dtype=[(k, e + v.dtype.str[1:]) for k, v in cols])
        for k, v in cols:
            rec[k] = v
        data += rec.tobytes()
    path.write_bytes(data)
    return path


def write_pcd(path, xyz, fields: dict, encoding="binary"):
    """PCD with F8 x y z and the given fields (``binary``: little-endian records; ``ascii``)."""
    cols = [("x", xyz[:, 0].astype("f8")), ("y", xyz[:, 1].astype("f8")), ("z", xyz[:, 2].astype("f8"))]
    cols += [(k, np.asarray(v)) for k, v in fields.items()]
    ts = [PCD_TYPES[v.dtype.str[1:]] for _, v in cols]
    head = ["VERSION 0.7", "FIELDS " + " ".join(k for k, _ in cols), "SIZE " + " ".join(str(s) for _, s in ts),
            "TYPE " + " ".join(t for t, _ in ts), "COUNT " + " ".join("1" for _ in cols), f"WIDTH {len(xyz)}",
            "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(xyz)}", f"DATA {encoding}"]
    data = ("\n".join(head) + "\n").encode()
    if encoding == "ascii":
        rows = [" ".join(repr(float(v[i])) if v.dtype.kind == "f" else str(int(v[i])) for _, v in cols)
                for i in range(len(xyz))]
        data += ("\n".join(rows) + "\n").encode()
    else:
        rec = np.empty(len(xyz), dtype=[(k, "<" + v.dtype.str[1:]) for k, v in cols])
        for k, v in cols:
            rec[k] = v
        data += rec.tobytes()
    path.write_bytes(data)
    return path


def expected_offsets(stored: np.ndarray) -> np.ndarray:
    """The contract: float = seconds, unsigned integer = nanoseconds (hand-written twin)."""
    if stored.dtype.kind == "f":
        return np.array([float(v) for v in stored])
    return np.array([int(v) / 1e9 for v in stored])


CASES = [(name, code) for name in TIME_FIELDS for code in ("f4", "f8", "u4")] + [("t", "u2"), ("time", "u1")]


@pytest.mark.parametrize("fmt,encoding", [("ply", "binary_little_endian"), ("ply", "binary_big_endian"),
                                          ("ply", "ascii"), ("pcd", "binary"), ("pcd", "ascii")])
@pytest.mark.parametrize("name,code", CASES)
def test_each_time_field_and_dtype(tmp_path, fmt, encoding, name, code):
    xyz = _cloud()
    stored = _times(code, len(xyz))
    f = tmp_path / f"frame.{fmt}"
    (write_ply if fmt == "ply" else write_pcd)(f, xyz, {"intensity": np.ones(len(xyz), "f4"), name: stored}, encoding)
    tp = read_points(f, with_times=True)
    assert isinstance(tp, TimedPoints)
    assert tp.time_field == name
    assert tp.time_encoding == ("seconds" if code[0] == "f" else "nanoseconds")
    np.testing.assert_array_equal(tp.t_offset_s, expected_offsets(stored))
    np.testing.assert_array_equal(tp.xyz, xyz)
    assert tp.t_abs_s is None and tp.t_offset_s.dtype == np.float64


def test_pcd_uint64_nanoseconds(tmp_path):
    xyz = _cloud()
    ns = np.arange(len(xyz), dtype=np.uint64) * np.uint64(2_500_000) + np.uint64(7)
    tp = read_points(write_pcd(tmp_path / "f.pcd", xyz, {"t": ns}), with_times=True)
    np.testing.assert_array_equal(tp.t_offset_s, [int(v) / 1e9 for v in ns])


def test_first_found_wins_by_the_contract_order(tmp_path):
    """``time`` before ``t`` before ``timestamp`` before ``offset_time``, whatever the file's order."""
    xyz = _cloud(10)
    a = np.full(10, 0.01, "f4")
    b = np.full(10, 5_000_000, "u4")
    c = np.full(10, 0.03, "f8")
    f = write_ply(tmp_path / "f.ply", xyz, {"offset_time": b, "timestamp": c, "t": a})
    tp = read_points(f, with_times=True)
    assert tp.time_field == "t"
    np.testing.assert_array_equal(tp.t_offset_s, np.full(10, float(np.float32(0.01))))
    f2 = write_ply(tmp_path / "g.ply", xyz, {"offset_time": b, "timestamp": c})
    assert read_points(f2, with_times=True).time_field == "timestamp"
    f3 = write_ply(tmp_path / "h.ply", xyz, {"offset_time": b})
    np.testing.assert_array_equal(read_points(f3, with_times=True).t_offset_s, np.full(10, 0.005))


def test_existing_callers_unchanged(tmp_path):
    """read_point_cloud still gives the stored attribute; read_points without times the array."""
    xyz = _cloud()
    ns = _times("u4", len(xyz))
    f = write_pcd(tmp_path / "f.pcd", xyz, {"t": ns})
    cloud = read_point_cloud(f)
    assert cloud.attributes["t"].dtype == np.uint32
    np.testing.assert_array_equal(cloud.attributes["t"], ns)
    pts = read_points(f)
    assert isinstance(pts, np.ndarray)
    np.testing.assert_array_equal(pts, xyz)
    np.testing.assert_array_equal(read_frame(f), xyz)


def test_no_time_field(tmp_path):
    f = write_ply(tmp_path / "f.ply", _cloud(), {"intensity": np.ones(40, "f4")})
    tp = read_points(f, with_times=True)
    assert tp.t_offset_s is None and tp.time_field is None and not tp.has_times
    assert cloud_info(f)["point_times"] is None


@pytest.mark.parametrize("bad,what", [(1.5, "outside"), (-0.02, "outside"), (np.nan, "NaN")])
def test_offsets_outside_the_sweep_name_the_file(tmp_path, bad, what):
    xyz = _cloud()
    t = _times("f8", len(xyz))
    t[17] = bad
    f = write_ply(tmp_path / "frame_000017.ply", xyz, {"time": t})
    with pytest.raises(FileFormatError) as ei:
        read_points(f, with_times=True)
    msg = str(ei.value)
    assert "frame_000017.ply" in msg and what in msg and "'time'" in msg
    with pytest.raises(FileFormatError, match="frame_000017.ply"):
        read_frame(f, with_times=True)
    read_point_cloud(f)  # the cloud itself is still readable
    pt = cloud_info(f)["point_times"]
    assert pt["field"] == "time" and what in pt["problem"]


def test_integer_nanoseconds_beyond_one_second_refused(tmp_path):
    """Ouster ``t`` in ns: 1.2e9 ns = 1.2 s is outside the sweep (a stamp in the wrong unit)."""
    ns = np.full(40, 1_200_000_000, "u4")
    f = write_pcd(tmp_path / "f.pcd", _cloud(), {"t": ns})
    with pytest.raises(FileFormatError, match="1.2 s"):
        read_points(f, with_times=True)


def test_range_bounds_are_inclusive(tmp_path):
    t = np.linspace(OFFSET_RANGE_S[0], OFFSET_RANGE_S[1], 40)
    tp = read_points(write_ply(tmp_path / "f.ply", _cloud(), {"time": t}), with_times=True)
    np.testing.assert_array_equal(tp.t_offset_s, t)


def test_signed_integer_time_refused(tmp_path):
    f = write_ply(tmp_path / "f.ply", _cloud(), {"t": np.zeros(40, "i4")})
    with pytest.raises(FileFormatError, match="int32"):
        read_points(f, with_times=True)


def test_dropped_points_drop_their_times(tmp_path):
    xyz = _cloud()
    xyz[5] = np.nan
    t = _times("f4", 40)
    f = write_pcd(tmp_path / "f.pcd", xyz, {"time": t})
    tp = read_points(f, with_times=True, drop_nonfinite=True)
    keep = np.arange(40) != 5
    np.testing.assert_array_equal(tp.xyz, xyz[keep])
    np.testing.assert_array_equal(tp.t_offset_s, expected_offsets(t[keep]))


def test_records_are_read_only(tmp_path):
    tp = read_points(write_ply(tmp_path / "f.ply", _cloud(), {"t": _times("f4", 40)}), with_times=True)
    with pytest.raises(ValueError):
        tp.t_offset_s[0] = 0.5
    with pytest.raises(AttributeError):
        tp.time_field = "x"


def test_info_reports_span(tmp_path):
    ns = np.array([0, 25_000_000, 99_000_000] * 10, dtype="u4")
    f = write_pcd(tmp_path / "f.pcd", _cloud(30), {"t": ns})
    pt = cloud_info(f)["point_times"]
    assert pt["field"] == "t" and pt["dtype"] == "uint32" and pt["problem"] is None
    assert pt["min_s"] == 0.0 and pt["max_s"] == 0.099 and pt["span_s"] == 0.099


def test_kitti_bin_has_no_times(tmp_path):
    f = tmp_path / "000000.bin"
    rec = np.zeros((5, 4), "<f4")
    rec[:, :3] = _cloud(5)
    f.write_bytes(rec.tobytes())
    tp = read_frame(f, with_times=True)
    assert tp.t_offset_s is None
    np.testing.assert_array_equal(tp.xyz, rec[:, :3].astype(np.float64))


def test_las_gps_time_absolute_and_frame_offsets(tmp_path):
    laspy = require_extra("laspy")
    xyz = _cloud()
    gps = 1_000_000.0 + np.linspace(0.0, 0.09, 40)
    hdr = laspy.LasHeader(point_format=1, version="1.2")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.gps_time = gps
    f = tmp_path / "frame.las"
    las.write(f)
    tp = read_points(f, with_times=True)
    assert tp.time_field == "gps_time" and tp.t_offset_s is None
    np.testing.assert_array_equal(tp.t_abs_s, gps)
    fr = read_frame(f, with_times=True, time_s=1_000_000.0)
    np.testing.assert_array_equal(fr.t_offset_s, gps - 1_000_000.0)
    with pytest.raises(FileFormatError, match="frame.las"):
        read_frame(f, with_times=True, time_s=999_990.0)  # 10 s before the points: not this frame's clock
    pt = cloud_info(f)["point_times"]
    assert pt["field"] == "gps_time" and pt["min_s"] == gps[0] and pt["max_s"] == gps[-1]
