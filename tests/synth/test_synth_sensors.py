"""Sensor simulation: points on the surface, max range, no returns through walls, noise, motion, 2D."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.synth import (
    FlashSensor,
    Horizontal2D,
    Velodyne16,
    ZebRevo,
    build_world,
    deskew,
    make_trajectory,
    simulate_scan,
    simulate_scan_2d,
)
from minegeo.synth.trajectory import _arc_lengths


@pytest.fixture(scope="module")
def world():
    return build_world("small", 1)


def _pose(world, feature="regular", ds=0.0, height=1.6):
    f = world.features[feature]
    P = world.drifts[f["drift"]].centreline
    S = _arc_lengths(P)
    s = f["s_m"] + ds
    q = np.array([np.interp(s, S, P[:, i]) for i in range(3)])
    k = int(np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(P) - 2))
    t = P[k + 1] - P[k]
    t[2] = 0
    t /= np.linalg.norm(t)
    T = np.eye(4)
    T[:3, 0] = t
    T[:3, 1] = [-t[1], t[0], 0]
    T[:3, 2] = [0, 0, 1]
    T[:3, 3] = q + [0, 0, height] - 1.0 * T[:3, 1]  # right of the parked vehicle
    return T


SENSORS = [
    Velodyne16(azimuth_step_deg=1.0),
    ZebRevo(angular_step_deg=1.0),
    FlashSensor(width_px=48, height_px=36),
    Horizontal2D(angular_step_deg=0.5),
]


def _world_points(cloud, T):
    return cloud.points @ T[:3, :3].T + T[:3, 3]


@pytest.mark.parametrize("sensor", SENSORS, ids=lambda s: s.name)
def test_noise_free_points_lie_on_surface_within_range_and_not_through_walls(world, sensor):
    sensor = replace(sensor, range_noise_sigma_m=0.0)
    T = _pose(world, "irregular_roof")
    cloud = simulate_scan(world, sensor, T, seed=3)
    assert len(cloud) > 100
    rng_m = np.linalg.norm(cloud.points, axis=1)
    np.testing.assert_allclose(rng_m, cloud.attributes["range_m"], rtol=0, atol=1e-9)
    assert rng_m.max() <= sensor.max_range_m
    assert rng_m.min() >= sensor.min_range_m
    P = _world_points(cloud, T)
    # on the surface: the field vanishes (bisection bracket 1e-4 m)
    f = world.sdf(P)
    assert np.abs(f).max() < 2e-3
    # nothing seen through rock: the segment sensor -> hit stays in free space
    o = T[:3, 3]
    sub = P[:: max(1, len(P) // 400)]
    u = np.linspace(0.0, 1.0, 200)[:-1]
    seg = o + u[None, :, None] * (sub - o)[:, None, :]  # (k, 199, 3) samples sensor -> hit
    near_hit = np.linalg.norm(seg - sub[:, None, :], axis=2) <= 0.01
    f_seg = world.sdf(seg.reshape(-1, 3)).reshape(seg.shape[:2])
    assert f_seg[~near_hit].min() > -1e-3


def test_full_spec_velodyne_one_revolution(world):
    s = Velodyne16()
    assert (s.n_rings, s.azimuth_step_deg, s.max_range_m, s.range_noise_sigma_m) == (16, 0.2, 100.0, 0.03)
    T = _pose(world, "regular")
    cloud = simulate_scan(world, replace(s, range_noise_sigma_m=0.0), T, seed=1)
    assert 20000 < len(cloud) <= 16 * 1800
    assert set(np.unique(cloud.attributes["ring"])) == set(range(16))
    el = np.degrees(np.arcsin(cloud.points[:, 2] / np.linalg.norm(cloud.points, axis=1)))
    assert el.min() >= -15.0 - 1e-6 and el.max() <= 15.0 + 1e-6
    t = cloud.attributes["time_s"]
    assert t.min() >= 0 and t.max() < 0.1  # one rotation at 10 Hz
    # the other level (15 m below) is never seen from level 0
    assert _world_points(cloud, T)[:, 2].min() > T[2, 3] - 1.6 - 1.5
    assert np.abs(world.sdf(_world_points(cloud, T))).max() < 2e-3


def test_range_noise_is_added_along_the_ray(world):
    s = Velodyne16(azimuth_step_deg=2.0)
    T = _pose(world, "regular")
    clean = simulate_scan(world, replace(s, range_noise_sigma_m=0.0), T, seed=4)
    noisy = simulate_scan(world, s, T, seed=4)
    # match beams by (time, ring)
    key_c = np.round(clean.attributes["time_s"] * 1e7).astype(np.int64) * 16 + clean.attributes["ring"]
    key_n = np.round(noisy.attributes["time_s"] * 1e7).astype(np.int64) * 16 + noisy.attributes["ring"]
    common, ic, jn = np.intersect1d(key_c, key_n, return_indices=True)
    assert len(common) > 0.99 * len(clean)
    d = noisy.attributes["range_m"][jn] - clean.attributes["range_m"][ic]
    assert abs(d.std() - 0.03) < 0.003
    assert abs(d.mean()) < 0.003
    assert np.abs(d).max() < 6 * 0.03
    # same direction
    u_c = clean.points[ic] / np.linalg.norm(clean.points[ic], axis=1, keepdims=True)
    u_n = noisy.points[jn] / np.linalg.norm(noisy.points[jn], axis=1, keepdims=True)
    assert np.abs(u_c - u_n).max() < 1e-12
    # same seed -> identical, other seed -> different noise
    again = simulate_scan(world, s, T, seed=4)
    assert np.array_equal(again.points, noisy.points)
    other = simulate_scan(world, s, T, seed=5)
    assert not np.array_equal(other.points, noisy.points)


def test_max_range_is_respected(world):
    """A 5 m flash sensor looking along a drift sees nothing beyond 5 m; a 100 m LiDAR does."""
    T = _pose(world, "regular")
    flash = simulate_scan(world, FlashSensor(width_px=40, height_px=30, range_noise_sigma_m=0.0), T, seed=0)
    full = simulate_scan(world, FlashSensor(width_px=40, height_px=30, range_noise_sigma_m=0.0,
                                            max_range_m=100.0), T, seed=0)
    assert np.linalg.norm(flash.points, axis=1).max() <= 5.0
    assert len(full) > len(flash)
    assert np.linalg.norm(full.points, axis=1).max() > 5.0
    noisy = simulate_scan(world, Velodyne16(azimuth_step_deg=2.0, max_range_m=8.0), T, seed=2)
    assert noisy.attributes["range_m"].max() <= 8.0


def test_moving_sensor_timestamps_and_deskew(world):
    traj = make_trajectory(world, "walk", start="regular", length_m=4.0, seed=2)
    s = Velodyne16(azimuth_step_deg=2.0, range_noise_sigma_m=0.0)
    raw = simulate_scan(world, s, traj, seed=1, frame_stride=10)
    t = raw.attributes["time_s"]
    assert t.min() >= traj.times_s[0] and t.max() <= traj.times_s[-1] + s.frame_period_s
    assert raw.frame == "sensor"
    W = deskew(raw, traj)
    assert np.abs(world.sdf(W.points)).max() < 2e-3
    # without per-point poses (all points with the first pose of their frame) the cloud is smeared
    from minegeo.synth import interpolate_poses

    frame0 = np.floor(t / s.frame_period_s) * s.frame_period_s
    Tf = interpolate_poses(traj, frame0)
    naive = np.einsum("nij,nj->ni", Tf[:, :3, :3], raw.points) + Tf[:, :3, 3]
    assert np.abs(world.sdf(naive)).max() > 0.02


def test_horizontal_2d_ranges_and_bearings(world):
    T = _pose(world, "regular", height=1.0)
    for step in (0.25, 0.5):
        sensor = Horizontal2D(angular_step_deg=step)
        scan = simulate_scan_2d(world, sensor, T, seed=1)
        assert scan.bearings_rad.size == int(360 / step)
        np.testing.assert_allclose(np.diff(np.degrees(scan.bearings_rad)), step)
        ok = np.isfinite(scan.ranges_m)
        assert ok.mean() > 0.9
        assert np.nanmax(scan.ranges_m) <= 30.0
        xy = scan.points()
        P = np.column_stack([xy, np.zeros(len(xy))]) @ T[:3, :3].T + T[:3, 3]
        assert np.abs(world.sdf(P)).max() < 6 * sensor.range_noise_sigma_m * 2.5
    cloud = simulate_scan(world, Horizontal2D(), T, seed=1)
    assert np.all(cloud.points[:, 2] == 0.0)
    assert "bearing_rad" in cloud.attributes and "range_m" in cloud.attributes


def test_bad_sensor_inputs(world):
    T = _pose(world, "regular")
    with pytest.raises(InputError):
        simulate_scan(world, Velodyne16(max_range_m=0.1, min_range_m=0.5), T)
    with pytest.raises(InputError):
        simulate_scan(world, Velodyne16(), np.eye(3))
    with pytest.raises(InputError):
        simulate_scan(world, object(), T)
    with pytest.raises(InputError):
        simulate_scan_2d(world, Velodyne16(), T)
