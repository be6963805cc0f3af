"""minegeo.localize: global localization of scans in a map (georeferencing is :mod:`minegeo.georef`)."""

from minegeo.localize.correlative import (
    CorrelativeParams,
    CorrelativeResult,
    correlative_candidates,
    map_occupancy,
)
from minegeo.localize.pipeline import LocalizationResult, LocalizeParams, localize_scan
from minegeo.localize.prepared import FeatureParams, PreparedMap, PrepareParams, prepare_map
from minegeo.localize.uncertainty import PoseUncertainty, UncertaintyParams, pose_uncertainty

__all__ = [
    "LocalizeParams",
    "LocalizationResult",
    "localize_scan",
    "FeatureParams",
    "PrepareParams",
    "PreparedMap",
    "prepare_map",
]
__all__ += ["PoseUncertainty", "UncertaintyParams", "pose_uncertainty"]
__all__ += ["CorrelativeParams", "CorrelativeResult", "correlative_candidates", "map_occupancy"]


def _warmup() -> None:
    """The localization pipeline only calls the kernels of
    geometry, features and registration (warmed up by their packages): run it once on a tiny box."""
    import numpy as np

    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(0, 6.0, 0.5), np.arange(0, 4.0, 0.5), indexing="ij"), -1).reshape(-1, 2)
    walls = [np.column_stack([g[:, 0], g[:, 1], np.zeros(len(g))]),
             np.column_stack([g[:, 0], np.zeros(len(g)), g[:, 1]]),
             np.column_stack([g[:, 0], np.full(len(g), 4.0), g[:, 1]])]
    P = np.vstack(walls) + rng.normal(0, 0.01, (3 * len(g), 3))
    pm = prepare_map(P, PrepareParams(voxel_size_m=0.5))
    from minegeo.registration.ransac import RansacParams

    localize_scan(pm, P[::2], params=LocalizeParams(min_scan_points=10, ransac=RansacParams(max_iterations=2000)))
    from minegeo.localize.correlative import _warmup as _corr_warmup

    _corr_warmup()
    from minegeo.localize.gravity import _warmup as _gravity_warmup

    _gravity_warmup()  # the up estimate of the gravity fallback
    # the serial RANSAC/grid drivers and the indexed point-to-plane sums a real scan reaches (so that a
    # warm-up of this package alone, e.g. the demo's second process, covers its localizations)
    from minegeo.registration import warmup_scan_matching

    warmup_scan_matching()
