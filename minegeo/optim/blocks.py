"""The normal equations of the optimiser: sparse by d×d blocks (block Cholesky) or general (sparse LU).

One Levenberg–Marquardt iteration solves ``(H + λD) δ = −g`` with ``H = Σ Jᵀ W Ω J`` and
``g = Σ Jᵀ W Ω r`` over the free variables [Nocedal2006 Sec. 10.3].

* :class:`BlockSystem`: every variable has the same tangent dimension ``d`` (6 for SE(3) poses,
  3 for SE(2) poses, 15 for a navigation state (pose, velocity, IMU biases)). The free variables
  are put in a fill-reducing order once (minimum degree on the factor graph), the pattern of the
  Cholesky factor is computed once (elimination tree) [Davis2006 Thm. 4.2], each factor's blocks
  are accumulated by a serial Numba kernel straight into that pattern
  (:func:`minegeo.optim._kernels.accumulate_normal_equations`, ``accumulate_unary``), and each
  damping trial is a left-looking block Cholesky and two block triangular solves
  (:func:`~minegeo.optim._kernels.block_cholesky`); a damped matrix that is not positive definite
  gives no step (the caller raises the damping).
* :class:`SparseSystem`: variables of different dimensions (poses and plane landmarks): the same
  normal equations as a ``scipy.sparse`` matrix from per-factor blocks, solved by a sparse LU
  factorisation, which does not need ``H + λD`` to be positive definite.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from minegeo.optim import _kernels as K

__all__ = ["SINGULAR_PIVOT", "BlockSystem", "SingularSystemError", "SparseSystem", "elimination_order",
           "symbolic_cholesky"]

#: a pivot of the undamped ``H`` below this fraction of its diagonal entry: ``H`` is singular there
SINGULAR_PIVOT = 1e-12


class SingularSystemError(ArithmeticError):
    """The (damped) normal equations are exactly singular: a variable no factor constrains."""


def elimination_order(nf: int, pairs: np.ndarray) -> np.ndarray:
    """A fill-reducing elimination order of the free variables (minimum degree on ``AᵀA + A``).

    The order comes from SuperLU's multiple-minimum-degree ordering (``MMD_AT_PLUS_A``) applied to
    the variable-level pattern of ``H`` (one scalar per d×d block, made diagonally dominant so that
    SuperLU keeps the diagonal pivots); ``order[k]`` is the free variable eliminated k-th. The same
    order serves every iteration (the pattern of ``H`` does not change).
    """
    if nf <= 1 or pairs.shape[0] == 0:
        return np.arange(nf, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    deg = np.bincount(np.r_[a, b], minlength=nf).astype(np.float64)
    P = sp.coo_matrix((np.r_[np.full(a.size, -1.0), np.full(a.size, -1.0), deg + 1.0],
                       (np.r_[a, b, np.arange(nf)], np.r_[b, a, np.arange(nf)])), shape=(nf, nf)).tocsc()
    lu = spla.splu(P, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.argsort(lu.perm_c).astype(np.int64)


def symbolic_cholesky(nb: int, lower: np.ndarray):
    """Column patterns of the block Cholesky factor: ``(Lp, Li)`` from the lower block pattern of ``H``.

    ``lower`` holds ``(row, col)`` block pairs with ``row > col``. The pattern of column j is its own
    rows in ``H`` united with the patterns of its children in the elimination tree (the columns whose
    first sub-diagonal row is j) [Davis2006 Thm. 4.2]; the diagonal block comes first.
    """
    by_col = [[] for _ in range(nb)]
    for r_, c_ in lower.tolist():
        by_col[c_].append(r_)
    children = [[] for _ in range(nb)]
    cols = []
    for j in range(nb):
        parts = [np.asarray(by_col[j], dtype=np.int64)] + [cols[c][cols[c] > j] for c in children[j]]
        rows = np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)
        rows = rows[rows > j]
        cols.append(rows)
        if rows.size:
            children[int(rows[0])].append(j)
    Lp = np.zeros(nb + 1, dtype=np.int64)
    Lp[1:] = np.cumsum([c.size + 1 for c in cols])
    Li = np.concatenate([np.r_[j, c] for j, c in enumerate(cols)]).astype(np.int64) if nb else np.zeros(0, np.int64)
    return Lp, Li


class BlockSystem:
    """Normal equations over ``n`` variables of tangent dimension ``d``, as d×d blocks in the pattern
    of their Cholesky factor.

    Built once per optimisation from the variable pairs of every binary factor (ordering and
    symbolic factorisation). Per iteration: :meth:`reset`, then :meth:`add_binary` /
    :meth:`add_unary` per factor group; per damping trial: :meth:`solve`. Variable ``v``'s step is
    ``δ[col[v] : col[v] + d]`` (``col = -1`` for a held variable).

    Parameters
    ----------
    d : int
        Tangent dimension of every variable.
    n : int
        Number of variables.
    free : ndarray (n,) of bool
        The variables that move (the others are held: their blocks are skipped).
    pairs : ndarray (m, 2) of int
        Variable pairs of the binary factors (the pattern of ``H``).
    """

    def __init__(self, d: int, n: int, free: np.ndarray, pairs: np.ndarray):
        self.d = int(d)
        nf = int(free.sum())
        self.nf = nf
        fidx = np.full(n, -1, dtype=np.int64)
        fidx[free] = np.arange(nf)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        fe = fidx[pairs]
        both = (fe >= 0).all(axis=1) & (fe[:, 0] != fe[:, 1])
        order = elimination_order(nf, fe[both])
        rank = np.empty(nf, dtype=np.int64)
        rank[order] = np.arange(nf)
        # block index of each variable, -1 held (every variable held: no block at all)
        self.blk = np.where(fidx >= 0, rank[np.maximum(fidx, 0)], -1) if nf else np.full(n, -1, dtype=np.int64)
        bcol = self.blk[pairs]
        self.Lp, self.Li = symbolic_cholesky(nf, np.c_[np.maximum(bcol[:, 0], bcol[:, 1]),
                                                       np.minimum(bcol[:, 0], bcol[:, 1])][both])
        self.col = np.ascontiguousarray(np.where(self.blk >= 0, self.blk * self.d, -1))
        self.block_vertex = np.empty(nf, dtype=np.int64)  # variable index of each block column
        self.block_vertex[self.blk[self.blk >= 0]] = np.flatnonzero(self.blk >= 0)
        self.n_cols = nf * self.d
        self.Hx = self.g = None
        self.failed_block = -1

    def binary_slots(self, pairs: np.ndarray) -> tuple:
        """Where the blocks of binary factors on ``pairs`` (m, 2) go: ``(bcol, slot_ii, slot_jj,
        slot_ij, ij_lower)`` for :meth:`add_binary` (the pairs must be among those of the pattern)."""
        nf = self.nf
        bcol = np.ascontiguousarray(self.blk[np.asarray(pairs, dtype=np.int64).reshape(-1, 2)])
        bi, bj = bcol[:, 0], bcol[:, 1]
        both = (bi >= 0) & (bj >= 0) & (bi != bj)
        lo_r, lo_c = np.maximum(bi, bj), np.minimum(bi, bj)
        key = np.repeat(np.arange(nf, dtype=np.int64), np.diff(self.Lp)) * max(nf, 1) + self.Li
        slot_ii = np.where(bi >= 0, self.Lp[np.maximum(bi, 0)], -1)
        slot_jj = np.where(bj >= 0, self.Lp[np.maximum(bj, 0)], -1)
        slot_ij = np.where(both, np.searchsorted(key, lo_c * max(nf, 1) + lo_r), -1)
        return bcol, slot_ii, slot_jj, slot_ij, (bi > bj).astype(np.int64)

    def unary_blocks(self, var: np.ndarray) -> np.ndarray:
        """Block index of each variable in ``var`` (-1 held), for :meth:`add_unary`."""
        return np.ascontiguousarray(self.blk[np.asarray(var, dtype=np.int64)])

    def reset(self) -> None:
        """Zero ``H`` and ``g`` before a linearisation."""
        self.Hx = np.zeros((self.Li.size, self.d, self.d))
        self.g = np.zeros(self.n_cols)

    def add_binary(self, slots: tuple, r, Ji, Jj, WO) -> None:
        """Accumulate binary factors: ``r`` (m, k), ``Ji``, ``Jj`` (m, k, d), ``WO = w Ω`` (m, k, k)."""
        bcol, slot_ii, slot_jj, slot_ij, ij_lower = slots
        K.accumulate_normal_equations(r, Ji, Jj, WO, bcol, slot_ii, slot_jj, slot_ij, ij_lower, self.Hx, self.g)

    def add_unary(self, bcol, r, J, WO) -> None:
        """Accumulate unary factors: ``r`` (m, k), ``J`` (m, k, d), ``WO`` (m, k, k)."""
        K.accumulate_unary(r, J, WO, bcol, self.Lp, self.Hx, self.g)

    def cholesky(self, lam: float = 0.0, relative: bool = False, tiny: float = SINGULAR_PIVOT):
        """The block Cholesky factor ``L`` (values ``Lx`` (nnz, d, d) in the pattern ``(Lp, Li)``,
        elimination order) of ``H + λ D`` last assembled, or None if that matrix is not positive
        definite (a pivot ``≤ tiny ·`` its diagonal entry; :attr:`failed_block` is then the block
        column). ``D = diag(H)`` when ``relative``, else ``I``."""
        Lx = np.empty_like(self.Hx)
        self.failed_block = int(K.block_cholesky(self.Lp, self.Li, self.Hx, lam, relative, Lx, tiny))
        return None if self.failed_block >= 0 else Lx

    def solve_factored(self, Lx: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``x`` with ``L Lᵀ x = b`` for a factor ``Lx`` of :meth:`cholesky` (``b`` and ``x`` in the
        elimination order of the columns)."""
        return K.block_cholesky_solve(self.Lp, self.Li, Lx, np.ascontiguousarray(b, dtype=np.float64))

    def solve(self, lam: float, relative: bool, tiny: float = 0.0):
        """``δ`` with ``(H + λ D) δ = -g`` (elimination order), or None if not positive definite
        (see :meth:`cholesky`)."""
        Lx = self.cholesky(lam, relative, tiny)
        if Lx is None:
            return None
        return K.block_cholesky_solve(self.Lp, self.Li, Lx, -self.g)

    def gauss_newton_decrease(self):
        """``(½ gᵀH⁻¹g, -1)`` of the undamped normal equations last assembled (the decrease of the
        cost the Gauss–Newton model predicts), or ``(nan, v)`` when ``H`` is singular
        (:data:`SINGULAR_PIVOT`) at variable index ``v``."""
        delta = self.solve(0.0, False, SINGULAR_PIVOT)
        if delta is None:
            return float("nan"), int(self.block_vertex[self.failed_block])
        return -0.5 * float(self.g @ delta), -1


#: SuperLU options for the symmetric positive definite ``H + λD``: a fill-reducing minimum-degree
#: ordering of ``Aᵀ + A`` and pivots on the diagonal (no row interchanges: the LU of an SPD matrix is
#: stable without them), which keeps the symmetric structure; on the 1293-keyframe graph of a 2 km
#: drive with 8 floor planes it factors in 0.02 s with 0.27 M non-zeros, against 0.7 s and 6.2 M for
#: SuperLU's defaults (column ordering for an unsymmetric matrix, partial pivoting).
_SPD_LU = {"permc_spec": "MMD_AT_PLUS_A", "diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}


class SparseSystem:
    """Normal equations over columns of any layout, as a ``scipy.sparse`` matrix solved by sparse LU.

    Per iteration: :meth:`reset`, then :meth:`add` per factor group (each slot of a factor brings
    its Jacobian and the first column of its variable, -1 when held); per damping trial: :meth:`solve`.
    """

    def __init__(self, n_cols: int, singular_message: str):
        self.n_cols = int(n_cols)
        self.singular_message = singular_message
        self.g = np.zeros(self.n_cols)
        self._rows, self._cols, self._vals = [], [], []
        self.H = None

    def reset(self) -> None:
        self.g = np.zeros(self.n_cols)
        self._rows, self._cols, self._vals = [], [], []
        self.H = None

    def add(self, r, WO, slots) -> None:
        """Add factors with residuals ``r`` (m, k), ``WO = w Ω`` (m, k, k) and ``slots``, a sequence of
        ``(cols, J)``: ``cols`` (m,) the first column of the slot's variable (-1 held), ``J`` (m, k, d_slot).

        Blocks ``(a, b) = J_aᵀ WΩ J_b`` for every pair of free slots, ``g_a += J_aᵀ WΩ r``.
        """
        for cols_a, J_a in slots:
            keep_a = cols_a >= 0
            ar_a = np.arange(J_a.shape[2])
            JtW = np.einsum("eji,ejk->eik", J_a, WO)  # J_aᵀ W Ω
            np.add.at(self.g, (cols_a[keep_a, None] + ar_a[None, :]), np.einsum("eik,ek->ei", JtW, r)[keep_a])
            for cols_b, J_b in slots:
                keep = keep_a & (cols_b >= 0)
                ar_b = np.arange(J_b.shape[2])
                blk = np.einsum("eik,ekj->eij", JtW[keep], J_b[keep])
                self._rows.append(np.broadcast_to((cols_a[keep][:, None] + ar_a)[:, :, None], blk.shape).ravel())
                self._cols.append(np.broadcast_to((cols_b[keep][:, None] + ar_b)[:, None, :], blk.shape).ravel())
                self._vals.append(blk.ravel())

    def matrix(self):
        """``H`` (CSC) of the factors added since :meth:`reset`."""
        if self.H is None:
            self.H = sp.coo_matrix((np.concatenate(self._vals), (np.concatenate(self._rows),
                                                                 np.concatenate(self._cols))),
                                   shape=(self.n_cols, self.n_cols)).tocsc()
        return self.H

    def solve(self, lam: float, relative: bool):
        """``δ`` with ``(H + λ D) δ = -g``, ``D = diag(max(diag H, 1e-12))`` when ``relative`` else ``I``.

        Raises
        ------
        SingularSystemError
            The damped matrix is exactly singular (a variable no factor reaches).
        """
        H = self.matrix()
        diag = H.diagonal()
        D = np.maximum(diag, 1e-12) if relative else np.ones(diag.size)
        try:
            return spla.splu((H + sp.diags(lam * D)).tocsc(), **_SPD_LU).solve(-self.g)
        except RuntimeError as exc:  # exactly singular
            raise SingularSystemError(self.singular_message) from exc

    def gauss_newton_decrease(self):
        """Not computed by the LU path: ``(None, -1)``."""
        return None, -1
