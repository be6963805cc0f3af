"""DXF drawings for mine-planning CAD (Deswik, Vulcan, Surpac, AutoCAD) through the optional ``ezdxf``.

``pip install 'minegeo[dxf]'`` installs ezdxf; without it every writer raises
:class:`~minegeo.errors.OptionalDependencyError`.

What is written (AutoCAD 2010 DXF, ``$INSUNITS = 6`` metres, ``$MEASUREMENT = 1`` metric):

==========================  =================================  ===============================================
layer (default prefix)      entities                           what
==========================  =================================  ===============================================
``MINEGEO_SCAN_ORIGINS``    POINT                              placed scan origins (``localize``)
``MINEGEO_TRAJECTORY``      POLYLINE (3D)                      placed sensor trajectories (``localize``)
``MINEGEO_STATIONS``        POINT                              scanner stations (``mast``)
``MINEGEO_BEACONS``         POLYLINE (3D), 4 vertices          surveyed MAST beacons (``mast``)
``MINEGEO_ADJUSTED_POINTS`` POINT                              adjusted network points (``adjust``)
``MINEGEO_FIXED_POINTS``    POINT                              fixed (control) network points (``adjust``)
``MINEGEO_ELLIPSE95``       POLYLINE (3D), closed, 72 vertices 95 % error ellipses (``ELLIPSE99`` for 0.99...)
``MINEGEO_CONTROL_STATIONS`` POINT                             control stations, surveyed E N H (``slam --control``)
``MINEGEO_CHECK_STATIONS``  POINT                              check stations, surveyed E N H (``slam --control``)
``MINEGEO_RESIDUALS``       POLYLINE (3D), 2 vertices          surveyed -> estimated, exaggerated (``slam --control``)
``MINEGEO_LABELS``          TEXT                               names, at the point they name
==========================  =================================  ===============================================

Coordinates are the CRS coordinates (x = Easting, y = Northing, z = height, metres) as float64;
DXF stores doubles and ezdxf writes each with its shortest exact representation, so a file read
back gives every coordinate bit for bit. A result without a CRS is drawn in its own frame (the
map frame of ``localize``, the mine frame of ``mast``), and the custom property
``MINEGEO_FRAME`` says which.

**Ellipses are closed 3-D polylines of 72 vertices** (every 5 degrees) at the point's height,
not DXF ``ELLIPSE`` entities: polylines are imported by every mine-planning package as strings
(Surpac, Vulcan, Deswik), whereas ``ELLIPSE`` is a curve some of them drop or flatten to z = 0.
The largest gap between the 72-gon and the true ellipse is ``a (1 - cos 2.5 deg) < 0.001 a``
(0.05 mm for a 50 mm ellipse). The ellipse is the 95 % confidence ellipse of the 2-D
(Easting, Northing) covariance: semi-axes ``k sqrt(lambda)`` of its eigenvalues with
``k = sqrt(chi2(2, 0.95)) = sqrt(-2 ln 0.05) = 2.4477`` (Ghilani 2010, Ch. 19; the same ellipse as
:func:`minegeo.survey.ellipse.error_ellipse` with ``confidence=0.95``), or the semi-axes and
azimuth a verb already computed (``adjust``: ``k`` from the F distribution when sigma0 is
estimated; ``mast``).

Results that are not ``ok`` get **no** entity: their names and status are listed in the custom
property ``MINEGEO_NOT_PLACED`` (File > Drawing Properties > Custom in AutoCAD), never at a
coordinate. Files are written atomically (temporary file + rename).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError, OptionalDependencyError
from minegeo.io.limits import MAX_TABLE_FILE_BYTES, read_file_text

log = logging.getLogger(__name__)

__all__ = ["DxfDrawing", "ezdxf_module", "write_localize_dxf", "write_control_dxf", "nice_exaggeration", "ellipse_from_covariance", "ellipse_vertices",
           "read_trajectory_enh", "LAYERS", "ELLIPSE_VERTICES", "CHI2_2D_95_K"]

#: layer keys -> suffix of the layer name (``<prefix>_<suffix>``) and AutoCAD colour index
LAYERS = {
    "scan_origins": ("SCAN_ORIGINS", 1),
    "trajectory": ("TRAJECTORY", 4),
    "stations": ("STATIONS", 1),
    "beacons": ("BEACONS", 3),
    "adjusted_points": ("ADJUSTED_POINTS", 1),
    "fixed_points": ("FIXED_POINTS", 5),
    "ellipse": ("ELLIPSE95", 2),
    "labels": ("LABELS", 7),
    "control_stations": ("CONTROL_STATIONS", 5),
    "check_stations": ("CHECK_STATIONS", 1),
    "residuals": ("RESIDUALS", 6),
}
#: vertices of an ellipse polyline (one every 5 degrees)
ELLIPSE_VERTICES = 72
#: scale from the standard to the 95 % ellipse with known variance: sqrt(chi2(2 dof, 0.95)) = sqrt(-2 ln 0.05)
CHI2_2D_95_K = math.sqrt(-2.0 * math.log(0.05))


def ezdxf_module():
    """The ``ezdxf`` module (:class:`~minegeo.errors.OptionalDependencyError` naming the ``dxf`` extra when missing)."""
    try:
        import ezdxf
    except ImportError:
        raise OptionalDependencyError("ezdxf", "dxf") from None
    ez_log = logging.getLogger("ezdxf")
    if ez_log.level == logging.NOTSET:  # ezdxf narrates its housekeeping at INFO ("creating ... dictionary")
        ez_log.setLevel(logging.WARNING)
    return ezdxf


def ellipse_from_covariance(cov_en, k: float = CHI2_2D_95_K) -> tuple[float, float, float]:
    """Semi-axes and azimuth of the error ellipse ``k``-scaled from a 2x2 (E, N) covariance.

    Parameters
    ----------
    cov_en : array_like (2, 2)
        Covariance of (Easting, Northing), m^2.
    k : float
        Scale from the standard ellipse (default: 95 % with known variance, 2.4477).

    Returns
    -------
    (a, b, azimuth_rad) : floats
        Semi-major and semi-minor axes (m) and the grid azimuth of the major axis, clockwise from
        north, in ``[0, pi)`` (Ghilani 2010, Ch. 19: ``tan 2t = 2 sEN / (sNN - sEE)``).
    """
    S = np.asarray(cov_en, dtype=np.float64)
    if S.shape != (2, 2) or not np.isfinite(S).all():
        raise InputError(f"ellipse covariance must be a finite 2x2 matrix, got {S.tolist()}")
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    lmin, lmax = max(float(w[0]), 0.0), max(float(w[1]), 0.0)
    e, n = V[0, 1], V[1, 1]  # major-axis direction (E, N)
    az = math.atan2(e, n) % math.pi if lmax > lmin else 0.0
    return k * math.sqrt(lmax), k * math.sqrt(lmin), az


def ellipse_vertices(center, a: float, b: float, azimuth_rad: float, n: int = ELLIPSE_VERTICES) -> np.ndarray:
    """``n`` vertices of an ellipse in the horizontal plane of ``center`` (E, N, H), first on the major axis.

    The major axis points along the grid azimuth ``azimuth_rad`` (clockwise from north): unit vector
    ``u = (sin az, cos az)``, minor axis ``v = (cos az, -sin az)``; vertex ``i`` is
    ``c + a cos(th) u + b sin(th) v`` with ``th = 2 pi i / n``.
    """
    c = np.asarray(center, dtype=np.float64).reshape(3)
    th = 2.0 * np.pi * np.arange(n) / n
    u = np.array([math.sin(azimuth_rad), math.cos(azimuth_rad)])
    v = np.array([math.cos(azimuth_rad), -math.sin(azimuth_rad)])
    out = np.empty((n, 3))
    out[:, :2] = c[:2] + np.outer(a * np.cos(th), u) + np.outer(b * np.sin(th), v)
    out[:, 2] = c[2]
    return out



@contextmanager
def _fixed_metadata(ezdxf):
    """ezdxf writes the clock time and random GUIDs into a drawing's header ($TDCREATE, $TDUPDATE,
    $VERSIONGUID, $FINGERPRINTGUID and its own marker); inside this context it writes fixed values
    (2000-01-01, constant GUIDs), so the same drawing gives the same bytes (the run's time is in
    result.json)."""
    old = ezdxf.options.write_fixed_meta_data_for_testing
    ezdxf.options.write_fixed_meta_data_for_testing = True
    try:
        yield
    finally:
        ezdxf.options.write_fixed_meta_data_for_testing = old


class DxfDrawing:
    """A DXF drawing on minegeo's named layers (see the module docstring).

    Parameters
    ----------
    layer_prefix : str
        Prefix of every layer name (default ``MINEGEO``).
    crs : str, optional
        The CRS of the coordinates, recorded as the custom property ``MINEGEO_CRS``.
    frame : str
        What the coordinates are (``"CRS EPSG:5186"``, ``"map frame (no CRS)"``), as ``MINEGEO_FRAME``.
    text_height_m : float
        Height of the labels (m).
    ellipse_layer : str
        Suffix of the ellipse layer (``ELLIPSE95``; ``ELLIPSE99`` for 99 % ellipses).
    """

    def __init__(self, *, layer_prefix: str = "MINEGEO", crs: str | None = None, frame: str = "CRS",
                 text_height_m: float = 0.5, ellipse_layer: str = "ELLIPSE95"):
        ezdxf = ezdxf_module()
        if not layer_prefix or any(ch in layer_prefix for ch in '<>/\\":;?*|=`'):
            raise InputError(f"layer prefix {layer_prefix!r} is not a valid DXF layer name")
        with _fixed_metadata(ezdxf):
            self.doc = ezdxf.new("R2010", setup=False)
        self.doc.units = ezdxf.units.M
        self.doc.header["$INSUNITS"] = 6  # metres
        self.doc.header["$MEASUREMENT"] = 1  # metric
        self.msp = self.doc.modelspace()
        self.prefix = str(layer_prefix)
        self.text_height = float(text_height_m)
        self.layer_names = {k: f"{self.prefix}_{suf}" for k, (suf, _) in LAYERS.items()}
        self.layer_names["ellipse"] = f"{self.prefix}_{ellipse_layer}"
        self.counts: dict[str, int] = {}
        self.props = {"MINEGEO_CRS": crs or "none", "MINEGEO_FRAME": frame, "MINEGEO_UNITS": "m (x = E, y = N, z = H)"}

    def _layer(self, key: str) -> str:
        name = self.layer_names[key]
        if name not in self.doc.layers:
            self.doc.layers.add(name, color=LAYERS[key][1])
        self.counts[name] = self.counts.get(name, 0) + 1
        return name

    @staticmethod
    def _xyz(p) -> tuple[float, float, float]:
        v = np.asarray(p, dtype=np.float64).reshape(-1)
        if v.shape[0] == 2:
            v = np.append(v, 0.0)
        if v.shape[0] != 3 or not np.isfinite(v).all():
            raise InputError(f"a DXF coordinate must be 2 or 3 finite numbers, got {v.tolist()}")
        return float(v[0]), float(v[1]), float(v[2])

    def label(self, text: str, at) -> None:
        """A TEXT entity ``text`` on the labels layer, inserted at ``at`` (E, N, H)."""
        t = self.msp.add_text(str(text), height=self.text_height, dxfattribs={"layer": self._layer("labels")})
        t.set_placement(self._xyz(at))

    def point(self, layer: str, at, label: str | None = None) -> None:
        """A POINT on ``layer`` (a key of :data:`LAYERS`), with an optional label."""
        self.msp.add_point(self._xyz(at), dxfattribs={"layer": self._layer(layer)})
        if label:
            self.label(label, at)

    def polyline3d(self, layer: str, points, *, closed: bool = False, label: str | None = None) -> None:
        """A 3-D POLYLINE through ``points`` ((m, 3) or (m, 2) -> z = 0) on ``layer``."""
        pts = [self._xyz(p) for p in np.asarray(points, dtype=np.float64)]
        if len(pts) < 2:
            raise InputError(f"a polyline needs at least 2 vertices, got {len(pts)}")
        self.msp.add_polyline3d(pts, close=closed, dxfattribs={"layer": self._layer(layer)})
        if label:
            self.label(label, pts[0])

    def ellipse(self, center, a: float, b: float, azimuth_rad: float) -> None:
        """A closed 72-vertex polyline of the ellipse (semi-axes ``a``, ``b`` m, major axis at ``azimuth_rad``)."""
        if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(azimuth_rad)) or a < 0 or b < 0:
            log.warning("ellipse at %s not drawn: semi-axes %s, %s", center, a, b)
            return
        self.polyline3d("ellipse", ellipse_vertices(self._xyz(center), a, b, azimuth_rad), closed=True)

    def property(self, name: str, value: str) -> None:
        """A custom drawing property (``$CUSTOMPROPERTY``; AutoCAD: Drawing Properties > Custom)."""
        self.props[str(name)] = str(value)

    def to_bytes(self) -> bytes:
        """The DXF file's bytes (UTF-8), with the custom properties in its header."""
        for k, v in self.props.items():
            self.doc.header.custom_vars.append(k, v)
        buf = io.StringIO()
        with _fixed_metadata(ezdxf_module()):
            self.doc.write(buf)
        self.doc.header.custom_vars.clear()
        return buf.getvalue().encode("utf-8")

    def save(self, path) -> dict:
        """Write the drawing atomically; return ``{"path", "layers": {name: entity count}, "properties"}``."""
        from minegeo._provenance import atomic_write_bytes

        p = atomic_write_bytes(path, self.to_bytes())
        return {"path": str(p), "layers": dict(sorted(self.counts.items())), "properties": dict(self.props)}


def read_trajectory_enh(path) -> tuple[np.ndarray, str]:
    """Positions from a ``trajectory_global.csv`` of ``minegeo localize``.

    Returns
    -------
    (positions (m, 3) float64, frame) : the ``E_m N_m H_m`` columns (``"crs"``) when present,
    else ``x_map_m y_map_m z_map_m`` (``"map"``).
    """
    text = read_file_text(path, max_bytes=MAX_TABLE_FILE_BYTES, what="trajectory CSV")
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise FileFormatError(path, "empty trajectory file")
    reader = csv.DictReader(rows)
    cols = reader.fieldnames or []
    want = ("E_m", "N_m", "H_m") if all(c in cols for c in ("E_m", "N_m", "H_m")) else ("x_map_m", "y_map_m", "z_map_m")
    if not all(c in cols for c in want):
        raise FileFormatError(path, f"no E_m,N_m,H_m or x_map_m,y_map_m,z_map_m columns (header: {','.join(cols)})")
    try:
        P = np.array([[float(r[c]) for c in want] for r in reader], dtype=np.float64).reshape(-1, 3)
    except (TypeError, ValueError):
        raise FileFormatError(path, "a trajectory position is not a number") from None
    if not np.isfinite(P).all():
        raise FileFormatError(path, "a trajectory position is not finite")
    return P, ("crs" if want[0] == "E_m" else "map")


def _result_name(r: dict, i: int) -> str:
    """The label of a result: its ``name``, else the stem of its scan file (``inputs`` = [map, scan, ...])."""
    if r.get("name"):
        return str(r["name"])
    ins = r.get("inputs") or []
    if len(ins) >= 2 and isinstance(ins[1], dict) and ins[1].get("path"):
        return Path(str(ins[1]["path"])).name.split(".")[0]
    return f"result {i + 1}"


def _load_result(item, i: int) -> dict:
    if isinstance(item, dict):
        return item
    p = Path(item)
    f = p / "result.json" if p.is_dir() else p
    try:
        d = json.loads(read_file_text(f, max_bytes=MAX_TABLE_FILE_BYTES, what="result.json"))
    except json.JSONDecodeError as exc:
        raise FileFormatError(f, f"not a minegeo result.json ({exc})") from None
    if not isinstance(d, dict):
        raise FileFormatError(f, "not a minegeo result.json (no JSON object)")
    d.setdefault("result_dir", str(f.parent))
    return d


def _placed(r: dict) -> tuple[np.ndarray, np.ndarray | None, str]:
    """(scan origin (3,), position covariance in the drawing's axes (3, 3) or None, frame) of an ok result."""
    T_map = np.asarray(r["T_map_scan"], dtype=np.float64) if r.get("T_map_scan") is not None else None
    T_crs = np.asarray(r["T_crs_scan"], dtype=np.float64) if r.get("T_crs_scan") is not None else None
    T = T_crs if T_crs is not None else T_map
    if T is None or T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError("an ok localize result without a finite T_crs_scan / T_map_scan")
    C = r.get("position_cov_3x3")
    cov = None
    if C is not None:
        C = np.asarray(C, dtype=np.float64)  # map axes
        if C.shape == (3, 3) and np.isfinite(C).all():
            # R_crs_map = R_crs_scan R_map_scan^T: the covariance rotated into the CRS axes (the
            # georeferencing scale, within 1e-3 of 1 for a mine map, is not applied)
            R = T[:3, :3] @ T_map[:3, :3].T if (T_crs is not None and T_map is not None) else np.eye(3)
            cov = R @ C @ R.T
    return T[:3, 3].copy(), cov, ("crs" if T_crs is not None else "map")


def write_localize_dxf(path, results: list, *, layer_prefix: str = "MINEGEO", trajectories: dict | None = None,
                       text_height_m: float = 0.5) -> dict:
    """Draw ``minegeo localize`` results into a DXF for mine-planning CAD.

    Parameters
    ----------
    path : str or Path
        The ``.dxf`` to write (atomically).
    results : list of dict (or paths)
        Parsed ``result.json`` of ``minegeo localize`` (a path to one, or to its folder, is read).
        Each may carry ``name`` (the label; default: the scan file's stem) and ``result_dir``
        (the folder whose ``trajectory_global.csv`` is drawn). Only ``status == "ok"`` results
        are drawn; the others are listed in the custom property ``MINEGEO_NOT_PLACED``.
    layer_prefix : str
        Layer-name prefix (``MINEGEO_SCAN_ORIGINS``, ``..._TRAJECTORY``, ``..._ELLIPSE95``, ``..._LABELS``).
    trajectories : dict, optional
        ``{name: (m, 3) positions}`` in the drawing's coordinates, used instead of the CSV.
    text_height_m : float
        Label height (m).

    Returns
    -------
    dict
        ``path``, ``layers`` (entity count per layer), ``placed`` (names), ``not_placed``
        ([{name, status}]), ``frame`` (``"crs"``, ``"map"`` or ``"mixed"``), ``crs``.

    Raises
    ------
    OptionalDependencyError
        ezdxf is not installed (``pip install 'minegeo[dxf]'``).
    """
    items = [_load_result(r, i) for i, r in enumerate(results)]
    crs = next((r.get("crs") for r in items if r.get("status") == "ok" and r.get("T_crs_scan") is not None), None)
    placed = [(i, r) for i, r in enumerate(items) if r.get("status") == "ok"]
    frames = {_placed(r)[2] for _, r in placed}
    frame = frames.pop() if len(frames) == 1 else ("mixed" if frames else "crs")
    desc = {"crs": f"CRS {crs}" if crs else "CRS", "map": "map frame of the prior map (no CRS)",
            "mixed": "MIXED: CRS for results with T_crs_scan, map frame for the others"}[frame]
    dwg = DxfDrawing(layer_prefix=layer_prefix, crs=crs, frame=desc, text_height_m=text_height_m)
    names, not_placed = [], []
    for i, r in enumerate(items):
        name = _result_name(r, i)
        if r.get("status") != "ok":
            not_placed.append({"name": name, "status": str(r.get("status"))})
            continue
        origin, cov, fr = _placed(r)
        dwg.point("scan_origins", origin, label=name)
        if cov is not None:
            dwg.ellipse(origin, *ellipse_from_covariance(cov[:2, :2]))
        traj = None
        if trajectories and name in trajectories:
            traj = np.asarray(trajectories[name], dtype=np.float64).reshape(-1, 3)
        elif r.get("result_dir") and r.get("trajectory_csv"):
            f = Path(r["result_dir"]) / str(r["trajectory_csv"])
            if f.is_file():
                traj, tfr = read_trajectory_enh(f)
                if tfr != fr:
                    log.warning("%s: trajectory in the %s frame, scan origin in the %s frame; not drawn", f, tfr, fr)
                    traj = None
        if traj is not None and len(traj) >= 2:
            dwg.polyline3d("trajectory", traj)
        names.append(name)
    if not_placed:
        dwg.property("MINEGEO_NOT_PLACED", "; ".join(f"{n['name']} ({n['status']}: no position)" for n in not_placed))
    out = dwg.save(path)
    out.update(placed=names, not_placed=not_placed, frame=frame, crs=crs)
    return out


def nice_exaggeration(extent_m: float, largest_m: float, fraction: float = 0.05) -> float:
    """The exaggeration of residual vectors: the largest of 1, 2, 5 x 10^k (k >= 0) with
    ``x · largest_m ≤ fraction · extent_m`` (so the longest vector is at most ``fraction`` of the
    drawing's extent), at least 1."""
    if not (largest_m > 0.0 and extent_m > 0.0 and math.isfinite(largest_m) and math.isfinite(extent_m)):
        return 1.0
    target = fraction * extent_m / largest_m
    if target <= 1.0:
        return 1.0
    k = math.floor(math.log10(target))
    best = 1.0
    for e in (k - 1, k):
        for m in (1.0, 2.0, 5.0):
            x = m * 10.0**e
            if best < x <= target * (1.0 + 1e-12):
                best = x
    return best


def write_control_dxf(path, *, ids, is_control, surveyed_enh, estimated_enh, cov_enh=None, trajectory_enh=None,
                      crs: str | None = None, exaggeration: float | None = None, flagged=(),
                      layer_prefix: str = "MINEGEO", text_height_m: float = 0.5) -> dict:
    """Draw control and check stations of ``minegeo slam --control`` into a DXF, in the CRS.

    Entities (coordinates E, N, H in metres, float64):

    * a POINT at the surveyed ``E N H`` of every station, control stations on
      ``<prefix>_CONTROL_STATIONS``, check stations on ``<prefix>_CHECK_STATIONS``, and its id as TEXT
      (``<prefix>_LABELS``; a control station flagged by its w-test is labelled ``"<id> (flagged)"``);
    * the residual vector of every station on ``<prefix>_RESIDUALS``: a 2-vertex 3-D polyline from the
      surveyed point ``s`` to ``s + x (e − s)``, ``e`` the estimated point, ``x`` the exaggeration;
    * the 95 % horizontal error ellipse of every station whose covariance is given, centred at the
      surveyed point at its height, semi-axes ``x k √λ`` (λ the eigenvalues of the E N block of
      ``cov_enh``, ``k = √χ²(2, 0.95) = 2.4477``, :func:`ellipse_from_covariance`), on
      ``<prefix>_ELLIPSE95``: with the same exaggeration as the vectors, a residual whose tip lies
      outside its ellipse is outside the 95 % region;
    * the trajectory as one 3-D polyline on ``<prefix>_TRAJECTORY``.

    The exaggeration and what is drawn are stated in the custom properties
    ``MINEGEO_EXAGGERATION``, ``MINEGEO_ELLIPSES`` and ``MINEGEO_FLAGGED``, and in a TEXT at the first
    station.

    Parameters
    ----------
    path : str or Path
        The ``.dxf`` written (atomically).
    ids : sequence of str
    is_control : (n,) bool
    surveyed_enh, estimated_enh : (n, 3)
        Surveyed and estimated points in the CRS (m).
    cov_enh : (n, 3, 3), optional
        Covariance of the estimated points (m²); rows that are not finite get no ellipse.
    trajectory_enh : (m, 3), optional
    crs : str, optional
    exaggeration : float, optional
        Default :func:`nice_exaggeration` of the drawing's horizontal extent and the longest
        horizontal residual (the longest vector at most 5 % of the extent).
    flagged : sequence of str
        Ids of the control stations flagged by their w-test.

    Returns
    -------
    dict
        ``path``, ``layers`` (entity count per layer name), ``properties``, ``exaggeration``,
        ``ellipses`` (number drawn).
    """
    ids = [str(i) for i in ids]
    ctrl = np.asarray(is_control, dtype=bool).reshape(-1)
    s = np.asarray(surveyed_enh, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(estimated_enh, dtype=np.float64).reshape(-1, 3)
    n = len(ids)
    if ctrl.shape != (n,) or s.shape != (n, 3) or e.shape != (n, 3):
        raise InputError(f"write_control_dxf: {n} ids but is_control {ctrl.shape}, surveyed {s.shape}, "
                         f"estimated {e.shape}")
    traj = None if trajectory_enh is None else np.asarray(trajectory_enh, dtype=np.float64).reshape(-1, 3)
    d = e - s
    pts = s[:, :2] if traj is None else np.r_[s[:, :2], traj[:, :2]]
    extent = float(np.ptp(pts, axis=0).max()) if pts.shape[0] else 0.0
    largest = float(np.hypot(d[:, 0], d[:, 1]).max()) if n else 0.0
    x = float(exaggeration) if exaggeration is not None else nice_exaggeration(max(extent, 1.0), largest)
    if not (math.isfinite(x) and x > 0):
        raise InputError(f"exaggeration must be a positive number, got {exaggeration!r}")
    flagged = {str(f) for f in flagged}
    dwg = DxfDrawing(layer_prefix=layer_prefix, crs=crs, frame=f"CRS {crs}" if crs else "CRS",
                     text_height_m=text_height_m)
    n_ell = 0
    for i in range(n):
        name = ids[i] + (" (flagged)" if ids[i] in flagged else "")
        dwg.point("control_stations" if ctrl[i] else "check_stations", s[i], label=name)
        dwg.polyline3d("residuals", np.stack([s[i], s[i] + x * d[i]]))
        if cov_enh is not None:
            C = np.asarray(cov_enh[i], dtype=np.float64)
            if C.shape == (3, 3) and np.isfinite(C).all():
                a, b, az = ellipse_from_covariance(C[:2, :2])
                dwg.ellipse(s[i], x * a, x * b, az)
                n_ell += 1
    if traj is not None and traj.shape[0] >= 2:
        dwg.polyline3d("trajectory", traj)
    what = (f"residual vectors (surveyed -> estimated) and 95 % ellipses of the estimated points (k = "
            f"{CHI2_2D_95_K:.4f}) exaggerated x{x:g}")
    dwg.property("MINEGEO_EXAGGERATION", f"{x:g}")
    dwg.property("MINEGEO_ELLIPSES", f"{n_ell} of {n} stations (95 %, E N, exaggerated x{x:g}, centred at the "
                 "surveyed point)" if n_ell else "none (no covariances: rigid mode)")
    dwg.property("MINEGEO_FLAGGED", ", ".join(sorted(flagged)) or "none")
    if n:
        dwg.label(what, s[0] + [0.0, -3.0 * dwg.text_height, 0.0])
    out = dwg.save(path)
    out.update(exaggeration=x, ellipses=n_ell)
    return out
