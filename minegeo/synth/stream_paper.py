"""Sensor streams in the paper world (Baek et al. 2022's mine, ``build_world("paper", 1)``).

The carrier of a :class:`~minegeo.synth.stream_presets.StreamPreset` drives one fixed path of the
paper world (world seed :data:`PAPER_WORLD_SEED` = 1, the world of ``benchmarks/bench_slam.py``);
:func:`minegeo.synth.stream.simulate_stream` casts its sweeps from the same continuous pose curve
as in the drift networks (each beam at its own firing time, the world's rough rock and structures).
Paths (:data:`PAPER_NETWORKS`, 3-D floor centrelines in the world frame, smoothed over 1 m):

* ``paper-ring``: the ring roadway at the end of the L0 main drift (``ring_L0_049`` then
  ``ring_L0_050`` backwards, a 100 m circle of 16 m radius) once round from its junction with the
  main drift and 15 m on past the start, so the loop can close (114 m);
* ``paper-straight``: the L1 main drift end to end (``main_L1_052`` .. ``main_L1_071``, 505 m,
  level, a slight seeded wiggle);
* ``paper-ramp``: the last 20 m of the ring roadway (``ring_L0_049``), the 204 m ramp
  (``ramp_L0_051``, 25 m down, about 7 degrees) and the first 30 m of the L1 main drift, the corners
  cut by :func:`~minegeo.synth.sequence.route_path` (3 m); 251 m.

Motion (:func:`paper_motion`): the preset's speed profile along the path (cruise speed, lateral
acceleration and yaw-rate limits, from rest at ``STILL_S`` to rest at the path's end, where it stays);
yaw from the path; the sensor ``height_m`` above the **local floor** (the path's floor z at the
carrier's arc length; a drone: half the drift's height); pitch = the floor's grade (``-atan(dz/ds)``,
positive nose down as ``R = Rz Ry Rx``); the preset's bob, lateral sway, yaw sway, roll / pitch tilt
noise and height noise drawn as in :func:`~minegeo.synth.stream.stream_motion_stops`. The sensor must
stay at least 0.2 m inside the open space (the world's SDF along the curve; InputError otherwise).
Not simulated: survey stations (stop-and-go), other world seeds, drift widths other than the
world's (4.5 m) and the stream's ``roughness_m`` (the world has its own rock).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from minegeo.errors import InputError
from minegeo.synth.motion import MotionCurve, curve_from_samples, gaussian_smooth
from minegeo.synth.stream_presets import (
    KNOT_DT_S,
    PRESETS,
    STILL_S,
    StreamPreset,
    _speed_profile,
    carrier_sway,
)

__all__ = ["PAPER_NETWORKS", "PAPER_WORLD_SEED", "PaperNet", "paper_network", "paper_motion", "is_paper_network",
           "path_duration_s"]

#: the paper-world stream networks
PAPER_NETWORKS = ("paper-ring", "paper-straight", "paper-ramp")
#: world seed of the paper-world streams (``benchmarks/bench_slam.py``'s WORLD_SEED)
PAPER_WORLD_SEED = 1
#: spacing (m) of the dense path and the standard deviation (m) of its smoothing
_STEP_M, _SMOOTH_M = 0.05, 1.0
#: least clearance (m) of the sensor to the rock and structures
_CLEAR_M = 0.2


@dataclass(frozen=True, eq=False)
class PaperNet:
    """A paper-world stream's network: the world and the carrier's floor path.

    Attributes
    ----------
    name : str
        One of :data:`PAPER_NETWORKS`.
    world : MineWorld
    path : ndarray (k, 3)
        Dense (every 0.05 m), smoothed floor centreline, world frame (m).
    info : dict
        The ``network`` record of ``result.json``.
    """

    name: str
    world: object
    path: np.ndarray
    info: dict

    @property
    def widths(self) -> np.ndarray:
        """Drift width (m), as ``DriftNetwork.widths``."""
        return np.array([float(self.world.params.width_m)])


def is_paper_network(name) -> bool:
    """Whether a ``--stream-network`` value names a paper-world path (``paper-...``)."""
    return isinstance(name, str) and name.startswith("paper-")


@functools.lru_cache(maxsize=1)
def _paper_world():
    from minegeo.synth.world import build_world

    return build_world("paper", PAPER_WORLD_SEED)


def _raw_path(world, name: str) -> tuple[np.ndarray, list]:
    """The floor-centreline polyline (k, 3) of a paper path and the drifts it runs through."""
    from minegeo.synth.sequence import route_path
    from minegeo.synth.trajectory import _cut

    d = {x.name: x.centreline for x in world.drifts}

    def cat(parts):
        return np.concatenate([p if k == 0 else p[1:] for k, p in enumerate(parts)])

    if name == "paper-ring":
        parts = [d["ring_L0_049"], d["ring_L0_050"][::-1], _cut(d["ring_L0_049"], 0.0, 15.0)]
        return cat(parts), ["ring_L0_049", "ring_L0_050", "ring_L0_049"]
    if name == "paper-straight":
        names = [f"main_L1_{i:03d}" for i in range(52, 72)]
        return cat([d[n] for n in names]), names
    if name == "paper-ramp":
        route = [("ring_L0_049", True), ("ramp_L0_051", True), ("main_L1_052", True), ("main_L1_053", True)]
        first = float(np.linalg.norm(np.diff(d["main_L1_052"], axis=0), axis=1).sum())
        return route_path(world, route, start_m=-20.0, end_m=30.0 - first), [n for n, _ in route]
    raise InputError(f"unknown paper-world stream network {name!r}; one of {', '.join(PAPER_NETWORKS)}")


def paper_network(name: str) -> PaperNet:
    """The paper world (seed :data:`PAPER_WORLD_SEED`) and the dense floor path of ``name``."""
    from minegeo.synth.trajectory import _densify

    if name not in PAPER_NETWORKS:
        raise InputError(f"unknown paper-world stream network {name!r}; one of {', '.join(PAPER_NETWORKS)}")
    world = _paper_world()
    raw, drifts = _raw_path(world, name)
    C = _densify(raw, _STEP_M)
    C = gaussian_smooth(C, _SMOOTH_M / _STEP_M)              # the centreline's 2 m vertices and wiggle
    length = float(np.linalg.norm(np.diff(C, axis=0), axis=1).sum())
    grade = _grade(C)
    info = {"kind": "paper_world", "name": name, "world_preset": "paper", "world_seed": PAPER_WORLD_SEED,
            "drifts": drifts, "width_m": float(world.params.width_m), "path_length_m": length,
            "drop_m": float(C[0, 2] - C[-1, 2]), "max_grade_deg": float(np.degrees(np.abs(np.arctan(grade)).max()))}
    return PaperNet(name=name, world=world, path=C, info=info)


def _grade(C: np.ndarray) -> np.ndarray:
    """Floor grade ``dz / ds_horizontal`` at the vertices of a dense path."""
    sh = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C[:, :2], axis=0), axis=1))])
    return np.gradient(C[:, 2], sh)


def path_duration_s(net: PaperNet, preset: str | StreamPreset) -> float:
    """Time (s) at which the carrier comes to rest at the path's end (it starts at ``STILL_S``)."""
    pre = PRESETS[preset] if isinstance(preset, str) else preset
    return float(_speed_profile(net.path[:, :2], pre)[-1] + STILL_S)


def paper_motion(net: PaperNet, preset: str | StreamPreset, duration_s: float,
                 rng: np.random.Generator) -> MotionCurve:
    """The carrier's pose curve over ``[0, duration_s]`` along ``net.path`` (see the module docstring).

    Raises
    ------
    InputError
        ``duration_s`` past the carrier's arrival at the path's end, or a motion within 0.2 m of the
        rock.
    """

    pre = PRESETS[preset] if isinstance(preset, str) else preset
    name = preset if isinstance(preset, str) else "given"
    dt = KNOT_DT_S
    t = (np.arange(int(np.ceil((duration_s + 2.0) / dt)) + 4) - 1) * dt
    C = net.path
    ts = _speed_profile(C[:, :2], pre) + STILL_S
    if ts[-1] < duration_s:
        raise InputError(f"the {net.name} path ({net.info['path_length_m']:.0f} m) lasts {ts[-1]:.1f} s for the "
                         f"{name} carrier and the stream needs {duration_s:.1f} s (sweeps and 1 s of IMU): give "
                         f"--duration-s <= {np.floor(10 * (ts[-1] - 1.0)) / 10:g}")
    d = np.gradient(C[:, :2], axis=0)
    yaw_p = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    pitch_p = -np.arctan(gaussian_smooth(_grade(C), _SMOOTH_M / _STEP_M))
    base = np.column_stack([np.interp(t, ts, c) for c in (*C.T, yaw_p, pitch_p)])
    base = gaussian_smooth(base, pre.path_smooth_s / dt)
    xy, floor, yaw, grade_pitch = base[:, :2], base[:, 2], base[:, 3], base[:, 4]
    speed = np.linalg.norm(np.gradient(xy, dt, axis=0), axis=1)
    moving = np.clip(speed / max(pre.speed_mps, 1e-9), 0.0, 1.0)      # gait and sway scale with speed
    xy, yaw, pitch, roll, bob, vertical = carrier_sway(pre, t, xy, yaw, moving, 0.05 * float(net.widths.min()),
                                                       rng, pitch0=grade_pitch)
    p = net.world.params
    h0 = 0.5 * (p.wall_height_m + 0.5 * p.width_m) if pre.height_m is None else float(pre.height_m)
    z = floor + h0 + bob + vertical
    z = gaussian_smooth(z, 0.05 / dt)
    curve = curve_from_samples(t[0], dt, np.column_stack([xy, z]), np.column_stack([yaw, pitch, roll]))
    tc = np.arange(curve.t_start, curve.t_end, 0.05)
    clear = net.world.sdf(curve.rotation_position(tc)[1])
    if clear.min() < _CLEAR_M:
        raise InputError(f"the {name} motion on {net.name} comes within {clear.min():.2f} m of the rock at "
                         f"t = {tc[np.argmin(clear)]:.1f} s")
    return curve
