"""Carrier presets of the sensor streams and their speed profile (:mod:`minegeo.synth.stream`,
:mod:`minegeo.synth.stream_paper`): how a vehicle, a walker or a drone moves, and the time line
constants shared by the drift-network and the paper-world streams."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StreamPreset", "PRESETS", "STILL_S", "LEAD_S", "KNOT_DT_S", "carrier_sway"]

#: the carrier stands still for this long at the start (s)
STILL_S = 1.0
#: the first sweep starts this long after the IMU's first sample; the IMU runs this long past the last sweep (s)
LEAD_S = 0.5
#: spacing of the curve's control points (s)
KNOT_DT_S = 0.01


@dataclass(frozen=True)
class StreamPreset:
    """How a carrier moves (m, s, deg, Hz).

    Attributes
    ----------
    speed_mps, accel_mps2, lat_accel_mps2 : float
        Cruise speed, along-path and lateral acceleration limits of the path's speed profile.
    height_m : float or None
        Sensor height above the floor (None: half the lowest roof).
    corner_m : float
        Corner cut at junctions (capped at half the narrowest drift width).
    path_smooth_s : float
        Gaussian smoothing (s) of the planned path and heading.
    bob_m, bob_hz : float
        Vertical step bounce (amplitude, frequency; a sinusoid while moving).
    lateral_m : float
        Lateral sway amplitude at half the bob frequency (walking), or seeded smooth drift.
    yaw_sway_deg, tilt_deg : float
        Peak seeded yaw sway and roll / pitch sway.
    tilt_hz : tuple of float
        Frequency range (Hz) of the roll / pitch sway.
    tilt_from_accel : bool
        Multirotor attitude: pitch and roll from the horizontal acceleration.
    vertical_m : float
        Peak seeded smooth height oscillation.
    yaw_rate_dps : float
        Turn rate of the 180-degree turn at dead ends.
    """

    speed_mps: float
    accel_mps2: float
    lat_accel_mps2: float
    height_m: float | None
    corner_m: float
    path_smooth_s: float
    bob_m: float
    bob_hz: float
    lateral_m: float
    yaw_sway_deg: float
    tilt_deg: float
    tilt_hz: tuple
    tilt_from_accel: bool
    vertical_m: float
    yaw_rate_dps: float


PRESETS: dict[str, StreamPreset] = {
    "vehicle": StreamPreset(3.0, 0.8, 1.0, 1.8, 1.6, 0.3, 0.01, 2.5, 0.0, 0.5, 0.5, (0.5, 2.0), False, 0.0, 30.0),
    "handheld": StreamPreset(1.2, 0.6, 0.8, 1.4, 1.5, 0.2, 0.03, 1.8, 0.03, 5.0, 4.0, (0.4, 1.2), False, 0.0,
                             60.0),
    "drone": StreamPreset(4.0, 2.0, 2.0, None, 1.5, 0.2, 0.0, 0.0, 0.1, 5.0, 2.0, (0.2, 0.8), True, 0.15, 60.0),
}


def _speed_profile(C: np.ndarray, pre: StreamPreset) -> np.ndarray:
    """Times (s) at the vertices of a dense 2-D path: 0 at both ends, the speed limited by the cruise
    speed, the lateral acceleration (``v <= sqrt(a_lat / kappa)``) and the turn rate
    (``v <= yaw_rate / kappa``), reached within ``accel_mps2`` (forward and backward passes).
    ``kappa`` is the heading change per metre, its peak spread over +-0.5 m so a sharp corner is
    entered slowly."""
    from scipy.ndimage import maximum_filter1d

    from minegeo.synth.flight import _path_curvature, _vertex_times

    ds, kappa = _path_curvature(C)
    step = max(float(np.median(ds)) if len(ds) else 0.05, 1e-3)
    kappa = maximum_filter1d(kappa, size=2 * int(np.ceil(0.5 / step)) + 1)
    k = np.maximum(kappa, 1e-9)
    v = np.minimum(pre.speed_mps, np.minimum(np.sqrt(pre.lat_accel_mps2 / k), np.radians(pre.yaw_rate_dps) / k))
    return _vertex_times(v, ds, pre.accel_mps2, 1e-3)



def carrier_sway(pre: StreamPreset, t: np.ndarray, xy: np.ndarray, yaw: np.ndarray, moving: np.ndarray,
                 lateral_cap_m: float, rng: np.random.Generator, env=1.0, pitch0=None):
    """The preset's own motion about its path: ``(xy, yaw, pitch, roll, bob, vertical)``.

    ``xy`` moved sideways by the lateral sway (amplitude ``min(lateral_m, lateral_cap_m)``), ``yaw``
    plus the yaw sway; ``pitch`` the tilt draw plus ``pitch0`` when given (the path's own pitch, e.g. a
    ramp's grade), ``roll`` the tilt draw; with ``tilt_from_accel`` (a multirotor) both tilted by
    the path's horizontal acceleration, ``atan(a / g)``; ``bob`` the gait's vertical bounce and
    ``vertical`` the height noise (m). Gait and sway scale with ``moving`` (speed / cruise speed, 0-1);
    every draw is multiplied by ``env`` (1 away from a station stop, 0 on it). Draws from ``rng`` in
    a fixed order: phases, lateral sway, yaw sway, pitch, roll, height.
    """
    from minegeo.synth.imu import GRAVITY_MPS2
    from minegeo.synth.motion import gaussian_smooth
    from minegeo.synth.trajectory import _smooth_noise

    dt = KNOT_DT_S  # t is the curve's knot grid
    ph = rng.uniform(0, 2 * np.pi, 3)
    bob = env * pre.bob_m * moving * np.sin(2 * np.pi * pre.bob_hz * t + ph[0])
    lat_amp = min(pre.lateral_m, lateral_cap_m)
    if pre.bob_hz > 0:
        lat = lat_amp * moving * np.sin(np.pi * pre.bob_hz * t + ph[1])
    else:
        lat = _smooth_noise(rng, t, lat_amp, 0.02, 0.1)
    lat = env * lat
    yaw = yaw + np.radians(env * _smooth_noise(rng, t, pre.yaw_sway_deg, 0.05, 0.3))
    xy = xy + lat[:, None] * np.column_stack([-np.sin(yaw), np.cos(yaw)])
    pitch = np.radians(env * _smooth_noise(rng, t, pre.tilt_deg, *pre.tilt_hz))
    pitch = pitch if pitch0 is None else pitch0 + pitch
    roll = np.radians(env * _smooth_noise(rng, t, pre.tilt_deg, *pre.tilt_hz))
    if pre.tilt_from_accel:
        acc = gaussian_smooth(np.gradient(np.gradient(xy, dt, axis=0), dt, axis=0), 0.25 / dt)
        a_f = acc[:, 0] * np.cos(yaw) + acc[:, 1] * np.sin(yaw)
        a_l = -acc[:, 0] * np.sin(yaw) + acc[:, 1] * np.cos(yaw)
        pitch = pitch + np.arctan(a_f / GRAVITY_MPS2)
        roll = roll - np.arctan(a_l / GRAVITY_MPS2)
    vertical = env * _smooth_noise(rng, t, pre.vertical_m, 0.02, 0.1)
    return xy, yaw, pitch, roll, bob, vertical
