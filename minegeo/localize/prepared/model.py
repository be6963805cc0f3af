"""The prepared map (:class:`PreparedMap`): its arrays, parameters, lazily built indexes, and saving and loading."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes, to_jsonable
from minegeo._validate import as_points
from minegeo.errors import FileFormatError, InputError
from minegeo.localize._progress import announce
from minegeo.localize.params import FeatureParams, LocalizeParams, PrepareParams
from minegeo.localize.prepared.indexes import (
    _MAX_LOG2_SLOTS,
    _check_hash_table,
    _check_occupancy,
    _expand_occupancy,
    _expected_feature_rows,
    _grid_log2_start,
    _restore_kdtree,
    _restore_row_tree,
    _table_log2,
)
from minegeo.localize.prepared.store import (
    FPFH_DIM,
    INDEX_PREFIX,
    INDEX_VERSION,
    PREPARED_FORMAT,
    PREPARED_VERSION,
    _check_meta,
    _flag,
    _integer,
    _integrity_record,
    _number,
    _read_prepared_file,
    _stored,
    _verify_integrity,
)

#: the prepared map's one logger for all its modules (the CLI filters its summary line by this name)
log = logging.getLogger("minegeo.localize.prepared")


def params_hash(params: PrepareParams) -> str:
    """SHA-256 (hex) of the canonical JSON of ``params`` plus the file format version."""
    blob = json.dumps({"v": PREPARED_VERSION, "params": to_jsonable(asdict(params))}, sort_keys=True)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def _params_from_dict(d: dict) -> PrepareParams:
    f = dict(d["features"])
    return PrepareParams(voxel_size_m=d.get("voxel_size_m"), octree_level=d.get("octree_level"),
                         features=FeatureParams(**f), icp_voxel_size_m=d.get("icp_voxel_size_m"))


# ----------------------------------------------------------------------------- the prepared map
@dataclass
class PreparedMap:
    """A map ready for :func:`minegeo.localize.localize_scan`.

    Attributes
    ----------
    points : (m, 3) float64
        Downsampled map points in the ``work`` frame (map frame minus ``work_origin``), m.
    normals : (m, 3) float64
        Unit normals (oriented by ``params.features.orientation``).
    features : (m, 33) float64
        FPFH descriptors.
    icp_points : (k, 3) float64
        The ICP target (``params.icp_voxel_size_m`` voxel centroids, or every map point), work frame.
    icp_normals : (k, 3) float64
        PCA normals of ``icp_points`` (20 nearest neighbours), for point-to-plane ICP and the
        pose covariance.
    work_origin : (3,) float64
        Map-frame coordinates of the ``work`` frame's origin, m.
    params : PrepareParams
    params_hash : str
        :func:`params_hash` of ``params``.
    georef : dict or None
        The map's georeferencing record (``GeorefResult`` as a dict, from the sidecar) or
        None for a map without one; then ``crs`` is the cloud's own CRS, if any.
    crs : str or None
    source : dict
        ``{"path", "sha256", "n_points", "kind"}`` of the map file it was prepared from.
    timings_s : dict
        Seconds per preparation stage.
    """

    points: np.ndarray
    normals: np.ndarray
    features: np.ndarray
    icp_points: np.ndarray
    icp_normals: np.ndarray
    work_origin: np.ndarray
    params: PrepareParams
    params_hash: str
    georef: dict | None = None
    crs: str | None = None
    source: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    _kdtree: object = field(default=None, repr=False, compare=False)
    _georef_obj: object = field(default=None, repr=False, compare=False)
    _gicp_cache: dict = field(default_factory=dict, repr=False, compare=False)
    _occ_cache: dict = field(default_factory=dict, repr=False, compare=False)
    _feature_index: object = field(default=None, repr=False, compare=False)
    # search structures read from a file and checked, expanded on first use (``_restore_indexes``)
    _packed: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        # validated once here, so localization can search the map without re-scanning it
        # (``check_target=False``); the arrays must not be modified afterwards
        self.points = as_points(self.points, "prepared map points", min_points=1)
        m = self.points.shape[0]
        self.normals = as_points(self.normals, "prepared map normals", min_points=1)
        f = np.asarray(self.features)
        if f.ndim != 2:
            raise InputError(f"prepared map features must have shape (m, dim), got {f.shape}")
        self.features = as_points(f, "prepared map features", dim=f.shape[1], min_points=1)
        self.icp_points = as_points(self.icp_points, "prepared map ICP points", min_points=1)
        self.icp_normals = as_points(self.icp_normals, "prepared map ICP normals", min_points=1)
        self.work_origin = np.asarray(self.work_origin, dtype=np.float64)
        if (self.normals.shape[0] != m or self.features.shape[0] != m
                or self.icp_normals.shape[0] != self.icp_points.shape[0]):
            raise InputError("prepared map arrays disagree in length (points, normals, features; ICP points, normals)")
        if self.work_origin.shape != (3,) or not np.isfinite(self.work_origin).all():
            raise InputError(f"prepared map work_origin must be a finite 3-vector, got {self.work_origin!r}")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def kdtree(self):
        """pykdtree KD-tree over ``icp_points`` (built once per process, then reused)."""
        if self._kdtree is None:
            from pykdtree.kdtree import KDTree

            self._kdtree = KDTree(self.icp_points)
        return self._kdtree

    @property
    def feature_index(self):
        """Descriptor search tree over ``features`` (:func:`minegeo.registration.correspondences.build_feature_index`),
        built once per process and reused by every scan's RANSAC."""
        if self._feature_index is None:
            from minegeo.registration.correspondences import build_feature_index

            self._feature_index = build_feature_index(self.features)
        return self._feature_index

    def occupancy(self, params):
        """Occupancy table and floor anchors for the correlative search
        (:func:`minegeo.localize.correlative.map_occupancy`), built once per process and per
        cell setting."""
        from minegeo.localize.correlative import map_occupancy

        key = (float(params.cell_size_m), int(params.dilation_cells), float(params.anchor_max_tilt_deg))
        if key not in self._occ_cache:
            packed = self._packed.pop(("occupancy", key), None)
            if packed is not None:  # stored in the file: only its empty slots are added back
                self._occ_cache[key] = _expand_occupancy(packed)
            else:
                self._occ_cache[key] = map_occupancy(self.icp_points, self.points, self.normals, params)
        return self._occ_cache[key]

    def build_indexes(self, params=None, progress=None) -> dict:
        """Build every per-process search structure that :func:`localize_scan` with ``params``
        (:class:`LocalizeParams`, default the defaults) will use, so the first scan does not pay
        for them: the KD-trees of the ICP cloud, the descriptor tree, and for levelled scans
        with the correlative search its occupancy bitmap and thinned screening cloud (GICP:
        the target covariances). Returns the seconds spent per structure (0 when cached).
        ``progress(name)`` (optional) is called as each structure starts."""
        p = LocalizeParams() if params is None else params
        out = {}

        def _t(name, fn):
            announce(progress, name)
            t0 = time.perf_counter()
            fn()
            out[name] = time.perf_counter() - t0

        _t("kdtree", lambda: self.kdtree)
        _t("target_index", self.target_index)
        _t("feature_index", lambda: self.feature_index)
        if p.ransac.model == "levelled" and p.correlative is not None:
            _t("occupancy", lambda: self.occupancy(p.correlative.search))
            cp = p.correlative.search
            _t("screen_target", lambda: self.screen_target(cp.screen_voxel_size_m))
            if cp.screen_grid and cp.screen_voxel_size_m is not None:
                _t("screen_grid", lambda: self.screen_grid(cp.screen_voxel_size_m))
        if p.icp.method == "gicp":
            from minegeo.registration import GICPParams

            gp = GICPParams(max_correspondence_distance_m=float(p.icp.max_correspondence_m),
                            max_iterations=int(p.icp.max_iterations))
            _t("gicp_target", lambda: self.gicp_target(gp))
        return out

    def screen_target(self, voxel_size_m):
        """``(GatedKDTree, points, normals)`` of the ICP cloud thinned to one point per voxel of
        edge ``voxel_size_m`` (centroid, and mean normal renormalised; voxels whose normals
        disagree, mean length < 0.5, e.g. both faces of a thin railing, are left out), for the
        correlative search's screening stage. Built once per process and voxel size;
        ``None`` gives the full ICP cloud."""
        if voxel_size_m is None:
            return self.target_index(), self.icp_points, self.icp_normals
        key = ("screen", float(voxel_size_m))
        if key not in self._gicp_cache:
            from minegeo.geometry import voxel_downsample
            from minegeo.registration import build_target_index

            v = voxel_downsample(self.icp_points, float(voxel_size_m), normals=self.icp_normals)
            length = np.linalg.norm(v.normals, axis=1)
            ok = length >= 0.5
            if not ok.any():  # nothing coherent (degenerate map): screen on the full cloud
                self._gicp_cache[key] = (self.target_index(), self.icp_points, self.icp_normals)
            else:
                pts = np.ascontiguousarray(v.points[ok])
                nrm = np.ascontiguousarray(v.normals[ok] / length[ok, None])
                self._gicp_cache[key] = (build_target_index(pts), pts, nrm)
        return self._gicp_cache[key]

    def screen_grid(self, voxel_size_m):
        """Nearest-point lookup grid over :meth:`screen_target`'s points, cells of edge
        ``voxel_size_m``, reaching the screening stage's widest gate
        (:func:`minegeo.localize._kernels.build_nearest_grid`): ``(block_keys, nearest,
        log2_blocks, cell_m)``, built once per process and voxel size (~1 s and ~70 MB for the
        paper map at 0.5 m)."""
        from minegeo.localize import _kernels as LK

        key = ("screen_grid", float(voxel_size_m))
        if key not in self._gicp_cache and key in self._packed:  # stored: add back the empty slots
            keys, rows, log2, c = self._packed.pop(key)
            nearest = np.full((keys.shape[0], 512), -1, dtype=np.int32)
            nearest[keys != -1] = rows
            self._gicp_cache[key] = (keys, nearest, log2, c)
        if key not in self._gicp_cache:
            _, Qs, _ = self.screen_target(voxel_size_m)
            c = float(voxel_size_m)
            band, log2 = _grid_log2_start(Qs.shape[0], c)
            while True:
                keys, nearest, nb = LK.build_nearest_grid(np.ascontiguousarray(Qs), c, band, log2)
                if nb <= (1 << log2) // 2:
                    break
                log2 += 1
            self._gicp_cache[key] = (keys, nearest, log2, c)
        return self._gicp_cache[key]

    def target_index(self):
        """Numba gated KD-tree over ``icp_points`` (:func:`minegeo.registration.build_target_index`),
        built once per process (shared with :meth:`gicp_target`)."""
        if "index" not in self._gicp_cache:
            from minegeo.registration import build_target_index

            self._gicp_cache["index"] = build_target_index(self.icp_points)
        return self._gicp_cache["index"]

    def gicp_target(self, params):
        """``(covariances (k, 3, 3), KD-tree)`` of ``icp_points`` for GICP, computed once per
        process and per (ε, neighbours, covariance mode) from the stored ICP normals
        (plane covariances ``I − (1 − ε) n nᵀ``, [Ren2019 Eqs. 2-3])."""
        from minegeo.registration import estimate_gicp_covariances

        key = (float(params.epsilon), int(params.covariance_neighbours), str(params.covariance_mode))
        if key not in self._gicp_cache:
            self._gicp_cache[key] = estimate_gicp_covariances(self.icp_points, params, normals=self.icp_normals)
        return self._gicp_cache[key], self.target_index()

    @property
    def georef_result(self):
        """The :class:`~minegeo.georef.GeorefResult` or None."""
        if self.georef is None:
            return None
        if self._georef_obj is None:
            from minegeo.georef import GeorefResult

            self._georef_obj = GeorefResult.from_dict(self.georef)
        return self._georef_obj

    def points_map(self) -> np.ndarray:
        """Downsampled points in the ``map`` frame (m)."""
        return self.points + self.work_origin

    def check_params(self, params: PrepareParams | FeatureParams) -> None:
        """Raise :class:`InputError` if ``params`` differ from those the map was prepared with.

        The message names the ``--profile`` the map was prepared with and the one asked (or says
        that either is not a profile's values, e.g. after ``--voxel``), the differing values, and
        the two ways out: the map's profile for this run, or the map prepared again."""
        mine = self.params.features if isinstance(params, FeatureParams) else self.params
        if params != mine:
            a, b = to_jsonable(asdict(mine)), to_jsonable(asdict(params))
            diff = "; ".join(f"{k}: map {va!r}, this run {vb!r}" for k, va, vb in _diff(a, b))
            have, want = profile_name(mine), profile_name(params)
            other = "values of no profile (e.g. --voxel or --octree-level)"
            have_t = f"the values of --profile {have}" if have else other
            want_t = f"the values of --profile {want}" if want else other
            if have and want:
                todo = (f"run again with --profile {have}, or prepare the map again with "
                        f"'minegeo prepare-map --profile {want}'")
            elif have:
                todo = (f"run again with --profile {have} and without --voxel / --octree-level, or prepare the map "
                        "again with 'minegeo prepare-map' and this run's --profile / --voxel")
            else:
                todo = ("run again with the --profile / --voxel the map was prepared with (see its .json record), "
                        "or prepare the map again with 'minegeo prepare-map' and this run's --profile / --voxel")
            raise InputError(f"the prepared map was prepared with {have_t} and this run asks for {want_t} ({diff}): "
                             f"{todo}")

    # -- files --------------------------------------------------------------------------
    def save(self, path, *, indexes: bool = True) -> Path:
        """Write the prepared map to ``path`` (``.npz``, uncompressed, no pickles), atomically.

        The file holds the arrays plus a JSON ``meta`` string with ``format``, ``version``,
        ``params``, ``params_hash``, ``georef``, ``crs``, ``source`` and ``integrity``. With
        ``indexes`` it also holds every search structure built so far (:meth:`build_indexes`: the
        Numba KD-trees of the ICP cloud and of the thinned screening cloud, the descriptor tree,
        the occupancy bitmap, the lookup grid; ``meta["indexes"]``), which :meth:`load` restores
        instead of rebuilding them (~5 s for the 6.5 km paper map). Only pykdtree's tree is rebuilt.

        ``meta["integrity"]`` holds the SHA-256 of every stored array (of its dtype, shape and
        bytes, :func:`_array_digest`), a ``manifest`` hash of the meta (without the search
        structures' records) together with the six map arrays' hashes, and per search
        structure a hash of its meta record together with its arrays' hashes.
        """
        import io

        meta = {
            "format": PREPARED_FORMAT,
            "version": PREPARED_VERSION,
            "params": to_jsonable(asdict(self.params)),
            "params_hash": self.params_hash,
            "georef": to_jsonable(self.georef),
            "crs": self.crs,
            "source": to_jsonable(self.source),
            "timings_s": to_jsonable(self.timings_s),
        }
        arrays = {"points": self.points, "normals": self.normals, "features": self.features,
                  "icp_points": self.icp_points, "icp_normals": self.icp_normals, "work_origin": self.work_origin}
        if indexes:
            extra, meta["indexes"] = self._index_payload()
            arrays.update(extra)
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        meta = json.loads(json.dumps(meta, sort_keys=True))  # hash exactly what load reads back
        meta["integrity"] = _integrity_record(meta, arrays)
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
        return atomic_write_bytes(path, buf.getvalue())

    def _index_payload(self) -> tuple[dict, dict]:
        """Arrays (``index__*`` keys) and meta record of the search structures built so far
        (and of those read from a file and not used yet, as they were stored)."""
        arrays: dict = {}
        entries: list = []

        def put(name, d):
            for k, v in d.items():
                arrays[f"{INDEX_PREFIX}{name}__{k}"] = np.asarray(v)

        if "index" in self._gicp_cache:
            put("target", self._gicp_cache["index"].arrays())
            entries.append({"kind": "target_kdtree", "name": "target"})
        if self._feature_index is not None:
            fi = self._feature_index
            t = fi.tree
            d = {"rows": fi.rows}
            if not t.brute:  # the leaf storage is packed again on loading
                d.update(mu=t.mu, V=t.V, perm=t.perm, lstart=t.lstart)
            put("feature", d)
            entries.append({"kind": "feature_index", "name": "feature", "drop_zero_features": fi.drop_zero_features,
                            "brute": bool(t.brute), "rb": float(t.rb)})
        occs = [(key, occ.block_keys, occ.bits[occ.block_keys != -1], occ.anchors, occ.log2_blocks, occ.n_cells,
                 occ.n_blocks, occ.build_s) for key, occ in self._occ_cache.items()]
        occs += [(key[1], pk["keys"], pk["rows"], pk["anchors"], pk["log2"], pk["n_cells"], pk["n_blocks"],
                  pk["build_s"]) for key, pk in self._packed.items() if key[0] == "occupancy"]
        for i, (key, keys, rows, anchors, log2, n_cells, n_blocks, build_s) in enumerate(occs):
            name = f"occupancy{i}"
            put(name, {"block_keys": keys, "bits": rows, "anchors": anchors})  # used slots' rows only (others: 0)
            entries.append({"kind": "occupancy", "name": name, "key": list(key), "log2_blocks": log2,
                            "n_cells": n_cells, "n_blocks": n_blocks, "build_s": build_s})
        grids = []
        for i, (key, val) in enumerate(self._gicp_cache.items()):
            if not isinstance(key, tuple) or key[0] not in ("screen", "screen_grid"):
                continue
            name = f"{key[0]}{i}"
            if key[0] == "screen":
                index, pts, nrm = val
                full = pts is self.icp_points
                put(name, {} if full else {"points": pts, "normals": nrm, **{f"tree_{k}": v for k, v in index.arrays().items()}})
                entries.append({"kind": "screen_target", "name": name, "voxel_size_m": key[1], "full": full})
            else:
                keys, nearest, log2, c = val
                grids.append((name, key[1], keys, nearest[keys != -1], log2, c))  # used slots' rows (others: -1)
        n = len(self._gicp_cache)
        grids += [(f"screen_grid{n + j}", key[1], *pk) for j, (key, pk) in
                  enumerate((k, v) for k, v in self._packed.items() if k[0] == "screen_grid")]
        for name, v, keys, rows, log2, c in grids:  # after every screening cloud (load needs it first)
            put(name, {"keys": keys, "nearest": rows})
            entries.append({"kind": "screen_grid", "name": name, "voxel_size_m": v, "log2_blocks": log2, "cell_m": c})
        return arrays, {"version": INDEX_VERSION, "entries": entries}

    def _restore_indexes(self, z: dict, record, path, skip: dict | None = None) -> list[str]:
        """Check the stored search structures (``z``: the file's ``index__*`` arrays) and put them
        back in the caches.

        Every stored integer used as an index (KD-tree order, node ranges and children, descriptor
        rows, order and leaves, hash-table slots and keys, lookup-grid rows) is range-checked,
        every size announced in the meta (``log2_blocks``, ``n_cells``, ``n_blocks``) must be the
        one the builder would have chosen for the stored arrays and the map's point counts, and
        every dtype and shape must be the builder's, *before* anything is allocated from them:
        the Numba kernels do not bounds-check. The occupancy bitmap and the lookup grid are
        stored without their empty slots; they are expanded on first use (:meth:`occupancy`,
        :meth:`screen_grid`), i.e. only for the settings a localization asks for, so the
        expansion is never larger than building them would be.

        A structure that fails (or is named in ``skip``: it failed its integrity hash) is
        skipped with a warning and rebuilt when needed: the map itself is intact. Returns the
        kinds restored.
        """
        from minegeo.registration.correspondences import FeatureIndex, RowTree, row_tree_is_brute

        skip = skip or {}
        restored: list[str] = []
        if not isinstance(record, dict) or record.get("version") != INDEX_VERSION \
                or not isinstance(record.get("entries"), list):
            log.warning("%s: stored search structures of another format version: rebuilding them", path)
            return restored
        k = self.icp_points.shape[0]
        for e in record["entries"]:
            name = e.get("name") if isinstance(e, dict) else None
            if not isinstance(name, str):
                log.warning("%s: malformed search-structure record %.80r: it will be rebuilt", path, e)
                continue
            if name in skip:
                log.warning("%s: stored search structure %r not usable (%s): it will be rebuilt", path, name,
                            skip[name])
                continue
            pre = f"{INDEX_PREFIX}{name}__"
            try:
                a = {key[len(pre):]: v_ for key, v_ in z.items() if key.startswith(pre)}
                kind = e["kind"]
                if kind == "target_kdtree":
                    self._gicp_cache["index"] = _restore_kdtree(self.icp_points, a)
                elif kind == "feature_index":
                    dz, brute = _flag(e, "drop_zero_features"), _flag(e, "brute")
                    rows = _expected_feature_rows(self.features, dz)
                    if rows.size == 0:
                        raise ValueError("no descriptor row to search")
                    if not np.array_equal(_stored(a, "rows", np.int64, rows.shape), rows):
                        raise ValueError("descriptor rows are not the map's searchable rows")
                    B = np.ascontiguousarray(self.features[rows])
                    if brute != row_tree_is_brute(B.shape[0]):
                        raise ValueError("descriptor tree kind does not match the number of rows")
                    tree = RowTree(B=B, brute=True) if brute else _restore_row_tree(B, a, e.get("rb"))
                    self._feature_index = FeatureIndex(features=self.features, drop_zero_features=dz, rows=rows,
                                                       tree=tree)
                elif kind == "occupancy":
                    key, packed = _check_occupancy(a, e, k, self.points, self.normals)
                    self._packed[("occupancy", key)] = packed
                elif kind == "screen_target":
                    v = _number(e, "voxel_size_m", positive=True)
                    if _flag(e, "full"):
                        self._gicp_cache[("screen", v)] = (self.target_index(), self.icp_points, self.icp_normals)
                    else:
                        pts = _stored(a, "points", np.float64, ndim=2)
                        if not 1 <= pts.shape[0] <= k:
                            raise ValueError(f"{pts.shape[0]} screening points for a map of {k} ICP points")
                        pts = as_points(pts, "screening points")
                        nrm = as_points(_stored(a, "normals", np.float64, pts.shape), "screening normals")
                        tree = _restore_kdtree(pts, a, "tree_")
                        self._gicp_cache[("screen", v)] = (tree, pts, nrm)
                elif kind == "screen_grid":
                    v = _number(e, "voxel_size_m", positive=True)
                    if _number(e, "cell_m", positive=True) != v:
                        raise ValueError("lookup grid cell differs from its voxel size")
                    if ("screen", v) not in self._gicp_cache:
                        raise ValueError("lookup grid stored without its screening cloud")
                    n_s = self._gicp_cache[("screen", v)][1].shape[0]
                    log2 = _integer(e, "log2_blocks", 10, _MAX_LOG2_SLOTS)
                    keys = _stored(a, "keys", np.int64, (1 << log2,))
                    nb = int(np.count_nonzero(keys != -1))
                    rows = _stored(a, "nearest", np.int32, (nb, 512))
                    if rows.size and (rows.min() < -1 or rows.max() >= n_s):
                        raise ValueError("lookup grid rows out of range")
                    if log2 != _table_log2(_grid_log2_start(n_s, v)[1], nb):
                        raise ValueError(f"lookup grid size 2^{log2} is not the one built for {nb} blocks")
                    _check_hash_table(keys, log2, "lookup grid")
                    self._packed[("screen_grid", v)] = (keys, rows, log2, v)
                else:
                    raise ValueError(f"unknown kind {kind!r}")
                restored.append(kind)
            except (KeyError, ValueError, TypeError, IndexError, OverflowError, InputError) as exc:
                log.warning("%s: stored search structure %r not usable (%s): it will be rebuilt", path, name, exc)
        return restored

    @classmethod
    def load(cls, path, params: PrepareParams | None = None) -> PreparedMap:
        """Read a file written by :meth:`save`, checking all of it.

        The map's own arrays must be float64 of consistent shapes and finite, the meta fields of
        the right types, and every array and the meta must match the integrity record written
        by :meth:`save` (SHA-256 of each array's dtype, shape and bytes; of the meta). A damaged
        map array or meta is a :class:`FileFormatError`; a damaged search structure (hash or
        range checks, :meth:`_restore_indexes`) is skipped with a warning and rebuilt when
        needed. The archive itself must be an uncompressed ``.npz`` whose members hold exactly
        the bytes their headers announce, so nothing larger than the file is allocated on
        reading it.

        A file written before the integrity record existed (format version 1 without
        ``meta["integrity"]``) is refused with a request to prepare the map again: the
        record is an addition that older readers ignore, so the format version stays 1.

        Parameters
        ----------
        path : str or Path
        params : PrepareParams, optional
            If given, the file's parameters must equal these (else :class:`InputError`).

        Raises
        ------
        FileFormatError
            Not a prepared map, a newer format version, no integrity record, map arrays or meta
            that are malformed, non-finite or do not match their integrity hashes, or a
            parameter hash that does not match the stored parameters.
        InputError
            ``params`` given and different from the file's.
        """
        p = Path(path)
        meta, arrays, index_arrays, bad = _read_prepared_file(p)
        _check_meta(meta, p)
        try:
            stored = _params_from_dict(meta["params"])
        except (KeyError, TypeError, ValueError, AttributeError, InputError) as exc:
            raise FileFormatError(p, f"bad parameter record ({exc})") from None
        if params_hash(stored) != meta.get("params_hash"):
            raise FileFormatError(p, "parameter hash does not match the stored parameters (file edited or corrupted)")
        m = arrays["points"].shape[0]
        if (arrays["points"].shape != (m, 3) or arrays["normals"].shape != (m, 3)
                or arrays["features"].shape != (m, FPFH_DIM)
                or arrays["work_origin"].shape != (3,) or arrays["icp_points"].ndim != 2
                or arrays["icp_points"].shape[1] != 3 or arrays["icp_normals"].shape != arrays["icp_points"].shape):
            raise FileFormatError(p, "array shapes are inconsistent")
        try:
            pm = cls(points=arrays["points"], normals=arrays["normals"], features=arrays["features"],
                     icp_points=arrays["icp_points"], icp_normals=arrays["icp_normals"],
                     work_origin=arrays["work_origin"], params=stored, params_hash=meta["params_hash"],
                     georef=meta.get("georef"), crs=meta.get("crs"), source=meta.get("source") or {},
                     timings_s=meta.get("timings_s") or {})
        except InputError as exc:  # NaN/inf or inconsistent arrays in the file
            raise FileFormatError(p, f"corrupted arrays ({exc})") from None
        skip = _verify_integrity(meta, arrays, index_arrays, bad, p)
        if pm.georef is not None:
            try:
                pm.georef_result  # noqa: B018 - parsed now, so a bad record is a file error, not a late traceback
            except InputError as exc:
                raise FileFormatError(p, f"bad georeferencing record ({exc})") from None
        if params is not None:
            pm.check_params(params)
        if "indexes" in meta:
            pm._restore_indexes(index_arrays, meta["indexes"], p, skip)
        return pm


def profile_name(params: PrepareParams | FeatureParams) -> str | None:
    """The CLI ``--profile`` whose values ``params`` are exactly (``fast``, ``table3``), else None."""
    for name, ref in (("fast", PrepareParams.fast()), ("table3", PrepareParams())):
        if params == (ref.features if isinstance(params, FeatureParams) else ref):
            return name
    return None


def _diff(a: dict, b: dict, prefix: str = "") -> list:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _diff(va, vb, prefix + k + ".")
        elif va != vb:
            out.append((prefix + k, va, vb))
    return out
