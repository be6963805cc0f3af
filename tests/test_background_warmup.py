"""The demo's background compilation (:mod:`minegeo._background_warmup`): a second process compiles into
its own cache folder, and only the kernels this process has no cache entry for are copied in, each
loaded afterwards from the cache (no compilation here) with the same results; a child that fails is
reported and changes nothing.

The positive cases run in a fresh interpreter with an empty ``NUMBA_CACHE_DIR`` (the test process's
own cache is warm): one child compiles ``minegeo.mast`` (a few seconds)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from minegeo import _background_warmup as BW

SCRIPT = textwrap.dedent("""
    import json, os, sys
    import numpy as np
    from minegeo import _background_warmup as BW
    from minegeo.mast import _kernels as K

    out = {}
    sentinel = (("minegeo.mast._kernels", "_grow_segments"),)
    segs = np.array([[1.0, -1.0, 1.0, 1.0], [2.0, -1.0, 2.0, 1.0]])
    dirs = np.array([[1.0, 0.0], [0.0, 1.0]])
    if sys.argv[1] == "own-first":  # this process compiles one kernel before the child's cache arrives
        K._cast_rays(np.zeros(2), dirs, segs, 10.0)
    before = {f: BW.is_cached("minegeo.mast._kernels", f) for f in ("_cast_rays", "_grow_segments")}
    ipath = K._cast_rays._cache._cache_file._index_path
    st = os.stat(ipath) if before["_cast_rays"] else None
    own = (st.st_ino, st.st_mtime_ns) if st else None
    bg = BW.start(["minegeo.mast"], sentinel)
    out["started"] = bg is not None
    rec = bg.merge(timeout_s=300)
    out["record"] = rec
    out["folder_removed"] = not bg.folder.exists()
    out["before"] = before
    out["after"] = {f: BW.is_cached("minegeo.mast._kernels", f) for f in ("_cast_rays", "_grow_segments")}
    if own is not None:
        st = os.stat(ipath)
        out["own_index_kept"] = (st.st_ino, st.st_mtime_ns) == own  # the very same file, not rewritten
    xy = np.column_stack([np.linspace(0, 1, 8), np.zeros(8)])
    se = K._grow_segments(xy, np.full(8, 0.01), np.full(8, 1.0), 3, 2, 3)
    out["segments"] = np.asarray(se).tolist()
    out["hits"] = sum(K._grow_segments.stats.cache_hits.values())
    out["misses"] = sum(K._grow_segments.stats.cache_misses.values())
    out["again"] = BW.start(["minegeo.mast"], sentinel) is None  # now cached: nothing to do
    print(json.dumps(out))
""")


def _run(tmp_path, mode: str) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    r = subprocess.run([sys.executable, "-c", SCRIPT, mode], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_childs_kernels_are_copied_and_loaded_from_the_cache(tmp_path):
    out = _run(tmp_path, "cold")
    assert out["started"] and out["record"]["status"] == "ok" and out["folder_removed"]
    assert out["before"] == {"_cast_rays": False, "_grow_segments": False}
    assert out["after"] == {"_cast_rays": True, "_grow_segments": True}
    assert out["record"]["functions_copied"] >= 4  # the four mast kernels
    # loaded from the copied cache: no compilation in this process
    assert out["hits"] == 1 and out["misses"] == 0
    # the same answer as a kernel compiled here
    import numpy as np

    from minegeo.mast import _kernels as K

    xy = np.column_stack([np.linspace(0, 1, 8), np.zeros(8)])
    assert out["segments"] == np.asarray(K._grow_segments(xy, np.full(8, 0.01), np.full(8, 1.0), 3, 2, 3)).tolist()
    assert out["again"]


@pytest.mark.slow
def test_a_kernel_this_process_cached_itself_is_not_overwritten(tmp_path):
    out = _run(tmp_path, "own-first")
    assert out["before"] == {"_cast_rays": True, "_grow_segments": False}
    assert out["own_index_kept"]
    assert out["after"]["_grow_segments"] and out["hits"] == 1 and out["misses"] == 0


def test_a_failing_child_is_reported_and_nothing_is_copied(tmp_path):
    bg = BW.start(["minegeo.no_such_package"])
    assert bg is not None
    rec = bg.merge(timeout_s=120)
    assert rec["status"].startswith("failed (exit ") and rec["functions_copied"] == 0
    assert not bg.folder.exists()


def test_nothing_starts_when_the_sentinels_are_cached():
    import numpy as np

    from minegeo.registration import _kernels as K

    K.finite_max_abs(np.zeros((2, 3)))  # compiled or loaded: its index is in this process's cache
    assert BW.is_cached("minegeo.registration._kernels", "finite_max_abs")
    assert BW.start(["minegeo.mast"], (("minegeo.registration._kernels", "finite_max_abs"),)) is None


def test_warmup_rejects_an_unknown_module():
    import minegeo
    from minegeo.errors import InputError

    with pytest.raises(InputError, match="unknown warm-up module"):
        minegeo.warmup(modules=["minegeo.nope"])


@pytest.mark.slow
def test_the_child_stops_and_cleans_up_when_its_parent_dies(tmp_path):
    import signal
    import time

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    parent = subprocess.Popen(
        [sys.executable, "-c", "import time; from minegeo import _background_warmup as BW; "
         "bg = BW.start(['minegeo.localize']); print(bg.folder, bg.proc.pid, flush=True); time.sleep(120)"],
        env=env, stdout=subprocess.PIPE, text=True)
    folder, pid = parent.stdout.readline().split()
    assert os.path.isdir(folder)
    worker = ""
    for _ in range(200):  # the supervisor starts the compiling worker at once
        worker = open(f"/proc/{pid}/task/{pid}/children").read().split()
        if worker:
            break
        time.sleep(0.05)
    assert len(worker) == 1
    time.sleep(2.0)  # the worker is compiling (localize takes ~45 s)
    parent.send_signal(signal.SIGKILL)
    parent.wait()

    def state(p):  # a zombie is reaped by init; /proc/PID of a zombie still exists briefly
        return open(f"/proc/{p}/stat").read().split()[2] if os.path.exists(f"/proc/{p}") else "gone"

    for _ in range(480):  # up to 120 s, a hang guard (the supervisor polls every 0.25 s)
        if state(pid) in ("gone", "Z") and state(worker[0]) in ("gone", "Z") and not os.path.isdir(folder):
            break
        time.sleep(0.25)
    assert state(pid) in ("gone", "Z") and state(worker[0]) in ("gone", "Z") and not os.path.isdir(folder)


def test_warmup_verb_takes_modules(capsys):
    from minegeo.cli import main

    assert main(["warmup", "--module", "minegeo.survey"]) == 0
    out = capsys.readouterr().out
    assert "minegeo.survey" in out and "minegeo.slam" not in out
    assert main(["warmup", "--module", "minegeo.nope"]) == 2
    assert "unknown warm-up module" in capsys.readouterr().err


def test_nothing_starts_on_one_cpu_core(monkeypatch):
    monkeypatch.setattr(BW, "usable_cpus", lambda: 1)
    assert "one CPU core" in BW.reason_not_to_start()
    assert BW.start(["minegeo.mast"]) is None



WRITER = textwrap.dedent("""
    import os, sys, time
    cache = os.path.join(sys.argv[1], "cache")
    i = 0
    while True:  # like Numba: (re)creates its cache folder and writes files into it, without pause
        try:
            os.makedirs(cache, exist_ok=True)
            with open(os.path.join(cache, f"f{i % 50}.nbc"), "wb") as f:
                f.write(b"x" * 4096)
        except OSError:
            pass
        i += 1
""")


def test_the_folder_is_removed_after_the_writing_worker_is_dead(tmp_path):
    # the supervisor of a dead parent kills a worker that never stops writing into the folder, then removes it
    import signal
    import time

    folder = tmp_path / "warm"
    folder.mkdir()
    sup = (f"import sys; from pathlib import Path; from minegeo._background_warmup import _supervise; "
           f"_supervise(Path({str(folder)!r}), [], worker_argv=[sys.executable, '-c', {WRITER!r}, {str(folder)!r}])")
    parent = subprocess.Popen(
        [sys.executable, "-c", f"import subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', {sup!r}]); "
         "print(p.pid, flush=True); time.sleep(120)"], stdout=subprocess.PIPE, text=True)
    pid = parent.stdout.readline().strip()
    for _ in range(400):
        if (folder / "cache").is_dir() and len(list((folder / "cache").iterdir())) >= 10:
            break
        time.sleep(0.05)
    worker = open(f"/proc/{pid}/task/{pid}/children").read().split()
    assert len(worker) == 1
    parent.send_signal(signal.SIGKILL)
    parent.wait()

    def state(p):
        return open(f"/proc/{p}/stat").read().split()[2] if os.path.exists(f"/proc/{p}") else "gone"

    for _ in range(240):  # up to 60 s, a hang guard
        if state(pid) in ("gone", "Z") and state(worker[0]) in ("gone", "Z"):
            break
        time.sleep(0.25)
    time.sleep(0.5)  # a writer left alive would have recreated the folder by now
    assert state(pid) in ("gone", "Z") and state(worker[0]) in ("gone", "Z") and not folder.exists()
