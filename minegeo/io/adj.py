"""Published answers of the Krumm network examples: ``.adj`` files of adjusted coordinates.

Used to compare :func:`minegeo.survey.adjust_network` with the published results (tests,
benchmarks); nothing in the adjustment reads them.
"""

from __future__ import annotations

from minegeo.io.limits import MAX_TABLE_FILE_BYTES, read_file_text

__all__ = ["read_adj"]


def read_adj(path) -> dict[str, dict[str, float]]:
    """Read a Krumm ``.adj`` file of published adjusted coordinates.

    Returns ``{id: {...}}`` with, for 2D lines (8 tokens) ``x, dx_cm, sx_cm, y, dy_cm, sy_cm,
    sp_cm``; for 3D lines (11 tokens) additionally ``z, dz_cm, sz_cm``; for 1D lines (4 tokens)
    ``h, dh_mm, sh_mm``. Comment lines (``#``) and XML are skipped.
    """
    text = read_file_text(path, encoding="utf-8", max_bytes=MAX_TABLE_FILE_BYTES, what="Krumm .adj file")
    out = {}
    for raw in text.splitlines():
        line = raw.strip().replace("−", "-")
        if not line or line.startswith("#") or line.startswith("<"):
            continue
        tok = line.split()
        try:
            vals = [float(t) for t in tok[1:]]
        except ValueError:
            continue
        if len(vals) == 7:
            out[tok[0]] = dict(
                zip(("x", "dx_cm", "sx_cm", "y", "dy_cm", "sy_cm", "sp_cm"), vals, strict=True)
            )
        elif len(vals) == 10:
            out[tok[0]] = dict(
                zip(
                    ("x", "dx_cm", "sx_cm", "y", "dy_cm", "sy_cm", "z", "dz_cm", "sz_cm", "sp_cm"),
                    vals,
                    strict=True,
                )
            )
        elif len(vals) == 3:
            out[tok[0]] = dict(zip(("h", "dh_mm", "sh_mm"), vals, strict=True))
    return out
