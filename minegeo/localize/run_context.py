"""The context every stage of one localization pass shares: seed, progress, timings, warnings.

:func:`minegeo.localize.localize_scan` makes one :class:`RunContext` per pass and hands it to each
stage (scan features, RANSAC, ICP verification and decision, correlative search, rival check)
instead of four loose arguments. A stage announces itself and records its seconds through it
(:meth:`RunContext.timed`), adds warnings a surveyor should read to ``warnings``, and derives its
random draws from ``seed`` (each stage documents how).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from minegeo.localize._progress import ProgressFn, announce

__all__ = ["RunContext"]


@dataclass
class RunContext:
    """Seed, progress callback, timings and warnings of one localization pass.

    Mutable by design: the stages of the pass fill ``timings`` and ``warnings`` as they run.

    Attributes
    ----------
    seed : int
        The run's seed (>= 0, checked by the caller); every random draw of the pass derives from it.
    progress : callable or None
        ``progress(step)``, called when a step starts (:mod:`minegeo.localize._progress`).
    timings : dict of str to float
        Seconds per stage, wall clock (``time.perf_counter``), filled by the stages.
    warnings : list of str
        Notes for the result (``LocalizationResult.warnings``), in the order the stages raised them.
    """

    seed: int
    progress: ProgressFn | None = None
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def announce(self, step: str) -> None:
        """Call ``progress(step)`` when a callback was given."""
        announce(self.progress, step)

    @contextmanager
    def timed(self, key: str, step: str | None = None) -> Iterator[None]:
        """Announce ``step`` (when given), then record the seconds of the ``with`` block as ``timings[key]``."""
        if step is not None:
            self.announce(step)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[key] = time.perf_counter() - t0
