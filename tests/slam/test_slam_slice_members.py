"""The cross-section slices of the noise removal (:func:`minegeo.slam._kernels_mapping.slice_members`,
[Ren2019 Eq. 13] with the in-plane radius) against the naive twin that tests every point against
every slice: the same members, in the same (ascending) order, for random clouds and slices, points
on the slab's faces and on the radius included."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo.slam._kernels_mapping import slice_members


def naive_slice_members(points, centres, normals, half_thickness, radius):
    """Every point against every slice: ``|n·(p − c)| ≤ δ/2`` and ``|p − c|² − (n·(p − c))² ≤ R²``."""
    offsets, members = [0], []
    for c, n in zip(centres, normals, strict=True):
        for i, p in enumerate(points):
            dx, dy, dz = p[0] - c[0], p[1] - c[1], p[2] - c[2]
            d = dx * n[0] + dy * n[1] + dz * n[2]
            if abs(d) <= half_thickness and dx * dx + dy * dy + dz * dz - d * d <= radius * radius:
                members.append(i)
        offsets.append(len(members))
    return np.array(offsets), np.array(members, dtype=np.int64)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 400), s=st.integers(1, 12),
       half=st.floats(0.05, 2.0), radius=st.floats(0.1, 6.0), spread=st.floats(0.5, 60.0))
def test_slices_equal_the_naive_twin(seed, n, s, half, radius, spread):
    rng = np.random.default_rng(seed)
    P = rng.uniform(-spread, spread, (n, 3))
    C = rng.uniform(-spread, spread, (s, 3))
    N = rng.normal(size=(s, 3))
    assume(np.all(np.linalg.norm(N, axis=1) > 1e-3))
    N /= np.linalg.norm(N, axis=1)[:, None]
    if n:  # points exactly on a slab face and at the in-plane radius of slice 0 (the boundary cases)
        u = np.cross(N[0], [1.0, 0.0, 0.0] if abs(N[0, 0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        P[0] = C[0] + half * N[0]
        P[-1] = C[0] + radius * u
    off, mem = slice_members(P, C, N, half, radius)
    off_ref, mem_ref = naive_slice_members(P, C, N, half, radius)
    assert off.tolist() == off_ref.tolist()
    assert mem.tolist() == mem_ref.tolist()


def test_a_drift_of_points_split_into_its_slices():
    """A straight 3 m wide drift along x sampled every 0.1 m; slices every metre normal to x, 0.5 m
    thick: each holds the points of its 0.5 m band (x within ±0.25 m of its centre), all of them."""
    x, y, z = np.meshgrid(np.arange(0.0, 40.0, 0.1), np.arange(-1.5, 1.51, 0.5), np.arange(0.0, 3.01, 0.5),
                          indexing="ij")
    P = np.column_stack([x.ravel(), y.ravel(), z.ravel()]) + 1e-3  # off the band edges
    C = np.column_stack([np.arange(2.0, 38.0, 1.0), np.zeros(36), np.full(36, 1.5)])
    N = np.tile([1.0, 0.0, 0.0], (36, 1))
    off, mem = slice_members(P, C, N, 0.25, 8.0)
    for k in range(36):
        expect = np.flatnonzero(np.abs(P[:, 0] - C[k, 0]) <= 0.25)
        assert mem[off[k]:off[k + 1]].tolist() == expect.tolist()
