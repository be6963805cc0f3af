"""``minegeo georef --map M --gcps G --out MAP_GEO --report DIR``: every user mistake is one line,
exit 2, and nothing is written (not the map, not its sidecar ``MAP_GEO.georef.json``, not the
report folder); an earlier georeferenced map, sidecar and report folder stay byte-identical."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    copy_tree,
    dead_pid,
    hardlink_beside,
    leftovers,
    lock_path,
    run_cli,
    stream_link,
    symlink_beside,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)


def _gcps(mine: Path, tmp: Path, edit, name: str = "gcps_bad.csv") -> Path:
    lines = (mine / "gcps.csv").read_text(encoding="utf-8").splitlines()
    return write_file(tmp, name, "\n".join(edit(lines)) + "\n")


def _field(ls, row, col, value):
    f = ls[row].split(",")
    f[col] = value
    return ls[:row] + [",".join(f)] + ls[row + 1:]


def _collinear(ls):
    """The header, then every GCP on one straight line in both frames."""
    out = ls[:2]
    for i in range(6):
        x = 10.0 * i
        out.append(f"C{i},{x},{2 * x},{0.5 * x},{200000 + x},{600000 + 2 * x},{100 + 0.5 * x},0.005,0.005,0.005")
    return out


def _no_sigma_columns(ls):
    return [ls[0]] + [ln.rsplit(",", 3)[0] for ln in ls[1:]]


def _sidecar(out: Path) -> Path:
    return out.with_name(out.name + ".georef.json")


XYZ = "0 0 0\n10 0 0\n10 10 0\n0 10 3\n5 5 1\n"

MAP_CASES = {
    "missing": lambda t, m: t / "nope.ply",
    "folder": lambda t, m: a_folder(t),
    "empty": lambda t, m: write_file(t, "empty.ply", b""),
    "truncated": lambda t, m: truncated_copy(m / "map.ply", t / "half.ply"),
    "nan_row": lambda t, m: write_file(t, "nan.xyz", "0 0 0\n10 0 0\nnan 10 0\n0 10 3\n"),
    "inf_row": lambda t, m: write_file(t, "inf.xyz", "0 0 0\n10 0 0\n10 -inf 0\n0 10 3\n"),
    "two_columns": lambda t, m: write_file(t, "two.xyz", "0 0\n10 0\n10 10\n0 10\n"),
    "non_utf8": lambda t, m: write_file(t, "latin1.xyz", b"0 0 0\n10 0 0\n10 10 \xe9\xff\n0 10 3\n"),
    "stream": lambda t, m: Path("/dev/zero"),
    "stream_behind_ply_name": lambda t, m: stream_link(t, "zero.ply"),
    "folder_named_ply": lambda t, m: a_folder(t, "folder.ply"),
    "no_points": lambda t, m: write_file(t, "nopoints.ply", b"ply\nformat ascii 1.0\nelement vertex 0\n"
                                     b"property double x\nproperty double y\nproperty double z\nend_header\n"),
    "unknown_extension": lambda t, m: write_file(t, "map.dat", XYZ),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, mine, tmp_path, capsys):
    map_ = MAP_CASES[case](tmp_path, mine)
    out, rep = tmp_path / "map_geo.ply", tmp_path / "rep"
    assert_user_error("georef", ["--map", map_, "--gcps", mine / "gcps.csv", "--out", out, "--report", rep],
                      capsys, inputs=[map_, mine / "gcps.csv", tmp_path / "a_folder"],
                      outputs=[out, _sidecar(out), rep])


GCP_CASES = {
    "missing": (lambda t, m: t / "nope.csv", []),
    "folder": (lambda t, m: a_folder(t), []),
    "empty": (lambda t, m: write_file(t, "empty.csv", b""), []),
    "truncated": (lambda t, m: truncated_copy(m / "gcps.csv", t / "half.csv"), []),
    "nan_row": (lambda t, m: _gcps(m, t, lambda ls: _field(ls, 3, 4, "nan")), []),
    "inf_row": (lambda t, m: _gcps(m, t, lambda ls: _field(ls, 4, 2, "inf")), []),
    "wrong_columns": (lambda t, m: _gcps(m, t, lambda ls: ls[:3] + [ls[3].rsplit(",", 2)[0]] + ls[4:]), []),
    "non_utf8": (lambda t, m: write_file(t, "latin1.csv", (m / "gcps.csv").read_bytes().replace(b"GCP03", b"GCP\xe903")),
                 []),
    "stream": (lambda t, m: Path("/dev/zero"), ["--crs", "EPSG:5186"]),
    "header_only": (lambda t, m: _gcps(m, t, lambda ls: ls[:2]), []),
    "two_points": (lambda t, m: _gcps(m, t, lambda ls: ls[:4]), []),
    "duplicate_id": (lambda t, m: _gcps(m, t, lambda ls: ls + [ls[3]]), []),
    "collinear": (lambda t, m: _gcps(m, t, _collinear), []),
    "all_one_point": (lambda t, m: _gcps(m, t, lambda ls: ls[:2] + [ls[2].replace("GCP01", f"P{i}") for i in range(6)]),
                      []),
    "unknown_epsg_in_file": (lambda t, m: _gcps(m, t, lambda ls: [ln.replace("EPSG:5186", "EPSG:999999") for ln in ls]),
                             []),
    "unknown_epsg_option": (lambda t, m: _gcps(m, t, lambda ls: ls[1:]), ["--crs", "EPSG:999999"]),
    "geographic_crs_option": (lambda t, m: _gcps(m, t, lambda ls: ls[1:]), ["--crs", "EPSG:4326"]),
    "no_crs_at_all": (lambda t, m: _gcps(m, t, lambda ls: ls[1:]), []),
    "crs_option_contradicts_file": (lambda t, m: m / "gcps.csv", ["--crs", "EPSG:5187"]),
    "negative_default_sigma": (lambda t, m: _gcps(m, t, _no_sigma_columns), ["--default-sigma-m", "-0.01"]),
}


@pytest.mark.parametrize("case", sorted(GCP_CASES))
def test_bad_gcps(case, mine, tmp_path, capsys):
    make, extra = GCP_CASES[case]
    gcps = make(tmp_path, mine)
    out, rep = tmp_path / "map_geo.ply", tmp_path / "rep"
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", gcps, "--out", out, "--report", rep, *extra],
                      capsys, inputs=[mine / "map.ply", gcps, tmp_path / "a_folder"],
                      outputs=[out, _sidecar(out), rep])


OPTION_CASES = {
    "sigma_local_negative": ["--sigma-local-m", "-0.01"],
    "sigma_local_nan": ["--sigma-local-m", "nan"],
    "default_sigma_zero": ["--default-sigma-m", "0"],
    "blunder_alpha_0": ["--blunder-alpha", "0"],
    "blunder_alpha_above_1": ["--blunder-alpha", "1.5"],
    "max_scale_deviation_negative": ["--max-scale-deviation", "-0.1"],
    "max_sigma0_zero": ["--max-sigma0", "0"],
    "max_sigma0_nan": ["--max-sigma0", "nan"],
    "max_sigma0_1": ["--max-sigma0", "1"],
    "max_scale_deviation_1": ["--max-scale-deviation", "1"],
    "max_scale_deviation_nan": ["--max-scale-deviation", "nan"],
    "default_sigma_inf": ["--default-sigma-m", "inf"],
    "blunder_alpha_nan": ["--blunder-alpha", "nan"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, mine, tmp_path, capsys):
    out, rep = tmp_path / "map_geo.ply", tmp_path / "rep"
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", mine / "gcps.csv", "--out", out,
                                 "--report", rep, *OPTION_CASES[case]], capsys,
                      inputs=[mine / "map.ply", mine / "gcps.csv"], outputs=[out, _sidecar(out), rep])


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def work(mine, tmp_path):
    """map.ply and gcps.csv in a folder that also holds an earlier minegeo result (result.json)."""
    d = tmp_path / "work"
    d.mkdir()
    shutil.copy2(mine / "map.ply", d / "map.ply")
    shutil.copy2(mine / "gcps.csv", d / "gcps.csv")
    (d / "result.json").write_text('{"status": "ok"}', encoding="utf-8")
    return d


_symlink = symlink_beside
_hardlink = hardlink_beside


def _a_file(d: Path) -> Path:
    return a_file(d.parent)


#: case -> (--out, --report) from the work folder
OUT_CASES = {
    "out_is_the_map": lambda d: (d / "map.ply", d.parent / "rep"),
    "out_is_the_gcps": lambda d: (d / "gcps.csv", d.parent / "rep"),
    "out_symlink_to_map": lambda d: (_symlink(d / "map.ply", "geo.ply"), d.parent / "rep"),
    "out_hardlink_to_map": lambda d: (_hardlink(d / "map.ply", "geo.ply"), d.parent / "rep"),
    "sidecar_is_the_gcps": lambda d: ((d / "gcps.csv").rename(d / "geo.ply.georef.json") and d / "geo.ply",
                                      d.parent / "rep"),
    "report_is_the_gcps": lambda d: (d.parent / "geo.ply", d / "gcps.csv"),
    "report_symlink_to_map": lambda d: (d.parent / "geo.ply", _symlink(d / "map.ply", "rep")),
    "report_contains_the_inputs": lambda d: (d.parent / "geo.ply", d),
    "out_is_a_folder": lambda d: (a_folder(d.parent, "geo.ply"), d.parent / "rep"),
    "report_is_an_existing_file": lambda d: (d.parent / "geo.ply", _a_file(d)),
    "report_through_a_file": lambda d: (d.parent / "geo.ply", _a_file(d) / "rep"),
    "report_not_empty_no_result": lambda d: (d.parent / "geo.ply", a_folder(d.parent, "busy")),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, work, capsys):
    out, rep = OUT_CASES[case](work)
    gcps = work / "geo.ply.georef.json" if case == "sidecar_is_the_gcps" else work / "gcps.csv"
    assert_user_error("georef", ["--map", work / "map.ply", "--gcps", gcps, "--out", out, "--report", rep],
                      capsys, inputs=[work / "map.ply", gcps, work], outputs=[out, _sidecar(out), rep])


def test_failing_run_creates_no_parent_folder(mine, tmp_path, capsys):
    """Outputs in folders that do not exist yet: a failing run does not leave them behind (empty)."""
    out, rep = tmp_path / "new" / "geo" / "map_geo.ply", tmp_path / "new2" / "rep"
    gcps = GCP_CASES["collinear"][0](tmp_path, mine)
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", gcps, "--out", out, "--report", rep], capsys,
                      inputs=[mine / "map.ply", gcps], outputs=[out, _sidecar(out), rep])


@pytest.mark.parametrize("which", ["--out", "--report"])
def test_output_locked_by_live_run(which, mine, tmp_path, capsys):
    out, rep = tmp_path / "map_geo.ply", tmp_path / "rep"
    lk = write_lock(out if which == "--out" else rep, os.getpid(), "georef")
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", mine / "gcps.csv", "--out", out,
                                 "--report", rep], capsys, inputs=[mine / "map.ply", mine / "gcps.csv"],
                      outputs=[out, _sidecar(out), rep], expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(mine, tmp_path, capsys):
    out, rep = tmp_path / "map_geo.ply", tmp_path / "rep"
    write_lock(rep, dead_pid(), "georef")
    code, _, err = run_cli("georef", ["--map", mine / "map.ply", "--gcps", mine / "gcps.csv", "--out", out,
                                      "--report", rep], capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(rep).exists()
    assert out.is_file() and _sidecar(out).is_file() and (rep / "result.json").is_file()
    assert leftovers(tmp_path) == [] and leftovers(out.parent) == []


@pytest.fixture(scope="module")
def earlier(mine, tmp_path_factory):
    """An earlier successful georef: run/geo/map_geo.ply + sidecar, run/rep/ (result.json, report.html)."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "run"
    assert main(["georef", "--map", str(mine / "map.ply"), "--gcps", str(mine / "gcps.csv"),
                 "--out", str(d / "geo" / "map_geo.ply"), "--report", str(d / "rep")]) == 0
    return d


FAILING_RUNS = {
    "collinear_gcps": lambda t, m: ["--map", m / "map.ply", "--gcps", GCP_CASES["collinear"][0](t, m)],
    "nan_gcps": lambda t, m: ["--map", m / "map.ply", "--gcps", GCP_CASES["nan_row"][0](t, m)],
    "unknown_epsg": lambda t, m: ["--map", m / "map.ply", "--gcps", m / "gcps.csv", "--crs", "EPSG:999999"],
    "truncated_map": lambda t, m: ["--map", MAP_CASES["truncated"](t, m), "--gcps", m / "gcps.csv"],
    "bad_option": lambda t, m: ["--map", m / "map.ply", "--gcps", m / "gcps.csv", "--blunder-alpha", "2"],
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, mine, tmp_path, capsys):
    run = copy_tree(earlier, tmp_path / "run")
    before = tree_snapshot(run)
    out, rep = run / "geo" / "map_geo.ply", run / "rep"
    argv = FAILING_RUNS[case](tmp_path, mine)
    assert_user_error("georef", [*argv, "--out", out, "--report", rep], capsys,
                      inputs=[a for a in argv if isinstance(a, Path)], outputs=[out, _sidecar(out), rep])
    assert tree_snapshot(run) == before
