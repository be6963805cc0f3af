"""``minegeo info FILE`` tells what a file holds from its content (issue 28 point 5): control
points, trajectories (TUM, KITTI, CSV), g2o pose graphs, prepared maps and result records are
shown as such without ``--kind``, whatever their suffix; a point cloud with eight columns stays a
point cloud; ``--kind`` still forces the kind. Expected counts are the numbers of records written
by the test itself (or counted in the file's text), never the reader's output."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import shared_data

from minegeo.cli import main
from minegeo.geometry.se3 import exp_se3
from minegeo.io._quat import matrix_to_quat


def _info(path, capsys, *extra):
    code = main(["info", str(path), *extra])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _kind_line(out: str) -> str:
    first = out.splitlines()[0]
    assert first.startswith("kind "), first
    return first


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([exp_se3(np.concatenate([rng.normal(0, 0.5, 3), rng.normal(0, 5.0, 3)])) for _ in range(n)])


@pytest.fixture()
def gcps_csv(tmp_path):
    """A control-point file as a surveyor types it (header, no sigma columns, a CRS line)."""
    p = tmp_path / "gcps.csv"
    p.write_text("# crs: EPSG:5186\nid,x,y,z,E,N,H\nG1,0,0,0,200000,550000,100\nG2,10,0,0,200010,550000,100\n"
                 "G3,0,10,0,200000,550010,101\nG4,10,10,1,200010,550010,102\n", encoding="utf-8")
    return p


def test_gcps_csv_is_shown_as_control_points(gcps_csv, capsys):
    code, out, err = _info(gcps_csv, capsys)
    assert code == 0, err
    assert "control points" in _kind_line(out) and "detected" in _kind_line(out)
    assert "points         4" in out and "EPSG:5186" in out
    # --kind still forces: as a point cloud, its header line is not numbers (one error line, exit 2)
    code, out, err = _info(gcps_csv, capsys, "--kind", "cloud")
    assert code == 2 and err.startswith("minegeo info: error:") and err.count("\n") == 1


@pytest.mark.parametrize("fmt", ["tum", "kitti", "csv"])
def test_trajectory_files_are_shown_as_trajectories(fmt, tmp_path, capsys):
    T = _poses(7, seed=3)
    t = 100.0 + 0.5 * np.arange(7)
    rows = []
    for k in range(7):
        q = matrix_to_quat(T[k, :3, :3], order="xyzw")
        if fmt == "kitti":
            rows.append(" ".join(f"{v:.12g}" for v in T[k, :3, :].ravel()))
        elif fmt == "tum":
            rows.append(" ".join(f"{v:.12g}" for v in [t[k], *T[k, :3, 3], *q]))
        else:
            rows.append(",".join(f"{v:.12g}" for v in [t[k], *T[k, :3, 3], *q]))
    head = "time_s,x,y,z,qx,qy,qz,qw\n" if fmt == "csv" else ""
    p = tmp_path / "poses.txt"  # the suffix says nothing
    p.write_text(head + "\n".join(rows) + "\n", encoding="utf-8")
    code, out, err = _info(p, capsys)
    assert code == 0, err
    assert "trajectory" in _kind_line(out) and "point cloud" not in _kind_line(out)
    assert "poses          7" in out
    if fmt != "kitti":
        assert "duration_s     3.0" in out
    # --kind forces: the same numbers read as a point cloud of 7 points
    code, out, err = _info(p, capsys, "--kind", "cloud")
    if fmt != "csv":
        assert code == 0 and "point cloud (--kind)" in _kind_line(out) and "points    7" in out


def test_eight_column_point_cloud_stays_a_point_cloud(tmp_path, capsys):
    """x y z r g b intensity label: 8 numbers a line but no unit quaternion, so not TUM."""
    rng = np.random.default_rng(1)
    A = np.column_stack([rng.uniform(0, 50, (30, 3)), rng.integers(0, 255, (30, 3)), rng.uniform(0, 1, 30),
                         rng.integers(0, 5, 30)])
    p = tmp_path / "cloud.txt"
    np.savetxt(p, A, fmt="%.6f")
    code, out, err = _info(p, capsys)
    assert code == 0, err
    assert "point cloud" in _kind_line(out) and "points    30" in out


def test_g2o_file_is_shown_as_a_pose_graph(tmp_path, capsys):
    src = shared_data("pose_graph_g2o", "smallGrid3D.g2o")
    text = src.read_text(encoding="utf-8")
    p = tmp_path / "graph.txt"
    p.write_text(text, encoding="utf-8")
    code, out, err = _info(p, capsys)
    assert code == 0, err
    assert "pose graph (g2o)" in _kind_line(out)
    lines = [ln.split()[0] for ln in text.splitlines() if ln.strip()]
    assert f"vertices       {sum(w.startswith('VERTEX') for w in lines)}" in out
    assert f"edges          {sum(w.startswith('EDGE') for w in lines)}" in out


def test_prepared_map_and_result_record(tmp_path, capsys):
    from minegeo.io.types import PointCloud
    from minegeo.localize import PrepareParams, prepare_map

    rng = np.random.default_rng(2)
    # two walls and a floor of a 30 m drift: enough structure for normals and FPFH
    n = 6000
    x = rng.uniform(0, 30, n)
    side = rng.integers(0, 3, n)
    pts = np.column_stack([x, np.where(side == 0, -2.0, np.where(side == 1, 2.0, rng.uniform(-2, 2, n))),
                           np.where(side == 2, 0.0, rng.uniform(0, 3, n))])
    pm = prepare_map(PointCloud(points=pts), PrepareParams.fast())
    p = tmp_path / "map.bin"  # an .npz under another name
    pm.save(p)
    code, out, err = _info(p, capsys)
    assert code == 0, err
    assert "prepared map" in _kind_line(out) and "profile        fast" in out
    assert f"points         {len(pm)}" in out
    r = tmp_path / "r.json"
    r.write_text(json.dumps({"status": "failed", "reason": "no placement fits", "T_map_scan": None,
                             "versions": {"minegeo": "x"}}), encoding="utf-8")
    code, out, err = _info(r, capsys)
    assert code == 0, err
    assert "result record" in _kind_line(out) and "status         failed" in out
    # a JSON file that is no minegeo record: one line, exit 2
    (tmp_path / "other.json").write_text('{"a": 1}', encoding="utf-8")
    code, out, err = _info(tmp_path / "other.json", capsys)
    assert code == 2 and "not a minegeo result record" in err
