"""A handheld-like walk with fast roll/pitch sway through narrow drifts: motion-distorted 10 Hz sweeps.

A stress sequence for "poses stay on the manifold": thousands of frames whose relative
rotations are large and change direction every half second, so the odometry chains, inverts and
refines many relative poses. Deterministic from ``seed``.

1. World: :func:`sway_network`, a rectangular loop of narrow drifts (``width_m`` 3.2 m wide,
   ``height_m`` 3.0 m high) with one crosscut, rough rock (``roughness_m``), cast exactly by
   :class:`~minegeo.synth.flight.NetworkWorld`.
2. Route: :func:`~minegeo.synth.flight.plan_route` over the loop (it passes the junctions from
   several directions: loop closures), corners cut by arcs, a walking speed limited in curves
   (:func:`minegeo.synth.flight._nominal`).
3. Attitude: yaw = path heading + a seeded sway; roll and pitch are each a sinusoid of seeded
   frequency in ``[sway_hz_min, sway_hz_max]`` (Hz) and amplitude in ``[sway_deg_min,
   sway_deg_max]`` (deg) plus a slower wobble, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; a vertical step
   bob of 3 cm at 1.8 Hz. Poses on a 200 Hz clock (``T_world_sensor``: sensor x forward, y left, z up).
4. Frames: one VLP-16 rotation per frame at 10 Hz, each beam fired from the pose at its own time
   (:func:`~minegeo.synth.sensors.simulate_scan` on the clock trajectory, ``frame_times_s``): the
   sweeps are motion-distorted, every point in the sensor frame of its own firing time. A frame's
   time is the middle of its sweep; the truth is the pose at that time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from minegeo.errors import InputError
from minegeo.io.types import Trajectory

__all__ = ["SwayWalkParams", "sway_network", "sway_walk"]

log = logging.getLogger(__name__)

#: clock of the simulated motion (Hz): the beams' poses are interpolated on it
CLOCK_HZ = 200.0


@dataclass(frozen=True)
class SwayWalkParams:
    """Parameters of :func:`sway_walk` (m, s, deg, Hz).

    Attributes
    ----------
    n_frames : int
        Frames to simulate (10 Hz: ``n_frames / 10`` s of walking).
    speed_mps : float
        Walking speed on straight drift (slower in curves).
    sway_deg_min, sway_deg_max, sway_hz_min, sway_hz_max : float
        Amplitude and frequency ranges of the roll and pitch sway (each drawn once per axis).
    yaw_sway_deg : float
        Amplitude of the yaw sway about the path heading (0.7 Hz).
    azimuth_step_deg : float
        VLP-16 azimuth step (1 deg: 5760 beams per sweep).
    range_noise_m : float
        Range noise sigma.
    rate_hz : float
        Sweeps per second (one rotation per sweep).
    seed : int
    """

    n_frames: int = 2172
    speed_mps: float = 1.2
    sway_deg_min: float = 15.0
    sway_deg_max: float = 25.0
    sway_hz_min: float = 0.5
    sway_hz_max: float = 1.5
    yaw_sway_deg: float = 10.0
    azimuth_step_deg: float = 1.0
    range_noise_m: float = 0.02
    rate_hz: float = 10.0
    seed: int = 0

    def __post_init__(self):
        vals = (self.speed_mps, self.sway_deg_max, self.sway_hz_min, self.sway_hz_max, self.azimuth_step_deg,
                self.rate_hz)
        if not (isinstance(self.n_frames, int) and self.n_frames >= 2) or not all(np.isfinite(v) and v > 0
                                                                                  for v in vals):
            raise InputError(f"sway walk: n_frames >= 2 and positive finite speed, sway, step and rate needed, "
                             f"got {self}")
        if not (0 <= self.sway_deg_min <= self.sway_deg_max and self.sway_hz_min <= self.sway_hz_max):
            raise InputError("sway walk: need sway_deg_min <= sway_deg_max and sway_hz_min <= sway_hz_max")


def sway_network(width_m: float = 3.2, height_m: float = 3.0, roughness_m: float = 0.05, seed: int = 0):
    """Narrow-drift loop: a 60 m x 40 m rectangle of drifts with a crosscut at x = 25 m (a
    :class:`~minegeo.synth.network.DriftNetwork`, floor z = 0, roof ``height_m``)."""
    from minegeo.synth.network import DriftNetwork

    nodes = np.array([(0.0, 0.0), (25.0, 0.0), (60.0, 0.0), (60.0, 40.0), (25.0, 40.0), (0.0, 40.0)])
    edges = np.array([(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4)], np.int64)
    return DriftNetwork(nodes, edges, np.full(len(edges), float(width_m)), np.full(len(nodes), float(height_m)),
                        ("",) * len(nodes), {"kind": "sway_network", "width_m": width_m, "height_m": height_m},
                        roughness_m=float(roughness_m), roughness_seed=int(seed))


def _sway_clock(net, p: SwayWalkParams) -> Trajectory:
    """The walk's ``T_world_sensor`` on the :data:`CLOCK_HZ` clock, long enough for ``p.n_frames`` sweeps."""
    from minegeo.synth.flight import FlightParams, _nominal, plan_route
    from minegeo.synth.motion import rot_zyx

    duration = (p.n_frames + 1) / p.rate_hz
    fp = FlightParams(length_m=1.3 * duration * p.speed_mps + 50.0, speed_mps=p.speed_mps, accel_mps2=0.8,
                      lat_accel_mps2=0.8, corner_m=1.5, seed=p.seed)
    route = plan_route(net, fp.length_m, p.seed, start=0)
    t_n, xy_n, yaw_n = _nominal(net, route, fp)
    if t_n[-1] < duration:
        raise InputError(f"sway walk: the route lasts {t_n[-1]:.0f} s, {duration:.0f} s are needed")
    t = np.arange(0.0, duration + 1.0 / CLOCK_HZ, 1.0 / CLOCK_HZ)
    rng = np.random.default_rng([p.seed, 27])
    xy = np.column_stack([np.interp(t, t_n, xy_n[:, 0]), np.interp(t, t_n, xy_n[:, 1])])

    def sway(amp_deg: float, f_lo: float, f_hi: float) -> np.ndarray:
        a, f, ph = rng.uniform(p.sway_deg_min, p.sway_deg_max), rng.uniform(f_lo, f_hi), rng.uniform(0, 2 * np.pi)
        a = amp_deg if amp_deg else a
        wobble = 0.2 * np.sin(2 * np.pi * rng.uniform(0.05, 0.15) * t + rng.uniform(0, 2 * np.pi))
        return np.radians(a * ((1.0 - 0.2) * np.sin(2 * np.pi * f * t + ph) + wobble))

    roll = sway(0.0, p.sway_hz_min, p.sway_hz_max)
    pitch = sway(0.0, p.sway_hz_min, p.sway_hz_max)
    yaw = np.interp(t, t_n, yaw_n) + sway(p.yaw_sway_deg, 0.7, 0.7)
    z = 1.4 + 0.03 * np.sin(2 * np.pi * 1.8 * t)
    poses = np.tile(np.eye(4), (t.size, 1, 1))
    poses[:, :3, :3] = rot_zyx(yaw, pitch, roll)
    poses[:, :3, 3] = np.column_stack([xy, z])
    return Trajectory(times_s=t, poses=poses, frame="world", body="sensor")


def sway_walk(params: SwayWalkParams | None = None, net=None, *, chunk: int = 100):
    """Simulate the sway walk (see the module docstring).

    Parameters
    ----------
    params : SwayWalkParams, optional
    net : DriftNetwork, optional
        Default :func:`sway_network` (seeded with ``params.seed``).
    chunk : int
        Sweeps simulated per batch.

    Returns
    -------
    truth : Trajectory
        ``T_world_sensor`` at the frame times (middle of each sweep), ``frame="world"``.
    frames : list of (n_i, 3) float64 arrays
        Each sweep's points, each in the sensor frame of its own firing time (motion-distorted).
    clock : Trajectory
        The motion on the 200 Hz clock (for checks of the distortion).

    Raises
    ------
    InputError
        Parameters out of range, or a route too short for ``n_frames``.
    """
    from minegeo.synth.flight import NetworkWorld
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses

    p = params or SwayWalkParams()
    net = sway_network(seed=p.seed) if net is None else net
    clock = _sway_clock(net, p)
    world = NetworkWorld(net)
    sensor = Velodyne16(azimuth_step_deg=p.azimuth_step_deg, range_noise_sigma_m=p.range_noise_m,
                        rotation_rate_hz=p.rate_hz, max_range_m=100.0)
    period = 1.0 / p.rate_hz
    starts = np.arange(p.n_frames) * period + 0.5 * period / 2.0  # the clock starts before the first sweep
    mids = starts + 0.5 * period
    frames: list[np.ndarray] = []
    for c0 in range(0, p.n_frames, chunk):
        s = starts[c0:c0 + chunk]
        cloud = simulate_scan(world, sensor, clock, seed=p.seed * 100003 + c0, frame_times_s=s)
        tt = cloud.attributes["time_s"]
        cut = np.searchsorted(tt, np.r_[s[1:], np.inf], side="left")
        lo = 0
        for hi in cut:
            frames.append(np.ascontiguousarray(cloud.points[lo:hi]))
            lo = hi
        log.info("sway walk: %d / %d sweeps", len(frames), p.n_frames)
    truth = Trajectory(times_s=mids, poses=interpolate_poses(clock, mids), frame="world", body="sensor")
    return truth, frames, clock
