"""``minegeo demo --out DIR``: the cheap option and output mistakes (no full demo run here) are one
line, exit 2, and leave DIR (and an earlier folder there) exactly as it was."""

from __future__ import annotations

import json
import os

import pytest
from _contract import a_file, a_folder, assert_user_error, tree_snapshot, write_lock


def _a_file(tmp):
    return a_file(tmp)


def _earlier(tmp):
    """A folder holding an earlier minegeo result (result.json + a report)."""
    d = tmp / "earlier"
    d.mkdir()
    (d / "result.json").write_text(json.dumps({"status": "ok"}), encoding="utf-8")
    (d / "report.txt").write_text("earlier\n", encoding="utf-8")
    return d


#: case -> (--out maker, extra options)
CASES = {
    "negative_seed": (lambda t: t / "demo", ["--seed", "-1"]),
    "seed_beyond_numpy": (lambda t: t / "demo", ["--seed", str(2**32)]),
    "out_is_an_existing_file": (_a_file, []),
    "out_through_a_file": (lambda t: _a_file(t) / "demo", []),
    "out_not_empty_no_result": (lambda t: a_folder(t, "busy"), []),
    "out_holds_earlier_result_without_force": (_earlier, []),
    "force_negative_seed_into_earlier_result": (_earlier, ["--force", "--seed", "-1"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_option_or_output(case, tmp_path, capsys):
    make, extra = CASES[case]
    out = make(tmp_path)
    before = tree_snapshot(out)
    assert_user_error("demo", ["--out", out, *extra], capsys, outputs=[out])
    assert tree_snapshot(out) == before


def test_out_locked_by_live_run(tmp_path, capsys):
    out = tmp_path / "demo"
    lk = write_lock(out, os.getpid(), "demo")
    assert_user_error("demo", ["--out", out], capsys, outputs=[out], expect="being written by")
    assert lk.exists()
