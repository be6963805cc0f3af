"""Stage benchmarks of minegeo.geometry against Open3D 0.20 (voxel, octree, normals).

Each ``bench_*`` function returns ``{"minegeo_s", "open3d_s", "ratio", "agreement",
"compile_s", ...}``: steady-state seconds = minimum over ``repeats`` after one warm-up
call; ``compile_s`` = first call minus steady state (Numba JIT compile or cache load; ~0
when the kernels were already used in this process); ``ratio`` = minegeo_s / open3d_s.
Both libraries run on the same thread count (``numba.get_num_threads()``; Open3D via
``utility.set_max_threads``). ``benchmarks/bench_registration.py`` imports these.

Run ``python benchmarks/stages_geometry.py [--n 100000] [--repeats 5]`` for a markdown table.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from minegeo.geometry import NormalParams, Octree, estimate_normals, voxel_downsample


def _o3d():
    import open3d as o3d

    if hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(int(numba.get_num_threads()))
    return o3d


def _timeit(fn, repeats):
    """(first-call seconds, min steady-state seconds over ``repeats``, last result)."""
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return first, best, out


def make_tunnel(n: int = 100_000, seed: int = 0, radius: float = 2.5, length: float = 30.0):
    """Seeded drift section (arched wall + floor, wavy rough surface, 5 mm noise), metres."""
    rng = np.random.default_rng(seed)
    floor_depth = 0.6 * radius
    n_floor = n // 4
    n_wall = n - n_floor
    a0 = -np.arcsin(floor_depth / radius)
    th = rng.uniform(a0, np.pi - a0, n_wall)
    y = rng.uniform(0.0, length, n_wall)
    r = radius + 0.05 * np.sin(3 * th) * np.cos(1.3 * y) + rng.normal(0.0, 0.005, n_wall)
    wall = np.c_[r * np.cos(th), y, r * np.sin(th)]
    hc = np.sqrt(radius**2 - floor_depth**2)
    floor = np.c_[rng.uniform(-hc, hc, n_floor), rng.uniform(0.0, length, n_floor),
                  -floor_depth + rng.normal(0.0, 0.005, n_floor)]
    return np.vstack([wall, floor])


def _result(first, mine, theirs, agreement, **extra):
    return {"minegeo_s": mine, "open3d_s": theirs, "ratio": mine / theirs if theirs > 0 else np.nan,
            "agreement": agreement, "compile_s": max(0.0, first - mine),
            "threads": int(numba.get_num_threads()), **extra}


def bench_voxel(points, voxel_size_m, repeats=5):
    """Voxel downsampling; agreement = fraction of Open3D centroids reproduced bit-exactly (as sets)."""
    o3d = _o3d()
    pts = np.ascontiguousarray(points, dtype=np.float64)
    first, mine, res = _timeit(lambda: voxel_downsample(pts, voxel_size_m), repeats)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, theirs, d = _timeit(lambda: pcd.voxel_down_sample(voxel_size_m), repeats)
    A = np.asarray(d.points)
    B = res.points
    if A.shape == B.shape:
        A, B = A[np.lexsort(A.T[::-1])], B[np.lexsort(B.T[::-1])]
        agreement = float(np.mean(np.all(A == B, axis=1)))
    else:
        agreement = 0.0
    return _result(first, mine, theirs, agreement, n_out=int(B.shape[0]))


def bench_octree(points, level, repeats=5):
    """minegeo Octree build + closest-to-centre downsample vs Open3D ``convert_from_point_cloud``.

    Open3D has no octree downsampling, so its time is the octree build alone.
    Agreement = fraction of Open3D leaves whose point-index sets minegeo reproduces.
    """
    o3d = _o3d()
    pts = np.ascontiguousarray(points, dtype=np.float64)

    def ours():
        tree = Octree(pts, level)
        return tree, tree.downsample()

    first, mine, (tree, _) = _timeit(ours, repeats)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))

    def theirs_fn():
        oc = o3d.geometry.Octree(max_depth=level)
        oc.convert_from_point_cloud(pcd, size_expand=0.01)
        return oc

    _, theirs, oc = _timeit(theirs_fn, repeats)
    leaves = []

    def collect(node, info):
        if isinstance(node, o3d.geometry.OctreeLeafNode):
            leaves.append(tuple(sorted(node.indices)))
        return False

    oc.traverse(collect)
    mine_leaves = {tuple(tree.leaf_points(k).tolist()) for k in range(tree.n_leaves)}
    agreement = float(np.mean([lf in mine_leaves for lf in leaves])) if leaves else 0.0
    return _result(first, mine, theirs, agreement, n_out=int(tree.n_leaves))


def bench_normals(points, radius_m, max_nn, repeats=5, mode="accurate"):
    """PCA normals, hybrid(radius_m, max_nn) search or KNN(max_nn) when ``radius_m`` is None.

    Agreement = fraction of points within 1e-6 rad of Open3D's normal (up to sign).
    """
    o3d = _o3d()
    pts = np.ascontiguousarray(points, dtype=np.float64)
    params = NormalParams(radius_m=radius_m, max_nn=max_nn, mode=mode)
    first, mine, res = _timeit(lambda: estimate_normals(pts, params), repeats)
    best = np.inf
    ref = None
    for _ in range(max(1, repeats) + 1):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))  # fresh: no stored normals
        t0 = time.perf_counter()
        sp = (o3d.geometry.KDTreeSearchParamKNN(max_nn) if radius_m is None
              else o3d.geometry.KDTreeSearchParamHybrid(radius_m, max_nn))
        pcd.estimate_normals(sp)
        best = min(best, time.perf_counter() - t0)
        ref = np.asarray(pcd.normals)
    ang = np.arctan2(np.linalg.norm(np.cross(ref, res.normals), axis=1), np.abs(np.sum(ref * res.normals, axis=1)))
    return _result(first, mine, best, float(np.mean(ang < 1e-6)), mode=mode,
                   mean_neighbours=float(res.counts.mean()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    pts = make_tunnel(a.n, a.seed)
    rows = [
        ("voxel 0.1 m", bench_voxel(pts, 0.1, a.repeats)),
        ("octree level 8", bench_octree(pts, 8, a.repeats)),
        ("normals hybrid(0.2 m, 30) accurate", bench_normals(pts, 0.2, 30, a.repeats)),
        ("normals hybrid(0.2 m, 30) open3d mode", bench_normals(pts, 0.2, 30, a.repeats, mode="open3d")),
        ("normals knn(30) accurate", bench_normals(pts, None, 30, a.repeats)),
    ]
    print(f"synthetic tunnel, n = {a.n}, seed = {a.seed}, threads = {numba.get_num_threads()}\n")
    print("| stage | minegeo s | Open3D s | ratio | agreement | compile s |")
    print("|---|---|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['minegeo_s']:.4f} | {r['open3d_s']:.4f} | {r['ratio']:.2f} | "
              f"{r['agreement']:.4f} | {r['compile_s']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
