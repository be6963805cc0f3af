"""Stage 1 of :func:`~minegeo.localize.localize_scan`: the scan's features, and the scan frames.

Frames (module docstring of :mod:`minegeo.localize.pipeline`): the scan frame is
``scan_origin + points``; every stage works on the origin-subtracted points
``D = p_scan − scan_origin`` and on the map's ``work`` frame (``p_work = p_map − work_origin``).
A stage's placement ``T`` maps ``D`` into ``work``; :func:`to_map` / :func:`from_map` convert it
to and from ``T_map_scan`` (``p_map = R p_scan + t``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import InputError, TooFewPointsError
from minegeo.geometry import voxel_downsample
from minegeo.io.types import PointCloud
from minegeo.localize._progress import FEATURE_STEPS, StepTimings
from minegeo.localize.params import LocalizeParams
from minegeo.localize.prepared import prepare_cloud_features
from minegeo.localize.run_context import RunContext

__all__ = ["ScanFeatures", "scan_features", "scan_points", "to_map", "from_map"]


@dataclass(frozen=True)
class ScanFeatures:
    """The scan as every later stage sees it (all points relative to ``scan_origin``, m).

    Attributes
    ----------
    points : (n, 3) ndarray
        Every scan point read, ``p_scan − scan_origin``.
    scan_origin : (3,) ndarray
        Origin of the scan frame (``PointCloud.origin``; zeros for a bare array).
    feature_points, feature_normals, fpfh : ndarray
        Feature-level points (the scan downsampled by ``scan_voxel_size_m`` / ``scan_octree_level``),
        their normals ([Baek2022 Eq. 2]) and FPFH descriptors ([Baek2022 Eqs. 3-6]).
    icp_points : (m, 3) ndarray
        ICP-level points (voxel centroids at ``scan_icp_voxel_size_m``, or every point).
    centre : (3,) ndarray
        Centroid of ``feature_points``: the point about which placements are compared
        (:func:`~minegeo.registration.ransac.hypothesis_distance`).
    small_scan : bool
        Fewer feature-level points than ``LocalizeParams.ambiguity.small_scan_below_points``
        (a small scan: narrower ambiguity margins, unscreened ICP).
    """

    points: np.ndarray
    scan_origin: np.ndarray
    feature_points: np.ndarray
    feature_normals: np.ndarray
    fpfh: np.ndarray
    icp_points: np.ndarray
    centre: np.ndarray
    small_scan: bool


def scan_points(scan) -> tuple[np.ndarray, np.ndarray]:
    """(points relative to the scan's origin, the origin) — the scan frame is origin + points."""
    if isinstance(scan, PointCloud):
        pts, org = scan.points, np.asarray(scan.origin, dtype=np.float64)
    else:
        pts, org = scan, np.zeros(3)
    P = np.asarray(pts, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"scan points must have shape (n, 3), got {P.shape}")
    if P.shape[0] == 0:
        raise TooFewPointsError("the scan is empty: there is nothing to localize")
    return as_points(P, "scan points", min_points=1), org


def scan_features(scan_cloud, p: LocalizeParams, run: RunContext) -> ScanFeatures:
    """Downsample the scan, its normals and FPFH (the map's feature settings), and its ICP cloud.

    Records ``downsample``, ``normals`` and ``fpfh`` seconds in ``run.timings``.

    Raises
    ------
    TooFewPointsError
        Fewer than ``p.min_scan_points`` points after downsampling, or no FPFH descriptor.
    """
    P_raw, scan_origin = scan_points(scan_cloud)
    run.announce("downsample")
    feat_t = StepTimings(run.progress, FEATURE_STEPS)
    D, Nd, F = prepare_cloud_features(P_raw, p.scan_voxel_size_m, p.scan_octree_level, p.features, feat_t)
    timings = run.timings
    timings.update(feat_t)
    if D.shape[0] < p.min_scan_points:
        raise TooFewPointsError(
            f"the scan has only {D.shape[0]} points after downsampling ({p.describe_downsampling()}; "
            f"{P_raw.shape[0]} read); at least {p.min_scan_points} are needed to localize it"
        )
    if np.count_nonzero(np.any(F != 0.0, axis=1)) < p.ransac.ransac_n:
        raise TooFewPointsError(
            f"the scan's points are too sparse for FPFH within {p.features.fpfh_radius_m} m: no descriptor to match"
        )
    # the scan frame is scan_origin + points; keep D relative to scan_origin, fold it into T at the end
    t0 = time.perf_counter()
    if p.scan_icp_voxel_size_m is None:
        Dfine = P_raw
    else:
        Dfine = np.ascontiguousarray(voxel_downsample(P_raw, float(p.scan_icp_voxel_size_m)).points)
    timings["downsample"] += time.perf_counter() - t0
    return ScanFeatures(points=P_raw, scan_origin=scan_origin, feature_points=D, feature_normals=Nd, fpfh=F,
                        icp_points=Dfine, centre=D.mean(axis=0),
                        small_scan=D.shape[0] < int(p.ambiguity.small_scan_below_points))


def to_map(T_work_D: np.ndarray, scan_origin: np.ndarray, work_origin: np.ndarray) -> np.ndarray:
    """``T_map_scan`` from a transform of the origin-subtracted scan ``D = scan − scan_origin`` into ``work``.

    ``p_work = R (p_scan − o_s) + t``  ⇒  ``p_map = R p_scan + (t − R o_s + o_w)``.
    """
    T = np.array(T_work_D, dtype=np.float64, copy=True)
    T[:3, 3] = T[:3, 3] - T[:3, :3] @ scan_origin + work_origin
    return T


def from_map(T_map_scan, scan_origin: np.ndarray, work_origin: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_map`: a ``T_map_scan`` as a transform of ``D`` into ``work``."""
    T = np.array(T_map_scan, dtype=np.float64, copy=True)
    T[:3, 3] = T[:3, 3] + T[:3, :3] @ scan_origin - work_origin
    return T
