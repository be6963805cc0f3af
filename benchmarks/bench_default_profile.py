"""Benchmark: which ``--profile`` should ``minegeo localize`` / ``prepare-map`` use by default?

Runs every scan that ``minegeo synth --preset small --seed S`` writes (5 per seed: irregular
roof, X intersection, curve, regular drift, railings) against that seed's map, once per
*configuration* (a list of CLI options, turned into parameters by the CLI's own
``params_from_args``, so the numbers are those of the flags a user types), and counts

* **success**: status ``ok`` and the placed sensor trajectory within 0.10 m of the truth
  (largest error over the trajectory poses, ``truth.json`` ``scans[i].T_map_scan``);
* **wrong ok**: status ``ok`` and an error of 0.10 m or more (must be 0 for a default);
* time: map preparation + its search structures (once per map), and each scan's
  ``localize_scan`` wall time (map already prepared, Numba kernels compiled beforehand by
  ``minegeo.warmup()`` so compile time is not counted).

The map is used as the plain ``map.ply`` (map frame); the georeferencing does not change the
registration (it is done in the map frame, docs/localization.md, *Frames*).

``--levelled`` configurations are measured for information only: the synthetic scans are NOT
levelled (the first sensor pose tilts 0.2-6.8 deg), so they show what happens when the option is
given for a scanner that does not level its output; such an option cannot be a silent default.

Usage::

    python benchmarks/bench_default_profile.py --seeds 0-4 --work bench_out/default_profile \\
        --out benchmarks/results/default_profile_2026-11-25

Writes ``OUT.json`` (every run) and ``OUT.md`` (the table in docs/localization.md).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

#: (name, CLI options, eligible as the default profile, note). Only the two profiles are
#: candidates for the default; the option combinations are measured to say what a user can add
#: when a scan fails, and ``--levelled`` is valid only for a levelling scanner.
CONFIGS = (
    ("table3", ["--profile", "table3"], True, ""),
    ("fast", ["--profile", "fast"], True, ""),
    ("table3 + 1e6-draw floor", ["--profile", "table3", "--ransac-min-iterations", "1000000"], False,
     "option on top of a profile"),
    ("fast + 3 RANSAC runs", ["--profile", "fast", "--ransac-runs", "3"], False, "option on top of a profile"),
    ("fast + 4 hypotheses", ["--profile", "fast", "--hypotheses", "4"], False, "option on top of a profile"),
    ("fast --levelled 3", ["--profile", "fast", "--levelled", "3"], False,
     "scans NOT levelled: only valid for a levelling scanner"),
)

SUCCESS_M = 0.10


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def _params(opts: list[str]):
    """(PrepareParams, LocalizeParams) exactly as ``minegeo localize OPTS`` builds them."""
    from minegeo.cli import build_parser
    from minegeo.cli.localize import params_from_args

    args = build_parser(["localize"]).parse_args(["localize", "--map", "m", "--scan", "s", "--out", "o", *opts])
    return params_from_args(args)


def _world(work: Path, seed: int) -> Path:
    from minegeo.synth import write_world

    d = work / f"small_seed{seed}"
    if not (d / "truth.json").exists():
        write_world(d, "small", seed, force=True)
    return d


def run(seeds: list[int], work: Path, configs, log=print) -> list[dict]:
    import minegeo
    from minegeo.io import read_point_cloud, read_trajectory
    from minegeo.localize import localize_scan, prepare_map
    from minegeo.localize.pipeline import error_vs_truth

    t0 = time.perf_counter()
    minegeo.warmup()
    log(f"warm-up (Numba cache): {time.perf_counter() - t0:.1f} s")
    records = []
    for seed in seeds:
        d = _world(work, seed)
        truth = json.loads((d / "truth.json").read_text())
        cloud = read_point_cloud(d / "map.ply")
        scans = []
        for sc in truth["scans"]:
            traj = read_trajectory(d / sc["trajectory"], frame="scan")
            pts = np.asarray(traj.poses)[:, :3, 3] + np.asarray(traj.origin)
            scans.append((sc, read_point_cloud(d / sc["file"]), traj, pts))
        for name, opts, _eligible, _note in configs:
            prep, lp = _params(opts)
            t1 = time.perf_counter()
            pm = prepare_map(cloud, prep)
            t_prep = time.perf_counter() - t1
            t1 = time.perf_counter()
            idx = pm.build_indexes(lp)
            t_idx = time.perf_counter() - t1
            for sc, scan, traj, pts in scans:
                t1 = time.perf_counter()
                try:
                    r = localize_scan(pm, scan, traj, lp, seed=0)
                    status, reason = r.status, r.reason
                    err = error_vs_truth(r.T_map_scan, np.asarray(sc["T_map_scan"]), pts)["max_point_error_m"]
                except Exception as exc:  # noqa: BLE001 - a typed error is a result too
                    status, reason, err = "error", f"{type(exc).__name__}: {exc}", math.nan
                wall = time.perf_counter() - t1
                rec = {"seed": seed, "scan": sc["name"], "section": sc["section"], "sensor": sc["sensor"]["model"],
                       "length_m": sc["length_m"], "config": name, "options": opts, "status": status,
                       "reason": reason, "error_m": err, "localize_s": wall, "map_prepare_s": t_prep,
                       "map_indexes_s": t_idx, "map_index_parts_s": idx}
                records.append(rec)
                log(f"seed {seed} {sc['name']} {sc['section']:15s} {name:26s} {status:9s} "
                    f"err {err:8.3f} m  {wall:6.2f} s")
    return records


def summarize(records: list[dict], configs) -> list[dict]:
    rows = []
    for name, opts, eligible, note in configs:
        rs = [r for r in records if r["config"] == name]
        if not rs:
            continue
        ok = [r for r in rs if r["status"] == "ok"]
        good = [r for r in ok if r["error_m"] < SUCCESS_M]
        wrong = [r for r in ok if not r["error_m"] < SUCCESS_M]
        maps = {(r["seed"]): r["map_prepare_s"] + r["map_indexes_s"] for r in rs}
        t = np.array([r["localize_s"] for r in rs])
        rows.append({
            "config": name, "options": " ".join(opts), "eligible_default": eligible, "note": note, "n": len(rs),
            "success": len(good), "wrong_ok": len(wrong),
            "ambiguous": sum(r["status"] == "ambiguous" for r in rs),
            "failed": sum(r["status"] in ("failed", "error") for r in rs),
            "median_error_ok_m": float(np.median([r["error_m"] for r in good])) if good else math.nan,
            "max_error_ok_m": float(max((r["error_m"] for r in ok), default=math.nan)),
            "localize_median_s": float(np.median(t)), "localize_max_s": float(t.max()),
            "localize_total_s": float(t.sum()),
            "map_median_s": float(np.median(list(maps.values()))),
        })
    return rows


def choose(rows: list[dict]) -> str:
    """Success first, then no wrong ok, then time: the rule of issue 14."""
    cand = [r for r in rows if r["eligible_default"] and r["wrong_ok"] == 0]
    cand.sort(key=lambda r: (-r["success"], r["localize_total_s"] + r["map_median_s"]))
    return cand[0]["config"] if cand else ""


def markdown(rows: list[dict], records: list[dict], seeds, chosen: str) -> str:
    n_scans = len({(r["seed"], r["scan"]) for r in records})
    lines = [f"Scans of `minegeo synth --preset small --seed S`, S = {seeds[0]}..{seeds[-1]} ({n_scans} scans); "
             f"success = `ok` and trajectory error < {SUCCESS_M:.2f} m; wrong ok = `ok` and error >= "
             f"{SUCCESS_M:.2f} m. Times: wall, Numba kernels compiled beforehand; map = preparation + search "
             "structures per map (median over seeds); localize = per scan with the map prepared.", "",
             "| configuration | options | success | wrong ok | ambiguous | failed | median error of successes m "
             "| localize median / max s | all scans s | map s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        flag = f" (info: {r['note']})" if r["note"] else ""
        mark = " **(chosen default)**" if r["config"] == chosen else ""
        lines.append(f"| {r['config']}{mark}{flag} | `{r['options']}` | {r['success']}/{r['n']} | {r['wrong_ok']} | "
                     f"{r['ambiguous']} | {r['failed']} | {r['median_error_ok_m']:.3f} | "
                     f"{r['localize_median_s']:.2f} / {r['localize_max_s']:.2f} | {r['localize_total_s']:.1f} | "
                     f"{r['map_median_s']:.1f} |")
    lines += ["", "Per scan (status / error m):", "",
              "| seed | scan | section | sensor | " + " | ".join(r["config"] for r in rows) + " |",
              "|---|---|---|---|" + "---|" * len(rows)]
    by = {(r["seed"], r["scan"], r["config"]): r for r in records}
    for seed, scan in sorted({(r["seed"], r["scan"]) for r in records}):
        any_r = next(r for r in records if r["seed"] == seed and r["scan"] == scan)
        cells = []
        for row in rows:
            x = by.get((seed, scan, row["config"]))
            cells.append("-" if x is None else f"{x['status']} / {x['error_m']:.3f}")
        lines.append(f"| {seed} | {scan} | {any_r['section']} | {any_r['sensor']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-4", help="synth seeds, e.g. 0-4 or 0,2 (default 0-4)")
    ap.add_argument("--work", default="bench_out/default_profile", help="where the synthetic mines are written")
    ap.add_argument("--out", default="benchmarks/results/default_profile",
                    help="output stem: OUT.json and OUT.md")
    ap.add_argument("--configs", default=None,
                    help="comma-separated configuration names to run (default all: "
                         + ", ".join(c[0] for c in CONFIGS) + ")")
    a = ap.parse_args(argv)
    seeds = _seeds(a.seeds)
    configs = CONFIGS if a.configs is None else tuple(c for c in CONFIGS if c[0] in a.configs.split(","))
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    records = run(seeds, work, configs)
    rows = summarize(records, configs)
    chosen = choose(rows)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from minegeo._provenance import to_jsonable, versions

    doc = {"seeds": seeds, "success_threshold_m": SUCCESS_M, "summary": rows, "chosen_default": chosen,
           "records": records, "wall_s": time.perf_counter() - t0, "machine": platform.platform(),
           "versions": versions()}
    out.with_suffix(".json").write_text(json.dumps(to_jsonable(doc), indent=1, allow_nan=True) + "\n")
    md = markdown(rows, records, seeds, chosen)
    out.with_suffix(".md").write_text(md)
    print(md)
    print(f"chosen default: {chosen}; wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
