"""The parameters and the result record of a georeferencing (:func:`minegeo.georef.georeference`).

:class:`GeorefParams` holds the options of the control-point fit; :class:`GeorefResult` the
estimated map-to-CRS similarity ``T_crs_map = [[s·R, T], [0, 1]]``, its covariance and the
adjustment statistics per GCP, with :meth:`GeorefResult.as_dict` / :meth:`GeorefResult.from_dict`
as the JSON form that ``result.json`` and the ``.georef.json`` sidecar store. The model, frames and
statistics are described in :mod:`minegeo.georef.fit`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, flag, one_of, validate
from minegeo.errors import InputError
from minegeo.georef.crs import CRSInfo
from minegeo.survey.angles import RHO_ARCSEC, format_dms

__all__ = ["GeorefParams", "GeorefResult", "GeorefStatus"]

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



@dataclass(frozen=True)
class GeorefParams:
    """Parameters of :func:`georeference`.

    Each field but ``convention`` declares its rule in its metadata (:mod:`minegeo._params`): the same
    rule checks the dataclass, the ``minegeo georef`` option that sets it (``--sigma-local-m``,
    ``--blunder-alpha``, ``--max-scale-deviation``, ``--max-sigma0``) and its key in a ``--config``
    file; ``convention`` takes its spellings (``coordinate-frame``, any case) and is normalised here.

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

    model: str = one_of("similarity", _MODELS)
    convention: str = "position_vector"
    blunder_alpha: float = bounded(0.001, gt=0.0, lt=1.0)
    chi2_alpha: float = bounded(0.05, gt=0.0, lt=1.0)
    sigma_local_m: float = bounded(0.0, ge=0.0)
    variance: str = one_of("aposteriori", ("aposteriori", "apriori"))
    max_scale_deviation: float = bounded(0.01, gt=0.0, lt=1.0)
    origin_step_m: float = bounded(1000.0, gt=0.0)
    allow_geocentric: bool = flag(False)
    min_geometry_ratio: float = bounded(0.05, ge=0.0, lt=1.0)
    max_sigma0: float = bounded(10.0, gt=1.0)

    def __post_init__(self):
        validate(self)
        conv = str(self.convention).lower().replace("-", "_").replace(" ", "_")
        if conv not in _CONVENTIONS:
            raise InputError(
                f"unknown rotation convention {self.convention!r}: use 'position_vector' (EPSG 9606) "
                "or 'coordinate_frame' (EPSG 9607)"
            )
        object.__setattr__(self, "convention", _CONVENTIONS[conv])

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


class GeorefStatus(StrEnum):
    """Status of a georeferencing fit (:attr:`GeorefResult.status`); each member is its string value."""

    OK = "ok"
    #: the χ² test failed, a GCP was flagged or the geometry is weak: usable, with the warnings
    WARNING = "warning"
    #: the fit is refused (mismatched units or ids, a mirror image, an implausible residual)
    FAILED = "failed"


@dataclass(frozen=True)
class GeorefResult:
    """Map-to-CRS transformation estimated from GCPs, with its statistics.

    Frames: ``map`` (the map's own coordinates, metres), ``crs`` (E, N, H of the CRS, metres)
    and ``geo`` = ``crs − origin`` (the recorded local origin; what georeferenced clouds store).

    Attributes
    ----------
    status : GeorefStatus
        ``ok``, ``warning`` or ``failed``.
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

    status: GeorefStatus
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
                status=GeorefStatus(str(d["status"])),
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
