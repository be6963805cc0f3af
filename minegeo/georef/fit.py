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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo.errors import (
    ConvergenceError,
    CRSError,
    DegenerateGeometryError,
    FileFormatError,
    InputError,
    TooFewPointsError,
)
from minegeo.geometry.se3 import hat, log_so3
from minegeo.georef.crs import (
    CRSInfo,
    crs_info,
    grid_scale_factors,
    local_origin,
    outside_area_of_use,
    same_crs,
)
from minegeo.io.types import ControlPoints, PointCloud
from minegeo.survey.angles import RHO_ARCSEC, format_dms
from minegeo.survey.helmert import helmert3d
from minegeo.survey.lsq import LSQOptions, LSQResult

log = logging.getLogger(__name__)

__all__ = [
    "GeorefParams",
    "GeorefResult",
    "georeference",
    "apply_georef",
    "map_to_crs",
    "crs_to_map",
    "pose_to_crs",
    "point_covariance_crs",
    "unit_diagnosis",
    "sidecar_path",
    "write_georeferenced_map",
    "read_georef",
    "load_georeferenced_map",
]

_MODELS = ("rigid", "similarity")
_CONVENTIONS = {
    "position_vector": "position_vector",
    "pv": "position_vector",
    "9606": "position_vector",
    "epsg:9606": "position_vector",
    "bursa_wolf": "position_vector",
    "coordinate_frame": "coordinate_frame",
    "cf": "coordinate_frame",
    "9607": "coordinate_frame",
    "epsg:9607": "coordinate_frame",
}

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


@dataclass(frozen=True)
class GeorefParams:
    """Parameters of :func:`georeference`.

    Attributes
    ----------
    model : {"similarity", "rigid"}
        7-parameter similarity (scale estimated: absorbs the grid's combined scale factor)
        or 6-parameter rigid (``s = 1``).
    convention : {"position_vector", "coordinate_frame"}
        How rotation parameters are reported: EPSG 9606 (position vector, Bursa-Wolf) or EPSG
        9607 (coordinate frame, opposite signs). The estimate is the same.
    blunder_alpha : float
        Significance level of Baarda's w-test per coordinate (0.001 -> |w| > 3.29).
    chi2_alpha : float
        Significance level of the two-tailed χ² global test (0.05 -> 95 %).
    sigma_local_m : float
        A-priori standard deviation (m) of the map coordinates of every GCP (target picking
        in the scan), used when the GCP file has no ``sigma_x_m…`` columns; 0 = errorless.
    variance : {"aposteriori", "apriori"}
        Which σ0 scales the parameter covariance: the estimated σ̂0 (default; standard
        adjustment output) or the a-priori σ0 = 1 (when the GCP sigmas are trusted).
    max_scale_deviation : float
        Unit rule: the rotation-free scale estimate ŝ must satisfy ``|ŝ − 1| ≤`` this, else
        status ``failed`` (mismatched units or GCP ids).
    origin_step_m : float
        The recorded local origin is the GCP centroid in the CRS rounded to this step (m).
    allow_geocentric : bool
        Accept a geocentric Cartesian CRS (datum checks); a mine map needs a projected CRS.
    min_geometry_ratio : float
        Warn when the GCPs are nearly collinear: second/first singular value of the centred
        map coordinates below this ratio.
    max_sigma0 : float
        Status ``failed`` when σ̂0 exceeds this: the residuals are that many times larger than
        the stated GCP sigmas (a gross blunder, mismatched ids, or sigmas far too optimistic) —
        such a fit must not georeference a map.
    """

    model: str = "similarity"
    convention: str = "position_vector"
    blunder_alpha: float = 0.001
    chi2_alpha: float = 0.05
    sigma_local_m: float = 0.0
    variance: str = "aposteriori"
    max_scale_deviation: float = 0.01
    origin_step_m: float = 1000.0
    allow_geocentric: bool = False
    min_geometry_ratio: float = 0.05
    max_sigma0: float = 10.0

    def __post_init__(self):
        if self.model not in _MODELS:
            raise InputError(f"model must be 'rigid' or 'similarity', got {self.model!r}")
        conv = str(self.convention).lower().replace("-", "_").replace(" ", "_")
        if conv not in _CONVENTIONS:
            raise InputError(
                f"unknown rotation convention {self.convention!r}: use 'position_vector' (EPSG 9606) "
                "or 'coordinate_frame' (EPSG 9607)"
            )
        object.__setattr__(self, "convention", _CONVENTIONS[conv])
        for name in ("blunder_alpha", "chi2_alpha"):
            v = getattr(self, name)
            if not (0.0 < v < 1.0):
                raise InputError(f"{name} must be between 0 and 1, got {v!r}")
        if not (math.isfinite(self.sigma_local_m) and self.sigma_local_m >= 0):
            raise InputError(f"sigma_local_m must be >= 0 (m), got {self.sigma_local_m!r}")
        if self.variance not in ("aposteriori", "apriori"):
            raise InputError(f"variance must be 'aposteriori' or 'apriori', got {self.variance!r}")
        if not (math.isfinite(self.max_scale_deviation) and 0 < self.max_scale_deviation < 1):
            raise InputError(f"max_scale_deviation must be in (0, 1), got {self.max_scale_deviation!r}")
        if not (math.isfinite(self.origin_step_m) and self.origin_step_m > 0):
            raise InputError(f"origin_step_m must be > 0, got {self.origin_step_m!r}")
        if not (0 <= self.min_geometry_ratio < 1):
            raise InputError(f"min_geometry_ratio must be in [0, 1), got {self.min_geometry_ratio!r}")
        if not (self.max_sigma0 > 1):
            raise InputError(f"max_sigma0 must be > 1, got {self.max_sigma0!r}")

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class GeorefResult:
    """Map-to-CRS transformation estimated from GCPs, with its statistics.

    Frames: ``map`` (the map's own coordinates, metres), ``crs`` (E, N, H of the CRS, metres)
    and ``geo`` = ``crs − origin`` (the recorded local origin; what georeferenced clouds store).

    Attributes
    ----------
    status : {"ok", "warning", "failed"}
    reason : str
        Why the status is not "ok" (empty when ok).
    warnings : list of str
        Every check that fired.
    model, convention : str
    crs : str
        CRS as given (e.g. ``"EPSG:5186"``).
    crs_info : CRSInfo
    origin : ndarray (3,)
        Recorded local origin in the CRS (m); ``geo = crs − origin``.
    T_geo_map : ndarray (4, 4)
        ``p_geo = s·R·p_map + t_geo`` (small numbers, full precision).
    T_crs_map : ndarray (4, 4)
        ``p_crs = s·R·p_map + T``; its top-left block is ``s·R`` — **not a rigid transform**
        when ``s != 1`` (similarity model). ``T = t_geo + origin``.
    scale, scale_std : float
        ``s`` and its standard deviation (``s = 1``, std 0 for the rigid model).
    R : ndarray (3, 3)
        Rotation matrix (map axes -> CRS E, N, H axes).
    rotation_pv_rad : ndarray (3,)
        Position-vector rotation vector ``ω`` with ``R = exp([ω]×)`` (rad).
    rotation_rad : ndarray (3,)
        ``ω`` in the requested convention (``−ω`` for coordinate frame).
    rotation_std_rad : ndarray (3,)
        Standard deviations of small rotations about E, N, H (rad).
    euler_zyx_rad : ndarray (3,)
        (roll about E, pitch about N, yaw about H) with ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``;
        yaw is the map's rotation about the vertical (counter-clockwise from the map x axis
        to grid east).
    translation_m : ndarray (3,)
        ``T`` (CRS coordinates of the map origin, m).
    translation_std_m : ndarray (3,)
    cov : ndarray (6, 6) or (7, 7)
        Covariance of ``(T_E, T_N, T_H, δ_E, δ_N, δ_H[, ds])`` (m, rad, dimensionless).
    gcp_ids : list of str
    gcp_local_xyz, gcp_crs_enh : ndarray (n, 3)
        The control points used (map coordinates; CRS coordinates).
    sigma_used_m : ndarray (n, 3)
        A-priori standard deviations that made the weights (CRS + map contribution).
    residuals_m : ndarray (n, 3)
        ``v = fitted − observed`` in E, N, H (m).
    w : ndarray (n, 3)
        Baarda's w statistic per coordinate.
    redundancy : ndarray (n, 3)
        Redundancy numbers ``r_i`` (sum = dof).
    w_critical : float
    flags : list of str
        Per GCP: "" or comma list of "suspected blunder", "w-test", "weak r_i", "no check".
    blunder : ndarray (n,) of bool
        The suspected blunder (at most one GCP per run, the largest failing |w|).
    sigma0 : float
        A-posteriori standard deviation of unit weight (dimensionless, 1 expected).
    dof : int
    vtwv : float
    chi2 : dict
        ``statistic, dof, alpha, lower, upper, passed, verdict`` ("PASSED"/"FAILED").
    variance_used : str
    scale_estimate_spread : float
        Rotation-free scale estimate used by the unit rule.
    geometry_ratio : float
        Second/first singular value of the centred map GCP coordinates (0 = collinear).
    grid_factors : dict or None
        Point scale factor, height factor and combined factor at the GCP centroid.
    params : GeorefParams
    timings_s : dict
    """

    status: str
    reason: str
    warnings: list
    model: str
    convention: str
    crs: str
    crs_info: CRSInfo
    origin: np.ndarray
    T_geo_map: np.ndarray
    T_crs_map: np.ndarray
    scale: float
    scale_std: float
    R: np.ndarray
    rotation_pv_rad: np.ndarray
    rotation_rad: np.ndarray
    rotation_std_rad: np.ndarray
    euler_zyx_rad: np.ndarray
    translation_m: np.ndarray
    translation_std_m: np.ndarray
    cov: np.ndarray
    gcp_ids: list
    gcp_local_xyz: np.ndarray
    gcp_crs_enh: np.ndarray
    sigma_used_m: np.ndarray
    residuals_m: np.ndarray
    w: np.ndarray
    redundancy: np.ndarray
    w_critical: float
    flags: list
    blunder: np.ndarray
    sigma0: float
    dof: int
    vtwv: float
    chi2: dict
    variance_used: str
    scale_estimate_spread: float
    geometry_ratio: float
    grid_factors: dict | None
    params: GeorefParams
    timings_s: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ derived values
    @property
    def ok(self) -> bool:
        """True unless the status is "failed"."""
        return self.status != "failed"

    @property
    def n_gcps(self) -> int:
        return len(self.gcp_ids)

    @property
    def ds_ppm(self) -> float:
        """Scale difference ``(s − 1)·10⁶``."""
        return (self.scale - 1.0) * 1e6

    @property
    def rotation_dms(self) -> list:
        """Rotation parameters (requested convention) as signed DMS text."""
        return [format_dms(float(a), 3, signed=True) for a in self.rotation_rad]

    @property
    def rotation_arcsec(self) -> np.ndarray:
        return self.rotation_rad * RHO_ARCSEC

    @property
    def rotation_std_arcsec(self) -> np.ndarray:
        return self.rotation_std_rad * RHO_ARCSEC

    @property
    def euler_zyx_dms(self) -> list:
        return [format_dms(float(a), 2, signed=True) for a in self.euler_zyx_rad]

    @property
    def rms_m(self) -> dict:
        """RMS of the residuals: horizontal (E, N together), height, 3D (m)."""
        v = self.residuals_m
        return {
            "horizontal": float(np.sqrt(np.mean(np.sum(v[:, :2] ** 2, axis=1)))),
            "height": float(np.sqrt(np.mean(v[:, 2] ** 2))),
            "3d": float(np.sqrt(np.mean(np.sum(v**2, axis=1)))),
        }

    @property
    def suspected_blunder_id(self) -> str | None:
        idx = np.flatnonzero(self.blunder)
        return self.gcp_ids[int(idx[0])] if idx.size else None

    # ------------------------------------------------------------------ (de)serialisation
    def as_dict(self) -> dict:
        """JSON-ready dict (numbers as lists) that :meth:`from_dict` restores exactly."""
        gcps = []
        for i, gid in enumerate(self.gcp_ids):
            gcps.append(
                {
                    "id": gid,
                    "local_xyz_m": self.gcp_local_xyz[i].tolist(),
                    "crs_enh_m": self.gcp_crs_enh[i].tolist(),
                    "sigma_used_m": self.sigma_used_m[i].tolist(),
                    "residual_enh_m": self.residuals_m[i].tolist(),
                    "w": [None if not np.isfinite(x) else float(x) for x in self.w[i]],
                    "redundancy": self.redundancy[i].tolist(),
                    "flags": self.flags[i],
                    "suspected_blunder": bool(self.blunder[i]),
                }
            )
        return {
            "status": self.status,
            "reason": self.reason,
            "warnings": list(self.warnings),
            "model": self.model,
            "model_equation": "X_crs = T + s * R * x_map  (T_crs_map = [[s*R, T], [0, 1]]"
            + ("; s = 1 fixed)" if self.model == "rigid" else "; not rigid when s != 1)"),
            "convention": self.convention,
            "convention_note": "position_vector = EPSG 9606 (Bursa-Wolf): R = exp([omega]x); "
            "coordinate_frame = EPSG 9607: rotations of opposite sign",
            "crs": self.crs,
            "crs_info": self.crs_info.as_dict(),
            "origin": self.origin.tolist(),
            "frames": "map = input map frame; crs = (E, N, H) of the CRS; geo = crs - origin",
            "T_geo_map": self.T_geo_map.tolist(),
            "T_crs_map": self.T_crs_map.tolist(),
            "scale": self.scale,
            "scale_std": self.scale_std,
            "ds_ppm": self.ds_ppm,
            "R": self.R.tolist(),
            "rotation_pv_rad": self.rotation_pv_rad.tolist(),
            "rotation_rad": self.rotation_rad.tolist(),
            "rotation_arcsec": self.rotation_arcsec.tolist(),
            "rotation_dms": self.rotation_dms,
            "rotation_std_rad": self.rotation_std_rad.tolist(),
            "rotation_std_arcsec": self.rotation_std_arcsec.tolist(),
            "euler_zyx_rad": self.euler_zyx_rad.tolist(),
            "euler_zyx_dms": self.euler_zyx_dms,
            "translation_m": self.translation_m.tolist(),
            "translation_std_m": self.translation_std_m.tolist(),
            "cov": self.cov.tolist(),
            "cov_order": ["T_E", "T_N", "T_H", "rot_E", "rot_N", "rot_H"] + (["ds"] if self.cov.shape[0] == 7 else []),
            "gcps": gcps,
            "w_critical": self.w_critical,
            "sigma0": self.sigma0,
            "dof": self.dof,
            "vtwv": self.vtwv,
            "chi2": dict(self.chi2),
            "variance_used": self.variance_used,
            "rms_m": self.rms_m,
            "suspected_blunder": self.suspected_blunder_id,
            "scale_estimate_spread": self.scale_estimate_spread,
            "geometry_ratio": self.geometry_ratio,
            "grid_factors": self.grid_factors,
            "params": self.params.as_dict(),
            "timings_s": dict(self.timings_s),
        }

    @classmethod
    def from_dict(cls, d: dict) -> GeorefResult:
        """Rebuild a result from :meth:`as_dict` output (e.g. a ``.georef.json`` sidecar)."""
        try:
            g = d["gcps"]

            def arr(key, shape=None):
                a = np.asarray(d[key], dtype=np.float64)
                return a.reshape(shape) if shape is not None else a

            def num(key, default=float("nan")):
                v = d.get(key, default)
                return float("nan") if v is None else float(v)

            def col(key):
                return np.array(
                    [[np.nan if x is None else x for x in r[key]] for r in g], dtype=np.float64
                ).reshape(len(g), 3)

            return cls(
                status=str(d["status"]),
                reason=str(d.get("reason", "")),
                warnings=list(d.get("warnings", [])),
                model=str(d["model"]),
                convention=str(d["convention"]),
                crs=str(d["crs"]),
                crs_info=CRSInfo.from_dict(d.get("crs_info", {})),
                origin=arr("origin", (3,)),
                T_geo_map=arr("T_geo_map", (4, 4)),
                T_crs_map=arr("T_crs_map", (4, 4)),
                scale=float(d["scale"]),
                scale_std=num("scale_std", 0.0),
                R=arr("R", (3, 3)),
                rotation_pv_rad=arr("rotation_pv_rad", (3,)),
                rotation_rad=arr("rotation_rad", (3,)),
                rotation_std_rad=arr("rotation_std_rad", (3,)),
                euler_zyx_rad=arr("euler_zyx_rad", (3,)),
                translation_m=arr("translation_m", (3,)),
                translation_std_m=arr("translation_std_m", (3,)),
                cov=np.asarray(d["cov"], dtype=np.float64),
                gcp_ids=[str(r["id"]) for r in g],
                gcp_local_xyz=col("local_xyz_m"),
                gcp_crs_enh=col("crs_enh_m"),
                sigma_used_m=col("sigma_used_m"),
                residuals_m=col("residual_enh_m"),
                w=col("w"),
                redundancy=col("redundancy"),
                w_critical=num("w_critical"),
                flags=[str(r.get("flags", "")) for r in g],
                blunder=np.array([bool(r.get("suspected_blunder", False)) for r in g], dtype=bool),
                sigma0=num("sigma0"),
                dof=int(d["dof"]),
                vtwv=num("vtwv"),
                chi2=dict(d["chi2"]),
                variance_used=str(d.get("variance_used", "aposteriori")),
                scale_estimate_spread=num("scale_estimate_spread"),
                geometry_ratio=num("geometry_ratio"),
                grid_factors=d.get("grid_factors"),
                params=GeorefParams(**d.get("params", {})),
                timings_s=dict(d.get("timings_s", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a minegeo georeferencing record (missing or bad field: {exc})") from None


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


def _status(failed: list, warnings: list) -> tuple[str, str, list]:
    """``(status, reason, warnings)``: failed checks come first in the warning list."""
    if failed:
        status, reason = "failed", "; ".join(failed)
        warnings = failed + warnings
    elif warnings:
        status, reason = "warning", warnings[0]
    else:
        status, reason = "ok", ""
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


# ---------------------------------------------------------------------------- application
def _check_usable(result: GeorefResult, allow_failed: bool) -> None:
    if not isinstance(result, GeorefResult):
        raise InputError(f"result must be a GeorefResult, got {type(result).__name__}")
    if result.status == "failed" and not allow_failed:
        raise InputError(f"the georeferencing failed and must not be applied: {result.reason}")


def map_to_crs(points_map, result: GeorefResult, map_origin=None, *, allow_failed: bool = False) -> np.ndarray:
    """Map coordinates -> CRS coordinates **relative to** ``result.origin`` (the ``geo`` frame).

    ``p_geo = s·R·(p + o_map) + t_geo = s·R·p + (s·R·o_map + t_geo)``; add ``result.origin``
    for full CRS coordinates (only when printing: the sum loses precision at ~1e-9 m).
    """
    _check_usable(result, allow_failed)
    p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
    A = result.T_geo_map[:3, :3]
    b = result.T_geo_map[:3, 3]
    if map_origin is not None:
        b = A @ np.asarray(map_origin, dtype=np.float64).reshape(3) + b
    return p @ A.T + b


def crs_to_map(points_geo, result: GeorefResult, map_origin=None, *, allow_failed: bool = False) -> np.ndarray:
    """Inverse of :func:`map_to_crs`: ``geo`` coordinates (CRS − ``result.origin``) -> map coordinates.

    ``p_map = Rᵀ(p_geo − t_geo)/s − o_map`` (``o_map`` = the map cloud's own origin, if any).
    """
    _check_usable(result, allow_failed)
    q = np.asarray(points_geo, dtype=np.float64).reshape(-1, 3)
    p = (q - result.T_geo_map[:3, 3]) @ result.R / result.scale
    if map_origin is not None:
        p = p - np.asarray(map_origin, dtype=np.float64).reshape(3)
    return p


def pose_to_crs(T_map_body, result: GeorefResult, *, allow_failed: bool = False) -> np.ndarray:
    """Express body poses (sensor, vehicle) given in the map frame in the ``geo`` frame.

    ``T_geo_body = [[R·R_map_body, s·R·t_map_body + t_geo], [0, 1]]``: the position goes through
    the full similarity, the orientation only through the rotation ``R`` — a pose stays rigid even
    when the map-to-CRS scale ``s != 1``. Add ``result.origin`` to the translation for full CRS
    coordinates (printing only).

    Parameters
    ----------
    T_map_body : array_like (4, 4) or (m, 4, 4)
    result : GeorefResult

    Returns
    -------
    ndarray (4, 4) or (m, 4, 4)
        ``T_geo_body``.
    """
    _check_usable(result, allow_failed)
    T = np.asarray(T_map_body, dtype=np.float64)
    single = T.ndim == 2
    T = T.reshape(-1, 4, 4)
    if not np.isfinite(T).all():
        raise InputError("T_map_body contains NaN or inf")
    out = np.zeros_like(T)
    out[:, :3, :3] = np.einsum("ij,mjk->mik", result.R, T[:, :3, :3])
    out[:, :3, 3] = T[:, :3, 3] @ result.T_geo_map[:3, :3].T + result.T_geo_map[:3, 3]
    out[:, 3, 3] = 1.0
    return out[0] if single else out


def apply_georef(cloud: PointCloud, result: GeorefResult, *, allow_failed: bool = False) -> PointCloud:
    """Transform a map cloud into the CRS, stored relative to the recorded origin.

    Parameters
    ----------
    cloud : PointCloud
        The map (``points + cloud.origin`` are map coordinates, metres).
    result : GeorefResult
        From :func:`georeference`; a ``failed`` result is refused unless ``allow_failed``.

    Returns
    -------
    PointCloud
        ``points`` in the ``geo`` frame (CRS minus ``result.origin``), ``origin =
        result.origin``, ``crs = result.crs``, ``frame = "crs"``; normals rotated by ``R``;
        attributes copied. ``global_points`` gives full E, N, H. No precision is lost: the
        only large number, the origin, is never added to the points.
    """
    if not isinstance(cloud, PointCloud):
        raise InputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
    pts = map_to_crs(cloud.points, result, cloud.origin, allow_failed=allow_failed)
    normals = None if cloud.normals is None else cloud.normals @ result.R.T
    meta = dict(cloud.metadata)
    meta["georef"] = {
        "T_crs_map": result.T_crs_map.tolist(),
        "origin": result.origin.tolist(),
        "crs": result.crs,
        "model": result.model,
        "status": result.status,
    }
    return PointCloud(
        points=pts,
        normals=normals,
        attributes={k: np.array(v, copy=True) for k, v in cloud.attributes.items()},
        origin=result.origin.copy(),
        crs=result.crs,
        frame="crs",
        metadata=meta,
    )


def point_covariance_crs(points_map, result: GeorefResult) -> np.ndarray:
    """Covariance (m²) of transformed points due to the uncertainty of the transformation.

    ``X = T + s·exp([δ]×)·R·x`` gives the Jacobian ``J = [I, −s[R x]×, R x]`` with respect to
    ``(T, δ, ds)``; ``Σ_X = J Σ Jᵀ`` (first-order propagation; the map coordinates are taken as
    errorless). Returns ``(m, 3, 3)`` for ``m`` points given in map coordinates.
    """
    x = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
    C = result.cov
    u = C.shape[0]
    out = np.empty((x.shape[0], 3, 3))
    for i, xi in enumerate(x):
        rx = result.R @ xi
        J = np.zeros((3, u))
        J[:, :3] = np.eye(3)
        J[:, 3:6] = -result.scale * hat(rx)
        if u == 7:
            J[:, 6] = rx
        out[i] = J @ C @ J.T
    return out


# ---------------------------------------------------------------------------- files
#: ``format`` tag of the sidecar JSON
SIDECAR_FORMAT = "minegeo-georef"
SIDECAR_VERSION = 1


def sidecar_path(map_path) -> Path:
    """Sidecar of a georeferenced map: ``<MAP_GEO>.georef.json`` (e.g. ``map_geo.ply.georef.json``)."""
    p = Path(map_path)
    return p.parent / (p.name + ".georef.json")  # not with_name: it raises for "." (empty name)


def write_georeferenced_map(path, cloud_geo: PointCloud, result: GeorefResult, *, extra: dict | None = None) -> tuple:
    """Write a georeferenced cloud and its sidecar ``<path>.georef.json``, atomically.

    PLY/PCD/XYZ/CSV store the ``geo`` coordinates (CRS − origin) with the origin recorded in
    the header (``comment minegeo origin E N H``); LAS/LAZ store full CRS coordinates as
    integers with the origin as the LAS offset (1 mm resolution). The sidecar holds
    ``T_crs_map``, ``T_geo_map``, the origin, the CRS, the full fit statistics
    (:meth:`GeorefResult.as_dict`) and the SHA-256 of the written cloud, so
    :func:`load_georeferenced_map` can detect a sidecar that no longer matches its cloud.

    Returns
    -------
    (Path, Path)
        The cloud file and the sidecar.
    """
    from minegeo.io import write_point_cloud

    if not isinstance(result, GeorefResult):
        raise InputError(f"result must be a GeorefResult, got {type(result).__name__}")
    if not np.array_equal(cloud_geo.origin, result.origin):
        raise InputError("the cloud is not in the georeferenced frame of this result (origins differ): use apply_georef")
    p = Path(path)
    fmt = p.suffix.lower().lstrip(".")
    if fmt in ("las", "laz"):
        write_point_cloud(p, cloud_geo, las_offset=result.origin)
    else:
        write_point_cloud(p, cloud_geo, coordinates="local")
    return p, _write_sidecar(p, result, extra)


def _write_sidecar(p: Path, result: GeorefResult, extra: dict | None) -> Path:
    """The ``<p>.georef.json`` of a written georeferenced cloud ``p`` (see :func:`write_georeferenced_map`)."""
    from minegeo._provenance import sha256_file, write_json_atomic

    side = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "map_file": p.name,
        "map_sha256": sha256_file(p),
        "crs": result.crs,
        "origin": result.origin.tolist(),
        "T_crs_map": result.T_crs_map.tolist(),
        "T_geo_map": result.T_geo_map.tolist(),
        "frames": "points in the file are geo = CRS - origin (PLY/PCD/text) or full CRS (LAS); "
        "T_crs_map maps the original map frame into the CRS",
        # no timings: the sidecar is bit-identical for the same inputs (timings are in result.json)
        "georef": {k: v for k, v in result.as_dict().items() if k != "timings_s"},
    }
    if extra:
        side.update(extra)
    return write_json_atomic(sidecar_path(p), side)


#: Points of the map kept for the report's plan view (:func:`minegeo.report.georef_report.plot_georef_png`).
REPORT_CLOUD_POINTS = 20000


def report_sample_rows(n: int, max_points: int = REPORT_CLOUD_POINTS, seed: int = 0) -> np.ndarray:
    """Rows of an ``n``-point map that the report's plot draws (its own subsampling rule), sorted."""
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def stream_georeferenced_map(path, chunks, result: GeorefResult, n_points: int, *, allow_failed: bool = False,
                             extra: dict | None = None, progress=None) -> tuple:
    """:func:`apply_georef` + :func:`write_georeferenced_map` chunk by chunk, for a binary PLY output.

    The bytes written are those of ``write_georeferenced_map(path, apply_georef(cloud, result), ...)``
    for a cloud with x, y, z only (float64 binary little-endian PLY, ``geo`` coordinates with the
    origin in the header): the header of the same writer with the vertex count of the map, then
    each chunk through :func:`map_to_crs`. Memory: one chunk.

    Parameters
    ----------
    path : str or Path
        Output ``.ply`` (written in place: call it on a staged path, e.g. ``OutputTransaction.file``).
    chunks : PointChunks
        The map (:func:`minegeo.io.chunked.open_point_chunks`) opened with ``origin`` = the map
        cloud's local origin; every chunk is ``points`` of that cloud.
    result : GeorefResult
    n_points : int
        Points of the map (pass 1).
    allow_failed : bool
    extra : dict, optional
        Added to the sidecar.
    progress : callable, optional
        ``progress(bytes_read, size_bytes)`` after each chunk.

    Returns
    -------
    (Path, Path, PointCloud)
        The cloud file, the sidecar, and the rows :func:`report_sample_rows` of the
        georeferenced cloud (for the report's plot).
    """
    from minegeo.io.ply import write_ply_bytes

    _check_usable(result, allow_failed)
    p = Path(path)
    empty = PointCloud(points=np.zeros((0, 3)), origin=result.origin.copy(), crs=result.crs, frame="crs")
    head = write_ply_bytes(empty, coordinates="local")
    old = b"element vertex 0\n"
    if head.count(old) != 1:  # pragma: no cover - the writer's header layout changed
        raise InputError("internal error: unexpected PLY header layout for the chunked georeferenced map")
    head = head.replace(old, f"element vertex {int(n_points)}\n".encode("ascii"))
    rows = report_sample_rows(int(n_points))
    sample = np.empty((rows.size, 3))
    done = 0
    with open(p, "wb") as fh:
        fh.write(head)
        for c in chunks:
            g = map_to_crs(c, result, chunks.origin, allow_failed=allow_failed)
            fh.write(np.ascontiguousarray(g, dtype="<f8").tobytes())
            lo, hi = np.searchsorted(rows, [done, done + g.shape[0]])
            sample[lo:hi] = g[rows[lo:hi] - done]
            done += g.shape[0]
            if progress is not None:
                progress(chunks.bytes_read, chunks.size_bytes)
    if done != n_points:
        raise FileFormatError(chunks.path, f"the map changed while it was read ({n_points} then {done} points)")
    cloud = PointCloud(points=sample, origin=result.origin.copy(), crs=result.crs, frame="crs")
    return p, _write_sidecar(p, result, extra), cloud


def stream_georeferenced_las(path, chunks, result: GeorefResult, n_points: int, *, allow_failed: bool = False,
                             extra: dict | None = None, progress=None) -> tuple:
    """:func:`apply_georef` + :func:`write_georeferenced_map` chunk by chunk, LAS/LAZ in, LAS/LAZ out.

    Every record of the map is copied with **all its fields** (intensity, return numbers,
    classification, GPS time, colour, extra bytes) in the map's own point format and LAS version;
    only ``X, Y, Z`` change: ``X = round(p_geo / scale)`` with ``p_geo`` = :func:`map_to_crs` of
    the chunk and the header offset set to ``result.origin``, so the file holds full CRS
    coordinates ``X·scale + origin`` at the map's resolution (its own ``scale``), the same integers
    as the whole-file path writes (``write_georeferenced_map`` with ``las_offset = result.origin``
    and the scale the map was read with). The CRS record is replaced by ``result.crs``; the input's
    other VLRs are kept. Memory: one chunk.

    Parameters
    ----------
    path : str or Path
        Output ``.las`` or ``.laz`` (written in place: call it on a staged path).
    chunks : PointChunks
        The map (:func:`minegeo.io.chunked.open_point_chunks` of a LAS/LAZ file), ``origin`` set by
        pass 1; its chunks are the map cloud's ``points``.
    result : GeorefResult
    n_points : int
        Points of the map (pass 1).
    allow_failed : bool
    extra : dict, optional
        Added to the sidecar.
    progress : callable, optional
        ``progress(bytes_read, size_bytes)`` after each chunk.

    Returns
    -------
    (Path, Path, PointCloud)
        As :func:`stream_georeferenced_map`.
    """
    from minegeo.io.las import _laspy

    _check_usable(result, allow_failed)
    laspy = _laspy()
    p = Path(path)
    src = Path(chunks.path)
    rows = report_sample_rows(int(n_points))
    sample = np.empty((rows.size, 3))
    done = 0
    it = iter(chunks)  # the coordinates, with every check of the chunked reader
    try:
        with laspy.open(src) as rd:
            ih = rd.header
            hdr = laspy.LasHeader(point_format=ih.point_format, version=ih.version)
            hdr.scales = np.asarray(ih.scales, dtype=np.float64)
            hdr.offsets = result.origin.copy()
            crs_ids = {(b"LASF_Projection", 2111), (b"LASF_Projection", 2112), (b"LASF_Projection", 34735),
                       (b"LASF_Projection", 34736), (b"LASF_Projection", 34737)}

            def _keep(v):
                uid = v.user_id.encode() if isinstance(v.user_id, str) else bytes(v.user_id)
                return (uid.rstrip(b"\0"), int(v.record_id)) not in crs_ids and type(v).__name__ != "ExtraBytesVlr"

            hdr.vlrs.extend(v for v in ih.vlrs if _keep(v))
            if result.crs:
                import pyproj

                hdr.add_crs(pyproj.CRS.from_user_input(result.crs))
            scale = hdr.scales
            with laspy.open(p, mode="w", header=hdr, do_compress=p.suffix.lower() == ".laz") as wr:
                for pts in rd.chunk_iterator(chunks.chunk_points):
                    c = next(it)
                    if c.shape[0] != len(pts):  # pragma: no cover - both read the same file in the same chunks
                        raise FileFormatError(src, "the map changed while it was read")
                    g = map_to_crs(c, result, chunks.origin, allow_failed=allow_failed)
                    Xf = np.round(g / scale)
                    if Xf.size and (np.abs(Xf).max() > 2**31 - 1):
                        raise InputError(f"the georeferenced coordinates do not fit LAS 32-bit integers at the map's "
                                         f"scale {scale.tolist()} (the fit moves points by more than 2^31 units)")
                    rec = laspy.ScaleAwarePointRecord(pts.array.copy(), pts.point_format, scales=hdr.scales,
                                                      offsets=hdr.offsets)
                    rec.X = Xf[:, 0].astype(np.int32)
                    rec.Y = Xf[:, 1].astype(np.int32)
                    rec.Z = Xf[:, 2].astype(np.int32)
                    wr.write_points(rec)
                    lo, hi = np.searchsorted(rows, [done, done + g.shape[0]])
                    sample[lo:hi] = g[rows[lo:hi] - done]
                    done += g.shape[0]
                    if progress is not None:
                        progress(chunks.bytes_read, chunks.size_bytes)
    except (FileFormatError, InputError):
        raise
    except (KeyboardInterrupt, SystemExit, MemoryError):
        raise
    except BaseException as exc:  # laspy/lazrs raise several types
        raise FileFormatError(src, f"unreadable LAS/LAZ: truncated or corrupt ({type(exc).__name__}: {exc})") from None
    if done != n_points:
        raise FileFormatError(src, f"the map changed while it was read ({n_points} then {done} points)")
    cloud = PointCloud(points=sample, origin=result.origin.copy(), crs=result.crs, frame="crs")
    return p, _write_sidecar(p, result, extra), cloud


def read_georef(path) -> GeorefResult:
    """Read a :class:`GeorefResult` from a ``.georef.json`` sidecar or a ``georef`` ``result.json``."""
    from minegeo.io._json import load_json_file

    p = Path(path)
    d = load_json_file(p, what="georeferencing record")  # bounded, no duplicate keys, no NaN
    if isinstance(d, dict) and "georef" in d and isinstance(d["georef"], dict):
        d = d["georef"]
    elif isinstance(d, dict) and "result" in d and isinstance(d["result"], dict):
        d = d["result"]
    try:
        return GeorefResult.from_dict(d)
    except InputError as exc:
        raise FileFormatError(p, str(exc)) from None


def read_georef_sidecar(path, *, check_hash: bool = True) -> tuple:
    """The checks of :func:`load_georeferenced_map` without reading the cloud: ``(cloud path,
    sidecar path, GeorefResult)`` (for chunked reading of large maps, see
    :func:`minegeo.localize.prepared.prepare_map_file`). Raises as :func:`load_georeferenced_map`."""
    from minegeo._provenance import sha256_file
    from minegeo.io._json import load_json_file

    p = Path(path)
    if p.name.endswith(".georef.json"):
        side_p = p
        cloud_p = p.with_name(p.name[: -len(".georef.json")])
    else:
        cloud_p = p
        side_p = sidecar_path(p)
    if not side_p.exists():
        raise FileFormatError(
            cloud_p,
            f"no georeferencing sidecar {side_p.name} next to the map: georeference it with "
            "'minegeo georef --map MAP --gcps GCPS.csv --crs EPSG:xxxx --out MAP_GEO'",
        )
    side = load_json_file(side_p, what="georeferencing sidecar")  # bounded, no duplicate keys, no NaN
    if not isinstance(side, dict) or side.get("format") != SIDECAR_FORMAT:
        raise FileFormatError(side_p, f"not a minegeo georeferencing sidecar (format != {SIDECAR_FORMAT!r})")
    if int(side.get("version", 0)) > SIDECAR_VERSION:
        raise FileFormatError(side_p, f"sidecar version {side.get('version')} is newer than this minegeo")
    if not cloud_p.exists():
        raise FileFormatError(side_p, f"the georeferenced map {cloud_p} named by this sidecar does not exist")
    if check_hash and side.get("map_sha256") and sha256_file(cloud_p) != side["map_sha256"]:
        raise FileFormatError(
            cloud_p,
            "the map file changed after it was georeferenced (SHA-256 differs from the sidecar): re-run minegeo georef",
        )
    try:
        result = GeorefResult.from_dict(side["georef"])
    except (KeyError, InputError) as exc:
        raise FileFormatError(side_p, f"bad georeferencing record: {exc}") from None
    from minegeo.errors import CRSError
    from minegeo.georef.crs import validate_crs

    try:  # the CRS a map claims must be one pyproj knows and minegeo can work in
        validate_crs(result.crs)
    except CRSError as exc:
        raise FileFormatError(side_p, f"the sidecar's CRS cannot be used: {exc}") from None
    return cloud_p, side_p, result


def load_georeferenced_map(path, *, check_hash: bool = True) -> tuple:
    """Load a map written by ``minegeo georef`` (or :func:`write_georeferenced_map`).

    Parameters
    ----------
    path : str or Path
        The georeferenced cloud (``map_geo.ply``) or its sidecar (``map_geo.ply.georef.json``).
    check_hash : bool
        Verify the cloud's SHA-256 against the sidecar (a modified cloud is an error).

    Returns
    -------
    (PointCloud, GeorefResult)
        The cloud with ``points`` relative to ``result.origin`` (``cloud.origin``), ``crs`` and
        ``frame = "crs"``; and the georeferencing (``T_crs_map``, ``T_geo_map``, ``origin``,
        ``crs``, statistics).

    Raises
    ------
    FileFormatError
        Missing/invalid sidecar, hash mismatch, or a cloud whose recorded CRS differs.
    """
    from minegeo.io import read_point_cloud

    cloud_p, side_p, result = read_georef_sidecar(path, check_hash=check_hash)
    cloud = read_point_cloud(cloud_p, origin=result.origin)
    if cloud.crs and not same_crs(str(cloud.crs), result.crs):
        raise FileFormatError(cloud_p, f"the file says CRS {cloud.crs} but its sidecar says {result.crs}")
    cloud.crs = result.crs
    cloud.frame = "crs"
    cloud.metadata["georef_sidecar"] = str(side_p)
    return cloud, result
