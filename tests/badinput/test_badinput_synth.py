"""``minegeo synth OUTDIR``: option and output mistakes are one line, exit 2, nothing written.

synth reads no input file; its mistakes are option values and output folders. A successful run
here uses ``--mast-only`` (a MAST scenario, well under a second).
"""

from __future__ import annotations

import json
import os

import pytest
from _contract import (
    a_folder,
    assert_user_error,
    copy_tree,
    dead_pid,
    leftovers,
    lock_path,
    run_cli,
    tree_snapshot,
    write_lock,
)

OPTION_CASES = {
    "negative_seed": ["--seed", "-1"],
    "too_few_gcps": ["--gcps", "2"],
    "negative_gcps": ["--gcps", "-3"],
    "unknown_epsg": ["--crs", "EPSG:999999"],
    "crs_not_a_code": ["--crs", "not-a-crs"],
    "geographic_crs": ["--crs", "EPSG:4326"],
    "non_numeric_seed": ["--seed", "seven"],
    "seed_beyond_numpy": ["--seed", str(2**32)],
    "gcps_huge": ["--gcps", "1000000000"],
    "roughness_nan": ["--roughness-m", "nan"],
    "roughness_0": ["--roughness-m", "0"],
    "unmapped_negative": ["--unmapped", "-1"],
    "mast_only_with_twins": ["--mast-only", "--twins", "exact"],
    "mast_only_with_roughness": ["--mast-only", "--roughness-m", "0.1"],
    "mast_only_with_mast": ["--mast-only", "--mast"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, tmp_path, capsys):
    out = tmp_path / "mine"
    assert_user_error("synth", [out, *OPTION_CASES[case]], capsys, outputs=[out])


def test_outdir_is_an_existing_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("keep", encoding="utf-8")
    assert_user_error("synth", [f, "--mast-only"], capsys, outputs=[f])


def test_outdir_through_a_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("keep", encoding="utf-8")
    assert_user_error("synth", [f / "sub", "--mast-only"], capsys, outputs=[f / "sub"])


def test_outdir_not_empty_and_no_result(tmp_path, capsys):
    d = a_folder(tmp_path, "busy")
    assert_user_error("synth", [d, "--mast-only"], capsys, outputs=[d], expect="not empty")


def test_outdir_locked_by_live_run(tmp_path, capsys):
    out = tmp_path / "mine"
    lk = write_lock(out, os.getpid(), "synth")
    assert_user_error("synth", [out, "--mast-only"], capsys, outputs=[out], expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(tmp_path, capsys):
    out = tmp_path / "mine"
    write_lock(out, dead_pid(), "synth")
    code, _, err = run_cli("synth", [out, "--mast-only", "--seed", "3"], capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert (out / "scan.csv").is_file() and (out / "beacons.csv").is_file()
    assert leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def earlier(tmp_path_factory):
    """An earlier successful synth result (``--mast-only``) and an earlier result folder of another verb."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier")
    assert main(["synth", str(d / "synth"), "--mast-only", "--seed", "2"]) == 0
    (d / "result").mkdir()
    (d / "result" / "result.json").write_text(json.dumps({"status": "ok"}), encoding="utf-8")
    (d / "result" / "report.txt").write_text("earlier\n", encoding="utf-8")
    return d


@pytest.mark.parametrize("argv", [["--force", "--seed", "-1"], ["--force", "--gcps", "2"],
                                  ["--force", "--crs", "EPSG:999999"], ["--mast-only"]],
                         ids=["force_negative_seed", "force_too_few_gcps", "force_unknown_epsg", "no_force"])
@pytest.mark.parametrize("which", ["synth", "result"])
def test_failing_run_leaves_earlier_folder(which, argv, earlier, tmp_path, capsys):
    out = copy_tree(earlier / which, tmp_path / "out")
    before = tree_snapshot(out)
    assert_user_error("synth", [out, *argv], capsys, outputs=[out])
    assert tree_snapshot(out) == before
