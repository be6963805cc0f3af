"""Naive NumPy twin of the synthetic-mine field (``minegeo.synth._kernels``): no grid, every primitive.

Same definition as the kernel, written for clarity:

    f(p) = min( max(max_i g_i(p), ROCK_CLAMP) + n(p),  min(min_j s_j(p), SOLID_CLAMP) )

with the void primitives ``g_i`` (horseshoe drift segments, ellipsoid cavities, yawed box
pits), the roughness ``n`` (plane-wave octaves, zone multiplier) and the solids ``s_j``
(capsules, yawed boxes, and the vehicle's solids in its own frame). The kernel evaluates only
the primitives its acceleration grid lists near ``p``; this twin evaluates all of them, so
agreement checks the grid as well as the formulas.
"""

from __future__ import annotations

import numpy as np

ROCK_CLAMP = -1.2
SOLID_CLAMP = 1.5


def drift_inner(P, a, b, R, hw):
    d = b[:2] - a[:2]
    L2 = float(d @ d)
    s = np.zeros(len(P)) if L2 == 0 else np.clip(((P[:, :2] - a[:2]) @ d) / L2, 0.0, 1.0)
    c = a[None, :2] + s[:, None] * d[None, :]
    cz = a[2] + s * (b[2] - a[2])
    lat = np.linalg.norm(P[:, :2] - c, axis=1)
    v = P[:, 2] - cz
    dB = np.where(v <= hw, R - lat, R - np.sqrt(lat**2 + (v - hw) ** 2))
    return np.minimum(v, dB)


def box_sdf(P, c, h, yaw):
    q0 = P - c
    cy, sy = np.cos(yaw), np.sin(yaw)
    x = cy * q0[:, 0] + sy * q0[:, 1]
    y = -sy * q0[:, 0] + cy * q0[:, 1]
    q = np.abs(np.column_stack([x, y, q0[:, 2]])) - h
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def capsule_sdf(P, a, b, r):
    d = b - a
    L2 = float(d @ d)
    t = np.zeros(len(P)) if L2 == 0 else np.clip(((P - a) @ d) / L2, 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * d), axis=1) - r


def void_inner(P, prim, typ):
    if typ == 0:
        return drift_inner(P, prim[0:3], prim[3:6], prim[6], prim[7])
    if typ == 1:
        q = (P - prim[0:3]) / prim[3:6]
        return (1.0 - np.linalg.norm(q, axis=1)) * prim[3:6].min()
    return -box_sdf(P, prim[0:3], prim[3:6], prim[6])


def solid_sdf(P, prim, typ):
    if typ == 0:
        return capsule_sdf(P, prim[0:3], prim[3:6], prim[6])
    return box_sdf(P, prim[0:3], prim[3:6], prim[6])


def noise(P, waves, octaves, zones):
    mult = np.ones(len(P))
    for z in zones:
        d2 = np.sum((P - z[:3]) ** 2, axis=1)
        mult += np.where(d2 < 9.0 * z[3] ** 2, z[4] * np.exp(-d2 / z[3] ** 2), 0.0)
    total = np.zeros(len(P))
    for k0, n, amp, mode in octaves:
        k0, n = int(k0), int(n)
        W = waves[k0:k0 + n]
        S = np.sin(P @ W[:, :3].T + W[:, 3]).sum(axis=1) * np.sqrt(2.0 / n)
        sq = S / np.sqrt(1.0 + S * S)
        total += mult * amp * 0.5 * (1.0 + sq) if mode == 0 else amp * sq
    return total


def field(P, arrays, T_world_vehicle=None, with_noise=True, with_structures=True):
    """The field at points ``P`` (n, 3) from the world's arrays (``MineWorld._arrays``)."""
    P = np.asarray(P, float)
    rock = np.full(len(P), -np.inf)
    for prim, typ in zip(arrays["void_prims"], arrays["void_type"], strict=True):
        rock = np.maximum(rock, void_inner(P, prim, typ))
    rock = np.maximum(rock, ROCK_CLAMP)
    if with_noise:
        rock = rock + noise(P, arrays["waves"], arrays["octaves"], arrays["zones"])
    if not with_structures:
        return rock
    sol = np.full(len(P), SOLID_CLAMP)
    for prim, typ in zip(arrays["solid_prims"], arrays["solid_type"], strict=True):
        sol = np.minimum(sol, solid_sdf(P, prim, typ))
    if T_world_vehicle is not None:
        T = np.asarray(T_world_vehicle)
        Pv = (P - T[:3, 3]) @ T[:3, :3]
        for prim, typ in zip(arrays["veh_prims"], arrays["veh_type"], strict=True):
            sol = np.minimum(sol, solid_sdf(Pv, prim, typ))
    return np.minimum(rock, sol)
