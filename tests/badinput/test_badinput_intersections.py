"""``minegeo intersections build --map MAP --out DB``: every user mistake is one line, exit 2, nothing
written (not the base, not its ``DB.json`` record, not its ``DB.html`` report), the inputs unchanged and
an earlier base with its record and report byte-identical (issue 27).

(A map without intersections is not a user mistake: the base is written with status
``no_intersections`` and the run exits 1; it is tested in tests/semantic/test_semantic_cli.py.)
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    dead_pid,
    georef_variant,
    lock_path,
    run_cli,
    stream_link,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)

from minegeo.io import PointCloud, write_point_cloud
from minegeo.synth.network import DriftNetwork, network_cloud


@pytest.fixture(scope="module")
def netmap(tmp_path_factory):
    """A small drift network map (a 4-way crossing and a T, 20 m legs) in a folder of its own."""
    nodes = [(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)]
    edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]
    net = DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))
    d = tmp_path_factory.mktemp("net_map")
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    return d / "map.ply"


def _outputs(out: Path) -> list[Path]:
    return [out, out.with_name(out.name + ".json"), out.with_name(out.name + ".html")]


MAP_CASES = {
    "missing": lambda t, m, g: t / "nope.ply",
    "folder": lambda t, m, g: a_folder(t),
    "empty": lambda t, m, g: write_file(t, "empty.ply", b""),
    "truncated": lambda t, m, g: truncated_copy(m, t / "half.ply"),
    "junk_ply": lambda t, m, g: write_file(t, "junk.ply", "ply\nthis is not a point cloud\n"),
    "nan_row": lambda t, m, g: write_file(t, "nan.xyz", "0 0 0\n10 0 0\nnan 10 0\n0 10 3\n"),
    "inf_row": lambda t, m, g: write_file(t, "inf.xyz", "0 0 0\n10 0 0\n10 inf 0\n0 10 3\n"),
    "two_columns": lambda t, m, g: write_file(t, "two.xyz", "0 0\n10 0\n10 10\n0 10\n"),
    "stream": lambda t, m, g: Path("/dev/zero"),
    "stream_behind_ply_name": lambda t, m, g: stream_link(t, "zero.ply"),
    "no_points": lambda t, m, g: write_file(t, "nopoints.ply", b"ply\nformat ascii 1.0\nelement vertex 0\n"
                                        b"property double x\nproperty double y\nproperty double z\nend_header\n"),
    "three_points": lambda t, m, g: write_file(t, "three.xyz", "0 0 0\n10 0 0\n10 10 0\n"),
    "one_point_repeated": lambda t, m, g: write_file(t, "same.xyz", "1.5 2.5 3.5\n" * 500),
    "flat_floor_no_walls": lambda t, m, g: _floor(t),
    "unknown_extension": lambda t, m, g: write_file(t, "map.dat", "0 0 0\n10 0 0\n10 10 0\n0 10 3\n"),
    "a_base_as_map": lambda t, m, g: write_file(t, "kb.npz", b"PK\x03\x04" + bytes(100)),
    "sidecar_truncated": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_truncated"),
    "sidecar_unknown_epsg": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_unknown_epsg"),
    "sidecar_stale": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_stale"),
    "sidecar_folder": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_folder"),
}


def _floor(t: Path) -> Path:
    """A flat open floor of 10 000 points: no wall points in the wall band."""
    g = np.stack(np.meshgrid(np.linspace(-25, 25, 100), np.linspace(-25, 25, 100)), -1).reshape(-1, 2)
    p = t / "floor.ply"
    write_point_cloud(p, PointCloud(points=np.c_[g, np.zeros(len(g))]))
    return p


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, netmap, geo_map, tmp_path, capsys):
    m = MAP_CASES[case](tmp_path, netmap, geo_map)
    out = tmp_path / "out" / "kb.npz"
    ins = [m, tmp_path / "a_folder"]
    if case.startswith("sidecar"):
        ins += [Path(str(m) + ".georef.json"), m.parent]
    assert_user_error("intersections", ["build", "--map", m, "--out", out], capsys, inputs=ins,
                      outputs=_outputs(out))


OPTION_CASES = {  # (options, words of the error line)
    "cloud_radius_0": (["--cloud-radius", "0"], "argument --cloud-radius"),
    "cloud_radius_negative": (["--cloud-radius", "-5"], "argument --cloud-radius"),
    "cloud_radius_nan": (["--cloud-radius", "nan"], "argument --cloud-radius"),
    "cloud_radius_inf": (["--cloud-radius", "inf"], "argument --cloud-radius"),
    "cloud_radius_below_descriptor": (["--cloud-radius", "5"], "less than the descriptor radius"),
    "floor_cell_0": (["--floor-cell", "0"], "argument --floor-cell"),
    "floor_cell_nan": (["--floor-cell", "nan"], "argument --floor-cell"),
    "floor_cell_text": (["--floor-cell", "two"], "argument --floor-cell"),
    "seed_negative": (["--seed", "-1"], "argument --seed"),
    "seed_beyond_numpy": (["--seed", str(2**32)], "argument --seed"),
    "no_action": ([], "ACTION"),
    "unknown_action": (["rebuild"], "ACTION"),
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, netmap, tmp_path, capsys):
    opts, words = OPTION_CASES[case]
    out = tmp_path / "out" / "kb.npz"
    argv = ["build", "--map", netmap, "--out", out, *opts] if case not in ("no_action", "unknown_action") else \
        [*opts, "--map", netmap, "--out", out]
    assert_user_error("intersections", argv, capsys, inputs=[netmap], outputs=_outputs(out), expect=words)


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def map_in_folder(netmap, tmp_path):
    d = tmp_path / "work"
    d.mkdir()
    shutil.copy(netmap, d / "map.ply")
    return d / "map.ply"


OUT_CASES = {  # (extra options from the map path, the outputs the run was asked to write)
    "out_is_the_map": lambda m: ["--out", m],
    "json_is_the_map": lambda m: ["--out", m.parent.parent / "kb.npz", "--json", m],
    "report_is_the_map": lambda m: ["--out", m.parent.parent / "kb.npz", "--report", m],
    "report_is_the_out": lambda m: ["--out", m.parent.parent / "kb.npz", "--report", m.parent.parent / "kb.npz"],
    "json_is_the_report": lambda m: ["--out", m.parent.parent / "kb.npz", "--json", m.parent.parent / "r",
                                     "--report", m.parent.parent / "r"],
    "out_is_a_folder": lambda m: ["--out", a_folder(m.parent.parent, "busy")],
    "out_through_a_file": lambda m: ["--out", a_file(m.parent.parent) / "kb.npz"],
    "out_is_the_map_folder": lambda m: ["--out", m.parent],
    "out_is_the_map_by_symlink": lambda m: ["--out", _symlink(m)],
}


def _symlink(m: Path) -> Path:
    link = m.parent.parent / "link.ply"
    link.symlink_to(m)
    return link


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, map_in_folder, capsys):
    extra = OUT_CASES[case](map_in_folder)
    outs = [Path(extra[i + 1]) for i, a in enumerate(extra) if a in ("--out", "--json", "--report")]
    assert_user_error("intersections", ["build", "--map", map_in_folder, *extra], capsys,
                      inputs=[map_in_folder, map_in_folder.parent], outputs=outs)


def test_out_locked_by_live_run(netmap, tmp_path, capsys):
    out = tmp_path / "kb.npz"
    lk = write_lock(out, os.getpid(), "intersections")
    assert_user_error("intersections", ["build", "--map", netmap, "--out", out], capsys, inputs=[netmap],
                      outputs=_outputs(out), expect="being written by")
    assert lk.exists()


@pytest.fixture(scope="module")
def earlier(netmap, tmp_path_factory):
    """An earlier base with its record and report (a stale lock of a dead run taken over on the way)."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier_kb")
    write_lock(d / "kb.npz", dead_pid(), "intersections")
    assert main(["-q", "intersections", "build", "--map", str(netmap), "--out", str(d / "kb.npz")]) == 0
    assert not lock_path(d / "kb.npz").exists()
    return d


FAILING_RUNS = {
    "truncated_map": lambda t, m: (truncated_copy(m, t / "half.ply"), []),
    "flat_floor": lambda t, m: (_floor(t), []),
    "nan_cloud_radius": lambda t, m: (m, ["--cloud-radius", "nan"]),
    "cloud_radius_below_descriptor": lambda t, m: (m, ["--cloud-radius", "3"]),
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_base(case, earlier, netmap, tmp_path, capsys):
    d = tmp_path / "prev"
    shutil.copytree(earlier, d)
    before = tree_snapshot(d)
    m, extra = FAILING_RUNS[case](tmp_path, netmap)
    assert_user_error("intersections", ["build", "--map", m, "--out", d / "kb.npz", *extra], capsys,
                      inputs=[m], outputs=_outputs(d / "kb.npz"))
    assert tree_snapshot(d) == before


def _rezip(src: Path, dst: Path, edit) -> Path:
    """``src`` rewritten member by member (uncompressed, fresh ZIP checksums) with ``edit(name, bytes)``."""
    import zipfile

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, edit(info.filename, zin.read(info.filename)))
    return dst


def test_the_base_written_loads_and_an_edited_copy_does_not(earlier, tmp_path, capsys):
    """What ``build`` writes is what ``track`` accepts (the same file, loaded); one character of its meta
    changed (15.0 -> 16.0 m cloud radius) is refused as changed after it was written: through a rewritten
    archive by the integrity hash, in place by the archive's own checksum."""
    from minegeo.errors import FileFormatError
    from minegeo.semantic import IntersectionKB

    kb = IntersectionKB.load(earlier / "kb.npz")
    assert kb.status == "ok" and len(kb) == 2
    u32 = "utf-32-le"  # the meta is a NumPy unicode array: 4 bytes per character
    old, new = '"cloud_radius_m": 15.0'.encode(u32), '"cloud_radius_m": 16.0'.encode(u32)
    _rezip(earlier / "kb.npz", tmp_path / "edited.npz", lambda n, b: b.replace(old, new) if n == "meta.npy" else b)
    raw = bytearray((earlier / "kb.npz").read_bytes())
    raw[raw.index(old):raw.index(old) + len(old)] = new
    (tmp_path / "in_place.npz").write_bytes(bytes(raw))
    (tmp_path / "f").mkdir()
    for name, words in (("edited.npz", "changed after it was written (integrity hash mismatch: its meta"),
                        ("in_place.npz", "changed after it was written (archive checksum mismatch of 'meta.npy')")):
        with pytest.raises(FileFormatError, match=re.escape(words)):
            IntersectionKB.load(tmp_path / name)
        code, _, err = run_cli("track", ["--frames", tmp_path / "f", "--db", tmp_path / name,
                                         "--out", tmp_path / "o"], capsys)
        assert code == 2 and len(err) == 1 and words in err[0], err
