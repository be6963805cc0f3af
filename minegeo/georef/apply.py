"""Applying a georeferencing: points, poses and maps from the ``map`` frame into the CRS.

Frames (see :class:`~minegeo.georef.result.GeorefResult`): ``map`` (the map's own coordinates, m),
``crs`` (E, N, H of the CRS, m) and ``geo = crs − origin`` (the recorded local origin). Points go
through the full similarity ``p_geo = s·R·p_map + t_geo`` (:func:`map_to_crs`, inverse
:func:`crs_to_map`); poses keep their rotation rigid (:func:`pose_to_crs`); a cloud is stored in the
``geo`` frame with the origin recorded (:func:`apply_georef`), so the large CRS numbers are never
added to the points. :func:`stream_georeferenced_map` and :func:`stream_georeferenced_las` apply
and write a map chunk by chunk (memory: one chunk) with the bytes of the whole-file path; the
written map gets its sidecar from :mod:`minegeo.georef.sidecar`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.geometry.se3 import hat
from minegeo.georef.result import GeorefResult
from minegeo.georef.sidecar import _write_sidecar
from minegeo.io.types import PointCloud

__all__ = [
    "apply_georef",
    "map_to_crs",
    "crs_to_map",
    "pose_to_crs",
    "point_covariance_crs",
    "REPORT_CLOUD_POINTS",
    "report_sample_rows",
    "stream_georeferenced_map",
    "stream_georeferenced_las",
]


def _check_usable(result: GeorefResult, allow_failed: bool) -> None:
    if not isinstance(result, GeorefResult):
        raise InputError(f"result must be a GeorefResult, got {type(result).__name__}")
    if result.status == "failed" and not allow_failed:
        raise InputError(f"the georeferencing failed and must not be applied: {result.reason}")


def map_to_crs(points_map, result: GeorefResult, map_origin=None, *, allow_failed: bool = False) -> np.ndarray:
    """Map coordinates -> CRS coordinates **relative to** ``result.origin`` (the ``geo`` frame).

    ``p_geo = s·R·(p + o_map) + t_geo = s·R·p + (s·R·o_map + t_geo)``; add ``result.origin``
    for full CRS coordinates (only when printing: the sum loses precision at ~1e-9 m).
    """
    _check_usable(result, allow_failed)
    p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
    A = result.T_geo_map[:3, :3]
    b = result.T_geo_map[:3, 3]
    if map_origin is not None:
        b = A @ np.asarray(map_origin, dtype=np.float64).reshape(3) + b
    return p @ A.T + b


def crs_to_map(points_geo, result: GeorefResult, map_origin=None, *, allow_failed: bool = False) -> np.ndarray:
    """Inverse of :func:`map_to_crs`: ``geo`` coordinates (CRS − ``result.origin``) -> map coordinates.

    ``p_map = Rᵀ(p_geo − t_geo)/s − o_map`` (``o_map`` = the map cloud's own origin, if any).
    """
    _check_usable(result, allow_failed)
    q = np.asarray(points_geo, dtype=np.float64).reshape(-1, 3)
    p = (q - result.T_geo_map[:3, 3]) @ result.R / result.scale
    if map_origin is not None:
        p = p - np.asarray(map_origin, dtype=np.float64).reshape(3)
    return p


def pose_to_crs(T_map_body, result: GeorefResult, *, allow_failed: bool = False) -> np.ndarray:
    """Express body poses (sensor, vehicle) given in the map frame in the ``geo`` frame.

    ``T_geo_body = [[R·R_map_body, s·R·t_map_body + t_geo], [0, 1]]``: the position goes through
    the full similarity, the orientation only through the rotation ``R`` — a pose stays rigid even
    when the map-to-CRS scale ``s != 1``. Add ``result.origin`` to the translation for full CRS
    coordinates (printing only).

    Parameters
    ----------
    T_map_body : array_like (4, 4) or (m, 4, 4)
    result : GeorefResult

    Returns
    -------
    ndarray (4, 4) or (m, 4, 4)
        ``T_geo_body``.
    """
    _check_usable(result, allow_failed)
    T = np.asarray(T_map_body, dtype=np.float64)
    single = T.ndim == 2
    T = T.reshape(-1, 4, 4)
    if not np.isfinite(T).all():
        raise InputError("T_map_body contains NaN or inf")
    out = np.zeros_like(T)
    out[:, :3, :3] = np.einsum("ij,mjk->mik", result.R, T[:, :3, :3])
    out[:, :3, 3] = T[:, :3, 3] @ result.T_geo_map[:3, :3].T + result.T_geo_map[:3, 3]
    out[:, 3, 3] = 1.0
    return out[0] if single else out


def apply_georef(cloud: PointCloud, result: GeorefResult, *, allow_failed: bool = False) -> PointCloud:
    """Transform a map cloud into the CRS, stored relative to the recorded origin.

    Parameters
    ----------
    cloud : PointCloud
        The map (``points + cloud.origin`` are map coordinates, metres).
    result : GeorefResult
        From :func:`georeference`; a ``failed`` result is refused unless ``allow_failed``.

    Returns
    -------
    PointCloud
        ``points`` in the ``geo`` frame (CRS minus ``result.origin``), ``origin =
        result.origin``, ``crs = result.crs``, ``frame = "crs"``; normals rotated by ``R``;
        attributes copied. ``global_points`` gives full E, N, H. No precision is lost: the
        only large number, the origin, is never added to the points.
    """
    if not isinstance(cloud, PointCloud):
        raise InputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
    pts = map_to_crs(cloud.points, result, cloud.origin, allow_failed=allow_failed)
    normals = None if cloud.normals is None else cloud.normals @ result.R.T
    meta = dict(cloud.metadata)
    meta["georef"] = {
        "T_crs_map": result.T_crs_map.tolist(),
        "origin": result.origin.tolist(),
        "crs": result.crs,
        "model": result.model,
        "status": result.status,
    }
    return PointCloud(
        points=pts,
        normals=normals,
        attributes={k: np.array(v, copy=True) for k, v in cloud.attributes.items()},
        origin=result.origin.copy(),
        crs=result.crs,
        frame="crs",
        metadata=meta,
    )


def point_covariance_crs(points_map, result: GeorefResult) -> np.ndarray:
    """Covariance (m²) of transformed points due to the uncertainty of the transformation.

    ``X = T + s·exp([δ]×)·R·x`` gives the Jacobian ``J = [I, −s[R x]×, R x]`` with respect to
    ``(T, δ, ds)``; ``Σ_X = J Σ Jᵀ`` (first-order propagation; the map coordinates are taken as
    errorless). Returns ``(m, 3, 3)`` for ``m`` points given in map coordinates.
    """
    x = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
    C = result.cov
    u = C.shape[0]
    out = np.empty((x.shape[0], 3, 3))
    for i, xi in enumerate(x):
        rx = result.R @ xi
        J = np.zeros((3, u))
        J[:, :3] = np.eye(3)
        J[:, 3:6] = -result.scale * hat(rx)
        if u == 7:
            J[:, 6] = rx
        out[i] = J @ C @ J.T
    return out


#: Points of the map kept for the report's plan view (:func:`minegeo.report.georef_report.plot_georef_png`).
REPORT_CLOUD_POINTS = 20000


def report_sample_rows(n: int, max_points: int = REPORT_CLOUD_POINTS, seed: int = 0) -> np.ndarray:
    """Rows of an ``n``-point map that the report's plot draws (its own subsampling rule), sorted."""
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


class _ChunkSample:
    """The rows :func:`report_sample_rows` of a georeferenced map written chunk by chunk, and the
    count of its points (checked against pass 1 at the end)."""

    def __init__(self, n_points: int):
        self.n_points = int(n_points)
        self.rows = report_sample_rows(self.n_points)
        self.points = np.empty((self.rows.size, 3))
        self.done = 0

    def add(self, g: np.ndarray, chunks, progress) -> None:
        """Keep the sample rows of the next chunk ``g`` (CRS frame) and report progress."""
        lo, hi = np.searchsorted(self.rows, [self.done, self.done + g.shape[0]])
        self.points[lo:hi] = g[self.rows[lo:hi] - self.done]
        self.done += g.shape[0]
        if progress is not None:
            progress(chunks.bytes_read, chunks.size_bytes)

    def cloud(self, path, result: GeorefResult) -> PointCloud:
        """The sample as a cloud in the CRS; the map must have had ``n_points`` points."""
        if self.done != self.n_points:
            raise FileFormatError(path, f"the map changed while it was read ({self.n_points} then {self.done} points)")
        return PointCloud(points=self.points, origin=result.origin.copy(), crs=result.crs, frame="crs")


def stream_georeferenced_map(path, chunks, result: GeorefResult, n_points: int, *, allow_failed: bool = False,
                             extra: dict | None = None, progress=None) -> tuple:
    """:func:`apply_georef` + :func:`write_georeferenced_map` chunk by chunk, for a binary PLY output.

    The bytes written are those of ``write_georeferenced_map(path, apply_georef(cloud, result), ...)``
    for a cloud with x, y, z only (float64 binary little-endian PLY, ``geo`` coordinates with the
    origin in the header): the header of the same writer with the vertex count of the map, then
    each chunk through :func:`map_to_crs`. Memory: one chunk.

    Parameters
    ----------
    path : str or Path
        Output ``.ply`` (written in place: call it on a staged path, e.g. ``OutputTransaction.file``).
    chunks : PointChunks
        The map (:func:`minegeo.io.chunked.open_point_chunks`) opened with ``origin`` = the map
        cloud's local origin; every chunk is ``points`` of that cloud.
    result : GeorefResult
    n_points : int
        Points of the map (pass 1).
    allow_failed : bool
    extra : dict, optional
        Added to the sidecar.
    progress : callable, optional
        ``progress(bytes_read, size_bytes)`` after each chunk.

    Returns
    -------
    (Path, Path, PointCloud)
        The cloud file, the sidecar, and the rows :func:`report_sample_rows` of the
        georeferenced cloud (for the report's plot).
    """
    from minegeo.io.ply import write_ply_bytes

    _check_usable(result, allow_failed)
    p = Path(path)
    empty = PointCloud(points=np.zeros((0, 3)), origin=result.origin.copy(), crs=result.crs, frame="crs")
    head = write_ply_bytes(empty, coordinates="local")
    old = b"element vertex 0\n"
    if head.count(old) != 1:  # pragma: no cover - the writer's header layout changed
        raise InputError("internal error: unexpected PLY header layout for the chunked georeferenced map")
    head = head.replace(old, f"element vertex {int(n_points)}\n".encode("ascii"))
    sample = _ChunkSample(n_points)
    with open(p, "wb") as fh:
        fh.write(head)
        for c in chunks:
            g = map_to_crs(c, result, chunks.origin, allow_failed=allow_failed)
            fh.write(np.ascontiguousarray(g, dtype="<f8").tobytes())
            sample.add(g, chunks, progress)
    cloud = sample.cloud(chunks.path, result)
    return p, _write_sidecar(p, result, extra), cloud


def stream_georeferenced_las(path, chunks, result: GeorefResult, n_points: int, *, allow_failed: bool = False,
                             extra: dict | None = None, progress=None) -> tuple:
    """:func:`apply_georef` + :func:`write_georeferenced_map` chunk by chunk, LAS/LAZ in, LAS/LAZ out.

    Every record of the map is copied with **all its fields** (intensity, return numbers,
    classification, GPS time, colour, extra bytes) in the map's own point format and LAS version;
    only ``X, Y, Z`` change: ``X = round(p_geo / scale)`` with ``p_geo`` = :func:`map_to_crs` of
    the chunk and the header offset set to ``result.origin``, so the file holds full CRS
    coordinates ``X·scale + origin`` at the map's resolution (its own ``scale``), the same integers
    as the whole-file path writes (``write_georeferenced_map`` with ``las_offset = result.origin``
    and the scale the map was read with). The CRS record is replaced by ``result.crs``; the input's
    other VLRs are kept. Memory: one chunk.

    Parameters
    ----------
    path : str or Path
        Output ``.las`` or ``.laz`` (written in place: call it on a staged path).
    chunks : PointChunks
        The map (:func:`minegeo.io.chunked.open_point_chunks` of a LAS/LAZ file), ``origin`` set by
        pass 1; its chunks are the map cloud's ``points``.
    result : GeorefResult
    n_points : int
        Points of the map (pass 1).
    allow_failed : bool
    extra : dict, optional
        Added to the sidecar.
    progress : callable, optional
        ``progress(bytes_read, size_bytes)`` after each chunk.

    Returns
    -------
    (Path, Path, PointCloud)
        As :func:`stream_georeferenced_map`.
    """
    from minegeo.io.las import rewrite_las_xyz

    _check_usable(result, allow_failed)
    p = Path(path)
    src = Path(chunks.path)
    sample = _ChunkSample(n_points)
    it = iter(chunks)  # the coordinates, with every check of the chunked reader

    def integers(n_records: int, scale: np.ndarray) -> np.ndarray:
        """``X = round(p_geo / scale)`` of the next chunk (offset = ``result.origin``); keeps the report rows."""
        c = next(it)
        if c.shape[0] != n_records:  # pragma: no cover - both read the same file in the same chunks
            raise FileFormatError(src, "the map changed while it was read")
        g = map_to_crs(c, result, chunks.origin, allow_failed=allow_failed)
        Xf = np.round(g / scale)
        if Xf.size and (np.abs(Xf).max() > 2**31 - 1):
            raise InputError(f"the georeferenced coordinates do not fit LAS 32-bit integers at the map's "
                             f"scale {scale.tolist()} (the fit moves points by more than 2^31 units)")
        sample.add(g, chunks, progress)
        return Xf

    rewrite_las_xyz(src, p, integers, offsets=result.origin, crs=result.crs, chunk_points=chunks.chunk_points)
    cloud = sample.cloud(src, result)
    return p, _write_sidecar(p, result, extra), cloud
