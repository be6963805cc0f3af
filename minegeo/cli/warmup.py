"""``minegeo warmup``: compile every Numba kernel now and report the time per subpackage.

Progress: when a subpackage starts, ``[3/9] minegeo.features ...`` on stderr (not with ``-q``); when it
is done, ``[3/9] minegeo.features      2.10 s`` on stdout; then the total. The seconds are wall
seconds of compiling (or loading from Numba's cache) that subpackage's kernels on tiny inputs.
"""

from __future__ import annotations

import sys

HELP = "compile (or load from cache) all Numba kernels and report compile time"


def add_arguments(parser) -> None:
    parser.add_argument("--module", action="append", default=None, metavar="NAME",
                        help="only this subpackage, e.g. minegeo.localize (repeatable; default all)")


def run(args) -> int:
    from minegeo import _WARMUP_MODULES, warmup

    names = args.module if args.module is not None else _WARMUP_MODULES
    w = max(len(n) for n in names) if names else 8
    w = max(w, len("total"))

    def progress(name: str, i: int, n: int, seconds: float | None) -> None:
        tag = f"[{i}/{n}]"
        if seconds is None:
            if not args.quiet:
                print(f"{tag} {name} ...", file=sys.stderr, flush=True)
        else:
            print(f"{tag} {name:<{w}} {seconds:7.2f} s", flush=True)

    times = warmup(modules=args.module, progress=progress)
    tag = " " * len(f"[{len(names)}/{len(names)}]")
    print(f"{tag} {'total':<{w}} {sum(times.values()):7.2f} s")
    return 0
