"""``minegeo posegraph`` and ``minegeo evaluate`` through the CLI: outputs, costs, exit codes, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import shared_data

from minegeo.cli import main
from minegeo.io.g2o import read_g2o
from minegeo.slam.posegraph import optimize_pose_graph, pose_graph_cost


def test_posegraph_writes_the_optimised_graph_and_its_costs(tmp_path):
    src = shared_data("pose_graph_g2o", "smallGrid3D.g2o")
    assert main(["-q", "posegraph", str(src), "--out", str(tmp_path / "o.g2o")]) == 0
    out = read_g2o(tmp_path / "o.g2o")
    ref = optimize_pose_graph(read_g2o(src))
    assert np.array_equal(out.edge_values, read_g2o(src).edge_values)  # edges as read
    assert pose_graph_cost(out) == pytest.approx(ref.cost_final, rel=1e-9)
    rec = json.loads((tmp_path / "o.g2o.report" / "result.json").read_text())
    assert rec["status"] == "converged" and rec["result"]["cost_final"] == ref.cost_final
    assert rec["result"]["cost_initial"] == ref.cost_initial and rec["result"]["iterations"] == ref.iterations
    assert rec["provenance"]["inputs"][0]["sha256"] and (tmp_path / "o.g2o.report" / "report.html").is_file()


def test_posegraph_stopped_by_the_iteration_limit_exits_1(tmp_path):
    src = shared_data("pose_graph_g2o", "smallGrid3D.g2o")
    assert main(["-q", "posegraph", str(src), "--out", str(tmp_path / "o.g2o"), "--max-iterations", "1"]) == 1
    assert json.loads((tmp_path / "o.g2o.report" / "result.json").read_text())["status"] == "max_iterations"


def test_posegraph_bad_file_is_one_clear_line(tmp_path, capsys):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_XYZ 1 0 0 0\n")
    assert main(["posegraph", str(bad), "--out", str(tmp_path / "o.g2o")]) == 2
    err = capsys.readouterr().err
    assert "line 2: unknown record 'VERTEX_XYZ'" in err and "Traceback" not in err
    assert not (tmp_path / "o.g2o").exists()


def test_posegraph_refuses_to_overwrite_its_input(tmp_path, capsys):
    src = tmp_path / "g.g2o"
    src.write_bytes(shared_data("pose_graph_g2o", "tinyGrid3D.g2o").read_bytes())
    before = src.read_bytes()
    assert main(["posegraph", str(src), "--out", str(src)]) == 2
    assert src.read_bytes() == before


def test_evaluate_cli(tmp_path):
    from minegeo.io import write_trajectory
    from minegeo.io.types import Trajectory

    rng = np.random.default_rng(3)
    P = np.tile(np.eye(4), (50, 1, 1))
    P[:, 0, 3] = np.arange(50) * 0.5
    E = P.copy()
    E[:, 1, 3] += 0.1  # a constant 10 cm offset: removed by the alignment, seen without it
    E[:, 2, 3] += rng.normal(scale=1e-3, size=50)
    t = np.arange(50) * 0.1
    write_trajectory(tmp_path / "gt.tum", Trajectory(t, P))
    write_trajectory(tmp_path / "est.tum", Trajectory(t, E))
    assert main(["-q", "evaluate", "--est", str(tmp_path / "est.tum"), "--gt", str(tmp_path / "gt.tum"),
                 "--out", str(tmp_path / "a")]) == 0
    assert main(["-q", "evaluate", "--est", str(tmp_path / "est.tum"), "--gt", str(tmp_path / "gt.tum"),
                 "--out", str(tmp_path / "b"), "--no-align"]) == 0
    a = json.loads((tmp_path / "a" / "result.json").read_text())["result"]
    b = json.loads((tmp_path / "b" / "result.json").read_text())["result"]
    assert a["ate"]["rmse"] < 3e-3 and b["ate"]["rmse"] == pytest.approx(0.1, abs=3e-3)
