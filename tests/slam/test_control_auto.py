"""``ControlParams(drift_states="auto")`` (C6 of :mod:`minegeo.slam.control`): the likelihood-ratio
test of the graph with against without the drift states. Its statistic and degrees of freedom
against a dense twin (numpy inverse of the normal matrix assembled factor by factor), the choice
against ``scipy.stats.chi2`` on the two solutions solved apart, and the null distribution
``E[Δ] = f`` over seeded draws without a drift."""

from __future__ import annotations

import numpy as np
import pytest
from _control_common import CRS, OFFSET, biased_odometry, stations, truth
from scipy import stats

from minegeo.optim import Values
from minegeo.slam.control import (
    DRIFT_UNIT,
    ControlParams,
    DriftBetweenFactors,
    DriftWalkFactors,
    PositionFactors,
    apply_control,
)

ROLES = ["control", "check", "check", "control", "check", "check", "control"]


def _drive(n, dt, rng, scale=0.0, yaw_rate=0.0, sigma_rot=2e-5, sigma_trans=0.005):
    """A winding 20 m-per-keyframe chain (``truth(n, 20)``), keyframes ``dt`` s apart, its odometry
    ``Z = Z_true Exp(bias + noise)`` (noise per edge σ·√20 m, the bias not in the information), 7
    stations on keyframe times: ``(t, P, edges, Z, info, Stations)``."""
    t, T = truth(n, 20.0)
    t = t * dt
    edges, Z, info, P = biased_odometry(T, rng, sigma_rot * np.sqrt(20.0), sigma_trans * np.sqrt(20.0), scale, yaw_rate)
    times = t[np.linspace(0, n - 1, 7).round().astype(int)]
    st, _ = stations(t, T, times, ROLES, rng)
    return t, P, edges, Z, info, st


def _dense_H_and_objective(groups, values, n, d=9):
    """Dense ``H = Σ Jᵀ Ω J`` (n·d square) and ``H`` of the groups ``pseudo`` (the drift states' walk
    and prior), assembled factor by factor from each group's Jacobians, and ``Σ rᵀ Ω r``."""
    H = np.zeros((n * d, n * d))
    Hp = np.zeros_like(H)
    obj = 0.0
    for q, g in enumerate(groups):
        r, Js = g.linearize(values)
        for e in range(r.shape[0]):
            W = g.information[e]
            obj += float(r[e] @ W @ r[e])
            Jf = [np.pad(J[e], ((0, 0), (0, d - J.shape[2]))) for J in Js]
            for a, Ja in zip(g.variables[e], Jf, strict=True):
                for b, Jb in zip(g.variables[e], Jf, strict=True):
                    blk = Ja.T @ W @ Jb
                    H[a * d:(a + 1) * d, b * d:(b + 1) * d] += blk
                    if q >= 2:
                        Hp[a * d:(a + 1) * d, b * d:(b + 1) * d] += blk
    return H, Hp, obj


def test_statistic_and_drift_parameters_equal_a_dense_twin():
    """16 keyframes 10 s apart (the walk loose enough that its terms count), a 0.4 % scale and
    2e-4 rad/m yaw bias: ``objective`` is every factor's ``rᵀΩr`` (the prior included) and
    ``drift_parameters`` is ``3n − tr(H⁻¹ (H_walk + H_prior))`` with ``H⁻¹`` the dense inverse."""
    rng = np.random.default_rng(4)
    t, P, edges, Z, info, st = _drive(16, 10.0, rng, scale=0.004, yaw_rate=2e-4)
    p = ControlParams(drift_states=True, snooping=False)
    res = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, p)
    assert res.optimisation.status == "converged" and res.drift_states
    n, ctrl = t.size, st.is_control
    W = np.zeros((int(ctrl.sum()), 3, 3))
    W[:, 0, 0] = W[:, 1, 1] = st.sigma_h_m[ctrl] ** -2
    W[:, 2, 2] = st.sigma_v_m[ctrl] ** -2
    var = np.searchsorted(t, st.t_mid_s[ctrl])
    walk = np.stack([np.diag(DRIFT_UNIT**2 / (np.asarray(p.drift_walk) ** 2 * dt)) for dt in np.diff(t)])
    prior = np.diag((np.asarray(p.drift_prior) / DRIFT_UNIT) ** -2.0) / n
    groups = [DriftBetweenFactors(edges, Z, info, DRIFT_UNIT), PositionFactors(var, st.enh_local[ctrl], OFFSET, W),
              DriftWalkFactors(np.c_[np.arange(n - 1), np.arange(1, n)], walk),
              DriftWalkFactors(np.arange(n).reshape(-1, 1), np.tile(prior, (n, 1, 1)))]
    values = Values(res.poses, res.optimisation.values.vectors / DRIFT_UNIT)  # the optimiser's units
    H, Hp, obj = _dense_H_and_objective(groups, values, n)
    s = 1.0 / np.sqrt(np.diag(H))  # Jacobi scaling before the dense inverse
    Hinv = s[:, None] * np.linalg.inv(s[:, None] * H * s[None, :]) * s[None, :]
    f = 3 * n - float(np.trace(Hinv @ Hp))
    assert res.drift_parameters == pytest.approx(f, rel=1e-6)
    assert res.objective == pytest.approx(obj, rel=1e-8)
    assert 2.0 < f < 3.0 * n


@pytest.mark.parametrize(("bias", "expect"), [((0.005, 5e-5), True), ((0.0, 0.0), False)])
def test_auto_choice_is_the_likelihood_ratio_of_the_two_solutions(bias, expect):
    """Δ = objective without − objective with the drift states (two separate solves) against
    ``scipy.stats.chi2.ppf(0.95, f)``: "auto" takes the drift states exactly when Δ exceeds it, and
    returns the chosen solution bit for bit; the choice is recorded."""
    t, P, edges, Z, info, st = _drive(41, 10.0, np.random.default_rng(12), *bias)
    out = {d: apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(drift_states=d))
           for d in (False, True, "auto")}
    lr = out[False].objective - out[True].objective
    f = out[True].drift_parameters
    chosen = bool(lr > stats.chi2.ppf(0.95, f))
    assert chosen is expect
    a = out["auto"]
    assert a.drift_states is chosen
    np.testing.assert_array_equal(a.poses, out[chosen].poses)
    assert a.drift_choice["statistic"] == pytest.approx(lr, rel=1e-12) and a.drift_choice["dof"] == f
    assert a.drift_choice["chosen"] is chosen and out[True].drift_choice is None
    assert ("drift states (C4) added by the likelihood-ratio test" in a.keyframe_note) is chosen


def test_without_a_drift_the_statistic_averages_its_degrees_of_freedom():
    """30 draws of a 61-keyframe chain (1.2 km, keyframes 10 s apart), noise only: the mean of Δ is
    ``f`` (E[Δ] = f in the linearised model, see :func:`minegeo.slam.control.drift_states_test`)
    within 3 standard errors, and "auto" takes the drift states in at most 4 of the 30 (α = 0.05:
    1.5 expected; P(≥ 5) ≈ 2 %)."""
    lr, f = [], []
    for r in range(30):
        t, P, edges, Z, info, st = _drive(61, 10.0, np.random.default_rng([33, r]))
        a = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(drift_states=False, snooping=False))
        b = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(drift_states=True, snooping=False))
        lr.append(a.objective - b.objective)
        f.append(b.drift_parameters)
    lr, f = np.asarray(lr), np.asarray(f)
    se = lr.std(ddof=1) / np.sqrt(lr.size)
    assert abs(lr.mean() - f.mean()) <= 3.0 * se, (lr.mean(), f.mean(), se)
    assert int(np.sum(lr > stats.chi2.ppf(0.95, f))) <= 4
