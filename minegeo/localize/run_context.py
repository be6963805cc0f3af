"""The context every stage of one localization pass shares: seed, progress, timings, warnings.

:func:`minegeo.localize.localize_scan` makes one :class:`RunContext` per pass and hands it to each
stage (scan features, RANSAC, ICP verification and decision, correlative search, rival check)
instead of four loose arguments. A stage announces itself and records its seconds through it
(:meth:`RunContext.timed`), adds warnings a surveyor should read to ``warnings``, and takes the seed
of its random draws from :meth:`RunContext.stage_seed`, the one place where a stage's seed is derived
from the pass's ``seed`` (:data:`STAGE_SEEDS`).

Each stage's seed is the pass's seed itself (a stage that needs a second stream derives it inside,
as documented there: RANSAC's extra runs draw their seeds from ``default_rng(seed)``, the correlative
refinement permutes with ``seed + 1``). Spawning independent child seeds with
``numpy.random.SeedSequence(seed).spawn`` would decorrelate the stages' streams but change every seeded
result and every figure measured with one, so the derivation is declared here instead, and
changing it is one edit of :data:`STAGE_SEEDS`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from minegeo.localize._progress import ProgressFn, announce

__all__ = ["RunContext", "STAGE_SEEDS"]

#: The stages of a pass that draw random numbers, and the offset added to the pass's seed for each
#: (``RunContext.stage_seed``): RANSAC hypotheses, the correlative 4-DOF search, the rival search.
STAGE_SEEDS: dict[str, int] = {"ransac": 0, "correlative": 0, "rivals": 0}


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

    def stage_seed(self, stage: str) -> int:
        """The seed of ``stage``'s random draws: ``seed + STAGE_SEEDS[stage]`` (KeyError for a stage not declared)."""
        return self.seed + STAGE_SEEDS[stage]

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
