"""Issue 30, acceptance: a 0.5 m blunder in one control station is flagged by its w-test and named in
the report; with it removed the check RMSE returns (≤ 5 cm horizontal and vertical).

Truth: the stop-and-go motion of a small ``minegeo synth --stream vehicle`` drive and its surveyed
stations (:func:`minegeo.synth.stream.simulate_stream`, :func:`~minegeo.synth.stream.stream_stations`:
no sweeps rendered), keyframes every 1 s of the true motion, odometry the true relative motion
perturbed per edge by the random walk its information states (written here, as in
``benchmarks/bench_control.py``), so the control solution's statistics hold under H0. The report text
is the "Survey control" section of ``report.html`` (``control_html`` of the ``control`` record).
"""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.io.stations import Stations
from minegeo.kernels.lie import se3_exp, se3_inverse
from minegeo.slam.control import ControlParams, apply_control

BLUNDER_M = 0.5
#: odometry random walk: rad/sqrt(m), m/sqrt(m) across and along the motion
SIG_ROT, SIG_ACROSS, SIG_ALONG = 2e-5, 0.002, 0.004


@pytest.fixture(scope="module")
def drive():
    from minegeo.synth.stream import StreamParams, simulate_stream, stream_stations

    st = simulate_stream(StreamParams(preset="vehicle", duration_s=125.0, station_spacing_m=18.0, control_every=2,
                                      seed=3))
    stations, truth = stream_stations(st)
    t = np.arange(st.frame_times[0], st.frame_times[-1] + 1e-9, 1.0)
    R, p = st.curve.rotation_position(t)
    T = np.tile(np.eye(4), (t.size, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, p
    rng = np.random.default_rng(30)
    k = t.size
    edges = np.c_[np.arange(k - 1), np.arange(1, k)]
    Z, info = np.empty((k - 1, 4, 4)), np.zeros((k - 1, 6, 6))
    for e in range(k - 1):
        Zt = se3_inverse(T[e]) @ T[e + 1]
        d = float(np.linalg.norm(Zt[:3, 3]))
        u = Zt[:3, 3] / d if d > 1e-9 else np.array([1.0, 0.0, 0.0])
        sa, sc = max(SIG_ALONG * np.sqrt(d), 1e-5), max(SIG_ACROSS * np.sqrt(d), 1e-5)
        C = np.zeros((6, 6))
        C[:3, :3] = max(SIG_ROT * np.sqrt(d), 1e-6) ** 2 * np.eye(3)
        C[3:, 3:] = sc**2 * np.eye(3) + (sa**2 - sc**2) * np.outer(u, u)
        Z[e] = Zt @ se3_exp(np.linalg.cholesky(C) @ rng.standard_normal(6))
        info[e] = np.linalg.inv(C)
    P = np.empty_like(T)
    P[0] = np.eye(4)
    for e in range(k - 1):
        P[e + 1] = P[e] @ Z[e]
    return {"t": t, "P": P, "edges": edges, "Z": Z, "info": info, "stations": stations, "crs": truth["crs"]}


def _solve(drive, stations):
    return apply_control(drive["t"], drive["P"], drive["edges"], drive["Z"], drive["info"], stations, np.zeros(3),
                         drive["crs"], ControlParams(mode="graph"))


def _with(st: Stations, keep=None, shift=None) -> Stations:
    """The stations ``keep`` (indices, default all), the E of station ``shift`` moved by the blunder."""
    keep = np.arange(len(st)) if keep is None else np.asarray(keep)
    enh = st.enh_local.copy()
    if shift is not None:
        enh[shift, 0] += BLUNDER_M
    return Stations(ids=[st.ids[i] for i in keep], t_start_s=st.t_start_s[keep], t_end_s=st.t_end_s[keep],
                    enh_local=enh[keep], origin_enh=st.origin_enh, sigma_h_m=st.sigma_h_m[keep],
                    sigma_v_m=st.sigma_v_m[keep], roles=[st.roles[i] for i in keep], crs=st.crs)


def _report(c, st) -> str:
    from minegeo.cli.slam import control_record
    from minegeo.report.slam_report import control_html

    return control_html(control_record(c, st, np.zeros(3), st.crs, "graph"), None)


def test_a_blunder_in_one_control_station_is_flagged_named_and_removing_it_restores_the_check_rmse(drive):
    st = drive["stations"]
    ctrl = np.flatnonzero(st.is_control)
    assert ctrl.size >= 4 and st.is_check.sum() >= 3  # one control can be dropped, 3 remain
    clean = _solve(drive, st)
    # H0: nothing flagged, the chi-square test passes, the check RMSE meets the acceptance's 5 cm
    assert clean.stats.flagged_ids == () and clean.status == "ok", clean.reason
    assert clean.check.rmse_horizontal <= 0.05 and clean.check.rmse_vertical <= 0.05
    assert "flagged control stations (w-test)</th><td>none" in _report(clean, st).replace("\n", "")
    b = int(ctrl[1])  # a control station inside the traverse
    bad_st = _with(st, shift=b)
    bad = _solve(drive, bad_st)
    bid = st.ids[b]
    # the w-test flags it first (largest |w|, in E); the stations tied to it may exceed 3.29 through it
    assert bad.stats.flagged_ids[0] == bid and bad.stats.flagged[0][1] == "E", bad.stats.flagged
    # data snooping names it, and it alone: withheld, no control station is flagged
    assert bad.blunders == (bid,) and bad.unresolved == (), (bad.blunders, bad.unresolved)
    assert bad.status == "warning" and f"suspected blunder(s) by data snooping (the most suspect withheld and " \
        f"re-adjusted, in turn): {bid};" in bad.reason
    html = _report(bad, bad_st)
    assert f"{bid} E w=" in html  # the flag row of the report: id, component, w
    assert f"suspected blunder(s) by data snooping (the most suspect withheld and re-adjusted, in turn): {bid};" in html
    assert bad.check.rmse_horizontal > 2.0 * clean.check.rmse_horizontal  # the blunder bends the map
    # the blundered station removed: nothing flagged, the check RMSE back within 5 cm
    removed = _solve(drive, _with(bad_st, keep=[i for i in range(len(st)) if i != b]))
    assert removed.stats.flagged_ids == () and removed.status == "ok", removed.reason
    assert removed.check.rmse_horizontal <= 0.05 and removed.check.rmse_vertical <= 0.05
