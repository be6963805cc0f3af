"""The noise the LiDAR-inertial graph adds to each LiDAR edge (``InertialParams.edge_sigma_deg``,
``edge_sigma_m``) is a random walk per keyframe edge: over ``n`` edges it lets the LiDAR chain drift
by ``σ √n`` per axis against the IMU. It must match how the LiDAR odometry's relative error grows
along the chain, measured against the simulator's truth: far larger and the IMU's tilt (which an
accelerometer bias mimics on a level drive) overrides the LiDAR's; far smaller and the biased
registrations pull gravity away (module docstring of :mod:`minegeo.slam.inertial`).

Reference: the simulator's pose curve at the keyframe times (its ground truth), never the SLAM's
own output. Stream: the 20 s vehicle stream on the loop network (seed 1, 10 Hz, 0.4° azimuth step,
as ``minegeo synth --stream vehicle``), LiDAR only, each frame to the local map (``minegeo slam``'s
choice for a 10 Hz stream).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from minegeo.kernels.lie import se3_log
from minegeo.slam.inertial import InertialParams
from minegeo.slam.odometry import OdometryParams
from minegeo.slam.pipeline import SlamParams, run_slam
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

#: the span (keyframe edges) over which the chain's error growth is measured
SPAN = 8


@pytest.fixture(scope="module")
def chain_growth():
    """``(rotation deg, translation m)``: RMS per axis of the keyframe chain's relative error over
    ``SPAN`` edges, divided by ``√SPAN`` (the per-edge random walk that error amounts to)."""
    st = simulate_stream(StreamParams(preset="vehicle", duration_s=20.0, lidar_hz=10.0, azimuth_step_deg=0.4, seed=1))
    ft = st.frame_times
    frames = [(t, P, tau) for t, P, tau, _ring in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                              st.lidar_seed)]
    res = run_slam(iter(frames), SlamParams(odometry=OdometryParams(frame_target="submap"), remove_noise=False))
    assert res.odometry.frame_ok.all()
    K = res.poses[res.keyframes]
    G = st.curve.poses(ft[res.keyframes])
    assert K.shape[0] >= SPAN + 10  # at least ten spans
    err = []
    for i in range(K.shape[0] - SPAN):
        Z_true = np.linalg.inv(G[i]) @ G[i + SPAN]
        Z_est = np.linalg.inv(K[i]) @ K[i + SPAN]
        err.append(se3_log(np.ascontiguousarray(np.linalg.inv(Z_true) @ Z_est)))
    rms = np.sqrt(np.mean(np.asarray(err) ** 2, axis=0))
    rot = math.degrees(math.sqrt(np.mean(rms[:3] ** 2) / SPAN))
    trans = math.sqrt(np.mean(rms[3:] ** 2) / SPAN)
    return rot, trans


def test_edge_noise_matches_the_lidar_chains_error_growth(chain_growth):
    rot, trans = chain_growth
    p = InertialParams()
    # measured: 0.055 deg and 5.2 mm per sqrt(edge) (minegeo slam on ten 20 s streams written by
    # minegeo synth: 0.031-0.096 deg, 3.7-17.6 mm); stated: the defaults within a factor of two of it
    # (0.2 deg and 2 cm, the former defaults, are 3.6 and 3.8 times it: this test fails on them)
    assert 0.5 < p.edge_sigma_deg / rot < 2.0, (p.edge_sigma_deg, rot)
    assert 0.5 < p.edge_sigma_m / trans < 2.0, (p.edge_sigma_m, trans)
