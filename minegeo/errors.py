"""Typed errors raised by minegeo.

Every error a user can cause (bad input, unreadable file, degenerate geometry)
is a :class:`MinegeoError` subclass whose message a surveyor can act on. The
CLI turns these into a one-line message and exit code 2; anything else is a bug.

A bug that minegeo detects itself (a violated internal invariant, e.g. a pose the package composed
that is no longer a rigid transform) is an :class:`InternalError`: deliberately *not* a
:class:`MinegeoError`, so it can never be reported as "your input is wrong". The CLI prints one
line saying it is a bug and asking for a report, and exits with status 3 (1 stays Python's status
of an unexpected crash with its traceback; 2 is the user's mistake; 130 an interrupt).
"""

from __future__ import annotations


class MinegeoError(Exception):
    """Base class of every error minegeo raises for a user-caused problem."""


class InputError(MinegeoError, ValueError):
    """Input data are malformed: wrong shape or dtype, NaN/inf, empty, out of range."""


class TooFewPointsError(InputError):
    """Fewer points (or observations) than the method needs."""


class DegenerateGeometryError(MinegeoError, ValueError):
    """Geometry does not determine the answer (collinear control, planar-only scan, ...)."""


class FileFormatError(MinegeoError, OSError):
    """A file is unreadable, truncated, or its header does not match its contents."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class CRSError(MinegeoError, ValueError):
    """Unknown or unsuitable coordinate reference system."""


class ConvergenceError(MinegeoError, RuntimeError):
    """An iterative solver did not converge within its limits."""


class OptionalDependencyError(MinegeoError, ImportError):
    """An optional extra (e.g. laspy, matplotlib) is needed for this operation."""

    def __init__(self, package: str, extra: str):
        super().__init__(
            f"this needs the optional package '{package}': install it with pip install 'minegeo[{extra}]'"
        )


class OutputError(InputError):
    """An output path cannot be used: it is an input, lies inside an input, is locked by another
    run, or names a folder that holds something other than an earlier minegeo result."""


class InternalError(RuntimeError):
    """A violated internal invariant: a bug in minegeo, never a problem with the user's data.

    Not a :class:`MinegeoError` subclass (``except MinegeoError`` does not catch it). ``minegeo
    <verb>`` prints ``minegeo <verb>: internal error (a bug in minegeo, not in your data): <message>;
    please report it ...`` and exits with status 3.
    """
