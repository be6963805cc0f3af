"""Drift networks of straight drifts as point clouds, for intersection (junction) studies.

A :class:`DriftNetwork` is a planar graph: node positions (m, map frame, z up, floor at z = 0),
edges = straight drifts of a given width, and a roof height per node. The free space is the union
of **capsules** (points within ``width / 2`` of an edge's segment), so bends get a rounded outer
corner, dead ends a rounded end wall, and junctions the exact union of the drifts meeting there.
The roof over a point is the height of the node nearest to it (a Voronoi partition of the nodes),
which lets nearly-alike junctions differ only in roof height.

:func:`network_cloud` samples floor, walls and roof on that geometry with seeded noise;
:func:`intersections_network` is the test network of the intersection studies (three alike 4-way crossings, a T and a
Y); :func:`niosh_network` lays out the topology of a DARPA SubT NIOSH course from its edge list.
See ``docs/intersections.md``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo._jit import njit
from minegeo.errors import FileFormatError, InputError

__all__ = ["DriftNetwork", "NetworkCloud", "network_cloud", "intersections_network", "niosh_network",
           "junction_truth", "RoughnessField", "roughness_field", "with_roughness", "segment_distances",
           "wall_outline", "max_clearance_point"]


@dataclass(frozen=True, eq=False)
class DriftNetwork:
    """A graph of straight drifts.

    Attributes
    ----------
    nodes : ndarray (n, 2)
        Node positions (m, map frame x/y; the floor is z = 0).
    edges : ndarray (m, 2) int
        Node indices of each straight drift.
    widths : ndarray (m,)
        Drift width (m) per edge.
    node_heights : ndarray (n,)
        Roof height (m above the floor) of the region nearest to each node.
    names : tuple of str
        A name per node (``"X1"``, ``"T"``, ``""`` for ordinary nodes).
    info : dict
        Provenance of the layout (JSON-able).
    roughness_m : float
        RMS of the rock-surface roughness (m, along the surface normal; 0 = the flat, smooth
        surfaces of the plan). See :func:`roughness_field`.
    roughness_seed : int
        Seed of the roughness field.
    """

    nodes: np.ndarray
    edges: np.ndarray
    widths: np.ndarray
    node_heights: np.ndarray
    names: tuple = ()
    info: dict = field(default_factory=dict)
    roughness_m: float = 0.0
    roughness_seed: int = 0

    def degree(self) -> np.ndarray:
        """Number of drifts meeting at each node, shape (n,)."""
        return np.bincount(self.edges.ravel(), minlength=len(self.nodes))

    def junctions(self) -> np.ndarray:
        """Indices of the nodes of degree >= 3 (the intersections)."""
        return np.flatnonzero(self.degree() >= 3)


@dataclass(frozen=True, eq=False)
class NetworkCloud:
    """Sampled point cloud of a :class:`DriftNetwork`.

    Attributes
    ----------
    points : ndarray (N, 3)
        Map frame (m, z up).
    labels : ndarray (N,) int
        0 floor, 1 wall, 2 roof.
    """

    points: np.ndarray
    labels: np.ndarray


# ------------------------------------------------------------------------------------- roughness
ROUGHNESS_WAVES = 24
ROUGHNESS_WAVELENGTHS_M = (0.5, 6.0)


@dataclass(frozen=True, eq=False)
class RoughnessField:
    """A smooth, seeded random field h(p) (m) over 3-D space: the rock surface's offset along its
    outward normal (positive = overbreak, into the rock), see :func:`roughness_field`.

    ``h(p) = sum_k a_k sin(2 pi f_k . p + phi_k)``; ``freq`` (K, 3) in cycles per m, ``amp`` (K,) m,
    ``phase`` (K,) rad.
    """

    freq: np.ndarray
    amp: np.ndarray
    phase: np.ndarray

    def __call__(self, P: np.ndarray) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(P))
        for s in range(0, len(P), 65536):
            out[s:s + 65536] = np.sin(2.0 * np.pi * (P[s:s + 65536] @ self.freq.T) + self.phase) @ self.amp
        return out


def roughness_field(rms_m: float, seed: int = 0) -> RoughnessField:
    """The roughness field of a drift network: ``ROUGHNESS_WAVES`` plane waves.

    Directions uniform on the sphere, wavelengths log-uniform in ``ROUGHNESS_WAVELENGTHS_M``
    (0.5-6 m, the scale of drill-and-blast overbreak and half barrels), amplitude proportional to
    the wavelength (every wave has the same slope), phases uniform; scaled so that the RMS of h is
    ``rms_m`` (independent phases: ``RMS^2 = sum a_k^2 / 2``). At 0.1 m RMS the surface slope is about
    0.23 RMS. Seeded (``np.random.default_rng([seed, 18])``): the prior map and every simulated
    frame see the same rock.
    """
    if not (np.isfinite(rms_m) and rms_m >= 0.0):
        raise InputError(f"roughness_m must be a finite number >= 0, got {rms_m!r}")
    rng = np.random.default_rng([int(seed), 18])
    K = ROUGHNESS_WAVES
    u = rng.normal(size=(K, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    lo, hi = ROUGHNESS_WAVELENGTHS_M
    lam = np.exp(rng.uniform(np.log(lo), np.log(hi), K))
    phase = rng.uniform(0.0, 2.0 * np.pi, K)
    amp = lam * (float(rms_m) / np.sqrt(0.5 * np.sum(lam ** 2)))
    return RoughnessField(np.ascontiguousarray(u / lam[:, None]), np.ascontiguousarray(amp),
                          np.ascontiguousarray(phase))


@njit
def surface_offset(x, y, z, freq, amp, phase):
    """h(x, y, z) (m) of a :class:`RoughnessField` (its arrays)."""
    h = 0.0
    for k in range(amp.shape[0]):
        h += amp[k] * np.sin(2.0 * np.pi * (freq[k, 0] * x + freq[k, 1] * y + freq[k, 2] * z) + phase[k])
    return h


def with_roughness(net: DriftNetwork, rms_m: float, seed: int = 0) -> DriftNetwork:
    """``net`` with rough rock surfaces (RMS ``rms_m`` along the normal); 0 gives the flat plan."""
    from dataclasses import replace

    roughness_field(rms_m, seed)  # checks the value
    return replace(net, roughness_m=float(rms_m), roughness_seed=int(seed),
                   info={**net.info, "roughness_m": float(rms_m), "roughness_seed": int(seed)})


def segment_distances(P: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Distances from 2-D points to 2-D segments.

    Parameters
    ----------
    P : ndarray (k, 2)
        Points (m, map frame, horizontal).
    A, B : ndarray (m, 2)
        End points of the segments (m, same frame); a zero-length segment is its point.

    Returns
    -------
    ndarray (k, m)
        ``|P_i − Q_ij|`` (m), ``Q_ij = A_j + t (B_j − A_j)`` with ``t`` the projection of ``P_i``
        clipped to [0, 1] (the nearest point of segment ``j``).
    """
    d = B - A
    L2 = np.maximum((d * d).sum(1), 1e-12)
    t = np.clip(((P[:, None, :] - A[None]) * d[None]).sum(2) / L2[None], 0.0, 1.0)
    Q = A[None] + t[..., None] * d[None]
    return np.sqrt(((P[:, None, :] - Q) ** 2).sum(2))


def _inside_other(P: np.ndarray, own: np.ndarray, net: DriftNetwork, eps: float) -> np.ndarray:
    """True where a boundary point of capsule ``own[i]`` lies strictly inside another capsule."""
    A, B = net.nodes[net.edges[:, 0]], net.nodes[net.edges[:, 1]]
    out = np.zeros(len(P), bool)
    for s in range(0, len(P), 4096):
        D = segment_distances(P[s:s + 4096], A, B) - 0.5 * net.widths[None]
        D[np.arange(D.shape[0]), own[s:s + 4096]] = np.inf
        out[s:s + 4096] = (D < -eps).any(1)
    return out


def _roof(net: DriftNetwork, xy: np.ndarray) -> np.ndarray:
    """Roof height (m) over each xy: the height of the nearest node."""
    d2 = ((xy[:, None, :] - net.nodes[None]) ** 2).sum(2)
    return net.node_heights[np.argmin(d2, axis=1)]


def wall_outline(net: DriftNetwork, step: float, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """The noise-free wall outline of a network in plan: the boundary of the union of its capsules.

    Each drift is the capsule of radius ``width / 2`` around its centreline; its two sides and two
    half-circle ends are sampled, and the samples strictly inside another capsule (by more than
    ``eps``) are dropped, so the junctions are open.

    Parameters
    ----------
    net : DriftNetwork
    step : float
        Sample spacing (m) along the sides and the end arcs.
    eps : float
        Tolerance (m) of "strictly inside another capsule".

    Returns
    -------
    (ndarray (k, 2), ndarray (k, 2))
        Boundary points (m, map frame, horizontal) and their unit outward normals.
    """
    pts, nrm, own = [], [], []
    for e, (i, j) in enumerate(net.edges):
        a, b, r = net.nodes[i], net.nodes[j], 0.5 * net.widths[e]
        L = float(np.linalg.norm(b - a))
        u = (b - a) / max(L, 1e-12)
        n = np.array([-u[1], u[0]])
        t = np.linspace(0.0, L, max(int(np.ceil(L / step)), 1) + 1)
        for sgn in (1.0, -1.0):
            pts.append(a + t[:, None] * u + sgn * r * n)
            nrm.append(np.repeat((sgn * n)[None], len(t), 0))
        k = max(int(np.ceil(np.pi * r / step)), 2)
        for c, base in ((a, -u), (b, u)):
            phi = np.linspace(-0.5 * np.pi, 0.5 * np.pi, k + 1)
            dirs = np.cos(phi)[:, None] * base + np.sin(phi)[:, None] * np.array([-base[1], base[0]])
            pts.append(c + r * dirs)
            nrm.append(dirs)
        own.extend([e] * (2 * len(t) + 2 * (k + 1)))
    P, N, own = np.concatenate(pts), np.concatenate(nrm), np.asarray(own, np.int64)
    keep = ~_inside_other(P, own, net, eps)
    return P[keep], N[keep]


def _floor_grid(net: DriftNetwork, step: float) -> np.ndarray:
    """Points of the global lattice ``step * (i, j)`` inside the union of capsules, each once."""
    A, B = net.nodes[net.edges[:, 0]], net.nodes[net.edges[:, 1]]
    r = 0.5 * net.widths
    lo = np.minimum(A, B) - r[:, None]
    hi = np.maximum(A, B) + r[:, None]
    out = []
    for e in range(len(A)):
        i0, j0 = np.floor(lo[e] / step).astype(np.int64)
        i1, j1 = np.ceil(hi[e] / step).astype(np.int64)
        G = np.stack(np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij"), -1).reshape(-1, 2)
        X = G * step
        keep = segment_distances(X, A[e:e + 1], B[e:e + 1])[:, 0] < r[e]
        earlier = np.flatnonzero(np.all(lo[:e] <= hi[e], axis=1) & np.all(hi[:e] >= lo[e], axis=1))
        if earlier.size:
            X2 = X[keep]
            dup = (segment_distances(X2, A[earlier], B[earlier]) < r[earlier][None]).any(1)
            keep[np.flatnonzero(keep)[dup]] = False
        out.append(X[keep])
    return np.concatenate(out)


def network_cloud(net: DriftNetwork, spacing_m: float = 0.2, noise_m: float = 0.02, seed: int = 0) -> NetworkCloud:
    """Sample floor, walls and roof of a drift network as a point cloud.

    Parameters
    ----------
    net : DriftNetwork
    spacing_m : float
        Sample spacing (m) along walls, up walls and on the floor/roof grid.
    noise_m : float
        Standard deviation (m) of the isotropic Gaussian noise added to every point.
    seed : int
        Seed of the noise (``np.random.default_rng``).

    Returns
    -------
    NetworkCloud
        Points in the map frame (m, floor at z = 0) and labels (0 floor, 1 wall, 2 roof).
    """
    if not (np.isfinite(spacing_m) and spacing_m > 0.0 and np.isfinite(noise_m) and noise_m >= 0.0):
        raise InputError("spacing_m must be > 0 and noise_m >= 0")
    rng = np.random.default_rng(seed)
    W, WN = wall_outline(net, spacing_m, 0.02)
    hw = _roof(net, W)
    nz = np.floor(hw / spacing_m).astype(np.int64) + 1
    wall_xy = np.repeat(W, nz, axis=0)
    wall_z = np.concatenate([np.arange(k) * spacing_m for k in nz])
    F = _floor_grid(net, spacing_m)
    hr = _roof(net, F)
    P = np.concatenate([np.c_[F, np.zeros(len(F))], np.c_[wall_xy, wall_z], np.c_[F, hr]])
    labels = np.concatenate([np.zeros(len(F), np.int64), np.ones(len(wall_z), np.int64),
                             np.full(len(F), 2, np.int64)])
    if net.roughness_m > 0.0:
        # the rock: each sample moves along its outward normal (the surface NetworkWorld casts at)
        N = np.concatenate([np.tile([0.0, 0.0, -1.0], (len(F), 1)),
                            np.c_[np.repeat(WN, nz, axis=0), np.zeros(len(wall_z))],
                            np.tile([0.0, 0.0, 1.0], (len(F), 1))])
        # on the rock q = p + h(q) n (the implicit surface the ray caster meets): 4 fixed-point steps
        f = roughness_field(net.roughness_m, net.roughness_seed)
        Q = P
        for _ in range(4):
            Q = P + f(Q)[:, None] * N
        P = Q
    P = P + rng.normal(0.0, noise_m, P.shape) if noise_m > 0 else P
    return NetworkCloud(np.ascontiguousarray(P, dtype=np.float64), labels)


def max_clearance_point(W: np.ndarray, guess: np.ndarray, radius: float, net: DriftNetwork) -> np.ndarray:
    """Centre of the largest empty circle near a point: the free-space point farthest from the walls.

    Grid search over the square of half-size ``radius`` around ``guess`` (0.1 m steps), then twice
    refined around the best point (0.01 m, then 0.001 m steps), restricted to the free space (the
    union of the capsules) of ``net``.

    Parameters
    ----------
    W : ndarray (k, 2)
        Wall points (m, map frame, horizontal), e.g. :func:`wall_outline`.
    guess : ndarray (2,)
        Start of the search (m, same frame).
    radius : float
        Half-size (m) of the first search square.
    net : DriftNetwork

    Returns
    -------
    ndarray (2,)
        The point (m) maximising the clearance ``min_i |p − W_i|``.
    """
    from scipy.spatial import cKDTree

    A, B = net.nodes[net.edges[:, 0]], net.nodes[net.edges[:, 1]]

    tree = cKDTree(W)
    c, half, step = guess.astype(np.float64), radius, 0.1
    for _ in range(3):
        g = np.arange(-half, half + 0.5 * step, step)
        Q = c + np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
        d, _ = tree.query(Q)
        d = np.where((segment_distances(Q, A, B) < 0.5 * net.widths[None]).any(1), d, -1.0)
        c = Q[int(np.argmax(d))]
        half, step = 2.0 * step, step / 10.0
    return c


def junction_truth(net: DriftNetwork, radius_m: float = 4.0) -> np.ndarray:
    """Exact invariant points (k, 2) of the junctions (nodes of degree >= 3), in node order.

    The invariant point is the centre of the largest empty circle (maximum clearance to the walls),
    computed on the noise-free wall outline sampled every 2 cm, searched over the free space (the
    union of capsules) within ``radius_m`` of the node (see ``docs/intersections.md``).
    """
    W, _ = wall_outline(net, 0.02, 1e-6)
    return np.array([max_clearance_point(W, net.nodes[i], radius_m, net) for i in net.junctions()]).reshape(-1, 2)


def intersections_network(width_m: float = 4.5, heights_m=(3.0, 3.6, 4.2), default_height_m: float = 3.6,
                          leg_m: float = 28.0, spacing_m: float = 60.0) -> DriftNetwork:
    """Issue-18 test network: three alike 4-way crossings X1, X2, X3, a T and a Y (40 degree branch).

    X1, X2, X3 lie on one main drift along +x (``spacing_m`` apart), each crossed at right angles by a
    drift with two dead-end legs of ``leg_m``; the main drift ends in the T (through drift along y);
    X1's south leg continues to the Y, where a branch leaves the southbound drift at 40 degrees.
    The crossings are identical in plan and differ only in roof height (``heights_m``, m); every other
    region has ``default_height_m``. Legs are longer than the descriptor radius so dead ends do not
    enter a junction's descriptor.
    """
    s, L = spacing_m, leg_m
    nodes = [(0, 0), (s, 0), (2 * s, 0), (3 * s, 0), (0, -50.0),            # X1 X2 X3 T Y
             (-L, 0), (0, L), (s, L), (s, -L), (2 * s, L), (2 * s, -L),       # dead ends
             (3 * s, L), (3 * s, -L), (0, -50.0 - L)]
    a = np.deg2rad(40.0)
    nodes.append((L * np.sin(a), -50.0 - L * np.cos(a)))
    edges = [(5, 0), (0, 1), (1, 2), (2, 3), (0, 6), (0, 4), (1, 7), (1, 8), (2, 9), (2, 10), (3, 11), (3, 12),
             (4, 13), (4, 14)]
    h = np.full(len(nodes), float(default_height_m))
    h[:3] = heights_m
    names = ("X1", "X2", "X3", "T", "Y") + ("",) * (len(nodes) - 5)
    return DriftNetwork(np.array(nodes, np.float64), np.array(edges, np.int64), np.full(len(edges), float(width_m)),
                        h, names, {"kind": "intersections_network", "width_m": width_m, "heights_m": list(heights_m)})


def _read_edgelist(path) -> tuple[np.ndarray, np.ndarray, list]:
    p = Path(path)
    try:
        rows = list(csv.DictReader(p.open(newline="")))
    except OSError as exc:
        raise FileFormatError(p, f"cannot read the edge list ({exc})") from exc
    try:
        E = [(int(r["FROM"]), int(r["TO"]), float(r["LENGTH"])) for r in rows]
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(p, "expected columns FROM,TO,LENGTH with integer ids and lengths in m") from exc
    if not E or any(not np.isfinite(x[2]) or x[2] <= 0 for x in E):
        raise FileFormatError(p, "empty edge list or a non-positive length")
    ids = sorted({x[0] for x in E} | {x[1] for x in E})
    index = {v: k for k, v in enumerate(ids)}
    edges = np.array([(index[a], index[b]) for a, b, _ in E], np.int64)
    return edges, np.array([x[2] for x in E]), ids


def _stress_layout(edges: np.ndarray, lengths: np.ndarray, n: int, iters: int = 400) -> np.ndarray:
    """2-D node positions whose distances match graph shortest-path distances (stress majorization)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path

    A = coo_matrix((np.r_[lengths, lengths], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                   shape=(n, n)).tocsr()
    D = shortest_path(A, directed=False)
    if not np.all(np.isfinite(D)):
        raise InputError("the edge list is not one connected network")
    J = np.eye(n) - 1.0 / n                                   # classical MDS start (Torgerson)
    w, V = np.linalg.eigh(-0.5 * J @ (D ** 2) @ J)
    X = V[:, -2:] * np.sqrt(np.maximum(w[-2:], 0.0))
    Wt = np.where(D > 0, 1.0 / np.maximum(D, 1e-9) ** 2, 0.0)  # SMACOF with weights d^-2
    Lw = -Wt
    Lw[np.diag_indices(n)] = Wt.sum(1)
    Lp = np.linalg.pinv(Lw)
    for _ in range(iters):
        dist = np.sqrt(((X[:, None] - X[None]) ** 2).sum(2))
        Bm = -np.where(dist > 1e-12, Wt * D / np.maximum(dist, 1e-12), 0.0)
        Bm[np.diag_indices(n)] = -Bm.sum(1)
        X = Lp @ (Bm @ X)
    return X - X.mean(0)


def niosh_network(edgelist_csv, width_m: float = 2.9, height_m: float = 2.6) -> DriftNetwork:
    """A drift network in the topology of a DARPA SubT NIOSH course (``ex_edgelist.csv``/``sr_edgelist.csv``).

    The edge list gives node ids and drift lengths, **not coordinates**. Positions are one plausible
    embedding: classical MDS of the all-pairs shortest-path lengths, refined by stress majorization
    (SMACOF, weights d^-2); every drift is then the straight segment between its end nodes. The real
    drifts bend, so straight-segment lengths differ from the listed lengths and two drifts may cross
    where the real ones do not (``info["crossings"]`` counts such pairs, ``info["length_rel_err"]`` the
    length error). Width and height default to the entry dimensions read off the course fiducials
    (wall AprilTags at y = +1.45 / -1.43 m, roof prism at z = 2.61 m in the EX frame).
    """
    edges, lengths, ids = _read_edgelist(edgelist_csv)
    X = _stress_layout(edges, lengths, len(ids))
    seg = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
    crossings = 0
    for i in range(len(edges)):
        for j in range(i + 1, len(edges)):
            if set(edges[i]) & set(edges[j]):
                continue
            p, r = X[edges[i, 0]], X[edges[i, 1]] - X[edges[i, 0]]
            q, s = X[edges[j, 0]], X[edges[j, 1]] - X[edges[j, 0]]
            den = r[0] * s[1] - r[1] * s[0]
            if abs(den) > 1e-12:
                t = ((q - p)[0] * s[1] - (q - p)[1] * s[0]) / den
                u = ((q - p)[0] * r[1] - (q - p)[1] * r[0]) / den
                crossings += int(0.0 < t < 1.0 and 0.0 < u < 1.0)
    info = {"kind": "niosh_network", "source": str(edgelist_csv), "node_ids": ids, "width_m": width_m,
            "height_m": height_m, "crossings": crossings,
            "length_rel_err": {"median": float(np.median(np.abs(seg / lengths - 1.0))),
                               "max": float(np.max(np.abs(seg / lengths - 1.0)))}}
    return DriftNetwork(X, edges, np.full(len(edges), float(width_m)), np.full(len(ids), float(height_m)),
                        tuple(str(i) for i in ids), info)
