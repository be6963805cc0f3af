"""Online recognition and tracking (issue 18, deliverable 2): the right intersection is recognised from
ray-cast VLP-16 keyframes, a nearly-alike wrong one is refused by the verification, a keyframe without
walls gets ``no_walls``, and the tracker adds factors only for verified recognitions."""

from __future__ import annotations

import numpy as np
import pytest
from _netsim import drive

from minegeo.semantic import (
    RecognitionParams,
    RecognitionState,
    TrackParams,
    build_knowledge_base,
    recognise_keyframe,
    track,
)
from minegeo.synth import intersections_network, network_cloud


@pytest.fixture(scope="module")
def net():
    return intersections_network()


@pytest.fixture(scope="module")
def cloud(net):
    return network_cloud(net, seed=1).points


@pytest.fixture(scope="module")
def kb(cloud):
    return build_knowledge_base(cloud)


@pytest.fixture(scope="module")
def run(net):
    """A drive east through X1 (0, 0), frames every 1.2 m (2 Hz), with the true poses."""
    return drive(net, [(-14.0, 0.0), (16.0, 0.0)], step_m=1.2, seed=3)


#: Odometry error per 1.2 m step (1 sigma), a good LiDAR odometry's order of magnitude: 0.5 % of the step
#: on each axis, 0.03 deg of yaw, 0.02 deg of roll and of pitch; seeded.
STEP_T_REL, STEP_YAW_DEG, STEP_TILT_DEG, ODO_SEED = 0.005, 0.03, 0.02, 7
#: The odometry's first pose: the true one moved by the drift accumulated before this stretch (1.3 m, 3 deg).
START_OFFSET_M, START_YAW_DEG = (1.0, 0.8, 0.0), 3.0


def _rot(roll, pitch, yaw):
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
            @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))


def _odometry(truth, step_t_rel=STEP_T_REL, step_yaw_deg=STEP_YAW_DEG, step_tilt_deg=STEP_TILT_DEG, seed=ODO_SEED):
    """Odometry poses (n, 4, 4): the true first pose times the start offset, then each true step times a
    seeded random error (a random walk: the history's relative poses are off by millimetres to centimetres,
    the prediction by 1.6-1.9 m near X1)."""
    rng = np.random.default_rng(seed)
    D = np.eye(4)
    D[:3, :3], D[:3, 3] = _rot(0.0, 0.0, np.radians(START_YAW_DEG)), START_OFFSET_M
    O = [truth[0] @ D]
    for k in range(1, len(truth)):
        step = np.linalg.solve(truth[k - 1], truth[k])
        E = np.eye(4)
        E[:3, :3] = _rot(*np.radians(rng.normal(0.0, [step_tilt_deg, step_tilt_deg, step_yaw_deg])))
        E[:3, 3] = rng.normal(0.0, step_t_rel * np.linalg.norm(step[:3, 3]), 3)
        O.append(O[-1] @ step @ E)
    return np.stack(O)


@pytest.fixture(scope="module")
def odo(run):
    """The odometry the recognition gets (history and prediction); the truth is kept for checking."""
    return _odometry(run[1])


def _id_at(kb, xy):
    return int(np.argmin(np.hypot(*(kb.invariant_points[:, :2] - np.asarray(xy)).T)))


def _keyframe(run, odo, j, n_his=5):
    """Keyframe ``j``'s points, its history with the odometry's relative poses, its odometry pose."""
    frames, _ = run
    hs = [h for h in range(j - 2 * n_his, j, 2) if h >= 0]          # keyframes every 2.4 m
    hist = [(frames[h][1], np.linalg.solve(odo[j], odo[h])) for h in hs]
    return frames[j][1], hist, odo[j]


def test_recognises_the_right_intersection(run, odo, kb):
    """Keyframes 2-3 m before X1 and just past it, with the odometry (history and prediction) of ``_odometry``:
    X1 is the match (X2/X3/T also pass the PWCV; the CWC decides), verified by ICP; the registered pose
    agrees with the truth to 0.2 m while the odometry is 1.6-1.9 m off, the observed point with X1 to 0.3 m.
    (At x = -0.8 m, 0.8 m from the crossing's centre, the detector finds no junction within 8 m, and at
    x = -4.4 m it finds one only with a near-exact history: known weaknesses, docs/intersections.md
    "Results" and ``test_far_keyframe_needs_a_near_exact_history``.)"""
    x1 = _id_at(kb, (0, 0))
    done = 0
    for j in (9, 10, 12):           # sensor at x = -3.2, -2.0, +0.4 m
        P, hist, O = _keyframe(run, odo, j)
        T = run[1][j]                               # the truth, for checking only
        r = recognise_keyframe(P, hist, kb, T_world_kf_pred=O)
        assert r.status == "verified", r.reason
        assert r.intersection_id == x1
        assert r.pwcv_score >= 0.8 and len(r.candidates) > 1 and np.isfinite(r.cwc_score)
        assert r.icp_rms_m < 0.135 and r.icp_fitness > 0.6
        assert np.linalg.norm(r.T_world_keyframe_icp[:3, 3] - T[:3, 3]) < 0.2
        assert np.linalg.norm((T @ np.r_[r.z_keyframe, 1.0])[:2] - kb.invariant_points[x1, :2]) < 0.3
        assert np.linalg.norm(O[:3, 3] - T[:3, 3]) > 1.0            # the answer is not the prediction's
        assert r.prediction_error_m == pytest.approx(np.linalg.norm(r.T_world_keyframe_icp[:3, 3] - O[:3, 3]))
        done += 1
    assert done == 3


@pytest.mark.xfail(strict=True, reason="the detector at 4.4 m before a crossing needs the history's relative "
                   "poses to better than ~0.05 % / 0.003 deg per step (a limitation, reported in issue 28)")
def test_far_keyframe_needs_a_near_exact_history(run, kb):
    """Keyframe 8 (x = -4.4 m): verified with the true history; with the odometry of ``_odometry`` (seed 7)
    the drift skeleton has no junction."""
    P, hist, O = _keyframe(run, _odometry(run[1]), 8)
    r = recognise_keyframe(P, hist, kb, T_world_kf_pred=O)
    assert r.status == "verified", r.reason


def test_nearly_alike_wrong_intersection_is_refused(run, odo, cloud):
    """A base whose only crossing is X1's twin X2 (map cropped to 30 m < x < 90 m; same plan, roof 3.6 m
    instead of 3.0 m). With the odometry prediction, X2's point lies 60 m from the predicted junction,
    outside the gate: ``conflict`` before any ICP, even though X2 is the only candidate. Without a
    prediction the ICP verification rejects it: the walls fit, the roof does not (RMS 0.2 m against
    0.09-0.1 m for the right crossing). With a loose ICP limit (0.25 m) it is still a ``conflict`` with
    the prediction; only without a prediction would that loose verification accept it (what the gate is
    for). No case gives a factor for X2.
    (With X2 and X3 both in the base, the CWC cannot choose between them for X1: ``ambiguous``.)"""
    kb2 = build_knowledge_base(cloud[(cloud[:, 0] > 30.0) & (cloud[:, 0] < 90.0)])
    x2 = _id_at(kb2, (60, 0))
    P, hist, T = _keyframe(run, odo, 10)
    r = recognise_keyframe(P, hist, kb2, T_world_kf_pred=T)
    assert r.intersection_id == x2
    assert r.status == "conflict" and "outside the 3.0 m gate" in r.reason and np.isnan(r.icp_rms_m), (r.status,
                                                                                                       r.reason)
    r = recognise_keyframe(P, hist, kb2)
    assert r.status == "rejected" and r.icp_rms_m > 0.135 and "ICP distance" in r.reason, (r.status, r.reason)
    loose = RecognitionParams(icp_max_distance_m=0.25)
    r = recognise_keyframe(P, hist, kb2, loose, T_world_kf_pred=T)
    assert r.status == "conflict", (r.status, r.reason)
    free = recognise_keyframe(P, hist, kb2, loose)
    assert free.status == "verified" and free.intersection_id == x2


def test_no_walls_and_none(kb, run, odo):
    """A floor-only keyframe and an empty one: ``no_walls``; a keyframe in a plain drift: ``none``."""
    g = np.stack(np.meshgrid(np.linspace(-10, 10, 60), np.linspace(-10, 10, 60)), -1).reshape(-1, 2)
    floor = np.c_[g, np.full(len(g), -1.5)]
    assert recognise_keyframe(floor, [], kb).status == "no_walls"
    assert recognise_keyframe(np.zeros((0, 3)), [], kb).status == "no_walls"
    P, hist, T = _keyframe(run, odo, 0)    # x = -14 m: 14 m before X1
    r = recognise_keyframe(P, hist, kb, T_world_kf_pred=T)
    assert r.status == "none" and r.intersection_id == -1


def test_consecutive_count(run, odo, kb):
    """With a state, the first match is only a ``candidate``; the second in a row is verified."""
    st = RecognitionState()
    p = RecognitionParams(consecutive_required=2)
    P9, h9, O9 = _keyframe(run, odo, 9)
    P10, h10, O10 = _keyframe(run, odo, 10)
    a = recognise_keyframe(P9, h9, kb, p, T_world_kf_pred=O9, state=st)
    b = recognise_keyframe(P10, h10, kb, p, T_world_kf_pred=O10, state=st)
    assert a.status == "candidate" and a.streak == 1
    assert b.status == "verified" and b.streak == 2 and st.streak == 0


def test_track_adds_factors_only_for_verified(run, kb):
    """The tracker over the drive from a start pose 0.7 m and 5 deg off the truth (a realistic take-off
    error; the start is held, so the error is not fed as truth): X1 verified (factors only for
    verified recognitions), and the intersection factors pull the keyframes that saw X1 to within
    0.5 m of the truth, closer than the same run without the base (odometry from the wrong start). A
    base without intersections gives status ``no_intersections`` and odometry-only poses."""
    frames, truth = run
    c, s = np.cos(np.radians(5.0)), np.sin(np.radians(5.0))
    T_off = np.array([[c, -s, 0, 0.5], [s, c, 0, -0.5], [0, 0, 1, 0.1], [0, 0, 0, 1]], float)
    start = truth[0] @ T_off
    assert 0.69 < np.linalg.norm(start[:3, 3] - truth[0][:3, 3]) < 0.72
    res = track(frames, kb, TrackParams(T_world_start=start))
    assert res.status == "ok", res.reason
    assert res.poses.shape == (len(frames), 4, 4) and res.times_s.shape == (len(frames),)
    assert res.summary()["recognised_ids"] == [_id_at(kb, (0, 0))]
    assert all(e.recognition.status == "verified" for e in res.recognitions if e.factor)
    assert len(res.verified()) >= 1 and res.n_optimisations == len(res.verified())
    kf = [e.keyframe for e in res.recognitions if e.factor]
    idx = np.asarray(res.keyframes)[kf]
    err = np.linalg.norm(res.poses[idx, :3, 3] - truth[idx, :3, 3], axis=1)
    from dataclasses import replace

    empty = replace(kb, status="no_intersections")
    odo_only = track(frames, empty, TrackParams(T_world_start=start))
    err_odo = np.linalg.norm(odo_only.poses[idx, :3, 3] - truth[idx, :3, 3], axis=1)
    assert err.max() < 0.5 and np.all(err < err_odo), (err, err_odo)
    r0 = track(frames, empty, TrackParams(T_world_start=truth[0]))
    assert r0.status == "no_intersections" and not r0.verified()
