"""Bad input gives a typed error naming the file and the problem (never a silent wrong cloud)."""

from __future__ import annotations

import logging
import zipfile

import numpy as np
import pytest
from helpers import require_extra

from minegeo.errors import FileFormatError, InputError
from minegeo.io import PointCloud, read_point_cloud, write_point_cloud

PLY_ASCII = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def _err(path, match, **kw):
    with pytest.raises(FileFormatError, match=match) as ei:
        read_point_cloud(path, **kw)
    assert str(path.name) in str(ei.value)  # the message names the file
    return str(ei.value)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".las", ".laz", ".xyz", ".csv", ".pts", ".3d", ".txt"])
def test_empty_file(tmp_path, suffix):
    p = tmp_path / f"empty{suffix}"
    p.write_bytes(b"")
    _err(p, "empty")


def test_unknown_extension(tmp_path):
    p = tmp_path / "cloud.fls"
    p.write_bytes(b"x")
    _err(p, "unknown point-cloud file extension '.fls'")
    with pytest.raises(InputError, match="unknown point-cloud format"):
        read_point_cloud(p, format="fls")


def _binary_cloud(tmp_path, name, **kw):
    rng = np.random.default_rng(1)
    c = PointCloud(rng.normal(size=(100, 3)), attributes={"intensity": rng.random(100).astype(np.float32)})
    p = tmp_path / name
    write_point_cloud(p, c, **kw)
    return p


@pytest.mark.parametrize(
    "name,kw",
    [
        ("t.ply", {"encoding": "binary_little_endian"}),
        ("t.ply", {"encoding": "binary_big_endian"}),
        ("t.pcd", {"encoding": "binary"}),
        ("t.pcd", {"encoding": "binary_compressed"}),
        ("t.pcd", {"encoding": "ascii"}),
        ("t.ply", {"encoding": "ascii"}),
    ],
)
def test_truncated(tmp_path, name, kw):
    p = _binary_cloud(tmp_path, name, **kw)
    data = p.read_bytes()
    cut = data[: len(data) - 300]
    if kw["encoding"] in ("ascii",):
        cut = cut[: cut.rfind(b"\n") + 1]  # whole lines missing
    q = tmp_path / f"cut_{name}"
    q.write_bytes(cut)
    _err(q, "truncated")


def test_truncated_header(tmp_path):
    p = tmp_path / "h.ply"
    p.write_bytes(PLY_ASCII.split("end_header")[0].encode())
    _err(p, "end_header")
    q = tmp_path / "h.pcd"
    q.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n")
    _err(q, "DATA")


def test_truncated_las(tmp_path):
    require_extra("laspy")
    p = tmp_path / "t.las"
    write_point_cloud(p, PointCloud(np.random.default_rng(2).normal(size=(100, 3))))
    q = tmp_path / "cut.las"
    q.write_bytes(p.read_bytes()[:-500])
    _err(q, "LAS|truncated|unreadable")
    r = tmp_path / "junk.las"
    r.write_bytes(b"this is not a las file")
    _err(r, "LASF")


@pytest.mark.parametrize(
    "name,content,match",
    [
        ("a.ply", "plx\n" + PLY_ASCII[4:] + "1 2 3\n", "not a PLY"),
        ("b.ply", PLY_ASCII.replace("ascii", "binary_middle_endian") + "1 2 3\n", "unknown PLY format"),
        ("c.ply", PLY_ASCII.replace("property float z", "property quad z") + "1 2 3\n", "unknown property type"),
        ("d.ply", PLY_ASCII.replace("property float z\n", "") + "1 2\n", "no x, y, z"),
        ("e.ply", PLY_ASCII.replace("element vertex 3", "element face 3"), "no 'vertex' element"),
        ("f.ply", PLY_ASCII.replace("format ascii 1.0\n", "format ascii 1.0\nfrobnicate 2\n"), "unknown PLY header keyword"),
        ("a.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2 3\n", "3 FIELDS but 2 SIZE"),
        ("b.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA lzma\n1 2 3\n", "unknown PCD DATA"),
        ("c.pcd", "VERSION 0.7\nBOGUS 1\nFIELDS x y z\nDATA ascii\n", "unknown PCD header keyword"),
        ("d.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2 3\n", "unsupported TYPE"),
        ("e.pcd", "VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2 3\n", "no x, y, z"),
    ],
)
def test_wrong_header(tmp_path, name, content, match):
    p = tmp_path / name
    p.write_text(content)
    _err(p, match)


@pytest.mark.parametrize(
    "name,content,match",
    [
        ("a.ply", PLY_ASCII + "1 2 3\n4 5 6\n7 8 9\n10 11 12\n", "header declares 3 points but 4"),
        ("b.ply", PLY_ASCII + "1 2 3\n4 5 6\n", "header declares 3 points but 2"),
        ("c.ply", PLY_ASCII + "1 2 3\n4 5\n7 8 9\n", "line 9: expected 3 values, found 2"),
        ("a.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 3\nDATA ascii\n1 2 3\n", r"POINTS \(3\) differs from WIDTH\*HEIGHT"),
        ("b.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n7 8 9\n", "declares 2 points but 3"),
        ("a.xyz", "1 2 3\n4 5 6\n7 8\n", "line 3: expected 3 values, found 2"),
        ("b.xyz", "1 2 3\n4 5 six\n", "line 2: 'six' is not a number"),
        ("a.pts", "3\n1 2 3\n4 5 6\n", "declares 3 points but 2"),
        ("a.csv", "x,y,z,i\n1,2,3\n", "header of 3 column names|4 names"),
    ],
)
def test_wrong_counts_and_values(tmp_path, name, content, match):
    p = tmp_path / name
    p.write_text(content)
    _err(p, match)


def test_binary_count_mismatch(tmp_path):
    p = _binary_cloud(tmp_path, "t.ply")
    data = p.read_bytes().replace(b"element vertex 100", b"element vertex 90 ")
    q = tmp_path / "count.ply"
    q.write_bytes(data)
    _err(q, r"header vertex count \(90\) is wrong")
    p = _binary_cloud(tmp_path, "t.pcd", encoding="binary_compressed")
    data = p.read_bytes().replace(b"WIDTH 100", b"WIDTH 99").replace(b"POINTS 100", b"POINTS 99")
    q = tmp_path / "count.pcd"
    q.write_bytes(data)
    _err(q, "uncompressed size")


def test_corrupt_lzf(tmp_path):
    p = _binary_cloud(tmp_path, "t.pcd", encoding="binary_compressed")
    data = bytearray(p.read_bytes())
    i = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n") + 8
    data[i] = 0xFF  # a back reference before the start of the output
    q = tmp_path / "bad.pcd"
    q.write_bytes(bytes(data))
    _err(q, "LZF")


def test_nan_rows_rejected_with_line_or_dropped(tmp_path, caplog):
    p = tmp_path / "n.xyz"
    p.write_text("# x y z\n1 2 3\n\n# a comment inside the data\n4 nan 6\n7 8 9\nnan nan nan\n")
    msg = _err(p, "NaN")
    assert "2 point(s)" in msg and "point 1 (line 5)" in msg
    with caplog.at_level(logging.WARNING, logger="minegeo.io"):
        c = read_point_cloud(p, drop_nonfinite=True)
    assert len(c) == 2 and c.metadata["dropped_nonfinite"] == 2
    assert "dropped 2 point(s)" in caplog.text
    # binary: organized-cloud style NaN points
    pts = np.array([[1.0, 2, 3], [np.nan, np.nan, np.nan], [4, 5, 6]])
    raw = b"VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary\n"
    q = tmp_path / "n.pcd"
    q.write_bytes(raw + pts.astype("<f8").tobytes())
    _err(q, "point 1")
    np.testing.assert_array_equal(read_point_cloud(q, drop_nonfinite=True).points, pts[[0, 2]])


def test_zip_problems(tmp_path):
    p = tmp_path / "two.zip"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("a.xyz", "1 2 3\n")
        z.writestr("b.xyz", "1 2 3\n")
    _err(p, "exactly one point-cloud file")
    q = tmp_path / "fake.zip"
    q.write_bytes(b"not a zip")
    _err(q, "not a zip")
    r = tmp_path / "bad_inner.zip"
    with zipfile.ZipFile(r, "w") as z:
        z.writestr("a.ply", "ply\nformat ascii 1.0\n")
    with pytest.raises(FileFormatError, match=r"bad_inner.zip!a.ply: .*end_header"):
        read_point_cloud(r)


def test_bad_arguments(tmp_path, rng):
    c = PointCloud(rng.normal(size=(5, 3)))
    with pytest.raises(InputError, match="PLY encoding"):
        write_point_cloud(tmp_path / "a.ply", c, encoding="binary")
    with pytest.raises(InputError, match="dtype"):
        write_point_cloud(tmp_path / "a.ply", c, dtype="float16")
    with pytest.raises(InputError, match="origin"):
        write_point_cloud(tmp_path / "a.ply", c)
        read_point_cloud(tmp_path / "a.ply", origin="centre")
    with pytest.raises(InputError, match="scale"):
        read_point_cloud(tmp_path / "a.ply", scale=-1)
    with pytest.raises(InputError, match="PointCloud"):
        write_point_cloud(tmp_path / "b.ply", rng.normal(size=(5, 3)))
    with pytest.raises(FileNotFoundError):
        read_point_cloud(tmp_path / "missing.ply")


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz", ".csv"])
def test_attribute_name_clash_refused(tmp_path, rng, suffix):
    name = "Normal_X" if suffix == ".pcd" else "NX"  # PCD names normals normal_x ..
    c = PointCloud(rng.normal(size=(4, 3)), normals=np.tile([0.0, 0, 1], (4, 1)), attributes={name: np.zeros(4)})
    with pytest.raises(InputError, match="clashes"):
        write_point_cloud(tmp_path / f"a{suffix}", c)
    assert not list(tmp_path.iterdir())
