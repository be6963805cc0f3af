"""The SLAM keyframe graph as the control adjustment's input (:mod:`minegeo.slam.control`): the keyframe
poses, edges and information of a SLAM result, with a variable inserted at every station time; the
control stations' geometry checked (their surveyed coordinates before any work, their points in the map
before any adjustment)."""

from __future__ import annotations

import numpy as np

from minegeo.errors import InputError
from minegeo.kernels.lie import se3_exp, se3_inverse, se3_log
from minegeo.slam.control_factors import station_jacobian

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


#: the control stations determine the rotation about their best-fitting straight line when a turn of
#: one radian about it moves them, jointly, by more than this many standard deviations:
#: ``1/σ_θ > LINE_SIGMAS`` rad⁻¹, ``σ_θ`` the standard deviation of that rotation in the linearised
#: rigid fit with the stations' stated σ (:func:`rotation_about_line`); else the rotation is not
#: determined to better than ``1/LINE_SIGMAS`` rad ≈ 19 deg and no mode places the map. With one
#: station off a line through the others it is about ``d/σ ≤ LINE_SIGMAS`` (``d`` its distance from
#: the line, σ its standard deviation in the direction the turn moves it)
LINE_SIGMAS = 3.0


def rotation_about_line(points, sigma_h_m, sigma_v_m) -> dict:
    """The weakest rotation of a rigid fit to the points: its axis, standard deviation and lever arms.

    The linearised rigid fit (6 parameters: translation ``t`` and small rotation ``φ`` about the
    centroid ``x̄``) of points ``x_k`` observed with ``Σ_k = diag(σ_h², σ_h², σ_v²)`` has the design
    ``B_k = [I, −[x_k − x̄]ₓ]`` and the normal matrix ``N = Σ_k B_kᵀ Σ_k⁻¹ B_k``. With the
    translation eliminated (Schur complement ``S = N_φφ − N_φt N_tt⁻¹ N_tφ``), a rotation about the
    unit axis ``a`` has the standard deviation ``σ = 1/√(aᵀ S a)`` (a priori, σ0 = 1); the weakest
    axis is the eigenvector of the smallest eigenvalue ``λ_min`` of ``S``:
    ``σ_θ = 1/√λ_min`` (rad; ``inf`` when ``λ_min ≤ 0``). For points near one line it is the line's
    direction, and (equal σ, translation uncorrelated) ``1/σ_θ² = Σ_k d_k² / σ_k²``: a turn ``θ``
    about the line moves point ``k`` by ``θ d_k`` (``d_k`` its distance from the line, ``σ_k`` its
    standard deviation in the direction it moves).

    Parameters
    ----------
    points : (n, 3) m
        The stations' points (E N H, or the map's points at the station times).
    sigma_h_m, sigma_v_m : (n,) m
        Their horizontal and vertical standard deviations.

    Returns
    -------
    dict
        ``sigma_rad`` σ_θ (rad) and ``axis`` (3,) of the weakest rotation; ``line`` (3,) the direction
        of the points' best-fitting line through ``x̄`` (first right singular vector of the centred
        points), ``off_m`` (n,) their distances ``d_k`` from it and ``length_m`` their extent along it (m).
    """
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    sh, sv = np.asarray(sigma_h_m, np.float64), np.asarray(sigma_v_m, np.float64)
    w = np.c_[sh**-2, sh**-2, sv**-2]
    xc = X - X.mean(axis=0)
    N = np.zeros((6, 6))
    for x, wk in zip(xc, w, strict=True):
        B = np.c_[np.eye(3), -np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])]
        N += B.T @ (wk[:, None] * B)
    S = N[3:, 3:] - N[3:, :3] @ np.linalg.solve(N[:3, :3], N[:3, 3:])
    lam, V = np.linalg.eigh(0.5 * (S + S.T))
    sigma = float(1.0 / np.sqrt(lam[0])) if lam[0] > 0.0 else float("inf")
    u = np.linalg.svd(xc, full_matrices=False)[2][0]  # the best-fitting line (first right singular vector)
    along = xc @ u
    return {"sigma_rad": sigma, "axis": V[:, 0], "line": u, "off_m": np.linalg.norm(xc - np.outer(along, u), axis=1),
            "length_m": float(along.max() - along.min())}


def _weak_rotation(points, stations) -> tuple[bool, dict]:
    """``(not determined, rotation_about_line(...))`` of the control stations' ``points`` with their σ."""
    c = np.asarray(stations.is_control, dtype=bool)
    g = rotation_about_line(np.asarray(points, dtype=np.float64)[c], np.asarray(stations.sigma_h_m)[c],
                            np.asarray(stations.sigma_v_m)[c])
    return not g["sigma_rad"] * LINE_SIGMAS < 1.0, g


def _ids_and_rule(stations, g) -> tuple[str, str]:
    c = np.asarray(stations.is_control, dtype=bool)
    ids = ", ".join(str(i) for i, k in zip(stations.ids, c, strict=True) if k)
    deg = np.degrees(g["sigma_rad"])
    rule = (f"the rotation about that line is not determined (standard deviation "
            f"{f'{deg:.1f} deg' if deg <= 180.0 else 'over 180 deg'} from the stations' sigma, more than "
            f"{np.degrees(1.0 / LINE_SIGMAS):.1f} deg)")
    return ids, rule


def check_control_geometry(stations, mode: str, where: str = "") -> None:
    """Refuse control stations whose surveyed ``E N H`` lie on one straight line (``InputError``; before any work).

    The rule (:data:`LINE_SIGMAS`): the rotation about the stations' best-fitting line must be
    determined, ``σ_θ < 1/LINE_SIGMAS`` rad with ``σ_θ`` from their stated σ
    (:func:`rotation_about_line`); otherwise no mode (rigid, similarity or graph) places the map.
    The same rule holds for the map's points at the station times (:func:`check_map_geometry`).

    Parameters
    ----------
    stations : minegeo.io.stations.Stations
        With at least one control station (the count is checked by the caller).
    mode : str
        The mode named in the message.
    where : str
        Prefix of the message (``"--control FILE: "``).
    """
    weak, g = _weak_rotation(stations.enh_local, stations)
    if weak:
        ids, rule = _ids_and_rule(stations, g)
        c = np.asarray(stations.is_control, dtype=bool)
        raise InputError(f"{where}the {int(c.sum())} control stations ({ids}) lie on one straight line (at most "
                         f"{g['off_m'].max():.3f} m from it over {g['length_m']:.1f} m): {rule}; the {mode} mode "
                         "needs at least 3 not on one line (make a station off the line control, or add one)")


def check_map_geometry(points_map, stations, mode: str, where: str = "") -> None:
    """Refuse control stations whose points in the SLAM map lie on one straight line (``InputError``).

    The rigid (or similarity) fit and the graph turn the map: the rotation about a line through
    the map's station points ``points_map`` (the run's poses at the station times, C1) is determined
    by their distances from it, whatever the surveyed coordinates say. The rule of
    :func:`check_control_geometry` on ``points_map`` with the stations' σ; checked before any
    adjustment. Surveyed coordinates off the line while the map's points are on it is a station's
    wrong coordinate, time or role (the run passed it on the line), or a straight drive.

    Parameters
    ----------
    points_map : (n, 3) m
        Every station's point in the map (control and check; the control ones are used).
    stations : minegeo.io.stations.Stations
    mode, where : str
        As :func:`check_control_geometry`.
    """
    weak, g = _weak_rotation(points_map, stations)
    if weak:
        ids, rule = _ids_and_rule(stations, g)
        c = np.asarray(stations.is_control, dtype=bool)
        gs = rotation_about_line(np.asarray(stations.enh_local)[c], np.asarray(stations.sigma_h_m)[c],
                                 np.asarray(stations.sigma_v_m)[c])
        raise InputError(f"{where}the {int(c.sum())} control stations ({ids}) lie on one straight line in the SLAM "
                         f"map (the run's points at their times at most {g['off_m'].max():.3f} m from it over "
                         f"{g['length_m']:.1f} m), though their surveyed coordinates lie up to "
                         f"{gs['off_m'].max():.3f} m off their line: {rule}; check the stations' coordinates, times "
                         f"and roles; the {mode} mode needs at least 3 not on one line in the map (make a station "
                         "off the line control, or add one)")


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


def variable_rates_deg_s(slam_result, times_s) -> np.ndarray:
    """The sensor's angular rate (deg/s) at each of ``times_s`` (the graph's variables: keyframes and
    stations), from the run's frame trajectory at the frame nearest each time
    (:func:`minegeo.slam.odometry.keyframe_rates_deg_s`: the frames on either side). A station is a
    stop: its rate is about 0."""
    from minegeo.slam.odometry import keyframe_rates_deg_s

    ft = np.asarray(slam_result.times_s, dtype=np.float64)
    t = np.asarray(times_s, dtype=np.float64).reshape(-1)
    k = np.clip(np.searchsorted(ft, t), 1, ft.size - 1) if ft.size > 1 else np.zeros(t.size, dtype=np.int64)
    if ft.size > 1:
        k = np.where(np.abs(ft[k - 1] - t) <= np.abs(ft[k] - t), k - 1, k)
    return keyframe_rates_deg_s(ft, np.asarray(slam_result.poses, dtype=np.float64), k)


def slam_pose_noise(slam_result, times_s):
    """The keyframe pose noise (k, 6, 6) at ``times_s`` of a SLAM run (:func:`apply_control`'s
    ``pose_noise``): :func:`minegeo.slam.odometry.keyframe_pose_noise` of the run's odometry parameters
    at :func:`variable_rates_deg_s`; None when the run's edges carry no floor
    (``OdometryParams.edge_covariance_floor`` off: GICP's information, no calibrated noise model)."""
    from minegeo.slam.odometry import keyframe_pose_noise

    p = slam_result.params.odometry
    if not p.edge_covariance_floor:
        return None
    return keyframe_pose_noise(variable_rates_deg_s(slam_result, times_s), p)


def graph_pose_noise(times_s, pose_noise, graph_times_s) -> np.ndarray:
    """Each graph variable's own pose noise (nv, 6, 6) from that of the keyframes (``pose_noise``
    (k, 6, 6) at ``times_s``, :func:`minegeo.slam.odometry.keyframe_pose_noise`): a variable on a
    keyframe takes the keyframe's; one inserted between keyframes (a station) the larger of its two
    neighbours', entry by entry (the noise matrices are diagonal). ``pose_noise`` None: zeros."""
    times_s = np.asarray(times_s, dtype=np.float64)
    g = np.asarray(graph_times_s, dtype=np.float64)
    if pose_noise is None:
        return np.zeros((g.size, 6, 6))
    Q = np.asarray(pose_noise, dtype=np.float64)
    lo = np.clip(np.searchsorted(times_s, g), 1, max(times_s.size - 1, 1)) - 1  # the keyframes either side
    hi = np.minimum(lo + 1, times_s.size - 1)
    out = np.maximum(Q[lo], Q[hi])
    on_hi, on_lo = np.abs(times_s[hi] - g) <= SAME_TIME_S, np.abs(times_s[lo] - g) <= SAME_TIME_S
    out[on_hi] = Q[hi][on_hi]
    out[on_lo] = Q[lo][on_lo]
    return out


def station_point_noise(poses, offset, pose_noise) -> np.ndarray:
    """``J Q Jᵀ`` (n, 3, 3): a pose's own noise ``Q`` (n, 6, 6, right perturbation, (ω, ρ)) carried to
    the surveyed point ``p = R·offset + t`` of a station on it, ``J = [−R·hat(offset), R]``."""
    J = station_jacobian(poses, offset)
    C = J @ np.asarray(pose_noise) @ np.swapaxes(J, 1, 2)
    return 0.5 * (C + np.swapaxes(C, 1, 2))


def check_station_statistics(stations, pts, v, st_cov, G_times, G_poses, class_c: float):
    """``(check errors, class tests, misclosure ratios)`` of the check stations (None, None, empty
    without check stations): errors of the estimated points ``pts`` against the surveyed ones, the
    class test against the nearest control station (control residuals ``v``; relative covariance
    from ``st_cov`` without the check-control cross covariance, which the selected inverse does
    not hold), and the ratio 1:N with N the path length to the nearest control over the error."""
    from minegeo.survey.control_stats import check_errors, class_test, misclosure_ratio

    ctrl, chk = stations.is_control, stations.is_check
    ids = np.array(stations.ids, dtype=object)
    if not chk.any():
        return None, None, np.zeros(0)
    check = check_errors(pts[chk], stations.enh_local[chk], ids[chk])
    rel = None
    if st_cov is not None:
        ci, kj = np.flatnonzero(chk), np.flatnonzero(ctrl)
        d = np.hypot(*(stations.enh_local[ci, None, :2] - stations.enh_local[None, kj, :2]).transpose(2, 0, 1))
        near = kj[np.argmin(d, axis=1)]
        rel = st_cov[ci][:, :2, :2] + st_cov[near][:, :2, :2]
    classes = class_test(stations.enh_local[chk], check.delta, stations.enh_local[ctrl], v,
                         check_ids=ids[chk], control_ids=ids[ctrl], c=class_c, relative_cov_h=rel)
    path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(G_poses[:, :3, 3], axis=0), axis=1))]
    s_at = np.interp(stations.t_mid_s, G_times, path)
    tc = np.flatnonzero(ctrl)
    L = np.array([np.min(np.abs(s_at[i] - s_at[tc])) for i in np.flatnonzero(chk)])
    return check, classes, misclosure_ratio(L, check.horizontal)
