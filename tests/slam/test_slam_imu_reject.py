"""No silent runaway with an IMU: a registration whose rotation disagrees with the gyro is rejected,
the frame is held by the gyro's rotation and the constant-velocity translation, and the stretch is
flagged (``OdometryResult.held_stretches``, ``held_by = "imu"``).

Stream: 14 sweeps at 10 Hz of the simulated handheld walk (seed 1, from t = 13.0 s, the simulator's
own pose curve as the reference), its IMU with gyro biases of σ 0.02 rad/s. The registration is
corrupted on three consecutive frames: their registered pose turned by 10° of yaw about the sensor
(``register_frames`` wrapped). At 100 °/s of apparent turn rate and no change of translation, the
motion-prior guard of the LiDAR-only odometry (speed, angular rate 180 °/s, acceleration) accepts
them as it does today; with the IMU the gate ``θ_tol + n_σ √3 σ_θ`` rejects them (measured: bounds 3.9°,
5.8° and 7.7° for the three frames, the interval since the last registered frame growing to 0.3 s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import minegeo.slam.odometry as odometry
from minegeo.geometry.se3 import compose
from minegeo.io.imu import ImuSamples
from minegeo.kernels.lie import so3_log
from minegeo.slam.inertial import GyroAid
from minegeo.slam.odometry import OdometryParams, run_odometry
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.imu import ImuParams
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

BAD = (5, 6, 7)  # frame numbers whose registration is corrupted
YAW_DEG = 10.0


@pytest.fixture(scope="module")
def stream():
    st = simulate_stream(StreamParams(preset="handheld", duration_s=16.0, lidar_hz=10.0, azimuth_step_deg=0.4, seed=1,
                                      imu=ImuParams(gyroscope_bias_init=0.02)))
    ft = st.frame_times[130:144]
    sweeps = [(t, P, tau) for t, P, tau, _ring in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                               st.lidar_seed)]
    imu = ImuSamples(st.imu.t, st.imu.gyro, st.imu.accel)
    return sweeps, st.curve.poses(ft), imu, ft


@pytest.fixture
def corrupted(monkeypatch, stream):
    """``register_frames`` returning a pose turned by ``YAW_DEG`` about the sensor's z for the frames ``BAD``."""
    _sweeps, _truth, _imu, ft = stream
    bad_times = {float(ft[k]) for k in BAD}
    real = odometry.register_frames
    c, s = math.cos(math.radians(YAW_DEG)), math.sin(math.radians(YAW_DEG))
    Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def wrong(source, target, T_init, params, **kw):
        reg = real(source, target, T_init, params, **kw)
        if source.time_s in bad_times and reg.ok:
            T = compose(reg.T, Rz)
            T[:3, 3] = reg.T[:3, 3]  # the rotation only: the translation stays plausible
            reg.T = T
        return reg

    monkeypatch.setattr(odometry, "register_frames", wrong)


def _errors(poses, truth):
    """Position error (m) and rotation error (deg) of each frame, the truth in the first frame's frame."""
    G = np.einsum("ij,njk->nik", np.linalg.inv(truth[0]), truth)
    dp = np.linalg.norm(poses[:, :3, 3] - G[:, :3, 3], axis=1)
    dr = [math.degrees(np.linalg.norm(so3_log(np.ascontiguousarray(a[:3, :3].T @ b[:3, :3]))))
          for a, b in zip(G, poses, strict=True)]
    return dp, np.asarray(dr)


PARAMS = OdometryParams(keyframe_distance_m=0.3)


def test_imu_rejects_the_wrong_registrations_and_flags_them(stream, corrupted):
    sweeps, truth, imu, ft = stream
    lidar = run_odometry(iter(sweeps), PARAMS)
    li = run_odometry(iter(sweeps), PARAMS, imu=GyroAid(imu))
    # without the IMU: the guard as today (plausible speed, turn rate and acceleration): accepted, and the
    # heading is off by the wrong yaws from then on (measured: 18.9 deg at the last frame, 0.35 m of position
    # error; the keyframe refinement took back part of the 30 deg). The wrongly placed sweeps then spoil the
    # covariances of the next frames (taken among the last sweeps' points, covariance_frames): frames 9 and
    # 10 register wrongly and the acceleration guard holds them (with covariance_frames=1 every frame passes)
    assert lidar.frame_ok[list(BAD)].all()
    assert all(h["first_frame"] > BAD[-1] for h in lidar.held_stretches())
    dp_l, dr_l = _errors(lidar.poses, truth)
    assert dr_l[-1] > 10.0, dr_l
    # with the IMU: exactly the corrupted frames rejected, one flagged stretch held by the IMU
    assert [k for k in range(len(sweeps)) if not li.frame_ok[k]] == list(BAD)
    held = li.held_stretches()
    assert len(held) == 1 and (held[0]["first_frame"], held[0]["last_frame"]) == (BAD[0], BAD[-1])
    assert held[0]["held_by"] == "imu" and all(r.startswith("IMU disagreement") for r in held[0]["reasons"])
    assert held[0]["held_s"] == pytest.approx(ft[BAD[-1]] - ft[BAD[0] - 1])
    # and the trajectory stays right: rotations within 1 deg, positions within 5 cm of the truth after the
    # stretch and 15 cm within it (the constant velocity over 0.3 s of a handheld's sway); measured: 0.19 deg,
    # 0.033 m after the stretch, 0.094 m within it
    dp, dr = _errors(li.poses, truth)
    assert dr.max() < 1.0, dr
    after = np.arange(len(sweeps)) > BAD[-1]
    assert dp[after].max() < 0.05 and dp.max() < 0.15, dp


def test_without_imu_the_stretch_record_has_no_held_by(stream):
    sweeps, *_ = stream
    odo = run_odometry(iter(sweeps[:3]), PARAMS)
    odo.frame_ok[1], odo.frame_reason[1] = False, "overlap 0.10 below 0.30"  # a held frame, recorded as today
    (h,) = odo.held_stretches()
    assert "held_by" not in h and h["reasons"] == ["overlap 0.10 below 0.30"]
