"""Segmentation and Table 1 panel identification (options 1-6)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.mast import (
    TABLE1_OPTIONS,
    BeaconDesign,
    LineSegment,
    SegmentationParams,
    identify_panels,
    place_beacon,
    scan_to_xy,
    segment_scan,
    simulate_mast_scenario,
)
from minegeo.mast.segmentation import OPTION_IDENTIFIES


def _seg(p0, p1, start, end):
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    return LineSegment(start, end, 0.5 * (p0 + p1), u, p0, p1, float(np.linalg.norm(p1 - p0)), 0.0)


def _flags(a, b, W, p: SegmentationParams):
    qa, qb = np.linalg.norm(W[1] - W[0]), np.linalg.norm(W[2] - W[1])

    def ok(m, d):
        return (1 - p.length_short_fraction) * d - p.length_abs_tolerance_m <= m <= (
            1 + p.length_long_fraction) * d + p.length_abs_tolerance_m

    f = set()
    if ok(a.length_m, qa):
        f.add("p1")
    if ok(b.length_m, qb):
        f.add("p2")
    f.add("theta")  # the synthetic lines lie exactly on the panel lines
    c_design = np.linalg.norm(0.5 * (W[1] + W[2]) - 0.5 * (W[0] + W[1]))
    if abs(np.linalg.norm(b.centroid - a.centroid) - c_design) <= p.centroid_tolerance_fraction * c_design:
        f.add("c")
    return f


def test_table1_options_all_reachable_and_follow_the_table():
    beacon = place_beacon(BeaconDesign(1.2), "B1", (0.0, 0.0), 0.0, front="right")
    W = beacon.scan_order_vertices()
    p = SegmentationParams()
    rng = np.random.default_rng(3)
    seen = set()
    for _ in range(400):
        # lines lying on the first two panels (scan order), shortened / shifted along the panel
        a0, a1 = np.sort(rng.uniform(-0.2, 1.0, 2))
        b0, b1 = np.sort(rng.uniform(0.0, 1.3, 2))
        if a1 - a0 < 0.05 or b1 - b0 < 0.05:
            continue
        a = _seg(W[0] + a0 * (W[1] - W[0]), W[0] + a1 * (W[1] - W[0]), 0, 10)
        b = _seg(W[1] + b0 * (W[2] - W[1]), W[1] + b1 * (W[2] - W[1]), 10, 20)
        flags = _flags(a, b, W, p)
        expected = next((o for o in sorted(TABLE1_OPTIONS) if TABLE1_OPTIONS[o] <= flags), None)
        got = [m for m in identify_panels([a, b], [beacon], p) if m.panel_a == 0]
        if expected is None:
            assert not got
            continue
        assert len(got) == 1
        m = got[0]
        assert m.option == expected
        assert m.identified == OPTION_IDENTIFIES[expected]
        assert np.allclose(m.node, W[1], atol=1e-9)  # lines intersect at the shared panel edge
        seen.add(expected)
    assert seen == {1, 2, 3, 4, 5, 6}


def test_allowed_options_restrict_identification():
    beacon = place_beacon(BeaconDesign(1.2), "B1", (0.0, 0.0), 0.0, front="right")
    W = beacon.scan_order_vertices()
    a = _seg(W[0], W[1], 0, 10)
    b = _seg(W[1], W[2], 10, 20)
    full = identify_panels([a, b], [beacon])
    assert [m.option for m in full] == [1]
    only5 = identify_panels([a, b], [beacon], SegmentationParams(options=(5,)))
    assert [m.option for m in only5] == [5] and only5[0].identified == (True, False)
    with pytest.raises(InputError):
        SegmentationParams(options=(7,))


def test_deflection_sign_and_lengths_separate_beacons_and_panels():
    # B1 and B2 are mirror images on opposite walls: a (P1, P2) pair of B2 must not match B1
    sc = simulate_mast_scenario(0, position=4, beacon_length_m=2.0, sigma_range_m=0.0, wall_roughness_m=0.0)
    o = np.argsort(sc.scan.bearing_deg)
    b, r = sc.scan.bearing_deg[o], sc.scan.range_m[o]
    xy = scan_to_xy(b, r)
    segs = segment_scan(xy, r, b, 0.003)
    matches = identify_panels(segs, sc.beacons)
    labels = sc.hit_label[o]
    assert any(m.option == 1 for m in matches)
    for m in matches:
        for seg_i, panel, ident in ((m.seg_a, m.panel_a, m.identified[0]), (m.seg_b, m.panel_b, m.identified[1])):
            if not ident:
                continue
            s = segs[seg_i]
            true = np.bincount(labels[s.start : s.end + 1] + 2).argmax() - 2
            assert true == 3 * m.beacon_index + panel, (m.beacon_id, panel, true)


def test_segments_break_at_panel_edges_exact_scan():
    sc = simulate_mast_scenario(0, position=1, beacon_length_m=1.0, sigma_range_m=0.0, wall_roughness_m=0.0)
    o = np.argsort(sc.scan.bearing_deg)
    b, r = sc.scan.bearing_deg[o], sc.scan.range_m[o]
    xy = scan_to_xy(b, r)
    segs = segment_scan(xy, r, b, 0.003)
    labels = sc.hit_label[o]
    # every line is pure except possibly its shared node point
    for s in segs:
        lab = labels[s.start + 1 : s.end]
        if lab.size:
            assert np.unique(lab).size == 1
    assert all(s.n_points >= SegmentationParams().min_points for s in segs)
    assert math.isclose(np.linalg.norm(segs[0].direction), 1.0)
