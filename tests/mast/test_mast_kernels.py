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
