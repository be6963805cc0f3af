"""Smooth walls and unlevelled scans (issue 15 items 2-3): the fine agreement tells smooth drifts
apart, and a failed 6-DOF scan is levelled by its own up direction and searched again.

One smooth-walled study world (:func:`minegeo.synth.study.make_study_world`, roughness 0.05 m,
seed 7, a survey frame every 2.5 m), the CLI's fast profile. The scans were chosen so that the
behaviour before (``verify.fine_tolerance_m=None`` / ``gravity_fallback=None``) is not ``ok``:
each test fails when its mechanism is switched off or broken.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import cli_localize_params

from minegeo.localize import localize_scan, prepare_map
from minegeo.localize.params import AmbiguityParams, VerifyParams
from minegeo.localize.pipeline import error_vs_truth
from minegeo.localize.rivals import RivalParams, matched_support, rival_test

TOL_M = 0.10




@pytest.fixture(scope="module")
def smooth():
    from minegeo.synth.study import make_study_world

    sw = make_study_world(0.05, twins="none", seed=7, map_passes=4)
    prep, lp_lev = cli_localize_params(True)
    _, lp_6 = cli_localize_params(False)
    pm = prepare_map(sw.map, prep)
    pm.build_indexes(lp_lev)
    return {"pm": pm, "lev": lp_lev, "6dof": lp_6, "sw": sw}


def _err(T, sc) -> float:
    pts = np.asarray(sc.trajectory.poses)[:, :3, 3]
    return error_vs_truth(np.asarray(T), sc.T_map_scan, pts)["max_point_error_m"]


def test_fine_agreement_tells_smooth_drifts_apart(smooth):
    """A 20 m levelled scan of a 0.05 m-rough drift: other drifts of the same cross-section agree
    with it within 0.1 m almost as well as the right one (ambiguous without the fine level), but
    not within 0.04 m."""
    sc = smooth["sw"].draw_scans(4, 20.0, "mapped", levelled=True, seed=7)[0]
    lp = smooth["lev"]
    before = localize_scan(smooth["pm"], sc.cloud, sc.trajectory,
                           dataclasses.replace(lp, verify=dataclasses.replace(lp.verify, fine_tolerance_m=None)), seed=0)
    assert before.status == "ambiguous", before.reason
    r = localize_scan(smooth["pm"], sc.cloud, sc.trajectory, lp, seed=0)
    assert r.status == "ok", r.reason
    assert _err(r.T_map_scan, sc) < TOL_M
    # the rival record carries both levels and the chosen placement wins clearly at the fine one
    rv = r.rival_search
    assert rv is not None and 0 < rv["fine_tolerance_m"] < rv["chosen_plane_fitness"] + 1.0
    assert rv["fine_tolerance_m"] <= r.plane_tolerance_m
    b = rv["best_rival"]
    if b is not None and b["score_level"] == "full":
        assert b["fine_fitness"] < rv["fine_ambiguity_ratio"] * rv["chosen_fine_fitness"]


def test_gravity_fallback_levels_a_failed_6dof_scan(smooth):
    """An unlevelled 10 m scan whose 6-DOF RANSAC is starved (one iteration): failed without the
    fallback; with it, levelled by its own up estimate and placed correctly, the answer in the
    original scan frame (placed trajectory and T_map_scan both right)."""
    sc = smooth["sw"].draw_scans(2, 10.0, "mapped", levelled=False, seed=7)[1]
    lp = smooth["6dof"]
    starved = dataclasses.replace(lp, ransac=dataclasses.replace(lp.ransac, max_iterations=1))
    off = localize_scan(smooth["pm"], sc.cloud, sc.trajectory, dataclasses.replace(starved, gravity_fallback=None),
                        seed=0)
    assert off.status == "failed", off.reason
    assert off.gravity is None
    r = localize_scan(smooth["pm"], sc.cloud, sc.trajectory, starved, seed=0)
    assert r.status == "ok", (r.reason, r.gravity)
    assert _err(r.T_map_scan, sc) < TOL_M
    g = r.gravity
    assert g["status"] == "ok" and g["levelled_status"] == "ok"
    R = np.asarray(g["R_levelled_scan"])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    # R takes the estimated up onto z; the truth's up (row 3 of R_map_scan) is within the 95 % cone + tolerance
    up_true = np.asarray(sc.T_map_scan)[2, :3]
    up_est = np.asarray(g["up_scan"])
    assert np.degrees(np.arccos(np.clip(up_true @ (R.T @ np.array([0.0, 0.0, 1.0])), -1, 1))) < 20.0
    assert np.allclose(R @ up_est, [0, 0, 1], atol=1e-9)
    placed = np.asarray(r.trajectory_map.poses)[:, :3, 3]
    truth = np.einsum("ij,njk->nik", sc.T_map_scan, np.asarray(sc.trajectory.poses))[:, :3, 3]
    assert np.max(np.linalg.norm(placed - truth, axis=1)) < TOL_M
    # the hypotheses are in the original scan frame too: the chosen one is the answer before its
    # tight-gate polish (a few mm)
    assert np.allclose(np.asarray(r.hypotheses[0]["T_map_scan"]), r.T_map_scan, atol=0.01)
    assert any("levels the scan by its own up direction" in w for w in r.warnings)
    d = r.to_dict()
    assert d["gravity"]["levelled_status"] == "ok"


def test_rival_test_needs_both_levels():
    p = RivalParams()
    # coarse ratio reached, fine not: not a rival
    assert rival_test(0.9, 0.85, 0.2, 0.5, 0.9, p, chosen_fine_fitness=0.8, fine_fitness=0.5, fine_ratio=0.8) == ""
    # both reached: plane-fitness rival
    assert rival_test(0.9, 0.85, 0.2, 0.5, 0.9, p, chosen_fine_fitness=0.8, fine_fitness=0.7,
                      fine_ratio=0.8) == "plane fitness"
    # a rival better at the fine level is always a rival (the chosen placement is the doubtful one)
    assert rival_test(0.9, 0.85, 0.2, 0.5, 0.9, p, chosen_fine_fitness=0.5, fine_fitness=0.8,
                      fine_ratio=0.8) == "plane fitness"
    # without fine numbers: the old test
    assert rival_test(0.9, 0.85, 0.2, 0.5, 0.9, p) == "plane fitness"


def test_matched_support_fine_scale():
    sup = np.ones(10, bool)
    on_a = np.ones(10, bool)
    on_b = np.ones(10, bool)
    fine_a = np.ones(10, bool)
    fine_b = np.r_[np.ones(5, bool), np.zeros(5, bool)]
    # coarse identical, fine half: min(1, 1.125 * 0.5)
    frac, ratio = matched_support((sup, on_a, fine_a), (sup, on_b, fine_b), fine_scale=1.125)
    assert frac == 1.0 and ratio == pytest.approx(0.5625)
    # pre-checks (no fine_scale) ignore the fine level
    assert matched_support((sup, on_a, fine_a), (sup, on_b, fine_b))[1] == pytest.approx(1.0)


def test_fine_parameters_validated():
    from minegeo.errors import InputError

    with pytest.raises(InputError):
        VerifyParams(fine_tolerance_m=-0.1)
    with pytest.raises(InputError):
        AmbiguityParams(fine_ratio=1.5)
    with pytest.raises(InputError):
        VerifyParams(fine_noise_factor=float("nan"))
