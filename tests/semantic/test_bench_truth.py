"""The intersection benchmark's true junctions include the crossings the geometry makes.

``benchmarks/bench_intersections.truth_junctions``: two drifts that share no node but overlap form a junction
in the map. Expected points from a hand calculation: two strips of half-width r crossing at angle theta
(acute bisector along +x, crossing at O) have their medial-axis branch points on the acute bisector where the
clearance to the outer walls, ``r + s sin(theta/2)``, equals the distance to the reflex corner of the inner
walls at ``r / sin(theta/2)``: ``s = r (1 - sin(theta/2)) / (sin(theta/2) (1 + sin(theta/2)))``, one on
each side of O; a right-angle crossing has one, at O (clearance r sqrt(2) to the four corners).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import load_script

from minegeo.synth.network import DriftNetwork


@pytest.fixture(scope="module")
def bench():
    return load_script("benchmarks/bench_intersections.py", "bench_intersections_truth")


def _cross(theta_deg: float, width: float = 2.9, half_len: float = 25.0) -> DriftNetwork:
    """Two straight drifts through (0, 0) at +-theta/2 from +x, sharing no node (4 dead ends)."""
    a = np.deg2rad(0.5 * theta_deg)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([np.cos(a), -np.sin(a)])
    nodes = np.array([-half_len * u, half_len * u, -half_len * v, half_len * v])
    return DriftNetwork(nodes, np.array([[0, 1], [2, 3]]), np.full(2, width), np.full(4, 3.0), ("",) * 4,
                        {"kind": "test"})


def test_shallow_crossing_gives_the_two_branch_points(bench):
    theta, r = 30.0, 1.45
    J, names = bench.truth_junctions(_cross(theta, 2 * r), step_m=0.1)
    sn = np.sin(np.deg2rad(0.5 * theta))
    s = r * (1 - sn) / (sn * (1 + sn))
    assert names == ["x0-1a", "x0-1b"]
    got = J[np.argsort(J[:, 0])]
    np.testing.assert_allclose(got, [[-s, 0.0], [s, 0.0]], atol=0.05)


def test_right_angle_crossing_gives_its_centre_and_apart_drifts_none(bench):
    J, names = bench.truth_junctions(_cross(90.0), step_m=0.1)
    assert names == ["x0-1"]
    np.testing.assert_allclose(J, [[0.0, 0.0]], atol=0.05)
    # a dead end 3.5 m from the other drift's centreline (more than the 2.9 m width): no junction
    net = _cross(90.0)
    apart = DriftNetwork(np.array([[-30.0, 0.0], [30.0, 0.0], [0.0, 3.5], [0.0, 33.5]]), net.edges, net.widths,
                         np.full(4, 3.0), ("",) * 4, {"kind": "test"})
    assert len(bench.truth_junctions(apart, step_m=0.1)[0]) == 0
