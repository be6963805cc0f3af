"""Fuzzing the g2o reader: any text is either a valid pose graph or one FileFormatError naming the
problem, never another exception (a traceback in the CLI), and what it returns is well formed."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from minegeo.errors import FileFormatError
from minegeo.io.g2o import MAX_VERTEX_ID, PoseGraph, read_g2o

BASE = [
    "VERTEX_SE2 0 0 0 0",
    "VERTEX_SE2 1 1 0 0.1",
    "VERTEX_SE2 2 2 0.1 0.2",
    "EDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100",
    "EDGE_SE2 1 2 1 0.1 0.1 10 0 0 10 0 100",
    "EDGE_SE2 0 2 2 0.1 0.2 5 1 0 5 0 50",
    "FIX 0",
]

#: tokens a damaged or hand-edited file holds: huge, negative, fractional, non-finite ids and values
TOKENS = st.sampled_from(["0", "1", "2", "3", "-1", "0.5", "1e20", "-9.3e18", "9007199254740993", "nan", "inf",
                          "-inf", "x", "", "1e308", "-0", "VERTEX_SE2", "EDGE_SE2", "FIX", "VERTEX_SE3:QUAT",
                          "EDGE_SE3:QUAT", "#", "\u00e9", "1,5"])


@st.composite
def damaged(draw):
    lines = [ln.split(" ") for ln in BASE]
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["replace", "drop_token", "drop_line", "dup_line", "swap"]))
        k = draw(st.integers(0, len(lines) - 1)) if lines else 0
        if not lines:
            break
        if op == "replace":
            t = draw(st.integers(0, len(lines[k]) - 1))
            lines[k][t] = draw(TOKENS)
        elif op == "drop_token" and len(lines[k]) > 1:
            del lines[k][draw(st.integers(1, len(lines[k]) - 1))]
        elif op == "drop_line":
            del lines[k]
        elif op == "dup_line":
            lines.insert(k, list(lines[k]))
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
    return "\n".join(" ".join(ln) for ln in lines) + "\n"


def _well_formed(g: PoseGraph) -> None:
    n = g.n_vertices
    assert g.kind in ("SE2", "SE3")
    assert g.ids.dtype == np.int64 and np.all(np.diff(g.ids) > 0) and np.all(np.abs(g.ids) <= MAX_VERTEX_ID)
    assert g.edges.shape == (g.n_edges, 2) and (g.n_edges == 0 or (g.edges.min() >= 0 and g.edges.max() < n))
    assert np.all(g.edges[:, 0] != g.edges[:, 1])
    assert np.all(np.isfinite(g.poses)) and np.all(np.isfinite(g.information))
    assert set(g.fixed) <= set(g.ids.tolist())
    assert g.edge_lines.shape == (g.n_edges,)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=damaged())
def test_damaged_files_read_or_raise_one_file_format_error(tmp_path, text):
    p = tmp_path / "fuzz.g2o"
    p.write_text(text, encoding="utf-8")
    try:
        g = read_g2o(p)
    except FileFormatError as exc:
        assert str(exc).strip() and "\n" not in str(exc)
    else:
        _well_formed(g)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_arbitrary_bytes_never_crash_the_reader(tmp_path, data):
    p = tmp_path / "bytes.g2o"
    p.write_bytes(data)
    try:
        g = read_g2o(p)
    except FileFormatError:
        pass
    else:
        _well_formed(g)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(vid=st.integers(-(2**70), 2**70))
def test_vertex_ids_outside_the_range_are_refused_and_inside_read(tmp_path, vid):
    assume(vid != 0)
    p = tmp_path / "id.g2o"
    p.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 {vid} 1 0 0\nEDGE_SE2 0 {vid} 1 0 0 1 0 0 1 0 1\n")
    if abs(vid) > MAX_VERTEX_ID:
        try:
            read_g2o(p)
        except FileFormatError as exc:
            assert "line 2: vertex id" in str(exc)
        else:
            raise AssertionError(f"id {vid} was read")
    else:
        g = read_g2o(p)
        assert vid in g.ids.tolist()
