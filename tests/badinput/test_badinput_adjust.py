"""``minegeo adjust NETWORK --out DIR``: every user mistake is one line, exit 2, nothing written,
an earlier result folder untouched; two runs never write one folder.

Non-UTF-8 bytes are a mistake only in a JSON network: the Krumm text reader deliberately falls
back to Latin-1 (German example files), so a Latin-1 text network is valid input.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
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

RESULT_FILES = {"result.json", "report.txt", "report.html"}

GHILANI_JSON = {
    "name": "Ghilani Ex. 15.5",
    "points": {"P": {"x": 1303.599, "y": 1458.615}, "Q": {"x": 1636.436, "y": 1310.468},
               "R": {"x": 1503.395, "y": 888.362}, "S": {"x": 1506.262, "y": 785.061},
               "U": {"x": 1000.030, "y": 999.960}},
    "datum": {"type": "fix", "coordinates": ["P", "Q", "R", "S"]},
    "observations": [
        {"type": "angle", "at": "U", "from": "P", "to": "Q", "value_gon": 33.8805555555556,
         "sigma_gon": 0.00154320987654321},
        {"type": "angle", "at": "U", "from": "Q", "to": "R", "value_gon": 42.7873456790123,
         "sigma_gon": 0.00185185185185185},
        {"type": "angle", "at": "U", "from": "R", "to": "S", "value_gon": 11.6657407407407,
         "sigma_gon": 0.00185185185185185},
    ],
}


def _edit(net: Path, tmp: Path, old: str, new: str, name: str = "net.dat") -> Path:
    text = net.read_text(encoding="utf-8")
    assert old in text
    return write_file(tmp, name, text.replace(old, new))


def _json_variant(tmp: Path, text_edit=None, obj_edit=None) -> Path:
    d = json.loads(json.dumps(GHILANI_JSON))
    if obj_edit:
        obj_edit(d)
    text = json.dumps(d)
    if text_edit:
        text = text_edit(text)
    return write_file(tmp, "net.json", text)


ANGLE1 = "U P Q 33.8805555555556 0.00154320987654321"

NETWORK_CASES = {
    "missing": lambda t, n: t / "nope.dat",
    "folder": lambda t, n: a_folder(t),
    "empty": lambda t, n: write_file(t, "empty.dat", b""),
    "truncated": lambda t, n: truncated_copy(n, t / "half.dat"),
    "nan_observation": lambda t, n: _edit(n, t, ANGLE1, "U P Q nan 0.00154320987654321"),
    "inf_observation": lambda t, n: _edit(n, t, ANGLE1, "U P Q inf 0.00154320987654321"),
    "nan_sigma": lambda t, n: _edit(n, t, ANGLE1, "U P Q 33.8805555555556 nan"),
    "inf_coordinate": lambda t, n: _edit(n, t, "S 1506.262 785.061", "S 1506.262 inf"),
    "too_few_columns": lambda t, n: _edit(n, t, ANGLE1, "U P 33.8805555555556"),
    "too_many_columns": lambda t, n: _edit(n, t, ANGLE1, ANGLE1 + " 7 8 9"),
    "garbage_bytes": lambda t, n: write_file(t, "garbage.dat", b"\x00\x01\x02 not a network\n"),
    "stream": lambda t, n: Path("/dev/zero"),
    "unknown_point": lambda t, n: _edit(n, t, ANGLE1, "U P X 33.8805555555556 0.00154320987654321"),
    "too_few_observations": lambda t, n: write_file(t, "one_angle.dat", n.read_text(encoding="utf-8").split("\nU Q R")[0] + "\n"),
    "collinear_bearings": lambda t, n: write_file(
        t, "collinear.dat", "[Coordinates]\nA 0 0\nB 100 100\nU 200 200\n[Datum]\nfix A B\n[GridBearings,dms,s]\n"
        "A U 45°00'00\" 1\nB U 45°00'00\" 1\n"),
    "json_truncated": lambda t, n: write_file(t, "net.json", json.dumps(GHILANI_JSON)[: len(json.dumps(GHILANI_JSON)) // 2]),
    "json_nan": lambda t, n: _json_variant(t, text_edit=lambda s: s.replace("33.8805555555556", "NaN")),
    "json_inf": lambda t, n: _json_variant(t, text_edit=lambda s: s.replace("33.8805555555556", "1e999")),
    "json_wrong_type": lambda t, n: _json_variant(t, obj_edit=lambda d: d["observations"][0].update(value_gon="abc")),
    "json_not_an_object": lambda t, n: write_file(t, "net.json", "[1, 2, 3]"),
    "json_non_utf8": lambda t, n: write_file(t, "net.json", json.dumps(GHILANI_JSON).encode().replace(b'"U"', b'"\xdc"')),
}


@pytest.mark.parametrize("case", sorted(NETWORK_CASES))
def test_bad_network(case, network, tmp_path, capsys):
    net = NETWORK_CASES[case](tmp_path, network)
    out = tmp_path / "out"
    assert_user_error("adjust", [net, "--out", out], capsys, inputs=[net, tmp_path / "a_folder"], outputs=[out])


OPTION_CASES = {
    "confidence_0": ["--confidence", "0"],
    "confidence_1": ["--confidence", "1"],
    "confidence_above_1": ["--confidence", "1.5"],
    "confidence_negative": ["--confidence", "-0.5"],
    "confidence_nan": ["--confidence", "nan"],
    "alpha_0": ["--alpha", "0"],
    "alpha_above_1": ["--alpha", "2"],
    "alpha_w_negative": ["--alpha-w", "-0.1"],
    "alpha_tau_nan": ["--alpha-tau", "nan"],
    "max_iterations_0": ["--max-iterations", "0"],
    "max_iterations_negative": ["--max-iterations", "-5"],
    "max_iterations_huge": ["--max-iterations", "1000000000000"],
    "confidence_inf": ["--confidence", "inf"],
    "alpha_w_1": ["--alpha-w", "1"],
    "alpha_tau_text": ["--alpha-tau", "five percent"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, network, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("adjust", [network, "--out", out, *OPTION_CASES[case]], capsys, inputs=[network],
                      outputs=[out])


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def net_in_folder(network, tmp_path):
    """The network in a folder that also holds an earlier minegeo result (result.json)."""
    d = tmp_path / "work"
    d.mkdir()
    p = d / "net.dat"
    p.write_bytes(network.read_bytes())
    (d / "result.json").write_text('{"status": "ok"}', encoding="utf-8")
    return p


OUT_CASES = {
    "out_is_the_input": lambda p: p,
    "out_symlink_to_input": symlink_beside,
    "out_hardlink_to_input": hardlink_beside,
    "out_contains_the_input": lambda p: p.parent,
    "out_is_an_existing_file": lambda p: a_file(p.parent.parent),
    "out_through_a_file": lambda p: a_file(p.parent.parent) / "sub",
    "out_not_empty_no_result": lambda p: a_folder(p.parent.parent, "busy"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, net_in_folder, capsys):
    out = OUT_CASES[case](net_in_folder)
    assert_user_error("adjust", [net_in_folder, "--out", out], capsys, inputs=[net_in_folder, net_in_folder.parent],
                      outputs=[out])


def test_failing_run_creates_no_parent_folder(network, tmp_path, capsys):
    net = NETWORK_CASES["too_few_observations"](tmp_path, network)
    out = tmp_path / "new" / "sub" / "out"
    assert_user_error("adjust", [net, "--out", out], capsys, inputs=[net], outputs=[out])


def test_out_locked_by_live_run(network, tmp_path, capsys):
    out = tmp_path / "out"
    lk = write_lock(out, os.getpid(), "adjust")
    assert_user_error("adjust", [network, "--out", out], capsys, inputs=[network], outputs=[out],
                      expect="being written by")
    assert lk.exists()


def test_stale_lock_is_taken_over(network, tmp_path, capsys):
    out = tmp_path / "out"
    write_lock(out, dead_pid(), "adjust")
    code, _, err = run_cli("adjust", [network, "--out", out], capsys)
    assert code == 0, err
    assert any("taking over the lock" in ln for ln in err), err
    assert not lock_path(out).exists()
    assert {p.name for p in out.iterdir()} == RESULT_FILES
    assert leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def earlier(network, tmp_path_factory):
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "out"
    assert main(["adjust", str(network), "--out", str(d)]) == 0
    return d


FAILING_RUNS = {
    "too_few_observations": lambda t, n: [NETWORK_CASES["too_few_observations"](t, n)],
    "nan_observation": lambda t, n: [NETWORK_CASES["nan_observation"](t, n)],
    "truncated_json": lambda t, n: [NETWORK_CASES["json_truncated"](t, n)],
    "missing_network": lambda t, n: [t / "nope.dat"],
    "bad_confidence": lambda t, n: [n, "--confidence", "2"],
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, network, tmp_path, capsys):
    out = copy_tree(earlier, tmp_path / "out")
    before = tree_snapshot(out)
    argv = FAILING_RUNS[case](tmp_path, network)
    assert_user_error("adjust", [argv[0], "--out", out, *argv[1:]], capsys, inputs=[argv[0]], outputs=[out])
    assert tree_snapshot(out) == before


# ------------------------------------------------------------------------------------ concurrency

_SLOW_COMMIT = textwrap.dedent("""
    import sys, time
    import minegeo._output as o
    _commit = o.OutputTransaction._commit
    def slow_commit(self):
        time.sleep(float(sys.argv[1]))  # hold the lock long enough for the other run to meet it
        _commit(self)
    o.OutputTransaction._commit = slow_commit
    from minegeo.cli import main
    sys.exit(main(sys.argv[2:]))
""")


def test_two_concurrent_runs_one_output(network, tmp_path):
    """Two processes started at once on one --out: one writes the result, the other refuses (exit 2,
    one line naming the lock) and the folder holds exactly one complete result."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONWARNINGS": "ignore::DeprecationWarning"}
    cmd = [sys.executable, "-c", _SLOW_COMMIT, "4", "adjust", str(network), "--out", str(out)]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                              cwd=tmp_path) for _ in range(2)]
    res = [p.communicate(timeout=180) + (p.returncode,) for p in procs]
    codes = sorted(r[2] for r in res)
    assert codes == [0, 2], res
    loser = next(r for r in res if r[2] == 2)
    lines = [ln for ln in loser[1].splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("minegeo adjust: error:"), lines
    assert "being written by" in lines[0], lines
    assert {p.name for p in out.iterdir()} == RESULT_FILES
    d = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert f"{d['points']['U']['x']:.3f}" == "999.999"
    assert leftovers(tmp_path) == []


def test_lock_held_by_another_process(network, tmp_path):
    """A live minegeo process holding the lock (not this one): a CLI run refuses and names it; once
    released, the same command succeeds."""
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys\nfrom minegeo._output import output_lock\n"
         f"with output_lock('adjust', '--out', {str(out)!r}):\n    print('held', flush=True)\n    sys.stdin.read()\n"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        r = subprocess.run([sys.executable, "-m", "minegeo", "adjust", str(network), "--out", str(out)],
                           capture_output=True, text=True, timeout=120)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2, r
        assert len(lines) == 1 and lines[0].startswith("minegeo adjust: error:"), lines
        assert f"process {holder.pid}" in lines[0], lines
        assert not out.exists()
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    r = subprocess.run([sys.executable, "-m", "minegeo", "adjust", str(network), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert {p.name for p in out.iterdir()} == RESULT_FILES
    assert leftovers(tmp_path) == []
