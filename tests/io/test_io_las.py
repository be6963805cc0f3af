"""LAS/LAZ through laspy: integer scale/offset, CRS EPSG:5186, attributes, origin precision."""

from __future__ import annotations

import builtins
import sys

import numpy as np
import pytest
from helpers import require_extra

from minegeo.errors import InputError, OptionalDependencyError
from minegeo.io import PointCloud, read_point_cloud, write_point_cloud

laspy = require_extra("laspy")

E0, N0, H0 = 201_234.0, 551_987.0, 85.0  # Korea 2000 / Central Belt 2010 (EPSG:5186) range


def _cloud(rng, n=500):
    # global coordinates on the 1 mm grid, so LAS integers represent them exactly
    mm = rng.integers(-200_000, 200_000, (n, 3))
    glob = np.array([E0, N0, H0]) + mm * 1e-3
    return PointCloud(
        points=glob,
        normals=None,
        attributes={
            "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "rgb": rng.integers(0, 256, (n, 3)).astype(np.uint8),
            "classification": rng.integers(0, 20, n).astype(np.uint8),
            "gps_time": rng.uniform(0, 1e5, n),
            "range_m": rng.uniform(0, 100, n).astype(np.float32),
        },
        crs="EPSG:5186",
    )


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_roundtrip_scale_offset_crs(tmp_path, rng, suffix):
    c = _cloud(rng)
    p = tmp_path / f"c{suffix}"
    write_point_cloud(p, c, las_scale=0.001, las_offset=[E0, N0, 0.0])
    back = read_point_cloud(p)
    assert back.crs == "EPSG:5186"
    assert back.metadata["format"] == suffix[1:]
    assert back.metadata["las_scale"] == [0.001] * 3
    assert back.metadata["las_offset"] == [E0, N0, 0.0]
    np.testing.assert_allclose(back.points, c.points, rtol=0, atol=1e-9)
    for k in ("intensity", "rgb", "classification", "gps_time", "range_m"):
        np.testing.assert_array_equal(back.attributes[k], c.attributes[k], err_msg=k)
        assert back.attributes[k].dtype == c.attributes[k].dtype, k
    # the raw integers are exactly what they should be
    raw = laspy.read(p)
    np.testing.assert_array_equal(np.asarray(raw.X), np.round((c.points[:, 0] - E0) / 0.001).astype(np.int64))
    # writing again keeps the scale and offset it was read with, and the same integers
    write_point_cloud(tmp_path / f"again{suffix}", back)
    again = laspy.read(tmp_path / f"again{suffix}")
    np.testing.assert_array_equal(np.asarray(again.X), np.asarray(raw.X))
    np.testing.assert_array_equal(again.header.offsets, raw.header.offsets)
    np.testing.assert_array_equal(again.header.scales, raw.header.scales)


def test_las_origin_subtraction_is_exact(tmp_path, rng):
    """points = X*scale + (offset - origin): local coordinates equal the exact decimal values."""
    n = 1000
    X = rng.integers(-(2**30), 2**30, (n, 3))
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales = [0.0001, 0.0001, 0.0001]
    hdr.offsets = [4_500_000.0, 5_600_000.0, 100.0]
    las = laspy.LasData(hdr)
    las.X, las.Y, las.Z = X[:, 0], X[:, 1], X[:, 2]
    las.write(tmp_path / "big.las")
    origin = np.array([4_500_000.0, 5_600_000.0, 100.0])
    c = read_point_cloud(tmp_path / "big.las", origin=origin)
    np.testing.assert_array_equal(c.origin, origin)
    np.testing.assert_array_equal(c.points, X * 0.0001)  # offset - origin == 0 exactly
    f = read_point_cloud(tmp_path / "big.las", origin="file")
    np.testing.assert_array_equal(f.origin, origin)
    other = read_point_cloud(tmp_path / "big.las", origin=[4_500_100.0, 5_600_000.0, 0.0])
    np.testing.assert_allclose(other.points, X * 0.0001 + [-100.0, 0.0, 100.0], rtol=0, atol=1e-9)


@pytest.mark.parametrize("scale", [1e308, 0.0, float("nan")])
def test_las_damaged_scale_is_a_typed_error(tmp_path, rng, scale):
    """A header scale that overflows the coordinates, is zero or NaN: FileFormatError, no warning."""
    import warnings

    from minegeo.errors import FileFormatError

    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales = [0.001, 0.001, 0.001]
    las = laspy.LasData(hdr)
    X = rng.integers(-(2**30), 2**30, (50, 3))
    las.X, las.Y, las.Z = X[:, 0], X[:, 1], X[:, 2]
    p = tmp_path / "bad.las"
    las.write(p)
    raw = bytearray(p.read_bytes())
    raw[131:139] = np.float64(scale).tobytes()  # x scale factor (LAS header offset 131)
    p.write_bytes(bytes(raw))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FileFormatError):
            read_point_cloud(p)


def test_las_local_cloud_written_global(tmp_path, rng):
    local = rng.uniform(-10, 10, (100, 3)).round(3)
    c = PointCloud(local, origin=[E0, N0, H0], crs="EPSG:5186", normals=np.tile([0.0, 0.0, 1.0], (100, 1)))
    write_point_cloud(tmp_path / "l.las", c)
    back = read_point_cloud(tmp_path / "l.las", origin=[E0, N0, H0])
    np.testing.assert_allclose(back.points, local, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(back.normals, c.normals)  # extra-bytes nx ny nz
    with pytest.raises(InputError, match="global"):
        write_point_cloud(tmp_path / "x.las", c, coordinates="local")


def test_las_bad_attribute_and_range(tmp_path, rng):
    c = PointCloud(rng.normal(size=(10, 3)), attributes={"intensity": rng.normal(size=10)})
    with pytest.raises(InputError, match="intensity"):
        write_point_cloud(tmp_path / "a.las", c)
    far = PointCloud(np.array([[0.0, 0.0, 0.0], [1e7, 0.0, 0.0]]))
    with pytest.raises(InputError, match="32-bit"):
        write_point_cloud(tmp_path / "b.las", far, las_scale=0.0001)


def test_las_without_laspy(tmp_path, rng, monkeypatch):
    write_point_cloud(tmp_path / "a.las", PointCloud(rng.normal(size=(5, 3))))
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "laspy" or name.startswith("laspy."):
            raise ImportError("no laspy")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    monkeypatch.delitem(sys.modules, "laspy", raising=False)
    with pytest.raises(OptionalDependencyError, match="laspy"):
        read_point_cloud(tmp_path / "a.las")


def test_las12_geotiff_crs_and_8bit_colour(tmp_path, rng):
    """Older files: LAS 1.2 point format 3, CRS as GeoTIFF keys, colour stored as 8-bit values."""
    import pyproj

    n = 50
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.01, 0.01, 0.01]
    hdr.offsets = [E0, N0, 0.0]
    hdr.add_crs(pyproj.CRS("EPSG:5186"))
    las = laspy.LasData(hdr)
    X = rng.integers(0, 100_000, (n, 3))
    las.X, las.Y, las.Z = X[:, 0], X[:, 1], X[:, 2]
    rgb8 = rng.integers(0, 256, (n, 3))
    las.red, las.green, las.blue = rgb8[:, 0], rgb8[:, 1], rgb8[:, 2]
    las.write(tmp_path / "old.las")
    assert any("GeoKeyDirectory" in type(v).__name__ for v in laspy.read(tmp_path / "old.las").header.vlrs)
    c = read_point_cloud(tmp_path / "old.las", origin="auto")
    assert c.crs == "EPSG:5186"
    assert c.metadata["las_version"] == "1.2" and c.metadata["las_point_format"] == 3
    np.testing.assert_array_equal(c.attributes["rgb"], rgb8)  # all <= 255: kept as stored
    assert np.all(c.origin == np.round(c.origin)) and c.origin[0] > 1e5
    np.testing.assert_allclose(c.points + c.origin, X * 0.01 + [E0, N0, 0.0], rtol=0, atol=1e-9)
