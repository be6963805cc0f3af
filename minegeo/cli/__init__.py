"""``minegeo <verb>``: the command-line interface.

Each verb lives in its own module of this package (``minegeo.cli.<verb>``, listed in
:data:`VERBS`; helpers they share in ``minegeo.cli._common``) exposing ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``; this file only dispatches. Every verb also takes
``--config FILE`` and ``--dump-config`` (:mod:`minegeo.cli._config`, docs/config.md). User mistakes (any
:class:`~minegeo.errors.MinegeoError`, a missing file) print one clear line to
stderr and exit with status 2, without a traceback. ``--debug`` shows tracebacks.

Exit statuses: 0 done; 2 the user's mistake (one line); 3 a bug minegeo detected itself (an
:class:`~minegeo.errors.InternalError`, a violated internal invariant: one line saying it is a bug
and asking for a report, the run's log kept); 1 an unexpected crash (Python's traceback); 130
interrupted (Ctrl-C: one line ``minegeo <verb>: interrupted``, also when the interrupt arrives
inside a compiled Numba kernel, which re-raises it as a ``SystemError`` with the
``KeyboardInterrupt`` as its context); 141 stdout closed by its reader. Outputs are written
through :class:`minegeo._output.OutputTransaction`: on any non-zero status they are left as they were.

One-time Numba compilation is said apart (not with ``-q``): when a run starts compiling kernels that
are not in Numba's cache yet, one line ``compiling numerical kernels for first use (...) ...`` on stderr
before the wait; when a run spent 0.5 s or more compiling and the verb printed no time line of its own
(:func:`minegeo.cli._common.time_line`), one line after it, e.g. ``minegeo slam: 12.3 s of this run was
one-time Numba compilation (cached for later runs)``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from minegeo import __version__
from minegeo.cli import _config
from minegeo.errors import InternalError, MinegeoError

#: verb -> module implementing it. Modules are imported lazily so ``--help`` stays fast.
VERBS: dict[str, str] = {
    "info": "minegeo.cli.info",
    "synth": "minegeo.cli.synth",
    "demo": "minegeo.cli.demo",
    "adjust": "minegeo.cli.adjust",
    "mast": "minegeo.cli.mast",
    "georef": "minegeo.cli.georef",
    "prepare-map": "minegeo.cli.prepare_map",
    "localize": "minegeo.cli.localize",
    "localize-batch": "minegeo.cli.localize_batch",
    "slam": "minegeo.cli.slam",
    "intersections": "minegeo.cli.intersections",
    "track": "minegeo.cli.track",
    "posegraph": "minegeo.cli.posegraph",
    "evaluate": "minegeo.cli.evaluate",
    "warmup": "minegeo.cli.warmup",
}


def _load(verb: str):
    return importlib.import_module(VERBS[verb])


#: About how long each verb's first run compiles on an empty Numba cache, on an idle 2-core machine:
#: the CPU seconds of its documented small example in ``benchmarks/results/first_use_2026-11-29_after_head.json``
#: (``benchmarks/bench_first_use.py``; docs/first_use.md; ``localize`` and ``demo`` scaled by the same-load ratio of
#: ``first_use_2026-11-29_after2.json`` to ``..._after2_base.json``), rounded up to 5 s (0: nothing compiled); ``localize-batch`` and ``demo``
#: compile in two processes at once (half their CPU seconds). Only for the "about N s" of the first-use notice.
COLD_COMPILE_S: dict[str, float] = {
    "synth": 25, "info": 0, "adjust": 0, "mast": 10, "georef": 5, "prepare-map": 55, "localize": 70,
    "localize-batch": 100, "posegraph": 30, "demo": 110, "slam": 85, "evaluate": 10,
    "intersections": 10, "track": 80, "warmup": 220,
}


def _cold_compile_estimate(args) -> float | None:
    """The "about N s" of the first-use notice for ``args.verb`` (None when unknown)."""
    return COLD_COMPILE_S.get(args.verb)


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's one-line error form (no usage block before it; ``--help`` shows usage)."""

    def error(self, message):  # noqa: D102 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _DeferredLog(logging.Handler):
    """Hold a run's log records; they are printed when it ends (success or a bug), and dropped
    when it stops on a user mistake, whose one error line is then all that stderr shows."""

    def __init__(self, target: logging.Handler):
        super().__init__(logging.NOTSET)
        self.target = target
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)

    def finish(self, show: bool) -> None:
        if show:
            for r in self.records:
                if r.levelno >= self.target.level:
                    self.target.handle(r)
        self.records.clear()


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is an interrupt: a ``KeyboardInterrupt``, or an exception whose cause or
    context chain holds one (a Numba dispatcher that meets Ctrl-C inside a compiled kernel raises
    ``SystemError: CPUDispatcher(...) returned a result with an exception set`` from it)."""
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def build_parser(verbs: list[str] | None = None) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="minegeo",
        description="Survey-grade localization in a mine's official coordinate system, with the math shown.",
    )
    parser.add_argument("--version", action="version", version=f"minegeo {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", parser_class=_Parser)
    parser._verb_parsers = {}
    for verb in verbs if verbs is not None else VERBS:
        try:
            mod = _load(verb)
        except ImportError:
            continue  # verb not available in this build
        p = sub.add_parser(verb, help=getattr(mod, "HELP", ""), description=getattr(mod, "HELP", ""))
        mod.add_arguments(p)
        _config.add_config_options(p)  # --config FILE / --dump-config on every verb (docs/config.md)
        p.set_defaults(_run=mod.run)
        parser._verb_parsers[verb] = p
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # Only import the module of the verb asked for (fast start, and a broken
    # unrelated verb cannot break this one).
    verb = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser([verb] if verb in VERBS else None)
    args, dumped = _config.parse_with_config(parser, argv, verb)
    if dumped is not None:
        sys.stdout.write(dumped)
        return 0
    if not getattr(args, "_run", None):
        parser.print_help()
        return 0 if args.verb is None else 2
    # Log records go to stderr ("%(message)s"). With --debug they stream live; otherwise they are
    # held until the run ends, so that a user mistake shows exactly one error line.
    level = logging.DEBUG if args.debug else (logging.WARNING if args.quiet else logging.INFO)
    stream = logging.StreamHandler(sys.stderr)
    stream.setFormatter(logging.Formatter("%(message)s"))
    stream.setLevel(level)
    handler = stream if args.debug else _DeferredLog(stream)
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(min(level, old_level) if old_level else level)
    logging.captureWarnings(True)  # a Python warning is a log record too ("py.warnings")
    show_log = True
    from minegeo._output import RunClock
    from minegeo.cli import _common

    args._clock = RunClock()  # wall time and Numba compile time of this run, reported apart
    shown_before = _common.time_line_shown(False)  # a nested run (demo's steps) keeps the outer's flag
    from minegeo._output import progress_enabled

    notice = None if args.quiet else _common.FirstCompileNotice(args.verb, _cold_compile_estimate(args),
                                                                live=progress_enabled(args))
    from minegeo._provenance import CLI_ARGUMENTS

    # the run's options, recorded in result.json (provenance.arguments) so --config can repeat the run
    options = _config.options_parser(parser._verb_parsers[args.verb], args)
    arguments = CLI_ARGUMENTS.set(_config.arguments_record(options, args))
    try:
        return int(args._run(args) or 0)
    except MinegeoError as exc:
        if args.debug:
            raise
        show_log = False
        print(f"minegeo {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError) as exc:
        # e.g. --out naming an existing file, or a path through a file: the user's mistake, not a crash
        if args.debug:
            raise
        show_log = False
        name = getattr(exc, "filename", None) or ""
        print(f"minegeo {args.verb}: error: {exc.strerror or exc}: {name}", file=sys.stderr)
        return 2
    except InternalError as exc:
        if args.debug:
            raise
        print(f"minegeo {args.verb}: internal error (a bug in minegeo, not a problem with your data): {exc}; "
              "please report it to the minegeo maintainers with the command line, the output of "
              "`minegeo --version` and the traceback that --debug shows", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        show_log = False
        print(f"minegeo {args.verb}: interrupted", file=sys.stderr)
        return 130
    except SystemError as exc:
        if not _interrupted(exc) or args.debug:
            raise
        show_log = False
        print(f"minegeo {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout was closed by its reader (e.g. `minegeo ... | head -1`): the outputs were already
        # committed; stop printing quietly (Python's documented recipe) with the shell's SIGPIPE status
        import os

        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141
    finally:
        CLI_ARGUMENTS.reset(arguments)
        args._clock.close()
        if notice is not None:
            notice.close()
        logging.captureWarnings(False)
        root.removeHandler(handler)
        root.setLevel(old_level)
        if isinstance(handler, _DeferredLog):
            handler.finish(show_log)
        if show_log and not args.quiet and not _common.time_line_shown(shown_before):
            line = _common.compile_line(args.verb, args._clock.compile_s)
            if line:
                print(line, file=sys.stderr, flush=True)

