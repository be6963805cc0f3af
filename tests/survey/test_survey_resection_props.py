"""Resection / intersection / trilateration, adjustment invariances and blunder detection."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import DegenerateGeometryError, TooFewPointsError
from minegeo.survey import (
    Datum,
    LSQOptions,
    Network,
    Observation,
    adjust_network,
    adjust_observations,
    read_network,
)
from minegeo.survey.resection import intersection_2d, resection_2d, trilateration_2d

GON = math.pi / 200


def test_resection_function_reproduces_ghilani_15_5():
    ctrl = {
        "P": (1303.599, 1458.615),
        "Q": (1636.436, 1310.468),
        "R": (1503.395, 888.362),
        "S": (1506.262, 785.061),
    }
    angles = [
        ("P", "Q", 33.8805555555556 * GON),
        ("Q", "R", 42.7873456790123 * GON),
        ("R", "S", 11.6657407407407 * GON),
    ]
    sig = [0.00154320987654321 * GON, 0.00185185185185185 * GON, 0.00185185185185185 * GON]
    r = resection_2d(ctrl, angles=angles, sigma_angle_rad=sig, station="U")  # no approximate position given
    assert (f"{r.e_m:.4f}", f"{r.n_m:.4f}") == ("999.9989", "1000.0253")
    assert (f"{r.se_m * 100:.3f}", f"{r.sn_m * 100:.3f}") == ("2.057", "4.268")
    assert r.status == "ok"


def test_intersection_function_reproduces_ghilani_15_4():
    ctrl = {"R": (865.40, 4527.15), "S": (2432.55, 2047.25), "T": (2865.22, 27.15)}
    ang = [
        ("R", "U", "S", 55.6820987654321),
        ("S", "R", "U", 112.792283950617),
        ("S", "U", "T", 109.653395061728),
        ("T", "S", "U", 65.8706790123457),
    ]
    r = intersection_2d(ctrl, angles=[(a, b, c, v * GON) for a, b, c, v in ang], sigma_angle_rad=0.001 * GON)
    assert (f"{r.e_m:.4f}", f"{r.n_m:.4f}") == ("6860.7260", "3727.4751")
    assert (f"{r.se_m * 100:.3f}", f"{r.sn_m * 100:.3f}") == ("37.817", "17.809")


def _station_setup(seed):
    rng = np.random.default_rng(seed)
    ctrl = {f"C{i}": tuple(rng.uniform(-500, 500, 2) + [2.5e6, 6.1e6]) for i in range(4)}
    P = np.array([2.5e6, 6.1e6]) + rng.uniform(-100, 100, 2)
    return ctrl, P


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.floats(0, 2 * math.pi - 1e-6))
def test_exact_observations_give_zero_residuals_and_exact_station(seed, orient):
    ctrl, P = _station_setup(seed)
    dirs = {k: (math.atan2(v[0] - P[0], v[1] - P[1]) - orient) % (2 * math.pi) for k, v in ctrl.items()}
    dist = {k: math.hypot(v[0] - P[0], v[1] - P[1]) for k, v in ctrl.items()}
    r = resection_2d(ctrl, directions=dirs, distances=dist, sigma_direction_rad=1e-5, sigma_distance_m=0.002)
    assert abs(r.e_m - P[0]) < 1e-6 and abs(r.n_m - P[1]) < 1e-6
    assert np.max(np.abs(r.network.lsq.v)) < 1e-8
    assert abs(((r.orientation_rad - orient + math.pi) % (2 * math.pi)) - math.pi) < 1e-9


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.floats(1e-3, 1e3))
def test_scaling_all_weights_leaves_adjustment_unchanged(seed, k):
    ctrl, P = _station_setup(seed)
    rng = np.random.default_rng(seed + 1)
    dirs = {
        c: (math.atan2(v[0] - P[0], v[1] - P[1]) + rng.normal(0, 1e-5)) % (2 * math.pi)
        for c, v in ctrl.items()
    }
    dist = {c: math.hypot(v[0] - P[0], v[1] - P[1]) + rng.normal(0, 0.002) for c, v in ctrl.items()}
    r1 = resection_2d(
        ctrl, directions=dirs, distances=dist, sigma_direction_rad=1e-5, sigma_distance_m=0.002, approx=P
    )
    r2 = resection_2d(
        ctrl,
        directions=dirs,
        distances=dist,
        sigma_direction_rad=1e-5 * k,
        sigma_distance_m=0.002 * k,
        approx=P,
    )
    assert abs(r1.e_m - r2.e_m) < 1e-7 and abs(r1.n_m - r2.n_m) < 1e-7
    np.testing.assert_allclose(r1.cov, r2.cov, rtol=1e-6)
    np.testing.assert_allclose(r1.network.lsq.v, r2.network.lsq.v, atol=1e-9)
    np.testing.assert_allclose(r1.network.lsq.tau, r2.network.lsq.tau, rtol=1e-6)
    np.testing.assert_allclose(r1.network.lsq.redundancy, r2.network.lsq.redundancy, atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 5))
def test_gross_error_is_caught_by_data_snooping(seed, which):
    # a well-redundant distance network: 6 known points, one unknown, 6 distances + 6 directions
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * math.pi, 7)[:-1] + rng.uniform(-0.2, 0.2, 6)
    ctrl = {f"K{i}": (1000 + 300 * math.sin(a), 2000 + 300 * math.cos(a)) for i, a in enumerate(ang)}
    P = np.array([1000.0, 2000.0]) + rng.uniform(-30, 30, 2)
    dist = {c: math.hypot(v[0] - P[0], v[1] - P[1]) + rng.normal(0, 0.002) for c, v in ctrl.items()}
    dirs = {
        c: (math.atan2(v[0] - P[0], v[1] - P[1]) + rng.normal(0, 5e-6)) % (2 * math.pi)
        for c, v in ctrl.items()
    }
    bad = f"K{which}"
    dist[bad] += 0.05  # 25 sigma blunder
    r = resection_2d(
        ctrl, directions=dirs, distances=dist, sigma_direction_rad=5e-6, sigma_distance_m=0.002, approx=P
    )
    lsq = r.network.lsq
    i = lsq.suspected_blunder()
    assert i is not None
    assert lsq.obs_names[i] == f"distance P-{bad}"
    assert "w-test" in lsq.flags[i]
    assert lsq.chi2.passed is False


def test_too_few_observations_and_collinear_control():
    ctrl = {"A": (0.0, 0.0), "B": (100.0, 0.0), "C": (200.0, 0.0)}
    with pytest.raises(TooFewPointsError):
        trilateration_2d(ctrl, {"A": 50.0}, sigma_distance_m=0.01)
    with pytest.raises(TooFewPointsError):
        resection_2d(ctrl, directions={"A": 0.1, "B": 0.5}, sigma_direction_rad=1e-5)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        trilateration_2d(
            ctrl,
            {"A": math.hypot(50, 40), "B": math.hypot(50, 40), "C": math.hypot(150, 40)},
            sigma_distance_m=0.01,
        )
    # fixed network with too few observations: typed error with a clear reason
    pts = {"A": {"x": 0.0, "y": 0.0}, "B": {"x": 100.0, "y": 0.0}, "U": {"x": 50.0, "y": 50.0}}
    net = Network(
        pts,
        Datum("fix", (("A", "x"), ("A", "y"), ("B", "x"), ("B", "y"))),
        [Observation("distance", "A", "U", 70.7, 0.01)],
        2,
    )
    with pytest.raises(TooFewPointsError, match="cannot determine"):
        adjust_network(net)
    # intersection with the target on the line through both stations: singular normal matrix
    pts = {"A": {"x": 0.0, "y": 0.0}, "B": {"x": 100.0, "y": 100.0}, "U": {"x": 200.0, "y": 200.0}}
    obs = [
        Observation("azimuth", "A", "U", math.pi / 4, 1e-5),
        Observation("azimuth", "B", "U", math.pi / 4, 1e-5),
    ]
    with pytest.raises(DegenerateGeometryError, match="singular"):
        adjust_network(Network(pts, Datum("fix", (("A", "x"), ("A", "y"), ("B", "x"), ("B", "y"))), obs, 2))


def test_apriori_variant_and_lsq_api():
    # line fit with known sigma: a-priori covariance uses sigma0 = 1, a-posteriori sigma0_hat
    x = np.linspace(0, 10, 11)
    rng = np.random.default_rng(0)
    y = 2.0 + 0.5 * x + rng.normal(0, 0.1, x.size)

    def model(p):
        return p[0] + p[1] * x, np.column_stack([np.ones_like(x), x])

    post = adjust_observations(model, [0.0, 0.0], y, sigmas=np.full(x.size, 0.1))
    prio = adjust_observations(
        model, [0.0, 0.0], y, sigmas=np.full(x.size, 0.1), options=LSQOptions(variance="apriori")
    )
    np.testing.assert_allclose(post.x, prio.x)
    np.testing.assert_allclose(post.Sigma_xx, post.sigma0_sq * prio.Sigma_xx, rtol=1e-10)
    assert post.dof == 9 and abs(sum(post.redundancy) - 9) < 1e-9
    B = np.column_stack([np.ones_like(x), x])
    np.testing.assert_allclose(post.x, np.linalg.lstsq(B, y, rcond=None)[0], atol=1e-12)
    assert post.chi2.lower < post.chi2.upper


def test_network_weight_scaling_on_published_example():
    base = shared_data("krumm_gama_adjustment_examples")
    net = read_network(base / "2D/Ghilani21_10_DistanceAngle_fix.dat")
    r1 = adjust_network(net)
    scaled = [
        Observation(
            o.kind,
            o.station,
            o.target,
            o.value,
            o.sigma * 7.0,
            o.backsight,
            o.set_id,
            o.hi,
            o.ht,
            o.unit,
            o.line,
        )
        for o in net.observations
    ]
    net2 = Network(net.points, net.datum, scaled, net.dim, net.known_azimuths)
    r2 = adjust_network(net2)
    for p in ("C", "D"):
        assert abs(r1.points[p].x - r2.points[p].x) < 1e-9
        assert abs(r1.points[p].sx_m - r2.points[p].sx_m) < 1e-12
    assert abs(r1.lsq.chi2.statistic / r2.lsq.chi2.statistic - 49.0) < 1e-6


def test_danger_circle_resection_is_refused():
    ctrl = {"A": (100.0, 0.0), "B": (0.0, 100.0), "C": (-100.0, 0.0)}
    P = (100 * math.cos(-1.0), 100 * math.sin(-1.0))  # on the circle through A, B, C
    dirs = {k: math.atan2(v[0] - P[0], v[1] - P[1]) % (2 * math.pi) for k, v in ctrl.items()}
    with pytest.raises(DegenerateGeometryError, match="danger circle"):
        resection_2d(ctrl, directions=dirs, sigma_direction_rad=1e-5)
