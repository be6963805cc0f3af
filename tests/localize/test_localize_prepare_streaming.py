"""Chunked map preparation (:func:`minegeo.localize.prepared.prepare_map_file`, ``prepare-map
--chunk-points``): bit-identical to the in-memory path, memory flat in the input size."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from helpers import require_extra

from minegeo.geometry import octree_downsample, voxel_downsample
from minegeo.geometry.stream import OctreeAccumulator, VoxelAccumulator
from minegeo.io import write_point_cloud
from minegeo.io.types import PointCloud
from minegeo.localize.params import PrepareParams
from minegeo.localize.prepared import MemoryLimitError, load_map_cloud, prepare_map, prepare_map_file

ARRAYS = ("points", "normals", "features", "icp_points", "icp_normals", "work_origin")
FORMATS = {"ply": ("map.ply", {}), "ply_ascii": ("map.ply", {"binary": False}), "pcd": ("map.pcd", {}),
           "las": ("map.las", {}), "laz": ("map.laz", {})}
VOXEL = PrepareParams.fast()
OCTREE = PrepareParams(voxel_size_m=None, octree_level=8, features=VOXEL.features)


def _drift(n, seed=0, length=40.0, offset=(0.37, -2.1, 0.05)):
    """Points on the walls of a 5 m x 4 m drift ``length`` long (float64, map frame).

    A small offset keeps every mantissa bit in use: with a projected offset (10^6 m) the work-frame
    coordinates are multiples of 2^-35 m and short voxel sums are exact in any order, so a wrong
    summation order would go unnoticed (the georeferenced test covers large offsets)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, length, n)
    t = rng.uniform(0.0, 18.0, n)
    y = np.where(t < 5, t, np.where(t < 9, 5.0, np.where(t < 14, 14.0 - t, 0.0)))
    z = np.where(t < 5, 0.0, np.where(t < 9, t - 5.0, np.where(t < 14, 4.0, 18.0 - t)))
    P = np.column_stack([x, y, z]) + rng.normal(0, 0.01, (n, 3))
    return P + np.asarray(offset)


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("stream")
    cloud = PointCloud(points=_drift(12_000), crs="EPSG:5186")
    out = {}
    for key, (name, kw) in FORMATS.items():
        p = d / f"{key}_{name}"
        write_point_cloud(p, cloud, **kw)
        out[key] = p
    return out


def _same(a, b):
    for f in ARRAYS:
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert a.crs == b.crs and a.params_hash == b.params_hash


@pytest.mark.parametrize("key", sorted(FORMATS))
@pytest.mark.parametrize("params", [VOXEL, OCTREE], ids=["voxel", "octree"])
def test_streaming_is_bit_identical(maps, key, params):
    cloud, g = load_map_cloud(maps[key])
    ref = prepare_map(cloud, params, georef=g)
    for chunk in (997, 5000, 10**6):
        pm = prepare_map_file(maps[key], params, chunk_points=chunk)
        _same(ref, pm)
        s = pm.source["streaming"]
        # text blocks end on whole lines, so an ascii file may give a few more (shorter) chunks
        assert s["chunk_points"] == chunk and s["n_chunks"] >= -(-12_000 // chunk) and not s["read_whole"]
        assert pm.source["n_points"] == 12_000


def test_one_point_chunks_and_every_point_icp(tmp_path):
    p = tmp_path / "tiny.ply"
    write_point_cloud(p, PointCloud(points=_drift(400, seed=3)))
    for params in (PrepareParams(voxel_size_m=0.5, features=VOXEL.features, icp_voxel_size_m=None),
                   PrepareParams(voxel_size_m=None, octree_level=6, features=VOXEL.features)):
        cloud, _ = load_map_cloud(p)
        _same(prepare_map(cloud, params), prepare_map_file(p, params, chunk_points=1))


def test_georeferenced_map_streams(tmp_path):
    from minegeo.georef import apply_georef, georeference, write_georeferenced_map
    from minegeo.synth import build_map, build_world, make_gcps

    world = build_world("small", 0)
    cloud = build_map(world, seed=1)
    gcps, _ = make_gcps(world, n=8, seed=2)
    g = georeference(gcps)
    geo = tmp_path / "map_geo.ply"
    write_georeferenced_map(geo, apply_georef(cloud, g), g)
    mc, mg = load_map_cloud(geo)
    ref = prepare_map(mc, VOXEL, georef=mg)
    pm = prepare_map_file(geo, VOXEL, chunk_points=30_001)
    _same(ref, pm)
    assert pm.georef == ref.georef


@pytest.mark.parametrize("chunk", [1, 13, 4096, 10**6])
def test_accumulators_match_in_memory_downsampling(chunk):
    rng = np.random.default_rng(5)
    P = rng.normal(size=(3000, 3)) * [20.0, 3.0, 2.0] + [0.25, -3.0, 7.0]
    P = np.concatenate([P, P[:500], P[100:300]])  # repeated points: ties and long sums
    for v in (0.05, 0.7):
        acc = VoxelAccumulator(P.min(0), P.max(0), v)
        for i in range(0, len(P), chunk):
            acc.add(P[i : i + chunk])
        pts, cnt, keys = acc.result()
        ref = voxel_downsample(P, v)
        assert np.array_equal(pts, ref.points) and np.array_equal(cnt, ref.counts)
        assert np.array_equal(keys, ref.voxel_keys)
    for level in (3, 9):
        acc = OctreeAccumulator(P.min(0), P.max(0), level)
        for i in range(0, len(P), chunk):
            acc.add(P[i : i + chunk])
        pts, idx, codes, cnt = acc.result()
        ref = octree_downsample(P, level)
        assert np.array_equal(idx, ref.indices) and np.array_equal(pts, ref.points)
        assert np.array_equal(codes, ref.node_codes) and np.array_equal(cnt, ref.counts)


def test_memory_ceiling_refuses_clearly(maps):
    with pytest.raises(MemoryLimitError, match="max-memory-gb"):
        prepare_map_file(maps["ply"], VOXEL, max_memory_gb=0.001)


def test_cli_records_chunking(maps, tmp_path, capsys):
    from minegeo.cli import main

    out = tmp_path / "p.npz"
    code = main(["-q", "prepare-map", "--map", str(maps["las"]), "--out", str(out), "--profile", "fast",
                 "--chunk-points", "2500", "--max-memory-gb", "16"])
    assert code == 0
    rec = json.loads(out.with_name("p.npz.json").read_text())
    assert rec["streaming"]["chunk_points"] == 2500 and rec["streaming"]["n_chunks"] == 5
    assert rec["streaming"]["max_memory_gb"] == 16 and rec["n_points"] == 12_000


_CHILD = textwrap.dedent("""
    import sys, tracemalloc
    import numpy as np
    from minegeo.localize.params import PrepareParams
    from minegeo.localize.prepared import prepare_map_file
    p, chunk = sys.argv[1], int(sys.argv[2])
    params = PrepareParams(voxel_size_m=0.5, features=PrepareParams.fast().features, icp_voxel_size_m=0.25)
    prepare_map_file(p, params, chunk_points=chunk)  # compile the kernels first
    peak = {}

    def progress(step):  # the reading passes end when the normals start
        if step == "normals":
            peak["read"] = tracemalloc.get_traced_memory()[1]

    tracemalloc.start()
    prepare_map_file(p, params, chunk_points=chunk, progress=progress)
    print(peak["read"], tracemalloc.get_traced_memory()[1])
""")


def test_peak_memory_flat_when_input_grows_tenfold(tmp_path):
    """Same extent, 10x the points: the traced peak (NumPy allocations) of the reading passes and of
    the whole preparation must not grow with the input (a reader that kept the whole cloud would
    add >= 24 B x 900 000 points)."""
    peaks = []
    for n in (100_000, 1_000_000):
        p = tmp_path / f"m{n}.ply"
        P = _drift(n, seed=7, length=20.0)
        o = np.round(P.mean(axis=0))
        write_point_cloud(p, PointCloud(points=P - o, origin=o), dtype="float32", coordinates="local")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
        r = subprocess.run([sys.executable, "-c", _CHILD, str(p), "50000"], capture_output=True, text=True,
                           timeout=600, env=env, check=True)
        peaks.append([int(v) for v in r.stdout.split()[-2:]])
    (read1, all1), (read10, all10) = peaks
    assert read10 < read1 + 4_000_000, peaks  # reading + downsampling: one chunk + the cell tables
    assert all10 < all1 + 4_000_000, peaks  # the whole preparation


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


def test_load_or_prepare_streams_map_files(maps, tmp_path):
    """``localize --map MAP_FILE`` prepares through the chunked path (then its cache)."""
    import shutil

    from minegeo.localize.prepared import load_or_prepare

    p = tmp_path / "m.ply"
    shutil.copy(maps["ply"], p)
    pm, how = load_or_prepare(p, VOXEL)
    assert how == "computed" and "streaming" in pm.source and pm.source["sha256"]
    cloud, _ = load_map_cloud(p)
    _same(prepare_map(cloud, VOXEL), pm)
    assert load_or_prepare(p, VOXEL)[1] == "cache"


def test_e57_map_streams(tmp_path):
    """An E57 map (two scans with poses, written by pye57) prepares through ``iter_e57_chunks``."""
    pye57 = require_extra("pye57")
    p = tmp_path / "map.e57"
    P = _drift(6000, seed=9).astype(np.float32).astype(np.float64)
    with pye57.E57(str(p), mode="w") as e:
        for i, part in enumerate((P[:3500], P[3500:])):
            e.write_scan_raw({"cartesianX": part[:, 0], "cartesianY": part[:, 1], "cartesianZ": part[:, 2]},
                             name=f"station {i + 1}", rotation=np.array([1.0, 0.0, 0.0, 0.0]),
                             translation=np.array([0.5 * i, 0.0, 0.0]))
    cloud, _ = load_map_cloud(p)
    for params in (VOXEL, OCTREE):
        pm = prepare_map_file(p, params, chunk_points=1000)
        _same(prepare_map(cloud, params), pm)
        assert pm.source["streaming"]["format"] == "e57" and pm.source["n_points"] == 6000


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
