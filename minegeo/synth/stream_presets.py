"""Carrier presets of the sensor streams and their speed profile (:mod:`minegeo.synth.stream`,
:mod:`minegeo.synth.stream_paper`): how a vehicle, a walker or a drone moves, and the time line
constants shared by the drift-network and the paper-world streams."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StreamPreset", "PRESETS", "STILL_S", "LEAD_S", "KNOT_DT_S"]

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

