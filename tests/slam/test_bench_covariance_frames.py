"""The keyframe-edge error split of ``benchmarks/bench_covariance_frames.py`` and its paired summary.

``_edge_errors`` places the later keyframe from the true earlier one by the odometry's edge and splits
its error from the true pose along the true horizontal step, across it, vertically, and in yaw. The
edges here are built by hand from known errors (the expected values), on a path heading 30° and 120°
with a tilted sensor, so an axis taken in the sensor frame or a sign swapped shows.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("benchmarks/bench_covariance_frames.py", "bench_covariance_frames_test")


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_edge_errors_split_along_across_vertical_and_yaw(bench):
    heads = [30.0, 30.0, 120.0, 120.0]  # the true step's heading of each edge (deg)
    P = [np.zeros(3)]
    for h in heads:
        P.append(P[-1] + 2.0 * np.array([np.cos(np.radians(h)), np.sin(np.radians(h)), 0.1]))
    # the sensor yawed 10° off the step and pitched 3°: its axes are not the step's
    poses = np.array([_pose(_rot(2, h + 10.0) @ _rot(1, 3.0), p) for h, p in zip(heads + [120.0], P, strict=True)])
    errors = [(0.004, -0.002, 0.003, 0.05), (-0.004, 0.002, -0.003, -0.05), (0.004, 0.002, 0.003, 0.05),
              (-0.004, -0.002, -0.003, -0.05)]  # along, across (to the left), vertical (m), yaw (deg)
    edges = []
    for i, (a, c, v, y) in enumerate(errors):
        u = np.array([np.cos(np.radians(heads[i])), np.sin(np.radians(heads[i])), 0.0])
        n = np.array([-u[1], u[0], 0.0])
        B = poses[i + 1]
        B_est = _pose(_rot(2, y) @ B[:3, :3], B[:3, 3] + a * u + c * n + v * np.array([0.0, 0.0, 1.0]))
        edges.append(np.linalg.inv(poses[i]) @ B_est)
    odo = SimpleNamespace(keyframes=np.arange(5), keyframe_edges=np.array(edges))
    e = bench._edge_errors(odo, SimpleNamespace(poses=poses))
    assert e["edge_along_rms_m"] == pytest.approx(0.004, abs=1e-12)
    assert e["edge_across_rms_m"] == pytest.approx(0.002, abs=1e-12)
    assert e["edge_vertical_rms_m"] == pytest.approx(0.003, abs=1e-12)
    assert e["edge_yaw_rms_deg"] == pytest.approx(0.05, abs=1e-9)


def test_summary_pairs_the_seeds(bench):
    rows = []
    a = {1: 0.05, 2: 0.02, 3: 0.08}
    b = {1: 0.03, 2: 0.04, 3: 0.05}
    for v, x, order in ((9, a, (3, 1, 2)), (1, b, (1, 2, 3))):
        for seed in order:  # in another order for each value: the pairs are by seed
            rows.append({"seed": seed, "covariance_frames": v, "ate_rmse_m": x[seed], "ate_aligned_m": 0.0,
                         "odometry_ate_m": 0.0, "odometry_end_error_m": 0.0, "edge_along_rms_m": 0.0,
                         "edge_across_rms_m": 0.0, "edge_vertical_rms_m": 0.0, "edge_yaw_rms_deg": 0.0,
                         "plane_nodes": None})
    s = bench._summary(rows, [9, 1])[1]["ate_rmse_m"]
    d = np.array([b[k] - a[k] for k in (1, 2, 3)])  # -0.02, +0.02, -0.03
    assert s["paired_difference_mean"] == pytest.approx(d.mean())
    assert s["paired_difference_se"] == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    assert s["seeds_lower_than_first"] == 2
    assert s["median"] == pytest.approx(0.04)
