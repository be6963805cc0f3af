"""Core data types: :class:`PointCloud`, :class:`Trajectory`, :class:`ControlPoints`.

Coordinates are float64. Projected coordinates (10^6-10^7 m) are stored relative to an
explicit local ``origin`` (``points_global = points + origin``) so that float64 keeps
sub-millimetre resolution in every computation; ``origin`` is recorded in every result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import InputError

__all__ = ["PointCloud", "Trajectory", "ControlPoints"]


@dataclass
class PointCloud:
    """A point cloud in one named frame.

    Attributes
    ----------
    points : (n, 3) float64
        Coordinates in metres, relative to ``origin``.
    normals : (n, 3) float64 or None
        Unit normals (frame of ``points``), if known.
    attributes : dict[str, ndarray]
        Per-point extra fields, each of length n: e.g. ``intensity``, ``rgb`` (n, 3) uint8,
        ``time_s`` (float64 seconds), ``ring`` (uint16), ``label``.
    origin : (3,) float64
        Local origin (m); global coordinates are ``points + origin``.
    crs : str or None
        Coordinate reference system, e.g. ``"EPSG:5186"``; None for a local frame.
    frame : str
        Name of the frame the points are expressed in (``"map"``, ``"scan"``, ``"sensor"``...).
    metadata : dict
        Free-form facts about where the cloud came from (not per point): e.g. ``format``,
        ``units`` (``"cm"`` for 3DTK scans), LAS ``las_scale``/``las_offset``, ``source``.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    crs: str | None = None
    frame: str = "local"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = as_points(self.points, "points", min_points=0)
        n = self.points.shape[0]
        if self.normals is not None:
            self.normals = np.ascontiguousarray(np.asarray(self.normals, dtype=np.float64))
            if self.normals.shape != (n, 3):
                raise InputError(f"normals must have shape ({n}, 3), got {self.normals.shape}")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        for k, v in list(self.attributes.items()):
            v = np.asarray(v)
            if v.shape[0] != n:
                raise InputError(f"attribute {k!r} has {v.shape[0]} rows, expected {n}")
            self.attributes[k] = v

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def global_points(self) -> np.ndarray:
        """Points in the full (e.g. projected CRS) coordinates: ``points + origin``."""
        return self.points + self.origin

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the axis-aligned bounding box, in local coordinates."""
        if len(self) == 0:
            raise InputError("empty point cloud has no bounds")
        return self.points.min(axis=0), self.points.max(axis=0)

    def select(self, index) -> PointCloud:
        """A new cloud with the rows ``index`` (boolean mask or integer indices)."""
        return PointCloud(
            points=self.points[index],
            normals=None if self.normals is None else self.normals[index],
            attributes={k: v[index] for k, v in self.attributes.items()},
            origin=self.origin.copy(),
            crs=self.crs,
            frame=self.frame,
            metadata=dict(self.metadata),
        )


@dataclass
class Trajectory:
    """A timed sequence of poses ``T_world_body`` (4x4), e.g. a sensor path.

    Attributes
    ----------
    times_s : (m,) float64
        Timestamps in seconds (strictly increasing is not enforced; KITTI has none: 0..m-1).
    poses : (m, 4, 4) float64
        ``T_<frame>_<body>``: maps body (sensor) coordinates into ``frame``.
    frame, body : str
        Names of the two frames, e.g. ``"map"`` and ``"sensor"``.
    origin : (3,) float64
        Local origin of the ``frame`` coordinates (as for :class:`PointCloud`).
    """

    times_s: np.ndarray
    poses: np.ndarray
    frame: str = "world"
    body: str = "sensor"
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    crs: str | None = None

    def __post_init__(self) -> None:
        self.times_s = np.ascontiguousarray(np.asarray(self.times_s, dtype=np.float64).reshape(-1))
        self.poses = np.ascontiguousarray(np.asarray(self.poses, dtype=np.float64))
        m = self.times_s.shape[0]
        if self.poses.shape != (m, 4, 4):
            raise InputError(f"poses must have shape ({m}, 4, 4), got {self.poses.shape}")
        if not (np.isfinite(self.poses).all() and np.isfinite(self.times_s).all()):
            raise InputError("trajectory contains NaN or inf")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)

    def __len__(self) -> int:
        return int(self.times_s.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """(m, 3) positions of the body origin in ``frame`` (local coordinates)."""
        return self.poses[:, :3, 3].copy()


@dataclass
class ControlPoints:
    """Ground control points: the same physical points in the local map frame and in a CRS.

    Attributes
    ----------
    ids : list[str]
    local_xyz : (k, 3) float64
        Coordinates in the map (local) frame, metres.
    crs_enh : (k, 3) float64
        Easting, northing, height in ``crs``, metres.
    sigma_enh_m : (k, 3) float64
        A-priori standard deviations of the CRS coordinates (m).
    sigma_local_m : (k, 3) float64 or None
        A-priori standard deviations of the local coordinates (m), if known.
    crs : str or None
        e.g. ``"EPSG:5186"``.
    """

    ids: list
    local_xyz: np.ndarray
    crs_enh: np.ndarray
    sigma_enh_m: np.ndarray
    sigma_local_m: np.ndarray | None = None
    crs: str | None = None

    def __post_init__(self) -> None:
        self.ids = [str(i) for i in self.ids]
        k = len(self.ids)
        self.local_xyz = as_points(self.local_xyz, "local_xyz", min_points=0)
        self.crs_enh = as_points(self.crs_enh, "crs_enh", min_points=0)
        self.sigma_enh_m = np.broadcast_to(np.asarray(self.sigma_enh_m, dtype=np.float64), (k, 3)).copy()
        if self.local_xyz.shape[0] != k or self.crs_enh.shape[0] != k:
            raise InputError("ids, local_xyz and crs_enh must have the same number of rows")
        if len(set(self.ids)) != k:
            raise InputError("control point ids must be unique")
        if self.sigma_local_m is not None:
            self.sigma_local_m = np.broadcast_to(
                np.asarray(self.sigma_local_m, dtype=np.float64), (k, 3)
            ).copy()

    def __len__(self) -> int:
        return len(self.ids)
