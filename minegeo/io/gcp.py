"""Ground control point (GCP) files: CSV with local and CRS coordinates of the same marks.

Layout written by :func:`write_gcps` (and the canonical input)::

    # crs: EPSG:5186
    id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m
    GCP1,12.431,3.902,-1.250,201345.112,551203.447,87.402,0.005,0.005,0.010

* ``x y z``: the mark in the local (map/scan) frame, metres.
* ``E N H``: easting, northing, height in the CRS named by the ``# crs:`` line, metres.
* ``sigma_E_m sigma_N_m sigma_H_m``: a-priori standard deviations of ``E N H`` (m).
* optional ``sigma_x_m sigma_y_m sigma_z_m``: standard deviations of the local coordinates.

Reading is tolerant: header names are case-insensitive; ``easting northing height``
(or ``elevation``) are accepted for ``E N H``; ``sigma_E``/``sd_E`` for ``sigma_E_m``;
separators ``,`` ``;`` tab or spaces; ``#`` comment lines; UTF-8 (a byte-order mark is
skipped; other encodings are refused rather than turned into wrong ids). When the sigma columns are
missing every CRS coordinate gets ``default_sigma_m`` (**0.01 m** unless given) and a
warning is logged. Errors name the file, the line and the problem. Files larger than
:data:`~minegeo.io.limits.MAX_TABLE_FILE_BYTES`, coordinates beyond
:data:`~minegeo.io.limits.MAX_ABS_COORDINATE` and sigmas below
:data:`~minegeo.io.limits.MIN_SIGMA_M` are refused.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.errors import FileFormatError, InputError
from minegeo.io._table import check_sigma, new_id, number, read_table, table_writer
from minegeo.io.limits import MAX_ABS_COORDINATE, MAX_TABLE_FILE_BYTES, read_file_text
from minegeo.io.types import ControlPoints

log = logging.getLogger(__name__)

__all__ = ["read_gcps", "write_gcps", "is_gcp_header", "DEFAULT_GCP_SIGMA_M"]

#: a-priori sigma (m) of CRS coordinates when a GCP file has no sigma columns
DEFAULT_GCP_SIGMA_M = 0.01

_ALIASES = {
    "id": "id", "name": "id", "point": "id", "point_id": "id",
    "x": "x", "y": "y", "z": "z",
    "e": "E", "easting": "E", "n": "N", "northing": "N", "h": "H", "height": "H", "elevation": "H",
}  # fmt: skip
for _c in ("E", "N", "H", "x", "y", "z"):
    for _form in ("sigma_{}_m", "sigma_{}", "sd_{}", "s_{}", "std_{}", "std_{}_m"):
        _ALIASES[_form.format(_c.lower())] = f"sigma_{_c}_m"
_REQUIRED = ("id", "x", "y", "z", "E", "N", "H")


def is_gcp_header(names) -> bool:
    """True when the header names (any case, aliases such as ``easting``) hold every column of a GCP file."""
    return set(_REQUIRED) <= {_ALIASES.get(n.strip().lower(), n.strip()) for n in names}


def read_gcps(path, default_sigma_m: float = DEFAULT_GCP_SIGMA_M, crs: str | None = None) -> ControlPoints:
    """Read a GCP file into :class:`~minegeo.io.types.ControlPoints` (see the module docstring).

    Parameters
    ----------
    path : str or Path
    default_sigma_m : float
        Sigma (m) of E, N, H when the file has no sigma columns (default 0.01 m).
    crs : str, optional
        CRS to use when the file has no ``# crs:`` line (a conflicting line is an error).

    Raises
    ------
    FileFormatError
        Empty file, missing columns, wrong number of fields, non-numeric/NaN values,
        non-positive sigma or duplicate ids -- naming the file and the line.
    """
    p = Path(path)
    # strict UTF-8: a point id with a byte of another encoding would silently become "GCP?03"
    text = read_file_text(p, encoding="utf-8-sig", max_bytes=MAX_TABLE_FILE_BYTES, what="control-point file")
    def check_header(lineno: int, names: list[str], canon: list[str]) -> None:
        missing = [c for c in _REQUIRED if c not in canon]
        if missing:
            raise FileFormatError(
                p,
                f"line {lineno}: header lacks column(s) {', '.join(missing)} "
                f"(found: {', '.join(names)}; expected id,x,y,z,E,N,H[,sigma_E_m,sigma_N_m,sigma_H_m])",
            )
        if len(set(canon)) != len(canon):
            raise FileFormatError(p, f"line {lineno}: repeated column names in header {','.join(names)!r}")

    table = read_table(p, text, lambda n: _ALIASES.get(n.strip().lower(), n.strip()), check_header)
    if table is None:
        raise FileFormatError(p, "empty file (no header, no control points)")
    header = table.columns
    file_crs = table.crs
    numeric = [c for c in header if c != "id" and (c in _REQUIRED or c.startswith("sigma_"))]
    ids: list[str] = []
    rows: list[list[float]] = []
    row_lines: list[int] = []
    for lineno, rec in table.rows:
        vals = []
        for c in numeric:
            v = number(p, lineno, c, rec[c], MAX_ABS_COORDINATE, ": not a survey coordinate")
            if c.startswith("sigma_"):
                check_sigma(p, lineno, c, rec[c], v)
            vals.append(v)
        ids.append(new_id(p, lineno, rec["id"], ids, row_lines))
        rows.append(vals)
        row_lines.append(lineno)
    if not ids:
        raise FileFormatError(p, "no control points after the header")
    values = np.array(rows, dtype=np.float64)
    col = {c: values[:, j] for j, c in enumerate(numeric)}
    sig_names = ("sigma_E_m", "sigma_N_m", "sigma_H_m")
    present = [c in col for c in sig_names]
    if any(present) and not all(present):
        raise FileFormatError(p, "give all three of sigma_E_m, sigma_N_m, sigma_H_m or none")
    if all(present):
        sigma = np.column_stack([col[c] for c in sig_names])
    else:
        if not (math.isfinite(default_sigma_m) and default_sigma_m > 0):
            raise InputError(f"default_sigma_m must be > 0, got {default_sigma_m!r}")
        log.warning("%s: no sigma columns; using %.4g m for E, N and H of every control point", p, default_sigma_m)
        sigma = np.full((len(ids), 3), float(default_sigma_m))
    loc_names = ("sigma_x_m", "sigma_y_m", "sigma_z_m")
    sig_local = np.column_stack([col[c] for c in loc_names]) if all(c in col for c in loc_names) else None
    if crs is not None and file_crs is not None and crs != file_crs:
        raise FileFormatError(p, f"file says crs {file_crs!r} but crs={crs!r} was given")
    return ControlPoints(
        ids=ids,
        local_xyz=np.column_stack([col["x"], col["y"], col["z"]]),
        crs_enh=np.column_stack([col["E"], col["N"], col["H"]]),
        sigma_enh_m=sigma,
        sigma_local_m=sig_local,
        crs=file_crs or crs,
    )


def write_gcps(path, gcps: ControlPoints) -> Path:
    """Write control points as CSV, atomically.

    Parameters
    ----------
    path : str or Path
        Output file (the layout in the module docstring).
    gcps : ControlPoints
        Written with a ``# crs:`` line (if ``gcps.crs``), the header
        ``id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m`` (+ ``sigma_x_m,sigma_y_m,sigma_z_m``
        when local sigmas are known) and numbers in Python's shortest exact ``repr``, so
        :func:`read_gcps` gives back identical float64 values. Ids containing the separator
        are quoted (CSV rules).

    Returns
    -------
    Path
        The written file.
    """
    if not isinstance(gcps, ControlPoints):
        raise InputError(f"gcps must be ControlPoints, got {type(gcps).__name__}")
    buf, w = table_writer(gcps.crs)
    head = ["id", "x", "y", "z", "E", "N", "H", "sigma_E_m", "sigma_N_m", "sigma_H_m"]
    if gcps.sigma_local_m is not None:
        head += ["sigma_x_m", "sigma_y_m", "sigma_z_m"]
    w.writerow(head)
    for i, gid in enumerate(gcps.ids):
        vals = list(gcps.local_xyz[i]) + list(gcps.crs_enh[i]) + list(gcps.sigma_enh_m[i])
        if gcps.sigma_local_m is not None:
            vals += list(gcps.sigma_local_m[i])
        w.writerow([gid] + [repr(float(v)) for v in vals])
    return atomic_write_text(path, buf.getvalue())
