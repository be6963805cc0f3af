"""Sensor streams as a scanner records them: motion-distorted LiDAR sweeps with per-point times and an IMU.

One continuous pose curve (:class:`~minegeo.synth.motion.MotionCurve`) drives both sensors:

* **LiDAR**: a VLP-16-like spinning sensor at ``lidar_hz`` (10-20 Hz), every sweep kept. Each beam
  is cast from the curve's pose at its own firing time (:func:`~minegeo.synth.sensors.simulate_scan`
  on the curve), so a sweep taken while moving is distorted as a real one is. A point is written in
  the sensor frame **at its own firing time** with ``time`` = seconds after the frame time; the
  frame time is the **start of the sweep** (slam_contract.md, "Sensor streams").
* **IMU**: :func:`~minegeo.synth.imu.simulate_imu` at ``imu.rate_hz`` (100-400 Hz) from the same
  curve, axes of the LiDAR frame (no lever arm, no extrinsic), white noise + bias random walk.

Presets (:data:`PRESETS`): ``vehicle`` (3 m/s, smooth yaw from the path, small road bumps),
``handheld`` (1.2 m/s walk: 3 cm step bounce at 1.8 Hz, sway of a few degrees; the narrow loop of
:func:`~minegeo.synth.sequence_sway.sway_network`), ``drone`` (4 m/s cruise in the drifts, full 3-D
attitude: pitch and roll of a multirotor from its acceleration, ``atan(a_fwd / g)`` and
``-atan(a_left / g)``, plus seeded tilt noise; hover turns at dead ends). Networks
(:func:`stream_network`): ``loop`` (3.2 m wide, 3.0 m high), ``junctions`` (the issue-18 network at
3.5 m) or an edge list CSV (the NIOSH layout, :func:`~minegeo.synth.network.niosh_network`, 2.9 m x
2.6 m unless a width is given); rough rock of 5 cm RMS. ``paper-ring``, ``paper-straight`` and
``paper-ramp`` drive a fixed path of the paper world (``build_world("paper", 1)``; its rock and
structures; :mod:`minegeo.synth.stream_paper`).

Survey stations (``StreamParams.station_spacing_m``; ``minegeo synth --station-spacing-m``): every
``station_spacing_m`` of path the carrier decelerates to rest within its preset's limits, stands
``station_still_s`` (3 s) exactly still (pose constant, IMU reading gravity + bias + noise only),
and drives on (:func:`stream_motion_stops`). :func:`stream_stations` places the network in the CRS
(``T_crs_world``) and gives each stop's surveyed point (sensor origin + ``station_offset_m``), every
``control_every``-th a control station, the others check stations; ``stations.csv`` (the contract's
layout, survey noise added) and ``stations_truth.csv`` are written beside the stream.

Time line: the curve starts at 0 s at rest; the carrier starts moving at ``STILL_S`` = 1 s; the
first sweep starts at ``LEAD_S`` = 0.5 s; the IMU spans ``[0, last sweep end + LEAD_S]``.

Determinism: ``np.random.SeedSequence(seed).spawn(5)`` gives the streams ``motion`` (route
tie-breaks, sway and tilt draws), ``lidar`` (range noise), ``imu_noise``, ``imu_bias`` and
``stations`` (CRS placement, survey noise); every
array is float64. Same seed, same bytes.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from minegeo.errors import InputError, InternalError
from minegeo.synth.imu import GRAVITY_MPS2, ImuParams, imu_csv_text, imu_truth_csv_text, simulate_imu
from minegeo.synth.motion import MotionCurve, curve_from_samples, gaussian_smooth
from minegeo.synth.stream_presets import (
    KNOT_DT_S,
    LEAD_S,
    PRESETS,
    STILL_S,
    StreamPreset,
    _speed_profile,
    carrier_sway,
)

__all__ = ["StreamPreset", "PRESETS", "StreamParams", "Stream", "stream_network", "stream_motion",
           "simulate_stream", "iter_sweeps", "write_stream", "STILL_S", "LEAD_S", "stream_motion_stops",
           "stream_stations", "STATION_SIGMA_H_M", "STATION_SIGMA_V_M"]

log = logging.getLogger(__name__)

#: a station stop closer than this to a dead end (where the carrier turns) is skipped (m)
_STOP_END_GAP_M = 3.0
#: a-priori standard deviations (m) of the surveyed stations: E and N each, and H
STATION_SIGMA_H_M = 0.005
STATION_SIGMA_V_M = 0.008


@dataclass(frozen=True)
class StreamParams:
    """A sensor stream (see the module docstring).

    Attributes
    ----------
    preset : str
        ``vehicle``, ``handheld`` or ``drone`` (:data:`PRESETS`).
    duration_s : float
        Time covered by the sweeps (s); ``floor(duration_s * lidar_hz)`` sweeps.
    lidar_hz : float
        Sweeps per second (one rotation each), 10-20.
    azimuth_step_deg : float
        Azimuth step of a rotation (0.2 deg at 10 Hz, 0.4 deg at 20 Hz for a VLP-16).
    range_noise_m : float
        Range noise sigma (m).
    imu : ImuParams
    network : str
        ``loop``, ``junctions``, the path of an edge list CSV (NIOSH layout) or a paper-world path
        ``paper-ring``, ``paper-straight``, ``paper-ramp`` (:mod:`minegeo.synth.stream_paper`; no
        stations, no ``width_m``, ``roughness_m`` unused).
    width_m : float or None
        Drift width (None: the network's own).
    roughness_m : float
        RMS rock roughness (m).
    seed : int
    station_spacing_m : float or None
        Stop-and-go stations every this much path (m); None: no stops.
    control_every : int
        Every ``control_every``-th station (the first included) is a ``control`` station, the
        others ``check`` (100 m spacing, 5: control every 500 m).
    station_still_s : float
        Time the carrier stands still on a station (s).
    station_offset_m : tuple of 3 float
        The surveyed point in the sensor frame (x y z, m), as ``--station-offset``.
    crs : str
        Projected CRS of the stations (the network is placed in it by ``T_crs_world``).
    """

    preset: str = "vehicle"
    duration_s: float = 5.0
    lidar_hz: float = 10.0
    azimuth_step_deg: float = 0.2
    range_noise_m: float = 0.02
    imu: ImuParams = field(default_factory=ImuParams)
    network: str = "loop"
    width_m: float | None = None
    roughness_m: float = 0.05
    seed: int = 0
    station_spacing_m: float | None = None
    control_every: int = 5
    station_still_s: float = 3.0
    station_offset_m: tuple = (0.0, 0.0, 0.0)
    crs: str = "EPSG:5186"

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise InputError(f"unknown stream preset {self.preset!r}; one of {', '.join(PRESETS)}")
        for k in ("duration_s", "lidar_hz", "azimuth_step_deg"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"stream {k} must be > 0, got {v}")
        if not (np.isfinite(self.range_noise_m) and self.range_noise_m >= 0 and np.isfinite(self.roughness_m)
                and self.roughness_m >= 0):
            raise InputError("stream range_noise_m and roughness_m must be >= 0")
        if self.width_m is not None and not (np.isfinite(self.width_m) and self.width_m > 0):
            raise InputError(f"stream width_m must be > 0, got {self.width_m}")
        if self.station_spacing_m is not None and not (np.isfinite(self.station_spacing_m)
                                                       and self.station_spacing_m >= 2 * _STOP_END_GAP_M):
            raise InputError(f"station spacing must be >= {2 * _STOP_END_GAP_M:g} m, got {self.station_spacing_m}")
        if int(self.control_every) < 1 or not (np.isfinite(self.station_still_s) and self.station_still_s > 0):
            raise InputError("control_every must be >= 1 and station_still_s > 0")
        off = np.asarray(self.station_offset_m, dtype=np.float64)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise InputError(f"station_offset_m must be three finite numbers, got {self.station_offset_m!r}")
        object.__setattr__(self, "station_offset_m", tuple(float(v) for v in off))
        if str(self.network).startswith("paper-"):             # minegeo.synth.stream_paper
            from minegeo.synth.stream_paper import PAPER_NETWORKS

            if self.network not in PAPER_NETWORKS:
                raise InputError(f"unknown paper-world stream network {self.network!r}; one of "
                                 f"{', '.join(PAPER_NETWORKS)}")
            if self.station_spacing_m is not None or self.width_m is not None:
                raise InputError(f"{self.network}: survey stations and another drift width are not simulated in "
                                 "the paper world (drop --station-spacing-m / --drift-width-m)")


def stream_network(name: str, width_m: float | None = None, roughness_m: float = 0.05, seed: int = 0):
    """The drift network of a stream: ``loop``, ``junctions`` or an edge list CSV (NIOSH layout); a
    ``paper-...`` name gives the paper world and its path (:func:`~minegeo.synth.stream_paper.paper_network`;
    ``width_m`` and ``roughness_m`` unused)."""
    from minegeo.synth.stream_paper import is_paper_network, paper_network

    if is_paper_network(name):
        return paper_network(name)
    from minegeo.synth.network import intersections_network, niosh_network, with_roughness
    from minegeo.synth.sequence_sway import sway_network

    if name == "loop":
        net = sway_network(width_m=width_m or 3.2, height_m=3.0, roughness_m=0.0)
    elif name == "junctions":
        net = intersections_network(width_m=width_m or 3.5, heights_m=(3.0, 3.3, 3.6), default_height_m=3.3)
    else:
        net = niosh_network(name, width_m=width_m or 2.9)
    return with_roughness(net, roughness_m, seed) if roughness_m > 0 else net


def _route_samples(net, pre: StreamPreset, length_m: float, seed: int, t: np.ndarray, stops=None):
    """Planned path (k, 2), unwrapped heading (k,) and speed (k,) at times ``t``, smoothed, and the
    planned stops ``(arrival_s, departure_s)`` (empty without ``stops``).

    The route is :func:`~minegeo.synth.flight.plan_route`; corners are cut by
    :func:`~minegeo.synth.flight._cut_corners`; at a dead end the carrier stops and turns on the spot
    (smoothstep in yaw at ``yaw_rate_dps`` on average). Motion starts at :data:`STILL_S`.
    ``stops = (spacing_m, dwell_s)``: every ``spacing_m`` of path (measured from the start, a stop
    closer than :data:`_STOP_END_GAP_M` to a dead end skipped) the carrier decelerates to rest
    within ``accel_mps2``, stands ``dwell_s`` with path and heading held, then accelerates again.
    """
    from minegeo.synth.flight import _cut_corners, _legs, plan_route

    rng = np.random.default_rng(seed)
    corner = min(pre.corner_m, 0.5 * float(net.widths.min()))
    T, X, Y = [], [], []
    planned: list[tuple[float, float]] = []
    t0, yaw_prev, s_done = STILL_S, None, 0.0
    for leg in _legs(net, plan_route(net, length_m, seed)):
        C = _cut_corners(leg, corner)
        d = np.gradient(C, axis=0)
        yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        cuts: list[int] = []
        if stops is not None:                               # split the leg at the station vertices
            S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])
            k = np.arange(np.floor(s_done / stops[0]) + 1, np.floor((s_done + S[-1]) / stops[0]) + 1)
            for tgt in k * stops[0] - s_done:
                j = int(np.searchsorted(S, tgt))
                if _STOP_END_GAP_M <= S[min(j, len(S) - 1)] <= S[-1] - _STOP_END_GAP_M and (not cuts or j > cuts[-1]):
                    cuts.append(j)
            s_done += float(S[-1])
        bounds = [0, *cuts, len(C) - 1]
        parts = [np.zeros(1)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):   # each piece starts and ends at rest
            parts.append(_speed_profile(C[a:b + 1], pre)[1:] + parts[-1][-1] + (stops[1] if a > 0 else 0.0))
        ts = np.concatenate(parts) + t0                      # the dwell: time advances, the vertex stays
        if yaw_prev is not None:                            # turn on the spot at the dead end
            yaw += 2 * np.pi * np.round((yaw_prev + (1.0 if rng.random() < 0.5 else -1.0) * np.pi - yaw[0])
                                        / (2 * np.pi))
            dur = abs(yaw[0] - yaw_prev) / np.radians(pre.yaw_rate_dps)
            u = np.linspace(0.0, 1.0, 41)[1:-1]
            T.append(t0 + u * dur)
            X.append(np.repeat(C[:1], len(u), 0))
            Y.append(yaw_prev + (yaw[0] - yaw_prev) * (3 * u**2 - 2 * u**3))
            ts = ts + dur
        if cuts:                                             # a second sample at each stop: the departure
            dep = ts[cuts] + stops[1]
            planned += [(float(ts[j]), float(ts[j] + stops[1])) for j in cuts]
            o = np.argsort(np.concatenate([ts, dep]), kind="stable")
            ts, C, yaw = np.concatenate([ts, dep])[o], np.concatenate([C, C[cuts]])[o], \
                np.concatenate([yaw, yaw[cuts]])[o]
        T.append(ts)
        X.append(C)
        Y.append(yaw)
        t0, yaw_prev = ts[-1], yaw[-1]
    t_n, xy_n, yaw_n = np.concatenate(T), np.concatenate(X), np.concatenate(Y)
    keep = np.concatenate([[True], np.diff(t_n) > 1e-9])
    t_n, xy_n, yaw_n = t_n[keep], xy_n[keep], yaw_n[keep]
    if t_n[-1] < t[-1]:
        raise InputError(f"the planned route lasts {t_n[-1]:.0f} s, {t[-1]:.0f} s are needed")
    base = np.column_stack([np.interp(t, t_n, xy_n[:, 0]), np.interp(t, t_n, xy_n[:, 1]), np.interp(t, t_n, yaw_n)])
    base = gaussian_smooth(base, pre.path_smooth_s / KNOT_DT_S)
    speed = np.linalg.norm(np.gradient(base[:, :2], KNOT_DT_S, axis=0), axis=1)
    return base[:, :2], base[:, 2], speed, planned


def stream_motion(net, preset: str | StreamPreset, duration_s: float, rng: np.random.Generator) -> MotionCurve:
    """The carrier's pose curve over ``[0, duration_s]`` in ``net`` (see :class:`StreamPreset`).

    Parameters
    ----------
    net : DriftNetwork
    preset : str or StreamPreset
    duration_s : float
        Time span the curve must cover (s).
    rng : numpy.random.Generator
        The ``motion`` stream (route tie-breaks, sway and tilt draws).

    Raises
    ------
    InputError
        A route too short, or a motion that leaves the drifts (too narrow for the preset).
    """
    return stream_motion_stops(net, preset, duration_s, rng)[0]


def _stop_margin_s(pre: StreamPreset) -> float:
    """Time (s) between a planned arrival and the start of the exactly still span: the support of the
    Gaussian smoothings (+-4 sigma: path, multirotor acceleration, height) plus the cubic B-spline's
    support (3 knots) and 2 knots of finite differences."""
    acc = 4 * 0.25 + 2 * KNOT_DT_S if pre.tilt_from_accel else 0.0
    return 4 * pre.path_smooth_s + acc + 4 * 0.05 + 5 * KNOT_DT_S


def stream_motion_stops(net, preset: str | StreamPreset, duration_s: float, rng: np.random.Generator,
                        stops=None) -> tuple[MotionCurve, np.ndarray]:
    """:func:`stream_motion` with station stops: the curve and the still spans (k, 2) (s).

    ``stops = (spacing_m, still_s)``: every ``spacing_m`` of path the carrier decelerates within its
    preset's ``accel_mps2`` (and ``lat_accel_mps2`` in curves), stands, and accelerates again; the
    sway, bounce, tilt and height draws fade out over 1 s (smoothstep) before the stop and in after
    it, so on each returned span ``[t_start, t_end]`` (``t_end - t_start = still_s``) the pose is
    exactly constant (the curve's control points over the span are equal, checked) and velocity,
    acceleration and angular rate are exactly zero. Without ``stops`` the result is
    :func:`stream_motion`'s and the spans are empty.
    """
    from minegeo.synth.flight import flight_clearance
    from minegeo.synth.network import _roof

    pre = PRESETS[preset] if isinstance(preset, str) else preset
    dt = KNOT_DT_S
    # samples over [-dt, duration_s + 2 s]: the smoothing's end padding stays 2 s past the span used
    t = (np.arange(int(np.ceil((duration_s + 2.0) / dt)) + 4) - 1) * dt
    route_seed = int(rng.integers(0, 2**31 - 1))
    margin = _stop_margin_s(pre)
    plan = None if stops is None else (float(stops[0]), float(stops[1]) + 2.0 * margin)
    xy, yaw, speed, planned = _route_samples(net, pre, 1.3 * duration_s * pre.speed_mps + 50.0, route_seed, t, plan)
    moving = np.clip(speed / max(pre.speed_mps, 1e-9), 0.0, 1.0)      # gait and sway scale with speed
    env = _still_envelope(t, planned)                                  # 0 while stopped, 1 away from stops
    xy, yaw, pitch, roll, bob, vertical = carrier_sway(pre, t, xy, yaw, moving, 0.05 * float(net.widths.min()),
                                                       rng, env)
    h0 = 0.5 * float(net.node_heights.min()) if pre.height_m is None else float(pre.height_m)
    z = h0 + bob + vertical
    z = np.minimum(z, _roof(net, xy) - 0.5)
    z = gaussian_smooth(z, 0.05 / dt)
    curve = curve_from_samples(t[0], dt, np.column_stack([xy, z]), np.column_stack([yaw, pitch, roll]))
    tc = np.arange(curve.t_start, curve.t_end, 0.05)
    clear = flight_clearance(net, curve.rotation_position(tc)[1])
    if clear.min() < 0.2:
        raise InputError(f"the {preset if isinstance(preset, str) else 'given'} motion comes within "
                         f"{clear.min():.2f} m of the rock at t = {tc[np.argmin(clear)]:.1f} s: the drifts are too "
                         "narrow or low for it (give a wider drift)")
    spans = np.array([(a + margin, b - margin) for a, b in planned], dtype=np.float64).reshape(-1, 2)
    for a, b in spans:                                   # the control points over a span must be equal
        i0 = int(np.floor((a - curve.t0_s) / dt + 1e-9))
        i1 = int(np.floor((b - curve.t0_s) / dt - 1e-9)) + 3
        if i1 < curve.ctrl.shape[0] and not np.all(curve.ctrl[i0:i1 + 1] == curve.ctrl[i0]):
            raise InternalError(f"stream motion: the carrier is not still on the stop [{a:.3f}, {b:.3f}] s")
    return curve, spans


def _still_envelope(t: np.ndarray, planned) -> np.ndarray:
    """1 away from the stops, 0 on each planned stop ``[arrival, departure]``, a 1 s smoothstep between."""
    e = np.ones_like(t)
    for a, b in planned:
        u = np.clip(np.maximum(a - t, t - b), 0.0, 1.0)         # 0 inside, distance (s) outside, capped at 1
        e = np.minimum(e, u * u * (3.0 - 2.0 * u))
    return e


@dataclass(frozen=True, eq=False)
class Stream:
    """A simulated stream before its sweeps are cast (they are produced lazily by :func:`iter_sweeps`).

    Attributes
    ----------
    params : StreamParams
    net : DriftNetwork or PaperNet
        The drift network, or the paper world and the carrier's path
        (:class:`~minegeo.synth.stream_paper.PaperNet`).
    curve : MotionCurve
        The truth: ``T_world_sensor(t)``.
    frame_times : (n,) s
        Sweep start times (= frame times).
    imu : ImuData
    sensor : Velodyne16
    lidar_seed : numpy.random.SeedSequence
    station_spans : ndarray (k, 2)
        Still spans ``[t_start, t_end]`` (s) of the station stops inside the sweeps' time span
        (empty without stations).
    station_seed : numpy.random.SeedSequence or None
        Placement in the CRS and survey noise of the stations.
    """

    params: StreamParams
    net: object
    curve: MotionCurve
    frame_times: np.ndarray
    imu: object
    sensor: object
    lidar_seed: np.random.SeedSequence
    station_spans: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    station_seed: np.random.SeedSequence | None = None


def simulate_stream(params: StreamParams, net=None) -> Stream:
    """Plan the motion and simulate the IMU of a stream (the sweeps: :func:`iter_sweeps`).

    Parameters
    ----------
    params : StreamParams
    net : DriftNetwork or PaperNet, optional
        Default :func:`stream_network` of ``params.network`` (a ``paper-...`` network: the paper world
        and its path, :mod:`minegeo.synth.stream_paper`).
    """
    from minegeo.synth.sensors import Velodyne16
    from minegeo.synth.stream_paper import is_paper_network, paper_motion

    # a fifth child for the stations leaves the first four (and so a stream without stations) unchanged
    ss_motion, ss_lidar, ss_noise, ss_bias, ss_station = np.random.SeedSequence(int(params.seed)).spawn(5)
    if net is None:
        net = stream_network(params.network, params.width_m, params.roughness_m, int(params.seed))
    n = int(np.floor(params.duration_s * params.lidar_hz + 1e-9))
    if n < 1:
        raise InputError(f"a stream of {params.duration_s} s at {params.lidar_hz} Hz holds no sweep")
    period = 1.0 / params.lidar_hz
    frame_times = LEAD_S + np.arange(n) * period
    t_imu_end = frame_times[-1] + period + LEAD_S
    stops = None if params.station_spacing_m is None else (params.station_spacing_m, params.station_still_s)
    if is_paper_network(getattr(net, "name", None)):               # the paper world: no stations
        curve, spans = paper_motion(net, params.preset, t_imu_end, np.random.default_rng(ss_motion)), np.zeros((0, 2))
    else:
        curve, spans = stream_motion_stops(net, params.preset, t_imu_end, np.random.default_rng(ss_motion), stops)
    spans = spans[(spans[:, 0] >= frame_times[0]) & (spans[:, 1] <= frame_times[-1] + period)]
    if stops is not None and len(spans) == 0:
        raise InputError(f"no station stop falls inside the {params.duration_s:g} s run (one every "
                         f"{params.station_spacing_m:g} m of path): give a longer --duration-s or a shorter "
                         "--station-spacing-m")
    imu = simulate_imu(curve, params.imu, 0.0, t_imu_end, np.random.default_rng(ss_noise),
                       np.random.default_rng(ss_bias))
    sensor = Velodyne16(azimuth_step_deg=params.azimuth_step_deg, rotation_rate_hz=params.lidar_hz,
                        range_noise_sigma_m=params.range_noise_m, max_range_m=100.0)
    return Stream(params=params, net=net, curve=curve, frame_times=frame_times, imu=imu, sensor=sensor,
                  lidar_seed=ss_lidar, station_spans=spans, station_seed=ss_station if stops else None)


def stream_stations(st: Stream):
    """The surveyed stations of a stream and their truth.

    The drift network's world frame is placed in ``params.crs`` by a rigid ``T_crs_world``: a
    rotation about the vertical by a seeded angle and a translation to the Gwan-in mine location
    (:func:`minegeo.synth.dataset.crs_origin`, rounded to mm) at a seeded height of 150-250 m.
    Station ``k`` (in path order) stands on ``station_spans[k]``; its true point is the sensor
    origin plus the offset, ``p_world = p(t) + R(t) station_offset_m`` (the pose is constant on the
    span), ``enh_true = T_crs_world p_world``; the surveyed coordinates add
    ``N(0, STATION_SIGMA_H_M^2)`` to E and N and ``N(0, STATION_SIGMA_V_M^2)`` to H. Roles: every
    ``control_every``-th station from the first is ``control``, the others ``check``.

    Returns
    -------
    stations : Stations
        As written to ``stations.csv`` (surveyed, recorded km origin).
    truth : dict
        ``T_crs_world`` (4x4), ``enh_true`` (k, 3), ``p_world`` (k, 3), ``crs``.
    """
    from minegeo.io.stations import StationRole, Stations
    from minegeo.synth.dataset import crs_origin

    p = st.params
    if st.station_seed is None:
        raise InputError("this stream has no stations (station_spacing_m is None)")
    rng = np.random.default_rng(st.station_seed)
    E0, N0 = crs_origin(p.crs)
    H0 = float(rng.uniform(150.0, 250.0))
    theta = float(rng.uniform(0.0, 2 * np.pi))
    T = np.eye(4)
    T[:3, :3] = [[np.cos(theta), -np.sin(theta), 0.0], [np.sin(theta), np.cos(theta), 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [round(E0, 3), round(N0, 3), round(H0, 3)]
    spans = st.station_spans
    R, pos = st.curve.rotation_position(spans[:, 0])
    p_world = pos + R @ np.asarray(p.station_offset_m)
    enh_true = p_world @ T[:3, :3].T + T[:3, 3]
    k = len(spans)
    noise = rng.standard_normal((k, 3)) * [STATION_SIGMA_H_M, STATION_SIGMA_H_M, STATION_SIGMA_V_M]
    surveyed = enh_true + noise
    from minegeo.georef.crs import local_origin

    origin = local_origin(surveyed)
    roles = [StationRole.CONTROL if i % int(p.control_every) == 0 else StationRole.CHECK for i in range(k)]
    stations = Stations(ids=[f"ST{i + 1:03d}" for i in range(k)], t_start_s=spans[:, 0], t_end_s=spans[:, 1],
                        enh_local=surveyed - origin, origin_enh=origin, sigma_h_m=np.full(k, STATION_SIGMA_H_M),
                        sigma_v_m=np.full(k, STATION_SIGMA_V_M), roles=roles, crs=p.crs)
    return stations, {"T_crs_world": T, "enh_true": enh_true, "p_world": p_world, "crs": p.crs}


def iter_sweeps(world, sensor, curve, frame_times, seed, chunk: int = 10):
    """Cast the sweeps starting at ``frame_times`` from ``curve``, one beam at its own time.

    Yields
    ------
    (t_frame, points, time, ring)
        Frame time (s, sweep start); points (k, 3) in the sensor frame at each point's own firing
        time; ``time`` (k,) seconds after ``t_frame``; ``ring`` (k,) uint16.
    """
    from minegeo.synth.sensors import simulate_scan

    rng = np.random.default_rng(seed)
    ft = np.asarray(frame_times, dtype=np.float64)
    for c0 in range(0, len(ft), chunk):
        s = ft[c0:c0 + chunk]
        cloud = simulate_scan(world, sensor, curve, seed=rng, frame_times_s=s)
        tt = cloud.attributes["time_s"]
        # a beam belongs to the sweep whose [start, start + period) holds its firing time
        k = np.clip(np.searchsorted(s, tt, side="right") - 1, 0, len(s) - 1)
        cut = np.searchsorted(k, np.arange(len(s) + 1), side="left")
        for j in range(len(s)):
            sl = slice(cut[j], cut[j + 1])
            yield float(s[j]), cloud.points[sl], tt[sl] - s[j], cloud.attributes["ring"][sl]


def write_stream(folder, params: StreamParams, net=None, progress=None) -> dict:
    """Write a stream into ``folder`` (created): ``frames/NNNNNN.ply`` with ``frames/times.txt``, ``imu.csv``,
    ``imu_truth.csv``, ``groundtruth.txt`` (TUM at the frame times), ``result.json`` and, with
    stations, ``stations.csv`` and ``stations_truth.csv``.

    Returns
    -------
    dict
        The ``result.json`` record (parameters, counts, measured motion statistics).
    """
    from minegeo.io import write_point_cloud, write_trajectory
    from minegeo.io.types import PointCloud
    from minegeo.synth.flight import NetworkWorld

    out = Path(folder)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    st = simulate_stream(params, net)
    world = st.net.world if hasattr(st.net, "world") else NetworkWorld(st.net)   # the paper world: a MineWorld
    n_pts = []
    for i, (_tf, P, tt, ring) in enumerate(iter_sweeps(world, st.sensor, st.curve, st.frame_times, st.lidar_seed)):
        cloud = PointCloud(points=np.ascontiguousarray(P), attributes={"time": np.ascontiguousarray(tt),
                                                                        "ring": np.ascontiguousarray(ring)})
        write_point_cloud(out / "frames" / f"{i:06d}.ply", cloud)
        n_pts.append(len(P))
        if progress is not None:
            progress(i + 1, len(st.frame_times))
    # the SLAM contract's frames folder: DIR/times.txt, one frame time (s) per frame in name order
    (out / "frames" / "times.txt").write_text("".join(f"{t:.9f}\n" for t in st.frame_times))
    (out / "imu.csv").write_text(imu_csv_text(st.imu))
    (out / "imu_truth.csv").write_text(imu_truth_csv_text(st.imu))
    write_trajectory(out / "groundtruth.txt", st.curve.trajectory(st.frame_times), format="tum")
    rec = stream_record(st, n_pts)
    if st.station_seed is not None:
        rec["stations"] = _write_stations(out, st)
        rec["files"].update(stations="stations.csv", stations_truth="stations_truth.csv")
    (out / "result.json").write_text(json.dumps(rec, indent=2, sort_keys=True) + "\n")
    return rec


def _write_stations(out: Path, st: Stream) -> dict:
    """``stations.csv`` (surveyed, the contract's layout) and ``stations_truth.csv`` (true E N H and
    world x y z of the same points); returns the ``stations`` entry of ``result.json``."""
    from minegeo.io.stations import write_stations

    stations, truth = stream_stations(st)
    write_stations(out / "stations.csv", stations)
    lines = [f"# crs: {truth['crs']}", "id,t_start,t_end,E,N,H,x,y,z,role"]
    for i, sid in enumerate(stations.ids):
        nums = [stations.t_start_s[i], stations.t_end_s[i], *truth["enh_true"][i], *truth["p_world"][i]]
        lines.append(",".join([sid, *(repr(float(v)) for v in nums), str(stations.roles[i])]))
    (out / "stations_truth.csv").write_text("\n".join(lines) + "\n")
    p = st.params
    return {"n": len(stations), "control": int(stations.is_control.sum()), "check": int(stations.is_check.sum()),
            "crs": truth["crs"], "T_crs_world": truth["T_crs_world"].tolist(), "spacing_m": p.station_spacing_m,
            "control_every": int(p.control_every), "still_s": p.station_still_s,
            "station_offset_m": list(p.station_offset_m), "sigma_h_m": STATION_SIGMA_H_M,
            "sigma_v_m": STATION_SIGMA_V_M,
            "convention": "enh = T_crs_world (p_world(t) + R_world_sensor(t) station_offset_m), the pose constant "
                          "on [t_start, t_end]; stations.csv adds survey noise, stations_truth.csv does not"}


def stream_record(st: Stream, n_points: list) -> dict:
    """The JSON record of a stream: parameters, files, counts and measured motion statistics."""
    p = st.params
    s = st.curve.state(st.imu.t)
    speed = np.linalg.norm(s.v, axis=1)
    dist = float(np.sum(np.linalg.norm(np.diff(s.p, axis=0), axis=1)))
    params = asdict(replace(p, imu=ImuParams()))
    params["imu"] = asdict(p.imu)
    params["motion"] = asdict(PRESETS[p.preset])
    return {
        "verb": "synth", "kind": "sensor_stream", "status": "ok", "params": params,
        "conventions": {"frame_time": "sweep start", "point_time": "time: float seconds after the frame time",
                        "point_frame": "sensor frame at the point's own firing time (raw, motion-distorted)",
                        "imu_frame": "LiDAR frame (identity extrinsic, no lever arm)",
                        "gravity_mps2": GRAVITY_MPS2, "groundtruth": "TUM T_world_sensor at the frame times"},
        "network": {k: v for k, v in st.net.info.items() if k != "node_ids"},
        "files": {"frames": "frames/NNNNNN.ply (x y z time ring)", "times": "frames/times.txt", "imu": "imu.csv",
                  "imu_truth": "imu_truth.csv", "groundtruth": "groundtruth.txt"},
        "n_frames": int(len(st.frame_times)), "n_points": int(np.sum(n_points)),
        "points_per_frame": {"min": int(np.min(n_points)), "max": int(np.max(n_points))},
        "n_imu": int(len(st.imu.t)),
        "motion_stats": {"path_length_m": dist, "max_speed_mps": float(speed.max()),
                         "max_accel_mps2": float(np.linalg.norm(s.a, axis=1).max()),
                         "max_angular_rate_dps": float(np.degrees(np.linalg.norm(s.omega, axis=1).max())),
                         "max_tilt_deg": float(np.degrees(np.arccos(np.clip(s.R[:, 2, 2], -1, 1))).max())},
    }
