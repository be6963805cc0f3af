"""Map-registration factor (minegeo.semantic.mapfactor): no information along a direction the registration
leaves free (the axis of a straight drift), full information at a dead end, and in the factor graph the
free direction stays the odometry's. Expected values by hand (module docstring's formula with σ_rms = 0:
``Ω = D P D / σ_floor²``, ``P`` the projector on the constrained directions)."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.geometry.se3 import exp_so3
from minegeo.semantic.factors import FactorGraph
from minegeo.semantic.mapfactor import map_registration_information

SIGMA_F = 0.2


def _tunnel(dead_end: bool, step: float = 0.25):
    """Points (keyframe frame, sensor at the origin 1.3 m above the floor) and unit normals of a 2.9 m x
    2.6 m box drift along x from -10 to 10 m; ``dead_end`` closes it by a face at x = 8 m."""
    x = np.arange(-10.0, 10.0 + 1e-9, step)
    y = np.arange(-1.45, 1.45 + 1e-9, step)
    z = np.arange(-1.3, 1.3 + 1e-9, step)
    P, N = [], []
    for yy, n in ((-1.45, (0, 1, 0)), (1.45, (0, -1, 0))):            # walls
        X, Z = np.meshgrid(x, z)
        P.append(np.c_[X.ravel(), np.full(X.size, yy), Z.ravel()])
        N.append(np.tile(n, (X.size, 1)))
    for zz, n in ((-1.3, (0, 0, 1)), (1.3, (0, 0, -1))):               # floor, roof
        X, Y = np.meshgrid(x, y)
        P.append(np.c_[X.ravel(), Y.ravel(), np.full(X.size, zz)])
        N.append(np.tile(n, (X.size, 1)))
    P, N = np.concatenate(P).astype(float), np.concatenate(N).astype(float)
    if dead_end:
        keep = P[:, 0] <= 8.0
        P, N = P[keep], N[keep]
        Y, Z = np.meshgrid(y, z)
        P = np.r_[P, np.c_[np.full(Y.size, 8.0), Y.ravel(), Z.ravel()]]
        N = np.r_[N, np.tile((-1.0, 0.0, 0.0), (Y.size, 1))]
    return P, N


def _rotated(P, N, R):
    return P @ R.T, N @ R.T


@pytest.mark.parametrize("yaw_deg", [0.0, 37.0])
def test_straight_drift_gives_no_information_along_its_axis(yaw_deg):
    R = exp_so3(np.array([0.0, 0.0, np.radians(yaw_deg)]))
    P, N = _rotated(*_tunnel(False), R)
    W, info = map_registration_information(P, N, 0.0, SIGMA_F, 0.02)
    axis = np.r_[np.zeros(3), R[:, 0]]                                   # translation along the drift
    assert info["rank"] == 5
    assert np.linalg.norm(W @ axis) <= 1e-9 * np.abs(W).max()
    # by hand: D (I - a aᵀ) D / σ², a the (already unit, translation-only) free direction, D = diag(L·I, I)
    L = np.sqrt(np.mean(np.sum(P * P, axis=1)))
    d = np.r_[[L] * 3, [1.0] * 3]
    expected = d[:, None] * (np.eye(6) - np.outer(axis, axis)) * d[None, :] / SIGMA_F**2
    np.testing.assert_allclose(W, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    assert "translation along" in info["free"]


def test_dead_end_face_gives_full_information():
    P, N = _tunnel(True)
    W, info = map_registration_information(P, N, 0.0, SIGMA_F, 0.02)
    assert info["rank"] == 6 and info["free"] == ""
    L = np.sqrt(np.mean(np.sum(P * P, axis=1)))
    np.testing.assert_allclose(W, np.diag([L**2] * 3 + [1.0] * 3) / SIGMA_F**2, rtol=1e-9, atol=1e-9 * L**2 / SIGMA_F**2)
    # with the ICP's own noise term each constrained direction has less than the floor's information
    W2, _ = map_registration_information(P, N, 0.05, SIGMA_F, 0.02)
    assert np.all(np.linalg.eigvalsh(W - W2) >= -1e-9 * np.abs(W).max())
    assert np.linalg.eigvalsh(W2)[0] > 0


def test_graph_keeps_the_odometry_along_the_free_axis():
    """Keyframe 0 held, keyframe 1 by an odometry edge 10 m along x; a map factor on keyframe 1 that
    says 1 m farther along x and 0.3 m to the side: only the side moves (towards the map, weighted by
    hand: y = 0.3 · w_map / (w_map + w_odo))."""
    P, N = _tunnel(False)
    W, _ = map_registration_information(P, N, 0.0, SIGMA_F, 0.02)
    g = FactorGraph()
    g.add_keyframe(np.eye(4), fixed=True)
    Z = np.eye(4)
    Z[0, 3] = 10.0
    g.add_keyframe(Z)
    s_odo = 0.5
    g.add_relative(0, 1, Z, np.diag([1e4] * 3 + [1 / s_odo**2] * 3))
    T_map = Z.copy()
    T_map[0, 3] += 1.0
    T_map[1, 3] += 0.3
    g.add_map_registration(1, T_map, W)
    assert g.n_factors["map"] == 1
    res = g.optimize()
    assert res.status != "failed"
    t = g.poses[1][:3, 3]
    assert abs(t[0] - 10.0) < 1e-4            # the map's 1 m along x has no pull
    w_map, w_odo = 1 / SIGMA_F**2, 1 / s_odo**2
    assert t[1] == pytest.approx(0.3 * w_map / (w_map + w_odo), abs=1e-4)


def test_register_to_map_corrects_across_and_leaves_along_free():
    """A straight drift yawed 37° in the map; the keyframe predicted 0.3 m off along the drift, 0.15 m
    across and 0.1 m low: the registration brings across and vertical back (to 2 cm), its information
    has no component along the drift (keyframe frame x; the registered position along it is arbitrary:
    nothing there to register on, so it is not asserted)."""
    from minegeo.semantic.mapfactor import MapPrior, register_to_map
    from minegeo.semantic.recognition import RecognitionParams

    rng = np.random.default_rng(3)
    P, _ = _tunnel(False, step=0.2)
    T_true = np.eye(4)
    T_true[:3, :3] = exp_so3(np.array([0.0, 0.0, np.radians(37.0)]))
    T_true[:3, 3] = (40.0, -12.0, 1.3)
    prior = MapPrior.from_points(P @ T_true[:3, :3].T + T_true[:3, 3])
    src = P[np.abs(P[:, 0]) < 8.0][::3]
    src = src + rng.normal(0.0, 0.01, src.shape)
    ax, side = T_true[:3, 0], T_true[:3, 1]
    T_pred = T_true.copy()
    T_pred[:3, 3] += 0.3 * ax + 0.15 * side - np.r_[0.0, 0.0, 0.1]
    reg = register_to_map(0, src, T_pred, prior, RecognitionParams(), None, SIGMA_F, 0.02)
    assert reg.status == "factor", reg.reason
    assert reg.rank == 5
    d = reg.T_world_keyframe[:3, 3] - T_true[:3, 3]
    assert abs(d @ side) < 0.02 and abs(d[2]) < 0.02
    # the free direction is translation along the drift up to the map's PCA-normal noise (it mixes in a
    # little roll): its information is < 1e-3 of the floor's 1/σ² that across the drift gets
    W = reg.information
    ex, ey = np.r_[0, 0, 0, 1.0, 0, 0], np.r_[0, 0, 0, 0, 1.0, 0]
    assert ey @ W @ ey == pytest.approx(1 / SIGMA_F**2, rel=0.01)
    assert ex @ W @ ex <= 1e-3 / SIGMA_F**2
