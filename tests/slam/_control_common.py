"""Shared synthetic set-up of the control-station tests (tests/slam/test_slam_control.py,
tests/slam/test_control_drift.py): the CRS and origin, the lever arm, a keyframe path whose truth is
known and control/check stations observed on it."""

from __future__ import annotations

import numpy as np

from minegeo.io.stations import Stations
from minegeo.kernels.lie import se3_exp, se3_inverse
from minegeo.slam.control import interpolate_poses, station_points

CRS = "EPSG:5186"
ORIGIN = np.array([200000.0, 550000.0, 0.0])
#: χ²(2) 95 % quantile: a horizontal error inside its 95 % ellipse
CHI2_2_95 = 5.991464547107979
#: station offset (lever arm) in the sensor frame (m)
OFFSET = np.array([0.1, -0.05, -1.2])


def truth(n=121, step=2.0):
    """Keyframes every 1 s on a winding, climbing path with three bends (local CRS frame, m):
    times (n,) s and T_local_sensor (n, 4, 4); ``step`` metres between keyframes."""
    t = np.arange(n, dtype=np.float64)
    s = step * t
    yaw = 0.9 * np.sin(s / 60.0) + 0.004 * s
    pos = np.c_[np.cumsum(step * np.cos(yaw)), np.cumsum(step * np.sin(yaw)), 0.01 * s + 0.5 * np.sin(s / 40.0)]
    T = np.tile(np.eye(4), (n, 1, 1))
    c, si = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -si, si, c
    T[:, :3, 3] = pos + [300.0, 400.0, 80.0]
    return t, T


def stations(t, T, times, roles, rng, offset=OFFSET, sh=0.005, sv=0.01):
    """Stations at ``times`` (s) on the true path, observed with N(0, sh) horizontal and N(0, sv)
    vertical noise (m): (Stations, true station points (n, 3) in the local CRS frame)."""
    true = station_points(interpolate_poses(t, T, times), offset)
    enh = true + rng.standard_normal(true.shape) * [sh, sh, sv]
    n = len(times)
    st = Stations(ids=[f"S{i:02d}" for i in range(n)], t_start_s=times, t_end_s=times, enh_local=enh,
                  origin_enh=ORIGIN, sigma_h_m=np.full(n, sh), sigma_v_m=np.full(n, sv), roles=roles, crs=CRS)
    return st, true


def biased_odometry(T, rng, sigma_rot, sigma_trans, scale=0.0, yaw_rate=0.0):
    """Chain edges of the poses ``T``: ``Z = Z_true Exp(bias + noise)``, the bias (scale, yaw rate per m) not
    in the information; ``(edges, Z, information, P)`` with ``P`` the poses chained from the first."""
    k = T.shape[0]
    sig = np.r_[np.full(3, sigma_rot), np.full(3, sigma_trans)]
    Z = np.empty((k - 1, 4, 4))
    for e in range(k - 1):
        Zt = se3_inverse(T[e]) @ T[e + 1]
        d = np.linalg.norm(Zt[:3, 3])
        Z[e] = Zt @ se3_exp(np.r_[0.0, 0.0, yaw_rate * d, scale * Zt[:3, 3]] + rng.standard_normal(6) * sig)
    P = np.tile(np.eye(4), (k, 1, 1))
    for e in range(k - 1):
        P[e + 1] = P[e] @ Z[e]
    return np.c_[np.arange(k - 1), np.arange(1, k)], Z, np.tile(np.diag(sig**-2.0), (k - 1, 1, 1)), P


def write_box_drive(folder, seed: int, n_points: int, pos: np.ndarray, dt: float) -> None:
    """Frames of a sensor moving through a 12 x 8 x 3 m box room (its walls sampled at ``n_points``
    random points per frame, ``default_rng(seed)``), one ``NNNNNN.ply`` per row of ``pos`` (the sensor's
    position, m; it turns 0.02 rad per frame about z), and ``times.txt`` (``dt`` s apart)."""
    from minegeo.io import PointCloud, write_point_cloud

    rng = np.random.default_rng(seed)
    half, centre = np.array([6.0, 4.0, 1.5]), np.array([1.0, 0.3, 0.0])
    for i in range(len(pos)):
        u = rng.uniform(-1.0, 1.0, (n_points, 3)) * half
        face = rng.integers(0, 3, n_points)
        u[np.arange(n_points), face] = np.sign(u[np.arange(n_points), face]) * half[face]
        c, s = np.cos(0.02 * i), np.sin(0.02 * i)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        write_point_cloud(folder / f"{i:06d}.ply", PointCloud(points=(u + centre - pos[i]) @ R))
    (folder / "times.txt").write_text("".join(f"{dt * i:.6f}\n" for i in range(len(pos))))


def write_stations_csv(path, enh: np.ndarray, roles, dt: float, sigma_h_m: str, sigma_v_m: str) -> None:
    """A stations file (``# crs:`` line, one row per ``(frame, role)`` of ``roles``: the station ``S<j>``
    at that frame's time, its E N H from ``enh``, the sigmas as written)."""
    rows = [f"# crs: {CRS}", "id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role"]
    for j, (i, role) in enumerate(roles):
        rows.append(f"S{j + 1},{dt * i:.6f},{dt * i:.6f},{enh[i, 0]:.4f},{enh[i, 1]:.4f},{enh[i, 2]:.4f},"
                    f"{sigma_h_m},{sigma_v_m},{role}")
    path.write_text("\n".join(rows) + "\n")
