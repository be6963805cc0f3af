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
