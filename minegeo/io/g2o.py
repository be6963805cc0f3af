"""g2o pose-graph text files: ``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``, ``VERTEX_SE2``, ``EDGE_SE2``, ``FIX``.

The exchange format of pose-graph tools (g2o, GTSAM's ``readG2o``, SE-Sync, Ceres examples), as fixed
by ``slam_contract.md`` (the minegeo SLAM contract, see docs/slam.md):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw``: pose ``T_world_id`` (Hamilton quaternion, w last);
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw I11 I12 .. I16 I22 .. I66``: measurement ``Z_ij ≈ T_i⁻¹ T_j``
  and the 21 upper-triangular entries (row-major) of its 6×6 information matrix, ordered
  (translation, rotation);
* ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``;
* ``FIX id``: the vertex is held fixed.

An unknown record type, a short or non-numeric record, a vertex id that is not a whole number of
magnitude at most 2**53 (:data:`MAX_VERTEX_ID`), an edge from a vertex to itself, an edge to a
vertex id that is never defined and cannot be chained, a duplicate vertex id, or SE2 and SE3 records
mixed in one file are input errors that name the line. Files without (some) ``VERTEX`` lines (CSAIL, M3500, kitti_00)
get the missing poses by chaining the odometry edges ``(i, i + 1)`` from the first vertex, and the
graph says so (:attr:`PoseGraph.chained_ids`).

The writer keeps every edge exactly as read (its numbers are stored as read and printed with the
shortest round-trip repr), so ``read → optimise → write`` changes only the vertices.

Information matrices are kept as read, even when not positive semi-definite (the real
``cubicle.g2o`` holds 5021 such edges). :func:`non_psd_edges` lists them, and
:func:`gtsam_information` is what GTSAM's ``readG2o`` turns each of them into (the optimiser's
default for such edges, :mod:`minegeo.slam.posegraph`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.errors import FileFormatError, InputError
from minegeo.io._quat import matrix_to_quat, quat_to_matrix
from minegeo.io.limits import read_file_text

__all__ = ["PoseGraph", "read_g2o", "write_g2o", "format_g2o", "non_psd_edges", "gtsam_information",
           "edge_label", "se2_matrix", "MAX_VERTEX_ID"]

#: Largest g2o file read (the biggest standard benchmark, grid3D, is 19 MiB).
MAX_G2O_BYTES = 1 << 30

#: Largest vertex id magnitude read: every id is then an exact float64 and an int64 (g2o itself uses int).
MAX_VERTEX_ID = 2**53

_RECORDS = {  # name -> (kind, number of numeric fields after the tag)
    "VERTEX_SE3:QUAT": ("SE3", 8),
    "EDGE_SE3:QUAT": ("SE3", 2 + 7 + 21),
    "VERTEX_SE2": ("SE2", 4),
    "EDGE_SE2": ("SE2", 2 + 3 + 6),
    "FIX": (None, 1),
}


@dataclass
class PoseGraph:
    """A pose graph as read from (or to be written to) a g2o file.

    Attributes
    ----------
    kind : {"SE3", "SE2"}
        Pose type.
    ids : (n,) int64
        Vertex ids, in increasing order; ``poses[k]`` is the vertex ``ids[k]``.
    poses : (n, 4, 4) or (n, 3, 3) float64
        ``T_world_vertex`` (homogeneous; 3×3 for SE2).
    edges : (m, 2) int64
        ``(i, j)`` vertex *indices* into ``ids`` (not ids), in file order.
    measurements : (m, 4, 4) or (m, 3, 3) float64
        ``Z_ij``, the measured ``T_i⁻¹ T_j``.
    information : (m, 6, 6) or (m, 3, 3) float64
        Symmetric information matrices in the file's order: (tx, ty, tz, rx, ry, rz) for SE3
        (the rotation block belongs to g2o's quaternion-vector error; minegeo's cost, like GTSAM's,
        uses it for the rotation-vector residual), (x, y, θ) for SE2.
    fixed : tuple of int
        Vertex ids held fixed (``FIX`` records).
    chained_ids : tuple of int
        Vertex ids with no ``VERTEX`` record, initialised by chaining odometry edges.
    edge_values : (m, 7) or (m, 3) float64
        The measurement numbers exactly as read (x y z qx qy qz qw, or dx dy dθ), for writing back.
    edge_lines : (m,) int64 or None
        The file line of each edge (1-based), when read from a file; None for a graph built in memory.

    Notes
    -----
    Information matrices are kept as read, even when not positive semi-definite (the real
    ``cubicle.g2o`` holds such edges); :func:`non_psd_edges` lists them, and the optimiser replaces
    them by :func:`gtsam_information` or refuses them (``PoseGraphParams.indefinite_information``).
    """

    kind: str
    ids: np.ndarray
    poses: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    fixed: tuple = ()
    chained_ids: tuple = ()
    edge_values: np.ndarray = field(default=None, repr=False)
    edge_lines: np.ndarray = field(default=None, repr=False)

    @property
    def n_vertices(self) -> int:
        return int(self.ids.size)

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    def with_poses(self, poses: np.ndarray) -> PoseGraph:
        """The same graph with other vertex values (edges, information, fixes unchanged)."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != self.poses.shape:
            raise InputError(f"poses must have shape {self.poses.shape}, got {poses.shape}")
        return PoseGraph(self.kind, self.ids, poses, self.edges, self.measurements, self.information,
                         self.fixed, self.chained_ids, self.edge_values, self.edge_lines)


def edge_label(graph: PoseGraph, k: int) -> str:
    """How a message names edge ``k``: ``"line L (edge i -> j)"`` for a file, ``"edge k (i -> j)"`` else."""
    i, j = (int(graph.ids[v]) for v in graph.edges[k])
    if graph.edge_lines is not None:
        return f"line {int(graph.edge_lines[k])} (edge {i} -> {j})"
    return f"edge {k} ({i} -> {j})"


def non_psd_edges(graph: PoseGraph, rtol: float = 1e-9) -> np.ndarray:
    """Indices of the edges whose information matrix has an eigenvalue below ``-rtol·max|Ω|``."""
    if graph.n_edges == 0:
        return np.zeros(0, dtype=np.int64)
    ev = np.linalg.eigvalsh(graph.information)
    scale = np.maximum(1.0, np.abs(graph.information).reshape(graph.n_edges, -1).max(axis=1))
    return np.flatnonzero(ev[:, 0] < -rtol * scale)


def _gtsam_llt_r(A: np.ndarray) -> np.ndarray:
    """``R = Lᵀ`` of Eigen's unblocked ``LLT<Lower>`` of each matrix of the stack ``A`` (m, n, n),
    as left when it stops.

    Column k: ``x = a_kk − Σ_{j<k} L_kj²``; if ``x ≤ 0`` stop (columns k.. keep the input's lower
    triangle); else ``L_kk = √x``, ``L_ik = (a_ik − Σ_{j<k} L_ij L_kj) / L_kk`` for i > k. This is
    Eigen's ``llt_inplace::unblocked`` (matrices below 32 columns are never blocked); ``matrixU()``
    is the transpose of the lower triangle of the work matrix.
    """
    n = A.shape[-1]
    L = np.tril(np.array(A, dtype=np.float64))
    going = np.ones(L.shape[0], dtype=bool)
    for k in range(n):
        x = L[:, k, k] - np.einsum("ej,ej->e", L[:, k, :k], L[:, k, :k])
        going &= x > 0.0
        e = np.flatnonzero(going)
        if e.size == 0:
            break
        s = np.sqrt(x[e])
        L[e, k, k] = s
        if k + 1 < n:
            L[e, k + 1:, k] = (L[e, k + 1:, k] - np.einsum("eij,ej->ei", L[e, k + 1:, :k], L[e, k, :k])) / s[:, None]
    return np.swapaxes(L, 1, 2)


def gtsam_information(information: np.ndarray, kind: str) -> np.ndarray:
    """The information matrices GTSAM's ``readG2o`` actually uses for g2o edges: ``RᵀR``.

    ``readG2o`` builds ``noiseModel::Gaussian::Information(Ω_g)`` from the edge's matrix ``Ω_g`` in
    GTSAM's tangent order (SE3: rotation first, the file's (t, r) blocks swapped; SE2: the file's
    (x, y, θ)), which keeps ``R = matrixU()`` of Eigen's ``LLT`` of ``Ω_g`` (:func:`_gtsam_llt_r`)
    and whitens residuals with it, so the cost of the edge is ``½ rᵀ RᵀR r``. For a positive-definite
    ``Ω`` the factorisation completes and ``RᵀR = Ω`` (to rounding); for an indefinite one it stops at
    the first non-positive pivot and ``RᵀR`` is another matrix, positive semi-definite by
    construction (a Gram matrix). GTSAM's diagonal shortcut (``smart``: a diagonal ``Ω`` becomes
    ``Diagonal::Precisions``, NaN for a negative entry) is not reproduced: this is the ``LLT`` path.

    Parameters
    ----------
    information : (m, 6, 6) or (m, 3, 3) array (or one matrix)
        Symmetric information matrices in the file's order ((tx, ty, tz, rx, ry, rz) or (x, y, θ)).
    kind : {"SE3", "SE2"}

    Returns
    -------
    ndarray
        ``RᵀR`` in the file's order, symmetric positive semi-definite, the shape of ``information``.
    """
    info = np.asarray(information, dtype=np.float64)
    stack = info.reshape(-1, *info.shape[-2:])
    p = np.array([3, 4, 5, 0, 1, 2]) if kind == "SE3" else np.arange(3)
    R = _gtsam_llt_r(stack[:, p][:, :, p])
    used = np.einsum("eki,ekj->eij", R, R)
    q = np.argsort(p)
    return used[:, q][:, :, q].reshape(info.shape)


def se2_matrix(x: float, y: float, theta: float) -> np.ndarray:
    """Homogeneous 3×3 matrix of the planar pose (x, y, θ) (θ in rad, counter-clockwise)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _se3_matrix(v) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.asarray(v[3:7], dtype=np.float64))
    T[:3, 3] = v[:3]
    return T


def _upper_to_full(vals, n: int) -> np.ndarray:
    M = np.zeros((n, n))
    M[np.triu_indices(n)] = vals
    return M + np.triu(M, 1).T


def _check_id(path, lineno: int, token: str, value: float) -> None:
    """A vertex id must be a whole number of magnitude at most :data:`MAX_VERTEX_ID` (checked on the
    token itself, so that a long integer is never rounded to another id by ``float``)."""
    try:
        exact = int(token, 10)
    except ValueError:
        if value != int(value):
            raise FileFormatError(path, f"line {lineno}: vertex id {value!r} is not an integer") from None
        exact = int(value)
    if abs(exact) > MAX_VERTEX_ID:
        raise FileFormatError(path, f"line {lineno}: vertex id {token} is outside the ids minegeo reads "
                              "(whole numbers of magnitude at most 2**53)")


def _parse_lines(path, text: str):
    """Tokenised records: (line number, tag, numbers) with the file's kind checked."""
    kind = None
    records = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tag, *rest = line.split()
        if tag not in _RECORDS:
            raise FileFormatError(path, f"line {lineno}: unknown record {tag!r} (minegeo reads "
                                  f"{', '.join(_RECORDS)}); the line is not skipped silently")
        rkind, n = _RECORDS[tag]
        if len(rest) < n:
            raise FileFormatError(path, f"line {lineno}: {tag} needs {n} numbers, found {len(rest)}")
        try:
            nums = [float(t) for t in rest[:n]]
        except ValueError:
            raise FileFormatError(path, f"line {lineno}: {tag} holds a value that is not a number") from None
        if not all(math.isfinite(v) for v in nums):
            raise FileFormatError(path, f"line {lineno}: {tag} holds a NaN or infinite value")
        if rkind is not None:
            if kind is None:
                kind = rkind
            elif kind != rkind:
                raise FileFormatError(path, f"line {lineno}: {tag} in a file of {kind} records (SE2 and SE3 mixed)")
        for k in (0, 1) if tag.startswith("EDGE") else (0,):
            _check_id(path, lineno, rest[k], nums[k])
        if tag.startswith("EDGE") and nums[0] == nums[1]:
            raise FileFormatError(path, f"line {lineno}: edge from vertex {int(nums[0])} to itself (a self-loop "
                                  "constrains nothing)")
        records.append((lineno, tag, nums))
    if kind is None:
        raise FileFormatError(path, "no VERTEX or EDGE record: not a g2o pose-graph file?")
    return kind, records


def _chain(path, kind, vertex, edge_rows):
    """Initial poses of the ids that have no VERTEX line, by chaining odometry edges (i, i + 1)."""
    ids = sorted(vertex.keys() | {int(i) for i, _, _, _ in edge_rows} | {int(j) for _, j, _, _ in edge_rows})
    chained = [i for i in ids if i not in vertex]
    if not chained:
        return ids, ()
    odo = {(i, j): Z for i, j, Z, _ in edge_rows if j == i + 1}
    if ids[0] not in vertex:  # the first pose starts the chain at the origin
        vertex[ids[0]] = np.eye(4 if kind == "SE3" else 3)
    for k in ids:
        if k in vertex:
            continue
        if (k - 1, k) not in odo or (k - 1) not in vertex:
            raise FileFormatError(path, f"vertex {k} has no VERTEX record and no odometry edge ({k - 1}, {k}) "
                                  "to chain it from")
        vertex[k] = vertex[k - 1] @ odo[(k - 1, k)]
    return ids, tuple(chained)


def read_g2o(path) -> PoseGraph:
    """Read a g2o pose-graph file (SE3 or SE2).

    Parameters
    ----------
    path : str or Path
        The ``.g2o`` file.

    Returns
    -------
    PoseGraph

    Raises
    ------
    FileFormatError
        Unknown record (named with its line), short or non-numeric record, a vertex id that is not
        a whole number of magnitude at most 2**53, a self-loop edge, duplicate vertex id, SE2 and
        SE3 mixed, an edge whose vertex is undefined and cannot be chained, or no records.
    """
    text = read_file_text(path, max_bytes=MAX_G2O_BYTES, what="g2o file")
    kind, records = _parse_lines(path, text)
    vertex: dict[int, np.ndarray] = {}
    edge_rows, fixed = [], []
    nt = 6 if kind == "SE3" else 3
    for lineno, tag, v in records:
        if tag == "FIX":
            fixed.append(int(v[0]))
        elif tag.startswith("VERTEX"):
            vid = int(v[0])
            if vid in vertex:
                raise FileFormatError(path, f"line {lineno}: vertex {vid} is defined twice")
            try:
                vertex[vid] = _se3_matrix(v[1:]) if kind == "SE3" else se2_matrix(*v[1:4])
            except InputError as exc:
                raise FileFormatError(path, f"line {lineno}: {exc}") from None
        else:
            nv = 7 if kind == "SE3" else 3
            vals = np.asarray(v[2:2 + nv])
            try:
                Z = _se3_matrix(vals) if kind == "SE3" else se2_matrix(*vals)
            except InputError as exc:
                raise FileFormatError(path, f"line {lineno}: {exc}") from None
            info = _upper_to_full(v[2 + nv:], nt)
            edge_rows.append((int(v[0]), int(v[1]), Z, (info, vals, lineno)))
    ids, chained = _chain(path, kind, vertex, edge_rows)
    index = {vid: k for k, vid in enumerate(ids)}
    for f in fixed:
        if f not in index:
            raise FileFormatError(path, f"FIX {f}: no such vertex")
    m = len(edge_rows)
    d = 4 if kind == "SE3" else 3
    return PoseGraph(
        kind=kind,
        ids=np.asarray(ids, dtype=np.int64),
        poses=np.stack([vertex[i] for i in ids]),
        edges=np.asarray([(index[i], index[j]) for i, j, _, _ in edge_rows], dtype=np.int64).reshape(m, 2),
        measurements=np.stack([Z for _, _, Z, _ in edge_rows]) if m else np.zeros((0, d, d)),
        information=np.stack([e[0] for _, _, _, e in edge_rows]) if m else np.zeros((0, nt, nt)),
        fixed=tuple(sorted(set(fixed))),
        chained_ids=chained,
        edge_values=np.stack([e[1] for _, _, _, e in edge_rows]) if m else np.zeros((0, 7 if kind == "SE3" else 3)),
        edge_lines=np.asarray([e[2] for _, _, _, e in edge_rows], dtype=np.int64),
    )


def _num(x: float) -> str:
    return repr(float(x))


def format_g2o(graph: PoseGraph) -> str:
    """The g2o text of ``graph``: every vertex (its current pose), every FIX, every edge as read."""
    lines = []
    for vid, T in zip(graph.ids.tolist(), graph.poses, strict=True):
        if graph.kind == "SE3":
            q = matrix_to_quat(T[:3, :3])
            vals = [*T[:3, 3], *q]
            lines.append("VERTEX_SE3:QUAT " + " ".join([str(vid), *map(_num, vals)]))
        else:
            theta = math.atan2(T[1, 0], T[0, 0])
            lines.append("VERTEX_SE2 " + " ".join([str(vid), _num(T[0, 2]), _num(T[1, 2]), _num(theta)]))
    for f in graph.fixed:
        lines.append(f"FIX {f}")
    n = 6 if graph.kind == "SE3" else 3
    tri = np.triu_indices(n)
    tag = "EDGE_SE3:QUAT" if graph.kind == "SE3" else "EDGE_SE2"
    values = graph.edge_values
    for k, (a, b) in enumerate(graph.edges.tolist()):
        if values is None:  # a graph built in memory: the measurement from its matrix
            Z = graph.measurements[k]
            vals = ([*Z[:3, 3], *matrix_to_quat(Z[:3, :3])] if graph.kind == "SE3"
                    else [Z[0, 2], Z[1, 2], math.atan2(Z[1, 0], Z[0, 0])])
        else:
            vals = values[k]
        nums = [*map(_num, vals), *map(_num, graph.information[k][tri])]
        lines.append(" ".join([tag, str(int(graph.ids[a])), str(int(graph.ids[b])), *nums]))
    return "\n".join(lines) + "\n"


def write_g2o(path, graph: PoseGraph) -> Path:
    """Write ``graph`` as a g2o file, atomically (a partial file is never left behind)."""
    return atomic_write_text(path, format_g2o(graph))
