"""minegeo.features: local surface descriptors (FPFH) for global registration.

Public API
----------
FPFHParams, FPFHResult, compute_fpfh, hybrid_neighborhoods
"""

from __future__ import annotations

from minegeo.features.fpfh import FPFHParams, FPFHResult, compute_fpfh, hybrid_neighborhoods

__all__ = ["FPFHParams", "FPFHResult", "compute_fpfh", "hybrid_neighborhoods"]


def _warmup() -> None:
    """Compile the FPFH kernels on a tiny cloud (both weight modes)."""
    import numpy as np

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(8, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    for weight in ("inverse_distance", "open3d"):
        compute_fpfh(pts, nrm, FPFHParams(radius_m=2.0, max_nn=8, weight=weight))
