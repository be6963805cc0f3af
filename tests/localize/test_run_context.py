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


def test_stage_seed_is_the_pass_seed_plus_the_declared_offset_and_refuses_undeclared_stages():
    from minegeo.localize.run_context import STAGE_SEEDS

    run = RunContext(seed=41)
    assert {s: run.stage_seed(s) for s in STAGE_SEEDS} == {s: 41 + k for s, k in STAGE_SEEDS.items()}
    with pytest.raises(KeyError):
        run.stage_seed("not a stage")


def test_every_stage_of_the_pass_takes_its_seed_through_stage_seed():
    """No stage module reads ``run.seed`` directly: the derivation lives in one table (STAGE_SEEDS)."""
    from pathlib import Path

    import minegeo.localize as loc

    here = Path(loc.__file__).parent
    direct = [f.name for f in sorted(here.glob("*.py")) if f.name != "run_context.py" and "run.seed" in f.read_text()]
    assert direct == []
    users = {f.name for f in here.glob("*.py") if "stage_seed(" in f.read_text()}
    assert {"hypotheses.py", "rival_check.py"} <= users
