"""Drone flights through a :class:`~minegeo.synth.network.DriftNetwork` with VLP-16-like frames.

Three steps, each deterministic from a seed:

1. :func:`plan_route` -- a walk over the network graph (node ids) that passes every junction several
   times from different directions: at each node it takes the exit whose (node, entry drift, exit
   drift) turn has been flown least often, then the least-flown drift, ties broken by the seed; at a
   dead end it turns back. The walk stops once the route's centreline length reaches ``length_m``.
2. :func:`make_flight` -- a smooth 6-DoF trajectory along the route: position on the drift
   centrelines at ``height_m`` above the floor (default half the lowest roof), corners at junctions
   cut by quadratic Bezier arcs (``corner_m``), a hover turn of 180 degrees at dead ends; speed
   ``speed_mps`` limited by a lateral acceleration ``lat_accel_mps2`` in curves and by
   ``accel_mps2`` along the path; smooth seeded lateral / vertical oscillation and yaw sway; roll
   and pitch of a multirotor from its horizontal acceleration (``pitch = atan(a_forward / g)``,
   ``roll = -atan(a_left / g)``) plus smooth seeded tilt noise. The pose is sampled on a 10 Hz
   clock; a **frame** is taken each ``frame_step_m`` of travel or ``frame_yaw_deg`` of yaw or
   ``frame_max_dt_s`` of time, whichever comes first.
3. :func:`simulate_flight` -- one VLP-16 rotation per frame, simulated at the frame's pose (no motion
   distortion, as :func:`~minegeo.synth.sequence.simulate_sequence`) by
   :func:`~minegeo.synth.sensors.simulate_scan` on a :class:`NetworkWorld` (exact ray casting against
   the network's floor, walls and roofs, the same surfaces :func:`~minegeo.synth.network.network_cloud`
   samples). Frames are cached on disk in chunks of ``chunk`` frames, keyed by a hash of the network,
   the route and the parameters.
4. :func:`flight_curve` / :func:`flight_imu` -- the IMU of the flight: the 10 Hz clock poses joined by
   the uniform cubic B-spline that passes through every one of them (:func:`flight_curve`; the
   frames are clock samples, so each frame sits exactly on the curve), read by
   :func:`~minegeo.synth.imu.simulate_imu` (gyro and accelerometer at ``rate_hz``, white noise and
   bias random walk; default the ADIS16448 of :class:`~minegeo.synth.imu.ImuParams`, as the
   ``drone`` stream) and written as the contract's ``imu.csv`` next to the frames
   (:func:`write_flight_imu`).

The ray casting of step 3 (:class:`NetworkWorld`) is in :mod:`minegeo.synth.network_world` (importable here).

Frames: poses are ``T_world_sensor`` (4x4, m), world = the network's map frame (z up, floor z = 0);
sensor x forward, y left, z up. See ``docs/intersections.md`` ("Experiment: drone flight").
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from minegeo.errors import InputError
from minegeo.io.types import Trajectory
from minegeo.synth.motion import rot_zyx
from minegeo.synth.network_world import NetworkWorld

__all__ = ["NetworkWorld", "FlightParams", "Flight", "FlightFrames", "plan_route", "make_flight", "simulate_flight",
           "MINE_FLIGHT", "mine_flight",
           "flight_clearance", "junction_passes", "flight_curve", "flight_imu", "write_flight_imu",
           "FLIGHT_IMU_MARGIN_S"]

log = logging.getLogger(__name__)

G_MPS2 = 9.81
CLOCK_HZ = 10.0
#: the flight's IMU runs this long before the first and after the last clock pose (s): the drone
#: hovers there at its first / last pose
FLIGHT_IMU_MARGIN_S = 0.5


def flight_clearance(net, xyz: np.ndarray) -> np.ndarray:
    """Clearance (m) of points (k, 3) to the network's surfaces (lower bound; negative = outside).

    ``min(max_e (w_e / 2 - d_e), z, roof - z)`` with ``d_e`` the horizontal distance to drift ``e``'s
    segment and ``roof`` the height of the nearest node.
    """
    from minegeo.synth.network import _roof, segment_distances

    P = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    A, B = net.nodes[net.edges[:, 0]], net.nodes[net.edges[:, 1]]
    horiz = (0.5 * net.widths[None] - segment_distances(P[:, :2], A, B)).max(1)
    return np.minimum(horiz, np.minimum(P[:, 2], _roof(net, P[:, :2]) - P[:, 2]))


# ---------------------------------------------------------------------------------------- route
def _incident(net) -> list:
    inc = [[] for _ in range(len(net.nodes))]
    for e, (i, j) in enumerate(net.edges):
        inc[i].append(e)
        inc[j].append(e)
    return inc


def plan_route(net, length_m: float, seed: int = 0, start: int | None = None) -> np.ndarray:
    """Node ids of a walk over ``net`` of at least ``length_m`` (m of drift centrelines).

    Parameters
    ----------
    net : DriftNetwork
    length_m : float
        Minimum total length of the walk (sum of its drifts' segment lengths, m).
    seed : int
        Breaks ties between equally-flown exits.
    start : int, optional
        First node; default the first dead end (degree 1) next to a junction, else node 0.

    Returns
    -------
    ndarray (k,) int
        Node ids; consecutive ids share a drift. At a dead end the walk turns back (``a, b, a``).
    """
    if not (np.isfinite(length_m) and length_m > 0):
        raise InputError(f"length_m must be > 0, got {length_m}")
    deg, inc = net.degree(), _incident(net)
    if start is None:
        dead = [i for i in np.flatnonzero(deg == 1) if any(deg[j] >= 3 for j in net.edges[inc[i][0]])]
        start = int(dead[0]) if dead else 0
    rng = np.random.default_rng(seed)
    L = np.linalg.norm(net.nodes[net.edges[:, 0]] - net.nodes[net.edges[:, 1]], axis=1)
    edge_n = np.zeros(len(net.edges), np.int64)
    turns: dict = {}
    route, node, e_in, total = [int(start)], int(start), -1, 0.0
    while total < length_m:
        opts = [e for e in inc[node] if e != e_in] or [e_in]
        keys = [(turns.get((node, e_in, e), 0), edge_n[e], rng.random()) for e in opts]
        e = opts[min(range(len(opts)), key=lambda k: keys[k])]
        turns[(node, e_in, e)] = turns.get((node, e_in, e), 0) + 1
        edge_n[e] += 1
        total += L[e]
        node = int(net.edges[e, 1] if net.edges[e, 0] == node else net.edges[e, 0])
        route.append(node)
        e_in = e
    return np.asarray(route, np.int64)


# ---------------------------------------------------------------------------------------- trajectory
@dataclass(frozen=True)
class FlightParams:
    """Parameters of a drone flight (lengths m, speeds m/s, angles deg, times s).

    Attributes
    ----------
    length_m : float
        Minimum route length (centreline, m); the flown path is slightly shorter at cut corners.
    speed_mps, accel_mps2, lat_accel_mps2 : float
        Cruise speed, along-path acceleration limit, lateral (centripetal) acceleration limit.
    yaw_rate_dps : float
        Yaw rate of the hover turn at dead ends.
    height_m : float or None
        Flight height above the floor; None = half the lowest roof of the network.
    lateral_amp_m, vertical_amp_m : float
        Peak smooth seeded oscillation across the drift / up-down (the lateral one is capped at 6 % of
        the narrowest drift width).
    yaw_sway_deg, tilt_noise_deg : float
        Peak smooth seeded yaw sway and roll/pitch noise on top of the acceleration tilt.
    corner_m : float
        Corner cut at direction changes over 15 degrees (capped at half the narrowest drift width).
    frame_step_m, frame_yaw_deg, frame_max_dt_s : float
        A frame each ``frame_step_m`` of travel, ``frame_yaw_deg`` of yaw change or ``frame_max_dt_s``.
    azimuth_step_deg, range_noise_m, max_range_m : float
        VLP-16 model: azimuth step of one rotation (16 rings, -15..15 deg), range noise sigma, range.
    seed : int
        Seeds the route's tie-breaks, the motion noise and each frame's range noise.
    """

    length_m: float = 3000.0
    speed_mps: float = 1.5
    accel_mps2: float = 0.5
    lat_accel_mps2: float = 0.6
    yaw_rate_dps: float = 45.0
    height_m: float | None = None
    lateral_amp_m: float = 0.3
    vertical_amp_m: float = 0.15
    yaw_sway_deg: float = 3.0
    tilt_noise_deg: float = 1.0
    corner_m: float = 3.0
    frame_step_m: float = 1.0
    frame_yaw_deg: float = 15.0
    frame_max_dt_s: float = 2.0
    azimuth_step_deg: float = 0.4
    range_noise_m: float = 0.03
    max_range_m: float = 100.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class Flight:
    """A planned flight.

    Attributes
    ----------
    route : ndarray (k,) int
        Node ids flown (:func:`plan_route`).
    clock : Trajectory
        ``T_world_sensor`` on the 10 Hz clock (world = map frame).
    frame_index : ndarray (n,) int
        Indices into ``clock`` of the frames.
    path_length_m : float
        Length of the flown 3-D path over the frames (m).
    params : FlightParams
    """

    route: np.ndarray
    clock: Trajectory
    frame_index: np.ndarray
    path_length_m: float
    params: FlightParams

    @property
    def truth(self) -> Trajectory:
        """``T_world_sensor`` at the frames."""
        k = self.frame_index
        return Trajectory(times_s=self.clock.times_s[k], poses=self.clock.poses[k], frame="world", body="sensor")


def _legs(net, route: np.ndarray) -> list:
    """Split the route at reversals (dead ends): a list of node-position polylines (k, 2)."""
    legs, cur = [], [route[0]]
    for k in range(1, len(route)):
        cur.append(route[k])
        if k + 1 < len(route) and route[k + 1] == route[k - 1]:
            legs.append(net.nodes[np.asarray(cur)])
            cur = [route[k]]
    legs.append(net.nodes[np.asarray(cur)])
    return legs


def _cut_corners(P: np.ndarray, corner_m: float, step_m: float = 0.05) -> np.ndarray:
    """Dense 2-D polyline (every ``step_m``) through ``P`` with corners over 15 deg cut by Bezier arcs."""
    parts = [P[:1]]
    for k in range(1, len(P)):
        a, c = parts[-1][-1], P[k]
        if k + 1 < len(P):
            u, v = P[k] - P[k - 1], P[k + 1] - P[k]
            lu, lv = np.linalg.norm(u), np.linalg.norm(v)
            if u @ v < np.cos(np.radians(15.0)) * lu * lv:
                cu, cv = min(corner_m, 0.45 * lu), min(corner_m, 0.45 * lv)
                A, B = c - u / lu * cu, c + v / lv * cv
                n = max(int(np.ceil(np.linalg.norm(A - a) / step_m)), 1)
                parts.append(a + np.linspace(0, 1, n + 1)[1:, None] * (A - a))
                m = max(int(np.ceil((cu + cv) / step_m)), 4)
                t = np.linspace(0, 1, m + 1)[1:, None]
                parts.append((1 - t) ** 2 * A + 2 * (1 - t) * t * c + t**2 * B)
                continue
        n = max(int(np.ceil(np.linalg.norm(c - a) / step_m)), 1)
        parts.append(a + np.linspace(0, 1, n + 1)[1:, None] * (c - a))
    return np.concatenate(parts)


def _path_curvature(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segment lengths ``ds`` (k-1,) and heading change per metre ``kappa`` (k,; 0 at both ends) of a
    dense 2-D path ``C`` (k, 2): the turn at each inner vertex over the mean of its two segments."""
    ds = np.linalg.norm(np.diff(C, axis=0), axis=1)
    h = np.unwrap(np.arctan2(*np.diff(C, axis=0).T[::-1]))
    kappa = np.zeros(len(C))
    kappa[1:-1] = np.abs(np.diff(h)) / np.maximum(0.5 * (ds[1:] + ds[:-1]), 1e-9)
    return ds, kappa


def _vertex_times(v_cap: np.ndarray, ds: np.ndarray, accel_mps2: float, min_speed_mps: float) -> np.ndarray:
    """Times (s, 0 at the first vertex) at the vertices of a path with segment lengths ``ds``: the speed
    at each vertex at most ``v_cap``, 0 at both ends, reached within ``accel_mps2`` (a forward and a
    backward pass); each segment is run at the mean of its end speeds, at least ``min_speed_mps``."""
    v = np.array(v_cap, dtype=np.float64)
    v[0] = v[-1] = 0.0
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * accel_mps2 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * accel_mps2 * ds[i]))
    vm = np.maximum(0.5 * (v[1:] + v[:-1]), min_speed_mps)
    return np.concatenate([[0.0], np.cumsum(ds / vm)])


def _speed_profile(C: np.ndarray, p: FlightParams) -> np.ndarray:
    """Times (s) at the vertices of a dense 2-D path: curvature- and acceleration-limited speed, 0 at the ends."""
    ds, kappa = _path_curvature(C)
    kappa = np.convolve(kappa, np.ones(9) / 9.0, mode="same")
    v = np.minimum(p.speed_mps, np.sqrt(p.lat_accel_mps2 / np.maximum(kappa, 1e-9)))
    return _vertex_times(v, ds, p.accel_mps2, 0.05)


def _nominal(net, route: np.ndarray, p: FlightParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), 2-D positions and unwrapped yaw (rad) of the centreline flight with hover turns."""
    corner = min(p.corner_m, 0.5 * float(net.widths.min()))
    rng = np.random.default_rng([p.seed, 1])
    T, X, Y = [], [], []
    t0, yaw_prev = 0.0, None
    for leg in _legs(net, route):
        C = _cut_corners(leg, corner)
        ts = _speed_profile(C, p) + t0
        d = np.gradient(C, axis=0)
        yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        if yaw_prev is not None:                            # hover turn of 180 deg at the dead end
            sign = 1.0 if rng.random() < 0.5 else -1.0
            target = yaw_prev + sign * np.pi
            yaw += 2 * np.pi * np.round((target - yaw[0]) / (2 * np.pi))
            dur = np.pi / np.radians(p.yaw_rate_dps)
            s = np.linspace(0.0, 1.0, 21)[1:-1]
            T.append(t0 + s * dur)
            X.append(np.repeat(C[:1], len(s), 0))
            Y.append(yaw_prev + (yaw[0] - yaw_prev) * (3 * s**2 - 2 * s**3))
            ts = ts + dur
        T.append(ts)
        X.append(C)
        Y.append(yaw)
        t0, yaw_prev = ts[-1], yaw[-1]
    t, x, y = np.concatenate(T), np.concatenate(X), np.concatenate(Y)
    keep = np.concatenate([[True], np.diff(t) > 1e-9])
    return t[keep], x[keep], y[keep]


def _smooth(x: np.ndarray, n: int) -> np.ndarray:
    """Moving average over ``n`` samples (edges padded with the end values)."""
    k = np.ones(n) / n
    return np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), k, mode="valid")


def make_flight(net, params: FlightParams | None = None, route=None) -> Flight:
    """Plan a 6-DoF drone flight over ``net`` (see the module docstring).

    Parameters
    ----------
    net : DriftNetwork
    params : FlightParams, optional
    route : sequence of int, optional
        Node ids to fly (consecutive ids must share a drift); default :func:`plan_route` with
        ``params.length_m`` and ``params.seed``.

    Returns
    -------
    Flight
        Poses ``T_world_sensor`` on a 10 Hz clock and the frame indices.
    """
    from minegeo.synth.network import _roof
    from minegeo.synth.trajectory import _smooth_noise

    p = params or FlightParams()
    route = plan_route(net, p.length_m, p.seed) if route is None else np.asarray(route, np.int64)
    edges = {tuple(sorted(e)) for e in net.edges.tolist()}
    if len(route) < 2 or any(tuple(sorted((int(a), int(b)))) not in edges for a, b in zip(route[:-1], route[1:], strict=True)):
        raise InputError("route: consecutive node ids must share a drift")
    t_n, xy_n, yaw_n = _nominal(net, route, p)
    t = np.arange(0.0, t_n[-1], 1.0 / CLOCK_HZ)
    xy = np.column_stack([np.interp(t, t_n, xy_n[:, 0]), np.interp(t, t_n, xy_n[:, 1])])
    yaw = np.interp(t, t_n, yaw_n)
    rng = np.random.default_rng([p.seed, 2])
    lat = _smooth_noise(rng, t, min(p.lateral_amp_m, 0.06 * float(net.widths.min())), 0.01, 0.08)
    h0 = 0.5 * float(net.node_heights.min()) if p.height_m is None else float(p.height_m)
    z = h0 + _smooth_noise(rng, t, p.vertical_amp_m, 0.02, 0.1)
    yaw = yaw + np.radians(_smooth_noise(rng, t, p.yaw_sway_deg, 0.02, 0.15))
    xy = xy + lat[:, None] * np.column_stack([-np.sin(yaw), np.cos(yaw)])
    dt = 1.0 / CLOCK_HZ
    acc = np.stack([_smooth(np.gradient(np.gradient(xy[:, i], dt), dt), 10) for i in range(2)], 1)
    a_f = acc[:, 0] * np.cos(yaw) + acc[:, 1] * np.sin(yaw)
    a_l = -acc[:, 0] * np.sin(yaw) + acc[:, 1] * np.cos(yaw)
    pitch = np.arctan(a_f / G_MPS2) + np.radians(_smooth_noise(rng, t, p.tilt_noise_deg, 0.05, 0.3))
    roll = -np.arctan(a_l / G_MPS2) + np.radians(_smooth_noise(rng, t, p.tilt_noise_deg, 0.05, 0.3))
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = rot_zyx(yaw, pitch, roll)
    poses[:, :3, 3] = np.column_stack([xy, np.minimum(z, _roof(net, xy) - 0.6)])
    idx, last = [0], 0
    step = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))]
    for k in range(1, len(t)):
        if (step[k] - step[last] >= p.frame_step_m or abs(yaw[k] - yaw[last]) >= np.radians(p.frame_yaw_deg)
                or t[k] - t[last] >= p.frame_max_dt_s - 1e-9):
            idx.append(k)
            last = k
    idx = np.asarray(idx, np.int64)
    L = float(np.linalg.norm(np.diff(poses[idx, :3, 3], axis=0), axis=1).sum())
    clock = Trajectory(times_s=t, poses=poses, frame="world", body="sensor")
    return Flight(route=route, clock=clock, frame_index=idx, path_length_m=L, params=p)


def junction_passes(positions: np.ndarray, junction_xy: np.ndarray, pass_radius_m: float = 3.0,
                    visit_radius_m: float = 12.0) -> list:
    """Passes of a trajectory through junctions.

    A **visit** of junction ``j`` is a maximal run of consecutive samples within ``visit_radius_m``
    (horizontal) of its point ``junction_xy[j]``; a **pass** is a visit that comes within
    ``pass_radius_m`` of it. The entry direction is the bearing (deg, from +x) of the first sample of
    the visit seen from the junction.

    Returns
    -------
    list of dict
        ``junction`` (index into ``junction_xy``), ``first``/``last`` sample indices of the visit,
        ``closest`` sample index, ``min_dist_m``, ``entry_bearing_deg``.
    """
    P = np.asarray(positions, dtype=np.float64)[:, :2]
    out = []
    for j, c in enumerate(np.asarray(junction_xy, dtype=np.float64)):
        d = np.linalg.norm(P - c, axis=1)
        near = np.r_[False, d < visit_radius_m, False]
        starts = np.flatnonzero(~near[:-1] & near[1:])
        ends = np.flatnonzero(near[:-1] & ~near[1:])
        for a, b in zip(starts, ends, strict=True):
            k = a + int(np.argmin(d[a:b]))
            if d[k] <= pass_radius_m:
                v = P[a] - c
                out.append({"junction": j, "first": int(a), "last": int(b - 1), "closest": int(k),
                            "min_dist_m": float(d[k]), "entry_bearing_deg": float(np.degrees(np.arctan2(v[1], v[0])))})
    return sorted(out, key=lambda r: r["first"])


# ---------------------------------------------------------------------------------------- IMU
def _euler_zyx(R: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (rad; yaw unwrapped along the sequence) of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (k, 3, 3)."""
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    return np.column_stack([yaw, pitch, roll])


def flight_curve(flight: Flight, margin_s: float = FLIGHT_IMU_MARGIN_S):
    """The continuous motion of a flight: a cubic B-spline through every pose of its 10 Hz clock.

    The clock poses (``flight.clock``, ``T_world_sensor``; the frames are a subset of them) give
    six channels ``s_k`` (x, y, z in m; yaw unwrapped, pitch, roll in rad of ``Rz Ry Rx``) at
    ``t_k = t_0 + k h`` (``h = 1 / CLOCK_HZ``). The curve is the uniform cubic B-spline with knots
    at the ``t_k`` (:class:`~minegeo.synth.motion.MotionCurve`) that **interpolates** them,
    ``(c_{k-1} + 4 c_k + c_{k+1}) / 6 = s_k`` for every sample, so its pose at each clock time (and
    so at each frame time) is the pose the frame was simulated at (to rounding), and between them it
    is C2: position, velocity, acceleration and angular rate exist everywhere, as an IMU needs.
    ``margin_s`` (rounded to whole samples) of hover at the first and the last pose is added on
    both sides (the samples repeated); the end conditions are zero second difference of the
    control points (a natural spline). The tridiagonal system is solved per channel
    (:func:`scipy.linalg.solve_banded`).

    Returns
    -------
    MotionCurve
        Defined on ``[t_0 - margin, t_last + margin]`` (s).
    """
    from scipy.linalg import solve_banded

    from minegeo.synth.motion import MotionCurve

    t = flight.clock.times_s
    h = 1.0 / CLOCK_HZ
    if t.size < 2 or np.max(np.abs(np.diff(t) - h)) > 1e-6:
        raise InputError(f"flight_curve: the clock must be uniform at {CLOCK_HZ:g} Hz")
    P = flight.clock.poses
    S = np.column_stack([P[:, :3, 3], _euler_zyx(P[:, :3, :3])])
    m = int(round(margin_s / h))
    S = np.concatenate([np.repeat(S[:1], m, 0), S, np.repeat(S[-1:], m, 0)])
    n = len(S)
    # unknowns c_0 .. c_{n+1}; rows k = 0..n-1: c_k + 4 c_{k+1} + c_{k+2} = 6 s_k; natural ends
    # (c_0 - 2 c_1 + c_2 = 0, likewise at the end) give c_1 = s_0, c_n = s_{n-1}; the rest is
    # tridiagonal in c_2 .. c_{n-1}
    C = np.empty((n + 2, 6))
    C[1], C[n] = S[0], S[-1]
    if n > 2:
        rhs = 6.0 * S[1:n - 1].copy()
        rhs[0] -= C[1]
        rhs[-1] -= C[n]
        ab = np.zeros((3, n - 2))
        ab[0, 1:], ab[1], ab[2, :-1] = 1.0, 4.0, 1.0
        C[2:n] = solve_banded((1, 1), ab, rhs)
    C[0] = 2.0 * C[1] - C[2]
    C[n + 1] = 2.0 * C[n] - C[n - 1]
    return MotionCurve(t0_s=float(t[0]) - m * h, dt_knot_s=h, ctrl=C)


def flight_imu(flight: Flight, params=None, seed: int | None = None):
    """The flight's IMU (gyro and accelerometer on the sensor axes) from :func:`flight_curve`.

    :func:`~minegeo.synth.imu.simulate_imu` over the whole curve (from ``FLIGHT_IMU_MARGIN_S``
    before the first clock pose to as long after the last), samples at ``t_start + k / rate_hz``.

    Parameters
    ----------
    flight : Flight
    params : ImuParams, optional
        Default :class:`~minegeo.synth.imu.ImuParams` (200 Hz, ADIS16448 noise: the ``drone`` stream's).
    seed : int, optional
        Default ``flight.params.seed``; the white noise and the bias walk are the two children of
        ``SeedSequence([seed, 4])``.

    Returns
    -------
    ImuData
    """
    from minegeo.synth.imu import ImuParams, simulate_imu

    params = params or ImuParams()
    curve = flight_curve(flight)
    ss_noise, ss_bias = np.random.SeedSequence([int(flight.params.seed if seed is None else seed), 4]).spawn(2)
    return simulate_imu(curve, params, curve.t_start, curve.t_end, np.random.default_rng(ss_noise),
                        np.random.default_rng(ss_bias))


def write_flight_imu(folder, flight: Flight, params=None, seed: int | None = None) -> Path:
    """Write :func:`flight_imu` into ``folder`` as ``imu.csv`` (the SLAM contract's
    ``t,gx,gy,gz,ax,ay,az``: s on the frames' clock, rad/s, m/s² specific force with gravity, LiDAR
    axes) and ``imu_truth.csv`` (noise- and bias-free readings, biases, velocity); written atomically
    and kept when present. Returns the ``imu.csv`` path."""
    from minegeo.synth.imu import imu_csv_text, imu_truth_csv_text

    folder = Path(folder)
    out = folder / "imu.csv"
    if not out.exists():
        imu = flight_imu(flight, params, seed)
        for name, text in (("imu_truth.csv", imu_truth_csv_text(imu)), ("imu.csv", imu_csv_text(imu))):
            tmp = folder / f"{name}.tmp"
            tmp.write_text(text)
            os.replace(tmp, folder / name)
    return out


# ---------------------------------------------------------------------------------------- frames
@dataclass(frozen=True, eq=False)
class FlightFrames:
    """Simulated frames of a flight, cached on disk and read lazily.

    Attributes
    ----------
    folder : Path
        Cache folder: ``meta.json``, ``truth.tum`` and ``chunk_XXXX.npz`` (``counts``, float32 ``points``).
    truth : Trajectory
        ``T_world_sensor`` of the frames (world = map frame).
    chunk : int
        Frames per chunk file.
    """

    folder: Path
    truth: Trajectory
    chunk: int

    def __len__(self) -> int:
        return len(self.truth)

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        """``(time_s, points (n, 3) float64 in the sensor frame)`` in time order, read chunk by chunk."""
        for c0 in range(0, len(self), self.chunk):
            with np.load(self.folder / f"chunk_{c0 // self.chunk:04d}.npz") as z:
                counts, pts = z["counts"], z["points"].astype(np.float64)
            off = np.r_[0, np.cumsum(counts)]
            for k in range(len(counts)):
                yield float(self.truth.times_s[c0 + k]), pts[off[k]:off[k + 1]]


def _key(net, flight: Flight) -> str:
    h = hashlib.sha256()
    for a in (net.nodes, net.edges, net.widths, net.node_heights, flight.route):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps(asdict(flight.params), sort_keys=True, default=str).encode())
    if getattr(net, "roughness_m", 0.0):  # (flat networks keep their earlier cache keys)
        h.update(json.dumps([float(net.roughness_m), int(net.roughness_seed)]).encode())
    return h.hexdigest()[:16]


def simulate_flight(net, flight: Flight, cache_root, *, chunk: int = 200, progress=None) -> FlightFrames:
    """Simulate (or load from the cache) one VLP-16 rotation at each frame pose of ``flight``.

    Parameters
    ----------
    net : DriftNetwork
    flight : Flight
    cache_root : path
        Frames go to ``cache_root / <16 hex digits of a SHA-256 of net, route and params>``; chunks
        already there are kept (a run can be resumed).
    chunk : int
        Frames per chunk file.
    progress : callable, optional
        Called as ``progress(done, total)`` after each chunk.

    Returns
    -------
    FlightFrames
    """
    from minegeo.io import write_trajectory
    from minegeo.synth.sensors import Velodyne16, simulate_scan

    p = flight.params
    folder = Path(cache_root) / _key(net, flight)
    folder.mkdir(parents=True, exist_ok=True)
    truth = flight.truth
    world = NetworkWorld(net)
    sensor = Velodyne16(azimuth_step_deg=p.azimuth_step_deg, range_noise_sigma_m=p.range_noise_m,
                        max_range_m=p.max_range_m)
    seeds = np.random.default_rng([p.seed, 3]).integers(0, 2**31 - 1, len(truth))
    for c0 in range(0, len(truth), chunk):
        f = folder / f"chunk_{c0 // chunk:04d}.npz"
        if not f.exists():
            pts = [simulate_scan(world, sensor, truth.poses[k], seed=int(seeds[k])).points.astype(np.float32)
                   for k in range(c0, min(c0 + chunk, len(truth)))]
            tmp = folder / f"chunk_{c0 // chunk:04d}.tmp.npz"
            np.savez(tmp, counts=np.array([len(q) for q in pts], np.int64), points=np.concatenate(pts))
            os.replace(tmp, f)
            log.info("flight frames: %d / %d", min(c0 + chunk, len(truth)), len(truth))
        if progress is not None:
            progress(min(c0 + chunk, len(truth)), len(truth))
    if not (folder / "truth.tum").exists():
        write_trajectory(folder / "truth.tum", truth, "tum", coordinates="local")
        meta = {"params": asdict(p), "route": flight.route.tolist(), "frames": len(truth),
                "path_length_m": flight.path_length_m, "chunk": chunk, "network": net.info}
        (folder / "meta.json").write_text(json.dumps(meta, indent=1, default=str))
    return FlightFrames(folder=folder, truth=truth, chunk=chunk)


#: The drone flight of ``minegeo synth --flight`` on the small mine's level 0 (drift name, flown
#: forwards): from 2 m past the T junction at the west end of the main drift, past the Y and the X
#: junction, down the crosscut to the T of the parallel drift and 8 m west along it (about 55 m).
MINE_FLIGHT = {
    "drifts": (("main_L0_001", True), ("main_L0_002", True), ("crosscut_L0_006", True), ("parallel_L0_009", False)),
    "start_m": 2.0,
    "end_m": 8.0,
}


def mine_flight(world, *, rate_hz: float = 1.0, azimuth_step_deg: float = 2.0, seed: int = 0):
    """A drone flight through a :class:`~minegeo.synth.world.MineWorld` (``MINE_FLIGHT``, small preset).

    The carrier is :func:`~minegeo.synth.trajectory.make_trajectory`'s ``"fly"`` (1.0 m/s, 2.3 m above
    the floor, yaw and tilt sway); a VLP-16 (16 rings, +-15 deg, ``azimuth_step_deg``) records one
    rotation per frame at each pose of a ``rate_hz`` clock (no motion distortion), ray cast against
    the world the survey map was scanned from.

    Returns
    -------
    truth : Trajectory
        ``T_map_sensor`` (m; ``frame="map"``: the world frame of the mine, the frame of ``map.ply``).
    frames : list of (n_i, 3) ndarray
        Each frame's points in its sensor frame (m; x forward, y left, z up).
    """
    from dataclasses import replace as _replace

    from minegeo.synth.sensors import Velodyne16
    from minegeo.synth.sequence import route_path, simulate_sequence

    path = route_path(world, MINE_FLIGHT["drifts"], MINE_FLIGHT["start_m"], MINE_FLIGHT["end_m"])
    truth, frames = simulate_sequence(world, path, rate_hz=rate_hz, kind="fly", seed=seed,
                                      sensor=Velodyne16(azimuth_step_deg=azimuth_step_deg))
    return _replace(truth, frame="map"), frames
