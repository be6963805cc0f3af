"""Damaged files (truncated, bytes flipped or inserted) raise only typed minegeo errors.

Every reader of user files is fuzzed: point clouds (PLY, PCD, LAS, XYZ/CSV/PTS/3D, zip),
trajectories (TUM, KITTI), control points, survey networks (Krumm text, JSON, ``.adj``),
MAST scans and beacons. The only allowed outcomes are a valid result or a
:class:`~minegeo.errors.MinegeoError`; a NumPy ``RuntimeWarning`` (overflow, invalid value)
is turned into an error and fails the test. Hypothesis is derandomised so CI is deterministic.

LAZ is left out: its decoder (lazrs) can spend seconds on garbage; the LAZ-specific header
checks are exercised by the LAS/LAZ tests.
"""

from __future__ import annotations

import json
import re
import warnings
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from minegeo.errors import MinegeoError
from minegeo.io import (
    ControlPoints,
    PointCloud,
    Trajectory,
    read_gcps,
    read_point_cloud,
    read_trajectory,
    write_gcps,
    write_point_cloud,
    write_trajectory,
)
from minegeo.io.adj import read_adj
from minegeo.io.network import read_network
from minegeo.mast import read_beacons_csv, read_scan_csv
from minegeo.mast.beacons import BeaconDesign, place_beacon, write_beacons_csv
from minegeo.mast.scan import Scan2D, write_scan_csv

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
@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
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
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # an overflow warning is a failure
        try:
            c = read_point_cloud(p)
        except MinegeoError:  # a damaged file refused with a typed error: the property holds
            c = None
    assert c is None or np.isfinite(c.points).all()  # a cloud that loads has no NaN coordinates


# --------------------------------------------------------------------------------------------
# every reader of user files: valid seeds, then random and mutated bytes
# --------------------------------------------------------------------------------------------
KRUMM = """[Project]
fuzz seed
[Coordinates]
A 1000.000 2000.000 100.000
B 1100.000 2000.000 101.000
C 1050.000 2080.000 99.500
[Datum]
fix A B
[Distances]
A C 94.340 0.002 0.0001
B C 94.340
[Angles,dms,s]
A B C 302°00'00" 3"
[Directions,gon,mgon]
C A 0.0000 1
C B 64.0000
[ZenithAngles,gon,mgon]
A C 100.5 1 1.5 1.6
[LevelledHeightDifferences]
A C -0.500 94.3 0.001
[3DBaseline]
A C 50.0 80.0 -0.5 0.001 0.001 0.002
"""

NETWORK_JSON = {
    "name": "fuzz",
    "points": {"A": {"x": 0.0, "y": 0.0, "h": 10.0}, "B": {"x": 100.0, "y": 0.0}, "C": {"x": 50.0, "y": 80.0}},
    "datum": {"type": "dyn", "sigma_m": {"xA": 0.01, "yA": 0.01, "B": 0.02}},
    "known_azimuths": [{"from": "A", "to": "B", "value_deg": 90.0}],
    "observations": [
        {"type": "distance", "from": "A", "to": "C", "value_m": 94.34, "sigma_m": 0.01},
        {"type": "angle", "at": "C", "from": "A", "to": "B", "value_dms": "64°00'00\"", "sigma_arcsec": 5},
        {"type": "direction", "at": "C", "to": "A", "set": 1, "value_gon": 0.0, "sigma_mgon": 1},
        {"type": "height_difference", "from": "A", "to": "C", "value_m": -0.5, "sigma_m": 0.001},
        {"type": "baseline", "from": "A", "to": "C", "value_m": [50, 80, -0.5], "cov_m2": [[1e-6, 0, 0], [0, 1e-6, 0],
                                                                                        [0, 0, 1e-6]]},
    ],
}

ADJ = """# adjusted coordinates
A 1000.0000 0.0 0.1 2000.0000 0.0 0.1 0.2
C 1050.0000 0.1 0.2 2080.0000 0.1 0.2 0.3 99.5 0.0 0.1
H1 100.000 0.1 0.2
"""

#: tokens a damaged or hostile text file may hold at a random place
NASTY = [b"1e308", b"-1e308", b"nan", b"inf", b"1e400", b"9" * 40, b"\n", b",", b";", b" ", b"#", b"[", b"]",
         b"{", b"}", b'"', b"\x00", b"\xff", b"-", b"1e-308", b"0", b"[Datum]", b"NaN", b"Infinity", b'"A": 1,']


def _reader(kind):
    return {
        "tum": lambda p: read_trajectory(p),
        "kitti": lambda p: read_trajectory(p),
        "gcp": lambda p: read_gcps(p),
        "net.dat": lambda p: read_network(p),
        "net.json": lambda p: read_network(p),
        "adj": lambda p: read_adj(p),
        "scan": lambda p: read_scan_csv(p),
        "beacons": lambda p: read_beacons_csv(p),
        "zip": lambda p: read_point_cloud(p),
        "xyz": lambda p: read_point_cloud(p),
        "ply": lambda p: read_point_cloud(p),
        "pcd": lambda p: read_point_cloud(p),
    }[kind]


READER_FILES = {
    "tum": "t.tum",
    "kitti": "t.kitti",
    "gcp": "g.csv",
    "net.dat": "n.dat",
    "net.json": "n.json",
    "adj": "n.adj",
    "scan": "scan.csv",
    "beacons": "beacons.csv",
    "zip": "c.xyz.zip",
    "xyz": "c.xyz",
    "ply": "c.ply",
    "pcd": "c.pcd",
}


@pytest.fixture(scope="module")
def reader_seeds(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_readers")
    rng = np.random.default_rng(5)
    m = 6
    poses = np.tile(np.eye(4), (m, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(m, 3)) * 10
    tr = Trajectory(times_s=np.arange(m, dtype=float) * 0.1, poses=poses)
    write_trajectory(d / "t.tum", tr)
    write_trajectory(d / "t.kitti", tr)
    write_gcps(
        d / "g.csv",
        ControlPoints(
            ids=["G1", "G2", "G3", "G4"],
            local_xyz=rng.normal(size=(4, 3)) * 10,
            crs_enh=rng.normal(size=(4, 3)) * 10 + [200000, 550000, 80],
            sigma_enh_m=np.full((4, 3), 0.01),
            crs="EPSG:5186",
        ),
    )
    (d / "n.dat").write_text(KRUMM, encoding="utf-8")
    (d / "n.json").write_text(json.dumps(NETWORK_JSON, indent=1), encoding="utf-8")
    (d / "n.adj").write_text(ADJ, encoding="utf-8")
    b = np.sort(rng.uniform(0, 360, 40))
    write_scan_csv(d / "scan.csv", Scan2D(b, rng.uniform(1, 20, 40), 0.003, 0.01))
    design = BeaconDesign()
    write_beacons_csv(d / "beacons.csv", [place_beacon(design, "B1", (5, 5), 0, "left"),
                                          place_beacon(design, "B2", (-5, 8), 90, "right")])
    c = PointCloud(rng.normal(size=(12, 3)), attributes={"intensity": rng.random(12)})
    write_point_cloud(d / "c.xyz", c)
    write_point_cloud(d / "c.ply", c, encoding="ascii")
    write_point_cloud(d / "c.pcd", c, encoding="ascii")
    with zipfile.ZipFile(d / "c.xyz.zip", "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.write(d / "c.xyz", "c.xyz")
    seeds = {k: (d / name).read_bytes() for k, name in READER_FILES.items()}
    for k in seeds:  # the seeds themselves are valid
        _reader(k)(d / READER_FILES[k])
    return d, seeds


#: replacements of one whole token (number, name, JSON value) of a text file
TOKENS = [b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"1e-308", b"0", b"-1", b"1e400", b"abc", b"", b"null", b"true",
          b"[]", b"{}", b'"x"', b"[1, 2]", b'{"a": 1}', b"NaN", b"-Infinity", b"360", b"400.5", b"9" * 30]
_TOKEN_RE = re.compile(rb"(\s+|[,;:\[\]{}])")


def _mutate(data, b: bytearray) -> bytes:
    op = data.draw(st.sampled_from(["truncate", "flip", "insert", "nasty", "token", "token", "duplicate_line"]))
    if not b:
        return bytes(b)
    if op == "token":  # replace whole tokens: reaches the value checks behind the syntax checks
        parts = _TOKEN_RE.split(bytes(b))
        words = [i for i, t in enumerate(parts) if t and not _TOKEN_RE.fullmatch(t)]
        for _ in range(data.draw(st.integers(1, 2))):
            parts[data.draw(st.sampled_from(words))] = data.draw(st.sampled_from(TOKENS))
        return b"".join(parts)
    if op == "truncate":
        del b[data.draw(st.integers(0, len(b) - 1)) :]
    elif op == "flip":
        for _ in range(data.draw(st.integers(1, 4))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
    elif op == "insert":
        i = data.draw(st.integers(0, len(b)))
        b[i:i] = data.draw(st.binary(min_size=1, max_size=16))
    elif op == "nasty":
        for _ in range(data.draw(st.integers(1, 3))):
            i = data.draw(st.integers(0, len(b)))
            j = min(len(b), i + data.draw(st.integers(0, 6)))
            b[i:j] = data.draw(st.sampled_from(NASTY))
    else:
        lines = bytes(b).split(b"\n")
        k = data.draw(st.integers(0, len(lines) - 1))
        lines.insert(k, lines[k])
        b = bytearray(b"\n".join(lines))
    return bytes(b)


def _check_reader(kind, path):
    """A valid result or a MinegeoError; a RuntimeWarning or any other exception fails."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            out = _reader(kind)(path)
        except MinegeoError:
            return None
        # what every caller does next (extent, time span) must not overflow either
        if isinstance(out, PointCloud):
            assert np.isfinite(out.points).all()
            if len(out):
                g = out.global_points
                assert np.isfinite(np.ptp(g, axis=0)).all()
        elif isinstance(out, Trajectory):
            assert np.isfinite(out.poses).all() and np.isfinite(out.times_s).all()
            assert np.isfinite(np.diff(out.times_s)).all() and np.isfinite(np.ptp(out.positions, axis=0)).all()
    return out


#: kinds whose seed is text: every token is replaced in turn (exhaustive, deterministic)
TEXT_KINDS = ["tum", "kitti", "gcp", "net.dat", "net.json", "adj", "scan", "beacons", "xyz", "ply", "pcd"]


@pytest.mark.parametrize("kind", TEXT_KINDS)
def test_every_token_replaced(reader_seeds, kind):
    """Each token of the valid seed replaced by each hostile value, one at a time."""
    d, seeds = reader_seeds
    parts = _TOKEN_RE.split(seeds[kind])
    words = [i for i, t in enumerate(parts) if t and not _TOKEN_RE.fullmatch(t)]
    p = d / f"tok_{READER_FILES[kind]}"
    for i in words:
        for tok in (b"nan", b"inf", b"1e308", b"-1e308", b"1e-308", b"-1", b"0", b"x"):
            q = list(parts)
            q[i] = tok
            p.write_bytes(b"".join(q))
            _check_reader(kind, p)


@pytest.mark.parametrize("kind", list(READER_FILES))
@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_files_every_reader(reader_seeds, kind, data):
    d, seeds = reader_seeds
    raw = _mutate(data, bytearray(seeds[kind]))
    p = d / f"mut_{READER_FILES[kind]}"
    p.write_bytes(raw)
    _check_reader(kind, p)


@pytest.mark.parametrize("kind", list(READER_FILES))
@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.one_of(
    st.binary(max_size=600),
    st.lists(st.sampled_from(NASTY + [b"1", b"2.5", b"-3", b"A", b"x y z"]), max_size=60).map(b"".join),
))
def test_random_bytes_every_reader(reader_seeds, kind, raw):
    d, _ = reader_seeds
    p = d / f"rnd_{READER_FILES[kind]}"
    p.write_bytes(raw)
    _check_reader(kind, p)


#: any JSON value, nested a little
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**6), 10**6) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_json_network_with_any_member_replaced(reader_seeds, data):
    """Valid JSON of the wrong shape: each member of the network replaced by any JSON value."""
    d, _ = reader_seeds
    doc = json.loads(json.dumps(NETWORK_JSON))
    paths = [p for p in _paths(doc) if p]
    for _ in range(data.draw(st.integers(1, 2))):
        path = data.draw(st.sampled_from(paths))
        node = doc
        try:
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = data.draw(JSON_VALUES)
        except (KeyError, IndexError, TypeError):
            pass  # an earlier replacement removed this path
    p = d / "shape.json"
    p.write_text(json.dumps(doc), encoding="utf-8")
    _check_reader("net.json", p)
