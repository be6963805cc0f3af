"""Round trips of every point-cloud format (hypothesis-generated clouds for PLY and PCD)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from minegeo.errors import FileFormatError, InputError
from minegeo.io import PointCloud, read_point_cloud, write_point_cloud

FINITE64 = st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False, width=64)
FINITE32 = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False, width=32)


@st.composite
def clouds(draw, small: bool = False, with_attrs: bool = True):
    n = draw(st.integers(0, 40))
    elems = FINITE32 if small else FINITE64
    pts = draw(hnp.arrays(np.float64, (n, 3), elements=elems))
    normals = None
    attrs = {}
    if with_attrs and draw(st.booleans()):
        normals = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1, 1, width=32)))
    if with_attrs and draw(st.booleans()):
        attrs["rgb"] = draw(hnp.arrays(np.uint8, (n, 3)))
    if with_attrs and draw(st.booleans()):
        dt = draw(st.sampled_from([np.uint16, np.float32, np.int32, np.float64, np.uint8]))
        attrs["intensity"] = draw(hnp.arrays(dt, n, elements=hnp.from_dtype(np.dtype(dt), allow_nan=False, allow_infinity=False)))
    if with_attrs and draw(st.booleans()):
        attrs["label"] = draw(hnp.arrays(np.int16, n))
    return PointCloud(points=pts, normals=normals, attributes=attrs, crs=draw(st.sampled_from([None, "EPSG:5186"])))


def _check_same(a: PointCloud, b: PointCloud, exact: bool = True, text: bool = False):
    assert len(a) == len(b)
    if exact:
        np.testing.assert_array_equal(b.points, a.points)
    else:  # float32 storage: exactly the float32 rounding of the input
        np.testing.assert_array_equal(b.points, a.points.astype(np.float32).astype(np.float64))
    if a.normals is None:
        assert b.normals is None
    else:
        ref = a.normals if exact else a.normals.astype(np.float32).astype(np.float64)
        np.testing.assert_array_equal(b.normals, ref)
    assert set(a.attributes) == set(b.attributes)
    for k, v in a.attributes.items():
        np.testing.assert_array_equal(b.attributes[k], v)
        if k == "rgb":
            assert b.attributes[k].dtype == np.uint8
        elif not text:
            assert b.attributes[k].dtype == v.dtype, k
    assert b.crs == a.crs


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
@settings(max_examples=25, deadline=None)
@given(cloud=clouds())
def test_ply_roundtrip_float64(encoding, cloud):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.ply"
        write_point_cloud(p, cloud, encoding=encoding)
        back = read_point_cloud(p)
        assert back.metadata["encoding"] == encoding
    _check_same(cloud, back)


@pytest.mark.parametrize("encoding", ["ascii", "binary_big_endian"])
@settings(max_examples=20, deadline=None)
@given(cloud=clouds(small=True))
def test_ply_roundtrip_float32(encoding, cloud):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.ply"
        write_point_cloud(p, cloud, encoding=encoding, dtype="float32")
        back = read_point_cloud(p)
    _check_same(cloud, back, exact=False)


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
@settings(max_examples=25, deadline=None)
@given(cloud=clouds())
def test_pcd_roundtrip_float64(encoding, cloud):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.pcd"
        write_point_cloud(p, cloud, encoding=encoding)
        back = read_point_cloud(p)
        assert back.metadata["encoding"] == encoding
    _check_same(cloud, back)


@pytest.mark.parametrize("encoding", ["ascii", "binary_compressed"])
@settings(max_examples=20, deadline=None)
@given(cloud=clouds(small=True))
def test_pcd_roundtrip_float32(encoding, cloud):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.pcd"
        write_point_cloud(p, cloud, encoding=encoding, dtype="float32")
        back = read_point_cloud(p)
    _check_same(cloud, back, exact=False)


@pytest.mark.parametrize("suffix", [".xyz", ".txt", ".csv"])
@settings(max_examples=20, deadline=None)
@given(cloud=clouds())
def test_text_roundtrip(suffix, cloud):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"c{suffix}"
        write_point_cloud(p, cloud)
        if len(cloud) == 0:  # an empty text file holds no columns: refused with a typed error
            with pytest.raises(FileFormatError, match="no numeric data lines"):
                read_point_cloud(p)
        else:
            _check_same(cloud, read_point_cloud(p), text=True)


def test_pts_and_3d_roundtrip(tmp_path, rng):
    pts = rng.normal(size=(50, 3)) * 100
    c = PointCloud(pts, attributes={"intensity": rng.integers(-2048, 2047, 50), "rgb": rng.integers(0, 256, (50, 3)).astype(np.uint8)})
    write_point_cloud(tmp_path / "a.pts", c)
    back = read_point_cloud(tmp_path / "a.pts")
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.attributes["intensity"], c.attributes["intensity"])
    np.testing.assert_array_equal(back.attributes["rgb"], c.attributes["rgb"])
    assert back.metadata["declared_points"] == 50

    c3 = PointCloud(pts, attributes={"reflectance": rng.uniform(0, 1, 50)})
    write_point_cloud(tmp_path / "a.3d", c3)
    back = read_point_cloud(tmp_path / "a.3d")
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.attributes["reflectance"], c3.attributes["reflectance"])
    assert back.metadata["units"] == "cm"
    m = read_point_cloud(tmp_path / "a.3d", scale=0.01)
    np.testing.assert_allclose(m.points, pts * 0.01, rtol=0, atol=1e-15 * 1e3)
    assert m.metadata["units"] == "m"


def test_ply_both_endiannesses_identical_content(tmp_path, rng):
    c = PointCloud(rng.normal(size=(100, 3)), normals=rng.normal(size=(100, 3)), attributes={"intensity": rng.random(100).astype(np.float32)})
    write_point_cloud(tmp_path / "le.ply", c, encoding="binary_little_endian")
    write_point_cloud(tmp_path / "be.ply", c, encoding="binary_big_endian")
    le = (tmp_path / "le.ply").read_bytes()
    be = (tmp_path / "be.ply").read_bytes()
    assert b"binary_big_endian" in be and le != be
    a, b = read_point_cloud(tmp_path / "le.ply"), read_point_cloud(tmp_path / "be.ply")
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)
    np.testing.assert_array_equal(a.attributes["intensity"], b.attributes["intensity"])


def test_local_origin_roundtrip_and_precision(tmp_path, rng):
    """Projected coordinates: a local origin keeps float32 files sub-mm; 'file' restores it."""
    origin = np.array([512345.0, 4123456.0, 350.0])
    local = rng.uniform(-50, 50, (200, 3))
    c = PointCloud(local, origin=origin, crs="EPSG:5186")
    with pytest.raises(InputError, match="float32"):
        write_point_cloud(tmp_path / "g.ply", c, dtype="float32")  # global coords in float32: refused
    write_point_cloud(tmp_path / "l.ply", c, dtype="float32", coordinates="local")
    back = read_point_cloud(tmp_path / "l.ply", origin="file")
    np.testing.assert_array_equal(back.origin, origin)
    np.testing.assert_array_equal(back.points, local.astype(np.float32).astype(np.float64))
    assert back.crs == "EPSG:5186"
    glob = read_point_cloud(tmp_path / "l.ply")  # default: global coordinates, origin 0
    np.testing.assert_allclose(glob.points, local.astype(np.float32) + origin, rtol=0, atol=1e-9)
    auto = read_point_cloud(tmp_path / "l.ply", origin="auto")
    assert np.all(auto.origin == np.round(auto.origin))
    np.testing.assert_allclose(auto.points + auto.origin, glob.points, rtol=0, atol=1e-9)
    for suffix in (".pcd", ".xyz", ".csv"):
        write_point_cloud(tmp_path / f"l{suffix}", c, coordinates="local")
        b = read_point_cloud(tmp_path / f"l{suffix}", origin="file")
        np.testing.assert_array_equal(b.points, local)
        np.testing.assert_array_equal(b.origin, origin)


def test_2d_attribute_pcd_count_and_ply_columns(tmp_path, rng):
    desc = rng.random((30, 33)).astype(np.float32)
    c = PointCloud(rng.normal(size=(30, 3)), attributes={"fpfh": desc})
    write_point_cloud(tmp_path / "f.pcd", c, encoding="binary_compressed")
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "f.pcd").attributes["fpfh"], desc)
    write_point_cloud(tmp_path / "f.ply", c)
    back = read_point_cloud(tmp_path / "f.ply")
    np.testing.assert_array_equal(back.attributes["fpfh_32"], desc[:, 32])


def test_writing_never_touches_the_input(tmp_path, rng):
    c = PointCloud(rng.normal(size=(10, 3)))
    p = tmp_path / "in.ply"
    write_point_cloud(p, c)
    before = p.read_bytes()
    cloud = read_point_cloud(p)
    with pytest.raises(InputError, match="overwrite the input"):
        write_point_cloud(p, cloud, encoding="ascii")
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["in.ply"]  # no temp files left behind


def test_zip_roundtrip(tmp_path, rng):
    import zipfile

    c = PointCloud(rng.normal(size=(20, 3)))
    write_point_cloud(tmp_path / "a.pcd", c, encoding="binary_compressed")
    with zipfile.ZipFile(tmp_path / "a.pcd.zip", "w") as z:
        z.write(tmp_path / "a.pcd", "a.pcd")
    back = read_point_cloud(tmp_path / "a.pcd.zip")
    np.testing.assert_array_equal(back.points, c.points)
    assert back.metadata["source"].endswith("a.pcd.zip!a.pcd")


def test_ten_million_points_binary_ply(tmp_path):
    """10^7-point binary PLY writes and reads (vectorised; no timing assertion)."""
    n = 10_000_000
    pts = np.empty((n, 3))
    pts[:, 0] = np.arange(n) * 1e-3
    pts[:, 1] = -pts[:, 0]
    pts[:, 2] = 0.5
    c = PointCloud(pts, attributes={"intensity": (np.arange(n) % 65536).astype(np.uint16)})
    p = tmp_path / "big.ply"
    write_point_cloud(p, c)
    del c
    back = read_point_cloud(p)
    assert len(back) == n
    assert back.points[123456, 0] == 123456 * 1e-3 and back.points[-1, 1] == -(n - 1) * 1e-3
    assert back.attributes["intensity"][70000] == 70000 % 65536
    np.testing.assert_array_equal(back.points, pts)


@pytest.mark.parametrize(
    "name,kw",
    [("a.ply", {}), ("b.ply", {"encoding": "ascii"}), ("c.pcd", {"encoding": "binary_compressed"}), ("d.xyz", {}), ("e.csv", {})],
)
def test_writing_is_byte_deterministic(tmp_path, name, kw):
    rng = np.random.default_rng(7)
    c = PointCloud(rng.normal(size=(300, 3)), normals=rng.normal(size=(300, 3)), attributes={"intensity": rng.random(300)})
    write_point_cloud(tmp_path / f"1{name}", c, **kw)
    write_point_cloud(tmp_path / f"2{name}", c, **kw)
    assert (tmp_path / f"1{name}").read_bytes() == (tmp_path / f"2{name}").read_bytes()
