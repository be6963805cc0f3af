"""Trajectories, survey map, local scans, control points, write_world and the ``minegeo synth`` CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from minegeo.cli import main
from minegeo.errors import InputError
from minegeo.synth import (
    MINE_LAT_DEG,
    MINE_LON_DEG,
    FlashSensor,
    Velodyne16,
    ZebRevo,
    build_map,
    build_world,
    local_scan,
    make_gcps,
    make_trajectory,
)
from minegeo.synth.trajectory import _arc_lengths


@pytest.fixture(scope="module")
def world():
    return build_world("small", 1)


@pytest.mark.parametrize("kind", ["walk", "drive", "fly"])
def test_trajectory_kinds(world, kind):
    tr = make_trajectory(world, kind, start="curve", length_m=15.0, seed=3)
    R = tr.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.all(np.diff(tr.times_s) > 0)
    p = tr.positions
    assert world.sdf(p).min() > 0.3  # clear of rock and structures
    path_len = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum()
    assert 13.0 < path_len < 19.0
    # repeatable
    tr2 = make_trajectory(world, kind, start="curve", length_m=15.0, seed=3)
    assert np.array_equal(tr.poses, tr2.poses)


def test_trajectory_passes_parked_vehicle(world):
    """The route through the regular section passes the parked vehicle without touching it."""
    tr = make_trajectory(world, "drive", start="regular", length_m=20.0, seed=1)
    assert world.sdf(tr.positions).min() > 0.3


@pytest.mark.parametrize("length_m", [10.0, 20.0, 30.0])
def test_local_scan_lengths_and_truth(world, length_m):
    sensor = ZebRevo(angular_step_deg=2.0, range_noise_sigma_m=0.0)
    cloud, traj, T_map_scan = local_scan(world, "intersection:X", length_m, sensor, seed=2, max_rays=6000)
    assert cloud.frame == "scan" and traj.frame == "scan"
    np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-12)
    travelled = np.linalg.norm(np.diff(traj.positions[:, :2], axis=0), axis=1).sum()
    assert 0.85 * length_m < travelled < 1.2 * length_m
    P = cloud.points @ T_map_scan[:3, :3].T + T_map_scan[:3, 3]
    assert np.abs(world.sdf(P)).max() < 2e-3
    # the trajectory mapped by T_map_scan lies in the drift (sensor height above the floor)
    pm = traj.positions @ T_map_scan[:3, :3].T + T_map_scan[:3, 3]
    assert world.sdf(pm).min() > 0.3


def test_local_scan_sections_and_sensors(world):
    for section, sensor, kind in [("irregular_roof", Velodyne16(azimuth_step_deg=2.0), "walk"),
                                  ("sump", FlashSensor(width_px=32, height_px=24), "handheld"),
                                  ("regular", ZebRevo(angular_step_deg=2.0), "fly")]:
        cloud, traj, T = local_scan(world, section, 10.0, sensor, seed=1, kind=kind, max_rays=8000)
        assert len(cloud) > 500
        P = cloud.points @ T[:3, :3].T + T[:3, 3]
        assert np.abs(world.sdf(P)).max() < 6 * sensor.range_noise_sigma_m * 2.5
    with pytest.raises(InputError):
        local_scan(world, "nowhere", 10.0, Velodyne16(), seed=1)
    with pytest.raises(InputError):
        local_scan(world, "regular", 0.0, Velodyne16(), seed=1)


def test_survey_map_covers_every_drift(world):
    cloud = build_map(world, seed=4, sensor=Velodyne16(azimuth_step_deg=6.0, range_noise_sigma_m=0.0),
                      spacing_m=14.0)
    assert cloud.frame == "map"
    assert np.abs(world.sdf(cloud.points)).max() < 2e-3
    from scipy.spatial import cKDTree

    tree = cKDTree(cloud.points)
    for d in world.drifts:
        S = _arc_lengths(d.centreline)
        mid = np.array([np.interp(S[-1] / 2, S, d.centreline[:, i]) for i in range(3)])
        dist, _ = tree.query(mid + [0, 0, 1.0])
        assert dist < 4.0, d.name


def test_survey_map_passes_interleave_frames(world):
    """build_survey_map: one pass is build_map itself; a second pass adds frames half-way between
    (first mark = spacing, its own noise seed) on the same carrier path, appended after pass 0."""
    from minegeo.synth.dataset import build_survey_map

    one = build_survey_map(world, seed=4, passes=1, spacing_m=20.0)
    ref = build_map(world, seed=4, spacing_m=20.0)
    assert np.array_equal(one.points, ref.points)
    two = build_survey_map(world, seed=4, passes=2, spacing_m=20.0)
    extra = build_map(world, seed=4, spacing_m=20.0, first_mark_m=20.0, noise_seed=6)
    assert len(two) == len(ref) + len(extra) and two.frame == "map"
    assert np.array_equal(two.points[: len(ref)], ref.points) and np.array_equal(two.points[len(ref):], extra.points)
    assert np.array_equal(two.attributes["time_s"][len(ref):], extra.attributes["time_s"])
    # the extra frames sit between the first pass's frames (survey times interleave)
    t1, t2 = np.unique(ref.attributes["time_s"].round(1)), np.unique(extra.attributes["time_s"].round(1))
    assert not set(t1.tolist()) & set(t2.tolist())
    with pytest.raises(InputError):
        build_survey_map(world, passes=0)
    with pytest.raises(InputError):
        build_map(world, first_mark_m=-1.0)


def test_gcps_crs_consistent_with_pyproj(world):
    from pyproj import Transformer

    gcps, info = make_gcps(world, n=8, seed=5, crs="EPSG:5186", sigma_m=0.005)
    assert gcps.crs == "EPSG:5186" and len(gcps) == 8
    T = np.asarray(info["T_crs_map"])
    E0, N0 = Transformer.from_crs("EPSG:4326", "EPSG:5186", always_xy=True).transform(MINE_LON_DEG, MINE_LAT_DEG)
    assert abs(T[0, 3] - E0) < 1e-3 and abs(T[1, 3] - N0) < 1e-3
    assert 150 <= T[2, 3] <= 250
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(R[2, 2] - 1) < 1e-12  # rotation about the vertical only
    res = gcps.crs_enh - (gcps.local_xyz @ R.T + T[:3, 3])
    assert np.abs(res).max() < 5 * 0.005 and res.std() > 0.001
    # control points are on the rock walls, 1.2-1.6 m above the floor
    assert np.abs(world.sdf(gcps.local_xyz)).max() < 2e-3
    assert np.all(world.sdf(gcps.local_xyz, with_structures=False) < 2e-3)
    # back to geographic: at the Gwan-in mine, 38 07' N, 127 13' E
    lon, lat = Transformer.from_crs("EPSG:5186", "EPSG:4326", always_xy=True).transform(
        gcps.crs_enh[:, 0], gcps.crs_enh[:, 1])
    assert np.all(np.abs(lat - MINE_LAT_DEG) < 0.01) and np.all(np.abs(lon - MINE_LON_DEG) < 0.01)
    with pytest.raises(Exception):  # noqa: B017 - CRSError for an unknown CRS
        make_gcps(world, n=4, seed=1, crs="EPSG:999999")


@pytest.mark.slow
def test_cli_end_to_end_deterministic(tmp_path, capsys):
    """Acceptance: ``minegeo synth OUT --preset small --seed 1`` twice gives byte-identical files."""
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["synth", str(a), "--preset", "small", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "map.ply" in out and "scan_00" in out
    assert main(["synth", str(b), "--preset", "small", "--seed", "1"]) == 0
    fa = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    assert fa == fb
    assert {"map.ply", "gcps.csv", "truth.json", "report.txt", "trajectories/survey.txt"} <= set(fa)
    assert sum(f.startswith("scans/") for f in fa) >= 3
    for f in fa:
        if f != "result.json":  # the run record: its time and folder (tests/cli/test_config.py)
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    truth = json.loads((a / "truth.json").read_text())
    text = (a / "truth.json").read_text()
    assert str(tmp_path) not in text and "created_utc" not in text
    assert truth["crs"] == "EPSG:5186" and len(truth["scans"]) >= 3
    for s in truth["scans"]:
        T = np.array(s["T_map_scan"])
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    # the files read back with minegeo.io, and a scan mapped by its truth lies on the map's surface
    from minegeo.io import read_gcps, read_point_cloud, read_trajectory

    m = read_point_cloud(a / "map.ply")
    assert len(m) == truth["map"]["n_points"]
    sc = read_point_cloud(a / truth["scans"][0]["file"])
    tr = read_trajectory(a / truth["scans"][0]["trajectory"])
    assert len(tr) > 10
    g = read_gcps(a / "gcps.csv")
    assert len(g) == truth["gcps"]["n"]
    w = build_world("small", 1)
    T = np.array(truth["scans"][0]["T_map_scan"])
    P = sc.points @ T[:3, :3].T + T[:3, 3]
    assert np.median(np.abs(w.sdf(P))) < 0.05
    # refuses a non-empty directory without --force (one line on stderr, exit 2)
    assert main(["synth", str(a), "--seed", "1"]) == 2
    assert "--force" in capsys.readouterr().err
