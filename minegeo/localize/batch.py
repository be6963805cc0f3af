"""Batch localization of many scans in one prepared map on Dask (``minegeo localize-batch``).

Pure orchestration around the per-scan work of ``minegeo localize``
(:func:`minegeo.cli.localize.localize_and_write`): each scan gets the result folder
``minegeo localize`` would write for it, so a batch result equals one-by-one ``localize`` runs
with the same map, parameters and ``--seed`` (every scan gets the same seed) in every field
except :data:`VOLATILE_FIELDS`.

Design
------
* **Map once per worker, memory-mapped.** The driver loads (or prepares) the map once and
  exports its arrays and search structures unpacked as ``.npy`` files to
  ``OUT/.map_cache/<key>/`` (:func:`export_map_cache`, ``<key>`` from the map's SHA-256 and
  parameter hash). A task carries only paths; each worker process opens the arrays with
  ``np.load(mmap_mode="c")`` once (:func:`worker_map`, a module-level cache keyed by folder and
  key) and builds the remaining search structures once. Copy-on-write (``"c"``), not
  read-only (``"r"``): the pages are shared with the page cache all the same (a prepared map's
  arrays are never written), but read-only arrays are a different Numba type and would compile
  every kernel a second time (measured: 12 s on the first scan of a worker).
* **Resumable.** A scan counts as done (:func:`done_record`) when ``OUT/<name>/result.json``
  and ``report.html`` exist, the record parses, names this map (SHA-256 of the map input,
  prepared-parameter hash), this seed and this batch manifest (its ``batch.manifest_sha256``:
  map, localize parameters, seed, profile), the scan's SHA-256 matches the
  file now, and it is not a ``crash`` record (worker died or an unexpected error). Everything
  else is redone. The task (``minegeo.cli.localize_batch.localize_task``: only the CLI layer
  writes outputs) writes each scan folder through :class:`~minegeo._output.OutputTransaction`
  (staged, renamed into place): a killed worker leaves no half folder.
* **Another batch in OUT is refused** (:func:`check_out_folder`): ``OUT/batch_manifest.json``
  records the map and parameters; a different one, or a non-empty ``OUT`` without a manifest,
  is an :class:`~minegeo.errors.OutputError` before anything is written.
* **A failed scan never stops the batch.** An unreadable, empty or non-point-cloud file, an
  unusable scan (too few points, flat) gives a ``failed`` result folder whose ``reason`` is the
  error (``error.kind = "input"``); an unexpected exception or a dead worker gives one with
  ``error.kind = "crash"`` (redone on the next run).

Dask and distributed are the optional extra ``minegeo[dask]``, imported only inside
:func:`run_batch` (:class:`DaskUnavailableError` otherwise).
"""

from __future__ import annotations

import csv
import glob
import hashlib
import io
import json
import logging
import math
import os
import shutil
import time
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from minegeo.errors import InputError, MinegeoError, OptionalDependencyError, OutputError

log = logging.getLogger(__name__)

__all__ = ["DaskUnavailableError", "VOLATILE_FIELDS", "SUMMARY_COLUMNS", "BatchJob", "BatchResult",
           "summary_columns", "comparable_record", "find_scans", "result_names", "check_out_folder", "clean_leftovers", "manifest_record", "manifest_digest",
           "export_map_cache", "worker_map", "local_cluster", "numba_share", "apply_numba_share", "BLAS_THREAD_VARIABLES", "done_record", "summary_row", "write_summary_csv",
           "run_batch"]

#: ``result.json`` fields that may differ between a batch result and a one-by-one
#: ``minegeo localize`` of the same scan (dotted paths; ``*.timings_s``: a ``timings_s`` object at
#: any depth, e.g. ``correlative.timings_s``): the timings, the batch's own record (worker,
#: host, map cache) and ``provenance`` (a ``localize`` run's command-line options; a batch records
#: its options in ``batch_result.json``). Everything else, poses, covariances, status, reason, scores, parameters,
#: inputs, is equal in its JSON text.
VOLATILE_FIELDS = ("*.timings_s", "map_preparation.seconds", "batch", "provenance")
#: Columns of ``summary.csv`` for a georeferenced map (E, N, H: CRS coordinates of the scan origin;
#: heading: azimuth of the scan's x axis, degrees clockwise from grid north; radius95_m: the 95 %
#: position radius; time_s: the scan's own run). For a map without georeferencing the coordinate
#: columns are the map's ``x, y, z`` and the heading is clockwise from the map's +y
#: (:func:`summary_columns`).
SUMMARY_COLUMNS = ("scan", "status", "reason", "E", "N", "H", "heading", "radius95_m", "time_s")


def summary_columns(georeferenced: bool) -> tuple[str, ...]:
    """The ``summary.csv`` header: :data:`SUMMARY_COLUMNS` in a CRS, map ``x, y, z`` otherwise."""
    return SUMMARY_COLUMNS if georeferenced else tuple({"E": "x", "N": "y", "H": "z"}.get(c, c)
                                                       for c in SUMMARY_COLUMNS)
MANIFEST = "batch_manifest.json"
MAP_CACHE = ".map_cache"
#: the files the batch writes at its end, together (``minegeo localize-batch``)
BATCH_FILES = ("summary.csv", "report.html", "batch_result.json", "placements.dxf")
#: every name the batch itself uses in ``OUT``: no scan's result folder may take one of them
RESERVED_NAMES = (*BATCH_FILES, MANIFEST, MAP_CACHE)
_MANIFEST_FORMAT = "minegeo-localize-batch"


class DaskUnavailableError(OptionalDependencyError):
    """``localize-batch`` needs dask and distributed (``pip install 'minegeo[dask]'``)."""

    def __init__(self):
        super().__init__("dask[distributed]", "dask")


# ------------------------------------------------------------------------------------ records
def comparable_record(d: dict) -> dict:
    """``d`` (a ``result.json`` record) without :data:`VOLATILE_FIELDS` (a new dict)."""

    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if k != "timings_s"}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v

    out = strip(json.loads(json.dumps(d)))
    out.pop("batch", None)
    out.pop("provenance", None)
    if isinstance(out.get("map_preparation"), dict):
        out["map_preparation"].pop("seconds", None)
    return out


def find_scans(spec) -> list[Path]:
    """The scan files of ``--scans``: every regular, non-hidden file of a folder (not recursive),
    or the files matching a glob pattern, sorted by path.

    Raises
    ------
    InputError
        Nothing matches, or the folder does not exist.
    """
    s = str(spec)
    p = Path(s)
    if p.is_dir():
        files = sorted(q for q in p.iterdir() if not q.name.startswith(".") and not q.is_dir())
        if not files:
            raise InputError(f"--scans {s}: the folder holds no file")
        return files
    if not glob.has_magic(s):
        if p.exists():
            return [p]
        raise InputError(f"--scans {s} does not exist (give a folder or a glob pattern such as 'scans/*.ply')")
    files = sorted(Path(q) for q in glob.glob(s) if not Path(q).name.startswith(".") and not Path(q).is_dir())
    if not files:
        raise InputError(f"--scans {s}: no file matches the pattern")
    return files


def result_names(scans) -> list[str]:
    """Result folder name of each scan: its file name without extension, or the whole file name
    when two scans share a stem (``a.ply`` and ``a.las``) or the stem is a name the batch uses
    itself (:data:`RESERVED_NAMES`: ``summary.csv.ply`` gets the folder ``summary.csv.ply``);
    ``_2``, ``_3``... for equal names of different folders; leading dots dropped (a scan given by
    its path may be a hidden file).

    Names are compared without regard to case (``Scan.ply`` and ``scan.ply`` would be one folder
    on a case-insensitive shared drive). The result always passes :func:`check_result_names`.
    """
    reserved = {r.casefold() for r in RESERVED_NAMES}
    stems = [Path(s).stem.casefold() for s in scans]
    names, seen = [], set()
    for s in scans:
        stem = Path(s).stem
        key = stem.casefold()
        base = stem if stem and stems.count(key) == 1 and key not in reserved else Path(s).name
        base = base.lstrip(".") or "scan"  # a hidden name would look like a staging folder or lock
        name, k = base, 2
        while name.casefold() in seen or name.casefold() in reserved:
            name, k = f"{base}_{k}", k + 1
        seen.add(name.casefold())
        names.append(name)
    check_result_names(scans, names)
    return names


def check_result_names(scans, names) -> None:
    """The invariant of the name mapping, checked before any scan runs: one plain, visible name
    per scan, no two equal (ignoring case), none a name the batch uses itself.

    Raises
    ------
    RuntimeError
        A violated invariant of :func:`result_names` (a bug, not the user's input).
    """
    reserved = {r.casefold() for r in RESERVED_NAMES}
    if len(names) != len(scans):
        raise RuntimeError(f"result_names gave {len(names)} names for {len(scans)} scans")
    seen: dict[str, str] = {}
    for scan, n in zip(scans, names, strict=True):
        bad = (not n or n in (".", "..") or n.startswith(".") or "/" in n or "\\" in n or "\0" in n
               or n.casefold() in reserved or n.casefold() in seen)
        if bad:
            raise RuntimeError(f"result folder name {n!r} of scan {scan} is not usable (reserved, hidden or "
                               f"equal to the folder of {seen.get(n.casefold())})")
        seen[n.casefold()] = str(scan)


def manifest_record(map_input: dict, params_hash: str, lp_dict: dict, seed: int, profile: str) -> dict:
    """What ``OUT/batch_manifest.json`` holds: the map and the parameters of the batch."""
    return {"format": _MANIFEST_FORMAT, "version": 1, "map": {"path": map_input["path"],
                                                              "sha256": map_input["sha256"]},
            "map_params_hash": params_hash, "localize_params": lp_dict, "seed": int(seed), "profile": profile}


def manifest_digest(manifest: dict) -> str:
    """SHA-256 of a :func:`manifest_record` (canonical JSON): recorded in each scan's ``batch`` field."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode("utf-8")).hexdigest()


def check_out_folder(out: Path, manifest: dict) -> bool:
    """Refuse an ``OUT`` of another batch; True when it holds a batch of this map and parameters.

    Raises
    ------
    OutputError
        ``OUT`` is a file, is a non-empty folder without ``batch_manifest.json``, or its
        manifest names another map (SHA-256 or prepared parameters), other localize
        parameters, another seed or profile. Nothing is written.
    """
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out} exists and is not a folder")
    if not out.is_dir() or not any(out.iterdir()):
        return False
    mp = out / MANIFEST
    if not mp.is_file():
        raise OutputError(f"--out {out} is not empty and holds no localize-batch results ({MANIFEST}); choose a new "
                          "or empty folder")
    try:
        old = json.loads(mp.read_text(encoding="utf-8"))
        if not isinstance(old, dict) or old.get("format") != _MANIFEST_FORMAT:
            raise ValueError("not a batch manifest")
    except (OSError, ValueError) as exc:
        raise OutputError(f"--out {out}: unreadable {MANIFEST} ({exc}); choose a new folder") from None
    if old.get("map", {}).get("sha256") != manifest["map"]["sha256"] \
            or old.get("map_params_hash") != manifest["map_params_hash"]:
        raise OutputError(f"--out {out} holds the results of another map ({old.get('map', {}).get('path')}, SHA-256 "
                          f"{str(old.get('map', {}).get('sha256'))[:12]}...); refusing to mix maps, nothing was "
                          "overwritten: choose a new --out")
    for key, what in (("localize_params", "localize parameters"), ("seed", "seed"), ("profile", "profile")):
        if old.get(key) != manifest[key]:
            raise OutputError(f"--out {out} holds results of this map made with another {what}; refusing to mix "
                              "them, nothing was overwritten: choose a new --out (or the same options)")
    return True


def clean_leftovers(out: Path, quiet: bool = False) -> list[str]:
    """Remove what a dead run left inside ``OUT``: scan staging folders (``.NAME.minegeo-tmp-*``,
    ``.NAME.minegeo-old-*``) and scan lock files (``.NAME.minegeo-lock``). Call it only while
    holding the lock of ``OUT`` itself: then no other batch writes there, so every such entry is
    a leftover (also of workers on other hosts, whose locks the host-local stale-lock rule of
    :mod:`minegeo._output` could not take over). Returns the names removed (logged as a warning
    unless ``quiet``: the rollback of an interrupted run removes its own)."""
    from minegeo._output import _LOCK_SUFFIX, _OLD_TAG, _TMP_TAG

    gone = []
    if not out.is_dir():
        return gone
    for q in out.iterdir():
        n = q.name
        if n.startswith(".") and (_TMP_TAG in n or _OLD_TAG in n or n.endswith(_LOCK_SUFFIX)):
            if q.is_dir() and not q.is_symlink():
                shutil.rmtree(q, ignore_errors=True)
            else:
                q.unlink(missing_ok=True)
            gone.append(n)
    if gone and not quiet:
        log.warning("removed %d leftover(s) of an interrupted run in %s: %s", len(gone), out, ", ".join(sorted(gone)))
    return gone


def check_out_entries(out: Path, names) -> None:
    """Refuse, before any work, an ``OUT`` whose entries cannot take this batch's outputs: a scan's
    result folder name (``names``) that exists there as a file, a batch file
    (:data:`BATCH_FILES`) that is a folder, or a ``.map_cache`` that is not a folder.

    Raises
    ------
    OutputError
        Naming the entry and what the batch would write there. Nothing is written.
    """
    if not out.is_dir():
        return
    for n in names:
        q = out / n
        if os.path.lexists(q) and (q.is_symlink() or not q.is_dir()):
            raise OutputError(f"--out {out}: {q} exists and is not a folder, but it is where the result folder of "
                              f"scan {n} goes; move it away or choose another --out")
    for n in BATCH_FILES:
        q = out / n
        if os.path.lexists(q) and (q.is_symlink() or not q.is_file()):
            raise OutputError(f"--out {out}: {q} exists and is not a plain file, but the batch writes its {n} there; "
                              "move it away or choose another --out")
    q = out / MAP_CACHE
    if os.path.lexists(q) and (q.is_symlink() or not q.is_dir()):
        raise OutputError(f"--out {out}: {q} exists and is not a folder (the batch's map cache); move it away")


def _sig(p: Path):
    try:
        st = os.lstat(p)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


class OutState:
    """What ``OUT`` held before a batch run, and how a run that does not finish is taken back.

    The rule (docs/localization.md, "What a run that does not finish leaves"): after a run that
    stops early (a user mistake, a cluster that cannot start, Ctrl-C, a crash) ``OUT`` holds what
    it held before, plus the scan result folders this run completed (each written aside and
    renamed into place whole, so each is complete) and, when it added at least one and ``OUT``
    had none, the ``batch_manifest.json`` they belong to. Nothing else: no map cache this run
    wrote, no lock, no staging folder, no summary, report or record of this run. A run that stops
    before its first scan finishes leaves ``OUT`` as it was (absent if it was absent).

    Parameters
    ----------
    out : Path
        The batch folder.
    names : list of str
        The result folder names of this batch's scans.
    """

    def __init__(self, out: Path, names):
        self.out = Path(out)
        self.names = list(names)
        self.existed = self.out.is_dir()
        self.manifest_existed = (self.out / MANIFEST).exists()
        cache = self.out / MAP_CACHE
        self.cache_entries = {q.name for q in cache.iterdir()} if cache.is_dir() else None
        self.scans_before = {n: _sig(self.out / n / "result.json") for n in self.names}
        self.prepared = False

    def prepare(self, manifest: dict) -> None:
        """Create ``OUT``, remove a dead run's leftovers (:func:`clean_leftovers`), write the
        manifest. Call it only once the cluster runs, holding the lock of ``OUT``."""
        from minegeo._output import sigint_deferred
        from minegeo._provenance import write_json_atomic

        with sigint_deferred():
            self.prepared = True
            self.out.mkdir(parents=True, exist_ok=True)
        clean_leftovers(self.out)
        if not self.manifest_existed:
            write_json_atomic(self.out / MANIFEST, manifest)

    def added_scans(self) -> list[str]:
        """Result folders this run put in place (a new or replaced, complete ``result.json``)."""
        return [n for n in self.names if (self.out / n / "result.json").is_file()
                and _sig(self.out / n / "result.json") != self.scans_before[n]]

    def rollback(self) -> None:
        """Take back what this run added to ``OUT`` except its completed scan folders (the rule
        above). Call it after the workers have stopped, still holding the lock of ``OUT``."""
        from minegeo._output import sigint_deferred

        if not self.prepared:
            return
        with sigint_deferred():
            clean_leftovers(self.out, quiet=True)
            cache = self.out / MAP_CACHE
            if cache.is_dir():
                for q in list(cache.iterdir()):
                    if self.cache_entries is None or q.name not in self.cache_entries:
                        if q.is_dir() and not q.is_symlink():
                            shutil.rmtree(q, ignore_errors=True)
                        else:
                            q.unlink(missing_ok=True)
                if self.cache_entries is None and not any(cache.iterdir()):
                    cache.rmdir()
            added = self.added_scans()
            if not self.manifest_existed and not added:
                (self.out / MANIFEST).unlink(missing_ok=True)
            if not self.existed and self.out.is_dir() and not any(self.out.iterdir()):
                self.out.rmdir()
        if added:
            log.debug("kept %d complete scan result folder(s) of the interrupted run: %s", len(added), ", ".join(added))


# ------------------------------------------------------------------------------------ map cache
def _cache_key(map_sha256: str, params_hash: str) -> str:
    return hashlib.sha256(f"{map_sha256}|{params_hash}".encode("ascii")).hexdigest()[:16]


def map_cache_dir(out: Path, map_sha256: str, params_hash: str) -> Path:
    """``out/.map_cache/<key>/``: where :func:`export_map_cache` puts the map of this SHA-256 and
    prepared-parameter hash."""
    return Path(out) / MAP_CACHE / _cache_key(map_sha256, params_hash)


def export_map_cache(pm, out: Path, map_sha256: str) -> Path:
    """Write ``pm`` unpacked (one ``.npy`` per array, ``meta.json``) to ``out/.map_cache/<key>/``.

    Reused when it exists complete (its ``meta.json`` is written last); written into a
    hidden folder beside it and renamed into place. The search structures built so far are
    stored too, so workers restore them instead of building them.
    """
    from minegeo._provenance import to_jsonable
    from minegeo.localize.prepared import CORE_ARRAYS

    d = map_cache_dir(out, map_sha256, pm.params_hash)
    root, key = d.parent, d.name
    if (d / "meta.json").is_file():
        return d
    try:
        extra, indexes = pm._index_payload()
    except (AttributeError, TypeError, ValueError) as exc:  # not a stable API: rebuild on the workers then
        log.warning("search structures not exported with the map cache (%s): each worker builds them", exc)
        extra, indexes = {}, None
    root.mkdir(parents=True, exist_ok=True)
    tmp = root / f".{key}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        arrays = {k: getattr(pm, k) for k in CORE_ARRAYS}
        arrays.update(extra)
        for k, v in arrays.items():
            np.save(tmp / f"{k}.npy", np.ascontiguousarray(v), allow_pickle=False)
        meta = {"key": key, "map_sha256": map_sha256, "params": to_jsonable(asdict(pm.params)),
                "params_hash": pm.params_hash, "georef": to_jsonable(pm.georef), "crs": pm.crs,
                "source": to_jsonable(pm.source), "timings_s": to_jsonable(pm.timings_s), "indexes": indexes,
                "arrays": sorted(arrays)}
        (tmp / "meta.json").write_text(json.dumps(meta, sort_keys=True), encoding="utf-8")
        try:
            os.rename(tmp, d)
        except OSError:  # another batch on the same OUT wrote it meanwhile
            if not (d / "meta.json").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return d


#: this process's maps: ``{(cache folder, key): PreparedMap}`` (one per worker process)
_MAPS: dict = {}


def worker_map(cache_dir, lp=None):
    """The :class:`~minegeo.localize.prepared.PreparedMap` of an exported cache, opened once per
    process (arrays memory-mapped copy-on-write) with its search structures for ``lp``.

    Returns ``(prepared map, seconds to open it, seconds per search structure built)``; both
    are zero-ish once the map is open in this process.
    """
    from minegeo.localize.prepared import CORE_ARRAYS, PreparedMap
    from minegeo.localize.prepared.model import _params_from_dict

    d = Path(cache_dir)
    t0 = time.perf_counter()
    meta = json.loads((d / "meta.json").read_text(encoding="utf-8"))
    k = (str(d.resolve()), meta["key"])
    pm = _MAPS.get(k)
    if pm is None:
        A = {name: np.load(d / f"{name}.npy", mmap_mode="c", allow_pickle=False) for name in meta["arrays"]}
        pm = PreparedMap(**{name: A[name] for name in CORE_ARRAYS}, params=_params_from_dict(meta["params"]),
                         params_hash=meta["params_hash"], georef=meta["georef"], crs=meta["crs"],
                         source=meta["source"] or {}, timings_s=meta["timings_s"] or {})
        if meta.get("indexes"):
            pm._restore_indexes({n: a for n, a in A.items() if n not in CORE_ARRAYS}, meta["indexes"], d)
        _MAPS[k] = pm
    t_map = time.perf_counter() - t0
    index_s = pm.build_indexes(lp)
    return pm, t_map, index_s


# ------------------------------------------------------------------------------------ jobs
@dataclass
class BatchJob:
    """One scan of a batch: everything a worker needs (paths and small records only)."""

    scan: str
    name: str
    folder: str
    map_path: str
    map_input: dict
    map_how: str
    map_cache: str
    cache_file: str | None
    lp: object
    seed: int
    profile: str
    drop_nonfinite: bool = False
    batch_id: str = ""
    params_hash: str = ""
    manifest_sha256: str = ""
    numba_threads: int = 0
    #: the batch's :func:`manifest_record`: a task that finds its scan already done for it (a
    #: recomputation after a worker died holding the finished task's result) leaves the folder as it is
    manifest: dict | None = None


def done_record(job: BatchJob, manifest: dict) -> dict | None:
    """The earlier ``result.json`` of ``job`` when it is complete and valid for this batch, else None
    (see the module docstring)."""
    from minegeo._provenance import sha256_file

    d = Path(job.folder)
    try:
        if not (d / "report.html").is_file():
            return None
        rec = json.loads((d / "result.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("status") not in ("ok", "ambiguous", "failed"):
        return None
    if (rec.get("error") or {}).get("kind") == "crash":
        return None
    inputs = rec.get("inputs") or []
    mp = rec.get("map_preparation") or {}
    try:
        if inputs[0].get("sha256") != manifest["map"]["sha256"] or mp.get("params_hash") != manifest["map_params_hash"]:
            return None
        # the localize parameters a result records are the ones it ended with (a gravity fallback
        # levels them): the batch record names the manifest it was made for instead
        if (rec.get("batch") or {}).get("manifest_sha256") != manifest_digest(manifest) or rec.get("seed") != job.seed:
            return None
        sha = inputs[1].get("sha256")
        if sha is None or sha != sha256_file(job.scan):
            return None
    except (OSError, MinegeoError, IndexError, AttributeError, KeyError):
        return None
    return rec


# ------------------------------------------------------------------------------------ summary
def _origin_heading(rec: dict):
    T = rec.get("T_crs_scan") or rec.get("T_map_scan")
    if rec.get("status") != "ok" or T is None:
        return None, None
    T = np.asarray(T, dtype=np.float64)
    head = math.degrees(math.atan2(T[0, 0], T[1, 0])) % 360.0
    return T[:3, 3], head


def summary_row(job: BatchJob, rec: dict, resumed: bool = False) -> dict:
    """One ``summary.csv`` row (:data:`SUMMARY_COLUMNS`) plus ``name``, ``folder``, ``resumed``,
    ``T_map_scan`` (for the plan view) and the scan's SHA-256."""
    xyz, head = _origin_heading(rec)
    r95 = rec.get("position_95_radius_m") if rec.get("status") == "ok" else None
    inputs = rec.get("inputs") or []
    return {"scan": job.scan, "status": rec.get("status", "failed"), "reason": rec.get("reason", ""),
            "E": None if xyz is None else float(xyz[0]), "N": None if xyz is None else float(xyz[1]),
            "H": None if xyz is None else float(xyz[2]), "heading": head, "radius95_m": r95,
            "time_s": (rec.get("timings_s") or {}).get("total"), "name": job.name, "folder": job.name,
            "resumed": bool(resumed), "T_map_scan": rec.get("T_map_scan") if rec.get("status") == "ok" else None,
            "sha256": inputs[1].get("sha256") if len(inputs) > 1 and isinstance(inputs[1], dict) else None,
            "error_kind": (rec.get("error") or {}).get("kind")}


def _fmt(v, fmt: str) -> str:
    return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def write_summary_csv(path, rows, georeferenced: bool = True) -> Path:
    """``summary.csv`` (:func:`summary_columns`: E, N, H in a CRS, x, y, z in a map frame; empty
    cells for a scan without coordinates), atomically."""
    from minegeo._provenance import atomic_write_text

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(summary_columns(georeferenced))
    for r in rows:
        w.writerow([r["scan"], r["status"], r["reason"], _fmt(r["E"], ".4f"), _fmt(r["N"], ".4f"),
                    _fmt(r["H"], ".4f"), _fmt(r["heading"], ".4f"), _fmt(r["radius95_m"], ".4f"),
                    _fmt(r["time_s"], ".3f")])
    return atomic_write_text(path, buf.getvalue())


# ------------------------------------------------------------------------------------ driver
@dataclass
class BatchResult:
    """What :func:`run_batch` did: one row per scan (in the order of the scans) and counts."""

    rows: list
    n_resumed: int
    n_run: int
    seconds: float
    workers: int | None
    scheduler: str | None
    counts: dict = field(default_factory=dict)


def _client(workers: int, scheduler: str | None, client):
    """``(client, owned)``: the given client, one connected to ``scheduler``, or a local cluster."""
    if client is not None:
        return client, False
    bc = BatchCluster(workers, scheduler)
    bc.start()
    return bc, True


#: test hook: ``MINEGEO_TEST_BATCH_PAUSE=<stage>`` makes the driver wait at that stage (see :func:`pause_for_test`)
TEST_PAUSE_ENV = "MINEGEO_TEST_BATCH_PAUSE"
#: test hook: the file the driver writes when it has reached the stage it waits at
TEST_READY_ENV = "MINEGEO_TEST_BATCH_READY"
#: the stages :func:`pause_for_test` knows, in the order a run reaches them
TEST_STAGES = ("cluster-start", "scans", "commit")


def pause_for_test(stage: str) -> None:
    """Test hook: when ``$MINEGEO_TEST_BATCH_PAUSE`` names ``stage``, write the file
    ``$MINEGEO_TEST_BATCH_READY`` and wait (at most 120 s) for the test's Ctrl-C.

    Stages: ``cluster-start`` (the cluster is starting in its own thread), ``scans`` (the first
    scan has finished, the others are running), ``commit`` (every scan is done; the summary,
    report and record are staged, not yet in place). Without the variable it does nothing.
    """
    if os.environ.get(TEST_PAUSE_ENV) != stage:
        return
    ready = os.environ.get(TEST_READY_ENV)
    if ready:
        Path(ready).write_text(stage, encoding="utf-8")
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline:
        time.sleep(0.02)


class BatchCluster:
    """The Dask client of a batch (a local cluster, or a running scheduler's), started so that a
    Ctrl-C leaves nothing running and prints nothing.

    * **Workers never see Ctrl-C, and print nothing.** The terminal's Ctrl-C goes to the whole
      foreground process group, worker processes included. While the local cluster starts, this
      process's stderr and stdout point at ``/dev/null`` (unless ``quiet=False``), so the worker
      processes it spawns inherit them (a worker interrupted while it starts prints nothing), and
      each worker ignores SIGINT once it runs (:mod:`minegeo.localize._batch_worker`, a preload;
      it also silences a worker restarted later). The driver stops the workers itself.
    * **A Ctrl-C while the cluster starts** never interrupts its constructor: the cluster is built
      in a helper thread while the main thread waits; on Ctrl-C the main thread waits for the
      start to end (further Ctrl-C held back), closes what it made, then raises
      :class:`KeyboardInterrupt`. A half-built ``LocalCluster`` would make distributed's exit
      hook fail (``AssertionError: Status.init``).
    * **Quiet.** Unless ``quiet=False``, the ``distributed`` loggers (driver side) print nothing
      while the batch runs and closes; the batch records every scan's outcome itself.

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster, one thread each (ignored with ``scheduler``).
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler.
    quiet : bool
        Silence distributed's log lines (default True).
    connect_timeout_s : float
        How long to try reaching ``scheduler`` before giving up (s, default 20).
    """

    def __init__(self, workers: int, scheduler: str | None = None, quiet: bool = True,
                 connect_timeout_s: float = 20.0):
        self.workers = int(workers)
        self.scheduler = scheduler
        self.connect_timeout_s = float(connect_timeout_s)
        self.quiet = quiet
        self.client = None
        self.cluster = None
        self._levels: dict = {}

    # a Client-like face for run_batch
    def submit(self, *a, **k):
        return self.client.submit(*a, **k)

    @property
    def loop(self):
        return self.client.loop

    def _connect(self, box: dict) -> None:
        try:
            from dask.distributed import Client
        except ImportError:
            box["error"] = DaskUnavailableError()
            return
        try:
            if self.scheduler:
                try:
                    box["client"] = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s",
                                           set_as_default=False)
                except (OSError, TimeoutError) as exc:
                    box["error"] = InputError(f"--scheduler {self.scheduler}: cannot connect to the Dask scheduler "
                                              f"within {self.connect_timeout_s:g} s ({exc})")
                return
            from minegeo.localize._batch_worker import QUIET_ENV

            box["cluster"] = local_cluster(self.workers,
                                           silence_logs=(logging.CRITICAL + 1) if self.quiet else logging.ERROR,
                                           preload=["minegeo.localize._batch_worker"],
                                           env={QUIET_ENV: "1" if self.quiet else "0"})
            box["client"] = Client(box["cluster"], set_as_default=False)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread, which raises it
            box["error"] = exc

    def start(self) -> BatchCluster:
        """Start the cluster (or connect); a Ctrl-C meanwhile closes it again and is re-raised."""
        import threading

        from minegeo._output import sigint_deferred

        self._silence()
        box: dict = {}
        t = threading.Thread(target=self._connect, args=(box,), name="minegeo-batch-cluster-start", daemon=True)
        saved = _std_to_devnull() if (self.quiet and not self.scheduler) else None
        try:
            try:
                t.start()
                pause_for_test("cluster-start")
                while t.is_alive():
                    t.join(0.05)
            except BaseException:
                with sigint_deferred():
                    t.join()
                    self.client, self.cluster = box.get("client"), box.get("cluster")
                    self.close()
                raise
        finally:
            _std_restore(saved)
        self.client, self.cluster = box.get("client"), box.get("cluster")
        if "error" in box:
            self.close()
            raise box["error"]
        return self

    def close(self) -> None:
        """Close the client and the local cluster (its worker processes end), with Ctrl-C held back."""
        from minegeo._output import sigint_deferred

        with sigint_deferred():
            try:
                if self.client is not None:
                    try:
                        self.client.close(timeout=30)
                    except Exception as exc:  # noqa: BLE001 - closing a broken connection: nothing left to do
                        log.debug("closing the Dask client: %s", exc)
                if self.cluster is not None:
                    try:
                        self.cluster.close(timeout=30)
                    except Exception as exc:  # noqa: BLE001
                        log.debug("closing the local Dask cluster: %s", exc)
            finally:
                self.client = self.cluster = None
                self._unsilence()

    def _silence(self) -> None:
        if not self.quiet or self._levels:
            return
        for name in ("distributed", "tornado", "asyncio"):
            lg = logging.getLogger(name)
            self._levels[name] = (lg.level, lg.propagate)
            lg.setLevel(logging.CRITICAL + 1)
            lg.propagate = False

    def _unsilence(self) -> None:
        for name, (level, prop) in self._levels.items():
            lg = logging.getLogger(name)
            lg.setLevel(level)
            lg.propagate = prop
        self._levels.clear()

    def __enter__(self) -> BatchCluster:
        return self.start()

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def _std_to_devnull():
    """Point file descriptors 1 and 2 at ``/dev/null``; returns the saved copies (for :func:`_std_restore`)."""
    import sys

    from minegeo.localize._batch_worker import quiet_std_streams

    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (AttributeError, ValueError, OSError):
            pass
    saved = (os.dup(1), os.dup(2))
    quiet_std_streams()
    return saved


def _std_restore(saved) -> None:
    if saved is None:
        return
    from minegeo._output import sigint_deferred

    with sigint_deferred():
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)


#: thread-count variables ``distributed`` sets to 1 in every worker it spawns; left as the
#: driver has them (see :func:`local_cluster`)
BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def local_cluster(workers: int, silence_logs=logging.ERROR, **kwargs):
    """A ``distributed.LocalCluster`` of ``workers`` processes, one thread each, no dashboard,
    whose workers keep the driver's BLAS thread settings; ``kwargs`` go to ``LocalCluster`` (and
    on to each worker's nanny: ``preload``, ``env``).

    ``distributed`` starts workers with ``OMP/MKL/OPENBLAS_NUM_THREADS=1``
    (``distributed.nanny.pre-spawn-environ``); minegeo's covariance goes through BLAS, whose
    sums depend on its thread count in the last bits (measured: a jackknife covariance differed
    at 1e-16 relative between 1 and 2 OpenBLAS threads). Workers with the driver's settings give
    the bits ``minegeo localize`` gives in the same shell. Numba's threads are shared out instead
    (cores // workers per worker unless ``NUMBA_NUM_THREADS`` is set): minegeo's parallel kernels
    give the same bits for any thread count (the kernel tests check it; the batch tests compare
    workers of 1 and 2 Numba threads with a 2-thread ``localize``).

    The Numba share is applied inside each task (:attr:`BatchJob.numba_threads`,
    ``numba.set_num_threads``), not through the spawn environment: ``distributed`` writes the
    spawn environment into the *driver's* ``os.environ`` (at every worker start and restart) and
    never takes it back, and a ``NUMBA_NUM_THREADS`` there that differs from the driver's running
    thread pool makes Numba refuse every later compilation in the driver.
    """
    try:
        import dask
        from dask.distributed import LocalCluster
    except ImportError:
        raise DaskUnavailableError() from None
    env = {k: v for k, v in (dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {}).items()
           if k not in BLAS_THREAD_VARIABLES and not k.startswith("NUMBA_")}
    before = {k: os.environ.get(k) for k in env}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
            return LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                dashboard_address=None, silence_logs=silence_logs, **kwargs)
    finally:  # the nannies wrote env into this process's os.environ: put it back
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def numba_share(workers: int, scheduler: str | None) -> int:
    """Numba threads per worker of a local cluster: ``cores // workers`` (0 = leave the worker's
    default: with ``--scheduler``, or when ``NUMBA_NUM_THREADS`` is set by the user)."""
    if scheduler or "NUMBA_NUM_THREADS" in os.environ:
        return 0
    return max(1, (os.cpu_count() or 1) // max(1, int(workers)))


def apply_numba_share(n: int) -> None:
    """In a worker: use at most ``n`` Numba threads (0: unchanged)."""
    if n > 0:
        import numba

        numba.set_num_threads(max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS))))


def run_batch(jobs, manifest: dict, task, on_lost, *, workers: int = 1, scheduler: str | None = None, client=None,
              on_row=None) -> BatchResult:
    """Localize every job not already done (:func:`done_record`) on Dask; never stops on a bad scan.

    Parameters
    ----------
    jobs : list of BatchJob
    manifest : dict
        :func:`manifest_record` of the batch (what a done result must match).
    workers : int
        Worker processes of the local cluster (one thread each), when neither ``scheduler``
        nor ``client`` is given.
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler (its workers must see the same
        files: the scans, ``OUT`` and its map cache).
    client : distributed.Client or BatchCluster, optional
        An existing client (anything with ``submit``), not closed here; without it a
        :class:`BatchCluster` is started for the jobs to run and closed at the end.
    task : callable
        ``task(job) -> row`` run on a worker for each job to do: writes the scan's result folder
        and returns its :func:`summary_row`; must not raise for a bad scan
        (``minegeo.cli.localize_batch.localize_task``).
    on_lost : callable
        ``on_lost(job, exc) -> row`` run in the driver when a task raised or its worker died
        (``KilledWorker``): records the scan as failed.
    on_row : callable, optional
        ``on_row(row, n_done, n_total)`` as each scan finishes (a progress bar).

    Returns
    -------
    BatchResult
    """
    t0 = time.perf_counter()
    rows, todo = plan_batch(jobs, manifest)
    rows = dict(rows)
    n_res = len(rows)
    if n_res:
        log.debug("resuming: %d of %d scans already have a complete result for this map; %d to run",
                  n_res, len(jobs), len(todo))
    if todo:
        cl, owned = _client(workers, scheduler, client)
        try:
            _run_todo(cl, task, on_lost, jobs, todo, rows, on_row, len(jobs))
        finally:
            if owned:
                cl.close()
    ordered = [rows[i] for i in range(len(jobs))]
    counts = {s: sum(1 for r in ordered if r["status"] == s) for s in ("ok", "ambiguous", "failed")}
    return BatchResult(rows=ordered, n_resumed=n_res, n_run=len(todo), seconds=time.perf_counter() - t0,
                       workers=None if scheduler else int(workers), scheduler=scheduler, counts=counts)


def plan_batch(jobs, manifest: dict) -> tuple[dict, list]:
    """``(rows, todo)``: the :func:`summary_row` of every job already done (:func:`done_record`),
    by index, and the indexes of the jobs to run. Reads only."""
    rows: dict[int, dict] = {}
    todo = []
    for i, job in enumerate(jobs):
        rec = done_record(job, manifest)
        if rec is not None:
            rows[i] = summary_row(job, rec, resumed=True)
        else:
            todo.append(i)
    return rows, todo


def _run_todo(cl, task, on_lost, jobs, todo, rows, on_row, n_total) -> None:
    from dask.distributed import as_completed

    futs = {}
    for i in todo:
        f = cl.submit(task, jobs[i], key=f"minegeo-localize-{jobs[i].batch_id}-{i}", pure=False)
        futs[f.key] = (i, f)
    ac = as_completed([f for _, f in futs.values()], loop=cl.loop)
    for f in ac:
        i, _ = futs.pop(f.key)
        try:
            row = f.result()
        except Exception as exc:  # noqa: BLE001 - a dead worker (KilledWorker) or a lost task
            log.warning("scan %s: its worker failed (%s: %s); recorded as failed, redone on the next run",
                        jobs[i].scan, type(exc).__name__, exc)
            row = on_lost(jobs[i], exc)
        # Release the finished task at once: while a future is held, the scheduler recomputes it when
        # the worker holding its (already gathered) result dies, and that recomputation would run on
        # after the batch has ended and rewrite a finished scan folder.
        f.release()
        del f
        rows[i] = row
        if on_row is not None:
            on_row(row, len(rows), n_total)
        if len(rows) < n_total:
            pause_for_test("scans")
