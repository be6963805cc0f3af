"""Stage benchmarks of FPFH and feature RANSAC against Open3D 0.20.

Each ``bench_*`` returns ``{"minegeo_s", "open3d_s", "ratio", "agreement", "compile_s", ...}``
with ``ratio = minegeo_s / open3d_s`` on the same thread count (``numba.get_num_threads()``;
Open3D via ``utility.set_max_threads``). ``benchmarks/bench_registration.py`` imports them.

* :func:`bench_fpfh`: steady state = minimum over ``repeats`` after a warm-up call;
  ``agreement`` = worst per-point relative L1 difference of the descriptors (same normals,
  ``weight="open3d"``).
* :func:`bench_ransac`: both libraries run every seed once, interleaved, with the same
  iteration budget, checkers (edge length + distance), ``ransac_n``, distance and mutual
  filter; times are summed over seeds (feature matching included on both sides).
  ``agreement`` = ``{"minegeo_success", "open3d_success"}``: fraction of seeds whose
  transform is within ``success_deg`` and ``success_m`` of ``T_true`` (or of the
  highest-fitness transform found by either library when ``T_true`` is None).

Run ``python benchmarks/stages_features.py [--voxel 0.05] [--seeds 10]`` for a markdown table
on the 3DMatch redkitchen pair (``../shared/data/3dmatch_redkitchen_pair``) and a synthetic
tunnel T-junction.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np

from minegeo.features import FPFHParams, compute_fpfh
from minegeo.registration.ransac import RansacParams, register_ransac

REPO = Path(__file__).resolve().parents[1]


def _o3d():
    import open3d as o3d

    if hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(int(numba.get_num_threads()))
    return o3d


def _rel_l1(a, b):
    den = np.maximum(np.abs(b).sum(axis=1), 1e-300)
    return np.abs(a - b).sum(axis=1) / den


def bench_fpfh(points, normals, radius_m, max_nn, repeats=3):
    """FPFH (hybrid search included on both sides); agreement = max relative L1 per point."""
    o3d = _o3d()
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    prm = FPFHParams(radius_m=radius_m, max_nn=max_nn, weight="open3d")
    t0 = time.perf_counter()
    compute_fpfh(pts[:50], nrm[:50], prm)
    compile_s = time.perf_counter() - t0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(nrm)
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn)
    mine = theirs = np.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        ours = compute_fpfh(pts, nrm, prm).features
        mine = min(mine, time.perf_counter() - t0)
        t0 = time.perf_counter()
        ref = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pcd, search).data).T
        theirs = min(theirs, time.perf_counter() - t0)
    return {"minegeo_s": mine, "open3d_s": theirs, "ratio": mine / theirs, "agreement": float(_rel_l1(ours, ref).max()),
            "compile_s": compile_s, "threads": int(numba.get_num_threads()), "n": int(pts.shape[0])}


def _errors(T, T_ref):
    dR = T[:3, :3].T @ T_ref[:3, :3]
    ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    return ang, float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3]))


def bench_ransac(src, tgt, src_feat, tgt_feat, params: RansacParams, seeds, budget, T_true=None,
                 success_deg=5.0, success_m=None, minegeo_mode_params: RansacParams | None = None):
    """RANSAC on features, both libraries, same budget; agreement = success rates of both.

    Every seed runs minegeo then Open3D (interleaved, so both see the same machine load)
    with the same iteration budget and confidence (Eq. 8 early stop in both), checkers
    (edge length + distance), ``ransac_n``, distance and mutual filter; feature matching
    is inside the timed call on both sides. ``minegeo_s`` / ``open3d_s`` are the summed
    seconds, ``per_run_s`` the individual calls, ``success`` the per-seed verdicts.
    ``minegeo_mode_params`` (optional, same budget) adds a run of minegeo's own mode
    (distinct samples, least-squares refit) per seed, reported under ``"minegeo_mode"``.
    """
    o3d = _o3d()
    reg = o3d.pipelines.registration
    src = np.ascontiguousarray(src, dtype=np.float64)
    tgt = np.ascontiguousarray(tgt, dtype=np.float64)
    seeds = [int(s) for s in seeds]
    p = replace(params, max_iterations=int(budget))
    d = p.distance_threshold_m
    success_m = 2.0 * d if success_m is None else success_m
    t0 = time.perf_counter()
    register_ransac(src[:200], src[:200], src_feat[:200], src_feat[:200], replace(p, max_iterations=64), seed=0)
    compile_s = time.perf_counter() - t0
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    fs = reg.Feature()
    fs.data = np.ascontiguousarray(np.asarray(src_feat, dtype=np.float64).T)
    ft = reg.Feature()
    ft.data = np.ascontiguousarray(np.asarray(tgt_feat, dtype=np.float64).T)
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(p.edge_length_similarity),
                reg.CorrespondenceCheckerBasedOnDistance(d)]
    mine_T, theirs_T, mine_fit, theirs_fit, mine_t, theirs_t, mine_it = [], [], [], [], [], [], []
    mode_T, mode_t = [], []
    pm = None if minegeo_mode_params is None else replace(minegeo_mode_params, max_iterations=int(budget))
    for s in seeds:
        if pm is not None:
            t0 = time.perf_counter()
            mode_T.append(register_ransac(src, tgt, src_feat, tgt_feat, pm, seed=s).T_target_source)
            mode_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        r = register_ransac(src, tgt, src_feat, tgt_feat, p, seed=s)
        mine_t.append(time.perf_counter() - t0)
        mine_T.append(r.T_target_source)
        mine_fit.append(r.fitness)
        mine_it.append(r.iterations)
        o3d.utility.random.seed(s)
        t0 = time.perf_counter()
        rr = reg.registration_ransac_based_on_feature_matching(
            ps, pt, fs, ft, bool(p.mutual_filter), d, reg.TransformationEstimationPointToPoint(False), int(p.ransac_n),
            checkers, reg.RANSACConvergenceCriteria(int(budget), float(p.confidence)))
        theirs_t.append(time.perf_counter() - t0)
        theirs_T.append(np.asarray(rr.transformation))
        theirs_fit.append(rr.fitness)
    if T_true is None:
        allT = mine_T + theirs_T
        T_true = allT[int(np.argmax(mine_fit + theirs_fit))]

    def ok(Ts):
        return [bool((lambda e: e[0] < success_deg and e[1] < success_m)(_errors(T, T_true))) for T in Ts]

    mine_ok, theirs_ok = ok(mine_T), ok(theirs_T)
    mine_s, theirs_s = float(np.sum(mine_t)), float(np.sum(theirs_t))
    extra = {}
    if pm is not None:
        extra["minegeo_mode"] = {"success": ok(mode_T), "per_run_s": mode_t, "mode": pm.mode,
                                 "refit_iterations": pm.refit_iterations}
    return {**extra,"minegeo_s": mine_s, "open3d_s": theirs_s, "ratio": mine_s / theirs_s,
            "agreement": {"minegeo_success": float(np.mean(mine_ok)), "open3d_success": float(np.mean(theirs_ok))},
            "compile_s": compile_s, "threads": int(numba.get_num_threads()), "seeds": len(seeds),
            "budget": int(budget), "mode": p.mode, "n_source": int(src.shape[0]), "n_target": int(tgt.shape[0]),
            "per_run_s": {"minegeo": mine_t, "open3d": theirs_t},
            "success": {"minegeo": mine_ok, "open3d": theirs_ok},
            "fitness": {"minegeo": mine_fit, "open3d": theirs_fit}, "minegeo_iterations": mine_it,
            "success_rule": {"deg": success_deg, "m": success_m}}


# ----------------------------------------------------------------------------- main


def _prep_3dmatch(voxel):
    o3d = _o3d()
    root = REPO.parent / "shared" / "data" / "3dmatch_redkitchen_pair"
    out = []
    for name in ("cloud_bin_4.ply", "cloud_bin_0.ply"):
        pcd = o3d.io.read_point_cloud(str(root / name)).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        out.append((np.asarray(pcd.points).copy(), np.asarray(pcd.normals).copy()))
    T = np.eye(4)
    T[:3] = np.array(  # gt.log pair (0, 4): maps cloud_bin_4 into cloud_bin_0 (SOURCE.md)
        [[0.979957209, -0.0809359517, 0.181876614, -0.0865004597],
         [0.0980194727, 0.991351448, -0.0869879436, -0.458251665],
         [-0.173272374, 0.103077496, 0.979441054, 0.507580899]])
    return out[0], out[1], T


def _prep_tunnel(voxel, seed=3):
    sys.path.insert(0, str(REPO / "tests" / "registration"))
    from tunnel_fixture_ransac import centerline, local_section, tunnel_map, voxel_down

    from minegeo.geometry import NormalParams, estimate_normals
    from minegeo.geometry.se3 import invert, random_transform, transform_points

    dense = tunnel_map(0)
    M = voxel_down(dense, voxel)
    nm = estimate_normals(M, NormalParams(radius_m=2 * voxel, max_nn=30), orient_towards=centerline()).normals
    rng = np.random.default_rng(seed)
    c = np.array([rng.uniform(-20, 20), 0.0, 0.0])
    G = random_transform(rng, np.pi, 20.0)
    S = voxel_down(transform_points(G, local_section(dense, c, 12.0, rng)), voxel)
    ns = estimate_normals(S, NormalParams(radius_m=2 * voxel, max_nn=30),
                          orient_towards=transform_points(G, c[None])[0]).normals
    return (S, ns), (M, nm), invert(G)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.05, help="3DMatch voxel size (m)")
    ap.add_argument("--tunnel-voxel", type=float, default=0.4, help="tunnel voxel size (m)")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--budget", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    rows = []
    for name, (s, t, T), v in (("3dmatch", _prep_3dmatch(a.voxel), a.voxel),
                               ("tunnel", _prep_tunnel(a.tunnel_voxel), a.tunnel_voxel)):
        f = bench_fpfh(t[0], t[1], 5 * v, 100, a.repeats)
        rows.append((f"fpfh {name} (n={f['n']})", f))
        fs = compute_fpfh(s[0], s[1], FPFHParams(5 * v, 100, "open3d")).features
        ft = compute_fpfh(t[0], t[1], FPFHParams(5 * v, 100, "open3d")).features
        for mode in ("open3d", "minegeo"):
            prm = (RansacParams.open3d_compatible(1.5 * v) if mode == "open3d" else
                   RansacParams(distance_threshold_m=1.5 * v, ransac_n=3, max_validations=None))
            r = bench_ransac(s[0], t[0], fs, ft, prm, range(a.seeds), a.budget, T_true=T)
            rows.append((f"ransac {name} mode={mode}", r))
    print(f"threads: {numba.get_num_threads()}\n")
    print("| stage | minegeo s | Open3D s | ratio | agreement | compile s |")
    print("|---|---|---|---|---|---|")
    for label, r in rows:
        ag = r["agreement"]
        ag = (f"{ag['minegeo_success']:.2f} vs {ag['open3d_success']:.2f}" if isinstance(ag, dict) else f"{ag:.1e}")
        print(f"| {label} | {r['minegeo_s']:.3f} | {r['open3d_s']:.3f} | {r['ratio']:.2f} | {ag} | {r['compile_s']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
