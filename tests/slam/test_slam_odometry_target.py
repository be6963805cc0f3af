"""``minegeo slam --odometry auto|submap|frame``: what each frame registers to.

``auto`` (the default) registers a sensor stream (median frame interval up to 0.25 s) to the local
map of the last keyframes and a log of keyframes farther apart to the previous frame; the choice
and its reason are in result.json (``result.odometry_target``) and the parameters
(``parameters.odometry.frame_target``). Expected values: the median computed here by NumPy, and
the frame rates of the data written here (10 Hz and 2 Hz)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo.cli.slam import STREAM_INTERVAL_S, odometry_target


@given(st.lists(st.floats(1e-3, 5.0), min_size=1, max_size=40), st.floats(-1e3, 1e3))
@settings(max_examples=200, deadline=None)
def test_auto_takes_the_local_map_exactly_when_the_median_interval_is_a_streams(steps, t0):
    times = t0 + np.cumsum([0.0, *steps])
    med = float(np.median(np.diff(times)))
    assume(abs(med - STREAM_INTERVAL_S) > 1e-9)  # not on the boundary, where rounding of t0 + Σ decides
    target, why = odometry_target("auto", times.tolist())
    assert target == ("submap" if med <= STREAM_INTERVAL_S else "frame")
    assert why.startswith("auto: median frame interval")
    for choice in ("submap", "frame"):  # an explicit choice is taken as it is
        assert odometry_target(choice, times.tolist()) == (choice, f"--odometry {choice}")


@pytest.fixture(scope="module")
def stream(tmp_path_factory):
    """A 10 Hz vehicle stream of 12 sweeps (per-point times) and the same place at 2 Hz (every 5th
    sweep of 40), as frames folders."""
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.flight import NetworkWorld
    from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

    s = simulate_stream(StreamParams(preset="vehicle", duration_s=5.0, lidar_hz=10.0, azimuth_step_deg=1.5, seed=3))
    root = tmp_path_factory.mktemp("odometry_target")
    out = {}
    for name, ft in (("10hz", s.frame_times[10:22]), ("2hz", s.frame_times[5:45:5])):
        folder = root / name
        folder.mkdir()
        for k, (_t, P, tau, _ring) in enumerate(iter_sweeps(NetworkWorld(s.net), s.sensor, s.curve, ft, s.lidar_seed)):
            write_point_cloud(folder / f"{k:06d}.ply", PointCloud(points=P, attributes={"time": tau}))
        (folder / "times.txt").write_text("".join(f"{float(t)!r}\n" for t in ft))
        out[name] = folder
    return out


def _slam(frames, out, *extra) -> dict:
    from minegeo.cli import main

    assert main(["-q", "slam", "--frames", str(frames), "--out", str(out), "--no-planes", "--no-noise-removal",
                 *extra]) == 0
    return json.loads((out / "result.json").read_text())


@pytest.mark.parametrize(("name", "extra", "expected"), [("10hz", [], "submap"), ("2hz", [], "frame"),
                                                         ("10hz", ["--odometry", "frame"], "frame")])
def test_the_run_records_what_each_frame_registered_to(stream, tmp_path, name, extra, expected):
    res = _slam(stream[name], tmp_path / "out", *extra)
    assert res["parameters"]["odometry"]["frame_target"] == expected
    assert res["result"]["odometry_target"]["frame_target"] == expected
    assert res["result"]["odometry_target"]["chosen_by"].startswith("--odometry" if extra else "auto")
    assert res["result"]["failed_frames"] == 0
