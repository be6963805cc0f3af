"""RunContext: the stages' shared seed, progress, timings and warnings (minegeo.localize.run_context)."""

from __future__ import annotations

import pytest

from minegeo.localize.run_context import RunContext


def test_timed_announces_then_records_the_block_seconds_under_its_key():
    calls: list[str] = []
    run = RunContext(seed=3, progress=calls.append)
    with run.timed("ransac", "RANSAC"):
        assert calls == ["RANSAC"]  # announced when the step starts, before its work
        assert "ransac" not in run.timings
    assert calls == ["RANSAC"]
    assert set(run.timings) == {"ransac"} and run.timings["ransac"] >= 0.0


def test_timed_records_a_failed_stage_and_lets_its_error_through():
    run = RunContext(seed=0)  # no progress callback: nothing to call
    with pytest.raises(ZeroDivisionError):
        with run.timed("icp"):
            1 / 0  # noqa: B018
    assert "icp" in run.timings


def test_each_run_has_its_own_timings_and_warnings():
    a, b = RunContext(seed=1), RunContext(seed=1)
    a.timings["x"] = 1.0
    a.warnings.append("w")
    assert b.timings == {} and b.warnings == []
