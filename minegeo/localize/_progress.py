"""Step reporting for long library calls (``progress`` callbacks), without any display code.

The library never prints and never imports a progress-bar package: a long function takes an
optional ``progress`` callable and calls ``progress(step)`` with a short human-readable name
(``"downsample"``, ``"normals"``, ``"FPFH"``, ``"RANSAC"``, ...) **when that step starts**. The
caller decides what to show (``minegeo prepare-map`` and ``minegeo localize`` drive a tqdm bar on
stderr with it). Exceptions raised by the callback propagate (e.g. to cancel a run).
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ProgressFn", "announce", "StepTimings", "FEATURE_STEPS"]

#: ``progress(step)``: called when the named step starts.
ProgressFn = Callable[[str], None]


def announce(progress: ProgressFn | None, step: str) -> None:
    """Call ``progress(step)`` when a callback was given."""
    if progress is not None:
        progress(step)


class StepTimings(dict):
    """A ``timings`` dict that announces the next step when a step's time is recorded.

    :func:`minegeo.localize.prepared.prepare_cloud_features` records ``downsample``, then
    ``normals``, then ``fpfh`` seconds into the dict it is given, each right after the step
    ends; with ``follows={"downsample": "normals", "normals": "FPFH"}`` this dict calls
    ``progress("normals")`` when ``downsample`` is first recorded, and so on, so the caller sees
    each step start without that function knowing about progress at all. Later updates of the
    same key (``timings["downsample"] += ...``) announce nothing.
    """

    def __init__(self, progress: ProgressFn | None, follows: dict[str, str]):
        super().__init__()
        self._progress = progress
        self._follows = dict(follows)

    def __setitem__(self, key, value) -> None:
        first = key not in self
        super().__setitem__(key, value)
        if first and key in self._follows:
            announce(self._progress, self._follows[key])


#: What follows each step of ``prepare_cloud_features`` (see :class:`StepTimings`).
FEATURE_STEPS = {"downsample": "normals", "normals": "FPFH"}
