"""``minegeo slam`` end to end on simulated VLP-16 frames: the contract's outputs, accuracy against the
truth, skipped frames, and bad folders (times missing, not increasing) as one clear error line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from minegeo.cli import main
from minegeo.io import PointCloud, read_trajectory, write_point_cloud
from minegeo.io.g2o import read_g2o
from minegeo.io.types import Trajectory
from minegeo.slam.evaluate import evaluate_trajectory


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    traj = make_trajectory(world, "drive", length_m=18.0, seed=5)
    ts = np.arange(0.0, traj.times_s[-1], 0.25)
    P = interpolate_poses(traj, ts)
    sensor = Velodyne16(azimuth_step_deg=0.4)
    d = tmp_path_factory.mktemp("frames")
    for k, T in enumerate(P):
        pts = simulate_scan(world, sensor, T, seed=k).points
        if k % 2:  # half the frames as KITTI .bin (float32 x, y, z, reflectance)
            rec = np.zeros((pts.shape[0], 4), "<f4")
            rec[:, :3] = pts
            rec.tofile(d / f"{k:06d}.bin")
        else:
            write_point_cloud(d / f"{k:06d}.ply", PointCloud(points=pts))
    (d / "times.txt").write_text("".join(f"{t + 1000.0:.6f}\n" for t in ts))
    truth = Trajectory(ts + 1000.0, np.einsum("ij,njk->nik", np.linalg.inv(P[0]), P))
    return d, truth


def test_slam_writes_the_contract_outputs_and_follows_the_truth(sequence, tmp_path):
    frames, truth = sequence
    assert main(["-q", "slam", "--frames", str(frames), "--out", str(tmp_path / "o")]) == 0
    o = tmp_path / "o"
    for name in ("trajectory.tum", "keyframes.tum", "graph.g2o", "loops.csv", "map.ply", "result.json", "report.html"):
        assert (o / name).is_file(), name
    est = read_trajectory(o / "trajectory.tum")
    assert est.times_s.size == truth.times_s.size and np.array_equal(est.times_s, truth.times_s)
    assert np.allclose(est.poses[0], np.eye(4))  # the first frame is the map frame
    ev = evaluate_trajectory(est, truth, align=False)
    assert ev.ate.max < 0.01 * ev.path_length_m
    kf = read_trajectory(o / "keyframes.tum")
    g = read_g2o(o / "graph.g2o")
    assert g.n_vertices == kf.times_s.size and np.allclose(g.poses, kf.poses, atol=1e-9)
    rec = json.loads((o / "result.json").read_text())
    assert rec["result"]["frames"] == truth.times_s.size and rec["result"]["skipped_frames"] == []
    assert len(rec["provenance"]["inputs"]) == truth.times_s.size
    assert set(rec["module_timings_s"]) >= {"odometry", "loop_closure", "pose_graph", "map", "total"}
    assert (o / "loops.csv").read_text().startswith("i,j,fitness,rmse_m,accepted,reason")


def test_unreadable_and_empty_frames_are_skipped_and_reported(sequence, tmp_path):
    frames, truth = sequence
    d = tmp_path / "frames"
    d.mkdir()
    for p in frames.iterdir():
        (d / p.name).write_bytes(p.read_bytes())
    bad = sorted(d.glob("*.bin"))[2]
    bad.write_bytes(bad.read_bytes()[:-7])  # truncated mid-record
    empty = sorted(d.glob("*.ply"))[3]
    write_point_cloud(empty, PointCloud(points=np.zeros((5, 3))))
    assert main(["-q", "slam", "--frames", str(d), "--out", str(tmp_path / "o")]) == 0
    rec = json.loads((tmp_path / "o" / "result.json").read_text())
    skipped = {s["frame"]: s["reason"] for s in rec["result"]["skipped_frames"]}
    assert set(skipped) == {bad.name, empty.name}
    assert "16-byte" in skipped[bad.name] and "fewer than" in skipped[empty.name]
    assert read_trajectory(tmp_path / "o" / "trajectory.tum").times_s.size == truth.times_s.size - 2


def test_times_must_increase_and_must_exist(sequence, tmp_path, capsys):
    frames, _ = sequence
    d = tmp_path / "frames"
    d.mkdir()
    names = sorted(p.name for p in frames.iterdir() if p.name != "times.txt")[:4]
    for n in names:
        (d / n).write_bytes((frames / n).read_bytes())
    (d / "times.txt").write_text("1.0\n2.0\n2.0\n3.0\n")
    assert main(["slam", "--frames", str(d), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"frame {names[2]}: time 2.000000 s is not after the previous frame's" in err and "Traceback" not in err
    (d / "times.txt").unlink()
    for n in names:  # names like 000001.ply carry numbers: they become the times; rename to remove them
        (d / n).rename(d / ("frame_" + "abcdefgh"[names.index(n)] + (d / n).suffix))
    assert main(["slam", "--frames", str(d), "--out", str(tmp_path / "o")]) == 2
    assert "has no number in its name and there is no times.txt" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_times_file_elsewhere_pattern_and_frame_numbers(sequence, tmp_path, caplog):
    """The MulRan layout: scans next to pose text files, times in a file beside the folder."""
    from minegeo.io.frames import list_frames

    frames, truth = sequence
    d = tmp_path / "scans"
    d.mkdir()
    names = sorted(p.name for p in frames.iterdir() if p.suffix == ".ply")[:5]
    for n in names:
        (d / n).write_bytes((frames / n).read_bytes())
    (d / "odom_poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)  # not a frame
    (tmp_path / "t.txt").write_text("".join(f"{10.0 + k:.1f}\n" for k in range(5)))
    with pytest.raises(Exception, match=r"holds 5 times for 6 frames.*--pattern"):
        list_frames(d, times_file=tmp_path / "t.txt")
    got = list_frames(d, times_file=tmp_path / "t.txt", pattern="*.ply")
    assert [f.path.name for f in got] == names and [f.time_s for f in got] == [10.0, 11.0, 12.0, 13.0, 14.0]
    e = tmp_path / "numbered"
    e.mkdir()
    for k, n in enumerate(names):
        (e / f"{k:06d}.ply").write_bytes((frames / n).read_bytes())
    with caplog.at_level("WARNING", logger="minegeo.io.frames"):
        assert [f.time_s for f in list_frames(e)] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert "consecutive numbers from 0" in caplog.text and "--times" in caplog.text
    out = tmp_path / "o"
    assert main(["slam", "--frames", str(d), "--times", str(tmp_path / "t.txt"), "--pattern", "*.ply",
                 "--out", str(out), "--no-noise-removal"]) == 0
    res = json.loads((out / "result.json").read_text())
    assert res["result"]["times_from"] == "file" and res["result"]["frames"] == 5
    assert any(i["path"].endswith("t.txt") for i in res["provenance"]["inputs"])
    assert read_trajectory(out / "trajectory.tum").times_s[0] == 10.0


def _interrupt_in_a_kernel(*args, **kwargs):
    """What Numba does on Ctrl-C inside a compiled kernel: a SystemError with the interrupt as context."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:  # the SystemError's __context__ is the interrupt, as Numba's
        raise SystemError("CPUDispatcher(<function gicp_step_loop at 0x7f>) returned a result with an "  # noqa: B904
                          "exception set")


@pytest.mark.parametrize("how", ["numba", "python"])
def test_ctrl_c_is_one_line_exit_130_and_leaves_out_as_it_was(sequence, tmp_path, capsys, monkeypatch, how):
    """Issue 27, 7b: Ctrl-C inside a Numba kernel surfaces as ``SystemError`` (context KeyboardInterrupt);
    either way the run says ``minegeo slam: interrupted`` once, exits 130 and writes nothing."""
    from minegeo.slam import pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "run_slam", _interrupt_in_a_kernel if how == "numba" else interrupted)
    frames, _ = sequence
    before = sorted(p.name for p in tmp_path.iterdir())
    capsys.readouterr()
    assert main(["slam", "--frames", str(frames), "--out", str(tmp_path / "o")]) == 130
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == ["minegeo slam: interrupted"]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no OUT, no staging folder, no lock


def test_a_system_error_that_is_not_an_interrupt_stays_a_crash(sequence, tmp_path, monkeypatch):
    from minegeo.slam import pipeline

    def broken(*args, **kwargs):
        raise SystemError("something else")

    monkeypatch.setattr(pipeline, "run_slam", broken)
    frames, _ = sequence
    with pytest.raises(SystemError, match="something else"):
        main(["slam", "--frames", str(frames), "--out", str(tmp_path / "o")])


def test_an_internal_invariant_is_reported_as_a_bug_exit_3(sequence, tmp_path, capsys, monkeypatch):
    """A violated internal invariant is a bug: exit 3, one line that says so and asks for a report,
    never "error:" (the user's mistake, exit 2); nothing is written."""
    from minegeo.errors import InternalError
    from minegeo.slam import pipeline

    def bug(*args, **kwargs):
        raise InternalError("T_init: an internal transform has left SE(3)")

    monkeypatch.setattr(pipeline, "run_slam", bug)
    frames, _ = sequence
    capsys.readouterr()
    assert main(["slam", "--frames", str(frames), "--out", str(tmp_path / "o")]) == 3
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("minegeo slam: internal error (a bug in minegeo")
    assert "please report it" in err[0] and "left SE(3)" in err[0]
    assert not (tmp_path / "o").exists()


def test_long_fast_rotating_walk_keeps_every_pose_on_se3(tmp_path):
    """A short run of the issue-27 stress sequence (handheld sway +-15-25 deg at 0.5-1.5 Hz, motion-
    distorted sweeps, 3.2 m drifts) through the CLI: it completes and its trajectory reads back
    with every rotation orthonormal to rounding."""
    from minegeo.geometry.se3 import orthonormality_error
    from minegeo.synth.sequence import write_frames
    from minegeo.synth.sequence_sway import SwayWalkParams, sway_walk

    truth, frames, _ = sway_walk(SwayWalkParams(n_frames=40, azimuth_step_deg=2.0, seed=3))
    write_frames(tmp_path / "f", truth.times_s, frames)
    assert main(["-q", "slam", "--frames", str(tmp_path / "f"), "--out", str(tmp_path / "o")]) == 0
    est = read_trajectory(tmp_path / "o" / "trajectory.tum")
    assert est.times_s.size == 40
    assert max(orthonormality_error(T) for T in est.poses) < 1e-12
