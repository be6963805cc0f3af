"""Control and check stations in a SLAM result: rigid fit or position factors in the pose graph.

Frames: ``map`` (the SLAM world frame, first frame = origin), ``local`` (the CRS, ``E N H`` minus
the stations' recorded origin ``o``, a multiple of 1000 m, float64: ``E N H = local + o``).

Station point
-------------
Station ``k`` stands still on ``[t_start, t_end]``; its time is the middle ``t_k``. The point the
run puts on it is the sensor origin plus the offset ``a`` (``--station-offset``, sensor frame, m)::

    p_k = R(t_k) a + t(t_k)                                                             (C1)

with ``T(t_k) = (R, t)`` the sensor pose at ``t_k``, interpolated on SE(3) between the two
bracketing poses ``T_0``, ``T_1`` (times ``t_0 ≤ t_k ≤ t_1``): ``T = T_0 Exp(s Log(T_0⁻¹ T_1))``,
``s = (t_k − t_0)/(t_1 − t_0)``.

Modes
-----
``rigid``: :func:`minegeo.georef.georeference` fits ``T_local_map`` to the control stations' points
(C1) and their ``E N H``, with ``ControlParams.model``:

* ``"rigid"`` (6 parameters, ``s = 1``): every pose becomes ``T_local_map T``;
* ``"similarity"`` (7 parameters, ``T_local_map = [[s R, T], [0, 1]]``, the scale ``s`` estimated
  with its standard deviation, a posteriori: scaled by σ̂0): every point (pose position, station,
  map point) becomes ``p_local = s R p_map + T`` and every pose's rotation ``R R_map``. The scale takes
  out a constant odometry scale error and the grid's combined scale factor together (``s − 1`` in
  ppm in the result); it cannot take out a drift that grows along the traverse.

``graph``: every station (control and check) gets a pose variable at its time ``t_k`` in the
keyframe graph: the odometry edge ``(a, b)`` of the keyframes bracketing ``t_k`` (consecutive,
``b = a + 1``) is split into ``a → k → b`` with measurements ``Exp(s Log Z_ab)`` and
``Exp((1 − s) Log Z_ab)`` (their product is ``Z_ab``) and information ``Ω_ab / s`` and
``Ω_ab / (1 − s)`` (a random walk: the two halves' covariances add up to the edge's), ``s`` the
time fraction (several stations in one edge split it in time order). A control station adds the
position factor (:class:`PositionFactors`)::

    r_k = R_k a + t_k − p̄_k,      Ω_k = diag(σ_h⁻², σ_h⁻², σ_v⁻²)                    (C2)
    ∂r/∂φ = −R_k [a]ₓ,   ∂r/∂ρ = R_k      (right perturbation T ← T Exp(φ, ρ))

``p̄_k`` the surveyed ``E N H`` (local). The graph is solved by the one optimiser
(:func:`minegeo.optim.levenberg_marquardt`), started from the rigid fit of the control stations
(rigid model), no pose held: the position factors fix the gauge (≥ 3 control stations not on a
line). A check station's variable carries no factor of its coordinates: check stations never enter
the fit (moving one leaves the solution bit-identical).

With ``ControlParams(drift_states=True)`` every variable also carries drift states
``β = (s, p, y)`` (odometry scale error, pitch and yaw rate per metre) taken out of each odometry
measurement (:class:`DriftBetweenFactors`, C4), a random walk between consecutive variables
(``r = β_j − β_i``, information ``1/(σ_w² Δt)``, ``Δt`` the time between them) and a prior
``N(0, σ_p²)`` spread over the ``n`` variables (``Ω_p / n`` on each; :class:`DriftWalkFactors`):
a systematic drift that between factors alone cannot represent. Inside the optimiser the states are
held in units of :data:`DRIFT_UNIT` (numerical conditioning of the 9 × 9 blocks); every output is
in scale and rad/m. The walk σ_w (``ControlParams.drift_walk``) is sized so that what it lets the
drift do between two control stations stays below the odometry noise itself: over ``D`` m driven at
speed ``v`` (time ``τ = D/v``) a scale walk moves a point along the path by about
``σ_w,s √τ D/2`` and a yaw-rate walk across it by about ``σ_w,y √τ D²/6``, against the odometry's
``σ_along √D`` and ``σ_rot D^1.5/√3``.

``ControlParams(drift_states="auto")`` chooses between the two models by a likelihood-ratio test of
the data (C6, :func:`drift_states_test`): both graphs are solved, and the drift states are taken
when they lower ``vᵀPv`` by more than chance would with no drift::

    Δ = vᵀPv₀ − vᵀPv_β  >  χ²_f(1 − α),    f = 3n − tr(H⁻¹ H_walk) − tr(H⁻¹ H_prior)     (C6)

(``vᵀPv₀`` the plain graph's, ``vᵀPv_β`` the drift graph's, every factor with the walk and prior;
``f`` the number of drift parameters the data determine, ``H`` the drift graph's normal matrix, ``H⁻¹``
from the selected inverse (C3), whose pattern holds the cross covariances of the walk's neighbouring
variables; α = ``ControlParams.drift_alpha``, 0.05). With no drift both ``vᵀPv`` are quadratic forms
of the noise and ``E[Δ] = f`` in the linearised model (measured: mean 1.93 for f = 2.02 over 200
runs, Kolmogorov–Smirnov p = 0.88 against χ²(f), ``benchmarks/bench_control.py``). The plain
graph's own χ² test (:func:`drift_states_needed`) is not the choice: that omnibus test spreads its
degrees of freedom over misfits a drift cannot make and misses the benchmark's bias in 15 of 200 runs,
whose plain ellipses cover about 20 % (choosing by it, auto covers 89.8 %; by C6, 94.3 %). A model chosen by a test is not
calibrated for a drift near the test's detection limit (76 % coverage at 0.4 × that bias):
``ControlResult.uncertainty_note`` says so. The choice, ``Δ``, ``f`` and both σ̂0 are in
``ControlResult.drift_choice``, ``keyframe_note`` and ``drift_states``.

Uncertainty
-----------
The marginal covariance of every pose is the diagonal block of ``H⁻¹`` at the solution, computed by
the selected inverse (Takahashi recursion) on the block Cholesky factor ``H = L Lᵀ`` the optimiser
uses, in its fill-reducing order, never a dense inverse (:func:`selected_inverse`)::

    Σ_ij = −Σ_{s∈S_j} Σ_is L_sj L_jj⁻¹     (i ∈ S_j, the rows below j in column j of L)
    Σ_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_{s∈S_j} Σ_js L_sj L_jj⁻¹                                  (C3)

The covariance of a station point is ``J Σ_kk Jᵀ`` with ``J = [−R[a]ₓ, R]`` (C2), its 95 %
horizontal ellipse that of the E N block (:func:`minegeo.survey.ellipse.error_ellipse`).

Statistics (:mod:`minegeo.survey.control_stats`)
------------------------------------------------
Control residuals ``v_k = p_k − p̄_k`` (adjusted minus observed); their cofactors (graph)
``Qvv_k = Σll_k − J Σ_kk Jᵀ`` (exact per station, cross-station blocks not formed: the w-tests of
a diagonal ``P`` need only the diagonal); in rigid mode ``Qvv = Qll − A N⁻¹ Aᵀ`` of the rigid or
similarity fit (CS7, :func:`minegeo.survey.control_stats.fit_residual_cofactors`); redundancy ``r = 6·(edges) + 3·(controls) − 6·(variables)``
(graph; with drift states ``− 3 + Σ_i tr(Σ_βi Ω_p)/n`` and the prior's terms left out of ``vᵀPv``,
C5, see :func:`_solve_graph`) or ``3·controls − 6`` (rigid model) and ``3·controls − 7``
(similarity model) in rigid mode. σ̂0² and the χ² test are those of the
whole adjustment, ``vᵀPv = 2F`` (every factor of the graph; the control residuals only in rigid
mode). Check stations: errors and RMSE (CS4), class test against the nearest control (CS5), with
the 95 % relative ellipse when covariances are known, misclosure ratio ``1:N`` (CS6) with ``L`` the
path length from the nearest control station in time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, flag, group, one_of, validate
from minegeo.errors import ConvergenceError, InputError
from minegeo.kernels.lie import se3_inverse
from minegeo.optim import (
    BetweenFactors,
    FactorProblem,
    LMParams,
    Values,
    levenberg_marquardt,
)
from minegeo.slam.control_factors import (  # the factors and covariances, re-exported
    DriftBetweenFactors,
    DriftWalkFactors,
    PositionFactors,
    marginal_covariances,
    selected_inverse,
    station_jacobian,
    station_points,
)
from minegeo.slam.control_graph import (
    _insert_stations,
    check_control_geometry,
    check_map_geometry,
    check_station_statistics,
    graph_inputs,
    graph_pose_noise,
    interpolate_poses,
    slam_pose_noise,
    station_point_noise,
    variable_rates_deg_s,
)

__all__ = ["ControlParams", "ControlResult", "ControlStatus", "DriftBetweenFactors", "DriftWalkFactors", "PositionFactors",
           "apply_control", "check_control_geometry", "check_map_geometry", "check_station_frames", "drift_states_needed",
           "drift_states_test", "graph_inputs", "graph_pose_noise", "slam_pose_noise", "station_point_noise", "variable_rates_deg_s",
           "interpolate_poses", "marginal_covariances", "selected_inverse", "station_jacobian", "station_points"]

log = logging.getLogger(__name__)

MODES = ("rigid", "graph")
#: units of the drift states inside the optimiser: 10⁻² for the scale, 10⁻³ rad/m for the pitch and
#: yaw rates. The block Cholesky tests each 9 × 9 block's pivots against the block's largest diagonal
#: entry (``SINGULAR_PIVOT`` = 10⁻¹²), so the states' information must be of the order of the
#: pose's: in SI units the stiff walk (``1/(σ_w² Δt)`` ~ 10¹⁴ for σ_w = 10⁻⁷ rad/m/√s) dwarfed the
#: pose's translation and the undamped system was "singular" in the middle of a 500 m control gap
#: (tests/slam/test_control_drift.py); with the scale in 10⁻³ its pivot at a stop (no travel, no
#: scale information) fell below 10⁻¹² of the pose's rotation (~10⁸ rad⁻²) on a drive with control
#: every 100 m. Chosen so that both stay regular (an empirical conditioning choice; the results
#: do not depend on it)
DRIFT_UNIT = np.array([1e-2, 1e-3, 1e-3])
#: what the 95 % ellipses of graph mode are worth, per drift-state choice (``ControlResult.uncertainty_note``;
#: Monte Carlo of ``benchmarks/bench_control.py``, docs/survey.md "Control in the pose graph")
UNCERTAINTY_NOTES = {
    False: "ellipses from the odometry's stated noise alone: calibrated when the odometry has no systematic drift; "
           "a drift (scale, heading rate) makes them too small (drift states 'on' model it)",
    True: "ellipses with the drift states (C4): calibrated with and without a constant odometry drift in the "
          "Monte Carlo benchmark",
    "auto": "ellipses of a model chosen by a test of the data (C6): not calibrated for a drift near the test's "
            "detection limit (too small when a real drift is not detected); for ellipses and a class test that "
            "hold with or without a drift use drift states 'on'",
}


#: a station whose middle time lies between two frames further apart than this many times the
#: median frame interval (and whose still span holds no frame) falls in a gap of the trajectory
GAP_FACTOR = 3.0


def check_station_frames(stations, frame_times_s, what: str = "the frames") -> None:
    """Refuse a station the run's poses cannot place (``InputError``, naming the station and its line).

    * its still span ``[t_start, t_end]`` must lie inside ``[t_0, t_last]`` of the frame times;
    * **gap**: with ``t_a ≤ t_mid ≤ t_b`` the frames around the station's middle time, the station
      falls in a gap of the trajectory when no frame time lies in its still span and
      ``t_b − t_a > GAP_FACTOR · median(Δt)``: its pose (C1) would be interpolated across an
      interval in which the scanner was not observed, not measured while it stood on the station.

    Parameters
    ----------
    stations : minegeo.io.stations.Stations
    frame_times_s : (f,) s, increasing
        Times of the frames (listed, or used by the run).
    what : str
        How the frames are named in the message (``"the frames of --frames DIR"``).
    """
    ft = np.asarray(frame_times_s, dtype=np.float64).reshape(-1)
    if ft.size == 0:
        return
    stations.check_time_span(float(ft[0]), float(ft[-1]), what)
    if ft.size < 2:
        return
    dt = np.diff(ft)
    gap = GAP_FACTOR * float(np.median(dt))
    for i in np.argsort(stations.t_start_s, kind="stable"):
        t0, t1, tm = stations.t_start_s[i], stations.t_end_s[i], stations.t_mid_s[i]
        if np.any((ft >= t0) & (ft <= t1)):
            continue
        b = min(max(int(np.searchsorted(ft, tm, side="left")), 1), ft.size - 1)
        if ft[b] - ft[b - 1] > gap:
            raise InputError(
                f"{stations.source or 'stations'}: line {stations.lines[i]}: station {stations.ids[i]} at "
                f"{tm:.3f} s falls in a gap of the trajectory: no frame of {what} between {ft[b - 1]:.3f} and "
                f"{ft[b]:.3f} s ({ft[b] - ft[b - 1]:.3f} s; the frames are {np.median(dt):.3f} s apart), so its "
                "pose would be a guess across the gap (check the station times, or the frames missing there)")


@dataclass(frozen=True)
class ControlParams:
    """Parameters of :func:`apply_control`.

    Attributes
    ----------
    mode : {"rigid", "graph"}
    model : {"rigid", "similarity"}
        The fit of ``rigid`` mode: 6 parameters, or 7 with the scale estimated (``graph`` mode
        starts from a rigid placement; a similarity with drift states is refused).
    class_c : float
        ICSM SP1 class constant (mm), 50 = Class D.
    lm : LMParams
    drift_states : bool or "auto"
        Graph mode: estimate a systematic odometry drift (scale, pitch and yaw rate) per variable
        as a random walk (C4) besides the poses; "auto": only when they lower ``vᵀPv`` significantly
        (likelihood-ratio test at ``drift_alpha``, C6, :func:`drift_states_test`).
    drift_alpha : float
        Significance level of the "auto" choice (C6), in (0, 1).
    drift_prior : tuple of 3 float
        A-priori standard deviations of the drift states (scale, rad/m, rad/m): the datum of a
        constant drift, spread over the variables.
    drift_walk : tuple of 3 float
        Their random-walk standard deviations per √s of time between variables (scale/√s,
        rad/m/√s). The default (2·10⁻⁵, 10⁻⁷, 10⁻⁷) keeps the walk's effect over a 500 m control
        interval driven at 2 m/s at about half (0.35 along, 0.51 across) the odometry's own random walk of 0.01 m/√m along and
        2·10⁻⁵ rad/√m (module docstring); a walk 10× looser follows the odometry's noise (check
        errors 11-14 % larger without a bias, ellipses covering 100 %, tests/slam/test_control_drift.py).
    snooping : bool
        When a control station is flagged, name the suspected blunders by data snooping (the most
        suspect withheld and the adjustment repeated, in turn, while more than 3 remain).

    Each field but ``drift_states``, ``drift_prior`` and ``drift_walk`` (checked here) declares its
    rule in its metadata (:mod:`minegeo._params`; ``class_c``: ``minegeo slam --class-constant``).
    """

    mode: str = one_of("graph", MODES)
    model: str = one_of("rigid", ("rigid", "similarity"))
    class_c: float = bounded(50.0, gt=0.0)
    lm: LMParams = group(LMParams)
    drift_states: bool | str = False
    drift_prior: tuple = (0.02, 1e-4, 1e-4)
    drift_walk: tuple = (2e-5, 1e-7, 1e-7)
    drift_alpha: float = bounded(0.05, gt=0.0, lt=1.0)
    snooping: bool = flag(True)

    def __post_init__(self):
        validate(self)
        if self.drift_states not in (True, False, "auto"):
            raise InputError(f"drift_states must be True, False or 'auto', got {self.drift_states!r}")
        if self.model == "similarity" and self.mode != "rigid":
            raise InputError("the similarity model is a fit after SLAM (mode 'rigid'); the graph mode has no scale")
        if self.mode == "rigid" and self.drift_states is not False:
            raise InputError(f"drift_states {self.drift_states!r} needs the graph mode (drift states are variables of "
                             f"the pose graph; a {self.model} fit has none)")
        for name in ("drift_walk", "drift_prior"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v) & (v > 0)):
                raise InputError(f"{name} must be 3 positive numbers (scale, pitch, yaw), got {getattr(self, name)!r}")


class ControlStatus(StrEnum):
    """Status of a :class:`ControlResult` (each member is its string value)."""

    OK = "ok"
    WARNING = "warning"
    FAILED = "failed"


@dataclass(frozen=True)
class ControlResult:
    """Outcome of :func:`apply_control`.

    Attributes
    ----------
    mode, reason : str
    status : ControlStatus
        ``status`` "ok", "warning" (χ² test failed or a control flagged) or "failed" (the graph did
        not converge: the poses are the rigid fit's).
    origin_enh : (3,)
        Recorded origin ``o`` of the local CRS frame (m).
    times_s, poses : (k,), (k, 4, 4)
        Graph variables (keyframes and station variables, in time order), ``T_local_sensor``.
    station_var : (n,) int
        Variable of each station (graph mode) or -1 (rigid).
    station_enh_local : (n, 3)
        The run's point of every station (C1), local frame (m).
    station_cov_enh : (n, 3, 3) or None
        Its covariance (m², graph mode).
    covariances : (k, 6, 6) or None
        Marginal covariance of every variable (rotation first; rad², m²).
    T_local_map : (4, 4)
        The rigid (or similarity: top-left block ``s R``) fit of the control stations (graph mode:
        the starting placement).
    stats, check, classes : ControlStatistics, CheckErrors or None, ClassTest or None
    global_chi2 : Chi2Test
    misclosure_ratio : (n_check,)
    ellipses_check : list of ErrorEllipse
        95 % horizontal ellipses at the check stations (graph mode).
    keyframe_note : str
        How the station poses entered the graph.
    blunders : tuple of str
        Suspected blunders by data snooping (withheld in this order until no control station was
        flagged); the poses and statistics are those of the adjustment with every control station.
    unresolved : tuple of str
        Control stations still flagged when only 3 were left (snooping stopped).
    drift_states : bool
        Whether the solution carries the drift states (C4): ``ControlParams.drift_states`` True, or
        "auto" and the likelihood-ratio test took them (C6).
    objective : float
        ``vᵀPv`` of every factor of the solved graph, the drift prior included (``2F`` at the
        solution; graph mode): the statistic of C6. Without drift states it equals
        ``global_chi2.statistic``.
    drift_parameters : float
        With drift states: the number of drift parameters the data determine,
        ``f = 3n − tr(H⁻¹ H_walk) − tr(H⁻¹ H_prior)`` (C6); NaN without.
    uncertainty_note : str
        What the ellipses (and the class test's relative ellipses) are worth under the drift-state
        choice (:data:`UNCERTAINTY_NOTES`; graph mode, empty in rigid mode).
    drift_choice : dict or None
        "auto" only: the test of C6 (:func:`drift_states_test`): ``statistic`` Δ, ``dof`` f,
        ``critical`` χ²_f(1 − α), ``alpha``, ``p_value``, ``sigma0_without``/``sigma0_with`` and
        ``chosen``; also stated in :attr:`keyframe_note`.
    model : {"rigid", "similarity"}
        The fit of rigid mode (``ControlParams.model``; "rigid" in graph mode).
    scale, scale_std : float
        Similarity model: the estimated map-to-CRS scale ``s`` and its a-posteriori standard
        deviation (σ̂0-scaled, :attr:`minegeo.georef.GeorefResult.scale_std`); 1 and 0 otherwise.
    """

    mode: str
    status: ControlStatus
    reason: str
    origin_enh: np.ndarray
    times_s: np.ndarray
    poses: np.ndarray
    station_var: np.ndarray
    station_enh_local: np.ndarray
    station_cov_enh: np.ndarray | None
    covariances: np.ndarray | None
    T_local_map: np.ndarray
    stats: object
    check: object
    classes: object
    global_chi2: object
    misclosure_ratio: np.ndarray
    ellipses_check: list
    keyframe_note: str
    optimisation: object = None
    blunders: tuple = ()
    unresolved: tuple = ()
    drift_states: bool = False
    objective: float = float("nan")
    drift_parameters: float = float("nan")
    uncertainty_note: str = ""
    drift_choice: dict | None = None
    model: str = "rigid"
    scale: float = 1.0
    scale_std: float = 0.0

    @property
    def similarity(self) -> bool:
        """The result of a 7-parameter fit after SLAM (rigid mode, similarity model)."""
        return self.mode == "rigid" and self.model == "similarity"

    def transform(self, times_s: np.ndarray, poses_map: np.ndarray, graph_times_s: np.ndarray,
                  graph_poses_map: np.ndarray) -> np.ndarray:
        """Frames (times, ``T_map_sensor``) into the local CRS frame: each frame's correction
        ``C = T_local_var T_map_var⁻¹`` interpolated on SE(3) between the two bracketing graph variables
        (``graph_*`` the variables' map poses before the correction, in :attr:`times_s` order). The
        similarity (:attr:`similarity`) applies exactly: position ``s R t + T``, rotation ``R R_map``."""
        if self.similarity:
            return self.apply_similarity(poses_map)
        C = self.poses @ np.stack([se3_inverse(T) for T in graph_poses_map])
        t = np.clip(np.asarray(times_s, dtype=np.float64), graph_times_s[0], graph_times_s[-1])
        return interpolate_poses(graph_times_s, C, t) @ poses_map

    def apply_similarity(self, poses_map: np.ndarray) -> np.ndarray:
        """Poses ``T_map_sensor`` (k, 4, 4) into the local CRS frame by :attr:`T_local_map` ``= [[s R, T],
        [0, 1]]``: position ``s R t + T`` (the scale on the points), rotation ``R R_map`` (a rotation)."""
        P = np.array(poses_map, dtype=np.float64, copy=True)
        sR = self.T_local_map[:3, :3]
        P[:, :3, :3] = (sR / np.cbrt(np.linalg.det(sR))) @ P[:, :3, :3]
        P[:, :3, 3] = P[:, :3, 3] @ sR.T + self.T_local_map[:3, 3]
        return P


def _rigid_fit(points_map, stations, crs, model, start_only: bool = False):
    """``T_local_map`` (4x4) by :func:`minegeo.georef.georeference` on the control stations.

    ``start_only``: the fit is only the graph's starting point, so its statistics (χ², w-tests of a
    rigid fit that drift fails) are not logged as warnings; the graph's own are the result."""
    from minegeo.georef import GeorefParams, georeference
    from minegeo.io.types import ControlPoints

    c = stations.is_control
    sig = np.c_[stations.sigma_h_m, stations.sigma_h_m, stations.sigma_v_m][c]
    gcps = ControlPoints(ids=[i for i, k in zip(stations.ids, c, strict=True) if k], local_xyz=points_map[c],
                         crs_enh=stations.enh[c], sigma_enh_m=sig, crs=crs)
    glog = logging.getLogger("minegeo.georef")
    level = glog.level
    if start_only:
        glog.setLevel(logging.ERROR)
    try:
        res = georeference(gcps, crs, GeorefParams(model=model, max_sigma0=1e12))
    except ConvergenceError as exc:  # named in the stations' terms, with the closed-form fit's misfit
        T0 = _start_placement(points_map, stations)
        v = np.linalg.norm(points_map[c] @ T0[:3, :3].T + T0[:3, 3] - stations.enh_local[c], axis=1)
        k = int(np.argmax(v))
        raise ConvergenceError(
            f"the {model} fit of the {int(c.sum())} control stations ({', '.join(gcps.ids)}) to the run's points "
            f"at their times did not converge: {exc}; after the closed-form rigid fit station {gcps.ids[k]} is "
            f"{v[k]:.3f} m from its surveyed point (sigma {stations.sigma_h_m[c][k]:.3f} m horizontal): check the "
            "stations' coordinates, times and roles") from None
    finally:
        glog.setLevel(level)
    T = np.array(res.T_geo_map, dtype=np.float64)
    T[:3, 3] += np.asarray(res.origin, dtype=np.float64) - stations.origin_enh  # whole km: exact
    return T, res


def _start_placement(points_map, stations) -> np.ndarray:
    """``T_local_map`` (4x4, rigid) placing the map on the control stations, the graph's starting point:
    the weighted Kabsch/Umeyama SVD solution (:func:`minegeo.registration.estimation.kabsch`, weights
    ``1/σ_h²``) of the stations' map points onto their local E N H. Closed form, so it cannot fail to
    converge (the iterative Helmert fit of :func:`_rigid_fit` did not converge on 3 of 6 synthetic
    stop-and-go streams with 3 control stations); collinear control stations, which leave the rotation
    about their line free, are a :class:`~minegeo.errors.DegenerateGeometryError`."""
    from minegeo.registration.estimation import kabsch

    c = stations.is_control
    return kabsch(points_map[c], stations.enh_local[c], weights=1.0 / np.asarray(stations.sigma_h_m)[c] ** 2)


def _sigma0(chi2) -> float:
    """``σ̂0 = √(vᵀPv / r)`` of a :class:`~minegeo.survey.lsq.Chi2Test`."""
    return float(np.sqrt(chi2.statistic / max(chi2.dof, 1)))


def drift_states_needed(chi2) -> bool:
    """The plain graph fails the upper tail of its global χ² test, ``vᵀPv > χ²_r(1 − α/2)`` (σ̂0
    too large for the odometry's stated noise). An omnibus misfit test, not the "auto" choice (that
    is :func:`drift_states_test`, which has the power against a drift this test lacks, C6)."""
    return bool(chi2.dof > 0 and chi2.statistic > chi2.upper)


def drift_states_test(objective_without: float, objective_with: float, drift_parameters: float,
                      alpha: float = 0.05) -> dict:
    """The likelihood-ratio test that chooses the drift states (C6, ``drift_states="auto"``).

    ``Δ = vᵀPv₀ − vᵀPv_β`` (the plain graph's minus the drift graph's, every factor with its walk
    and prior: :attr:`ControlResult.objective`) against ``χ²_f(1 − α)``, ``f`` the number of drift
    parameters the data determine (:attr:`ControlResult.drift_parameters`,
    ``3n − tr(H⁻¹ H_walk) − tr(H⁻¹ H_prior)``). With no drift (the drift states' true value 0, which
    the walk and prior centre on), both ``vᵀPv`` are quadratic forms of the odometry and station
    noise and ``E[Δ] = f`` exactly in the linearised model: ``E[vᵀPv] = Σ`` of the redundancy numbers
    of the real observations, ``N − u`` for the plain graph and ``N − u − 3n + f`` with the drift
    states. A drift the model represents adds its noncentrality. ``f ≤ 0`` never takes them.

    Returns
    -------
    dict
        ``statistic`` Δ, ``dof`` f, ``critical``, ``alpha``, ``p_value``, ``chosen`` (bool).
    """
    from scipy import stats

    lr = float(objective_without) - float(objective_with)
    f = float(drift_parameters)
    if not f > 0:
        return {"statistic": lr, "dof": f, "critical": float("nan"), "alpha": float(alpha), "p_value": float("nan"),
                "chosen": False}
    crit = float(stats.chi2.ppf(1.0 - alpha, f))
    return {"statistic": lr, "dof": f, "critical": crit, "alpha": float(alpha),
            "p_value": float(stats.chi2.sf(max(lr, 0.0), f)), "chosen": bool(lr > crit)}


def _solve_graph(graph, stations, offset, T_lm, p: ControlParams, drift: bool) -> dict:
    """Solve the station graph with control position factors, with or without the drift states (C4).

    Returns a dict: ``opt`` (the optimiser's result), ``poses`` (k, 4, 4), ``vectors`` (drift states
    or None), ``covs`` (k, 6, 6) pose marginals, ``st_cov`` (n, 3, 3) station point covariances,
    ``gchi`` (the global χ² test, C5), ``status``/``reason`` ("ok" or "failed").

    Redundancy (C5): ``r = 6·edges + 3·controls − 6·variables`` without drift states. With them the
    random-walk factors bring ``3·(variables − 1)`` residuals for ``3·variables`` unknowns, and the
    prior ``Ω_prior`` (the datum of the drift states) is spread over the ``n`` variables as
    ``Ω_prior / n`` on each (a constant drift gets exactly ``Ω_prior``, and every state an absolute
    anchor of its own besides the stiff walk). The prior is not a
    measurement (its residual is the estimate itself, ~0 against a loose σ), so its terms are left
    out of ``vᵀPv`` and their redundancy numbers ``3n − Σ_i tr(Σ_βi Ω_prior)/n`` out of ``r``:
    ``r = 6·edges + 3·controls − 6·variables − 3 + Σ_i tr(Σ_βi Ω_prior)/n`` (``Σ_βi`` the marginal
    covariance of variable ``i``'s drift states).
    """
    from minegeo.survey.lsq import chi2_global_test

    G_times, G_poses0, G_edges, G_Z, G_info, var, W = graph
    ctrl = stations.is_control
    nv = G_times.size
    if drift:
        start = Values(np.ascontiguousarray(T_lm @ G_poses0), np.zeros((nv, 3)))
        dt = np.diff(G_times)
        walk = np.zeros((nv - 1, 3, 3))
        walk[:, [0, 1, 2], [0, 1, 2]] = DRIFT_UNIT**2 / (np.asarray(p.drift_walk)[None, :] ** 2 * dt[:, None])
        prior = np.diag((np.asarray(p.drift_prior, dtype=np.float64) / DRIFT_UNIT) ** -2.0)  # states β / DRIFT_UNIT
        groups = [DriftBetweenFactors(G_edges, G_Z, G_info, DRIFT_UNIT),
                  PositionFactors(var[ctrl], stations.enh_local[ctrl], offset, W),
                  DriftWalkFactors(np.c_[np.arange(nv - 1), np.arange(1, nv)], walk),
                  DriftWalkFactors(np.arange(nv).reshape(-1, 1), np.tile(prior / nv, (nv, 1, 1)))]
        dim = 9
    else:
        start = Values(np.ascontiguousarray(T_lm @ G_poses0))
        groups = [BetweenFactors(G_edges, G_Z, G_info),
                  PositionFactors(var[ctrl], stations.enh_local[ctrl], offset, W)]
        dim = 6
    problem = FactorProblem(nv, dim, groups, (), p.lm,
                            labels=lambda v: (f"graph variable {v} (t = {G_times[v]:.3f} s)", int(v)),
                            hint=": fewer than 3 control stations off one line leave the map free to turn")
    opt = levenberg_marquardt(problem, start, p.lm)
    out = {"opt": opt, "status": "ok", "reason": ""}
    if opt.status != "converged":
        out["status"], out["reason"] = "failed", f"the graph with control did not converge: {opt.reason}"
        values = start
    else:
        values = opt.values
    values = Values(np.ascontiguousarray(values.poses), values.vectors)
    if drift:
        full, cross = marginal_covariances(problem, values, pairs=np.c_[np.arange(nv - 1), np.arange(1, nv)])
        # C6: effective number of drift parameters f = 3n − tr(H⁻¹ H_walk) − tr(H⁻¹ H_prior) (units cancel)
        Sb, Cb = full[:, 6:, 6:], cross[:, 6:, 6:]
        var_diff = Sb[:-1] + Sb[1:] - Cb - np.swapaxes(Cb, 1, 2)
        tr_walk = float(np.einsum("eij,eji->", walk, var_diff))
        tr_prior = float(np.einsum("nij,ji->", Sb, prior)) / nv
        out["drift_parameters"] = 3.0 * nv - tr_walk - tr_prior
    else:
        full = marginal_covariances(problem, values)
    if drift:  # the drift states and their covariance back in their units (scale, rad/m)
        full[:, 6:, 6:] *= np.outer(DRIFT_UNIT, DRIFT_UNIT)
        full[:, :6, 6:] *= DRIFT_UNIT
        full[:, 6:, :6] *= DRIFT_UNIT[:, None]
        prior = np.diag(np.asarray(p.drift_prior, dtype=np.float64) ** -2.0)
        opt = replace(opt, values=Values(opt.values.poses, opt.values.vectors * DRIFT_UNIT))
        out["opt"] = opt
    G_poses = values.poses
    J = station_jacobian(G_poses[var], offset)
    covs = full[:, :6, :6]
    res = problem.evaluate(values)
    vpv = 2.0 * problem.cost(res)
    out["objective"] = vpv  # every factor, the drift prior included (C6's statistic)
    dof = 6 * G_edges.shape[0] + 3 * int(ctrl.sum()) - 6 * nv
    if drift:
        vpv -= float(np.einsum("ni,ij,nj->", res[3] * DRIFT_UNIT, prior, res[3] * DRIFT_UNIT)) / nv
        dof = int(round(dof - 3 + float(np.einsum("nij,ji->", full[:, 6:, 6:], prior)) / nv))
    out.update(poses=G_poses, vectors=opt.values.vectors if drift else None, covs=covs, st_cov=J @ covs[var] @ np.swapaxes(J, 1, 2),
               gchi=chi2_global_test(vpv, max(dof, 0)))
    return out


def _check_control_inputs(times_s, stations, crs, mode: str) -> None:
    """The user's mistakes :func:`apply_control` refuses before any work (``InputError``)."""
    if not crs:
        raise InputError("the stations need a CRS (--crs or a '# crs:' line in the stations file)")
    if times_s.size < 2 or np.any(np.diff(times_s) <= 0):
        raise InputError("the keyframe times must be at least two, strictly increasing")
    n_ctrl = int(stations.is_control.sum())
    if n_ctrl < 3:
        raise InputError(f"{n_ctrl} control station(s): the {mode} mode needs at least 3 not on one line "
                         "(make more stations control, or add stations)")
    check_control_geometry(stations, mode)
    # the pose is taken at the middle time: it must lie on the graph (graph_inputs(res, t_mid) puts a
    # variable there); the whole still span is checked against the frames by the caller
    out_mid = np.flatnonzero((stations.t_mid_s < times_s[0]) | (stations.t_mid_s > times_s[-1]))
    if out_mid.size:
        i = int(out_mid[0])
        raise InputError(f"{stations.source or 'stations'}: line {stations.lines[i]}: station {stations.ids[i]} at "
                         f"{stations.t_mid_s[i]:.3f} s is outside the SLAM keyframes [{times_s[0]:.3f}, "
                         f"{times_s[-1]:.3f}] s (another clock or another run?)")


def apply_control(times_s, poses, edges, Z, information, stations, offset, crs=None,
                  params: ControlParams | None = None, pose_noise=None) -> ControlResult:
    """Put a SLAM keyframe graph into the CRS of its control stations (see the module docstring).

    Parameters
    ----------
    times_s : (k,) s
        Keyframe times, increasing.
    poses : (k, 4, 4)
        ``T_map_sensor`` of the keyframes (the optimised SLAM graph).
    edges, Z, information : (m, 2), (m, 4, 4), (m, 6, 6)
        The graph's between factors (``r = Log(Z⁻¹ T_i⁻¹ T_j)``, information rotation first).
    stations : minegeo.io.stations.Stations
    offset : (3,)
        Surveyed point in the sensor frame (m).
    crs : str, optional
        Default ``stations.crs``. ``params``: :class:`ControlParams`.
    pose_noise : (k, 6, 6), optional
        Each keyframe's own pose noise ``Q`` (:func:`minegeo.slam.odometry.keyframe_pose_noise`). Graph
        mode: ``J Q Jᵀ`` (:func:`station_point_noise`) added to a control factor's ``Σ`` and to every
        station's covariance, ``Q`` to every pose's (between keyframes :func:`graph_pose_noise`).

    Raises
    ------
    InputError
        A station outside the keyframes' time span, fewer than 3 control stations, overlapping spans, no CRS.
    """
    from minegeo.survey.control_stats import control_statistics, fit_residual_cofactors, redundancy_share
    from minegeo.survey.ellipse import error_ellipse

    p = params or ControlParams()
    crs = crs or stations.crs
    times_s = np.asarray(times_s, dtype=np.float64)
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64).reshape(3)
    mode_name = "similarity" if p.model == "similarity" else p.mode
    _check_control_inputs(times_s, stations, crs, mode_name)
    n_ctrl = int(stations.is_control.sum())
    t_st = stations.t_mid_s
    ctrl, chk = stations.is_control, stations.is_check
    pts_map = station_points(interpolate_poses(times_s, poses, t_st), offset)
    check_map_geometry(pts_map, stations, mode_name, f"{stations.source}: " if stations.source else "")
    if p.mode == "graph":  # only the graph's starting point: closed form, it cannot fail to converge
        T_lm = _start_placement(pts_map, stations)
    else:
        T_lm, fit = _rigid_fit(pts_map, stations, crs, p.model)
    cov_ll = stations.covariance()
    ids = np.array(stations.ids, dtype=object)
    status, reason, opt, covs, st_cov, ellipses = "ok", "", None, None, None, []
    use_drift, drift_choice, objective, drift_par = False, None, float("nan"), float("nan")
    scale, scale_std = 1.0, 0.0
    if p.mode == "rigid":
        if fit.status == "failed":  # unit mismatch, mirror image: the fit must not place the map
            status, reason = "failed", f"the {p.model} fit of the control stations failed: {fit.reason}"
        if p.model == "similarity":
            scale, scale_std = float(fit.scale), float(fit.scale_std)
        s_fit = np.cbrt(np.linalg.det(T_lm[:3, :3]))
        Rt = T_lm.copy()
        Rt[:3, :3] /= s_fit  # poses keep a rotation; the points carry the scale
        G_times, G_poses = times_s, Rt @ poses
        G_poses[:, :3, 3] = poses[:, :3, 3] @ T_lm[:3, :3].T + T_lm[:3, 3]
        pts = pts_map @ T_lm[:3, :3].T + T_lm[:3, 3]
        dof = 3 * n_ctrl - (6 if p.model == "rigid" else 7)
        v = pts[ctrl] - stations.enh_local[ctrl]
        qvv = fit_residual_cofactors(pts_map[ctrl] @ T_lm[:3, :3].T, cov_ll[ctrl], scale=p.model == "similarity")
        stats = control_statistics(v, cov_ll[ctrl], qvv=qvv, dof=dof, ids=ids[ctrl])
        gchi = stats.chi2
        var = np.full(len(stations), -1, dtype=np.int64)
        note = ("rigid fit" if p.model == "rigid" else "similarity fit (7 parameters, scale estimated)") + \
            ": station poses interpolated on SE(3) between keyframes"
    else:
        G_times, G_poses0, G_edges, G_Z, G_info, var, n_new = _insert_stations(
            times_s, poses, np.asarray(edges, np.int64).reshape(-1, 2), np.asarray(Z, np.float64),
            np.asarray(information, np.float64), t_st)
        note = (f"{n_new} station variable(s) inserted at the station times (odometry edge split by time "
                f"fraction), {len(stations) - n_new} on keyframes at the same time")
        Qg = graph_pose_noise(times_s, pose_noise, G_times)
        cov_obs = cov_ll + station_point_noise(T_lm @ G_poses0[var], offset, Qg[var])  # Σ + J Q Jᵀ
        graph = (G_times, G_poses0, G_edges, G_Z, G_info, var, np.linalg.inv(cov_obs[ctrl]))
        use_drift = p.drift_states is True
        g = _solve_graph(graph, stations, offset, T_lm, p, use_drift)
        if p.drift_states == "auto":  # C6: both models, the drift states when they lower vᵀPv significantly
            g_drift = _solve_graph(graph, stations, offset, T_lm, p, True)
            drift_choice = drift_states_test(g["objective"], g_drift["objective"], g_drift["drift_parameters"],
                                             p.drift_alpha)
            if g["status"] != "ok" or g_drift["status"] != "ok":  # a failed solve is no evidence either way
                drift_choice["chosen"] = g["status"] != "ok" and g_drift["status"] == "ok"
            drift_choice.update(sigma0_without=_sigma0(g["gchi"]), sigma0_with=_sigma0(g_drift["gchi"]))
            use_drift = drift_choice["chosen"]
            why = (f"the likelihood-ratio test (vTPv lowered by {drift_choice['statistic']:.2f} on "
                   f"{drift_choice['dof']:.2f} degrees of freedom, critical {drift_choice['critical']:.2f} at alpha "
                   f"{p.drift_alpha:g}; sigma0 {drift_choice['sigma0_without']:.2f} without, "
                   f"{drift_choice['sigma0_with']:.2f} with them)")
            note += (f"; drift states (C4) added by {why}" if use_drift else f"; no drift states: not significant in {why}")
            if use_drift:
                g = g_drift
        opt, G_poses, covs, st_cov, gchi = g["opt"], g["poses"], g["covs"], g["st_cov"], g["gchi"]
        objective, drift_par = g["objective"], g.get("drift_parameters", float("nan"))
        if g["status"] != "ok":
            status, reason = g["status"], g["reason"]
        pts = station_points(G_poses[var], offset)
        v = pts[ctrl] - stations.enh_local[ctrl]
        qvv = np.zeros((3 * n_ctrl, 3 * n_ctrl))
        for q, c in enumerate(np.flatnonzero(ctrl)):
            qvv[3 * q:3 * q + 3, 3 * q:3 * q + 3] = cov_obs[c] - st_cov[c]
        # the graph's χ² test is gchi (every factor); the stations' statistics take their share of the redundancy
        stats = control_statistics(v, cov_obs[ctrl], qvv=qvv, dof=redundancy_share(qvv, cov_obs[ctrl]), ids=ids[ctrl])
        covs, st_cov = covs + Qg, st_cov + station_point_noise(G_poses[var], offset, Qg[var])  # the poses' own noise
        ellipses = [error_ellipse(st_cov[c][:2, :2], confidence=0.95) for c in np.flatnonzero(chk)]
    check, classes, ratio = check_station_statistics(stations, pts, v, st_cov, G_times, G_poses, p.class_c)
    snoop = ((), ()) if not (stats.flagged and p.snooping) else _data_snooping(
        (times_s, poses, edges, Z, information), stations, offset, crs, p, stats.flagged_ids, pose_noise)
    if status == "ok" and (gchi.passed is False or stats.flagged):
        status, reason = "warning", _warning_reason(gchi, stats, snoop)
    log.info("control (%s): %s %s", p.mode if p.mode == "graph" else f"{p.model} fit", status, reason)
    return ControlResult(mode=p.mode, status=ControlStatus(status), reason=reason, origin_enh=stations.origin_enh.copy(),
                         times_s=G_times, poses=G_poses, station_var=var, station_enh_local=pts,
                         station_cov_enh=st_cov, covariances=covs, T_local_map=T_lm, stats=stats, check=check,
                         classes=classes, global_chi2=gchi, misclosure_ratio=ratio, ellipses_check=ellipses,
                         keyframe_note=note, optimisation=opt, blunders=snoop[0], unresolved=snoop[1],
                         drift_states=use_drift, objective=objective, drift_parameters=drift_par,
                         uncertainty_note="" if p.mode == "rigid" else UNCERTAINTY_NOTES[p.drift_states],
                         drift_choice=drift_choice, model=p.model if p.mode == "rigid" else "rigid", scale=scale,
                         scale_std=scale_std)


def _data_snooping(graph, stations, offset, crs, p: ControlParams, flagged_ids, pose_noise=None) -> tuple:
    """Baarda's data snooping over the control stations (CS3): while a control station is flagged
    and more than 3 remain (and would stay off one line), withhold the most suspect one (largest
    ``|w|``: made a check station) and adjust again. A single blunder spreads into the residuals of
    the stations the graph ties to it, so several can exceed the critical value in the one
    adjustment; the withheld ones are the suspected blunders. Returns ``(suspects, still flagged when
    snooping stopped)`` (ids)."""
    from dataclasses import replace

    from minegeo.io.stations import StationRole

    suspects, st, flagged = [], stations, tuple(flagged_ids)
    pts_map = station_points(interpolate_poses(graph[0], np.asarray(graph[1], dtype=np.float64), stations.t_mid_s),
                             offset)
    q = replace(p, snooping=False)
    glog = logging.getLogger("minegeo.georef")
    level = glog.level
    glog.setLevel(logging.ERROR)  # each re-adjustment starts from a rigid fit: its warnings once, not per pass
    try:
        while flagged and int(st.is_control.sum()) > 3:
            sid = flagged[0]
            nxt = replace(st, roles=[StationRole.CHECK if i == sid else r for i, r in zip(st.ids, st.roles, strict=True)])
            try:  # the remaining control stations on one line: no adjustment to test; snooping stops
                check_control_geometry(nxt, p.mode)
                check_map_geometry(pts_map, nxt, p.mode)
            except InputError:
                break
            suspects.append(sid)
            st = nxt
            flagged = apply_control(*graph, st, offset, crs, q, pose_noise).stats.flagged_ids
    finally:
        glog.setLevel(level)
    return tuple(suspects), tuple(flagged)


def _warning_reason(gchi, stats, snoop) -> str:
    """The ``reason`` of a "warning": the failed χ² test, the flagged control stations and, after data
    snooping, the suspected blunders named."""
    suspects, unresolved = snoop
    parts = []
    if gchi.passed is False:
        parts.append(f"the chi-square test of the adjustment failed ({gchi.sigma0_text()})")
    if stats.flagged:
        parts.append("control station(s) flagged by the w-test: " + ", ".join(stats.flagged_ids))
    if suspects:
        parts.append("suspected blunder(s) by data snooping (the most suspect withheld and re-adjusted, in turn): "
                     + ", ".join(suspects)
                     + (f"; still flagged with 3 control stations left: {', '.join(unresolved)}" if unresolved else
                        "; with them withheld no control station is flagged: check their coordinates and "
                        "identification, or make them check stations and re-run"))
    return "; ".join(parts)
