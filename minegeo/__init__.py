"""minegeo: survey-grade localization in a mine's official coordinate system.

Subpackages
-----------
io            point clouds, trajectories and ground control points (PLY, PCD, LAS/LAZ, XYZ/CSV, TUM, KITTI)
geometry      downsampling (voxel, octree), neighbour search, normals
features      FPFH descriptors
registration  correspondences, RANSAC, ICP variants
survey        least-squares adjustment, Helmert transformations, resection, error ellipses
mast          beacon positioning of a 2D scanner (Simela et al.)
synth         seeded synthetic mine world with sensors and ground truth
report        result JSON and human-readable reports
"""

from __future__ import annotations

import importlib
import logging
import time

__version__ = "0.1.0"
__all__ = ["__version__", "warmup", "show_versions"]

logging.getLogger(__name__).addHandler(logging.NullHandler())

#: Modules that expose ``_warmup()``: compile their Numba kernels on tiny inputs.
_WARMUP_MODULES = (
    "minegeo.io",
    "minegeo.synth",
    "minegeo.geometry",
    "minegeo.features",
    "minegeo.registration",
    "minegeo.survey",
    "minegeo.mast",
    "minegeo.localize",
    "minegeo.slam",
)


def warmup(verbose: bool = False, modules=None, progress=None) -> dict[str, float]:
    """Compile (or load from cache) every Numba kernel on tiny inputs.

    Parameters
    ----------
    verbose : bool
        Log the time of each subpackage.
    modules : iterable of str, optional
        Only these subpackages (names of ``_WARMUP_MODULES``, e.g. ``"minegeo.localize"``), in
        this order; default all.
    progress : callable, optional
        ``progress(name, i, n, seconds)``, called twice per subpackage: when it starts
        (``seconds=None``) and when it is done (``seconds``: wall seconds it took); ``i`` counts
        from 1 to ``n``, the number of subpackages asked for. A subpackage absent from this build
        is reported done in 0 s and left out of the returned times.

    Returns
    -------
    dict
        Seconds spent per subpackage, so compile time can be reported apart from run time.
    """
    log = logging.getLogger(__name__)
    out: dict[str, float] = {}
    names = _WARMUP_MODULES if modules is None else tuple(modules)
    unknown = [n for n in names if n not in _WARMUP_MODULES]
    if unknown:
        from minegeo.errors import InputError

        raise InputError(f"unknown warm-up module(s) {unknown}; choose from {list(_WARMUP_MODULES)}")
    n = len(names)
    for i, name in enumerate(names, start=1):
        if progress is not None:
            progress(name, i, n, None)
        t0 = time.perf_counter()
        try:
            mod = importlib.import_module(name)
        except ImportError:  # subpackage not present in this build
            if progress is not None:
                progress(name, i, n, 0.0)
            continue
        fn = getattr(mod, "_warmup", None)
        if fn is not None:
            fn()
        out[name] = time.perf_counter() - t0
        if verbose:
            log.info("warmup %s: %.2f s", name, out[name])
        if progress is not None:
            progress(name, i, n, out[name])
    return out


def show_versions() -> str:
    """Text block with minegeo's and its dependencies' versions (also returned for logging)."""
    from minegeo._provenance import versions

    return "\n".join(f"{k:>10}: {v}" for k, v in versions().items())
