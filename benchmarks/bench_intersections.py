"""Issue-18 acceptance experiments: a drone flight through a drift network (Liang et al. 2024, Table I).

Network (``--network``): ``synthetic`` = ``intersections_network()`` (three alike 4-way crossings
X1-X3 differing only in roof height, a T and a Y; 4.5 m drifts), or ``niosh`` = ``niosh_network`` of
the DARPA SubT NIOSH EX edge list (2.9 m x 2.6 m drifts; a plausible embedding, not the real mine).
Rock (``--roughness-m``, default 0.1 m RMS): floor, walls and roofs displaced along their normal by the
seeded smooth field ``roughness_field`` (0.5-6 m wavelengths, seed 1), the same rock in the map and in
every frame; 0 gives the flat, smooth surfaces of the plan (a degenerate stress case: nothing observes
the motion along a straight drift). Prior map: ``network_cloud`` (0.2 m spacing, 2 cm noise, seed 7);
knowledge base ``build_knowledge_base`` on it, with floor cells of ``--floor-cell-m`` (default 1 m; the
library's 2 m cells let the bumps of a 0.1 m rough floor into the wall band and moved X1's invariant
point 1.55 m), the same skeleton parameters in the tracker. Flight (``minegeo.synth.flight``): a graph walk of >= ``--length-km``
passing every junction several times from different directions, 1.5 m/s cruise, height half the lowest
roof, a VLP-16 rotation (16 rings, +-15 deg, 0.4 deg azimuth step, 3 cm range noise) per frame, one
frame per 1 m of travel / 15 deg of yaw / 2 s, simulated at the frame pose (no motion distortion).

Methods on the same frames:

(a) ``odometry``: ``run_odometry`` (``OdometryParams(frame_target=--odometry)``, default ``submap``:
    frame to the local map of the last 5 keyframes; ``frame``: frame to frame, Ren2019 Eq. 7), ``run_backend(use_loops=False,
    use_planes=False)``;
(b) ``odometry + loops``: ``run_backend(use_loops=True, use_planes=False)`` (generic geometric loop
    closure of ``minegeo.slam.loops``);
(c) ``ours (no map)``: ``minegeo.semantic.tracking.track(frames, kb, use_map=False)``;
(d) ``ours (map)``: ``track(..., use_map=True, map_points=<the prior map>)``: the intersection factors and
    the map-registration factors (``minegeo.semantic.mapfactor``: keyframes more than 50 m of path from
    the last verified intersection registered to the prior map every 10 m, information only in the
    directions the registration constrains); ``--no-map-factors`` leaves the map points out.

(a) and (b) start in the first frame's sensor frame; their poses are put into the map frame with the
**true first pose** (a known take-off pose); (c) and (d) get the same pose as ``TrackParams.T_world_start``
and reuse the odometry of (a) (same parameters, same frames). No alignment is fitted: the map frame is
the world frame. Precision counts the recognitions that became factors.

Metrics per method over all frames (position error ``e_k = |t_est,k - t_true,k|``, m): MAE (mean
``e_k``), RMSE, max (the paper's "MAE" is this maximum), REP-1..5 = ``e`` at the frame where 20, 40, ..,
100 % of the path is flown, as % of the path flown so far. Recognition (``track`` only, status
``verified``). The **true junctions** (``truth_junctions``) come from the drift geometry: every edge-list
node of degree >= 3 (``junction_truth``) plus every geometric crossing, where two drifts that share no node
come within their width of each other (the drifts overlap: the map and the frames show a junction there;
the NIOSH embedding makes three such points, ``x1-45``, ``x33-47a`` and ``x33-47b``), placed at the local maxima of
the clearance to the noise-free walls. A **visit** of true junction j = a maximal run of frames within 15 m
(horizontal) of its invariant point, a **pass** = a visit coming within 3 m. With the map a recognition is
**correct** when the true junction the keyframe observes (the true junction within 2 m of the observed
invariant point placed by the true keyframe pose, ``T_true,k z``) is the one its knowledge-base id names
(the base point within 2 m of it); precision = correct / verified recognitions; recall = passes with a
correct recognition of that junction during the visit / passes. Without the map ids are the tracker's own
online entries: an entry's junction is the true junction nearest to the true position of the keyframe that
created it, and a recognition is correct when the true junction nearest the true position at its time
(within 15 m) is its entry's junction. With the map, a check independent of the junction list too:
``precision_observed_point`` = the fraction of verified recognitions whose named knowledge-base point lies
within 2 m of where the observed invariant point truly is, and the largest ICP keyframe position error
``|t_ICP - t_true,k|`` (the pose the factor pulls toward); ``wrong_list`` lists every
recognition that fails either check.

``--imu``: the flight's IMU (``minegeo.synth.flight.write_flight_imu``: the 10 Hz poses joined by the
interpolating cubic B-spline, gyro + accelerometer at 200 Hz with the ADIS16448 noise and bias random walk
of the ``drone`` stream, seed = the flight's) is written as ``imu.csv`` next to the cached frames, read back
as ``minegeo track --imu`` reads it, and given to every method: the odometry takes the gyro as each
registration's rotation guess and rejects a registration that disagrees with it (the stretch is then held
by the IMU and flagged); (a) and (b) run the LiDAR-inertial back end (``run_backend(imu=...)``: IMU
preintegration factors between keyframes), (c) and (d) the tracker on that odometry (no factor from a held
keyframe). ``--no-imu`` is the same run without it, labelled ``_noimu``. Every run lists the odometry's
flagged (held) stretches.

``--corridor``: the corridor experiment in the spirit of Sec. 4.2: a 160 m drift with a crossing at
40 m, a T at 80 m and a crossing at 120 m (4 m wide; roofs 3.0 / 3.6 / 4.2 m), flown out and back with
two side legs (400 m); 20 "surveyed tags" on the drift walls at 1.5 m height; the error of a tag seen
from frame k is ``|T_est,k T_true,k^-1 p - p|`` (the tag placed with the estimated pose), per pass.

Usage::

    python benchmarks/bench_intersections.py --quick
    python benchmarks/bench_intersections.py --length-km 3.2 [--network niosh] [--corridor] [--threads 2]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import sys
import time
import traceback
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CACHE = Path.home() / ".cache" / "minegeo_bench" / "intersections"
NIOSH_EX = REPO.parent / "shared" / "data" / "subt_tunnel_niosh_mine" / "ex_edgelist.csv"
METHODS = ("odometry", "odometry + loops", "ours (no map)", "ours (map)")
VISIT_M, PASS_M, ID_MATCH_M = 15.0, 3.0, 2.0


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------- setup
def corridor_network():
    """The corridor network, its 400 m route and the 20 tag positions (map frame, m)."""
    from minegeo.synth.network import DriftNetwork

    nodes = [(0, 0), (40, 0), (80, 0), (120, 0), (160, 0), (40, 20), (40, -20), (80, 20), (120, 20), (120, -20)]
    edges = [(0, 1), (1, 2), (2, 3), (3, 4), (1, 5), (1, 6), (2, 7), (3, 8), (3, 9)]
    h = np.full(len(nodes), 3.6)
    h[1], h[3] = 3.0, 4.2
    names = ("", "X1", "T", "X3") + ("",) * 6
    net = DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.0), h, names,
                       {"kind": "corridor", "width_m": 4.0})
    route = [0, 1, 2, 3, 4, 3, 8, 3, 2, 1, 6, 1, 0]
    x = 4.0 + 8.0 * np.arange(20)
    tags = np.column_stack([x, np.where(np.arange(20) % 2 == 0, 2.0, -2.0), np.full(20, 1.5)])
    return net, route, tags


def setup(args):
    """Network, KB parameters and the route (None = planned) for the options."""
    from minegeo.semantic import KBParams, SkeletonParams
    from minegeo.synth.network import intersections_network, niosh_network

    fc = args.floor_cell_m
    if args.corridor:
        net, route, _ = corridor_network()
        return net, KBParams(SkeletonParams(floor_cell_m=fc)), route
    if args.network == "niosh":
        return niosh_network(NIOSH_EX), KBParams(SkeletonParams(min_branch_m=2.5, merge_radius_m=2.0,
                                                                refine_radius_m=2.0, floor_cell_m=fc)), None
    return intersections_network(), KBParams(SkeletonParams(floor_cell_m=fc)), None


def _segment_gap(a, b, c, d) -> tuple[float, np.ndarray]:
    """Smallest distance (m) between the 2-D segments ab and cd, and the midpoint of the closest pair."""
    r, s = b - a, d - c
    den = r[0] * s[1] - r[1] * s[0]
    if abs(den) > 1e-12:
        t = ((c - a)[0] * s[1] - (c - a)[1] * s[0]) / den
        u = ((c - a)[0] * r[1] - (c - a)[1] * r[0]) / den
        if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
            return 0.0, a + t * r
    best = (np.inf, a)
    for p, q0, q1 in ((a, c, d), (b, c, d), (c, a, b), (d, a, b)):
        v = q1 - q0
        q = q0 + np.clip(np.dot(p - q0, v) / max(np.dot(v, v), 1e-24), 0.0, 1.0) * v
        g = float(np.linalg.norm(p - q))
        if g < best[0]:
            best = (g, 0.5 * (p + q))
    return best


def truth_junctions(net, step_m: float = 0.05) -> tuple[np.ndarray, list]:
    """The true junctions of the drift geometry: invariant points (k, 2) (map frame, m) and names.

    (1) every edge-list node of degree >= 3 (``junction_truth``: the largest empty circle within 4 m of the
    node), named by the node; (2) every **geometric crossing**: two drifts that share no node whose
    centrelines come within the mean of their widths of each other (their drifts overlap, so the map and
    the frames show a junction there; the 2-D embedding of an edge list creates these). A crossing's
    invariant points are the strict local maxima of the clearance ``c(p)`` = distance from ``p`` to the
    noise-free wall outline (2 cm samples) over the free space (union of capsules) within
    ``w/sin(theta/2) + w`` of the centrelines' closest point (``w`` the wider width, ``theta`` the angle
    between the drifts), on a ``step_m`` grid, with ``c > w_min/2 + 0.1 m`` (wider than a drift: a straight
    drift, a bend or a dead end has ``c <= w/2``), each refined to 1 cm by the same largest-empty-circle
    search as (1); a shallow crossing has two (where the drifts merge and where they part), a touching dead
    end one. Points within ``ID_MATCH_M`` of an earlier one are dropped. Named ``xA-B`` (A, B edge indices;
    ``xA-Ba``, ``xA-Bb`` when a crossing has several).
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from minegeo.synth.network import junction_truth, max_clearance_point, segment_distances, wall_outline

    pts = [tuple(p) for p in junction_truth(net)]
    names = [net.names[i] or str(int(i)) for i in net.junctions()]
    W, _ = wall_outline(net, 0.02, 1e-6)
    tree = cKDTree(W)
    N, E, w = net.nodes, net.edges, net.widths
    A, B = N[E[:, 0]], N[E[:, 1]]
    for i in range(len(E)):
        for j in range(i + 1, len(E)):
            if set(E[i].tolist()) & set(E[j].tolist()):
                continue
            gap, mid = _segment_gap(A[i], B[i], A[j], B[j])
            if gap > 0.5 * (w[i] + w[j]):
                continue
            u, v = B[i] - A[i], B[j] - A[j]
            cos = abs(u @ v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12)
            half = min(max(w[i], w[j]) * (1.0 / max(np.sin(0.5 * np.arccos(min(cos, 1.0))), 0.05) + 1.0), 40.0)
            g = np.arange(-half, half + 0.5 * step_m, step_m)
            Q = mid + np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
            c, _ = tree.query(Q)
            c = np.where((segment_distances(Q, A, B) < 0.5 * w[None]).any(1), c, -1.0).reshape(len(g), len(g))
            peak = (c == ndimage.maximum_filter(c, size=int(round(1.0 / step_m)) | 1)) & (c > 0.5 * w.min() + 0.1)
            lab, n = ndimage.label(peak)
            for m in range(1, n + 1):
                cells = np.flatnonzero(lab.ravel() == m)
                guess = Q[cells[int(np.argmax(c.ravel()[cells]))]]
                p = max_clearance_point(W, guess, 2.0 * step_m, net)
                if all(np.hypot(*(p - q)) > ID_MATCH_M for q in pts):
                    pts.append(tuple(p))
                    names.append(f"x{i}-{j}")
    for nm in {n for n in names if names.count(n) > 1}:        # several points of one crossing: xA-Ba, xA-Bb, ..
        for c, k in enumerate(k for k, n in enumerate(names) if n == nm):
            names[k] = nm + "abcdefghij"[c % 10]
    return np.array(pts, dtype=np.float64).reshape(-1, 2), names


# ---------------------------------------------------------------------------------------- methods
def _odometry(frames, folder: Path, params, imu=None):
    from minegeo.slam.inertial import GyroAid
    from minegeo.slam.odometry import run_odometry

    key = hashlib.sha256((repr(params) + ("" if imu is None else f"imu {imu.source} {len(imu)}")).encode())
    f = folder / f"odometry.{key.hexdigest()[:10]}{'' if imu is None else '.imu'}.pkl"
    if f.exists():
        with open(f, "rb") as fh:
            return pickle.load(fh)
    t0 = time.perf_counter()
    odo = run_odometry(iter(frames), params, imu=None if imu is None else GyroAid(imu))
    out = (odo, time.perf_counter() - t0)
    with open(f, "wb") as fh:
        pickle.dump(out, fh)
    return out


def held_summary(odo) -> dict:
    """The odometry's flagged stretches (frames held by the motion prior or the IMU): count, frames, seconds
    and each stretch (first/last frame, start time, seconds held, held by, reasons)."""
    held = odo.held_stretches()
    return {"stretches": len(held), "frames": int(sum(h["frames"] for h in held)),
            "held_s_total": float(sum(h["held_s"] for h in held)), "list": held}


def run_slam_methods(frames, T0: np.ndarray, odometry, imu=None, methods=METHODS) -> dict:
    """(a) odometry and (b) odometry + loops, poses in the map frame (anchored at the true first pose);
    with ``imu`` the odometry is gyro-aided and the back end LiDAR-inertial."""
    from minegeo.slam.pipeline import SlamParams, run_backend

    params = SlamParams(use_planes=False, remove_noise=False, odometry=odometry)
    odo, t_odo = _odometry(frames, frames.folder, params.odometry, imu)
    _log(f"odometry: {len(odo.times_s)} frames, {odo.keyframes.size} keyframes, "
         f"{int((~odo.frame_ok).sum())} failed, {t_odo:.0f} s")
    out = {"_odometry": odo, "_odo_keep": odo, "_odo_time": t_odo, "_held": held_summary(odo)}
    for name, loops in (("odometry", False), ("odometry + loops", True)):
        if name not in methods:
            continue
        t0 = time.perf_counter()
        try:
            res = run_backend(odo, params, use_loops=loops, imu=imu)
        except Exception as exc:  # noqa: BLE001  (reported in the table, the other methods still count)
            out[name] = {"error": f"failed: {type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=4)}
            continue
        out[name] = {"poses": np.einsum("ij,njk->nik", T0, res.poses), "time_s": t_odo + time.perf_counter() - t0,
                     "anchored": "true first pose", "loops_accepted": sum(c.accepted for c in res.loops),
                     "loop_candidates": len(res.loops), "failed_frames": int((~odo.frame_ok).sum())}
        if imu is not None:
            out[name]["inertial"] = getattr(getattr(res, "inertial", None), "status", None)
    return out


def run_track(frames, kb, T0: np.ndarray, use_map: bool, odometry, odo=None, imu=None,
              gate_drift: float | None = None, map_points=None) -> dict:
    """``minegeo.semantic.tracking.track`` from the true first pose (``TrackParams.T_world_start``), on the
    odometry already computed for (a) and (b) when its parameters are the tracker's (the same frames)."""
    from minegeo.semantic.recognition import RecognitionParams
    from minegeo.semantic.tracking import TrackParams, track

    # the online detection uses the skeleton parameters the base was built with (narrow NIOSH drifts)
    params = TrackParams(recognition=RecognitionParams(skeleton=kb.params.skeleton), T_world_start=T0,
                         odometry=odometry, **({} if gate_drift is None else {"gate_drift_fraction": gate_drift}))
    if odo is not None and odo.params != params.odometry:
        odo = None
    t0 = time.perf_counter()
    try:
        res = track(iter(frames), kb, params, use_map=use_map, odometry=odo, imu=imu, map_points=map_points)
    except Exception as exc:  # noqa: BLE001  (reported in the table, the other methods still count)
        return {"error": f"failed: {type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=4)}
    t = time.perf_counter() - t0
    return {"poses": np.asarray(res.poses, dtype=np.float64), "times_s": np.asarray(res.times_s, float),
            "time_s": t, "anchored": "true first pose (TrackParams.T_world_start)", "status": res.status,
            "reason": res.reason, "failed_frames": int((~res.odometry.frame_ok).sum()),
            "summary": res.summary(), "recognitions": [e.summary() for e in res.recognitions],
            "timings_s": {k: float(v) for k, v in res.timings_s.items()}, "_result": res,
            "_online_frames": res.keyframes[res.online_keyframes].tolist()}


# ---------------------------------------------------------------------------------------- metrics
def _on_truth(res: dict, truth) -> tuple[np.ndarray, np.ndarray]:
    """Estimated poses at the truth frames (matched by time within 1 ms) and the matched truth indices."""
    t = res.get("times_s", truth.times_s)
    idx = np.clip(np.searchsorted(t, truth.times_s), 0, len(t) - 1)
    ok = np.abs(np.asarray(t)[idx] - truth.times_s) < 1e-3
    return res["poses"][idx[ok]], np.flatnonzero(ok)


def trajectory_metrics(res: dict, truth) -> dict:
    P, k = _on_truth(res, truth)
    e = np.linalg.norm(P[:, :3, 3] - truth.poses[k, :3, 3], axis=1)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth.poses[:, :3, 3], axis=0), axis=1))][k]
    rep = {}
    for q in range(1, 6):
        i = min(int(np.searchsorted(s, q / 5 * s[-1])), len(s) - 1)
        rep[f"rep{q}_pct"] = float(100.0 * e[i] / max(s[i], 1e-9))
    return {"n": int(len(e)), "path_m": float(s[-1]), "mae_m": float(e.mean()), "rmse_m": float(np.sqrt((e**2).mean())),
            "max_m": float(e.max()), "end_m": float(e[-1]), **rep, "_err": e, "_idx": k}


def _get(obj, *names, default=None):
    for n in names:
        v = obj.get(n) if isinstance(obj, dict) else getattr(obj, n, None)
        if v is not None:
            return v
    return default


def recognition_metrics(res: dict, truth, kb, J: np.ndarray, passes: list, use_map: bool) -> dict:
    """Precision / recall of the verified recognitions (module docstring)."""
    recs = res.get("recognitions", [])
    status = [str(_get(r, "status", default="")) for r in recs]
    ver = [r for r, s in zip(recs, status, strict=True) if r.get("factor", s == "verified")]   # factors added
    out = {"recognitions": len(recs), "by_status": {s: status.count(s) for s in sorted(set(status))},
           "verified": len(ver), "passes": len(passes)}
    if not ver:
        return {**out, "precision": None, "recall": 0.0 if passes else None, "confusion": []}
    t = np.array([float(_get(r, "time_s", "t", "time", default=np.nan)) for r in ver])
    ids = np.array([int(_get(r, "intersection_id", "kb_id", "id", default=-1)) for r in ver])
    k = np.clip(np.searchsorted(truth.times_s, t), 0, len(truth) - 1)
    d = np.linalg.norm(truth.poses[k, None, :2, 3] - J[None], axis=2)
    near = np.where(d.min(1) <= VISIT_M, d.argmin(1), -1)
    # where the observed invariant point truly is: the keyframe's true pose applied to z
    zk = np.array([[np.nan] * 3 if r.get("z_keyframe_m") is None else [np.nan if v is None else v
                                                                       for v in r["z_keyframe_m"]] for r in ver])
    Tt = truth.poses[k]
    obs = np.einsum("nij,nj->ni", Tt[:, :3, :3], zk) + Tt[:, :3, 3]
    if use_map:
        # the true junction the keyframe observes: nearest the observed point, within ID_MATCH_M (else none)
        do = np.linalg.norm(obs[:, None, :2] - J[None], axis=2)
        do = np.where(np.isfinite(do), do, np.inf)
        near = np.where(do.min(1) <= ID_MATCH_M, do.argmin(1), -1)
        kbj = np.linalg.norm(kb.invariant_points[:, None, :2] - J[None], axis=2)
        id_to_j = np.where(kbj.min(1) <= ID_MATCH_M, kbj.argmin(1), -2)
        assigned = np.array([id_to_j[i] if 0 <= i < len(id_to_j) else -2 for i in ids])
    else:                 # an online id is the true junction nearest the true position where it was created
        ent = res.get("online_entry_junction", [])
        assigned = np.array([ent[i] if 0 <= i < len(ent) else -2 for i in ids])
    correct = (assigned == near) & (near >= 0)
    # the label-free check: the observed point against the named knowledge-base point, and the ICP keyframe
    # position (the factor's pose) against the true one
    named = np.array([kb.invariant_points[i] if use_map and 0 <= i < len(kb) else [np.nan] * 3 for i in ids])
    e_obs = np.linalg.norm(obs - named, axis=1)
    icp = np.array([[np.nan] * 3 if r.get("icp_position_m") is None else r["icp_position_m"] for r in ver])
    e_icp = np.linalg.norm(icp - Tt[:, :3, 3], axis=1)
    geo = e_obs <= ID_MATCH_M
    hit = 0
    for p in passes:
        hit += bool(np.any(correct & (near == p["junction"]) & (k >= p["first"]) & (k <= p["last"])))
    conf = [[int(np.sum((near == a) & (assigned == b))) for b in range(len(J))] for a in range(len(J))]
    wrong = [{"time_s": float(t[w]), "intersection_id": int(ids[w]), "assigned_junction": int(assigned[w]),
              "observed_junction": int(near[w]) if use_map else None,
              "nearest_true_junction": int(d[w].argmin()), "nearest_true_junction_m": float(d[w].min()),
              "observed_point_to_named_m": float(e_obs[w]), "icp_position_error_m": float(e_icp[w])}
             for w in np.flatnonzero(~correct | ~geo)]
    return {**out, "precision": float(correct.mean()), "recall": float(hit / max(len(passes), 1)),
            "wrong": int((~correct).sum()), "wrong_list": wrong,
            "precision_observed_point": float(geo.mean()) if use_map else None,
            "observed_point_to_named_max_m": float(np.nanmax(e_obs)) if use_map else None,
            "icp_position_error_max_m": float(np.nanmax(e_icp)) if np.isfinite(e_icp).any() else None,
            "confusion": conf}


def tag_errors(res: dict, truth, tags: np.ndarray) -> list:
    """Per tag pass (time order): tag id, frame, error (m) of the tag placed with the estimated pose."""
    from minegeo.synth.flight import junction_passes

    P, k = _on_truth(res, truth)
    est = dict(zip(k.tolist(), P, strict=True))
    rows = []
    for p in junction_passes(truth.poses[:, :3, 3], tags[:, :2], pass_radius_m=3.0, visit_radius_m=4.0):
        f = p["closest"]
        if f not in est:
            continue
        Tt, Te = truth.poses[f], est[f]
        q = Tt[:3, :3].T @ (tags[p["junction"]] - Tt[:3, 3])
        rows.append({"tag": p["junction"], "frame": f, "err_m": float(np.linalg.norm(Te[:3, :3] @ q + Te[:3, 3]
                                                                                   - tags[p["junction"]]))})
    return sorted(rows, key=lambda r: r["frame"])


# ---------------------------------------------------------------------------------------- figures
def error_map_figure(net, truth, results: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from minegeo.synth.network import network_cloud

    W = network_cloud(net, 0.5, 0.0)
    W = W.points[W.labels == 1]
    names = [m for m in METHODS if "metrics" in results.get(m, {})]
    fig, axes = plt.subplots(1, max(len(names), 1), figsize=(4.6 * max(len(names), 1), 4.4), squeeze=False)
    for ax, m in zip(axes[0], names, strict=False):
        r, met = results[m], results[m]["metrics"]
        ax.scatter(W[:, 0], W[:, 1], s=0.2, c="0.75", rasterized=True)
        P = truth.poses[met["_idx"], :3, 3]
        sc = ax.scatter(P[:, 0], P[:, 1], c=met["_err"], s=2, cmap="jet", vmin=0, rasterized=True)
        fig.colorbar(sc, ax=ax, shrink=0.7, label="position error (m)")
        ax.set_title(f"{m}\nRMSE {met['rmse_m']:.2f} m, max {met['max_m']:.2f} m", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        del r
    axes[0][0].set_ylabel("y (m)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def corridor_figure(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.6))
    for m, rr in rows.items():
        ax.plot(range(len(rr)), [r["err_m"] for r in rr], "o-", ms=3, label=m)
    any_rows = next(iter(rows.values()), [])
    ax.set_xticks(range(len(any_rows)), [str(r["tag"]) for r in any_rows], fontsize=6)
    ax.set_xlabel("tag id, in the order passed")
    ax.set_ylabel("tag position error (m)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------- output
def _fmt(x, f="{:.2f}"):
    return "–" if x is None else f.format(x)


def markdown(meta: dict, results: dict, corridor: dict | None) -> str:
    L = [f"# Drone flight through a drift network, Table I form ({meta['date']})", "", meta["conditions"], "",
         "| Method | MAE (m) | RMSE (m) | max (m) | REP-1 (%) | REP-2 (%) | REP-3 (%) | REP-4 (%) | REP-5 (%) "
         "| precision | recall | failed frames | status | time (s) |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in METHODS:
        r = results.get(m, {})
        if "metrics" not in r:
            L.append(f"| {m} | not available: {r.get('error', 'not run (--methods)')} |||||||||||||")
            continue
        x, rec = r["metrics"], r.get("recognition") or {}
        L.append(f"| {m} | {x['mae_m']:.2f} | {x['rmse_m']:.2f} | {x['max_m']:.2f} | "
                 + " | ".join(f"{x[f'rep{q}_pct']:.2f}" for q in range(1, 6))
                 + f" | {_fmt(rec.get('precision'), '{:.1%}')} | {_fmt(rec.get('recall'), '{:.1%}')} "
                 f"| {r.get('failed_frames', '–')} | {r.get('status', r.get('inertial') or '–')} | {r['time_s']:.0f} |")
    fl = meta["flight"]
    L += ["", f"Flight: {fl['path_length_m']:.0f} m, {fl['frames']} frames, {fl['duration_s']:.0f} s; route of "
          f"{fl['route_nodes']} nodes; junction passes: {fl['passes_per_junction']}; entry directions per junction: "
          f"{fl['directions_per_junction']}. Knowledge base: {meta['kb']}.", "",
          "Target (ours with map): RMSE <= 0.5 m over >= 3 km; recognition precision 100 %, recall >= 90 %: "
          + meta.get("target", "not evaluated"), ""]
    held = meta.get("held")
    if held is not None:
        L += [f"IMU: {meta.get('imu', 'none')}.", "",
              f"Flagged (held) stretches of the odometry: {held['stretches']} ({held['frames']} frames, "
              f"{held['held_s_total']:.1f} s held)" + (":" if held["list"] else "."), ""]
        if held["list"]:
            L += ["| first frame | last frame | from (s) | held (s) | held by | reasons |", "|---|---|---|---|---|---|"]
            for h in held["list"][:60]:
                L.append(f"| {h['first_frame']} | {h['last_frame']} | {h['from_time_s']:.1f} | {h['held_s']:.1f} | "
                         f"{h.get('held_by', 'motion prior')} | {'; '.join(h['reasons'])[:160]} |")
            if len(held["list"]) > 60:
                L.append(f"| ... {len(held['list']) - 60} more in the JSON | | | | | |")
            L.append("")
    for m in METHODS:
        r = results.get(m, {})
        extra = {k: v for k, v in r.items() if k in ("anchored", "loops_accepted", "loop_candidates", "failed_frames",
                                                     "reason", "inertial")}
        if r.get("recognition"):
            extra["recognition"] = {k: v for k, v in r["recognition"].items() if k != "confusion"}
        if isinstance(r.get("summary"), dict):      # the factors of each kind
            extra["factors"] = {"intersection": r["summary"].get("factors"),
                                "map": (r["summary"].get("map_registrations") or {}).get("factors", 0),
                                "map_registrations": r["summary"].get("map_registrations")}
        if extra:
            L.append(f"* {m}: {json.dumps(extra, default=str)}")
    if corridor:
        L += ["", "## Corridor (400 m, 20 tags)", "", "| pass | tag | " + " | ".join(corridor) + " |",
              "|---|---|" + "---|" * len(corridor)]
        base = next(iter(corridor.values()))
        for i, r0 in enumerate(base):
            L.append(f"| {i} | {r0['tag']} | " + " | ".join(f"{rr[i]['err_m']:.2f}" if i < len(rr) else "–"
                                                         for rr in corridor.values()) + " |")
        L.append("| mean | | " + " | ".join(f"{np.mean([r['err_m'] for r in rr]):.2f}" for rr in corridor.values())
                 + " |")
        L.append("| max | | " + " | ".join(f"{np.max([r['err_m'] for r in rr]):.2f}" for rr in corridor.values())
                 + " |")
    L += ["", f"Machine: {meta['machine']}; wall time {meta['wall_s']:.0f} s; code {meta['git']}."]
    return "\n".join(L) + "\n"


def _git() -> str:
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                                 capture_output=True, text=True, check=True).stdout.strip()
        return head + ("+dirty" if changed else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _flight_meta(flight, truth, J, J_names, passes) -> dict:
    per = {nm: 0 for nm in J_names}
    dirs = {k: set() for k in per}
    for p in passes:
        nm = J_names[p["junction"]]
        per[nm] += 1
        dirs[nm].add(int(round(p["entry_bearing_deg"] / 15.0)) * 15 % 360)
    return {"path_length_m": flight.path_length_m, "frames": len(truth), "duration_s": float(truth.times_s[-1]),
            "route_nodes": int(len(flight.route)), "route": flight.route.tolist(), "passes_per_junction": per,
            "directions_per_junction": {k: len(v) for k, v in dirs.items()},
            "true_junctions": {nm: [float(x), float(y)] for nm, (x, y) in zip(J_names, J, strict=True)}}


def main() -> None:  # noqa: PLR0915
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--length-km", type=float, default=3.2)
    ap.add_argument("--network", choices=("synthetic", "niosh"), default="synthetic")
    ap.add_argument("--corridor", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="a 0.5 km flight (smoke test)")
    ap.add_argument("--roughness-m", type=float, default=0.1,
                    help="RMS rock roughness of the drifts (m; 0 = flat smooth surfaces, a degenerate stress case)")
    ap.add_argument("--floor-cell-m", type=float, default=1.0,
                    help="SkeletonParams.floor_cell_m of the knowledge base and the tracker (library default 2 m)")
    ap.add_argument("--odometry", choices=("submap", "frame"), default="submap",
                    help="frame target of the GICP odometry of every method (OdometryParams.frame_target)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--imu", action="store_true", help="simulate the flight's IMU and give it to every method")
    g.add_argument("--no-imu", action="store_true", help="without the IMU, results labelled _noimu")
    ap.add_argument("--methods", default=None,
                    help="comma-separated subset of: " + ",".join(METHODS) + " (default all; the odometry always runs)")
    ap.add_argument("--gate-drift", type=float, default=None,
                    help="TrackParams.gate_drift_fraction of ours (map): the path-fraction gate instead of the library "
                    "default, the covariance (Mahalanobis) gate; results labelled _gateX")
    ap.add_argument("--no-map-factors", action="store_true",
                    help="ours (map) without the map-registration factors (the prior map's points not given to track)")
    ap.add_argument("--label", default="", help="appended to the results' file names (_LABEL)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--img", type=Path, default=REPO / "docs" / "img")
    args = ap.parse_args()
    import numba

    from minegeo.semantic import build_knowledge_base
    from minegeo.synth.flight import FlightParams, junction_passes, make_flight, simulate_flight
    from minegeo.synth.network import network_cloud

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    wall0 = time.perf_counter()
    import os
    import subprocess

    def _uptime() -> str:
        try:
            return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return f"load average {os.getloadavg()}"

    uptime_start = _uptime()
    net, kbp, route = setup(args)
    from minegeo.slam.odometry import OdometryParams
    from minegeo.synth.network import with_roughness

    if args.roughness_m > 0:
        net = with_roughness(net, args.roughness_m, seed=1)
    odometry = OdometryParams(frame_target=args.odometry)
    length = 0.5 if args.quick else args.length_km
    cloud = network_cloud(net, 0.2, 0.02, seed=7)
    kb = build_knowledge_base(cloud.points, kbp)
    J, J_names = truth_junctions(net)
    kb_txt = f"{len(kb.ids)} junctions found of {len(J)} ({kb.status})"
    _log(f"network {net.info.get('kind')}: {len(net.nodes)} nodes, {len(net.edges)} drifts; KB {kb_txt}")
    flight = make_flight(net, FlightParams(length_m=1000 * length, seed=args.seed), route=route)
    frames = simulate_flight(net, flight, CACHE, progress=lambda d, n: _log(f"frames {d}/{n}"))
    truth = frames.truth
    T0 = truth.poses[0]
    passes = junction_passes(truth.poses[:, :3, 3], J, PASS_M, VISIT_M)
    imu, imu_txt = None, "none"
    if args.imu:
        from minegeo.io.imu import read_imu_csv
        from minegeo.slam.inertial import InertialParams, check_imu_for_frames
        from minegeo.synth.flight import write_flight_imu

        imu_path = write_flight_imu(frames.folder, flight)
        imu = read_imu_csv(imu_path)
        check_imu_for_frames(imu, truth.times_s[0], truth.times_s[-1], InertialParams().max_gap_s, str(imu_path))
        imu_txt = (f"{imu_path} ({len(imu)} samples, {imu.rate_hz:.0f} Hz, ImuParams() defaults: ADIS16448 noise "
                   f"and bias random walk; seed {args.seed})")
        _log(f"IMU: {imu_txt}")
    _log(f"flight {flight.path_length_m:.0f} m, {len(truth)} frames, {len(passes)} junction passes ({frames.folder})")
    methods = METHODS if args.methods is None else tuple(m for m in METHODS if m in args.methods.split(","))
    results = run_slam_methods(frames, T0, odometry, imu, methods)
    held = results.pop("_held")
    _log(f"held stretches: {held['stretches']} ({held['frames']} frames, {held['held_s_total']:.1f} s)")
    for m, use_map in (("ours (no map)", False), ("ours (map)", True)):
        if m not in methods:
            continue
        _log(f"{m} ...")
        results[m] = run_track(frames, kb, T0, use_map, odometry, results.pop("_odometry", None) if not use_map
                               else results.get("_odo_keep"), imu=imu, gate_drift=args.gate_drift if use_map else None,
                               map_points=cloud.points if use_map and not args.no_map_factors else None)
        if "time_s" in results[m]:
            results[m]["time_s"] += results.get("_odo_time", 0.0)
    for k in ("_odometry", "_odo_keep", "_odo_time"):
        results.pop(k, None)
    for m, r in results.items():
        if "poses" in r:
            r["metrics"] = trajectory_metrics(r, truth)
            if m == "ours (no map)":
                f = np.asarray(r.pop("_online_frames", []), np.int64)
                d = np.linalg.norm(truth.poses[f, None, :2, 3] - J[None], axis=2).reshape(len(f), len(J))
                r["online_entry_junction"] = [int(j) if d[e, j] <= VISIT_M else -1
                                              for e, j in enumerate(d.argmin(1) if len(f) else [])]
            if m.startswith("ours"):
                r["recognition"] = recognition_metrics(r, truth, kb, J, passes, m == "ours (map)")
            x = r["metrics"]
            _log(f"{m}: MAE {x['mae_m']:.2f} RMSE {x['rmse_m']:.2f} max {x['max_m']:.2f} m")
        else:
            _log(f"{m}: {r['error']}")
    tag = "corridor" if args.corridor else args.network
    variant = (("" if args.roughness_m > 0 else "_flat") + ("" if args.odometry == "submap" else "_f2f")
               + ("_imu" if args.imu else "_noimu" if args.no_imu else "")
               + ("" if args.gate_drift is None else f"_gate{args.gate_drift:g}"))
    suffix = f"{tag}{variant}{'_quick' if args.quick else ''}"
    date = time.strftime("%Y-%m-%d")
    args.out.mkdir(parents=True, exist_ok=True)
    img_dir = args.out if args.quick else args.img
    error_map_figure(net, truth, results, img_dir / f"intersections_error_{suffix}.png",
                     f"{tag}: {flight.path_length_m / 1000:.2f} km, {len(truth)} frames")
    from minegeo.report.intersections_report import plot_similarity_png
    from minegeo.semantic import similarity_matrix

    if len(kb):
        png = plot_similarity_png(similarity_matrix(kb), similarity_matrix(kb, "cwc"))
        if png:
            (img_dir / f"intersections_similarity_{suffix}.png").write_bytes(png)
    corridor = None
    if args.corridor:
        _, _, tags = corridor_network()
        corridor = {m: tag_errors(r, truth, tags) for m, r in results.items() if "poses" in r}
        corridor_figure(corridor, img_dir / f"intersections_corridor{variant}{'_quick' if args.quick else ''}.png")
    ours = results.get("ours (map)", {})
    target = "not evaluated (ours (map) not available)"
    if "metrics" in ours:
        rec = ours.get("recognition", {})
        ok = (ours["metrics"]["rmse_m"] <= 0.5 and ours["metrics"]["path_m"] >= 3000 and rec.get("precision") == 1.0
              and (rec.get("recall") or 0) >= 0.9)
        target = "met" if ok else "missed"
    meta = {"date": date, "conditions": __doc__.split("\n\n")[1].replace("\n", " "), "seed": args.seed,
            "network": tag, "quick": args.quick, "roughness_m": args.roughness_m, "odometry": args.odometry,
            "floor_cell_m": args.floor_cell_m, "kb": kb_txt, "flight": _flight_meta(flight, truth, J, J_names, passes),
            "target": target, "map_factors": not args.no_map_factors, "imu": imu_txt, "held": held, "gate_drift_fraction": args.gate_drift, "git": _git(), "threads": args.threads, "wall_s": time.perf_counter() - wall0,
            "machine": f"{os.cpu_count()} cores; uptime at the start: {uptime_start}; at the end: {_uptime()}",
            "cache": str(frames.folder)}
    clean = {m: {k: v for k, v in r.items() if k not in ("poses", "times_s", "recognitions", "traceback")}
             | ({"metrics": {k: v for k, v in r["metrics"].items() if not k.startswith("_")}} if "metrics" in r else {})
             for m, r in results.items()}
    for m, r in clean.items():
        r.pop("_result", None)
        if m.startswith("ours") and "recognitions" in results[m]:   # the factors, for recomputing the metrics
            r["factor_recognitions"] = [x for x in results[m]["recognitions"] if x.get("factor")]
    stem = args.out / ("intersections_" + date + ("" if tag == "synthetic" else f"_{tag}") + variant
                       + ("_quick" if args.quick else "") + (f"_{args.label}" if args.label else ""))
    Path(f"{stem}.json").write_text(json.dumps({"meta": meta, "results": clean, "corridor": corridor}, indent=1,
                                               default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    Path(f"{stem}.md").write_text(markdown(meta, clean, corridor))
    print(Path(f"{stem}.md").read_text())


if __name__ == "__main__":
    main()
