"""minegeo.mast — MAST beacon positioning of a horizontal 2D scanner.

Simela, Marshall & Daneshmend, *Automated laser scanner 2D positioning and orienting by
method of triangulation for underground mine surveying* (MAST). Two beacons of three
panels (lengths 2:3:1) are bolted on opposite drift walls and surveyed; one horizontal
scan then gives the scanner's mine-frame position and azimuth with a covariance.

Public API
----------
* :func:`locate_scanner` (:class:`MastParams`, :class:`MastResult`) — the whole pipeline.
* Beacons: :class:`Beacon`, :class:`BeaconDesign`, :func:`place_beacon`,
  :func:`read_beacons_csv`, :func:`write_beacons_csv`.
* Scans: :class:`Scan2D`, :func:`read_scan_csv`, :func:`write_scan_csv`, :func:`scan_to_xy`.
* Steps: :func:`segment_scan`, :func:`identify_panels` (:class:`SegmentationParams`,
  ``TABLE1_OPTIONS``), :func:`icp_point_to_line`, :func:`resect_scanner_pose`.
* Synthetic scenes: :class:`MastScenarioOptions`, :func:`simulate_mast_scenario`,
  :func:`write_mast_scenario`, :func:`build_mast_world`, ``PAPER_POSITIONS``.
"""

from __future__ import annotations

from minegeo.mast.beacons import Beacon, BeaconDesign, place_beacon, read_beacons_csv, write_beacons_csv
from minegeo.mast.icp import IcpResult, icp_point_to_line
from minegeo.mast.pipeline import MastParams, MastResult, MastStatus, locate_scanner
from minegeo.mast.resection import ResectionObservations, condition_sigmas, resect_scanner_pose
from minegeo.mast.scan import Scan2D, read_scan_csv, scan_to_xy, write_scan_csv
from minegeo.mast.scenario import (
    PAPER_POSITIONS,
    WALL_CONFIGS,
    MastScenario,
    MastScenarioOptions,
    MastWorld,
    build_mast_world,
    simulate_mast_scenario,
    write_mast_scenario,
)
from minegeo.mast.segmentation import (
    TABLE1_OPTIONS,
    LineSegment,
    PanelMatch,
    SegmentationParams,
    identify_panels,
    segment_scan,
)

__all__ = [
    "Beacon",
    "BeaconDesign",
    "place_beacon",
    "read_beacons_csv",
    "write_beacons_csv",
    "IcpResult",
    "icp_point_to_line",
    "MastParams",
    "MastResult",
    "MastStatus",
    "locate_scanner",
    "ResectionObservations",
    "condition_sigmas",
    "resect_scanner_pose",
    "Scan2D",
    "read_scan_csv",
    "scan_to_xy",
    "write_scan_csv",
    "PAPER_POSITIONS",
    "WALL_CONFIGS",
    "MastScenario",
    "MastScenarioOptions",
    "MastWorld",
    "build_mast_world",
    "simulate_mast_scenario",
    "write_mast_scenario",
    "TABLE1_OPTIONS",
    "LineSegment",
    "PanelMatch",
    "SegmentationParams",
    "identify_panels",
    "segment_scan",
]


def _warmup() -> None:
    """Compile the Numba kernels of this package on tiny inputs."""
    import numpy as np

    from minegeo.mast._kernels import _cast_rays, _grow_segments, _nearest_segment, _split_segments

    segs = np.array([[1.0, -1.0, 1.0, 1.0], [2.0, -1.0, 2.0, 1.0]])
    dirs = np.array([[1.0, 0.0], [0.0, 1.0]])
    _cast_rays(np.zeros(2), dirs, segs, 10.0)
    _nearest_segment(np.array([[1.1, 0.0], [0.0, 0.0]]), segs, 0.0)
    xy = np.column_stack([np.linspace(0, 1, 8), np.zeros(8)])
    se = _grow_segments(xy, np.full(8, 0.01), np.full(8, 1.0), 3, 2, 3)
    _split_segments(xy, np.ascontiguousarray(se), np.full(len(se), 1e-4), 30.0, 3)
