"""Sensor streams in the paper world (minegeo.synth.stream_paper): height above the local floor, pitch
on the ramp, points at their own firing time, gyro against the truth rotation, determinism, bad input.

The references are the world's own geometry (its drift centrelines, which lie on the floor, and its
SDF), not the stream's smoothed path or curve. Sweeps are cast with a 1 degree azimuth step (a
paper-world sweep at 0.2 degree costs about 0.6 s).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from minegeo.errors import InputError
from minegeo.synth.imu import ImuParams
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream, write_stream
from minegeo.synth.stream_paper import PAPER_NETWORKS, paper_network

FAST = {"azimuth_step_deg": 1.0}
DRIFTS = {"paper-ring": ["ring_L0_049", "ring_L0_050"], "paper-straight": [f"main_L1_{i:03d}" for i in range(52, 72)],
          "paper-ramp": ["ring_L0_049", "ramp_L0_051", "main_L1_052", "main_L1_053"]}


def _floor_reference(world, names):
    """Dense floor points (every ~5 cm) of the named drifts' centrelines, straight from the world."""
    out = []
    for d in world.drifts:
        if d.name in names:
            c = d.centreline
            n = np.maximum(np.ceil(np.linalg.norm(np.diff(c, axis=0), axis=1) / 0.05).astype(int), 1)
            out += [c[i] + np.linspace(0, 1, k, endpoint=False)[:, None] * (c[i + 1] - c[i]) for i, k in enumerate(n)]
    return np.concatenate(out)


def _nearest_floor(ref, P):
    """Index of the horizontally nearest reference floor point of each point of ``P``."""
    from scipy.spatial import cKDTree

    return cKDTree(ref[:, :2]).query(P[:, :2])[1]


@pytest.fixture(scope="module")
def streams():
    """30 s of vehicle motion on each path (motion and IMU only; no sweeps)."""
    return {n: simulate_stream(StreamParams(preset="vehicle", network=n, duration_s=30.0, seed=2, **FAST))
            for n in PAPER_NETWORKS}


@pytest.mark.parametrize("name", PAPER_NETWORKS)
def test_truth_inside_the_drift_at_sensor_height_above_the_local_floor(streams, name):
    st = streams[name]
    world = st.net.world
    t = np.arange(st.curve.t_start, st.imu.t[-1], 0.05)
    _, p = st.curve.rotation_position(t)
    assert world.sdf(p).min() > 0.5                              # inside the open space, clear of the rock
    ref = _floor_reference(world, DRIFTS[name])
    i = _nearest_floor(ref, p)
    lateral = np.linalg.norm(p[:, :2] - ref[i, :2], axis=1)
    assert lateral.max() < 1.0                                   # on the drift's axis (sway, smoothing)
    h = p[:, 2] - ref[i, 2]
    # 1.8 m above the floor where the carrier is (bob 1 cm); at the ramp's ends the path rounds the
    # floor's kink over a few metres (1 m smoothing, 3 m corner cut), as a vehicle straddling a crest
    assert np.percentile(np.abs(h - 1.8), 90) < 0.02 and np.abs(h - 1.8).max() < 0.15, (h.min(), h.max())
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).sum() > 60.0   # 30 s at up to 3 m/s


def test_ramp_pitch_follows_the_grade(streams):
    """On the ramp the truth pitch (nose down, ``R = Rz Ry Rx``) is the grade of the ramp's floor
    centreline at the carrier's position, within the vehicle's 0.5 degree tilt noise."""
    st = streams["paper-ramp"]
    world = st.net.world
    (ramp,) = [d for d in world.drifts if d.name == "ramp_L0_051"]
    ref = _floor_reference(world, ["ramp_L0_051"])
    sh = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref[:, :2], axis=0), axis=1))])
    t = np.arange(st.curve.t_start, st.imu.t[-1], 0.05)
    R, p = st.curve.rotation_position(t)
    i = _nearest_floor(ref, p)
    on = (np.linalg.norm(p[:, :2] - ref[i, :2], axis=1) < 1.0) & (sh[i] > 5.0) & (sh[i] < sh[-1] - 5.0)
    assert on.sum() > 200                                        # > 10 s on the ramp
    j = np.clip(np.searchsorted(sh, sh[i[on]][:, None] + [-2.0, 2.0]), 0, len(sh) - 1)   # grade over +-2 m
    grade = (ref[j[:, 1], 2] - ref[j[:, 0], 2]) / (sh[j[:, 1]] - sh[j[:, 0]])
    pitch = np.arcsin(-R[on, 2, 0])
    assert np.degrees(np.abs(np.arctan(grade))).min() > 5.0      # a real ramp (25 m down over 204 m)
    assert np.degrees(np.abs(pitch + np.arctan(grade))).max() < 0.8
    assert ramp.centreline[0, 2] - ramp.centreline[-1, 2] == pytest.approx(25.0, abs=0.5)


def test_gyro_integrates_to_the_truth_rotation(streams):
    """Ring: 10 s of the gyro (ADIS16448 white noise; its simulated bias, known here, removed)
    integrated; the ring turns the vehicle by ~100 degrees; the integral agrees with the curve within
    0.05 degree (white noise ~0.03 degree); with the bias left in it is off by at most its drift."""
    st = streams["paper-ring"]
    imu = st.imu
    k = (imu.t >= 15.0) & (imu.t <= 25.0)
    tt = imu.t[k]

    def integrate(g):
        R = np.eye(3)
        for a in range(len(tt) - 1):
            R = R @ Rotation.from_rotvec(0.5 * (g[a] + g[a + 1]) * (tt[a + 1] - tt[a])).as_matrix()
        return R

    Rc, _ = st.curve.rotation_position([tt[0], tt[-1]])
    rel = Rc[0].T @ Rc[1]
    assert np.degrees(Rotation.from_matrix(rel).magnitude()) > 60.0
    assert np.degrees(Rotation.from_matrix(rel.T @ integrate(imu.gyro[k] - imu.bias_gyro[k])).magnitude()) < 0.05
    bias_bound = np.degrees(np.linalg.norm(imu.bias_gyro[k], axis=1).max() * (tt[-1] - tt[0])) + 0.05
    assert np.degrees(Rotation.from_matrix(rel.T @ integrate(imu.gyro[k])).magnitude()) < bias_bound


def test_sweep_points_lie_on_the_rock_at_their_own_firing_time():
    """A sweep at 3 m/s on the ring, noise-free ranges: each point placed with the truth pose at its
    own time lies on the world's surface (SDF ~ 0); placed with the sweep-start pose it does not."""
    st = simulate_stream(StreamParams(preset="vehicle", network="paper-ring", duration_s=9.0, seed=2,
                                      range_noise_m=0.0, **FAST))
    tf = 8.0
    assert np.linalg.norm(st.curve.state([tf]).v) > 2.5
    ((t0, P, tt, _ring),) = list(iter_sweeps(st.net.world, st.sensor, st.curve, [tf], st.lidar_seed))
    assert t0 == tf and len(P) > 5000 and tt.max() > 0.09
    R, o = st.curve.rotation_position(tf + tt)
    f_own = st.net.world.sdf(np.einsum("nij,nj->ni", R, P) + o)
    R0, o0 = st.curve.rotation_position([tf])
    f_start = st.net.world.sdf(P @ R0[0].T + o0[0])
    assert np.abs(f_own).max() < 0.002, np.abs(f_own).max()          # measured 1e-4 m
    assert np.percentile(np.abs(f_start), 99) > 0.05 and np.mean(np.abs(f_start) > 0.02) > 0.1


def _files(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_paper_stream_deterministic_and_recorded(tmp_path):
    kw = {"preset": "vehicle", "network": "paper-ramp", "duration_s": 0.3, "imu": ImuParams(rate_hz=100.0), **FAST}
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    write_stream(a, StreamParams(seed=3, **kw))
    write_stream(b, StreamParams(seed=3, **kw))
    write_stream(c, StreamParams(seed=4, **kw))
    fa, fb, fc = _files(a), _files(b), _files(c)
    assert fa == fb
    assert sorted(k for k in fa if k.endswith(".ply")) == [f"frames/{i:06d}.ply" for i in range(3)]
    for k in ("imu.csv", "groundtruth.txt", "frames/000001.ply"):
        assert fa[k] != fc[k], k
    net = json.loads(fa["result.json"])["network"]
    assert net["name"] == "paper-ramp" and net["world_preset"] == "paper" and net["world_seed"] == 1
    assert net["path_length_m"] == pytest.approx(251.5, abs=1.0) and net["drop_m"] == pytest.approx(25.0, abs=0.1)
    assert 6.5 < net["max_grade_deg"] < 8.0


def test_handheld_walks_the_ring():
    st = simulate_stream(StreamParams(preset="handheld", network="paper-ring", duration_s=6.0, seed=1, **FAST))
    _, p = st.curve.rotation_position(np.arange(st.curve.t_start, st.imu.t[-1], 0.05))
    assert st.net.world.sdf(p).min() > 0.5 and np.abs(p[:, 2] - 1.4).max() < 0.1


@pytest.mark.parametrize("kw,expect", [
    ({"network": "paper-circle"}, "unknown paper-world"),
    ({"network": "paper-ring", "station_spacing_m": 20.0}, "stations"),
    ({"network": "paper-ring", "width_m": 3.0}, "width"),
])
def test_bad_paper_params(kw, expect):
    with pytest.raises(InputError, match=expect):
        StreamParams(**kw)


def test_duration_past_the_path_end_says_how_long_the_path_lasts():
    net = paper_network("paper-ring")
    with pytest.raises(InputError, match=r"paper-ring path \(114 m\) lasts 4\d\.\d s .* --duration-s <= 4\d"):
        simulate_stream(StreamParams(network="paper-ring", duration_s=60.0, **FAST), net)
