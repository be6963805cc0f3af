"""``minegeo adjust`` on hostile or damaged network files keeps the CLI contract (issue 14).

The JSON network goes through :func:`minegeo.io.jsonio.load_json_text`: nesting deeper than
``MAX_JSON_DEPTH`` (thousands deep used to end in a RecursionError traceback), duplicate keys
(a point typed twice used to keep its last value silently), ``NaN``/``Infinity``/``1e400``
and mistyped members are each one line on stderr and exit status 2; the input is unchanged.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
from pathlib import Path

import pytest

from minegeo.cli import main
from minegeo.errors import FileFormatError
from minegeo.io.jsonio import MAX_JSON_DEPTH
from minegeo.io.network import read_network

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

NET = {
    "points": {"A": {"x": 0.0, "y": 0.0}, "B": {"x": 100.0, "y": 0.0}, "C": {"x": 50.0, "y": 80.0}},
    "datum": {"type": "fix", "coordinates": ["A", "B"]},
    "observations": [
        {"type": "distance", "from": "A", "to": "C", "value_m": 94.34, "sigma_m": 0.01},
        {"type": "distance", "from": "B", "to": "C", "value_m": 94.34, "sigma_m": 0.01},
        {"type": "angle", "at": "C", "from": "A", "to": "B", "value_deg": 296.0, "sigma_arcsec": 5},
    ],
}
GOOD = json.dumps(NET, indent=1)


def _edit(fn):
    d = copy.deepcopy(NET)
    fn(d)
    return json.dumps(d)


CASES = {
    # nesting
    "deep-100000": ("[" * 100_000 + "]" * 100_000, "nested 100000 levels"),
    "deep-in-object": ('{"points": ' + "[" * 5000 + "]" * 5000 + ', "observations": []}', "nested"),
    "deep-just-over": ('{"points": {}, "observations": ' + "[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH + "}",
                       f"more than the {MAX_JSON_DEPTH}"),
    "deep-inside-string-is-fine-but-dup": ('{"name": "' + "[" * 5000 + '", "name": 1}', "duplicate key 'name'"),
    # duplicate keys
    "duplicate-point": (GOOD.replace('"B": {', '"A": {"x": 5, "y": 5}, "B": {', 1), "duplicate key 'A'"),
    "duplicate-member": (GOOD.replace('"value_m": 94.34,', '"value_m": 94.34, "value_m": 95.0,', 1),
                         "duplicate key 'value_m'"),
    # non-finite numbers
    "nan": (GOOD.replace("94.34", "NaN", 1), "NaN"),
    "infinity": (GOOD.replace("94.34", "Infinity", 1), "Infinity"),
    "minus-infinity": (GOOD.replace("0.01", "-Infinity", 1), "-Infinity"),
    "overflow-1e400": (GOOD.replace("94.34", "1e400", 1), "too large"),
    "huge-integer": (GOOD.replace("100.0", "1" * 400, 1), "too large"),
    "huge-coordinate": (GOOD.replace("100.0", "1e300", 1), "within"),
    # invalid JSON and mistyped members
    "not-json": ('{"points": {"A": ', "invalid JSON"),
    "not-utf8": (b'{"name": "\xff\xfe"}', "UTF-8"),
    "top-level-list": ("[1, 2, 3]", "needs 'points' and 'observations'"),
    "points-is-list": (_edit(lambda d: d.update(points=[1, 2])), "'points' must be a JSON object"),
    "point-is-number": (_edit(lambda d: d["points"].update(A=3)), "point 'A' must be a JSON object"),
    "coordinate-is-text": (_edit(lambda d: d["points"]["A"].update(x="east")), "point 'A' x must be a number"),
    "observation-is-list": (_edit(lambda d: d["observations"].append([1])), "observation 3 must be a JSON object"),
    "missing-to": (_edit(lambda d: d["observations"][0].pop("to")), "observation 0: missing 'to'"),
    "missing-value": (_edit(lambda d: d["observations"][1].pop("value_m")), "observation 1: missing 'value_m'"),
    "value-is-object": (_edit(lambda d: d["observations"][0].update(value_m={})), "value_m must be a number"),
    "angle-is-list": (_edit(lambda d: d["observations"][2].update(value_deg=[64])), "value_deg must be a number"),
    "angle-nan-text": (_edit(lambda d: d["observations"][2].update(value_deg="nan")), "not a finite angle"),
    "baseline-cov-shape": (
        _edit(lambda d: d["observations"].append({"type": "baseline", "from": "A", "to": "C", "value_m": [50, 80, 0],
                                                  "cov_m2": [[1, 0], [0, 1]]})),
        "3x3 matrix",
    ),
    "datum-coordinates-not-list": (_edit(lambda d: d["datum"].update(coordinates="AB")), "must be a JSON list"),
    "dimension-7": (_edit(lambda d: d.update(dimension=7)), "'dimension' must be 1, 2 or 3"),
    "sigma-1e-300": (_edit(lambda d: d["observations"][0].update(sigma_m=1e-300)), "below 1e-09"),
}


def sha256(p) -> str:
    return hashlib.sha256(Path(p).read_bytes()).hexdigest()


@pytest.mark.parametrize("case", list(CASES))
def test_adjust_refuses_with_one_line(case, tmp_path, capsys, caplog):
    text, match = CASES[case]
    p = tmp_path / "net.json"
    p.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    before = sha256(p)
    capsys.readouterr()
    try:
        with caplog.at_level(logging.WARNING):
            code = main(["adjust", str(p), "--out", str(tmp_path / "out")])
    except Exception as exc:  # noqa: BLE001 - a traceback is what the contract forbids
        pytest.fail(f"uncaught {type(exc).__name__}: {exc}")
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert "Traceback" not in err and "Warning" not in err
    assert len(lines) == 1, lines
    assert lines[0].startswith("minegeo adjust: error: "), lines[0]
    assert "net.json" in lines[0]
    assert match in lines[0], lines[0]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert sha256(p) == before
    assert not (tmp_path / "out" / "result.json").exists()


def test_valid_json_network_still_adjusts(tmp_path, capsys):
    """Positive control (and a byte-order mark is still accepted)."""
    p = tmp_path / "net.json"
    p.write_bytes(b"\xef\xbb\xbf" + GOOD.encode("utf-8"))
    assert main(["adjust", str(p), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "result.json").exists()


def test_network_file_size_is_bounded(tmp_path, monkeypatch):
    import minegeo.io.network as network

    p = tmp_path / "net.json"
    p.write_text(GOOD, encoding="utf-8")
    monkeypatch.setattr(network, "MAX_TABLE_FILE_BYTES", 100)
    with pytest.raises(FileFormatError, match="larger than"):
        read_network(p)


@pytest.mark.parametrize(
    "text, match",
    [
        ("[Coordinates]\nA 0 0\nB nan 0\n[Datum]\nfix A\n[Distances]\nA B 1 0.01\n", "line 3"),
        ("[Coordinates]\nA 0 0\nB 1 0\n[Datum]\nfix A\n[Angles]\nA B A inf 0.001\n", "line 7"),
        ("[Coordinates]\nA 0 0\nB 1 0\n[Datum]\nfix A\n[Distances]\nA B -5 0.01\n", "must not be negative"),
        ("[Coordinates]\nA 0\nB 1\n[Datum]\nfix A\n[LevelledHeightDifferences]\nA B 1 -3 0.001\n", "negative"),
    ],
    ids=["nan-coordinate", "inf-angle", "negative-distance", "negative-levelling-length"],
)
def test_krumm_text_bad_numbers_name_the_line(text, match, tmp_path, capsys):
    p = tmp_path / "net.dat"
    p.write_text(text, encoding="utf-8")
    capsys.readouterr()
    assert main(["adjust", str(p), "--out", str(tmp_path / "out")]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("minegeo adjust: error: ") and match in lines[0], lines
