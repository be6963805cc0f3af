"""GICP covariances of a frame among the points of the frames before it (issue 29, the ramp's tilt).

One sweep of a spinning LiDAR samples a floor along its rings, metres apart: the kNN of a point of
one sweep lie along its own ring and their PCA plane follows the ring line and the relief along it.
With the rings of the earlier sweeps (the sensor has moved) in the neighbourhood the plane is the
floor's again."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.registration import GICPParams, estimate_gicp_covariances
from minegeo.slam.frame_covariances import covariances_with_history
from minegeo.slam.odometry import OdometryParams


def _line(y: float) -> np.ndarray:
    """A straight ring segment on the sloping plane ``z = 0.1 x + 0.2 y``: points 0.3 m apart along x."""
    x = np.arange(-3.0, 3.01, 0.3)
    return np.c_[x, np.full(x.size, y), 0.1 * x + 0.2 * y]


def _normal_angle_deg(C: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Angle (deg) between each covariance's plane normal (its smallest eigenvector) and ``normal``."""
    n = np.linalg.eigh(C)[1][:, :, 0]
    return np.degrees(np.arccos(np.clip(np.abs(n @ (normal / np.linalg.norm(normal))), 0.0, 1.0)))


def test_history_gives_the_surface_that_one_sweep_cannot():
    params = GICPParams(1.0)
    cur = _line(5.0)  # one sweep: its ring alone, collinear (no plane)
    history = np.concatenate([_line(5.0 + 0.3 * i) for i in range(1, 9)])  # the same ring of 8 earlier sweeps
    assert np.allclose(estimate_gicp_covariances(cur, params), np.eye(3))  # the frame's own: isotropic
    C = covariances_with_history(cur, history, params, voxel_m=0.3)
    assert np.all(_normal_angle_deg(C, np.array([-0.1, -0.2, 1.0])) < 0.5)
    # the plane model [Ren2019 Eq. 3]: eigenvalues (eps, 1, 1)
    assert np.allclose(np.linalg.eigvalsh(C), [params.epsilon, 1.0, 1.0])


def test_without_history_the_covariances_are_the_frames_own():
    rng = np.random.default_rng(4)
    P = rng.normal(size=(500, 3)) * [3.0, 2.0, 0.05]  # a noisy plane patch
    params = GICPParams(1.0)
    C = covariances_with_history(P, np.zeros((0, 3)), params)
    assert np.allclose(C, estimate_gicp_covariances(P, params), atol=1e-9)


def test_covariances_with_history_match_a_naive_pca_of_the_union():
    """Naive twin: scipy's kNN in the union of the frame and its history, NumPy's covariance and
    ``eigh``, then ``C = I − (1 − ε) n nᵀ`` [Ren2019 Eq. 3]."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    P = rng.uniform(-4.0, 4.0, size=(300, 3)) * [1.0, 1.0, 0.02]  # a rough floor patch, the frame
    H = rng.uniform(-4.0, 4.0, size=(900, 3)) * [1.0, 1.0, 0.02] + [0.0, 0.0, 0.003]  # earlier sweeps
    params = GICPParams(1.0)
    C = covariances_with_history(P, H, params)
    U = np.concatenate([P, H])
    _, idx = cKDTree(U).query(P, k=params.covariance_neighbours)
    n = np.array([np.linalg.eigh(np.cov(U[i].T, bias=True))[1][:, 0] for i in idx])
    expected = np.eye(3) - (1.0 - params.epsilon) * n[:, :, None] * n[:, None, :]
    assert np.allclose(C, expected, atol=1e-9)


def test_collinear_neighbourhoods_are_isotropic():
    P = np.c_[np.linspace(0.0, 10.0, 50), np.zeros(50), np.zeros(50)]
    C = covariances_with_history(P, np.zeros((0, 3)), GICPParams(1.0))
    assert np.allclose(C, np.eye(3))


def test_covariance_frames_is_validated():
    assert OdometryParams().covariance_frames == 9
    with pytest.raises(InputError):
        OdometryParams(covariance_frames=0)


@pytest.mark.parametrize("n", [1, 3, 8])
def test_the_local_map_holds_the_last_local_map_keyframes(n):
    """Frame to local map: after 10 keyframes the local map is made of the last ``local_map_keyframes``
    keyframe clouds (``keyframe_submap_size``, the frame-to-frame refinement's sub-map, plays no part),
    each moved into the last keyframe's frame. Expected: the union, computed here by NumPy, of the last
    ``n`` clouds at their poses relative to the last one, voxelised as the odometry does."""
    from minegeo.geometry import voxel_downsample
    from minegeo.slam.odometry import _next_submap, prepare_frame

    rng = np.random.default_rng(5)
    params = OdometryParams(frame_target="submap", local_map_keyframes=n, keyframe_submap_size=2)
    clouds, poses, submap, mine = [], [], None, []
    for k in range(10):
        P = np.c_[rng.uniform(-6, 6, 600), rng.uniform(-2, 2, 600), rng.uniform(-0.1, 0.1, 600)] + [0, 0, 0.3 * k]
        T = np.eye(4)
        T[0, 3] = 1.5 * k
        cur = prepare_frame(P, float(k), params)
        mine.append((cur.points.copy(), T[:3, 3].copy()))
        clouds, poses, submap = _next_submap(clouds, poses, cur, T, False, params)
        assert len(clouds) == min(k + 1, n) and len(poses) == len(clouds)
    parts = [C + (t - mine[-1][1]) for C, t in mine[-n:]]
    expected = voxel_downsample(np.concatenate(parts), params.voxel_size_m).points
    assert submap.points.shape == expected.shape
    np.testing.assert_allclose(np.sort(submap.points, axis=0), np.sort(expected, axis=0), atol=1e-9)
