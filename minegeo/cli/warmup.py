"""``minegeo warmup``: compile every Numba kernel now and report the time per subpackage."""

from __future__ import annotations

HELP = "compile (or load from cache) all Numba kernels and report compile time"


def add_arguments(parser) -> None:
    parser.add_argument("--module", action="append", default=None, metavar="NAME",
                        help="only this subpackage, e.g. minegeo.localize (repeatable; default all)")


def run(args) -> int:
    from minegeo import warmup

    times = warmup(modules=args.module)
    for name, sec in times.items():
        print(f"{name:<24} {sec:7.2f} s")
    print(f"{'total':<24} {sum(times.values()):7.2f} s")
    return 0
