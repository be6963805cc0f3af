"""``track`` reports ``ok`` only on what it has checked (issue 29, deliverable 5 and the NIOSH acceptance:
"without the IMU the run ends without a runaway reported as ok").

* ``unchecked_stretches`` against a naive twin (hypothesis): a keyframe is unchecked when its path
  distance to every checked keyframe exceeds the limit.
* A hand-made 600 m odometry with one verified intersection near the start: the keyframes more than
  200 m of path from it and from the start pose form one stretch (bounds computed by hand), and the
  status is ``partial``, not ``ok``.
* A recognition 10 m away from where 20 m of odometry put the keyframe (a wrong recognition or a
  runaway): its factor fails the χ² test (3 degrees of freedom, p = 0.999: 16.27 from the table) after
  the optimisation and the status is ``inconsistent``; the same run with the recognition where the
  odometry puts it is ``ok``.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import minegeo.semantic.tracking as tracking
from minegeo.semantic.recognition import Recognition
from minegeo.semantic.tracking import TrackParams, track, unchecked_stretches
from minegeo.slam.odometry import OdometryResult

CHI2_3_0999 = 16.266  # χ² quantile, 3 degrees of freedom, p = 0.999 (statistical table)


def _naive(path, checked, limit):
    """Unchecked keyframes one by one, then their runs as (first, last)."""
    bad = [all(abs(s - path[c]) > limit for c in checked) for s in path]
    runs, k = [], 0
    while k < len(bad):
        if bad[k]:
            j = k
            while j + 1 < len(bad) and bad[j + 1]:
                j += 1
            runs.append((k, j))
            k = j + 1
        else:
            k += 1
    return runs


@settings(max_examples=60, deadline=None)
@given(steps=st.lists(st.floats(0.0, 50.0), min_size=1, max_size=40),
       checked=st.lists(st.integers(0, 40), max_size=5), limit=st.floats(1.0, 300.0))
def test_unchecked_stretches_equal_the_naive_twin(steps, checked, limit):
    path = np.r_[0.0, np.cumsum(steps)]
    checked = [c for c in checked if c < path.size]
    assume(all(abs(path[k] - path[c]) != limit for k in range(path.size) for c in checked))  # no tie at the limit
    kf = np.arange(path.size) * 2
    times = np.arange(2 * path.size) * 0.5
    got = unchecked_stretches(path, checked, limit, kf, times)
    assert [(s["first_keyframe"], s["last_keyframe"]) for s in got] == _naive(list(path), checked, limit)
    for s in got:
        assert s["first_frame"] == 2 * s["first_keyframe"] and s["last_time_s"] == times[2 * s["last_keyframe"]]
        assert s["path_m"] == pytest.approx(path[s["last_keyframe"]] - path[s["first_keyframe"]])


def _odometry(n: int, step_m: float = 2.0) -> OdometryResult:
    """``n`` keyframes ``step_m`` apart along x, every frame registered."""
    poses = np.stack([np.eye(4)] * n)
    poses[:, 0, 3] = step_m * np.arange(n)
    step = np.eye(4)
    step[0, 3] = step_m
    return OdometryResult(np.arange(n, dtype=float), poses, np.ones(n, bool), [""] * n, [""] * n, np.ones(n),
                          np.arange(n), np.stack([step] * (n - 1)), np.stack([np.eye(6) * 1e4] * (n - 1)),
                          [np.zeros((10, 3))] * n)


class _KB:
    """A one-intersection base at (20, 1, 0) (what the tracker reads of a base)."""

    status = "ok"
    invariant_points = np.array([[20.0, 1.0, 0.0]])

    def __len__(self):
        return 1


def _stub(monkeypatch, at: dict):
    """Recognition verified at the keyframes ``at`` (keyframe → offset of the world pose it claims, m)."""

    def recognise(cloud, hist, kb, rp, T_world_kf_pred=None, gate_m=None, gate_cov=None, state=None):
        k = len(recognise.calls)
        recognise.calls.append(k)
        if k not in at:
            return Recognition("none", "not here")
        T = T_world_kf_pred.copy()
        T[:3, 3] += at[k]
        return Recognition("verified", intersection_id=0, z_keyframe=np.linalg.solve(T, [20.0, 1.0, 0.0, 1.0])[:3],
                           completeness=1.0, T_world_keyframe_icp=T)

    recognise.calls = []
    monkeypatch.setattr(tracking, "recognise_keyframe", recognise)


def test_a_runaway_beyond_every_check_is_partial_not_ok(monkeypatch):
    _stub(monkeypatch, {10: np.zeros(3)})  # keyframe 10 at 20 m: one verified intersection
    res = track(None, _KB(), TrackParams(T_world_start=np.eye(4)), odometry=_odometry(300))
    assert res.n_optimisations == 1 and not res.inconsistent_factors
    # checks at 0 m (start) and 20 m; 200 m limit: keyframes beyond 220 m of path, 111 (222 m) .. 299 (598 m)
    (s,) = res.unchecked_stretches
    assert (s["first_keyframe"], s["last_keyframe"]) == (111, 299)
    assert s["path_m"] == pytest.approx(598.0 - 222.0) and s["max_path_from_check_m"] == pytest.approx(578.0)
    assert res.status == "partial" and "189 of 300 keyframes" in res.reason
    from minegeo.semantic.tracking import TrackStatus

    assert type(res.status) is TrackStatus and f"{res.status}" == "partial"  # a member, printed as its value
    assert res.summary()["unchecked_stretches"] == [s]


@pytest.mark.parametrize("offset_m, status", [(0.0, "ok"), (10.0, "inconsistent")])
def test_a_factor_the_odometry_contradicts_is_inconsistent(monkeypatch, offset_m, status):
    # keyframes 2 m apart over 58 m; verified at keyframe 5 (10 m) where the odometry puts it, and at
    # keyframe 15 (30 m) with the claimed pose ``offset_m`` across the drift
    _stub(monkeypatch, {5: np.zeros(3), 15: np.array([0.0, offset_m, 0.0])})
    res = track(None, _KB(), TrackParams(T_world_start=np.eye(4)), odometry=_odometry(30))
    assert res.n_optimisations == 2 and not res.unchecked_stretches
    assert res.status == status, res.reason
    if status == "inconsistent":
        assert 15 in [f["keyframe"] for f in res.inconsistent_factors]
        assert all(f["chi2"] > CHI2_3_0999 and f["chi2_limit"] == pytest.approx(CHI2_3_0999, abs=1e-3)
                   for f in res.inconsistent_factors)
        assert "keyframe" in res.reason and "not trusted" in res.reason
    else:
        assert not res.inconsistent_factors


def test_check_parameters_are_validated():
    from minegeo.errors import InputError

    for kw in ({"unchecked_path_m": 0.0}, {"unchecked_path_m": float("inf")}, {"factor_test_probability": 1.0}):
        with pytest.raises(InputError):
            TrackParams(**kw)
