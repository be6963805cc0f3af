"""``minegeo localize-batch``: localize many scans in one prepared map, in parallel on Dask.

``--map`` is a prepared map (``.npz`` from ``minegeo prepare-map``; a map file is prepared once,
as ``localize`` does, cache beside it), ``--scans`` a folder (every non-hidden file in it) or a
glob pattern, ``--out`` the batch folder. A local Dask cluster of ``--workers`` processes (one
thread each) by default, or the workers of a running ``dask.distributed`` scheduler
(``--scheduler tcp://host:8786``; they must see the same files). Needs ``pip install
'minegeo[dask]'``.

``OUT`` holds one result folder per scan, named after the scan file (``OUT/scan_07/``), exactly as
``minegeo localize --map MAP --scan SCAN --seed SEED`` writes it (every scan gets the same
``--seed``; the two ``result.json`` differ only in :data:`minegeo.localize.batch.VOLATILE_FIELDS`:
timings and the ``batch`` record), plus ``summary.csv`` (scan, status, reason, E, N, H,
heading, radius95_m, time_s), ``report.html`` (status counts, plan view of the placed scans,
table), ``batch_result.json`` (parameters, versions, seed, input hashes, counts, rows),
``batch_manifest.json`` (the map and parameters this folder belongs to), ``.map_cache/``
(the map's arrays as ``.npy`` files the workers memory-map) and, with ``--dxf``,
``placements.dxf`` (every ``ok`` scan for mine-planning CAD).

A scan that cannot be localized at all (unreadable, empty, not a point cloud, too few points,
flat; a worker that died) gets a ``failed`` result folder whose ``reason`` says why; the batch
goes on. Re-running the same command skips the scans whose results are complete and valid
(same map, parameters, seed and scan SHA-256) and does the rest. An ``OUT`` holding a batch of
another map (or other parameters) is refused, nothing written.

Exit status 0 when every scan is ``ok``, 1 when any is ``ambiguous`` or ``failed`` (summary.csv
says which), 2 for a user mistake (one stderr line; ``OUT`` as it was), 130 for Ctrl-C (one
stderr line). A run that stops early leaves ``OUT`` as it was plus the scan folders it completed
(each whole) and their manifest, nothing else (:class:`minegeo.localize.batch.OutState`;
docs/localization.md, "What a run that does not finish leaves in OUT").
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import time
import uuid
from dataclasses import asdict
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "localize many scans in one prepared map in parallel (Dask): one result folder per scan + summary.csv"


def add_arguments(parser) -> None:
    from minegeo._params import arg_type
    from minegeo.cli._argtypes import nonnegative_int, positive_float, positive_int
    from minegeo.cli.localize import LEVELLED_MAX_DEG, add_profile_arguments

    parser.add_argument("--map", required=True, help="prepared map (.npz from minegeo prepare-map) or a map file")
    parser.add_argument("--scans", required=True, help="folder of scan files, or a glob pattern ('scans/*.ply')")
    parser.add_argument("--out", required=True, help="batch folder (one result folder per scan, summary.csv, "
                                                     "report.html, batch_result.json); re-running resumes it")
    parser.add_argument("--workers", type=positive_int, default=None,
                        help=f"worker processes of the local Dask cluster, one thread each (default {DEFAULT_WORKERS}, "
                             f"at most {WORKERS_PER_CORE} per CPU core; not with --scheduler)")
    parser.add_argument("--scheduler", type=scheduler_address, default=None, metavar="ADDRESS",
                        help="address of a running dask.distributed scheduler (e.g. tcp://10.0.0.5:8786) instead "
                             "of a local cluster; its workers must see --map, --scans and --out at the same paths")
    parser.add_argument("--scheduler-timeout-s", type=positive_float, default=20.0, metavar="S",
                        help="how long to try reaching --scheduler before giving up (default 20 s)")
    parser.add_argument("--seed", type=nonnegative_int, default=0,
                        help="random seed of every scan (default 0): the same as minegeo localize --seed")
    add_profile_arguments(parser)
    parser.add_argument("--icp", default=None, choices=("point_to_point", "point_to_plane", "gicp"),
                        help="ICP variant (as minegeo localize)")
    parser.add_argument("--levelled", type=arg_type("minegeo.registration.ransac_params:RansacParams", "max_tilt_deg",
                                                    le=LEVELLED_MAX_DEG), default=None, metavar="DEG",
                        help="the scans are levelled (as minegeo localize --levelled), a tilt in (0, 90] degrees")
    parser.add_argument("--no-cache", action="store_true",
                        help="a map file given as --map: do not read or write its prepared-map cache")
    parser.add_argument("--drop-nonfinite", action="store_true", help="drop scan points with NaN/inf coordinates")
    parser.add_argument("--dxf", action="store_true",
                        help="also write OUT/placements.dxf for mine-planning CAD: every ok scan's origin, 95 %% ellipse "
                             "and label on MINEGEO_* layers (needs minegeo[dxf])")


#: local cluster size without --workers
DEFAULT_WORKERS = 2
#: most worker processes per CPU core --workers accepts (more only wait for the cores)
WORKERS_PER_CORE = 4
#: transports a dask.distributed scheduler address may name
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                       r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def scheduler_address(text: str) -> str:
    """argparse type of ``--scheduler``: ``[SCHEME://]HOST:PORT``.

    ``SCHEME`` one of :data:`SCHEDULER_SCHEMES` (default ``tcp``), ``HOST`` a host name, an IPv4
    address or an IPv6 address in brackets (``[::1]``), ``PORT`` 1-65535. Checked before any work;
    whether a scheduler answers there is found out when the batch connects.
    """
    import argparse
    import ipaddress

    t = str(text).strip()
    form = "give it as tcp://HOST:PORT, e.g. tcp://10.0.0.5:8786 (an IPv6 address in brackets: tcp://[::1]:8786)"
    scheme, sep, rest = t.partition("://")
    if not sep:
        scheme, rest = "tcp", t
    if scheme.lower() not in SCHEDULER_SCHEMES:
        raise argparse.ArgumentTypeError(f"{text!r}: unknown transport {scheme!r} (one of "
                                         f"{', '.join(SCHEDULER_SCHEMES)}); {form}")
    if rest.startswith("["):
        host, close, port = rest[1:].partition("]")
        if not close or not port.startswith(":"):
            raise argparse.ArgumentTypeError(f"{text!r} is not a scheduler address; {form}")
        port = port[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: {host!r} is not an IPv6 address; {form}") from None
    else:
        host, colon, port = rest.rpartition(":")
        if not colon:
            raise argparse.ArgumentTypeError(f"{text!r} has no port; {form}")
        if ":" in host:
            raise argparse.ArgumentTypeError(f"{text!r}: an IPv6 address needs brackets; {form}")
        if not _HOSTNAME.match(host):
            raise argparse.ArgumentTypeError(f"{text!r}: {host!r} is not a host name or address; {form}")
    if not (port.isdigit() and port.isascii() and 1 <= int(port) <= 65535):
        raise argparse.ArgumentTypeError(f"{text!r}: the port must be a whole number from 1 to 65535; {form}")
    return t


def _check_options(args) -> None:
    """Option combinations and the environment, before any file is read (the values themselves
    were checked by their argparse types)."""
    from minegeo.errors import InputError

    if args.scheduler is not None and args.workers is not None:
        raise InputError("--workers sets the size of the local cluster and --scheduler uses a running cluster "
                         "instead; give one of them")
    if args.workers is None:
        args.workers = DEFAULT_WORKERS
    most = WORKERS_PER_CORE * (os.cpu_count() or 1)
    if args.workers > most:
        raise InputError(f"--workers {args.workers}: at most {most} on this machine ({WORKERS_PER_CORE} per CPU "
                         f"core); each worker is a process running one scan at a time")
    if not Path(args.map).exists():
        raise InputError(f"--map {args.map} does not exist")
    if args.dxf:
        from minegeo.cli._dxf import require_dxf

        require_dxf()  # a missing ezdxf stops the run before any work
    import importlib.util

    if importlib.util.find_spec("distributed") is None or importlib.util.find_spec("dask") is None:
        from minegeo.localize.batch import DaskUnavailableError

        raise DaskUnavailableError()


def run(args) -> int:
    """The batch, in the order that keeps ``OUT``'s contract (docs/localization.md): every check
    before any work; the lock of ``OUT``; the cluster started (nothing written yet, so a cluster
    that cannot start leaves ``OUT`` as it was); ``OUT`` prepared (manifest, map cache); the scans;
    the summary, report and record staged and renamed into place together. A run that stops
    early takes back everything but its completed scan folders (:class:`~minegeo.localize.batch.OutState`)."""
    from minegeo._output import OutputTransaction, check_outputs, output_lock
    from minegeo._provenance import input_record, to_jsonable
    from minegeo.cli._common import summary_lines_quiet
    from minegeo.cli.localize import DEFAULT_PROFILE, params_from_args
    from minegeo.localize import batch as B
    from minegeo.localize.prepared import is_prepared_file, load_or_prepare, params_hash

    _check_options(args)
    prep, lp = params_from_args(args)
    out = Path(args.out)
    scans = B.find_scans(args.scans)
    names = B.result_names(scans)  # checked: unique, none a name the batch uses itself
    ins = {"--map": args.map, **({"--scans": args.scans} if Path(args.scans).is_dir() else {})}
    ins.update({f"scan {s}": s for s in scans})
    check_outputs(ins, folders={"--out": out})
    B.check_out_entries(out, names)
    files = {n: out / n for n in B.BATCH_FILES}
    OutputTransaction("localize-batch", inputs=ins, files=files).check()
    map_input = input_record(args.map)
    profile = getattr(args, "profile", None) or DEFAULT_PROFILE
    lp_dict = to_jsonable(asdict(lp))
    # a prepared map is read (and checked) first; a map file only after the --out check, since
    # preparing it writes its cache beside it: a user mistake writes nothing
    t0 = time.perf_counter()
    pm = how = None
    if is_prepared_file(args.map):
        pm, how = load_or_prepare(args.map, prep, use_cache=False, write_cache=False)
    manifest = B.manifest_record(map_input, pm.params_hash if pm is not None else params_hash(prep), lp_dict,
                                 args.seed, profile)
    B.check_out_folder(out, manifest)
    if pm is None:
        with summary_lines_quiet():
            pm, how = load_or_prepare(args.map, prep, use_cache=not args.no_cache, write_cache=not args.no_cache)
    t_map = time.perf_counter() - t0
    created = _missing_top(out)
    try:
        with output_lock("localize-batch", "--out", out):
            B.check_out_folder(out, manifest)
            B.check_out_entries(out, names)
            state = B.OutState(out, names)
            try:
                res, record = _run_locked(args, out, scans, names, pm, how, manifest, map_input, t_map, state,
                                          files, prep, lp)
            except BaseException:
                state.rollback()  # after the cluster closed (no worker writes any more), under the lock
                raise
    except BaseException:
        _remove_if_empty(created)
        raise
    if not getattr(args, "quiet", False):
        _print(res, record, out)
    return 0 if res.counts.get("ok", 0) == len(res.rows) else 1


def _run_locked(args, out, scans, names, pm, how, manifest, map_input, t_map, state, files, prep, lp):
    from minegeo._output import OutputTransaction
    from minegeo.localize import batch as B
    from minegeo.localize.prepared import cache_path, is_prepared_file

    cache = B.map_cache_dir(out, map_input["sha256"], pm.params_hash)
    batch_id = uuid.uuid4().hex[:12]
    cache_file = None if (is_prepared_file(args.map) or args.no_cache) else str(cache_path(args.map, prep))
    jobs = [B.BatchJob(scan=str(s), name=n, folder=str(out / n), map_path=str(args.map), map_input=map_input,
                       map_how=how, map_cache=str(cache), cache_file=cache_file, params_hash=pm.params_hash,
                       manifest_sha256=B.manifest_digest(manifest), lp=lp, seed=int(args.seed),
                       profile=manifest["profile"], drop_nonfinite=bool(args.drop_nonfinite), batch_id=batch_id,
                       numba_threads=B.numba_share(args.workers, args.scheduler), manifest=manifest)
            for s, n in zip(scans, names, strict=True)]
    _, todo = B.plan_batch(jobs, manifest)
    cluster = B.BatchCluster(args.workers, args.scheduler, quiet=not args.debug,
                               connect_timeout_s=args.scheduler_timeout_s)
    try:
        if todo:
            cluster.start()  # before anything is written: a cluster that cannot start leaves OUT as it was
        state.prepare(manifest)
        if todo:
            pm.build_indexes(lp)  # exported with the map: workers restore them instead of building them
            B.export_map_cache(pm, out, map_input["sha256"])
        with _Bar(args, len(jobs)) as bar:
            res = B.run_batch(jobs, manifest, localize_task, lost_task, workers=args.workers,
                              scheduler=args.scheduler, client=cluster if todo else None, on_row=bar)
    finally:
        cluster.close()
    if todo:  # every task has ended: a staging folder or lock of a worker that died is a leftover
        B.clean_leftovers(out, quiet=True)
    # the summary, report, record (and drawing) of this run: staged, renamed into place together
    with OutputTransaction("localize-batch", files=files, drop_unwritten=True) as tx:
        record = _write_batch_outputs(args, out, res, pm, manifest, map_input, t_map, how,
                                      {n: tx.file(n) for n in files})
        B.pause_for_test("commit")
    return res, record


def _missing_top(p: Path) -> Path | None:
    """The outermost missing folder of ``p`` and its parents (what a run creates to write ``p``)."""
    top = None
    for anc in [Path(os.path.abspath(p)), *Path(os.path.abspath(p)).parents]:
        if anc.exists():
            break
        top = anc
    return top


def _remove_if_empty(top: Path | None) -> None:
    """Remove ``top`` (a folder this run created) when no file was put under it."""
    import shutil

    from minegeo._output import sigint_deferred

    if top is None:
        return
    with sigint_deferred():
        if top.is_dir() and not any(q.is_file() or q.is_symlink() for q in top.rglob("*")):
            shutil.rmtree(top, ignore_errors=True)


def _write_batch_outputs(args, out: Path, res, pm, manifest: dict, map_input: dict, t_map: float, how: str,
                         to: dict) -> dict:
    """Write the batch's own files to the paths ``to`` (``{name in BATCH_FILES: staged path}``);
    ``out`` is the batch folder whose scan folders they describe."""
    from minegeo._provenance import arguments_provenance, versions, write_json_atomic
    from minegeo.cli._common import whole_run_timings
    from minegeo.localize import batch as B
    from minegeo.report.batch_report import batch_status, write_batch_report

    B.write_summary_csv(to["summary.csv"], res.rows, georeferenced=pm.georef is not None)
    word, text = batch_status(res.counts)
    timings = {"map_load_or_prepare": t_map, "batch": res.seconds, **whole_run_timings(args)}
    rows = [{k: v for k, v in r.items() if k != "T_map_scan"} for r in res.rows]
    record = {
        "verb": "localize-batch", "status": {"OK": "ok", "WARNINGS": "warning"}.get(word, "failed"), "reason": text,
        "counts": res.counts, "n_scans": len(res.rows), "n_resumed": res.n_resumed, "n_run": res.n_run,
        "scans_per_minute": (60.0 * res.n_run / res.seconds) if res.n_run and res.seconds > 0 else None,
        "frame": "crs" if pm.georef is not None else "map", "crs": pm.crs,
        "summary_csv": "summary.csv", "summary_columns": list(B.summary_columns(pm.georef is not None)),
        "comparable_to_localize": "each scan's result.json equals minegeo localize's with the same --map, --scan, "
                                  "options and --seed except " + ", ".join(B.VOLATILE_FIELDS),
        "profile": manifest["profile"], "seed": int(args.seed), "workers": res.workers, "scheduler": res.scheduler,
        "params": {"localize": manifest["localize_params"], "map": json.loads(json.dumps(asdict(pm.params)))},
        "map_preparation": {"source": how, "params_hash": pm.params_hash, "n_points": len(pm)},
        "inputs": [map_input] + [{"path": r["scan"], "sha256": r["sha256"]} for r in res.rows],
        "scans": rows, "versions": versions(), "timings_s": timings, "provenance": arguments_provenance(),
    }
    if args.dxf:  # every placed scan in one drawing for mine-planning CAD (ok results only)
        from minegeo.cli._dxf import dxf_record
        from minegeo.io.dxf import write_localize_dxf

        recs = []
        for r in res.rows:
            try:
                d = json.loads((out / r["folder"] / "result.json").read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                log.warning("%s: no result.json for the DXF (%s)", r["folder"], exc)
                continue
            recs.append({**d, "name": r["name"], "result_dir": str(out / r["folder"])})
        record["dxf"] = dxf_record(to["placements.dxf"], write_localize_dxf(to["placements.dxf"], recs))
    write_batch_report(to["report.html"], record, res.rows, pm)
    write_json_atomic(to["batch_result.json"], record)
    return record


def _print(res, record: dict, out: Path) -> None:
    c = res.counts
    n = len(res.rows)
    print(f"{record['status'].upper()}: {record['reason']}")
    rate = record["scans_per_minute"]
    print(f"  {res.n_run} scans run now" + (f" ({rate:.1f} per minute)" if rate else "")
          + f", {res.n_resumed} kept from an earlier run; {res.seconds:.1f} s")
    for r in res.rows:
        if r["status"] != "ok":
            print(f"  {r['status'].upper()} {r['name']}: {r['reason']}")
    if c.get("ok", 0) < n:
        print("  NO POSITION for the scans above (coordinates only for ok scans)")
    print(f"  wrote {out / 'summary.csv'}, {out / 'report.html'}, {out / 'batch_result.json'} and one folder per scan")


class _Bar:
    """tqdm bar over the scans (stderr, terminals only; see :func:`minegeo._output.progress_enabled`)."""

    def __init__(self, args, total: int):
        from minegeo._output import progress_enabled

        self._bar = None
        if progress_enabled(args):
            import sys

            from tqdm import tqdm

            self._bar = tqdm(total=total, desc="localize-batch", file=sys.stderr, leave=False, dynamic_ncols=True)

    def __call__(self, row, n_done, n_total) -> None:
        log.debug("%s: %s (%d/%d)", row["name"], row["status"], n_done, n_total)
        if self._bar is not None:
            self._bar.n = n_done
            self._bar.set_postfix_str(f"{row['name']} {row['status']}")
            self._bar.refresh()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        if self._bar is not None:
            self._bar.close()
        return False


# ------------------------------------------------------------------------------------ worker side
def _batch_field(job) -> dict:
    return {"batch_id": job.batch_id, "name": job.name, "manifest_sha256": job.manifest_sha256,
            "map_cache": job.map_cache, "host": socket.gethostname(), "pid": os.getpid()}


def failed_record(job, kind: str, err, scan_input: dict, map_params: dict | None, params_hash: str | None,
                  seconds: float) -> dict:
    """``result.json`` of a scan that could not be localized (``kind``: ``input`` or ``crash``)."""
    from minegeo._provenance import to_jsonable, versions
    from minegeo.localize.result import ANSWER_FIELDS

    etype, msg = (type(err).__name__, str(err)) if isinstance(err, BaseException) else ("WorkerError", str(err))
    what = "the scan could not be used" if kind == "input" else "the scan's run stopped unexpectedly"
    rec = {"status": "failed", "reason": f"{what}: {msg}",
           "error": {"kind": kind, "type": etype, "message": msg,
                     "note": "input: the file is unreadable, empty, not a point cloud or not localizable (kept; redone "
                             "only when the file changes); crash: worker died or unexpected error (redone on the "
                             "next run)"}}
    rec.update({k: None for k in ANSWER_FIELDS})
    rec.update({"params": {"localize": to_jsonable(asdict(job.lp)), "map": map_params}, "seed": int(job.seed),
                "timings_s": {"total": seconds}, "warnings": [], "profile": job.profile,
                "inputs": [job.map_input, scan_input],
                "map_preparation": {"source": job.map_how, "params_hash": params_hash},
                "versions": versions(), "batch": _batch_field(job)})
    return rec


def write_failed_folder(job, rec: dict) -> None:
    """Write the ``failed`` result folder of ``job`` (result.json and a FAILED report), atomically."""
    from minegeo._output import OutputTransaction
    from minegeo._provenance import write_json_atomic
    from minegeo.report.batch_report import write_scan_failure_report

    with OutputTransaction("localize-batch", folders={"--out": Path(job.folder)}) as tx:
        st = tx.folder("--out")
        write_scan_failure_report(st / "report.html", rec)
        write_json_atomic(st / "result.json", rec)


def localize_task(job) -> dict:
    """Run on a worker: localize one scan into its result folder; returns its summary row.

    Never raises for a bad scan: a user-type error (:class:`~minegeo.errors.MinegeoError`, an
    unreadable file) gives a ``failed`` folder of kind ``input``, any other exception one of kind
    ``crash`` (redone on the next run).
    """
    from minegeo._output import OutputTransaction, RunClock
    from minegeo._provenance import input_record, write_json_atomic
    from minegeo.cli.localize import localize_and_write, read_scan_inputs, result_base
    from minegeo.errors import MinegeoError, OutputError
    from minegeo.localize.batch import apply_numba_share, done_record, summary_row, worker_map

    if getattr(job, "manifest", None):
        # run twice (Dask recomputes a finished task whose worker died before its result was
        # released): the result this batch wrote is complete and valid, so it is kept as it is
        rec = done_record(job, job.manifest)
        if rec is not None:
            log.info("scan %s: already done for this batch; its result folder is kept", job.scan)
            return summary_row(job, rec)
    apply_numba_share(getattr(job, "numba_threads", 0))
    clock = RunClock()
    t_start = time.perf_counter()
    scan_input = {"path": job.scan, "sha256": None, "size_bytes": None}
    pm = None
    try:
        pm, t_map, index_s = worker_map(job.map_cache, job.lp)
        try:
            scan_input = input_record(job.scan)
            scan, traj, t_read = read_scan_inputs(job.scan, None, job.lp, drop_nonfinite=job.drop_nonfinite)
            base = result_base(pm, job.map_how, t_map, index_s, profile=job.profile, inputs=[job.map_input, scan_input],
                               seed=job.seed, cache_file=job.cache_file)
            with OutputTransaction("localize-batch", inputs={"--map": job.map_path, "SCAN": job.scan},
                                   folders={"--out": Path(job.folder)}) as tx:
                _, d = localize_and_write(tx.folder("--out"), pm, scan, traj, job.lp, seed=job.seed, base=base,
                                          t_read=t_read, t_start=t_start, run_timings=clock.timings)
                d["batch"] = _batch_field(job)
                write_json_atomic(tx.folder("--out") / "result.json", d)
            return summary_row(job, d)
        except OutputError as exc:  # the scan's folder is locked or not a result folder: not the scan's fault
            kind, err = "crash", exc
        except (MinegeoError, OSError) as exc:
            kind, err = "input", exc
    except Exception as exc:  # noqa: BLE001 - a bug or a broken worker: recorded, the batch goes on
        log.exception("scan %s: unexpected error", job.scan)
        kind, err = "crash", exc
    finally:
        clock.close()
    rec = failed_record(job, kind, err, scan_input, None if pm is None else json.loads(json.dumps(asdict(pm.params))),
                        None if pm is None else pm.params_hash, time.perf_counter() - t_start)
    write_failed_folder(job, rec)
    return summary_row(job, rec)


def lost_task(job, exc) -> dict:
    """Driver side: the task of ``job`` raised or its worker died; write a ``crash`` failed folder."""
    from minegeo.errors import MinegeoError
    from minegeo.localize.batch import summary_row

    rec = failed_record(job, "crash", f"worker failed ({type(exc).__name__}: {exc})",
                        {"path": job.scan, "sha256": None, "size_bytes": None}, None,
                        job.params_hash or None, 0.0)
    try:
        write_failed_folder(job, rec)
    except (OSError, MinegeoError) as exc2:
        log.warning("scan %s: could not write its failed result folder: %s", job.scan, exc2)
    return summary_row(job, rec)
