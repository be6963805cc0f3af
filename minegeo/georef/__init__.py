"""minegeo.georef: georeferencing a map from ground control points, and the CRS it lives in.

* :mod:`~minegeo.georef.crs`: projected CRSs through pyproj, the recorded local origin, grid scale factors;
* :mod:`~minegeo.georef.fit`: the control-point fit (similarity / rigid), its statistics and blunder checks;
* :mod:`~minegeo.georef.result`: its parameters (:class:`GeorefParams`) and result record (:class:`GeorefResult`);
* :mod:`~minegeo.georef.apply`: the transformation applied to points, poses and maps (streamed for large maps);
* :mod:`~minegeo.georef.sidecar`: the georeferenced map on disk with its ``.georef.json`` sidecar.

It sits beside :mod:`minegeo.survey` (whose Helmert adjustment it calls) and below
:mod:`minegeo.localize`, which places its results in the CRS through it; it never imports a
package above it.
"""

from minegeo.georef.apply import (
    REPORT_CLOUD_POINTS,
    apply_georef,
    crs_to_map,
    map_to_crs,
    point_covariance_crs,
    pose_to_crs,
    report_sample_rows,
    stream_georeferenced_las,
    stream_georeferenced_map,
)
from minegeo.georef.crs import (
    CRSInfo,
    crs_info,
    grid_scale_factors,
    local_origin,
    outside_area_of_use,
    same_crs,
    validate_crs,
)
from minegeo.georef.fit import georeference, unit_diagnosis
from minegeo.georef.result import GeorefParams, GeorefResult, GeorefStatus
from minegeo.georef.sidecar import (
    SIDECAR_FORMAT,
    SIDECAR_VERSION,
    load_georeferenced_map,
    read_georef,
    read_georef_sidecar,
    sidecar_path,
    write_georeferenced_map,
)

__all__ = [
    "CRSInfo",
    "crs_info",
    "grid_scale_factors",
    "local_origin",
    "outside_area_of_use",
    "same_crs",
    "validate_crs",
    "GeorefParams",
    "GeorefResult",
    "GeorefStatus",
    "georeference",
    "unit_diagnosis",
    "apply_georef",
    "crs_to_map",
    "map_to_crs",
    "point_covariance_crs",
    "pose_to_crs",
    "REPORT_CLOUD_POINTS",
    "report_sample_rows",
    "stream_georeferenced_las",
    "stream_georeferenced_map",
    "SIDECAR_FORMAT",
    "SIDECAR_VERSION",
    "load_georeferenced_map",
    "read_georef",
    "read_georef_sidecar",
    "sidecar_path",
    "write_georeferenced_map",
]
