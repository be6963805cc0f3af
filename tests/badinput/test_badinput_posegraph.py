"""``minegeo posegraph IN.g2o --out OUT.g2o``: every user mistake is one line, exit 2, nothing
written, an earlier result untouched (issue 27 cases 5, 6, 12 among them).

A graph that no edge leaves unconstrained is not a mistake even when it does not converge: that
is status ``max_iterations`` (exit 1) with the result written, tested in tests/slam.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    copy_tree,
    hardlink_beside,
    run_cli,
    symlink_beside,
    tree_snapshot,
    truncated_copy,
    write_file,
)

INFO = "10 0 0 10 0 100"
GOOD = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nVERTEX_SE2 2 2 0.1 0.2\nVERTEX_SE2 3 2 1 1.6\n"
        f"EDGE_SE2 0 1 1 0 0.1 {INFO}\nEDGE_SE2 1 2 1 0.1 0.1 {INFO}\nEDGE_SE2 2 3 1 0 1.4 {INFO}\n"
        f"EDGE_SE2 0 3 2 1 1.6 {INFO}\n")


@pytest.fixture
def good(tmp_path) -> Path:
    return write_file(tmp_path, "good.g2o", GOOD)


GRAPH_CASES = {
    "missing": (lambda t: t / "nope.g2o", None),
    "folder": (lambda t: a_folder(t), None),
    "empty": (lambda t: write_file(t, "empty.g2o", b""), "no VERTEX or EDGE"),
    "truncated": (lambda t: truncated_copy(write_file(t, "g.g2o", GOOD), t / "half.g2o"), "line"),
    "stream": (lambda t: Path("/dev/zero"), None),
    "non_utf8": (lambda t: write_file(t, "latin1.g2o", b"# Schacht S\xfcd\n" + GOOD.encode()), None),
    "unknown_record": (lambda t: write_file(t, "u.g2o", GOOD + "EDGE_XYZ 0 1\n"), "line 9: unknown record"),
    "nan_value": (lambda t: write_file(t, "n.g2o", GOOD.replace("VERTEX_SE2 1 1 0", "VERTEX_SE2 1 nan 0")), "NaN"),
    # case 5: vertex ids outside int64 / huge
    "vertex_id_1e20": (lambda t: write_file(t, "id.g2o", GOOD + "VERTEX_SE2 1e20 0 0 0\n"), "line 9: vertex id 1e20"),
    "vertex_id_minus_9_3e18": (lambda t: write_file(t, "id.g2o", GOOD + f"EDGE_SE2 3 -9.3e18 1 0 0 {INFO}\n"),
                               "line 9: vertex id -9.3e18"),
    "vertex_id_fraction": (lambda t: write_file(t, "id.g2o", GOOD + "FIX 0.5\n"), "line 9: vertex id 0.5"),
    # case 6: every vertex fixed
    "every_vertex_fixed": (lambda t: write_file(t, "fix.g2o", GOOD + "FIX 0\nFIX 1\nFIX 2\nFIX 3\n"),
                           "every vertex (4) is held fixed"),
    # case 12: zero information, self-loop
    "zero_information_vertex": (lambda t: write_file(t, "z.g2o", GOOD + "VERTEX_SE2 4 3 1 0\n"
                                                 "EDGE_SE2 3 4 1 0 0 0 0 0 0 0 0\n"), "id 4"),
    "zero_information_everywhere": (lambda t: write_file(t, "z.g2o", GOOD.replace(INFO, "0 0 0 0 0 0")), "id 1"),
    "heading_left_free": (lambda t: write_file(t, "h.g2o", GOOD + "VERTEX_SE2 4 3 1 0\n"
                                           "EDGE_SE2 3 4 1 0 0 1 0 0 1 0 0\n"), "vertex id 4"),
    "self_loop": (lambda t: write_file(t, "loop.g2o", GOOD + f"EDGE_SE2 2 2 0 0 0 {INFO}\n"),
                  "line 9: edge from vertex 2 to itself"),
    "disconnected": (lambda t: write_file(t, "d.g2o", GOOD + "VERTEX_SE2 10 0 0 0\nVERTEX_SE2 11 1 0 0\n"
                                      f"EDGE_SE2 10 11 1 0 0 {INFO}\n"), "id 10"),
}


@pytest.mark.parametrize("case", sorted(GRAPH_CASES))
def test_bad_graph(case, tmp_path, capsys):
    make, expect = GRAPH_CASES[case]
    graph = make(tmp_path)
    out = tmp_path / "res" / "out.g2o"
    assert_user_error("posegraph", [graph, "--out", out], capsys, inputs=[graph, tmp_path / "a_folder"],
                      outputs=[out], expect=expect)


def test_indefinite_information_refused_on_request(tmp_path, capsys):
    graph = write_file(tmp_path, "ind.g2o", GOOD + "EDGE_SE2 1 3 1 1 1.5 1 0 0 1 0 -5\n")
    out = tmp_path / "res" / "out.g2o"
    assert_user_error("posegraph", [graph, "--out", out, "--indefinite-information", "refuse"], capsys,
                      inputs=[graph], outputs=[out],
                      expect="line 9 (edge 1 -> 3): the information matrix is not positive semi-definite")


OPTION_CASES = {
    "max_iterations_0": ["--max-iterations", "0"],
    "max_iterations_negative": ["--max-iterations", "-5"],
    "max_iterations_not_a_number": ["--max-iterations", "ten"],
    "max_iterations_fraction": ["--max-iterations", "2.5"],
    "robust_scale_0": ["--robust-scale", "0"],
    "robust_scale_nan": ["--robust-scale", "nan"],
    "robust_scale_inf": ["--robust-scale", "inf"],
    "robust_unknown": ["--robust", "tukey"],
    "indefinite_unknown": ["--indefinite-information", "keep"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, good, tmp_path, capsys):
    out = tmp_path / "res" / "out.g2o"
    assert_user_error("posegraph", [good, "--out", out, *OPTION_CASES[case]], capsys, inputs=[good], outputs=[out])


OUT_CASES = {
    "out_is_the_graph": lambda g: ["--out", g],
    "out_symlink_to_graph": lambda g: ["--out", symlink_beside(g)],
    "out_hardlink_to_graph": lambda g: ["--out", hardlink_beside(g)],
    "out_is_a_folder": lambda g: ["--out", a_folder(g.parent, "busy")],
    "out_through_a_file": lambda g: ["--out", a_file(g.parent) / "sub.g2o"],
    "report_is_the_graph": lambda g: ["--out", g.parent / "o.g2o", "--report", g],
    "report_contains_the_graph": lambda g: ["--out", g.parent / "o.g2o", "--report", g.parent],
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, good, capsys):
    argv = OUT_CASES[case](good)
    outs = [argv[i + 1] for i, a in enumerate(argv) if a in ("--out", "--report")]
    assert_user_error("posegraph", [good, *argv], capsys, inputs=[good, good.parent], outputs=outs)


def test_failing_run_leaves_an_earlier_result(good, tmp_path, capsys):
    out = tmp_path / "res" / "out.g2o"
    code, _, err = run_cli("posegraph", [good, "--out", out], capsys)
    assert code == 0, err
    before = tree_snapshot(out.parent)
    snapshot = copy_tree(out.parent, tmp_path / "copy")
    bad = GRAPH_CASES["self_loop"][0](tmp_path)
    assert_user_error("posegraph", [bad, "--out", out], capsys, inputs=[bad], outputs=[out])
    assert tree_snapshot(out.parent) == before == tree_snapshot(snapshot)
