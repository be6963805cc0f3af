"""PWCV / CWC descriptors (issue 18): heading invariance, missing wall segments, completeness, stacking.

The synthetic network (:func:`minegeo.synth.intersections_network`) has three alike 4-way crossings
X1-X3 (roof 3.0 / 3.6 / 4.2 m), a T and a Y. Each property is also checked against a deliberately
broken similarity (no circular shift; no occlusion rule) to show the test would catch it.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import InputError
from minegeo.semantic import (
    DescriptorParams,
    build_knowledge_base,
    completeness,
    cwc,
    invariant_point,
    pwcv,
    similarity,
    stack_keyframes,
)
from minegeo.semantic import _kernels_skeleton as K
from minegeo.synth import intersections_network, network_cloud

SECTOR = 2.0 * np.pi / DescriptorParams().n_sectors


@pytest.fixture(scope="module")
def kb():
    net = intersections_network()
    kb = build_knowledge_base(network_cloud(net, seed=1).points)
    assert kb.status == "ok" and len(kb) == 5
    return kb


def _index(kb, xy):
    return int(np.argmin(np.hypot(*(kb.invariant_points[:, :2] - np.asarray(xy)).T)))


def _rotz(psi):
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _no_shift_similarity(a, b):
    """Broken on purpose: the Ruzicka score at shift 0 only (heading-dependent)."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    return float(np.minimum(a, b).sum() / np.maximum(a, b).sum())


@settings(max_examples=12, deadline=None)
@given(psi=st.floats(-np.pi, np.pi), which=st.sampled_from([(0.0, 0.0), (179.4, 0.0), (1.1, -53.0)]))
def test_heading_invariance(kb, psi, which):
    """The descriptors of a junction's cloud rotated by any yaw about its invariant point match the
    originals with similarity >= 0.99, and the recovered yaw is within one sector of the truth."""
    i = _index(kb, which)
    C = kb.invariant_points[i]
    Q = (kb.cloud(i) - C) @ _rotz(psi).T + C
    for desc, ref in ((pwcv(Q, C), kb.pwcv[i]), (cwc(Q, C), kb.cwc[i])):
        r = similarity(desc, ref)
        assert r.score >= 0.99
        assert abs(_wrap(r.yaw_rad - psi)) <= SECTOR + 1e-9
        assert abs(_wrap(r.shift * SECTOR - psi)) <= SECTOR + 1e-9
        assert similarity(desc, ref, occlusion=False).score >= 0.99


def test_broken_no_shift_fails_heading_invariance(kb):
    """Without the circular shift the rotated T (30 degrees) falls far below 0.99."""
    i = _index(kb, (179.4, 0.0))
    C = kb.invariant_points[i]
    Q = (kb.cloud(i) - C) @ _rotz(np.deg2rad(30.0)).T + C
    assert _no_shift_similarity(pwcv(Q, C), kb.pwcv[i]) < 0.8
    assert _no_shift_similarity(cwc(Q, C), kb.cwc[i]) < 0.8


def test_invariant_point_is_rotation_equivariant(kb):
    """The invariant point of the rotated walls is the rotated invariant point (to 2 cm)."""
    for i in range(len(kb)):
        C = kb.invariant_points[i]
        P = kb.cloud(i)
        h = P[:, 2] - C[2]
        W = P[(h > 0.4) & (h < 2.2), :2]
        c0, r0 = invariant_point(W, C[:2] + 0.7, 3.0)
        R = _rotz(1.0)[:2, :2]
        c1, r1 = invariant_point((W - C[:2]) @ R.T, np.array([0.5, -0.6]), 3.0)
        assert np.hypot(*(c0 - C[:2])) < 0.02
        assert np.hypot(*(c1 - R @ (c0 - C[:2]))) < 0.02
        assert abs(r0 - r1) < 0.01


def _occlude(P, C, start, frac):
    """Remove every point (any height, r > 1 m) in the bearing block from ``start`` that holds ``frac``
    of the wall-band points within 12 m: a missing wall segment (occlusion, a partial scan)."""
    d = P[:, :2] - C[:2]
    th = np.mod(np.arctan2(d[:, 1], d[:, 0]) - start, 2.0 * np.pi)
    r = np.hypot(d[:, 0], d[:, 1])
    h = P[:, 2] - C[2]
    wall = (h > 0.4) & (h < 2.2) & (r < 12.0) & (r > 1.0)
    width = np.sort(th[wall])[int(frac * wall.sum())]
    return P[~((th <= width) & (r > 1.0))]


@settings(max_examples=10, deadline=None)
@given(start=st.floats(0.0, 2.0 * np.pi), frac=st.floats(0.2, 0.3), psi=st.floats(-np.pi, np.pi))
def test_missing_wall_segments(kb, start, frac, psi):
    """20-30 % of the wall removed in one bearing block, then rotated: PWCV of the T and the Y, CWC of
    each crossing X1-X3 stay >= 0.8 with the true intersection and above every other one."""
    th = 0.8
    for xy, kind in (((179.4, 0.0), "pwcv"), ((1.1, -53.0), "pwcv"), ((0.0, 0.0), "cwc"), ((60.0, 0.0), "cwc"),
                     ((120.0, 0.0), "cwc")):
        i = _index(kb, xy)
        C = kb.invariant_points[i]
        Q = (_occlude(kb.cloud(i), C, start, frac) - C) @ _rotz(psi).T + C
        d = pwcv(Q, C) if kind == "pwcv" else cwc(Q, C)
        ref = kb.pwcv if kind == "pwcv" else kb.cwc
        s = np.array([similarity(d, ref[j]).score for j in range(len(kb))])
        assert s[i] >= th
        assert s[i] > np.delete(s, i).max()
        assert 0.5 < completeness(pwcv(Q, C), kb.pwcv[i]) < 0.95


def test_broken_no_occlusion_rule_fails_missing_walls(kb):
    """Without the occlusion rule (cells seen empty where the reference has a wall counted as
    mismatches) the occluded T falls below the 0.8 threshold."""
    i = _index(kb, (179.4, 0.0))
    C = kb.invariant_points[i]
    v = pwcv(_occlude(kb.cloud(i), C, 1.3, 0.25), C)
    assert similarity(v, kb.pwcv[i]).score >= 0.8
    assert similarity(v, kb.pwcv[i], occlusion=False).score < 0.8


def test_completeness_and_similarity_edges():
    a = np.zeros(360)
    a[10:100] = 0.5
    b = a.copy()
    b[200:250] = 0.3
    assert completeness(a, b) == pytest.approx(90 / 140)
    assert completeness(b, a) == 1.0            # capped
    assert completeness(a, np.zeros(360)) == 0.0
    assert similarity(np.zeros(360), b).score == 0.0   # nothing comparable
    r = similarity(np.roll(b, 37), b)
    assert r.score == pytest.approx(1.0) and r.shift == 37
    with pytest.raises(InputError):
        similarity(a, np.zeros(120))
    with pytest.raises(InputError):
        similarity(np.full(360, np.nan), b)
    with pytest.raises(InputError):
        pwcv(np.zeros((10, 3)), (0.0, 0.0, np.nan))
    with pytest.raises(InputError):
        pwcv(np.zeros((10, 2)), (0.0, 0.0, 0.0))


def test_shift_kernel_matches_numpy():
    rng = np.random.default_rng(3)
    a = np.where(rng.random((3, 40)) < 0.3, 0.0, rng.random((3, 40)))
    b = np.where(rng.random((3, 40)) < 0.3, 0.0, rng.random((3, 40)))
    out = np.empty(40)
    for occl in (False, True):
        K.shift_ruzicka(a, b, occl, out)
        for k in range(40):
            bk = np.roll(b, k, axis=1)
            m = ~((a == 0) & (bk > 0)) if occl else np.ones_like(a, bool)
            assert out[k] == pytest.approx(np.minimum(a, bk)[m].sum() / np.maximum(a, bk)[m].sum())
        assert K.ruzicka_frac(a, b, 7.0, occl) == pytest.approx(out[7])


def test_stack_keyframes_eq20():
    """[Liang2024 Eq. 20]: the union of the current keyframe and the transformed neighbours."""
    rng = np.random.default_rng(0)
    P0, P1 = rng.random((5, 3)), rng.random((4, 3))
    T = np.eye(4)
    T[:3, :3] = _rotz(0.4)
    T[:3, 3] = (1.0, 2.0, 0.5)
    D = stack_keyframes([P0, P1], [T])
    assert np.allclose(D[:5], P0) and np.allclose(D[5:], P1 @ T[:3, :3].T + T[:3, 3])
    with pytest.raises(InputError):
        stack_keyframes([P0, P1], [])
