"""Do minegeo's ``@njit_parallel`` kernels pay for their compilation? Per kernel: compile CPU seconds
as ``parallel=True`` and as its serial twin, and warm run time on the inputs a verb really gives it.

Three steps (each its own command; the captured inputs live in a scratch folder, not in the repository)::

    # 1. run a verb with every parallel kernel of the scoped modules wrapped: it counts the calls,
    #    times them and keeps copies of the inputs of the first and of the largest call
    NUMBA_NUM_THREADS=2 python benchmarks/bench_parallel_pay.py capture --cap DIR/localize_t2 -- localize --map ...
    NUMBA_NUM_THREADS=1 python benchmarks/bench_parallel_pay.py capture --cap DIR/localize_t1 -- localize --map ...
    # 2. per kernel, in its own process: compile a parallel and a serial twin (``cache=False``, the
    #    same options as minegeo/_jit.py) and time both on the captured inputs (1 and 2 threads,
    #    minimum of --repeat runs); the outputs of serial, parallel@1 and parallel@2 compared bit for bit
    NUMBA_NUM_THREADS=2 python benchmarks/bench_parallel_pay.py measure --cap DIR --out DIR/measure.json
    # 3. the table (json + md) with the decision of each kernel
    python benchmarks/bench_parallel_pay.py report --cap DIR --measure DIR/measure.json \
        --out benchmarks/results/parallel_pay_2026-11-29

Compile seconds are ``time.process_time()`` around ``dispatcher.compile(signature)`` of a fresh twin
(``cache=False``; the kernels it calls are already loaded, so the figure is the kernel's own
compilation), after one throw-away parallel compilation that initialises Numba's parfor machinery.
The serial twin is compiled twice (before and after the parallel one) and the second figure is kept.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the modules whose parallel kernels are in scope (registration/_kernels_gicp.py and slam/ are not)
MODULES = ("minegeo.geometry._kernels", "minegeo.localize._kernels", "minegeo.localize._kernels_gravity",
           "minegeo.features._kernels", "minegeo.registration._kernels", "minegeo.registration._kernels_ransac",
           "minegeo.kernels.kdtree", "minegeo.synth._kernels")
#: keep a kernel parallel when 2 threads could save more than this per run of a verb (s)
PAY_S = 0.2
#: prepare-map's per-point geometry: its work grows with the user's map (10 M points = 85x the example)
MAP_SCALE = ("minegeo.geometry._kernels.normals_hybrid_fused", "minegeo.geometry._kernels.grid_hybrid",
             "minegeo.features._kernels.spfh_kernel", "minegeo.features._kernels.fpfh_kernel")
#: kept parallel for a reason outside the measured verbs (stated in the table)
KEEP_OTHER = {"minegeo.kernels.kdtree.kd_nn_warm_parallel":
              "the parallel twin of kd_nn_warm_serial, chosen by size (>= 4096 query rows, registration/loop.py; "
              ">= 65536 pairs in registration/_kernels_gicp.py): a real LiDAR frame of 100k+ points in slam"}
RULE = (f"keep parallel where 2 threads could save more than {PAY_S} s in one run of a verb on its documented "
        "input (half the kernel's 1-thread seconds in that run, est_1t_s, whose calls are large enough for "
        "two threads to split) and the verb's own 2-thread run (NUMBA_NUM_THREADS=2, same load) did not spend "
        "longer in it than the 1-thread run; or where the kernel is prepare-map's per-point geometry (normals, "
        "neighbour search, FPFH: their work grows with the user's map); else serial (@njit). On this loaded "
        "machine (1-minute load 10 to 25 on 2 cores) the 2-thread figures cannot show the speedup an idle "
        "machine gives, so the first condition uses the ideal split")


def decide(key: str, ideal: float, slower_in_run: bool) -> tuple[str, str]:
    """The decision of the rule for one kernel: ``("parallel" | "serial", why)``."""
    if key in MAP_SCALE:
        return "parallel", "prepare-map per-point work (grows with the map)"
    if key in KEEP_OTHER:
        return "parallel", KEEP_OTHER[key]
    if ideal > PAY_S and not slower_in_run:
        return "parallel", f"2 threads save up to {ideal:.2f} s per run"
    if ideal > PAY_S:
        return "serial", f"up to {ideal:.2f} s per run ideally, but its 2-thread run was slower (many small calls)"
    return "serial", f"2 threads save at most {ideal:.2f} s per run"


def _nbytes(obj) -> int:
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, (tuple, list)):
        return sum(_nbytes(o) for o in obj)
    return 8


def _copy(obj):
    if isinstance(obj, np.ndarray):
        return obj.copy()
    if isinstance(obj, tuple):
        return tuple(_copy(o) for o in obj)
    if isinstance(obj, list):
        return [_copy(o) for o in obj]
    return copy.copy(obj)


def _parallel_dispatchers():
    import importlib

    from numba.core.registry import CPUDispatcher

    out = {}
    for mod in MODULES:
        m = importlib.import_module(mod)
        for name, obj in vars(m).items():
            if isinstance(obj, CPUDispatcher) and obj.targetoptions.get("parallel") and \
                    obj.py_func.__module__ == mod:
                out[f"{mod}.{name}"] = (m, name, obj)
    return out


def capture(args) -> int:
    """Run ``minegeo <argv>`` with the scoped parallel kernels wrapped (Python callers only)."""
    disp = _parallel_dispatchers()
    import minegeo.cli  # noqa: F401 - imports the verbs' modules, whose bindings are patched below

    rec: dict[str, dict] = {}

    def wrap(key, d):
        r = rec.setdefault(key, {"calls": 0, "total_s": 0.0, "first": None, "largest": None, "largest_bytes": -1,
                                 "times": []})

        def w(*a):
            nb = _nbytes(a)
            keep_first = r["first"] is None
            keep_large = nb > r["largest_bytes"] and nb < 400e6
            saved = _copy(a) if (keep_first or keep_large) else None
            t0 = time.perf_counter()
            res = d(*a)
            dt = time.perf_counter() - t0
            r["calls"] += 1
            r["total_s"] += dt
            r["times"].append(dt)
            if keep_first:
                r["first"] = saved
            if keep_large:
                r["largest"], r["largest_bytes"] = saved, nb
            return res

        w.__wrapped__ = d
        return w

    wrappers = {key: wrap(key, d) for key, (m, name, d) in disp.items()}
    by_obj = {id(d): (key, name) for key, (m, name, d) in disp.items()}
    for mname, m in list(sys.modules.items()):
        if not mname.startswith("minegeo") or m is None:
            continue
        last = mname.rsplit(".", 1)[-1]
        for attr, obj in list(vars(m).items()):
            hit = by_obj.get(id(obj))
            if hit is None:
                continue
            # jitted callers must keep the dispatcher; their modules are the _kernels* ones,
            # except the defining module itself, whose Python-level drivers call it too
            if last.startswith("_kernels") or last == "kdtree":
                if mname + "." + attr != hit[0]:
                    continue
            setattr(m, attr, wrappers[hit[0]])
    from minegeo.cli import main

    t0 = time.perf_counter()
    try:
        rc = main(args.argv)
    except SystemExit as e:
        rc = e.code
    wall = time.perf_counter() - t0
    cap = Path(args.cap)
    cap.mkdir(parents=True, exist_ok=True)
    import numba

    meta = {"argv": args.argv, "rc": rc, "wall_s": wall, "threads": numba.get_num_threads(),
            "uptime": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), "kernels": {}}
    for key, r in rec.items():
        if r["calls"] == 0:
            continue
        meta["kernels"][key] = {"calls": r["calls"], "total_s": r["total_s"],
                                "max_call_s": max(r["times"]) if r["times"] else 0.0,
                                "largest_bytes": r["largest_bytes"]}
        with open(cap / f"{key}.pkl", "wb") as fh:
            pickle.dump({"first": r["first"], "largest": r["largest"]}, fh, protocol=pickle.HIGHEST_PROTOCOL)
    (cap / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"rc={rc} wall={wall:.1f}s kernels called: {len(meta['kernels'])}", file=sys.stderr)
    return 0


def _twins(d):
    import numba

    from minegeo._jit import NJIT_OPTIONS

    opts = {**NJIT_OPTIONS, "cache": False}
    return (lambda: numba.njit(**opts)(d.py_func)), (lambda: numba.njit(**{**opts, "parallel": True})(d.py_func))


def _outputs(res, a):
    """Everything a call produced: its return value and its (possibly written) array arguments."""
    return [res, *[x for x in a if isinstance(x, np.ndarray)]]


def _same_bits(x, y) -> bool:
    if isinstance(x, np.ndarray) and isinstance(y, np.ndarray):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    if isinstance(x, (tuple, list)) and isinstance(y, (tuple, list)):
        return len(x) == len(y) and all(_same_bits(p, q) for p, q in zip(x, y, strict=True))
    if isinstance(x, float) and isinstance(y, float):
        return np.float64(x).tobytes() == np.float64(y).tobytes()
    return type(x) is type(y) and x == y


def _measure_one(key: str, pkl: Path, repeat: int) -> dict:
    import numba
    from numba import typeof

    from minegeo._jit import njit_parallel, prange

    @njit_parallel(cache=False)
    def _init(x):  # the parfor machinery's own one-time setup, kept out of the first kernel's figure
        s = 0.0
        for i in prange(x.shape[0]):
            s += x[i]
        return s

    _init(np.ones(4))
    _, _, d = _parallel_dispatchers()[key]
    with open(pkl, "rb") as fh:
        samples = pickle.load(fh)
    a = samples["largest"] if samples["largest"] is not None else samples["first"]
    sig = tuple(typeof(x) for x in a)
    mk_ser, mk_par = _twins(d)
    out = {"kernel": key, "signature": str(sig), "input_bytes": _nbytes(a)}
    c0 = time.process_time()
    mk_ser().compile(sig)
    out["compile_serial_first_s"] = time.process_time() - c0
    par = mk_par()
    c0 = time.process_time()
    par.compile(sig)
    out["compile_parallel_s"] = time.process_time() - c0
    ser = mk_ser()
    c0 = time.process_time()
    ser.compile(sig)
    out["compile_serial_s"] = time.process_time() - c0

    def run(f, threads):
        numba.set_num_threads(threads)
        best, res = np.inf, None
        for _ in range(repeat):
            b = _copy(a)
            t0 = time.perf_counter()
            r = f(*b)
            dt = time.perf_counter() - t0
            best = min(best, dt)
            res = _outputs(r, b)
        return best, res

    out["warm_serial_s"], rs = run(ser, 1)
    out["warm_parallel_1t_s"], r1 = run(par, 1)
    out["warm_parallel_2t_s"], r2 = run(par, 2)
    out["bit_identical_serial_vs_parallel_2t"] = _same_bits(rs, r2)
    out["bit_identical_parallel_1t_vs_2t"] = _same_bits(r1, r2)
    return out


def measure(args) -> int:
    cap = Path(args.cap)
    metas = {m.parent: json.loads(m.read_text()) for m in cap.glob("*/meta.json")}
    keys = sorted({k for m in metas.values() for k, r in m["kernels"].items() if r["calls"]})
    rows = []
    for key in keys:
        if args.only and not any(o in key for o in args.only):
            continue
        # the verb whose captured call was largest
        d = max((d for d, m in metas.items() if m["kernels"].get(key, {}).get("calls")),
                key=lambda d: metas[d]["kernels"][key]["largest_bytes"])
        pk = d / f"{key}.pkl"
        cmd = [sys.executable, __file__, "_one", key, str(pk), str(args.repeat)]
        env = {**os.environ, "NUMBA_NUM_THREADS": "2", "PYTHONPATH": str(ROOT)}
        p = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if p.returncode != 0:
            print(f"{key}: failed\n{p.stderr[-2000:]}", file=sys.stderr)
            rows.append({"kernel": key, "error": p.stderr.strip().splitlines()[-1:]})
            continue
        r = json.loads(p.stdout.strip().splitlines()[-1])
        r["from_capture"] = pk.parent.name
        r["uptime"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
        rows.append(r)
        print(f"{key}: compile par {r['compile_parallel_s']:.2f} ser {r['compile_serial_s']:.2f}  warm ser "
              f"{r['warm_serial_s']:.4f} par1 {r['warm_parallel_1t_s']:.4f} par2 {r['warm_parallel_2t_s']:.4f} "
              f"bits {r['bit_identical_serial_vs_parallel_2t']}", file=sys.stderr, flush=True)
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def report(args) -> int:
    cap = Path(args.cap)
    rows = {r["kernel"]: r for m in args.measure for r in json.loads(Path(m).read_text()) if "error" not in r}
    verbs: dict[str, dict] = {}
    for meta in sorted(cap.glob("*/meta.json")):
        verbs[meta.parent.name] = json.loads(meta.read_text())
    table = []
    for key, r in sorted(rows.items()):
        ratio = r["warm_parallel_2t_s"] / r["warm_serial_s"] if r["warm_serial_s"] > 0 else 1.0
        per_verb = {}
        for vname, meta in verbs.items():
            k = meta["kernels"].get(key)
            if k is None or not k["calls"] or meta["threads"] != 1 or vname.startswith("warmup"):
                continue
            # the verb's 1-thread seconds in the kernel: its in-run total (which includes loading the
            # kernel from the cache on the first call), at most calls x the largest call's warm time
            est = min(k["total_s"], k["calls"] * r["warm_serial_s"])
            per_verb[vname] = {"calls": k["calls"], "total_1t_s_in_run": round(k["total_s"], 4),
                               "est_1t_s": round(est, 4),
                               "saving_2t_s": round(est * max(0.0, 1.0 - ratio), 4),
                               "ideal_saving_2t_s": round(est / 2, 4)}
            t2 = verbs.get(vname[:-3] + "_t2", {}).get("kernels", {}).get(key)
            if t2 is not None:
                per_verb[vname]["total_2t_s_in_run"] = round(t2["total_s"], 4)
        best = max((v["saving_2t_s"] for v in per_verb.values()), default=0.0)
        ideal = max((v["ideal_saving_2t_s"] for v in per_verb.values()), default=0.0)
        slower = any(v.get("total_2t_s_in_run", 0.0) > v["total_1t_s_in_run"] for v in per_verb.values()
                     if v["ideal_saving_2t_s"] == ideal)
        decision, why = decide(key, ideal, slower)
        table.append({**r, "decision": decision, "why": why, "ratio_2t_over_serial": round(ratio, 3),
                      "per_verb": per_verb,
                      "max_saving_per_run_s": round(best, 3), "max_ideal_saving_per_run_s": round(ideal, 3),
                      "compile_extra_s": round(r["compile_parallel_s"] - r["compile_serial_s"], 3)})
    doc = {"rule": RULE,
           "captures": {k: {"argv": v["argv"], "uptime": v["uptime"], "threads": v["threads"],
                            "wall_s": round(v["wall_s"], 1)} for k, v in verbs.items()},
           "rows": table}
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    lines = [f"Rule: {doc['rule']}.", "",
             "| kernel | compile CPU s parallel | serial | warm s serial | parallel 1 thr | parallel 2 thr | "
             "per verb run: calls, est. 1-thr s, in-run s 1 / 2 thr | bits serial = parallel | decision |",
             "|---|---:|---:|---:|---:|---:|---|---|---|"]
    for r in table:
        pv = "; ".join(f"{v[:-3]}: {d['calls']}, {d['est_1t_s']:.3f}, {d['total_1t_s_in_run']:.2f} / "
                       f"{d.get('total_2t_s_in_run', float('nan')):.2f}" for v, d in r["per_verb"].items())
        lines.append(f"| `{r['kernel'].replace('minegeo.', '')}` | {r['compile_parallel_s']:.2f} | "
                     f"{r['compile_serial_s']:.2f} | {r['warm_serial_s']:.4f} | {r['warm_parallel_1t_s']:.4f} | "
                     f"{r['warm_parallel_2t_s']:.4f} | {pv} | {r['bit_identical_serial_vs_parallel_2t']} | "
                     f"**{r['decision']}**: {r['why']} |")
    lines += ["", "Captures (verb, threads, load):", ""]
    lines += [f"* `{k}`: `minegeo {' '.join(v['argv'])}` ; {v['uptime']}" for k, v in doc["captures"].items()]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "_one":
        print(json.dumps(_measure_one(argv[1], Path(argv[2]), int(argv[3]))))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("--cap", required=True)
    c.add_argument("argv", nargs=argparse.REMAINDER)
    m = sub.add_parser("measure")
    m.add_argument("--cap", required=True)
    m.add_argument("--out", required=True)
    m.add_argument("--repeat", type=int, default=7)
    m.add_argument("--only", nargs="*", default=None)
    r = sub.add_parser("report")
    r.add_argument("--cap", required=True)
    r.add_argument("--measure", required=True, nargs="+")
    r.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if args.cmd == "capture":
        if args.argv and args.argv[0] == "--":
            args.argv = args.argv[1:]
        return capture(args)
    return {"measure": measure, "report": report}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
