"""Damaged files (truncated, bytes flipped or inserted) raise only typed minegeo errors.

LAZ is left out: its decoder (lazrs) can spend seconds on garbage; the LAZ-specific header
checks are exercised by the LAS/LAZ tests.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from minegeo.errors import MinegeoError
from minegeo.io import PointCloud, read_point_cloud, write_point_cloud

CASES = [
    ("a.ply", {}),
    ("b.ply", {"encoding": "ascii"}),
    ("c.ply", {"encoding": "binary_big_endian"}),
    ("d.pcd", {}),
    ("e.pcd", {"encoding": "ascii"}),
    ("f.pcd", {"encoding": "binary_compressed"}),
    ("g.xyz", {}),
    ("h.csv", {}),
    ("i.pts", {}),
    ("j.3d", {}),
    ("k.las", {}),
]


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(3)
    c = PointCloud(
        rng.normal(size=(25, 3)),
        normals=rng.normal(size=(25, 3)),
        attributes={"rgb": rng.integers(0, 256, (25, 3)).astype(np.uint8), "intensity": rng.random(25).astype(np.float32)},
    )
    out = {}
    for name, kw in CASES:
        cc = PointCloud(c.points, attributes={"rgb": c.attributes["rgb"]}) if name.endswith(".las") else c
        write_point_cloud(d / name, cc, **kw)
        out[name] = (d / name).read_bytes()
    return d, out


@pytest.mark.parametrize("name", [c[0] for c in CASES])
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_damaged_files_raise_typed_errors(valid_files, name, data):
    d, files = valid_files
    b = bytearray(files[name])
    op = data.draw(st.sampled_from(["truncate", "flip", "insert"]))
    if op == "truncate":
        b = b[: data.draw(st.integers(0, len(b) - 1))]
    elif op == "flip":
        for _ in range(data.draw(st.integers(1, 4))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
    else:
        i = data.draw(st.integers(0, len(b)))
        b[i:i] = data.draw(st.binary(min_size=1, max_size=16))
    p = d / f"damaged_{name}"
    p.write_bytes(bytes(b))
    try:
        c = read_point_cloud(p)
    except MinegeoError:
        return
    assert np.isfinite(c.points).all()  # a cloud that loads has no NaN coordinates
