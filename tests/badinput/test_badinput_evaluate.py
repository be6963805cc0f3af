"""``minegeo evaluate --est EST --gt GT --out DIR``: every user mistake is one line, exit 2, nothing
written, an earlier result folder untouched.

The readers' one check (minegeo.io.trajectory: times finite, within 1e20 s, strictly increasing;
proper rotations; non-zero unit quaternions), the option values (checked before any file is read),
the option combinations that contradict, and the matching rule of KITTI files (no times: same number
of poses, as ``evo_ape kitti``, or their times given with ``--est-times``/``--gt-times``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from _contract import (
    a_folder,
    assert_user_error,
    copy_tree,
    run_cli,
    stream_link,
    symlink_beside,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)

N = 50


@pytest.fixture(scope="module")
def trajs(tmp_path_factory):
    """gt/est as TUM and KITTI (50 poses, 10 Hz, a 49 m path), a 10-pose KITTI estimate, KITTI times files, the
    ground truth 1000 s later."""
    from minegeo.geometry.se3 import exp_so3
    from minegeo.io import Trajectory, write_trajectory

    d = tmp_path_factory.mktemp("trajs")
    rng = np.random.default_rng(27)
    P = np.tile(np.eye(4), (N, 1, 1))
    T = np.eye(4)
    for i in range(N):
        S = np.eye(4)
        S[:3, :3] = exp_so3(rng.normal(scale=0.1, size=3))
        S[:3, 3] = [1.0, 0.1 * rng.normal(), 0.05 * rng.normal()]
        T = T @ S
        P[i] = T
    E = P.copy()
    E[:, :3, 3] += rng.normal(scale=0.05, size=(N, 3))
    t = 100.0 + 0.1 * np.arange(N)
    write_trajectory(d / "gt.tum", Trajectory(t, P))
    write_trajectory(d / "est.tum", Trajectory(t, E))
    write_trajectory(d / "gt.kitti", Trajectory(np.arange(N, dtype=float), P))
    write_trajectory(d / "est.kitti", Trajectory(np.arange(N, dtype=float), E))
    write_trajectory(d / "est10.kitti", Trajectory(np.arange(10.0), E[:10]))
    write_trajectory(d / "gt_shifted.tum", Trajectory(t + 1000.0, P))
    (d / "gt_times.txt").write_text("".join(f"{v:.6f}\n" for v in t))
    (d / "est10_times.txt").write_text("".join(f"{v:.6f}\n" for v in t[:10]))
    return d


def _tum_edit(t: Path, d: Path, name: str, row: int, value: str) -> Path:
    """A copy of est.tum whose data row ``row`` is replaced by ``value``."""
    lines = (d / "est.tum").read_text().splitlines()
    lines[1 + row] = value
    return write_file(t, name, "\n".join(lines) + "\n")


def _kitti_reflection(t: Path, d: Path) -> Path:
    lines = (d / "est.kitti").read_text().splitlines()
    v = lines[5].split()
    v[0:3], v[4:7], v[8:11] = ["1", "0", "0"], ["0", "1", "0"], ["0", "0", "-1"]  # diag(1, 1, -1)
    lines[5] = " ".join(v)
    return write_file(t, "refl.kitti", "\n".join(lines) + "\n")


def _fifo(t: Path) -> Path:
    os.mkfifo(t / "pipe.tum")
    return t / "pipe.tum"


#: --est cases (the same reader reads --gt: a few of them are repeated there)
EST_CASES = {
    "missing": lambda t, d: t / "nope.tum",
    "folder": lambda t, d: a_folder(t),
    "empty": lambda t, d: write_file(t, "empty.tum", b""),
    "comments_only": lambda t, d: write_file(t, "c.tum", "# timestamp x y z qx qy qz qw\n"),
    "truncated": lambda t, d: truncated_copy(d / "est.tum", t / "half.tum"),
    "nan_row": lambda t, d: _tum_edit(t, d, "nan.tum", 3, "100.3 nan 0 0 0 0 0 1"),
    "inf_position": lambda t, d: _tum_edit(t, d, "inf.tum", 3, "100.3 inf 0 0 0 0 0 1"),
    "nan_time": lambda t, d: _tum_edit(t, d, "nant.tum", 3, "nan 0 0 0 0 0 0 1"),
    "duplicated_time": lambda t, d: _tum_edit(t, d, "dup.tum", 3, "100.2 0 0 0 0 0 0 1"),
    "decreasing_time": lambda t, d: _tum_edit(t, d, "dec.tum", 3, "99 0 0 0 0 0 0 1"),
    "huge_times": lambda t, d: write_file(t, "huge.tum", "".join(f"{v} 0 0 0 0 0 0 1\n" for v in
                                                           ("-1.7e308", "0", "1.7e308", "1.71e308"))),
    "time_1e400": lambda t, d: _tum_edit(t, d, "t400.tum", 3, "1e400 0 0 0 0 0 0 1"),
    "zero_quaternion": lambda t, d: _tum_edit(t, d, "q0.tum", 3, "100.3 0 0 0 0 0 0 0"),
    "quaternion_norm_2": lambda t, d: _tum_edit(t, d, "q2.tum", 3, "100.3 0 0 0 0 0 0 2"),
    "huge_quaternion": lambda t, d: _tum_edit(t, d, "qbig.tum", 3, "100.3 0 0 0 1e300 1e300 0 0"),
    "huge_position": lambda t, d: _tum_edit(t, d, "xbig.tum", 3, "100.3 1e300 0 0 0 0 0 1"),
    "wrong_columns": lambda t, d: _tum_edit(t, d, "cols.tum", 3, "100.3 0 0 0 0 0 1"),
    "reflection_kitti": lambda t, d: _kitti_reflection(t, d),
    "not_a_rotation_kitti": lambda t, d: write_file(t, "scaled.kitti", "2 0 0 0 0 2 0 0 0 0 2 0\n" * 3),
    "binary_junk": lambda t, d: write_file(t, "junk.tum", np.random.default_rng(5).integers(0, 256, 4096, np.uint8)
                                       .tobytes()),
    "non_utf8": lambda t, d: write_file(t, "latin1.tum", b"# \xe9\xff\n0 0 0 0 0 0 0 1\n1 \xe9 0 0 0 0 0 1\n"),
    "stream": lambda t, d: Path("/dev/zero"),
    "stream_behind_tum_name": lambda t, d: stream_link(t, "zero.tum"),
    "fifo": lambda t, d: _fifo(t),
}


@pytest.mark.parametrize("case", sorted(EST_CASES))
def test_bad_estimate(case, trajs, tmp_path, capsys):
    est = EST_CASES[case](tmp_path, trajs)
    out = tmp_path / "out"
    assert_user_error("evaluate", ["--est", est, "--gt", trajs / "gt.tum", "--out", out], capsys,
                      inputs=[est, trajs], outputs=[out])


@pytest.mark.parametrize("case", ["folder", "empty", "nan_row", "duplicated_time", "zero_quaternion", "huge_times",
                                  "reflection_kitti", "binary_junk", "stream"])
def test_bad_ground_truth(case, trajs, tmp_path, capsys):
    gt = EST_CASES[case](tmp_path, trajs)
    est = trajs / ("est.kitti" if case == "reflection_kitti" else "est.tum")
    out = tmp_path / "out"
    assert_user_error("evaluate", ["--est", est, "--gt", gt, "--out", out], capsys, inputs=[gt, trajs],
                      outputs=[out])


def test_reflection_is_named_with_its_line(trajs, tmp_path, capsys):
    """Issue 27 case 8: a KITTI rotation block diag(1, 1, -1) was evaluated (a 90 deg error, exit 0)."""
    est = _kitti_reflection(tmp_path, trajs)
    line = assert_user_error("evaluate", ["--est", est, "--gt", trajs / "gt.kitti", "--out", tmp_path / "out"], capsys,
                             inputs=[est, trajs], outputs=[tmp_path / "out"], expect="line 6: the rotation block is a "
                             "reflection")
    assert str(est) in line


def test_huge_times_are_refused_as_times(trajs, tmp_path, capsys):
    est = EST_CASES["huge_times"](tmp_path, trajs)
    assert_user_error("evaluate", ["--est", est, "--gt", trajs / "gt.tum", "--out", tmp_path / "out"], capsys,
                      inputs=[est, trajs], outputs=[tmp_path / "out"], expect="line 1: time -1.7e+308 s is not a time stamp")


#: option values, each refused before any file is read (a missing --gt shows it: its error would come first)
OPTION_CASES = {
    "delta_half_frame": (["--delta", "0.5"], "--delta 0.5: with --delta-unit frames"),
    "delta_inf": (["--delta", "inf"], "argument --delta"),
    "delta_nan": (["--delta", "nan"], "argument --delta"),
    "delta_0": (["--delta", "0"], "argument --delta"),
    "delta_negative": (["--delta", "-2"], "argument --delta"),
    "delta_huge_frames": (["--delta", "1e300"], "--delta 1e+300"),
    "delta_m_inf": (["--delta", "inf", "--delta-unit", "m"], "argument --delta"),
    "delta_m_negative": (["--delta", "-0.5", "--delta-unit", "m"], "argument --delta"),
    "delta_unit_unknown": (["--delta-unit", "km"], "argument --delta-unit"),
    "max_diff_0": (["--max-diff", "0"], "argument --max-diff"),
    "max_diff_negative": (["--max-diff", "-0.01"], "argument --max-diff"),
    "max_diff_nan": (["--max-diff", "nan"], "argument --max-diff"),
    "max_diff_inf": (["--max-diff", "inf"], "argument --max-diff"),
    "no_align_and_scale": (["--no-align", "--scale"], "--scale and --no-align contradict"),
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, trajs, tmp_path, capsys):
    extra, expect = OPTION_CASES[case]
    out = tmp_path / "out"
    assert_user_error("evaluate", ["--est", trajs / "est.tum", "--gt", tmp_path / "not_read.tum", "--out", out, *extra],
                      capsys, inputs=[trajs], outputs=[out], expect=expect)


def _times(t: Path, name: str, values) -> Path:
    return write_file(t, name, "".join(f"{v}\n" for v in values))


#: (argv after --out, expected text): how poses are matched
MATCH_CASES = {
    # issue 27 case 10: 10 KITTI poses against 50 were "matched" by index
    "kitti_lengths_differ": (lambda t, d: ["--est", d / "est10.kitti", "--gt", d / "gt.kitti"],
                             "holds 10 poses and"),
    "kitti_against_timed": (lambda t, d: ["--est", d / "est.kitti", "--gt", d / "gt.tum"], "--est-times"),
    "timed_against_kitti": (lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt.kitti"], "--gt-times"),
    "times_for_a_tum_file": (lambda t, d: ["--est", d / "est.tum", "--est-times", d / "gt_times.txt",
                                           "--gt", d / "gt.tum"], "with its own times"),
    "times_count_differs": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", d / "gt_times.txt",
                                          "--gt", d / "gt.tum"], "holds 50 times for 10 poses"),
    "times_folder": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", a_folder(t), "--gt", d / "gt.tum"],
                     "is a folder, not a times file"),
    "times_fifo": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", _fifo(t), "--gt", d / "gt.tum"],
                   "is a FIFO"),
    "times_device": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", Path("/dev/zero"), "--gt", d / "gt.tum"],
                     "is a character device"),
    "times_missing": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", t / "nope.txt", "--gt", d / "gt.tum"],
                      "no such file"),
    "times_decreasing": (lambda t, d: ["--est", d / "est10.kitti", "--est-times",
                                       _times(t, "dec.txt", [100.0, 100.1, 100.2, 100.1, *range(101, 107)]),
                                       "--gt", d / "gt.tum"], "line 4: time 100.100000 s is not after"),
    "times_huge": (lambda t, d: ["--est", d / "est10.kitti", "--est-times",
                                 _times(t, "huge.txt", ["-1.7e308", 0, "1.7e308", *range(1, 8)]),
                                 "--gt", d / "gt.tum"], "not a time stamp"),
    "times_nan": (lambda t, d: ["--est", d / "est10.kitti", "--est-times", _times(t, "nan.txt", [0, "nan", *range(2, 10)]),
                                "--gt", d / "gt.tum"], "line 2: 'nan'"),
    "times_junk": (lambda t, d: ["--est", d / "est10.kitti", "--est-times",
                                 write_file(t, "junk.txt", np.random.default_rng(6).integers(0, 256, 512, np.uint8).tobytes()),
                                 "--gt", d / "gt.tum"], "junk.txt"),
    "max_diff_for_kitti": (lambda t, d: ["--est", d / "est.kitti", "--gt", d / "gt.kitti", "--max-diff", "0.5"],
                           "--max-diff matches poses by time"),
    "no_common_times": (lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt_shifted.tum"], "match the ground truth"),
    "delta_beyond_the_path": (lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt.tum", "--delta", "100",
                                            "--delta-unit", "m"], "no pose pair is 100 m"),
    "delta_beyond_the_poses": (lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt.tum", "--delta", "50"],
                               "no pose pair is 50 frames"),
}


@pytest.mark.parametrize("case", sorted(MATCH_CASES))
def test_bad_matching(case, trajs, tmp_path, capsys):
    make, expect = MATCH_CASES[case]
    argv = make(tmp_path, trajs)
    out = tmp_path / "out"
    assert_user_error("evaluate", [*argv, "--out", out], capsys, inputs=[trajs, *argv[1::2]], outputs=[out],
                      expect=expect)


def test_kitti_runs_that_are_well_posed(trajs, tmp_path, capsys):
    """The same files, well posed: equal-length KITTI by index; KITTI with times by time."""
    code, out, err = run_cli("evaluate", ["--est", trajs / "est.kitti", "--gt", trajs / "gt.kitti",
                                          "--out", tmp_path / "a"], capsys)
    assert code == 0 and "matched 50 poses by index" in out, err
    code, out, err = run_cli("evaluate", ["--est", trajs / "est10.kitti", "--est-times", trajs / "est10_times.txt",
                                          "--gt", trajs / "gt.kitti", "--gt-times", trajs / "gt_times.txt",
                                          "--out", tmp_path / "b"], capsys)
    assert code == 0 and "matched 10 poses by time" in out, err


# ------------------------------------------------------------------------------------ outputs


OUT_CASES = {
    "out_is_the_estimate": lambda d: d / "est.tum",
    "out_symlink_to_gt": lambda d: symlink_beside(d / "gt.tum", "gt_link"),
    "out_contains_the_inputs": lambda d: d,
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, trajs, tmp_path, capsys):
    d = copy_tree(trajs, tmp_path / "work")
    out = OUT_CASES[case](d)
    assert_user_error("evaluate", ["--est", d / "est.tum", "--gt", d / "gt.tum", "--out", out], capsys,
                      inputs=[d], outputs=[out])


def test_out_locked_by_live_run(trajs, tmp_path, capsys):
    out = tmp_path / "out"
    write_lock(out, os.getpid(), "evaluate")
    assert_user_error("evaluate", ["--est", trajs / "est.tum", "--gt", trajs / "gt.tum", "--out", out], capsys,
                      inputs=[trajs], outputs=[out], expect="being written by")


@pytest.fixture(scope="module")
def earlier(trajs, tmp_path_factory):
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "out"
    assert main(["-q", "evaluate", "--est", str(trajs / "est.tum"), "--gt", str(trajs / "gt.tum"), "--out", str(d)]) == 0
    return d


FAILING_RUNS = {
    "reflection": lambda t, d: ["--est", _kitti_reflection(t, d), "--gt", d / "gt.kitti"],
    "kitti_lengths_differ": lambda t, d: ["--est", d / "est10.kitti", "--gt", d / "gt.kitti"],
    "duplicated_time": lambda t, d: ["--est", EST_CASES["duplicated_time"](t, d), "--gt", d / "gt.tum"],
    "delta_half_frame": lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt.tum", "--delta", "0.5"],
    "no_align_and_scale": lambda t, d: ["--est", d / "est.tum", "--gt", d / "gt.tum", "--no-align", "--scale"],
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, trajs, tmp_path, capsys):
    out = copy_tree(earlier, tmp_path / "out")
    before = tree_snapshot(out)
    argv = FAILING_RUNS[case](tmp_path, trajs)
    assert_user_error("evaluate", [*argv, "--out", out], capsys, inputs=[trajs, argv[1]], outputs=[out])
    assert tree_snapshot(out) == before
