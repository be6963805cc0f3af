"""Chunked point-cloud reading (:mod:`minegeo.io.chunked`): the chunks of every format are the
whole-file reader's points bit for bit; damaged files are typed errors."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import FileFormatError, InputError, OptionalDependencyError
from minegeo.io import read_point_cloud, write_point_cloud
from minegeo.io.chunked import iter_point_chunks, open_point_chunks, scan_bounds
from minegeo.io.types import PointCloud

N = 1003
CASES = {
    "ply_le": ("m.ply", {"binary": True}),
    "ply_be_f32": ("m.ply", {"encoding": "binary_big_endian", "dtype": "float32"}),
    "ply_ascii": ("m.ply", {"binary": False}),
    "ply_ascii_f32": ("m.ply", {"binary": False, "dtype": "float32"}),
    "ply_local": ("m.ply", {"binary": True, "coordinates": "local"}),
    "pcd_bin": ("m.pcd", {"binary": True}),
    "pcd_ascii": ("m.pcd", {"binary": False}),
    "pcd_compressed": ("m.pcd", {"encoding": "binary_compressed"}),
    "las": ("m.las", {}),
    "laz": ("m.laz", {}),
    "xyz": ("m.xyz", {}),
}


def _cloud(n=N, seed=0):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 3)) * [40.0, 8.0, 3.0] + [1234.5, -77.25, 12.0]
    return PointCloud(points=P, crs="EPSG:5186", origin=np.array([1000.0, 0.0, 0.0]),
                      attributes={"intensity": rng.integers(0, 255, n).astype(np.uint16)})


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("chunked")
    out = {}
    for key, (name, kw) in CASES.items():
        p = d / f"{key}_{name}"
        write_point_cloud(p, _cloud(), **kw)
        out[key] = p
    return out


@pytest.mark.parametrize("key", sorted(CASES))
@pytest.mark.parametrize("chunk", [1, 7, N - 1, N, 10 * N])
def test_chunks_are_the_whole_read(files, key, chunk):
    p = files[key]
    ref = read_point_cloud(p).points
    src = open_point_chunks(p, chunk)
    parts = list(src)
    assert all(c.dtype == np.float64 and c.ndim == 2 and c.shape[1] == 3 for c in parts)
    assert max(c.shape[0] for c in parts) <= chunk
    got = np.concatenate(parts)
    assert np.array_equal(got, ref)
    assert src.crs == "EPSG:5186" and src.n_points == N
    assert src.bytes_read == src.size_bytes
    assert np.array_equal(np.concatenate(list(src)), ref)  # a second pass reads the same


@pytest.mark.parametrize("key", ["ply_le", "ply_local", "las", "pcd_ascii"])
def test_origin_and_bounds_as_whole_read(files, key):
    o = np.array([1200.0, -70.0, 10.0])
    ref = read_point_cloud(files[key], origin=o).points
    assert np.array_equal(np.concatenate(list(iter_point_chunks(files[key], 100, origin=o))), ref)
    n, lo, hi = scan_bounds(open_point_chunks(files[key], 64, origin=o))
    assert n == N and np.array_equal(lo, ref.min(axis=0)) and np.array_equal(hi, ref.max(axis=0))


def _truncate(src, dst, keep_frac):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep_frac)])
    return dst


@pytest.mark.parametrize("key", ["ply_le", "ply_ascii", "pcd_bin", "pcd_ascii", "las", "laz"])
def test_truncated_file_is_a_typed_error(files, key, tmp_path):
    p = _truncate(files[key], tmp_path / files[key].name, 0.6)
    with pytest.raises(FileFormatError):
        for _ in open_point_chunks(p, 50):
            pass


def test_nan_and_bad_arguments(tmp_path):
    c = _cloud(50)
    c.points[31, 1] = np.nan
    p = tmp_path / "nan.ply"
    write_point_cloud(p, c)
    with pytest.raises(FileFormatError, match="point 31"):
        list(open_point_chunks(p, 8))
    with pytest.raises(InputError):
        open_point_chunks(p, 0)
    with pytest.raises(InputError):
        open_point_chunks(tmp_path / "missing.ply", 10)


def test_e57_without_the_extra_names_it(tmp_path, monkeypatch):
    """An E57 map on an installation without pye57: the one-line error names the extra to install."""
    import builtins

    p = tmp_path / "m.e57"
    p.write_bytes(b"ASTM-E57" + b"\0" * 100)
    real_import = builtins.__import__

    def no_pye57(name, *args, **kwargs):
        if name == "pye57" or name.startswith("pye57."):
            raise ImportError("No module named 'pye57' (simulated)")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pye57)
    with pytest.raises(OptionalDependencyError, match=r"minegeo\[e57\]"):
        open_point_chunks(p, 10)


@pytest.mark.parametrize("key", ["las", "laz"])
def test_corrupt_las_header_counts_refused_before_laspy(files, key, tmp_path):
    """A huge VLR count (laspy would loop on it) and, for LAZ, a chunk-table pointer outside the
    file are refused as the whole-file reader refuses them."""
    data = bytearray(files[key].read_bytes())
    bad = tmp_path / f"vlr.{key}"
    bad.write_bytes(bytes(data[:100]) + b"\xff\xff\xff\x7f" + bytes(data[104:]))
    with pytest.raises(FileFormatError, match="VLR"):
        open_point_chunks(bad, 100)
    if key == "laz":
        off = int.from_bytes(data[96:100], "little")
        data[off : off + 8] = (len(data) + 1000).to_bytes(8, "little", signed=True)
        bad.write_bytes(bytes(data))
        with pytest.raises(FileFormatError, match="chunk table"):
            list(open_point_chunks(bad, 100))
