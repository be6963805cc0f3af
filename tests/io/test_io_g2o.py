"""g2o pose-graph files: the standard benchmark files read, written and read back exactly; bad files refused."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data

from minegeo.errors import FileFormatError
from minegeo.io.g2o import format_g2o, gtsam_information, non_psd_edges, read_g2o, write_g2o

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


@pytest.mark.parametrize(
    "text, message",
    [
        ("VERTEX_SE2 100000000000000000000 0 0 0\n", "line 1: vertex id 100000000000000000000 is outside"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 -9.3e18 1 0 0\nEDGE_SE2 0 -9.3e18 1 0 0 1 0 0 1 0 1\n",
         "line 2: vertex id -9.3e18 is outside"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 1 0 0 0 1 0 0 1 0 1\n",
         "line 4: edge from vertex 1 to itself"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nFIX 0.5\n", "line 3: vertex id 0.5 is not an integer"),
    ],
)
def test_vertex_ids_and_self_loops_are_refused_naming_the_line(tmp_path, text, message):
    p = tmp_path / "bad.g2o"
    p.write_text(text)
    with pytest.raises(FileFormatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_g2o(p)


def test_edges_remember_their_file_lines(tmp_path):
    p = tmp_path / "g.g2o"
    p.write_text("VERTEX_SE2 0 0 0 0\n# comment\nVERTEX_SE2 1 1 0 0\n\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
                 "EDGE_SE2 1 0 -1 0 0 1 0 0 1 0 1\n")
    assert read_g2o(p).edge_lines.tolist() == [5, 6]


def test_gtsam_information_by_hand():
    """Eigen's LLT of the SE2 matrix (GTSAM's order is the file's (x, y, θ)) stops at column 1:
    L00 = 2, L10 = 1.5, L20 = 0.5; x = 1 − 1.5² < 0; columns 1, 2 keep the input's lower
    triangle, so L = [[2,0,0],[1.5,1,0],[0.5,0.5,2]] and RᵀR = L Lᵀ."""
    omega = np.array([[4.0, 3.0, 1.0], [3.0, 1.0, 0.5], [1.0, 0.5, 2.0]])
    expect = np.array([[4.0, 3.0, 1.0], [3.0, 3.25, 1.25], [1.0, 1.25, 4.5]])
    assert np.allclose(gtsam_information(omega, "SE2"), expect, rtol=0, atol=1e-15)
    pd = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])  # complete factorisation: Ω itself
    assert np.allclose(gtsam_information(pd, "SE2"), pd, rtol=1e-15, atol=1e-15)
    # SE3: the same rule on the rotation-first permutation of the file's (t, r) matrix
    big = np.zeros((6, 6))
    big[np.ix_([3, 4, 5], [3, 4, 5])] = omega  # rotation block of the file = first block for GTSAM
    big[np.ix_([0, 1, 2], [0, 1, 2])] = np.diag([5.0, 6.0, 7.0])  # translation, after the failed column
    out = gtsam_information(big, "SE3")
    assert np.allclose(out[np.ix_([3, 4, 5], [3, 4, 5])], expect, atol=1e-15)
    assert np.allclose(out[np.ix_([0, 1, 2], [0, 1, 2])], np.diag([25.0, 36.0, 49.0]), atol=1e-15)  # R = Ω there
    assert np.all(np.linalg.eigvalsh(out) >= -1e-12)


def _gtsam_used(path, is3d):
    from helpers import require_oracle

    gtsam = require_oracle("gtsam")
    graph, _ = gtsam.readG2o(str(path), is3d)
    R = np.stack([np.asarray(graph.at(k).noiseModel().R()) for k in range(graph.size())])
    p = np.argsort([3, 4, 5, 0, 1, 2]) if is3d else np.arange(3)  # GTSAM's tangent order back to the file's
    return np.einsum("eki,ekj->eij", R, R)[:, p][:, :, p]


def test_gtsam_information_equals_gtsam_on_every_cubicle_edge():
    """Oracle: the matrices GTSAM's readG2o whitens with (RᵀR of each factor's noise model), for all
    16869 edges of cubicle.g2o, 5021 of them indefinite."""
    path = shared_data("pose_graph_g2o", "cubicle.g2o")
    g = read_g2o(path)
    used = _gtsam_used(path, True)
    mine = gtsam_information(g.information, "SE3")
    scale = np.abs(used).max(axis=(1, 2))
    assert np.abs(mine - used).max(axis=(1, 2)).max() <= 1e-12 * scale.max()
    assert non_psd_edges(g).size == 5021


def test_gtsam_information_equals_gtsam_on_indefinite_se2_edges(tmp_path):
    p = tmp_path / "se2.g2o"
    p.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nVERTEX_SE2 2 2 0 0.2\n"
                 "EDGE_SE2 0 1 1 0 0.1 4 3 1 1 0.5 2\nEDGE_SE2 1 2 1 0 0.1 1 0.2 0.1 2 0.3 -3\n"
                 "EDGE_SE2 0 2 2 0 0.2 -1 0.2 0.1 2 0.3 3\n")
    g = read_g2o(p)
    assert non_psd_edges(g).tolist() == [0, 1, 2]
    assert np.allclose(gtsam_information(g.information, "SE2"), _gtsam_used(p, False), rtol=0, atol=1e-12)
