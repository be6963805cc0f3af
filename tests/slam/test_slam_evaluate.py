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


def test_kitti_files_are_matched_by_index_as_evo_ape_kitti(tmp_path):
    """Two KITTI files (no times): pose k with pose k, ATE equal to evo's on the files it reads itself;
    different lengths are refused, as evo's APE refuses them."""
    _evo()
    from evo.core import metrics
    from evo.tools import file_interface

    from minegeo.io import read_trajectory, write_trajectory

    rng = np.random.default_rng(11)
    gt_p = _path(rng, n=60)
    est_p = np.einsum("ij,njk->nik", random_transform(rng, max_angle_rad=2.0, max_translation=20.0), _noisy(rng, gt_p))
    t = np.arange(60.0)
    write_trajectory(tmp_path / "gt.kitti", Trajectory(t, gt_p))
    write_trajectory(tmp_path / "est.kitti", Trajectory(t, est_p))
    write_trajectory(tmp_path / "est20.kitti", Trajectory(t[:20], est_p[:20]))
    gt, est = read_trajectory(tmp_path / "gt.kitti"), read_trajectory(tmp_path / "est.kitti")
    res = evaluate_trajectory(est, gt, match="index", rpe_delta=3)

    ref = file_interface.read_kitti_poses_file(str(tmp_path / "gt.kitti"))
    e = file_interface.read_kitti_poses_file(str(tmp_path / "est.kitti"))
    e.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert res.n_matched == 60
    assert res.ate.rmse == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)

    short = read_trajectory(tmp_path / "est20.kitti")
    with pytest.raises(metrics.MetricsException, match="same number of poses"):
        metrics.APE().process_data((ref, file_interface.read_kitti_poses_file(str(tmp_path / "est20.kitti"))))
    with pytest.raises(InputError, match="the estimate holds 20 poses and the ground truth 60"):
        evaluate_trajectory(short, gt, match="index")


def test_parameters_evo_refuses_are_refused():
    """evo: a frame delta must be whole (MetricsException), a delta with no pair is an error (FilterException);
    Sim(3) scale is part of the alignment, so scale without alignment contradicts."""
    _evo()
    from evo.core import metrics

    rng = np.random.default_rng(2)
    p = _path(rng, n=20)
    t = np.arange(20.0)
    with pytest.raises(metrics.MetricsException, match="integer"):
        metrics.RPE(delta=0.5, delta_unit=metrics.Unit.frames)
    for kw, match in [({"rpe_delta": 0.5}, "whole number of frames"), ({"rpe_delta": float("inf")}, "whole number"),
                      ({"rpe_delta": float("inf"), "rpe_unit": "m"}, "positive finite"),
                      ({"rpe_delta": 0.0, "rpe_unit": "m"}, "positive finite"),
                      ({"max_diff_s": float("nan")}, "max_diff_s"), ({"max_diff_s": 0.0}, "max_diff_s"),
                      ({"scale": True, "align": False}, "contradict"),
                      ({"rpe_delta": 20}, "no pose pair is 20 frames apart"),
                      ({"rpe_delta": 1e6, "rpe_unit": "m"}, "no pose pair is 1e\\+06 m")]:
        with pytest.raises(InputError, match=match):
            evaluate_trajectory(Trajectory(t, p), Trajectory(t, p), **kw)
    assert evaluate_trajectory(Trajectory(t, p), Trajectory(t, p), rpe_delta=19.0).rpe_translation.n == 1


def test_trajectories_that_fail_the_readers_check_are_refused():
    """Built in code (not read from a file), a reflection or duplicated times is still refused, naming the pose."""
    rng = np.random.default_rng(3)
    p = _path(rng, n=10)
    t = np.arange(10.0)
    bad = p.copy()
    bad[4, :3, 2] *= -1.0
    with pytest.raises(InputError, match="estimate pose 4: the rotation block is a reflection"):
        evaluate_trajectory(Trajectory(t, bad), Trajectory(t, p))
    td = t.copy()
    td[6] = td[5]
    with pytest.raises(InputError, match="ground truth pose 6: time 5.000000 s is not after"):
        evaluate_trajectory(Trajectory(t, p), Trajectory(td, p))
