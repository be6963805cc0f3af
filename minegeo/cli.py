"""``minegeo <verb>``: the command-line interface.

Each verb lives in its own module exposing ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``; this file only dispatches. User mistakes (any
:class:`~minegeo.errors.MinegeoError`, a missing file) print one clear line to
stderr and exit with status 2, without a traceback. ``--debug`` shows tracebacks.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from minegeo import __version__
from minegeo.errors import MinegeoError

#: verb -> module implementing it. Modules are imported lazily so ``--help`` stays fast.
VERBS: dict[str, str] = {
    "info": "minegeo.io._cli",
    "synth": "minegeo.synth._cli",
    "demo": "minegeo._cli_demo",
    "adjust": "minegeo.survey._cli",
    "mast": "minegeo.mast._cli",
    "georef": "minegeo.localize._cli_georef",
    "prepare-map": "minegeo.localize._cli_prepare",
    "localize": "minegeo.localize._cli_localize",
    "warmup": "minegeo._cli_warmup",
}


def _load(verb: str):
    return importlib.import_module(VERBS[verb])


def build_parser(verbs: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="minegeo",
        description="Survey-grade localization in a mine's official coordinate system, with the math shown.",
    )
    parser.add_argument("--version", action="version", version=f"minegeo {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for verb in verbs if verbs is not None else VERBS:
        try:
            mod = _load(verb)
        except ImportError:
            continue  # verb not available in this build
        p = sub.add_parser(verb, help=getattr(mod, "HELP", ""), description=getattr(mod, "HELP", ""))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # Only import the module of the verb asked for (fast start, and a broken
    # unrelated verb cannot break this one).
    verb = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser([verb] if verb in VERBS else None)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else (logging.WARNING if args.quiet else logging.INFO),
        format="%(message)s",
    )
    if not getattr(args, "_run", None):
        parser.print_help()
        return 0 if args.verb is None else 2
    from minegeo._output import RunClock

    args._clock = RunClock()  # wall time and Numba compile time of this run, reported apart
    try:
        return int(args._run(args) or 0)
    except MinegeoError as exc:
        if args.debug:
            raise
        print(f"minegeo {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError) as exc:
        # e.g. --out naming an existing file, or a path through a file: the user's mistake, not a crash
        if args.debug:
            raise
        name = getattr(exc, "filename", None) or ""
        print(f"minegeo {args.verb}: error: {exc.strerror or exc}: {name}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"minegeo {args.verb}: interrupted", file=sys.stderr)
        return 130
    finally:
        args._clock.close()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
