"""Find the first stage of ``minegeo localize`` whose output depends on the Numba thread count.

Runs the localization of one scan in a subprocess per thread count (``NUMBA_NUM_THREADS``), with
every stage function of :mod:`minegeo.localize.pipeline` (and of the gravity fallback) wrapped so
that each call's arguments and outputs are reduced to SHA-256 digests of their arrays' bytes
(recursively through dataclasses, tuples, lists and dicts). The digests of the runs are then
compared call by call; the first call whose inputs agree and whose outputs differ is the stage
that breaks bit-identity.

Usage (map prepared with ``minegeo prepare-map``)::

    python benchmarks/check_thread_determinism.py --map map_geo.prepared.npz --scan mine/scans/scan_04.ply \
        --threads 1 2

Prints one line per differing call and exits 1 when a difference is found, 0 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import tempfile

#: Stage functions wrapped in the child (module, attribute).
STAGES = [
    ("minegeo.localize.pipeline", "scan_features"),
    ("minegeo.localize.pipeline", "ransac_hypotheses"),
    ("minegeo.localize.pipeline", "verify_context"),
    ("minegeo.localize.pipeline", "verify_and_decide"),
    ("minegeo.localize.pipeline", "check_rivals"),
    ("minegeo.localize.pipeline", "polish"),
    ("minegeo.localize.pipeline", "pose_covariance"),
    ("minegeo.localize.pipeline", "judge_fit"),
    ("minegeo.localize.pipeline", "place"),
]
#: Lower-level public functions wrapped where they are looked up (module attribute).
INNER = [
    ("minegeo.localize.scan", "prepare_cloud_features"),
    ("minegeo.localize.hypotheses", "register_ransac"),
    ("minegeo.localize.hypotheses", "correlative_candidates"),
    ("minegeo.localize.rivals", "correlative_candidates"),
    ("minegeo.localize.verification", "register_gicp"),
    ("minegeo.localize.verification", "register_icp"),
]


def _is_timing(name) -> bool:
    """Wall-clock fields (seconds measured, never compared)."""
    n = str(name).lower()
    return ("time" in n or "timing" in n or n.startswith("t_")
            or n in ("seconds", "wall_s", "work_s", "build_s", "startup_s"))


def digest(obj, prefix="", out=None, depth=0):
    """``{path: digest}`` of every array / number / string reachable from ``obj``."""
    import numpy as np

    if out is None:
        out = {}
    if depth > 6:
        return out
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        if a.dtype == object:
            for i, v in enumerate(a.reshape(-1)[:64]):
                digest(v, f"{prefix}[{i}]", out, depth + 1)
        else:
            out[prefix] = f"{a.dtype}{a.shape}:" + hashlib.sha256(a.tobytes()).hexdigest()[:16]
    elif isinstance(obj, (bool, int, float, complex, str, bytes, type(None), np.generic)):
        out[prefix] = repr(obj)[:80] if not isinstance(obj, float) else float(obj).hex()
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            if _is_timing(f.name):
                continue
            digest(getattr(obj, f.name, None), f"{prefix}.{f.name}", out, depth + 1)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            if _is_timing(k):
                continue
            digest(v, f"{prefix}[{k!r}]", out, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj[:200]):
            digest(v, f"{prefix}[{i}]", out, depth + 1)
    elif hasattr(obj, "__dict__") and not callable(obj):
        for k, v in vars(obj).items():
            if k.startswith("_") or _is_timing(k):
                continue
            digest(v, f"{prefix}.{k}", out, depth + 1)
    return out


def _child(map_path, scan_path, traj_path, seed, out_path):
    import importlib
    import inspect

    log = []

    def wrap(mod, name):
        m = importlib.import_module(mod)
        f = getattr(m, name, None)
        if f is None or getattr(f, "_wrapped", False):
            return

        sig = inspect.signature(f)

        def g(*a, **k):
            r = f(*a, **k)
            try:  # arguments by name, so that a timings dict passed in is recognised and skipped
                args = dict(sig.bind(*a, **k).arguments)
            except TypeError:
                args = {"args": a, **k}
            log.append({"call": f"{mod}.{name}", "in": digest(args), "out": digest(r)})
            return r

        g._wrapped = True
        setattr(m, name, g)

    for mod, name in STAGES + INNER:
        wrap(mod, name)
    from minegeo.cli.localize import read_scan_inputs
    from minegeo.localize.params import LocalizeParams
    from minegeo.localize.pipeline import localize_scan
    from minegeo.localize.prepared import PreparedMap

    pm = PreparedMap.load(map_path)
    lp = LocalizeParams.fast() if pm.params.features == LocalizeParams.fast().features else LocalizeParams()
    scan, traj, _ = read_scan_inputs(scan_path, traj_path or None, lp)
    res = localize_scan(pm, scan, traj, lp, seed=seed)
    log.append({"call": "result", "in": {}, "out": digest(res)})
    with open(out_path, "w") as fh:
        json.dump(log, fh)


def run(map_path, scan_path, threads, seed=0, traj_path=""):
    """Logs of the runs, one per thread count."""
    logs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for t in threads:
            out = os.path.join(tmp, f"log{t}.json")
            env = {**os.environ, "NUMBA_NUM_THREADS": str(t)}
            subprocess.run([sys.executable, __file__, "--child", map_path, scan_path, traj_path, str(seed), out], env=env,
                           check=True)
            with open(out) as fh:
                logs[t] = json.load(fh)
    return logs


def compare(a, b):
    """Lines describing the differing calls of two logs, first difference first."""
    lines = []
    for k, (ca, cb) in enumerate(zip(a, b, strict=False)):
        if ca["call"] != cb["call"]:
            lines.append(f"call {k}: different call sequence {ca['call']} vs {cb['call']}")
            break
        din = [p for p in ca["in"] if ca["in"].get(p) != cb["in"].get(p)]
        dout = [p for p in set(ca["out"]) | set(cb["out"]) if ca["out"].get(p) != cb["out"].get(p)]
        if din or dout:
            lines.append(f"call {k} {ca['call']}: {len(din)} input(s) differ {din[:4]}, {len(dout)} output(s) "
                         f"differ {sorted(dout)[:6]}")
    if len(a) != len(b):
        lines.append(f"{len(a)} vs {len(b)} calls")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", required=True)
    ap.add_argument("--scan", required=True)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trajectory", default="")
    args = ap.parse_args(argv)
    logs = run(args.map, args.scan, args.threads, args.seed, args.trajectory)
    ref = args.threads[0]
    bad = False
    for t in args.threads[1:]:
        lines = compare(logs[ref], logs[t])
        print(f"threads {ref} vs {t}: {len(logs[ref])} calls, " + ("identical" if not lines else "DIFFERENT"))
        for line in lines:
            print("  " + line)
        bad = bad or bool(lines)
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]), sys.argv[6])
    else:
        sys.exit(main())
