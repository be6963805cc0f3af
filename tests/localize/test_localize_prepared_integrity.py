"""Every stored array of a prepared map is covered by its integrity hash, every stored index is
range-checked on load (issue 14: "the contract holds for every user mistake").

Each damage kind below is applied to **every** array of a saved prepared map (enumerated from
the file, so an array added to the format is covered automatically) and to every meta field,
twice: *naive* (the file edited, the integrity record left as it was) and *forged* (the
integrity record recomputed, as a deliberate forger would; then only the range, type and
consistency checks stand between the file and the Numba kernels). Loading must either raise
:class:`FileFormatError` (map arrays and meta) or warn and rebuild the damaged search structure,
with structures bit-identical to the undamaged map's, and never raise anything else.

The loads run in one child process (this file run as a script) whose address space is capped
(``RLIMIT_AS``) at its size after a warm-up plus 1 GiB, so a regression that allocates from a
damaged size fails fast (``MemoryError``, reported per case) instead of eating the machine.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import resource
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

CHILD_EXTRA_BYTES = 1 << 30
WARNING_PHRASE = "will be rebuilt"


# ----------------------------------------------------------------------------- the map
def _box_drift(a, b, width, height, step, rng):
    """Surface points (floor, walls, irregular roof) of a straight rectangular drift (xy, z=0)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    v = np.array([-u[1], u[0]])
    s = np.arange(0.0, length, step)
    w = np.arange(-width / 2, width / 2 + 1e-9, step)
    h = np.arange(0.0, height + 1e-9, step)
    S1, W1 = np.meshgrid(s, w, indexing="ij")
    floor = np.column_stack([a + np.outer(S1.ravel(), u) + np.outer(W1.ravel(), v), np.zeros(S1.size)])
    roof = floor.copy()
    roof[:, 2] = height + 0.3 * np.sin(S1.ravel() / 3.0)
    S2, H2 = np.meshgrid(s, h, indexing="ij")
    walls = [np.column_stack([a + np.outer(S2.ravel(), u) + side * width / 2 * v, H2.ravel()]) for side in (-1.0, 1.0)]
    P = np.vstack([floor, roof, *walls])
    return P + rng.normal(0.0, 0.01, P.shape)


def _map_points():
    rng = np.random.default_rng(14)
    parts = [_box_drift((0, 0), (40, 0), 5.0, 4.0, 0.3, rng), _box_drift((40, -2.5), (40, 25), 4.0, 4.0, 0.3, rng),
             _box_drift((18, 0), (18, -14), 4.0, 3.5, 0.3, rng)]
    return np.vstack(parts) + np.array([512_000.0, 4_100_000.0, 350.0])


def _levelled_params():
    """Localization settings whose ``build_indexes`` uses every kind of stored structure."""
    from minegeo.localize import LocalizeParams

    base = LocalizeParams.fast()
    return replace(base, ransac=replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0,
                                        max_iterations=100_000),
                   correlative=replace(base.correlative, mode="always"))


def _read(path):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(str(z["meta"]))
    return arrays, meta


def _write(path, arrays, meta, forged):
    """A prepared-map file; ``forged``: with the integrity record recomputed for the new content."""
    from minegeo.localize.prepared.store import _integrity_record

    meta = json.loads(json.dumps(meta))
    if forged:
        meta.pop("integrity", None)
        meta["integrity"] = _integrity_record(meta, arrays)
    np.savez(path, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)


# ----------------------------------------------------------------------------- damage
ARRAY_KINDS = ("value", "out_of_range", "nan", "dtype", "shape")
_OTHER_DTYPE = {"float64": np.float32, "int64": np.int32, "int32": np.int64, "uint64": np.int64}


def _applies(x: np.ndarray, kind: str) -> bool:
    if kind == "out_of_range":
        return x.dtype.kind == "i"  # signed integers are the indices (uint64 rows are bit masks)
    if kind == "nan":
        return x.dtype.kind == "f"
    return True


def _damage_array(x: np.ndarray, kind: str) -> np.ndarray:
    """``x`` with one kind of damage (first element: the root node of a tree, the first slot...)."""
    y = np.array(x, copy=True)
    flat = y.reshape(-1)
    if kind == "value":
        flat[0] = flat[0] + (0.5 if y.dtype.kind == "f" else 1)
    elif kind == "out_of_range":
        flat[0] = np.iinfo(y.dtype).max if y.dtype == np.int32 else 10**12
    elif kind == "nan":
        flat[0] = np.nan
    elif kind == "dtype":
        y = y.astype(_OTHER_DTYPE[str(y.dtype)])
    elif kind == "shape":
        y = y[:-1] if y.shape[0] > 1 else np.concatenate([y, y])
    return y


def _meta_cases(meta: dict) -> list:
    """``(field path, variant, new value)`` for every meta field (core fields and every field of
    every search structure's record)."""
    cases = []
    for key, value in meta.items():
        if key == "indexes":
            continue
        bad = 5 if value is None or isinstance(value, str) else "x"
        cases.append(((key,), "wrong_type", bad))
    cases.append((("params", "voxel_size_m"), "wrong_type", "1.0"))
    cases.append((("integrity", "manifest"), "wrong_type", 5))
    for i, e in enumerate(meta["indexes"]["entries"]):
        for f, v in e.items():
            path = ("indexes", "entries", i, f)
            if f in ("name", "kind"):
                cases.append((path, "wrong_value", v + "_x"))
                continue
            cases.append((path, "wrong_type", str(v)))
            if isinstance(v, bool):
                cases.append((path, "huge", 2))
            elif isinstance(v, int):
                cases.append((path, "huge", 10**15))
            elif isinstance(v, float):
                cases.append((path, "huge", 1e300))
            elif isinstance(v, list):
                cases.append((path, "huge", [v[0], 10**15, *v[2:]]))
    return cases


def _set_field(meta: dict, path: tuple, value) -> dict:
    meta = json.loads(json.dumps(meta))
    d = meta
    for p in path[:-1]:
        d = d[p]
    d[path[-1]] = value
    return meta


def _cases(arrays: dict, meta: dict) -> list:
    """Every case: ``{"id", "what": "array"|"meta", "target", "kind", "forged"}``."""
    out = []
    for name, x in sorted(arrays.items()):
        for kind in ARRAY_KINDS:
            if _applies(x, kind):
                for forged in (False, True):
                    out.append({"id": f"{'forged' if forged else 'naive'}:{name}:{kind}", "what": "array",
                                "target": name, "kind": kind, "forged": forged})
    for path, variant, value in _meta_cases(meta):
        for forged in (False, True):
            if forged and path[0] == "integrity":
                continue
            out.append({"id": f"{'forged' if forged else 'naive'}:meta.{'.'.join(map(str, path))}:{variant}",
                        "what": "meta", "target": list(path), "kind": variant, "value": value, "forged": forged})
    # sizes that drive allocations, enlarged consistently (the hash table / leaf list really are that long)
    out.append({"id": "forged:lookup_grid_enlarged", "what": "special", "target": "grid", "kind": "huge",
                "forged": True})
    out.append({"id": "forged:descriptor_leaves_many", "what": "special", "target": "leaves", "kind": "huge",
                "forged": True})
    return out


def _damaged_file(case: dict, arrays: dict, meta: dict, path: Path) -> None:
    arrays = dict(arrays)
    if case["what"] == "array":
        arrays[case["target"]] = _damage_array(arrays[case["target"]], case["kind"])
    elif case["what"] == "meta":
        meta = _set_field(meta, tuple(case["target"]), case["value"])
    elif case["target"] == "grid":
        i = next(i for i, e in enumerate(meta["indexes"]["entries"]) if e["kind"] == "screen_grid")
        pre = f"index__{meta['indexes']['entries'][i]['name']}__"
        keys = arrays[pre + "keys"]
        # 32 MB of keys, a valid hash table (each key at its probe position): 8 GB once expanded
        arrays[pre + "keys"], arrays[pre + "nearest"] = _rehash(keys[keys != -1], arrays[pre + "nearest"], 22)
        meta = _set_field(meta, ("indexes", "entries", i, "log2_blocks"), 22)
    else:  # half a million empty descriptor leaves: 4 GB of packed leaf storage
        n = arrays["index__feature__perm"].shape[0]
        arrays["index__feature__lstart"] = np.concatenate([np.zeros(500_000, np.int64),
                                                           np.minimum(np.arange(32, n + 32, 32), n)])
    _write(path, arrays, meta, case["forged"])


def _rehash(keys: np.ndarray, rows: np.ndarray, log2: int):
    """The block keys (and their rows) re-inserted into a table of ``2^log2`` slots by the kernels'
    hashing and linear probing (:func:`minegeo.localize._kernels.block_slot`)."""
    from minegeo.localize.prepared.indexes import _hash_home

    mask = (1 << log2) - 1
    table = np.full(1 << log2, -1, dtype=np.int64)
    slot_of = np.empty(keys.size, dtype=np.int64)
    home = _hash_home(keys, log2)
    for j, (k, s) in enumerate(zip(keys.tolist(), home.tolist(), strict=True)):
        while table[s] != -1:
            s = (s + 1) & mask
        table[s] = k
        slot_of[j] = s
    return table, rows[np.argsort(slot_of)]


def _structure_digests(pm, lp) -> dict:
    """SHA-256 per search structure that ``lp`` uses (after ``build_indexes``), and of the map."""
    from minegeo.localize.prepared.store import CORE_ARRAYS, _array_digest

    cp = lp.correlative.search
    v = cp.screen_voxel_size_m
    occ = pm.occupancy(cp)
    t = pm.feature_index.tree
    screen_index, screen_pts, screen_nrm = pm.screen_target(v)
    keys, nearest, log2, cell = pm.screen_grid(v)
    parts = {
        "map": {k: getattr(pm, k) for k in CORE_ARRAYS},
        "target": pm.target_index().arrays(),
        "feature": {"rows": pm.feature_index.rows, "brute": np.array(t.brute), "rb": np.array(t.rb),
                    **{k: getattr(t, k) for k in ("mu", "V", "perm", "lstart", "lead", "Bp", "loT", "hiT")
                       if getattr(t, k) is not None}},
        "occupancy": {"keys": occ.block_keys, "bits": occ.bits, "anchors": occ.anchors, "table": occ.table,
                      "table_lo": occ.table_lo, "sizes": np.array([occ.log2_blocks, occ.n_cells, occ.n_blocks])},
        "screen": {"points": screen_pts, "normals": screen_nrm, **screen_index.arrays()},
        "screen_grid": {"keys": keys, "nearest": nearest, "log2": np.array(log2), "cell": np.array(cell)},
    }
    return {name: hashlib.sha256("".join(_array_digest(np.asarray(d[k])) for k in sorted(d)).encode()).hexdigest()
            for name, d in parts.items()}


# ----------------------------------------------------------------------------- the child process
def _vm_size() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize")


def _outcome(path, lp, handler) -> dict:
    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    handler.messages.clear()
    try:
        q = PreparedMap.load(path)
    except FileFormatError as exc:
        return {"outcome": "FileFormatError", "message": str(exc)}
    except Exception as exc:  # noqa: BLE001 - any other exception (MemoryError included) is the failure
        return {"outcome": "other", "message": f"{type(exc).__name__}: {exc}"}
    warnings = list(handler.messages)
    try:
        q.build_indexes(lp)
        digests = _structure_digests(q, lp)
    except Exception as exc:  # noqa: BLE001
        return {"outcome": "other", "message": f"after loading: {type(exc).__name__}: {exc}", "warnings": warnings}
    return {"outcome": "ok", "warnings": warnings, "digests": digests}


def _child(spec_path: str, out_path: str) -> None:
    """Load the undamaged file (warm-up), cap the address space, then every damaged file."""

    class _Collect(logging.Handler):
        messages: list = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    handler = _Collect()
    logger = logging.getLogger("minegeo.localize.prepared")
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    spec = json.loads(Path(spec_path).read_text())
    lp = _levelled_params()
    arrays, meta = _read(spec["base"])
    results = {"baseline": _outcome(spec["base"], lp, handler)}
    limit = _vm_size() + CHILD_EXTRA_BYTES
    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    results["limit_bytes"] = limit
    with tempfile.TemporaryDirectory() as tmp:
        for case in spec["cases"]:
            f = Path(tmp) / "damaged.npz"
            _damaged_file(case, arrays, meta, f)
            results[case["id"]] = _outcome(f, lp, handler)
            f.unlink()
    Path(out_path).write_text(json.dumps(results))


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """A saved prepared map holding every kind of search structure, its in-memory digests, and
    every case's outcome from the memory-capped child process."""
    from minegeo.localize import PrepareParams, prepare_map

    d = tmp_path_factory.mktemp("integrity")
    P = _map_points()
    pm = prepare_map(P, PrepareParams.fast())
    lp = _levelled_params()
    pm.build_indexes(lp)
    base = d / "map.npz"
    pm.save(base)
    arrays, meta = _read(base)
    cases = _cases(arrays, meta)
    spec, out = d / "spec.json", d / "results.json"
    spec.write_text(json.dumps({"base": str(base), "cases": cases}))
    proc = subprocess.run([sys.executable, __file__, str(spec), str(out)], capture_output=True, text=True,
                          timeout=900, check=False)
    if proc.returncode != 0:
        pytest.fail(f"the child process failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return {"path": base, "P": P, "pm": pm, "lp": lp, "arrays": arrays, "meta": meta, "cases": cases,
            "results": json.loads(out.read_text()), "digests": _structure_digests(pm, lp)}


def _structure_of(case: dict, meta: dict) -> str | None:
    """Name of the search structure a case damages, or None for the map itself."""
    if case["what"] == "array":
        name = case["target"]
        return name.split("__")[1] if name.startswith("index__") else None
    if case["what"] == "meta":
        path = case["target"]
        return meta["indexes"]["entries"][path[2]]["name"] if path[0] == "indexes" else None
    return "screen_grid" if case["target"] == "grid" else "feature"


def _check(case: dict, res: dict, prepared) -> str | None:
    """Why ``res`` breaks the contract for ``case`` (None when it holds)."""
    ref = prepared["results"]["baseline"]["digests"]
    structure = _structure_of(case, prepared["meta"])
    if res["outcome"] == "other":
        return f"raised {res['message']}"
    detectable = case["kind"] != "value" or not case["forged"]  # a forger's in-range value is a valid file
    if structure is None:  # the map's arrays or meta: a clear FileFormatError
        if res["outcome"] == "FileFormatError":
            msg = res["message"]
            if "damaged.npz" not in msg:
                return f"error message does not name the file: {msg}"
            if case["what"] == "array" and not case["forged"] and case["kind"] == "value" and (
                    f"array {case['target']!r} does not match its integrity hash" not in msg
                    or "prepare the map again with minegeo prepare-map" not in msg):
                return f"unclear message: {msg}"
            return None
        return "loaded a damaged map" if detectable else None
    # a search structure: warned about, rebuilt, bit-identical to the undamaged map's
    if res["outcome"] != "ok":
        return f"a damaged search structure made the whole file unusable: {res['message']}"
    if not detectable:
        return None
    silent_ok = case["what"] == "meta" and case["forged"] and case["target"][-1] == "build_s"  # a timing, not used
    if not silent_ok and not any(WARNING_PHRASE in m for m in res["warnings"]):
        return f"no warning for a damaged {structure!r}"
    diff = sorted(k for k in ref if k != "map" and res["digests"].get(k) != ref[k])
    if diff:
        return f"structures {diff} differ from the undamaged map's"
    return None


# ----------------------------------------------------------------------------- tests
def test_every_stored_array_and_structure_is_enumerated(prepared):
    """The cases cover every array of the file (so an added array is damaged too) and every kind of
    stored structure, and the undamaged file restores them all, silently, bit-identical to the
    in-memory map's."""
    from minegeo.localize.prepared import CORE_ARRAYS

    arrays, meta = prepared["arrays"], prepared["meta"]
    assert set(CORE_ARRAYS) < set(arrays)
    kinds = {e["kind"] for e in meta["indexes"]["entries"]}
    assert kinds == {"target_kdtree", "feature_index", "occupancy", "screen_target", "screen_grid"}
    assert not any(e.get("brute") for e in meta["indexes"]["entries"]), "the descriptor tree must not be brute force"
    assert set(meta["integrity"]["arrays"]) == set(arrays)
    damaged = {c["target"] for c in prepared["cases"] if c["what"] == "array"}
    assert damaged == set(arrays)
    base = prepared["results"]["baseline"]
    assert base["outcome"] == "ok" and base["warnings"] == []
    assert base["digests"] == prepared["digests"]
    assert prepared["results"]["limit_bytes"] > 0


@pytest.mark.parametrize("forged", [False, True], ids=["naive", "forged"])
@pytest.mark.parametrize("kind", ARRAY_KINDS)
def test_damaged_array(prepared, kind, forged):
    """One kind of damage to each stored array in turn: a clear FileFormatError for the map's
    arrays, a warning and a bit-identical rebuild for a search structure's, nothing else."""
    cases = [c for c in prepared["cases"] if c["what"] == "array" and c["kind"] == kind and c["forged"] == forged]
    assert cases
    bad = {c["target"]: why for c in cases if (why := _check(c, prepared["results"][c["id"]], prepared))}
    assert not bad, json.dumps(bad, indent=1)


@pytest.mark.parametrize("forged", [False, True], ids=["naive", "forged"])
def test_damaged_meta_field(prepared, forged):
    """Every meta field of the wrong type (a string where a number is expected...) or of a huge
    value (sizes that drive allocations): FileFormatError for the map's meta, warning and
    rebuild for a search structure's record."""
    cases = [c for c in prepared["cases"] if c["what"] == "meta" and c["forged"] == forged]
    assert len(cases) > 20
    bad = {c["id"]: why for c in cases if (why := _check(c, prepared["results"][c["id"]], prepared))}
    assert not bad, json.dumps(bad, indent=1)


def test_consistently_enlarged_sizes_are_refused_before_allocating(prepared):
    """A lookup grid announced and stored with 2^22 slots (8 GB once expanded) and half a million
    empty descriptor leaves (4 GB of leaf storage), integrity recomputed: refused by the size
    checks under the child's 1 GiB margin, rebuilt, bit-identical."""
    for cid in ("forged:lookup_grid_enlarged", "forged:descriptor_leaves_many"):
        case = next(c for c in prepared["cases"] if c["id"] == cid)
        why = _check(case, prepared["results"][cid], prepared)
        assert why is None, (cid, why)


def test_naive_edit_of_a_map_array_names_the_array(prepared, tmp_path):
    """In-process: the exact message of a changed point, and a NaN point (caught before the hash)."""
    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    arrays, meta = prepared["arrays"], prepared["meta"]
    f = tmp_path / "edited.npz"
    pts = arrays["points"].copy()
    pts[3, 1] += 1e-3
    _write(f, {**arrays, "points": pts}, meta, forged=False)
    with pytest.raises(FileFormatError, match=r"array 'points' does not match its integrity hash: the file was "
                                              r"edited or corrupted; prepare the map again with minegeo prepare-map"):
        PreparedMap.load(f)
    pts[3, 1] = np.inf
    _write(f, {**arrays, "points": pts}, meta, forged=True)
    with pytest.raises(FileFormatError, match="points.*NaN or inf"):
        PreparedMap.load(f)


def test_file_without_integrity_record_is_refused(prepared, tmp_path):
    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    meta = dict(prepared["meta"])
    meta.pop("integrity")
    f = tmp_path / "old.npz"
    _write(f, prepared["arrays"], meta, forged=False)
    with pytest.raises(FileFormatError, match="no integrity hashes.*prepare the map again with minegeo prepare-map"):
        PreparedMap.load(f)


def test_archive_members_cannot_announce_more_than_they_hold(prepared, tmp_path):
    """A compressed member (a zip bomb could announce gigabytes) and a member whose array header
    announces more bytes than it holds are refused before anything is allocated from them."""
    import zipfile

    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    src = prepared["path"]
    comp = tmp_path / "compressed.npz"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(comp, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info.filename))
    with pytest.raises(FileFormatError, match=r"compressed \(minegeo writes its stores uncompressed\)"):
        PreparedMap.load(comp)
    # the header of 'points' announces 10^10 rows (240 GB) while the member holds the real ones
    big = tmp_path / "header.npz"
    n = prepared["arrays"]["points"].shape[0]
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(big, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename == "points.npy":
                data = _announce_rows(data, n, 10**10)
            zout.writestr(info, data)
    with zipfile.ZipFile(big) as z:
        assert b"(10000000000, 3)" in z.read("points.npy")[:128], "test file not built as intended"
    with pytest.raises(FileFormatError, match="points.*announces"):
        PreparedMap.load(big)


def _announce_rows(data: bytes, n_old: int, n_new: int) -> bytes:
    """An ``.npy`` (format 1.0) whose header announces ``n_new`` rows instead of ``n_old`` (the
    header keeps its length: padding spaces are dropped)."""
    hlen = 10 + int.from_bytes(data[8:10], "little")
    header = data[:hlen]
    old, new = f"'shape': ({n_old}, 3)".encode(), f"'shape': ({n_new}, 3)".encode()
    grow = len(new) - len(old)
    header = header.replace(old, new, 1)
    assert header.endswith(b" " * grow + b"\n")
    return header[: -(grow + 1)] + b"\n" + data[hlen:]


def test_cli_localize_with_a_tampered_prepared_map(prepared, tmp_path, capsys):
    """``minegeo localize`` with an edited prepared map: exit 2, one stderr line, file unchanged."""
    from minegeo.cli import main
    from minegeo.io import write_point_cloud
    from minegeo.io.types import PointCloud

    arrays, meta = prepared["arrays"], prepared["meta"]
    bad = tmp_path / "tampered.npz"
    pts = arrays["points"].copy()
    pts[11, 0] += 0.25
    _write(bad, {**arrays, "points": pts}, meta, forged=False)
    before = hashlib.sha256(bad.read_bytes()).hexdigest()
    P = prepared["P"]
    sel = np.sum((P[:, :2] - np.array([512_030.0, 4_100_000.0])) ** 2, axis=1) < 10.0**2
    scan = tmp_path / "scan.ply"
    write_point_cloud(scan, PointCloud(points=P[sel] - np.array([512_030.0, 4_100_000.0, 351.0])))
    capsys.readouterr()
    code = main(["localize", "--map", str(bad), "--scan", str(scan), "--out", str(tmp_path / "out"),
                 "--profile", "fast"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("minegeo localize: error: "), err
    assert "array 'points' does not match its integrity hash" in lines[0]
    assert hashlib.sha256(bad.read_bytes()).hexdigest() == before


def test_localization_with_every_structure_forged_is_bit_identical(prepared, tmp_path):
    """Every search structure damaged out of range at once, integrity recomputed: each is
    rebuilt and the localization is bit-identical to the undamaged map's."""
    from minegeo.localize import PreparedMap, localize_scan

    arrays, meta = dict(prepared["arrays"]), prepared["meta"]
    for name in ("index__target__idx", "index__feature__perm"):
        arrays[name] = _damage_array(arrays[name], "out_of_range")
    for name in [k for k in arrays if k.endswith("__nearest") or k.endswith("__tree_left")]:
        arrays[name] = _damage_array(arrays[name], "out_of_range")
    occ = next(e for e in meta["indexes"]["entries"] if e["kind"] == "occupancy")
    meta = _set_field(meta, ("indexes", "entries", meta["indexes"]["entries"].index(occ), "n_cells"), 10**12)
    f = tmp_path / "forged.npz"
    _write(f, arrays, meta, forged=True)
    P, lp = prepared["P"], prepared["lp"]
    c, s = math.cos(0.7), math.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.array([512_030.0, 4_100_002.0, 351.0])
    sel = np.sum((P[:, :2] - np.array([512_036.0, 4_100_001.0])) ** 2, axis=1) < 11.0**2
    X = (P[sel] - t) @ R
    ref = localize_scan(PreparedMap.load(prepared["path"]), X, None, lp, seed=0)
    q = PreparedMap.load(f)
    assert not q._packed.get(("screen_grid", lp.correlative.search.screen_voxel_size_m))
    got = localize_scan(q, X, None, lp, seed=0)
    assert got.status == ref.status
    np.testing.assert_array_equal(got.T_map_scan, ref.T_map_scan)
    np.testing.assert_array_equal(got.covariance_6x6, ref.covariance_6x6)
    assert [h["plane_fitness"] for h in got.hypotheses] == [h["plane_fitness"] for h in ref.hypotheses]


if __name__ == "__main__":  # the memory-capped child of the ``prepared`` fixture
    _child(sys.argv[1], sys.argv[2])
    os._exit(0)


@pytest.mark.parametrize("case, words", [
    ("random_bytes", "not a NumPy .npz archive"), ("empty", "empty file"), ("npy", "single NumPy array"),
    ("folder", "is a folder"), ("pickled_meta", "holds Python objects"), ("stream", "not a regular file")])
def test_a_file_that_is_not_a_prepared_map_is_named_so(case, words, prepared, tmp_path):
    """Issue 27: random bytes passed NumPy's advice to load them with ``allow_pickle`` on to the user."""
    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    f = tmp_path / "map.npz"
    if case == "random_bytes":
        f.write_bytes(np.random.default_rng(27).bytes(5000))
    elif case == "empty":
        f.write_bytes(b"")
    elif case == "npy":
        with open(f, "wb") as fh:
            np.save(fh, prepared["arrays"]["points"])
    elif case == "folder":
        f.mkdir()
    elif case == "pickled_meta":
        np.savez(f, meta=np.array([{"format": "minegeo-prepared-map"}], dtype=object), **prepared["arrays"])
    else:
        f.symlink_to("/dev/zero")
    with pytest.raises(FileFormatError, match=words) as ei:
        PreparedMap.load(f)
    msg = str(ei.value)
    assert "pickle" not in msg.replace("holds Python objects", "") and "\n" not in msg
    assert msg.startswith(str(f)) and ("not a minegeo prepared map" in msg or case in ("folder", "pickled_meta"))


def test_a_byte_changed_in_place_is_named_a_change(prepared, tmp_path):
    """One byte of the meta changed in the file itself (the archive's own CRC no longer matches): refused
    as changed after it was written, not as an unreadable archive."""
    from minegeo.errors import FileFormatError
    from minegeo.localize import PreparedMap

    raw = bytearray(prepared["path"].read_bytes())
    key = '"format"'.encode("utf-32-le")  # the meta is a NumPy unicode array: 4 bytes per character
    i = raw.index(key) + 4
    raw[i] ^= 0x01  # "format" -> "gormat"
    f = tmp_path / "edited.npz"
    f.write_bytes(bytes(raw))
    with pytest.raises(FileFormatError, match=r"was changed after it was written \(archive checksum mismatch of "
                                              r"'meta.npy'\): prepare the map again"):
        PreparedMap.load(f)
