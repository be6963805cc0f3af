"""``minegeo prepare-map --map M --out P.npz``: every user mistake is one line, exit 2, nothing
written (not the ``.npz``, not its record ``P.npz.json``); an earlier prepared map and its record
stay byte-identical."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    dead_pid,
    georef_variant,
    leftovers,
    lock_path,
    run_cli,
    stream_link,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)

FAST = ["--profile", "fast"]


def _record(out: Path) -> Path:
    return out.with_name(out.name + ".json")


MAP_CASES = {
    "missing": lambda t, m, g: t / "nope.ply",
    "folder": lambda t, m, g: a_folder(t),
    "empty": lambda t, m, g: write_file(t, "empty.ply", b""),
    "truncated": lambda t, m, g: truncated_copy(m / "map.ply", t / "half.ply"),
    "nan_row": lambda t, m, g: write_file(t, "nan.xyz", "0 0 0\n10 0 0\nnan 10 0\n0 10 3\n"),
    "inf_row": lambda t, m, g: write_file(t, "inf.xyz", "0 0 0\n10 0 0\n10 inf 0\n0 10 3\n"),
    "two_columns": lambda t, m, g: write_file(t, "two.xyz", "0 0\n10 0\n10 10\n0 10\n"),
    "non_utf8": lambda t, m, g: write_file(t, "latin1.xyz", b"0 0 0\n10 0 0\n10 10 \xe9\xff\n0 10 3\n"),
    "stream": lambda t, m, g: Path("/dev/zero"),
    "stream_behind_ply_name": lambda t, m, g: stream_link(t, "zero.ply"),
    "folder_named_ply": lambda t, m, g: a_folder(t, "folder.ply"),
    "no_points": lambda t, m, g: write_file(t, "nopoints.ply", b"ply\nformat ascii 1.0\nelement vertex 0\n"
                                        b"property double x\nproperty double y\nproperty double z\nend_header\n"),
    "three_points": lambda t, m, g: write_file(t, "three.xyz", "0 0 0\n10 0 0\n10 10 0\n"),
    "one_point_repeated": lambda t, m, g: write_file(t, "same.xyz", "1.5 2.5 3.5\n" * 500),
    "unknown_extension": lambda t, m, g: write_file(t, "map.dat", "0 0 0\n10 0 0\n10 10 0\n0 10 3\n"),
    "sidecar_truncated": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_truncated"),
    "sidecar_non_utf8": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_non_utf8"),
    "sidecar_unknown_epsg": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_unknown_epsg"),
    "sidecar_stale": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_stale"),
    "sidecar_folder": lambda t, m, g: georef_variant(g, t / "geo", "sidecar_folder"),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, mine, geo_map, tmp_path, capsys):
    map_ = MAP_CASES[case](tmp_path, mine, geo_map)
    out = tmp_path / "prep.npz"
    assert_user_error("prepare-map", ["--map", map_, "--out", out, *FAST], capsys,
                      inputs=[map_, tmp_path / "a_folder", *([map_.parent] if map_.parent.name == "geo" else [])],
                      outputs=[out, _record(out)])


OPTION_CASES = {
    "voxel_0": ["--voxel", "0"],
    "voxel_negative": ["--voxel", "-1"],
    "voxel_nan": ["--voxel", "nan"],
    "voxel_inf": ["--voxel", "inf"],
    "octree_level_negative": ["--octree-level", "-1"],
    "octree_level_huge": ["--octree-level", "99"],
    "icp_voxel_nan": ["--icp-voxel", "nan"],
    "icp_voxel_inf": ["--icp-voxel", "inf"],
    "icp_voxel_negative": ["--icp-voxel", "-0.1"],
    "chunk_points_0": ["--chunk-points", "0"],
    "chunk_points_fraction": ["--chunk-points", "1e5"],
    "max_memory_gb_nan": ["--max-memory-gb", "nan"],
    "max_memory_gb_negative": ["--max-memory-gb", "-1"],
    "octree_level_0": ["--octree-level", "0"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, mine, tmp_path, capsys):
    out = tmp_path / "prep.npz"
    assert_user_error("prepare-map", ["--map", mine / "map.ply", "--out", out, *FAST, *OPTION_CASES[case]], capsys,
                      inputs=[mine / "map.ply", mine], outputs=[out, _record(out)])


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def work(mine, tmp_path):
    d = tmp_path / "work"
    d.mkdir()
    shutil.copy2(mine / "map.ply", d / "map.ply")
    return d


def _a_file(d: Path, name="afile.npz") -> Path:
    return a_file(d.parent, name)


#: case -> (--map, --out) from the work folder
OUT_CASES = {
    "out_is_the_map": lambda d: ((d / "map.ply").rename(d / "map.npz") and d / "map.npz",) * 2,
    "out_symlink_to_map": lambda d: (d / "map.ply", (d / "p.npz").symlink_to(d / "map.ply") or d / "p.npz"),
    "out_hardlink_to_map": lambda d: (d / "map.ply", os.link(d / "map.ply", d / "p.npz") or d / "p.npz"),
    "out_not_npz": lambda d: (d / "map.ply", d.parent / "prep.ply"),
    "out_is_a_folder": lambda d: (d / "map.ply", a_folder(d.parent, "prep.npz")),
    "out_exists_without_force": lambda d: (d / "map.ply", _a_file(d)),
    "out_through_a_file": lambda d: (d / "map.ply", _a_file(d, "afile") / "prep.npz"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, work, capsys):
    map_, out = OUT_CASES[case](work)
    assert_user_error("prepare-map", ["--map", map_, "--out", out, *FAST], capsys, inputs=[map_, work],
                      outputs=[out, _record(out)])


def test_failing_run_creates_no_parent_folder(mine, tmp_path, capsys):
    out = tmp_path / "new" / "sub" / "prep.npz"
    assert_user_error("prepare-map", ["--map", MAP_CASES["nan_row"](tmp_path, mine, None), "--out", out, *FAST],
                      capsys, outputs=[out, _record(out)])


def test_out_locked_by_live_run(mine, tmp_path, capsys):
    out = tmp_path / "prep.npz"
    lk = write_lock(out, os.getpid(), "prepare-map")
    assert_user_error("prepare-map", ["--map", mine / "map.ply", "--out", out, *FAST], capsys,
                      inputs=[mine / "map.ply", mine], outputs=[out, _record(out)], expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(mine, tmp_path, capsys):
    out = tmp_path / "prep.npz"
    write_lock(out, dead_pid(), "prepare-map")
    code, _, err = run_cli("prepare-map", ["--map", mine / "map.ply", "--out", out, *FAST], capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert out.is_file() and _record(out).is_file()
    assert leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def earlier(mine, tmp_path_factory):
    """An earlier prepared map: prep/prep.npz and its record prep/prep.npz.json."""
    from minegeo.cli import main

    out = tmp_path_factory.mktemp("prep") / "prep.npz"
    assert main(["-q", "prepare-map", "--map", str(mine / "map.ply"), "--out", str(out), *FAST]) == 0
    return out


FAILING_RUNS = {
    "truncated_map": lambda t, m: ["--map", MAP_CASES["truncated"](t, m, None), "--force"],
    "nan_map": lambda t, m: ["--map", MAP_CASES["nan_row"](t, m, None), "--force"],
    "bad_voxel": lambda t, m: ["--map", m / "map.ply", "--voxel", "-1", "--force"],
    "no_force": lambda t, m: ["--map", m / "map.ply"],
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, mine, tmp_path, capsys):
    d = tmp_path / "prep"
    shutil.copytree(earlier.parent, d)
    out = d / earlier.name
    before = tree_snapshot(d)
    argv = FAILING_RUNS[case](tmp_path, mine)
    assert_user_error("prepare-map", [*argv, "--out", out, *FAST], capsys, inputs=[argv[1]],
                      outputs=[out, _record(out)])
    assert tree_snapshot(d) == before
