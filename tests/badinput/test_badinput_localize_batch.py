"""``minegeo localize-batch --map M --scans DIR_OR_GLOB --out OUT``: every user mistake is one line,
exit 2, nothing written (no OUT, no manifest, no map cache), before any Dask worker starts; an
``OUT`` holding another batch stays byte-identical.

Option values (counts, the scheduler's address) and contradicting options are refused by their
argparse types and checks before any file is read; an ``OUT`` whose entries cannot take the
batch's outputs (a batch file that is a folder, a scan's folder name taken by a file) before any
scan runs; a scheduler that does not answer leaves ``OUT`` exactly as it was (the cluster is
reached before anything is written).

Bad *scan files* are not user mistakes for a batch: each gets a ``failed`` result folder and the
batch goes on (tests/localize/test_localize_batch.py). An ``OUT`` of another map, seed or
profile is one, shown here with a manifest as an earlier batch writes it (no cluster needed).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    dead_pid,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)
from helpers import require_extra

FAST = ["--profile", "fast"]


@pytest.fixture(scope="module")
def prep(mine, tmp_path_factory):
    from minegeo.cli import main

    out = tmp_path_factory.mktemp("prepared") / "map_fast.npz"
    assert main(["-q", "prepare-map", "--map", str(mine / "map.ply"), "--out", str(out), *FAST]) == 0
    return out


@pytest.fixture
def scans(mine, tmp_path):
    d = tmp_path / "scans"
    d.mkdir()
    for i in (0, 1):
        shutil.copy2(mine / "scans" / f"scan_{i:02d}.ply", d / f"scan_{i:02d}.ply")
    return d


OPTION_CASES = {
    "seed_negative": ["--seed", "-1"],
    "seed_float": ["--seed", "1.5"],
    "seed_nan": ["--seed", "nan"],
    "workers_0": ["--workers", "0"],
    "workers_negative": ["--workers", "-2"],
    "workers_float": ["--workers", "2.0"],
    "workers_inf": ["--workers", "inf"],
    "workers_huge": ["--workers", "1000000"],
    "workers_above_four_per_core": ["--workers", str(4 * (os.cpu_count() or 1) + 1)],
    "voxel_0": ["--voxel", "0"],
    "levelled_above_90": ["--levelled", "91"],
    "levelled_0": ["--levelled", "0"],
    "levelled_nan": ["--levelled", "nan"],
    "workers_not_a_number": ["--workers", "two"],
    "workers_with_scheduler": ["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"],
    "scheduler_colons": ["--scheduler", "::::"],
    "scheduler_empty": ["--scheduler", ""],
    "scheduler_no_port": ["--scheduler", "tcp://127.0.0.1"],
    "scheduler_port_0": ["--scheduler", "tcp://127.0.0.1:0"],
    "scheduler_port_too_big": ["--scheduler", "tcp://127.0.0.1:70000"],
    "scheduler_port_not_a_number": ["--scheduler", "tcp://127.0.0.1:http"],
    "scheduler_unknown_transport": ["--scheduler", "http://127.0.0.1:8786"],
    "scheduler_ipv6_unbracketed": ["--scheduler", "tcp://::1:8786"],
    "scheduler_ipv6_bad": ["--scheduler", "tcp://[::g]:8786"],
    "scheduler_bracket_unclosed": ["--scheduler", "tcp://[::1:8786"],
    "scheduler_host_with_space": ["--scheduler", "tcp://my host:8786"],
    "scheduler_host_slash": ["--scheduler", "tcp://host/x:8786"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, prep, scans, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST, *OPTION_CASES[case]],
                      capsys, inputs=[prep, scans], outputs=[out])


MAP_CASES = {
    "missing": lambda t, m, p: t / "nope.npz",
    "folder_named_npz": lambda t, m, p: a_folder(t, "folder.npz"),
    "prepared_empty": lambda t, m, p: write_file(t, "empty.npz", b""),
    "prepared_truncated": lambda t, m, p: truncated_copy(p, t / "half.npz"),
    "prepared_not_a_zip": lambda t, m, p: write_file(t, "text.npz", "0 0 0\n1 1 1\n"),
    "map_file_empty": lambda t, m, p: write_file(t, "empty.ply", b""),
    "map_file_three_points": lambda t, m, p: write_file(t, "three.xyz", "0 0 0\n10 0 0\n10 10 0\n"),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, mine, prep, scans, tmp_path, capsys):
    map_ = MAP_CASES[case](tmp_path, mine, prep)
    out = tmp_path / "out"
    assert_user_error("localize-batch", ["--map", map_, "--scans", scans, "--out", out, *FAST], capsys,
                      inputs=[map_, scans, tmp_path / "a_folder"], outputs=[out])


def test_prepared_map_with_other_parameters(prep, scans, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST, "--voxel", "0.7"],
                      capsys, inputs=[prep, scans], outputs=[out])


SCANS_CASES = {
    "missing_folder": lambda t: t / "no_such_folder",
    "empty_folder": lambda t: (t / "empty_dir").mkdir() or t / "empty_dir",
    "glob_matches_nothing": lambda t: t / "scans" / "*.las",
    "only_subfolders": lambda t: (t / "sub" / "inner").mkdir(parents=True) or t / "sub",
}


@pytest.mark.parametrize("case", sorted(SCANS_CASES))
def test_bad_scans(case, prep, scans, tmp_path, capsys):
    spec = SCANS_CASES[case](tmp_path)
    out = tmp_path / "out"
    assert_user_error("localize-batch", ["--map", prep, "--scans", spec, "--out", out, *FAST], capsys,
                      inputs=[prep, scans], outputs=[out])


def _manifest(out: Path, prep: Path, **change) -> Path:
    """``OUT`` as an earlier batch of ``prep`` (seed 0, fast) leaves it, with ``change`` applied."""
    from dataclasses import asdict

    from minegeo._provenance import input_record, to_jsonable
    from minegeo.cli.localize import params_from_args
    from minegeo.localize.batch import MANIFEST, manifest_record
    from minegeo.localize.prepared import PreparedMap

    class A:
        profile = "fast"

    _, lp = params_from_args(A())
    m = manifest_record(input_record(prep), PreparedMap.load(prep).params_hash, to_jsonable(asdict(lp)), 0, "fast")
    for k, v in change.items():
        if k == "sha256":
            m["map"]["sha256"] = v
        else:
            m[k] = v
    (out / "scan_00").mkdir(parents=True)
    (out / "scan_00" / "result.json").write_text('{"status": "ok"}', encoding="utf-8")
    (out / MANIFEST).write_text(json.dumps(m), encoding="utf-8")
    return out


OUT_CASES = {
    "another_map": (lambda o, p: _manifest(o, p, sha256="0" * 64), "another map"),
    "another_map_params": (lambda o, p: _manifest(o, p, map_params_hash="f" * 64), "another map"),
    "another_seed": (lambda o, p: _manifest(o, p, seed=5), "another seed"),
    "another_profile": (lambda o, p: _manifest(o, p, profile="table3"), "another profile"),
    "not_a_batch_folder": (lambda o, p: a_folder(o.parent, o.name), "holds no localize-batch results"),
    "manifest_garbage": (lambda o, p: (o.mkdir(), write_file(o, "batch_manifest.json", b"\xff\x00 not json"))
                         and o, "unreadable"),
    "an_existing_file": (lambda o, p: a_file(o.parent, o.name), "not a folder"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_out(case, prep, scans, tmp_path, capsys):
    make, expect = OUT_CASES[case]
    out = make(tmp_path / "out", prep)
    before = tree_snapshot(out, with_mtime=True)
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST], capsys,
                      inputs=[prep, scans], outputs=[out], expect=expect)
    assert tree_snapshot(out, with_mtime=True) == before


def test_out_is_the_map(prep, scans, capsys):
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", prep, *FAST], capsys,
                      inputs=[prep, scans], outputs=[prep])


def test_out_inside_the_scans_folder(prep, scans, capsys):
    out = scans / "results"
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST], capsys,
                      inputs=[prep], outputs=[out])


def test_out_is_a_scan(prep, scans, capsys):
    out = scans / "scan_00.ply"
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans / "*.ply", "--out", out, *FAST], capsys,
                      inputs=[prep, scans], outputs=[out])


def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then closed)."""
    import socket

    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return so.getsockname()[1]


@pytest.mark.parametrize("earlier", [False, True], ids=["new_out", "out_of_an_earlier_batch"])
def test_scheduler_not_answering_writes_nothing(earlier, prep, scans, tmp_path, capsys):
    """Issue 27 case 1: the cluster is reached before OUT is touched (no manifest, no map cache)."""
    require_extra("distributed")
    out = _manifest(tmp_path / "out", prep) if earlier else tmp_path / "out"
    before = tree_snapshot(out, with_mtime=True)
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST, "--scheduler",
                                         f"tcp://127.0.0.1:{_closed_port()}", "--scheduler-timeout-s", "2"], capsys,
                      inputs=[prep, scans], outputs=[out], expect="cannot connect to the Dask scheduler")
    assert tree_snapshot(out, with_mtime=True) == before


ENTRY_CASES = {
    # an earlier minegeo version put the folder of a scan named summary.csv.ply at OUT/summary.csv
    "summary_csv_is_a_folder": lambda o: (o / "summary.csv" / "result.json"),
    "report_html_is_a_folder": lambda o: (o / "report.html" / "x"),
    "map_cache_is_a_file": lambda o: o / ".map_cache",
    "scan_folder_is_a_file": lambda o: o / "scan_00",
}


@pytest.mark.parametrize("case", sorted(ENTRY_CASES))
def test_out_entry_that_cannot_take_an_output(case, prep, scans, tmp_path, capsys):
    """Issue 27 case 2, the class: OUT's entries are checked against the batch's own names and the
    scans' folder names before any work, not when the summary is written after every scan ran."""
    out = _manifest(tmp_path / "out", prep)
    p = ENTRY_CASES[case](out)
    p.parent.mkdir(parents=True, exist_ok=True)
    if p.exists() and p.is_dir():
        shutil.rmtree(p)
    p.write_text("{}", encoding="utf-8")
    before = tree_snapshot(out, with_mtime=True)
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST], capsys,
                      inputs=[prep, scans], outputs=[out], expect="move it away")
    assert tree_snapshot(out, with_mtime=True) == before


def test_out_locked_by_live_run(prep, scans, tmp_path, capsys):
    out = tmp_path / "out"
    lk = write_lock(out, os.getpid(), "localize-batch")
    assert_user_error("localize-batch", ["--map", prep, "--scans", scans, "--out", out, *FAST], capsys,
                      inputs=[prep, scans], outputs=[out], expect="being written by")
    assert lk.exists()
    lk.unlink()
    assert dead_pid() > 0
