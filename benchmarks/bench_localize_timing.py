"""Localization timing of the code on ``sys.path``: the five scans of the small synthetic mine.

Used to show that a refactoring is no slower: run it once per version in fresh processes, the
old version first put on the path (``PYTHONPATH=<old checkout>``), alternately, and compare the
medians::

    PYTHONPATH=/tmp/base python benchmarks/bench_localize_timing.py --out old.json
    python benchmarks/bench_localize_timing.py --out new.json

Conditions printed in the JSON: Numba threads, repeats, the scans (synth preset ``small`` seed
11, 6-DOF and ``--levelled 3``, ``--profile fast``, seed 3) and the prepared map (built once and
not timed). Compile time is excluded (one warm-up localization first).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    import numba

    numba.set_num_threads(args.threads)
    import minegeo
    from minegeo.cli import build_parser
    from minegeo.io import read_point_cloud, read_trajectory
    from minegeo.localize import localize_scan, prepare_map
    from minegeo.synth import write_world

    try:
        from minegeo.cli.localize import params_from_args
    except ImportError:  # the layout before the CLIs moved to minegeo/cli/
        from minegeo.localize._cli_localize import params_from_args

    work = Path(tempfile.mkdtemp(prefix="minegeo_timing_"))
    write_world(work / "mine", "small", 11)
    times: dict[str, list[float]] = {}
    status: dict[str, str] = {}
    for levelled in (False, True):
        opts = ["--profile", "fast"] + (["--levelled", "3"] if levelled else [])
        a = build_parser(["localize"]).parse_args(["localize", "--map", "m", "--scan", "s", "--out", "o", *opts])
        pp, lp = params_from_args(a)
        pm = prepare_map(read_point_cloud(work / "mine" / "map.ply"), pp)
        for k in range(5):
            scan = read_point_cloud(work / "mine" / "scans" / f"scan_{k:02d}.ply")
            traj = read_trajectory(work / "mine" / "trajectories" / f"scan_{k:02d}.txt")
            name = f"scan_{k:02d}_{'lev' if levelled else '6dof'}"
            localize_scan(pm, scan, traj, lp, seed=3)  # warm-up (compilation, caches)
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                res = localize_scan(pm, scan, traj, lp, seed=3)
                times.setdefault(name, []).append(time.perf_counter() - t0)
            status[name] = res.status
    med = {n: statistics.median(v) for n, v in times.items()}
    out = {"minegeo": Path(minegeo.__file__).parent.parent.name, "threads": args.threads, "repeat": args.repeat,
           "median_s": med, "status": status, "total_median_s": sum(med.values()), "all_s": times}
    Path(args.out).write_text(json.dumps(out, indent=1))
    sys.stderr.write(f"{out['minegeo']}: total of medians {out['total_median_s']:.2f} s\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
