"""The SLAM run: odometry → loop closure → pose-graph optimisation → map (Ren et al. 2019, Fig. 1).

:func:`run_slam` takes frames in time order and returns every used frame's pose, the keyframes,
the optimised pose graph, the loop list and the map cloud:

1. GICP odometry with keyframes (:mod:`minegeo.slam.odometry`);
2. for each keyframe in turn, loop candidates by the paper's rules, verified by GICP
   (:mod:`minegeo.slam.loops`); after each accepted loop the graph is optimised, so later
   candidates are searched from corrected poses;
3. the pose graph (keyframe poses, odometry and loop edges with their information matrices, and,
   with ``use_planes``, floor-plane landmarks with pose–plane edges [Ren2019 Eq. 11], Sec. 3.4.2)
   optimised by Levenberg–Marquardt (:mod:`minegeo.slam.posegraph`);
4. with an IMU (``imu``, :mod:`minegeo.slam.inertial`): the gyro as each registration's rotation
   guess and for deskewing, then the keyframe graph again with IMU preintegration factors
   [Forster2017 Sec. VI-D], velocity and bias states per keyframe and gravity;
5. the frames between keyframes placed by their odometry relative to the preceding keyframe (the
   contract's trajectory), the keyframe clouds moved into the world frame and voxel-compressed
   into the map (Sec. 3.5).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

import numpy as np

from minegeo._params import bounded, flag, group, validate
from minegeo._validate import internal_transform
from minegeo.geometry import voxel_downsample
from minegeo.geometry.se3 import compose, relative
from minegeo.io.g2o import PoseGraph
from minegeo.kernels.lie import se3_log
from minegeo.registration import build_target_index
from minegeo.slam.inertial import GyroAid, InertialParams, InertialResult, optimize_inertial_graph
from minegeo.slam.loops import LoopCandidate, LoopParams, find_loop, loop_correction
from minegeo.slam.mapping import NoiseRemovalResult, RoadwayNoiseParams, remove_roadway_noise
from minegeo.slam.odometry import (
    OdometryParams,
    OdometryResult,
    PreparedFrame,
    edge_covariance_floor,
    floored_information,
    keyframe_rates_deg_s,
    run_odometry,
)
from minegeo.slam.planes import (
    FloorPlaneParams,
    PlaneStatus,
    extract_floor_plane,
    plane_in_sensor_frame,
)
from minegeo.slam.posegraph import PlaneSet, PoseGraphParams, PoseGraphResult, optimize_pose_graph

__all__ = ["SlamParams", "SlamResult", "keyframe_graph", "run_backend", "run_slam"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlamParams:
    """Parameters of :func:`run_slam` (each stage's own dataclass, and the map voxel in m).

    Attributes
    ----------
    use_planes : bool
        Add floor-plane landmarks to the pose graph (Ren et al. 2019 Sec. 3.4.2).
    floor : FloorPlaneParams
        Floor extraction in the sub-map around each keyframe (keyframes within ``floor.radius_m``
        of it along the path, in the world frame from the current poses). The default height band,
        1 to 3.5 m below the sensor, is for a vehicle-mounted sensor about 2 m above the floor: it
        leaves out most of the walls, which otherwise outnumber the floor's inliers.
    plane_max_angle_deg, plane_max_offset_m : float
        A keyframe's floor joins the plane node of the previous keyframe's floor while its normal
        and the node's running floor differ by at most this angle and the two planes' heights below
        the keyframe by at most this offset (a roadway section of constant grade); else a new node
        starts (see ``_associate_floors``).
    plane_revisit_distance_m : float
        A floor that matches neither of the latest plane nodes joins an older node (a floor driven
        again after a loop) when a keyframe of that node lies within this horizontal distance at
        the current poses and its floor agrees within the angle and offset above (m; 0 turns the
        linking off: every revisit starts a new node).
    plane_smoothing : float
        Weight of a new floor in its node's running floor, which the next floors are compared with
        (0 < w ≤ 1; 1 compares with the latest floor only).
    plane_sigma_angle_deg, plane_sigma_offset_m : float
        Lower bounds of the standard deviations of a floor observation (normal angles, offset):
        the fit's own ``rms/√N`` is far below the floor's departure from a plane.
    remove_noise : bool
        Remove the roadway noise (moving objects, points between sensor and walls) from the
        world-frame keyframe cloud before the voxel compression (Sec. 3.5); ``noise`` its parameters.
    map_voxel_m : float
        Voxel of the map's compression (m, > 0).
    posegraph : PoseGraphParams
        The back end's Levenberg–Marquardt, with Marquardt's damping ``λ diag(H)`` (unit-free): a SLAM
        graph mixes pose rotations and translations with plane angles and offsets, whose information
        differs by orders of magnitude. With GTSAM's ``λ I`` (the g2o verb's default) the ring of
        ``tests/slam/test_slam_ring.py`` with an injected heading drift crawled 500 iterations at 2.7e-9
        of the cost each and stopped unconverged; with ``λ diag(H)`` it converges in 8 to within 4 mm.

    Each field declares its rule in its metadata (:mod:`minegeo._params`): the stages' groups are
    instances of their classes (which check themselves); the same rules check ``minegeo slam
    --map-voxel`` and its ``--config`` key.
    """

    odometry: OdometryParams = group(OdometryParams)
    loops: LoopParams = group(LoopParams)
    posegraph: PoseGraphParams = group(PoseGraphParams, lambda: PoseGraphParams(damping="diagonal"))
    map_voxel_m: float = bounded(0.1, gt=0.0)
    use_planes: bool = flag(True)
    floor: FloorPlaneParams = group(FloorPlaneParams, lambda: FloorPlaneParams(min_below_sensor_m=1.0,
                                                                               max_below_sensor_m=3.5))
    plane_max_angle_deg: float = bounded(3.0, gt=0.0)
    plane_max_offset_m: float = bounded(0.3, gt=0.0)
    plane_sigma_angle_deg: float = bounded(0.5, gt=0.0)
    plane_sigma_offset_m: float = bounded(0.05, gt=0.0)
    plane_revisit_distance_m: float = bounded(4.0, ge=0.0)
    plane_smoothing: float = bounded(0.2, gt=0.0, le=1.0)
    remove_noise: bool = flag(True)
    noise: RoadwayNoiseParams = group(RoadwayNoiseParams)

    def __post_init__(self):
        validate(self)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class SlamResult:
    """Outcome of :func:`run_slam`.

    Attributes
    ----------
    times_s, poses : (n,), (n, 4, 4)
        Every used frame's time and pose ``T_world_sensor`` (world = first frame), keyframes from
        the optimised graph, the others by odometry from the preceding keyframe.
    keyframes : (k,) int64
        Frame indices of the keyframes; ``keyframe_poses`` (k, 4, 4) optimised.
    graph : PoseGraph
        The optimised keyframe graph (odometry edges then loop edges).
    loops : list of LoopCandidate
        Every loop candidate tried, accepted or not, with scores and reasons.
    map_points : (m, 3)
        The map in the world frame (voxel centroids of the keyframe clouds).
    odometry : OdometryResult
    optimisation : PoseGraphResult or None
    planes : PlaneSet or None
        With ``use_planes``: the floor-plane nodes (optimised) and pose–plane edges (pose =
        keyframe index); ``floor_status`` gives each keyframe's extraction status (:class:`PlaneStatus`).
    """

    times_s: np.ndarray
    poses: np.ndarray
    keyframes: np.ndarray
    keyframe_poses: np.ndarray
    graph: PoseGraph
    loops: list
    map_points: np.ndarray
    odometry: OdometryResult
    optimisation: PoseGraphResult | None
    params: SlamParams
    timings_s: dict = field(default_factory=dict)
    planes: PlaneSet | None = None
    floor_status: list[PlaneStatus] = field(default_factory=list)
    noise: NoiseRemovalResult | None = None
    inertial: InertialResult | None = None

    def summary(self) -> dict:
        acc = [c for c in self.loops if c.accepted]
        out = {
            "frames": int(self.times_s.size), "keyframes": int(self.keyframes.size),
            "failed_frames": int((~self.odometry.frame_ok).sum()),
            "weak_frames": int(sum(bool(w) for w in self.odometry.frame_weak)),
            "loop_candidates": len(self.loops), "loops_accepted": len(acc),
            "map_points": int(self.map_points.shape[0]),
            "path_length_m": float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum()),
            "pose_graph": None if self.optimisation is None else {
                "status": self.optimisation.status, "reason": self.optimisation.reason,
                "cost_initial": self.optimisation.cost_initial, "cost_final": self.optimisation.cost_final,
                "iterations": self.optimisation.iterations},
            "planes": None if self.planes is None else {
                "nodes": self.planes.n_planes, "edges": self.planes.n_edges,
                "keyframes_without_floor": int(sum(st != "ok" for st in self.floor_status))},
            "map_noise_removed": None if self.noise is None else {
                k: v for k, v in self.noise.counts.items() if k not in ("track_points", "slices")}
            | {"slices": self.noise.counts["slices"]},
        }
        if self.inertial is not None:  # LiDAR-inertial: velocities, biases, gravity (the LiDAR-only record is unchanged)
            out["inertial"] = self.inertial.summary(self.times_s[self.keyframes])
        return out


def keyframe_graph(kf_poses: np.ndarray, odo: OdometryResult, loops: list[LoopCandidate],
                   params: OdometryParams | None = None, rates_deg_s: np.ndarray | None = None) -> PoseGraph:
    """The keyframe pose graph: odometry edges ``(k−1, k)``, the odometry's edges across keyframes
    placed by the guess (``OdometryResult.keyframe_extra_edges``), then the accepted loops;
    information in g2o order (t, r).

    Each edge carries GICP's information ``Ω_G``; with ``params.edge_covariance_floor`` (``params``
    defaults to ``odo.params``) it carries ``(Ω_G⁻¹ + F)⁻¹`` (:func:`~minegeo.slam.odometry.floored_information`)
    with ``F`` of :func:`~minegeo.slam.odometry.edge_covariance_floor`: for an odometry edge by its
    measured translation and rotation, for a loop edge the loop floor, both with the angular rates of
    the sensor at the edge's keyframes (:func:`~minegeo.slam.odometry.keyframe_rates_deg_s`). An edge
    of negligible information (trace below 1e-3: a chain edge relative to a guessed pose) is kept as
    it is.

    Parameters
    ----------
    kf_poses : (K, 4, 4)
        Keyframe poses ``T_world_keyframe`` (the graph's initial values).
    odo : OdometryResult
    loops : list of LoopCandidate
        The accepted ones become loop edges.
    params : OdometryParams, optional
    rates_deg_s : (K,) array, optional
        :func:`~minegeo.slam.odometry.keyframe_rates_deg_s` of ``odo`` when the caller already has them
        (the back end computes them once per run, not once per optimisation).
    """
    params = params or odo.params
    k = kf_poses.shape[0]
    extra = odo.keyframe_extra_edges
    acc = [c for c in loops if c.accepted]
    edges = [(a, a + 1) for a in range(k - 1)] + [(i, j) for i, j, _, _ in extra] + [(c.i, c.j) for c in acc]
    Z = list(odo.keyframe_edges) + [Z for _, _, Z, _ in extra] + [c.T_i_j for c in acc]
    info_wr = list(odo.keyframe_information) + [I for _, _, _, I in extra] + [c.information for c in acc]
    if params.edge_covariance_floor and edges:
        rates = rates_deg_s if rates_deg_s is not None else keyframe_rates_deg_s(odo.times_s, odo.poses, odo.keyframes)
        n_odo = len(edges) - len(acc)
        info_wr = [_floored(I, Zm, (rates[i], rates[j]), params, loop=m >= n_odo)
                   for m, ((i, j), Zm, I) in enumerate(zip(edges, Z, info_wr, strict=True))]
    p = [3, 4, 5, 0, 1, 2]  # (ω, ρ) → the file's (t, r) order; the solver permutes back
    info = [np.asarray(I)[p][:, p] for I in info_wr]
    m = len(edges)
    return PoseGraph("SE3", np.arange(k, dtype=np.int64), np.ascontiguousarray(kf_poses),
                     np.asarray(edges, dtype=np.int64).reshape(m, 2),
                     np.stack(Z) if m else np.zeros((0, 4, 4)), np.stack(info) if m else np.zeros((0, 6, 6)))


def _floored(info: np.ndarray, Z: np.ndarray, rates: tuple, params: OdometryParams, *, loop: bool) -> np.ndarray:
    """``info`` (ω, ρ) with the covariance floor of the edge ``Z`` (:func:`keyframe_graph`)."""
    info = np.asarray(info, dtype=np.float64)
    if np.trace(info) < 1e-3:
        return info
    angle = math.degrees(float(np.linalg.norm(se3_log(np.ascontiguousarray(Z))[:3])))
    F = edge_covariance_floor(float(np.linalg.norm(Z[:3, 3])), angle, params, rates_deg_s=rates, loop=loop)
    return floored_information(0.5 * (info + info.T), F)


def _path_lengths(poses: np.ndarray) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))]


def _floor_observations(odo: OdometryResult, kf_poses: np.ndarray, params: SlamParams):
    """Floor plane of each keyframe's sub-map, measured in its sensor frame, and plane-node association.

    The sub-map of keyframe ``k``: the clouds of the keyframes within ``floor.radius_m`` of it along
    the path, in the world frame from the current poses; the floor is extracted about the keyframe
    position with ``up`` its sensor z axis (seed ``k``). The information of an observation is
    ``diag(1/σ_a², 1/σ_a², 1/σ_d²)`` with ``σ_d = max(rms/√N, plane_sigma_offset_m)`` and
    ``σ_a = max(rms/(√N·s), plane_sigma_angle_deg)``, ``s`` the RMS in-plane spread of the inliers.
    The nodes are assigned by :func:`_associate_floors` at ``kf_poses``.

    Returns ``(pose index, node) edges, measurements (m, 4), information (m, 3, 3), status per keyframe``.
    """
    fp = params.floor
    path = _path_lengths(kf_poses)
    world = [P @ T[:3, :3].T + T[:3, 3] for P, T in zip(odo.keyframe_clouds, kf_poses, strict=True)]
    sa_min, sd_min = np.deg2rad(params.plane_sigma_angle_deg), params.plane_sigma_offset_m
    kfs, meas, info, status = [], [], [], []
    for k, T in enumerate(kf_poses):
        near = np.flatnonzero(np.abs(path - path[k]) <= fp.radius_m)
        sub = np.concatenate([world[j] for j in near])
        res = extract_floor_plane(sub, T[:3, 3], fp, seed=k, up=T[:3, 2])
        status.append(res.status)
        if res.status != PlaneStatus.OK:
            continue
        Q = sub[res.inliers]
        spread = np.sqrt(max(float(np.mean(np.sum((Q - Q.mean(axis=0)) ** 2, axis=1))) / 2.0, 1e-12))
        sd = max(res.rms_m / np.sqrt(res.n_inliers), sd_min)
        sa = max(res.rms_m / (np.sqrt(res.n_inliers) * spread), sa_min)
        kfs.append(k)
        meas.append(plane_in_sensor_frame(res.plane, T))
        info.append(np.diag([1.0 / sa ** 2, 1.0 / sa ** 2, 1.0 / sd ** 2]))
    m = len(kfs)
    meas_a = np.asarray(meas).reshape(m, 4)
    kf_a = np.asarray(kfs, dtype=np.int64)
    return (np.column_stack([kf_a, _associate_floors(kf_a, meas_a, kf_poses, params)]).astype(np.int64).reshape(m, 2),
            meas_a, np.asarray(info).reshape(m, 3, 3), status)


def _associate_floors(kfs: np.ndarray, meas: np.ndarray, kf_poses: np.ndarray, params: SlamParams) -> np.ndarray:
    """Plane node of each floor observation (keyframe ``kfs[e]``, plane ``meas[e]`` in its sensor frame).

    The floors are taken into the world frame at ``kf_poses`` [Ren2019 Eq. 9] [Ren2019 Eq. 10] (inverse),
    in keyframe order. Each node keeps a running floor, ``(1 − w)·floor + w·new floor`` renormalised,
    ``w = plane_smoothing`` (w = 1: the latest floor): single floors scatter by 1-4° in normal (the
    sub-map fit), and compared with the latest floor alone a level drift split into a new node every
    50-100 m (benchmarks/bench_slam.py). A floor joins, in this order of preference:

    1. the node of the previous floor, else the node before it (a single odd floor, a muck pile or a
       junction, gets its own node and does not split the section), while its normal and the node's
       running floor differ by at most ``plane_max_angle_deg`` and their heights below the keyframe
       by at most ``plane_max_offset_m`` (a roadway section of constant grade);
    2. with ``plane_revisit_distance_m > 0``, an older node (a floor driven again after a loop) with
       an observing keyframe within that horizontal distance (at the current poses) whose floor
       agrees in the same way (which also excludes another level); the nearest such keyframe's node;
    3. a new node.
    """
    cos_max = np.cos(np.deg2rad(params.plane_max_angle_deg))
    last: dict[int, np.ndarray] = {}  # node → its running floor (world frame)
    nodes = np.zeros(kfs.size, dtype=np.int64)
    world = np.zeros((kfs.size, 4))
    pos = kf_poses[kfs, :3, 3] if kfs.size else np.zeros((0, 3))
    floors = _floors_in_world(meas, kf_poses[kfs]) if kfs.size else world
    for e, _ in enumerate(kfs):
        pl = floors[e]
        t = pos[e]
        world[e] = pl
        hit = [q for q in sorted(last, reverse=True)[:2] if _same_section(pl, last[q], t, cos_max, params)]
        if not hit and params.plane_revisit_distance_m > 0 and e:
            recent = set(sorted(last, reverse=True)[:2])
            d = np.hypot(pos[:e, 0] - t[0], pos[:e, 1] - t[1])
            ok = (d <= params.plane_revisit_distance_m) & ~np.isin(nodes[:e], list(recent))
            for f in np.flatnonzero(ok)[np.argsort(d[ok], kind="stable")]:
                if _same_section(pl, world[f], t, cos_max, params):
                    hit = [int(nodes[f])]
                    break
        node = hit[0] if hit else (max(last) + 1 if last else 0)
        if node in last:  # the node's running floor: one noisy floor moves it by a fraction only
            q = (1.0 - params.plane_smoothing) * last[node] + params.plane_smoothing * pl
            last[node] = q / np.linalg.norm(q[:3])
        else:
            last[node] = pl
        nodes[e] = node
    return nodes


def _same_section(pl, q, t, cos_max: float, params: SlamParams) -> bool:
    """Same roadway section: normals within the angle, heights below the keyframe at ``t`` within the offset."""
    return (float(pl[:3] @ q[:3]) >= cos_max
            and abs((pl[:3] @ t + pl[3]) - (q[:3] @ t + q[3])) <= params.plane_max_offset_m)


def _plane_set(obs, kf_poses: np.ndarray, params: SlamParams) -> PlaneSet | None:
    """Plane nodes associated (:func:`_associate_floors`) and initialised from their first observation,
    both at the current poses ``kf_poses`` (after a loop closure a revisited floor is then near its
    earlier observations and joins their node)."""
    edges, meas, info, _ = obs
    if edges.shape[0] == 0:
        return None
    edges = np.column_stack([edges[:, 0], _associate_floors(edges[:, 0], meas, kf_poses, params)])
    n_nodes = int(edges[:, 1].max()) + 1
    first = [int(np.flatnonzero(edges[:, 1] == q)[0]) for q in range(n_nodes)]
    planes = _floors_in_world(meas[first], kf_poses[edges[first, 0]])
    return PlaneSet(planes, edges, meas, info)


def _floors_in_world(meas: np.ndarray, T_world_kf: np.ndarray) -> np.ndarray:
    """Planes ``meas`` (m, 4) measured in the sensor frames of the poses ``T_world_kf`` (m, 4, 4) in the
    world frame, row by row the formula of :func:`minegeo.slam.planes.plane_in_world_frame`:
    ``n = R n_s``, ``d = d_s − n·t`` [Ren2019 Eq. 10] (the poses are the pipeline's own, rigid)."""
    n = np.einsum("eij,ej->ei", T_world_kf[:, :3, :3], meas[:, :3])
    return np.column_stack([n, meas[:, 3] - np.einsum("ei,ei->e", n, T_world_kf[:, :3, 3])])


def _optimise(kf_poses, odo, loops, obs, params: SlamParams, rates=None) -> PoseGraphResult:
    return optimize_pose_graph(keyframe_graph(kf_poses, odo, loops, params.odometry, rates), params.posegraph,
                               _plane_set(obs, kf_poses, params) if obs is not None else None)


def _close_loops(odo: OdometryResult, params: SlamParams, obs=None, rates=None):
    """Loop closure keyframe by keyframe; the keyframe graph re-optimised after an accepted loop that
    corrects the current poses by more than ``params.loops.reoptimise_m`` / ``reoptimise_deg``
    (:func:`minegeo.slam.loops.loop_correction`); the loops accepted since the last optimisation are
    all in it."""
    kf_poses = odo.poses[odo.keyframes].copy()
    path = _path_lengths(kf_poses)  # distance along the trajectory does not depend on the drift much
    frames: dict[int, PreparedFrame] = {}

    def prepared(k: int) -> PreparedFrame:
        if k not in frames:
            P = odo.keyframe_clouds[k]
            index = build_target_index(P) if P.shape[0] >= params.odometry.min_points else None
            if index is not None:
                P = index.data  # the very array the index holds (GICP checks the target by identity)
            frames[k] = PreparedFrame(float(odo.times_s[odo.keyframes[k]]), P, odo.keyframe_covariances[k], index)
        return frames[k]

    loops: list[LoopCandidate] = []
    frame_list = _LazyFrames(prepared, kf_poses.shape[0])
    for k in range(1, kf_poses.shape[0]):
        tried = find_loop(k, kf_poses, path, frame_list, params.loops, params.odometry)
        loops.extend(tried)
        lp = params.loops
        every = lp.reoptimise_m == 0 and lp.reoptimise_deg == 0
        moved = [loop_correction(c, kf_poses) for c in tried if c.accepted]
        if any(every or m > lp.reoptimise_m or a > lp.reoptimise_deg for m, a in moved):
            opt = _optimise(kf_poses, odo, loops, obs, params, rates)
            if opt.status != "failed":
                kf_poses = _optimised_poses(opt)
    return kf_poses, loops


def _optimised_poses(opt: PoseGraphResult) -> np.ndarray:
    """The optimised keyframe poses, each checked as an internal invariant (a rigid transform: a
    solver that returned a non-rigid pose with a status other than "failed" is a bug) and
    re-projected onto SE(3)."""
    return _optimised_poses_of(opt.graph.poses)


def _optimised_poses_of(poses: np.ndarray) -> np.ndarray:
    return np.stack([internal_transform(T, f"optimised pose of keyframe {k}") for k, T in enumerate(poses)])


class _LazyFrames:
    """``frames[k]`` prepared on first use (search trees only for keyframes a loop test needs)."""

    def __init__(self, get, n):
        self._get, self._n = get, n

    def __getitem__(self, k):
        return self._get(int(k))

    def __len__(self):
        return self._n


def _all_poses(odo: OdometryResult, kf_poses: np.ndarray) -> np.ndarray:
    """Every frame: keyframes as optimised, the others by odometry from the preceding keyframe,
    ``T_f = T_kf^opt (T_kf^odo)⁻¹ T_f^odo`` (each product re-projected onto SE(3))."""
    out = odo.poses.copy()
    kf = odo.keyframes
    for a in range(kf.size):
        start, stop = kf[a], kf[a + 1] if a + 1 < kf.size else odo.poses.shape[0]
        for f in range(start, stop):
            out[f] = compose(kf_poses[a], relative(odo.poses[start], odo.poses[f]))
    return out


def run_slam(frames: Iterable[tuple[float, np.ndarray]], params: SlamParams | None = None, progress=None,
             imu=None, inertial: InertialParams | None = None) -> SlamResult:
    """Run the SLAM chain on frames ``(time_s, points in the sensor frame)`` in time order.

    The odometry (:func:`minegeo.slam.odometry.run_odometry`) then :func:`run_backend` on its result.
    ``imu`` (:class:`minegeo.io.imu.ImuSamples`, from a CSV or a bag, checked against the frames'
    time span by the caller, :func:`minegeo.slam.inertial.check_imu_for_frames`) makes it
    LiDAR-inertial (:mod:`minegeo.slam.inertial`, parameters ``inertial``); without it the run is the
    LiDAR-only one.

    Returns
    -------
    SlamResult
        Poses of every frame, keyframes, optimised graph, loop list, map and timings per module
        (odometry prepare / frame-to-frame / keyframe refinement, loops, graph, map).
    """
    params = params or SlamParams()
    aid = None if imu is None else GyroAid(imu, inertial)
    t0 = time.perf_counter()
    odo = run_odometry(frames, params.odometry, progress, imu=aid)
    return run_backend(odo, params, odometry_s=time.perf_counter() - t0, imu=aid)


def _inertial(odo: OdometryResult, kf_poses: np.ndarray, graph: PoseGraph, aid: GyroAid, params: SlamParams):
    """The keyframe graph's LiDAR edges with the IMU (:func:`minegeo.slam.inertial.optimize_inertial_graph`)."""
    p = [3, 4, 5, 0, 1, 2]  # the file's (t, r) information order → (ω, ρ)
    info = np.asarray(graph.information)[:, p][:, :, p]
    return optimize_inertial_graph(aid, odo.times_s[odo.keyframes], kf_poses, graph.edges, graph.measurements, info,
                                   lm=params.posegraph, trajectory=(odo.times_s, _all_poses(odo, kf_poses)))


def run_backend(odo: OdometryResult, params: SlamParams | None = None, *, use_loops: bool = True,
                odometry_s: float = 0.0, imu=None) -> SlamResult:
    """The back end on a finished odometry: floor planes, loop closure, pose graph, map.

    Lets the same odometry be run through several back ends (the ablation of Ren et al. 2019,
    Figs. 13-15): ``params.use_planes`` switches the floor-plane landmarks, ``use_loops`` the loop
    closure. With neither, the keyframe graph holds only the odometry edges and its optimum is the
    chained odometry itself, so no optimisation is run (``optimisation`` is None).

    Parameters
    ----------
    odo : OdometryResult
        From :func:`minegeo.slam.odometry.run_odometry` (it is not modified).
    params : SlamParams, optional
        ``params.odometry`` must be the parameters the odometry ran with (loop verification reuses
        them).
    use_loops : bool
        Search and verify loop closures (Sec. 3.4.1).
    odometry_s : float
        Time the odometry took (s), recorded in ``timings_s``.
    imu : GyroAid or ImuSamples, optional
        With it the keyframe graph is solved again with IMU preintegration factors
        (:func:`minegeo.slam.inertial.optimize_inertial_graph`; ``SlamResult.inertial``).

    Returns
    -------
    SlamResult
    """
    params = params or SlamParams()
    t1 = time.perf_counter()
    obs = None
    if params.use_planes and odo.keyframes.size > 1:
        obs = _floor_observations(odo, odo.poses[odo.keyframes], params)
    t_planes = time.perf_counter()
    rates = (keyframe_rates_deg_s(odo.times_s, odo.poses, odo.keyframes) if params.odometry.edge_covariance_floor
             else None)  # the edge floor's keyframe rates, once for every optimisation of the run
    if use_loops:
        kf_poses, loops = _close_loops(odo, params, obs, rates)
    else:
        kf_poses, loops = odo.poses[odo.keyframes].copy(), []
    t2 = time.perf_counter()
    opt = None
    if odo.keyframes.size > 1 and (use_loops or obs is not None):
        opt = _optimise(kf_poses, odo, loops, obs, params, rates)
    if opt is not None and opt.status != "failed":
        kf_poses = _optimised_poses(opt)
    graph = opt.graph if opt is not None else keyframe_graph(kf_poses, odo, loops, params.odometry, rates)
    inertial = None
    if imu is not None and odo.keyframes.size > 1:
        inertial = _inertial(odo, kf_poses, graph, imu if isinstance(imu, GyroAid) else GyroAid(imu), params)
        if inertial.status != "failed":
            kf_poses = _optimised_poses_of(inertial.keyframe_poses)
            graph = graph.with_poses(kf_poses)
    elif imu is not None:
        log.warning("one keyframe: no IMU keyframe graph (it needs two; the gyro served the odometry only)")
    t3 = time.perf_counter()
    poses = _all_poses(odo, kf_poses)
    world = [P @ T[:3, :3].T + T[:3, 3] for P, T in zip(odo.keyframe_clouds, kf_poses, strict=True)]
    cloud = np.concatenate(world) if world else np.zeros((0, 3))
    t_noise = time.perf_counter()
    noise = None
    if params.remove_noise and cloud.shape[0]:
        source = np.repeat(np.arange(len(world)), [w.shape[0] for w in world])
        noise = remove_roadway_noise(cloud, kf_poses[:, :3, 3], params.noise, source)
        cloud = cloud[noise.keep]
    t_noise = time.perf_counter() - t_noise
    map_points = voxel_downsample(cloud, params.map_voxel_m).points if cloud.shape[0] else cloud
    t4 = time.perf_counter()
    timings = {**{f"odometry_{k}": v for k, v in odo.timings_s.items()}, "odometry": odometry_s,
               "floor_planes": t_planes - t1, "loop_closure": t2 - t_planes, "pose_graph": t3 - t2,
               "map_noise": t_noise, "map": t4 - t3, "total": odometry_s + (t4 - t1)}
    planes = opt.planes if opt is not None else None
    return SlamResult(odo.times_s, poses, odo.keyframes, kf_poses, graph, loops, map_points, odo, opt, params, timings,
                      planes, obs[3] if obs is not None else [], noise, inertial)
