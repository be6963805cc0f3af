"""``minegeo intersections build`` and ``minegeo track`` end to end on a small drift network (issue 18,
deliverable 4): the contract outputs with provenance, the right intersection recognised as a factor,
the bad inputs of the issue as clear statuses (a map without intersections, keyframes without walls,
a look-alike intersection in the wrong place) and one-line errors, and determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _netsim import drive

from minegeo.cli import main
from minegeo.io import PointCloud, read_trajectory, write_point_cloud
from minegeo.synth.network import DriftNetwork, junction_truth, network_cloud


def _net(two_crossings: bool = False) -> DriftNetwork:
    """A 4-way crossing X at (0, 0) and a T at (40, 0) (20 m legs); with ``two_crossings`` a twin of X at
    (80, 0) instead of the T (same plan, same roof)."""
    if two_crossings:
        nodes = [(0, 0), (80, 0), (-20, 0), (0, 20), (0, -20), (100, 0), (80, 20), (80, -20)]
        edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6), (1, 7)]
    else:
        nodes = [(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)]
        edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]
    return DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))


def _write_frames(folder, frames) -> None:
    folder.mkdir()
    for k, (_, P) in enumerate(frames):
        write_point_cloud(folder / f"{k:06d}.ply", PointCloud(points=P))
    (folder / "times.txt").write_text("".join(f"{t:.6f}\n" for t, _ in frames))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Map, frames of a drive east through X (x = -14 .. 10 m) and the true poses."""
    d = tmp_path_factory.mktemp("track")
    net = _net()
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    frames, truth = drive(net, [(-14.0, 0.0), (10.0, 0.0)], step_m=1.2, seed=3)
    _write_frames(d / "frames", frames)
    return d, net, truth


@pytest.fixture(scope="module")
def db(scene):
    d, _, _ = scene
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(d / "kb.npz")]) == 0
    return d / "kb.npz"


def _start(truth) -> list[str]:
    T = truth[0]
    return ["--start", *(f"{v:.6f}" for v in (*T[:3, 3], np.degrees(np.arctan2(T[1, 0], T[0, 0]))))]


def test_build_writes_the_base_with_provenance(scene, db):
    d, net, _ = scene
    rec = json.loads(db.with_name("kb.npz.json").read_text())
    assert rec["status"] == "ok" and rec["result"]["intersections"] == 2
    assert sorted(rec["result"]["degree"]) == [3, 4]
    C = np.array(rec["result"]["invariant_points_m"])[:, :2]
    J = junction_truth(net)
    assert np.linalg.norm(C[:, None] - J[None], axis=2).min(1).max() < 0.1   # both junctions, in place
    import hashlib

    sha = hashlib.sha256((d / "map.ply").read_bytes()).hexdigest()
    assert rec["provenance"]["inputs"] == [{"path": str(d / "map.ply"), "sha256": sha}]
    assert db.with_name("kb.npz.html").is_file() and "Similarity" in db.with_name("kb.npz.html").read_text()


def test_track_end_to_end(scene, db, tmp_path):
    """Contract outputs; the crossing X is recognised and verified, its factors only from ``verified``;
    the poses follow the truth (TUM, one per frame, times from times.txt)."""
    d, _, truth = scene
    out = tmp_path / "o"
    assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(db), "--out", str(out),
                 *_start(truth)]) == 0
    for name in ("trajectory.tum", "keyframes.tum", "recognitions.csv", "result.json", "report.html"):
        assert (out / name).is_file(), name
    est = read_trajectory(out / "trajectory.tum")
    assert est.poses.shape == truth.shape
    assert np.linalg.norm(est.poses[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.5
    rec = json.loads((out / "result.json").read_text())
    r = rec["result"]
    x_id = int(np.argmin(np.linalg.norm(np.array(json.loads(db.with_name("kb.npz.json").read_text())
                                                 ["result"]["invariant_points_m"])[:, :2], axis=1)))
    assert rec["status"] == "ok" and r["recognised_ids"] == [x_id] and r["factors"] >= 1
    # ok: every factor passed its χ² test and no keyframe is 200 m of path from a check (the flight is short)
    assert r["inconsistent_factors"] == [] and r["unchecked_stretches"] == []
    assert rec["parameters"]["unchecked_path_m"] == 200.0
    assert "Stretches placed by the odometry alone" in (out / "report.html").read_text()
    assert all(e["status"] == "verified" for e in r["recognitions"] if e["factor"])
    assert {e["status"] for e in r["recognitions"]} <= {"verified", "candidate", "ambiguous", "no_walls"}
    names = {i["path"].rsplit("/", 1)[-1] for i in rec["provenance"]["inputs"]}
    assert {"kb.npz", "000000.ply", f"{len(truth) - 1:06d}.ply"} <= names
    assert rec["parameters"]["T_world_start"] is not None
    assert "map_registrations" not in r and "map" not in rec["inputs"]   # no --map: no map factors
    csv = (out / "recognitions.csv").read_text().splitlines()
    assert csv[0].startswith("time_s,keyframe,status,intersection_id") and any(",verified," in x for x in csv)


def test_start_and_truth_in_the_crs(scene, db, tmp_path):
    """``--start-frame crs`` and ``--truth-frame crs`` on a georeferenced base (CRS and origin recorded in
    the base): the pose and the truth given in CRS grid coordinates (map + origin, by hand) give the
    same run as in the map frame; ``trajectory_crs.tum`` is ``trajectory.tum`` + origin."""
    from dataclasses import replace

    from minegeo.semantic import IntersectionKB

    d, _, truth = scene
    origin = np.array([220000.0, 613000.0, 50.0])
    geo_db = tmp_path / "kb_geo.npz"
    replace(IntersectionKB.load(db), georef={"crs": "EPSG:5186", "origin_m": origin.tolist()}).save(geo_db)
    T = truth[0]
    yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
    rows = ["".join(f"{k * 0.5:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} 0 0 0 1\n") for k, p in enumerate(truth[:, :3, 3])]
    (tmp_path / "truth_map.tum").write_text("".join(rows))
    rows_crs = ["".join(f"{k * 0.5:.6f} {p[0] + origin[0]:.6f} {p[1] + origin[1]:.6f} {p[2] + origin[2]:.6f} 0 0 0 1\n")
                for k, p in enumerate(truth[:, :3, 3])]
    (tmp_path / "truth_crs.tum").write_text("".join(rows_crs))
    base = ["-q", "track", "--frames", str(d / "frames"), "--db", str(geo_db)]
    a, b = tmp_path / "a", tmp_path / "b"
    assert main([*base, "--out", str(a), "--start", *(f"{v:.6f}" for v in (*T[:3, 3], yaw)),
                 "--truth", str(tmp_path / "truth_map.tum")]) == 0
    assert main([*base, "--out", str(b), "--start-frame", "crs", "--truth-frame", "crs",
                 "--start", *(f"{v:.6f}" for v in (*(T[:3, 3] + origin), yaw)),
                 "--truth", str(tmp_path / "truth_crs.tum")]) == 0
    ta, tb = read_trajectory(a / "trajectory.tum"), read_trajectory(b / "trajectory.tum")
    assert np.abs(ta.poses - tb.poses).max() < 1e-6
    ra, rb = (json.loads((x / "result.json").read_text())["result"]["truth"] for x in (a, b))
    assert abs(ra["rmse_m"] - rb["rmse_m"]) < 1e-6 and ra["rmse_m"] < 0.5
    tc = read_trajectory(b / "trajectory_crs.tum")
    assert np.abs(tc.poses[:, :3, 3] + tc.origin - (tb.poses[:, :3, 3] + origin)).max() < 1e-6


def test_track_with_the_prior_map(scene, db, tmp_path, monkeypatch):
    """``--map``: the map's points reach :func:`~minegeo.semantic.tracking.track` as ``map_points`` (the
    file's points, in the base's frame), and the map registrations it tried are counted in result.json
    (by status, factors by rank: a count of the run's own list), named in the report, with the map's
    path and SHA-256 in the inputs. The flight (24 m) is shorter than the 50 m after which the tracker
    registers to the map, so the test's wrapper starts them at once, every 4 m of path."""
    import hashlib
    from dataclasses import replace

    import minegeo.semantic.tracking as tracking
    from minegeo.io import read_point_cloud

    d, _, truth = scene
    seen = {}
    real = tracking.track

    def spy(frames, kb, params=None, **kw):
        seen["map_points"] = kw.get("map_points")
        params = replace(params, map_factor_after_m=0.0, map_factor_spacing_m=4.0)
        seen["res"] = res = real(frames, kb, params, **kw)
        return res

    monkeypatch.setattr(tracking, "track", spy)
    out = tmp_path / "o"
    assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(db), "--out", str(out),
                 "--map", str(d / "map.ply"), *_start(truth)]) == 0
    np.testing.assert_array_equal(seen["map_points"], read_point_cloud(d / "map.ply").points)
    regs = seen["res"].map_registrations
    assert len(regs) >= 2
    rec = json.loads((out / "result.json").read_text())
    m = rec["result"]["map_registrations"]
    statuses = [g.status for g in regs]
    assert m["tried"] == len(regs) and m["factors"] == statuses.count("factor")
    assert m["by_status"] == {k: statuses.count(k) for k in set(statuses)}
    assert sum(m["factor_rank"].values()) == m["factors"]
    assert rec["inputs"]["map"] == str(d / "map.ply")
    sha = hashlib.sha256((d / "map.ply").read_bytes()).hexdigest()
    assert {"path": str(d / "map.ply"), "sha256": sha} in rec["provenance"]["inputs"]
    html = (out / "report.html").read_text()
    assert "map factors / registrations tried" in html and f"{m['factors']} / {m['tried']}" in html
    est = read_trajectory(out / "trajectory.tum")
    assert np.linalg.norm(est.poses[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.5


def test_prior_map_in_projected_coordinates_reaches_the_base_frame(scene, db, tmp_path):
    """A georeferenced base (origin o) and its map written in projected coordinates (map + o, read with
    an automatic origin): ``--map`` gives the points in the base's frame, ``p + origin_map - o``, i.e.
    the map the base was built from (to the PLY's precision); the map without the origin is refused, and
    so is a map that records another CRS."""
    from dataclasses import replace

    from minegeo.cli.track import _read_prior_map
    from minegeo.errors import InputError
    from minegeo.io import read_point_cloud
    from minegeo.semantic import IntersectionKB

    d, _, _ = scene
    origin = np.array([220000.0, 613000.0, 50.0])
    kb = replace(IntersectionKB.load(db), georef={"crs": "EPSG:5186", "origin_m": origin.tolist()})
    P = read_point_cloud(d / "map.ply").points
    write_point_cloud(tmp_path / "map_crs.ply", PointCloud(points=P + origin))
    got = _read_prior_map(tmp_path / "map_crs.ply", kb, db)
    assert np.abs(got - P).max() < 1e-3
    with pytest.raises(InputError, match="holds none of the base's 2 junctions"):
        _read_prior_map(tmp_path / "map_crs.ply", replace(kb, georef={}), db)
    # the same coordinates recorded in another CRS: refused before the extent is looked at
    write_point_cloud(tmp_path / "map_utm.ply", PointCloud(points=P + origin, crs="EPSG:32633"))
    with pytest.raises(InputError, match="is in CRS EPSG:32633 but the base"):
        _read_prior_map(tmp_path / "map_utm.ply", kb, db)


def test_track_is_deterministic(scene, db, tmp_path):
    d, _, truth = scene
    outs = []
    for name in ("a", "b"):
        assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(db), "--out", str(tmp_path / name),
                     *_start(truth)]) == 0
        outs.append(tmp_path / name)
    for f in ("trajectory.tum", "keyframes.tum", "recognitions.csv"):
        assert (outs[0] / f).read_bytes() == (outs[1] / f).read_bytes(), f
    a, b = (json.loads((o / "result.json").read_text())["result"] for o in outs)
    assert a == b


def test_map_without_intersections(tmp_path, capsys, scene):
    """A single straight drift: ``build`` writes a base with status ``no_intersections`` and exits 1 with
    one line; ``track`` on it runs odometry only, status ``no_intersections``, no factor, exit 1."""
    d, _, truth = scene
    net = DriftNetwork(np.array([[-30.0, 0.0], [30.0, 0.0]]), np.array([[0, 1]]), np.array([4.5]), np.array([3.6, 3.6]))
    write_point_cloud(tmp_path / "drift.ply", PointCloud(points=network_cloud(net, seed=2).points))
    capsys.readouterr()
    assert main(["-q", "intersections", "build", "--map", str(tmp_path / "drift.ply"),
                 "--out", str(tmp_path / "kb.npz")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_intersections" in err[0] and "Traceback" not in err[0]
    assert json.loads((tmp_path / "kb.npz.json").read_text())["status"] == "no_intersections"
    assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(tmp_path / "kb.npz"),
                 "--out", str(tmp_path / "o"), *_start(truth)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("minegeo track: no_intersections")
    rec = json.loads((tmp_path / "o" / "result.json").read_text())
    assert rec["status"] == "no_intersections" and rec["result"]["factors"] == 0
    assert read_trajectory(tmp_path / "o" / "trajectory.tum").times_s.size == len(truth)


def test_keyframes_without_walls(tmp_path, db, capsys):
    """Frames of an open floor (no wall in the wall band): every keyframe is ``no_walls`` with the reason,
    no factor, status ``no_recognition``, exit 1."""
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.linspace(-15, 15, 90), np.linspace(-15, 15, 90)), -1).reshape(-1, 2)
    frames = [(0.5 * k, np.c_[g + [-0.5 * k, 0.0], -1.5 + 0.02 * rng.standard_normal(len(g))]) for k in range(6)]
    _write_frames(tmp_path / "f", frames)
    assert main(["-q", "track", "--frames", str(tmp_path / "f"), "--db", str(db), "--out", str(tmp_path / "o"),
                 "--start", "0", "0", "1.5", "0"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("minegeo track: no_recognition")
    rec = json.loads((tmp_path / "o" / "result.json").read_text())
    assert rec["result"]["factors"] == 0 and rec["result"]["status_counts"] == {"no_walls": rec["result"]["keyframes"]}
    assert all(e["status"] == "no_walls" and "wall points" in e["reason"] for e in rec["result"]["recognitions"])
    # a flat floor does not fix the pose: the odometry's held frames are recorded, not printed
    assert rec["result"]["odometry_notes"] and all("degenerate" in m for m in rec["result"]["odometry_notes"])


def test_look_alike_in_the_wrong_place_is_a_conflict(tmp_path, capsys):
    """The base holds only the twin of the crossing driven through (80 m away): the recognitions are
    ``conflict`` (the twin's point lies 80 m from the predicted one, outside the prediction's gate: refused
    before any ICP), no factor, status ``no_recognition``."""
    net = _net(two_crossings=True)
    P = network_cloud(net, seed=1).points
    write_point_cloud(tmp_path / "map.ply", PointCloud(points=P[P[:, 0] > 40.0]))
    assert main(["-q", "intersections", "build", "--map", str(tmp_path / "map.ply"),
                 "--out", str(tmp_path / "kb.npz")]) == 0
    frames, truth = drive(net, [(-14.0, 0.0), (6.0, 0.0)], step_m=1.2, seed=3)
    _write_frames(tmp_path / "f", frames)
    capsys.readouterr()
    assert main(["-q", "track", "--frames", str(tmp_path / "f"), "--db", str(tmp_path / "kb.npz"),
                 "--out", str(tmp_path / "o"), *_start(truth)]) == 1
    rec = json.loads((tmp_path / "o" / "result.json").read_text())
    st = [e["status"] for e in rec["result"]["recognitions"]]
    assert "conflict" in st and "verified" not in st and rec["result"]["factors"] == 0, st
    c = next(e for e in rec["result"]["recognitions"] if e["status"] == "conflict")
    assert "lies outside the 99.9 % gate" in c["reason"] and "of the prediction" in c["reason"], c["reason"]
    assert c["icp_rms_m"] is None
    assert rec["status"] == "no_recognition"


@pytest.mark.parametrize("case", ["missing_db", "not_a_db", "no_frames"])
def test_user_mistakes_are_one_line_errors(case, scene, db, tmp_path, capsys):
    d, _, _ = scene
    frames, base = str(d / "frames"), str(db)
    if case == "missing_db":
        base = str(tmp_path / "nope.npz")
    elif case == "not_a_db":
        (tmp_path / "bad.npz").write_bytes(b"not a knowledge base")
        base = str(tmp_path / "bad.npz")
    else:
        (tmp_path / "empty").mkdir()
        frames = str(tmp_path / "empty")
    capsys.readouterr()
    assert main(["-q", "track", "--frames", frames, "--db", base, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("minegeo track: error:") and "Traceback" not in err[0], err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("case", ["missing", "not_a_cloud"])
def test_build_user_mistakes_are_one_line_errors(case, tmp_path, capsys):
    m = tmp_path / "map.ply"
    if case == "not_a_cloud":
        m.write_text("ply\nthis is not a point cloud\n")
    capsys.readouterr()
    assert main(["-q", "intersections", "build", "--map", str(m), "--out", str(tmp_path / "kb.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("minegeo intersections: error:") and "Traceback" not in err[0], err
    assert not (tmp_path / "kb.npz").exists()


def test_floor_cell_and_odometry_options_reach_the_run(scene, tmp_path):
    """``intersections build --floor-cell`` is the base's skeleton floor cell, and ``track`` detects the
    keyframes' junctions with the base's skeleton parameters; ``track`` registers each frame to the local
    map by default (``--odometry frame``: to the previous frame). Both are recorded in result.json."""
    d, _, truth = scene
    kb = tmp_path / "kb1.npz"
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(kb),
                 "--floor-cell", "1"]) == 0
    assert json.loads(kb.with_name("kb1.npz.json").read_text())["parameters"]["skeleton"]["floor_cell_m"] == 1.0
    for mode in ("submap", "frame"):
        out = tmp_path / mode
        extra = [] if mode == "submap" else ["--odometry", "frame"]
        assert main(["-q", "track", "--frames", str(d / "frames"), "--db", str(kb), "--out", str(out),
                     *_start(truth), *extra]) in (0, 1)
        p = json.loads((out / "result.json").read_text())["parameters"]
        assert p["recognition"]["skeleton"]["floor_cell_m"] == 1.0
        assert p["odometry"]["frame_target"] == mode
