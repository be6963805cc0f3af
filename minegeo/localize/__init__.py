"""minegeo.localize: georeferencing a map and global localization of scans in it."""

from minegeo.localize.crs import CRSInfo, crs_info, local_origin, validate_crs
from minegeo.localize.georef import (
    GeorefParams,
    GeorefResult,
    apply_georef,
    crs_to_map,
    georeference,
    load_georeferenced_map,
    map_to_crs,
    point_covariance_crs,
    pose_to_crs,
    read_georef,
    sidecar_path,
    write_georeferenced_map,
)

__all__ = [
    "CRSInfo",
    "crs_info",
    "local_origin",
    "validate_crs",
    "GeorefParams",
    "GeorefResult",
    "apply_georef",
    "crs_to_map",
    "georeference",
    "load_georeferenced_map",
    "map_to_crs",
    "point_covariance_crs",
    "pose_to_crs",
    "read_georef",
    "sidecar_path",
    "write_georeferenced_map",
]


def _warmup() -> None:
    """Georeferencing has no Numba kernels (small dense LSQ); the localization pipeline adds its own."""
    return None
