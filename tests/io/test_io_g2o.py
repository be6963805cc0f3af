"""g2o pose-graph files: the standard benchmark files read, written and read back exactly; bad files refused."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data

from minegeo.errors import FileFormatError
from minegeo.io.g2o import format_g2o, non_psd_edges, read_g2o, write_g2o

# name -> (kind, vertices, edges) from the data set's SOURCE.md table (chained counts for files without VERTEX lines)
STANDARD = {
    "sphere2500.g2o": ("SE3", 2500, 4949),
    "torus3D.g2o": ("SE3", 5000, 9048),
    "smallGrid3D.g2o": ("SE3", 125, 297),
    "tinyGrid3D.g2o": ("SE3", 9, 11),
    "parking-garage.g2o": ("SE3", 1661, 6275),
    "cubicle.g2o": ("SE3", 5750, 16869),
    "intel.g2o": ("SE2", 1728, 2512),
    "MIT.g2o": ("SE2", 808, 827),
    "CSAIL.g2o": ("SE2", None, 1172),
    "manhattan.g2o": ("SE2", None, 5453),
    "kitti_00.g2o": ("SE2", None, 4677),
}


@pytest.mark.parametrize("name", sorted(STANDARD))
def test_standard_files_read_with_the_published_counts(name):
    g = read_g2o(shared_data("pose_graph_g2o", name))
    kind, nv, ne = STANDARD[name]
    assert g.kind == kind and g.n_edges == ne
    if nv is not None:
        assert g.n_vertices == nv and g.chained_ids == ()
    else:  # no VERTEX lines: every pose chained from odometry (i, i+1)
        assert len(g.chained_ids) == g.n_vertices > 0
    d = 4 if kind == "SE3" else 3
    R = g.poses[:, : d - 1, : d - 1]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(d - 1), atol=1e-9)
    assert np.allclose(g.information, np.swapaxes(g.information, 1, 2))


@pytest.mark.parametrize("name", ["parking-garage.g2o", "intel.g2o", "CSAIL.g2o"])
def test_write_then_read_gives_the_same_graph(tmp_path, name):
    g = read_g2o(shared_data("pose_graph_g2o", name))
    out = write_g2o(tmp_path / "out.g2o", g)
    h = read_g2o(out)
    assert h.kind == g.kind and np.array_equal(h.ids, g.ids) and np.array_equal(h.edges, g.edges)
    assert np.array_equal(h.edge_values, g.edge_values)  # edges exactly as read
    assert np.array_equal(h.information, g.information)
    assert np.allclose(h.poses, g.poses, atol=1e-12)
    assert h.chained_ids == ()  # every vertex is written


def test_edges_are_written_exactly_as_read(tmp_path):
    src = shared_data("pose_graph_g2o", "tinyGrid3D.g2o")
    g = read_g2o(src)
    text = format_g2o(g)
    edges_in = [list(map(float, ln.split()[1:])) for ln in src.read_text().splitlines() if ln.startswith("EDGE")]
    edges_out = [list(map(float, ln.split()[1:])) for ln in text.splitlines() if ln.startswith("EDGE")]
    assert edges_in == edges_out


def test_cubicle_non_psd_information_is_kept_and_counted():
    g = read_g2o(shared_data("pose_graph_g2o", "cubicle.g2o"))
    bad = non_psd_edges(g)
    assert bad.size > 0  # the real file holds indefinite information matrices
    assert np.linalg.eigvalsh(g.information[bad[0]])[0] < 0


def test_fix_records_are_read_and_written(tmp_path):
    p = tmp_path / "g.g2o"
    p.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nFIX 1\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    g = read_g2o(p)
    assert g.fixed == (1,)
    assert "FIX 1" in format_g2o(g)


@pytest.mark.parametrize(
    "text, message",
    [
        ("VERTEX_SE2 0 0 0 0\nEDGE_XYZ 0 1 2\n", "line 2: unknown record 'EDGE_XYZ'"),
        ("VERTEX_SE2 0 0 0\n", "line 1: VERTEX_SE2 needs 4 numbers"),
        ("VERTEX_SE2 0 0 zero 0\n", "line 1: VERTEX_SE2 holds a value that is not a number"),
        ("VERTEX_SE2 0 0 nan 0\n", "NaN or infinite"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", "line 2: vertex 0 is defined twice"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n", "SE2 and SE3 mixed"),
        ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 5 1 0 0 1 0 0 1 0 1\n", "vertex 5 has no VERTEX record and no odometry edge (4, 5)"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", "not unit length"),
        ("# only a comment\n", "no VERTEX or EDGE record"),
        ("VERTEX_SE2 0 0 0 0\nFIX 7\n", "FIX 7: no such vertex"),
    ],
)
def test_bad_files_name_the_problem(tmp_path, text, message):
    p = tmp_path / "bad.g2o"
    p.write_text(text)
    with pytest.raises(FileFormatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_g2o(p)
