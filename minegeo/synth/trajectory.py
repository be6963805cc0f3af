"""Sensor trajectories through the synthetic mine (walking, driving, flying) and pose interpolation.

Poses are ``T_world_sensor`` (4x4): the sensor frame is x forward, y left, z up. A
trajectory follows a route along drift floor centrelines (through junctions, taking
the straightest continuation; U-turn at dead ends), at a carrier-dependent height
and with seeded, smooth sway. Poses too close to a structure (the parked vehicle,
railings) are pushed sideways so the sensor never starts inside a solid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from minegeo.errors import DegenerateGeometryError, InputError
from minegeo.io.types import Trajectory

__all__ = ["MotionParams", "MOTIONS", "make_trajectory", "interpolate_poses", "route_polyline",
           "resolve_start"]


@dataclass(frozen=True)
class MotionParams:
    """How a carrier moves (lengths m, angles deg, frequencies Hz).

    Attributes
    ----------
    speed_mps : float
        Mean speed along the route.
    height_m : float
        Sensor height above the floor centreline.
    lateral_sway_m, height_sway_m : float
        Amplitudes of smooth seeded sideways / vertical motion.
    yaw_sway_deg, pitch_sway_deg, roll_sway_deg : float
        Amplitudes of smooth seeded attitude motion around the path direction.
    follow_slope : bool
        True: the x axis follows the 3D path (vehicle on a ramp); False: stays level.
    bob_hz : float
        Frequency of the periodic vertical bob (steps when walking), 0 for none.
    """

    speed_mps: float
    height_m: float
    lateral_sway_m: float
    height_sway_m: float
    yaw_sway_deg: float
    pitch_sway_deg: float
    roll_sway_deg: float
    follow_slope: bool
    bob_hz: float = 0.0


MOTIONS: dict[str, MotionParams] = {
    "walk": MotionParams(1.2, 1.5, 0.25, 0.03, 8.0, 5.0, 3.0, False, 1.8),
    "drive": MotionParams(2.5, 2.0, 0.05, 0.0, 1.0, 0.5, 0.5, True, 0.0),
    "fly": MotionParams(1.0, 2.3, 0.35, 0.2, 15.0, 4.0, 4.0, False, 0.0),
    # slow walk sweeping a short-range device (iPad-like flash sensor) over walls and roof
    "handheld": MotionParams(0.6, 1.4, 0.15, 0.03, 35.0, 20.0, 5.0, False, 1.5),
}


# ---------------------------------------------------------------------- routes
def _oriented(poly: np.ndarray, forward: bool) -> np.ndarray:
    return poly if forward else poly[::-1]


def _arc_lengths(P: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])


def _cut(P: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """Sub-polyline of P between arc lengths s0 <= s1 (3D length)."""
    s = _arc_lengths(P)
    s0 = min(max(s0, 0.0), s[-1])
    s1 = min(max(s1, s0), s[-1])

    def at(x):
        k = int(np.clip(np.searchsorted(s, x, side="right") - 1, 0, len(P) - 2))
        u = (x - s[k]) / max(s[k + 1] - s[k], 1e-12)
        return P[k] * (1 - u) + P[k + 1] * u

    inner = P[(s > s0) & (s < s1)]
    return np.vstack([at(s0), inner, at(s1)])


def resolve_start(world, start) -> tuple[int, float]:
    """Turn a start specification into ``(drift index, arc length from the drift's first node)``.

    ``start`` may be ``None`` (first drift, s = 0), ``(drift, s_m)``, a dict with keys
    ``drift`` and ``s_m``, a feature name of ``world.features`` (``"irregular_roof"``,
    ``"curve"``, ``"regular"``, ``"sump"``, ``"meshed"``) or a 3-vector (snapped to the
    nearest centreline point).
    """
    if start is None:
        return 0, 0.0
    if isinstance(start, str):
        if start not in world.features or not isinstance(world.features[start], dict):
            raise InputError(f"unknown start feature {start!r}; known: irregular_roof, curve, regular, sump, meshed")
        f = world.features[start]
        return int(f["drift"]), float(f["s_m"])
    if isinstance(start, dict):
        return int(start["drift"]), float(start["s_m"])
    arr = np.asarray(start, dtype=float).ravel()
    if arr.size == 2:
        k = int(arr[0])
        if not 0 <= k < len(world.drifts):
            raise InputError(f"drift index {k} out of range 0..{len(world.drifts) - 1}")
        return k, float(arr[1])
    if arr.size == 3:
        best = (np.inf, 0, 0.0)
        for k, d in enumerate(world.drifts):
            P = d.centreline
            s = _arc_lengths(P)
            for i in range(len(P) - 1):
                ab = P[i + 1] - P[i]
                u = float(np.clip(np.dot(arr - P[i], ab) / max(np.dot(ab, ab), 1e-12), 0, 1))
                dist = float(np.linalg.norm(P[i] + u * ab - arr))
                if dist < best[0]:
                    best = (dist, k, s[i] + u * (s[i + 1] - s[i]))
        return best[1], best[2]
    raise InputError(f"cannot interpret start={start!r}")


def route_polyline(world, drift: int, s_m: float, forward: bool, length_m: float) -> np.ndarray:
    """Floor-centreline polyline of ``length_m`` (3D arc length) starting at ``(drift, s_m)``.

    Moves along the drift towards its last node (``forward``) or first node; at a
    junction continues on the drift with the smallest turning angle, at a dead end turns
    back along the same drift.
    """
    adj = world.adjacency()
    parts = []
    remaining = float(length_m)
    k, fwd = int(drift), bool(forward)
    P = world.drifts[k].centreline
    s_here = float(np.clip(s_m, 0.0, _arc_lengths(P)[-1]))
    for _ in range(10000):
        P = world.drifts[k].centreline
        L = _arc_lengths(P)[-1]
        if fwd:
            seg = _cut(P, s_here, min(L, s_here + remaining))
        else:
            seg = _cut(P, max(0.0, s_here - remaining), s_here)[::-1]
        parts.append(seg)
        remaining -= float(_arc_lengths(seg)[-1])
        if remaining <= 1e-9:
            break
        node = world.drifts[k].b if fwd else world.drifts[k].a
        d_in = seg[-1, :2] - seg[max(0, len(seg) - 3), :2]
        d_in = d_in / max(np.linalg.norm(d_in), 1e-12)
        best = None
        for k2, _other in adj[node]:
            if k2 == k and len(adj[node]) > 1:
                continue
            D2 = world.drifts[k2]
            f2 = D2.a == node
            Q = _oriented(D2.centreline, f2)
            d_out = Q[min(2, len(Q) - 1), :2] - Q[0, :2]
            d_out = d_out / max(np.linalg.norm(d_out), 1e-12)
            c = float(np.dot(d_in, d_out))
            if k2 == k:
                c = -2.0  # dead end: turn back
            if best is None or c > best[0]:
                best = (c, k2, f2)
        _, k, fwd = best
        s_here = 0.0 if fwd else _arc_lengths(world.drifts[k].centreline)[-1]
    path = np.vstack([parts[0]] + [p[1:] for p in parts[1:]])
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > 1e-9])
    return path[keep]


# ---------------------------------------------------------------------- poses
def _smooth_noise(rng: np.random.Generator, t: np.ndarray, amp: float, f_lo: float, f_hi: float,
                  n: int = 4) -> np.ndarray:
    """Smooth seeded signal: sum of ``n`` sinusoids with random frequencies/phases, peak <= amp."""
    out = np.zeros_like(t)
    if amp == 0:
        return out
    for _ in range(n):
        f = rng.uniform(f_lo, f_hi)
        out += np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return amp * out / n


def _densify(C: np.ndarray, step_m: float = 0.25) -> np.ndarray:
    """Resample a polyline every ``step_m`` of 3D arc length (keeps the end points)."""
    S = _arc_lengths(C)
    if S[-1] <= 0:
        return C[:1].copy()
    s = np.concatenate([np.arange(0.0, S[-1], step_m), [S[-1]]])
    return np.column_stack([np.interp(s, S, C[:, i]) for i in range(3)])


def _frames_from_path(C: np.ndarray, window_m: float = 1.0):
    """Unit 3D tangent at each vertex of a dense path (central difference over +-window_m).

    Where the path turns back on itself (dead end) the difference degenerates; the
    previous tangent is kept there, so the heading flips once at the turning point.
    """
    s = _arc_lengths(C)
    j0 = np.clip(np.searchsorted(s, s - window_m), 0, len(C) - 1)
    j1 = np.clip(np.searchsorted(s, s + window_m), 0, len(C) - 1)
    v = C[j1] - C[j0]
    nv = np.linalg.norm(v[:, :2], axis=1)
    tan = np.zeros_like(C)
    last = None
    for i in range(len(C)):
        if nv[i] > 0.3 * window_m:
            last = v[i] / np.linalg.norm(v[i])
        elif last is None:
            k = min(i + 1, len(C) - 1)
            w = C[k] - C[max(0, k - 1)]
            last = w / max(np.linalg.norm(w), 1e-12)
        tan[i] = last
    return tan


def make_trajectory(world, kind: str = "walk", start=None, length_m: float = 20.0, seed: int = 0, *,
                    forward: bool = True, rate_hz: float = 50.0, speed_mps: float | None = None,
                    path: np.ndarray | None = None, clearance_m: float = 0.45) -> Trajectory:
    """Ground-truth sensor trajectory ``T_world_sensor`` along the drift network.

    Parameters
    ----------
    world : MineWorld
    kind : {"walk", "drive", "fly", "handheld"}
        Carrier: handheld walk (1.2 m/s, 1.5 m, sway and step bob), vehicle (2.5 m/s, 2.0 m,
        pitch follows the ramp), drone (1.0 m/s, 2.3 m, larger yaw sway), slow sweeping
        handheld device (0.6 m/s, yaw +-35 deg, pitch +-20 deg; for the flash sensor).
    start : see :func:`resolve_start`
    length_m : float
        Route length (m, along the floor centreline).
    seed : int
        Seeds the sway signals.
    forward : bool
        Direction along the start drift.
    rate_hz : float
        Pose rate (poses are interpolated linearly / by slerp in between).
    speed_mps : float, optional
        Overrides the carrier's speed.
    path : (k, 3) array, optional
        Explicit floor-centreline path (world frame) instead of ``start``/``length_m``.
    clearance_m : float
        Minimum distance from the sensor to any surface; closer poses are pushed sideways.

    Returns
    -------
    Trajectory
        ``frame="world"``, ``body="sensor"``, times from 0 s.

    Raises
    ------
    InputError
        Unknown kind, non-positive length/rate.
    DegenerateGeometryError
        No collision-free lateral position exists somewhere along the route.
    """
    if kind not in MOTIONS:
        raise InputError(f"trajectory kind must be one of {sorted(MOTIONS)}, got {kind!r}")
    if not (length_m > 0 and rate_hz > 0):
        raise InputError("length_m and rate_hz must be > 0")
    mp = MOTIONS[kind]
    speed = float(speed_mps or mp.speed_mps)
    rng = np.random.default_rng(seed)
    if path is None:
        k, s0 = resolve_start(world, start)
        path = route_polyline(world, k, s0, forward, length_m)
    C = _densify(np.asarray(path, dtype=float))
    S = _arc_lengths(C)
    total = S[-1]
    n = max(2, int(math.floor(total / speed * rate_hz)) + 1)
    t = np.arange(n) / rate_hz
    s = np.minimum(t * speed, total)
    tan_c = _frames_from_path(C)
    pos = np.column_stack([np.interp(s, S, C[:, i]) for i in range(3)])
    tan = tan_c[np.clip(np.searchsorted(S, s), 0, len(C) - 1)]
    h = tan[:, :2] / np.maximum(np.linalg.norm(tan[:, :2], axis=1, keepdims=True), 1e-12)
    left = np.column_stack([-h[:, 1], h[:, 0], np.zeros(n)])
    lat = _smooth_noise(rng, t, mp.lateral_sway_m, 0.02, 0.1)
    dh = _smooth_noise(rng, t, mp.height_sway_m, 0.05, 0.2)
    if mp.bob_hz:
        dh = dh + 0.03 * np.sin(2 * np.pi * mp.bob_hz * t)
    yaw = np.radians(_smooth_noise(rng, t, mp.yaw_sway_deg, 0.05, 0.3))
    pitch = np.radians(_smooth_noise(rng, t, mp.pitch_sway_deg, 0.05, 0.3))
    roll = np.radians(_smooth_noise(rng, t, mp.roll_sway_deg, 0.05, 0.3))
    # keep clear of structures: push sideways where needed, then smooth the correction
    base = pos + np.array([0, 0, mp.height_m]) + dh[:, None] * np.array([0, 0, 1.0])
    cand = base + lat[:, None] * left
    f = world.sdf(cand)
    corr = np.zeros(n)
    bad = np.flatnonzero(f < clearance_m)
    if bad.size:
        offs = np.array([x for a in np.arange(0.2, 1.61, 0.2) for x in (a, -a)])
        for i in bad:
            trial = cand[i][None, :] + offs[:, None] * left[i][None, :]
            ft = world.sdf(trial)
            ok = np.flatnonzero(ft >= clearance_m + 0.1)
            if ok.size:
                corr[i] = offs[ok[0]]
        w = max(1, int(rate_hz * 1.0))
        ker = np.ones(2 * w + 1)
        # max-magnitude dilation then moving average keeps the correction where it is needed
        sgn_max = np.convolve(np.abs(corr) > 0, ker, mode="same") > 0
        mag = np.zeros(n)
        for i in np.flatnonzero(sgn_max):
            lo, hi = max(0, i - w), min(n, i + w + 1)
            j = lo + int(np.argmax(np.abs(corr[lo:hi])))
            mag[i] = corr[j]
        corr = np.convolve(mag, ker / ker.sum(), mode="same")
        cand = cand + corr[:, None] * left
        f = world.sdf(cand)
        if (f < 0.15).any():
            i = int(np.argmin(f))
            raise DegenerateGeometryError(
                f"trajectory cannot keep clear of structures near {np.round(cand[i], 2).tolist()} "
                f"(clearance {f[i]:.2f} m); choose another start or carrier"
            )
    x_axis = tan.copy() if mp.follow_slope else np.column_stack([h, np.zeros(n)])
    x_axis /= np.linalg.norm(x_axis, axis=1, keepdims=True)
    z_axis = np.cross(x_axis, left)
    z_axis /= np.linalg.norm(z_axis, axis=1, keepdims=True)
    y_axis = np.cross(z_axis, x_axis)
    R_path = np.stack([x_axis, y_axis, z_axis], axis=2)
    R_sway = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = R_path @ R_sway
    poses[:, :3, 3] = cand
    poses[:, 3, 3] = 1.0
    return Trajectory(times_s=t, poses=poses, frame="world", body="sensor")


# ---------------------------------------------------------------------- interpolation
def _quats(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat()  # x y z w
    # make consecutive quaternions on the same hemisphere for slerp
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


class _Interp:
    """Pose interpolation: linear in translation, slerp in rotation (Shoemake 1985)."""

    def __init__(self, traj: Trajectory):
        self.t = traj.times_s
        self.p = traj.poses[:, :3, 3]
        self.q = _quats(traj.poses[:, :3, :3])

    def __call__(self, times: np.ndarray):
        times = np.asarray(times, dtype=float)
        m = len(self.t)
        if m == 1:
            R = np.broadcast_to(_quat_to_R(self.q[:1]), (len(times), 3, 3)).copy()
            return R, np.broadcast_to(self.p[0], (len(times), 3)).copy()
        k = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, m - 2)
        dt = self.t[k + 1] - self.t[k]
        u = np.clip((times - self.t[k]) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
        p = self.p[k] * (1 - u)[:, None] + self.p[k + 1] * u[:, None]
        q0, q1 = self.q[k], self.q[k + 1]
        c = np.clip(np.sum(q0 * q1, axis=1), -1.0, 1.0)
        th = np.arccos(c)
        sth = np.sin(th)
        small = sth < 1e-9
        w0 = np.where(small, 1 - u, np.sin((1 - u) * th) / np.where(small, 1.0, sth))
        w1 = np.where(small, u, np.sin(u * th) / np.where(small, 1.0, sth))
        q = q0 * w0[:, None] + q1 * w1[:, None]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        return _quat_to_R(q), p


def interpolate_poses(traj: Trajectory, times) -> np.ndarray:
    """Poses (n, 4, 4) of ``traj`` at ``times`` (s): linear translation, slerp rotation, clamped at the ends."""
    R, p = _Interp(traj)(np.asarray(times, dtype=float).reshape(-1))
    T = np.zeros((len(p), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T
