"""``minegeo localize-batch`` (issue 19): Dask batch localization of many scans in one prepared map.

* a batch (on a ``LocalCluster`` of 2 worker processes, given as ``--scheduler``) writes for every
  scan the result folder ``minegeo localize`` writes one by one with the same seed: the
  ``result.json`` texts are equal except :data:`minegeo.localize.batch.VOLATILE_FIELDS`;
* the map the workers memory-map gives the same localization as the prepared file;
* unreadable, empty and non-point-cloud files each get a ``failed`` folder with the reason, the
  batch finishes (``--workers 1``: the CLI's own local cluster);
* a re-run skips the complete results (bytes and mtimes unchanged, ``n_run`` counter) and redoes a
  missing or changed one;
* an ``OUT`` of another map is refused, nothing changed;
* a worker killed mid-batch (``os._exit`` in the worker process while it writes a scan's staged
  folder) loses no finished result and leaves no half folder, staging folder or lock; the re-run
  completes the rest;
* issue 27: scans named after the batch's own files; Ctrl-C (SIGINT to the process group) while
  the cluster starts, while scans run and before the final renames: exit 130, one stderr line, no
  process left, ``OUT`` as the rule in docs/localization.md says.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import require_extra

require_extra("distributed")

from minegeo.cli import main  # noqa: E402
from minegeo.localize.batch import SUMMARY_COLUMNS, comparable_record, summary_columns  # noqa: E402

FAST = ["--profile", "fast"]
SEED = 7


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The small synthetic mine (5 scans) and its map prepared with --profile fast."""
    from minegeo.synth import write_world

    d = tmp_path_factory.mktemp("batch_world")
    write_world(d / "mine", "small", SEED)
    assert main(["-q", "prepare-map", "--map", str(d / "mine" / "map.ply"), "--out", str(d / "map.npz"), *FAST]) == 0
    return {"mine": d / "mine", "map": d / "map.npz", "scans": d / "mine" / "scans"}


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 worker processes, one thread each; a dead worker's task is not retried
    (allowed-failures 0), so a kill shows as a lost scan. (A cluster started with distributed's
    defaults runs its workers with 1 BLAS thread: compare with ``OPENBLAS_NUM_THREADS=1 minegeo
    localize`` then.)"""
    import dask
    from dask.distributed import Client

    from minegeo.localize.batch import local_cluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        lc = local_cluster(2)  # a LocalCluster whose workers keep this process's BLAS threads
        client = Client(lc)
    try:
        yield lc, client
    finally:
        client.close()
        lc.close()


def _batch(world, out, *extra, scans=None):
    argv = ["-q", "localize-batch", "--map", str(world["map"]), "--scans", str(scans or world["scans"]),
            "--out", str(out), *FAST, *map(str, extra)]
    return main(argv)


def _tree(d: Path) -> dict:
    return {str(p.relative_to(d)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(d.rglob("*")) if p.is_file() and ".map_cache" not in p.parts}


def _json(p: Path) -> dict:
    return json.loads(p.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def batch_out(world, cluster, tmp_path_factory):
    """One batch of the 5 scans on the module's cluster (--scheduler ADDRESS), seed 3."""
    out = tmp_path_factory.mktemp("batch") / "out"
    code = _batch(world, out, "--scheduler", cluster[0].scheduler_address, "--seed", 3)
    assert code in (0, 1)
    return out


def test_batch_equals_localize_one_by_one(world, batch_out, tmp_path):
    summary = list(csv.reader((batch_out / "summary.csv").read_text(encoding="utf-8").splitlines()))
    # the module's map is not georeferenced: map x, y, z, never headed E, N, H
    assert tuple(summary[0]) == ("scan", "status", "reason", "x", "y", "z", "heading", "radius95_m", "time_s")
    assert summary_columns(True) == SUMMARY_COLUMNS and SUMMARY_COLUMNS[3:6] == ("E", "N", "H")
    rows = {Path(r[0]).stem: dict(zip(summary[0], r, strict=True)) for r in summary[1:]}
    assert sorted(rows) == [f"scan_{i:02d}" for i in range(5)]
    n_ok = 0
    for name, row in rows.items():
        one = tmp_path / name
        code = main(["-q", "localize", "--map", str(world["map"]), "--scan", row["scan"], "--out", str(one), "--seed",
                     "3", *FAST])
        a, b = _json(batch_out / name / "result.json"), _json(one / "result.json")
        assert (code == 0) == (a["status"] == "ok")
        # everything but the timings and the batch's own record is the same JSON text
        assert json.dumps(comparable_record(a)) == json.dumps(comparable_record(b)), name
        assert set(a) - set(b) == {"batch"} and not set(b) - set(a)
        # the batch records its options once, in batch_result.json; localize in each record
        assert a["provenance"] == {"arguments": None} and b["provenance"]["arguments"]["scan"] == row["scan"]
        assert a["T_map_scan"] == b["T_map_scan"] and a["covariance_6x6"] == b["covariance_6x6"]
        assert row["status"] == a["status"]
        if a["status"] == "ok":
            n_ok += 1
            assert float(row["x"]) == pytest.approx(a["T_map_scan"][0][3], abs=1e-4)
            assert float(row["radius95_m"]) == pytest.approx(a["position_95_radius_m"], abs=1e-4)
        else:
            assert row["x"] == "" and row["radius95_m"] == ""
    assert n_ok >= 3
    rec = _json(batch_out / "batch_result.json")
    assert rec["seed"] == 3 and {"minegeo", "numpy"} <= set(rec["versions"])
    assert rec["inputs"][0]["sha256"] == hashlib.sha256(world["map"].read_bytes()).hexdigest()
    assert rec["counts"]["ok"] == n_ok and rec["n_run"] == 5 and rec["n_resumed"] == 0
    html = (batch_out / "report.html").read_text(encoding="utf-8")
    assert 'data-status="' in html and "data:image/png;base64," in html


def test_driver_environment_and_numba_untouched(world, batch_out, tmp_path):
    """distributed writes its spawn environment into the driver's ``os.environ``; a
    ``NUMBA_NUM_THREADS`` left there made Numba refuse every later compilation in this process
    ("Cannot set NUMBA_NUM_THREADS ... once the threads have been launched"). After a local
    cluster (the CLI's own, --workers 2) the driver still compiles and runs parallel kernels."""
    import numba

    before = os.environ.get("NUMBA_NUM_THREADS")
    assert _batch(world, tmp_path / "out2", "--workers", 2, "--seed", 3) in (0, 1)
    assert os.environ.get("NUMBA_NUM_THREADS") == before

    @numba.njit(parallel=True)
    def _fresh(x):  # a new function: compiling it reloads Numba's configuration from os.environ
        s = 0.0
        for i in numba.prange(x.shape[0]):
            s += x[i]
        return s

    assert _fresh(np.ones(1000)) == 1000.0
    # the two local workers' results equal the 2-worker scheduler batch
    for d in sorted((tmp_path / "out2").iterdir()):
        if d.is_dir() and (d / "result.json").is_file():
            assert comparable_record(_json(d / "result.json")) == comparable_record(_json(batch_out / d.name / "result.json"))


def test_batch_dxf_reads_back_every_ok_scan(world, batch_out, cluster, tmp_path):
    """``--dxf``: placements.dxf holds one origin, one 95 % ellipse and one label per ``ok`` scan, at
    the scan origin its result.json states (map frame here: the synthetic map is not georeferenced),
    to the millimetre (in fact exactly); failed and ambiguous scans are not drawn. The run resumes
    every scan of ``batch_out`` (same map, options and seed) and only adds the drawing."""
    ezdxf = require_extra("ezdxf")
    out = tmp_path / "out"
    shutil.copytree(batch_out, out)
    assert _batch(world, out, "--scheduler", cluster[0].scheduler_address, "--seed", 3, "--dxf") in (0, 1)
    rec = _json(out / "batch_result.json")
    assert rec["n_run"] == 0 and rec["dxf"]["file"] == "placements.dxf"
    want = {}
    for r in rec["scans"]:
        d = _json(out / r["folder"] / "result.json")
        if d["status"] == "ok":
            want[r["name"]] = np.asarray(d.get("T_crs_scan") or d["T_map_scan"])[:3, 3]
    assert want, "no ok scan to draw"
    msp = ezdxf.readfile(out / "placements.dxf").modelspace()
    labels = {t.dxf.text: np.array(tuple(t.dxf.insert)) for t in msp.query('TEXT[layer=="MINEGEO_LABELS"]')}
    origins = np.array([tuple(e.dxf.location) for e in msp.query('POINT[layer=="MINEGEO_SCAN_ORIGINS"]')])
    assert sorted(labels) == sorted(want)
    assert len(origins) == len(want) and len(msp.query('POLYLINE[layer=="MINEGEO_ELLIPSE95"]')) == len(want)
    for name, xyz in want.items():
        assert np.abs(labels[name] - xyz).max() < 1e-3
        assert np.min(np.abs(origins - xyz).max(axis=1)) < 1e-3


def test_mmap_map_gives_the_same_localization(world, batch_out):
    """The worker's map (arrays memory-mapped from OUT/.map_cache) equals the prepared file's."""
    import numpy as np

    from minegeo.io import read_point_cloud
    from minegeo.localize import LocalizeParams, localize_scan
    from minegeo.localize.batch import _MAPS, worker_map
    from minegeo.localize.prepared import CORE_ARRAYS, PreparedMap

    cache = next((batch_out / ".map_cache").iterdir())
    lp = LocalizeParams.fast()
    pm, _, _ = worker_map(cache, lp)
    try:
        ref = PreparedMap.load(world["map"])
        for k in CORE_ARRAYS:
            a = getattr(pm, k)
            assert isinstance(a.base, np.memmap) or isinstance(a, np.memmap), k
            assert np.array_equal(a, getattr(ref, k)), k
        assert worker_map(cache, lp)[0] is pm  # once per process
        scan = read_point_cloud(world["scans"] / "scan_01.ply")
        r1, r2 = localize_scan(pm, scan, None, lp, seed=0), localize_scan(ref, scan, None, lp, seed=0)
        assert json.dumps(comparable_record(r1.to_dict())) == json.dumps(comparable_record(r2.to_dict()))
    finally:
        _MAPS.clear()


def test_bad_files_fail_and_the_batch_goes_on(world, tmp_path):
    """Unreadable (dangling link), empty, garbage and a text file: each a failed folder with the reason."""
    d = tmp_path / "scans"
    d.mkdir()
    shutil.copy2(world["scans"] / "scan_01.ply", d / "scan_01.ply")
    (d / "empty.ply").write_bytes(b"")
    (d / "garbage.ply").write_bytes(os.urandom(4096))
    (d / "notes.txt").write_text("site visit 12 May, no coordinates here\n", encoding="utf-8")
    (d / "gone.ply").symlink_to(tmp_path / "does_not_exist.ply")
    out = tmp_path / "out"
    assert _batch(world, out, "--workers", 1, scans=d) == 1
    reasons = {"empty": "empty", "garbage": "ply", "notes": "numeric", "gone": "no such file"}
    for name, word in reasons.items():
        r = _json(out / name / "result.json")
        assert r["status"] == "failed" and r["error"]["kind"] == "input", (name, r["reason"])
        assert word in r["reason"].lower(), (name, r["reason"])
        assert r["T_map_scan"] is None
        assert 'data-status="FAILED"' in (out / name / "report.html").read_text(encoding="utf-8")
    assert _json(out / "scan_01" / "result.json")["status"] == "ok"
    rows = list(csv.DictReader((out / "summary.csv").read_text(encoding="utf-8").splitlines()))
    assert len(rows) == 5 and sum(r["status"] == "failed" for r in rows) == 4
    assert not [p for p in out.rglob("*") if "minegeo-tmp" in p.name or p.name.endswith(".tmp")]


def test_resume_skips_complete_results(world, batch_out, cluster, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(batch_out, out)
    before = _tree(out)
    assert _batch(world, out, "--scheduler", cluster[0].scheduler_address, "--seed", 3) in (0, 1)
    after = _tree(out)
    scan_files = [k for k in before if "/" in k]
    assert all(after[k] == before[k] for k in scan_files)  # no scan folder touched
    rec = _json(out / "batch_result.json")
    assert rec["n_run"] == 0 and rec["n_resumed"] == 5
    # a scan folder without its result.json, and a scan whose file changed, are redone; the rest kept
    (out / "scan_02" / "result.json").unlink()
    scans = tmp_path / "scans"
    shutil.copytree(world["scans"], scans)
    with open(scans / "scan_04.ply", "ab") as fh:
        fh.write(b"\n")
    assert _batch(world, out, "--scheduler", cluster[0].scheduler_address, "--seed", 3, scans=scans) in (0, 1)
    rec = _json(out / "batch_result.json")
    redone = sorted(r["name"] for r in rec["scans"] if not r["resumed"])
    # scan paths changed (another folder): every record names its scan by SHA-256, so only the two are redone
    assert redone == ["scan_02", "scan_04"], redone
    now = _tree(out)
    for k in scan_files:
        if not k.startswith(("scan_02/", "scan_04/")):
            assert now[k] == before[k], k


def test_a_task_run_again_keeps_the_finished_folder(world, batch_out, cluster, tmp_path, monkeypatch):
    """Dask recomputes a finished task when the worker holding its result dies while the driver
    still holds the future; that second run (which may outlive the batch) must not rewrite the
    scan's finished folder. The task itself checks :func:`done_record` first."""
    from minegeo.cli.localize_batch import localize_task
    from minegeo.localize import batch as B

    out = tmp_path / "out"
    shutil.copytree(batch_out, out)
    seen = []
    orig = B.run_batch

    def spy(jobs, manifest, *a, **k):
        seen.extend(jobs)
        return orig(jobs, manifest, *a, **k)

    monkeypatch.setattr(B, "run_batch", spy)
    assert _batch(world, out, "--scheduler", cluster[0].scheduler_address, "--seed", 3) in (0, 1)
    before = _tree(out)
    job = next(j for j in seen if j.name == "scan_01")
    assert job.manifest is not None
    row = localize_task(job)  # as a recomputation on a worker would run it
    assert _tree(out) == before
    assert row == B.summary_row(job, _json(out / "scan_01" / "result.json"))
    # an incomplete folder (its report missing) is not done: the task runs and rewrites it
    (out / "scan_01" / "report.html").unlink()
    localize_task(job)
    assert _tree(out)["scan_01/result.json"] != before["scan_01/result.json"]


def test_out_of_another_map_is_refused(world, batch_out, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(batch_out, out)
    before = _tree(out)
    other = tmp_path / "other.npz"
    shutil.copy2(world["map"], other)
    with open(other, "ab") as fh:  # another file (SHA-256) of the same map: a zip reads past the tail
        fh.write(b"\0")
    capsys.readouterr()
    code = main(["localize-batch", "--map", str(other), "--scans", str(world["scans"]), "--out", str(out), *FAST,
                 "--seed", "3"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and "another map" in err[0], err
    assert _tree(out) == before


def _kill_on(name):
    """Installed in every worker: the worker process dies (os._exit) while it writes scan ``name``
    (inside its staged result folder, holding the folder's lock)."""
    import minegeo.cli.localize as L

    orig = getattr(L, "_unpatched_localize_and_write", L.localize_and_write)
    L._unpatched_localize_and_write = orig

    def write(stage, *a, **k):
        if Path(stage).name.startswith(f".{name}."):
            (Path(stage) / "partial.txt").write_text("a half-written result\n", encoding="utf-8")
            os._exit(13)
        return orig(stage, *a, **k)

    L.localize_and_write = write
    return os.getpid()


def _unkill():
    import minegeo.cli.localize as L

    L.localize_and_write = getattr(L, "_unpatched_localize_and_write", L.localize_and_write)


def _on_workers(client, fn, *args):
    import sys

    import cloudpickle

    mod = sys.modules[__name__]
    cloudpickle.register_pickle_by_value(mod)
    try:
        return client.run(fn, *args)
    finally:
        cloudpickle.unregister_pickle_by_value(mod)


def test_worker_killed_mid_batch_then_rerun_completes(world, cluster, tmp_path):
    lc, client = cluster
    client.wait_for_workers(2, timeout=60)
    assert len(set(_on_workers(client, _kill_on, "scan_03").values())) == 2
    out = tmp_path / "out"
    try:
        assert _batch(world, out, "--scheduler", lc.scheduler_address) == 1
    finally:
        client.wait_for_workers(2, timeout=60)
        _on_workers(client, _unkill)
    rec = _json(out / "scan_03" / "result.json")
    assert rec["status"] == "failed" and rec["error"]["kind"] == "crash", rec["reason"]
    first = _json(out / "batch_result.json")
    crashed = sorted(r["name"] for r in first["scans"] if r["error_kind"] == "crash")
    assert "scan_03" in crashed and len(crashed) < 5
    # the dead worker's staging folder and lock are removed when the batch ends (nothing
    # half-written is in scan_03/ or anywhere in OUT)
    assert not [p.name for p in out.iterdir() if ".minegeo-" in p.name]
    assert not (out / "scan_03" / "partial.txt").exists()
    finished = {k: v for k, v in _tree(out).items() if "/" in k and k.split("/")[0] not in crashed
                and not k.startswith(".")}
    assert sum(1 for k in finished if k.endswith("result.json")) == 5 - len(crashed)
    assert _batch(world, out, "--scheduler", lc.scheduler_address) in (0, 1)
    after = _tree(out)
    changed = sorted(k for k, v in finished.items() if after.get(k) != v)
    assert not changed, f"finished results touched by the re-run: {changed} (crashed: {crashed})"  # untouched
    r = _json(out / "batch_result.json")
    assert r["n_run"] == len(crashed) and r["n_resumed"] == 5 - len(crashed)
    assert not [x for x in r["scans"] if x["error_kind"] == "crash"]
    assert "error" not in _json(out / "scan_03" / "result.json")
    assert not [p.name for p in out.iterdir() if "minegeo-tmp" in p.name or p.name.endswith("minegeo-lock")]


def test_without_dask_one_clear_line(world, tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n in ("dask", "distributed") else real(n, *a))
    capsys.readouterr()
    code = main(["localize-batch", "--map", str(world["map"]), "--scans", str(world["scans"]), "--out",
                 str(tmp_path / "o"), *FAST])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and "minegeo[dask]" in err[0], err
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------------- issue 27


def test_scan_names_never_take_the_batchs_own_names(world, cluster, tmp_path):
    """Scans named after the batch's own files (``summary.csv.ply``, ``report.html.ply``) get
    folders of their whole file names; the batch's summary, report and record are written
    (before: every scan ran, then "Is a directory: .../summary.csv")."""
    from minegeo.localize.batch import RESERVED_NAMES, result_names

    d = tmp_path / "scans"
    d.mkdir()
    shutil.copy2(world["scans"] / "scan_00.ply", d / "summary.csv.ply")
    shutil.copy2(world["scans"] / "scan_01.ply", d / "report.html.ply")
    out = tmp_path / "out"
    assert _batch(world, out, "--scheduler", cluster[0].scheduler_address, scans=d) in (0, 1)
    rec = _json(out / "batch_result.json")
    assert sorted(r["folder"] for r in rec["scans"]) == ["report.html.ply", "summary.csv.ply"]
    assert (out / "summary.csv").is_file() and (out / "report.html").is_file()
    assert _json(out / "summary.csv.ply" / "result.json")["inputs"][1]["path"] == str(d / "summary.csv.ply")
    # the mapping alone, on names a hand-made list says must not collide (case ignored)
    scans = [f"a/{n}.ply" for n in RESERVED_NAMES] + ["a/X.ply", "b/x.las", "a/x_2.ply", "c/x.ply", "d/.hidden.ply"]
    names = result_names(scans)
    assert len({n.casefold() for n in names}) == len(scans)
    assert not {n.casefold() for n in names} & {r.casefold() for r in RESERVED_NAMES}
    assert not [n for n in names if n.startswith(".")]


def _tree_all(d: Path) -> dict:
    """Every entry under ``d`` (hidden ones and the map cache included): kind, bytes, mtime."""
    if not d.exists():
        return {}
    return {str(p.relative_to(d)): ("dir",) if p.is_dir() else (hashlib.sha256(p.read_bytes()).hexdigest(),
                                                                p.stat().st_mtime_ns)
            for p in sorted(d.rglob("*"))}


def _interrupt_at(stage: str, world, out: Path, tmp_path: Path, *extra) -> tuple[int, list[str]]:
    """Run the CLI in its own process group (as a terminal runs it), wait until it reaches
    ``stage`` (:func:`minegeo.localize.batch.pause_for_test`), then send SIGINT to the whole group
    as Ctrl-C does. Returns (exit status, non-empty stderr lines); asserts no process is left."""
    import signal
    import subprocess
    import sys
    import time

    ready = tmp_path / f"ready-{stage}"
    env = dict(os.environ, MINEGEO_TEST_BATCH_PAUSE=stage, MINEGEO_TEST_BATCH_READY=str(ready))
    argv = [sys.executable, "-m", "minegeo", "localize-batch", "--map", str(world["map"]), "--scans",
            str(world.get("two", world["scans"])), "--out", str(out), *FAST, *map(str, extra)]
    p = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        t0 = time.monotonic()
        while not ready.exists() and p.poll() is None and time.monotonic() - t0 < 300:
            time.sleep(0.05)
        assert ready.exists(), f"never reached {stage}: {p.poll()} {p.stderr.read() if p.poll() is not None else ''}"
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    time.sleep(0.5)
    ps = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-g", str(p.pid)], capture_output=True, text=True).stdout
    left = [ln for ln in ps.splitlines() if ln.split()[1:2] and not ln.split()[1].startswith("Z")]
    assert not left, f"processes of the run still alive: {left}"  # (an exited, unreaped child is not)
    return p.returncode, [ln for ln in err.splitlines() if ln.strip()]


@pytest.fixture(scope="module")
def two(world, tmp_path_factory):
    """The world with a scans folder of 2 scans (the interrupted runs)."""
    d = tmp_path_factory.mktemp("two") / "scans"
    d.mkdir()
    for i in (0, 1):
        shutil.copy2(world["scans"] / f"scan_{i:02d}.ply", d / f"scan_{i:02d}.ply")
    return {**world, "two": d}


def _assert_rule(out: Path, before: dict, names=("scan_00", "scan_01")) -> list[str]:
    """OUT after an interrupted run: as before, plus complete scan folders this run added, plus
    the manifest when it added one to an OUT without one; nothing hidden of a run (docs rule)."""
    after = _tree_all(out)
    added = sorted({k.split("/")[0] for k in after if k not in before or after[k] != before[k]}
                   - {"batch_manifest.json"})
    assert set(added) <= set(names), f"entries this run left: {added}"
    for n in added:  # each complete, as minegeo localize writes it
        assert {"result.json", "report.html"} <= {p.name for p in (out / n).iterdir()}, n
        assert _json(out / n / "result.json")["status"] in ("ok", "ambiguous", "failed")
    assert not [k for k in before if k not in after], "an entry of the earlier OUT was removed"
    manifest_new = "batch_manifest.json" in after and "batch_manifest.json" not in before
    assert manifest_new == bool(added and "batch_manifest.json" not in before)
    if "batch_manifest.json" in before:
        assert after["batch_manifest.json"] == before["batch_manifest.json"]
    leftovers = [p.name for p in out.parent.iterdir() if ".minegeo-" in p.name]
    leftovers += [k for k in after if ".minegeo-" in k or k not in before and k.startswith(".map_cache")]
    assert not leftovers, leftovers
    return added


@pytest.mark.parametrize("stage", ["cluster-start", "scans"])
def test_ctrl_c_leaves_out_as_it_was(stage, two, tmp_path):
    """Issue 27 case 3: Ctrl-C (SIGINT to the whole process group, workers included) while the
    local cluster starts and while scans run (the first scan done): exit 130, one line, no worker
    traceback, no process left; OUT follows the rule: absent after an interrupted start, else only
    complete scan folders and their manifest (no lock, staging folder, map cache or summary)."""
    out = tmp_path / "out"
    code, err = _interrupt_at(stage, two, out, tmp_path, "--workers", 1 if stage == "cluster-start" else 2)
    assert code == 130 and err == ["minegeo localize-batch: interrupted"], err
    if stage == "cluster-start":
        assert sorted(p.name for p in tmp_path.iterdir()) == [f"ready-{stage}"]
    else:
        added = _assert_rule(out, {})
        assert "scan_00" in added  # the scan that finished before the Ctrl-C is kept
        assert _batch(two, out, "--workers", 2, scans=two["two"]) in (0, 1)  # and the re-run resumes it
        assert _json(out / "batch_result.json")["n_resumed"] == len(added)


def test_ctrl_c_before_the_commit_leaves_an_earlier_batch(two, batch_out, tmp_path):
    """Ctrl-C once every scan is done, before the summary, report and record are renamed into
    place, on an OUT of an earlier batch (one of its scan folders deleted, so this run adds it):
    every earlier file byte-identical (mtimes too), the added scan folder complete, nothing else."""
    out = tmp_path / "out"
    shutil.copytree(batch_out, out)
    for n in ("scan_02", "scan_03", "scan_04"):
        shutil.rmtree(out / n)
    shutil.rmtree(out / "scan_01")
    before = _tree_all(out)
    code, err = _interrupt_at("commit", two, out, tmp_path, "--workers", 1, "--seed", 3)
    assert code == 130 and err == ["minegeo localize-batch: interrupted"], err
    assert _assert_rule(out, before) == ["scan_01"]


def test_batch_repeated_from_its_batch_result_json(world, batch_out, tmp_path):
    """``--config batch_result.json`` runs the same batch again: every scan's record the same JSON text
    but for timings, the summary the same but for its time column."""
    rec = batch_out / "batch_result.json"
    assert _json(rec)["provenance"]["arguments"]["seed"] == 3
    again = tmp_path / "again"
    assert main(["-q", "localize-batch", "--config", str(rec), "--out", str(again)]) in (0, 1)
    names = sorted(p.name for p in batch_out.iterdir() if (p / "result.json").is_file())
    assert len(names) == 5 and names == sorted(p.name for p in again.iterdir() if (p / "result.json").is_file())
    for n in names:
        a, b = _json(batch_out / n / "result.json"), _json(again / n / "result.json")
        assert json.dumps(comparable_record(a)) == json.dumps(comparable_record(b)), n

    def rows(d):
        r = list(csv.reader((d / "summary.csv").read_text(encoding="utf-8").splitlines()))
        t = r[0].index("time_s")
        return [x[:t] + x[t + 1:] for x in r]
    assert rows(batch_out) == rows(again)
