"""``minegeo slam --frames DIR --out OUT``: every user mistake is one line, exit 2, nothing written,
the inputs and an earlier result folder untouched (issue 27 and the SLAM contract).

The frames here are small (a few hundred points of a box-shaped room each): every case fails before
or while reading them, never in the odometry.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from _contract import a_file, a_folder, assert_user_error, copy_tree

N_FRAMES = 4


@pytest.fixture(scope="module")
def frames_src(tmp_path_factory):
    """A frames folder: ``000000.ply`` ... (sensor frame, points on the walls of a 6 x 4 x 3 m room)
    and ``times.txt``."""
    from minegeo.io import PointCloud, write_point_cloud

    d = tmp_path_factory.mktemp("frames_src") / "frames"
    d.mkdir()
    rng = np.random.default_rng(27)
    for k in range(N_FRAMES):
        u = rng.uniform(-1.0, 1.0, (600, 3)) * [3.0, 2.0, 1.5]
        face = rng.integers(0, 3, 600)
        u[np.arange(600), face] = np.sign(u[np.arange(600), face]) * np.array([3.0, 2.0, 1.5])[face]
        write_point_cloud(d / f"{k:06d}.ply", PointCloud(points=u + [0.1 * k, 0.0, 0.0]))
    (d / "times.txt").write_text("".join(f"{0.1 * k:.6f}\n" for k in range(N_FRAMES)))
    return d


@pytest.fixture
def frames(frames_src, tmp_path):
    return copy_tree(frames_src, tmp_path / "frames")


def _times(d: Path, text: str) -> Path:
    (d / "times.txt").write_text(text)
    return d


def _tiny_frames(d: Path) -> Path:
    from minegeo.io import PointCloud, write_point_cloud

    for p in sorted(d.glob("*.ply")):
        write_point_cloud(p, PointCloud(points=np.zeros((5, 3))))
    return d


def _garbage_frames(d: Path) -> Path:
    for p in sorted(d.glob("*.ply")):
        p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    return d


def _no_numbers(d: Path) -> Path:
    (d / "times.txt").unlink()
    for k, p in enumerate(sorted(d.glob("*.ply"))):
        p.rename(d / f"frame_{'abcd'[k]}.ply")
    return d


FRAMES_CASES = {
    "missing": lambda t, d: t / "nope",
    "a_file": lambda t, d: a_file(t),
    "empty_folder": lambda t, d: a_folder(t),
    "no_times": lambda t, d: _no_numbers(d),
    "times_not_increasing": lambda t, d: _times(d, "0.0\n0.1\n0.1\n0.3\n"),
    "times_nan": lambda t, d: _times(d, "0.0\nnan\n0.2\n0.3\n"),
    "times_inf": lambda t, d: _times(d, "0.0\n0.1\n0.2\ninf\n"),
    "times_count": lambda t, d: _times(d, "0.0\n0.1\n0.2\n"),
    "times_not_numbers": lambda t, d: _times(d, "0.0\n0.1\nzwei\n0.3\n"),
    # issue 27, case 11: strictly increasing and finite, but the keyframe interval overflows and the
    # trajectory file (|t| <= 1e20 s) could not be read back
    "times_near_float_max": lambda t, d: _times(d, "-1.7e308\n0\n1.7e308\n1.71e308\n"),
    "times_beyond_file_range": lambda t, d: _times(d, "1e21\n2e21\n3e21\n4e21\n"),
    "every_frame_too_small": lambda t, d: _tiny_frames(d),
    "every_frame_unreadable": lambda t, d: _garbage_frames(d),
}

EXPECT = {
    "times_near_float_max": "beyond",
    "times_beyond_file_range": "beyond",
    "every_frame_too_small": "none of the 4 frames can be used",
    "every_frame_unreadable": "none of the 4 frames can be used",
}


@pytest.mark.parametrize("case", sorted(FRAMES_CASES))
def test_bad_frames(case, frames, tmp_path, capsys):
    d = FRAMES_CASES[case](tmp_path, frames)
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", d, "--out", out], capsys, inputs=[d, frames], outputs=[out],
                      expect=EXPECT.get(case))


def _fifo(t: Path) -> Path:
    p = t / "times.fifo"
    os.mkfifo(p)
    return p


TIMES_CASES = {
    "missing": (lambda t: t / "nope.txt", "no such file"),
    "folder": (lambda t: a_folder(t), "is a folder"),
    "fifo": (_fifo, "not a regular file"),
    "char_device": (lambda t: Path("/dev/zero"), "not a regular file"),
}


@pytest.mark.parametrize("case", sorted(TIMES_CASES))
def test_bad_times_option(case, frames, tmp_path, capsys):
    make, expect = TIMES_CASES[case]
    times = make(tmp_path)
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", frames, "--times", times, "--out", out], capsys,
                      inputs=[frames, times], outputs=[out], expect=expect)


OPTION_CASES = {
    "voxel_0": ["--voxel", "0"],
    "voxel_nan": ["--voxel", "nan"],
    "max_distance_negative": ["--max-distance", "-1"],
    "max_distance_inf": ["--max-distance", "inf"],
    "keyframe_distance_0": ["--keyframe-distance", "0"],
    "keyframe_angle_0": ["--keyframe-angle", "0"],
    "keyframe_angle_above_180": ["--keyframe-angle", "200"],
    "keyframe_interval_negative": ["--keyframe-interval", "-10"],
    "loop_gap_0": ["--loop-gap", "0"],
    "loop_radius_nan": ["--loop-radius", "nan"],
    "loop_radius_not_below_gap": ["--loop-gap", "8", "--loop-radius", "8"],
    "map_voxel_0": ["--map-voxel", "0"],
    "seed_negative": ["--seed", "-1"],
    "seed_not_whole": ["--seed", "1.5"],
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", frames, "--out", out, *OPTION_CASES[case]], capsys,
                      inputs=[frames], outputs=[out])


def test_out_is_the_frames_folder(frames, tmp_path, capsys):
    assert_user_error("slam", ["--frames", frames, "--out", frames], capsys, inputs=[frames], outputs=[frames])


def test_out_is_a_file(frames, tmp_path, capsys):
    f = a_file(tmp_path, "out_file")
    assert_user_error("slam", ["--frames", frames, "--out", f], capsys, inputs=[frames, f], outputs=[f])


def test_an_earlier_result_survives_a_bad_run(frames, tmp_path, capsys):
    """An earlier ``slam`` result folder stays byte-identical when a later run into it fails."""
    from _contract import run_cli

    out = tmp_path / "out"
    code, _, lines = run_cli("slam", ["--frames", frames, "--out", out], capsys)
    assert code == 0 and (out / "result.json").is_file(), lines
    assert_user_error("slam", ["--frames", _times(frames, "0.0\n0.0\n0.2\n0.3\n"), "--out", out], capsys,
                      inputs=[frames], outputs=[out])


DESKEW_OPTION_CASES = {
    "no_deskew_with_deskew_iterations": ["--no-deskew", "--deskew-iterations", "1"],
    "deskew_iterations_2": ["--deskew-iterations", "2"],
    "deskew_iterations_not_whole": ["--deskew-iterations", "0.5"],
    "max_speed_0": ["--max-speed", "0"],
    "max_angular_rate_nan": ["--max-angular-rate", "nan"],
    "max_acceleration_negative": ["--max-acceleration", "-1"],
}


@pytest.mark.parametrize("case", sorted(DESKEW_OPTION_CASES))
def test_bad_deskew_or_motion_option(case, frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", frames, "--out", out, *DESKEW_OPTION_CASES[case]], capsys,
                      inputs=[frames], outputs=[out])


def test_no_deskew_on_frames_without_times_is_fine(frames, tmp_path, capsys):
    """``--no-deskew`` with frames that carry no per-point times is not a contradiction: it runs."""
    import json

    from _contract import run_cli

    out = tmp_path / "out"
    code, _, lines = run_cli("slam", ["--frames", frames, "--out", out, "--no-deskew"], capsys)
    assert code == 0, lines
    d = json.loads((out / "result.json").read_text())["result"]["deskew"]
    assert d["ran"] is False and d["enabled"] is False
