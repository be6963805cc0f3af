"""A georeferenced map on disk: the cloud file and its ``<MAP_GEO>.georef.json`` sidecar.

PLY/PCD/text clouds store the ``geo`` coordinates (CRS − origin) with the origin in the header;
LAS/LAZ store full CRS coordinates as integers with the origin as the LAS offset. The sidecar
(format ``minegeo-georef``, version 1) holds ``T_crs_map``, ``T_geo_map``, the origin, the CRS, the
full fit record (:meth:`~minegeo.georef.result.GeorefResult.as_dict`, without timings, so it is
bit-identical for the same inputs) and the SHA-256 of the written cloud, so a reader detects a
sidecar that no longer matches its cloud.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.georef.crs import same_crs
from minegeo.georef.result import GeorefResult
from minegeo.io.types import PointCloud

__all__ = [
    "SIDECAR_FORMAT",
    "SIDECAR_VERSION",
    "sidecar_path",
    "write_georeferenced_map",
    "read_georef",
    "read_georef_sidecar",
    "load_georeferenced_map",
]

#: ``format`` tag of the sidecar JSON
SIDECAR_FORMAT = "minegeo-georef"
SIDECAR_VERSION = 1


def sidecar_path(map_path) -> Path:
    """Sidecar of a georeferenced map: ``<MAP_GEO>.georef.json`` (e.g. ``map_geo.ply.georef.json``)."""
    p = Path(map_path)
    return p.parent / (p.name + ".georef.json")  # not with_name: it raises for "." (empty name)


def write_georeferenced_map(path, cloud_geo: PointCloud, result: GeorefResult, *, extra: dict | None = None) -> tuple:
    """Write a georeferenced cloud and its sidecar ``<path>.georef.json``, atomically.

    PLY/PCD/XYZ/CSV store the ``geo`` coordinates (CRS − origin) with the origin recorded in
    the header (``comment minegeo origin E N H``); LAS/LAZ store full CRS coordinates as
    integers with the origin as the LAS offset (1 mm resolution). The sidecar holds
    ``T_crs_map``, ``T_geo_map``, the origin, the CRS, the full fit statistics
    (:meth:`GeorefResult.as_dict`) and the SHA-256 of the written cloud, so
    :func:`load_georeferenced_map` can detect a sidecar that no longer matches its cloud.

    Returns
    -------
    (Path, Path)
        The cloud file and the sidecar.
    """
    from minegeo.io import write_point_cloud

    if not isinstance(result, GeorefResult):
        raise InputError(f"result must be a GeorefResult, got {type(result).__name__}")
    if not np.array_equal(cloud_geo.origin, result.origin):
        raise InputError("the cloud is not in the georeferenced frame of this result (origins differ): use apply_georef")
    p = Path(path)
    fmt = p.suffix.lower().lstrip(".")
    if fmt in ("las", "laz"):
        write_point_cloud(p, cloud_geo, las_offset=result.origin)
    else:
        write_point_cloud(p, cloud_geo, coordinates="local")
    return p, _write_sidecar(p, result, extra)


def _write_sidecar(p: Path, result: GeorefResult, extra: dict | None) -> Path:
    """The ``<p>.georef.json`` of a written georeferenced cloud ``p`` (see :func:`write_georeferenced_map`)."""
    from minegeo._provenance import sha256_file, write_json_atomic

    side = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "map_file": p.name,
        "map_sha256": sha256_file(p),
        "crs": result.crs,
        "origin": result.origin.tolist(),
        "T_crs_map": result.T_crs_map.tolist(),
        "T_geo_map": result.T_geo_map.tolist(),
        "frames": "points in the file are geo = CRS - origin (PLY/PCD/text) or full CRS (LAS); "
        "T_crs_map maps the original map frame into the CRS",
        # no timings: the sidecar is bit-identical for the same inputs (timings are in result.json)
        "georef": {k: v for k, v in result.as_dict().items() if k != "timings_s"},
    }
    if extra:
        side.update(extra)
    return write_json_atomic(sidecar_path(p), side)



def read_georef(path) -> GeorefResult:
    """Read a :class:`GeorefResult` from a ``.georef.json`` sidecar or a ``georef`` ``result.json``."""
    from minegeo.io.jsonio import load_json_file

    p = Path(path)
    d = load_json_file(p, what="georeferencing record")  # bounded, no duplicate keys, no NaN
    if isinstance(d, dict) and "georef" in d and isinstance(d["georef"], dict):
        d = d["georef"]
    elif isinstance(d, dict) and "result" in d and isinstance(d["result"], dict):
        d = d["result"]
    try:
        return GeorefResult.from_dict(d)
    except InputError as exc:
        raise FileFormatError(p, str(exc)) from None


def read_georef_sidecar(path, *, check_hash: bool = True) -> tuple:
    """The checks of :func:`load_georeferenced_map` without reading the cloud: ``(cloud path,
    sidecar path, GeorefResult)`` (for chunked reading of large maps, see
    :func:`minegeo.localize.prepared.prepare_map_file`). Raises as :func:`load_georeferenced_map`."""
    from minegeo._provenance import sha256_file
    from minegeo.io.jsonio import load_json_file

    p = Path(path)
    if p.name.endswith(".georef.json"):
        side_p = p
        cloud_p = p.with_name(p.name[: -len(".georef.json")])
    else:
        cloud_p = p
        side_p = sidecar_path(p)
    if not side_p.exists():
        raise FileFormatError(
            cloud_p,
            f"no georeferencing sidecar {side_p.name} next to the map: georeference it with "
            "'minegeo georef --map MAP --gcps GCPS.csv --crs EPSG:xxxx --out MAP_GEO'",
        )
    side = load_json_file(side_p, what="georeferencing sidecar")  # bounded, no duplicate keys, no NaN
    if not isinstance(side, dict) or side.get("format") != SIDECAR_FORMAT:
        raise FileFormatError(side_p, f"not a minegeo georeferencing sidecar (format != {SIDECAR_FORMAT!r})")
    if int(side.get("version", 0)) > SIDECAR_VERSION:
        raise FileFormatError(side_p, f"sidecar version {side.get('version')} is newer than this minegeo")
    if not cloud_p.exists():
        raise FileFormatError(side_p, f"the georeferenced map {cloud_p} named by this sidecar does not exist")
    if check_hash and side.get("map_sha256") and sha256_file(cloud_p) != side["map_sha256"]:
        raise FileFormatError(
            cloud_p,
            "the map file changed after it was georeferenced (SHA-256 differs from the sidecar): re-run minegeo georef",
        )
    try:
        result = GeorefResult.from_dict(side["georef"])
    except (KeyError, InputError) as exc:
        raise FileFormatError(side_p, f"bad georeferencing record: {exc}") from None
    from minegeo.errors import CRSError
    from minegeo.georef.crs import validate_crs

    try:  # the CRS a map claims must be one pyproj knows and minegeo can work in
        validate_crs(result.crs)
    except CRSError as exc:
        raise FileFormatError(side_p, f"the sidecar's CRS cannot be used: {exc}") from None
    return cloud_p, side_p, result


def load_georeferenced_map(path, *, check_hash: bool = True) -> tuple:
    """Load a map written by ``minegeo georef`` (or :func:`write_georeferenced_map`).

    Parameters
    ----------
    path : str or Path
        The georeferenced cloud (``map_geo.ply``) or its sidecar (``map_geo.ply.georef.json``).
    check_hash : bool
        Verify the cloud's SHA-256 against the sidecar (a modified cloud is an error).

    Returns
    -------
    (PointCloud, GeorefResult)
        The cloud with ``points`` relative to ``result.origin`` (``cloud.origin``), ``crs`` and
        ``frame = "crs"``; and the georeferencing (``T_crs_map``, ``T_geo_map``, ``origin``,
        ``crs``, statistics).

    Raises
    ------
    FileFormatError
        Missing/invalid sidecar, hash mismatch, or a cloud whose recorded CRS differs.
    """
    from minegeo.io import read_point_cloud

    cloud_p, side_p, result = read_georef_sidecar(path, check_hash=check_hash)
    cloud = read_point_cloud(cloud_p, origin=result.origin)
    if cloud.crs and not same_crs(str(cloud.crs), result.crs):
        raise FileFormatError(cloud_p, f"the file says CRS {cloud.crs} but its sidecar says {result.crs}")
    cloud.crs = result.crs
    cloud.frame = "crs"
    cloud.metadata["georef_sidecar"] = str(side_p)
    return cloud, result
