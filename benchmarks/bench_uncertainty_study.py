"""Benchmark: is the reported 95 % position region calibrated both ways? (issue 15, item 6)

Study worlds of :func:`minegeo.synth.study.make_study_world` (``twins="none"``, ``map_passes=4``:
a survey frame every 2.5 m) at the three wall roughnesses of issue 15 (0.05 / 0.08 / 0.25 m);
in each, ``--n`` "mapped" scans per length (10 / 20 / 30 m) x frame (levelled: z up, random heading;
unlevelled: uniformly random rotation), ZEB-REVO-like walk, 50 000 beams. Parameters exactly as
``minegeo localize --profile fast`` builds them (``+ --levelled 3`` for levelled scans), seed 0 —
i.e. the pipeline as shipped, rival search and polish included.

**The point.** ``position_95_radius_m`` is a region for the *scan origin*: the origin of the scan
frame, which is the translation of ``T_map_scan`` (the reported position). The error scored is
``e = t(T_map_scan) − t(T_map_scan_true)`` (m, map axes); the rotation error
``log(R Rᵀ_true)`` is kept for the 6-D check.

**Per cell** (roughness x length x frame, ``ok`` scans only):

* ``coverage``: share of scans with ``|e| ≤ position_95_radius_m`` (target 93–97 % over the study);
* ``ratio``: ``median_i(r95_i) / RMS`` with ``RMS = sqrt(mean_i |e_i|²)`` over the cell, i.e. the
  median of ``r95_i / RMS`` (target ≤ 3: for a calibrated isotropic Gaussian it is
  ``√7.815 / √3 = 1.61``, for an elongated ellipsoid up to 2.8);
* also the 95 % ellipsoid coverage (``eᵀ Σ_tt⁻¹ e ≤ 7.815``) and the RMS Mahalanobis distance.

Modes::

    # localize (cache the final ICP pairs of every ok scan, score what result.json reports)
    nice -n 5 python benchmarks/bench_uncertainty_study.py run --seeds 21,22 --n 6 \\
        --cache /tmp/unc_study --out benchmarks/results/uncertainty_study_2026-11-26
    # re-score cached scans offline with the estimator of the working tree (seconds, for tuning)
    python benchmarks/bench_uncertainty_study.py offline --seeds 11,12 --cache /tmp/unc_study

``offline`` recomputes :func:`~minegeo.localize.uncertainty.pose_uncertainty` from the cached pairs
(the very arrays the pipeline passed, captured by wrapping the function) and adds the pipeline's
weak-axis polish term, so it reproduces the pipeline's number for the code under test. Statuses come
from the ``run`` that filled the cache (a changed estimator can change the status of a weak scan
through the weak-direction displacement check, which offline mode does not replay).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROUGHNESS = (0.05, 0.08, 0.25)
LENGTHS = (10.0, 20.0, 30.0)
FRAMES = (True, False)  # levelled, unlevelled
CHI2_6D_95 = 12.591587243743977


def _params(levelled: bool):
    """(PrepareParams, LocalizeParams) exactly as ``minegeo localize --profile fast [--levelled 3]``."""
    from minegeo.cli import build_parser
    from minegeo.cli.localize import params_from_args

    opts = ["--profile", "fast"] + (["--levelled", "3"] if levelled else [])
    args = build_parser(["localize"]).parse_args(["localize", "--map", "m", "--scan", "s", "--out", "o", *opts])
    return params_from_args(args)


def cell_key(rough: float, length: float, levelled: bool) -> str:
    return f"{rough:g} m | {length:g} m | {'levelled' if levelled else 'unlevelled'}"


def _draw_seed(world_seed: int, rough: float, length: float, levelled: bool) -> int:
    return int(world_seed * 100_000 + round(rough * 1000) * 100 + int(length) * 2 + int(levelled))


class _Spy:
    """Wraps ``covariance.pose_uncertainty`` and keeps the paired arrays of its last call.

    The pipeline's only call site is :func:`minegeo.localize.covariance.pose_covariance`, which
    looks the name up in the namespace of :mod:`minegeo.localize.covariance`: patch it there.
    """

    def __init__(self):
        import minegeo.localize.covariance as pl

        self.pl = pl
        self.orig = pl.pose_uncertainty
        self.last = None

    def __enter__(self):
        orig = self.orig

        def spy(P_work, Q, Nq, corr, origin_work, params=None, *, check_target=True):
            c = np.asarray(corr, dtype=np.int64)
            P = np.asarray(P_work)
            self.last = {"P": P[c[:, 0]].copy(), "Q": np.asarray(Q)[c[:, 1]].copy(),
                         "N": np.asarray(Nq)[c[:, 1]].copy(), "o": np.asarray(origin_work, float).copy(),
                         "lo": P.min(axis=0), "hi": P.max(axis=0)}
            return orig(P_work, Q, Nq, corr, origin_work, params, check_target=check_target)

        self.pl.pose_uncertainty = spy
        return self

    def __exit__(self, *exc):
        self.pl.pose_uncertainty = self.orig
        return False


def _e6(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    from minegeo.geometry.se3 import log_so3

    return np.r_[log_so3(T_est[:3, :3] @ T_true[:3, :3].T), T_est[:3, 3] - T_true[:3, 3]]


def run(seeds, n: int, cache: Path, log=print, map_passes: int = 4, roughness=ROUGHNESS) -> list[dict]:
    """Localize every scan of the study worlds ``seeds``; cache the pairs of every ``ok`` scan."""
    import minegeo
    from minegeo.localize import localize_scan, prepare_map
    from minegeo.localize.pipeline import error_vs_truth
    from minegeo.synth.study import make_study_world

    minegeo.warmup()
    cache.mkdir(parents=True, exist_ok=True)
    records = []
    for ws in seeds:
        for rough in roughness:
            t0 = time.perf_counter()
            sw = make_study_world(rough, twins="none", seed=int(ws), map_passes=int(map_passes))
            log(f"world seed {ws} roughness {rough:g}: {len(sw.map)} map points, {time.perf_counter() - t0:.0f} s")
            for levelled in FRAMES:
                prep, lp = _params(levelled)
                pm = prepare_map(sw.map, prep)
                pm.build_indexes(lp)
                for length in LENGTHS:
                    scans = sw.draw_scans(n, length, "mapped", levelled=levelled,
                                          seed=_draw_seed(ws, rough, length, levelled))
                    for i, sc in enumerate(scans):
                        t1 = time.perf_counter()
                        with _Spy() as spy:
                            r = localize_scan(pm, sc.cloud, sc.trajectory, lp, seed=0)
                        wall = time.perf_counter() - t1
                        e6 = _e6(r.T_map_scan, sc.T_map_scan)
                        pts = np.asarray(sc.trajectory.poses)[:, :3, 3]
                        ev = error_vs_truth(r.T_map_scan, sc.T_map_scan, pts)
                        u = r.uncertainty or {}
                        name = f"w{ws}_r{rough:g}_{'lev' if levelled else 'unl'}_{length:g}_{i}"
                        rec = {"name": name, "world_seed": int(ws), "roughness_m": rough, "length_m": length,
                               "levelled": levelled, "index": i, "cell": cell_key(rough, length, levelled),
                               "status": r.status, "reason": r.reason, "e6": e6.tolist(),
                               "err_m": float(np.linalg.norm(e6[3:])),
                               "traj_max_err_m": ev["max_point_error_m"], "localize_s": wall,
                               "r95_m": float(r.position_95_radius_m), "h95_m": float(r.horizontal_95_radius_m),
                               "cov_6x6": None if r.covariance_6x6 is None else np.asarray(r.covariance_6x6).tolist(),
                               "information_ratio": u.get("information_ratio"), "sigma_m": r.sigma_m,
                               "weak_axis_polish_term": bool(u.get("weak_axis_polish_term", False)),
                               "polish_shift_6": None if not (r.polish and r.polish["applied"]) else r.polish["shift_6"],
                               "n_pairs": None if spy.last is None else int(spy.last["P"].shape[0]),
                               "uncertainty": {k: v for k, v in u.items() if not isinstance(v, (list, dict))}}
                        if r.status == "ok" and spy.last is not None:
                            np.savez(cache / f"{name}.npz", **spy.last)
                        records.append(rec)
                        log(f"  {rec['cell']} #{i} {r.status:9s} err {1e3 * rec['err_m']:7.1f} mm  r95 "
                            f"{1e3 * rec['r95_m']:7.1f} mm  {wall:4.1f} s")
    return records


# ---------------------------------------------------------------------------------------------- scoring
def score_one(e6: np.ndarray, C: np.ndarray | None) -> dict:
    """Coverage indicators of one covariance (6x6, (ω, t) about the scan origin) for the true error."""
    from minegeo.localize.uncertainty import CHI2_3D_95, radii_95

    et = e6[3:]
    if C is None:
        return {"degenerate": True}
    Ct = C[3:, 3:]
    r95, h95 = radii_95(Ct)
    m2 = float(et @ np.linalg.solve(Ct, et))
    sd = np.sqrt(np.diag(Ct))
    return {"degenerate": False, "r95_m": r95, "h95_m": h95, "err_m": float(np.linalg.norm(et)),
            "in_ball": bool(np.linalg.norm(et) <= r95), "in_plan": bool(np.linalg.norm(et[:2]) <= h95),
            "in_ell3": bool(m2 <= CHI2_3D_95), "m2_3": m2,
            "in_ell6": bool(float(e6 @ np.linalg.solve(C, e6)) <= CHI2_6D_95),
            "z": (et / sd).tolist()}


def summarise(scored: list[dict]) -> dict:
    """Per-cell and overall coverage and ratio; ``scored`` items have ``cell`` and the score_one keys."""
    out = {}
    cells = sorted({s["cell"] for s in scored}, key=_cell_order)
    for key in cells + ["all"]:
        ss = [s for s in scored if (key == "all" or s["cell"] == key) and not s["degenerate"]]
        if not ss:
            continue
        err = np.array([s["err_m"] for s in ss])
        r95 = np.array([s["r95_m"] for s in ss])
        if key == "all":  # the per-cell ratio needs the cell's RMS: pool the per-scan ratios over cells
            ratios = np.concatenate([np.array([s["r95_m"] for s in scored if s["cell"] == c and not s["degenerate"]])
                                     / out[c]["rms_err_m"] for c in cells if c in out])
        else:
            ratios = r95 / math.sqrt(float(np.mean(err ** 2)))
        n = len(ss)
        cov = float(np.mean([s["in_ball"] for s in ss]))
        out[key] = {"n": n, "coverage": cov, "coverage_ci95": _wilson(cov, n),
                    "median_ratio": float(np.median(ratios)),
                    "rms_err_m": float(math.sqrt(np.mean(err ** 2))), "median_err_m": float(np.median(err)),
                    "median_r95_m": float(np.median(r95)), "max_err_over_r95": float(np.max(err / r95)),
                    "ell3": float(np.mean([s["in_ell3"] for s in ss])),
                    "ell6": float(np.mean([s["in_ell6"] for s in ss])),
                    "rms_mahal_3": float(math.sqrt(np.mean([s["m2_3"] for s in ss]) / 3.0)),
                    "rms_z_xyz": np.sqrt(np.mean(np.array([s["z"] for s in ss]) ** 2, axis=0)).tolist()}
    return out


def _cell_order(key: str):
    r, L, f = (p.strip() for p in key.split("|"))
    return (float(r.split()[0]), f != "levelled", float(L.split()[0]))


def _wilson(p: float, n: int) -> list[float]:
    """95 % Wilson interval of a binomial proportion."""
    z = 1.959963984540054
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return [max(0.0, c - h), min(1.0, c + h)]


def table_md(summary: dict, title: str) -> str:
    lines = [title, "",
             "| roughness | length | frame | n ok | coverage (95 % CI) | median r95 / RMS err | RMS err (mm) | "
             "median err (mm) | median r95 (mm) | worst err / r95 | ellipsoid | RMS Mahalanobis/√3 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, s in summary.items():
        lab = ["**all**", "", ""] if key == "all" else [p.strip() for p in key.split("|")]
        lo, hi = s["coverage_ci95"]
        lines.append(f"| {lab[0]} | {lab[1]} | {lab[2]} | {s['n']} | {100 * s['coverage']:.1f} % "
                     f"({100 * lo:.0f}–{100 * hi:.0f}) | {s['median_ratio']:.2f} | {1e3 * s['rms_err_m']:.2f} | "
                     f"{1e3 * s['median_err_m']:.2f} | {1e3 * s['median_r95_m']:.2f} | {s['max_err_over_r95']:.2f} | "
                     f"{100 * s['ell3']:.0f} % | {s['rms_mahal_3']:.2f} |")
    return "\n".join(lines) + "\n"


def terms_md(scored: list[dict]) -> str:
    """Median / 90th percentile share of the data term and of every model term in ``tr(Σ_tt)``."""
    shares: dict[str, list] = {}
    for s in scored:
        u = s["unc"]
        if u.covariance_6x6 is None:
            continue
        tot = float(np.trace(u.covariance_6x6[3:, 3:]))
        shares.setdefault("data", []).append(float(np.trace(u.covariance_data_6x6[3:, 3:])) / tot)
        for name, M in u.model_terms.items():
            shares.setdefault(name, []).append(float(np.trace(M[3:, 3:])) / tot)
    lines = ["| term | scans | median share of tr(Σ_tt) | 90th percentile | max |", "|---|---|---|---|---|"]
    for name, v in shares.items():
        lines.append(f"| {name} | {len(v)} | {np.median(v):.3f} | {np.percentile(v, 90):.3f} | {np.max(v):.3f} |")
    return "\n".join(lines) + "\n"


def offline_scores(records: list[dict], cache: Path, params=None, weak_ratio: float = 1e-2,
                   weak_polish_term: bool = True) -> list[dict]:
    """Re-compute the pipeline's covariance of every cached ``ok`` scan with the working tree's estimator."""
    from minegeo.localize.uncertainty import UncertaintyParams, pose_uncertainty

    prm = replace(params or UncertaintyParams(), degeneracy_ratio=0.0)  # as the pipeline calls it
    out = []
    for rec in records:
        if rec["status"] != "ok":
            continue
        f = cache / f"{rec['name']}.npz"
        if not f.exists():
            continue
        z = np.load(f)
        k = z["P"].shape[0]
        idx = np.arange(k)
        u = pose_uncertainty(z["P"], z["Q"], z["N"], np.column_stack([idx, idx]), z["o"], prm)
        if (u.covariance_6x6 is not None and weak_polish_term and rec["polish_shift_6"] is not None
                and u.information_ratio < weak_ratio):  # as the pipeline (IcpParams.weak_axis_polish_term)
            d6 = np.asarray(rec["polish_shift_6"])
            u = u.with_model_term("weak_axis_polish", np.outer(d6, d6))
        s = score_one(np.asarray(rec["e6"]), u.covariance_6x6)
        s.update(cell=rec["cell"], name=rec["name"], unc=u)
        out.append(s)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("run", "offline"))
    ap.add_argument("--seeds", default="21,22", help="world seeds (each: one world per roughness)")
    ap.add_argument("--n", type=int, default=6, help="scans per world x length x frame")
    ap.add_argument("--cache", default="/tmp/unc_study", help="cached pairs and records")
    ap.add_argument("--out", default=None, help="OUT.json / OUT.md (run mode)")
    ap.add_argument("--map-passes", type=int, default=4, help="survey passes of the map (4: a frame every 2.5 m)")
    ap.add_argument("--roughness", default=",".join(f"{r:g}" for r in ROUGHNESS), help="wall roughnesses (m)")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    cache = Path(args.cache)
    rec_file = cache / f"records_{'_'.join(map(str, seeds))}.json"
    if args.mode == "run":
        t0 = time.perf_counter()
        records = run(seeds, args.n, cache, log=lambda m: print(m, file=sys.stderr, flush=True),
                      map_passes=args.map_passes, roughness=[float(r) for r in args.roughness.split(",") if r])
        wall = time.perf_counter() - t0
        rec_file.write_text(json.dumps(records))
        scored = []
        for rec in records:
            if rec["status"] == "ok":
                s = score_one(np.asarray(rec["e6"]), None if rec["cov_6x6"] is None else np.asarray(rec["cov_6x6"]))
                s["cell"] = rec["cell"]
                scored.append(s)
        summ = summarise(scored)
        n_all = len(records)
        n_ok = sum(r["status"] == "ok" for r in records)
        n_amb = sum(r["status"] == "ambiguous" for r in records)
        title = (f"Study worlds seeds {args.seeds} (`map_passes={args.map_passes}`), {args.n} scans per world x length x frame: "
                 f"{n_all} scans, {n_ok} `ok`, {n_amb} `ambiguous`, {n_all - n_ok - n_amb} `failed`; "
                 f"largest `ok` error {1e3 * max((r['err_m'] for r in records if r['status'] == 'ok'), default=0):.1f} mm; "
                 f"{wall:.0f} s. What `result.json` reports (`position_95_radius_m`, scan origin).")
        md = table_md(summ, title)
        print(md)
        if args.out:
            out = Path(args.out)
            out.parent.mkdir(parents=True, exist_ok=True)
            from minegeo._provenance import to_jsonable, versions

            out.with_suffix(".json").write_text(json.dumps(to_jsonable(
                {"meta": {"seeds": seeds, "n": args.n, "wall_s": wall, "versions": versions()},
                 "summary": summ, "records": records}), indent=1))
            out.with_suffix(".md").write_text(md)
    else:
        records = json.loads(rec_file.read_text())
        scored = offline_scores(records, cache)
        print(table_md(summarise(scored), f"Offline re-score, seeds {args.seeds}"))
        print(terms_md(scored))
    return 0


if __name__ == "__main__":
    sys.exit(main())
