"""Georeferencing a mine map: the map-to-CRS transformation from ground control points (GCPs).

A map built underground (SLAM or a registered scan network) lives in its own local frame
``map``. Ground control points — marks whose map coordinates ``x_i`` were picked in the scan
and whose grid coordinates ``X_i = (E, N, H)`` were surveyed (e.g. by traverse from the
portal) — fix the transformation into the mine's official projected CRS (Baek et al. 2022,
Sec. 2.1: "transformed into the UTM coordinate system by calculating the transformation
matrix between ground control points and reference points").

Model (3D similarity, Ghilani 2010 Ch. 18 "3D conformal coordinate transformation"; EPSG
methods 9606/9607)::

    X_i = T + s · R · x_i            (observation equations, X_i observed, x_i errorless)
    T_crs_map = [[s·R, T], [0, 1]]   (4x4; NOT a rigid transform when s != 1)

* ``model="similarity"``: 7 parameters (T, 3 rotations, scale ``s = 1 + ds``);
* ``model="rigid"``: 6 parameters, ``s = 1`` fixed.

The rotation is estimated exactly (``R = exp([ω]×)``, any size: a map's yaw against grid north
is arbitrary); ``ω`` is the **position-vector** rotation vector (EPSG 9606, "Bursa-Wolf"), the
coordinate-frame convention (EPSG 9607) reports ``−ω``. For small angles ``ω`` are the EPSG
rx, ry, rz. Rotation standard deviations refer to small rotations about the CRS E, N, H axes
at the solution (left perturbation ``R = exp([δ]×)·R̂``).

The weighted least-squares adjustment (Gauss-Markov, ``N = BᵀWB``, ``Σxx = σ0²N⁻¹``) is
:func:`minegeo.survey.helmert3d` on coordinates reduced to a recorded local origin (a CRS
point rounded to whole kilometres, see :mod:`minegeo.georef.crs`), so coordinates of
10⁶–10⁷ m lose no precision. Weights are ``W = Σll⁻¹`` from the a-priori standard deviations
of the CRS coordinates, optionally inflated by those of the map coordinates
(``σ² = σ_ENH² + s²·(R Σ_xyz Rᵀ)_jj``, exact for isotropic map sigmas, diagonal otherwise).

Statistics (:mod:`minegeo.survey.lsq`): residuals ``v = fitted − observed`` per GCP and axis,
``σ̂0 = sqrt(vᵀWv / r)`` with ``r = 3n − u``, the two-tailed χ² test of ``vᵀWv ~ χ²(r)``,
parameter standard deviations, redundancy numbers and Baarda's w-test per coordinate
(``|w| > 3.29`` at α = 0.001). A GCP is flagged when one of its coordinates fails the
w-test; the GCP with the largest ``|w|`` is the suspected blunder (data snooping: remove it
and re-run).

Refusals and status (never a confident wrong answer):

* fewer than 3 GCPs -> :class:`~minegeo.errors.TooFewPointsError` (3 non-collinear points are
  the minimum for a 3D rotation; 3 points leave only 2 (similarity) or 3 (rigid) redundant
  coordinates);
* collinear or coincident GCPs in the map -> :class:`~minegeo.errors.DegenerateGeometryError`
  (the rotation about the line is undetermined);
* unknown EPSG code, geographic (degrees) or non-metre CRS ->
  :class:`~minegeo.errors.CRSError`;
* **unit rule**: the spread ratio ``ŝ = rms|X_i − X̄| / rms|x_i − x̄|`` estimates the scale
  independently of the rotation. ``|ŝ − 1| > max_scale_deviation`` (default 0.01, i.e. 1 %,
  while real grid scale factors are < 0.1 %) means the two coordinate sets are in different
  units (km, feet, mm) or the GCP ids are mismatched: status ``failed``, with the likely
  unit named;
* the map and CRS coordinates are mirror images (e.g. E and N swapped) -> status ``failed``;
* ``σ̂0 > max_sigma0`` (default 10: residuals ten times the stated GCP sigmas — a gross blunder,
  mismatched ids, or wildly optimistic sigmas) -> status ``failed`` naming the suspected GCP;
* no similarity fits at all after a failed unit check (e.g. degrees with heights in metres) ->
  :class:`~minegeo.errors.InputError`;
* χ² test failed or a GCP failed the w-test -> status ``warning`` with the suspected GCP.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from minegeo.errors import (
    ConvergenceError,
    CRSError,
    DegenerateGeometryError,
    InputError,
    TooFewPointsError,
)
from minegeo.geometry.se3 import log_so3
from minegeo.georef.crs import (
    CRSInfo,
    crs_info,
    grid_scale_factors,
    local_origin,
    outside_area_of_use,
    same_crs,
)
from minegeo.georef.result import GeorefParams, GeorefResult, GeorefStatus
from minegeo.io.types import ControlPoints
from minegeo.survey.helmert import helmert3d
from minegeo.survey.lsq import LSQOptions, LSQResult

log = logging.getLogger(__name__)

__all__ = ["georeference", "unit_diagnosis"]

#: known unit ratios (CRS unit per map unit expressed as the scale a fit would find)
_UNIT_GUESSES = (
    (1e-3, "the CRS coordinates look like kilometres while the map is in metres"),
    (1e3, "the map looks like it is in kilometres (or the CRS coordinates in millimetres)"),
    (1e-2, "the map looks like it is in centimetres (e.g. 3DTK scans): read it with scale 0.01"),
    (0.3048, "the CRS coordinates look like feet while the map is in metres (ratio 0.3048)"),
    (1 / 0.3048, "the map looks like it is in feet while the CRS coordinates are in metres (ratio 3.2808)"),
    (0.3048006096, "the CRS coordinates look like US survey feet while the map is in metres"),
    (100.0, "the CRS coordinates look like centimetres while the map is in metres"),
)



# ---------------------------------------------------------------------------- helpers
def unit_diagnosis(scale: float, scale_horizontal: float | None = None) -> str:
    """Name the likely unit mismatch for a rotation-free scale estimate (CRS units per map unit).

    ``scale_horizontal`` (the same ratio from E, N and map x, y only) recognises longitude/latitude
    in degrees given together with heights in metres.
    """
    if not (math.isfinite(scale) and scale > 0):
        return "the control coordinates have no spread in one of the two systems"
    sh = scale if scale_horizontal is None or not math.isfinite(scale_horizontal) else scale_horizontal
    if 2e-6 < sh < 2e-5:  # 1 degree ~ 111 km of latitude, 111 km x cos(lat) of longitude
        return (
            "the CRS coordinates look like degrees of longitude/latitude, not projected metres: convert "
            "them to the projected grid first"
        )
    best = None
    for ratio, text in _UNIT_GUESSES:
        if not text:
            continue
        dev = abs(math.log(scale / ratio))
        if dev < 0.02 and (best is None or dev < best[0]):
            best = (dev, text)
    if best is not None:
        return best[1]
    return (
        "the distances between control points differ by this factor between the map and the CRS: "
        "check the units of both files and that each GCP id refers to the same mark in both"
    )


def _spread_scale(src_c: np.ndarray, dst_c: np.ndarray) -> float:
    """Rotation-free scale estimate ``rms|dst_c| / rms|src_c|`` (centred coordinates)."""
    a = float(np.sqrt(np.sum(src_c**2)))
    b = float(np.sqrt(np.sum(dst_c**2)))
    return b / a if a > 0 else float("nan")


def _procrustes_rms(src_c: np.ndarray, dst_c: np.ndarray, s: float, proper: bool) -> float:
    """RMS residual of the best orthogonal (proper or improper) fit with scale ``s``."""
    U, _, Vt = np.linalg.svd(dst_c.T @ src_c)
    E = np.eye(3)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    if (proper and d < 0) or (not proper and d > 0):
        E[2, 2] = -1.0
    Q = U @ E @ Vt
    r = dst_c - s * src_c @ Q.T
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))), Q


def _euler_zyx(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) with ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return np.array([roll, pitch, yaw])


# ---------------------------------------------------------------------------- estimation
@dataclass(frozen=True)
class _Screening:
    """Rotation-free diagnostics of the GCPs before any fit (see :func:`_screen_gcps`).

    Attributes
    ----------
    s_spread : float
        Rotation-free scale estimate (CRS units per map unit).
    s_test : float
        ``s_spread`` when usable, else 1: the scale of the Procrustes checks and the weights.
    Q0 : ndarray (3, 3)
        Best proper rotation map -> CRS at scale ``s_test``.
    """

    s_spread: float
    s_test: float
    Q0: np.ndarray


@dataclass(frozen=True)
class _Fit:
    """The Helmert fit of :func:`_fit_helmert`, scaled back to CRS units (m).

    Attributes
    ----------
    lsq : LSQResult
        Adjustment statistics of :func:`minegeo.survey.helmert3d` (``w``, ``redundancy``,
        ``flags``, ``chi2``, ``sigma0``…), dimensionless.
    fit_similarity : bool
        True when the 7-parameter model was fitted (requested, or diagnostic after a unit failure).
    s : float
        Scale ``s``.
    R : ndarray (3, 3)
        Rotation map axes -> CRS E, N, H axes.
    t_geo : ndarray (3,)
        Translation in the ``geo`` frame (m).
    resid : ndarray (n, 3)
        Residuals ``v = fitted − observed`` in E, N, H (m).
    cov : ndarray (6, 6) or (7, 7)
        Parameter covariance (m, rad, dimensionless).
    t_fit : float
        Seconds of the adjustment.
    """

    lsq: LSQResult
    fit_similarity: bool
    s: float
    R: np.ndarray
    t_geo: np.ndarray
    resid: np.ndarray
    cov: np.ndarray
    t_fit: float


def _checked_inputs(gcps: ControlPoints, crs, p: GeorefParams):
    """Validate the GCPs and the CRS; return ``(info, src, crs_enh, sig_enh)`` (m)."""
    if not isinstance(gcps, ControlPoints):
        raise InputError(f"gcps must be ControlPoints (see minegeo.io.read_gcps), got {type(gcps).__name__}")
    if crs is None:
        crs = gcps.crs
    elif gcps.crs and not same_crs(str(crs), str(gcps.crs)):
        raise CRSError(
            f"the control points are in {gcps.crs} but {crs} was requested: give the CRS of the E, N, H "
            "coordinates (or transform them first)"
        )
    info = crs_info(crs, allow_geocentric=p.allow_geocentric)
    n = len(gcps)
    need = 3
    if n < need:
        raise TooFewPointsError(
            f"{n} ground control point(s) given; a 3D {'rigid' if p.model == 'rigid' else 'similarity'} "
            f"transformation needs at least 3 non-collinear GCPs ({6 if p.model == 'rigid' else 7} unknowns, "
            "3 coordinates per GCP), and 4 or more to locate a wrong GCP"
        )
    src = np.ascontiguousarray(gcps.local_xyz, dtype=np.float64)
    crs_enh = np.ascontiguousarray(gcps.crs_enh, dtype=np.float64)
    sig_enh = np.asarray(gcps.sigma_enh_m, dtype=np.float64)
    if not (np.isfinite(sig_enh).all() and np.all(sig_enh > 0)):
        raise InputError("the a-priori standard deviations of the GCP CRS coordinates must be finite and > 0")
    return info, src, crs_enh, sig_enh


def _map_geometry(src: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Centred map coordinates, extent (m) and singular value ratio; refuse coincident/collinear GCPs."""
    n = len(src)
    src_c = src - src.mean(axis=0)
    sv = np.linalg.svd(src_c, compute_uv=False)
    extent = float(np.max(np.linalg.norm(src_c, axis=1))) if n else 0.0
    if sv[0] <= 1e-9 * max(extent, 1e-300) or extent == 0.0:
        raise DegenerateGeometryError(
            "all ground control points coincide in the map: they cannot fix the transformation"
        )
    ratio = float(sv[1] / sv[0])
    if ratio < 1e-7:
        raise DegenerateGeometryError(
            f"the {n} ground control points lie on a straight line in the map (spread across the line "
            f"{sv[1]:.2e} m vs {sv[0]:.1f} m along it): the rotation about that line is undetermined. "
            "Add a GCP off the line (e.g. in a cross-cut or at a different height)"
        )
    return src_c, extent, ratio


def _screen_gcps(src_c: np.ndarray, ratio: float, dst: np.ndarray, sig_enh: np.ndarray, p: GeorefParams,
                 failed: list, warnings: list) -> _Screening:
    """Unit rule, mirror check and geometry warnings (rotation-free, before any fit).

    ``src_c`` are the centred map coordinates with singular value ratio ``ratio``
    (:func:`_map_geometry`), ``dst`` the CRS coordinates reduced to the recorded origin (m).
    Appends to ``failed`` (unit mismatch, mirror image) and ``warnings`` (weak geometry,
    only 3 GCPs).
    """
    dst_c = dst - dst.mean(axis=0)
    s_spread = _spread_scale(src_c, dst_c)
    if not (abs(s_spread - 1.0) <= p.max_scale_deviation):
        failed.append(
            f"unit check failed: the distances between GCPs are {s_spread:.6g} times larger in the CRS "
            f"than in the map (allowed 1 ± {p.max_scale_deviation:g}); "
            f"{unit_diagnosis(s_spread, _spread_scale(src_c[:, :2], dst_c[:, :2]))}"
        )
    s_test = s_spread if math.isfinite(s_spread) and s_spread > 0 else 1.0
    rms_proper, Q0 = _procrustes_rms(src_c, dst_c, s_test, proper=True)
    rms_mirror, _ = _procrustes_rms(src_c, dst_c, s_test, proper=False)
    if rms_mirror < 0.1 * rms_proper and rms_proper > 10.0 * float(np.max(sig_enh)) and ratio > 0.01:
        failed.append(
            f"the CRS coordinates are a mirror image of the map (best mirrored fit RMS {rms_mirror:.3f} m vs "
            f"{rms_proper:.3f} m for a proper rotation): Easting and Northing are probably swapped, or one "
            "axis of the map is flipped (left-handed frame)"
        )

    if ratio < p.min_geometry_ratio:
        warnings.append(
            f"weak geometry: the GCPs are nearly collinear in the map (singular value ratio {ratio:.3g} < "
            f"{p.min_geometry_ratio:g}); the rotation about their common line is poorly determined — see "
            "the rotation standard deviations"
        )
    if len(src_c) == 3:
        warnings.append(
            "only 3 GCPs (minimum): a wrong GCP can be detected by the chi-square test but not reliably "
            "located; use 4 or more"
        )
    return _Screening(s_spread, s_test, Q0)


def _sigmas_used(gcps: ControlPoints, sig_enh: np.ndarray, scr: _Screening, p: GeorefParams) -> np.ndarray:
    """A-priori standard deviations (m) of the weights: CRS sigmas + map sigmas propagated through s·R."""
    n = len(sig_enh)
    if gcps.sigma_local_m is not None:
        sig_loc = np.asarray(gcps.sigma_local_m, dtype=np.float64)
        if not (np.isfinite(sig_loc).all() and np.all(sig_loc >= 0)):
            raise InputError("the a-priori standard deviations of the GCP map coordinates must be >= 0")
    else:
        sig_loc = np.full((n, 3), p.sigma_local_m)
    s_w = scr.s_test if p.model == "similarity" else 1.0
    Q0 = scr.Q0
    var_loc = np.einsum("jk,ik,jk->ij", Q0, sig_loc**2, Q0) * s_w**2  # diag(Q Σ Qᵀ) per point
    sigma_used = np.sqrt(sig_enh**2 + var_loc)
    if np.any(sig_loc > 0) and not np.allclose(sig_loc, sig_loc[:, :1]):
        log.info("anisotropic map-coordinate sigmas: only the diagonal of s²RΣRᵀ enters the weights")
    return sigma_used


def _fit_helmert(src: np.ndarray, dst: np.ndarray, sigma_used: np.ndarray, s_test: float,
                 p: GeorefParams, failed: list) -> _Fit:
    """Weighted 3D Helmert adjustment ``X_i = T + s·R·x_i`` of the reduced CRS coordinates ``dst`` (m).

    After a failed unit check the fit is a diagnostic 7-parameter one on ``dst / s_test``, scaled
    back (appends a note to ``failed`` when the rigid model was requested).
    """
    n = len(src)
    opts = LSQOptions(
        variance=p.variance, alpha_w=p.blunder_alpha, alpha_global=p.chi2_alpha, max_iterations=100
    )
    # with a unit mismatch a rigid fit is meaningless (and may not converge): the numbers of a
    # failed result then come from a diagnostic 7-parameter fit that shows the actual scale
    fit_similarity = p.model == "similarity" or bool(failed and "unit check" in failed[0])
    if fit_similarity and p.model == "rigid":
        failed.append(
            "model 'rigid' was requested; the parameters shown come from a diagnostic 7-parameter fit "
            "(to show the actual scale) and must not be used"
        )
    # a diagnostic fit of grossly mis-scaled data is solved on CRS coordinates divided by the
    # rotation-free scale estimate k (scale near 1: Gauss-Newton converges), then scaled back
    k_unit = s_test if fit_similarity and failed and "unit check" in failed[0] else 1.0
    t_fit = time.perf_counter()
    try:
        h = helmert3d(
            src,
            dst if k_unit == 1.0 else dst / k_unit,
            sigma_used if k_unit == 1.0 else sigma_used / k_unit,
            estimate_scale=fit_similarity,
            convention=p.convention,
            options=opts,
        )
    except ConvergenceError:
        if not failed:
            raise
        # the input is already known to be wrong and not even a diagnostic fit exists
        raise InputError(
            "georeferencing impossible: " + "; ".join(failed) + " (no similarity transformation fits these "
            "coordinates at all, e.g. longitude/latitude with heights in metres)"
        ) from None
    t_fit = time.perf_counter() - t_fit
    s = float(h.scale) * k_unit
    R = np.asarray(h.R, dtype=np.float64)
    t_geo = np.asarray(h.T, dtype=np.float64) * k_unit
    resid = np.asarray(h.residuals, dtype=np.float64).reshape(n, 3) * k_unit
    cov = np.asarray(h.cov, dtype=np.float64)
    if k_unit != 1.0:
        dk = np.ones(cov.shape[0])
        dk[:3] = k_unit
        if cov.shape[0] == 7:
            dk[6] = k_unit
        cov = cov * dk[:, None] * dk[None, :]
    return _Fit(h.lsq, fit_similarity, s, R, t_geo, resid, cov, t_fit)


def _transforms(s: float, R: np.ndarray, t_geo: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T_geo_map, T_crs_map)`` (4x4, top-left block ``s·R``): ``T = t_geo + origin`` (m)."""
    T_geo = np.eye(4)
    T_geo[:3, :3] = s * R
    T_geo[:3, 3] = t_geo
    T_crs = T_geo.copy()
    T_crs[:3, 3] = t_geo + origin
    return T_geo, T_crs


def _gcp_flags(lsq, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
    """Per-GCP w statistics, redundancy numbers, ``|w|``, the suspected blunder and flag texts."""
    w = np.asarray(lsq.w, dtype=np.float64).reshape(n, 3)
    red = np.asarray(lsq.redundancy, dtype=np.float64).reshape(n, 3)
    obs_flags = [str(f) for f in lsq.flags]
    aw = np.where(np.isfinite(w), np.abs(w), 0.0)
    fails = aw > lsq.w_critical
    blunder = np.zeros(n, dtype=bool)
    if fails.any():
        blunder[int(np.argmax(aw.max(axis=1)))] = True
    flags = []
    for i in range(n):
        fl: list[str] = []
        if blunder[i]:
            fl.append("suspected blunder")
        elif fails[i].any():
            fl.append("w-test")
        kinds = set(",".join(obs_flags[3 * i : 3 * i + 3]).split(","))
        if "weak r_i" in kinds:
            fl.append("weak r_i")
        if "no check" in kinds:
            fl.append("no check")
        flags.append(",".join(fl))
    return w, red, aw, blunder, flags


def _adjustment_checks(fit: _Fit, gcps: ControlPoints, aw: np.ndarray, blunder: np.ndarray,
                       p: GeorefParams, failed: list, warnings: list) -> dict:
    """χ² global test, the suspected blunder and the σ̂0 limit; return the χ² record.

    Appends to ``warnings`` (χ² failed, suspected blunder) and ``failed`` (σ̂0 > ``max_sigma0``).
    """
    lsq, resid = fit.lsq, fit.resid
    chi = lsq.chi2
    chi2 = {
        "statistic": float(chi.statistic),
        "dof": int(chi.dof),
        "alpha": float(chi.alpha),
        "lower": float(chi.lower),
        "upper": float(chi.upper),
        "passed": chi.passed,
        "verdict": chi.verdict,
    }
    if chi.passed is False:
        side = "too large: residuals exceed the GCP sigmas" if chi.statistic > chi.upper else (
            "too small: the GCP sigmas are pessimistic"
        )
        warnings.append(
            f"chi-square test FAILED (vTWv = {chi.statistic:.2f} outside [{chi.lower:.2f}, {chi.upper:.2f}], "
            f"sigma0 = {lsq.sigma0:.3f}, {side})"
        )
    if blunder.any():
        i = int(np.flatnonzero(blunder)[0])
        j = int(np.argmax(aw[i]))
        warnings.append(
            f"GCP {gcps.ids[i]} is a suspected blunder (|w| = {aw[i, j]:.2f} > {lsq.w_critical:.2f} in "
            f"{'ENH'[j]}, residual {resid[i, j] * 1000:.1f} mm): check its coordinates and "
            "identification, remove it and re-run"
        )

    if np.isfinite(lsq.sigma0) and lsq.sigma0 > p.max_sigma0:
        sb = f" (suspected: GCP {gcps.ids[int(np.flatnonzero(blunder)[0])]})" if blunder.any() else ""
        failed.append(
            f"the GCPs do not fit a {'similarity' if fit.fit_similarity else 'rigid'} transformation: sigma0 = "
            f"{lsq.sigma0:.1f} > {p.max_sigma0:g}, the residuals (RMS {np.sqrt(np.mean(resid**2)) * 1000:.0f} mm) "
            f"are far larger than the stated GCP sigmas. Look for a gross blunder{sb}, mismatched GCP ids, a "
            "wrong CRS, or sigmas that are far too optimistic"
        )
    return chi2


def _crs_checks(info: CRSInfo, crs_enh: np.ndarray, sig_enh: np.ndarray, extent: float,
                fit_similarity: bool, warnings: list) -> dict | None:
    """Warnings about the CRS (web-map projection, grid scale vs rigid model, area of use).

    Returns the grid scale factors at the GCP centroid (None for a geocentric CRS).
    """
    name_l = info.name.lower()
    if info.epsg == 3857 or "pseudo-mercator" in name_l or "pseudo mercator" in name_l:
        warnings.append(
            f"{info.name} is a web-map projection with large scale distortion, not a survey grid: use the "
            "mine's projected CRS (national TM grid or UTM zone)"
        )
    gf = grid_scale_factors(info.user_input, *(crs_enh.mean(axis=0))) if info.kind != "geocentric" else None
    if gf is not None and not fit_similarity:
        lever = extent * abs(gf["combined_factor"] - 1.0)
        if lever > 3.0 * float(np.median(sig_enh)):
            warnings.append(
                f"the grid's combined scale factor here is {gf['combined_ppm']:+.1f} ppm: a rigid fit leaves up to "
                f"{lever * 1000:.1f} mm in the residuals over the GCP extent — consider model 'similarity'"
            )
    area_msg = outside_area_of_use(info.user_input, crs_enh[:, :2]) if info.kind != "geocentric" else None
    if area_msg:
        warnings.append(area_msg)
    return gf


def _status(failed: list, warnings: list) -> tuple[GeorefStatus, str, list]:
    """``(status, reason, warnings)``: failed checks come first in the warning list."""
    if failed:
        status, reason = GeorefStatus.FAILED, "; ".join(failed)
        warnings = failed + warnings
    elif warnings:
        status, reason = GeorefStatus.WARNING, warnings[0]
    else:
        status, reason = GeorefStatus.OK, ""
    for msg in warnings:
        log.warning("georeference: %s", msg)
    return status, reason, warnings


def georeference(gcps: ControlPoints, crs=None, params: GeorefParams | None = None) -> GeorefResult:
    """Estimate the map-to-CRS transformation ``T_crs_map`` from ground control points.

    Parameters
    ----------
    gcps : ControlPoints
        Map coordinates ``local_xyz`` (m, errorless unless sigmas are given), CRS coordinates
        ``crs_enh`` (E, N, H in m) and their a-priori standard deviations ``sigma_enh_m``.
    crs : str, optional
        The CRS of ``crs_enh`` (e.g. ``"EPSG:5186"``); default ``gcps.crs``. If both are given
        they must be the same CRS.
    params : GeorefParams, optional

    Returns
    -------
    GeorefResult
        With ``status`` "ok", "warning" (χ² test failed, a GCP flagged, weak geometry…) or
        "failed" (unit mismatch, mirrored coordinates): a failed result must not be used.

    Raises
    ------
    TooFewPointsError
        Fewer than 3 GCPs.
    DegenerateGeometryError
        The GCPs are coincident or collinear in the map.
    CRSError
        Unknown, geographic, non-metre CRS, or ``crs`` contradicts ``gcps.crs``.

    Notes
    -----
    Observation equations ``X_i = T + s·R·x_i`` (Ghilani 2010, Ch. 18, the 3D conformal
    coordinate transformation), solved by Gauss-Newton from the closed-form start of
    [Umeyama1991 Eqs. 40-42] in :func:`minegeo.survey.helmert3d`; the CRS coordinates are first
    reduced by the recorded origin ``o`` (exact), so ``T = t_geo + o``.
    """
    t0 = time.perf_counter()
    p = params or GeorefParams()
    info, src, crs_enh, sig_enh = _checked_inputs(gcps, crs, p)
    n = len(src)
    src_c, extent, ratio = _map_geometry(src)
    origin = local_origin(crs_enh, p.origin_step_m)
    dst = crs_enh - origin  # exact (Sterbenz) for coordinates near the origin

    warnings: list[str] = []
    failed: list[str] = []
    scr = _screen_gcps(src_c, ratio, dst, sig_enh, p, failed, warnings)
    sigma_used = _sigmas_used(gcps, sig_enh, scr, p)
    fit = _fit_helmert(src, dst, sigma_used, scr.s_test, p, failed)
    s, R, t_geo, cov, lsq = fit.s, fit.R, fit.t_geo, fit.cov, fit.lsq
    T_geo, T_crs = _transforms(s, R, t_geo, origin)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    omega = log_so3(R)
    rot = omega if p.convention == "position_vector" else -omega

    w, red, aw, blunder, flags = _gcp_flags(lsq, n)
    chi2 = _adjustment_checks(fit, gcps, aw, blunder, p, failed, warnings)
    gf = _crs_checks(info, crs_enh, sig_enh, extent, fit.fit_similarity, warnings)
    status, reason, warnings = _status(failed, warnings)

    return GeorefResult(
        status=status,
        reason=reason,
        warnings=warnings,
        model="similarity" if fit.fit_similarity else "rigid",
        convention=p.convention,
        crs=info.user_input,
        crs_info=info,
        origin=origin,
        T_geo_map=T_geo,
        T_crs_map=T_crs,
        scale=s,
        scale_std=float(std[6]) if fit.fit_similarity else 0.0,
        R=R,
        rotation_pv_rad=omega,
        rotation_rad=rot,
        rotation_std_rad=std[3:6].copy(),
        euler_zyx_rad=_euler_zyx(R),
        translation_m=t_geo + origin,
        translation_std_m=std[:3].copy(),
        cov=cov,
        gcp_ids=list(gcps.ids),
        gcp_local_xyz=src.copy(),
        gcp_crs_enh=crs_enh.copy(),
        sigma_used_m=sigma_used,
        residuals_m=fit.resid,
        w=w,
        redundancy=red,
        w_critical=float(lsq.w_critical),
        flags=flags,
        blunder=blunder,
        sigma0=float(lsq.sigma0),
        dof=int(lsq.dof),
        vtwv=float(lsq.vtwv),
        chi2=chi2,
        variance_used=str(lsq.variance_used),
        scale_estimate_spread=float(scr.s_spread),
        geometry_ratio=ratio,
        grid_factors=gf,
        params=p,
        timings_s={"fit": fit.t_fit, "total": time.perf_counter() - t0},
    )
