"""End-to-end determinism through the CLI: same inputs + seed => same outputs.

* ``synth`` twice with the same seed: every file byte-identical.
* ``mast``, ``georef``, ``adjust`` and ``localize`` twice on the same inputs: ``result.json``
  identical once the wall-clock keys are removed (recursively): :data:`WALL_CLOCK_KEYS`
  (``timings_s``, ``created_utc``) and :data:`WALL_CLOCK_PATHS` (``map_preparation.seconds`` of
  ``localize``). The other output files (georeferenced map, CSV, text report; the sidecar JSON
  without those keys) are byte-identical too.

Each run happens in its own working directory with the same *relative* output path, so recorded
output paths are equal; inputs are given by the same absolute paths.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from minegeo.cli import main

#: Keys removed before comparing, anywhere in the tree: stage timings (``timings_s``, e.g. also
#: ``details.timings_s`` in MAST) and the creation time (``provenance.created_utc``). Together with
#: :data:`WALL_CLOCK_PATHS` nothing else may differ between two runs.
WALL_CLOCK_KEYS = frozenset({"timings_s", "created_utc"})
#: Wall-clock fields under other names, removed by exact path: ``localize``'s map preparation time.
WALL_CLOCK_PATHS = frozenset({("map_preparation", "seconds")})


def strip_wall_clock(obj, path=()):
    if isinstance(obj, dict):
        return {k: strip_wall_clock(v, (*path, k)) for k, v in obj.items()
                if k not in WALL_CLOCK_KEYS and (*path, k) not in WALL_CLOCK_PATHS}
    if isinstance(obj, list):
        return [strip_wall_clock(v, path) for v in obj]
    return obj


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def run_twice(tmp_path, monkeypatch, argv, ok_codes=(0,)):
    """Run ``minegeo -q <argv>`` in two fresh working directories; return both."""
    dirs, codes = [], []
    for k in (1, 2):
        d = tmp_path / f"run{k}"
        d.mkdir()
        monkeypatch.chdir(d)
        codes.append(main(["-q", *[str(a) for a in argv]]))
        dirs.append(d)
    assert codes[0] == codes[1] and codes[0] in ok_codes
    return dirs


def assert_same_results(a: Path, b: Path, json_names=("result.json",)):
    ta, tb = tree_bytes(a), tree_bytes(b)
    assert sorted(ta) == sorted(tb)
    for name in ta:
        if name.endswith(".json"):
            ja, jb = json.loads(ta[name]), json.loads(tb[name])
            assert strip_wall_clock(ja) == strip_wall_clock(jb), name
        elif name.endswith((".ply", ".csv", ".txt")):
            assert ta[name] == tb[name], name
    for n in json_names:
        assert n in ta
    return ta


@pytest.fixture(scope="module")
def mine(tmp_path_factory):
    from minegeo.synth import write_world

    d = tmp_path_factory.mktemp("mine")
    write_world(d, "small", 11)
    return d


@pytest.mark.slow
def test_synth_twice_byte_identical(mine, tmp_path):
    """A second ``synth`` with the same seed reproduces the module's mine byte for byte."""
    from minegeo.report.synth_report import plot_synth_png, synth_report_html

    assert main(["-q", "synth", str(tmp_path / "again"), "--seed", "11"]) == 0
    a, b = tree_bytes(mine), tree_bytes(tmp_path / "again")
    report = b.pop("report.html")  # the CLI adds its report to what ``write_world`` writes
    record = json.loads(b.pop("result.json"))  # and its run record (its time: never byte-identical)
    assert record["record"] == "truth.json" and record["provenance"]["arguments"]["seed"] == 11
    assert sorted(a) == sorted(b)
    different = [name for name in a if a[name] != b[name]]
    assert not different
    assert "map.ply" in a and "truth.json" in a and "gcps.csv" in a
    # the report depends only on the folder's files: rebuilt from the module's mine, byte for byte
    truth = json.loads(a["truth.json"])
    assert synth_report_html(mine, truth, plot_synth_png(mine, truth)).encode("utf-8") == report


def test_georef_twice_identical(mine, tmp_path, monkeypatch):
    r1, r2 = run_twice(tmp_path, monkeypatch, ["georef", "--map", mine / "map.ply", "--gcps", mine / "gcps.csv",
                                               "--out", "o/map_geo.ply", "--report", "o"])
    files = assert_same_results(r1 / "o", r2 / "o")
    assert files["map_geo.ply"] == tree_bytes(r2 / "o")["map_geo.ply"]


def test_mast_twice_identical(tmp_path, monkeypatch):
    from minegeo.mast.scenario import write_mast_scenario

    scene = write_mast_scenario(tmp_path / "scene", seed=11, position=2)
    r1, r2 = run_twice(tmp_path, monkeypatch, ["mast", "--scan", scene["scan"].resolve(),
                                               "--beacons", scene["beacons"].resolve(), "--out", "o"])
    assert_same_results(r1 / "o", r2 / "o")
    d = json.loads((r1 / "o" / "result.json").read_text(encoding="utf-8"))
    assert d["status"] == "ok" and "timings_s" in d and "created_utc" in d["provenance"]


def test_adjust_twice_identical(tmp_path, monkeypatch):
    net = tmp_path / "resection.dat"
    net.write_text(
        "[Coordinates]\nP 1303.599 1458.615\nQ 1636.436 1310.468\nR 1503.395 888.362\n"
        "S 1506.262 785.061\nU 1000.030 999.960\n[Datum]\nfix xP yP xQ yQ xR yR xS yS\n"
        "[Angles]\nU P Q 33.8805555555556 0.00154320987654321\n"
        "U Q R 42.7873456790123 0.00185185185185185\nU R S 11.6657407407407 0.00185185185185185\n"
        "[Distances]\nU P 550.02 0.02\n",
        encoding="utf-8",
    )
    r1, r2 = run_twice(tmp_path, monkeypatch, ["adjust", net, "--out", "o"])
    assert_same_results(r1 / "o", r2 / "o")
    for name in ("report.txt",):
        assert (r1 / "o" / name).read_bytes() == (r2 / "o" / name).read_bytes()


def test_localize_twice_identical(mine, tmp_path, monkeypatch):
    """Same map, scan and ``--seed``: the same pose, scores and status (exit 0 ok, 1 ambiguous/failed).

    ``--no-cache`` so that neither run reads a prepared map the other wrote (the cache record in
    ``map_preparation`` would legitimately differ)."""
    r1, r2 = run_twice(tmp_path, monkeypatch, ["localize", "--map", mine / "map.ply", "--scan",
                                               mine / "scans" / "scan_02.ply", "--out", "o", "--seed", "5",
                                               "--no-cache"], ok_codes=(0, 1))
    assert_same_results(r1 / "o", r2 / "o")
    d = json.loads((r1 / "o" / "result.json").read_text(encoding="utf-8"))
    assert d["seed"] == 5 and d["status"] in ("ok", "ambiguous", "failed")
