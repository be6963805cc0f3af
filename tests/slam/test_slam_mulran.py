"""MulRan Riverside02, 100 real Ouster OS1-64 keyframes: minegeo's GICP odometry against the SC-PGO
reference poses (issue 17, acceptance point "MulRan"; results and discussion in docs/slam_mulran.md).

Data: ``../shared/data/mulran_riverside02_keyframes`` (SOURCE.md). The reference is another SLAM
system's output (FAST-LIO2 + SC-PGO), not ground truth. SOURCE.md states its trust: "Expect agreement
within decimetres and a few tenths of a degree, not centimetres", x/y trusted more than z. The
thresholds are read from that sentence and from the issue, not fitted to minegeo's result:

* ``TRUST_T_M = 0.30`` m per consecutive relative pose: "decimetres" (plural), up to three;
* ``TRUST_ROT_DEG = 0.5`` deg per relative pose: "a few tenths of a degree", up to five tenths;
* ``TYPICAL_T_M = 0.10`` m for the median pair: "decimetre-level";
* ``MIN_WITHIN = 0.95``: at least 95 % of the 99 pairs within both bounds, and each pair outside them
  must be a pair where the *reference* is the odd one out, shown from the scans themselves with
  nothing of minegeo's registration: small_gicp's GICP (the oracle, ``helpers.require_oracle``)
  started at the reference's relative pose leaves it and ends within the trust bounds of minegeo's
  estimate (the reference is not a fit of the two scans, minegeo's is the one next to it), and the
  reference leaves the two scans further apart than minegeo's pose (median nearest-neighbour
  distance of the raw points within 50 m, by at least 1 cm). Three such pairs are known: keyframes
  34, 35 and 62, where the reference's relative pose misaligns the scans by 0.3-1.9 m (small_gicp from
  the reference ends 0.165 / 0.022 / 0.003 m from minegeo's pose);
* every one of minegeo's 99 relative poses is a fit for small_gicp too: started there, it stays within
  the same trust bounds;
* the path length within 1 % of the reference's (the issue's wording).

Parameters: every frame is a keyframe (``keyframe_interval_s=0.1``, below the smallest time step,
0.2 s, so even a frame whose motion is misjudged is one); voxel 0.3 m and gate 1 m, minegeo's
defaults, suit these 13k-point sweeps once the initial guess is within about a metre. The keyframes
are 0.6-14.2 m apart at irregular times (0.2-21.2 s) while the car drives at a steady speed between
stops. With the previous frame's motion alone as the guess (minegeo before the time-scaled guess),
keyframes 31-32 (8.1 m, then 14.2 m) start 5-6 m short and GICP settles in a wrong minimum along
the road (repeated roadside structure; overlap still above 0.9, so nothing is flagged): keyframes
31-40 were lost by up to 13 m and the path was 17 % short, and this test failed (11 pairs outside,
path ratio 0.829). The odometry now also tries the previous motion scaled to the time step (when
the steps differ by more than 25 %) and keeps the better overlap.

The data folder missing: skipped with the reason, or failed under ``MINEGEO_REQUIRE_SHARED_DATA=1``
(``helpers.shared_data``); small_gicp missing: skipped, or failed under ``MINEGEO_REQUIRE_ORACLE=1``.
Runtime about 40 s on 2 shared cores.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_oracle, shared_data

from minegeo.io.frames import read_frame
from minegeo.slam.odometry import OdometryParams, run_odometry

TRUST_T_M = 0.30
TRUST_ROT_DEG = 0.5
TYPICAL_T_M = 0.10
MIN_WITHIN = 0.95
ARBITER_MARGIN_M = 0.01
ARBITER_RANGE_M = 50.0
PATH_TOL = 0.01
ORACLE_VOXEL_M, ORACLE_GATE_M, ORACLE_ITERS = 0.3, 1.0, 64

PARAMS = OdometryParams(keyframe_interval_s=0.1)


def read_kitti_poses(path) -> np.ndarray:
    """(n, 4, 4) poses from KITTI rows (12 floats, row-major [R|t])."""
    rows = np.loadtxt(path, dtype=np.float64).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    T[:, :3, :] = rows
    return T


def relative(poses: np.ndarray) -> np.ndarray:
    """``T_{k-1}⁻¹ T_k`` for consecutive poses, (n-1, 4, 4)."""
    return np.einsum("nij,njk->nik", np.linalg.inv(poses[:-1]), poses[1:])


def pose_difference(A: np.ndarray, B: np.ndarray, R_world: np.ndarray) -> dict:
    """Differences of relative poses ``B`` against ``A`` (both (n, 4, 4), the same frames).

    Translation: ``t_B - t_A`` (in frame ``k-1``) turned into the world frame by ``R_world`` (the
    reference's gravity-aligned orientation of ``k-1``): ``horizontal_m`` is its x/y part,
    ``vertical_m`` its z part. Rotation: the angle of ``R_A⁻¹ R_B`` (deg).
    """
    d = np.einsum("nij,nj->ni", R_world, B[:, :3, 3] - A[:, :3, 3])
    E = np.einsum("nji,njk->nik", A[:, :3, :3], B[:, :3, :3])
    cos = np.clip((np.trace(E, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return {"translation_m": np.linalg.norm(d, axis=1), "horizontal_m": np.linalg.norm(d[:, :2], axis=1),
            "vertical_m": np.abs(d[:, 2]), "rotation_deg": np.degrees(np.arccos(cos))}


def relative_errors(est: np.ndarray, ref: np.ndarray) -> dict:
    """Errors of the consecutive relative poses of ``est`` against those of ``ref`` (n, 4, 4)."""
    return pose_difference(relative(ref), relative(est), ref[:-1, :3, :3])


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def scan_gap_m(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> float:
    """Median nearest-neighbour distance (m) of the raw ``source`` points within ``ARBITER_RANGE_M``
    of the sensor, moved by ``T`` (target ← source), to the raw ``target`` points."""
    from scipy.spatial import cKDTree

    P = source[np.linalg.norm(source, axis=1) < ARBITER_RANGE_M]
    d, _ = cKDTree(target).query(P @ T[:3, :3].T + T[:3, 3])
    return float(np.median(d))


def oracle_gicp(source, target, T_init) -> np.ndarray:
    """small_gicp's GICP (the oracle, not minegeo's) of the raw ``source`` into ``target`` from ``T_init``
    (target ← source): the same voxel (0.3 m) and gate (1 m) as minegeo's odometry, one thread."""
    small_gicp = require_oracle("small_gicp")
    res = small_gicp.align(np.ascontiguousarray(target, dtype=np.float64),
                           np.ascontiguousarray(source, dtype=np.float64), np.asarray(T_init, dtype=np.float64),
                           registration_type="GICP", downsampling_resolution=ORACLE_VOXEL_M,
                           max_correspondence_distance=ORACLE_GATE_M, num_threads=1, max_iterations=ORACLE_ITERS)
    return np.asarray(res.T_target_source)


def reference_is_the_odd_one(source, target, Z_ref, Z_est, R_world) -> tuple[bool, str]:
    """The reference's relative pose ``Z_ref`` (target ← source) is not a fit of the scans, and
    minegeo's ``Z_est`` is: small_gicp's GICP started at ``Z_ref`` leaves it and ends within the trust
    bounds of ``Z_est``, and ``Z_ref`` leaves the scans at least ``ARBITER_MARGIN_M`` further apart than
    ``Z_est`` (raw nearest-neighbour distances). Neither judgement uses minegeo's registration."""
    Z_fit = oracle_gicp(source, target, Z_ref)
    diff = pose_difference(Z_est[None], Z_fit[None], R_world[None])
    near = diff["translation_m"][0] <= TRUST_T_M and diff["rotation_deg"][0] <= TRUST_ROT_DEG
    gap_ref, gap_est = scan_gap_m(source, target, Z_ref), scan_gap_m(source, target, Z_est)
    ok = near and gap_ref >= gap_est + ARBITER_MARGIN_M
    return ok, (f"small_gicp from the reference ends {diff['translation_m'][0]:.3f} m / "
                f"{diff['rotation_deg'][0]:.3f} deg from minegeo's pose; scan gap {gap_ref:.3f} m (reference) "
                f"vs {gap_est:.3f} m (minegeo)")


@pytest.fixture(scope="module")
def mulran():
    root = shared_data("mulran_riverside02_keyframes")
    times = np.loadtxt(root / "times.txt")
    files = sorted((root / "scans").glob("*.pcd"))
    assert len(files) == times.size == 100
    frames = [(float(t), read_frame(f)) for t, f in zip(times, files, strict=True)]
    ref = read_kitti_poses(root / "optimized_poses_scpgo.txt")
    odo = run_odometry(frames, PARAMS)
    return frames, ref, odo


def test_every_frame_is_a_registered_keyframe(mulran):
    _, _, odo = mulran
    assert odo.keyframes.tolist() == list(range(100))
    assert odo.frame_ok.all(), [r for r in odo.frame_reason if r]


def test_relative_poses_agree_with_the_reference_within_its_trust(mulran):
    frames, ref, odo = mulran
    err = relative_errors(odo.poses, ref)
    t, rot = err["translation_m"], err["rotation_deg"]
    within = (t <= TRUST_T_M) & (rot <= TRUST_ROT_DEG)
    assert np.median(t) <= TYPICAL_T_M, f"median translation error {np.median(t):.3f} m"
    assert within.mean() >= MIN_WITHIN, (
        f"{(~within).sum()} of {within.size} pairs beyond {TRUST_T_M} m / {TRUST_ROT_DEG} deg: keyframes "
        f"{[(int(i) + 1, round(float(t[i]), 2), round(float(rot[i]), 2)) for i in np.flatnonzero(~within)]}")
    Ze, Zr = relative(odo.poses), relative(ref)
    unexplained = []
    for i in np.flatnonzero(~within):  # pair (i, i+1): scan i+1 into scan i
        ok, why = reference_is_the_odd_one(frames[i + 1][1], frames[i][1], Zr[i], Ze[i], ref[i, :3, :3])
        if not ok:
            unexplained.append(f"keyframe {i + 1}: {t[i]:.3f} m / {rot[i]:.3f} deg off; {why}")
    assert not unexplained, "beyond the reference's trust, and the reference is not shown wrong:\n" + "\n".join(
        unexplained)


def test_every_relative_pose_is_a_fit_for_an_independent_gicp(mulran):
    """small_gicp (the oracle) started at each of minegeo's 99 relative poses stays within the reference's
    trust bounds of it (measured: median 0.016 m / 0.04 deg, max 0.20 m / 0.29 deg): minegeo's poses are
    minima of another implementation's GICP cost on the raw scans, not of its own only."""
    frames, ref, odo = mulran
    Ze = relative(odo.poses)
    Zf = np.stack([oracle_gicp(frames[i + 1][1], frames[i][1], Ze[i]) for i in range(len(Ze))])
    diff = pose_difference(Ze, Zf, ref[:-1, :3, :3])
    bad = np.flatnonzero((diff["translation_m"] > TRUST_T_M) | (diff["rotation_deg"] > TRUST_ROT_DEG))
    assert bad.size == 0, [(int(i) + 1, round(float(diff["translation_m"][i]), 3),
                            round(float(diff["rotation_deg"][i]), 3)) for i in bad]


def test_path_length_within_one_percent(mulran):
    _, ref, odo = mulran
    ratio = path_length(odo.poses) / path_length(ref)
    assert abs(ratio - 1.0) <= PATH_TOL, f"path length ratio {ratio:.4f}"
