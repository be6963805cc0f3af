"""E57 input (issue 19, deliverable 3): scans merged by their stored poses, streaming, damaged files.

Files are written by pye57 itself (``E57.write_scan_raw``: cartesian coordinates as *single*
precision floats, pose as doubles) and, for what pye57 cannot write (double-precision
coordinates, spherical coordinates, invalid returns, a scan without coordinates), through
pye57's libE57 bindings directly.
"""

from __future__ import annotations

import re
import sys
import zipfile

import numpy as np
import pytest
from helpers import require_extra

pye57 = require_extra("pye57")
from pye57 import libe57  # noqa: E402

from minegeo.cli import main  # noqa: E402
from minegeo.errors import FileFormatError, InputError, MinegeoError, OptionalDependencyError  # noqa: E402
from minegeo.io import cloud_info, read_point_cloud  # noqa: E402
from minegeo.io.e57 import e57_scan_poses, iter_e57_chunks, read_e57  # noqa: E402


def _quat_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat(axis, angle):
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * a])


#: two scans with clearly different poses: a yaw + tilt and a large (projected) translation
POSES = [(_quat([0, 0, 1], 0.7), np.array([12.5, -3.25, 1.5])),
         (_quat([1, 2, 3], -1.1), np.array([512345.678, 4123456.789, -812.5]))]


def _scan_points(seed, n):
    """Scan-frame points exactly representable in float32 (pye57 stores E57_SINGLE)."""
    rng = np.random.default_rng(seed)
    return np.round(rng.uniform(-20.0, 20.0, (n, 3)) * 256.0) / 256.0


@pytest.fixture
def two_scans(tmp_path):
    """An E57 written by pye57: two scans (1500 and 1000 points) with different poses."""
    path = tmp_path / "two.e57"
    pts = [_scan_points(1, 1500), _scan_points(2, 1000)]
    with pye57.E57(str(path), mode="w") as e:
        for i, (p, (q, t)) in enumerate(zip(pts, POSES, strict=True)):
            e.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]},
                             name=f"station {i + 1}", rotation=q, translation=t)
    expected = np.concatenate([p @ _quat_matrix(q).T + t for p, (q, t) in zip(pts, POSES, strict=True)])
    return path, pts, expected


def _write_raw_scan(path, scans):
    """Write an E57 through libE57: each scan a dict with ``fields`` {name: (array, kind)} where kind is
    "double", "single", "int:min:max"; optional ``pose`` (q, t). Empty list -> a file without scans."""
    imf = libe57.ImageFile(str(path), "w")
    try:
        imf.extensionsAdd("", libe57.E57_V1_0_URI)
        root = imf.root()
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, "{test-file}"))
        root.set("versionMajor", libe57.IntegerNode(imf, 1))
        root.set("versionMinor", libe57.IntegerNode(imf, 0))
        root.set("data3D", libe57.VectorNode(imf, True))
        root.set("images2D", libe57.VectorNode(imf, True))
        for si, sc in enumerate(scans):
            node = libe57.StructureNode(imf)
            node.set("guid", libe57.StringNode(imf, f"{{scan-{si}}}"))
            node.set("name", libe57.StringNode(imf, sc.get("name", f"raw {si}")))
            if "pose" in sc:
                q, t = sc["pose"]
                pose = libe57.StructureNode(imf)
                rot = libe57.StructureNode(imf)
                for k, v in zip("wxyz", q, strict=True):
                    rot.set(k, libe57.FloatNode(imf, float(v)))
                tr = libe57.StructureNode(imf)
                for k, v in zip("xyz", t, strict=True):
                    tr.set(k, libe57.FloatNode(imf, float(v)))
                pose.set("rotation", rot)
                pose.set("translation", tr)
                node.set("pose", pose)
            proto = libe57.StructureNode(imf)
            for name, (_arr, kind) in sc["fields"].items():
                if kind == "double":
                    proto.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, -1e12, 1e12))
                elif kind == "single":
                    proto.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_SINGLE, -1e6, 1e6))
                else:
                    _, lo, hi = kind.split(":")
                    proto.set(name, libe57.IntegerNode(imf, int(lo), int(lo), int(hi)))
            points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
            node.set("points", points)
            root["data3D"].append(node)
            n = len(next(iter(sc["fields"].values()))[0])
            bufs = libe57.VectorSourceDestBuffer()
            keep = []
            for name, (arr, kind) in sc["fields"].items():
                a = np.ascontiguousarray(arr, dtype=np.float64 if kind in ("double", "single") else np.uint16)
                keep.append(a)
                bufs.append(libe57.SourceDestBuffer(imf, name, a, n, True, True))
            w = points.writer(bufs)
            w.write(n)
            w.close()
    finally:
        imf.close()


def _xyz_fields(p, kind="double"):
    return {"cartesianX": (p[:, 0], kind), "cartesianY": (p[:, 1], kind), "cartesianZ": (p[:, 2], kind)}


# -- round trips -------------------------------------------------------------------------------------------------


def test_two_scans_written_by_pye57_come_back_in_the_file_frame(two_scans):
    path, pts, expected = two_scans
    cloud = read_e57(path)
    assert cloud.points.dtype == np.float64 and cloud.frame == "e57_file"
    np.testing.assert_allclose(cloud.points, expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(cloud.attributes["scan_index"], np.repeat([0, 1], [1500, 1000]))
    scans = cloud.metadata["e57_scans"]
    assert [s["name"] for s in scans] == ["station 1", "station 2"]
    for s, (q, t) in zip(scans, POSES, strict=True):
        np.testing.assert_allclose(s["T_file_scan"][:3, :3], _quat_matrix(q), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(s["T_file_scan"][:3, 3], t)
        assert s["guid"] and s["coordinates"] == "cartesian"
    # each scan's points are that scan's, transformed by that scan's own pose
    for i, (p, (q, t)) in enumerate(zip(pts, POSES, strict=True)):
        back = cloud.points[cloud.attributes["scan_index"] == i] - t
        np.testing.assert_allclose(back @ _quat_matrix(q), p, rtol=0, atol=1e-9)


def test_poses_without_points_and_the_generic_reader(two_scans):
    path, _, expected = two_scans
    poses = e57_scan_poses(path)
    assert [(p["index"], p["points"]) for p in poses] == [(0, 1500), (1, 1000)]
    np.testing.assert_array_equal(poses[1]["T_file_scan"][:3, 3], POSES[1][1])
    c = read_point_cloud(path, origin="auto")
    assert c.metadata["format"] == "e57"
    assert np.all(c.origin == np.round(c.origin)) and np.abs(c.points).max() < 3e6  # a whole-metre local origin
    np.testing.assert_allclose(c.global_points, expected, rtol=0, atol=1e-9)


def test_chunks_stream_the_same_points_in_the_same_order(two_scans):
    path, _, _ = two_scans
    full = read_e57(path).points
    chunks = list(iter_e57_chunks(path, 400))
    assert all(c.dtype == np.float64 and c.shape[1] == 3 and 0 < len(c) <= 400 for c in chunks)
    assert [len(c) for c in chunks] == [400, 400, 400, 300, 400, 400, 200]  # per scan, never spanning two
    np.testing.assert_array_equal(np.concatenate(chunks), full)
    with pytest.raises(InputError):
        next(iter_e57_chunks(path, 0))


def test_scan_selection_by_index_and_name(two_scans):
    path, _, expected = two_scans
    np.testing.assert_array_equal(read_e57(path, scans=[1]).points, read_e57(path, scans="station 2").points)
    np.testing.assert_allclose(read_e57(path, scans=1).points, expected[1500:], rtol=0, atol=1e-9)
    with pytest.raises(InputError, match="no scan named"):
        read_e57(path, scans="nope")
    with pytest.raises(InputError, match="out of range"):
        read_e57(path, scans=[2])


def test_double_precision_coordinates_at_projected_size(tmp_path):
    """Double-precision cartesian coordinates and a pose far from the origin: float64 throughout."""
    rng = np.random.default_rng(4)
    p = rng.uniform(-30, 30, (500, 3))
    q, t = _quat([0.2, -0.1, 1.0], 2.3), np.array([698765.4321, 5432109.8765, 123.456])
    _write_raw_scan(tmp_path / "d.e57", [{"fields": _xyz_fields(p), "pose": (q, t)}])
    c = read_e57(tmp_path / "d.e57", origin="auto")
    np.testing.assert_allclose(c.global_points, p @ _quat_matrix(q).T + t, rtol=0, atol=2e-9)


def test_spherical_scan_is_converted_by_the_e57_convention(tmp_path):
    rng = np.random.default_rng(5)
    r, az, el = rng.uniform(1, 40, 300), rng.uniform(-np.pi, np.pi, 300), rng.uniform(-1.2, 1.2, 300)
    fields = {"sphericalRange": (r, "double"), "sphericalAzimuth": (az, "double"), "sphericalElevation": (el, "double")}
    _write_raw_scan(tmp_path / "s.e57", [{"fields": fields, "pose": POSES[0]}])
    xyz = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    c = read_e57(tmp_path / "s.e57")
    np.testing.assert_allclose(c.points, xyz @ _quat_matrix(POSES[0][0]).T + POSES[0][1], rtol=0, atol=1e-9)
    assert c.metadata["e57_scans"][0]["coordinates"] == "spherical"


def test_invalid_returns_dropped_intensity_and_colour_kept(tmp_path):
    rng = np.random.default_rng(6)
    p = rng.uniform(-5, 5, (200, 3))
    state = (np.arange(200) % 10 == 0).astype(np.int32) * 2
    fields = {**_xyz_fields(p), "cartesianInvalidState": (state, "int:0:2"),
              "intensity": (np.linspace(0, 1, 200), "double"),
              "colorRed": (np.arange(200) % 256, "int:0:255"), "colorGreen": (np.full(200, 7), "int:0:255"),
              "colorBlue": (np.full(200, 255), "int:0:255")}
    _write_raw_scan(tmp_path / "v.e57", [{"fields": fields}])
    c = read_point_cloud(tmp_path / "v.e57")
    ok = state == 0
    np.testing.assert_array_equal(c.points, p[ok])
    assert c.metadata["e57_invalid_dropped"] == 20
    np.testing.assert_allclose(c.attributes["intensity"], np.linspace(0, 1, 200)[ok])
    np.testing.assert_array_equal(c.attributes["rgb"][:, 0], (np.arange(200) % 256)[ok])
    assert c.attributes["rgb"].dtype == np.uint8


def test_e57_inside_a_zip(two_scans, tmp_path):
    path, _, expected = two_scans
    z = tmp_path / "scan.e57.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.write(path, "inner.e57")
    np.testing.assert_allclose(read_point_cloud(z).points, expected, rtol=0, atol=1e-9)


# -- damaged files -----------------------------------------------------------------------------------------------


def _damaged(kind, src, dst):
    data = src.read_bytes()
    if kind == "truncated":
        dst.write_bytes(data[: len(data) // 2])
    elif kind == "appended":
        dst.write_bytes(data + b"\0" * 100)
    elif kind == "garbage":
        dst.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    elif kind == "text":
        dst.write_text("x,y,z\n1,2,3\n")
    elif kind == "empty":
        dst.write_bytes(b"")
    elif kind == "bitflip":  # a byte inside the point data: libE57's page checksum catches it
        b = bytearray(data)
        b[3000] ^= 0xFF
        dst.write_bytes(bytes(b))
    elif kind == "header_only":
        dst.write_bytes(data[:20])
    return dst


@pytest.mark.parametrize("kind, message", [
    ("truncated", "truncated"), ("appended", "longer than its header"), ("garbage", "not an E57 file"),
    ("text", "not an E57 file"), ("empty", "empty file"), ("bitflip", "checksum"),
    ("header_only", "truncated"),
])
def test_damaged_files_give_a_clear_typed_error(two_scans, tmp_path, kind, message):
    bad = _damaged(kind, two_scans[0], tmp_path / f"{kind}.e57")
    with pytest.raises(FileFormatError, match=message) as ei:
        read_point_cloud(bad)
    assert str(bad) in str(ei.value) and "\n" not in str(ei.value)  # one line, naming the file


def test_file_without_scans(tmp_path):
    _write_raw_scan(tmp_path / "zero.e57", [])
    with pytest.raises(FileFormatError, match="no 3D scans"):
        read_e57(tmp_path / "zero.e57")


def test_scan_without_coordinates(tmp_path):
    _write_raw_scan(tmp_path / "i.e57", [{"fields": {"intensity": (np.linspace(0, 1, 10), "double")}}])
    with pytest.raises(FileFormatError, match="neither cartesianX/Y/Z nor spherical"):
        read_e57(tmp_path / "i.e57")


def test_directory_and_missing_file(tmp_path):
    d = tmp_path / "folder.e57"
    d.mkdir()
    with pytest.raises(FileFormatError, match="directory"):
        read_e57(d)
    with pytest.raises(FileNotFoundError):
        read_e57(tmp_path / "missing.e57")


def test_without_pye57_the_error_names_the_extra(two_scans, monkeypatch):
    monkeypatch.setitem(sys.modules, "pye57", None)
    with pytest.raises(OptionalDependencyError, match=r"minegeo\[e57\]"):
        read_e57(two_scans[0])
    assert issubclass(OptionalDependencyError, MinegeoError)


def _crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of ``data``: the checksum of every E57 page (ASTM E2807 Sec. 8.2.2)."""
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def _edit_pose_text(src, dst, scan: int, part: str, key: str, text: str):
    """Copy of the E57 ``src`` whose XML element ``pose/part/key`` of scan ``scan`` reads ``text`` (padded
    with spaces to the written length), with the page checksums recomputed: a file damaged or written by
    another program, not one libE57 would refuse."""

    raw = bytearray(src.read_bytes())
    page = 1024
    logical = b"".join(raw[i:i + page - 4] for i in range(0, len(raw), page))
    starts = [m.start() for m in re.finditer(rb"<vectorChild", logical)]
    seg = logical.index(f"<{part} ".encode(), starts[scan])
    m = re.compile(rf"<{key} type=\"Float\">([^<]*)</{key}>".encode()).search(logical, seg)
    old = m.group(1)
    assert len(text) <= len(old), (text, old)
    new = text.encode().ljust(len(old))
    logical = logical[:m.start(1)] + new + logical[m.end(1):]
    for k, i in enumerate(range(0, len(raw), page)):
        chunk = logical[k * (page - 4):(k + 1) * (page - 4)]
        raw[i:i + page - 4] = chunk
        raw[i + page - 4:i + page] = _crc32c(chunk).to_bytes(4, "big")
    dst.write_bytes(bytes(raw))
    return dst


def _posed(tmp_path, q, t=(1.25, -2.5, 3.75)):
    p = tmp_path / "posed.e57"
    _write_raw_scan(p, [{"fields": _xyz_fields(_scan_points(3, 40)), "pose": (q, t), "name": "station A"}])
    return p


@pytest.mark.parametrize("q, part, key, text, words", [
    # issue 27: <w>nan</w> in an identity pose was reported as "quaternion [0,0,0,0]"
    ((1 + 2**-52, 0, 0, 0), "rotation", "w", "nan", "(w=nan, x=0, y=0, z=0) holds a value that is not a finite"),
    ((0.5, 0.5, 0.5, 0.5), "rotation", "x", "inf", "(w=5e-01, x=inf, y=5e-01, z=5e-01)"),
    ((0.5, 0.5, 0.5, 0.5), "rotation", "y", "abc", "(w=5e-01, x=5e-01, y=abc, z=5e-01)"),
    # libE57 reads an unparsable w as 0, leaving the unit quaternion (0, 0, 0, 1): a silent 180 deg turn
    ((1e-9, 0, 0, 1), "rotation", "w", "nan", "(w=nan, x=0, y=0, z=1)"),
    ((0.5, 0.5, 0.5, 0.5), "rotation", "w", "0", "has length 0.866025, not 1"),
    # libE57 reads an unparsable translation as 0: the scan would sit at the origin
    ((1, 0, 0, 0), "translation", "y", "nan", "pose translation (x=1.25, y=nan, z=3.75)"),
])
def test_bad_pose_values_are_named_as_written(tmp_path, q, part, key, text, words):
    bad = _edit_pose_text(_posed(tmp_path, q), tmp_path / "bad.e57", 0, part, key, text)
    for fn in (read_e57, e57_scan_poses):
        with pytest.raises(FileFormatError, match=re.escape(words)) as ei:
            fn(bad)
        msg = str(ei.value)
        assert msg.startswith(f"{bad}: scan 0 ('station A'): pose ") and "\n" not in msg


def test_zero_quaternion_is_named(tmp_path):
    with pytest.raises(FileFormatError, match=re.escape("quaternion (w=0, x=0, y=0, z=0) has zero length")):
        read_e57(_posed(tmp_path, (0.0, 0.0, 0.0, 0.0)))


def test_pose_edit_helper_alone_changes_nothing(tmp_path):
    """The editing helper of the tests above, rewriting a value as itself, gives a file read as written."""
    src = _posed(tmp_path, (0.5, 0.5, 0.5, 0.5))
    same = _edit_pose_text(src, tmp_path / "same.e57", 0, "rotation", "w", "5e-01")
    assert same.read_bytes() == src.read_bytes()
    np.testing.assert_array_equal(read_e57(same).points, read_e57(src).points)


# -- CLI ---------------------------------------------------------------------------------------------------------


def test_info_shows_scans_and_poses(two_scans, capsys):
    path, _, expected = two_scans
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "format    e57" in out and "scans     2" in out
    assert "'station 2': 1,000 points (cartesian), position (512345.6780, 4123456.7890, -812.5000)" in out
    info = cloud_info(path)
    np.testing.assert_allclose(info["bounds_min"], expected.min(axis=0), rtol=0, atol=1e-9)


def test_info_of_a_damaged_file_is_one_line_exit_2(two_scans, tmp_path, capsys):
    bad = _damaged("truncated", two_scans[0], tmp_path / "t.e57")
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "truncated" in err[0]
