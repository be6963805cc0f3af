"""Scaling of ``minegeo prepare-map`` with the input size (issue 19): time and peak RSS.

Synthetic map tiles: points on the walls, floor and roof of a drift 200 m long, 5 m wide, 4 m
high, with a 60 m cross-cut (about 4 700 m² of rock surface), with 1 cm noise, written
as binary little-endian PLY float32 in local coordinates (``comment minegeo origin``, a projected
offset of 352 000 / 4 150 000 / 120 m). Every size covers the **same extent**: only the density
grows, so the downsampled map (voxel 0.5 m) has the same size at every n and the ICP target
(voxel 0.1 m, ~0.5 M cells) is saturated from 10^7 points on: a flat peak memory from 10^7 to
10^8 means the preparation does not depend on the input size.
Files are generated chunk by chunk (10^6 points at a time) into ``~/.cache/minegeo_bench/``
and reused.

Each size runs ``python -m minegeo prepare-map --map F --out O.npz`` (default profile) in a
fresh process; wall time is measured around it and peak RSS from ``os.wait4`` (``ru_maxrss``
of that process). A power law ``t = c n^a`` is fitted (least squares in log-log) over the sizes
run. Writes ``benchmarks/results/prepare_scaling_<date>.{json,md}``.

With ``--georef`` each tile is also georeferenced (``minegeo georef``, 8 synthetic control points,
rigid; an x, y, z-only PLY is streamed): wall time and peak RSS (``--no-prepare``: georef only,
written to ``georef_scaling_<date>.json``).

Run: ``python benchmarks/bench_prepare_scaling.py [--sizes 1e6 1e7 1e8] [--chunk-points N] [--georef]``
(10^6 and 10^7: about a minute on the shared 2-core machine; 10^8: a few minutes more and
1.2 GB of disk).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path.home() / ".cache" / "minegeo_bench" / "prepare_scaling"
ORIGIN = np.array([352_000.0, 4_150_000.0, 120.0])
GEN_CHUNK = 1_000_000
#: (x0, y0, x1, y1) of the drift centre lines, m
DRIFTS = [(0.0, 0.0, 200.0, 0.0), (100.0, 0.0, 100.0, 60.0)]
WIDTH, HEIGHT = 5.0, 4.0


def _drift_points(rng, k: int) -> np.ndarray:
    """``k`` points on the drifts' surfaces (local frame, m), uniform in arc length."""
    lens = np.array([np.hypot(x1 - x0, y1 - y0) for x0, y0, x1, y1 in DRIFTS])
    which = rng.choice(len(DRIFTS), size=k, p=lens / lens.sum())
    seg = np.array(DRIFTS)[which]
    s = rng.uniform(0.0, 1.0, k)
    d = seg[:, 2:] - seg[:, :2]
    along = seg[:, :2] + s[:, None] * d
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / np.hypot(d[:, 0], d[:, 1])[:, None]
    perim = 2 * (WIDTH + HEIGHT)
    t = rng.uniform(0.0, perim, k)
    u = np.where(t < WIDTH, t, np.where(t < WIDTH + HEIGHT, WIDTH, np.where(t < 2 * WIDTH + HEIGHT,
                                                                        2 * WIDTH + HEIGHT - t, 0.0))) - WIDTH / 2
    z = np.where(t < WIDTH, 0.0, np.where(t < WIDTH + HEIGHT, t - WIDTH,
                                          np.where(t < 2 * WIDTH + HEIGHT, HEIGHT, perim - t)))
    P = np.column_stack([along + u[:, None] * nrm, z]) + rng.normal(0.0, 0.01, (k, 3))
    return P


def make_tile(n: int) -> Path:
    """Binary PLY float32 of ``n`` points (generated once, chunk by chunk)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    p = CACHE / f"drifts_{n}.ply"
    if p.exists():
        return p
    tmp = p.with_suffix(".tmp")
    head = ("ply\nformat binary_little_endian 1.0\ncomment minegeo crs EPSG:5186\n"
            f"comment minegeo origin {ORIGIN[0]:.1f} {ORIGIN[1]:.1f} {ORIGIN[2]:.1f}\n"
            f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    rng = np.random.default_rng(n)
    with open(tmp, "wb") as fh:
        fh.write(head.encode("ascii"))
        left = n
        while left:
            k = min(GEN_CHUNK, left)
            fh.write(_drift_points(rng, k).astype("<f4").tobytes())
            left -= k
    tmp.replace(p)
    return p


def run_one(path: Path, out: Path, chunk_points: int | None) -> dict:
    cmd = [sys.executable, "-m", "minegeo", "-q", "prepare-map", "--map", str(path), "--out", str(out), "--force"]
    if chunk_points:
        cmd += ["--chunk-points", str(chunk_points)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode()
    if proc.returncode != 0:
        raise RuntimeError(f"prepare-map failed ({proc.returncode}): {err}")
    rec = json.loads(out.with_name(out.name + ".json").read_text())
    t = rec["timings_s"]
    return {"n_points": rec["n_points"], "file_bytes": path.stat().st_size, "wall_s": wall,
            "peak_rss_gb": ru.ru_maxrss * 1024 / 1e9, "n_down": rec["n_down"], "n_icp_points": rec["n_icp_points"],
            "read_downsample_s": t["read"], "sha256_s": t["sha256"], "features_s": t.get("normals", 0) + t.get("fpfh", 0),
            "icp_target_s": t.get("icp_target", 0), "search_structures_s": sum(t["search_structures"].values()),
            "chunk_points": rec["streaming"]["chunk_points"], "n_chunks": rec["streaming"]["n_chunks"],
            "load_before": os.getloadavg()}


def write_gcps(path: Path) -> None:
    """8 control points of the tile: map coordinates (projected offset) and EPSG:5186 coordinates
    from a known rigid transform (yaw 30 deg), 2 mm noise, sigma 5 mm."""
    rng = np.random.default_rng(1)
    loc = np.array([[0, -2.5, 1], [60, 2.5, 3], [120, -2.5, 0], [200, 2.5, 2], [100, 60, 4], [97.5, 30, 1],
                    [180, -2.5, 4], [30, 2.5, 0]], dtype=float)
    a = np.radians(30.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    crs = loc @ R.T + [201_000.0, 552_000.0, 80.0] + rng.normal(0, 0.002, loc.shape)
    xyz = loc + ORIGIN
    lines = ["# crs: EPSG:5186", "id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m"]
    lines += [f"G{i},{x:.4f},{y:.4f},{z:.4f},{e:.4f},{n:.4f},{h:.4f},0.005,0.005,0.005"
              for i, ((x, y, z), (e, n, h)) in enumerate(zip(xyz, crs, strict=True))]
    path.write_text("\n".join(lines) + "\n")


def make_las_tile(n: int) -> Path:
    """The PLY tile of ``n`` points as LAS 1.2, point format 1 (intensity, return numbers,
    classification, GPS time: 28 B per point), scale 1 mm, offset = the tile's origin; written
    chunk by chunk (random intensity and GPS time, so the streamed georef has fields to carry)."""
    import laspy

    from minegeo.io.chunked import open_point_chunks

    p = CACHE / f"drifts_{n}.las"
    if p.exists():
        return p
    src = make_tile(n)
    chunks = open_point_chunks(src, origin="file")
    hdr = laspy.LasHeader(point_format=1, version="1.2")
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = np.asarray(ORIGIN, dtype=np.float64)
    rng = np.random.default_rng(n)
    tmp = p.with_suffix(".tmp")
    t = 0.0
    with laspy.open(tmp, mode="w", header=hdr, do_compress=False) as wr:
        for c in chunks:
            rec = laspy.ScaleAwarePointRecord.zeros(len(c), header=hdr)
            X = np.round(c / hdr.scales).astype(np.int32)
            rec.X, rec.Y, rec.Z = X[:, 0], X[:, 1], X[:, 2]
            rec.intensity = rng.integers(0, 65535, len(c)).astype(np.uint16)
            rec.gps_time = t + np.arange(len(c)) * 1e-6
            t += len(c) * 1e-6
            wr.write_points(rec)
    tmp.replace(p)
    return p


def run_georef(path: Path) -> dict:
    """``minegeo georef`` of a tile in a fresh process (x, y, z PLY -> PLY, or LAS -> LAS with every
    field carried: both streamed): wall time, peak RSS."""
    gcp = CACHE / "gcps.csv"
    write_gcps(gcp)
    out = CACHE / f"geo_{path.stem}{'.las' if path.suffix == '.las' else '.ply'}"
    cmd = [sys.executable, "-m", "minegeo", "-q", "georef", "--map", str(path), "--gcps", str(gcp), "--out", str(out),
           "--report", str(CACHE / f"geo_{path.stem}_report"), "--model", "rigid"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    for q in (out, out.with_name(out.name + ".georef.json")):
        q.unlink(missing_ok=True)
    import shutil

    shutil.rmtree(CACHE / f"geo_{path.stem}_report", ignore_errors=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"georef failed: {proc.stderr.read().decode()}")
    res = json.loads((CACHE / f"geo_{path.stem}_report" / "result.json").read_text())
    row = {"format": path.suffix[1:], "n_points": int(path.stem.split("_")[-1]), "wall_s": wall, "peak_rss_gb": ru.ru_maxrss * 1024 / 1e9,
           "out_bytes": out.stat().st_size, "status": res["status"],
           "streamed": "transform_and_write_map" in res["timings_s"], "load_before": os.getloadavg()}
    out.unlink()  # 24 B per point: not kept
    return row


def fit_power(rows: list) -> dict:
    n = np.array([r["n_points"] for r in rows], dtype=float)
    t = np.array([r["wall_s"] for r in rows])
    if len(rows) < 2:
        return {}
    a, logc = np.polyfit(np.log(n), np.log(t), 1)
    tr = np.array([r["read_downsample_s"] for r in rows])
    ar = np.polyfit(np.log(n), np.log(tr), 1)[0]
    return {"a_wall": float(a), "c_wall": float(np.exp(logc)), "a_read_downsample": float(ar)}


def markdown(rows: list, fit: dict, meta: dict) -> str:
    lines = [f"prepare-map scaling, {meta['date']} ({meta['machine']})", "",
             "| input points | file | wall time | peak RSS | read+downsample (2 passes) | SHA-256 | normals+FPFH | "
             "ICP target | search structures | map / ICP points | chunks | load (1 min) |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['n_points']:.0e} | {r['file_bytes'] / 1e9:.2f} GB | {r['wall_s']:.1f} s | "
                     f"{r['peak_rss_gb']:.2f} GB | {r['read_downsample_s']:.1f} s | {r['sha256_s']:.1f} s | "
                     f"{r['features_s']:.1f} s | {r['icp_target_s']:.1f} s | {r['search_structures_s']:.1f} s | "
                     f"{r['n_down']} / {r['n_icp_points']} | {r['n_chunks']} x {r['chunk_points']} | "
                     f"{r['load_before'][0]:.2f} |")
    if fit:
        lines += ["", f"Fit over these sizes: wall time ∝ n^{fit['a_wall']:.2f}; read + downsample ∝ "
                      f"n^{fit['a_read_downsample']:.2f}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e6, 1e7])
    ap.add_argument("--chunk-points", type=int, default=None)
    ap.add_argument("--date", default=_dt.date.today().isoformat())
    ap.add_argument("--tag", default="")
    ap.add_argument("--georef", action="store_true", help="also time minegeo georef of each tile (streamed)")
    ap.add_argument("--no-prepare", action="store_true", help="skip prepare-map (with --georef)")
    ap.add_argument("--las", action="store_true", help="with --georef: LAS tiles (point format 1) -> LAS")
    args = ap.parse_args()
    rows, geo_rows = [], []
    for s in args.sizes:
        n = int(s)
        path = make_tile(n)
        if not args.no_prepare:
            r = run_one(path, CACHE / f"drifts_{n}.npz", args.chunk_points)
            print(json.dumps(r), flush=True)
            rows.append(r)
        if args.georef:
            geo_rows.append(run_georef(make_las_tile(n) if args.las else path))
            print(json.dumps(geo_rows[-1]), flush=True)
    if args.no_prepare:
        out = ROOT / "benchmarks" / "results" / f"georef_scaling_{args.date}{args.tag}.json"
        out.write_text(json.dumps({"rows": geo_rows, "load_after": os.getloadavg(),
                                   "machine": f"{os.cpu_count()} cores, shared"}, indent=1))
        return
    fit = fit_power(rows)
    meta = {"date": args.date, "machine": f"{os.cpu_count()} cores, shared", "uname": " ".join(os.uname()),
            "extent": "same extent at every size (density grows)", "drifts": DRIFTS, "profile": "default"}
    out = ROOT / "benchmarks" / "results" / f"prepare_scaling_{args.date}{args.tag}"
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows, "fit": fit, "georef": geo_rows}, indent=1))
    out.with_suffix(".md").write_text(markdown(rows, fit, meta))
    print(markdown(rows, fit, meta))


if __name__ == "__main__":
    main()
