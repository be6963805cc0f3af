"""The odometry's parameters, records and result (:mod:`minegeo.slam.odometry`): `OdometryParams`, a
prepared frame, one registration's verdict, `OdometryResult`, and the covariance floor of an edge
(:func:`edge_covariance_floor`, :func:`floored_information`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from minegeo._params import bounded, flag, one_of, validate
from minegeo.kernels.lie import so3_log
from minegeo.registration import GICPParams
from minegeo.slam.observability import surface_translation_ratio

#: the fields of :class:`OdometryParams` that make the edge covariance floor (:func:`edge_covariance_floor`)
EDGE_FLOOR_FIELDS = ("edge_sigma_tilt_deg_per_sqrt_m", "edge_sigma_tilt_deg_per_deg", "edge_sigma_yaw_deg_per_sqrt_m",
                     "edge_sigma_trans_xy_m_per_sqrt_m", "edge_sigma_trans_z_m_per_sqrt_m", "edge_sigma_trans_z_m_per_deg",
                     "edge_sigma_tilt_deg_per_deg_s", "edge_sigma_yaw_deg_per_deg_s", "edge_sigma_trans_xy_m_per_deg_s",
                     "edge_sigma_trans_z_m_per_deg_s", "loop_sigma_tilt_deg", "loop_sigma_yaw_deg", "loop_sigma_trans_xy_m",
                     "loop_sigma_trans_z_m")
#: the fields of :class:`OdometryParams` that make a keyframe's own pose noise (:func:`keyframe_pose_noise`)
KEYFRAME_NOISE_FIELDS = ("keyframe_sigma_tilt_deg", "keyframe_sigma_yaw_deg", "keyframe_sigma_trans_xy_m",
                         "keyframe_sigma_trans_z_m", "keyframe_sigma_tilt_deg_per_deg_s", "keyframe_sigma_yaw_deg_per_deg_s",
                         "keyframe_sigma_trans_xy_m_per_deg_s", "keyframe_sigma_trans_z_m_per_deg_s")


#: What each frame registers to (``OdometryParams.frame_target``).
FrameTarget = Literal["frame", "submap"]


@dataclass(frozen=True)
class OdometryParams:
    """Parameters of the GICP odometry (distances in m, angles in deg, times in s).

    Each field with a bound or a fixed set of values declares it in its metadata
    (:mod:`minegeo._params`): the same rule checks the dataclass, the ``minegeo slam`` option that
    sets the field (``--voxel``, ``--max-distance``, ``--keyframe-distance``, ``--keyframe-angle``,
    ``--keyframe-interval``, ``--deskew-iterations``, ``--max-speed``, ``--max-angular-rate``,
    ``--max-acceleration``) and its key in a ``--config`` file. ``gicp_max_iterations`` and
    ``covariance_neighbours`` take the bounds of :class:`~minegeo.registration.GICPParams`.
    """

    voxel_size_m: float = bounded(0.3, gt=0.0)
    max_correspondence_distance_m: float = bounded(1.0, gt=0.0)
    gicp_max_iterations: int = bounded(30, ge=0, integer=True)
    covariance_neighbours: int = bounded(20, ge=3, integer=True)
    keyframe_distance_m: float = bounded(2.0, gt=0.0)
    keyframe_angle_deg: float = bounded(10.0, gt=0.0)
    keyframe_interval_s: float = bounded(10.0, gt=0.0)
    min_points: int = 200
    min_fitness: float = bounded(0.3, ge=0.0, le=1.0)
    sigma_floor_m: float = bounded(0.01, gt=0.0)
    coarse_gate_factor: float = bounded(3.0, gt=0.0)
    translation_observability_ratio: float = bounded(0.03, gt=0.0)
    surface_observability_ratio: float = bounded(0.004, gt=0.0)
    keyframe_submap_size: int = 5
    #: ``frame_target="submap"``: the local map each frame registers to is made of the last this many
    #: keyframes (2 m apart by default). Eight rather than five: on the paper world's ramp (a half turn on
    #: a 7° grade) 0.30 → 0.23 % of the path unaligned, on the 60 s drone flight (seed 1) 0.27 → 0.14 %,
    #: the drone's 20 s 0.70 → 0.65 %, the other streams by at most 0.012 % either way (issue 29, with
    #: ``covariance_frames = 9``; docs/slam.md)
    local_map_keyframes: int = bounded(8, ge=1, integer=True)
    #: the GICP covariances of a frame's points from the kNN among its own points and those of the
    #: ``covariance_frames - 1`` registered frames before it, moved into its frame by the odometry's
    #: poses and voxelised together (:mod:`minegeo.slam.frame_covariances`: one sweep's neighbourhoods
    #: follow its laser rings on the floor and the roof, which biased the tilt of a turn on a grade,
    #: issue 29); 1: its own points only (the intersection tracker's, ``TRACK_ODOMETRY``)
    covariance_frames: int = bounded(9, ge=1, integer=True)
    turn_retry_yaw_deg: tuple = (20.0, -20.0, 40.0, -40.0, 60.0, -60.0)
    unconverged_retry_fitness: float = 0.6
    #: what each frame registers to: ``"frame"`` the previous frame (Ren2019 Sec. 3.3, chained by
    #: [Ren2019 Eq. 7]), ``"submap"`` the local map of the last ``local_map_keyframes`` keyframes (frame to
    #: local map: the laser rings of several keyframes interleave, so neither the partner search nor
    #: the target's covariances follow the ring pattern, which biases frame-to-frame GICP towards no
    #: motion and no tilt change with sparse rings)
    frame_target: FrameTarget = one_of("frame", FrameTarget)
    #: deskew frames whose points carry per-point times (:mod:`minegeo.slam.deskew`), from the
    #: constant-velocity twist of the odometry's last motion; frames without times are unaffected
    deskew: bool = flag(True)
    #: after a frame's registration, deskew it again with the twist of its own newly estimated motion
    #: (from the previous registered frame to it) and register once more (0: no second pass)
    deskew_iterations: int = bounded(1, ge=0, le=1, integer=True)
    #: the first frame has no motion before it: it is deskewed by the first registered motion (to the
    #: second frame), whose velocity one registration fixes poorly along a drift, and it anchors the
    #: local map of the seconds after. Once the frames of this many seconds after it are registered, it
    #: is deskewed again with the velocity of the least-squares line through their positions
    #: (:func:`minegeo.slam.odometry.start_velocity`) and replaces itself in the keyframes and the local
    #: map (0, the default: never; docs/slam.md, "The first frame's deskewing": off until its ATE gain is shown)
    start_deskew_window_s: float = bounded(0.0, ge=0.0)
    #: plausible-motion bounds (no silent runaway): a registration whose motion since the last
    #: registered frame exceeds a speed (m/s) or an angular rate (deg/s), or whose velocity differs
    #: from the previous motion's by more than an acceleration (m/s², between the middles of the two
    #: intervals), is rejected and the frame held by the constant-velocity prior
    max_speed_m_s: float = bounded(30.0, gt=0.0)
    max_angular_rate_deg_s: float = bounded(180.0, gt=0.0)
    max_acceleration_m_s2: float = bounded(20.0, gt=0.0)
    #: registration noise allowed in the acceleration test (m): two positions off by this much change
    #: a velocity over ``dt`` by ``2·motion_noise_m/dt`` (in a smooth box drift at 1 m per 0.1 s frame,
    #: frame-to-frame GICP scattered by up to 0.13 m: 25 m/s² of apparent acceleration)
    motion_noise_m: float = bounded(0.1, gt=0.0)
    #: degenerate geometry: a registration whose normalised point-to-plane constraint matrix
    #: (:func:`minegeo.registration.constraint_analysis`, GICP's ``degeneracy_ratio``) has
    #: ``λ_min / λ_max`` below this is rejected (dimensionless; GICP flags below 1e-2 as weak)
    min_constraint_ratio: float = bounded(1e-4, ge=0.0, lt=1.0)
    #: edge covariance floor (:func:`edge_covariance_floor`), added by the back end to the GICP
    #: covariance of every keyframe edge and loop edge of the pose graph: GICP's Hessian treats each
    #: point as an independent measurement while the errors of neighbouring points are correlated
    #: (wall relief, the model error of the local planes, deskew error, the sparse rings' under-read
    #: rotation), so alone it is over-confident. Odometry edges, in the sensor frame: tilt (rotation
    #: about the sensor x and y axes) a random walk in deg per √m of the edge's translation plus deg per
    #: deg of its rotation; yaw (about the sensor z axis, the spin axis) deg per √m; translation along
    #: the sensor x and y axes m per √m, along its z axis m per √m plus m per deg of the edge's
    #: rotation. Loop edges (two keyframes registered directly, at any relative heading): a constant
    #: per block (``loop_sigma_*``). Both: a turn term per block, deg or m per deg/s of the angular
    #: rate of the sensor at each of the edge's two keyframes (a sweep taken in a turn is deskewed and
    #: registered less well). All 0: GICP's covariance alone. Fitted by maximum likelihood, jointly
    #: with the keyframes' own pose noise (``keyframe_sigma_*``), on the odometry and loop edges of
    #: simulated 10 Hz stop-and-go streams against their truth (``benchmarks/bench_edge_covariance.py``,
    #: docs/slam.md "Edge covariance")
    #: apply the floor (True: ``slam --control``, whose statistics need calibrated edges; False by
    #: default: plain SLAM keeps GICP's information, because with the floor the plane factors weigh
    #: more and cost ATE on some streams, see docs/slam.md "Edge covariance")
    edge_covariance_floor: bool = flag(False)
    edge_sigma_tilt_deg_per_sqrt_m: float = bounded(0.024, ge=0.0)
    edge_sigma_tilt_deg_per_deg: float = bounded(0.0, ge=0.0)
    edge_sigma_yaw_deg_per_sqrt_m: float = bounded(0.0063, ge=0.0)
    edge_sigma_trans_xy_m_per_sqrt_m: float = bounded(0.00069, ge=0.0)
    edge_sigma_trans_z_m_per_sqrt_m: float = bounded(0.0, ge=0.0)
    edge_sigma_trans_z_m_per_deg: float = bounded(0.0014, ge=0.0)
    edge_sigma_tilt_deg_per_deg_s: float = bounded(0.0038, ge=0.0)
    edge_sigma_yaw_deg_per_deg_s: float = bounded(0.00024, ge=0.0)
    edge_sigma_trans_xy_m_per_deg_s: float = bounded(2.8e-05, ge=0.0)
    edge_sigma_trans_z_m_per_deg_s: float = bounded(0.00045, ge=0.0)
    loop_sigma_tilt_deg: float = bounded(0.079, ge=0.0)
    loop_sigma_yaw_deg: float = bounded(0.0, ge=0.0)
    loop_sigma_trans_xy_m: float = bounded(0.0022, ge=0.0)
    loop_sigma_trans_z_m: float = bounded(0.0085, ge=0.0)
    #: a keyframe's own pose noise (:func:`keyframe_pose_noise`): the error of a keyframe's
    #: registration that belongs to its sweep (deskew error, the sweep's sampling of the walls), shared
    #: by every edge at that keyframe with opposite signs on its two sides, so it cancels along a chain
    #: and around a loop and is not in the edges' floor; it is in a pose's own error, so in the control
    #: factor of a station on that pose and in the reported covariance of every pose. Per block as the
    #: floor (tilt, yaw in deg; translation along the sensor x, y and z axes in m), a constant plus a
    #: term per deg/s of the sensor's angular rate at the keyframe; fitted jointly with the floor
    #: (``benchmarks/bench_edge_covariance.py``)
    keyframe_sigma_tilt_deg: float = bounded(0.071, ge=0.0)
    keyframe_sigma_yaw_deg: float = bounded(0.0, ge=0.0)
    keyframe_sigma_trans_xy_m: float = bounded(0.0024, ge=0.0)
    keyframe_sigma_trans_z_m: float = bounded(0.0066, ge=0.0)
    keyframe_sigma_tilt_deg_per_deg_s: float = bounded(0.017, ge=0.0)
    keyframe_sigma_yaw_deg_per_deg_s: float = bounded(0.0096, ge=0.0)
    keyframe_sigma_trans_xy_m_per_deg_s: float = bounded(0.0009, ge=0.0)
    keyframe_sigma_trans_z_m_per_deg_s: float = bounded(0.0011, ge=0.0)

    def __post_init__(self):
        validate(self)

    def gicp(self) -> GICPParams:
        return GICPParams(self.max_correspondence_distance_m, max_iterations=self.gicp_max_iterations,
                          covariance_neighbours=self.covariance_neighbours)


@dataclass
class PreparedFrame:
    """A frame ready for GICP: downsampled points (sensor frame), covariances, search index.

    ``surface_ratio`` is :func:`minegeo.slam.observability.surface_translation_ratio` of the frame;
    None until :meth:`surface` computes it from ``surface_inputs`` (the kNN PCA of the
    covariances: normals, eigenvalues, status), which happens only for a registration whose
    translation is weakly observed (most frames never need it)."""

    time_s: float
    points: np.ndarray
    covariances: np.ndarray
    index: object
    surface_ratio: float | None = 1.0
    surface_inputs: tuple | None = field(default=None, repr=False)

    def surface(self) -> float:
        """The frame's :func:`~minegeo.slam.observability.surface_translation_ratio` (computed once)."""
        if self.surface_ratio is None:
            self.surface_ratio = surface_translation_ratio(self.points, *self.surface_inputs)
            self.surface_inputs = None
        return self.surface_ratio


@dataclass
class Registration:
    """One GICP registration ``T_target_source`` with its verdict and edge information (right, (ω, ρ))."""

    T: np.ndarray
    ok: bool
    reason: str
    fitness: float
    rmse_m: float
    information: np.ndarray
    weak: str = ""  # a weakly observed pose direction (a straight smooth drift): kept, flagged
    converged: bool = True
    constraint_ratio: float = 1.0  # GICP's normalised constraint λ_min / λ_max (degenerate geometry near 0)


@dataclass(frozen=True)
class OdometryResult:
    """Poses of every frame and the keyframe chain.

    Attributes
    ----------
    times_s : (n,) float64
    poses : (n, 4, 4) float64
        ``T_world_sensor`` of every frame (world = first frame).
    frame_ok : (n,) bool
        False for frames that failed to register (placed by the constant-velocity guess).
    frame_reason : list of str
        Why a frame failed ("" when it registered).
    frame_weak : list of str
        The weakly observed direction of a frame's registration ("" when well constrained).
    fitness : (n,) float64
        GICP overlap of each frame with its predecessor (1 for the first).
    keyframes : (k,) int64
        Frame indices of the keyframes.
    keyframe_edges : (k-1, 4, 4) float64
        Refined ``T_{k-1} ⁻¹ T_k`` between consecutive keyframes.
    keyframe_information : (k-1, 6, 6) float64
        Their information matrices, right perturbation, (ω, ρ) order.
    keyframe_clouds : list of (m, 3) arrays
        Downsampled keyframe points in the keyframe's sensor frame (for loops and the map).
    deskewed : (n,) bool
        True for the frames deskewed to their frame time (points with times, ``params.deskew``).
    deskew_twist : (n, 6) float64
        The body twist ``(ω, v)`` (rad/s, m/s, sensor frame) each deskewed frame was finally
        deskewed with (:mod:`minegeo.slam.deskew`); zeros for frames not deskewed.
    constraint_ratio : (n,) float64
        GICP's normalised constraint ratio of each frame's registration (1 for the first frame; NaN
        when no registration ran).
    imu_aided : bool
        True when the odometry ran with an IMU (gyro guesses, deskew and gate); held frames are then
        held by the gyro's rotation (``held_by`` in :meth:`held_stretches`).
    keyframe_extra_edges : list of (i, j, (4, 4), (6, 6))
        Keyframe edges ``(i, j, T_i⁻¹ T_j, information)`` between non-consecutive keyframes (numbers
        into ``keyframes``): with ``frame_target="submap"``, a keyframe registered to the local map of
        keyframe ``i`` when the keyframes between them were placed by the guess (not registered). That
        registration measures ``T_i⁻¹ T_j``; the consecutive edge into ``j`` then carries the guess's
        weak information (1e-6), since it is relative to a guessed pose.
    """

    times_s: np.ndarray
    poses: np.ndarray
    frame_ok: np.ndarray
    frame_reason: list
    frame_weak: list
    fitness: np.ndarray
    keyframes: np.ndarray
    keyframe_edges: np.ndarray
    keyframe_information: np.ndarray
    keyframe_clouds: list = field(repr=False, default_factory=list)
    keyframe_covariances: list = field(repr=False, default_factory=list)
    params: OdometryParams = field(default_factory=OdometryParams)
    timings_s: dict = field(default_factory=dict)
    keyframe_extra_edges: list = field(default_factory=list)
    deskewed: np.ndarray | None = None
    deskew_twist: np.ndarray | None = None
    constraint_ratio: np.ndarray | None = None
    imu_aided: bool = False

    def held_stretches(self) -> list[dict]:
        """The stretches of consecutive frames placed by the constant-velocity motion prior alone
        (not registered: failed or rejected as implausible), in time order.

        Each is ``{"first_frame", "last_frame", "frames", "first_time_s", "last_time_s",
        "from_time_s", "held_s", "reasons"}``: frame indices (0-based, in the frames used), their
        times (s), ``from_time_s`` the time of the last registered frame before the stretch (the
        first frame when the stretch starts the run) and ``held_s = last_time_s − from_time_s``, how
        long the trajectory was carried by the motion prior alone; ``reasons`` the distinct reasons.
        With an IMU (``imu_aided``) each also has ``"held_by": "imu"``: the frames' rotations are the
        gyro's and their translations the constant velocity's (a registration the IMU disagrees with is
        one of the reasons, :func:`_imu_disagreement`).
        """
        out = []
        ok = np.asarray(self.frame_ok, dtype=bool)
        k, n = 1, ok.size  # frame 0 is the origin of the map frame, never held
        while k < n:
            if ok[k]:
                k += 1
                continue
            j = k
            while j + 1 < n and not ok[j + 1]:
                j += 1
            t = self.times_s
            reasons = list(dict.fromkeys(self.frame_reason[i] for i in range(k, j + 1)))
            out.append({"first_frame": int(k), "last_frame": int(j), "frames": int(j - k + 1),
                        "first_time_s": float(t[k]), "last_time_s": float(t[j]), "from_time_s": float(t[k - 1]),
                        "held_s": float(t[j] - t[k - 1]), "reasons": reasons,
                        **({"held_by": "imu"} if self.imu_aided else {})})
            k = j + 1
        return out

    def summary(self) -> dict:
        cr = self.constraint_ratio
        finite = cr[np.isfinite(cr)] if cr is not None else np.zeros(0)
        held = self.held_stretches()
        return {"frames": int(self.times_s.size), "failed_frames": int((~self.frame_ok).sum()),
                "weak_frames": sum(bool(w) for w in self.frame_weak),
                "keyframes": int(self.keyframes.size), "params": asdict(self.params),
                "deskewed_frames": int(self.deskewed.sum()) if self.deskewed is not None else 0,
                "held_stretches": held, "held_s_total": float(sum(h["held_s"] for h in held)),
                "min_constraint_ratio": float(finite.min()) if finite.size else None}


def edge_covariance_floor(length_m: float, angle_deg: float, params: OdometryParams, *,
                          rates_deg_s: tuple[float, float] = (0.0, 0.0), loop: bool = False) -> np.ndarray:
    """The covariance floor ``F`` (6x6, (ω, ρ) order, rad² and m², the edge's right perturbation: the
    axes of the source sensor frame) added to a GICP edge's covariance.

    ``F = diag(σ_t², σ_t², σ_z², σ_h², σ_h², σ_v²)``. For an odometry edge of translation
    ``L = length_m`` (m) and rotation angle ``θ = angle_deg`` (deg)::

        σ_t² = a_t² L + (b_t θ)² + c_t² W   tilt, about the sensor x and y axes (deg², converted to rad²)
        σ_z² = a_z² L + c_z² W              yaw, about the sensor z (spin) axis (deg², converted to rad²)
        σ_h² = a_h² L + c_h² W              translation along the sensor x and y axes (m²)
        σ_v² = a_v² L + (b_v θ)² + c_v² W   translation along the sensor z axis (m²)

    and for a loop edge (``loop``: two keyframes registered directly, whatever their relative heading;
    ``L`` and ``θ`` play no part)::

        σ_t² = l_t² + c_t² W,  σ_z² = l_z² + c_z² W,  σ_h² = l_h² + c_h² W,  σ_v² = l_v² + c_v² W

    with ``W = ω_i² + ω_j²`` the squared angular rates (deg/s) of the sensor at the edge's two keyframes
    (``rates_deg_s``, :func:`keyframe_rates_deg_s`): a sweep taken in a turn is deskewed and registered
    less well, whichever edge it is on. ``a_t = edge_sigma_tilt_deg_per_sqrt_m``,
    ``b_t = edge_sigma_tilt_deg_per_deg``, ``a_z = edge_sigma_yaw_deg_per_sqrt_m``,
    ``a_h = edge_sigma_trans_xy_m_per_sqrt_m``, ``a_v = edge_sigma_trans_z_m_per_sqrt_m``,
    ``b_v = edge_sigma_trans_z_m_per_deg``, ``c_* = edge_sigma_*_per_deg_s``, ``l_* = loop_sigma_*``:
    along the path a random walk (variance proportional to the distance, as the station split of
    :func:`minegeo.slam.control.graph_inputs` assumes). The constants are fitted by maximum likelihood
    against the simulator's truth, jointly with :func:`keyframe_pose_noise`, whose share of an edge's
    error is not in ``F`` (``benchmarks/bench_edge_covariance.py``, ``docs/slam.md`` "Edge covariance").
    """
    L, th = float(length_m), float(angle_deg)
    W = float(rates_deg_s[0]) ** 2 + float(rates_deg_s[1]) ** 2
    d2r = math.radians(1.0) ** 2
    p = params
    if loop:
        t2, z2, h2, v2 = (p.loop_sigma_tilt_deg**2, p.loop_sigma_yaw_deg**2, p.loop_sigma_trans_xy_m**2,
                          p.loop_sigma_trans_z_m**2)
    else:
        t2 = p.edge_sigma_tilt_deg_per_sqrt_m**2 * L + (p.edge_sigma_tilt_deg_per_deg * th) ** 2
        z2 = p.edge_sigma_yaw_deg_per_sqrt_m**2 * L
        h2 = p.edge_sigma_trans_xy_m_per_sqrt_m**2 * L
        v2 = p.edge_sigma_trans_z_m_per_sqrt_m**2 * L + (p.edge_sigma_trans_z_m_per_deg * th) ** 2
    s_t2 = d2r * (t2 + p.edge_sigma_tilt_deg_per_deg_s**2 * W)
    s_z2 = d2r * (z2 + p.edge_sigma_yaw_deg_per_deg_s**2 * W)
    s_h2 = h2 + p.edge_sigma_trans_xy_m_per_deg_s**2 * W
    s_v2 = v2 + p.edge_sigma_trans_z_m_per_deg_s**2 * W
    return np.diag([s_t2, s_t2, s_z2, s_h2, s_h2, s_v2])


def keyframe_rates_deg_s(times_s: np.ndarray, poses: np.ndarray, keyframes: np.ndarray) -> np.ndarray:
    """The sensor's angular rate (deg/s) at each keyframe: the rotation angle of ``T_{f−1}⁻¹ T_{f+1}``
    over ``t_{f+1} − t_{f−1}`` for the keyframe's frame ``f`` (the frames on either side, one side at
    the ends; 0 for a run of one frame). ``poses`` are the odometry's ``T_world_sensor``."""
    n = len(times_s)
    out = np.zeros(len(keyframes))
    for a, f in enumerate(np.asarray(keyframes, dtype=np.int64)):
        f0, f1 = max(int(f) - 1, 0), min(int(f) + 1, n - 1)
        if f1 > f0 and times_s[f1] > times_s[f0]:
            R = poses[f0, :3, :3].T @ poses[f1, :3, :3]
            out[a] = math.degrees(float(np.linalg.norm(so3_log(np.ascontiguousarray(R))))) / float(times_s[f1] - times_s[f0])
    return out


def keyframe_pose_noise(rates_deg_s, params: OdometryParams) -> np.ndarray:
    """A keyframe's own pose noise ``Q`` (n, 6, 6), (ω, ρ) order, rad² and m², the pose's right
    perturbation (the axes of its sensor frame), for the sensor's angular rates ``ω`` (deg/s, (n,),
    :func:`keyframe_rates_deg_s`)::

        Q = diag(σ_t², σ_t², σ_z², σ_h², σ_h², σ_v²),   σ_b² = k_b² + (m_b ω)²   for each block b

    with ``k_b = keyframe_sigma_*`` and ``m_b = keyframe_sigma_*_per_deg_s`` (tilt and yaw in deg,
    converted to rad). The model of the graph's errors is ``x_k = y_k Exp(n_k)``, ``n_k ~ N(0, Q_k)``:
    the keyframe's estimated pose ``x_k`` (its sweep's registration) is the true pose ``y_k`` with an
    error of its own, besides the error accumulated along the edges (:func:`edge_covariance_floor`).
    An edge ``Z = x_i⁻¹ x_j`` then errs by ``w + n_j − Ad(Z⁻¹) n_i``: the ``n`` cancel along a chain
    and around a loop, so they are not in the edges; a station on pose ``k`` (a control factor, a check
    station's estimate, a pose's reported covariance) carries ``Q_k`` (:func:`minegeo.slam.control.apply_control`).
    """
    w2 = np.asarray(rates_deg_s, dtype=np.float64).reshape(-1) ** 2
    d2r = math.radians(1.0) ** 2
    p = params
    Q = np.zeros((w2.size, 6, 6))
    Q[:, 0, 0] = Q[:, 1, 1] = d2r * (p.keyframe_sigma_tilt_deg**2 + p.keyframe_sigma_tilt_deg_per_deg_s**2 * w2)
    Q[:, 2, 2] = d2r * (p.keyframe_sigma_yaw_deg**2 + p.keyframe_sigma_yaw_deg_per_deg_s**2 * w2)
    Q[:, 3, 3] = Q[:, 4, 4] = p.keyframe_sigma_trans_xy_m**2 + p.keyframe_sigma_trans_xy_m_per_deg_s**2 * w2
    Q[:, 5, 5] = p.keyframe_sigma_trans_z_m**2 + p.keyframe_sigma_trans_z_m_per_deg_s**2 * w2
    return Q


def floored_information(information: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """``(Ω⁻¹ + F)⁻¹`` computed as ``(I + Ω F)⁻¹ Ω`` (no inverse of a possibly singular ``Ω``), symmetrised."""
    info = np.linalg.solve(np.eye(6) + information @ floor, information)
    return 0.5 * (info + info.T)
