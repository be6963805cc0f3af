"""RANSAC options added for mine drifts: levelled-frames check, [Baek2022 Eq. 8] floor, K distinct hypotheses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.geometry.se3 import exp_so3, make_transform, transform_points
from minegeo.registration.ransac import RansacParams, hypothesis_distance, register_ransac


def _blob(rng, n=200):
    return rng.uniform(-4.0, 4.0, (n, 3)) * np.array([1.0, 0.8, 0.6])


def _case(rng, tilt_deg: float, n=200, outliers=0.5):
    """Source blob, target = G(source) + noise; correspondences with a fraction of wrong ones."""
    src = _blob(rng, n)
    yaw = rng.uniform(-math.pi, math.pi)
    R = exp_so3(np.array([0.0, 0.0, yaw]))
    if tilt_deg:
        R = exp_so3(np.radians(tilt_deg) * np.array([1.0, 0.0, 0.0])) @ R
    G = make_transform(R, rng.uniform(-10, 10, 3))
    tgt = transform_points(G, src) + 0.002 * rng.standard_normal((n, 3))
    j = np.arange(n)
    bad = rng.random(n) < outliers
    j[bad] = rng.integers(0, n, int(bad.sum()))
    corr = np.stack([np.arange(n), j], axis=1).astype(np.int64)
    return src, tgt, corr, G


def _params(**kw):
    base = {"distance_threshold_m": 0.05, "ransac_n": 3, "max_iterations": 20000, "max_validations": None}
    return RansacParams(**{**base, **kw})


def test_levelled_check_accepts_levelled_truth(rng):
    src, tgt, corr, G = _case(rng, tilt_deg=0.0)
    r = register_ransac(src, tgt, correspondences=corr, params=_params(max_tilt_deg=3.0), seed=1)
    d, a = hypothesis_distance(r.T_target_source, G, src.mean(axis=0))
    assert d < 0.01 and a < 0.1
    # every returned hypothesis respects the prior
    for T, _, _ in r.alternatives:
        assert math.degrees(math.acos(min(1.0, T[2, 2]))) <= 3.0 + 1e-9


def test_levelled_check_refuses_tilted_truth(rng):
    """A 20 deg tilt violates a 3 deg prior: the true pose can never be returned."""
    src, tgt, corr, G = _case(rng, tilt_deg=20.0)
    free = register_ransac(src, tgt, correspondences=corr, params=_params(), seed=1)
    assert hypothesis_distance(free.T_target_source, G, src.mean(axis=0))[0] < 0.01
    r = register_ransac(src, tgt, correspondences=corr, params=_params(max_tilt_deg=3.0), seed=1)
    assert r.n_tilt_rejected > 0
    if r.n_inliers > 0:
        assert math.degrees(math.acos(min(1.0, r.T_target_source[2, 2]))) <= 3.0 + 1e-9
        assert hypothesis_distance(r.T_target_source, G, src.mean(axis=0))[1] > 10.0


def test_min_iterations_floor(rng):
    src, tgt, corr, _ = _case(rng, tilt_deg=0.0, outliers=0.2)
    eq8 = register_ransac(src, tgt, correspondences=corr, params=_params(), seed=2)
    assert eq8.status == "converged" and eq8.iterations < 5000
    floor = register_ransac(src, tgt, correspondences=corr, params=_params(min_iterations=15000), seed=2)
    assert floor.iterations >= 15000
    np.testing.assert_allclose(floor.T_target_source, eq8.T_target_source, atol=1e-6)


def test_k_hypotheses_distinct_and_ordered(rng):
    # two copies of the target far apart: two equally good placements exist
    src, tgt, corr, G = _case(rng, tilt_deg=0.0, outliers=0.0)
    tgt2 = np.vstack([tgt, tgt + np.array([40.0, 0.0, 0.0])])
    corr2 = corr.copy()
    corr2[1::2, 1] += src.shape[0]
    p = _params(n_hypotheses=5, distance_threshold_m=0.05)
    r = register_ransac(src, tgt2, correspondences=corr2, params=p, seed=3)
    alts = r.alternatives
    assert 2 <= len(alts) <= 5
    np.testing.assert_array_equal(alts[0][0], r.T_target_source)
    c = src.mean(axis=0)
    for i in range(len(alts)):
        for k in range(i):
            d, a = hypothesis_distance(alts[i][0], alts[k][0], c)
            assert d > p.distinct_distance or a > p.distinct_angle_deg
    # both copies are found among the hypotheses
    G2 = G.copy()
    G2[0, 3] += 40.0
    assert any(hypothesis_distance(T, G, c)[0] < 0.05 for T, _, _ in alts)
    assert any(hypothesis_distance(T, G2, c)[0] < 0.05 for T, _, _ in alts)
    # deterministic
    r2 = register_ransac(src, tgt2, correspondences=corr2, params=p, seed=3)
    for (Ta, fa, ea), (Tb, fb, eb) in zip(alts, r2.alternatives, strict=True):
        np.testing.assert_array_equal(Ta, Tb)
        assert fa == fb and ea == eb


@pytest.mark.parametrize("kw", [{"max_tilt_deg": 0.0}, {"max_tilt_deg": -1.0}, {"min_iterations": -1},
                                {"n_hypotheses": 1}, {"n_hypotheses": 2.5}, {"min_iterations": True}])
def test_bad_options_are_typed_errors(kw):
    with pytest.raises(InputError):
        RansacParams(**kw)


# ----------------------------------------------------------------------------- levelled (4-DOF) model


def test_yaw_fit_exact_and_matches_naive(rng):
    from minegeo.registration._kernels_ransac_levelled import yaw_fit

    P = rng.uniform(-5, 5, (7, 3))
    th = rng.uniform(-math.pi, math.pi)
    R = exp_so3(np.array([0.0, 0.0, th]))
    t = rng.uniform(-50, 50, 3)
    Q = P @ R.T + t
    T, spread = yaw_fit(np.ascontiguousarray(P), np.ascontiguousarray(Q))
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], t, atol=1e-9)
    # naive twin: brute-force yaw minimising the squared residuals
    Qn = Q + 0.05 * rng.standard_normal(Q.shape)
    T2, _ = yaw_fit(np.ascontiguousarray(P), np.ascontiguousarray(Qn))
    grid = np.linspace(-math.pi, math.pi, 72001)

    def cost(a):
        Ra = exp_so3(np.array([0.0, 0.0, a]))
        X = P @ Ra.T
        tt = (Qn - X).mean(axis=0)
        return float(np.sum((X + tt - Qn) ** 2))

    best = grid[int(np.argmin([cost(a) for a in grid]))]
    assert abs(math.atan2(T2[1, 0], T2[0, 0]) - best) < 2e-4
    assert spread > 0


def test_levelled_model_recovers_levelled_pose_with_two_point_samples(rng):
    src, tgt, corr, G = _case(rng, tilt_deg=0.0, outliers=0.9)
    p = _params(model="levelled", ransac_n=2, distance_threshold_m=0.05, max_iterations=20000)
    r = register_ransac(src, tgt, correspondences=corr, params=p, seed=4)
    d, a = hypothesis_distance(r.T_target_source, G, src.mean(axis=0))
    assert d < 0.01 and a < 0.05
    r2 = register_ransac(src, tgt, correspondences=corr, params=p, seed=4)
    np.testing.assert_array_equal(r.T_target_source, r2.T_target_source)
    # 90 % outliers: [Baek2022 Eq. 8] needs ~1/w^2 = 100x fewer draws than ~1/w^3 for the 3-point rigid model
    assert r.iterations < 5000


def test_levelled_model_validation():
    with pytest.raises(InputError):
        RansacParams(model="yaw")
    with pytest.raises(InputError):
        RansacParams(model="rigid", ransac_n=2)
    with pytest.raises(InputError):
        RansacParams(model="levelled", ransac_n=2, normal_angle_threshold_rad=0.5)
    assert RansacParams(model="levelled", ransac_n=2).ransac_n == 2
