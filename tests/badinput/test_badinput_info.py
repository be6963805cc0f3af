"""``minegeo info FILE [--json OUT]``: every user mistake is one line, exit 2, nothing written."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from _contract import (
    a_folder,
    assert_user_error,
    dead_pid,
    leftovers,
    lock_path,
    run_cli,
    stream_link,
    truncated_copy,
    write_lock,
)


def _text(tmp: Path, name: str, data) -> Path:
    p = tmp / name
    p.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return p


def _gcp_edit(mine: Path, tmp: Path, name: str, edit) -> Path:
    lines = (mine / "gcps.csv").read_text(encoding="utf-8").splitlines()
    return _text(tmp, name, "\n".join(edit(lines)) + "\n")


def _field(lines, row, col, value):
    f = lines[row].split(",")
    f[col] = value
    return lines[:row] + [",".join(f)] + lines[row + 1:]


XYZ = "0 0 0\n1 0 0\n1 1 0\n0 1 1\n2 2 2\n"

#: case -> (FILE maker, extra options)
FILE_CASES = {
    "missing": (lambda t, m: t / "does_not_exist.ply", []),
    "folder": (lambda t, m: a_folder(t), []),
    "empty_ply": (lambda t, m: _text(t, "empty.ply", b""), []),
    "empty_xyz": (lambda t, m: _text(t, "empty.xyz", b""), []),
    "truncated_ply": (lambda t, m: truncated_copy(m / "scans" / "scan_04.ply", t / "half.ply"), []),
    "truncated_xyz": (lambda t, m: _text(t, "half.xyz", XYZ[: len(XYZ) // 2]), []),
    "nan_row": (lambda t, m: _text(t, "nan.xyz", "0 0 0\n1 0 0\nnan 1 0\n0 1 1\n"), []),
    "inf_row": (lambda t, m: _text(t, "inf.xyz", "0 0 0\n1 0 0\n1 inf 0\n0 1 1\n"), []),
    "two_columns": (lambda t, m: _text(t, "two.xyz", "0 0\n1 0\n1 1\n0 1\n"), []),
    "ragged_columns": (lambda t, m: _text(t, "ragged.xyz", "0 0 0\n1 0 0\n1 1\n0 1 1\n"), []),
    "non_utf8": (lambda t, m: _text(t, "latin1.xyz", b"0 0 0\n1 0 0\n1 1 \xe9\xff\n0 1 1\n"), []),
    "stream_xyz": (lambda t, m: Path("/dev/zero"), ["--format", "xyz"]),
    "stream_ply": (lambda t, m: Path("/dev/zero"), ["--format", "ply"]),
    "stream_pcd": (lambda t, m: Path("/dev/zero"), ["--format", "pcd"]),
    "stream_no_format": (lambda t, m: Path("/dev/zero"), []),
    "stream_behind_ply_name": (lambda t, m: stream_link(t, "zero.ply"), []),
    "folder_named_ply": (lambda t, m: a_folder(t, "folder.ply"), []),
    "unknown_format_option": (lambda t, m: _text(t, "ok.xyz", XYZ), ["--format", "nonsense"]),
    "gcp_empty": (lambda t, m: _text(t, "g.csv", b""), ["--kind", "gcp"]),
    "gcp_truncated": (lambda t, m: truncated_copy(m / "gcps.csv", t / "g.csv"), ["--kind", "gcp"]),
    "gcp_nan_row": (lambda t, m: _gcp_edit(m, t, "g.csv", lambda ls: _field(ls, 3, 4, "nan")), ["--kind", "gcp"]),
    "gcp_inf_row": (lambda t, m: _gcp_edit(m, t, "g.csv", lambda ls: _field(ls, 3, 1, "-inf")), ["--kind", "gcp"]),
    "gcp_wrong_columns": (lambda t, m: _gcp_edit(m, t, "g.csv", lambda ls: ls[:3] + [ls[3].rsplit(",", 4)[0]] + ls[4:]),
                          ["--kind", "gcp"]),
    "gcp_non_utf8": (lambda t, m: _text(t, "g.csv", (m / "gcps.csv").read_bytes().replace(b"GCP03", b"GCP\xe903")),
                     ["--kind", "gcp"]),
    "gcp_stream": (lambda t, m: Path("/dev/zero"), ["--kind", "gcp"]),
    "trajectory_nan_row": (lambda t, m: _text(t, "t.tum", "0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n"),
                           ["--kind", "trajectory"]),
    "trajectory_wrong_columns": (lambda t, m: _text(t, "t.tum", "0 0 0 0 0 0 0 1\n1 1 0 0 0 0 1\n"),
                                 ["--kind", "trajectory"]),
    "trajectory_empty": (lambda t, m: _text(t, "t.tum", b""), ["--kind", "trajectory"]),
    "trajectory_non_utf8": (lambda t, m: _text(t, "t.tum", b"# \xff\xfe\n0 0 0 0 0 0 0 1\n1 \xe9 0 0 0 0 0 1\n"),
                            ["--kind", "trajectory"]),
    "trajectory_stream": (lambda t, m: Path("/dev/zero"), ["--kind", "trajectory", "--format", "tum"]),
}


@pytest.mark.parametrize("case", sorted(FILE_CASES))
def test_bad_file(case, mine, tmp_path, capsys):
    make, extra = FILE_CASES[case]
    f = make(tmp_path, mine)
    out = tmp_path / "out" / "info.json"
    assert_user_error("info", [f, *extra, "--json", out], capsys, inputs=[f, tmp_path / "a_folder"],
                      outputs=[out])


@pytest.fixture
def cloud(mine, tmp_path):
    """A valid input cloud in its own folder (the folder tree is checked too)."""
    d = tmp_path / "in"
    d.mkdir()
    return Path(shutil.copy2(mine / "scans" / "scan_04.ply", d / "scan.ply"))


OUT_CASES = {
    "json_is_the_input": lambda f: f,
    "json_symlink_to_input": lambda f: (f.parent / "link.json").symlink_to(f) or f.parent / "link.json",
    "json_hardlink_to_input": lambda f: os.link(f, f.parent / "hard.json") or f.parent / "hard.json",
    "json_is_a_folder": lambda f: a_folder(f.parent.parent, "jsondir"),
    "json_through_a_file": lambda f: (f.parent / "afile").write_text("keep") and f.parent / "afile" / "x.json",
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_json_output(case, cloud, capsys):
    out = OUT_CASES[case](cloud)
    assert_user_error("info", [cloud, "--json", out], capsys, inputs=[cloud, cloud.parent], outputs=[out])


def test_json_locked_by_live_run(cloud, tmp_path, capsys):
    out = tmp_path / "o" / "info.json"
    lk = write_lock(out, os.getpid(), "info")
    assert_user_error("info", [cloud, "--json", out], capsys, inputs=[cloud], outputs=[out],
                      expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(cloud, tmp_path, capsys):
    out = tmp_path / "o" / "info.json"
    write_lock(out, dead_pid(), "info")
    code, _, err = run_cli("info", [cloud, "--json", out], capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert json.loads(out.read_text(encoding="utf-8"))["verb"] == "info"
    assert leftovers(out.parent) == []
