"""Cross-cutting contracts of every ``minegeo`` verb (README "Every CLI run ..." and cli.py).

1. A user mistake (missing file, directory instead of file, empty or truncated file, NaN rows,
   unknown EPSG code, collinear control, too few observations) gives exit status 2 and exactly
   one line on stderr, ``minegeo <verb>: error: ...``, never a traceback.
2. Inputs are never modified (SHA-256 and mtime unchanged).
3. Outputs are written atomically (no ``*.tmp`` left), ``result.json`` parses and records the
   package versions, the seed (where the verb has one) and the SHA-256 of the real input files.
4. ``--version`` / ``--help`` / ``<verb> --help`` exit 0.

Runs in-process through :func:`minegeo.cli.main` (one Python, one Numba compilation) on one
small synthetic mine and one MAST scenario made once for the module.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from minegeo.cli import VERBS, main

SEED = 7


@pytest.fixture(scope="module")
def mine(tmp_path_factory):
    from minegeo.synth import write_world

    d = tmp_path_factory.mktemp("mine")
    write_world(d, "small", SEED)
    return d


@pytest.fixture(scope="module")
def mast_scene(tmp_path_factory):
    from minegeo.mast.scenario import write_mast_scenario

    d = tmp_path_factory.mktemp("mast")
    return write_mast_scenario(d, seed=SEED)


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    """Ghilani (2010) Ex. 15.5 resection (angles in gon), written by hand (no shared data needed)."""
    d = tmp_path_factory.mktemp("net")
    p = d / "ghilani15_5.dat"
    p.write_text(
        "[Coordinates]\nP 1303.599 1458.615\nQ 1636.436 1310.468\nR 1503.395 888.362\n"
        "S 1506.262 785.061\nU 1000.030 999.960\n[Datum]\nfix xP yP xQ yQ xR yR xS yS\n"
        "[Angles]\nU P Q 33.8805555555556 0.00154320987654321\n"
        "U Q R 42.7873456790123 0.00185185185185185\nU R S 11.6657407407407 0.00185185185185185\n",
        encoding="utf-8",
    )
    return p


def run_cli(argv, capsys):
    capsys.readouterr()
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_user_error(verb, argv, capsys, expect=None):
    """Exit 2, one stderr line ``minegeo <verb>: error: ...``, no traceback."""
    try:
        code, _, err = run_cli([verb, *argv], capsys)
    except SystemExit as exc:  # an option refused by its argparse type (cli/_argtypes.py): the same one line
        code, err = exc.code, capsys.readouterr().err
    except Exception as exc:  # noqa: BLE001 - a traceback is exactly what the contract forbids
        pytest.fail(f"{verb} {argv}: uncaught {type(exc).__name__}: {exc}")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert "Traceback" not in err
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"minegeo {verb}: error:"), lines[0]
    if expect is not None:
        assert expect.lower() in lines[0].lower(), lines[0]
    return lines[0]


def snapshot(paths):
    return {str(p): (hashlib.sha256(Path(p).read_bytes()).hexdigest(), os.stat(p).st_mtime_ns) for p in paths}


def no_tmp_left(*dirs):
    left = [p for d in dirs for p in Path(d).rglob("*") if p.name.endswith(".tmp")]
    assert not left, left


def check_provenance(prov, input_paths, seed="absent"):
    assert {"minegeo", "numpy", "python"} <= set(prov["versions"])
    if seed != "absent":
        assert prov["seed"] == seed
    recorded = {Path(r["path"]).resolve(): r["sha256"] for r in prov["inputs"]}
    for p in input_paths:
        assert recorded[Path(p).resolve()] == hashlib.sha256(Path(p).read_bytes()).hexdigest(), p


# ---------------------------------------------------------------- bad input files


def _bad_files(tmp: Path, mine: Path) -> dict[str, Path]:
    empty = tmp / "empty.ply"
    empty.write_bytes(b"")
    raw = (mine / "scans" / "scan_04.ply").read_bytes()
    trunc = tmp / "truncated.ply"
    trunc.write_bytes(raw[: len(raw) // 2])
    nan_xyz = tmp / "nan.xyz"
    nan_xyz.write_text("0 0 0\n1 0 0\nnan 1 0\n0 1 1\n", encoding="utf-8")
    lines = (mine / "gcps.csv").read_text(encoding="utf-8").splitlines()
    fields = lines[3].split(",")
    fields[4] = "nan"
    nan_gcp = tmp / "nan_gcps.csv"
    nan_gcp.write_text("\n".join(lines[:3] + [",".join(fields)] + lines[4:]) + "\n", encoding="utf-8")
    return {"empty": empty, "truncated": trunc, "nan_xyz": nan_xyz, "nan_gcp": nan_gcp,
            "missing": tmp / "does_not_exist.ply", "dir": tmp}


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "truncated", "nan_xyz"])
def test_info_user_errors(case, mine, tmp_path, capsys):
    f = _bad_files(tmp_path, mine)[case]
    assert_user_error("info", [f], capsys)


def test_info_gcp_nan_row(mine, tmp_path, capsys):
    f = _bad_files(tmp_path, mine)["nan_gcp"]
    assert_user_error("info", [f, "--kind", "gcp"], capsys)


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "truncated", "nan_xyz"])
def test_georef_bad_map(case, mine, tmp_path, capsys):
    f = _bad_files(tmp_path, mine)[case]
    before = snapshot([mine / "gcps.csv"])
    assert_user_error("georef", ["--map", f, "--gcps", mine / "gcps.csv", "--out", tmp_path / "o" / "geo.ply",
                                 "--report", tmp_path / "o"], capsys)
    assert snapshot([mine / "gcps.csv"]) == before
    assert not (tmp_path / "o" / "geo.ply").exists()


def _gcp_variant(mine: Path, tmp: Path, name: str, edit) -> Path:
    lines = (mine / "gcps.csv").read_text(encoding="utf-8").splitlines()
    p = tmp / name
    p.write_text("\n".join(edit(lines)) + "\n", encoding="utf-8")
    return p


def _collinear(lines):
    """Keep the header; put every GCP on one straight line in both frames."""
    out = lines[:2]
    for i in range(6):
        x = 10.0 * i
        out.append(f"C{i},{x},{2 * x},{0.5 * x},{200000 + x},{600000 + 2 * x},{100 + 0.5 * x},0.005,0.005,0.005")
    return out


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "nan", "collinear", "two_points", "epsg", "epsg_in_file",
                                  "crs_mismatch"])
def test_georef_bad_gcps(case, mine, tmp_path, capsys):
    makers = {
        "missing": lambda: tmp_path / "nope.csv",
        "dir": lambda: tmp_path,
        "empty": lambda: _gcp_variant(mine, tmp_path, "e.csv", lambda ls: []),
        "nan": lambda: _bad_files(tmp_path, mine)["nan_gcp"],
        "collinear": lambda: _gcp_variant(mine, tmp_path, "c.csv", _collinear),
        "two_points": lambda: _gcp_variant(mine, tmp_path, "t.csv", lambda ls: ls[:4]),
        "epsg": lambda: _gcp_variant(mine, tmp_path, "n.csv", lambda ls: [ln for ln in ls if not ln.startswith("# crs")]),
        "epsg_in_file": lambda: _gcp_variant(mine, tmp_path, "b.csv",
                                             lambda ls: [ln.replace("EPSG:5186", "EPSG:999999") for ln in ls]),
        "crs_mismatch": lambda: mine / "gcps.csv",
    }
    gcps = makers[case]()
    extra = ["--crs", "EPSG:999999"] if case in ("epsg", "crs_mismatch") else []
    expect = {"epsg": "unknown coordinate reference system", "epsg_in_file": "unknown coordinate reference system",
              "crs_mismatch": "EPSG:5186", "collinear": None}.get(case)
    before = snapshot([mine / "map.ply"])
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", gcps, "--out", tmp_path / "o" / "geo.ply",
                                 "--report", tmp_path / "o", *extra], capsys, expect=expect)
    assert snapshot([mine / "map.ply"]) == before
    assert not (tmp_path / "o" / "geo.ply").exists()


def _scan_variant(scene, tmp: Path, edit) -> Path:
    lines = Path(scene["scan"]).read_text(encoding="utf-8").splitlines()
    p = tmp / "scan_bad.csv"
    p.write_text("\n".join(edit(lines)) + "\n", encoding="utf-8")
    return p


def _nan_bearing_row(lines):
    """A NaN *bearing* is a damaged file (a NaN *range* is a documented "no return" row)."""
    i = next(k for k, ln in enumerate(lines) if ln.startswith("bearing_deg")) + 5
    return lines[:i] + ["nan,5.0"] + lines[i:]


def _header_only(lines):
    return [ln for ln in lines if ln.startswith(("#", "bearing_deg"))]


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "nan", "header_only"])
def test_mast_bad_scan(case, mast_scene, tmp_path, capsys):
    if case == "missing":
        scan = tmp_path / "nope.csv"
    elif case == "dir":
        scan = tmp_path
    else:
        edit = {"empty": lambda ls: [], "nan": _nan_bearing_row, "header_only": _header_only}[case]
        scan = _scan_variant(mast_scene, tmp_path, edit)
    before = snapshot([mast_scene["beacons"]])
    assert_user_error("mast", ["--scan", scan, "--beacons", mast_scene["beacons"], "--out", tmp_path / "o"], capsys)
    assert snapshot([mast_scene["beacons"]]) == before


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "nan"])
def test_mast_bad_beacons(case, mast_scene, tmp_path, capsys):
    lines = Path(mast_scene["beacons"]).read_text(encoding="utf-8").splitlines()
    p = tmp_path / "b.csv"
    if case == "empty":
        p.write_text("", encoding="utf-8")
    elif case == "nan":
        f = lines[2].split(",")
        f[2] = "nan"
        p.write_text("\n".join(lines[:2] + [",".join(f)] + lines[3:]) + "\n", encoding="utf-8")
    beacons = {"missing": tmp_path / "nope.csv", "dir": tmp_path, "empty": p, "nan": p}[case]
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", beacons, "--out", tmp_path / "o"], capsys)


def test_mast_beacon_out_of_view_is_documented_failed_status(tmp_path, capsys):
    """docs/mast.md: exit 1 = ``failed`` status, reason printed and written to result.json."""
    from minegeo.mast.scenario import write_mast_scenario

    scene = write_mast_scenario(tmp_path / "in", seed=SEED, visible_beacons=("B2",))
    out = tmp_path / "o"
    code, _, err = run_cli(["mast", "--scan", scene["scan"], "--beacons", scene["beacons"], "--out", out], capsys)
    assert code == 1 and "Traceback" not in err
    d = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert d["status"] == "failed"
    assert "B1" in d["reason"] and "out of view" in d["reason"]
    no_tmp_left(out)


@pytest.mark.parametrize("case", ["missing", "dir", "empty", "too_few", "nan", "collinear", "garbage"])
def test_adjust_user_errors(case, tmp_path, capsys):
    texts = {
        "empty": "",
        "too_few": "[Coordinates]\nA 0 0\nB 100 0\nU 50 50\n[Datum]\nfix A B\n[Distances]\nA U 70.7 0.01\n",
        "nan": "[Coordinates]\nA 0 0\nB 100 0\nU 50 50\n[Datum]\nfix A B\n[Distances]\n"
               "A U nan 0.01\nB U 70.7 0.01\nA B 100 0.01\n",
        "collinear": "[Coordinates]\nA 0 0\nB 100 100\nU 200 200\n[Datum]\nfix A B\n[GridBearings,dms,s]\n"
                     "A U 45°00'00\" 1\nB U 45°00'00\" 1\n",
        "garbage": "\x00\x01\x02 not a network\n",
    }
    if case == "missing":
        net = tmp_path / "nope.dat"
    elif case == "dir":
        net = tmp_path
    else:
        net = tmp_path / f"{case}.dat"
        net.write_text(texts[case], encoding="utf-8")
    assert_user_error("adjust", [net, "--out", tmp_path / "o"], capsys)


def test_adjust_truncated_json(tmp_path, capsys):
    net = tmp_path / "net.json"
    net.write_text('{"points": {"A": {"x": 0, "y": 0}', encoding="utf-8")
    assert_user_error("adjust", [net, "--out", tmp_path / "o"], capsys)


def test_synth_bad_seed(tmp_path, capsys):
    assert_user_error("synth", [tmp_path / "out", "--seed", "-1"], capsys, expect="seed")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["--gcps", "2"], ["--crs", "EPSG:999999"]])
def test_synth_bad_options_fail_before_work(argv, tmp_path, capsys):
    assert_user_error("synth", [tmp_path / "out", *argv], capsys)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_synth_outdir_not_empty(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("x", encoding="utf-8")
    assert_user_error("synth", [tmp_path], capsys, expect="not empty")
    assert (tmp_path / "keep.txt").read_text(encoding="utf-8") == "x"


def test_synth_outdir_is_a_file(tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("x", encoding="utf-8")
    try:
        assert_user_error("synth", [f], capsys, expect="not a directory")
    finally:
        assert f.read_text(encoding="utf-8") == "x"


def test_demo_refuses_nonempty_out(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("mine", encoding="utf-8")
    assert_user_error("demo", ["--out", tmp_path], capsys, expect="not empty")
    assert (tmp_path / "keep.txt").read_text(encoding="utf-8") == "mine"


def test_out_naming_an_existing_file(mine, mast_scene, network, tmp_path, capsys):
    """``--out`` that is a file (or a path through a file) is a user mistake, not a crash."""
    f = tmp_path / "afile"
    f.write_text("keep", encoding="utf-8")
    assert_user_error("mast", ["--scan", mast_scene["scan"], "--beacons", mast_scene["beacons"], "--out", f], capsys)
    assert_user_error("adjust", [network, "--out", f], capsys)
    assert_user_error("adjust", [network, "--out", f / "sub"], capsys)
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", mine / "gcps.csv", "--out", tmp_path / "g.ply",
                                 "--report", f], capsys)
    assert f.read_text(encoding="utf-8") == "keep"


@pytest.mark.parametrize("target", ["gcps", "sidecar_of_map", "report_over_gcps"])
def test_georef_never_overwrites_its_inputs(target, mine, tmp_path, capsys):
    """Any output path that resolves to an input (map or GCP file) is refused before anything is written."""
    gcps = tmp_path / "gcps.csv"
    gcps.write_bytes((mine / "gcps.csv").read_bytes())
    argv = {"gcps": ["--out", gcps, "--report", tmp_path / "rep"],
            "sidecar_of_map": ["--out", tmp_path / "geo.ply", "--report", tmp_path / "rep"],
            "report_over_gcps": ["--out", tmp_path / "geo.ply", "--report", tmp_path]}[target]
    if target == "sidecar_of_map":
        gcps = gcps.rename(tmp_path / "geo.ply.georef.json")
    if target == "report_over_gcps":
        gcps = gcps.rename(tmp_path / "result.json")
    before = snapshot([gcps, mine / "map.ply"])
    # the report folder is replaced as a whole, so a GCP file inside it is refused as such
    expect = "lies inside --report" if target == "report_over_gcps" else "is the input"
    assert_user_error("georef", ["--map", mine / "map.ply", "--gcps", gcps, "--crs", "EPSG:5186", *argv], capsys,
                      expect=expect)
    assert snapshot([gcps, mine / "map.ply"]) == before


@pytest.mark.parametrize("case", ["missing", "dir", "truncated", "nan_xyz", "empty"])
def test_localize_bad_scan(case, mine, tmp_path, capsys):
    f = _bad_files(tmp_path, mine)[case]
    before = snapshot([mine / "map.ply"])
    assert_user_error("localize", ["--map", mine / "map.ply", "--scan", f, "--out", tmp_path / "o", "--no-cache"],
                      capsys)
    assert snapshot([mine / "map.ply"]) == before


@pytest.mark.parametrize("case", ["missing", "dir", "truncated", "nan_xyz", "empty"])
def test_localize_and_prepare_map_bad_map(case, mine, tmp_path, capsys):
    f = _bad_files(tmp_path, mine)[case]
    scan = mine / "scans" / "scan_04.ply"
    assert_user_error("localize", ["--map", f, "--scan", scan, "--out", tmp_path / "o", "--no-cache"], capsys)
    assert_user_error("prepare-map", ["--map", f, "--out", tmp_path / "p.npz"], capsys)
    assert not (tmp_path / "p.npz").exists()


def test_localize_bad_trajectory_and_options(mine, tmp_path, capsys):
    scan, traj = mine / "scans" / "scan_04.ply", tmp_path / "t.tum"
    traj.write_text("0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n", encoding="utf-8")
    base = ["--map", mine / "map.ply", "--scan", scan, "--out", tmp_path / "o", "--no-cache"]
    assert_user_error("localize", [*base, "--trajectory", traj], capsys)
    assert_user_error("localize", [*base, "--voxel", "-1"], capsys)
    assert_user_error("prepare-map", ["--map", mine / "map.ply", "--out", tmp_path / "p.ply"], capsys)


def test_map_is_the_current_directory(tmp_path, monkeypatch, capsys):
    """``--map .`` used to raise ValueError in georef.sidecar_path (Path('.').with_name)."""
    monkeypatch.chdir(tmp_path)
    assert_user_error("localize", ["--map", ".", "--scan", tmp_path / "s.ply", "--out", tmp_path / "o"], capsys)
    assert_user_error("prepare-map", ["--map", ".", "--out", tmp_path / "p.npz"], capsys)


# ---------------------------------------------------------------- successful runs


def test_info_success_contract(mine, tmp_path, capsys):
    inp = [mine / "map.ply"]
    before = snapshot(inp)
    code, out, _ = run_cli(["info", mine / "map.ply", "--json", tmp_path / "info.json"], capsys)
    assert code == 0 and "points" in out
    assert snapshot(inp) == before
    no_tmp_left(tmp_path)
    d = json.loads((tmp_path / "info.json").read_text(encoding="utf-8"))
    check_provenance(d["provenance"], inp)


def test_georef_success_contract(mine, tmp_path, capsys):
    inp = [mine / "map.ply", mine / "gcps.csv"]
    before = snapshot(inp)
    rep = tmp_path / "rep"
    code, out, err = run_cli(["georef", "--map", inp[0], "--gcps", inp[1], "--out", tmp_path / "geo" / "map_geo.ply",
                              "--report", rep], capsys)
    assert code == 0, err
    assert snapshot(inp) == before
    no_tmp_left(tmp_path)
    d = json.loads((rep / "result.json").read_text(encoding="utf-8"))
    assert d["status"].lower() == "ok"
    check_provenance(d["provenance"], inp)
    assert (tmp_path / "geo" / "map_geo.ply").stat().st_size > 0
    assert (rep / "report.html").exists()
    # refusing to overwrite the input map is a user error, and the map stays intact
    assert_user_error("georef", ["--map", inp[0], "--gcps", inp[1], "--out", inp[0], "--report", rep], capsys)
    assert snapshot(inp) == before


def test_mast_success_contract(mast_scene, tmp_path, capsys):
    inp = [mast_scene["scan"], mast_scene["beacons"]]
    before = snapshot(inp)
    code, out, err = run_cli(["mast", "--scan", inp[0], "--beacons", inp[1], "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    assert snapshot(inp) == before
    no_tmp_left(tmp_path)
    d = json.loads((tmp_path / "o" / "result.json").read_text(encoding="utf-8"))
    assert d["status"] == "ok"
    check_provenance(d["provenance"], inp)
    umask = os.umask(0o022)
    os.umask(umask)
    for p in (tmp_path / "o").iterdir():  # atomic writes must not leave mkstemp's 0600 mode
        assert p.stat().st_mode & 0o777 == 0o666 & ~umask, p
    truth = json.loads(Path(mast_scene["truth"]).read_text(encoding="utf-8"))
    assert abs(d["x"] - truth["x_m"]) < 0.01 and abs(d["y"] - truth["y_m"]) < 0.01


def test_adjust_success_contract(network, tmp_path, capsys):
    before = snapshot([network])
    code, out, err = run_cli(["adjust", network, "--out", tmp_path / "o"], capsys)
    assert code == 0, err
    assert snapshot([network]) == before
    no_tmp_left(tmp_path)
    d = json.loads((tmp_path / "o" / "result.json").read_text(encoding="utf-8"))
    check_provenance(d["provenance"], [network])
    # Ghilani (2010) Ex. 15.5: U = (999.999, 1000.025) ft-ish units, as tests/survey check to 0.1 mm
    assert f"{d['points']['U']['x']:.3f}" == "999.999" and f"{d['points']['U']['y']:.3f}" == "1000.025"


def test_localize_success_contract(mine, tmp_path, capsys):
    """Map and scan unchanged (the documented prepared-map cache may appear beside the map), result.json
    records the seed, versions and the SHA-256 of both inputs; exit 0 ok, 1 ambiguous/failed."""
    inp = [mine / "map.ply", mine / "scans" / "scan_02.ply"]
    before = snapshot(inp)
    code, _, err = run_cli(["localize", "--map", inp[0], "--scan", inp[1], "--out", tmp_path / "o", "--seed", "3"],
                           capsys)
    assert code in (0, 1) and "Traceback" not in err
    assert snapshot(inp) == before
    no_tmp_left(tmp_path, mine)
    d = json.loads((tmp_path / "o" / "result.json").read_text(encoding="utf-8"))
    assert (code == 0) == (d["status"] == "ok")
    check_provenance({"versions": d["versions"], "inputs": d["inputs"], "seed": d["seed"]}, inp, seed=3)


def test_synth_success_contract(mine):
    """The module's mine was written by ``write_world``: truth.json records seed, versions, hashes."""
    no_tmp_left(mine)
    t = json.loads((mine / "truth.json").read_text(encoding="utf-8"))
    assert t["seed"] == SEED and {"minegeo", "numpy"} <= set(t["versions"])
    for rel, h in t["files_sha256"].items():
        assert hashlib.sha256((mine / rel).read_bytes()).hexdigest() == h, rel


# ---------------------------------------------------------------- help / version


def test_version_and_help_subprocess():
    for argv in (["--version"], ["--help"]):
        r = subprocess.run([sys.executable, "-m", "minegeo", *argv], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert "minegeo" in r.stdout
    assert "0." in subprocess.run([sys.executable, "-m", "minegeo", "--version"], capture_output=True,
                                  text=True, timeout=120).stdout


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_verb_help_exits_0(verb, capsys):
    with pytest.raises(SystemExit) as exc:
        main([verb, "--help"])
    assert exc.value.code == 0
    assert "usage: minegeo" in capsys.readouterr().out


def test_no_verb_prints_help_and_exits_0(capsys):
    assert main([]) == 0
    assert "VERB" in capsys.readouterr().out
