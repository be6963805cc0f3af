"""Map preparation for global localization: downsample, normals, FPFH, saved once (Baek et al. 2022, Sec. 2.2-2.3).

A *prepared map* holds everything of the prior map that the localization of a scan needs
and that does not depend on the scan: the downsampled map points (Sec. 2.2), their surface
normals ([Baek2022 Eq. 2]) and FPFH descriptors ([Baek2022 Eqs. 3-6]), in the **map frame** relative to a recorded
working origin, plus the georeferencing of the map (if any). It is computed once
(:func:`prepare_map`, ``minegeo prepare-map``) and stored as a NumPy ``.npz`` file without
pickles (:meth:`PreparedMap.save` / :meth:`PreparedMap.load`), carrying a format version and
a hash of the parameters; loading with other parameters is an error, so a scan is never
matched against features computed with different settings. Map *files* are prepared by
:func:`prepare_map_file`, which reads them in chunks (two passes, memory bounded by the
downsampled map plus one chunk) and gives the same arrays as :func:`prepare_map`, bit for bit.

Frames
------
``map``   the frame of the map *before* georeferencing (the ``map`` of ``T_crs_map``); for a
          map without georeferencing sidecar, the file's own coordinates.
``work``  ``map`` minus ``work_origin`` (a rounded point near the map's centre): all
          arrays of a :class:`PreparedMap` are in this frame (float64 precision for any map).
``geo``   CRS minus the georeferencing origin (see :mod:`minegeo.georef`).

Normal orientation
------------------
FPFH depends on the signs of the normals, so the map and the scan must be oriented by the
same rotation-invariant rule. Default ``"void"``: each normal is flipped to point towards
the centroid of the points within a cube of half-edge ``orientation_radius_m`` around it
(for a drift wider than a few metres this is the drift's interior, the air side where the
scanner was). ``"none"`` keeps the PCA solver's sign (Open3D's behaviour, not rotation
invariant); ``"centroid"`` orients towards the whole cloud's centroid.

Modules
-------
:mod:`~minegeo.localize.prepared.model`    :class:`PreparedMap`, its parameters hash, saving and loading;
:mod:`~minegeo.localize.prepared.store`    the ``.npz`` format: constants, integrity manifest, checked reading;
:mod:`~minegeo.localize.prepared.indexes`  restoring and checking the stored search indexes;
:mod:`~minegeo.localize.prepared.build`    :func:`prepare_map`, :func:`prepare_map_file`, the cache.
Every public name of these modules is importable from this package.
"""

from __future__ import annotations

from minegeo.localize.params import FAST_FEATURES, FeatureParams, PrepareParams
from minegeo.localize.prepared.build import (
    CHUNK_BYTES_PER_POINT,
    FEATURE_BYTES_PER_POINT,
    ICP_BYTES_PER_POINT,
    ICP_NORMAL_NN,
    MIN_CHUNK_POINTS,
    MemoryLimitError,
    cache_path,
    is_georeferenced,
    is_prepared_file,
    load_map_cloud,
    load_or_prepare,
    orient_normals_void,
    prepare_cloud_features,
    prepare_map,
    prepare_map_file,
)
from minegeo.localize.prepared.model import PreparedMap, params_hash, profile_name
from minegeo.localize.prepared.store import (
    CORE_ARRAYS,
    FPFH_DIM,
    INDEX_PREFIX,
    INDEX_VERSION,
    INTEGRITY_ALGORITHM,
    PREPARED_FORMAT,
    PREPARED_VERSION,
)

__all__ = [
    "FeatureParams",
    "PrepareParams",
    "PreparedMap",
    "prepare_map",
    "prepare_map_file",
    "MemoryLimitError",
    "prepare_cloud_features",
    "orient_normals_void",
    "params_hash",
    "cache_path",
    "PREPARED_FORMAT",
    "PREPARED_VERSION",
    "FAST_FEATURES",
    "profile_name",
    "is_georeferenced",
    "is_prepared_file",
    "load_map_cloud",
    "load_or_prepare",
    "CORE_ARRAYS",
    "FPFH_DIM",
    "INDEX_PREFIX",
    "INDEX_VERSION",
    "INTEGRITY_ALGORITHM",
    "ICP_NORMAL_NN",
    "CHUNK_BYTES_PER_POINT",
    "FEATURE_BYTES_PER_POINT",
    "ICP_BYTES_PER_POINT",
    "MIN_CHUNK_POINTS",
]
