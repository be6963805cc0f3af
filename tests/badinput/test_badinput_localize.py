"""``minegeo localize --map M --scan S [--trajectory T] --out DIR``: every user mistake is one line,
exit 2, nothing written (no result folder, no prepared-map cache beside the map); an earlier result
folder stays byte-identical.

Most runs use a prepared map (``prepare-map --profile fast``, made once) so that a scan that is
only found unusable after the map is loaded costs a fraction of a second.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    copy_tree,
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


def _xyz(tmp: Path, name: str, pts) -> Path:
    return write_file(tmp, name, "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in pts))


def _planar(tmp: Path) -> Path:
    """A flat 40 m x 40 m floor, 0.4 m spacing: no 3D structure to register."""
    g = np.arange(0.0, 40.0, 0.4)
    xx, yy = np.meshgrid(g, g)
    return _xyz(tmp, "planar.xyz", np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)]))


def _line(tmp: Path) -> Path:
    t = np.arange(0.0, 60.0, 0.05)
    return _xyz(tmp, "line.xyz", np.column_stack([t, 0.5 * t, np.zeros(t.size)]))


@pytest.fixture(scope="module")
def prep(mine, tmp_path_factory):
    """The module's map prepared once with --profile fast."""
    from minegeo.cli import main

    out = tmp_path_factory.mktemp("prepared") / "map_fast.npz"
    assert main(["-q", "prepare-map", "--map", str(mine / "map.ply"), "--out", str(out), *FAST]) == 0
    return out


SCAN_CASES = {
    "missing": lambda t, m: t / "nope.ply",
    "folder": lambda t, m: a_folder(t),
    "empty": lambda t, m: write_file(t, "empty.ply", b""),
    "truncated": lambda t, m: truncated_copy(m / "scans" / "scan_04.ply", t / "half.ply"),
    "nan_row": lambda t, m: write_file(t, "nan.xyz", "0 0 0\n1 0 0\nnan 1 0\n0 1 1\n" * 20),
    "inf_row": lambda t, m: write_file(t, "inf.xyz", "0 0 0\n1 0 0\n1 inf 0\n0 1 1\n" * 20),
    "two_columns": lambda t, m: write_file(t, "two.xyz", "0 0\n1 0\n1 1\n0 1\n" * 20),
    "non_utf8": lambda t, m: write_file(t, "latin1.xyz", b"0 0 0\n1 0 0\n1 1 \xe9\xff\n0 1 1\n" * 20),
    "stream": lambda t, m: Path("/dev/zero"),
    "stream_behind_ply_name": lambda t, m: stream_link(t, "zero.ply"),
    "folder_named_ply": lambda t, m: a_folder(t, "folder.ply"),
    "unknown_extension": lambda t, m: write_file(t, "scan.dat", "0 0 0\n1 0 0\n1 1 0\n0 1 1\n"),
    "ten_points": lambda t, m: _xyz(t, "ten.xyz", np.random.default_rng(1).uniform(0, 20, (10, 3))),
    "planar_only": lambda t, m: _planar(t),
    "collinear": lambda t, m: _line(t),
    "one_point_repeated": lambda t, m: write_file(t, "same.xyz", "12.25 -3.5 1.75\n" * 500),
}


@pytest.mark.parametrize("case", sorted(SCAN_CASES))
def test_bad_scan(case, mine, prep, tmp_path, capsys):
    scan = SCAN_CASES[case](tmp_path, mine)
    out = tmp_path / "out"
    assert_user_error("localize", ["--map", prep, "--scan", scan, "--out", out, *FAST], capsys,
                      inputs=[scan, prep, prep.parent, tmp_path / "a_folder"], outputs=[out])


MAP_CASES = {
    "missing": lambda t, m, g, p: t / "nope.ply",
    "folder": lambda t, m, g, p: a_folder(t),
    "empty": lambda t, m, g, p: write_file(t, "empty.ply", b""),
    "truncated": lambda t, m, g, p: truncated_copy(m / "map.ply", t / "half.ply"),
    "nan_row": lambda t, m, g, p: write_file(t, "nan.xyz", "0 0 0\n10 0 0\nnan 10 0\n0 10 3\n" * 50),
    "non_utf8": lambda t, m, g, p: write_file(t, "latin1.xyz", b"0 0 0\n10 0 0\n10 10 \xe9\xff\n0 10 3\n" * 50),
    "stream": lambda t, m, g, p: Path("/dev/zero"),
    "stream_behind_ply_name": lambda t, m, g, p: stream_link(t, "zero.ply"),
    "stream_behind_npz_name": lambda t, m, g, p: stream_link(t, "zero.npz"),
    "folder_named_npz": lambda t, m, g, p: a_folder(t, "folder.npz"),
    "three_points": lambda t, m, g, p: write_file(t, "three.xyz", "0 0 0\n10 0 0\n10 10 0\n"),
    "sidecar_truncated": lambda t, m, g, p: georef_variant(g, t / "geo", "sidecar_truncated"),
    "sidecar_non_utf8": lambda t, m, g, p: georef_variant(g, t / "geo", "sidecar_non_utf8"),
    "sidecar_unknown_epsg": lambda t, m, g, p: georef_variant(g, t / "geo", "sidecar_unknown_epsg"),
    "sidecar_stale": lambda t, m, g, p: georef_variant(g, t / "geo", "sidecar_stale"),
    "sidecar_folder": lambda t, m, g, p: georef_variant(g, t / "geo", "sidecar_folder"),
    "prepared_truncated": lambda t, m, g, p: truncated_copy(p, t / "half.npz"),
    "prepared_not_a_zip": lambda t, m, g, p: write_file(t, "text.npz", "0 0 0\n1 1 1\n"),
    "prepared_empty": lambda t, m, g, p: write_file(t, "empty.npz", b""),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, mine, geo_map, prep, tmp_path, capsys):
    map_ = MAP_CASES[case](tmp_path, mine, geo_map, prep)
    scan, out = mine / "scans" / "scan_00.ply", tmp_path / "out"
    assert_user_error("localize", ["--map", map_, "--scan", scan, "--out", out, *FAST, "--no-cache"], capsys,
                      inputs=[map_, scan, tmp_path / "a_folder", *([map_.parent] if map_.parent.name == "geo" else [])],
                      outputs=[out])


def test_prepared_map_with_other_parameters(mine, prep, tmp_path, capsys):
    """docs: asking a prepared map for other parameters than the file's is an error."""
    scan, out = mine / "scans" / "scan_00.ply", tmp_path / "out"
    assert_user_error("localize", ["--map", prep, "--scan", scan, "--out", out, *FAST, "--voxel", "0.7"], capsys,
                      inputs=[prep, scan], outputs=[out])


TRAJ_CASES = {
    "missing": lambda t, m: t / "nope.tum",
    "folder": lambda t, m: a_folder(t),
    "empty": lambda t, m: write_file(t, "empty.tum", b""),
    "truncated": lambda t, m: truncated_copy(m / "trajectories" / "scan_00.txt", t / "half.txt"),
    "nan_row": lambda t, m: write_file(t, "nan.tum", "0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n"),
    "inf_row": lambda t, m: write_file(t, "inf.tum", "0 0 0 0 0 0 0 1\n1 inf 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n"),
    "wrong_columns": lambda t, m: write_file(t, "cols.tum", "0 0 0 0 0 0 0 1\n1 1 0 0 0 0 1\n2 0 0 0 0 0 0 1\n"),
    "zero_quaternion": lambda t, m: write_file(t, "q0.tum", "0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 0\n2 0 0 0 0 0 0 1\n"),
    "non_utf8": lambda t, m: write_file(t, "latin1.tum", b"# \xe9\xff\n0 0 0 0 0 0 0 1\n1 \xe9 0 0 0 0 0 1\n"),
    "stream": lambda t, m: Path("/dev/zero"),
}


@pytest.mark.parametrize("case", sorted(TRAJ_CASES))
def test_bad_trajectory(case, mine, prep, tmp_path, capsys):
    traj = TRAJ_CASES[case](tmp_path, mine)
    scan, out = mine / "scans" / "scan_00.ply", tmp_path / "out"
    assert_user_error("localize", ["--map", prep, "--scan", scan, "--trajectory", traj, "--out", out, *FAST],
                      capsys, inputs=[traj, scan, prep, tmp_path / "a_folder"], outputs=[out])


OPTION_CASES = {
    "seed_negative": ["--seed", "-1"],
    "voxel_0": ["--voxel", "0"],
    "voxel_negative": ["--voxel", "-0.5"],
    "voxel_nan": ["--voxel", "nan"],
    "octree_level_negative": ["--octree-level", "-1"],
    "ransac_runs_0": ["--ransac-runs", "0"],
    "ransac_runs_negative": ["--ransac-runs", "-2"],
    "ransac_max_iterations_0": ["--ransac-max-iterations", "0"],
    "ransac_max_iterations_negative": ["--ransac-max-iterations", "-5"],
    "ransac_min_iterations_negative": ["--ransac-min-iterations", "-1"],
    "hypotheses_0": ["--hypotheses", "0"],
    "levelled_0": ["--levelled", "0"],
    "levelled_above_90": ["--levelled", "91"],
    "levelled_nan": ["--levelled", "nan"],
    "polish_negative": ["--polish", "-1"],
    "polish_nan": ["--polish", "nan"],
    "fine_tolerance_negative": ["--fine-tolerance", "-0.01"],
    "fine_tolerance_nan": ["--fine-tolerance", "nan"],
    "seed_beyond_numpy": ["--seed", str(2**32)],
    "voxel_inf": ["--voxel", "inf"],
    "octree_level_huge": ["--octree-level", "30"],
    "hypotheses_1": ["--hypotheses", "1"],
    "ransac_runs_fraction": ["--ransac-runs", "1.5"],
    "ransac_max_iterations_huge": ["--ransac-max-iterations", "1e12"],
    "ransac_min_above_max": ["--ransac-min-iterations", "1000", "--ransac-max-iterations", "100"],
    "levelled_with_no_gravity_fallback": ["--levelled", "3", "--no-gravity-fallback"],
    "correlative_with_no_gravity_fallback": ["--correlative", "always", "--no-gravity-fallback"],
    "polish_inf": ["--polish", "inf"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, mine, prep, tmp_path, capsys):
    scan, out = mine / "scans" / "scan_00.ply", tmp_path / "out"
    assert_user_error("localize", ["--map", prep, "--scan", scan, "--out", out, *FAST, *OPTION_CASES[case]], capsys,
                      inputs=[prep, scan], outputs=[out])


def test_failing_run_writes_no_map_cache(mine, tmp_path, capsys):
    """The prepared-map cache is documented for runs that localize; a run stopped by an unusable scan
    writes nothing, not even the cache beside the map (the map's folder is unchanged)."""
    d = tmp_path / "maps"
    d.mkdir()
    map_ = Path(shutil.copy2(mine / "map.ply", d / "map.ply"))
    scan = SCAN_CASES["planar_only"](tmp_path, mine)
    assert_user_error("localize", ["--map", map_, "--scan", scan, "--out", tmp_path / "out", *FAST], capsys,
                      inputs=[map_, d, scan], outputs=[tmp_path / "out"])


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def work(mine, prep, tmp_path):
    """Map (prepared), scan and trajectory in a folder that also holds an earlier result (result.json)."""
    d = tmp_path / "work"
    d.mkdir()
    shutil.copy2(prep, d / "map.npz")
    shutil.copy2(mine / "scans" / "scan_00.ply", d / "scan.ply")
    shutil.copy2(mine / "trajectories" / "scan_00.txt", d / "traj.txt")
    (d / "result.json").write_text('{"status": "ok"}', encoding="utf-8")
    return d


def _a_file(d: Path, name="afile") -> Path:
    return a_file(d.parent, name)


OUT_CASES = {
    "out_is_the_scan": lambda d: d / "scan.ply",
    "out_is_the_map": lambda d: d / "map.npz",
    "out_is_the_trajectory": lambda d: d / "traj.txt",
    "out_symlink_to_scan": lambda d: (d / "link").symlink_to(d / "scan.ply") or d / "link",
    "out_hardlink_to_scan": lambda d: os.link(d / "scan.ply", d / "hard") or d / "hard",
    "out_contains_the_inputs": lambda d: d,
    "out_is_an_existing_file": lambda d: _a_file(d),
    "out_through_a_file": lambda d: _a_file(d) / "sub",
    "out_not_empty_no_result": lambda d: a_folder(d.parent, "busy"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, work, capsys):
    out = OUT_CASES[case](work)
    assert_user_error("localize", ["--map", work / "map.npz", "--scan", work / "scan.ply", "--trajectory",
                                   work / "traj.txt", "--out", out, *FAST], capsys,
                      inputs=[work / "map.npz", work / "scan.ply", work / "traj.txt", work], outputs=[out])


def test_failing_run_creates_no_parent_folder(mine, prep, tmp_path, capsys):
    out = tmp_path / "new" / "sub" / "out"
    scan = SCAN_CASES["one_point_repeated"](tmp_path, mine)
    assert_user_error("localize", ["--map", prep, "--scan", scan, "--out", out, *FAST], capsys,
                      inputs=[prep, scan], outputs=[out])


def test_out_locked_by_live_run(mine, prep, tmp_path, capsys):
    out = tmp_path / "out"
    lk = write_lock(out, os.getpid(), "localize")
    assert_user_error("localize", ["--map", prep, "--scan", mine / "scans" / "scan_00.ply", "--out", out, *FAST],
                      capsys, inputs=[prep, mine / "scans" / "scan_00.ply"], outputs=[out],
                      expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(mine, prep, tmp_path, capsys):
    out = tmp_path / "out"
    write_lock(out, dead_pid(), "localize")
    code, _, err = run_cli("localize", ["--map", prep, "--scan", mine / "scans" / "scan_00.ply", "--out", out,
                                        *FAST], capsys)
    assert code in (0, 1), err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert (out / "result.json").is_file()
    assert leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def earlier(mine, prep, tmp_path_factory):
    """An earlier successful (status ok) localization of scan_00 with its trajectory."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "out"
    assert main(["-q", "localize", "--map", str(prep), "--scan", str(mine / "scans" / "scan_00.ply"),
                 "--trajectory", str(mine / "trajectories" / "scan_00.txt"), "--out", str(d), *FAST]) == 0
    assert {"result.json", "report.html", "trajectory_global.csv"} <= {p.name for p in d.iterdir()}
    return d


FAILING_RUNS = {
    "one_point_repeated": lambda t, m: ["--scan", SCAN_CASES["one_point_repeated"](t, m)],
    "planar_only": lambda t, m: ["--scan", SCAN_CASES["planar_only"](t, m)],
    "truncated_scan": lambda t, m: ["--scan", SCAN_CASES["truncated"](t, m)],
    "missing_scan": lambda t, m: ["--scan", t / "nope.ply"],
    "bad_trajectory": lambda t, m: ["--scan", m / "scans" / "scan_00.ply", "--trajectory", TRAJ_CASES["nan_row"](t, m)],
    "bad_option": lambda t, m: ["--scan", m / "scans" / "scan_00.ply", "--polish", "-1"],
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, mine, prep, tmp_path, capsys):
    out = copy_tree(earlier, tmp_path / "out")
    before = tree_snapshot(out)
    argv = FAILING_RUNS[case](tmp_path, mine)
    assert_user_error("localize", ["--map", prep, *argv, "--out", out, *FAST], capsys,
                      inputs=[prep, *(a for a in argv if isinstance(a, Path))], outputs=[out])
    assert tree_snapshot(out) == before
