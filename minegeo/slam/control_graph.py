"""The SLAM keyframe graph as the control adjustment's input (:mod:`minegeo.slam.control`): the keyframe
poses, edges and information of a SLAM result, with a variable inserted at every station time; the
control stations' geometry checked before any work."""

from __future__ import annotations

import numpy as np

from minegeo.errors import InputError
from minegeo.kernels.lie import se3_exp, se3_inverse, se3_log

#: a station time within this of a keyframe's time uses that keyframe (s)
SAME_TIME_S = 1e-6


def interpolate_poses(times_s: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses at times ``t`` (k,): ``T_0 Exp(s Log(T_0⁻¹ T_1))`` between the bracketing poses (C1).

    Raises
    ------
    InputError
        A time outside ``[times_s[0], times_s[-1]]``.
    """
    times_s = np.asarray(times_s, dtype=np.float64)
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if np.any(t < times_s[0]) or np.any(t > times_s[-1]):
        raise InputError(f"station times [{t.min():.3f}, {t.max():.3f}] s outside the trajectory "
                         f"[{times_s[0]:.3f}, {times_s[-1]:.3f}] s")
    out = np.empty((t.size, 4, 4))
    for q, tq in enumerate(t):
        a = min(int(np.searchsorted(times_s, tq, side="right")) - 1, times_s.size - 2)
        a = max(a, 0)
        if times_s.size == 1 or tq == times_s[a]:
            out[q] = poses[a]
            continue
        s = (tq - times_s[a]) / (times_s[a + 1] - times_s[a])
        out[q] = poses[a] @ se3_exp(s * se3_log(se3_inverse(poses[a]) @ poses[a + 1]))
    return out


#: control stations all within this many times their largest stated standard deviation of their
#: best-fitting straight line lie "on one line": the rotation about the line is then determined to no
#: better than σ/(3σ) ≈ 0.3 rad, no georeference (:func:`check_control_geometry`)
LINE_SIGMAS = 3.0


def check_control_geometry(stations, mode: str, where: str = "") -> None:
    """Refuse control stations on one straight line (``InputError``; before any work).

    With ``X_k`` the control stations' ``E N H`` (local, m) and ``u`` the direction of their best-fitting
    line (first right singular vector of the centred ``X``), the distance of each from the line is
    ``d_k = |(X_k − X̄) − ((X_k − X̄)·u) u|``; the stations lie on one line when
    ``max_k d_k ≤ LINE_SIGMAS · max(σ_h, σ_v)``: a rotation of the map about that line moves no control
    station by more than its own noise, so no mode (rigid, similarity or graph) determines it.

    Parameters
    ----------
    stations : minegeo.io.stations.Stations
        With at least one control station (the count is checked by the caller).
    mode : str
        The mode named in the message.
    where : str
        Prefix of the message (``"--control FILE: "``).
    """
    c = np.asarray(stations.is_control, dtype=bool)
    X = np.asarray(stations.enh_local, dtype=np.float64)[c]
    Xc = X - X.mean(axis=0)
    u = np.linalg.svd(Xc, full_matrices=False)[2][0]
    off = float(np.max(np.linalg.norm(Xc - np.outer(Xc @ u, u), axis=1)))
    sig = float(max(np.max(np.asarray(stations.sigma_h_m)[c]), np.max(np.asarray(stations.sigma_v_m)[c])))
    if off <= LINE_SIGMAS * sig:
        ids = ", ".join(str(i) for i, k in zip(stations.ids, c, strict=True) if k)
        raise InputError(f"{where}the {int(c.sum())} control stations ({ids}) lie on one straight line (at most "
                         f"{off:.3f} m from it, within {LINE_SIGMAS:g} x their sigma {sig:.3f} m): the rotation about "
                         f"that line is not determined; the {mode} mode needs at least 3 not on one line (make a "
                         "station off the line control, or add one)")


def graph_inputs(slam_result, station_times_s=None) -> tuple:
    """``(times_s, poses, edges, Z, information)`` of a :class:`~minegeo.slam.pipeline.SlamResult`'s
    keyframe graph: keyframe times and ``T_map_sensor``, edges, measurements and the information in
    the residual order (rotation first; the graph stores the g2o order (t, r)).

    With ``station_times_s``, every station time not on a keyframe becomes a variable whose pose is
    the run's frame trajectory at that time (:func:`interpolate_poses` on the frames, which are
    still on a stop): the odometry edge ``(a, b)`` around it is split into ``Z_ak = T_a⁻¹ T_k`` and
    ``Z_kb = Z_ak⁻¹ Z_ab`` (their product is ``Z_ab``; information ``Ω_ab / f`` and
    ``Ω_ab / (1 − f)``, ``f`` the fraction of the edge's translation, clipped to [0.01, 0.99]); a
    station before the first or after the last keyframe (within the frames) is chained to it by
    ``T_u⁻¹ T_v`` with the end odometry edge's information over the ratio of translations.
    A split by time fraction would place a stop-and-go station where a constant velocity between
    the keyframes puts it, off by up to the keyframe distance.
    """
    g = slam_result.graph
    p = [3, 4, 5, 0, 1, 2]
    info = np.ascontiguousarray(np.asarray(g.information)[:, p][:, :, p])
    kt = np.asarray(slam_result.times_s)[slam_result.keyframes]
    kP = np.asarray(slam_result.keyframe_poses)
    edges, Z = np.asarray(g.edges), np.asarray(g.measurements)
    if station_times_s is None:
        return kt, kP, edges, Z, info
    ft = np.asarray(slam_result.times_s)
    t_new = sorted({float(t) for t in np.atleast_1d(station_times_s)
                    if ft[0] <= t <= ft[-1] and not np.any(np.abs(kt - t) <= SAME_TIME_S)})
    if not t_new:
        return kt, kP, edges, Z, info
    T_new = interpolate_poses(np.asarray(slam_result.times_s), np.asarray(slam_result.poses), np.array(t_new))
    all_t = np.r_[kt, t_new]
    order = np.argsort(all_t, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    P_all = np.concatenate([kP, T_new])[order]
    E, ZZ, OO = [], [], []
    for e in range(edges.shape[0]):
        a, b = int(edges[e, 0]), int(edges[e, 1])
        inside = [kt.size + m for m, t in enumerate(t_new) if b == a + 1 and kt[a] < t < kt[b]]
        if not inside:
            E.append((rank[a], rank[b]))
            ZZ.append(Z[e])
            OO.append(info[e])
            continue
        L = max(float(np.linalg.norm(Z[e][:3, 3])), 1e-9)
        Zrest, Ta, f_prev = Z[e], kP[a], 0.0
        prev = a
        for v in inside:
            Tv = T_new[v - kt.size]
            Zav = se3_inverse(Ta) @ Tv if prev == a else se3_inverse(T_new[prev - kt.size]) @ Tv
            f = float(np.clip(np.linalg.norm((se3_inverse(Ta) @ Tv)[:3, 3]) / L, 0.01, 0.99))
            df = max(f - f_prev, 0.01)
            E.append((rank[prev], rank[v]))
            ZZ.append(Zav)
            OO.append(info[e] / df)
            Zrest = se3_inverse(Zav) @ Zrest
            prev, f_prev = v, f
        E.append((rank[prev], rank[b]))
        ZZ.append(Zrest)
        OO.append(info[e] / max(1.0 - f_prev, 0.01))
    # stations before the first or after the last keyframe (frames there, no keyframe yet): a chain
    # of odometry edges Z = T_u⁻¹ T_v from the end keyframe, information that of the end odometry edge
    # scaled by the ratio of translations (clipped to [0.01, 100])
    odo = [e for e in range(edges.shape[0]) if int(edges[e, 1]) == int(edges[e, 0]) + 1]
    for side in ("before", "after"):
        out = [kt.size + m for m, t in enumerate(t_new) if (t < kt[0] if side == "before" else t > kt[-1])]
        if not out:
            continue
        if not odo:
            raise InputError(f"stations {side} the keyframes of a graph without odometry edges")
        e_ref = odo[0] if side == "before" else odo[-1]
        L = max(float(np.linalg.norm(Z[e_ref][:3, 3])), 1e-9)
        chain = ([0] + out[::-1]) if side == "before" else ([kt.size - 1] + out)
        for u, v in zip(chain[:-1], chain[1:], strict=True):
            Tu = kP[u] if u < kt.size else T_new[u - kt.size]
            Tv = T_new[v - kt.size]
            a, b, Zuv = (v, u, se3_inverse(Tv) @ Tu) if side == "before" else (u, v, se3_inverse(Tu) @ Tv)
            f = float(np.clip(np.linalg.norm(Zuv[:3, 3]) / L, 0.01, 100.0))
            E.append((rank[a], rank[b]))
            ZZ.append(Zuv)
            OO.append(info[e_ref] / f)
    return (all_t[order], np.ascontiguousarray(P_all), np.asarray(E, dtype=np.int64), np.stack(ZZ),
            np.ascontiguousarray(np.stack(OO)))


def _insert_stations(times_s, poses, edges, Z, info, t_st):
    """Graph variables at the station times (see the module docstring): returns the new times,
    poses, edges, measurements, information and the variable of each station."""
    k = times_s.size
    var_of = np.full(t_st.size, -1, dtype=np.int64)
    new_t = []
    for q, t in enumerate(t_st):
        hit = np.flatnonzero(np.abs(times_s - t) <= SAME_TIME_S)
        if hit.size:
            var_of[q] = hit[0]
        else:
            new_t.append((t, q))
    all_t = np.r_[times_s, [t for t, _ in new_t]]
    order = np.argsort(all_t, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    T_new = np.empty((all_t.size, 4, 4))
    T_new[:k] = poses
    if new_t:
        T_new[k:] = interpolate_poses(times_s, poses, np.array([t for t, _ in new_t]))
    for m, (_, q) in enumerate(new_t):
        var_of[q] = k + m
    # split consecutive keyframe edges that contain inserted variables
    E, ZZ, OO = [], [], []
    inserted = np.arange(k, all_t.size)
    ins_t = all_t[k:]
    for e in range(edges.shape[0]):
        a, b = int(edges[e, 0]), int(edges[e, 1])
        inside = inserted[(ins_t > times_s[min(a, b)]) & (ins_t < times_s[max(a, b)])] if abs(b - a) == 1 else []
        if len(inside) == 0 or b != a + 1:
            E.append((a, b))
            ZZ.append(Z[e])
            OO.append(info[e])
            continue
        xi = se3_log(np.ascontiguousarray(Z[e]))
        chain = [a] + sorted(inside.tolist(), key=lambda v: all_t[v]) + [b]
        s = (all_t[chain] - times_s[a]) / (times_s[b] - times_s[a])
        for u in range(len(chain) - 1):
            f = s[u + 1] - s[u]
            E.append((chain[u], chain[u + 1]))
            ZZ.append(se3_exp(f * xi))
            OO.append(info[e] / f)
    edges_new = rank[np.asarray(E, dtype=np.int64)]
    T_sorted = np.empty_like(T_new)
    T_sorted[rank] = T_new
    return all_t[order], T_sorted, edges_new, np.stack(ZZ), np.stack(OO), rank[var_of], len(new_t)
