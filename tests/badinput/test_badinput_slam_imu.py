"""``minegeo slam --imu IMU.csv``: every mistake in the IMU is one line, exit 2, nothing written, the
inputs and an earlier result folder untouched (issue 29, deliverable 4; the SLAM contract's
"Sensor streams": header ``t,gx,gy,gz,ax,ay,az``, rows strictly increasing, covering the frames).

The frames are 4 small box-room clouds at 0.0-0.3 s; every case fails before the odometry.
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


@pytest.fixture(scope="module")
def frames_src(tmp_path_factory):
    return write_box_room_frames(tmp_path_factory.mktemp("imu_frames_src") / "frames", N_FRAMES)


@pytest.fixture
def frames(frames_src, tmp_path):
    return copy_tree(frames_src, tmp_path / "frames")


_rows = imu_rows


def _imu(tmp: Path, rows: list[str], header: str = "t,gx,gy,gz,ax,ay,az") -> Path:
    p = tmp / "imu.csv"
    p.write_text(header + "\n" + "\n".join(rows) + "\n")
    return p


GOOD_T = IMU_T

#: case -> (rows of the IMU CSV or a header, extra options, text the error line must hold)
CASES = {
    "starts after the first frame": (_rows(GOOD_T[GOOD_T > 0.05]), [], "do not cover the frames' time span"),
    "ends before the last frame": (_rows(GOOD_T[GOOD_T < 0.2]), [], "do not cover the frames' time span"),
    "rows out of order": (_rows(GOOD_T[[0, 1, 3, 2, *range(4, GOOD_T.size)]]), [], "line 5"),
    "repeated time": (_rows(np.r_[GOOD_T[:10], GOOD_T[9:]]), [], "line 12"),
    "gap over the limit": (_rows(GOOD_T[(GOOD_T < 0.1) | (GOOD_T > 0.2)]), [], "longer than the 0.05 s allowed"),
    "gap over a set limit": (_rows(GOOD_T[(GOOD_T < 0.1) | (GOOD_T > 0.12)]), ["--imu-max-gap", "0.02"],
                             "longer than the 0.02 s allowed"),
    "wrong header": ("t,ax,ay,az,gx,gy,gz", [], "expected 't,gx,gy,gz,ax,ay,az'"),
    "NaN gyro": ([*_rows(GOOD_T[:5]), "0.0,nan,0,0,0,0,9.8", *_rows(GOOD_T[6:])], [], "nan"),
    "only one sample": (_rows([0.0]), [], "must cover the frames"),
    "bad extrinsic": (_rows(GOOD_T), ["--imu-extrinsic", "1 2 3"], "extrinsic"),
    "extrinsic not a rotation": (_rows(GOOD_T), ["--imu-extrinsic", "0 0 0 0 0 0 0"], "quaternion"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_imu_is_one_line_exit_2(case, frames, tmp_path, capsys):
    rows, extra, expect = CASES[case]
    imu = _imu(tmp_path, [], header=rows) if isinstance(rows, str) else _imu(tmp_path, rows)
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", str(frames), "--imu", str(imu), *extra, "--out", str(out)], capsys,
                      inputs=[frames, imu], outputs=[out], expect=expect)


def test_imu_options_need_imu(frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", str(frames), "--imu-max-gap", "0.1", "--out", str(out)], capsys,
                      inputs=[frames], outputs=[out], expect="--imu-max-gap needs --imu")
    assert_user_error("slam", ["--frames", str(frames), "--imu-extrinsic", "0 0 0 0 0 0 1", "--out", str(out)],
                      capsys, inputs=[frames], outputs=[out], expect="--imu-extrinsic needs --imu")
    assert_user_error("slam", ["--frames", str(frames), "--imu", str(tmp_path), "--out", str(out)], capsys,
                      inputs=[frames], outputs=[out], expect="is a folder")
    assert_user_error("slam", ["--frames", str(frames), "--imu", str(tmp_path / "nope.csv"), "--out", str(out)],
                      capsys, inputs=[frames], outputs=[out])


#: noise file text -> text the error line must hold
BAD_NOISE = {
    "a key missing": (KALIBR_IMU_YAML.replace("gyroscope_random_walk", "gyro_rw"), "without gyroscope_random_walk"),
    "a negative density": (KALIBR_IMU_YAML.replace("1.86e-03", "-1.86e-03"),
                           "line 2: accelerometer_noise_density must be a finite number > 0, got '-1.86e-03'"),
    "not a number": (KALIBR_IMU_YAML.replace("2.66e-05", "small"),
                     "line 7: gyroscope_random_walk must be a finite number > 0, got 'small'"),
    "infinite": (KALIBR_IMU_YAML.replace("2.66e-05", "inf"), "line 7: gyroscope_random_walk must be a finite number"),
    "two IMUs": ("imu0:\n" + KALIBR_IMU_YAML.replace("\n", "\n  ") + "imu1:\n  gyroscope_noise_density: 1e-4\n",
                 "gyroscope_noise_density given again"),
    "empty": ("", "without gyroscope_noise_density"),
}


@pytest.mark.parametrize("case", sorted(BAD_NOISE))
def test_bad_imu_noise_is_one_line_exit_2(case, frames, tmp_path, capsys):
    text, expect = BAD_NOISE[case]
    imu, noise, out = _imu(tmp_path, _rows(GOOD_T)), tmp_path / "imu.yaml", tmp_path / "out"
    noise.write_text(text)
    assert_user_error("slam", ["--frames", str(frames), "--imu", str(imu), "--imu-noise", str(noise), "--out", str(out)],
                      capsys, inputs=[frames, imu, noise], outputs=[out], expect=expect)
    assert_user_error("slam", ["--frames", str(frames), "--imu-noise", str(noise), "--out", str(out)], capsys,
                      inputs=[frames, noise], outputs=[out], expect="--imu-noise needs --imu")


def test_a_good_imu_runs(frames, tmp_path, capsys, monkeypatch):
    """The same frames with an IMU that covers them run (the cases above fail on the IMU alone); the
    IMU's noise from a Kalibr imu.yaml reaches the engine and the record."""
    imu = _imu(tmp_path, _rows(GOOD_T))
    noise = tmp_path / "imu.yaml"
    noise.write_text(KALIBR_IMU_YAML)
    seen = capture_gyro_aid_noise(monkeypatch)
    out = tmp_path / "out"
    code, _, lines = run_cli("slam", ["--frames", str(frames), "--imu", str(imu), "--keyframe-distance", "0.15",
                                      "--out", str(out), "--no-planes", "--imu-noise", str(noise)], capsys,
                                 timeout_s=600)  # a whole run, compiling on a cold cache: a hang guard only
    assert code == 0, lines
    assert (out / "trajectory.tum").is_file()
    want = {**KALIBR_IMU_NOISE, "integration_sigma": 0.0}
    assert seen and all(s == want for s in seen)
    rec = json.loads((out / "result.json").read_text())
    assert rec["imu_noise"] == want
    assert str(noise) in {i["path"] for i in rec["provenance"]["inputs"]}
