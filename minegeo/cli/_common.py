"""Helpers shared by the verbs of :mod:`minegeo.cli` (``localize`` and ``prepare-map``).

A step progress bar on stderr, the whole run's timings (Python start-up included when the
process was launched for the verb) and their one-line printout, and a context hiding
``prepare_map``'s own summary log line.
"""

from __future__ import annotations

import logging
import sys

__all__ = ["StepBar", "startup_s", "whole_run_timings", "time_line", "summary_lines_quiet", "FirstCompileNotice",
           "compile_line", "compile_note", "time_line_shown"]

#: whether the running verb has formatted its own time line (:func:`time_line`): then ``minegeo.cli``
#: does not add its compile line (:func:`compile_line`) after the run.
_TIME_LINE_SHOWN = False


def time_line_shown(set_to: bool) -> bool:
    """Set the "verb printed its own time line" flag to ``set_to``; return its value before.

    ``minegeo.cli.main`` calls ``prev = time_line_shown(False)`` when a run starts and
    ``time_line_shown(prev)`` when it ends (which tells whether this run showed one, and gives a
    nested run such as the demo's steps the outer run's flag back)."""
    global _TIME_LINE_SHOWN
    old, _TIME_LINE_SHOWN = _TIME_LINE_SHOWN, bool(set_to)
    return old


#: compile seconds below which a run's compilation is not worth a line of its own
COMPILE_LINE_MIN_S = 0.5


def compile_line(verb: str, compile_s: float) -> str | None:
    """``minegeo slam: 12.3 s of this run was one-time Numba compilation (cached for later runs)``, or
    None when the run compiled less than :data:`COMPILE_LINE_MIN_S` seconds."""
    if not compile_s >= COMPILE_LINE_MIN_S:
        return None
    return f"minegeo {verb}: {compile_s:.1f} s of this run was one-time Numba compilation (cached for later runs)"


def compile_note(args) -> str:
    """``12.3 s of it one-time Numba compilation, cached for later runs`` (``0.0 s`` when every kernel
    came from Numba's cache): the compile seconds of the run ``args`` so far
    (:class:`minegeo._output.RunClock`). Marks the run as having shown its own time line."""
    global _TIME_LINE_SHOWN
    from minegeo._output import run_timings

    _TIME_LINE_SHOWN = True
    c = run_timings(args)["compile_s"]
    if c < 0.05:
        return "0.0 s of it Numba compilation: every kernel came from the cache"
    return f"{c:.1f} s of it one-time Numba compilation, cached for later runs"


class FirstCompileNotice:
    """Print ``compiling numerical kernels for first use (once; about N s) ...`` to stderr once, when
    the first Numba compilation of a run starts (a kernel, or a signature of it, not in Numba's
    on-disk cache yet: loading from the cache is not compilation and says nothing).

    ``live`` (stderr is a terminal, as for progress bars): printed at once. Otherwise (a script, a
    log file) it is an INFO log record, held with the run's log like every other one, so that a run
    ending in the user's mistake still prints exactly one line.

    Listens to Numba's ``numba:compile`` event from construction to :meth:`close`. ``estimate_s``
    is the verb's one-time compile time on an empty cache (``minegeo.cli.COLD_COMPILE_S``); a
    partly filled cache compiles less."""

    def __init__(self, verb: str, estimate_s: float | None = None, live: bool = True):
        self.verb = verb
        self.estimate_s = estimate_s
        self.live = live
        self.shown = False
        self._listener = None
        try:
            from numba.core import event

            notice = self

            class _Listener(event.Listener):
                def on_start(self, ev):
                    notice._first()

                def on_end(self, ev):
                    pass

            self._listener = _Listener()
            event.register("numba:compile", self._listener)
        except Exception:  # noqa: BLE001 - an old Numba without the event API: no notice
            self._listener = None

    def _first(self) -> None:
        if self.shown:
            return
        self.shown = True
        about = (f"; about {self.estimate_s:.0f} s on an idle machine" if self.estimate_s and self.estimate_s >= 1
                 else "")
        text = (f"minegeo {self.verb}: compiling numerical kernels for first use (once, cached for later "
                f"runs{about}) ...")
        if not self.live:  # a log record: held with the run's log, dropped when the run ends in a user error
            logging.getLogger("minegeo.cli").info("%s", text)
            return
        try:
            print(text, file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        if self._listener is not None:
            from numba.core import event

            try:
                event.unregister("numba:compile", self._listener)
            finally:
                self._listener = None


class StepBar:
    """A tqdm progress bar on stderr naming the step that runs (``localize``, ``prepare-map``).

    Called as ``bar(step)`` when a step starts (the ``progress`` callback of
    :func:`~minegeo.localize.prepare_map`, :meth:`~minegeo.localize.PreparedMap.build_indexes` and
    :func:`~minegeo.localize.localize_scan`); the bar counts finished steps. Off when stderr is not
    a terminal or with ``--quiet`` (:func:`minegeo._output.progress_enabled`); it disappears when
    closed, so the result lines stay clean. ``total`` is an estimate: optional steps (the
    correlative search) extend it.
    """

    def __init__(self, args, name: str, total: int):
        from minegeo._output import progress_enabled

        self.name = name
        self.steps: list[str] = []
        self.enabled = progress_enabled(args)
        self._bar = None
        if self.enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=name, file=sys.stderr, leave=False, dynamic_ncols=True,
                             bar_format="{desc} {bar} {n_fmt}/{total_fmt} steps [{elapsed}]")

    def __call__(self, step: str) -> None:
        self.steps.append(step)
        if self._bar is None:
            return
        if len(self.steps) > 1:
            self._bar.update(1)
        if self._bar.n >= self._bar.total:
            self._bar.total = self._bar.n + 1
        self._bar.set_description_str(f"{self.name}: {step}")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> StepBar:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def startup_s() -> float | None:
    """Age of this process in seconds (Linux ``/proc``; None elsewhere).

    ``age - run clock`` is what the run clock (:class:`minegeo._output.RunClock`, started by
    ``minegeo.cli`` once the verb's module is imported) does not see: the Python start-up and
    the imports before it (importing ``minegeo.localize`` loads NumPy, SciPy, Numba, pyproj and
    every localization module). Resolution: one clock tick (10 ms)."""
    import os

    try:
        with open("/proc/self/stat", encoding="ascii") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of proc(5), counted after the ")" of the name
        with open("/proc/uptime", encoding="ascii") as fh:
            uptime = float(fh.read().split()[0])
        age = uptime - start_ticks / float(os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return age if age >= 0.0 else None


def launched_for(verb: str | None) -> bool:
    """True when this process was started as ``minegeo VERB ...`` (not a test run, not a verb that
    ``minegeo demo`` or a script calls in-process, where the process age is not this run's)."""
    first = next((a for a in sys.argv[1:] if not a.startswith("-")), None)
    return verb is not None and first == verb


def whole_run_timings(args) -> dict[str, float]:
    """``run_timings(args)`` (``wall_s``, ``compile_s``, ``work_s``) and, when the process was
    started for this verb, ``startup_s`` (process start to the run clock: Python start-up and the
    imports before it) and ``process_wall_s`` (the process age: what the user waited)."""
    from minegeo._output import run_timings

    t = dict(run_timings(args))
    age = startup_s() if launched_for(getattr(args, "verb", None)) else None
    if age is not None and age >= t["wall_s"]:
        t["startup_s"] = age - t["wall_s"]
        t["process_wall_s"] = age
    return t


def time_line(t: dict) -> str:
    """``12.3 s wall (0.0 s compiling Numba kernels [once, then cached], 1.2 s Python start-up and imports)``.

    Marks the run as having shown its own time line (:func:`time_line_shown`)."""
    global _TIME_LINE_SHOWN
    _TIME_LINE_SHOWN = True
    wall = t.get("process_wall_s", t["wall_s"])
    parts = [f"{t['compile_s']:.1f} s compiling Numba kernels [once, then cached]"]
    if "startup_s" in t:
        parts.append(f"{t['startup_s']:.1f} s Python start-up and imports")
    return f"{wall:.1f} s wall (" + ", ".join(parts) + ")"


class summary_lines_quiet:
    """Context: hide ``prepare_map``'s own INFO summary line (``prepared map: ... in X s``); the
    CLI prints the whole run's times instead (that line's seconds are preparation only and were
    read as the run's time)."""

    def __enter__(self):
        self._log = logging.getLogger("minegeo.localize.prepared")
        self._f = _DropPrefix("prepared map:")
        self._log.addFilter(self._f)
        return self

    def __exit__(self, *exc):
        self._log.removeFilter(self._f)
        return False


class _DropPrefix(logging.Filter):
    def __init__(self, prefix: str):
        super().__init__()
        self.prefix = prefix

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.levelno == logging.INFO and str(record.msg).startswith(self.prefix))
