"""Every reader is bounded, and every reader problem keeps the CLI contract (issue 14).

Contract (README): a user mistake gives exit status 2 and exactly one line on stderr,
``minegeo <verb>: error: ...``; no traceback, no warning line; the input file is unchanged.

Classes of damaged or hostile input, one parametrised test each:

* streams: ``/dev/zero``, ``/dev/urandom``, a FIFO whose writer never stops;
* headers announcing more points than the file holds, and a zip bomb;
* headers (and text preamble lines) that never end;
* JSON nested thousands deep, with duplicate keys or NaN (georef sidecar, prepared-map meta;
  the survey network JSON is in ``tests/survey/test_survey_json_limits.py``);
* text files cut mid-line;
* huge coordinates (``1e308``) that would overflow later arithmetic.

Stream and allocation cases run ``minegeo.cli.main`` in a subprocess under
``RLIMIT_AS = 2 GiB`` and a timeout, with ``RuntimeWarning`` as an error, so that a regression
fails fast instead of eating the shared machine. The other cases run in-process through
:func:`minegeo.cli.main` with ``capsys``; RuntimeWarnings are errors there too.
"""

from __future__ import annotations

import hashlib
import logging
import os
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import require_extra

from minegeo.cli import main
from minegeo.errors import FileFormatError
from minegeo.io import ControlPoints, PointCloud, read_point_cloud, write_gcps, write_point_cloud
from minegeo.io.limits import MAX_HEADER_BYTES, MAX_HEADER_LINE_BYTES
from minegeo.mast.beacons import BeaconDesign, place_beacon, write_beacons_csv

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

#: address-space limit of the subprocess runs (bytes): importing minegeo needs ~1 GiB of it
AS_LIMIT_BYTES = 2 << 30
#: wall-clock limit of one subprocess run (s); a correct run takes about one second
TIMEOUT_S = 60

_LIMITED = r"""
import resource, sys, warnings
lim = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
warnings.simplefilter("error", RuntimeWarning)
from minegeo.cli import main
sys.exit(main(sys.argv[2:]))
"""


def sha256(p) -> str:
    return hashlib.sha256(Path(p).read_bytes()).hexdigest()


def _one_error_line(verb: str, code: int, err: str, match: str | None) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    assert "Warning" not in err, err
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"minegeo {verb}: error:"), lines[0]
    if match is not None:
        assert match.lower() in lines[0].lower(), lines[0]
    return lines[0]


def run_limited(argv) -> subprocess.CompletedProcess:
    """``minegeo.cli.main(argv)`` in a child with ``RLIMIT_AS`` and a timeout."""
    return subprocess.run(
        [sys.executable, "-c", _LIMITED, str(AS_LIMIT_BYTES), *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        env={**os.environ, "MINEGEO_NO_PROGRESS": "1"},
    )


def assert_limited_error(argv, match=None, inputs=()) -> str:
    before = {p: sha256(p) for p in inputs}
    r = run_limited(argv)
    line = _one_error_line(argv[0], r.returncode, r.stderr, match)
    assert {p: sha256(p) for p in inputs} == before
    return line


def assert_user_error(argv, capsys, caplog, match=None, inputs=()) -> str:
    """In-process: exit 2, one stderr line, no traceback, no warning logged, inputs unchanged."""
    before = {p: sha256(p) for p in inputs}
    capsys.readouterr()
    caplog.clear()
    try:
        with caplog.at_level(logging.WARNING):
            code = main([str(a) for a in argv])
    except SystemExit as exc:
        pytest.fail(f"{argv}: SystemExit({exc.code}) instead of a one-line error")
    except Exception as exc:  # noqa: BLE001 - a traceback is what the contract forbids
        pytest.fail(f"{argv}: uncaught {type(exc).__name__}: {exc}")
    err = capsys.readouterr().err
    line = _one_error_line(argv[0], code, err, match)
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert not warned, warned  # a warning line before the error breaks "exactly one line"
    assert {p: sha256(p) for p in inputs} == before
    return line


# --------------------------------------------------------------------------------------------
# valid companions (the other input of a two-input verb)
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("good")
    design = BeaconDesign()
    write_beacons_csv(d / "beacons.csv", [place_beacon(design, "B1", (5, 5), 0, "left"),
                                          place_beacon(design, "B2", (-5, 8), 90, "right")])
    (d / "scan.csv").write_text("bearing_deg,range_m\n10.0,5.0\n20.0,5.5\n", encoding="utf-8")
    rng = np.random.default_rng(2)
    write_gcps(
        d / "gcps.csv",
        ControlPoints(
            ids=["G1", "G2", "G3", "G4"],
            local_xyz=rng.normal(size=(4, 3)) * 10,
            crs_enh=rng.normal(size=(4, 3)) * 10 + [200000.0, 550000.0, 80.0],
            sigma_enh_m=np.full((4, 3), 0.01),
            crs="EPSG:5186",
        ),
    )
    write_point_cloud(d / "map.ply", PointCloud(rng.normal(size=(50, 3))))
    return d


# --------------------------------------------------------------------------------------------
# 1. streams: character devices and an endless FIFO are refused before being opened
# --------------------------------------------------------------------------------------------
STREAM_CASES = [
    (["info", "/dev/zero", "--format", "ply"], "character device"),
    (["info", "/dev/urandom", "--format", "xyz"], "character device"),
    (["info", "/dev/zero", "--format", "pcd"], "character device"),
    (["info", "/dev/urandom", "--format", "las"], "character device"),
    (["info", "/dev/zero", "--format", "zip"], "character device"),
    (["info", "/dev/zero", "--kind", "trajectory", "--format", "tum"], "character device"),
    (["info", "/dev/urandom", "--kind", "gcp"], "character device"),
    (["mast", "--scan", "/dev/zero", "--beacons", "{beacons}", "--out", "{out}"], "character device"),
    (["mast", "--scan", "{scan}", "--beacons", "/dev/urandom", "--out", "{out}"], "character device"),
    (["georef", "--map", "/dev/zero", "--gcps", "{gcps}", "--out", "{out}/m.ply", "--report", "{out}/r"], None),
    (["georef", "--map", "{map}", "--gcps", "/dev/urandom", "--out", "{out}/m.ply", "--report", "{out}/r"], None),
    (["adjust", "/dev/zero", "--out", "{out}"], None),
]


def _fill(argv, good: Path, out: Path) -> list[str]:
    keys = {"beacons": good / "beacons.csv", "scan": good / "scan.csv", "gcps": good / "gcps.csv",
            "map": good / "map.ply", "out": out}
    out_argv = []
    for a in argv:
        for k, v in keys.items():
            a = a.replace("{" + k + "}", str(v))
        out_argv.append(a)
    return out_argv


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero and /dev/urandom")
@pytest.mark.parametrize("argv, match", STREAM_CASES, ids=[" ".join(c[0][:4]) for c in STREAM_CASES])
def test_character_devices_are_refused(argv, match, good, tmp_path):
    assert_limited_error(_fill(argv, good, tmp_path / "out"), match)  # under its SIGALRM limit (a hang fails)


@pytest.fixture
def endless_fifo(tmp_path):
    """A FIFO with a writer thread that never stops (until the test ends)."""
    if not hasattr(os, "mkfifo") or not sys.platform.startswith("linux"):
        pytest.skip("needs Linux FIFOs")
    made = []

    def make(name: str) -> Path:
        p = tmp_path / name
        os.mkfifo(p)
        fd = os.open(p, os.O_RDWR | os.O_NONBLOCK)  # Linux: never blocks, keeps the pipe open
        stop = threading.Event()
        chunk = b"1.0 2.0 3.0\n" * 4096

        def writer():
            while not stop.is_set():
                try:
                    os.write(fd, chunk)
                except BlockingIOError:  # pipe full: nobody is reading
                    time.sleep(0.002)
                except OSError:
                    return

        t = threading.Thread(target=writer, daemon=True)
        t.start()
        made.append((stop, t, fd))
        return p

    yield make
    for stop, t, fd in made:
        stop.set()
        t.join(5)
        os.close(fd)


@pytest.mark.parametrize(
    "argv",
    [
        ["info", "{fifo}"],
        ["info", "{fifo}", "--kind", "gcp"],
        ["info", "{fifo}", "--kind", "trajectory", "--format", "tum"],
        ["mast", "--scan", "{fifo}", "--beacons", "{beacons}", "--out", "{out}"],
        ["adjust", "{fifo}", "--out", "{out}"],
    ],
    ids=["info", "info-gcp", "info-trajectory", "mast", "adjust"],
)
def test_endless_fifo_is_refused(argv, endless_fifo, good, tmp_path):
    fifo = endless_fifo("stream.xyz")
    argv = [a.replace("{fifo}", str(fifo)) for a in argv]
    assert_limited_error(_fill(argv, good, tmp_path / "out"))


# --------------------------------------------------------------------------------------------
# 2. a header announcing more points than the file holds; a zip bomb
# --------------------------------------------------------------------------------------------
def _ply_binary(n_declared: int, n_real: int = 10) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n_declared}\nproperty double x\n"
            "property double y\nproperty double z\nend_header\n").encode()
    return head + np.zeros((n_real, 3)).tobytes()


def _pcd(n_declared: int, mode: str, body: bytes) -> bytes:
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n_declared}\nHEIGHT 1\n"
            f"POINTS {n_declared}\nDATA {mode}\n").encode()
    return head + body


def _las_with_count(tmp: Path, count: int) -> bytes:
    laspy = require_extra("laspy")
    p = tmp / "ok.las"
    write_point_cloud(p, PointCloud(np.random.default_rng(0).normal(size=(20, 3))))
    b = bytearray(p.read_bytes())
    hdr = laspy.LasHeader.read_from(p.open("rb"))
    assert hdr.version.minor >= 4
    b[247:255] = int(count).to_bytes(8, "little")  # LAS 1.4 64-bit point count
    return bytes(b)


COUNT_CASES = {
    "ply-binary-4e9-vertices": ("c.ply", lambda tmp: _ply_binary(4_000_000_000), "truncated"),
    "ply-ascii-1e12-vertices": (
        "c.ply",
        lambda tmp: b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n1 2 3\n4 5 6\n",
        "header declares",
    ),
    "pcd-binary-4e9-points": ("c.pcd", lambda tmp: _pcd(4_000_000_000, "binary", bytes(120)), "truncated"),
    "pcd-compressed-3.6e9-bytes": (
        "c.pcd",
        # 300 million points x 12 bytes = 3.6e9 bytes announced for 16 compressed bytes
        lambda tmp: _pcd(300_000_000, "binary_compressed",
                         np.array([16, 3_600_000_000], dtype="<u4").tobytes() + bytes(16)),
        "lzf expands at most",
    ),
    "pcd-ascii-1e12-points": ("c.pcd", lambda tmp: _pcd(10**12, "ascii", b"1 2 3\n"), "header declares"),
    "pcd-ascii-count-1e8": (
        "c.pcd",
        lambda tmp: b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 100000000\nWIDTH 2\nHEIGHT 1\n"
        b"POINTS 2\nDATA ascii\n1 2 3\n4 5 6\n",
        "values per point",
    ),
    "pts-1e12-points": ("c.pts", lambda tmp: b"1000000000000\n1 2 3\n4 5 6\n", "header declares"),
    "las-1e15-points": ("c.las", lambda tmp: _las_with_count(tmp, 10**15), "truncated"),
}


@pytest.mark.parametrize("case", list(COUNT_CASES))
def test_header_counts_are_checked_before_allocating(case, tmp_path):
    name, make, match = COUNT_CASES[case]
    p = tmp_path / name
    p.write_bytes(make(tmp_path))
    assert_limited_error(["info", p], match, inputs=[p])


@pytest.fixture(scope="module")
def zip_bomb(tmp_path_factory):
    """96 MiB of zeros deflated to ~100 KB (ratio ~1000), written in 1 MiB chunks."""
    p = tmp_path_factory.mktemp("bomb") / "bomb.xyz.zip"
    with zipfile.ZipFile(p, "w", compression=zipfile.ZIP_DEFLATED) as zf, zf.open("bomb.xyz", "w") as fh:
        block = bytes(1 << 20)
        for _ in range(96):
            fh.write(block)
    return p


def test_zip_bomb_is_refused_before_inflating(zip_bomb):
    assert zip_bomb.stat().st_size < 1 << 20
    assert_limited_error(["info", zip_bomb], "zip bomb", inputs=[zip_bomb])


# --------------------------------------------------------------------------------------------
# 3. headers that never end are an error within MAX_HEADER_BYTES
# --------------------------------------------------------------------------------------------
_PLY_TAIL = b"\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n"
_PCD_TAIL = b"\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2 3\n"
#: headers whose end lies beyond the cap: the reader must give up at the cap (not scan on)
NEVER_ENDING = {
    "ply": ("h.ply", b"ply\nformat ascii 1.0\ncomment " + b"x" * MAX_HEADER_BYTES + _PLY_TAIL,
            f"first {MAX_HEADER_BYTES} bytes"),
    "ply-no-end": ("e.ply", b"ply\nformat ascii 1.0\ncomment " + b"x" * (MAX_HEADER_BYTES + 100),
                   f"first {MAX_HEADER_BYTES} bytes"),
    "pcd": ("h.pcd", b"# " + b"x" * MAX_HEADER_BYTES + _PCD_TAIL, f"first {MAX_HEADER_BYTES} bytes"),
    "xyz": ("h.xyz", b"x" * (MAX_HEADER_LINE_BYTES + 100) + b"\n1 2 3\n", f"longer than {MAX_HEADER_LINE_BYTES}"),
    "csv": ("h.csv", b"# " + b"a," * (MAX_HEADER_LINE_BYTES // 2 + 100) + b"\n1,2,3\n",
            f"longer than {MAX_HEADER_LINE_BYTES}"),
}


@pytest.mark.parametrize("case", list(NEVER_ENDING))
def test_header_that_never_ends(case, tmp_path, capsys, caplog):
    name, data, match = NEVER_ENDING[case]
    p = tmp_path / name
    p.write_bytes(data)
    assert_user_error(["info", p], capsys, caplog, match, inputs=[p])  # under its SIGALRM limit (a hang fails)


# --------------------------------------------------------------------------------------------
# 4. JSON readers outside the survey network: georef sidecar, prepared-map meta
# --------------------------------------------------------------------------------------------
JSON_CASES = {
    "deep-100000": ("[" * 100_000 + "]" * 100_000, "nested"),
    "deep-65": ('{"georef": ' + "[" * 64 + "]" * 64 + "}", "nested"),
    "duplicate-key": ('{"format": "minegeo-georef", "format": "x"}', "duplicate key 'format'"),
    "nan": ('{"georef": {"scale": NaN}}', "NaN"),
    "infinity": ('{"georef": {"scale": -Infinity}}', "Infinity"),
    "overflow": ('{"georef": {"scale": 1e400}}', "too large"),
}


@pytest.mark.parametrize("case", list(JSON_CASES))
def test_georef_json_readers(case, tmp_path):
    from minegeo.georef import load_georeferenced_map, read_georef

    text, match = JSON_CASES[case]
    side = tmp_path / "map.ply.georef.json"
    side.write_text(text, encoding="utf-8")
    write_point_cloud(tmp_path / "map.ply", PointCloud(np.zeros((3, 3))))
    h = sha256(side)
    for reader in (read_georef, load_georeferenced_map):
        with pytest.raises(FileFormatError, match=match) as ei:
            reader(side)
        assert "map.ply.georef.json" in str(ei.value)
    assert sha256(side) == h


@pytest.mark.parametrize("case", ["deep-100000", "duplicate-key"])
def test_prepared_map_meta_json(case, tmp_path):
    from minegeo.localize.prepared import PreparedMap

    text, match = JSON_CASES[case]
    p = tmp_path / "map.prepared.npz"
    np.savez(p, meta=np.array(text), points=np.zeros((3, 3)))
    with pytest.raises(FileFormatError, match=match):
        PreparedMap.load(p)


# --------------------------------------------------------------------------------------------
# 5. text files cut mid-line
# --------------------------------------------------------------------------------------------
def _rows(n=6, sep=" ") -> str:
    return "".join(sep.join(f"{v:.4f}" for v in (i + 0.5, 2 * i + 0.25, 3 * i + 0.125)) + "\n" for i in range(n))


CUT_CASES = {
    "xyz": (["info", "{p}"], "c.xyz", _rows() + "7.5 14.25", "line 7"),
    "csv": (["info", "{p}"], "c.csv", "x,y,z\n" + _rows(sep=",") + "7.5,14.25", "line 8"),
    "pts": (["info", "{p}"], "c.pts", "7\n" + _rows() + "7.5 14", "line 8"),
    "ply-ascii": (["info", "{p}"], "c.ply",
                  "ply\nformat ascii 1.0\nelement vertex 7\nproperty double x\nproperty double y\nproperty double z\n"
                  "end_header\n" + _rows() + "7.5 14.25", "line 14"),
    "pcd-ascii": (["info", "{p}"], "c.pcd", _pcd(7, "ascii", b"").decode() + _rows() + "7.5", "line 16"),
    "tum": (["info", "{p}", "--kind", "trajectory"], "t.tum",
            "".join(f"{i} {i} 0 0 0 0 0 1\n" for i in range(5)) + "5 5 0 0 0", "line 6"),
    "gcp": (["info", "{p}", "--kind", "gcp"], "g.csv",
            "id,x,y,z,E,N,H\nA,0,0,0,1,2,3\nB,1,0,0,2,2,3\nC,0,1,0,1,3,3\nD,1,1,1,2,3,4\nE,2,1,0,3,3", "line 6"),
    "scan": (["mast", "--scan", "{p}", "--beacons", "{beacons}", "--out", "{out}"], "s.csv",
             "bearing_deg,range_m\n10,5\n20,5.5\n30", "line 4"),
    "beacons": (["mast", "--scan", "{scan}", "--beacons", "{p}", "--out", "{out}"], "b.csv",
                "beacon_id,vertex,x_m,y_m\nB1,0,0,0\nB1,1,1,1\nB1,2,2,1\nB1,3,3", "row 5"),
}


@pytest.mark.parametrize("case", list(CUT_CASES))
def test_line_cut_short_names_the_line(case, good, tmp_path, capsys, caplog):
    argv, name, text, match = CUT_CASES[case]
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    argv = [a.replace("{p}", str(p)) for a in _fill(argv, good, tmp_path / "out")]
    assert_user_error(argv, capsys, caplog, match, inputs=[p])


@pytest.mark.parametrize("name", ["c.xyz", "c.csv", "c.ply", "c.pcd"])
def test_last_line_without_end_of_line_is_read_and_reported(name, tmp_path, capsys, caplog):
    """Policy: a number cut short cannot be seen; the missing end-of-line is reported, not fatal."""
    p = tmp_path / name
    c = PointCloud(np.arange(21, dtype=float).reshape(7, 3) + 0.5)
    write_point_cloud(p, c, binary=False)
    data = p.read_bytes()
    assert data.endswith(b"\n")
    p.write_bytes(data[:-3])  # "20.5\n" -> "20": a number cut short, and no end-of-line
    lines = data.decode().splitlines()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        cloud = read_point_cloud(p)
    assert cloud.metadata["unterminated_last_line"] == len(lines)
    assert cloud.points[-1, 2] == 20.0
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warned) == 1 and "no end-of-line" in warned[0] and f"({len(lines)}:" in warned[0]
    capsys.readouterr()
    assert main(["info", str(p)]) == 0
    # a complete file says nothing
    p.write_bytes(data)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert "unterminated_last_line" not in read_point_cloud(p).metadata
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


# --------------------------------------------------------------------------------------------
# 6. huge coordinates: refused with the file named, no RuntimeWarning on the way
# --------------------------------------------------------------------------------------------
def _full_scan_with(i: int, value: str) -> bytes:
    """A 720-return scan (sigmas stated, so the pipeline would run) whose return ``i`` is ``value``."""
    rows = [f"{0.5 * k},{value if k == i else '5.0'}\n" for k in range(720)]
    return ("# sigma_range_m: 0.003\n# sigma_bearing_deg: 0.01\nbearing_deg,range_m\n" + "".join(rows)).encode()


HUGE_CASES = {
    "xyz-1e308": (["info", "{p}"], "h.xyz", b"1e308 0 0\n-1e308 1 1\n0 0 0\n", "beyond"),
    "xyz-1e300-origin-auto": (["georef", "--map", "{p}", "--gcps", "{gcps}", "--out", "{out}/m.ply", "--report",
                               "{out}/r"], "h.xyz", b"1e300 0 0\n-1e300 1 1\n0 0 0\n5 5 5\n", "beyond"),
    "ply-binary-1e308": (["info", "{p}"], "h.ply", _ply_binary(2, 0) + np.array([[1e308, 0, 0], [-1e308, 0, 0]]).tobytes(),
                         "beyond"),
    "pcd-float32-max": (["info", "{p}"], "h.pcd",
                        _pcd(2, "binary", np.array([[3.4e38, 0, 0], [-3.4e38, 0, 0]], dtype="<f4").tobytes()),
                        "beyond"),
    "tum-1e308": (["info", "{p}", "--kind", "trajectory"], "h.tum",
                  b"0 1e308 0 0 0 0 0 1\n1 -1e308 0 0 0 0 0 1\n", "beyond"),
    "tum-time-1e308": (["info", "{p}", "--kind", "trajectory"], "t.tum",
                       b"1e308 0 0 0 0 0 0 1\n-1e308 1 0 0 0 0 0 1\n", "time"),
    "tum-quaternion-1e308": (["info", "{p}", "--kind", "trajectory"], "q.tum",
                             b"0 0 0 0 0 0 0 1e308\n1 1 0 0 0 0 0 1\n", "quaternion"),
    "gcp-1e308": (["info", "{p}", "--kind", "gcp"], "g.csv",
                  b"id,x,y,z,E,N,H\nA,1e308,0,0,1,2,3\nB,-1e308,1,1,4,5,6\nC,0,5,0,7,8,9\n", "beyond"),
    "gcp-sigma-1e-308": (["info", "{p}", "--kind", "gcp"], "s.csv",
                         b"id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m\nA,0,0,0,1,2,3,1e-308,0.01,0.01\n", "below"),
    "scan-range-1e308": (["mast", "--scan", "{p}", "--beacons", "{beacons}", "--out", "{out}"], "r.csv",
                         _full_scan_with(10, "1e308"), "line 14: range"),
    "beacons-1e308": (["mast", "--scan", "{scan}", "--beacons", "{p}", "--out", "{out}"], "b.csv",
                      b"beacon_id,vertex,x_m,y_m\nB1,0,1e308,0\nB1,1,1,1\nB1,2,2,1\nB1,3,-1e308,0\n", "beyond"),
    "network-1e308": (["adjust", "{p}", "--out", "{out}"], "n.dat",
                      b"[Coordinates]\nA 0 0\nB 1e308 0\nC 50 80\n[Datum]\nfix A B\n[Distances]\nA C 94.34 0.01\n"
                      b"B C 94.34 0.01\n", "line 3"),
    "network-sigma-1e-300": (["adjust", "{p}", "--out", "{out}"], "s.dat",
                             b"[Coordinates]\nA 0 0\nB 100 0\nC 50 80\n[Datum]\nfix A B\n[Distances]\nA C 94.34 1e-300\n"
                             b"B C 94.34 0.01\n", "line 8"),
}


@pytest.mark.parametrize("case", list(HUGE_CASES))
def test_huge_values_are_refused_without_runtime_warnings(case, good, tmp_path, capsys, caplog):
    argv, name, data, match = HUGE_CASES[case]
    p = tmp_path / name
    p.write_bytes(data)
    argv = [a.replace("{p}", str(p)) for a in _fill(argv, good, tmp_path / "out")]
    assert_user_error(argv, capsys, caplog, match, inputs=[p])


def test_large_projected_coordinates_still_read(tmp_path):
    """Positive control: 10^7 m coordinates (and 10^11, inside the bound) read with origin='auto'."""
    p = tmp_path / "big.xyz"
    p.write_text("5000000.25 60000000.5 120.0\n5000010.25 60000020.5 121.0\n1e11 -1e11 0\n", encoding="utf-8")
    c = read_point_cloud(p, origin="auto")
    assert np.isfinite(c.points).all() and np.all(c.global_points[0] == [5000000.25, 60000000.5, 120.0])
