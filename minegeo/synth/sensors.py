"""Sensor models and ray-cast simulation against the synthetic mine.

Every sensor is a frozen dataclass with units in its field names. Its sensor frame is
x forward, y left, z up. A simulation casts one ray per beam firing from the sensor
pose at the firing time (sphere tracing of :class:`~minegeo.synth.world.MineWorld`),
so occlusion, maximum range and motion during the sweep are physical. Range noise
``N(0, range_noise_sigma_m^2)`` is drawn in Python from ``np.random.default_rng(seed)``
(one draw per fired beam, hit or not, so the stream does not depend on the geometry)
and added along the beam. Returns beyond ``max_range_m`` or closer than
``min_range_m`` are dropped.

Specifications follow Baek et al. (2022), Table 1: ZEB-REVO (Hokuyo UTM-30LX-F, 270
degree line rotated about the forward axis, 30 m, +-3 cm), Velodyne PUCK-LITE (16
channels over +-15 degrees, 100 m, +-3 cm), iPad Pro flash LiDAR (5 m); the horizontal
2D scanner is the range-bearing profiler of the MAST beacon method (Simela et al.).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_transform
from minegeo.errors import InputError
from minegeo.io.types import PointCloud, Trajectory
from minegeo.synth.trajectory import _Interp

__all__ = ["Velodyne16", "ZebRevo", "FlashSensor", "Horizontal2D", "simulate_scan", "deskew", "Scan2D",
           "simulate_scan_2d", "SENSORS"]


@dataclass(frozen=True)
class Velodyne16:
    """16-ring spinning LiDAR (VLP-16 / PUCK-LITE-like).

    16 rings evenly over ``vertical_fov_deg`` (2 degree spacing), one firing column every
    ``azimuth_step_deg`` of a rotation at ``rotation_rate_hz``; a frame is one rotation.
    """

    n_rings: int = 16
    vertical_fov_deg: tuple = (-15.0, 15.0)
    azimuth_step_deg: float = 0.2
    rotation_rate_hz: float = 10.0
    max_range_m: float = 100.0
    min_range_m: float = 0.5
    range_noise_sigma_m: float = 0.03
    name: str = "velodyne16"

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.rotation_rate_hz

    def rays(self, frame_starts: np.ndarray):
        n_az = int(round(360.0 / self.azimuth_step_deg))
        az = np.radians(np.arange(n_az) * self.azimuth_step_deg)
        el = np.radians(np.linspace(self.vertical_fov_deg[0], self.vertical_fov_deg[1], self.n_rings))
        ce, se = np.cos(el), np.sin(el)
        d = np.stack([np.outer(np.cos(az), ce), np.outer(np.sin(az), ce), np.outer(np.ones(n_az), se)], axis=2)
        d = d.reshape(-1, 3)
        dt = np.repeat(np.arange(n_az) * (self.frame_period_s / n_az), self.n_rings)
        ring = np.tile(np.arange(self.n_rings, dtype=np.uint16), n_az)
        return _tile_frames(d, dt, {"ring": ring}, frame_starts)


@dataclass(frozen=True)
class ZebRevo:
    """Handheld rotating 2D scanner (GeoSLAM ZEB-REVO-like: Hokuyo line on a rotating head).

    A 270 degree line (beam angle ``alpha`` from +x, step ``angular_step_deg``) in a plane
    containing the forward axis; the plane rotates about x at ``rotation_rate_hz``:
    ``d = (cos a, sin a cos b, sin a sin b)`` with ``b = 2 pi f_rot t``. A frame is one line
    (``line_rate_hz``).
    """

    fov_deg: float = 270.0
    angular_step_deg: float = 0.25
    line_rate_hz: float = 40.0
    rotation_rate_hz: float = 0.5
    max_range_m: float = 30.0
    min_range_m: float = 0.1
    range_noise_sigma_m: float = 0.03
    name: str = "zebrevo"

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.line_rate_hz

    def rays(self, frame_starts: np.ndarray):
        half = self.fov_deg / 2
        a = np.radians(np.arange(-half, half + 1e-9, self.angular_step_deg))
        dt_line = (np.arange(a.size) / a.size) * (self.frame_period_s * 0.75)  # 270 of 360 degrees of a turn
        t = (np.asarray(frame_starts, float)[:, None] + dt_line[None, :]).ravel()
        aa = np.tile(a, len(frame_starts))
        b = 2 * np.pi * self.rotation_rate_hz * t
        d = np.column_stack([np.cos(aa), np.sin(aa) * np.cos(b), np.sin(aa) * np.sin(b)])
        return d, t, {}


@dataclass(frozen=True)
class FlashSensor:
    """Short-range dense flash LiDAR (iPad-Pro-like): an equi-angular grid of pixels per frame."""

    width_px: int = 192
    height_px: int = 144
    hfov_deg: float = 122.0
    vfov_deg: float = 92.0
    frame_rate_hz: float = 10.0
    max_range_m: float = 5.0
    min_range_m: float = 0.2
    range_noise_sigma_m: float = 0.01
    name: str = "flash"

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    def rays(self, frame_starts: np.ndarray):
        u = np.radians((np.arange(self.width_px) + 0.5) / self.width_px * self.hfov_deg - self.hfov_deg / 2)
        v = np.radians((np.arange(self.height_px) + 0.5) / self.height_px * self.vfov_deg - self.vfov_deg / 2)
        U, V = np.meshgrid(u, v)
        d = np.column_stack([np.ones(U.size), np.tan(U).ravel(), np.tan(V).ravel()])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return _tile_frames(d, np.zeros(U.size), {}, frame_starts)


@dataclass(frozen=True)
class Horizontal2D:
    """Horizontal 2D range-bearing scanner (beacon work): beams in the sensor x-y plane.

    Bearing ``theta`` counter-clockwise from +x, ``angular_step_deg`` 0.25 or 0.5 degrees
    over ``fov_deg``; a frame is one rotation at ``rotation_rate_hz``.
    """

    angular_step_deg: float = 0.25
    fov_deg: float = 360.0
    rotation_rate_hz: float = 10.0
    max_range_m: float = 30.0
    min_range_m: float = 0.1
    range_noise_sigma_m: float = 0.01
    name: str = "horizontal2d"

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.rotation_rate_hz

    def bearings_rad(self) -> np.ndarray:
        n = int(round(self.fov_deg / self.angular_step_deg))
        if self.fov_deg < 360.0:
            n += 1
        return np.radians(-self.fov_deg / 2 + np.arange(n) * self.angular_step_deg) if self.fov_deg < 360 \
            else np.radians(np.arange(n) * self.angular_step_deg)

    def rays(self, frame_starts: np.ndarray):
        b = self.bearings_rad()
        d = np.column_stack([np.cos(b), np.sin(b), np.zeros(b.size)])
        dt = np.arange(b.size) * (self.frame_period_s * self.fov_deg / 360.0 / b.size)
        return _tile_frames(d, dt, {"bearing_rad": b}, frame_starts)


#: name -> default sensor
SENSORS = {"velodyne16": Velodyne16(), "zebrevo": ZebRevo(), "flash": FlashSensor(), "horizontal2d": Horizontal2D()}


def _tile_frames(d, dt, attrs, frame_starts):
    fs = np.asarray(frame_starts, float)
    n = len(fs)
    D = np.tile(d, (n, 1))
    t = (fs[:, None] + dt[None, :]).ravel()
    A = {k: np.tile(v, n) for k, v in attrs.items()}
    return D, t, A


def _check_sensor(sensor):
    if not hasattr(sensor, "rays") or not hasattr(sensor, "max_range_m"):
        raise InputError(f"not a sensor model: {type(sensor).__name__}")
    if not (sensor.max_range_m > sensor.min_range_m >= 0 and sensor.range_noise_sigma_m >= 0):
        raise InputError(f"{sensor.name}: need max_range_m > min_range_m >= 0 and range_noise_sigma_m >= 0")


def simulate_scan(world, sensor, pose, seed: int = 0, *, frame_stride: int = 1, frame_times_s=None,
                  chunk_rays: int = 2_000_000) -> PointCloud:
    """Simulate a sensor in the mine by ray casting, from a fixed pose or along a trajectory.

    Parameters
    ----------
    world : MineWorld
    sensor : Velodyne16 | ZebRevo | FlashSensor | Horizontal2D
    pose : (4, 4) array, Trajectory or MotionCurve
        ``T_world_sensor``. A fixed pose simulates one frame (one rotation / one flash; the
        ZEB-REVO a full half-turn of its head, i.e. ``0.5 / rotation_rate_hz`` s of lines).
        A trajectory simulates frames over its time span; each beam uses the pose
        interpolated at its own firing time (motion distortion is real). A
        :class:`~minegeo.synth.motion.MotionCurve` (needs ``frame_times_s``) gives each beam the
        curve's exact pose at its firing time.
    seed : int, SeedSequence or Generator
        Seeds the range noise (a Generator is drawn from and left advanced).
    frame_stride : int
        Simulate every ``frame_stride``-th frame only (thins long sequences).
    frame_times_s : array, optional
        Explicit frame start times (overrides the regular frame clock).
    chunk_rays : int
        Rays cast per batch (memory bound).

    Returns
    -------
    PointCloud
        ``frame="sensor"``: each point in the sensor frame **at its own timestamp**
        (``attributes["time_s"]``), ``range_m`` (noisy measured range) and, per sensor,
        ``ring`` or ``bearing_rad``. Use :func:`deskew` to assemble into the world frame.
    """
    _check_sensor(sensor)
    if frame_stride < 1:
        raise InputError("frame_stride must be >= 1")
    if hasattr(pose, "rotation_position"):  # a continuous-time MotionCurve (minegeo.synth.motion)
        if frame_times_s is None:
            raise InputError("simulate_scan on a motion curve needs frame_times_s")
        traj = Trajectory(times_s=np.zeros(1), poses=np.eye(4)[None], frame="world", body="sensor")
    elif isinstance(pose, Trajectory):
        traj = pose
    else:
        T = as_transform(pose, "T_world_sensor")
        traj = Trajectory(times_s=np.zeros(1), poses=T[None], frame="world", body="sensor")
    if frame_times_s is not None:
        starts = np.asarray(frame_times_s, float).reshape(-1)
    elif len(traj) == 1:
        if isinstance(sensor, ZebRevo):
            nl = int(round(0.5 / sensor.rotation_rate_hz * sensor.line_rate_hz))
            starts = traj.times_s[0] + np.arange(nl) * sensor.frame_period_s
        else:
            starts = traj.times_s[:1].copy()
    else:
        t0, t1 = traj.times_s[0], traj.times_s[-1]
        starts = t0 + np.arange(0.0, t1 - t0, sensor.frame_period_s)
        starts = starts[::frame_stride]
    rng = np.random.default_rng(seed)
    interp = pose.rotation_position if hasattr(pose, "rotation_position") else _Interp(traj)
    out_p, out_t, out_r, out_a = [], [], [], {}
    # group frames into chunks of about chunk_rays rays
    d1, _, _ = sensor.rays(starts[:1])
    per_frame = max(1, d1.shape[0])
    fpc = max(1, chunk_rays // per_frame)
    for c0 in range(0, len(starts), fpc):
        D_s, t, A = sensor.rays(starts[c0:c0 + fpc])
        R, o = interp(t)
        D_w = np.einsum("nij,nj->ni", R, D_s)
        D_w /= np.linalg.norm(D_w, axis=1, keepdims=True)
        r_true = world.cast(o, D_w, sensor.max_range_m)
        noise = rng.normal(0.0, 1.0, r_true.shape[0]) * sensor.range_noise_sigma_m
        r = r_true + noise
        ok = np.isfinite(r_true) & (r >= sensor.min_range_m) & (r <= sensor.max_range_m)
        out_p.append(D_s[ok] * r[ok, None])
        out_t.append(t[ok])
        out_r.append(r[ok])
        for k, v in A.items():
            out_a.setdefault(k, []).append(v[ok])
    attrs = {"time_s": np.concatenate(out_t), "range_m": np.concatenate(out_r)}
    for k, v in out_a.items():
        attrs[k] = np.concatenate(v)
    return PointCloud(points=np.concatenate(out_p) if out_p else np.zeros((0, 3)), attributes=attrs,
                      frame="sensor")


def deskew(cloud: PointCloud, trajectory: Trajectory, T_target_world=None) -> PointCloud:
    """Assemble per-timestamp sensor-frame points into one frame using the trajectory.

    ``p_world = R(t_i) p_i + o(t_i)`` with the pose of ``trajectory`` (``T_world_sensor``)
    interpolated at each point's ``time_s``; optionally mapped on by ``T_target_world``
    (e.g. ``invert(T_world_scan)`` for the scan frame).
    """
    if "time_s" not in cloud.attributes:
        raise InputError("cloud has no per-point 'time_s' attribute; cannot deskew")
    interp = _Interp(trajectory)
    t = cloud.attributes["time_s"]
    P = np.empty_like(cloud.points)
    for c0 in range(0, len(t), 1_000_000):  # bounded memory for maps of 1e7 points
        R, o = interp(t[c0:c0 + 1_000_000])
        P[c0:c0 + 1_000_000] = np.einsum("nij,nj->ni", R, cloud.points[c0:c0 + 1_000_000]) + o
    frame = trajectory.frame
    if T_target_world is not None:
        T = as_transform(T_target_world, "T_target_world")
        P = P @ T[:3, :3].T + T[:3, 3]
        frame = "target"
    return PointCloud(points=P, attributes=dict(cloud.attributes), frame=frame)


@dataclass
class Scan2D:
    """One rotation of a :class:`Horizontal2D` scanner as range-bearing observations.

    ``ranges_m`` has one entry per beam (NaN where nothing returned within range);
    ``bearings_rad`` counter-clockwise from the sensor +x axis; ``T_world_sensor`` the truth.
    """

    bearings_rad: np.ndarray
    ranges_m: np.ndarray
    T_world_sensor: np.ndarray
    sensor: Horizontal2D
    time_s: np.ndarray

    def points(self) -> np.ndarray:
        """(k, 2) x, y in the sensor frame of the valid returns."""
        ok = np.isfinite(self.ranges_m)
        return np.column_stack([np.cos(self.bearings_rad[ok]), np.sin(self.bearings_rad[ok])]) * self.ranges_m[ok, None]


def simulate_scan_2d(world, sensor: Horizontal2D, T_world_sensor, seed: int = 0) -> Scan2D:
    """One static rotation of a horizontal 2D scanner: ranges (NaN = no return) and bearings."""
    if not isinstance(sensor, Horizontal2D):
        raise InputError("simulate_scan_2d needs a Horizontal2D sensor")
    _check_sensor(sensor)
    T = as_transform(T_world_sensor, "T_world_sensor")
    b = sensor.bearings_rad()
    D_s = np.column_stack([np.cos(b), np.sin(b), np.zeros(b.size)])
    D_w = D_s @ T[:3, :3].T
    o = np.broadcast_to(T[:3, 3], D_w.shape).copy()
    r_true = world.cast(o, D_w, sensor.max_range_m)
    rng = np.random.default_rng(seed)
    r = r_true + rng.normal(0.0, 1.0, b.size) * sensor.range_noise_sigma_m
    r[~np.isfinite(r_true) | (r < sensor.min_range_m) | (r > sensor.max_range_m)] = np.nan
    dt = np.arange(b.size) * (sensor.frame_period_s * sensor.fov_deg / 360.0 / b.size)
    return Scan2D(bearings_rad=b, ranges_m=r, T_world_sensor=T, sensor=sensor, time_s=dt)
