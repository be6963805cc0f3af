"""Safe outputs for every CLI verb: checked before any work, locked, staged, committed whole.

The contract a surveyor relies on (README, "Every CLI run ..."):

* **Inputs are never modified.** Every output path is checked against every input before
  anything is written: an output may not *be* an input (same path, symlink or hard link), may
  not lie *inside* an input folder, and an output folder that is replaced as a whole may not
  hold an input.
* **A result folder never mixes runs.** A verb writes its folder into a hidden staging folder
  next to it (``.NAME.minegeo-tmp-*``) and only when the run ends without an error is the
  staging folder renamed into place; an earlier result folder at that path is replaced as a
  whole. A run that stops with an error leaves the earlier folder exactly as it was and
  creates nothing new.
* **Single output files** (``--json``, a georeferenced map and its sidecar, a prepared map)
  are staged under their own names in a hidden folder ``.minegeo-tmp-*`` beside their target
  and moved into place together at the end, after every input has been validated.
* **Two runs never write one output.** Each target is locked by a lock file
  ``.NAME.minegeo-lock`` in its parent folder (created with ``O_EXCL``); a second run refuses
  with a message that names the other run's process. A lock left by a process that no longer
  runs (same host) is taken over with a warning.
* **Ctrl-C leaves nothing behind.** Creating a lock or a staging folder and recording it, the
  commit (the renames into place) and the cleanup run with SIGINT deferred
  (:func:`sigint_deferred`): a Ctrl-C that arrives there takes effect right after, so a lock or
  staging folder is always either recorded (and removed by the cleanup) or not created, and a
  commit is never half done: it is all in place, or none of it.

Usage in a verb::

    with OutputTransaction("localize", inputs={"--scan": scan, "--map": map_},
                           folders={"--out": out}) as tx:
        d = tx.folder("--out")            # staging folder: write everything here
        write_json_atomic(d / "result.json", ...)
    # committed here; on an exception nothing is left behind

:class:`RunClock` measures wall time and the part of it spent compiling Numba kernels
(``numba:compile`` events), so every result can report compile time apart from work time.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path

from minegeo.errors import OutputError

__all__ = ["OutputTransaction", "RunClock", "check_outputs", "is_result_folder", "run_timings", "progress_enabled",
           "output_lock", "sigint_deferred"]

log = logging.getLogger(__name__)

_LOCK_SUFFIX = ".minegeo-lock"
_TMP_TAG = ".minegeo-tmp-"
_OLD_TAG = ".minegeo-old-"


@contextmanager
def sigint_deferred():
    """Run a short critical section with SIGINT (Ctrl-C) held back until it ends.

    A SIGINT that arrives inside the block is recorded; when the block ends, the handler that was
    in force before is called with it (Python's default handler raises
    :class:`KeyboardInterrupt` there, after the block). Nested blocks defer to the outermost.
    Outside the main thread (a Dask worker's task thread, where Python never runs signal
    handlers) it does nothing. Keep the block short: a user's Ctrl-C waits for it.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def _hold(signum, frame):  # noqa: ARG001 - signal handler signature
        pending.append(signum)

    try:
        old = signal.signal(signal.SIGINT, _hold)
    except (ValueError, OSError):  # no signal handling here (an embedded interpreter)
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if pending:
            if callable(old):
                old(signal.SIGINT, None)
            elif old == signal.SIG_DFL:
                raise KeyboardInterrupt


def _real(p) -> Path:
    """Absolute path with symlinks resolved (the path need not exist)."""
    return Path(os.path.realpath(os.path.abspath(os.fspath(p))))


def _same_file(a: Path, b: Path) -> bool:
    if _real(a) == _real(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)  # hard links
    except OSError:
        return False


def _inside(child: Path, parent: Path) -> bool:
    """True when ``child`` lies strictly inside the folder ``parent`` (both resolved)."""
    c, p = _real(child), _real(parent)
    return c != p and p in c.parents


def is_result_folder(path) -> bool:
    """True for a folder that holds an earlier minegeo result (a parsable ``result.json`` object)."""
    f = Path(path) / "result.json"
    try:
        if not f.is_file() or f.stat().st_size > (256 << 20):
            return False
        with open(f, encoding="utf-8") as fh:
            head = fh.read(1)
        return head == "{"
    except (OSError, UnicodeDecodeError):
        return False


def check_outputs(inputs: Mapping[str, object], files: Mapping[str, object] = (),
                  folders: Mapping[str, object] = ()) -> None:
    """Refuse outputs that would touch an input (see the module docstring).

    Parameters
    ----------
    inputs : mapping
        ``{label: path}`` of every input (files or folders; ``None`` values are ignored). The
        label is how the user named it (``"--map"``, ``"NETWORK"``).
    files, folders : mapping
        ``{label: path}`` of the output files and of the output folders (replaced as a whole).

    Raises
    ------
    OutputError
        An output is an input, lies inside an input folder, is a folder where a file is expected
        (or the reverse), or an output folder holds an input.
    """
    ins = {k: Path(os.fspath(v)) for k, v in dict(inputs).items() if v is not None}
    files = {k: Path(os.fspath(v)) for k, v in dict(files or {}).items() if v is not None}
    folders = {k: Path(os.fspath(v)) for k, v in dict(folders or {}).items() if v is not None}
    for lab, out in list(files.items()) + list(folders.items()):
        for ilab, inp in ins.items():
            if _same_file(out, inp):
                raise OutputError(f"{lab} {out} is the input {ilab}: minegeo never overwrites an input; "
                                  "name a new output")
            if _inside(out, inp):
                raise OutputError(f"{lab} {out} lies inside the input folder {ilab} {inp}; "
                                  "write outputs somewhere else")
    for lab, out in files.items():
        if out.is_dir():
            raise OutputError(f"{lab} {out} is a folder; name a file")
        if out.parent.exists() and not out.parent.is_dir():
            raise OutputError(f"{lab} {out}: {out.parent} is not a folder")
    for lab, out in folders.items():
        if out.exists() and not out.is_dir():
            raise OutputError(f"{lab} {out} exists and is not a folder")
        for ilab, inp in ins.items():
            if _inside(inp, out):
                raise OutputError(f"the input {ilab} {inp} lies inside {lab} {out}, which this run replaces "
                                  "as a whole; move the input or choose another output folder")
    # a file may be written inside an output folder (it is staged with it); nothing else may overlap
    allpaths = [(lab, _real(p), False) for lab, p in files.items()] + \
        [(lab, _real(p), True) for lab, p in folders.items()]
    for i, (la, pa, da) in enumerate(allpaths):
        for lb, pb, db in allpaths[i + 1:]:
            if pa == pb or (da and db and (pa in pb.parents or pb in pa.parents)):
                raise OutputError(f"outputs {la} and {lb} overlap ({pa} / {pb}); give them separate paths")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class _Lock:
    """An ``O_EXCL`` lock file ``.NAME.minegeo-lock`` beside ``target``."""

    def __init__(self, target: Path, label: str, verb: str):
        self.target = target
        self.label = label
        self.verb = verb
        self.path = target.parent / f".{target.name}{_LOCK_SUFFIX}"
        self.held = False

    def acquire(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        info = {"pid": os.getpid(), "host": socket.gethostname(), "verb": self.verb,
                "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        for attempt in range(2):
            try:
                with sigint_deferred():  # created <=> recorded as held (released by the cleanup)
                    fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                    self.held = True
            except FileExistsError:
                other = self._read()
                if attempt == 0 and other is not None and other.get("host") == info["host"] \
                        and isinstance(other.get("pid"), int) and not _pid_alive(other["pid"]):
                    log.warning("taking over the lock %s left by minegeo process %s, which no longer runs",
                                self.path, other["pid"])
                    try:
                        self.path.unlink()
                    except FileNotFoundError:
                        pass
                    continue
                who = (f"minegeo {other.get('verb', '')} (process {other.get('pid')} on {other.get('host')}, "
                       f"started {other.get('started_utc')})") if other else "another minegeo run"
                raise OutputError(f"{self.label} {self.target} is being written by {who}; wait for it to "
                                  f"finish, or delete the lock file {self.path} if that run has died") from None
            try:
                with os.fdopen(fd, "w", encoding="utf-8") as fh:
                    json.dump(info, fh)
            except BaseException:
                self.release()
                raise
            return

    def _read(self):
        try:
            with open(self.path, encoding="utf-8") as fh:
                d = json.loads(fh.read(4096))
            return d if isinstance(d, dict) else None
        except (OSError, ValueError):
            return None

    def release(self) -> None:
        with sigint_deferred():
            if self.held:
                try:
                    self.path.unlink()
                except FileNotFoundError:
                    pass
                self.held = False


class OutputTransaction:
    """Check, lock, stage and commit the outputs of one CLI run (see the module docstring).

    Parameters
    ----------
    verb : str
        The verb (named in lock files and messages).
    inputs : mapping
        ``{label: path}`` of every input file or folder.
    folders : mapping
        ``{label: path}`` of result folders; each is written as a whole.
    files : mapping
        ``{label: path}`` of single output files.
    replace : {"result", "any"}
        Which existing non-empty folder may be replaced: ``"result"`` (default) only one that
        holds an earlier minegeo result (``result.json``); ``"any"`` whatever it holds (for an
        explicit ``--force``).
    overwrite_files : bool
        Whether existing output files may be replaced (default True).
    drop_unwritten : bool
        An output file this run did not write is removed at the commit (default False: left as
        it is). For a set of files that describe one run together (a batch's summary, report,
        record and optional drawing): an earlier run's drawing is not left beside this run's record.
    """

    def __init__(self, verb: str, *, inputs: Mapping[str, object] = (), folders: Mapping[str, object] = (),
                 files: Mapping[str, object] = (), replace: str = "result", overwrite_files: bool = True,
                 drop_unwritten: bool = False):
        self.verb = verb
        self.inputs = {k: v for k, v in dict(inputs or {}).items() if v is not None}
        self.folders = {k: Path(os.fspath(v)) for k, v in dict(folders or {}).items() if v is not None}
        self.files = {k: Path(os.fspath(v)) for k, v in dict(files or {}).items() if v is not None}
        if replace not in ("result", "any"):
            raise ValueError(f"replace must be 'result' or 'any', got {replace!r}")
        self.replace = replace
        self.overwrite_files = overwrite_files
        self.drop_unwritten = drop_unwritten
        self._locks: list[_Lock] = []
        self._stage: dict[str, Path] = {}
        self._tmpfiles: dict[str, Path] = {}
        self._filedirs: list[Path] = []
        self._in_folder: dict[str, tuple[str, Path]] = {}
        self._created: list[Path] = []
        self.committed = False

    # -- checks -------------------------------------------------------------------------------
    def check(self) -> None:
        """Validate every output against every input and the replace rules (no side effects)."""
        check_outputs(self.inputs, self.files, self.folders)
        for lab, d in self.folders.items():
            if d.is_dir() and any(d.iterdir()) and self.replace != "any" and not is_result_folder(d):
                raise OutputError(f"{lab} {d} is not empty and holds no earlier minegeo result (result.json); "
                                  "minegeo replaces a result folder as a whole, so choose a new or empty folder")
        if not self.overwrite_files:
            for lab, f in self.files.items():
                if f.exists():
                    raise OutputError(f"{lab} {f} exists; use --force to overwrite it")

    # -- context ------------------------------------------------------------------------------
    def __enter__(self) -> OutputTransaction:
        self.check()
        # a file inside an output folder is staged inside that folder's staging copy
        self._in_folder = {}
        for lab, f in self.files.items():
            for flab, d in self.folders.items():
                if _inside(f, d):
                    self._in_folder[lab] = (flab, _real(f).relative_to(_real(d)))
        targets = sorted([(str(_real(p)), lab, p) for lab, p in list(self.folders.items()) + list(self.files.items())
                          if lab not in self._in_folder])
        # folders this run creates (missing parents of the outputs): removed again if the run fails
        for _, _, p in targets:
            top = None
            for anc in [_real(p), *_real(p).parents][1:]:
                if anc.exists():
                    break
                top = anc
            if top is not None and top not in self._created:
                self._created.append(top)
        try:
            # each lock and staging folder is created and recorded with Ctrl-C held back, so the
            # cleanup below always knows it (sigint_deferred)
            for _, lab, p in targets:
                lk = _Lock(_real(p), lab, self.verb)
                with sigint_deferred():
                    self._locks.append(lk)
                    lk.acquire()
            self.check()  # again, under the locks
            tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
            for lab, d in self.folders.items():
                rd = _real(d)
                s = rd.parent / f".{rd.name}{_TMP_TAG}{tag}"
                with sigint_deferred():
                    s.mkdir(parents=True)
                    self._stage[lab] = s
            for lab, (flab, rel) in self._in_folder.items():
                self._tmpfiles[lab] = self._stage[flab] / rel
                self._tmpfiles[lab].parent.mkdir(parents=True, exist_ok=True)
            for lab, f in self.files.items():
                if lab in self._in_folder:
                    continue
                rf = _real(f)
                sd = rf.parent / f"{_TMP_TAG[:-1]}-{tag}"  # one hidden staging folder per parent
                if sd not in self._filedirs:
                    with sigint_deferred():
                        sd.mkdir(parents=True)
                        self._filedirs.append(sd)
                self._tmpfiles[lab] = sd / rf.name  # same name: sidecars named after it stay right
        except BaseException:
            self._cleanup()
            raise
        return self

    def folder(self, label: str) -> Path:
        """The staging folder to write the result folder ``label`` into."""
        return self._stage[label]

    def file(self, label: str) -> Path:
        """The staged path to write the output file ``label`` to (moved into place at commit).

        It has the final file's name, in a hidden staging folder beside the final file, so a file
        written next to it under a derived name (a sidecar) is staged too."""
        return self._tmpfiles[label]

    def final(self, label: str) -> Path:
        """The path ``label`` will have once committed (for messages and links)."""
        return self.folders.get(label) or self.files[label]

    def __exit__(self, exc_type, exc, tb) -> bool:
        # commit and cleanup with Ctrl-C held back: the renames are all done or none is, and the
        # staging folders and locks are always removed; the Ctrl-C takes effect just after
        with sigint_deferred():
            try:
                if exc_type is None:
                    self._commit()
            finally:
                self._cleanup()
        return False

    # -- commit / cleanup ---------------------------------------------------------------------
    def _commit(self) -> None:
        for lab, s in self._stage.items():
            final = _real(self.folders[lab])
            old = None
            if final.exists():
                old = final.parent / f".{final.name}{_OLD_TAG}{os.getpid()}-{uuid.uuid4().hex[:8]}"
                os.rename(final, old)
            try:
                os.rename(s, final)
            except BaseException:
                if old is not None:
                    os.rename(old, final)
                raise
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        for lab, t in self._tmpfiles.items():
            if lab not in self._in_folder and t.exists():
                os.replace(t, _real(self.files[lab]))
            elif lab not in self._in_folder and self.drop_unwritten:
                _real(self.files[lab]).unlink(missing_ok=True)  # an earlier run's file this run did not write
        self.committed = True

    def _cleanup(self) -> None:
        for s in self._stage.values():
            if s.exists():
                shutil.rmtree(s, ignore_errors=True)
        for sd in self._filedirs:
            if sd.exists():
                shutil.rmtree(sd, ignore_errors=True)
        self._filedirs.clear()
        for lk in reversed(self._locks):
            lk.release()
        self._locks.clear()
        if not self.committed:
            for top in self._created:  # only if nothing was put there meanwhile
                if top.is_dir() and not any(q.is_file() or q.is_symlink() for q in top.rglob("*")):
                    shutil.rmtree(top, ignore_errors=True)
        self._created.clear()


class RunClock:
    """Wall time of a run and the part of it spent compiling Numba kernels.

    Compile time is the total duration of Numba's ``numba:compile`` events while the clock runs
    (loading a kernel from Numba's on-disk cache is not compilation and counts as work).
    """

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self._listener = None
        self._ctx = None
        try:
            from numba.core import event

            self._listener = event.TimingListener()
            self._ctx = event.install_listener("numba:compile", self._listener)
            self._ctx.__enter__()
        except Exception:  # noqa: BLE001 - an old Numba without the event API: report 0
            self._listener = None
            self._ctx = None

    @property
    def compile_s(self) -> float:
        lst = self._listener
        return float(lst.duration) if lst is not None and lst.done else 0.0

    def timings(self) -> dict[str, float]:
        """``{"wall_s", "compile_s", "work_s"}`` so far (work = wall - compile)."""
        wall = time.perf_counter() - self.t0
        comp = min(self.compile_s, wall)
        return {"wall_s": wall, "compile_s": comp, "work_s": wall - comp}

    def close(self) -> None:
        if self._ctx is not None:
            try:
                self._ctx.__exit__(None, None, None)
            finally:
                self._ctx = None


@contextmanager
def output_lock(verb: str, label: str, path):
    """Hold the lock of one output (file or folder) without staging it (for composite verbs)."""
    lk = _Lock(_real(path), label, verb)
    try:
        lk.acquire()
        yield lk
    finally:
        lk.release()


def run_timings(args) -> dict[str, float]:
    """The :class:`RunClock` timings of the CLI run ``args`` (zeros compile time outside the CLI)."""
    clock = getattr(args, "_clock", None)
    if clock is None:
        clock = RunClock()
        try:
            args._clock = clock
        except AttributeError:
            pass
    return clock.timings()


def progress_enabled(args=None) -> bool:
    """Progress bars go to stderr only when it is a terminal and ``--quiet`` was not given."""
    if args is not None and getattr(args, "quiet", False):
        return False
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):
        return False
