"""``minegeo slam``, ``minegeo posegraph`` and ``minegeo evaluate`` reports open in the browser under the report contract
(no outside request, no console error, figures decoded, status banner first; see test_reports_browser.py)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data
from test_reports_browser import browser, check_report, shots  # noqa: F401 - fixtures

from minegeo.cli import main


@pytest.fixture(scope="module")
def slam_reports(browser, tmp_path_factory):  # noqa: F811 - the imported fixture
    from minegeo.geometry.se3 import exp_so3
    from minegeo.io import write_trajectory
    from minegeo.io.types import Trajectory

    root = tmp_path_factory.mktemp("slam_reports")
    g = shared_data("pose_graph_g2o", "smallGrid3D.g2o")
    assert main(["-q", "posegraph", str(g), "--out", str(root / "grid.g2o"), "--report", str(root / "pg")]) == 0
    assert main(["-q", "posegraph", str(g), "--out", str(root / "grid1.g2o"), "--report", str(root / "pg1"),
                 "--max-iterations", "1"]) == 1
    rng = np.random.default_rng(0)
    T, P = np.eye(4), []
    for _ in range(80):
        T = T @ np.block([[exp_so3(rng.normal(scale=0.05, size=3)), np.array([[0.5], [0.0], [0.0]])],
                          [np.zeros((1, 3)), np.ones((1, 1))]])
        P.append(T.copy())
    P = np.stack(P)
    E = P.copy()
    E[:, :3, 3] += rng.normal(scale=0.05, size=(80, 3))
    t = np.arange(80) * 0.1
    write_trajectory(root / "gt.tum", Trajectory(t, P))
    write_trajectory(root / "est.tum", Trajectory(t, E))
    assert main(["-q", "evaluate", "--est", str(root / "est.tum"), "--gt", str(root / "gt.tum"),
                 "--out", str(root / "ev")]) == 0
    # minegeo slam on 12 simulated VLP-16 frames
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    traj = make_trajectory(world, "drive", length_m=8.0, seed=5)
    fr = root / "frames"
    fr.mkdir()
    for k, T in enumerate(interpolate_poses(traj, np.arange(12) * 0.25)):
        write_point_cloud(fr / f"{k:04d}.ply", PointCloud(points=simulate_scan(world, Velodyne16(azimuth_step_deg=0.4),
                                                                               T, seed=k).points))
    (fr / "times.txt").write_text("".join(f"{0.25 * k:.2f}\n" for k in range(12)))
    assert main(["-q", "slam", "--frames", str(fr), "--out", str(root / "slam")]) == 0
    return {"slam": (root / "slam" / "report.html", "OK"),
            "posegraph_ok": (root / "pg" / "report.html", "OK"),
            "posegraph_stopped": (root / "pg1" / "report.html", "FAILED"),
            "evaluate": (root / "ev" / "report.html", "OK")}


@pytest.mark.parametrize("case", ["slam", "posegraph_ok", "posegraph_stopped", "evaluate"])
def test_slam_report_in_browser(case, slam_reports, browser, shots):  # noqa: F811
    path, expected = slam_reports[case]
    check_report(browser, path, expected, shots / f"{case}.png", min_images=1)
