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
