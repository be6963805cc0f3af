"""The output folder of a batch localization: its manifest, reserved names, refusal of another batch, leftovers.

``OUT/batch_manifest.json`` (:data:`MANIFEST`) records the map and parameters of the batch that owns
``OUT``; :func:`check_out_folder` refuses a different one (an :class:`~minegeo.errors.OutputError`
before anything is written); :class:`OutState` records what a run found in ``OUT`` so that a run
stopped early takes back everything but its completed scan folders.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

from minegeo.errors import OutputError

log = logging.getLogger(__name__)


MANIFEST = "batch_manifest.json"
MAP_CACHE = ".map_cache"
#: the files the batch writes at its end, together (``minegeo localize-batch``)
BATCH_FILES = ("summary.csv", "report.html", "batch_result.json", "placements.dxf")
#: every name the batch itself uses in ``OUT``: no scan's result folder may take one of them
RESERVED_NAMES = (*BATCH_FILES, MANIFEST, MAP_CACHE)
_MANIFEST_FORMAT = "minegeo-localize-batch"


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
