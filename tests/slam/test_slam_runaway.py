"""No silent runaway: a registration that no plausible motion explains is rejected, the frame is held
by the constant-velocity prior, the stretch is flagged, and the run goes on.

Reference: the simulator's pose curve (ground truth) at the frame times; the corrupted frame is made
in the test (a sweep moved 0.8 m, as a frame stamped with the wrong time, or a sweep of another place).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from minegeo.cli import main
from minegeo.io import write_point_cloud
from minegeo.io.types import PointCloud
from minegeo.slam.odometry import OdometryParams
from minegeo.slam.pipeline import SlamParams, run_slam
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

BAD = 10  # the corrupted frame


@pytest.fixture(scope="module")
def stream():
    """20 sweeps at 10 Hz (0.4 deg azimuth step) from t = 4.5 s, the vehicle at 2.7-3 m/s on a straight."""
    st = simulate_stream(StreamParams(preset="vehicle", duration_s=20.0, lidar_hz=10.0, azimuth_step_deg=0.4, seed=1))
    idx = list(range(40, 60))
    ft = st.frame_times[idx + [195]]  # the last: a sweep 15 s later, round the corner (yaw ~90 deg off)
    sweeps = [(t, P, tau) for t, P, tau, _ring in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                               st.lidar_seed)]
    return sweeps[:-1], sweeps[-1], st.curve.poses(ft[:-1])


def _errors(poses, truth):
    G = np.einsum("ij,njk->nik", np.linalg.inv(truth[0]), truth)
    return np.linalg.norm(poses[:, :3, 3] - G[:, :3, 3], axis=1)


def _shifted(sweeps, dx=0.8):
    out = list(sweeps)
    t, P, tau = out[BAD]
    out[BAD] = (t, P + np.array([dx, 0.0, 0.0]), tau)
    return out


@pytest.mark.parametrize("kind", ["shifted", "elsewhere"])
def test_a_corrupted_frame_is_held_by_the_prior_and_flagged(stream, kind):
    sweeps, other, truth = stream
    frames = _shifted(sweeps) if kind == "shifted" else sweeps[:BAD] + [(sweeps[BAD][0], *other[1:])] + sweeps[BAD + 1:]
    res = run_slam(iter(frames), SlamParams(odometry=OdometryParams(), remove_noise=False, use_planes=False))
    odo = res.odometry
    held = odo.held_stretches()
    assert [(h["first_frame"], h["last_frame"]) for h in held] == [(BAD, BAD)], held
    h = held[0]
    assert h["first_time_s"] == pytest.approx(sweeps[BAD][0]) and h["held_s"] == pytest.approx(0.1)
    assert odo.frame_ok.sum() == len(frames) - 1  # the run went on: every other frame registered
    e = _errors(res.poses, truth)
    assert e[BAD] < 0.1  # held by the constant-velocity prior, not moved with the corrupted sweep
    assert e.max() < 0.1


def test_without_the_motion_check_the_shifted_frame_would_be_accepted(stream):
    # the reason the check exists: bounds wide open, the 0.8 m shifted sweep registers and moves its pose
    sweeps, _, truth = stream
    p = OdometryParams(max_speed_m_s=1e6, max_acceleration_m_s2=1e9, max_angular_rate_deg_s=1e9)
    res = run_slam(iter(_shifted(sweeps)), SlamParams(odometry=p, remove_noise=False, use_planes=False))
    assert res.odometry.frame_ok.all()
    assert _errors(res.poses, truth)[BAD] > 0.25  # measured 0.40 m


def test_the_cli_reports_the_held_stretch(stream, tmp_path):
    sweeps, _, _ = stream
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, (_t, P, tau) in enumerate(_shifted(sweeps[:14])):
        write_point_cloud(frames / f"{i:06d}.ply", PointCloud(points=np.ascontiguousarray(P),
                                                              attributes={"time": np.ascontiguousarray(tau)}))
    (frames / "times.txt").write_text("".join(f"{t:.9f}\n" for t, _, _ in sweeps[:14]))
    out = tmp_path / "out"
    assert main(["--quiet", "slam", "--frames", str(frames), "--out", str(out), "--no-planes",
                 "--no-noise-removal"]) == 0
    r = json.loads((out / "result.json").read_text())["result"]
    assert r["deskew"]["ran"] and r["deskew"]["frames_deskewed"] == 14
    assert len(r["deskew"]["per_frame"]) == 14
    [h] = r["motion_prior_stretches"]
    assert (h["first_frame"], h["last_frame"]) == (BAD, BAD)
    assert h["first_time_s"] == pytest.approx(sweeps[BAD][0], abs=1e-9)
    assert r["motion_prior_held_s"] == pytest.approx(0.1)
    assert "implausible motion" in h["reasons"][0]
    html = (out / "report.html").read_text()
    assert "Held by the constant-velocity motion prior" in html and f"{BAD}–{BAD}" in html


def _reg(ratio=0.01):
    from minegeo.slam.odometry import Registration

    return Registration(np.eye(4), True, "", 1.0, 0.01, np.eye(6), constraint_ratio=ratio)


def _step(dx, yaw_deg=0.0):
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = dx
    return T


def test_the_bounds_by_hand():
    """Hand-computed limits at 10 Hz with the default bounds (30 m/s, 180 deg/s, 20 m/s² + 0.1 m of
    noise: a velocity change of at most 20·0.1 + 2·0.1/0.1 = 4 m/s after a 3 m/s motion)."""
    from minegeo.slam.odometry import _implausible

    p, R, v0 = OdometryParams(), np.eye(3), np.array([3.0, 0.0, 0.0])
    assert _implausible(_reg(), _step(0.69), 0.1, v0, 0.1, R, p) == ""          # 6.9 m/s: Δv 3.9
    assert "velocity change 4.1" in _implausible(_reg(), _step(0.71), 0.1, v0, 0.1, R, p)
    assert _implausible(_reg(), _step(-0.09), 0.1, v0, 0.1, R, p) == ""         # braking: Δv 3.9
    assert "speed 31.0" in _implausible(_reg(), _step(3.1), 0.1, None, 0.0, R, p)  # no previous motion
    assert "angular rate 190" in _implausible(_reg(), _step(0.0, 19.0), 0.1, None, 0.0, R, p)
    assert _implausible(_reg(), _step(0.0, 17.0), 0.1, None, 0.0, R, p) == ""
    # the previous velocity is compared in the world frame: a 90 deg yawed sensor driving along its x
    Rz = _step(0.0, 90.0)[:3, :3]
    assert _implausible(_reg(), _step(0.3), 0.1, np.array([0.0, 3.0, 0.0]), 0.1, Rz, p) == ""
    assert "velocity change" in _implausible(_reg(), _step(0.3), 0.1, v0, 0.1, Rz, p)  # 3 m/s x -> 3 m/s y


def test_degenerate_geometry_is_rejected():
    from minegeo.slam.odometry import _implausible

    p = OdometryParams()
    assert "degenerate geometry" in _implausible(_reg(5e-5), _step(0.3), 0.1, None, 0.0, np.eye(3), p)
    assert _implausible(_reg(2e-4), _step(0.3), 0.1, None, 0.0, np.eye(3), p) == ""
