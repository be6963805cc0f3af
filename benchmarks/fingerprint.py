"""Bit-identity fingerprint of minegeo's outputs: CLI verbs and public API functions.

A refactoring that promises "behaviour unchanged" proves it by running this script before and
after and comparing the two JSON files (``--compare``)::

    python benchmarks/fingerprint.py --out /tmp/fp_before.json            # at the old commit
    python benchmarks/fingerprint.py --out /tmp/fp_after.json --compare /tmp/fp_before.json

What is hashed (SHA-256):

* **CLI** (``demo``, ``synth``, ``localize`` 6-DOF and levelled, ``mast``, ``adjust``): every
  output file; ``*.json`` after removing the wall-clock keys of the end-to-end determinism test
  (``timings_s``, ``created_utc``, ``map_preparation.seconds``, :data:`SKIP_KEYS`) and the ``versions`` record;
  ``report.html`` and ``report.txt`` are left out (they print the timings).
* **API**: the numeric fields (arrays and scalars, recursively through dataclasses) of
  ``voxel_downsample``, ``octree_downsample``, ``estimate_normals``, ``compute_fpfh``,
  ``register_icp`` (point-to-point and point-to-plane), ``register_gicp``, ``register_ransac``,
  ``umeyama``, ``helmert2d``, ``helmert3d``, ``adjust_network``, ``icp_point_to_line``,
  ``estimate_up`` on the shared real data and the synthetic mine; timings left out.

The shared data folder is ``../shared/data`` beside the repository (``MINEGEO_SHARED_DATA``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MINEGEO_SHARED_DATA", REPO.parent / "shared" / "data"))
#: wall-clock and process-state keys left out of every JSON record (times; the SLAM modules' times; the
#: streaming reader's first-pass time; a memory estimate from the process's RSS; the demo's background
#: compilation record, which depends on the Numba cache being cold or warm)
SKIP_KEYS = frozenset({"timings_s", "created_utc", "versions", "seconds", "compile_s", "time_s", "build_s",
                       "module_timings_s", "bounds_pass_s", "memory_estimate_peak_bytes", "background_compilation"})
SKIP_FILES = (".html", "report.txt")
_WORK: list[Path] = [Path("/nonexistent")]  # the scratch folder of this run


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in SKIP_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _hash_tree(root: Path) -> dict[str, str]:
    """Hashes of the output files below ``root``; the scratch folder's path inside JSON files is
    replaced by ``<work>`` so that runs in different scratch folders compare equal."""
    out = {}
    for p in sorted(root.rglob("*")):
        if not p.is_file() or p.name.endswith(SKIP_FILES):
            continue
        if p.suffix == ".json":
            data = json.dumps(_strip(json.loads(p.read_text())), sort_keys=True).encode()
            data = data.replace(str(_WORK[0]).encode(), b"<work>")
        elif p.suffix == ".npz":  # a prepared map: its arrays, and its meta JSON without wall-clock
                # keys and without the integrity manifest (it hashes the index records, build times included)
            with np.load(p) as z:
                data = b"".join(json.dumps(_strip({**json.loads(str(z[k])), "integrity": None})).encode() if k == "meta"
                                else z[k].tobytes() for k in sorted(z.files))
            data = data.replace(str(_WORK[0]).encode(), b"<work>")
        else:
            data = p.read_bytes()
        out[str(p.relative_to(root))] = hashlib.sha256(data).hexdigest()[:16]
    return out


def _numeric(obj, h, depth=0):
    """Feed every numeric leaf of ``obj`` into the hash ``h`` (dataclasses, dicts, tuples)."""
    if depth > 6:
        return
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fiub":
            h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, (bool, int, float, np.floating, np.integer)):
        h.update(repr(float(obj)).encode())
    elif isinstance(obj, str):
        h.update(obj.encode())
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            if "timing" in f.name or f.name in SKIP_KEYS or f.name in ("provenance", "params"):
                continue
            _numeric(getattr(obj, f.name), h, depth + 1)
    elif isinstance(obj, dict):
        for k in sorted(obj, key=str):
            if k in SKIP_KEYS or "timing" in str(k):
                continue
            h.update(str(k).encode())
            _numeric(obj[k], h, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _numeric(v, h, depth + 1)


def _fp(obj) -> str:
    h = hashlib.sha256()
    _numeric(obj, h)
    return h.hexdigest()[:16]


def run_cli(work: Path) -> dict[str, str]:
    from minegeo.cli import main

    fp: dict[str, str] = {}
    with contextlib.chdir(work):
        assert main(["-q", "demo", "--out", "demo"]) == 0
        fp.update({f"cli/demo/{k}": v for k, v in _hash_tree(work / "demo").items()})
        assert main(["-q", "synth", "mine", "--preset", "small", "--seed", "11"]) == 0
        mine = work / "mine"
        main(["-q", "georef", "--map", str(mine / "map.ply"), "--gcps", str(mine / "gcps.csv"),
              "--out", "geo/map_geo.ply", "--report", "geo"])
        for k in range(5):
            for tag, extra in (("6dof", []), ("lev", ["--levelled", "3"])):
                out = f"loc_{tag}_{k}"
                main(["-q", "localize", "--map", str(mine / "map.ply"),
                      "--scan", str(mine / "scans" / f"scan_{k:02d}.ply"),
                      "--trajectory", str(mine / "trajectories" / f"scan_{k:02d}.txt"),
                      "--out", out, "--seed", "3", *extra])
                fp.update({f"cli/{out}/{n}": v for n, v in _hash_tree(work / out).items()})
        fp.update({f"cli/geo/{n}": v for n, v in _hash_tree(work / "geo").items() if "prepared" not in n})
        sc = work / "demo" / "mast_scenario"
        main(["-q", "mast", "--scan", str(sc / "scan.csv"), "--beacons", str(sc / "beacons.csv"), "--out", "mast"])
        fp.update({f"cli/mast/{n}": v for n, v in _hash_tree(work / "mast").items()})
        kg = DATA / "krumm_gama_adjustment_examples"
        if kg.exists():
            for i, f in enumerate(sorted(p for p in kg.rglob("*") if p.suffix == ".dat"
                                         and "SOURCE" not in p.name and "README" not in p.name)):
                out = f"adj_{i:02d}"
                main(["-q", "adjust", str(f), "--out", out])  # exit 1 (test failed) is an output too
                fp.update({f"cli/adjust/{f.relative_to(kg)}/{n}": v for n, v in _hash_tree(work / out).items()
                           if (work / out).exists()})
    return fp


def run_api() -> dict[str, str]:
    from minegeo import features, geometry, mast, registration, survey
    from minegeo.io import read_point_cloud

    fp: dict[str, str] = {}
    xyz = lambda p: read_point_cloud(p).points  # noqa: E731
    bun0, bun4 = xyz(DATA / "pcl_bunny_icp" / "bun0.pcd"), xyz(DATA / "pcl_bunny_icp" / "bun4.pcd")
    src, tgt = xyz(DATA / "small_gicp_pair" / "source.ply"), xyz(DATA / "small_gicp_pair" / "target.ply")
    k0, k4 = xyz(DATA / "3dmatch_redkitchen_pair" / "cloud_bin_0.ply"), xyz(DATA / "3dmatch_redkitchen_pair" / "cloud_bin_4.ply")
    fp["api/voxel"] = _fp(geometry.voxel_downsample(src, 0.3))
    fp["api/octree"] = _fp(geometry.octree_downsample(k0, 8))
    s = geometry.voxel_downsample(src, 0.3).points
    t = geometry.voxel_downsample(tgt, 0.3).points
    nrm = geometry.estimate_normals(t, geometry.NormalParams(radius_m=1.0, max_nn=30))
    fp["api/normals"] = _fp(nrm)
    eye = np.eye(4)
    fp["api/icp_p2p_bunny"] = _fp(registration.register_icp(bun0, bun4, eye, registration.ICPParams(
        max_correspondence_distance_m=0.05, max_iterations=50)))
    fp["api/icp_p2plane"] = _fp(registration.register_icp(s, t, eye, registration.ICPParams(
        max_correspondence_distance_m=1.0, method="point_to_plane"), target_normals=nrm.normals))
    fp["api/gicp"] = _fp(registration.register_gicp(s, t, eye, registration.GICPParams(max_correspondence_distance_m=1.0)))
    a = geometry.voxel_downsample(k0, 0.05).points
    b = geometry.voxel_downsample(k4, 0.05).points
    na = geometry.estimate_normals(a, geometry.NormalParams(radius_m=0.1, max_nn=30)).normals
    nb = geometry.estimate_normals(b, geometry.NormalParams(radius_m=0.1, max_nn=30)).normals
    fa = features.compute_fpfh(a, na, features.FPFHParams(radius_m=0.25, max_nn=100))
    fb = features.compute_fpfh(b, nb, features.FPFHParams(radius_m=0.25, max_nn=100))
    fp["api/fpfh"] = _fp(fa)
    fp["api/ransac"] = _fp(registration.register_ransac(b, a, fb.features, fa.features, registration.RansacParams(
        distance_threshold_m=0.075, ransac_n=3, max_iterations=100000, mutual_filter=True), seed=5))
    rng = np.random.default_rng(7)
    p = rng.normal(size=(50, 3))
    fp["api/umeyama"] = _fp(registration.umeyama(p, 1.5 * p @ np.diag([1, -1, -1]) + 3.0 + 0.01 * rng.normal(size=(50, 3)),
                                                  with_scale=True))
    pts = rng.normal(size=(8, 2)) * 100
    fp["api/helmert2d"] = _fp(survey.helmert2d(pts, pts @ [[0.6, -0.8], [0.8, 0.6]] + 5 + rng.normal(size=(8, 2)) * 0.01))
    p3 = rng.normal(size=(8, 3)) * 100
    fp["api/helmert3d"] = _fp(survey.helmert3d(p3, p3 + 5 + rng.normal(size=(8, 3)) * 0.01))
    kg = DATA / "krumm_gama_adjustment_examples"
    for f in sorted(kg.rglob("*.dat")):
        with contextlib.suppress(Exception):
            fp[f"api/adjust/{f.relative_to(kg)}"] = _fp(survey.adjust_network(survey.read_network(f)))
    th = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    wall = np.c_[10 * np.cos(th), 6 * np.sin(th)]
    c, s_ = np.cos(0.05), np.sin(0.05)
    moved = (wall - [0.3, 0.2]) @ np.array([[c, -s_], [s_, c]]).T
    panels = np.c_[wall, np.roll(wall, -1, axis=0)]
    fp["api/mast_icp"] = _fp(mast.icp_point_to_line(moved, panels, np.eye(3)))
    from minegeo.localize.gravity import estimate_up
    fp["api/estimate_up"] = _fp(estimate_up(b))
    return fp


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--compare", help="an earlier fingerprint JSON to compare with")
    ap.add_argument("--only", choices=("cli", "api"))
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "minegeo_fingerprint"),
                    help="scratch folder of the CLI runs (emptied first; give each concurrent run its own)")
    args = ap.parse_args(argv)
    fp: dict[str, str] = {}
    errors: dict[str, str] = {}
    if args.only != "cli":
        try:
            fp.update(run_api())
        except Exception as exc:  # report and go on: the comparison names what is missing
            errors["api"] = f"{type(exc).__name__}: {exc}"
    if args.only != "api":
        # a fixed folder: result.json records absolute output paths
        work = Path(args.work).resolve()
        _WORK[0] = work
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        fp.update(run_cli(work))
    Path(args.out).write_text(json.dumps({"fingerprint": fp, "errors": errors}, indent=1, sort_keys=True))
    sys.stderr.write(f"{len(fp)} fingerprints, errors: {errors}\n")
    if args.compare:
        old = json.loads(Path(args.compare).read_text())["fingerprint"]
        keys = sorted(set(old) | set(fp))
        diff = [k for k in keys if old.get(k) != fp.get(k)]
        for k in diff:
            sys.stderr.write(f"DIFF {k}: {old.get(k)} -> {fp.get(k)}\n")
        sys.stderr.write(f"{len(keys) - len(diff)}/{len(keys)} identical\n")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
