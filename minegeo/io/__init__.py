"""minegeo.io: point clouds, trajectories and ground control points."""

from minegeo.io.types import ControlPoints, PointCloud, Trajectory

__all__ = ["PointCloud", "Trajectory", "ControlPoints"]
