"""Procedural rough tunnel with a T-junction for FPFH/RANSAC tests (no minegeo.synth dependency).

Main drift along x (|x| <= half_length), cross drift along +y from the junction; circular
cross-section of radius ~2.5 m with seeded low-frequency roughness (so places differ), flat
floor at z = -1.6 m. Points are sampled uniformly on the surfaces, then voxel-downsampled.
"""

from __future__ import annotations

import numpy as np


def _rough(rng, n_terms=16, amp=0.35, n_bumps=40, length=60.0):
    """Wall offset (m) as a function of (s, theta): smooth waves plus blast-like bumps."""
    k_s = rng.uniform(0.1, 1.2, n_terms)
    k_t = rng.integers(1, 7, n_terms)
    ph = rng.uniform(0, 2 * np.pi, (n_terms, 2))
    a = rng.uniform(0.3, 1.0, n_terms) * amp / np.sqrt(n_terms / 4)
    bs = rng.uniform(-length, length, n_bumps)
    bt = rng.uniform(-0.5, np.pi + 0.5, n_bumps)
    ba = rng.uniform(-0.6, 0.6, n_bumps)
    bw = rng.uniform(0.5, 1.5, n_bumps)

    def f(s, th):
        out = np.zeros_like(s)
        for i in range(n_terms):
            out += a[i] * np.sin(k_s[i] * s + ph[i, 0]) * np.cos(k_t[i] * th + ph[i, 1])
        for i in range(n_bumps):
            out += ba[i] * np.exp(-((s - bs[i]) ** 2 + (2.5 * (th - bt[i])) ** 2) / (2 * bw[i] ** 2))
        return out

    return f


def _drift(rng, s_lo, s_hi, radius, floor_z, spacing, rough):
    """Points (s, lateral, z) of one drift: curved wall/roof and flat floor."""
    length = s_hi - s_lo
    th_lo = -np.arcsin(min(1.0, -floor_z / radius))  # wall meets the floor at theta = th_lo
    arc = (np.pi - 2 * th_lo) * radius
    n_wall = int(length * arc / spacing**2)
    s = rng.uniform(s_lo, s_hi, n_wall)
    th = rng.uniform(th_lo, np.pi - th_lo, n_wall)  # angle about the drift axis, z = r sin(theta)
    r = radius + rough(s, th)
    wall = np.stack([s, r * np.cos(th), r * np.sin(th)], axis=1)
    half_w = radius * np.cos(th_lo)
    n_floor = int(length * 2 * half_w / spacing**2)
    fl = np.stack([rng.uniform(s_lo, s_hi, n_floor), rng.uniform(-half_w, half_w, n_floor),
                   np.full(n_floor, floor_z) + 0.02 * rng.standard_normal(n_floor)], axis=1)
    wall = wall[wall[:, 2] > floor_z]
    return np.concatenate([wall, fl])


def tunnel_map(seed=0, half_length=30.0, cross_length=25.0, radius=2.5, floor_z=-1.6, spacing=0.12):
    """Dense map points (m, 3) of a T-junction: main drift along x, cross drift along +y."""
    rng = np.random.default_rng(seed)
    main = _drift(rng, -half_length, half_length, radius, floor_z, spacing, _rough(rng))
    cross = _drift(rng, 0.0, cross_length, radius, floor_z, spacing, _rough(rng))
    cross = cross[:, [1, 0, 2]]  # drift along +y
    # open the junction: drop main-drift wall points inside the cross drift and vice versa
    main = main[~((np.abs(main[:, 0]) < radius * 0.95) & (main[:, 1] > 0) & (main[:, 2] > floor_z + 0.05))]
    cross = cross[cross[:, 1] > radius * 0.95]
    return np.concatenate([main, cross])


def voxel_down(points, voxel):
    """Voxel-centroid downsampling (plain NumPy, sorted by voxel key)."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    out = np.zeros((inv.max() + 1, 3))
    np.add.at(out, inv, points)
    return out / np.bincount(inv)[:, None]


def local_section(map_dense, center, radius_m, rng, noise_m=0.02):
    """Points of the dense map within radius_m of center, re-sampled with a little noise."""
    sel = np.linalg.norm(map_dense - center, axis=1) < radius_m
    pts = map_dense[sel]
    keep = rng.random(pts.shape[0]) < 0.7
    return pts[keep] + noise_m * rng.standard_normal((int(keep.sum()), 3))


def centerline(half_length=30.0, cross_length=25.0, step=0.5):
    """Positions along the drift axes (for orienting map normals into the void)."""
    a = np.stack([np.arange(-half_length, half_length + step, step), np.zeros(int(2 * half_length / step) + 1),
                  np.zeros(int(2 * half_length / step) + 1)], axis=1)
    ys = np.arange(0.0, cross_length + step, step)
    b = np.stack([np.zeros_like(ys), ys, np.zeros_like(ys)], axis=1)
    return np.concatenate([a, b])
