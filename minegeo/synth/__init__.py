"""minegeo.synth: a seeded, deterministic synthetic underground mine with sensors and ground truth.

The world is a signed distance field (positive in air, negative in rock, zero on the
surface) of a multi-level drift network with horseshoe profiles, ramps at 6-8 degrees,
T/X/Y intersections, a ring roadway, dead ends, blast overbreak and texture, rock
bolts and straps, pipes, cables, a ventilation duct, railings at a sump and a
movable parked vehicle. Sensors (VLP-16-like, ZEB-REVO-like, iPad-like flash, 2D
horizontal range-bearing) are simulated by sphere tracing. Study options (wall roughness,
exact / near copies of levels, unmapped headings) and :func:`make_study_world` serve
localization studies where drifts look alike. See ``docs/synth.md``.
"""

from __future__ import annotations

from minegeo.synth.dataset import (
    MINE_LAT_DEG,
    MINE_LON_DEG,
    SCAN_PLANS,
    ScanSpec,
    build_map,
    build_survey_map,
    local_scan,
    make_gcps,
    survey_path,
    write_world,
)
from minegeo.synth.sensors import (
    SENSORS,
    FlashSensor,
    Horizontal2D,
    Scan2D,
    Velodyne16,
    ZebRevo,
    deskew,
    simulate_scan,
    simulate_scan_2d,
)
from minegeo.synth.study import StudyScan, StudyWorld, make_study_world, measure_wall_roughness
from minegeo.synth.trajectory import MOTIONS, MotionParams, interpolate_poses, make_trajectory
from minegeo.synth.world import (
    LININGS,
    PRESETS,
    Drift,
    Intersection,
    MineWorld,
    WorldParams,
    build_world,
    roughness_amplitudes,
)

__all__ = [
    "MineWorld",
    "WorldParams",
    "Drift",
    "Intersection",
    "PRESETS",
    "build_world",
    "Velodyne16",
    "ZebRevo",
    "FlashSensor",
    "Horizontal2D",
    "SENSORS",
    "simulate_scan",
    "simulate_scan_2d",
    "Scan2D",
    "deskew",
    "MotionParams",
    "MOTIONS",
    "make_trajectory",
    "interpolate_poses",
    "build_map",
    "build_survey_map",
    "local_scan",
    "make_gcps",
    "survey_path",
    "write_world",
    "ScanSpec",
    "SCAN_PLANS",
    "MINE_LAT_DEG",
    "MINE_LON_DEG",
    "LININGS",
    "roughness_amplitudes",
    "make_study_world",
    "StudyWorld",
    "StudyScan",
    "measure_wall_roughness",
]


def _warmup() -> None:
    """Compile the field and ray-casting kernels on a tiny input (a single straight drift)."""
    import numpy as np

    from minegeo.synth import _kernels as K

    a = {
        "grid_f": np.array([-5.0, -5.0, -2.0, 2.0]),
        "grid_i": np.array([6, 5, 5], np.int64),
        "void_prims": np.array([[-2.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.25, 2.25]]),
        "void_type": np.zeros(1, np.int64),
        "solid_prims": np.array([[0.0, 1.5, 1.0, 1.0, 1.5, 1.0, 0.05, 0.0], [0.0, -1.0, 0.5, 0.3, 0.3, 0.3, 0.0, 0.0]]),
        "solid_type": np.array([0, 1], np.int64),
        "waves": np.array([[1.0, 0.5, 0.2, 0.3], [0.2, 1.0, 0.1, 1.0]]),
        "octaves": np.array([[0.0, 1.0, 0.1, 0.0], [1.0, 1.0, 0.01, 1.0]]),
        "zones": np.array([[0.0, 0.0, 1.0, 2.0, 0.5]]),
    }
    n = int(np.prod(a["grid_i"]))
    start = np.zeros(n + 1, np.int64)
    start[1:] = np.arange(1, n + 1)
    v_items = np.zeros(n, np.int64)
    s_start = np.zeros(n + 1, np.int64)
    s_items = np.zeros(0, np.int64)
    veh = (np.eye(4), np.array([[0.0, 0.0, 0.5, 0.5, 0.5, 0.5, 0.0, 0.0]]), np.ones(1, np.int64),
           np.array([0.0, 0.0, 0.5, 1.0]))
    P = np.array([[0.0, 0.0, 1.0], [0.0, 3.0, 1.0]])
    out = np.empty(2)
    K.sdf_many(P, a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], start, v_items, a["solid_prims"],
               a["solid_type"], s_start, s_items, a["waves"], a["octaves"], a["zones"], *veh, True, True, out)
    K.noise_parts_many(P, a["waves"], a["octaves"], a["zones"], np.empty(2), np.empty(2))
    D = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    K.cast_rays(P[:1].repeat(2, 0), D, 10.0, 0.45, 1e-3, 100, 1e-4, a["grid_f"], a["grid_i"], a["void_prims"],
                a["void_type"], start, v_items, a["solid_prims"], a["solid_type"], s_start, s_items, a["waves"],
                a["octaves"], a["zones"], *veh, True, -0.011, 0.8, out, np.empty(2, np.int64))

from minegeo.synth.network import (  # noqa: E402  (drift networks for intersection studies)
    DriftNetwork,
    NetworkCloud,
    intersections_network,
    junction_truth,
    network_cloud,
    niosh_network,
)

__all__ += ["DriftNetwork", "NetworkCloud", "intersections_network", "junction_truth", "network_cloud",
            "niosh_network"]
