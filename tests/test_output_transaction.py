"""Unit tests of :mod:`minegeo._output`: checked, locked, staged outputs committed as a whole."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from minegeo._output import OutputTransaction, RunClock, check_outputs, output_lock
from minegeo.errors import OutputError


def tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones included) with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_output_equal_to_input_refused_by_path_symlink_and_hardlink(tmp_path):
    src = tmp_path / "map.ply"
    src.write_bytes(b"ply data")
    (tmp_path / "link.ply").symlink_to(src)
    os.link(src, tmp_path / "hard.ply")
    for out in (src, tmp_path / "link.ply", tmp_path / "hard.ply", tmp_path / "sub" / ".." / "map.ply"):
        with pytest.raises(OutputError, match="is the input"):
            check_outputs({"FILE": src}, files={"--json": out})
    check_outputs({"FILE": src}, files={"--json": tmp_path / "other.json"})


def test_output_inside_input_folder_and_input_inside_output_folder_refused(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "a.ply").write_bytes(b"x")
    with pytest.raises(OutputError, match="inside the input folder"):
        check_outputs({"--frames": frames}, folders={"--out": frames / "out"})
    with pytest.raises(OutputError, match="lies inside --out"):
        check_outputs({"--scan": frames / "a.ply"}, folders={"--out": frames})
    with pytest.raises(OutputError, match="is the input"):
        check_outputs({"--frames": frames}, folders={"--out": frames})


def test_overlapping_outputs_refused_but_a_file_may_live_in_an_output_folder(tmp_path):
    with pytest.raises(OutputError, match="overlap"):
        check_outputs({}, folders={"--out": tmp_path / "o", "--report": tmp_path / "o" / "r"})
    with pytest.raises(OutputError, match="overlap"):
        check_outputs({}, files={"--a": tmp_path / "x", "--b": tmp_path / "x"})
    check_outputs({}, files={"--out": tmp_path / "o" / "map.ply"}, folders={"--report": tmp_path / "o"})


def test_folder_committed_whole_and_earlier_result_kept_on_error(tmp_path):
    out = tmp_path / "out"
    with OutputTransaction("t", folders={"--out": out}) as tx:
        (tx.folder("--out") / "result.json").write_text('{"run": 1}')
        (tx.folder("--out") / "extra.csv").write_text("1")
        assert not out.exists()  # nothing visible before the commit
    assert tree(out) == {"result.json": b'{"run": 1}', "extra.csv": b"1"}
    before = tree(tmp_path)
    with pytest.raises(RuntimeError), OutputTransaction("t", folders={"--out": out}) as tx:
        (tx.folder("--out") / "result.json").write_text('{"run": 2}')
        raise RuntimeError("crash mid-run")
    assert tree(tmp_path) == before  # earlier folder intact, no staging folder or lock left
    # a successful second run replaces the folder as a whole: the old extra file is gone
    with OutputTransaction("t", folders={"--out": out}) as tx:
        (tx.folder("--out") / "result.json").write_text('{"run": 3}')
    assert tree(out) == {"result.json": b'{"run": 3}'}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_foreign_non_empty_folder_is_not_replaced_without_force(tmp_path):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "my_notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="holds no earlier minegeo result"):
        with OutputTransaction("t", folders={"--out": out}):
            pass
    assert tree(out) == {"my_notes.txt": b"keep me"}
    with OutputTransaction("t", folders={"--out": out}, replace="any") as tx:
        (tx.folder("--out") / "result.json").write_text("{}")
    assert tree(out) == {"result.json": b"{}"}


def test_files_staged_under_their_names_and_moved_together(tmp_path):
    a, b = tmp_path / "map_geo.ply", tmp_path / "map_geo.ply.georef.json"
    with OutputTransaction("t", files={"--out": a, "sidecar": b}) as tx:
        assert tx.file("--out").name == a.name and tx.file("sidecar").parent == tx.file("--out").parent
        tx.file("--out").write_text("cloud")
        tx.file("sidecar").write_text("side")
        assert not a.exists() and not b.exists()
    assert a.read_text() == "cloud" and b.read_text() == "side"
    assert sorted(p.name for p in tmp_path.iterdir()) == [a.name, b.name]
    with pytest.raises(OutputError, match="exists; use --force"):
        with OutputTransaction("t", files={"--out": a}, overwrite_files=False):
            pass


def test_file_inside_output_folder_is_committed_with_it(tmp_path):
    rep = tmp_path / "o"
    with OutputTransaction("t", files={"--out": rep / "geo.ply"}, folders={"--report": rep}) as tx:
        tx.file("--out").write_text("cloud")
        (tx.folder("--report") / "result.json").write_text("{}")
    assert tree(rep) == {"geo.ply": b"cloud", "result.json": b"{}"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]


def test_second_writer_refused_while_first_holds_the_lock(tmp_path):
    out = tmp_path / "out"
    with OutputTransaction("first", folders={"--out": out}):
        with pytest.raises(OutputError, match=r"being written by minegeo first \(process"):
            with OutputTransaction("second", folders={"--out": out}):
                pass
    with OutputTransaction("third", folders={"--out": out}) as tx:  # lock released: fine again
        (tx.folder("--out") / "result.json").write_text("{}")


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path, caplog):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a pid that has just ended
    lock = tmp_path / ".out.minegeo-lock"
    lock.write_text(json.dumps({"pid": proc.pid, "host": socket.gethostname(), "verb": "x", "started_utc": "t"}))
    with OutputTransaction("t", folders={"--out": out}) as tx:
        (tx.folder("--out") / "result.json").write_text("{}")
    assert "no longer runs" in caplog.text
    assert not lock.exists() and (out / "result.json").exists()


def test_lock_of_another_host_is_respected(tmp_path):
    lock = tmp_path / ".out.minegeo-lock"
    lock.write_text(json.dumps({"pid": 1, "host": "another-host", "verb": "x", "started_utc": "t"}))
    with pytest.raises(OutputError, match="another-host"):
        with output_lock("demo", "--out", tmp_path / "out"):
            pass
    assert lock.exists()


def test_two_processes_one_wins(tmp_path):
    """Two real processes race for one output folder: exactly one commits, the other refuses."""
    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from minegeo._output import OutputTransaction\n"
        "from minegeo.errors import OutputError\n"
        "try:\n"
        "    with OutputTransaction('race', folders={'--out': Path(sys.argv[1])}) as tx:\n"
        "        time.sleep(1.5)\n"
        "        (tx.folder('--out') / 'result.json').write_text(sys.argv[2])\n"
        "except OutputError as e:\n"
        "    print(e); sys.exit(2)\n"
    )
    out = tmp_path / "out"
    procs = [subprocess.Popen([sys.executable, "-c", code, str(out), f'{{"who": {k}}}'],
                              stdout=subprocess.PIPE, text=True) for k in (1, 2)]
    codes = [p.wait(timeout=60) for p in procs]
    assert sorted(codes) == [0, 2], codes
    loser = procs[codes.index(2)].stdout.read()
    assert "being written by" in loser
    winner = codes.index(0) + 1
    assert json.loads((out / "result.json").read_text()) == {"who": winner}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_run_clock_counts_numba_compilation_apart():
    from numba import njit

    clock = RunClock()
    try:
        @njit(cache=False)
        def f(x):  # a fresh function: compiled now, inside the clock
            return x * 2.0 + 1.0

        t0 = time.perf_counter()
        assert f(1.0) == 3.0
        elapsed = time.perf_counter() - t0
        t = clock.timings()
    finally:
        clock.close()
    assert 0.0 < t["compile_s"] <= elapsed + 1e-6
    assert t["wall_s"] == pytest.approx(t["compile_s"] + t["work_s"])


def test_failed_run_removes_the_parent_folders_it_created(tmp_path):
    out = tmp_path / "new" / "deeper" / "out"
    with pytest.raises(RuntimeError), OutputTransaction("t", folders={"--out": out}) as tx:
        (tx.folder("--out") / "result.json").write_text("{}")
        raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
    with OutputTransaction("t", files={"--json": tmp_path / "a" / "b.json"}) as tx:
        tx.file("--json").write_text("{}")
    assert (tmp_path / "a" / "b.json").read_text() == "{}"


def test_closed_stdout_after_the_commit_is_not_a_traceback(tmp_path):
    """`minegeo adjust ... | head -1`: the reader closes the pipe; the result is committed, no traceback."""
    net = tmp_path / "n.dat"
    net.write_text("[Coordinates]\nP 1303.599 1458.615\nQ 1636.436 1310.468\nR 1503.395 888.362\n"
                   "S 1506.262 785.061\nU 1000.030 999.960\n[Datum]\nfix xP yP xQ yQ xR yR xS yS\n"
                   "[Angles]\nU P Q 33.8805555555556 0.00154320987654321\n"
                   "U Q R 42.7873456790123 0.00185185185185185\nU R S 11.6657407407407 0.00185185185185185\n",
                   encoding="utf-8")
    p = subprocess.run(f"{sys.executable} -m minegeo adjust {net} --out {tmp_path / 'o'} | true; "
                       "echo ${PIPESTATUS[0]}", shell=True, executable="/bin/bash", capture_output=True, text=True,
                       timeout=120)
    assert "Traceback" not in p.stderr, p.stderr
    assert p.stdout.strip() in ("0", "141"), p.stdout
    assert (tmp_path / "o" / "result.json").is_file()


def _interrupt_self():
    import signal

    os.kill(os.getpid(), signal.SIGINT)  # Python raises KeyboardInterrupt at the next bytecode of the main thread


def test_ctrl_c_during_the_commit_takes_effect_after_it(tmp_path, monkeypatch):
    """A Ctrl-C between the renames of a commit (two result folders and a file): every output is
    in place and then the KeyboardInterrupt is raised, no staging folder or lock left; never half
    a commit (issue 27)."""
    import minegeo._output as O

    a, b, f = tmp_path / "a", tmp_path / "b", tmp_path / "x.json"
    real_rename, calls = os.rename, []

    def rename(src, dst):
        real_rename(src, dst)
        calls.append(dst)
        if len(calls) == 1:
            _interrupt_self()

    monkeypatch.setattr(O.os, "rename", rename)
    with pytest.raises(KeyboardInterrupt):
        with OutputTransaction("t", folders={"--a": a, "--b": b}, files={"--json": f}) as tx:
            (tx.folder("--a") / "result.json").write_text("{}")
            (tx.folder("--b") / "result.json").write_text("{}")
            tx.file("--json").write_text("{}")
    assert len(calls) == 2
    assert tree(tmp_path) == {"a/result.json": b"{}", "b/result.json": b"{}", "x.json": b"{}"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "x.json"]


def test_ctrl_c_while_a_lock_is_taken_leaves_no_lock(tmp_path, monkeypatch):
    """A Ctrl-C right after the lock file is created (while its record is written): the run stops,
    and neither the lock nor a staging folder stays behind."""
    import json as _json

    import minegeo._output as O

    class J:
        loads = staticmethod(_json.loads)

        @staticmethod
        def dump(obj, fh):
            _interrupt_self()
            _json.dump(obj, fh)

    monkeypatch.setattr(O, "json", J)
    with pytest.raises(KeyboardInterrupt):
        with OutputTransaction("t", folders={"--out": tmp_path / "out"}):
            pass
    with pytest.raises(KeyboardInterrupt):
        with output_lock("t", "--out", tmp_path / "out"):
            pass
    assert list(tmp_path.iterdir()) == []


def test_sigint_deferred_nests_and_delivers_once():
    import signal

    from minegeo._output import sigint_deferred

    seen = []
    old = signal.signal(signal.SIGINT, lambda s, f: seen.append(s))
    try:
        with sigint_deferred():
            with sigint_deferred():
                _interrupt_self()
                _interrupt_self()
                time.sleep(0.01)
            assert seen == []  # held by both blocks
        assert seen == [signal.SIGINT]  # the handler in force before is called once, after the outer block
    finally:
        signal.signal(signal.SIGINT, old)
