"""Provenance, hashing, timing and atomic output helpers shared by every pipeline.

Every result minegeo writes carries the parameters used, package versions, the
seed, the recorded local origin and SHA-256 hashes of its input files, so a
surveyor can reproduce and audit it. Files are written atomically (temporary
file in the same directory, then ``os.replace``) so a crash never leaves a
half-written result, and inputs are never opened for writing.
"""

from __future__ import annotations

import contextvars
import dataclasses
import datetime as _dt
import hashlib
import json
import os
import platform
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "versions",
    "sha256_file",
    "input_record",
    "to_jsonable",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_json_atomic",
    "StageTimer",
    "provenance",
]


def versions() -> dict[str, str]:
    """Versions of minegeo, Python and the numerical dependencies (missing ones are omitted)."""
    from importlib import metadata

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for name in ("minegeo", "numpy", "scipy", "numba", "pykdtree", "pyproj", "laspy", "matplotlib"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def sha256_file(path: str | os.PathLike, chunk_bytes: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in chunks (the file is opened read-only).

    Raises
    ------
    FileFormatError
        ``path`` is not a regular file (a device such as ``/dev/zero``, a pipe or a socket):
        its length is not known, so it could never be hashed (nor read) to the end.
    """
    import stat

    from minegeo.errors import FileFormatError

    st = os.stat(path)
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(21, "is a folder, not a file", str(path))
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(path, "is not a regular file (a device, pipe or socket): minegeo reads "
                                    "files of known length only; copy the data into a file first")
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            block = fh.read(chunk_bytes)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def input_record(path: str | os.PathLike) -> dict[str, Any]:
    """``{"path", "sha256", "size_bytes"}`` for an input file, for result JSON ``inputs``."""
    p = Path(path)
    return {"path": str(p), "sha256": sha256_file(p), "size_bytes": p.stat().st_size}


def to_jsonable(obj: Any) -> Any:
    """Convert dataclasses, NumPy scalars/arrays, paths and tuples into JSON-serialisable values.

    Non-finite floats become ``None`` (JSON has no NaN); callers that need to
    distinguish should record a status field.
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if np.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    return obj


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file + ``os.replace``); creates parent dirs."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            if hasattr(os, "fchmod"):  # mkstemp makes 0600 files; give the usual open() mode (0666 & ~umask)
                os.fchmod(fh.fileno(), 0o666 & ~_umask())
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return p


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 text atomically (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` (converted by :func:`to_jsonable`) as indented, key-stable JSON, atomically."""
    text = json.dumps(to_jsonable(obj), indent=2, sort_keys=False, allow_nan=False)
    return atomic_write_text(path, text + "\n")


#: the options of the ``minegeo`` command being run (option name -> value, the ``--config`` file form),
#: set by :func:`minegeo.cli.main` for the run; recorded by :func:`provenance` as ``"arguments"``
CLI_ARGUMENTS: contextvars.ContextVar[dict | None] = contextvars.ContextVar("minegeo_cli_arguments", default=None)


def arguments_provenance() -> dict[str, Any]:
    """``{"arguments": options}`` of the ``minegeo`` command being run (``None`` outside one): the
    ``provenance`` block of records that carry their versions, seed and inputs at the top level
    (``localize``, ``localize-batch``, ``prepare-map``, ``demo``), read back by ``--config``."""
    arguments = CLI_ARGUMENTS.get()
    return {"arguments": None if arguments is None else to_jsonable(arguments)}


def provenance(seed: int | None = None, origin: Any = None, inputs: list | None = None) -> dict[str, Any]:
    """Standard provenance block: versions, seed, local origin, input hashes, UTC time, and within a
    ``minegeo`` command its options (``"arguments"``, which ``--config result.json`` reads back)."""
    rec = {
        "versions": versions(),
        "seed": seed,
        "origin": to_jsonable(origin),
        "inputs": [input_record(p) if not isinstance(p, dict) else p for p in (inputs or [])],
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    arguments = CLI_ARGUMENTS.get()
    if arguments is not None:
        rec["arguments"] = to_jsonable(arguments)
    return rec


class StageTimer:
    """Wall-clock timer per named stage (seconds, ``time.perf_counter``).

    Examples
    --------
    >>> t = StageTimer()
    >>> with t("normals"):
    ...     pass
    >>> sorted(t.as_dict())
    ['normals', 'total']
    """

    def __init__(self) -> None:
        self._t: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._t[stage] = self._t.get(stage, 0.0) + time.perf_counter() - t0

    def add(self, stage: str, seconds: float) -> None:
        self._t[stage] = self._t.get(stage, 0.0) + float(seconds)

    def as_dict(self) -> dict[str, float]:
        d = dict(self._t)
        d["total"] = float(sum(self._t.values()))
        return d
