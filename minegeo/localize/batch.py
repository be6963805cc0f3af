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

Modules: this one holds the scans, the map cache, the summary and :func:`run_batch`; the output
folder's manifest and checks are in :mod:`minegeo.localize.batch_folder`, the Dask cluster in
:mod:`minegeo.localize.batch_cluster` (their public names are importable here).
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

from minegeo.errors import InputError, MinegeoError
from minegeo.localize.batch_cluster import (
    BLAS_THREAD_VARIABLES,
    TEST_PAUSE_ENV,
    TEST_READY_ENV,
    TEST_STAGES,
    BatchCluster,
    DaskUnavailableError,
    _client,
    apply_numba_share,
    local_cluster,
    numba_share,
    pause_for_test,
)
from minegeo.localize.batch_folder import (
    BATCH_FILES,
    MANIFEST,
    MAP_CACHE,
    RESERVED_NAMES,
    OutState,
    check_out_entries,
    check_out_folder,
    check_result_names,
    clean_leftovers,
    manifest_digest,
    manifest_record,
    result_names,
)

log = logging.getLogger(__name__)

__all__ = ["DaskUnavailableError", "VOLATILE_FIELDS", "SUMMARY_COLUMNS", "BatchJob", "BatchResult",
           "summary_columns", "comparable_record", "find_scans", "result_names", "check_out_folder", "clean_leftovers", "manifest_record", "manifest_digest",
           "export_map_cache", "worker_map", "local_cluster", "numba_share", "apply_numba_share", "BLAS_THREAD_VARIABLES", "done_record", "summary_row", "write_summary_csv",
           "run_batch", "BatchCluster", "OutState", "MANIFEST", "MAP_CACHE", "BATCH_FILES", "RESERVED_NAMES",
           "check_out_entries", "check_result_names", "pause_for_test", "TEST_PAUSE_ENV", "TEST_READY_ENV",
           "TEST_STAGES"]

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
@dataclass(frozen=True)
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
@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` did: one row per scan (in the order of the scans) and counts."""

    rows: list
    n_resumed: int
    n_run: int
    seconds: float
    workers: int | None
    scheduler: str | None
    counts: dict = field(default_factory=dict)


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
