"""``minegeo demo``: the whole chain on the built-in small synthetic mine.

Steps (each through the same CLI verb a surveyor would run, so the demo exercises the
real contracts and writes the real reports):

1. ``minegeo synth``   - generate the small mine: map, local scans, trajectories, GCPs, truth.
2. ``minegeo georef``  - georeference the map into EPSG:5186 from the GCPs.
3. ``minegeo mast``    - position a 2D scanner from wall beacons (synthetic MAST scenario).
4. ``minegeo localize`` - place three local scans and their trajectories in the CRS
   (``--profile fast``, the CLI default: 1 m voxels, 3-point RANSAC, point-to-plane ICP; the
   paper-faithful Table 3 profile is ``--profile table3``, see docs/localization.md).

A summary table compares every answer with the synthetic ground truth; it is printed and
written to ``OUT/report.html`` (:mod:`minegeo.report.demo_report`) with a relative link to each
step's own ``report.html``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

HELP = "run the whole chain on the built-in small synthetic mine and print a summary"

log = logging.getLogger(__name__)


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="minegeo-demo", help="output directory (default ./minegeo-demo)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing demo directory")


def _run_verb(argv: list[str]) -> int:
    from minegeo.cli import main

    return main(["-q", *argv])


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _err_m(T_est, T_true) -> tuple[float, float]:
    from minegeo.geometry.se3 import rotation_angle

    T_est, T_true = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    # remove a similarity scale before comparing rotations (polar decomposition)
    U, _, Vt = np.linalg.svd(T_est[:3, :3])
    T_est = T_est.copy()
    T_est[:3, :3] = U @ Vt
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    dr = float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])))
    return dt, dr


def run(args) -> int:
    from minegeo._output import output_lock
    from minegeo.errors import InputError

    out = Path(args.out)
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not args.force:
        raise InputError(f"{out} exists and is not empty; use --force or another --out")
    # one demo at a time per folder; each step below stages and commits its own result folder
    with output_lock("demo", "--out", out):
        return _run(args, out)


def _row(step: str, t0: float | None, status: str, result: str, report: Path | None, out: Path) -> dict:
    """One summary row; ``report`` is linked relative to ``out`` when the step wrote it."""
    rel = report.relative_to(out).as_posix() if report is not None and report.is_file() else None
    return {"step": step, "time_s": None if t0 is None else time.perf_counter() - t0, "status": status,
            "result": result, "report": rel}


class _Rows(list):
    """The summary rows; each appended row advances the demo's progress bar."""

    def __init__(self, bar):
        super().__init__()
        self.bar = bar

    def append(self, row) -> None:
        super().append(row)
        self.bar.set_postfix_str(str(row.get("step", "")))
        self.bar.update(1)


def _run(args, out: Path) -> int:
    import sys

    from tqdm import tqdm

    from minegeo._output import progress_enabled

    with tqdm(total=6, desc="demo", unit="step", file=sys.stderr, disable=not progress_enabled(args)) as bar:
        return _steps(args, out, _Rows(bar))


def _steps(args, out: Path, rows) -> int:
    t_start = time.perf_counter()
    mine = out / "mine"

    # 1. synthetic mine
    t0 = time.perf_counter()
    argv = ["synth", str(mine), "--preset", "small", "--seed", str(args.seed)]
    if args.force:
        argv.append("--force")
    if _run_verb(argv) != 0:
        return 1
    truth = _json(mine / "truth.json")
    rows.append(_row("synth", t0, "ok", f"small mine written to {mine}", mine / "report.html", out))

    # 2. georeference the map
    t0 = time.perf_counter()
    geo_dir = out / "georef"
    geo_map = out / "map_geo.ply"
    rc = _run_verb(["georef", "--map", str(mine / "map.ply"), "--gcps", str(mine / "gcps.csv"),
                    "--crs", "EPSG:5186", "--out", str(geo_map), "--report", str(geo_dir), "--force"])
    if rc == 0:
        g = _json(geo_dir / "result.json")
        T_est = g.get("T_crs_map") or g.get("result", {}).get("T_crs_map")
        dt, dr = _err_m(T_est, truth["T_crs_map"]) if T_est is not None else (float("nan"),) * 2
        rows.append(_row("georef", t0, str(g.get("status")),
                         f"status {g.get('status')}, sigma0 {g.get('result', {}).get('sigma0', float('nan')):.3f}, "
                         f"vs truth {dt * 1000:.1f} mm / {dr * 3600:.1f}\"", geo_dir / "report.html", out))
    else:
        rows.append(_row("georef", None, "failed", f"failed (exit {rc})", geo_dir / "report.html", out))

    # 3. MAST beacon positioning
    t0 = time.perf_counter()
    from minegeo.mast.scenario import write_mast_scenario

    mast_in = out / "mast_scenario"
    paths = write_mast_scenario(mast_in, seed=args.seed)
    rc = _run_verb(["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]),
                    "--out", str(out / "mast")])
    m = _json(out / "mast" / "result.json") if (out / "mast" / "result.json").exists() else {}
    mt = _json(paths["truth"])
    if m.get("status") == "ok":
        dpos = float(np.hypot(m["x"] - mt["x_m"], m["y"] - mt["y_m"]))
        daz = (m["azimuth_deg"] - mt["azimuth_deg"] + 180.0) % 360.0 - 180.0
        rows.append(_row("mast", t0, "ok",
                         f"x {m['x']:.4f} y {m['y']:.4f} az {m['azimuth_dms']}; vs truth "
                         f"{dpos * 1000:.2f} mm / {abs(daz) * 3600:.1f}\"; 95% ellipse "
                         f"a={m['ellipse95']['a_m'] * 1000:.2f} mm", out / "mast" / "report.html", out))
    else:
        rows.append(_row("mast", None, str(m.get("status") or "failed"),
                         f"status {m.get('status')}: {m.get('reason')} (exit {rc})", out / "mast" / "report.html", out))

    # 4. localize the local scans
    from minegeo.cli import VERBS

    if "localize" in VERBS:
        try:
            __import__(VERBS["localize"])
            have_localize = True
        except ImportError:
            have_localize = False
        if have_localize:
            scans = truth.get("scans", [])
            for sc in scans[:3]:
                t0 = time.perf_counter()
                name = Path(sc["file"]).stem if "file" in sc else sc.get("name", "scan")
                dest = out / "localize" / name
                argv = ["localize", "--map", str(geo_map if geo_map.exists() else mine / "map.ply"),
                        "--scan", str(mine / sc["file"]), "--out", str(dest), "--seed", str(args.seed),
                        "--profile", "fast"]
                if sc.get("trajectory"):
                    argv += ["--trajectory", str(mine / sc["trajectory"])]
                rc = _run_verb(argv)
                res = dest / "result.json"
                if not res.exists():
                    rows.append(_row(f"localize {name}", None, "failed", f"failed (exit {rc})", None, out))
                    continue
                r = _json(res)
                txt = f"status {r['status']}"
                if r.get("T_map_scan") is not None and r.get("inlier_rmse_m") is not None:
                    dt, dr = _err_m(r["T_map_scan"], sc["T_map_scan"])
                    txt += f", inlier RMSE {r['inlier_rmse_m']:.3f} m, vs truth {dt:.3f} m / {dr:.2f} deg"
                if r["status"] != "ok":
                    txt += f" ({r.get('reason')})"
                rows.append(_row(f"localize {name}", t0, str(r["status"]), txt, dest / "report.html", out))

    from minegeo.report.demo_report import write_demo_report

    total = time.perf_counter() - t_start
    report = write_demo_report(out / "report.html", rows, args.seed, total,
                               {"preset": "small", "crs": "EPSG:5186", "localize profile": "fast",
                                "localized scans": "first 3"})
    from minegeo._output import run_timings
    from minegeo._provenance import versions, write_json_atomic

    write_json_atomic(out / "result.json", {
        "command": "demo", "status": "ok" if all(r.get("status") == "ok" for r in rows) else "warnings",
        "seed": int(args.seed), "steps": list(rows),
        "parameters": {"preset": "small", "crs": "EPSG:5186", "localize_profile": "fast", "localized_scans": 3},
        "timings_s": {"total": total, **run_timings(args)}, "versions": versions(),
    })
    w = max(len(r["step"]) for r in rows)
    print(f"\nminegeo demo (seed {args.seed}) - outputs in {out}/")
    print(f"{'step':<{w}}  {'time':>7}  result")
    for r in rows:
        t = "-" if r["time_s"] is None else f"{r['time_s']:.1f} s"
        print(f"{r['step']:<{w}}  {t:>7}  {r['result']}")
    print(f"{'total':<{w}}  {total:6.1f}s  (includes one-time Numba compilation on a fresh install)")
    print(f"report: {report}")
    return 0
