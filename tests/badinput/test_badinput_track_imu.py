"""``minegeo track --imu IMU.csv``: the IMU is read and checked as ``minegeo slam`` checks it
(``minegeo.cli._imu``, one reader for both verbs): a mistake is one line, exit 2, nothing written, the
inputs unchanged (issue 29, deliverables 4 and the bad-input acceptance).

Scene: a base built from a straight drift (``intersections build`` exits 1 on it, ``no_intersections``,
but writes it: a valid base) and 4 small box-room frames at 0.0-0.3 s; every case fails before the
odometry, and the same frames with an IMU that covers them run (exit 1: no intersection to recognise).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _contract import (
    IMU_T,
    KALIBR_IMU_NOISE,
    KALIBR_IMU_YAML,
    assert_user_error,
    capture_gyro_aid_noise,
    copy_tree,
    imu_rows,
    run_cli,
    write_box_room_frames,
)

N_FRAMES = 4
GOOD_T = IMU_T


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from minegeo.cli import main
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.network import DriftNetwork, network_cloud

    d = tmp_path_factory.mktemp("track_imu_scene")
    net = DriftNetwork(np.array([[-15.0, 0.0], [15.0, 0.0]]), np.array([[0, 1]]), np.array([4.5]), np.array([3.6, 3.6]))
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, spacing_m=0.4, seed=2).points))
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(d / "kb.npz")]) == 1
    write_box_room_frames(d / "frames", N_FRAMES)
    return d


@pytest.fixture
def frames(scene, tmp_path):
    return copy_tree(scene / "frames", tmp_path / "frames")


def _imu(tmp: Path, t) -> Path:
    p = tmp / "imu.csv"
    p.write_text("t,gx,gy,gz,ax,ay,az\n" + "".join(r + "\n" for r in imu_rows(t)))
    return p


#: case -> (IMU sample times or None for no --imu, extra options, text the error line must hold)
CASES = {
    "ends before the last frame": (GOOD_T[GOOD_T < 0.2], [], "do not cover the frames' time span"),
    "starts after the first frame": (GOOD_T[GOOD_T > 0.05], [], "do not cover the frames' time span"),
    "gap over the limit": (GOOD_T[(GOOD_T < 0.1) | (GOOD_T > 0.2)], [], "longer than the 0.05 s allowed"),
    "gap over a set limit": (GOOD_T[(GOOD_T < 0.1) | (GOOD_T > 0.12)], ["--imu-max-gap", "0.02"],
                             "longer than the 0.02 s allowed"),
    "max gap without --imu": (None, ["--imu-max-gap", "0.1"], "--imu-max-gap needs --imu"),
    "extrinsic without --imu": (None, ["--imu-extrinsic", "0 0 0 0 0 0 1"], "--imu-extrinsic needs --imu"),
    "bad extrinsic": (GOOD_T, ["--imu-extrinsic", "1 2 3"], "extrinsic"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_imu_is_one_line_exit_2(case, scene, frames, tmp_path, capsys):
    t, extra, expect = CASES[case]
    imu = [] if t is None else ["--imu", str(_imu(tmp_path, t))]
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", str(frames), "--db", str(scene / "kb.npz"), *imu, *extra,
                                "--out", str(out)], capsys,
                      inputs=[frames, scene / "kb.npz", *([Path(imu[1])] if imu else [])], outputs=[out],
                      expect=expect)


def test_imu_a_folder_or_missing(scene, frames, tmp_path, capsys):
    out = tmp_path / "out"
    base = ["--frames", str(frames), "--db", str(scene / "kb.npz"), "--out", str(out)]
    assert_user_error("track", [*base, "--imu", str(tmp_path)], capsys, inputs=[frames], outputs=[out],
                      expect="is a folder")
    assert_user_error("track", [*base, "--imu", str(tmp_path / "nope.csv")], capsys, inputs=[frames], outputs=[out])


def test_a_good_imu_runs(scene, frames, tmp_path, capsys, monkeypatch):
    """The same frames with an IMU that covers them run (the cases above fail on the IMU alone); the
    IMU's noise from a Kalibr imu.yaml reaches the engine and the record."""
    out, noise = tmp_path / "out", tmp_path / "imu.yaml"
    noise.write_text(KALIBR_IMU_YAML)
    seen = capture_gyro_aid_noise(monkeypatch)
    code, _, lines = run_cli("track", ["--frames", str(frames), "--db", str(scene / "kb.npz"), "--imu",
                                       str(_imu(tmp_path, GOOD_T)), "--keyframe-distance", "0.15", "--out", str(out),
                                       "--imu-noise", str(noise)], capsys)
    assert code == 1 and (out / "trajectory.tum").is_file(), lines  # 1: the base holds no intersection
    want = {**KALIBR_IMU_NOISE, "integration_sigma": 0.0}
    assert seen and all(s == want for s in seen)
    assert json.loads((out / "result.json").read_text())["imu_noise"] == want
