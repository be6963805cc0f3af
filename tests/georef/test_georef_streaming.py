"""``minegeo georef`` of a large map, chunk by chunk (:func:`minegeo.georef.stream_georeferenced_map`,
:func:`minegeo.georef.stream_georeferenced_las`): the bytes, sidecar and report sample of the
whole-file path (``apply_georef`` + ``write_georeferenced_map``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import require_extra

from minegeo.io import write_point_cloud
from minegeo.io.types import PointCloud


@pytest.mark.parametrize("far", [False, True], ids=["local", "projected"])
def test_georef_streams_the_same_bytes(tmp_path, capsys, far):
    """``minegeo georef`` of an x, y, z-only PLY streams it (pass 1: count and origin, pass 2:
    transform + write) and writes the bytes, sidecar and report sample of the in-memory path."""
    from minegeo.cli import main
    from minegeo.cli.georef import streamable_map
    from minegeo.georef import (
        GeorefParams,
        apply_georef,
        georeference,
        read_georef,
        report_sample_rows,
        write_georeferenced_map,
    )
    from minegeo.io import read_point_cloud, write_gcps
    from minegeo.synth import build_world, make_gcps

    world = build_world("small", seed=0)
    gcps, _ = make_gcps(world, n=8, seed=1, crs="EPSG:5186", sigma_m=0.005)
    rng = np.random.default_rng(0)
    lo, hi = gcps.local_xyz.min(axis=0) - 5.0, gcps.local_xyz.max(axis=0) + 5.0
    pts = np.vstack([rng.uniform(lo, hi, (25_000, 3)), gcps.local_xyz])
    shift = np.array([20_000.0, 0.0, 0.0]) if far else np.zeros(3)  # far: origin "auto" is not 0
    gcps.local_xyz[:] += shift
    mp, gp = tmp_path / "map.ply", tmp_path / "gcps.csv"
    write_point_cloud(mp, PointCloud(points=pts + shift))
    write_gcps(gp, gcps)
    out = tmp_path / "geo" / "map_geo.ply"
    assert streamable_map(mp, out) is not None
    code = main(["-q", "georef", "--map", str(mp), "--gcps", str(gp), "--crs", "EPSG:5186", "--out", str(out),
                 "--report", str(tmp_path / "rep"), "--model", "rigid"])
    assert code == 0
    res = json.loads((tmp_path / "rep" / "result.json").read_text())
    assert "transform_and_write_map" in res["timings_s"]
    g = read_georef(out.with_name(out.name + ".georef.json"))
    assert g.as_dict()["T_geo_map"] == georeference(gcps, "EPSG:5186", GeorefParams(model="rigid")).as_dict()["T_geo_map"]
    cloud_geo = apply_georef(read_point_cloud(mp, origin="auto"), g)
    ref = tmp_path / "ref_geo.ply"
    write_georeferenced_map(ref, cloud_geo, g)
    assert out.read_bytes() == ref.read_bytes()
    side, side_ref = (json.loads(q.with_name(q.name + ".georef.json").read_text()) for q in (out, ref))
    for k in ("map_file", "inputs", "report"):
        side.pop(k, None), side_ref.pop(k, None)
    assert side == side_ref
    rows = report_sample_rows(len(cloud_geo))
    assert rows.size == 20_000 and np.all(np.diff(rows) > 0)
    from minegeo.cli.georef import map_origin_auto
    from minegeo.georef import stream_georeferenced_map

    chunks = streamable_map(mp, out)
    n = map_origin_auto(chunks)
    assert np.array_equal(chunks.origin, read_point_cloud(mp, origin="auto").origin)
    _, _, sample = stream_georeferenced_map(tmp_path / "again.ply", chunks, g, n)
    assert np.array_equal(sample.points, cloud_geo.points[rows])
    assert (tmp_path / "again.ply").read_bytes() == ref.read_bytes()


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_georef_streams_las_with_every_field(tmp_path, suffix):
    """``minegeo georef`` of a LAS/LAZ map to a LAS/LAZ output streams it record by record: every
    field of every record (intensity, classification, GPS time, colour, an extra dimension) is the
    input's, in its point format; X, Y, Z are the integers the whole-file path writes
    (``write_georeferenced_map`` of ``apply_georef``), at the map's scale with the header offset
    = the result's origin; the CRS is the target's. Chunks of 997 points, so many chunks."""
    laspy = require_extra("laspy")
    import pyproj

    from minegeo.cli import main
    from minegeo.cli.georef import map_origin_auto, streamable_map
    from minegeo.georef import (
        apply_georef,
        read_georef,
        stream_georeferenced_las,
        write_georeferenced_map,
    )
    from minegeo.io import read_point_cloud, write_gcps
    from minegeo.synth import build_world, make_gcps

    world = build_world("small", seed=0)
    gcps, _ = make_gcps(world, n=8, seed=1, crs="EPSG:5186", sigma_m=0.005)
    rng = np.random.default_rng(4)
    lo, hi = gcps.local_xyz.min(axis=0) - 5.0, gcps.local_xyz.max(axis=0) + 5.0
    pts = np.vstack([rng.uniform(lo, hi, (9_000, 3)), gcps.local_xyz])
    shift = np.array([250_000.0, 4_100_000.0, 300.0])  # a map in another projected frame: origin "auto" != 0
    gcps.local_xyz[:] += shift
    n = len(pts)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = np.array([250_000.0, 4_100_000.0, 0.0])
    hdr.add_extra_dim(laspy.ExtraBytesParams(name="range_m", type=np.float32))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = (pts + shift).T
    las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    las.classification = rng.integers(0, 31, n).astype(np.uint8)
    las.gps_time = np.cumsum(rng.uniform(0, 1e-3, n))
    las.red, las.green, las.blue = (rng.integers(0, 65535, n).astype(np.uint16) for _ in range(3))
    las.range_m = rng.uniform(0, 80, n).astype(np.float32)
    mp, gp = tmp_path / f"map{suffix}", tmp_path / "gcps.csv"
    las.write(str(mp))
    write_gcps(gp, gcps)
    out = tmp_path / "geo" / f"map_geo{suffix}"
    chunks = streamable_map(mp, out)
    assert chunks is not None and chunks.format == suffix[1:]
    code = main(["-q", "georef", "--map", str(mp), "--gcps", str(gp), "--crs", "EPSG:5186", "--out", str(out),
                 "--report", str(tmp_path / "rep"), "--model", "rigid"])
    assert code == 0
    assert "transform_and_write_map" in json.loads((tmp_path / "rep" / "result.json").read_text())["timings_s"]
    g = read_georef(out.with_name(out.name + ".georef.json"))
    # the whole-file path's integers
    ref = tmp_path / f"ref{suffix}"
    write_georeferenced_map(ref, apply_georef(read_point_cloud(mp, origin="auto"), g), g)
    a, b, src = laspy.read(str(out)), laspy.read(str(ref)), laspy.read(str(mp))
    for k in ("X", "Y", "Z"):
        assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), k
    assert np.array_equal(a.header.offsets, g.origin) and np.array_equal(a.header.scales, src.header.scales)
    assert np.array_equal(a.header.offsets, b.header.offsets) and np.array_equal(a.header.scales, b.header.scales)
    assert a.header.point_format.id == 3 and a.header.point_count == n
    for k in ("intensity", "classification", "gps_time", "red", "green", "blue", "range_m", "return_number"):
        assert np.array_equal(np.asarray(a[k]), np.asarray(src[k])), k
    assert pyproj.CRS.from_user_input(a.header.parse_crs()) == pyproj.CRS.from_user_input("EPSG:5186")
    np.testing.assert_allclose(a.header.mins, np.column_stack([a.x, a.y, a.z]).min(axis=0))
    # the same through the library with small chunks
    chunks = streamable_map(mp, out)
    chunks.chunk_points = 997
    assert map_origin_auto(chunks) == n
    _, _, sample = stream_georeferenced_las(tmp_path / f"again{suffix}", chunks, g, n)
    c = laspy.read(str(tmp_path / f"again{suffix}"))
    for k in ("X", "Y", "Z", "intensity", "gps_time", "range_m"):
        assert np.array_equal(np.asarray(c[k]), np.asarray(a[k])), k
    assert sample.points.shape == (min(n, 20_000), 3)
