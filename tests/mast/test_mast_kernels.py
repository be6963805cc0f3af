"""Numba kernels of minegeo.mast against naive twins."""

from __future__ import annotations

import numpy as np
from reference.naive_mast import naive_cast_rays, naive_nearest_segment, naive_sse

from minegeo.mast._kernels import _cast_rays, _nearest_segment, _prefix_sums, _sse_range


def test_cast_rays_matches_naive(rng):
    segs = rng.uniform(-5, 5, size=(25, 4))
    ang = rng.uniform(0, 2 * np.pi, 200)
    dirs = np.ascontiguousarray(np.column_stack([np.sin(ang), np.cos(ang)]))
    o = np.array([0.3, -0.2])
    r, idx, _ = _cast_rays(o, dirs, segs, 30.0)
    r2, idx2 = naive_cast_rays(o, dirs, segs, 30.0)
    np.testing.assert_array_equal(idx, idx2)
    np.testing.assert_allclose(r, r2, rtol=1e-10, atol=1e-12)
    assert (idx >= 0).sum() > 50


def test_nearest_segment_matches_naive(rng):
    segs = rng.uniform(-3, 3, size=(8, 4))
    pts = rng.uniform(-3, 3, size=(300, 2))
    d, idx, sd = _nearest_segment(pts, segs, 0.05)
    d2, idx2 = naive_nearest_segment(pts, segs, 0.05)
    np.testing.assert_array_equal(idx, idx2)
    ok = np.isfinite(d2)
    np.testing.assert_allclose(d[ok], d2[ok], atol=1e-12)
    np.testing.assert_allclose(np.abs(sd[ok]), d2[ok], atol=1e-12)


def test_sse_prefix_matches_naive(rng):
    xy = np.ascontiguousarray(rng.normal(size=(40, 2)) * [3.0, 0.1])
    P = _prefix_sums(xy)
    for i, j in [(0, 39), (3, 10), (5, 6), (20, 38)]:
        assert abs(_sse_range(P, i, j) - naive_sse(xy[i : j + 1])) < 1e-9


def test_scenario_returns_lie_on_the_surfaces_they_hit():
    from minegeo.mast import scan_to_xy, simulate_mast_scenario

    sc = simulate_mast_scenario(0, position=3, beacon1_rotation_deg=-10.0, sigma_range_m=0.0)
    x, y, az = sc.truth["x_m"], sc.truth["y_m"], sc.truth["azimuth_deg"]
    s = scan_to_xy(sc.scan.bearing_deg, sc.scan.range_m)
    a = np.radians(az)
    R = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])  # clockwise rotation by the azimuth
    p = s @ R.T + [x, y]
    panels = np.vstack([b.panels() for b in sc.beacons])
    on = sc.hit_label >= 0
    assert on.sum() > 50
    for pt, lab in zip(p[on], sc.hit_label[on], strict=True):
        ax, ay, bx, by = panels[lab]
        e = np.array([bx - ax, by - ay])
        q = pt - [ax, ay]
        assert abs(e[0] * q[1] - e[1] * q[0]) / np.linalg.norm(e) < 1e-9
        assert -1e-9 <= (q @ e) / (e @ e) <= 1 + 1e-9
    assert np.all(sc.scan.range_m <= 30.0)
