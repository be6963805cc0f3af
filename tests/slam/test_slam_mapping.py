"""Roadway noise removal (Ren et al. 2019 Sec. 3.5): synthetic straight and curved roadways with a box
and a horseshoe cross-section, noise blobs and a pedestrian inside, an overbreak behind a wall."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.slam import mapping
from minegeo.slam.mapping import RoadwayNoiseParams, remove_roadway_noise, section_frames

WIDTH, WALL_H, SENSOR_H = 5.0, 4.0, 2.0  # box: 5 m × 4 m; horseshoe: walls 3 m + half circle r 2.5


def _profile(shape: str, t: np.ndarray):
    """Points (lateral, height above floor) along the perimeter, t ∈ [0, 1)."""
    if shape == "box":
        parts = [(WIDTH, lambda s: (s - WIDTH / 2, 0 * s)), (WALL_H, lambda s: (WIDTH / 2 + 0 * s, s)),
                 (WIDTH, lambda s: (WIDTH / 2 - s, WALL_H + 0 * s)), (WALL_H, lambda s: (-WIDTH / 2 + 0 * s, WALL_H - s))]
    else:
        r, h = WIDTH / 2, 3.0
        parts = [(WIDTH, lambda s: (s - r, 0 * s)), (h, lambda s: (r + 0 * s, s)),
                 (np.pi * r, lambda s: (r * np.cos(s / r), h + r * np.sin(s / r))), (h, lambda s: (-r + 0 * s, h - s))]
    lengths = np.array([p[0] for p in parts])
    edges = np.r_[0.0, np.cumsum(lengths)] / lengths.sum()
    u, v = np.empty_like(t), np.empty_like(t)
    for k, (L, f) in enumerate(parts):
        sel = (t >= edges[k]) & (t < edges[k + 1])
        u[sel], v[sel] = f((t[sel] - edges[k]) / (edges[k + 1] - edges[k]) * L)
    return u, v, lengths.sum()


def _path(kind: str, length: float, n: int):
    s = np.linspace(0.0, length, n)
    if kind == "straight":
        return np.stack([s, 0 * s, 0 * s], axis=1), s
    R = 25.0  # a curve of radius 25 m (~69° over 30 m)
    return np.stack([R * np.sin(s / R), R * (1 - np.cos(s / R)), 0 * s], axis=1), s


def _frame_at(kind: str, s: np.ndarray):
    """Centreline point, lateral unit vector at arc length s (up = z)."""
    if kind == "straight":
        c = np.stack([s, 0 * s, 0 * s], axis=1)
        lat = np.tile([0.0, 1.0, 0.0], (s.size, 1))
    else:
        R = 25.0
        c = np.stack([R * np.sin(s / R), R * (1 - np.cos(s / R)), 0 * s], axis=1)
        tang = np.stack([np.cos(s / R), np.sin(s / R), 0 * s], axis=1)
        lat = np.cross([0.0, 0.0, 1.0], tang)
    return c, lat


def _to_world(kind, s, u, v):
    c, lat = _frame_at(kind, s)
    return c + u[:, None] * lat + v[:, None] * np.array([0.0, 0.0, 1.0])


def roadway(kind="straight", shape="box", length=30.0, seed=0):
    rng = np.random.default_rng(seed)
    perim = _profile(shape, np.array([0.0]))[2]
    n = int(length * perim * 150)  # 150 points per m²
    s = rng.uniform(0, length, n)
    u, v, _ = _profile(shape, rng.uniform(0, 1, n))
    # overbreak: a recess 0.6 m deep behind the left wall, 4 m long, 1.5-2.7 m high (the wall there is gone)
    over_sel = (u < -WIDTH / 2 + 1e-9) & (s >= 10) & (s <= 14) & (v >= 1.5) & (v <= 2.7)
    u = np.where(over_sel, u - 0.6, u)
    surface = _to_world(kind, s, u, v) + rng.normal(0, 0.02, (n, 3))
    over = surface[over_sel]
    surface = surface[~over_sel]
    n, m = surface.shape[0], over.shape[0]
    # noise blobs inside (σ 0.15 m, at least ~0.8 m from any surface) and a pedestrian on the floor
    blobs = []
    for _ in range(8):
        sc, uc, vc = rng.uniform(3, length - 3), rng.uniform(-1.4, 1.4), rng.uniform(1.0, 3.0)
        k = 150
        blobs.append(_to_world(kind, sc + rng.normal(0, 0.15, k), uc + rng.normal(0, 0.15, k),
                               vc + rng.normal(0, 0.15, k)))
    k = 800
    ang, rad = rng.uniform(0, 2 * np.pi, k), 0.25 * np.sqrt(rng.uniform(0, 1, k))
    ped = _to_world(kind, 20.0 + rad * np.cos(ang), 1.0 + rad * np.sin(ang), rng.uniform(0, 1.8, k))
    noise = np.concatenate(blobs + [ped])
    track, _ = _path(kind, length, int(length / 2) + 1)  # a keyframe every 2 m
    track[:, 2] += SENSOR_H
    points = np.concatenate([surface, over, noise])
    labels = np.r_[np.zeros(n), np.ones(m), np.full(noise.shape[0], 2), ].astype(int)
    ped_mask = np.zeros(points.shape[0], bool)
    ped_mask[-k:] = True
    return points, track, labels, ped_mask


@pytest.mark.parametrize("kind,shape", [("straight", "box"), ("curved", "box"), ("straight", "horseshoe"),
                                        ("curved", "horseshoe")])
def test_noise_and_pedestrian_removed_surface_and_overbreak_kept(kind, shape):
    points, track, labels, ped = roadway(kind, shape)
    res = remove_roadway_noise(points, track, RoadwayNoiseParams())
    removed = ~res.keep
    thr = res.params.noise_threshold_m
    # points of the pedestrian within the threshold of the floor cannot be told from the floor
    ped_floor = ped & (np.abs(points[:, 2] - _floor_z(kind, points)) <= thr + 0.05)
    noise = (labels == 2) & ~ped_floor
    assert removed[noise].mean() >= 0.95, (removed[noise].mean(), res.counts)
    assert removed[labels == 0].mean() <= 0.01, (removed[labels == 0].mean(), res.counts)
    assert not removed[labels == 1].any()  # overbreak behind the wall is structure
    assert res.counts["removed"] == removed.sum()
    assert res.counts["slices"].get("ok", 0) >= 0.9 * len(res.slices)


def _floor_z(kind, points):
    return np.zeros(points.shape[0])  # the synthetic floors are at z = 0


def test_deterministic_with_the_seed():
    points, track, _, _ = roadway("curved", "horseshoe", length=16.0, seed=1)
    a = remove_roadway_noise(points, track, RoadwayNoiseParams(seed=5))
    b = remove_roadway_noise(points, track, RoadwayNoiseParams(seed=5))
    assert np.array_equal(a.keep, b.keep) and a.counts == b.counts


def test_track_points_skipped_as_the_paper_says():
    track = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [12, 0, 0], [13, 0, 0], [13, 1, 0], [13, 2, 0.0]])
    _, normals, index, st = section_frames(track, RoadwayNoiseParams(track_step_m=None))
    assert st[0] == "first_point" and st[1] == "ok" and st[3] == "step_too_long"
    assert st[4] == "heading_change" and st[5] == "heading_change"  # 90° turn at track point 4
    assert index.tolist() == [1, 2, 6]
    assert np.allclose(normals[0], [1, 0, 0]) and np.allclose(normals[2], [0, 1, 0])
    _, _, _, st = section_frames(np.array([[0, 0, 0], [1, 0, 0], [2, 0.15, 0], [3, 0.45, 0.0]]),
                                 RoadwayNoiseParams(max_heading_change_deg=45.0, max_curvature_rad_per_m=0.1))
    assert st[2] == "curvature"


def test_a_broken_inside_test_fails(monkeypatch):
    """With the sign of the fitted surfaces ignored (|distance|), the overbreak behind the wall is removed."""
    points, track, labels, _ = roadway("straight", "box", length=16.0)
    orig = mapping._inside_distances

    def broken(*a, **k):
        dist, stats, status = orig(*a, **k)
        return (None if dist is None else np.abs(dist)), stats, status

    monkeypatch.setattr(mapping, "_inside_distances", broken)
    res = remove_roadway_noise(points, track)
    assert (~res.keep)[labels == 1].mean() > 0.5


def test_bad_parameters_are_rejected():
    with pytest.raises(InputError):
        RoadwayNoiseParams(slice_thickness_m=0.0)
    with pytest.raises(InputError):
        RoadwayNoiseParams(vote_fraction=0.0)


def test_static_structure_seen_from_several_keyframes_is_kept():
    """A duct under the roof (every keyframe sees it) stays with ``source``; the moving blobs go."""
    points, track, labels, ped = roadway("straight", "box", seed=2)
    rng = np.random.default_rng(7)
    k = 3000
    x, a = rng.uniform(2, 28, k), rng.uniform(0, 2 * np.pi, k)
    duct = np.stack([x, -1.0 + 0.3 * np.cos(a), 3.2 + 0.3 * np.sin(a)], axis=1)
    pts = np.concatenate([points, duct])
    source = np.r_[rng.integers(0, 15, points.shape[0]), rng.integers(0, 15, k)]
    blobs = labels == 2
    source[np.flatnonzero(blobs)] = np.r_[np.repeat(np.arange(100, 108), 150), np.full(800, 108)]  # one view each
    is_duct = np.r_[np.zeros(points.shape[0], bool), np.ones(k, bool)]
    paper = remove_roadway_noise(pts, track)
    assert (~paper.keep)[is_duct].mean() > 0.9  # the paper's method takes the duct for noise
    res = remove_roadway_noise(pts, track, source=source)
    assert (~res.keep)[is_duct].mean() < 0.02 and res.counts["kept_static"] > 0.9 * k
    noise = np.r_[blobs & ~(ped & (points[:, 2] <= 0.25)), np.zeros(k, bool)]
    assert (~res.keep)[noise].mean() >= 0.95
