"""Compile Numba kernels in a second process while this one works (a cold start on two cores).

Numba compiles on one core, and on a fresh install compilation is most of a first run (the demo:
111 s of 126 s). :func:`start` launches ``python -m minegeo._background_warmup`` that runs
:func:`minegeo.warmup` for the given subpackages **into a private cache folder** (its own
``NUMBA_CACHE_DIR``); :meth:`BackgroundWarmup.merge` later waits for it and copies the cache
entries of every kernel this process has no cache entry for into this process's own Numba cache.

Why a private folder: Numba's cache index of a function is read, extended and rewritten by the
process that compiles it; two processes adding *different* signatures of one function at the
same moment can leave an index naming the other's code. Here only this process ever writes its
cache, and only between steps (never while compiling): an index is copied after all the data
files it names, each file by an atomic rename, and only when this cache has no index for that
function yet. A kernel loaded from the copied cache is the same machine code the other process
compiled from the same source (Numba checks the source file's stamp and the CPU in the index);
results are bit-identical to compiling here.

The child is two processes in their own process group: a supervisor and the worker that
compiles. When the process that started them dies without merging, the supervisor kills the
worker, waits for it, and only then removes the folder (removing it while the worker still writes
cache files would leave it behind); :meth:`BackgroundWarmup.cancel` kills the whole group.

Speed only: when the child cannot start, fails, or is not finished in time, this process simply
compiles what it needs itself.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"


def _dispatchers(module_name: str):
    """The cached Numba dispatchers defined in module ``module_name`` (imported)."""
    mod = importlib.import_module(module_name)
    for obj in vars(mod).values():
        cache = getattr(obj, "_cache", None)
        py = getattr(obj, "py_func", None)
        if cache is not None and py is not None and py.__module__ == module_name and hasattr(cache, "_cache_path"):
            yield obj


def _kernel_modules() -> list[str]:
    """Names of the loaded ``minegeo`` modules that define cached Numba kernels."""
    out = []
    for name in sorted(sys.modules):
        if (name == "minegeo" or name.startswith("minegeo.")) and next(_dispatchers(name), None) is not None:
            out.append(name)
    return out


def cache_path_of(module_name: str) -> str | None:
    """This process's Numba cache folder for the kernels of ``module_name`` (None without any)."""
    d = next(_dispatchers(module_name), None)
    return None if d is None else str(d._cache._cache_path)


def is_cached(module_name: str, function: str) -> bool:
    """True when this process's Numba cache holds entries for ``module_name.function`` that are valid
    for its current source (Numba ignores an index whose source stamp or Numba version differs)."""
    obj = getattr(importlib.import_module(module_name), function)
    try:
        return bool(obj._cache._cache_file._load_index())
    except (OSError, EOFError, pickle.UnpicklingError):
        return False


@dataclass
class BackgroundWarmup:
    """A running background compilation (see the module docstring)."""

    modules: tuple[str, ...]
    folder: Path
    proc: subprocess.Popen
    t_start: float = field(default_factory=time.perf_counter)
    record: dict = field(default_factory=dict)

    def merge(self, timeout_s: float = 180.0) -> dict:
        """Wait (at most ``timeout_s``) for the child, copy its cache entries that this process lacks,
        remove its folder; returns the record ``{modules, status, seconds, waited_s, functions_copied}``."""
        if self.record:
            return self.record
        t0 = time.perf_counter()
        try:
            rc = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            rc = None
            self._stop()
        waited = time.perf_counter() - t0
        copied = 0
        status = "ok"
        if rc is None:
            status = f"not finished after {timeout_s:.0f} s: stopped, kernels compiled here"
        elif rc != 0:
            status = f"failed (exit {rc}): kernels compiled here"
        else:
            try:
                copied = _merge_caches(self.folder)
            except (OSError, ValueError, pickle.UnpicklingError, ImportError) as e:  # speed only
                status = f"cache not merged ({e}): kernels compiled here"
        if status != "ok":
            log.warning("background compilation: %s", status)
        _remove(self.folder)
        self.record = {"modules": list(self.modules), "status": status,
                       "seconds": time.perf_counter() - self.t_start, "waited_s": waited,
                       "functions_copied": copied}
        return self.record

    def _stop(self) -> None:
        """Kill the child's process group (its supervisor and the compiling worker, see :func:`_main`)."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (AttributeError, ProcessLookupError, PermissionError):  # no process groups here
                self.proc.kill()
            self.proc.wait()

    def cancel(self) -> None:
        """Stop the child (if running) and remove its folder, without merging."""
        self._stop()
        _remove(self.folder)
        if not self.record:
            self.record = {"modules": list(self.modules), "status": "cancelled",
                           "seconds": time.perf_counter() - self.t_start, "waited_s": 0.0, "functions_copied": 0}


def usable_cpus() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def reason_not_to_start(sentinels=()) -> str | None:
    """Why a second compiling process would not help (None: it would): the JIT is off, only one CPU
    core is usable (the two processes would share it: slower than compiling here), or every
    ``(module, function)`` of ``sentinels`` is already in this process's Numba cache."""
    import numba

    if numba.config.DISABLE_JIT:
        return "not started (Numba JIT disabled)"
    if usable_cpus() < 2:
        return "not started (one CPU core: a second process would compete with this one)"
    try:
        if sentinels and all(is_cached(m, f) for m, f in sentinels):
            return "not needed (kernels already cached)"
    except (AttributeError, ImportError) as e:
        return f"not started (cache not readable: {e})"
    return None


def start(modules, sentinels=()) -> BackgroundWarmup | None:
    """Start compiling the kernels of ``modules`` (names of :data:`minegeo._WARMUP_MODULES`) in a
    second process; None when :func:`reason_not_to_start` gives a reason or the process cannot start."""
    why = reason_not_to_start(sentinels)
    if why is not None:
        log.info("background compilation %s", why)
        return None
    return launch(modules)


def launch(modules) -> BackgroundWarmup | None:
    """Start the second process without the checks of :func:`reason_not_to_start` (for a caller that
    made them); None when it cannot start."""
    folder = Path(tempfile.mkdtemp(prefix="minegeo-warmup-"))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder / "cache")}
    cmd = [sys.executable, "-m", "minegeo._background_warmup", str(folder), *modules]
    try:
        proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError as e:
        log.info("background compilation not started: %s", e)
        shutil.rmtree(folder, ignore_errors=True)
        return None
    log.info("background compilation of %s started (pid %d)", ", ".join(modules), proc.pid)
    return BackgroundWarmup(tuple(modules), folder, proc)


def _index_data_names(index: Path) -> list[str] | None:
    """The data-file names an index lists (Numba's format: pickled version, then the pickled
    ``(source stamp, {key: data name})``); None when it is of another Numba version."""
    import numba

    with open(index, "rb") as f:
        version = pickle.load(f)
        rest = f.read()
    if version != numba.__version__:
        return None
    _stamp, overloads = pickle.loads(rest)
    return sorted(set(overloads.values()))


def _copy_atomic(src: Path, dst: Path) -> None:
    tmp = dst.with_name(f"{dst.name}.tmp.{uuid.uuid4().hex[:16]}")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _merge_caches(folder: Path) -> int:
    """Copy every function cache of the child (``folder/manifest.json``) whose index this process's
    cache lacks: data files first, the index last; returns the number of functions copied."""
    manifest = json.loads((folder / MANIFEST).read_text())
    pairs = set()
    for name, child_path in manifest.items():
        mine = cache_path_of(name)
        if mine is not None:
            pairs.add((Path(child_path), Path(mine)))
    copied = 0
    for src_dir, dst_dir in sorted(pairs):
        if not src_dir.is_dir() or src_dir == dst_dir:
            continue
        dst_dir.mkdir(parents=True, exist_ok=True)
        for index in sorted(src_dir.glob("*.nbi")):
            if (dst_dir / index.name).exists():
                continue  # this process has (or is making) its own entries for that function
            names = _index_data_names(index)
            if not names or not all((src_dir / n).is_file() for n in names):
                continue
            for n in names:
                _copy_atomic(src_dir / n, dst_dir / n)
            _copy_atomic(index, dst_dir / index.name)
            copied += 1
    return copied


def _remove(folder: Path) -> None:
    """Remove ``folder`` (a process that was writing into it is already dead; retried once for a
    file its last system call completed after the first pass)."""
    shutil.rmtree(folder, ignore_errors=True)
    if folder.exists():
        time.sleep(0.2)
        shutil.rmtree(folder, ignore_errors=True)


def _exit_when_orphaned(parent: int, poll_s: float = 0.5) -> None:
    """Worker thread: when the supervisor is gone, exit at once (whoever stopped it removes the folder)."""
    while True:
        time.sleep(poll_s)
        if os.getppid() != parent:
            os._exit(0)


def _work(folder: Path, modules: list[str]) -> int:
    """Worker: compile ``modules`` into this process's cache, then write ``folder/manifest.json``."""
    import threading

    threading.Thread(target=_exit_when_orphaned, args=(os.getppid(),), daemon=True).start()
    import minegeo

    minegeo.warmup(modules=modules)
    manifest = {name: cache_path_of(name) for name in _kernel_modules()}
    tmp = folder / f"{MANIFEST}.tmp"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, folder / MANIFEST)
    return 0


def _supervise(folder: Path, modules: list[str], poll_s: float = 0.25, worker_argv=None) -> int:
    """Supervisor: run the worker; when the process that started this one is gone (nobody will
    merge), kill the worker, wait for it, *then* remove the folder.

    The folder is removed only after the worker is dead: a worker still compiling would write new
    cache files into it while it is being removed and leave it behind."""
    parent = os.getppid()
    if worker_argv is None:  # (a test passes another worker)
        worker_argv = [sys.executable, "-m", "minegeo._background_warmup", "--work", str(folder), *modules]
    worker = subprocess.Popen(worker_argv, stdin=subprocess.DEVNULL)
    while True:
        try:
            rc = worker.wait(timeout=poll_s)
        except subprocess.TimeoutExpired:
            rc = None
        if os.getppid() != parent:
            if rc is None:
                worker.kill()
                worker.wait()
            _remove(folder)
            return 0
        if rc is not None:
            return rc


def _main(argv: list[str]) -> int:
    """``python -m minegeo._background_warmup FOLDER MODULE...`` (the supervisor) or
    ``... --work FOLDER MODULE...`` (the worker it starts)."""
    if argv[0] == "--work":
        return _work(Path(argv[1]), argv[2:])
    return _supervise(Path(argv[0]), argv[1:])


if __name__ == "__main__":
    raise SystemExit(_main(sys.argv[1:]))
