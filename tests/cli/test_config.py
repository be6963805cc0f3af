"""``--config FILE`` and ``--dump-config`` on every verb (minegeo/cli/_config.py, docs/config.md).

The reference for every parsed value is ``argparse`` itself: the namespace the verb's parser gives
for a command line without ``--config`` (independent of the file reader and writer under test).
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from badinput._contract import assert_user_error
from helpers import shared_data
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

from minegeo.cli import VERBS, build_parser, main
from minegeo.cli._config import OWN_DESTS, _subcommands, parse_with_config, verb_actions

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11 (3.10 reads JSON configs only)


def _parse(argv: list[str]):
    verb = argv[0]
    parser = build_parser([verb])
    return parse_with_config(parser, argv, verb)


def _required_argv(command: list[str]) -> list[str]:
    """The command's required options and positionals, each given the dummy value ``x`` (or its first choice)."""
    argv = []
    parser = build_parser([command[0]])._verb_parsers[command[0]]
    if len(command) > 1:
        parser = _subcommands(parser).choices[command[1]]
    for a in verb_actions(parser):
        v = str(next(iter(a.choices))) if a.choices else "x"
        if not a.option_strings:
            argv.append(v)
        elif a.required:
            argv += [a.option_strings[-1], v]
    return argv


def _ns(args) -> dict:
    return {k: v for k, v in vars(args).items() if k not in OWN_DESTS}


def _commands() -> list[list[str]]:
    """Every verb, and every subcommand of a verb that has them (``intersections build``)."""
    out = []
    for verb in sorted(VERBS):
        subs = _subcommands(build_parser([verb])._verb_parsers[verb])
        out += [[verb, c] for c in subs.choices] if subs is not None else [[verb]]
    return out


@pytest.mark.parametrize("fmt", ["toml", "json"])
@pytest.mark.parametrize("command", _commands(), ids=" ".join)
def test_dump_config_read_back_gives_the_same_options(command, fmt, tmp_path, capsys):
    """Every verb: --dump-config (no required option needed) read back with --config gives the
    namespace of the defaults, and TOML read back gives the same table as the JSON dump."""
    assert main([*command, "--dump-config", fmt]) == 0
    text = capsys.readouterr().out
    doc = tomllib.loads(text) if fmt == "toml" else json.loads(text)
    f = tmp_path / f"c.{fmt}"
    f.write_text(text)
    req = _required_argv(command)
    plain, _ = _parse([*command, *req])
    from_file, _ = _parse([*command, *req, "--config", str(f)])
    assert _ns(from_file) == _ns(plain)
    set_keys = {k for k, v in json.loads(_dump(command, "json")).items() if v is not None}
    assert {k for k, v in doc.items() if v is not None} == set_keys  # unset (None) options are commented out in TOML, null in JSON


def _dump(command, fmt, extra=()):
    _, text = _parse([*command, *extra, "--dump-config", fmt])
    return text


_text = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12)
_pos = st.floats(min_value=1e-12, max_value=1e12, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
          phases=(Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink))  # no "explain": minutes on a failure
@given(voxel=_pos, angle=st.floats(min_value=0.0, max_value=180.0), seed=st.integers(0, 10**9),
       offset=st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=3, max_size=3),
       pattern=_text, out=_text, no_planes=st.booleans(), control_mode=st.sampled_from([None, "rigid", "graph"]))
def test_dumped_values_read_back_exactly(tmp_path_factory, voxel, angle, seed, offset, pattern, out, no_planes,
                                         control_mode):
    """Arbitrary floats (shortest repr), strings (quotes, backslashes, control characters, any
    Unicode), integers, lists and flags written by the TOML emitter parse back to the same values."""
    assume(angle > 0.0)
    # argparse reads "-1e+16" as an option name (only "-1" / "-1.5" look like negative numbers to it)
    offset_text = [repr(x) if x >= 0 or re.fullmatch(r"-\d+\.\d+", repr(x)) else f"{x:.20f}" for x in offset]
    argv = ["slam", f"--frames={pattern}", f"--out={out}", f"--voxel={voxel!r}", f"--keyframe-angle={angle!r}",
            f"--seed={seed}", f"--pattern={pattern}", "--station-offset", *offset_text]
    argv += ["--no-planes"] if no_planes else []
    argv += [f"--control-mode={control_mode}"] if control_mode else []
    direct, _ = _parse(argv)
    f = tmp_path_factory.mktemp("cfg") / "c.toml"
    f.write_text(_dump(argv[:1], "toml", argv[1:]), encoding="utf-8")
    back, _ = _parse(["slam", "--config", str(f)])
    assert _ns(back) == _ns(direct)
    assert all(math.copysign(1, a) == math.copysign(1, b)
               for a, b in zip(back.station_offset, direct.station_offset, strict=True))


def test_command_line_overrides_the_file_and_required_options_come_from_it(tmp_path):
    f = tmp_path / "slam.toml"
    f.write_text('frames = "fr"\nout = "o"\nvoxel = 0.5\nmax_distance = 2\nno-planes = true\n')
    args, _ = _parse(["slam", "--config", str(f), "--voxel", "0.7"])
    assert (args.frames, args.out, args.voxel, args.max_distance, args.no_planes) == ("fr", "o", 0.7, 2.0, True)
    # a repeatable option given on the command line replaces the file's list
    w = tmp_path / "w.json"
    w.write_text('{"module": ["minegeo.slam", "minegeo.mast"]}')
    assert _parse(["warmup", "--config", str(w)])[0].module == ["minegeo.slam", "minegeo.mast"]
    assert _parse(["warmup", "--config", str(w), "--module", "minegeo.io"])[0].module == ["minegeo.io"]
    # one of a mutually exclusive pair on the command line wins over the other in the file
    loc = tmp_path / "loc.toml"
    loc.write_text("voxel = 0.5\n")
    args, _ = _parse(["prepare-map", "--map", "m", "--out", "o", "--config", str(loc), "--octree-level", "6"])
    assert (args.voxel, args.octree_level) == (None, 6)


_BAD = {  # file text -> what the one error line must say
    "voxl = 0.3\n": "unknown key 'voxl'",
    'voxel = "0.3"\n': "key 'voxel' must be a number",
    "voxel = -1.0\n": "key 'voxel': OdometryParams.voxel_size_m must be a finite number > 0, got -1.0",
    "voxel = true\n": "key 'voxel' takes one value",
    "seed = 1.5\n": "key 'seed'",
    "no-planes = 1\n": "key 'no-planes' is a flag",
    "station-offset = [1.0, 2.0]\n": "key 'station-offset' takes exactly 3 values",
    "control-mode = \"both\"\n": "key 'control-mode': invalid choice",
    "pattern = 3\n": "key 'pattern' must be a string",
    "voxel = 0.3\nvoxel-size = 1\n": "unknown key 'voxel-size'",
    "voxel = 0.3\nmax_distance = 1.0\nmax-distance = 2.0\n": "are the same option",
    "voxel = [1\n": "not valid TOML",
}


@pytest.mark.parametrize("text", list(_BAD))
def test_a_bad_config_is_one_error_line_naming_key_and_file_before_any_work(text, tmp_path, capsys):
    frames, out = tmp_path / "frames", tmp_path / "out"
    frames.mkdir()
    f = tmp_path / "bad.toml"
    f.write_text(text)
    line = assert_user_error("slam", ["--frames", str(frames), "--out", str(out), "--config", str(f)], capsys,
                             inputs=[frames, f], outputs=[out], expect=_BAD[text])
    assert "bad.toml" in line


def test_a_result_json_of_another_verb_or_without_options_is_refused(tmp_path, capsys):
    f = tmp_path / "result.json"
    f.write_text(json.dumps({"command": "posegraph", "provenance": {"arguments": {"graph": "g"}}}))
    assert_user_error("slam", ["--config", str(f)], capsys, inputs=[f], expect="not of `minegeo slam`")
    f.write_text(json.dumps({"tool": "minegeo adjust", "provenance": {"arguments": {"network": "n"}}}))
    assert_user_error("slam", ["--config", str(f)], capsys, inputs=[f], expect="result of `minegeo adjust`")
    f.write_text(json.dumps({"command": "slam", "provenance": {"seed": 0}}))
    assert_user_error("slam", ["--config", str(f)], capsys, inputs=[f], expect="records no options")


@pytest.mark.parametrize("option", ["--conf", "--dump"])
def test_abbreviated_config_options_are_refused(option, tmp_path, capsys):
    """argparse accepts abbreviations; the file (or the dump) must not be silently skipped by one."""
    f = tmp_path / "c.toml"
    f.write_text("voxel = 0.5\n")
    argv = ["--frames", "f", "--out", str(tmp_path / "o"), option] + ([str(f)] if option == "--conf" else [])
    assert_user_error("slam", argv, capsys, inputs=[f], outputs=[tmp_path / "o"], expect="in full")


def test_toml_without_tomllib_says_to_use_json(tmp_path, capsys, monkeypatch):
    """Python 3.10 (no tomllib): a TOML file is refused with one line; a JSON file works."""
    monkeypatch.setitem(sys.modules, "tomllib", None)  # `import tomllib` raises ImportError
    f = tmp_path / "c.toml"
    f.write_text("voxel = 0.5\n")
    assert_user_error("slam", ["--frames", "f", "--out", str(tmp_path / "o"), "--config", str(f)], capsys,
                      inputs=[f], outputs=[tmp_path / "o"], expect="reading TOML needs Python 3.11")
    j = tmp_path / "c.json"
    j.write_text('{"voxel": 0.5, "frames": "f", "out": "o"}')
    assert _parse(["slam", "--config", str(j)])[0].voxel == 0.5


# ------------------------------------------------------------------ repeating a run from its result.json


def _same_result(a: Path, b: Path, outputs: dict) -> None:
    """Two result.json equal but for timings, creation time and the output folders given."""
    def drop(d):
        if isinstance(d, dict):
            return {k: drop(v) for k, v in d.items() if "timing" not in k and k != "created_utc"}
        return [drop(v) for v in d] if isinstance(d, list) else d

    def norm(p):
        text = p.read_text()
        for old, new in outputs.items():
            text = text.replace(str(old), "OUT").replace(str(new), "OUT")
        return drop(json.loads(text))
    assert norm(a) == norm(b)


def test_posegraph_repeated_from_its_result_json(tmp_path, capsys):
    g = shared_data("pose_graph_g2o", "tinyGrid3D.g2o")
    o1, o2 = tmp_path / "a" / "o.g2o", tmp_path / "b" / "o.g2o"
    main(["posegraph", str(g), "--out", str(o1), "--robust", "huber", "--robust-scale", "0.5",
          "--max-iterations", "7"])
    rec = o1.with_name("o.g2o.report") / "result.json"
    main(["posegraph", "--config", str(rec), "--out", str(o2)])
    assert o1.read_bytes() == o2.read_bytes()
    _same_result(rec, o2.with_name("o.g2o.report") / "result.json", {tmp_path / "a": tmp_path / "b"})


def test_georef_repeated_from_its_result_json(tmp_path, capsys):
    from minegeo.io import ControlPoints, PointCloud, write_gcps, write_point_cloud

    rng = np.random.default_rng(3)
    local = rng.uniform(-50, 50, (8, 3))
    c, s = math.cos(0.3), math.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    crs_pts = local @ R.T + [219000.0, 613000.0, 200.0] + rng.normal(0, 0.004, (8, 3))
    write_gcps(tmp_path / "g.csv", ControlPoints([f"P{i}" for i in range(8)], local, crs_pts,
                                                 sigma_enh_m=np.full((8, 3), 0.005), crs="EPSG:5186"))
    write_point_cloud(tmp_path / "map.ply", PointCloud(np.vstack([local, rng.uniform(-50, 50, (500, 3))])))
    a, b = tmp_path / "a", tmp_path / "b"
    rc = main(["georef", "--map", str(tmp_path / "map.ply"), "--gcps", str(tmp_path / "g.csv"), "--out",
               str(a / "geo.ply"), "--report", str(a / "r"), "--model", "rigid", "--blunder-alpha", "0.01",
               "--default-sigma-m", "0.02"])
    assert rc == 0
    assert main(["georef", "--config", str(a / "r" / "result.json"), "--out", str(b / "geo.ply"),
                 "--report", str(b / "r")]) == 0
    assert (a / "geo.ply").read_bytes() == (b / "geo.ply").read_bytes()
    _same_result(a / "r" / "result.json", b / "r" / "result.json", {a: b})


def test_slam_repeated_from_its_result_json(tmp_path, capsys):
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    traj = make_trajectory(world, "drive", length_m=6.0, seed=5)
    ts = np.arange(0.0, traj.times_s[-1], 0.5)[:6]
    frames = tmp_path / "frames"
    frames.mkdir()
    for k, T in enumerate(interpolate_poses(traj, ts)):
        pts = simulate_scan(world, Velodyne16(azimuth_step_deg=0.8), T, seed=k).points
        write_point_cloud(frames / f"{k:06d}.ply", PointCloud(points=pts))
    (frames / "times.txt").write_text("".join(f"{t:.6f}\n" for t in ts))
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "slam", "--frames", str(frames), "--out", str(a), "--voxel", "0.4", "--no-planes",
                 "--keyframe-distance", "1.5", "--map-voxel", "0.2"]) == 0
    assert main(["-q", "slam", "--config", str(a / "result.json"), "--out", str(b)]) == 0
    for name in ("trajectory.tum", "keyframes.tum", "graph.g2o", "map.ply"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    _same_result(a / "result.json", b / "result.json", {a: b})
    assert json.loads((b / "result.json").read_text())["parameters"]["odometry"]["voxel_size_m"] == 0.4


#: a report's sections of wall-clock times ("Timings", "Time per module", "Run time (s; ...)"), to the next section
_TIMING_SECTION = re.compile(r"<h2[^>]*>(?:Timings|Time per module|Run time)[^<]*</h2>.*?(?=<h2[ >]|</body>)", re.S)


def _same_folder(a: Path, b: Path) -> None:
    """Every file of two output folders byte-identical, but the result records (``*.json``: equal but
    for timings and the folder names) and the HTML reports (equal once their sections of wall-clock
    times are cut and the folder names replaced)."""
    names = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert any(n.suffix == ".json" for n in names)
    for n in names:
        if n.suffix == ".json":
            _same_result(a / n, b / n, {a: b})
        elif n.suffix == ".html":
            ha, hb = (_TIMING_SECTION.sub("", (d / n).read_text()).replace(str(d), "OUT") for d in (a, b))
            assert ha == hb, n
        else:
            assert (a / n).read_bytes() == (b / n).read_bytes(), n


def test_adjust_repeated_from_its_result_json(tmp_path, capsys):
    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Ghilani15_5_Angle_fix.dat")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "adjust", str(dat), "--out", str(a), "--variance", "apriori", "--alpha", "0.01",
                 "--confidence", "0.99"]) == 0
    assert json.loads((a / "result.json").read_text())["provenance"]["arguments"]["alpha"] == 0.01
    assert main(["-q", "adjust", "--config", str(a / "result.json"), "--out", str(b)]) == 0
    _same_folder(a, b)


def test_evaluate_repeated_from_its_result_json(tmp_path, capsys):
    rng = np.random.default_rng(11)
    t = np.arange(40) * 0.1
    xyz = np.c_[np.cumsum(rng.normal(0.5, 0.1, 40)), rng.normal(0, 0.2, 40), np.zeros(40)]
    q = np.tile([0.0, 0.0, 0.0, 1.0], (40, 1))
    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    np.savetxt(gt, np.c_[t, xyz, q], fmt="%.6f")
    np.savetxt(est, np.c_[t, xyz + rng.normal(0, 0.05, xyz.shape), q], fmt="%.6f")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "evaluate", "--est", str(est), "--gt", str(gt), "--out", str(a), "--delta", "5",
                 "--no-align"]) == 0
    assert json.loads((a / "result.json").read_text())["provenance"]["arguments"]["delta"] == 5
    assert main(["-q", "evaluate", "--config", str(a / "result.json"), "--out", str(b)]) == 0
    _same_folder(a, b)


def test_info_repeated_from_its_json(tmp_path, capsys):
    """``info``'s options (``--kind``, ``--format``) are in its ``--json`` record: a TUM file read as a
    cloud (``--kind cloud --format xyz``; told apart without them it is a trajectory) is read so again."""
    rng = np.random.default_rng(5)
    f = tmp_path / "poses.txt"
    np.savetxt(f, np.c_[np.arange(6) * 0.1, rng.normal(0, 3, (6, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (6, 1))],
               fmt="%.6f")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "info", str(f), "--kind", "cloud", "--format", "xyz", "--json", str(a / "info.json")]) == 0
    assert main(["-q", "info", "--config", str(a / "info.json"), "--json", str(b / "info.json")]) == 0
    assert json.loads((b / "info.json").read_text())["result"]["kind"] == "cloud"
    _same_folder(a, b)


def test_mast_repeated_from_its_result_json(tmp_path, capsys):
    from minegeo.mast import write_mast_scenario

    sc = write_mast_scenario(tmp_path / "sc", seed=3, position=2, beacon1_rotation_deg=10.0,
                             mine_origin_m=(500000.0, 6000000.0))
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "mast", "--scan", str(sc["scan"]), "--beacons", str(sc["beacons"]), "--out", str(a),
                 "--sigma-panel-m", "0.002", "--sigma-beacon-m", "0.001", "--variance", "apriori",
                 "--options", "1,2,3", "--dxf"]) == 0
    assert main(["-q", "mast", "--config", str(a / "result.json"), "--out", str(b)]) == 0
    assert (b / "mast.dxf").is_file()
    _same_folder(a, b)


@pytest.fixture(scope="module")
def drifts(tmp_path_factory):
    """``map.ply`` of two intersections (a crossing at (0, 0), a T at (40, 0), 20 m legs) and 16 frames
    ``frames/`` of a drive through the crossing, with the true first pose (tests/semantic's scene)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "semantic"))
    from _netsim import drive

    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.network import DriftNetwork, network_cloud

    nodes = [(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)]
    edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]
    net = DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))
    d = tmp_path_factory.mktemp("drifts")
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    frames, truth = drive(net, [(-14.0, 0.0), (4.0, 0.0)], step_m=1.2, seed=3)
    (d / "frames").mkdir()
    for k, (_, P) in enumerate(frames):
        write_point_cloud(d / "frames" / f"{k:06d}.ply", PointCloud(points=P))
    (d / "frames" / "times.txt").write_text("".join(f"{t:.6f}\n" for t, _ in frames))
    return d, truth[0]


def test_intersections_build_repeated_from_its_json(drifts, tmp_path, capsys):
    d, _ = drifts
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(a / "kb.npz"),
                 "--floor-cell", "1.5", "--cloud-radius", "14", "--seed", "4"]) == 0
    assert main(["-q", "intersections", "build", "--config", str(a / "kb.npz.json"), "--out", str(b / "kb.npz")]) == 0
    _same_folder(a, b)


def test_track_repeated_from_its_result_json(drifts, tmp_path, capsys):
    d, T = drifts
    kb = tmp_path / "kb.npz"
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(kb)]) == 0
    yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(kb), "--out", str(a),
                 "--start", *(f"{v:.6f}" for v in (*T[:3, 3], yaw)), "--pwcv-threshold", "0.75", "--n-his", "3",
                 "--voxel", "0.35", "--gate", "2.5"]) == 0
    assert json.loads((a / "result.json").read_text())["result"]["factors"] >= 1
    assert main(["-q", "track", "--config", str(a / "result.json"), "--out", str(b)]) == 0
    _same_folder(a, b)


def test_synth_stream_repeated_from_its_result_json(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "synth", str(a), "--stream", "handheld", "--duration-s", "0.6", "--seed", "4",
                 "--imu-hz", "150", "--lidar-hz", "12"]) == 0
    args = json.loads((a / "result.json").read_text())["provenance"]["arguments"]
    assert (args["seed"], args["imu-hz"], args["lidar-hz"]) == (4, 150.0, 12.0)
    assert main(["-q", "synth", str(b), "--config", str(a / "result.json")]) == 0
    _same_folder(a, b)


def test_synth_mast_only_repeated_from_its_result_json(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "synth", str(a), "--mast-only", "--seed", "7"]) == 0
    assert main(["-q", "synth", str(b), "--config", str(a / "result.json")]) == 0
    _same_folder(a, b)


def test_synth_mine_repeated_from_its_result_json(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["-q", "synth", str(a), "--seed", "2", "--gcps", "5"]) == 0
    assert json.loads((a / "result.json").read_text())["record"] == "truth.json"
    assert main(["-q", "synth", str(b), "--config", str(a / "result.json")]) == 0
    assert json.loads((b / "truth.json").read_text())["gcps"]["n"] == 5
    _same_folder(a, b)
