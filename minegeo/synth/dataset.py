"""Datasets from the synthetic mine: survey map, local scans, ground control points, files on disk.

Mirrors the experiment of Baek et al. (2022, Sec. 2 and 3.2): a global point cloud of
the whole mine from a survey pass, local point clouds of 10/20/30 m of drift in
different kinds of section (irregular roof, curve, intersection, regular, railings near
the sump), and control points on the walls giving the map in the national grid
(Korea 2000 / Central Belt 2010, EPSG:5186; the mine is placed at the Gwan-in mine,
38 deg 07' 00" N, 127 deg 13' 24" E).

Frames: ``map`` = the world frame of :class:`MineWorld`; ``scan`` = the sensor pose at
the start of a local scan; ``T_map_scan`` maps scan coordinates into the map.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text, sha256_file, versions, write_json_atomic
from minegeo.errors import CRSError, InputError
from minegeo.geometry.se3 import invert
from minegeo.io.types import ControlPoints, Trajectory
from minegeo.synth.sensors import FlashSensor, Velodyne16, ZebRevo, deskew, simulate_scan
from minegeo.synth.trajectory import (
    MOTIONS,
    _arc_lengths,
    make_trajectory,
    resolve_start,
    route_polyline,
)
from minegeo.synth.world import MineWorld, build_world

__all__ = ["build_map", "build_survey_map", "local_scan", "make_gcps", "write_world", "survey_path", "ScanSpec",
           "SCAN_PLANS", "MINE_LAT_DEG", "MINE_LON_DEG", "crs_origin", "study_params", "params_dict"]

log = logging.getLogger(__name__)

#: Gwan-in mine (Baek et al. 2022, Sec. 3.1): 38 deg 07' 00" N, 127 deg 13' 24" E
MINE_LAT_DEG = 38.0 + 7.0 / 60.0
MINE_LON_DEG = 127.0 + 13.0 / 60.0 + 24.0 / 3600.0


# ---------------------------------------------------------------------- survey map
def survey_path(world: MineWorld) -> tuple[np.ndarray, np.ndarray]:
    """Continuous floor path visiting every drift (depth-first, backtracking at ends).

    Returns the path (k, 3) and a boolean per path vertex: True on the first traversal
    of a drift (where the surveyor scans), False while backtracking. Drifts in
    ``world.unmapped`` are not entered.
    """
    adj = world.adjacency()
    seen: set[int] = set(world.unmapped)
    visited = {0}
    parts: list[tuple[np.ndarray, bool]] = []

    def visit(node: int) -> None:
        for k, other in sorted(adj[node]):
            if k in seen:
                continue
            seen.add(k)
            d = world.drifts[k]
            poly = d.centreline if d.a == node else d.centreline[::-1]
            parts.append((poly, True))
            if other not in visited:
                visited.add(other)
                visit(other)
            parts.append((poly[::-1], False))

    visit(0)
    while parts and not parts[-1][1]:
        parts.pop()
    pts, flags = [], []
    for poly, first in parts:
        start = 0 if not pts else 1
        pts.append(poly[start:])
        flags.append(np.full(len(poly) - start, first))
    P = np.vstack(pts)
    F = np.concatenate(flags)
    return P, F


def build_map(world: MineWorld, seed: int = 0, *, sensor=None, spacing_m: float | None = None,
              kind: str = "drive", return_trajectory: bool = False, first_mark_m: float | None = None,
              noise_seed: int | None = None):
    """Global point cloud of the whole mine from one survey pass, in the map (= world) frame.

    The carrier follows :func:`survey_path`; while on a drift for the first time it
    records one sensor frame every ``spacing_m`` metres. Points are assembled with the
    true trajectory (a perfect survey-grade registration), so the map frame is the world
    frame exactly; only the range noise of the sensor remains.

    Parameters
    ----------
    world : MineWorld
    seed : int
        Seeds the carrier's sway and the range noise.
    sensor : sensor model, optional
        Default: a Velodyne16 (0.2 deg for ``paper``; a 3 degree azimuth step for ``small``
        so tests stay fast).
    spacing_m : float, optional
        Distance between recorded frames (default 10 m small, 12 m paper).
    first_mark_m : float, optional
        Arc length of the first recorded frame along the survey path (default ``spacing_m / 2``);
        frames at ``first_mark_m + k spacing_m``. A second pass with ``first_mark_m = spacing_m``
        and another ``noise_seed`` fills in the frames half-way between (see
        :func:`build_survey_map`).
    noise_seed : int, optional
        Seed of the range noise (default ``seed + 1``); ``seed`` alone drives the carrier's sway.

    Returns
    -------
    PointCloud
        ``frame="map"`` with ``time_s`` of the survey. With ``return_trajectory`` also the
        survey :class:`Trajectory` (``T_map_sensor``).

    Notes
    -----
    A world with unmapped drifts (``world.unmapped``) is surveyed as
    :meth:`MineWorld.survey_world`: the route does not enter them and they do not exist for the
    sensor (their mouths are rock), as in a map surveyed before they were driven.
    """
    world = world.survey_world()
    small = world.preset != "paper"
    if sensor is None:
        sensor = Velodyne16(azimuth_step_deg=3.0) if small else Velodyne16()
    if spacing_m is None:
        spacing_m = 10.0 if small else 12.0
    if spacing_m <= 0:
        raise InputError("spacing_m must be > 0")
    P, first = survey_path(world)
    traj = make_trajectory(world, kind, path=P, seed=seed, rate_hz=20.0)
    speed = MOTIONS[kind].speed_mps
    S = _arc_lengths(P)
    # arc-length intervals of first traversals
    first_mark = spacing_m / 2 if first_mark_m is None else float(first_mark_m)
    if not (math.isfinite(first_mark) and first_mark >= 0):
        raise InputError(f"first_mark_m must be >= 0, got {first_mark_m!r}")
    marks = np.arange(first_mark, S[-1], spacing_m)
    k = np.clip(np.searchsorted(S, marks, side="right") - 1, 0, len(S) - 2)
    keep = first[k + 1]
    times = marks[keep] / speed
    cloud = simulate_scan(world, sensor, traj, seed=seed + 1 if noise_seed is None else int(noise_seed),
                          frame_times_s=times)
    out = deskew(cloud, traj)
    out.frame = "map"
    log.info("survey map: %d points from %d frames over %.0f m", len(out), len(times), S[-1])
    if return_trajectory:
        traj.frame = "map"
        return out, traj
    return out


def build_survey_map(world: MineWorld, seed: int = 0, *, passes: int = 1, spacing_m: float | None = None):
    """The survey map of :func:`build_map` with ``passes`` interleaved passes of frames.

    Pass ``j`` (0-based) records frames at ``spacing/2 + j·spacing/passes + k·spacing`` with
    range-noise seed ``seed + 1 + j`` on the same carrier path (``seed``), so ``passes = 2`` adds
    the frames half-way between those of ``passes = 1`` (one frame every 6 m on the paper
    preset) and pass 0 is exactly ``build_map(world, seed)``.

    Parameters
    ----------
    world : MineWorld
    seed : int
        Carrier sway of every pass; pass ``j`` draws its range noise from ``seed + 1 + j``.
    passes : int
        Number of interleaved passes (>= 1); the frame spacing becomes ``spacing / passes``.
    spacing_m : float, optional
        Frame spacing of one pass (default as :func:`build_map`: 10 m small, 12 m paper).

    Returns
    -------
    PointCloud
        ``frame="map"``; the passes' points (and their per-point attributes such as
        ``time_s``) concatenated in pass order.

    Raises
    ------
    InputError
        ``passes`` not an integer >= 1.
    """
    if isinstance(passes, bool) or not isinstance(passes, (int, np.integer)) or passes < 1:
        raise InputError(f"passes must be an integer >= 1, got {passes!r}")
    small = world.preset != "paper"
    sp = (10.0 if small else 12.0) if spacing_m is None else float(spacing_m)
    parts = [build_map(world, seed, spacing_m=sp, first_mark_m=sp / 2 + j * sp / passes, noise_seed=seed + 1 + j)
             for j in range(int(passes))]
    if len(parts) == 1:
        return parts[0]
    out = parts[0]
    pts = np.vstack([c.points + np.asarray(c.origin, dtype=np.float64) for c in parts]) - np.asarray(out.origin)
    attrs = {k: np.concatenate([c.attributes[k] for c in parts]) for k in out.attributes
             if all(k in c.attributes for c in parts)}
    return replace(out, points=pts, normals=None, attributes=attrs)


# ---------------------------------------------------------------------- local scans
def _section_path(world: MineWorld, section, length_m: float) -> tuple[np.ndarray, str]:
    """Floor path of ``length_m`` centred on a section (feature name, intersection, or start spec)."""
    if isinstance(section, str) and section.startswith("intersection"):
        typ = section.split(":")[1] if ":" in section else None
        cands = [it for it in world.intersections if typ is None or it.type == typ]
        if not cands:
            raise InputError(f"no intersection of type {typ!r} in this world")
        node = cands[0].node
        adj = world.adjacency()
        k, _ = sorted(adj[node])[0]
        d = world.drifts[k]
        fwd = d.a == node
        s0 = 0.0 if fwd else d.length_m
        back = route_polyline(world, k, s0, not fwd, length_m / 2)
        ahead = route_polyline(world, k, s0, fwd, length_m / 2)
        return np.vstack([back[::-1], ahead[1:]]), "intersection"
    if section == "sump":  # end at the dead end behind the sump: walk in and stop at the railings
        f = world.features["sump"]
        d = world.drifts[f["drift"]]
        L = d.length_m
        path = route_polyline(world, f["drift"], L - 2.0, False, length_m)[::-1]
        return path, "railings"
    k, s = resolve_start(world, section)
    back = route_polyline(world, k, s, False, length_m / 2)
    ahead = route_polyline(world, k, s, True, length_m / 2)
    name = section if isinstance(section, str) else "custom"
    return np.vstack([back[::-1], ahead[1:]]), name


def local_scan(world: MineWorld, start, length_m: float, sensor, seed: int = 0, *, kind: str = "walk",
               max_rays: int | None = None, frame_stride: int | None = None):
    """A local scan of ``length_m`` of drift, assembled in its own scan frame.

    Parameters
    ----------
    world : MineWorld
        Use ``world.with_vehicle(...)`` to move the parked vehicle before scanning.
    start : str, dict, tuple or (3,) array
        A section: ``"irregular_roof"``, ``"curve"``, ``"regular"``, ``"meshed"``, ``"sump"``
        (railings, ends at the dead end), ``"intersection"`` / ``"intersection:X"``
        (centred on a junction), or a start spec of :func:`resolve_start` (then the scan is
        centred there).
    length_m : float
        Scan length along the drift: 10, 20 or 30 m (the paper's local cloud lengths;
        other positive values are accepted).
    sensor : sensor model
    seed : int
    kind : str
        Carrier: ``walk``, ``drive``, ``fly`` or ``handheld`` (slow, sweeping: for the
        flash sensor).
    max_rays, frame_stride
        Thin the frames so at most ``max_rays`` beams are cast (or keep every
        ``frame_stride``-th frame).

    Returns
    -------
    cloud : PointCloud
        Points in the scan frame (``frame="scan"``), with ``time_s`` and ``range_m``.
    trajectory : Trajectory
        ``T_scan_sensor`` (the first pose is the identity), as a SLAM system would give.
    T_map_scan : (4, 4) ndarray
        Ground truth: scan frame -> map frame.
    """
    if not length_m > 0:
        raise InputError(f"length_m must be > 0, got {length_m}")
    path, _ = _section_path(world, start, float(length_m))
    traj = make_trajectory(world, kind, path=path, seed=seed, rate_hz=50.0)
    T_map_scan = traj.poses[0].copy()
    frame_stride = _frame_stride(traj, sensor, max_rays, frame_stride)
    raw = simulate_scan(world, sensor, traj, seed=seed + 1, frame_stride=frame_stride)
    return _to_scan_frame(raw, traj, T_map_scan)


def _frame_stride(traj, sensor, max_rays: int | None, frame_stride: int | None) -> int:
    """The frame stride of :func:`local_scan`: at most ``max_rays`` beams over the trajectory."""
    if frame_stride is None:
        n_frames = max(1, int((traj.times_s[-1] - traj.times_s[0]) / sensor.frame_period_s))
        d1, _, _ = sensor.rays(np.zeros(1))
        total = n_frames * d1.shape[0]
        frame_stride = 1 if not max_rays else max(1, int(math.ceil(total / max_rays)))
        if isinstance(sensor, ZebRevo):  # avoid strides that repeat the head angle
            per_rot = int(round(sensor.line_rate_hz / sensor.rotation_rate_hz))
            while math.gcd(frame_stride, per_rot) != 1:
                frame_stride += 1
    return frame_stride


def _to_scan_frame(raw, traj, T_map_scan):
    """Deskew a raw (sensor-frame, timestamped) cloud into the scan frame ``T_map_scan``; trajectory as ``T_scan_sensor``."""
    T_scan_map = invert(T_map_scan)
    cloud = deskew(raw, traj, T_scan_map)
    cloud.frame = "scan"
    poses = np.einsum("ij,njk->nik", T_scan_map, traj.poses)
    traj_scan = Trajectory(times_s=traj.times_s, poses=poses, frame="scan", body="sensor")
    return cloud, traj_scan, T_map_scan


# ---------------------------------------------------------------------- control points
def crs_origin(crs: str) -> tuple[float, float]:
    """Grid coordinates ``(E, N)`` (m) of the synthetic mine's location in ``crs`` (:class:`CRSError` when unusable)."""
    try:
        from pyproj import CRS, Transformer

        CRS.from_user_input(crs)
        tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    except Exception as exc:  # pyproj raises its own CRSError subclasses
        raise CRSError(f"cannot use CRS {crs!r}: {exc}") from None
    E, N = tr.transform(MINE_LON_DEG, MINE_LAT_DEG)
    if not (np.isfinite(E) and np.isfinite(N)):
        raise CRSError(f"the mine location 38d07'N 127d13'E is outside the area of {crs}")
    return float(E), float(N)


def make_gcps(world: MineWorld, n: int = 10, seed: int = 0, crs: str = "EPSG:5186", sigma_m: float = 0.005):
    """Ground control points on the drift walls, with grid coordinates and survey noise.

    The map is placed in ``crs`` by a rigid transform ``T_crs_map`` (scale 1): rotation
    about the vertical by a seeded angle, translation to the Gwan-in mine location
    (38 deg 07' 00" N, 127 deg 13' 24" E converted with pyproj) and a seeded height of the
    first level's floor between 150 and 250 m. GCPs are wall points 1.2-1.6 m above the
    floor, spread along the network; ``crs_enh = T_crs_map p_map + N(0, sigma_m^2 I)``.

    Returns
    -------
    gcps : ControlPoints
        ``local_xyz`` exact (map frame), ``crs_enh`` noisy, ``sigma_enh_m = sigma_m``.
    info : dict
        ``T_crs_map`` (4x4), ``origin_enh`` (E, N, H of the map origin), ``rotation_deg``,
        ``scale`` (1.0), ``grid_scale_factor`` (pyproj point scale factor at the mine: the
        rigid truth ignores it), ``crs``, ``sigma_m``, ``lat_deg``, ``lon_deg``.
    """
    if n < 3:
        raise InputError(f"need at least 3 control points, got {n}")
    if sigma_m < 0:
        raise InputError("sigma_m must be >= 0")
    rng = np.random.default_rng(seed)
    E0, N0 = crs_origin(crs)
    H0 = float(rng.uniform(150.0, 250.0))
    theta = float(rng.uniform(0.0, 2 * np.pi))
    c, s = math.cos(theta), math.sin(theta)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [round(E0, 3), round(N0, 3), round(H0, 3)]
    # wall points: evenly spaced along the drifts (by cumulative length), alternating sides
    kinds_ok = ("main", "parallel", "crosscut", "ramp", "ring", "branch")
    drifts = [(k, d) for k, d in enumerate(world.drifts)
              if d.kind in kinds_ok and d.length_m > 8 and k not in world.unmapped]
    lengths = np.array([d.length_m - 6.0 for _, d in drifts])
    cum = np.concatenate([[0], np.cumsum(lengths)])
    targets = (np.arange(n) + rng.uniform(0.2, 0.8, n)) / n * cum[-1]
    pts = []
    for i, tgt in enumerate(targets):
        j = int(np.clip(np.searchsorted(cum, tgt, side="right") - 1, 0, len(drifts) - 1))
        k, d = drifts[j]
        P = d.centreline
        S = _arc_lengths(P)
        h = rng.uniform(1.2, 1.6)
        side0 = 1.0 if i % 2 == 0 else -1.0
        placed = None
        # try the drawn place first, then nearby places / the other wall (junction mouths have no wall)
        for ds in (0.0, 2.0, -2.0, 4.0, -4.0, 6.0, -6.0):
            for side in (side0, -side0):
                s_m = float(np.clip(3.0 + (tgt - cum[j]) + ds, 0.5, S[-1] - 0.5))
                q = np.array([np.interp(s_m, S, P[:, a]) for a in range(3)])
                m = int(np.clip(np.searchsorted(S, s_m, side="right") - 1, 0, len(P) - 2))
                tdir = P[m + 1, :2] - P[m, :2]
                tdir /= np.linalg.norm(tdir)
                nrm = side * np.array([-tdir[1], tdir[0], 0.0])
                o = q + np.array([0.0, 0.0, h])
                r = world.cast(o[None], nrm[None], 3.5)[0]
                if np.isfinite(r) and world.sdf((o + (r + 0.05) * nrm)[None], with_structures=False)[0] < 0:
                    placed = o + r * nrm  # on rock, not on a pipe or the vehicle
                    break
            if placed is not None:
                break
        if placed is None:
            raise InputError(f"could not place control point {i + 1} on a wall of drift {d.name}")
        pts.append(placed)
    local = np.array(pts)
    enh = local @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, sigma_m, local.shape)
    ids = [f"GCP{i + 1:02d}" for i in range(n)]
    gcps = ControlPoints(ids=ids, local_xyz=local, crs_enh=enh, sigma_enh_m=np.full((n, 3), sigma_m), crs=crs)
    try:
        from pyproj import Proj

        k_scale = float(Proj(crs).get_factors(MINE_LON_DEG, MINE_LAT_DEG).meridional_scale)
    except Exception:  # informational only
        k_scale = float("nan")
    info = {
        "crs": crs,
        "T_crs_map": T,
        "origin_enh": T[:3, 3].copy(),
        "rotation_deg": math.degrees(theta),
        "scale": 1.0,
        "grid_scale_factor": k_scale,
        "sigma_m": float(sigma_m),
        "lat_deg": MINE_LAT_DEG,
        "lon_deg": MINE_LON_DEG,
    }
    return gcps, info


# ---------------------------------------------------------------------- files
@dataclass(frozen=True)
class ScanSpec:
    """One local scan written by :func:`write_world`."""

    section: str
    length_m: float
    sensor: str
    kind: str
    max_rays: int
    vehicle: str = "map"  # "map": parked as in the map; "moved": at the second parking place
    noise_sigma_m: float | None = None


#: Scans written per preset (section types of Baek et al. 2022, Sec. 3.2: a-f).
SCAN_PLANS: dict[str, tuple] = {
    "small": (
        ScanSpec("irregular_roof", 20.0, "zebrevo", "walk", 25_000),
        ScanSpec("intersection:X", 10.0, "velodyne16", "walk", 25_000),
        ScanSpec("curve", 30.0, "velodyne16", "drive", 25_000),
        ScanSpec("regular", 20.0, "velodyne16", "walk", 25_000, vehicle="moved", noise_sigma_m=0.05),
        ScanSpec("sump", 10.0, "flash", "handheld", 25_000),
    ),
    "paper": (
        ScanSpec("irregular_roof", 20.0, "zebrevo", "walk", 1_000_000),
        ScanSpec("curve", 20.0, "velodyne16", "walk", 1_000_000),
        ScanSpec("intersection:X", 20.0, "velodyne16", "walk", 1_000_000),
        ScanSpec("intersection:T", 20.0, "zebrevo", "walk", 1_000_000),
        ScanSpec("regular", 20.0, "zebrevo", "walk", 1_000_000, vehicle="moved"),
        ScanSpec("sump", 20.0, "flash", "handheld", 1_000_000),
        ScanSpec("regular", 10.0, "velodyne16", "walk", 1_000_000, noise_sigma_m=0.08),
        ScanSpec("irregular_roof", 30.0, "zebrevo", "walk", 1_000_000),
    ),
}

_SENSOR_CLASSES = {"velodyne16": Velodyne16, "zebrevo": ZebRevo, "flash": FlashSensor}


def _sensor(spec: ScanSpec):
    cls = _SENSOR_CLASSES[spec.sensor]
    s = cls()
    if spec.noise_sigma_m is not None:
        from dataclasses import replace

        s = replace(s, range_noise_sigma_m=spec.noise_sigma_m)
    return s


def study_params(preset: str, options: dict | None):
    """The preset's :class:`WorldParams` with study options (validated); see :func:`write_world`.

    Raises
    ------
    InputError
        Unknown preset or option, or an invalid value.
    """
    from minegeo.synth.world_params import NEW_OPTION_DEFAULTS, PRESETS, _check_params

    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    opts = dict(options or {})
    bad = sorted(set(opts) - set(NEW_OPTION_DEFAULTS))
    if bad:
        raise InputError(f"unknown world option(s) {bad}; known: {sorted(NEW_OPTION_DEFAULTS)}")
    p = replace(PRESETS[preset], **opts)
    _check_params(p)
    return p


def params_dict(params) -> dict:
    """``asdict(params)`` without the study options left at their defaults (``truth.json`` of older worlds unchanged)."""
    from minegeo.synth.world import NEW_OPTION_DEFAULTS

    d = asdict(params)
    for k, v in NEW_OPTION_DEFAULTS.items():
        if k in d and d[k] == v:
            del d[k]
    return d


def _T_list(T) -> list:
    return [[float(v) for v in row] for row in np.asarray(T)]


def write_world(outdir, preset: str = "small", seed: int = 0, *, force: bool = False, n_gcps: int = 10,
                crs: str = "EPSG:5186", progress=None, options: dict | None = None) -> dict:
    """Generate a mine and write map, local scans, trajectories, GCPs and ``truth.json`` to ``outdir``.

    Files (all written atomically; contents depend only on ``preset`` and ``seed``):
    ``map.ply`` (binary little-endian float64 x y z + time_s, map frame),
    ``scans/scan_XX.ply`` (scan frame, + time_s, range_m), ``trajectories/survey.txt`` and
    ``trajectories/scan_XX.txt`` (TUM ``t x y z qx qy qz qw``; survey in the map frame,
    scans in their scan frame), ``gcps.csv`` and ``truth.json`` (T_crs_map, T_map_scan per
    scan, sensors, sections, intersections, vehicle poses, SHA-256 of every file).

    Parameters
    ----------
    progress : callable, optional
        Called as ``progress(step_name)`` after each step (the CLI drives a tqdm bar).
    options : dict, optional
        Study options of :class:`~minegeo.synth.world.WorldParams` applied to the preset
        (``wall_roughness_m``, ``lining``, ``repeat_levels``, ``unmapped_headings``,
        ``heading_length_m``); they appear in ``truth.json`` (``world_params`` and the world summary).
        None or empty: the preset as is.

    Raises
    ------
    InputError
        ``outdir`` exists and is not empty, unless ``force``.
    """
    from minegeo.io import write_gcps, write_point_cloud, write_trajectory

    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not force:
        raise InputError(f"{out} is not empty; use --force to overwrite")
    if preset not in SCAN_PLANS:
        raise InputError(f"unknown preset {preset!r}; choose one of {sorted(SCAN_PLANS)}")
    step = progress or (lambda name: None)
    world = build_world(preset, seed, params=study_params(preset, options)) if options else build_world(preset, seed)
    step("world")
    rng = np.random.default_rng(seed)
    sub = [int(x) for x in rng.integers(0, 2**31 - 1, 8 + len(SCAN_PLANS[preset]))]
    cloud, survey = build_map(world, seed=sub[0], return_trajectory=True)
    write_point_cloud(out / "map.ply", cloud, binary=True)
    write_trajectory(out / "trajectories" / "survey.txt", survey, format="tum")
    step("map")
    park = world.features["parking"]
    scans = []
    for i, spec in enumerate(SCAN_PLANS[preset]):
        w = world if spec.vehicle == "map" else world.with_vehicle(park[1])
        sensor = _sensor(spec)
        c, tr, T_map_scan = local_scan(w, spec.section, spec.length_m, sensor, seed=sub[8 + i], kind=spec.kind,
                                       max_rays=spec.max_rays)
        name = f"scan_{i:02d}"
        write_point_cloud(out / "scans" / f"{name}.ply", c, binary=True)
        write_trajectory(out / "trajectories" / f"{name}.txt", tr, format="tum")
        scans.append({
            "name": name,
            "file": f"scans/{name}.ply",
            "trajectory": f"trajectories/{name}.txt",
            "section": "railings" if spec.section == "sump" else spec.section,
            "length_m": spec.length_m,
            "carrier": spec.kind,
            "sensor": {"model": sensor.name, **asdict(sensor)},
            "n_points": len(c),
            "T_map_scan": _T_list(T_map_scan),
            "T_world_vehicle": _T_list(w.T_world_vehicle) if w.T_world_vehicle is not None else None,
            "vehicle_moved_since_map": spec.vehicle != "map",
        })
        step(name)
    gcps, info = make_gcps(world, n=n_gcps, seed=sub[1], crs=crs)
    write_gcps(out / "gcps.csv", gcps)
    step("gcps")
    written = ["map.ply", "trajectories/survey.txt", "gcps.csv"]
    for sc in scans:
        written += [sc["file"], sc["trajectory"]]
    files = {name: sha256_file(out / name) for name in sorted(written)}  # only what this run wrote
    truth = {
        "generator": "minegeo.synth.write_world",
        "preset": preset,
        "seed": int(seed),
        "frames": {"map": "world frame of the synthetic mine (m), first level floor at z=0",
                   "scan": "sensor pose at the start of the local scan",
                   "T_a_b": "maps coordinates in frame b into frame a: p_a = R p_b + t"},
        "crs": crs,
        "origin_enh": info["origin_enh"],
        "T_crs_map": _T_list(info["T_crs_map"]),
        "crs_placement": {k: info[k] for k in ("rotation_deg", "scale", "grid_scale_factor", "sigma_m",
                                               "lat_deg", "lon_deg")},
        "world": world.summary(),
        "world_params": params_dict(world.params),
        "intersections": [{"node": it.node, "type": it.type, "degree": it.degree, "level": it.level,
                           "position": list(it.position)} for it in world.intersections],
        "dead_ends": [[float(v) for v in world.nodes[i]] for i in world.dead_ends],
        "drifts": [{"name": d.name, "kind": d.kind, "level": d.level, "length_m": round(d.length_m, 6),
                    "from": list(map(float, d.centreline[0])), "to": list(map(float, d.centreline[-1]))}
                   for d in world.drifts],
        "map": {"file": "map.ply", "trajectory": "trajectories/survey.txt", "n_points": len(cloud),
                "T_world_vehicle": _T_list(world.T_world_vehicle)},
        "scans": scans,
        "gcps": {"file": "gcps.csv", "n": len(gcps), "sigma_m": info["sigma_m"]},
        "files_sha256": files,
        "versions": versions(),
    }
    write_json_atomic(out / "truth.json", truth)
    report = [f"minegeo synthetic mine: preset {preset}, seed {seed}",
              f"drifts: {len(world.drifts)} ({world.total_length_m:.0f} m), levels {world.params.n_levels}, "
              f"loops {world.n_independent_loops()}, intersections "
              + ", ".join(f"{k} x{v}" for k, v in world.summary()["intersections_by_type"].items()),
              f"map.ply: {len(cloud)} points (map frame)"]
    for s in scans:
        report.append(f"{s['file']}: {s['n_points']} points, {s['section']}, {s['length_m']:.0f} m, "
                      f"{s['sensor']['model']} ({s['carrier']})")
    report.append(f"gcps.csv: {len(gcps)} control points in {crs} (sigma {info['sigma_m'] * 1000:.0f} mm)")
    atomic_write_text(out / "report.txt", "\n".join(report) + "\n")
    step("truth")
    return truth
