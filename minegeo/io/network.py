"""Reading a survey-network file: Krumm/Gama text or JSON, chosen by the file suffix.

The formats are in :mod:`minegeo.io.network_krumm` and :mod:`minegeo.io.network_json`, the
records they return in :mod:`minegeo.io.network_types`; :func:`minegeo.survey.adjust_network`
adjusts them.
"""

from __future__ import annotations

from pathlib import Path

from minegeo.io.jsonio import load_json_text
from minegeo.io.limits import MAX_TABLE_FILE_BYTES, read_file_bytes
from minegeo.io.network_json import network_from_dict
from minegeo.io.network_krumm import parse_krumm
from minegeo.io.network_types import Network

__all__ = ["read_network"]


def read_network(path) -> Network:
    """Read a network file: ``.json`` (see :func:`network_from_dict`) or Krumm text (anything else).

    Parameters
    ----------
    path : str or Path
        The file; at most :data:`~minegeo.io.limits.MAX_TABLE_FILE_BYTES` bytes.

    Returns
    -------
    Network

    Raises
    ------
    FileFormatError
        Unreadable or malformed file.
    """
    p = Path(path)
    data = read_file_bytes(p, max_bytes=MAX_TABLE_FILE_BYTES, what="survey network file")
    if p.suffix.lower() == ".json":
        # depth, duplicate keys (a point given twice), NaN/Infinity: all refused with the path
        d = load_json_text(data, p)
        return network_from_dict(d, str(p))
    try:
        text = data.decode("utf-8-sig")  # tolerate a byte-order mark
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return parse_krumm(text, str(p))
