"""Whole-map rival search before an ``ok`` (issue 15): exact twins are ``ambiguous``, ordinary scans stay ``ok``.

One exact-twin study world (:func:`minegeo.synth.study.make_study_world`, seed 3: level 0
copied 25 m below, map surveyed independently on both levels), the CLI's fast profile (with
``--levelled 3`` for levelled scans). The scans were chosen so that the old behaviour
(``rival=None``) is ``ok`` on each twin: the tests fail when the search is skipped.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from helpers import cli_localize_params

from minegeo.errors import InputError
from minegeo.localize import localize_scan, prepare_map
from minegeo.localize.correlative import CorrelativeParams, correlative_candidates
from minegeo.localize.pipeline import LocalizeParams, error_vs_truth
from minegeo.localize.prepared import prepare_cloud_features
from minegeo.localize.rivals import RivalParams, attitude, matched_support, rival_test

TOL_M = 0.10  # largest trajectory error of a placement that counts as "that place"




@pytest.fixture(scope="module")
def study():
    from minegeo.synth.study import make_study_world

    sw = make_study_world(None, twins="exact", seed=3)
    prep, lp_lev = cli_localize_params(True)
    _, lp_6 = cli_localize_params(False)
    pm = prepare_map(sw.map, prep)
    pm.build_indexes(lp_lev)
    scans = {
        # a 10 m twin, levelled: the old code said ok; the twin reaches the plane-fitness ratio
        "twin_levelled": sw.draw_scans(3, 10.0, "twin", levelled=True, seed=3)[2],
        # a 10 m twin, arbitrary rotation (6-DOF): the map covers the two levels differently, so only
        # the support-matched test sees the twin
        "twin_6dof": sw.draw_scans(1, 10.0, "twin", levelled=False, seed=3)[0],
        # an ordinary 20 m scan of the decline (no copy)
        "ordinary": sw.draw_scans(2, 20.0, "mapped", levelled=True, seed=3)[1],
    }
    return {"pm": pm, "lev": lp_lev, "6dof": lp_6, "scans": scans, "cache": {}}


def _run(study, name, on=True):
    key = (name, on)
    if key not in study["cache"]:
        sc = study["scans"][name]
        lp = study["6dof" if name == "twin_6dof" else "lev"]
        if not on:
            lp = dataclasses.replace(lp, rival=None)
        study["cache"][key] = localize_scan(study["pm"], sc.cloud, sc.trajectory, lp, seed=0)
    return study["cache"][key]


def _err(T, T_true, sc) -> float:
    pts = np.asarray(sc.trajectory.poses)[:, :3, 3]
    return error_vs_truth(np.asarray(T), T_true, pts)["max_point_error_m"]


def _check_twin_ambiguous(study, name):
    sc = study["scans"][name]
    assert sc.label == "twin" and len(sc.twins_T_map_scan) == 1
    before = _run(study, name, on=False)
    assert before.status == "ok", before.reason  # the coin flip of issue 15
    r = _run(study, name)
    assert r.status == "ambiguous", r.reason
    assert "whole-map rival search" in r.reason
    # both placements are listed as rejected candidates: the truth and its twin, each within TOL_M
    rc = r.to_dict()["rejected_candidates"]
    listed = [np.asarray(h["T_map_scan"]) for h in rc["hypotheses"]]
    assert min(_err(T, sc.T_map_scan, sc) for T in listed) < TOL_M
    assert min(_err(T, sc.twins_T_map_scan[0], sc) for T in listed) < TOL_M
    # the best rival is the other copy (the chosen placement is one of the two)
    rv = r.rival_search
    b = rv["best_rival"]
    chosen_is_truth = _err(r.T_map_scan, sc.T_map_scan, sc) < TOL_M
    other = sc.twins_T_map_scan[0] if chosen_is_truth else sc.T_map_scan
    assert _err(b["T_map_scan"], other, sc) < TOL_M, b
    assert abs(b["distance_to_chosen_m"] - 25.0) < 0.5
    assert rv["self_found"] and rv["covered"]
    return r, b, rv


def test_exact_twin_levelled_is_ambiguous_with_the_twin_listed(study):
    _, b, rv = _check_twin_ambiguous(study, "twin_levelled")
    assert b["test_passed"] == "plane fitness"
    assert b["margin"] <= 1.0 / rv["ambiguity_ratio"]


def test_exact_twin_6dof_is_ambiguous_by_the_support_matched_test(study):
    _, b, _ = _check_twin_ambiguous(study, "twin_6dof")
    # its plane fitness stays below the ratio (the map covers the copy less), but on the points
    # the map covers at both places it fits as well
    assert b["test_passed"] == "support-matched"
    assert b["matched_ratio"] >= 0.95 and b["common_fraction"] >= 0.5


def test_ordinary_scan_stays_ok_and_names_its_best_rival(study):
    sc = study["scans"]["ordinary"]
    r0, r = _run(study, "ordinary", on=False), _run(study, "ordinary")
    assert r0.status == "ok" and r.status == "ok", r.reason
    assert _err(r.T_map_scan, sc.T_map_scan, sc) < TOL_M
    # the search decides, it does not move the answer
    assert np.array_equal(r.T_map_scan, r0.T_map_scan)
    assert np.array_equal(r.covariance_6x6, r0.covariance_6x6)
    d = r.to_dict()["rival_search"]
    b = d["best_rival"]
    assert b is not None and "NOT a position" in b["note"]
    assert np.asarray(b["T_map_scan"]).shape == (4, 4)
    assert b["distance_to_chosen_m"] > r.params.ambiguity.distance_m
    assert math.isfinite(b["margin"]) and b["margin"] > 1.0 / r.params.ambiguity.ratio
    assert b["matched_ratio"] < d["params"]["matched_ratio"] and not b["test_passed"]
    assert d["margin"] == b["margin"] and d["self_found"] and "every floor anchor" in d["guarantee"]
    assert "best rival" in r.reason and "margin" in r.reason
    assert r.timings_s["rival_search"] > 0.0


def test_rival_search_is_deterministic(study):
    sc = study["scans"]["ordinary"]
    r1 = _run(study, "ordinary")
    r2 = localize_scan(study["pm"], sc.cloud, sc.trajectory, study["lev"], seed=0)
    d1, d2 = r1.to_dict(), r2.to_dict()
    for d in (d1, d2):  # wall-clock times are the only allowed difference
        d.pop("timings_s")
        if d["correlative"] is not None:
            d["correlative"].pop("timings_s")
    assert json.dumps(d1, sort_keys=True) == json.dumps(d2, sort_keys=True)
    assert d1["rival_search"]["candidates"]
    assert not [k for k in d1["rival_search"] if "time" in k]


def test_off_gives_the_previous_behaviour(study):
    for name in ("ordinary", "twin_levelled"):
        r = _run(study, name, on=False)
        assert r.rival_search is None and r.to_dict()["rival_search"] is None
        assert not [k for k in r.timings_s if k.startswith("rival_search")]
        assert not [h for h in r.hypotheses if h["source"].startswith("rival search")]
        assert "best rival" not in r.reason
    with pytest.raises(InputError, match="LocalizeParams.rival"):
        LocalizeParams(rival=1)
    with pytest.raises(InputError, match="matched_ratio"):
        RivalParams(matched_ratio=1.5)
    with pytest.raises(InputError, match="LocalizeParams.rival"):
        LocalizeParams(rival=CorrelativeParams())


def test_printout_and_report_show_the_rival(study):
    from minegeo.cli.localize import _rival_line
    from minegeo.report.localize_report import localize_report_html

    r = _run(study, "ordinary")
    line = _rival_line(r)
    assert "best rival (NOT a position; rejected" in line and "margin" in line
    html = localize_report_html(r, study["pm"])
    assert "Whole-map rival search" in html and "NOT a position" in html
    assert _rival_line(_run(study, "ordinary", on=False)) is None


def test_attitude_splits_tilt_and_heading():
    def rz(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def rx(a):
        c, s = math.cos(a), math.sin(a)
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])

    for psi, tilt in ((0.3, 0.0), (-2.0, 0.05), (1.0, 1.2)):
        R = rz(psi) @ rx(tilt)
        t, h = attitude(R)
        assert t == pytest.approx(math.degrees(tilt), abs=1e-9)
        if tilt < 1e-12:
            assert h == pytest.approx(math.degrees(psi), abs=1e-9)


def test_matched_support_and_rival_test():
    sup_a = np.array([1, 1, 1, 1, 0, 0], bool)
    on_a = np.array([1, 1, 1, 0, 0, 0], bool)
    sup_b = np.array([1, 1, 0, 1, 1, 1], bool)
    on_b = np.array([1, 1, 0, 0, 1, 1], bool)
    frac, ratio = matched_support((sup_a, on_a), (sup_b, on_b))
    assert frac == pytest.approx(3 / 6) and ratio == pytest.approx((2 / 3) / (2 / 3))
    p = RivalParams()
    assert rival_test(0.8, 0.75, 0.2, 0.5, 0.9, p) == "plane fitness"
    assert rival_test(0.8, 0.60, 0.6, 0.97, 0.9, p) == "support-matched"
    assert rival_test(0.8, 0.60, 0.4, 0.97, 0.9, p) == ""  # too little common support
    assert rival_test(0.8, 0.60, 0.6, 0.90, 0.9, p) == ""


def test_one_grid_pivot_equals_the_default_search(study):
    """``grid_references`` with the default reference point is the default search, bit for bit,
    and a witness adds only the coverage record."""
    pm, lp = study["pm"], study["lev"]
    sc = study["scans"]["ordinary"]
    D, Nd, _ = prepare_cloud_features(np.asarray(sc.cloud.points), lp.scan_voxel_size_m, None, lp.features)
    cp = CorrelativeParams(n_coarse=500, n_refine=40, n_candidates=8)
    occ = pm.occupancy(cp)
    kw = {"seed": 0, "refine_target": (pm.target_index(), pm.icp_points, pm.icp_normals)}
    a = correlative_candidates(occ, D, Nd, cp, **kw)
    b = correlative_candidates(occ, D, Nd, cp, grid_references=[(a.reference_point, None)], **kw)
    c = correlative_candidates(occ, D, Nd, cp, witness=a.candidates[0][0], **kw)
    assert len(a.candidates) == len(b.candidates) == len(c.candidates) > 0
    for x, y, z in zip(a.candidates, b.candidates, c.candidates, strict=True):
        assert np.array_equal(x[0], y[0]) and x[1] == y[1]
        assert np.array_equal(x[0], z[0]) and x[1] == z[1]
    assert a.coverage is None and c.coverage["grid_self_bin_rank"] is not None


def test_pivots_land_on_mapped_floor_and_spread_for_translations():
    """The first pivot (all headings) is the scan floor point that the chosen placement puts
    nearest to a floor anchor; the others (chosen heading +- 1 step) are spread over the floor."""
    from minegeo.localize.rivals import _pivots

    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(-10, 10, 400), rng.uniform(-2, 2, 400), np.zeros(400)])
    wall = np.column_stack([rng.uniform(-10, 10, 200), np.full(200, 2.5), rng.uniform(0, 4, 200)])
    Dr = np.vstack([floor, wall])
    Nr = np.vstack([np.tile([0.0, 0.0, 1.0], (400, 1)), np.tile([0.0, -1.0, 0.0], (200, 1))])
    t = np.array([100.0, 50.0, -3.0])
    anchors = np.array([[100.0 + 7.3, 50.2, -3.0], [300.0, 0.0, 0.0]])
    cp = CorrelativeParams()
    piv = _pivots(Dr, Nr, [0.0, 0.0], t, anchors, cp, 4, 1)
    assert len(piv) == 5
    q0, h0 = piv[0]
    assert h0 is None  # every heading
    best = floor[np.argmin(np.linalg.norm(floor + t - anchors[0], axis=1))]
    assert np.array_equal(q0, best)
    for q, h in piv[1:]:
        assert sorted(h.tolist()) == [0, 1, 119] and q[2] == 0.0
    # spread: every further pivot is far from the others (farthest-point order over a 20 m floor)
    xy = np.array([q[:2] for q, _ in piv])
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(5) * 1e9
    assert d.min() > 3.0
