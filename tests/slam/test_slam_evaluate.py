"""ATE / RPE agree with evo (``evo_ape`` / ``evo_rpe``) on the same trajectories to 1e-9, and have the
properties they must: exact data gives zero, a rigid or similarity motion of the estimate is removed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import InputError
from minegeo.geometry.se3 import exp_so3, random_transform
from minegeo.io.types import Trajectory
from minegeo.slam.evaluate import associate, evaluate_trajectory


def _path(rng, n=120, step=0.5):
    """A smooth random 6-DOF path (a drone-like flight), poses T_world_sensor."""
    T = np.eye(4)
    out = []
    for _ in range(n):
        T = T @ np.block([[exp_so3(rng.normal(scale=0.05, size=3)), np.array([[step], [0.0], [0.0]])
                           + rng.normal(scale=0.05, size=(3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
        out.append(T.copy())
    return np.stack(out)


def _noisy(rng, poses, sigma_t=0.05, sigma_r=0.01):
    out = poses.copy()
    for k in range(len(out)):
        out[k, :3, :3] = out[k, :3, :3] @ exp_so3(rng.normal(scale=sigma_r, size=3))
        out[k, :3, 3] += rng.normal(scale=sigma_t, size=3)
    return out


def _evo():
    from helpers import require_oracle

    return require_oracle("evo")


def _evo_traj(times, poses):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.asarray(times, float))


@pytest.mark.parametrize("scale", [False, True])
@pytest.mark.parametrize("delta, unit", [(1, "frames"), (10, "frames"), (5.0, "m")])
def test_agrees_with_evo(scale, delta, unit):
    _evo()
    from evo.core import metrics, sync

    rng = np.random.default_rng(4)
    gt_p = _path(rng)
    est_p = _noisy(rng, gt_p)
    est_p = np.einsum("ij,njk->nik", random_transform(rng, max_angle_rad=np.pi, max_translation=50.0), est_p)
    if scale:
        est_p[:, :3, 3] *= 0.7
    t_gt = np.arange(len(gt_p)) * 0.1
    t_est = t_gt + rng.uniform(-0.004, 0.004, size=t_gt.size)  # clocks differ by a few ms
    res = evaluate_trajectory(Trajectory(t_est, est_p), Trajectory(t_gt, gt_p), scale=scale,
                              rpe_delta=delta, rpe_unit=unit)

    ref, est = sync.associate_trajectories(_evo_traj(t_gt, gt_p), _evo_traj(t_est, est_p), max_diff=0.01)
    est.align(ref, correct_scale=scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    s = ape.get_all_statistics()
    for k in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        assert getattr(res.ate, k) == pytest.approx(s[k], rel=1e-9, abs=1e-12), k
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta,
                      delta_unit=metrics.Unit.frames if unit == "frames" else metrics.Unit.meters, all_pairs=False,
                      pairs_from_reference=True)
    rpe.process_data((ref, est))
    s = rpe.get_all_statistics()
    assert res.rpe_translation.n == len(rpe.error)
    for k in ("rmse", "mean", "median", "max"):
        assert getattr(res.rpe_translation, k) == pytest.approx(s[k], rel=1e-9, abs=1e-12), k
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=delta,
                        delta_unit=metrics.Unit.frames if unit == "frames" else metrics.Unit.meters, all_pairs=False,
                        pairs_from_reference=True)
    rpe_r.process_data((ref, est))
    assert res.rpe_rotation_deg.rmse == pytest.approx(rpe_r.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)


@settings(max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), scale=st.booleans())
def test_a_rigid_or_similar_copy_has_zero_error(seed, scale):
    rng = np.random.default_rng(seed)
    gt = _path(rng, n=40)
    M = random_transform(rng, max_angle_rad=np.pi, max_translation=1e3)
    est = np.einsum("ij,njk->nik", M, gt)
    if scale:
        est[:, :3, 3] *= 2.5
    t = np.arange(40.0)
    res = evaluate_trajectory(Trajectory(t, est), Trajectory(t, gt), scale=scale)
    assert res.ate.rmse < 1e-8 and res.ate_rotation_deg.max < 1e-5 and res.rpe_translation.max < 1e-8


def test_association_matches_nearest_time_within_tolerance():
    i_ref, i_est = associate(np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.004, 0.995, 2.5, 3.02]), 0.01)
    assert i_ref.tolist() == [0, 1] and i_est.tolist() == [0, 1]


def test_no_common_times_is_a_clear_error():
    rng = np.random.default_rng(0)
    p = _path(rng, n=10)
    with pytest.raises(InputError, match="match the ground truth within"):
        evaluate_trajectory(Trajectory(np.arange(10.0) + 100, p), Trajectory(np.arange(10.0), p))


def test_misalignment_is_seen_without_alignment():
    rng = np.random.default_rng(1)
    gt = _path(rng, n=30)
    est = gt.copy()
    est[:, :3, 3] += [1.0, 0.0, 0.0]
    t = np.arange(30.0)
    assert evaluate_trajectory(Trajectory(t, est), Trajectory(t, gt), align=False).ate.rmse == pytest.approx(1.0)
    assert evaluate_trajectory(Trajectory(t, est), Trajectory(t, gt)).ate.rmse < 1e-9
