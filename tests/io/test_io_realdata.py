"""The real files in ../shared/data load with the documented counts, fields and extents."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_open3d, shared_data

from minegeo.io import PointCloud, cloud_info, read_point_cloud, write_point_cloud

BUNNY_COUNTS = {"bun0.pcd": 397, "bun4.pcd": 361, "bunny.pcd": 397, "bun01.pcd": 200, "bun02.pcd": 217, "bun03.pcd": 197}


@pytest.mark.parametrize("name", sorted(BUNNY_COUNTS))
def test_pcl_bunny_pcds(name):
    c = read_point_cloud(shared_data("pcl_bunny_icp", name))
    assert len(c) == BUNNY_COUNTS[name]
    assert c.metadata["encoding"] == "ascii"  # all six are ASCII PCD (v0.7 or v.5)
    if name == "bun0.pcd":
        assert c.normals is not None and "curvature" in c.attributes
        np.testing.assert_allclose(np.linalg.norm(c.normals, axis=1), 1.0, atol=1e-5)
        np.testing.assert_allclose(c.points[0], [0.0054215998, 0.11349, 0.040748999], rtol=0, atol=1e-9)
    # bunny.pcd holds the same points as bun0.pcd
    if name == "bunny.pcd":
        b0 = read_point_cloud(shared_data("pcl_bunny_icp", "bun0.pcd"))
        np.testing.assert_allclose(c.points, b0.points, atol=1e-6)


def test_subt_satsop_zip_pcd():
    c = read_point_cloud(shared_data("subt_urban_satsop_scan", "Urban_Circuit_LowRes_Scan_alpha_LowerFloor.pcd.zip"))
    assert len(c) == 259_086
    lo, hi = c.bounds()
    # SOURCE.md: x -35.3..69.1, y -4.7..84.8, z -9.0..-0.2 m
    np.testing.assert_allclose(lo, [-35.3, -4.7, -9.0], atol=0.05)
    np.testing.assert_allclose(hi, [69.1, 84.8, -0.2], atol=0.05)
    assert c.attributes["rgb"].dtype == np.uint8 and c.attributes["rgb"].shape == (259_086, 3)
    assert "intensity" in c.attributes and "gpstime" in c.attributes
    assert c.metadata["rgb_source"].startswith("16-bit")


@pytest.mark.parametrize("name,count", [("cloud_bin_0.ply", 258_342), ("cloud_bin_4.ply", 313_395)])
def test_3dmatch_plys(name, count):
    c = read_point_cloud(shared_data("3dmatch_redkitchen_pair", name))
    assert len(c) == count
    assert c.metadata["encoding"] == "binary_little_endian" and c.metadata["dtype"] == "float32"
    assert np.isfinite(c.points).all()


@pytest.mark.parametrize("name,count", [("source.ply", 69_792), ("target.ply", 69_088)])
def test_small_gicp_plys(name, count):
    c = read_point_cloud(shared_data("small_gicp_pair", name))
    assert len(c) == count
    assert c.attributes["intensity"].dtype == np.float32  # scalar_intensity renamed
    ext = c.points.max(axis=0) - c.points.min(axis=0)
    if name == "source.ply":  # SOURCE.md: about 42 m x 58 m x 12 m
        np.testing.assert_allclose(ext, [42, 58, 12], atol=1.0)


@pytest.mark.parametrize("name", ["scan000.3d", "scan001.3d", "scan002.3d"])
def test_3dtk_scans(name):
    c = read_point_cloud(shared_data("3dtk_sample_scans", name))
    assert len(c) == 81_360  # 360 x 225 grid
    assert c.metadata["grid"] == "360 x 225"
    assert c.metadata["units"] == "cm"
    m = read_point_cloud(shared_data("3dtk_sample_scans", name), scale=0.01)
    assert m.metadata["units"] == "m"
    np.testing.assert_allclose(m.points, c.points * 0.01, rtol=1e-15, atol=0)


def test_dragon_xyz():
    c = read_point_cloud(shared_data("simpleicp_dragon", "dragon1.xyz"))
    assert len(c) == 100_000
    np.testing.assert_array_equal(c.points[0], [3.1798, 5.0338, 5.6575])
    ext = c.points.max(axis=0) - c.points.min(axis=0)
    np.testing.assert_allclose(ext, [20.5, 9.2, 14.4], atol=0.1)


def test_cloud_info_real_file():
    p = shared_data("small_gicp_pair", "source.ply")
    info = cloud_info(p)
    assert info["points"] == 69_792 and info["format"] == "ply"
    assert info["attributes"]["intensity"]["dtype"] == "float32"
    assert len(info["sha256"]) == 64 and info["size_bytes"] == p.stat().st_size


@pytest.mark.oracle
def test_open3d_reads_our_pcd_and_ply(tmp_path, rng):
    """Open3D (PCL-compatible LZF) reads what we write, and we read what it writes."""
    o3d = require_open3d()
    pts = rng.normal(size=(5000, 3)) * 10
    nrm = rng.normal(size=(5000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rgb = rng.integers(0, 256, (5000, 3)).astype(np.uint8)
    c = PointCloud(pts, normals=nrm, attributes={"rgb": rgb})
    # Open3D 0.20 reads binary PCD fields of SIZE 8 as zeros, so PCD is compared in float32
    for name, kw in [
        ("c.pcd", {"encoding": "binary_compressed", "dtype": "float32"}),
        ("b.pcd", {"encoding": "binary", "dtype": "float32"}),
        ("a.pcd", {"encoding": "ascii"}),
        ("le.ply", {"encoding": "binary_little_endian"}),
        ("be.ply", {"encoding": "binary_big_endian"}),
        ("asc.ply", {"encoding": "ascii"}),
    ]:
        write_point_cloud(tmp_path / name, c, **kw)
        o = o3d.io.read_point_cloud(str(tmp_path / name))
        ref = pts.astype(np.float32).astype(np.float64) if kw.get("dtype") == "float32" else pts
        np.testing.assert_allclose(np.asarray(o.points), ref, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(np.asarray(o.colors) * 255.0, rgb, atol=1e-6, err_msg=name)
    o = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o.normals = o3d.utility.Vector3dVector(nrm)
    o.colors = o3d.utility.Vector3dVector(rgb / 255.0)
    o3d.io.write_point_cloud(str(tmp_path / "o3d_c.pcd"), o, write_ascii=False, compressed=True)
    o3d.io.write_point_cloud(str(tmp_path / "o3d_b.ply"), o, write_ascii=False)
    for name in ("o3d_c.pcd", "o3d_b.ply"):
        back = read_point_cloud(tmp_path / name)
        assert back.metadata["encoding"] in ("binary_compressed", "binary_little_endian")
        f32 = back.metadata["dtype"] == "float32"  # Open3D writes PCD as float32, PLY as double

        def r(a, f32=f32):
            return a.astype(np.float32).astype(np.float64) if f32 else a

        np.testing.assert_array_equal(back.points, r(pts))
        np.testing.assert_array_equal(back.normals, r(nrm))
        np.testing.assert_array_equal(back.attributes["rgb"], rgb)
