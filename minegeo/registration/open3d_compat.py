"""The Open3D 0.20 emulation of GICP: where ``registration_generalized_icp`` differs from minegeo's GICP.

:func:`minegeo.registration.register_gicp` reads two conventions from here, each chosen once from
its :class:`~minegeo.registration.GICPParams`:

* the surface covariances (:func:`covariance_convention`, ``covariance_mode``): minegeo's kNN PCA
  (two-pass covariance centred on the point, Jacobi eigen-solve), ``C = I - (1 - ε) n nᵀ``
  ([Ren2019 Eq. 3]) and ``C = I`` for a point without a surface (fewer than 3 neighbours, collinear,
  coincident, or a zero given normal); or Open3D's (raw moments in absolute coordinates and
  ``FastEigen3x3``, then ``R diag(ε, 1, 1) Rᵀ`` with its Rodrigues rotation ``e_x → n``, for every
  point whatever its neighbourhood);
* the convergence test (:func:`convergence_tests`, ``convergence``): the step test (``|Δt| <
  step_translation_m`` and ``angle(ΔR) < step_rotation_rad``) or Open3D's
  ``ICPConvergenceCriteria`` (``|Δfitness| < relative_fitness`` and ``|Δrmse| < relative_rmse``).

:data:`GICP_OPEN3D_FIELDS` is the parameter set of :meth:`GICPParams.open3d
<minegeo.registration.GICPParams.open3d>`. The kernels take the covariance convention as flags
(``mode_open3d``, ``rodrigues``): a Numba kernel cannot call this module. See
``../shared/specs/open3d_oracle.md`` §11.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GICP_OPEN3D_FIELDS", "CovarianceConvention", "MINEGEO_COVARIANCES", "OPEN3D_COVARIANCES",
           "covariance_convention", "convergence_tests"]

#: The :class:`~minegeo.registration.GICPParams` fields of Open3D 0.20 ``registration_generalized_icp``
#: semantics: Open3D's covariances and convergence test, no stop on a 2-cycle of correspondence sets.
GICP_OPEN3D_FIELDS = {"covariance_mode": "open3d", "convergence": "open3d", "stop_on_cycle": False}


@dataclass(frozen=True)
class CovarianceConvention:
    """How GICP turns points and normals into per-point covariances.

    Attributes
    ----------
    pca_open3d : bool
        The kNN PCA of the kernels (``mode_open3d`` of :func:`minegeo.kernels.eig3.pca_normal`):
        raw moments + ``FastEigen3x3`` (True) or the centred two-pass covariance + Jacobi (False).
    rodrigues : bool
        The plane covariance of a unit normal ``n`` (dimensionless): Open3D's ``R diag(ε, 1, 1) Rᵀ``
        with ``R`` its Rodrigues rotation ``e_x → n`` (True), or ``I - (1 - ε) n nᵀ`` (False).
    isotropic_without_surface : bool
        A point without a surface model (PCA status not OK, or a zero given normal) gets ``C = I``
        (True); False keeps the plane covariance of whatever normal it has, as Open3D does.
    """

    pca_open3d: bool
    rodrigues: bool
    isotropic_without_surface: bool

    def isotropic(self, no_surface: np.ndarray) -> np.ndarray:
        """(n,) bool: the rows whose covariance is ``I``, from the rows without a surface model."""
        if self.isotropic_without_surface:
            return no_surface
        return np.zeros(no_surface.shape[0], dtype=np.bool_)


#: minegeo's covariances (``covariance_mode="minegeo"``).
MINEGEO_COVARIANCES = CovarianceConvention(pca_open3d=False, rodrigues=False, isotropic_without_surface=True)
#: Open3D 0.20's covariances (``covariance_mode="open3d"``).
OPEN3D_COVARIANCES = CovarianceConvention(pca_open3d=True, rodrigues=True, isotropic_without_surface=False)


def covariance_convention(params) -> CovarianceConvention:
    """The :class:`CovarianceConvention` of ``params.covariance_mode`` (a validated ``GICPParams``)."""
    return OPEN3D_COVARIANCES if params.covariance_mode == "open3d" else MINEGEO_COVARIANCES


def convergence_tests(params) -> dict:
    """The tolerances of :class:`~minegeo.registration.loop.Termination` for ``params.convergence``:
    Open3D's fitness and inlier-RMSE changes (``"open3d"``, dimensionless and m) or the step test
    (``"step"``, m and rad); the tests not used are ``None``."""
    if params.convergence == "open3d":
        return {"relative_fitness": params.relative_fitness, "relative_rmse": params.relative_rmse,
                "step_translation": None, "step_rotation": None}
    return {"relative_fitness": None, "relative_rmse": None, "step_translation": params.step_translation_m,
            "step_rotation": params.step_rotation_rad}
