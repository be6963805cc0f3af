"""Synthetic MAST scenarios: a horizontal 2D scanner in a straight drift with two beacons.

Reproduces the simulation set-up of Simela, Marshall & Daneshmend (section
"Simulation Results"): Beacon 2 is fixed on the west wall (wall azimuth 0 deg);
Beacon 1 sits on the opposite wall on Beacon 2's mid-panel normal rotated by
``beacon1_rotation_deg`` (+10 = divergent, 0 = parallel, -10 = convergent walls,
our naming: with +10 the walls diverge northwards); seven scanner positions form a
triangle between the beacons (apex = position 1 next to Beacon 2, base = positions
5-7 next to Beacon 1). The scanner azimuth follows the paper's rule: parallel to the
closest wall, otherwise the mean of the two wall directions.

The scan is simulated by exact 2D ray-segment intersection with occlusion
(:func:`minegeo.mast._kernels._cast_rays`): walls are polylines with a slight
roughness pushed into the rock (never in front of a beacon), beacons are the three
panels of :class:`~minegeo.mast.beacons.BeaconDesign`. Noise: Gaussian range noise
``sigma_range_m`` and (optional) Gaussian bearing noise ``sigma_bearing_deg`` on
the *recorded* bearing (the ray itself travels along the true bearing). Rays that
hit nothing within ``max_range_m`` give no return. Deterministic under ``seed``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from minegeo._provenance import write_json_atomic
from minegeo._validate import check_positive
from minegeo.errors import InputError
from minegeo.mast._kernels import _cast_rays
from minegeo.mast.beacons import Beacon, BeaconDesign, place_beacon, write_beacons_csv
from minegeo.mast.scan import Scan2D, write_scan_csv

__all__ = [
    "PAPER_POSITIONS",
    "WALL_CONFIGS",
    "MastScenarioOptions",
    "MastWorld",
    "MastScenario",
    "build_mast_world",
    "simulate_mast_scenario",
    "write_mast_scenario",
]

#: Scanner positions 1-7 of the paper's Table 2 (mine frame, m).
PAPER_POSITIONS: dict[int, tuple[float, float]] = {
    1: (7.000, 7.000),
    2: (10.932, 6.219),
    3: (10.932, 7.781),
    4: (11.000, 7.000),
    5: (14.863, 5.437),
    6: (14.863, 8.563),
    7: (15.000, 7.000),
}
#: Named wall configurations -> Beacon 1 rotation (deg).
WALL_CONFIGS: dict[str, float] = {"divergent": 10.0, "parallel": 0.0, "convergent": -10.0}

_B2_CENTRE = (6.0, 7.0)


@dataclass(frozen=True)
class MastScenarioOptions:
    """Options of a synthetic MAST scene (all lengths in metres, angles in degrees).

    ``position`` picks one of the paper's seven scanner positions; ``scanner_xy_m``
    and ``scanner_azimuth_deg`` override the position and the paper's azimuth rule.
    ``beacon_ids`` are the ids of (Beacon 1, Beacon 2). ``mine_origin_m`` is added to
    every written mine coordinate (to exercise large projected coordinates).
    ``visible_beacons`` (ids) removes the others from the scene (not from the beacon
    list). Both beacons run P1 -> P3 northwards (mirror images of each other, which
    makes them distinguishable); ``point_symmetric_beacons`` instead turns Beacon 1 through
    180 deg so the pair is point-symmetric and cannot be told apart by shape.
    """

    position: int = 4
    scanner_xy_m: tuple | None = None
    scanner_azimuth_deg: float | None = None
    beacon1_rotation_deg: float = 0.0
    beacon_length_m: float = 1.0
    beacon_depth_m: float | None = None
    beacon_spacing_m: float = 10.0
    angular_step_deg: float = 0.25
    fov_deg: float = 270.0
    max_range_m: float = 30.0
    sigma_range_m: float = 0.003
    sigma_bearing_deg: float = 0.0
    wall_roughness_m: float = 0.005
    wall_vertex_spacing_m: float = 0.2
    wall_half_length_m: float = 15.0
    beacon_ids: tuple = ("B1", "B2")
    visible_beacons: tuple | None = None
    point_symmetric_beacons: bool = False
    mine_origin_m: tuple = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("beacon_length_m", "beacon_spacing_m", "angular_step_deg", "fov_deg", "max_range_m"):
            check_positive(getattr(self, name), name)
        for name in ("sigma_range_m", "sigma_bearing_deg", "wall_roughness_m"):
            check_positive(getattr(self, name), name, allow_zero=True)
        if self.scanner_xy_m is None and self.position not in PAPER_POSITIONS:
            raise InputError(f"position must be 1-7 (paper Table 2), got {self.position}")
        if self.fov_deg > 360.0:
            raise InputError(f"fov_deg must be <= 360, got {self.fov_deg}")

    def truth_pose(self) -> tuple[float, float, float]:
        """True scanner (x, y, azimuth_deg) in the local mine frame (before ``mine_origin_m``)."""
        g = float(self.beacon1_rotation_deg)
        if self.scanner_xy_m is not None:
            xy = tuple(float(c) for c in self.scanner_xy_m)
        else:
            xy = PAPER_POSITIONS[self.position]
        if self.scanner_azimuth_deg is not None:
            az = float(self.scanner_azimuth_deg)
        elif self.scanner_xy_m is not None or self.position in (2, 3, 4):
            az = 0.5 * g
        elif self.position == 1:
            az = 0.0
        else:
            az = g
        return xy[0], xy[1], az % 360.0


@dataclass
class MastWorld:
    """Noise-free geometry of a scene (local mine frame, before ``mine_origin_m``).

    Attributes
    ----------
    options : MastScenarioOptions
    beacons : list[Beacon]
        Beacons in the local mine frame.
    segments : (k, 4) float64
        Every reflecting segment ``[ax, ay, bx, by]`` (walls + visible beacon panels).
    segment_label : (k,) int64
        ``-1`` for walls, ``3 * beacon_index + panel`` for beacon panels.
    bearings_deg : (m,) float64
        Nominal bearings of all rays.
    true_range_m : (m,) float64
        Exact range per ray (NaN = no return).
    hit_label : (m,) int64
        Label of the segment hit (-2 = no return).
    """

    options: MastScenarioOptions
    beacons: list
    segments: np.ndarray
    segment_label: np.ndarray
    bearings_deg: np.ndarray
    true_range_m: np.ndarray
    hit_label: np.ndarray

    def noisy_scan(self, rng: np.random.Generator) -> tuple[Scan2D, np.ndarray]:
        """Draw one noisy scan; returns the scan and the hit label of each kept return.

        Noise is drawn for every ray (hit or not) so the random stream does not depend
        on the geometry.
        """
        o = self.options
        m = self.bearings_deg.size
        dr = rng.standard_normal(m) * o.sigma_range_m
        db = rng.standard_normal(m) * o.sigma_bearing_deg
        keep = np.isfinite(self.true_range_m)
        r = self.true_range_m + dr
        keep &= r > 0
        scan = Scan2D(
            self.bearings_deg[keep] + db[keep],
            r[keep],
            sigma_range_m=o.sigma_range_m,
            sigma_bearing_deg=o.sigma_bearing_deg,
        )
        return scan, self.hit_label[keep]


def _wall_polyline(p0, direction, half_len, spacing, rough, into_rock, rng, keep_flat):
    n = max(2, int(math.ceil(2 * half_len / spacing)) + 1)
    s = np.linspace(-half_len, half_len, n)
    off = np.abs(rng.standard_normal(n)) * rough
    for lo, hi in keep_flat:
        off[(s >= lo) & (s <= hi)] = 0.0
    pts = p0 + s[:, None] * direction + off[:, None] * into_rock
    return np.hstack([pts[:-1], pts[1:]])


def build_mast_world(options: MastScenarioOptions, rng: np.random.Generator) -> MastWorld:
    """Build walls and beacons of the paper's scene and cast the noise-free scan.

    The wall roughness (half-normal offsets into the rock every
    ``wall_vertex_spacing_m``, zero under the beacons) is drawn from ``rng``.
    """
    o = options
    design = BeaconDesign(total_length_m=o.beacon_length_m, depth_m=o.beacon_depth_m)
    g = math.radians(o.beacon1_rotation_deg)
    c2 = np.array(_B2_CENTRE)
    c1 = c2 + o.beacon_spacing_m * np.array([math.cos(g), -math.sin(g)])
    if o.point_symmetric_beacons:
        # Beacon 1 = Beacon 2 turned through 180 deg: identical shape seen from the drift
        b1 = place_beacon(design, o.beacon_ids[0], c1, o.beacon1_rotation_deg + 180.0, front="right")
    else:
        b1 = place_beacon(design, o.beacon_ids[0], c1, o.beacon1_rotation_deg, front="left")
    b2 = place_beacon(design, o.beacon_ids[1], c2, 0.0, front="right")
    beacons = [b1, b2]
    half_chord = 0.5 * float(np.linalg.norm(b1.vertices_m[3] - b1.vertices_m[0]))
    flat = [(-half_chord - 0.05, half_chord + 0.05)]
    segs = [
        _wall_polyline(
            c2, np.array([0.0, 1.0]), o.wall_half_length_m, o.wall_vertex_spacing_m,
            o.wall_roughness_m, np.array([-1.0, 0.0]), rng, flat,
        ),
        _wall_polyline(
            c1, np.array([math.sin(g), math.cos(g)]), o.wall_half_length_m, o.wall_vertex_spacing_m,
            o.wall_roughness_m, np.array([math.cos(g), -math.sin(g)]), rng, flat,
        ),
    ]
    labels = [np.full(len(s), -1, dtype=np.int64) for s in segs]
    visible = o.beacon_ids if o.visible_beacons is None else tuple(o.visible_beacons)
    for bi, b in enumerate(beacons):
        if b.beacon_id in visible:
            segs.append(b.panels())
            labels.append(3 * bi + np.arange(3, dtype=np.int64))
    segments = np.ascontiguousarray(np.vstack(segs))
    segment_label = np.concatenate(labels)

    x, y, az = o.truth_pose()
    n_rays = int(math.floor(o.fov_deg / o.angular_step_deg + 1e-9)) + (0 if o.fov_deg >= 360.0 else 1)
    bearings = -0.5 * o.fov_deg + o.angular_step_deg * np.arange(n_rays)
    a = np.radians(az + bearings)
    dirs = np.ascontiguousarray(np.column_stack([np.sin(a), np.cos(a)]))
    rng_m, idx, _ = _cast_rays(np.array([x, y]), dirs, segments, float(o.max_range_m))
    hit = np.where(idx >= 0, segment_label[np.maximum(idx, 0)], -2)
    return MastWorld(o, beacons, segments, segment_label, bearings, rng_m, hit)


@dataclass
class MastScenario:
    """A simulated scan with its beacons and truth (mine coordinates include ``mine_origin_m``)."""

    scan: Scan2D
    beacons: list
    truth: dict
    options: MastScenarioOptions
    hit_label: np.ndarray = field(repr=False)
    seed: int | None = None


def _shift(beacons: list, origin) -> list:
    o = np.asarray(origin, dtype=np.float64)
    if not np.any(o):
        return list(beacons)
    return [Beacon(b.beacon_id, b.vertices_m + o) for b in beacons]


def simulate_mast_scenario(seed: int = 0, options: MastScenarioOptions | None = None, **kw) -> MastScenario:
    """Simulate one MAST scene.

    Parameters
    ----------
    seed : int
        Seeds wall roughness and measurement noise (``np.random.default_rng(seed)``).
    options : MastScenarioOptions, optional
        Scene options; keyword arguments override individual fields.

    Returns
    -------
    MastScenario
        ``truth`` = ``{"x_m", "y_m", "azimuth_deg"}`` in the mine frame.
    """
    o = options if options is not None else MastScenarioOptions()
    if kw:
        o = replace(o, **kw)
    rng = np.random.default_rng(seed)
    world = build_mast_world(o, rng)
    scan, labels = world.noisy_scan(rng)
    x, y, az = o.truth_pose()
    ox, oy = (float(c) for c in o.mine_origin_m)
    truth = {"x_m": x + ox, "y_m": y + oy, "azimuth_deg": az}
    return MastScenario(scan, _shift(world.beacons, o.mine_origin_m), truth, o, labels, seed)


def write_mast_scenario(outdir, seed: int = 0, **options) -> dict[str, Path]:
    """Simulate a scene and write ``scan.csv``, ``beacons.csv`` and ``truth.json`` to ``outdir``.

    Files
    -----
    scan.csv
        ``bearing_deg,range_m`` (see :func:`minegeo.mast.scan.read_scan_csv`), with
        ``# sigma_range_m`` / ``# sigma_bearing_deg`` comments stating the noise model.
    beacons.csv
        ``beacon_id,vertex,x_m,y_m`` (see :func:`minegeo.mast.beacons.read_beacons_csv`).
    truth.json
        ``{"x_m", "y_m", "azimuth_deg", "seed", "options"}``.

    Returns
    -------
    dict
        Paths of the three files.
    """
    sc = simulate_mast_scenario(seed, MastScenarioOptions(**options))
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"scan": out / "scan.csv", "beacons": out / "beacons.csv", "truth": out / "truth.json"}
    write_scan_csv(paths["scan"], sc.scan, comments={"seed": seed, "source": "minegeo.mast.scenario"})
    write_beacons_csv(paths["beacons"], sc.beacons)
    write_json_atomic(paths["truth"], {**sc.truth, "seed": seed, "options": asdict(sc.options)})
    return paths

