"""Benchmark of :func:`minegeo.localize.gravity.estimate_up` against study-world ground truth (issue 15).

Unlevelled scans (uniformly random rotation of the scan frame) of 10/20/30 m are drawn from study
worlds of wall roughness 0.05 / 0.08 / 0.25 m (``minegeo.synth.make_study_world``, 2 levels joined
by a 6-8 deg ramp): ``--mapped`` scans per length uniformly over the mapped drifts (about a third
of the drift length is the ramp) plus ``--ramp`` scans per length drawn on the ramp only. The true
up in the scan frame is ``R_map_scan.T @ [0, 0, 1]``. A scan is a *ramp scan* when its drift is the
ramp.

Reported per roughness: statuses; on level drifts the angle error of ``up`` (median, p90, max),
the coverage of the stated 95 % ellipse and cone; on ramps how often the truth lies inside the
stated residual-tilt search (tilt within ``tilt_range_deg`` and the cross-drift rest within
``tilt_tolerance_deg``). Writes ``benchmarks/results/gravity_<date>.json`` and ``.md``.

Run: ``python benchmarks/bench_gravity.py [--mapped 7] [--ramp 3] [--date YYYY-MM-DD]``
(about 4-5 min on the shared 2-core machine).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from minegeo.localize.gravity import GravityParams, estimate_up
from minegeo.synth import make_study_world
from minegeo.synth.study import StudyWorld

ROUGHNESS = (0.05, 0.08, 0.25)
LENGTHS = (10.0, 20.0, 30.0)
log = logging.getLogger("bench_gravity")


class _RampOnly(StudyWorld):
    """The same world, scans drawn only on ramp drifts."""

    def _candidates(self, label):
        ks, L = super()._candidates(label)
        keep = [i for i, k in enumerate(ks) if self.world.drifts[k].kind == "ramp"]
        return [ks[i] for i in keep], L[keep]


def _row(sc, world, res, rough, length, source) -> dict:
    up_true = sc.T_map_scan[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    a = res.assess(up_true)
    ev = res.evidence
    return {"roughness_m": rough, "length_m": length, "source": source, "drift": int(sc.drift),
            "kind": world.drifts[sc.drift].kind, "n_points": len(sc.cloud), "status": res.status,
            "reason": res.reason, "angle_deg": a["angle_deg"], "mahalanobis2": a["mahalanobis2"],
            "in_ellipse95": bool(a["in_ellipse95"]), "in_cone95": bool(a["in_cone95"]),
            "tilt_deg": a["tilt_deg"], "cross_deg": a["cross_deg"], "in_search": bool(a["in_search"]),
            "sigma_deg": res.sigma_deg, "cone95_deg": res.cone95_deg,
            "tilt_range_deg": list(res.tilt_range_deg), "tilt_tolerance_deg": res.tilt_tolerance_deg,
            "wall_spread": None if ev is None else ev.wall_spread,
            "walls_slope_deg": None if ev is None else ev.walls_slope_deg,
            "seconds": res.timings_s.get("total", math.nan)}


def _stats(rows: list[dict]) -> dict:
    out = {"n": len(rows)}
    for st in ("ok", "ambiguous", "failed"):
        out[st] = sum(r["status"] == st for r in rows)
    est = [r for r in rows if r["status"] != "failed"]
    ok = [r for r in rows if r["status"] == "ok"]
    if est:
        e = np.array([r["angle_deg"] for r in est])
        out.update(median_deg=float(np.median(e)), p90_deg=float(np.percentile(e, 90)), max_deg=float(e.max()),
                   ellipse95=float(np.mean([r["in_ellipse95"] for r in est])),
                   cone95=float(np.mean([r["in_cone95"] for r in est])),
                   in_search=float(np.mean([r["in_search"] for r in est])),
                   wrong_gt_20deg=int(np.sum(e > 20.0)))
    if ok:
        e = np.array([r["angle_deg"] for r in ok])
        out.update(ok_median_deg=float(np.median(e)), ok_ellipse95=float(np.mean([r["in_ellipse95"] for r in ok])),
                   ok_cone95=float(np.mean([r["in_cone95"] for r in ok])),
                   ok_in_search=float(np.mean([r["in_search"] for r in ok])),
                   ok_wrong_gt_20deg=int(np.sum(e > 20.0)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mapped", type=int, default=7, help="scans per length over all mapped drifts")
    ap.add_argument("--ramp", type=int, default=3, help="extra scans per length on the ramp only")
    ap.add_argument("--date", default=_dt.date.today().isoformat())
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    params = GravityParams()
    rows = []
    t0 = time.perf_counter()
    for wi, rough in enumerate(ROUGHNESS):
        sw = make_study_world(roughness_m=rough, twins="none", unmapped=0, seed=11 + wi)
        ramp_sw = _RampOnly(world=sw.world, map=sw.map, options=sw.options)
        slopes = sw.world.features["ramp_slopes_deg"]
        for length in LENGTHS:
            for source, w, n in (("mapped", sw, args.mapped), ("ramp", ramp_sw, args.ramp)):
                for sc in w.draw_scans(n, length, "mapped", levelled=False, seed=100 + wi):
                    res = estimate_up(sc.cloud.points, params=params)
                    r = _row(sc, sw.world, res, rough, length, source)
                    r["ramp_slope_deg"] = slopes
                    rows.append(r)
                    log.info("%.2f m %2.0f m %-6s %-8s %-9s err %6.2f deg cone95 %5.2f in_search %s (%.1f s)", rough,
                             length, source, r["kind"], r["status"], r["angle_deg"], r["cone95_deg"], r["in_search"],
                             r["seconds"])
    wall = time.perf_counter() - t0
    summary = {}
    for rough in ROUGHNESS:
        rr = [r for r in rows if r["roughness_m"] == rough]
        summary[f"{rough:g}"] = {"level": _stats([r for r in rr if r["kind"] != "ramp"]),
                                 "ramp": _stats([r for r in rr if r["kind"] == "ramp"]),
                                 "level_by_length": {f"{L:g}": _stats([r for r in rr if r["kind"] != "ramp"
                                                                      and r["length_m"] == L]) for L in LENGTHS}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"gravity_{args.date}"
    meta = {"date": args.date, "params": params.__dict__, "wall_s": wall, "n_scans": len(rows),
            "n_ramp_scans": sum(r["kind"] == "ramp" for r in rows),
            "worlds": {f"{r:g}": 11 + i for i, r in enumerate(ROUGHNESS)}}
    stem.with_suffix(".json").write_text(json.dumps({"meta": meta, "summary": summary, "rows": rows}, indent=1,
                                                    default=float))
    lines = [f"# estimate_up on unlevelled study-world scans ({args.date})", "",
             f"{len(rows)} scans ({meta['n_ramp_scans']} on the ramp), wall time {wall:.0f} s. "
             "Error = angle between `up` and the truth; coverage over scans with an estimate (ok + ambiguous).", "",
             "| roughness | drifts | n | ok / amb / failed | median err (deg) | p90 | max | 95 % ellipse | 95 % cone "
             "| truth in tilt search | > 20 deg off (ok only) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for rough in ROUGHNESS:
        for part in ("level", "ramp"):
            s = summary[f"{rough:g}"][part]
            if s["n"] == 0:
                continue
            lines.append(f"| {rough:g} m | {part} | {s['n']} | {s['ok']} / {s['ambiguous']} / {s['failed']} | "
                         f"{s.get('median_deg', math.nan):.2f} | {s.get('p90_deg', math.nan):.2f} | "
                         f"{s.get('max_deg', math.nan):.1f} | {s.get('ellipse95', math.nan):.0%} | "
                         f"{s.get('cone95', math.nan):.0%} | {s.get('in_search', math.nan):.0%} | "
                         f"{s.get('ok_wrong_gt_20deg', 0)} |")
    lines += ["", "Level drifts by scan length (median error deg / 95 % ellipse coverage):", "",
              "| roughness | 10 m | 20 m | 30 m |", "|---|---|---|---|"]
    for rough in ROUGHNESS:
        cells = []
        for L in LENGTHS:
            s = summary[f"{rough:g}"]["level_by_length"][f"{L:g}"]
            cells.append(f"{s.get('median_deg', math.nan):.2f} / {s.get('ellipse95', math.nan):.0%} (n {s['n']})")
        lines.append(f"| {rough:g} m | " + " | ".join(cells) + " |")
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
