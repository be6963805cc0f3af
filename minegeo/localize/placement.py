"""Stage 6 of :func:`~minegeo.localize.localize_scan`: the pose and trajectory in the map and the CRS.

``T_map_sensor(τ) = T_map_scan · T_scan_sensor(τ)`` ([Baek2022 Eq. 18]); the ``geo`` / CRS poses
go through the map's georeferencing (:func:`~minegeo.georef.pose_to_crs`: the position
through the similarity, the orientation through its rotation only, so the pose stays rigid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import InputError
from minegeo.geometry.se3 import hat
from minegeo.georef import pose_to_crs
from minegeo.io.types import Trajectory
from minegeo.localize.prepared import PreparedMap

__all__ = ["Placement", "place"]


@dataclass
class Placement:
    """Outcome of :func:`place` (``LocalizationResult`` fields of the same names).

    Attributes
    ----------
    T_geo_scan, T_crs_scan : (4, 4) ndarray or None
        Scan → ``geo`` (CRS minus ``georef_origin``) and → full CRS coordinates.
    georef_origin : (3,) ndarray or None
    crs : str or None
    trajectory_map, trajectory_geo : Trajectory or None
        The sensor trajectory in the map and the CRS ([Baek2022 Eq. 18]).
    trajectory_sigma_m : (m,) ndarray or None
        1-σ 3-D position uncertainty of each pose from the pose covariance, m.
    warnings : list of str
    """

    T_geo_scan: np.ndarray | None = None
    T_crs_scan: np.ndarray | None = None
    georef_origin: np.ndarray | None = None
    crs: str | None = None
    trajectory_map: Trajectory | None = None
    trajectory_geo: Trajectory | None = None
    trajectory_sigma_m: np.ndarray | None = None
    warnings: list = field(default_factory=list)


def _trajectory_sigma(T_map_scan: np.ndarray, Tm: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """1-σ position uncertainty of each placed pose (m): ``dp = −[p − o]× ω + t`` for a
    perturbation ``(ω, t)`` about the scan origin ``o``."""
    o_map = T_map_scan[:3, :3] @ np.zeros(3) + T_map_scan[:3, 3]
    d = Tm[:, :3, 3] - o_map
    sigma = np.empty(d.shape[0])
    for i, di in enumerate(d):
        J = np.hstack([-hat(di), np.eye(3)])
        sigma[i] = math.sqrt(max(float(np.trace(J @ cov @ J.T)), 0.0))
    return sigma


def place(T_map_scan: np.ndarray, pm: PreparedMap, trajectory, cov: np.ndarray | None) -> Placement:
    """The scan pose in the ``geo`` frame and the CRS, and the trajectory ``T_scan_sensor`` (scan
    frame) moved into the map and the CRS with [Baek2022 Eq. 18], with its per-pose σ under
    ``cov`` (``covariance_6x6``; None: no σ)."""
    out = Placement(crs=pm.crs)
    g = pm.georef_result
    if g is not None:
        out.T_geo_scan = pose_to_crs(T_map_scan, g, allow_failed=True)
        out.T_crs_scan = out.T_geo_scan.copy()
        out.T_crs_scan[:3, 3] += g.origin
        out.georef_origin = np.asarray(g.origin, dtype=np.float64)
        if g.status == "failed":
            out.warnings.append("the map's georeferencing is marked failed: CRS coordinates are not reliable")
    elif out.crs:
        out.T_crs_scan = T_map_scan.copy()
    if trajectory is None:
        return out
    if not isinstance(trajectory, Trajectory):
        raise InputError(f"trajectory must be a Trajectory, got {type(trajectory).__name__}")
    poses = np.asarray(trajectory.poses, dtype=np.float64).copy()
    poses[:, :3, 3] += np.asarray(trajectory.origin, dtype=np.float64)
    Tm = np.einsum("ij,njk->nik", T_map_scan, poses)
    out.trajectory_map = Trajectory(times_s=np.asarray(trajectory.times_s, dtype=np.float64).copy(), poses=Tm,
                                    frame="map", body=trajectory.body)
    if g is not None:
        Tg = pose_to_crs(Tm, g, allow_failed=True)
        out.trajectory_geo = Trajectory(times_s=out.trajectory_map.times_s.copy(), poses=Tg, frame="crs",
                                        body=trajectory.body, origin=np.asarray(g.origin, dtype=np.float64).copy(),
                                        crs=g.crs)
    if cov is not None:
        out.trajectory_sigma_m = _trajectory_sigma(T_map_scan, Tm, cov)
    return out
