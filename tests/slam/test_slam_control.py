"""Control stations in the pose graph (minegeo.slam.control): position factor, drift, check stations,
marginal covariances and their calibration, on small synthetic chains whose truth is known."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _control_common import CHI2_2_95, CRS, OFFSET, stations, truth

from minegeo.io.stations import Stations
from minegeo.kernels.lie import se3_exp, se3_inverse
from minegeo.optim import Values
from minegeo.slam.control import (
    ControlParams,
    PositionFactors,
    apply_control,
)


def _odometry(T, rng, sigma_rot=2e-4, sigma_trans=0.01, yaw_bias=0.0):
    k = T.shape[0]
    edges = np.c_[np.arange(k - 1), np.arange(1, k)]
    Z = np.empty((k - 1, 4, 4))
    sig = np.r_[np.full(3, sigma_rot), np.full(3, sigma_trans)]
    for e in range(k - 1):
        Z[e] = se3_inverse(T[e]) @ T[e + 1] @ se3_exp(rng.standard_normal(6) * sig + [0, 0, yaw_bias, 0, 0, 0])
    info = np.tile(np.diag(sig**-2.0), (k - 1, 1, 1))
    return edges, Z, info


def _chain(Z):
    P = np.tile(np.eye(4), (Z.shape[0] + 1, 1, 1))
    for e in range(Z.shape[0]):
        P[e + 1] = P[e] @ Z[e]
    return P


ROLES = ["control", "check", "check", "control", "check", "check", "control", "check", "check", "control"]
TIMES = np.array([0.5, 12.5, 24.5, 40.5, 52.5, 66.5, 80.5, 92.5, 104.5, 119.5])


def test_position_factor_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    T = np.stack([se3_exp(rng.standard_normal(6)) for _ in range(4)])
    f = PositionFactors([0, 3, 1], rng.standard_normal((3, 3)), OFFSET, np.tile(np.eye(3), (3, 1, 1)))
    _, (J,) = f.linearize(Values(T))
    Jn, h = np.zeros_like(J), 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        Tp = np.stack([P @ se3_exp(d) for P in T])
        Tm = np.stack([P @ se3_exp(-d) for P in T])
        Jn[:, :, k] = (f.residuals(Values(Tp)) - f.residuals(Values(Tm))) / (2 * h)
    np.testing.assert_allclose(J, Jn, atol=1e-8)


def _run(mode, st, t, P, edges, Z, info):
    return apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(mode=mode))


def test_graph_control_beats_rigid_fit_on_a_drifting_chain():
    t, T = truth()
    rng = np.random.default_rng(11)
    edges, Z, info = _odometry(T, rng, yaw_bias=2e-4)  # heading drift 0.1 rad/km, not in the information
    P = _chain(Z)
    st, true = stations(t, T, TIMES, ROLES, rng, OFFSET)
    chk = st.is_check
    err = {}
    for mode in ("rigid", "graph"):
        res = _run(mode, st, t, P, edges, Z, info)
        e = res.station_enh_local[chk] - true[chk]  # against the truth used to make the data
        err[mode] = np.sqrt(np.mean(e**2, axis=0))
    assert res.optimisation.status == "converged"
    # measured (seed 11): RMSE h rigid 0.245 m, graph 0.071 m; v 0.027 m and 0.033 m (no vertical drift)
    assert np.hypot(*err["graph"][:2]) < 0.5 * np.hypot(*err["rigid"][:2])
    assert np.hypot(*err["graph"][:2]) < 0.1 and err["graph"][2] < 0.06


def test_check_stations_never_influence_the_fit():
    t, T = truth()
    rng = np.random.default_rng(5)
    edges, Z, info = _odometry(T, rng)
    P = _chain(Z)
    st, _ = stations(t, T, TIMES, ROLES, rng, OFFSET)
    enh = st.enh_local.copy()
    enh[st.is_check] += [1.0, -2.0, 0.5]
    moved = Stations(ids=st.ids, t_start_s=st.t_start_s, t_end_s=st.t_end_s, enh_local=enh,
                     origin_enh=st.origin_enh, sigma_h_m=st.sigma_h_m, sigma_v_m=st.sigma_v_m, roles=st.roles,
                     crs=CRS)
    for mode in ("rigid", "graph"):
        a, b = _run(mode, st, t, P, edges, Z, info), _run(mode, moved, t, P, edges, Z, info)
        assert np.array_equal(a.poses, b.poses)
        assert np.array_equal(a.station_enh_local, b.station_enh_local)
        assert not np.array_equal(a.check.delta, b.check.delta)  # the check errors do see the move


def _dense_covariance(res, edges_all, Z_all, info_all, var_ctrl, target, W):
    """Naive twin: H = Σ Jᵀ Ω J with J by central differences of every residual over every
    variable (no block structure, no ordering), then a dense inverse."""
    from minegeo.optim import BetweenFactors

    poses = res.poses
    n = poses.shape[0]
    groups = [BetweenFactors(edges_all, Z_all, info_all), PositionFactors(var_ctrl, target, OFFSET, W)]

    def resid(Ps):
        return [g.residuals(Values(Ps)) for g in groups]

    r0 = resid(poses)
    H = np.zeros((6 * n, 6 * n))
    Js = [np.zeros(r.shape + (6 * n,)) for r in r0]
    h = 1e-6
    for v in range(n):
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            Pp, Pm = poses.copy(), poses.copy()
            Pp[v] = poses[v] @ se3_exp(d)
            Pm[v] = poses[v] @ se3_exp(-d)
            for J, rp, rm in zip(Js, resid(Pp), resid(Pm), strict=True):
                J[..., 6 * v + k] = (rp - rm) / (2 * h)
    for J, g in zip(Js, groups, strict=True):
        H += np.einsum("mai,mab,mbj->ij", J, g.information, J)
    return np.linalg.inv(H)


def test_marginal_covariances_equal_the_dense_inverse_on_a_small_graph():
    from minegeo.slam.control import _insert_stations

    t, T = truth(n=25)
    rng = np.random.default_rng(2)
    edges, Z, info = _odometry(T, rng)
    # a loop edge too, so the pattern is not a plain chain
    edges = np.r_[edges, [[2, 20]]]
    Z = np.r_[Z, (se3_inverse(T[2]) @ T[20])[None]]
    info = np.r_[info, info[:1]]
    P = _chain(Z[:-1])
    times = np.array([0.5, 6.5, 12.5, 17.5, 23.5])
    st, _ = stations(t, T, times, ["control", "check", "control", "check", "control"], rng, OFFSET)
    res = _run("graph", st, t, P, edges, Z, info)
    _, _, E2, Z2, O2, var, _ = _insert_stations(t, P, edges, Z, info, st.t_mid_s)
    ctrl = st.is_control
    W = np.zeros((3, 3, 3))
    W[:, 0, 0] = W[:, 1, 1] = st.sigma_h_m[ctrl] ** -2
    W[:, 2, 2] = st.sigma_v_m[ctrl] ** -2
    S = _dense_covariance(res, E2, Z2, O2, var[ctrl], st.enh_local[ctrl], W)
    n = res.poses.shape[0]
    dense = np.stack([S[6 * v:6 * v + 6, 6 * v:6 * v + 6] for v in range(n)])
    np.testing.assert_allclose(res.covariances, dense, rtol=2e-4, atol=1e-12 * np.abs(dense).max())


def test_95_percent_ellipses_at_check_stations_are_calibrated():
    """60 runs of a small chain (noise drawn from the graph's information, survey noise from the
    stations' sigmas): the true horizontal error of a check station lies inside its 95 % ellipse
    in 95 % of cases; 240 cases, binomial sd 1.4 %: accepted within 3.5 sd."""
    t, T = truth(n=61)
    times = np.array([0.5, 8.5, 16.5, 30.5, 38.5, 46.5, 59.5])
    roles = ["control", "check", "check", "control", "check", "check", "control"]
    inside, total = 0, 0
    for r in range(60):
        rng = np.random.default_rng([7, r])
        edges, Z, info = _odometry(T, rng, sigma_rot=5e-4, sigma_trans=0.02)
        st, true = stations(t, T, times, roles, rng, OFFSET)
        res = _run("graph", st, t, _chain(Z), edges, Z, info)
        chk = st.is_check
        e = (res.station_enh_local - true)[chk][:, :2]
        C = res.station_cov_enh[chk][:, :2, :2]
        inside += int((np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e) <= CHI2_2_95).sum())
        total += e.shape[0]
    cov = inside / total
    sd = np.sqrt(0.95 * 0.05 / total)
    assert abs(cov - 0.95) <= 3.5 * sd, f"coverage {cov:.3f} of {total}"


def test_too_few_control_stations_is_a_user_error():
    from minegeo.errors import InputError

    t, T = truth(n=30)
    rng = np.random.default_rng(1)
    edges, Z, info = _odometry(T, rng)
    st, _ = stations(t, T, np.array([2.5, 10.5, 20.5]), ["control", "check", "control"], rng, OFFSET)
    with pytest.raises(InputError, match="at least 3"):
        _run("graph", st, t, _chain(Z), edges, Z, info)


def test_a_blunder_in_one_control_station_is_flagged_and_named():
    """0.5 m added to the E of one control station (the issue's acceptance case, small chain): its
    w-test flags it by name; the others are not flagged; without the blunder nothing is flagged."""
    t, T = truth()
    rng = np.random.default_rng(11)
    edges, Z, info = _odometry(T, rng)
    P = _chain(Z)
    st, _ = stations(t, T, TIMES, ROLES, rng, OFFSET)
    clean = _run("graph", st, t, P, edges, Z, info)
    enh = st.enh_local.copy()
    enh[3, 0] += 0.5  # S03, a control station
    bad = Stations(ids=st.ids, t_start_s=st.t_start_s, t_end_s=st.t_end_s, enh_local=enh, origin_enh=st.origin_enh,
                   sigma_h_m=st.sigma_h_m, sigma_v_m=st.sigma_v_m, roles=st.roles, crs=CRS)
    res = _run("graph", bad, t, P, edges, Z, info)
    assert clean.stats.flagged_ids == ()
    assert res.stats.flagged_ids[:1] == ("S03",)
    assert res.status == "warning" and "S03" in res.reason
    from minegeo.slam.control import ControlStatus

    assert type(res.status) is ControlStatus  # a member, printed and serialised as "warning"


def test_station_on_a_keyframe_time_uses_that_keyframe_and_frames_follow_the_graph():
    """A station at a keyframe's time adds no variable; ControlResult.transform maps the graph's own
    map poses onto its CRS poses (the frames between follow the interpolated correction)."""
    from minegeo.slam.control import _insert_stations

    t, T = truth(n=40)
    rng = np.random.default_rng(4)
    edges, Z, info = _odometry(T, rng)
    P = _chain(Z)
    times = np.array([1.0, 10.5, 20.0, 30.5, 38.0])
    st, _ = stations(t, T, times, ["control", "check", "control", "check", "control"], rng, OFFSET)
    res = _run("graph", st, t, P, edges, Z, info)
    assert res.times_s.size == t.size + 2 and "2 station variable(s) inserted" in res.keyframe_note
    assert np.array_equal(res.times_s[res.station_var[[0, 2, 4]]], times[[0, 2, 4]])
    g_t, g_P = _insert_stations(t, P, edges, Z, info, st.t_mid_s)[:2]
    np.testing.assert_allclose(res.transform(g_t, g_P, g_t, g_P), res.poses, atol=1e-9)


def test_drift_between_factor_jacobians_match_finite_differences():
    from minegeo.slam.control import DriftBetweenFactors

    rng = np.random.default_rng(0)
    T = np.stack([se3_exp(rng.standard_normal(6)) for _ in range(3)])
    Z = np.stack([se3_exp(rng.standard_normal(6)) for _ in range(2)])
    f = DriftBetweenFactors([[0, 1], [2, 1]], Z, np.tile(np.eye(6), (2, 1, 1)))
    v = Values(T, rng.standard_normal((3, 3)) * [0.01, 1e-3, 1e-3])
    _, J = f.linearize(v)
    col, h = np.arange(3) * 9, 1e-6
    for slot in (0, 1):
        Jn = np.zeros((2, 6, 9))
        for e in range(2):
            for k in range(9):
                dp = np.zeros(27)
                dp[9 * f.variables[e, slot] + k] = h
                Jn[e, :, k] = (f.residuals(v.retract(col, dp))[e] - f.residuals(v.retract(col, -dp))[e]) / (2 * h)
        w = J[slot].shape[2]
        np.testing.assert_allclose(J[slot], Jn[:, :, :w], atol=1e-7)
        if w < 9:
            assert np.abs(Jn[:, :, w:]).max() < 1e-9  # the end pose's drift states do not enter


def test_drift_states_take_out_a_scale_and_heading_bias():
    """Odometry with 1 % scale and 1e-4 rad/m yaw bias (not in its information): control in the
    graph with drift states (C4) brings the check stations to the truth within 2 cm horizontally,
    the plain graph does not (measured RMSE h 1.1 cm vs 13.9 cm), and its states are the injected bias."""
    t, T = truth()
    rng = np.random.default_rng(11)
    edges, Z, info = _odometry(T, rng, sigma_rot=2e-5, sigma_trans=0.002)
    for e in range(Z.shape[0]):
        Zt = se3_inverse(T[e]) @ T[e + 1]
        Z[e] = Z[e] @ se3_exp(np.r_[0.0, 0.0, 1e-4 * np.linalg.norm(Zt[:3, 3]), 0.01 * Zt[:3, 3]])
    P = _chain(Z)
    st, true = stations(t, T, TIMES, ROLES, rng, OFFSET)
    err = {}
    for name, cp in (("graph", ControlParams()), ("drift", ControlParams(drift_states=True))):
        res = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, cp)
        e = (res.station_enh_local - true)[st.is_check]
        err[name] = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
        if name == "drift":
            beta = np.median(res.optimisation.values.vectors, axis=0)
    assert res.optimisation.status == "converged"
    assert err["drift"] < 0.02 < err["graph"]
    # the drift states recover the injected bias (measured 0.00988, 3e-6, 9.94e-5)
    assert abs(beta[0] - 0.01) < 1e-3 and abs(beta[1]) < 1e-5 and abs(beta[2] - 1e-4) < 1e-5


def test_redundant_odometry_edges_leave_the_station_tests_unchanged():
    """A graph whose odometry carries redundancy of its own (each edge given twice, as loop closures
    and extra edges add): the graph's redundancy exceeds the 3n of the control stations, and the
    stations' w-tests, residuals and check errors equal those of the equivalent graph (each edge once
    with twice the information), with a 0.5 m blunder flagged the same way."""
    t, T = truth()
    rng = np.random.default_rng(11)
    edges, Z, info = _odometry(T, rng)
    P = _chain(Z)
    st, _ = stations(t, T, TIMES, ROLES, rng, OFFSET)
    enh = st.enh_local.copy()
    enh[3, 0] += 0.5
    bad = replace(st, enh_local=enh)
    for s in (st, bad):
        twice = _run("graph", s, t, P, np.r_[edges, edges], np.r_[Z, Z], np.r_[info, info])
        once = _run("graph", s, t, P, edges, Z, 2.0 * info)
        assert twice.global_chi2.dof > 3 * 4  # the odometry's own redundancy (4 control stations)
        assert twice.stats.flagged_ids == once.stats.flagged_ids
        np.testing.assert_allclose(twice.stats.w, once.stats.w, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(twice.stats.v, once.stats.v, atol=1e-7)
        np.testing.assert_allclose(twice.check.delta, once.check.delta, atol=1e-7)
    assert twice.stats.flagged_ids[:1] == ("S03",)
