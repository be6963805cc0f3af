"""``minegeo track --frames F --db DB --out OUT``: every user mistake is one line, exit 2, nothing
written, the inputs unchanged and an earlier result folder untouched (issue 27).

The base (``--db``) is checked whole before any frame is read: a file that is not a minegeo
intersection base, one changed after it was written (an array, or its meta record: parameters,
status, provenance, georeferencing, under the integrity hash), one whose stored values are out of
range (a rehashed edit), one of another format version. Options are checked before anything is
read, and so are contradicting combinations (``--no-map`` with an option that only applies to the
base's intersections).

(A run without a recognition is not a user mistake: it exits 1 with a result written; it is tested in
tests/semantic/test_semantic_cli.py.)
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from _contract import (
    a_file,
    a_folder,
    assert_user_error,
    copy_tree,
    dead_pid,
    lock_path,
    run_cli,
    stream_link,
    tree_snapshot,
    truncated_copy,
    write_file,
    write_lock,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "semantic"))
from _netsim import drive  # noqa: E402

from minegeo.io import PointCloud, write_point_cloud  # noqa: E402
from minegeo.synth.network import DriftNetwork, network_cloud  # noqa: E402


def _net() -> DriftNetwork:
    """A 4-way crossing at (0, 0) and a T at (40, 0), 20 m legs (as tests/semantic/test_semantic_cli.py)."""
    nodes = [(0, 0), (40, 0), (-20, 0), (0, 20), (0, -20), (40, 20), (40, -20)]
    edges = [(2, 0), (0, 1), (0, 3), (0, 4), (1, 5), (1, 6)]
    return DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))


def _write_frames(folder: Path, frames) -> Path:
    folder.mkdir(parents=True)
    for k, (_, P) in enumerate(frames):
        write_point_cloud(folder / f"{k:06d}.ply", PointCloud(points=P))
    (folder / "times.txt").write_text("".join(f"{t:.6f}\n" for t, _ in frames))
    return folder


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """``map.ply``, its base ``kb.npz`` (``minegeo intersections build``) and 5 frames of a drive in the
    west leg (``frames/``), in one folder of their own."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("track_scene")
    net = _net()
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    frames, _ = drive(net, [(-14.0, 0.0), (-9.0, 0.0)], step_m=1.2, seed=3)
    _write_frames(d / "frames", frames)
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(d / "kb.npz")]) == 0
    return d


def _arrays_meta(db: Path):
    with np.load(db, allow_pickle=False) as z:
        return {k: z[k] for k in z.files if k != "meta"}, json.loads(str(z["meta"]))


def _base(tmp: Path, db: Path, name: str, edit, rehash: bool = False) -> Path:
    """A copy of the base with ``edit(arrays, meta)`` applied; ``rehash``: its integrity record
    recomputed for the edited content (a forger, or a writer with a bug)."""
    from minegeo.semantic import knowledge

    arrays, meta = _arrays_meta(db)
    edit(arrays, meta)
    if rehash:
        meta.pop("integrity", None)
        meta["integrity"] = knowledge._integrity_record(meta, arrays)
    p = tmp / name
    np.savez(p, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    return p


def _set(path: str, value):
    def edit(arrays, meta):
        *head, last = path.split(".")
        d = meta
        for k in head:
            d = d[k]
        d[last] = value
    return edit


def _bump_array(arrays, meta):
    arrays["cloud_points"] = arrays["cloud_points"] + np.r_[1e-6, 0.0, 0.0]


def _version_1(tmp: Path, db: Path) -> Path:
    """The base as format version 1 wrote it (per-array SHA-256, no integrity record over the meta)."""
    arrays, meta = _arrays_meta(db)
    meta["sha256"] = meta.pop("integrity")["arrays"]
    meta["version"] = meta["provenance"]["version"] = 1
    p = tmp / "v1.npz"
    np.savez(p, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    return p


DB_CASES = {  # (maker, words of the error line)
    "missing": (lambda t, d: t / "nope.npz", "No such file"),
    "folder": (lambda t, d: a_folder(t), "is a folder"),
    "empty": (lambda t, d: write_file(t, "empty.npz", b""), "empty file"),
    "random_bytes": (lambda t, d: write_file(t, "rnd.npz", np.random.default_rng(27).bytes(5000)),
                     "not a minegeo intersection base (not a NumPy .npz archive)"),
    "text": (lambda t, d: write_file(t, "kb.npz", "this is not a knowledge base\n"), "not a NumPy .npz archive"),
    "stream": (lambda t, d: Path("/dev/zero"), "not a regular file"),
    "stream_behind_npz_name": (lambda t, d: stream_link(t, "zero.npz"), "not a regular file"),
    "truncated": (lambda t, d: truncated_copy(d / "kb.npz", t / "half.npz"), "not a minegeo intersection base"),
    "npy_array": (lambda t, d: _npy(t), "single NumPy array"),
    "pickled_meta": (lambda t, d: _pickled(t, d), "holds Python objects"),
    "other_npz": (lambda t, d: _other_npz(t), "not a minegeo intersection base (no 'meta' entry)"),
    "prepared_map_format": (lambda t, d: _base(t, d / "kb.npz", "prep.npz", _set("format", "minegeo-prepared-map")),
                            "not a minegeo intersection base (format 'minegeo-prepared-map')"),
    "map_ply": (lambda t, d: d / "map.ply", "not a NumPy .npz archive"),
    "array_changed": (lambda t, d: _base(t, d / "kb.npz", "arr.npz", _bump_array),
                      "changed after it was written (integrity hash mismatch: array 'cloud_points')"),
    # issue 27, case 13: meta.params.cloud_radius_m edited to -5 was accepted
    "meta_cloud_radius_edited": (lambda t, d: _base(t, d / "kb.npz", "neg.npz", _set("params.cloud_radius_m", -5)),
                                 "changed after it was written (integrity hash mismatch: its meta record"),
    "meta_cloud_radius_rehashed": (lambda t, d: _base(t, d / "kb.npz", "neg2.npz", _set("params.cloud_radius_m", -5),
                                                      rehash=True),
                                   "params: KBParams.cloud_radius_m must be a finite number > 0"),
    "meta_n_sectors_rehashed": (lambda t, d: _base(t, d / "kb.npz", "ns.npz", _set("params.descriptor.n_sectors", 4),
                                                   rehash=True),
                                "params.descriptor: DescriptorParams.n_sectors must be a whole number >= 8"),
    "meta_georef_edited": (lambda t, d: _base(t, d / "kb.npz", "geo.npz",
                                              _set("georef", {"crs": "EPSG:5186", "origin_m": [1.0, 2.0, 3.0]})),
                           "integrity hash mismatch"),
    "meta_status_rehashed": (lambda t, d: _base(t, d / "kb.npz", "st.npz", _set("status", "no_intersections"),
                                                rehash=True), "status 'no_intersections' with 2 intersection(s)"),
    "integrity_removed": (lambda t, d: _base(t, d / "kb.npz", "noint.npz", lambda a, m: m.pop("integrity")),
                          "integrity record is missing"),
    "version_1": (lambda t, d: _version_1(t, d / "kb.npz"), "rebuild it with minegeo intersections build"),
    "version_9": (lambda t, d: _base(t, d / "kb.npz", "v9.npz", _set("version", 9), rehash=True),
                  "newer than this minegeo reads"),
}


def _npy(t: Path) -> Path:
    p = t / "kb.npz"
    with open(p, "wb") as fh:
        np.save(fh, np.zeros((4, 3)))
    return p


def _pickled(t: Path, d: Path) -> Path:
    arrays, _ = _arrays_meta(d / "kb.npz")
    p = t / "pickled.npz"
    np.savez(p, meta=np.array([{"format": "minegeo-intersection-kb"}], dtype=object), **arrays)
    return p


def _other_npz(t: Path) -> Path:
    p = t / "other.npz"
    np.savez(p, points=np.zeros((10, 3)))
    return p


@pytest.mark.parametrize("case", sorted(DB_CASES))
def test_bad_base(case, scene, tmp_path, capsys):
    make, words = DB_CASES[case]
    db = make(tmp_path, scene)
    out = tmp_path / "out"
    line = assert_user_error("track", ["--frames", scene / "frames", "--db", db, "--out", out], capsys,
                             inputs=[db, scene / "frames", tmp_path / "a_folder"], outputs=[out], expect=words)
    assert "allow_pickle" not in line


def _frames_copy(t: Path, d: Path, edit) -> Path:
    f = copy_tree(d / "frames", t / "frames")
    edit(f)
    return f


FRAMES_CASES = {
    "missing": lambda t, d: t / "nope",
    "empty_folder": lambda t, d: _empty(t),
    "a_file": lambda t, d: d / "map.ply",
    "stream": lambda t, d: Path("/dev/zero"),
    "only_junk_files": lambda t, d: _junk_frames(t),
    "one_frame": lambda t, d: _frames_copy(t, d, lambda f: ([p.unlink() for p in sorted(f.glob("*.ply"))[1:]],
                                                            (f / "times.txt").write_text("0.0\n"))),
    "times_count_mismatch": lambda t, d: _frames_copy(t, d, lambda f: (f / "times.txt").write_text("0.0\n0.5\n")),
    "times_nan": lambda t, d: _frames_copy(t, d, lambda f: (f / "times.txt").write_text(
        (f / "times.txt").read_text().replace("0.500000", "nan", 1))),
    "times_not_increasing": lambda t, d: _frames_copy(t, d, lambda f: (f / "times.txt").write_text(
        "".join(f"{1.0 - 0.1 * k:.6f}\n" for k in range(len(list(f.glob("*.ply"))))))),
}


def _empty(t: Path) -> Path:
    (t / "empty").mkdir()
    return t / "empty"


def _junk_frames(t: Path) -> Path:
    f = t / "junk"
    f.mkdir()
    for k in range(3):
        (f / f"{k:06d}.ply").write_bytes(b"ply\nthis is not a point cloud\n")
    return f


@pytest.mark.parametrize("case", sorted(FRAMES_CASES))
def test_bad_frames(case, scene, tmp_path, capsys):
    frames = FRAMES_CASES[case](tmp_path, scene)
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", frames, "--db", scene / "kb.npz", "--out", out], capsys,
                      inputs=[frames, scene / "kb.npz"], outputs=[out])


OPTION_CASES = {  # (options, words of the error line)
    "start_nan": (["--start", "0", "0", "nan", "0"], "argument --start"),
    "start_inf": (["--start", "inf", "0", "1.5", "0"], "argument --start"),
    "start_three_values": (["--start", "0", "0", "1.5"], "--start"),
    "start_not_a_number": (["--start", "x", "0", "1.5", "0"], "argument --start"),
    "pwcv_threshold_0": (["--pwcv-threshold", "0"], "argument --pwcv-threshold"),
    "pwcv_threshold_above_1": (["--pwcv-threshold", "1.5"], "argument --pwcv-threshold"),
    "pwcv_threshold_nan": (["--pwcv-threshold", "nan"], "argument --pwcv-threshold"),
    "n_his_negative": (["--n-his", "-1"], "argument --n-his"),
    "n_his_fraction": (["--n-his", "2.5"], "argument --n-his"),
    "consecutive_0": (["--consecutive", "0"], "argument --consecutive"),
    "icp_max_distance_0": (["--icp-max-distance", "0"], "argument --icp-max-distance"),
    "icp_max_distance_nan": (["--icp-max-distance", "nan"], "argument --icp-max-distance"),
    "gate_negative": (["--gate", "-3"], "argument --gate"),
    "gate_drift_nan": (["--gate-drift", "nan"], "argument --gate-drift"),
    "gate_drift_negative": (["--gate-drift", "-0.1"], "argument --gate-drift"),
    "unchecked_path_0": (["--unchecked-path", "0"], "argument --unchecked-path"),
    "unchecked_path_nan": (["--unchecked-path", "nan"], "argument --unchecked-path"),
    "voxel_0": (["--voxel", "0"], "argument --voxel"),
    "voxel_inf": (["--voxel", "inf"], "argument --voxel"),
    "keyframe_distance_negative": (["--keyframe-distance", "-2"], "argument --keyframe-distance"),
    "seed_negative": (["--seed", "-1"], "argument --seed"),
    "seed_beyond_numpy": (["--seed", str(2**32)], "argument --seed"),
    "no_map_with_gate_drift": (["--no-map", "--gate-drift", "0.1"], "--gate-drift applies"),
    "no_map_with_icp_max_distance": (["--no-map", "--icp-max-distance", "0.2"], "--icp-max-distance applies"),
    "odometry_unknown": (["--odometry", "imu"], "argument --odometry"),
    "start_frame_without_start": (["--start-frame", "crs"], "--start-frame gives the frame of --start"),
    "truth_frame_without_truth": (["--truth-frame", "map"], "--truth-frame gives the frame of --truth"),
    "start_frame_unknown": (["--start", "0", "0", "1.5", "0", "--start-frame", "wgs84"], "argument --start-frame"),
    "start_in_crs_base_without_crs": (["--start", "-14", "0", "1.5", "0", "--start-frame", "crs"],
                                      "not georeferenced"),
}


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_option(case, scene, tmp_path, capsys):
    opts, words = OPTION_CASES[case]
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out, *opts], capsys,
                      inputs=[scene / "frames", scene / "kb.npz"], outputs=[out], expect=words)


TRUTH_CASES = {
    "missing": lambda t: t / "nope.tum",
    "empty": lambda t: write_file(t, "empty.tum", b""),
    "junk": lambda t: write_file(t, "junk.tum", "this is not a trajectory\n"),
    "nan_pose": lambda t: write_file(t, "nan.tum", "0.0 nan 0 1.5 0 0 0 1\n0.5 0 0 1.5 0 0 0 1\n"),
}


@pytest.mark.parametrize("case", sorted(TRUTH_CASES))
def test_bad_truth(case, scene, tmp_path, capsys):
    truth = TRUTH_CASES[case](tmp_path)
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out,
                                "--truth", truth], capsys, inputs=[scene / "frames", scene / "kb.npz", truth],
                      outputs=[out])


def test_truth_in_crs_for_a_base_without_crs(scene, tmp_path, capsys):
    """``--truth-frame crs`` needs a georeferenced base (its origin converts the truth): refused before
    any frame is tracked."""
    truth = write_file(tmp_path, "truth.tum", "0.0 -14 0 1.5 0 0 0 1\n0.5 -13 0 1.5 0 0 0 1\n")
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out,
                                "--truth", truth, "--truth-frame", "crs"], capsys,
                      inputs=[scene / "frames", scene / "kb.npz", truth], outputs=[out], expect="not georeferenced")


# ------------------------------------------------------------------------------------ --map


_PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def _ply(t: Path, name: str, rows: list[str]) -> Path:
    return write_file(t, name, _PLY_HEAD.format(n=len(rows)) + "".join(r + "\n" for r in rows))


def _shifted_map(t: Path, d: Path, shift) -> Path:
    """The map the base was built from, moved by ``shift`` (m): a map in another frame."""
    from minegeo.io import read_point_cloud

    p = t / "shifted.ply"
    write_point_cloud(p, PointCloud(points=read_point_cloud(d / "map.ply").points + np.asarray(shift, float)))
    return p


MAP_CASES = {  # (maker, words of the error line): --map is checked before any frame is tracked
    "missing": (lambda t, d: t / "nope.ply", "No such file (name the map the base was built from)"),
    "folder": (lambda t, d: a_folder(t), "is a folder"),
    "stream": (lambda t, d: Path("/dev/zero"), "not a regular file"),
    "zero_bytes": (lambda t, d: write_file(t, "zero.ply", b""), "empty"),
    "junk_text": (lambda t, d: write_file(t, "junk.ply", "this is not a point cloud\n"), "junk.ply"),
    "no_points": (lambda t, d: _ply(t, "none.ply", []), "holds 0 point(s)"),
    "three_points": (lambda t, d: _ply(t, "three.ply", ["0 0 0", "1 0 0", "0 1 0"]), "holds 3 point(s)"),
    "nan_point": (lambda t, d: _ply(t, "nan.ply", [f"{k} 0 0" for k in range(11)] + ["nan 1 1"]), "NaN or inf"),
    "inf_point": (lambda t, d: _ply(t, "inf.ply", [f"{k} 0 0" for k in range(11)] + ["1 inf 1"]), "NaN or inf"),
    # a map in another frame (500 m east of the base's): its extent holds none of the base's junctions
    "other_frame": (lambda t, d: _shifted_map(t, d, (500.0, 0.0, 0.0)), "holds none of the base's 2 junctions"),
    # ... or with projected coordinates (an automatic origin) while the base has none
    "projected_coordinates": (lambda t, d: _shifted_map(t, d, (350000.0, 4100000.0, 0.0)),
                              "holds none of the base's 2 junctions"),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map(case, scene, tmp_path, capsys):
    make, words = MAP_CASES[case]
    prior = make(tmp_path, scene)
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out,
                                "--map", prior], capsys,
                      inputs=[prior, scene / "frames", scene / "kb.npz"], outputs=[out], expect=words)


def test_map_with_no_map(scene, tmp_path, capsys):
    """``--map`` adds factors against the base's map frame, which ``--no-map`` ignores: refused before
    anything is read."""
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out,
                                "--map", scene / "map.ply", "--no-map"], capsys,
                      inputs=[scene / "frames", scene / "kb.npz", scene / "map.ply"], outputs=[out],
                      expect="--map adds factors in the base's map frame")


# ------------------------------------------------------------------------------------ outputs


@pytest.fixture
def work(scene, tmp_path):
    """Frames and base in a folder of their own (copies), with the map beside them."""
    d = tmp_path / "work"
    d.mkdir()
    copy_tree(scene / "frames", d / "frames")
    for name in ("kb.npz", "map.ply"):
        (d / name).write_bytes((scene / name).read_bytes())
    return d


OUT_CASES = {
    "out_is_the_frames": lambda w: w / "frames",
    "out_inside_the_frames": lambda w: w / "frames" / "result",
    "out_is_the_base": lambda w: w / "kb.npz",
    "out_contains_the_inputs": lambda w: w,
    "out_is_an_existing_file": lambda w: a_file(w.parent),
    "out_through_a_file": lambda w: a_file(w.parent) / "sub",
    "out_not_empty_no_result": lambda w: a_folder(w.parent, "busy"),
}


@pytest.mark.parametrize("case", sorted(OUT_CASES))
def test_bad_output(case, work, capsys):
    out = OUT_CASES[case](work)
    assert_user_error("track", ["--frames", work / "frames", "--db", work / "kb.npz", "--out", out], capsys,
                      inputs=[work / "frames", work / "kb.npz", work], outputs=[out])


def test_out_locked_by_live_run(scene, tmp_path, capsys):
    out = tmp_path / "out"
    lk = write_lock(out, os.getpid(), "track")
    assert_user_error("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out], capsys,
                      inputs=[scene / "frames", scene / "kb.npz"], outputs=[out], expect="being written by")
    assert lk.exists()


@pytest.fixture(scope="module")
def earlier(scene, tmp_path_factory):
    """A real earlier result of ``track`` (no start pose, 5 frames in a drift: status ``unanchored``,
    exit 1, outputs written); a stale lock of a dead run is taken over on the way."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("earlier") / "out"
    write_lock(d, dead_pid(), "track")
    assert main(["-q", "track", "--frames", str(scene / "frames"), "--db", str(scene / "kb.npz"),
                 "--out", str(d)]) in (0, 1)
    assert (d / "result.json").is_file() and not lock_path(d).exists()
    return d


FAILING_RUNS = {  # issue 27, case 13: an earlier result was replaced by a run on an edited base
    "meta_cloud_radius_edited": lambda t, d: (["--db", DB_CASES["meta_cloud_radius_edited"][0](t, d)]),
    "meta_cloud_radius_rehashed": lambda t, d: (["--db", DB_CASES["meta_cloud_radius_rehashed"][0](t, d)]),
    "random_bytes_base": lambda t, d: (["--db", DB_CASES["random_bytes"][0](t, d)]),
    "junk_frames": lambda t, d: (["--db", d / "kb.npz", "--frames", _junk_frames(t)]),
    "nan_option": lambda t, d: (["--db", d / "kb.npz", "--gate", "nan"]),
}


@pytest.mark.parametrize("case", sorted(FAILING_RUNS))
def test_failing_run_leaves_earlier_result(case, earlier, scene, tmp_path, capsys):
    out = copy_tree(earlier, tmp_path / "out")
    before = tree_snapshot(out)
    extra = FAILING_RUNS[case](tmp_path, scene)
    frames = extra[extra.index("--frames") + 1] if "--frames" in extra else scene / "frames"
    argv = ["--frames", scene / "frames", "--out", out, *extra] if "--frames" not in extra else ["--out", out, *extra]
    db = extra[extra.index("--db") + 1]
    assert_user_error("track", argv, capsys, inputs=[db, frames], outputs=[out])
    assert tree_snapshot(out) == before


def test_a_good_run_replaces_the_earlier_result(earlier, scene, tmp_path, capsys):
    """The same command on the unchanged base replaces the earlier folder as a whole (the contract's
    counterpart: only a failing run leaves it as it was)."""
    out = copy_tree(earlier, tmp_path / "out")
    (out / "stray.txt").write_text("from an older run\n")
    code, _, err = run_cli("track", ["--frames", scene / "frames", "--db", scene / "kb.npz", "--out", out], capsys)
    assert code in (0, 1), err
    assert (out / "result.json").is_file() and not (out / "stray.txt").exists()
