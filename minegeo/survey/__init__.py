"""minegeo.survey — least-squares adjustment, transformations, resection and error ellipses.

Stable public API (other packages, e.g. :mod:`minegeo.mast`, import these names from here)
-----------------------------------------------------------------------------------------
Least squares (:mod:`minegeo.survey.lsq`), model ``v + B·Δ = f``, ``N = BᵀWB``:

* ``adjust(fun, x0, weights, *, constraints=None, options=None, param_names=None,
  obs_names=None, linear=False) -> LSQResult`` — ``fun(x) -> (f, B)`` with ``B = −∂F/∂x``,
  ``f = F(x) − l``; residuals ``v = l̂ − l``.
* ``adjust_observations(model, x0, observed, *, sigmas=None | cov=None | weights=None,
  angular=None, options=None, ...) -> LSQResult`` — give ``model(x) -> (F(x), ∂F/∂x)`` and the
  observations; easiest entry point.
* ``adjust_linear(B, l, weights, ...) -> LSQResult`` — linear ``l + v = B·x``.
* ``LSQOptions(variance="aposteriori"|"apriori", sigma0_apriori=1.0, alpha_global=0.05,
  alpha_w=0.001, alpha_tau=0.05, ...)``.
* ``LSQResult`` fields: ``x, v, dof, vtwv, sigma0_sq, sigma0 (property), Qxx, Sigma_xx, std,
  redundancy, w (Baarda), tau (Pope), w_critical, tau_critical, flags, chi2 (Chi2Test: statistic,
  lower, upper, passed, verdict), iterations, converged, param_names, obs_names``.
* ``weights_from_sigmas(sigmas, sigma0_apriori=1.0)``, ``chi2_global_test(vtwv, dof, ...)``.

Ellipses (:mod:`minegeo.survey.ellipse`):

* ``error_ellipse(cov2x2, confidence=None|0.95, dof=None, sigma0_known=True) -> ErrorEllipse``
  (``semi_major_m, semi_minor_m, azimuth_rad`` clockwise from north, ``k``, ``confidence``,
  ``basis``); 95 % scale sqrt(χ²(2,.95)) = 2.4477 with σ0 known, sqrt(2F(2,r,.95)) estimated.
* ``relative_ellipse(cov_full, i, j, ...)``, ``point_ellipses(cov, dof, sigma0_known)``,
  ``ellipse_scale(confidence, dof, sigma0_known)``.

Transformations (:mod:`minegeo.survey.helmert`):

* ``helmert2d(src_xy, dst_en, sigma_dst=None) -> Helmert2DResult`` (params a, b, Tx, Ty with
  std/cov, scale, rotation_rad/rotation_dms, residuals, sigma0, ``transform(points) ->
  (EN, cov)``); design ``[x −y 1 0; y x 0 1]``.
* ``affine2d(src_xy, dst_en, sigma_dst=None) -> Affine2DResult``.
* ``helmert3d(src_xyz, dst_xyz, sigma_dst=None, *, estimate_scale=True,
  convention="position_vector"|"coordinate_frame") -> Helmert3DResult`` (7- or 6-parameter).
* ``apply_helmert7(points, tx, ty, tz, rx″, ry″, rz″, ds_ppm, convention)``,
  ``apply_helmert2d(points, tx, ty, scale, rotation_rad)``, ``helmert7_matrix``.

Angles (:mod:`minegeo.survey.angles`): ``parse_dms``, ``parse_angle``, ``format_dms``,
``format_gon``, ``azimuth``, ``azimuth_distance``, ``polar_to_rect``, ``azimuth_to_bearing``,
``bearing_to_azimuth``, ``wrap_2pi``, ``wrap_pi``, unit conversions.

Networks (:mod:`minegeo.survey.network`): ``adjust_network(net, options=None,
confidence=0.95) -> NetworkResult`` (``points`` {id: PointResult x, y, h, sx_m, sy_m, sh_m,
cov, ellipse_standard, ellipse_95}, ``observations``, ``orientations``, ``relative_ellipses``,
``lsq``, ``local_origin``); restrictions in :mod:`minegeo.survey.restrictions`. The readers
are in :mod:`minegeo.io` and exported here: ``read_network(path)`` (Krumm/Gama text or JSON,
:mod:`minegeo.io.network`), ``parse_krumm(text)`` (:mod:`minegeo.io.network_krumm`),
``network_from_dict(d)`` (:mod:`minegeo.io.network_json`); ``Network``, ``Observation``,
``Datum`` are in :mod:`minegeo.io.network_types`.

Resection (:mod:`minegeo.survey.resection`): ``resection_2d(control, directions=, distances=,
angles=, sigma_...)``, ``intersection_2d(control, angles=, azimuths=, ...)``,
``trilateration_2d(control, distances, sigma_distance_m=...)`` -> ``StationResult`` (e_m, n_m,
cov, se_m, sn_m, orientation_rad, ellipses, status/reason, network).

Reports (``result.json``, ``report.txt``, ``report.html``) are written by ``minegeo adjust``
outside this package, which never imports them; they are documented with the formats in
``docs/survey.md``.

Coordinates are (Easting, Northing[, height]) in metres; azimuths clockwise from grid north.
This package has no Numba kernels (small dense problems, NumPy/SciPy only).
"""

from __future__ import annotations

from minegeo.io.network import read_network
from minegeo.io.network_json import network_from_dict
from minegeo.io.network_krumm import parse_krumm
from minegeo.survey.angles import (
    azimuth,
    azimuth_distance,
    azimuth_to_bearing,
    bearing_to_azimuth,
    format_dms,
    format_gon,
    gon_to_rad,
    parse_angle,
    parse_dms,
    polar_to_rect,
    rad_to_gon,
    wrap_2pi,
    wrap_pi,
)
from minegeo.survey.ellipse import (
    ErrorEllipse,
    ellipse_scale,
    error_ellipse,
    point_ellipses,
    relative_ellipse,
)
from minegeo.survey.helmert import (
    Affine2DResult,
    Helmert2DResult,
    Helmert3DResult,
    affine2d,
    apply_helmert2d,
    apply_helmert7,
    helmert2d,
    helmert3d,
    helmert7_matrix,
)
from minegeo.survey.lsq import (
    Chi2Test,
    LSQOptions,
    LSQResult,
    adjust,
    adjust_linear,
    adjust_observations,
    chi2_global_test,
    weights_from_sigmas,
)
from minegeo.survey.network import Datum, Network, NetworkResult, Observation, adjust_network
from minegeo.survey.resection import (
    StationResult,
    StationStatus,
    intersection_2d,
    resection_2d,
    trilateration_2d,
)

__all__ = [
    "azimuth",
    "azimuth_distance",
    "azimuth_to_bearing",
    "bearing_to_azimuth",
    "format_dms",
    "format_gon",
    "gon_to_rad",
    "parse_angle",
    "parse_dms",
    "polar_to_rect",
    "rad_to_gon",
    "wrap_2pi",
    "wrap_pi",
    "ErrorEllipse",
    "ellipse_scale",
    "error_ellipse",
    "point_ellipses",
    "relative_ellipse",
    "Affine2DResult",
    "Helmert2DResult",
    "Helmert3DResult",
    "affine2d",
    "apply_helmert2d",
    "apply_helmert7",
    "helmert2d",
    "helmert3d",
    "helmert7_matrix",
    "Chi2Test",
    "LSQOptions",
    "LSQResult",
    "adjust",
    "adjust_linear",
    "adjust_observations",
    "chi2_global_test",
    "weights_from_sigmas",
    "Datum",
    "Network",
    "NetworkResult",
    "Observation",
    "adjust_network",
    "network_from_dict",
    "parse_krumm",
    "read_network",
    "StationResult",
    "StationStatus",
    "intersection_2d",
    "resection_2d",
    "trilateration_2d",
]


def _warmup() -> None:
    """No Numba kernels in minegeo.survey: nothing to compile (kept for ``minegeo.warmup()``)."""
    return None
