"""``--dxf`` of ``localize``, ``mast`` and ``adjust``: the drawing for mine-planning CAD and its record.

Each verb builds its drawing with :mod:`minegeo.io.dxf` inside its result folder's staging copy and
records the file in ``result.json`` under ``"dxf"``: ``file`` (name in the result folder),
``sha256``, ``size_bytes``, ``layers`` (entity count per layer), ``frame`` and ``crs``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["require_dxf", "dxf_record", "write_localize_result_dxf"]


def require_dxf() -> None:
    """Raise :class:`~minegeo.errors.OptionalDependencyError` now (before any work) when ezdxf is missing."""
    from minegeo.io.dxf import ezdxf_module

    ezdxf_module()


def dxf_record(path: Path, summary: dict) -> dict:
    """The ``result.json`` record of a written DXF (``summary`` from :meth:`DxfDrawing.save`)."""
    from minegeo._provenance import sha256_file

    p = Path(path)
    rec = {"file": p.name, "sha256": sha256_file(p), "size_bytes": p.stat().st_size,
           "layers": summary.get("layers", {}), "units": "m", "axes": "x = Easting, y = Northing, z = height"}
    for k in ("frame", "crs", "placed", "not_placed"):
        if k in summary:
            rec[k] = summary[k]
    if "frame" not in rec:
        rec["frame"] = summary.get("properties", {}).get("MINEGEO_FRAME")
    return rec


def write_localize_result_dxf(stage: Path, d: dict, name: str = "placement.dxf") -> dict:
    """Write ``stage/name`` for one ``localize`` result record ``d`` (its trajectory CSV is in ``stage``)."""
    from minegeo.io.dxf import write_localize_dxf

    summary = write_localize_dxf(stage / name, [{**d, "result_dir": str(stage)}])
    return dxf_record(stage / name, summary)
