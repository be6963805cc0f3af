"""The bad-input contract of every ``minegeo`` verb, as ONE assertion helper (issue 14).

README: a user mistake gives exit status 2 and exactly one line on stderr,
``minegeo <verb>: error: ...``, never a traceback; inputs are never modified; a run that fails
with a user error writes nothing new and leaves an earlier result folder exactly as it was
(``minegeo._output.OutputTransaction``).

:func:`assert_user_error` runs ``minegeo.cli.main([verb, *argv])`` in-process and checks

(a) exit status 2 (an argparse ``SystemExit`` counts as the exit status it carries; any other
    exception is the traceback a real run would print);
(b) exactly one non-empty stderr line, starting ``minegeo <verb>: error:``, no ``Traceback``, no
    ``Warning``. ``cli.main`` installs its own log handler on the (captured) ``sys.stderr`` (it
    holds the run's records and prints them when the run ends, drops them on a user mistake) and
    routes Python warnings into logging; pytest records Python warnings itself, so during the
    call the helper resets the warning filters to the defaults a real process has;
(c) every input unchanged: files by SHA-256, size and mtime, folders as a whole tree, special
    files (``/dev/zero``) and missing paths by their kind;
(d) no new or mixed output: the tree (relative paths, kinds, SHA-256) of the parent folder of every
    output (its nearest existing ancestor when it does not exist) is the same after the run, so no
    staging ``.minegeo-tmp-*`` folder, lock file or partial file is left and an earlier result
    folder is byte-identical.

Every call runs under a time limit (SIGALRM: :data:`TIMEOUT_S`, :data:`STREAM_TIMEOUT_S` when an
argument is a character device or FIFO) and an address-space limit, so that a reader that never
stops reading ``/dev/zero`` fails the test instead of the shared machine.

The other functions here are plain utilities (a CLI runner for the runs that must succeed, lock
files, bad-file makers), not assertions.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import signal
import socket
import stat
import sys
import time
import warnings
from collections.abc import Iterable
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from minegeo.cli import main

#: one call may take this long before it is stopped: a watchdog against a hang (a reader stuck on a
#: stream), not a speed bound. A failing run takes well under 5 s, but a call that does the work (a
#: stale lock taken over, then a whole localization) compiles its Numba kernels first on a fresh
#: clone: 60 s was too little on a 2-core 2.0 GHz Xeon under the two test workers (CI, 2026-12-02)
TIMEOUT_S = 600
#: ... and this long when an argument is a stream (``/dev/zero``): refusing it needs no reading
STREAM_TIMEOUT_S = 10
#: address space one call may add to the test process (a reader slurping /dev/zero)
EXTRA_ADDRESS_SPACE = 3 << 30
#: an output snapshot root with more entries than this is a test mistake (e.g. "/tmp")
_MAX_SNAPSHOT_ENTRIES = 20000
#: Python's default warning filters hide these categories from a CLI user
_HIDDEN_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


class ContractTimeout(BaseException):
    """A call ran longer than :data:`TIMEOUT_S` (BaseException: no ``except Exception`` swallows it)."""


# ---------------------------------------------------------------------------------- snapshots


def _sha256(p: Path) -> str:
    h = hashlib.sha256()
    with open(p, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _entry(p: Path, with_mtime: bool):
    st = os.lstat(p)
    if stat.S_ISLNK(st.st_mode):
        return ("symlink", os.readlink(p))
    if stat.S_ISDIR(st.st_mode):
        return ("dir",)
    if stat.S_ISREG(st.st_mode):
        rec = ("file", st.st_size, _sha256(p))
        return rec + (st.st_mtime_ns,) if with_mtime else rec
    return ("special", stat.S_IFMT(st.st_mode))


def tree_snapshot(root, with_mtime: bool = False) -> dict[str, tuple]:
    """``{relative path: kind record}`` of ``root`` and everything under it (hidden files included,
    symlinks not followed). A missing root is ``{".": ("missing",)}``."""
    root = Path(root)
    if not os.path.lexists(root):
        return {".": ("missing",)}
    snap = {".": _entry(root, with_mtime)}
    if snap["."][0] != "dir":
        return snap
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            snap[str(p.relative_to(root))] = _entry(p, with_mtime)
            if len(snap) > _MAX_SNAPSHOT_ENTRIES:
                raise AssertionError(f"snapshot root {root} is too large: name outputs inside tmp_path")
    return snap


def _input_state(p: Path):
    """An input as it must stay: a file by content and mtime, a folder as a whole tree."""
    if not os.path.lexists(p):
        return {".": ("missing",)}
    st = os.stat(p) if os.path.exists(p) else os.lstat(p)
    if stat.S_ISDIR(st.st_mode):
        return tree_snapshot(p, with_mtime=True)
    if stat.S_ISREG(st.st_mode):
        return {".": ("file", st.st_size, _sha256(Path(p)), st.st_mtime_ns)}
    return {".": ("special", stat.S_IFMT(st.st_mode))}  # /dev/zero: never hashed


def _output_root(out: Path) -> Path:
    """The folder whose tree must not change: the output's parent, or its nearest existing ancestor."""
    root = Path(os.path.abspath(out)).parent
    while not root.exists():
        root = root.parent
    return root


def _diff(before: dict, after: dict) -> list[str]:
    out = []
    for k in sorted(set(before) | set(after)):
        a, b = before.get(k), after.get(k)
        if a == b:
            continue
        if a is None:
            out.append(f"new {k} {b[0]}")
        elif b is None:
            out.append(f"removed {k}")
        else:
            out.append(f"changed {k}: {a[0]}->{b[0]}" + (" (content)" if a[:1] == b[:1] else ""))
    return out


# ---------------------------------------------------------------------------------- guards


def _show_warning(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


@contextmanager
def _as_a_real_process(argv: list[str]):
    """The warning filters a real ``minegeo`` process has (pytest installs its own); ``argv`` unused."""
    with warnings.catch_warnings():
        warnings.resetwarnings()
        warnings.simplefilter("default")
        for cat in _HIDDEN_WARNINGS:
            warnings.filterwarnings("ignore", category=cat)
        warnings.showwarning = _show_warning
        yield


@contextmanager
def _limits(timeout_s: float):
    def _alarm(signum, frame):
        raise ContractTimeout(f"still running after {timeout_s} s (a reader stuck on a stream?)")

    old_handler = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as fh:
        vm = int(fh.read().split()[0]) * resource.getpagesize()
    cap = vm + EXTRA_ADDRESS_SPACE
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old_handler)


def _is_stream(arg: str) -> bool:
    try:
        mode = os.stat(arg).st_mode
    except (OSError, ValueError):
        return False
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


def _call(verb: str, argv, capsys, timeout_s: float):
    """``(exit status, stdout, stderr lines incl. logs/warnings, uncaught exception or None)``."""
    full = [str(verb), *(os.fspath(a) if isinstance(a, os.PathLike) else str(a) for a in argv)]
    if any(_is_stream(a) for a in full[1:]):
        timeout_s = min(timeout_s, STREAM_TIMEOUT_S)
    capsys.readouterr()
    exc = None
    with _as_a_real_process(full):
        try:
            with _limits(timeout_s):
                code = main(full)
        except SystemExit as e:  # argparse: usage line(s) + "error:" on stderr
            code = e.code if isinstance(e.code, int) else 1
        except BaseException as e:  # noqa: BLE001 - a real process would print a traceback
            if isinstance(e, KeyboardInterrupt):
                raise
            code, exc = None, e
    cap = capsys.readouterr()
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    return code, cap.out, lines, exc


# ---------------------------------------------------------------------------------- the assertion


def assert_user_error(verb: str, argv: Iterable, capsys, *, inputs: Iterable = (), outputs: Iterable = (),
                      expect: str | None = None, timeout_s: float = TIMEOUT_S) -> str:
    """Run ``minegeo VERB ARGV`` in-process and assert the whole bad-input contract (a)-(d).

    Parameters
    ----------
    inputs : paths
        Every input file or folder of the run (and folders holding inputs whose tree must not
        change, e.g. the folder of a map beside which a cache could be written).
    outputs : paths
        Every output path the run was asked to write (``--out``, ``--json``, ``--report``, a map's
        sidecar...); the tree of each one's parent folder must be unchanged.
    expect : str, optional
        Text the error line must contain (case-insensitive).

    Returns the error line.
    """
    argv = list(argv)
    ins = {str(p): _input_state(Path(p)) for p in inputs}
    roots = sorted({_output_root(Path(p)) for p in outputs})
    before = {str(r): tree_snapshot(r) for r in roots}

    code, out, lines, exc = _call(verb, argv, capsys, timeout_s)

    problems = []
    shown = " | ".join(lines[:6]) + (f" | ... ({len(lines)} lines)" if len(lines) > 6 else "")
    if exc is not None:
        problems.append(f"uncaught {type(exc).__name__}: {str(exc)[:300]} (a traceback in a real run)")
    elif code != 2:
        problems.append(f"exit status {code}, not 2")
    if len(lines) != 1:
        problems.append(f"{len(lines)} non-empty stderr lines, not 1: {shown or '(none)'}")
    prefix = f"minegeo {verb}: error:"
    if lines and not lines[0].startswith(prefix):
        problems.append(f"stderr does not start with {prefix!r}: {lines[0][:200]!r}")
    elif lines and not lines[0][len(prefix):].strip():
        problems.append("the error line says nothing after 'error:'")
    if any("Traceback" in ln for ln in lines):
        problems.append("Traceback on stderr")
    if any("Warning" in ln for ln in lines):
        problems.append(f"Warning on stderr: {[ln for ln in lines if 'Warning' in ln][:2]}")
    if expect is not None and lines and expect.lower() not in lines[0].lower():
        problems.append(f"error line lacks {expect!r}: {lines[0][:200]!r}")
    for p, st in ins.items():
        now = _input_state(Path(p))
        if now != st:
            problems.append(f"input {p} modified: {_diff(st, now)[:5]}")
    for r in roots:
        d = _diff(before[str(r)], tree_snapshot(r))
        if d:
            problems.append(f"output folder {r} changed: {d[:6]}" + (f" (+{len(d) - 6})" if len(d) > 6 else ""))
    if problems:
        pytest.fail(f"minegeo {verb} {' '.join(map(str, argv))}:\n  - " + "\n  - ".join(problems), pytrace=False)
    return lines[0]


# ---------------------------------------------------------------------------------- utilities


def run_cli(verb: str, argv: Iterable, capsys, timeout_s: float = TIMEOUT_S):
    """``(exit status, stdout, stderr lines incl. logs/warnings)`` of an in-process run that must not raise."""
    code, out, lines, exc = _call(verb, list(argv), capsys, timeout_s)
    if exc is not None:
        pytest.fail(f"minegeo {verb}: uncaught {type(exc).__name__}: {exc}")
    return code, out, lines


def lock_path(target) -> Path:
    """The lock file ``.NAME.minegeo-lock`` of an output ``target`` (as ``minegeo._output`` names it)."""
    t = Path(os.path.realpath(os.path.abspath(target)))
    return t.parent / f".{t.name}.minegeo-lock"


def write_lock(target, pid: int, verb: str) -> Path:
    """Create the lock file of ``target`` as if run ``pid`` on this host were writing it."""
    p = lock_path(target)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"pid": pid, "host": socket.gethostname(), "verb": verb,
                             "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}), encoding="utf-8")
    return p


def dead_pid() -> int:
    """A process id that no process on this host has right now."""
    try:
        top = int(Path("/proc/sys/kernel/pid_max").read_text())
    except (OSError, ValueError):
        top = 32768
    for pid in range(top - 1, 300, -1):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except PermissionError:
            continue
    raise RuntimeError("no free pid found")


def truncated_copy(src, dst) -> Path:
    """``dst`` = the first half of the bytes of ``src`` (a file cut short by a copy or a full disk)."""
    raw = Path(src).read_bytes()
    Path(dst).write_bytes(raw[: len(raw) // 2])
    return Path(dst)


def a_folder(tmp: Path, name: str = "a_folder") -> Path:
    """A non-empty folder given where a file is expected (its tree must stay as it is)."""
    d = tmp / name
    d.mkdir()
    (d / "inside.txt").write_text("keep\n", encoding="utf-8")
    return d


def copy_tree(src, dst) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return Path(dst)


def leftovers(folder) -> list[str]:
    """Staging, lock or old-copy entries left in ``folder`` (not recursive)."""
    return sorted(p.name for p in Path(folder).iterdir() if ".minegeo-" in p.name)


def georef_variant(geo_map, dst_dir, case: str) -> Path:
    """A copy of a georeferenced map (``minegeo georef`` output + sidecar) in ``dst_dir``, damaged.

    ``sidecar_truncated`` (half of the JSON), ``sidecar_non_utf8``, ``sidecar_unknown_epsg`` (EPSG:9999,
    an unknown code, in the sidecar and the PLY header, with the sidecar's map SHA-256 updated so
    only the CRS is wrong), ``sidecar_stale`` (the map changed after georef: the sidecar's SHA-256
    no longer matches), ``sidecar_folder`` (a folder where the sidecar should be).
    """
    geo_map, dst_dir = Path(geo_map), Path(dst_dir)
    dst_dir.mkdir(parents=True, exist_ok=True)
    m = dst_dir / geo_map.name
    s = dst_dir / (geo_map.name + ".georef.json")
    raw = geo_map.read_bytes()
    side = Path(str(geo_map) + ".georef.json").read_bytes()
    if case == "sidecar_unknown_epsg":
        raw = raw.replace(b"EPSG:5186", b"EPSG:9999", 1)
        side = side.replace(b"EPSG:5186", b"EPSG:9999").replace(
            hashlib.sha256(geo_map.read_bytes()).hexdigest().encode(), hashlib.sha256(raw).hexdigest().encode())
    elif case == "sidecar_truncated":
        side = side[: len(side) // 2]
    elif case == "sidecar_non_utf8":
        side = side.replace(b'"crs"', b'"cr\xe9s"', 1) + b"\xff"
    elif case == "sidecar_stale":
        i = raw.index(b"end_header\n") + len(b"end_header\n") + 3
        raw = raw[:i] + bytes([raw[i] ^ 0x40]) + raw[i + 1:]
    elif case != "sidecar_folder":
        raise ValueError(case)
    m.write_bytes(raw)
    if case == "sidecar_folder":
        s.mkdir()
        (s / "inside.txt").write_text("keep\n", encoding="utf-8")
    else:
        s.write_bytes(side)
    return m


def stream_link(tmp: Path, name: str) -> Path:
    """``tmp/name`` -> ``/dev/zero``: a stream behind a file name with the right suffix (a reader
    that picks its format from the suffix must still refuse it before reading)."""
    p = Path(tmp) / name
    p.symlink_to("/dev/zero")
    return p


def symlink_beside(p: Path, name: str = "link") -> Path:
    """A symlink ``name`` beside ``p`` pointing at it."""
    (p.parent / name).symlink_to(p)
    return p.parent / name


def hardlink_beside(p: Path, name: str = "hard") -> Path:
    """A hard link ``name`` beside ``p``."""
    os.link(p, p.parent / name)
    return p.parent / name


def a_file(d: Path, name: str = "afile") -> Path:
    """A plain file ``d/name`` holding "keep" (an output path that names an existing file)."""
    f = d / name
    f.write_text("keep", encoding="utf-8")
    return f


def write_file(tmp: Path, name: str, data) -> Path:
    """``tmp/name`` holding ``data`` (bytes as they are, text as UTF-8): a bad input file."""
    p = tmp / name
    p.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return p


#: times of an IMU that covers :func:`write_box_room_frames`' frames (0.0-0.3 s) at 200 Hz
IMU_T = np.arange(-0.05, 0.40, 0.005)


def write_box_room_frames(d, n: int = 4):
    """``n`` small box-room frames (600 points on the faces of a 6 x 4 x 3 m box, moving 0.1 m along x
    per frame) at 0.0, 0.1, ... s into the new folder ``d`` with their ``times.txt``; returns ``d``."""
    from minegeo.io import PointCloud, write_point_cloud

    d.mkdir()
    rng = np.random.default_rng(29)
    half = np.array([3.0, 2.0, 1.5])
    for k in range(n):
        u = rng.uniform(-1.0, 1.0, (600, 3)) * half
        face = rng.integers(0, 3, 600)
        u[np.arange(600), face] = np.sign(u[np.arange(600), face]) * half[face]
        write_point_cloud(d / f"{k:06d}.ply", PointCloud(points=u + [0.1 * k, 0.0, 0.0]))
    (d / "times.txt").write_text("".join(f"{0.1 * k:.6f}\n" for k in range(n)))
    return d


def imu_rows(t) -> list[str]:
    """IMU CSV rows at times ``t``: a small constant x rate and gravity on z (the contract's units)."""
    return [f"{x:.6f},0.01,0.0,0.0,0.0,0.0,9.80665" for x in t]


#: a Kalibr imu.yaml (its own layout: topic, rate, the four densities) with figures unlike the defaults
KALIBR_IMU_YAML = """#Accelerometers
accelerometer_noise_density: 1.86e-03   #Noise density (continuous-time)
accelerometer_random_walk:   4.33e-04   #Bias random walk

#Gyroscopes
gyroscope_noise_density:     1.87e-04   #Noise density (continuous-time)
gyroscope_random_walk:       2.66e-05   #Bias random walk

rostopic:                    /imu0      #the IMU ROS topic
update_rate:                 200.0      #Hz (for discretization of the values above)
"""
#: the figures of :data:`KALIBR_IMU_YAML`, typed by hand
KALIBR_IMU_NOISE = {"gyroscope_noise_density": 1.87e-04, "gyroscope_random_walk": 2.66e-05,
                    "accelerometer_noise_density": 1.86e-03, "accelerometer_random_walk": 4.33e-04}


def capture_gyro_aid_noise(monkeypatch) -> list:
    """Record the IMU noise every :class:`minegeo.slam.inertial.GyroAid` is made with (the engine's view)."""
    from dataclasses import asdict

    from minegeo.slam import inertial

    seen, init = [], inertial.GyroAid.__init__

    def spy(self, imu, params=None):
        init(self, imu, params)
        seen.append(asdict(self.params.noise))

    monkeypatch.setattr(inertial.GyroAid, "__init__", spy)
    return seen
