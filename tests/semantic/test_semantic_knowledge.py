"""Intersection knowledge base (issue 18): every junction found, descriptors tell types and twins apart,
bad input gives statuses or typed errors, the .npz round trip."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from helpers import shared_data

from minegeo.errors import FileFormatError, InputError
from minegeo.semantic import (
    IntersectionKB,
    KBParams,
    SkeletonParams,
    build_knowledge_base,
    knowledge,
    similarity_matrix,
)
from minegeo.synth import DriftNetwork, intersections_network, junction_truth, network_cloud, niosh_network


@pytest.fixture(scope="module")
def net():
    return intersections_network()


@pytest.fixture(scope="module")
def kb(net):
    return build_knowledge_base(network_cloud(net, seed=1).points)


def _match(kb, net):
    """Index of the knowledge-base intersection nearest to each true junction, and the distances (m)."""
    truth = junction_truth(net)
    d = np.hypot(*(kb.invariant_points[:, None, :2] - truth[None]).transpose(2, 0, 1))
    return np.argmin(d, axis=0), d


def test_finds_every_junction(kb, net):
    """Five junctions, each within 1 m of the exact invariant point, none extra, degrees right."""
    assert kb.status == "ok" and kb.reason == ""
    idx, d = _match(kb, net)
    assert len(kb) == len(net.junctions()) == 5
    assert np.all(d.min(axis=0) < 1.0)
    assert np.all(d.min(axis=0) < 0.25)                 # measured: <= 0.08 m
    assert sorted(idx.tolist()) == list(range(5))       # one-to-one: no extra, no double
    assert np.array_equal(kb.degree[idx], net.degree()[net.junctions()])
    assert np.all(np.abs(kb.invariant_points[:, 2]) < 0.1)   # floor height at z = 0


def test_similarity_matrices(kb, net):
    """X1-X3 alike by PWCV (> 0.8), separated by CWC (< 0.8, roof 3.0 / 3.6 / 4.2 m); types differ (< 0.8)."""
    idx, _ = _match(kb, net)
    x, t, y = idx[:3], idx[3], idx[4]
    S, M = similarity_matrix(kb), similarity_matrix(kb, "cwc")
    assert np.allclose(S, S.T) and np.allclose(np.diag(S), 1.0)
    for a in x:
        for b in x:
            if a != b:
                assert S[a, b] > 0.8
                assert M[a, b] < 0.8
                assert M[a, b] < S[a, b] - 0.2
        assert S[a, t] < 0.8 and S[a, y] < 0.8
    assert S[t, y] < 0.8
    with pytest.raises(InputError):
        similarity_matrix(kb, "fpfh")


def test_broken_pwcv_only_cannot_separate_twins(kb, net):
    """What CWC is for: by PWCV alone the crossings are above the 0.8 threshold (would all match)."""
    idx, _ = _match(kb, net)
    S = similarity_matrix(kb)
    assert min(S[idx[0], idx[1]], S[idx[0], idx[2]], S[idx[1], idx[2]]) > 0.8


def test_no_intersections_status():
    """A single straight drift, and a drift with a bend: no junction, a status and a reason."""
    for nodes in ([(0.0, 0.0), (80.0, 0.0)], [(0.0, 0.0), (40.0, 0.0), (60.0, 30.0)]):
        n = len(nodes)
        net = DriftNetwork(np.array(nodes), np.array([(i, i + 1) for i in range(n - 1)]), np.full(n - 1, 4.5),
                           np.full(n, 3.5))
        kb = build_knowledge_base(network_cloud(net, seed=2).points)
        assert kb.status == "no_intersections" and len(kb) == 0
        assert "degree >= 3" in kb.reason
        assert kb.pwcv.shape == (0, 360) and kb.cwc.shape == (0, 12, 360)
        assert similarity_matrix(kb).shape == (0, 0)


def test_bad_input_is_typed():
    with pytest.raises(InputError):
        build_knowledge_base(np.zeros((0, 3)))
    P = network_cloud(intersections_network(), spacing_m=0.5, seed=0).points
    Q = P.copy()
    Q[7, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        build_knowledge_base(Q)
    with pytest.raises(InputError):
        build_knowledge_base(P[:, :2])
    with pytest.raises(InputError, match="wall"):
        build_knowledge_base(P * np.array([1.0, 1.0, 0.0]))      # flat: no wall points
    with pytest.raises(InputError):
        build_knowledge_base(P, KBParams(skeleton=SkeletonParams(cell_m=-1.0)))


def test_save_load_roundtrip(kb, tmp_path):
    p = kb.save(tmp_path / "kb.npz")
    kb2 = IntersectionKB.load(p)
    assert kb2.status == kb.status and kb2.params == kb.params and kb2.provenance == kb.provenance
    for k in ("ids", "degree", "invariant_points", "clearance_m", "cloud_offsets", "cloud_points", "pwcv", "cwc"):
        a, b = getattr(kb2, k), getattr(kb, k)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), k   # bit for bit
    assert np.array_equal(kb2.cloud(2), kb.cloud(2))
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["pwcv"] = arrays["pwcv"] + 1e-9
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FileFormatError, match=r"changed after it was written \(integrity hash mismatch: array 'pwcv'"):
        IntersectionKB.load(tmp_path / "bad.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FileFormatError, match=r"not a minegeo intersection base \(not a NumPy .npz archive\)"):
        IntersectionKB.load(tmp_path / "junk.npz")


# -- the stored records: every one under the integrity hash and checked on loading ------------------------------

def _arrays_meta(p):
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(str(z["meta"]))
    return arrays, meta


def _write(path, arrays, meta, rehash: bool):
    """The archive with ``meta`` as given; with ``rehash`` its integrity record recomputed (as a writer with
    a bug, or someone covering an edit, would), so only the value checks stand between it and a run."""
    if rehash:
        meta = {k: v for k, v in meta.items() if k != "integrity"}
        meta["integrity"] = knowledge._integrity_record(meta, arrays)
    np.savez(path, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    return path


def _edit(meta, dotted, value):
    m = json.loads(json.dumps(meta))
    *head, last = dotted.split(".")
    d = m
    for k in head:
        d = d[k]
    d[last] = value
    return m


META_EDITS = {  # (field, value, words of the error)
    "negative_cloud_radius": ("params.cloud_radius_m", -5, "params: KBParams.cloud_radius_m must be a finite number > 0"),
    "nan_cloud_radius": ("params.cloud_radius_m", "NaN", "params.cloud_radius_m must be a number"),
    "cloud_radius_below_descriptor": ("params.cloud_radius_m", 5.0, "at least the descriptor radius"),
    "zero_cell": ("params.skeleton.cell_m", 0.0, "params.skeleton: SkeletonParams.cell_m must be a finite number > 0"),
    "float_sectors": ("params.descriptor.n_sectors", 360.5, "params.descriptor.n_sectors must be a whole number"),
    "few_sectors": ("params.descriptor.n_sectors", 4, "params.descriptor: DescriptorParams.n_sectors must be a whole number >= 8"),
    "bool_radius": ("params.descriptor.radius_m", True, "params.descriptor.radius_m must be a number"),
    "band_reversed": ("params.skeleton.wall_band_m", [2.2, 0.4], "params.skeleton: SkeletonParams.wall_band_m must be an increasing"),
    "unknown_param": ("params.skeleton.extra_m", 1.0, "unknown field params.skeleton.extra_m"),
    "status": ("status", "great", "status must be"),
    "georef_origin": ("georef", {"crs": "EPSG:5186", "origin_m": [1.0, 2.0]}, "georef.origin_m"),
    "provenance": ("provenance", [], "provenance must be an object"),
}


@pytest.mark.parametrize("case", sorted(META_EDITS))
def test_edited_meta_is_refused(case, kb, tmp_path):
    """An edited meta record is refused as changed after writing; with its hash recomputed, the value check
    refuses it naming the field (issue 27: cloud_radius_m = -5 was accepted)."""
    p = kb.save(tmp_path / "kb.npz")
    arrays, meta = _arrays_meta(p)
    field, value, words = META_EDITS[case]
    if field.endswith("extra_m"):
        meta2 = json.loads(json.dumps(meta))
        meta2["params"]["skeleton"]["extra_m"] = value
    else:
        meta2 = _edit(meta, field, value)
    with pytest.raises(FileFormatError, match=r"changed after it was written \(integrity hash mismatch: its meta"):
        IntersectionKB.load(_write(tmp_path / "edited.npz", arrays, meta2, rehash=False))
    with pytest.raises(FileFormatError, match=re.escape(words)) as ei:
        IntersectionKB.load(_write(tmp_path / "rehashed.npz", arrays, meta2, rehash=True))
    assert "rebuild it with minegeo intersections build" in str(ei.value) and "\n" not in str(ei.value)


def test_rehashed_unedited_file_loads(kb, tmp_path):
    """The rehashing helper of the test above changes nothing by itself (so its refusals are the edits')."""
    p = kb.save(tmp_path / "kb.npz")
    arrays, meta = _arrays_meta(p)
    kb2 = IntersectionKB.load(_write(tmp_path / "same.npz", arrays, meta, rehash=True))
    assert kb2.params == kb.params and kb2.pwcv.tobytes() == kb.pwcv.tobytes()


ARRAY_EDITS = {
    "nan_cloud": ("cloud_points", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a), "cloud_points"),
    "offsets_past_end": ("cloud_offsets", lambda a: a + np.r_[np.zeros(a.size - 1, np.int64), 5], "cloud_offsets"),
    "degree_two": ("degree", lambda a: np.full_like(a, 2), "degree"),
    "float_ids": ("ids", lambda a: a.astype(np.float64), "dtype float64, not int64"),
    "pwcv_short": ("pwcv", lambda a: a[:, :-1], "inconsistent array shapes"),
}


@pytest.mark.parametrize("case", sorted(ARRAY_EDITS))
def test_edited_arrays_are_refused(case, kb, tmp_path):
    p = kb.save(tmp_path / "kb.npz")
    arrays, meta = _arrays_meta(p)
    name, f, words = ARRAY_EDITS[case]
    arrays[name] = np.ascontiguousarray(f(arrays[name]))
    with pytest.raises(FileFormatError, match=r"changed after it was written|dtype"):
        IntersectionKB.load(_write(tmp_path / "edited.npz", arrays, meta, rehash=False))
    with pytest.raises(FileFormatError, match=re.escape(words)):
        IntersectionKB.load(_write(tmp_path / "rehashed.npz", arrays, meta, rehash=True))


def test_other_versions_and_non_bases(kb, tmp_path):
    p = kb.save(tmp_path / "kb.npz")
    arrays, meta = _arrays_meta(p)
    old = {k: v for k, v in meta.items() if k != "integrity"}
    old["version"] = 1
    old["sha256"] = {k: v for k, v in meta["integrity"]["arrays"].items()}
    np.savez(tmp_path / "v1.npz", meta=np.array(json.dumps(old, sort_keys=True)), **arrays)
    with pytest.raises(FileFormatError, match=r"older minegeo .*version 1.*rebuild it with minegeo intersections build"):
        IntersectionKB.load(tmp_path / "v1.npz")
    with pytest.raises(FileFormatError, match="newer than this minegeo reads"):
        IntersectionKB.load(_write(tmp_path / "v9.npz", arrays, _edit(meta, "version", 9), rehash=True))
    for name, data, words in (("rnd.npz", np.random.default_rng(0).bytes(5000), "not a NumPy .npz archive"),
                              ("empty.npz", b"", "empty file")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(FileFormatError, match=re.escape(words)) as ei:
            IntersectionKB.load(tmp_path / name)
        assert "allow_pickle" not in str(ei.value) and "not a minegeo intersection base" in str(ei.value)
    np.save(tmp_path / "one.npy", arrays["pwcv"])
    with pytest.raises(FileFormatError, match="single NumPy array"):
        IntersectionKB.load(tmp_path / "one.npy")
    np.savez(tmp_path / "pickled.npz", meta=np.array([{"a": 1}], dtype=object), **arrays)
    with pytest.raises(FileFormatError, match="holds Python objects"):
        IntersectionKB.load(tmp_path / "pickled.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(FileFormatError, match=r"not a minegeo intersection base \(no 'meta' entry\)"):
        IntersectionKB.load(tmp_path / "other.npz")
    np.savez_compressed(tmp_path / "zipped.npz", meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    with pytest.raises(FileFormatError, match="compressed"):
        IntersectionKB.load(tmp_path / "zipped.npz")


def test_deterministic(net):
    P = network_cloud(net, seed=5).points
    a, b = build_knowledge_base(P), build_knowledge_base(P.copy())
    assert np.array_equal(a.invariant_points, b.invariant_points) and np.array_equal(a.cwc, b.cwc)


def _seg_dist(P, a, b):
    """Distance (m) of the points P (k, 2) to the segment a-b."""
    ab = b - a
    t = np.clip(((P - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1)


def _layout_defects(net, search_m=2.0):
    """What the straight-line layout makes of the topology, from the network geometry alone (no detector).

    Returns (ill_posed, contacts): ``ill_posed`` (k,) bool per junction (in ``net.junctions()`` order):
    two of its drifts at angle a do not separate before the shorter one ends (centrelines a width w apart
    only after ``w / sin(min(a, 90 deg))``: one tunnel in the cloud, no fork), or its largest empty circle
    lies beyond ``search_m`` (the reference point ``junction_truth(net, search_m)`` is then the edge of the
    search, not the invariant point). ``contacts`` (m, 2): points of a drift within one width of a
    non-adjacent drift (walls touching: a junction of the generated geometry, absent from the topology).
    """
    A, B, w = net.nodes[net.edges[:, 0]], net.nodes[net.edges[:, 1]], net.widths
    ill = []
    for n in net.junctions():
        inc = np.flatnonzero((net.edges == n).any(axis=1))
        v = [net.nodes[net.edges[e][net.edges[e] != n][0]] - net.nodes[n] for e in inc]
        merged = False
        for a in range(len(inc)):
            for b in range(a + 1, len(inc)):
                ang = np.arccos(np.clip(v[a] @ v[b] / np.linalg.norm(v[a]) / np.linalg.norm(v[b]), -1.0, 1.0))
                sep = max(w[inc[a]], w[inc[b]]) / np.sin(min(ang, np.pi / 2))
                merged |= bool(sep >= min(np.linalg.norm(v[a]), np.linalg.norm(v[b])))
        ill.append(merged)
    shift = np.linalg.norm(junction_truth(net, 3 * search_m) - junction_truth(net, search_m), axis=1)
    ill = np.asarray(ill) | (shift > 0.1)
    contacts = []
    s = np.linspace(0.0, 1.0, 1001)[:, None]
    for i in range(len(net.edges)):
        P = A[i] + s * (B[i] - A[i])
        for j in range(len(net.edges)):
            if i != j and not set(net.edges[i]) & set(net.edges[j]):
                contacts.append(P[_seg_dist(P, A[j], B[j]) < 0.5 * (w[i] + w[j])])
    return ill, np.concatenate(contacts)


def test_niosh_ex_layout():
    """The NIOSH EX course topology laid out by stress majorization. The junctions the layout leaves
    well posed (read off the geometry by ``_layout_defects``, not off the detector) are all found at their
    exact invariant points (1 m; median 0.1 m); every extra intersection lies where the layout makes two
    non-adjacent drifts touch (within one drift width of the contact) or at an ill-posed junction's
    invariant point (a limitation of the layout, documented in docs/intersections.md)."""
    net = niosh_network(shared_data("subt_tunnel_niosh_mine", "ex_edgelist.csv"))
    assert len(net.junctions()) == 19
    kb = build_knowledge_base(network_cloud(net, seed=1).points,
                              KBParams(SkeletonParams(min_branch_m=2.5, merge_radius_m=2.0, refine_radius_m=2.0)))
    ill, contacts = _layout_defects(net, 2.0)
    assert 0 < ill.sum() <= 4 and len(contacts) > 0      # the layout's defects are few, and present
    truth = junction_truth(net, 2.0)
    d = np.hypot(*(kb.invariant_points[:, None, :2] - truth[None]).transpose(2, 0, 1))
    err = d.min(axis=0)[~ill]
    assert np.all(err < 1.0), f"well-posed junctions missed: {np.flatnonzero(~ill)[err >= 1.0].tolist()}"
    assert np.median(err) < 0.1
    ill_points = junction_truth(net, 6.0)[ill]         # their largest empty circles, searched wider
    for k in np.flatnonzero(d.min(axis=1) > 1.0):
        x = kb.invariant_points[k, :2]
        near_contact = np.min(np.linalg.norm(contacts - x, axis=1)) <= net.widths.max()
        near_ill = np.min(np.linalg.norm(ill_points - x, axis=1)) <= 1.0
        assert near_contact or near_ill, f"extra intersection at {x.round(2).tolist()} with no cause in the layout"


def test_online_side_finds_the_same_invariant_point(kb, net):
    """A 15 m crop around a sensor 3 m from each junction, in the sensor frame (any yaw), as stacked
    keyframes would give: the same pipeline finds one junction at the map's invariant point (to 0.1 m;
    measured <= 0.06 m) and its PWCV matches the right knowledge-base entry with the yaw recovered."""
    from minegeo.semantic import drift_skeleton, pwcv, similarity

    P = network_cloud(net, seed=3).points            # another noise draw than the map's
    rng = np.random.default_rng(0)
    for i in range(len(kb)):
        C = kb.invariant_points[i]
        s = np.r_[C[:2] + rng.uniform(-3.0, 3.0, 2), 1.5]
        psi = rng.uniform(-np.pi, np.pi)
        R = np.array([[np.cos(psi), -np.sin(psi), 0.0], [np.sin(psi), np.cos(psi), 0.0], [0.0, 0.0, 1.0]])
        Q = (P[np.hypot(*(P[:, :2] - s[:2]).T) < 15.0] - s) @ R       # sensor frame: R^T (p - s)
        sk = drift_skeleton(Q)
        c_true = (C - s) @ R
        assert sk.junction_xy.shape == (1, 2)
        assert np.hypot(*(sk.junction_xy[0] - c_true[:2])) < 0.1
        c = np.r_[sk.junction_xy[0], sk.floor.height(sk.junction_xy)[0]]
        sims = [similarity(pwcv(Q, c), kb.pwcv[j]) for j in range(len(kb))]
        best = int(np.argmax([r.score for r in sims]))
        assert sims[i].score > 0.95
        if kb.degree[i] == 3:                         # T and Y are unique; X1-X3 are PWCV twins
            assert best == i
        yaw = -psi                                     # the sensor frame is the map rotated by -psi
        period = np.pi / 2 if kb.degree[i] == 4 else 2 * np.pi   # a square crossing: yaw modulo 90 deg
        assert abs((sims[i].yaw_rad - yaw + period / 2) % period - period / 2) < np.deg2rad(2.0)


def _clearance_reference(world, position, half_m: float = 6.0, step_m: float = 0.1, search_m: float = 4.0):
    """Independent invariant point of a synthetic-mine junction: the centre of the largest empty circle
    of the world's own geometry (its signed distance field: air at every height 0.7-2.2 m above the
    junction's floor, every 0.1 m), searched within ``search_m`` of the junction's graph node; the
    clearance is the Euclidean distance transform of that air mask (SciPy). Returns (xy, clearance)."""
    from scipy import ndimage

    c = np.asarray(position, float)
    g = np.arange(-half_m, half_m + step_m / 2, step_m)
    X, Y = np.meshgrid(g, g, indexing="ij")
    air = np.ones(X.shape, bool)
    for h in np.arange(0.7, 2.2 + 1e-9, 0.1):
        Q = np.c_[c[0] + X.ravel(), c[1] + Y.ravel(), np.full(X.size, c[2] + h)]
        air &= (world.sdf(Q) > 0).reshape(X.shape)
    d = ndimage.distance_transform_edt(air) * step_m
    d[np.hypot(X, Y) > search_m] = 0.0
    k = np.unravel_index(np.argmax(d), d.shape)
    return np.array([c[0] + X[k], c[1] + Y[k]]), float(d[k])


def test_synthetic_mine_survey_map_gives_every_intersection():
    """The survey map ``minegeo synth`` writes (small preset, seed 0: a LiDAR frame every 10 m, two
    levels joined by a ramp) gives one knowledge-base entry per intersection of the synthetic mine
    (10: 6 T, 2 X, 2 Y), with the degree of its type, on its own level, each invariant point within
    0.35 m of the largest empty circle of the world's geometry (independent: the world's distance
    field on a 0.1 m grid; measured <= 0.30 m). Before the footprint closing and the level split the
    skeleton had 0 branches (free space 0 m^2)."""
    from minegeo.synth.dataset import SCAN_PLANS, build_map
    from minegeo.synth.world import build_world

    world = build_world("small", 0)
    sub0 = int(np.random.default_rng(0).integers(0, 2**31 - 1, 8 + len(SCAN_PLANS["small"]))[0])  # as write_world
    cloud = build_map(world, seed=sub0)
    assert cloud.points.shape[0] == 117117                 # the map.ply of `minegeo synth OUT` (seed 0)
    kb = build_knowledge_base(cloud.points + cloud.origin, KBParams())
    truth = world.intersections
    assert kb.status == "ok" and len(kb) == len(truth) == 10
    used = set()
    for it in truth:
        ref, _ = _clearance_reference(world, it.position)
        same_level = np.abs(kb.invariant_points[:, 2] - it.position[2]) < 2.0
        d = np.where(same_level, np.hypot(*(kb.invariant_points[:, :2] - ref).T), np.inf)
        j = int(np.argmin(d))
        assert d[j] < 0.35, (it, ref, kb.invariant_points[j])
        assert kb.degree[j] == it.degree and j not in used
        used.add(j)
