"""Test helper: a VLP-16-like sensor ray-cast in a :class:`~minegeo.synth.DriftNetwork` (capsule drifts,
flat floor at z = 0, roof height of the nearest node), and a drive along a polyline of it.

Walls carry a smooth roughness (``roughness_m``; the map from ``network_cloud`` has flat walls) so
that GICP odometry has structure along a straight drift. Sphere tracing of ``f(p) = min(z, roof(xy) - z, max_e(w_e / 2 - dist(xy, segment_e)))`` (steps capped
at 1 m: the roof is piecewise constant). Not part of the library (the flight simulator is
``minegeo.synth.flight``, written separately).
"""

from __future__ import annotations

import numpy as np


class NetworkWorld:
    def __init__(self, net, roughness_m=0.15):
        self.net = net
        self.rough = roughness_m
        self.A = net.nodes[net.edges[:, 0]]
        self.B = net.nodes[net.edges[:, 1]]
        self.hw = 0.5 * net.widths

    def _free(self, P):
        xy = P[:, :2]
        ab = self.B - self.A
        t = np.clip(np.einsum("nej,ej->ne", xy[:, None] - self.A[None], ab) / np.einsum("ej,ej->e", ab, ab), 0, 1)
        d = np.linalg.norm(xy[:, None] - (self.A[None] + t[..., None] * ab[None]), axis=2)
        horiz = np.max(self.hw[None] - d, axis=1)
        x, y = xy[:, 0], xy[:, 1]   # blasted-wall roughness: the map (network_cloud) has flat walls
        horiz = horiz + self.rough * np.sin(0.9 * x + 1.7 * y) * np.sin(1.3 * y - 0.7 * x + 0.4 * np.sin(0.5 * x))
        near = np.argmin(np.linalg.norm(xy[:, None] - self.net.nodes[None], axis=2), axis=1)
        roof = self.net.node_heights[near]
        return np.minimum(np.minimum(P[:, 2], roof - P[:, 2]), horiz)

    def cast(self, o, D, max_range):
        t = np.zeros(len(D))
        alive = np.ones(len(D), bool)
        for _ in range(300):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            f = self._free(o[idx] + t[idx, None] * D[idx])
            hit = f < 2e-3
            alive[idx[hit]] = False
            t[idx[~hit]] += np.minimum(np.maximum(0.7 * f[~hit], 1e-3), 1.0)
            alive &= t < max_range
        t[alive | (t >= max_range)] = np.nan
        return t


def scan(world, T, rng, az_step_deg=2.0, noise_m=0.02, max_range_m=60.0):
    """One VLP-16 rotation (16 rings over +-15 deg) at pose ``T`` (T_world_sensor); points in the sensor frame."""
    az = np.radians(np.arange(0.0, 360.0, az_step_deg))
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    D = np.stack([np.outer(np.cos(az), np.cos(el)), np.outer(np.sin(az), np.cos(el)),
                  np.outer(np.ones_like(az), np.sin(el))], axis=2).reshape(-1, 3)
    Dw = D @ T[:3, :3].T
    r = world.cast(np.broadcast_to(T[:3, 3], Dw.shape).copy(), Dw, max_range_m)
    ok = np.isfinite(r) & (r > 0.5)
    r = r[ok] + rng.normal(0.0, noise_m, ok.sum())
    return D[ok] * r[:, None]


def drive(net, waypoints, step_m=1.2, height_m=1.5, yaw_wobble_deg=3.0, seed=0, rate_hz=2.0):
    """Frames ``[(t, points)]`` and true poses (n, 4, 4) along the polyline ``waypoints`` (k, 2)."""
    W = np.asarray(waypoints, float)
    seg = np.diff(W, axis=0)
    L = np.r_[0.0, np.cumsum(np.linalg.norm(seg, axis=1))]
    s = np.arange(0.0, L[-1] + 1e-9, step_m)
    xy = np.c_[np.interp(s, L, W[:, 0]), np.interp(s, L, W[:, 1])]
    k = np.clip(np.searchsorted(L, s, side="right") - 1, 0, len(seg) - 1)
    yaw = np.arctan2(seg[k, 1], seg[k, 0]) + np.radians(yaw_wobble_deg) * np.sin(s / 7.0)
    world = NetworkWorld(net)
    rng = np.random.default_rng(seed)
    frames, poses = [], []
    for i in range(len(s)):
        T = np.eye(4)
        c, si = np.cos(yaw[i]), np.sin(yaw[i])
        T[:3, :3] = [[c, -si, 0], [si, c, 0], [0, 0, 1]]
        T[:3, 3] = [xy[i, 0], xy[i, 1], height_m]
        frames.append((i / rate_hz, scan(world, T, rng)))
        poses.append(T)
    return frames, np.stack(poses)
