"""``minegeo mast --scan S --beacons B --out DIR``: every user mistake is one line, exit 2, nothing
written, an earlier result folder untouched.

(A beacon out of view is not a user mistake: docs/mast.md documents it as status ``failed``,
exit 1, with a result written; it is tested in tests/test_cli_contracts.py.)
"""

from __future__ import annotations

import os
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
    symlink_beside,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)


def _lines(p) -> list[str]:
    return Path(p).read_text(encoding="utf-8").splitlines()


def _rows(scan_lines):
    """Index of the first data row of a scan file."""
    return next(k for k, ln in enumerate(scan_lines) if ln.startswith("bearing_deg")) + 1


def _scan(tmp: Path, scene, edit) -> Path:
    return write_file(tmp, "scan_bad.csv", "\n".join(edit(_lines(scene["scan"]))) + "\n")


def _beacons(tmp: Path, scene, edit) -> Path:
    return write_file(tmp, "beacons_bad.csv", "\n".join(edit(_lines(scene["beacons"]))) + "\n")


def _insert(ls, row):
    i = _rows(ls) + 5
    return ls[:i] + [row] + ls[i:]


def _negate_ranges(ls):
    i = _rows(ls)
    return ls[:i] + [f"{ln.split(',')[0]},-{ln.split(',')[1]}" for ln in ls[i:]]


def _set_field(ls, row, col, value):
    f = ls[row].split(",")
    f[col] = value
    return ls[:row] + [",".join(f)] + ls[row + 1:]


SCAN_CASES = {
    "missing": lambda t, s: t / "nope.csv",
    "folder": lambda t, s: a_folder(t),
    "empty": lambda t, s: write_file(t, "empty.csv", b""),
    "truncated": lambda t, s: truncated_copy(s["scan"], t / "half.csv"),
    "nan_bearing": lambda t, s: _scan(t, s, lambda ls: _insert(ls, "nan,5.0")),
    "inf_bearing": lambda t, s: _scan(t, s, lambda ls: _insert(ls, "inf,5.0")),
    "one_column_row": lambda t, s: _scan(t, s, lambda ls: _insert(ls, "12.5")),
    "three_column_row": lambda t, s: _scan(t, s, lambda ls: _insert(ls, "12.5,5.0,7.0")),
    "no_header": lambda t, s: _scan(t, s, lambda ls: [ln for ln in ls if not ln.startswith("bearing_deg")]),
    "non_utf8": lambda t, s: write_file(t, "latin1.csv", b"# site: Schacht S\xfcd\n" + Path(s["scan"]).read_bytes()),
    "stream": lambda t, s: Path("/dev/zero"),
    "header_only": lambda t, s: _scan(t, s, lambda ls: ls[: _rows(ls)]),
    "two_returns": lambda t, s: _scan(t, s, lambda ls: ls[: _rows(ls) + 2]),  # MAST needs >= 3
    "all_ranges_negative": lambda t, s: _scan(t, s, _negate_ranges),
    "one_negative_range": lambda t, s: _scan(t, s, lambda ls: _insert(ls, "-100.5,-4.0")),
}


@pytest.mark.parametrize("case", sorted(SCAN_CASES))
def test_bad_scan(case, mast_scene, tmp_path, capsys):
    scan = SCAN_CASES[case](tmp_path, mast_scene)
    out = tmp_path / "out"
    assert_user_error("mast", ["--scan", scan, "--beacons", mast_scene["beacons"], "--out", out], capsys,
                      inputs=[scan, mast_scene["beacons"], tmp_path / "a_folder"], outputs=[out])


BEACON_CASES = {
    "missing": lambda t, s: t / "nope.csv",
    "folder": lambda t, s: a_folder(t),
    "empty": lambda t, s: write_file(t, "empty.csv", b""),
    "truncated": lambda t, s: truncated_copy(s["beacons"], t / "half.csv"),
    "nan_coordinate": lambda t, s: _beacons(t, s, lambda ls: _set_field(ls, 2, 2, "nan")),
    "inf_coordinate": lambda t, s: _beacons(t, s, lambda ls: _set_field(ls, 3, 3, "inf")),
    "three_column_row": lambda t, s: _beacons(t, s, lambda ls: ls[:2] + [ls[2].rsplit(",", 1)[0]] + ls[3:]),
    "non_utf8": lambda t, s: write_file(t, "latin1.csv", Path(s["beacons"]).read_bytes().replace(b"B1,", b"B\xfc1,")),
    "stream": lambda t, s: Path("/dev/zero"),
    "one_beacon": lambda t, s: _beacons(t, s, lambda ls: [ln for ln in ls if not ln.startswith("B2,")]),
    "three_vertices": lambda t, s: _beacons(t, s, lambda ls: [ln for ln in ls if not ln.startswith("B2,3,")]),
    "collinear_vertices": lambda t, s: _beacons(
        t, s, lambda ls: [ln for ln in ls if not ln.startswith("B2,")]
        + ["B2,0,6.0,6.5", "B2,1,6.0,6.8", "B2,2,6.0,7.1", "B2,3,6.0,7.4"]),
}


@pytest.mark.parametrize("case", sorted(BEACON_CASES))
def test_bad_beacons(case, mast_scene, tmp_path, capsys):
    beacons = BEACON_CASES[case](tmp_path, mast_scene)
    out = tmp_path / "out"
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", beacons, "--out", out], capsys,
                      inputs=[mast_scene["scan"], beacons, tmp_path / "a_folder"], outputs=[out])


OPTION_CASES = {
    "sigma_range_negative": ["--sigma-range-m", "-0.003"],
    "sigma_range_nan": ["--sigma-range-m", "nan"],
    "sigma_bearing_negative": ["--sigma-bearing-deg", "-1"],
    "sigma_panel_negative": ["--sigma-panel-m", "-0.01"],
    "sigma_beacon_negative": ["--sigma-beacon-m", "-0.01"],
    "sigma_beacon_inf": ["--sigma-beacon-m", "inf"],
    "min_beacons_0": ["--min-beacons", "0"],
    "options_7": ["--options", "7"],
    "options_not_numbers": ["--options", "a,b"],
    "min_beacons_negative": ["--min-beacons", "-1"],
    "sigma_bearing_nan": ["--sigma-bearing-deg", "nan"],
    "sigma_panel_inf": ["--sigma-panel-m", "inf"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, mast_scene, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", mast_scene["beacons"], "--out", out,
                               *OPTION_CASES[case]], capsys, inputs=[mast_scene["scan"], mast_scene["beacons"]],
                      outputs=[out])


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def scene_in_folder(mast_scene, tmp_path):
    """Scan and beacons in a folder that also holds an earlier minegeo result (result.json)."""
    d = tmp_path / "work"
    d.mkdir()
    for k in ("scan", "beacons"):
        (d / Path(mast_scene[k]).name).write_bytes(Path(mast_scene[k]).read_bytes())
    (d / "result.json").write_text('{"status": "ok"}', encoding="utf-8")
    return d / "scan.csv", d / "beacons.csv"


OUT_CASES = {
    "out_is_the_scan": lambda s, b: s,
    "out_is_the_beacons": lambda s, b: b,
    "out_symlink_to_scan": lambda s, b: symlink_beside(s),
    "out_hardlink_to_beacons": lambda s, b: hardlink_beside(b),
    "out_contains_the_inputs": lambda s, b: s.parent,
    "out_is_an_existing_file": lambda s, b: a_file(s.parent.parent),
    "out_through_a_file": lambda s, b: a_file(s.parent.parent) / "sub",
    "out_not_empty_no_result": lambda s, b: a_folder(s.parent.parent, "busy"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, scene_in_folder, capsys):
    scan, beacons = scene_in_folder
    out = OUT_CASES[case](scan, beacons)
    assert_user_error("mast", ["--scan", scan, "--beacons", beacons, "--out", out], capsys,
                      inputs=[scan, beacons, scan.parent], outputs=[out])


def test_failing_run_creates_no_parent_folder(mast_scene, tmp_path, capsys):
    beacons = BEACON_CASES["one_beacon"](tmp_path, mast_scene)
    out = tmp_path / "new" / "sub" / "out"
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", beacons, "--out", out], capsys,
                      inputs=[mast_scene["scan"], beacons], outputs=[out])


def test_out_locked_by_live_run(mast_scene, tmp_path, capsys):
    out = tmp_path / "out"
    lk = write_lock(out, os.getpid(), "mast")
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", mast_scene["beacons"], "--out", out],
                      capsys, inputs=[mast_scene["scan"], mast_scene["beacons"]], outputs=[out],
                      expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(mast_scene, tmp_path, capsys):
    out = tmp_path / "out"
    write_lock(out, dead_pid(), "mast")
    code, _, err = run_cli("mast", ["--scan", mast_scene["scan"], "--beacons", mast_scene["beacons"], "--out", out],
                           capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert (out / "result.json").is_file()
    assert leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def earlier(mast_scene, tmp_path_factory):
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "out"
    assert main(["mast", "--scan", str(mast_scene["scan"]), "--beacons", str(mast_scene["beacons"]),
                 "--out", str(d)]) == 0
    return d


FAILING_RUNS = {
    "one_beacon": lambda t, s: (s["scan"], BEACON_CASES["one_beacon"](t, s), []),
    "header_only_scan": lambda t, s: (SCAN_CASES["header_only"](t, s), s["beacons"], []),
    "truncated_scan": lambda t, s: (SCAN_CASES["truncated"](t, s), s["beacons"], []),
    "missing_scan": lambda t, s: (t / "nope.csv", s["beacons"], []),
    "bad_sigma_option": lambda t, s: (s["scan"], s["beacons"], ["--sigma-range-m", "-1"]),
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, mast_scene, tmp_path, capsys):
    out = copy_tree(earlier, tmp_path / "out")
    before = tree_snapshot(out)
    scan, beacons, extra = FAILING_RUNS[case](tmp_path, mast_scene)
    assert_user_error("mast", ["--scan", scan, "--beacons", beacons, "--out", out, *extra], capsys,
                      inputs=[scan, beacons], outputs=[out])
    assert tree_snapshot(out) == before
