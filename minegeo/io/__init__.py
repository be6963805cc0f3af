"""minegeo.io: point clouds, trajectories and ground control points.

Point clouds: PLY, PCD (incl. LZF ``binary_compressed``), LAS/LAZ (optional laspy),
XYZ/TXT/CSV, Leica PTS, 3DTK ``.3d``, E57 (optional pye57: scans merged by their poses);
``.zip`` holding one of them. DXF drawings for CAD: :mod:`minegeo.io.dxf` (optional ezdxf). Trajectories: TUM,
KITTI, GeoSLAM-style text, CSV. Control points: CSV. See ``docs/io.md``.

The reading helpers other packages share are public modules: :mod:`minegeo.io.limits` (bounded
reads of regular files, coordinate and time ranges), :mod:`minegeo.io.jsonio` (the one JSON loader),
:mod:`minegeo.io.npzstore` (minegeo's checked ``.npz`` stores), :mod:`minegeo.io.text` (numeric text
tables) and :mod:`minegeo.io.angles` (angle tokens of survey files).
"""

from minegeo.io._quat import matrix_to_quat, quat_to_matrix
from minegeo.io.e57 import e57_scan_poses, iter_e57_chunks, read_e57
from minegeo.io.gcp import read_gcps, write_gcps
from minegeo.io.pointcloud import cloud_info, read_point_cloud, write_point_cloud
from minegeo.io.trajectory import read_trajectory, read_transform, write_trajectory
from minegeo.io.types import ControlPoints, PointCloud, Trajectory

__all__ = [
    "PointCloud",
    "Trajectory",
    "ControlPoints",
    "read_point_cloud",
    "write_point_cloud",
    "cloud_info",
    "read_e57",
    "e57_scan_poses",
    "iter_e57_chunks",
    "read_trajectory",
    "write_trajectory",
    "read_transform",
    "read_gcps",
    "write_gcps",
    "quat_to_matrix",
    "matrix_to_quat",
]


def _warmup() -> None:
    """Compile the LZF kernels (PCD binary_compressed) and the text parser on tiny inputs."""
    from minegeo.io._lzf import lzf_compress, lzf_decompress
    from minegeo.io.text import parse_table

    data = bytes(range(64)) * 4
    lzf_decompress(lzf_compress(data), len(data))
    parse_table("warmup", "1 2.5 -3e2\n", ncols=3, first_line=1)
