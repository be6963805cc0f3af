"""Synthetic LiDAR frame sequences for ``minegeo slam``: a drive along a route of the synthetic mine.

A route is a list of drifts of the :class:`~minegeo.synth.world.MineWorld` driven one after the
other (each forwards or backwards); the carrier follows it with the sway of its kind
(:func:`~minegeo.synth.trajectory.make_trajectory`), and a sensor (by default a VLP-16) records one
frame at each true pose of a regular clock, every point in the sensor frame of its frame. The frames
are written as a frames folder (binary PLY, name order, ``times.txt``) as ``minegeo slam`` reads it.

:func:`pick_gcps_in_map` plays the surveyor who reads the map coordinates of the control targets off
a SLAM map: each target is seen from the frame nearest to it and lands in the map where the SLAM
estimate of that frame puts it, so the picked coordinates carry the SLAM error (the world-to-map
transform is never used).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from minegeo.errors import InputError
from minegeo.io.types import ControlPoints, Trajectory

__all__ = ["DEMO_LOOP", "route_path", "simulate_sequence", "write_frames", "pick_gcps_in_map"]

log = logging.getLogger(__name__)

#: The loop of ``minegeo demo`` on the small preset: 5 m of the main drift before the X junction,
#: east along the main drift, south down the crosscut, west along the parallel drift, north up the
#: crosscut back to the X junction and 12 m along the start again (the loop closure). Entries:
#: (drift name, driven forwards); ``start_m``/``end_m`` cut the joined path (negative: from its end).
DEMO_LOOP = {
    "drifts": (("main_L0_002", True), ("main_L0_003", True), ("crosscut_L0_008", True),
               ("parallel_L0_010", False), ("crosscut_L0_006", False), ("main_L0_003", True)),
    "start_m": -5.0,  # relative to the end of the first drift
    "end_m": 12.0,  # along the last drift
}


def route_path(world, drifts, start_m: float = 0.0, end_m: float | None = None, *, corner_m: float = 3.0) -> np.ndarray:
    """Floor-centreline path (k, 3) along consecutive drifts of ``world``.

    Parameters
    ----------
    world : MineWorld
    drifts : sequence of (str, bool)
        Drift names with the direction driven (True: from its start node to its end node).
    start_m : float
        Where the path starts on the first drift: metres along it, or, when negative, metres before
        its end.
    end_m : float, optional
        Where the path ends on the last drift (metres along it as driven); default its end.
    corner_m : float
        Where two drifts meet at an angle over 15 degrees, the path leaves the first ``corner_m``
        before the junction and joins the second ``corner_m`` after it along a quadratic Bezier
        arc (a vehicle turns on a curve; for 90 degrees the arc passes 0.35 ``corner_m`` inside the
        corner).

    Returns
    -------
    (k, 3) ndarray
        World frame, metres.

    Raises
    ------
    InputError
        An unknown drift name, or two consecutive drifts that do not meet.
    """
    from minegeo.synth.trajectory import _arc_lengths, _cut

    by_name = {d.name: d for d in world.drifts}
    polys = []
    for name, forward in drifts:
        if name not in by_name:
            raise InputError(f"route: no drift {name!r} in this world")
        c = by_name[name].centreline
        polys.append(c if forward else c[::-1])
    for k in range(1, len(polys)):
        if np.linalg.norm(polys[k][0] - polys[k - 1][-1]) > 0.5:
            raise InputError(f"route: drift {drifts[k][0]} does not start where {drifts[k - 1][0]} ends")
    first_len = float(_arc_lengths(polys[0])[-1])
    s0 = first_len + start_m if start_m < 0 else float(start_m)
    last_len = float(_arc_lengths(polys[-1])[-1])
    pieces = [p.copy() for p in polys]
    joins: list[np.ndarray | None] = []
    for k in range(1, len(pieces)):
        a, b = pieces[k - 1], pieces[k]
        u, v = a[-1] - a[-2], b[1] - b[0]
        cos = float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
        if cos > np.cos(np.radians(15.0)) or corner_m <= 0:
            joins.append(None)
            continue
        corner = a[-1].copy()
        la, lb = float(_arc_lengths(a)[-1]), float(_arc_lengths(b)[-1])
        pieces[k - 1] = _cut(a, 0.0, la - min(corner_m, 0.45 * la))
        pieces[k] = _cut(b, min(corner_m, 0.45 * lb), lb)
        t = np.linspace(0.0, 1.0, 9)[1:-1, None]
        A, B = pieces[k - 1][-1], pieces[k][0]
        joins.append((1 - t) ** 2 * A + 2 * (1 - t) * t * corner + t**2 * B)
    parts = [pieces[0]]
    for k in range(1, len(pieces)):
        if joins[k - 1] is not None:
            parts.append(joins[k - 1])
            parts.append(pieces[k])
        else:
            parts.append(pieces[k][1:])
    path = np.concatenate(parts)
    total = float(_arc_lengths(path)[-1])
    s1 = total if end_m is None else total - (last_len - float(end_m))
    return _cut(path, s0, s1)


def simulate_sequence(world, path, *, rate_hz: float = 4.0, sensor=None, kind: str = "drive",
                      seed: int = 0) -> tuple[Trajectory, list[np.ndarray]]:
    """Frames of a sensor carried along ``path``, one at each pose of a ``rate_hz`` clock.

    Parameters
    ----------
    world : MineWorld
    path : (k, 3) array
        Floor-centreline path (:func:`route_path`).
    rate_hz : float
        Frames per second (the carrier's speed is that of ``kind``: 2.5 m/s for ``drive``).
    sensor : sensor model, optional
        Default :class:`~minegeo.synth.sensors.Velodyne16` with a 2 degree azimuth step.
    kind : str
        Carrier (see :func:`~minegeo.synth.trajectory.make_trajectory`).
    seed : int
        Seeds the carrier's sway and each frame's range noise.

    Returns
    -------
    truth : Trajectory
        ``T_world_sensor`` at each frame time (``frame="world"``, times from 0 s).
    frames : list of (n_i, 3) ndarray
        Each frame's points in its sensor frame (one rotation at a fixed pose: no motion distortion).

    Raises
    ------
    InputError
        ``rate_hz`` not positive.
    """
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory

    if not rate_hz > 0:
        raise InputError(f"rate_hz must be > 0, got {rate_hz}")
    sensor = Velodyne16(azimuth_step_deg=2.0) if sensor is None else sensor
    rng = np.random.default_rng(seed)
    traj = make_trajectory(world, kind, path=path, seed=int(rng.integers(0, 2**31 - 1)))
    ts = np.arange(0.0, traj.times_s[-1], 1.0 / rate_hz)
    P = interpolate_poses(traj, ts)
    seeds = rng.integers(0, 2**31 - 1, len(ts))
    frames = [simulate_scan(world, sensor, T, seed=int(s)).points for T, s in zip(P, seeds, strict=True)]
    log.info("sequence: %d frames over %.1f s", len(frames), ts[-1])
    return Trajectory(times_s=ts, poses=P, frame="world", body="sensor"), frames


def write_frames(folder, times_s, frames) -> list[Path]:
    """Write ``frames`` as a frames folder: ``000000.ply`` ... (binary PLY, sensor frame) and ``times.txt``.

    Parameters
    ----------
    folder : path
        Created if missing; must be empty (a frames folder is read whole).
    times_s : (n,) array
        Frame times (s), increasing.
    frames : list of (n_i, 3) ndarray

    Returns
    -------
    list of Path
        The frame files in order.

    Raises
    ------
    InputError
        ``folder`` exists and is not empty.
    """
    from minegeo._provenance import atomic_write_text
    from minegeo.io import PointCloud, write_point_cloud

    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise InputError(f"{folder} is not empty")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, pts in enumerate(frames):
        p = folder / f"{k:06d}.ply"
        write_point_cloud(p, PointCloud(points=np.ascontiguousarray(pts, dtype=np.float64)), binary=True)
        paths.append(p)
    atomic_write_text(folder / "times.txt", "".join(f"{float(t):.6f}\n" for t in times_s))
    return paths


def pick_gcps_in_map(gcps: ControlPoints, truth: Trajectory, estimate: Trajectory, map_points, *,
                     max_range_m: float = 10.0, tolerance_m: float = 0.3) -> tuple[ControlPoints, list[dict]]:
    """Map coordinates of the control targets as read off a SLAM map.

    Each target ``p`` (world frame, ``gcps.local_xyz``) is seen from the frame ``k`` whose true
    position is nearest; in that frame it is at ``T_world_sensor,k^-1 p`` and the SLAM estimate puts
    it at ``T_map_sensor,k T_world_sensor,k^-1 p``. A target farther than ``max_range_m`` from every
    frame, or with no map point within ``tolerance_m`` of its picked place (not in the map), is
    left out.

    Parameters
    ----------
    gcps : ControlPoints
        Targets with world-frame ``local_xyz`` and their grid coordinates ``crs_enh``.
    truth : Trajectory
        ``T_world_sensor`` of the frames.
    estimate : Trajectory
        ``T_map_sensor`` of the same frames (matched by time within 1 ms), e.g. the SLAM trajectory.
    map_points : (m, 3) array
        The SLAM map (map frame).
    max_range_m, tolerance_m : float

    Returns
    -------
    picked : ControlPoints
        The targets found, ``local_xyz`` in the map frame, ``crs_enh`` and sigmas as given.
    rows : list of dict
        Per target: ``id``, ``picked`` (bool), ``frame`` (index or None), ``range_m``, ``reason``.

    Raises
    ------
    InputError
        The trajectories share fewer than one time, or fewer than 3 targets are found.
    """
    from scipy.spatial import cKDTree

    t_est = np.asarray(estimate.times_s)
    idx = np.searchsorted(t_est, truth.times_s)
    idx = np.clip(idx, 0, len(t_est) - 1)
    ok = np.abs(t_est[idx] - truth.times_s) < 1e-3
    if not ok.any():
        raise InputError("pick_gcps_in_map: the estimate shares no frame time with the truth")
    Tw, Tm = truth.poses[ok], estimate.poses[idx[ok]]
    tree = cKDTree(np.asarray(map_points, dtype=float))
    keep, local, rows = [], [], []
    for i, (gid, p) in enumerate(zip(gcps.ids, gcps.local_xyz, strict=True)):
        d = np.linalg.norm(Tw[:, :3, 3] - p, axis=1)
        k = int(np.argmin(d))
        row = {"id": gid, "picked": False, "frame": k, "range_m": float(d[k]), "reason": ""}
        if d[k] > max_range_m:
            row.update(frame=None, reason=f"{d[k]:.1f} m from the nearest frame")
            rows.append(row)
            continue
        q = Tw[k, :3, :3].T @ (p - Tw[k, :3, 3])  # the target in the sensor frame of frame k
        m = Tm[k, :3, :3] @ q + Tm[k, :3, 3]
        gap = float(tree.query(m)[0])
        if gap > tolerance_m:
            row["reason"] = f"no map point within {tolerance_m} m ({gap:.2f} m)"
        else:
            row["picked"] = True
            keep.append(i)
            local.append(m)
        rows.append(row)
    if len(keep) < 3:
        raise InputError(f"only {len(keep)} control point(s) found in the map; need 3")
    sl = None if gcps.sigma_local_m is None else gcps.sigma_local_m[keep]
    picked = ControlPoints(ids=[gcps.ids[i] for i in keep], local_xyz=np.array(local),
                           crs_enh=gcps.crs_enh[keep], sigma_enh_m=gcps.sigma_enh_m[keep], sigma_local_m=sl,
                           crs=gcps.crs)
    return picked, rows
