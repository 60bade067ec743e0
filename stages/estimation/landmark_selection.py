"""Stage one of focused inference: choose the landmarks that matter (Beinhofer et al. MI, leverage, uniform, random).

Conventions: planar poses are ``(x, y, θ)``; 3-D poses are gtsam ``Pose3`` tangents
``(ω_x, ω_y, ω_z, t_x, t_y, t_z)`` (rotation first). Mu et al. Alg. 2 (collision risk) is in
:mod:`stages.estimation.collision`; all strategies return a :class:`LandmarkSelection`.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, TypeVar

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from stages.estimation.blas import blas_single
from stages.estimation.linear_system import SparseMatrix

FloatArray = npt.NDArray[np.float64]
Measure = Literal["logdet", "trace", "max_eig"]
SelectionStatus = Literal["ok", "budget_zero", "budget_exceeds_landmarks", "no_landmarks"]
T = TypeVar("T")


# ------------------------------------------------------------------ result
@dataclass
class LandmarkSelection:
    """Result of a landmark selection."""

    picks: list[int]
    """Landmark indices in the order picked."""
    scores: list[float]
    """Score at each pick (strategy-specific; see the function)."""
    status: SelectionStatus = "ok"
    extra: dict[str, FloatArray] = field(default_factory=dict)


def _status(budget: int, n: int) -> SelectionStatus | None:
    if n == 0:
        return "no_landmarks"
    if budget <= 0:
        return "budget_zero"
    if budget > n:
        return "budget_exceeds_landmarks"
    return None


# ------------------------------------------------------------------ sparse trajectory information
# The trajectory information ``Λ₀`` (odometry chain + priors) and every ``Λ_l`` (a block on the poses that see
# landmark l) are sparse; the dense strategies below used to invert the whole n×n matrix (n = 3 × poses) once per
# leverage draw and to carry a dense n×n covariance through the MI greedy. Here they factorise the sparse matrix
# (SuperLU with a symmetric ordering) and solve only for the columns they read: same numbers, ~10-50x faster on
# the sample (n = 1,707).
def _as_sparse(info: FloatArray | SparseMatrix) -> sp.csc_matrix:
    return sp.csc_matrix(info) if isinstance(info, np.ndarray) else info.tocsc()


def _scatter(n: int, parts: Sequence[tuple[npt.NDArray[np.int64], FloatArray]]) -> sp.csc_matrix:
    """``Σ_l E_l Λ_l E_lᵀ`` as a sparse n×n matrix (each ``Λ_l`` placed on its columns)."""
    rows, cols, data = [], [], []
    for c, B in parts:
        c = np.asarray(c, dtype=np.int64)
        if len(c) == 0:
            continue
        rows.append(np.repeat(c, len(c)))
        cols.append(np.tile(c, len(c)))
        data.append(np.asarray(B, dtype=float).ravel())
    if not rows:
        return sp.csc_matrix((n, n))
    return sp.csc_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


class _Factor:
    """Sparse LU of a symmetric positive definite matrix (SuperLU, symmetric mode): log-determinant and solves."""

    def __init__(self, A: SparseMatrix) -> None:
        self.n = A.shape[0]
        self.A = A.tocsc()
        self.lu = spla.splu(self.A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def logdet(self) -> float:
        return float(np.sum(np.log(np.abs(self.lu.U.diagonal()))))


# ------------------------------------------------------------------ selected inversion on BFS level blocks
LEVEL_BLOCK_MIN = 96
"""Consecutive BFS levels are merged into blocks of at least this many variables (fewer, larger dense products)."""


def _bfs_levels(graph: sp.csr_matrix) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Per vertex, ``(component, level)``: BFS depth from a pseudo-peripheral vertex of its component.

    Edges join only vertices of the same or of adjacent levels (BFS property), so a matrix with this
    pattern is block tridiagonal when its rows are ordered by level (Cuthill-McKee level structure).
    """
    import scipy.sparse.csgraph as csgraph

    n = graph.shape[0]
    _, comp = csgraph.connected_components(graph, directed=False)
    level = np.zeros(n, dtype=np.int64)
    for c in range(int(comp.max()) + 1 if n else 0):
        members = np.flatnonzero(comp == c)
        start, depth = int(members[0]), None
        for _ in range(3):  # George-Liu: jump to a vertex of the last level until the depth stops growing
            d = csgraph.shortest_path(graph, indices=start, unweighted=True, directed=False)[members]
            ecc = int(d.max())
            if depth is not None and ecc <= depth:
                break
            depth, dist = ecc, d
            last = members[d == ecc]
            deg = np.diff(graph.indptr)[last]
            start = int(last[np.argmin(deg)])
        level[members] = dist.astype(np.int64)
    return comp.astype(np.int64), level


class _LevelBlocks:
    """A sparsity pattern in block-tridiagonal form, and the selected inverse of SPD matrices with that pattern.

    The variables are ordered by (connected component, BFS level) and consecutive levels merged into blocks of
    at least ``min_block`` variables. Any SPD matrix whose pattern lies inside the given one is block tridiagonal
    in that order; the forward block Cholesky recursion gives its log-determinant and the backward (RTS /
    Takahashi) recursion the blocks ``Σ_kk`` and ``Σ_{k+1,k}`` of its inverse, which hold ``Σ[i, j]`` for every
    nonzero ``(i, j)`` of the pattern. Cost ``O(Σ_k b_k³)`` instead of ``O(n³)``; no ``n × n`` array.
    """

    def __init__(self, pattern: SparseMatrix, min_block: int | None = None) -> None:
        min_block = LEVEL_BLOCK_MIN if min_block is None else min_block
        g = sp.csr_matrix(pattern, copy=True)
        g.data = np.ones_like(g.data)
        g = (g + g.T).tocsr()
        self.n = n = g.shape[0]
        comp, level = _bfs_levels(g)
        order = np.lexsort((np.arange(n), level, comp))
        key = comp[order] * (n + 1) + level[order]
        lev_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        starts = [0]
        for s in lev_start[1:]:  # merge consecutive levels (of any component) into blocks of >= min_block
            if s - starts[-1] >= min_block:
                starts.append(int(s))
        self.perm = order.astype(np.int64)
        self.iperm = np.empty(n, dtype=np.int64)
        self.iperm[self.perm] = np.arange(n)
        self.start = np.array([*starts, n], dtype=np.int64)
        self.size = np.diff(self.start)
        self.K = len(self.size)
        self.block_of = np.repeat(np.arange(self.K), self.size)[self.iperm]  # block of each original index
        self.local = np.arange(n) - self.start[np.repeat(np.arange(self.K), self.size)]
        self.local = self.local[self.iperm]
        sz = self.size
        self.off_d = np.r_[0, np.cumsum(sz * sz)].astype(np.int64)
        self.off_c = np.r_[0, np.cumsum(sz[1:] * sz[:-1])].astype(np.int64)  # C_k = A[block k+1, block k]

    STORE_CHUNK = 1 << 18
    """Entries of a matrix placed in the flat store at once by :meth:`store`."""

    def cost(self) -> float:
        """Flops of one selected inversion, roughly (``Σ_k b_k³`` times a small constant)."""
        return float(np.sum(self.size.astype(float) ** 3)) * 6.0

    def _index(self, rows: npt.NDArray[np.int64], cols: npt.NDArray[np.int64]):
        """Flat positions of entries ``(i, j)``: ``(diag, upper, pos)``; ``pos`` indexes the diagonal or the lower
        store (``upper``: the entry is ``(j, i)`` of the lower store)."""
        bi, bj = self.block_of[rows], self.block_of[cols]
        li, lj = self.local[rows], self.local[cols]
        diag = bi == bj
        lower = bi == bj + 1
        upper = bj == bi + 1
        if not np.all(diag | lower | upper):
            raise ValueError("matrix pattern outside the level-block structure")
        pos = np.empty(len(rows), dtype=np.int64)
        pos[diag] = self.off_d[bi[diag]] + li[diag] * self.size[bi[diag]] + lj[diag]
        k = bj[lower]
        pos[lower] = self.off_c[k] + li[lower] * self.size[k] + lj[lower]
        k = bi[upper]
        pos[upper] = self.off_c[k] + lj[upper] * self.size[k] + li[upper]
        return diag, upper, pos

    def store(self, A: SparseMatrix) -> tuple[FloatArray, FloatArray]:
        """``A``'s diagonal blocks and lower neighbour blocks, flat (the input of :meth:`factor`)."""
        coo = sp.coo_matrix(A)
        coo.sum_duplicates()
        D = np.zeros(int(self.off_d[-1]))
        C = np.zeros(int(self.off_c[-1]))
        # in pieces: _index makes a dozen arrays the size of its input (A's 3.5 million entries on a 4-minute
        # corridor run with laps: ~28 MB each)
        for a in range(0, coo.nnz, self.STORE_CHUNK):
            b = a + self.STORE_CHUNK
            diag, upper, pos = self._index(coo.row[a:b].astype(np.int64), coo.col[a:b].astype(np.int64))
            data = coo.data[a:b]
            D[pos[diag]] = data[diag]
            low = ~diag & ~upper
            C[pos[low]] = data[low]
        return D, C

    def add(self, D: FloatArray, C: FloatArray, cols: npt.NDArray[np.int64], block: FloatArray) -> None:
        """``A[cols, cols] += block`` in the flat store (in place)."""
        rows = np.repeat(cols, len(cols))
        cc = np.tile(cols, len(cols))
        diag, upper, pos = self._index(rows, cc)
        vals = np.asarray(block, dtype=float).ravel()
        np.add.at(D, pos[diag], vals[diag])
        low = ~diag & ~upper
        np.add.at(C, pos[low], vals[low])

    def _blocks(self, D: FloatArray, C: FloatArray) -> tuple[list[FloatArray], list[FloatArray]]:
        sz = self.size
        Ds = [D[self.off_d[k] : self.off_d[k + 1]].reshape(sz[k], sz[k]) for k in range(self.K)]
        Cs = [C[self.off_c[k] : self.off_c[k + 1]].reshape(sz[k + 1], sz[k]) for k in range(self.K - 1)]
        return Ds, Cs

    def logdet(self, D: FloatArray, C: FloatArray) -> float:
        """``log det A`` (forward block Cholesky only)."""
        Ds, Cs = self._blocks(D, C)
        total = 0.0
        S = Ds[0]
        for k in range(self.K):
            Lk = np.linalg.cholesky(S)
            total += 2.0 * float(np.sum(np.log(np.diag(Lk))))
            if k + 1 < self.K:
                X = np.linalg.inv(Lk) @ Cs[k].T  # L⁻¹ C_kᵀ
                S = Ds[k + 1] - X.T @ X
        return total

    def factor(self, D: FloatArray, C: FloatArray) -> _SelectedInverse:
        """Forward block Cholesky and backward selected inversion of the matrix stored in ``(D, C)``."""
        Ds, Cs = self._blocks(D, C)
        K = self.K
        Sinv: list[FloatArray] = []
        W: list[FloatArray] = []  # W_k = C_k S_k⁻¹
        total = 0.0
        S = Ds[0]
        for k in range(K):
            Lk = np.linalg.cholesky(S)
            total += 2.0 * float(np.sum(np.log(np.diag(Lk))))
            Li = np.linalg.inv(Lk)  # numpy's LAPACK: scipy.linalg links its own, multi-threaded OpenBLAS
            Sinv.append(Li.T @ Li)
            if k + 1 < K:
                W.append(Cs[k] @ Sinv[k])
                S = Ds[k + 1] - W[k] @ Cs[k].T
        sig_d = np.empty_like(D)
        sig_c = np.empty_like(C)
        Sk1 = Sinv[K - 1]
        sig_d[self.off_d[K - 1] :] = Sk1.ravel()
        for k in range(K - 2, -1, -1):
            Lk = -Sk1 @ W[k]  # Σ[k+1, k]
            Sk = Sinv[k] - W[k].T @ Lk
            Sk = 0.5 * (Sk + Sk.T)
            sig_d[self.off_d[k] : self.off_d[k + 1]] = Sk.ravel()
            sig_c[self.off_c[k] : self.off_c[k + 1]] = Lk.ravel()
            Sk1 = Sk
        return _SelectedInverse(self, total, sig_d, sig_c)


@dataclass
class _SelectedInverse:
    """Entries of ``A⁻¹`` on the level-block structure of ``A``, and ``log det A``."""

    blocks: _LevelBlocks
    logdet: float
    sig_d: FloatArray
    sig_c: FloatArray

    def entries(self, rows: npt.NDArray[np.int64], cols: npt.NDArray[np.int64]) -> FloatArray:
        """``A⁻¹[rows[i], cols[i]]`` for entries inside the structure."""
        diag, _, pos = self.blocks._index(rows, cols)
        out = np.empty(len(pos))
        out[diag] = self.sig_d[pos[diag]]
        out[~diag] = self.sig_c[pos[~diag]]
        return out

    def block(self, cols: npt.NDArray[np.int64]) -> FloatArray:
        """``A⁻¹[cols, cols]``."""
        m = len(cols)
        return self.entries(np.repeat(cols, m), np.tile(cols, m)).reshape(m, m)

    def trace(self) -> float:
        b = self.blocks
        return float(sum(np.trace(self.sig_d[b.off_d[k] : b.off_d[k + 1]].reshape(s, s)) for k, s in enumerate(b.size)))


# ------------------------------------------------------------------ mutual information (Beinhofer et al.)
def schur_contribution(J_x: FloatArray, J_l: FloatArray, landmark_prior_info: float | FloatArray = 0.0) -> FloatArray:
    """Information a landmark's measurements add to the trajectory, the landmark marginalised (Schur complement).

    ``J_x`` (rows × trajectory cols on the landmark's support) and ``J_l`` (rows × landmark dim) are
    the stacked whitened Jacobians of all of that landmark's measurements; ``landmark_prior_info`` is the weak
    prior's information, one value or one per landmark dimension.
    """
    Hll = J_l.T @ J_l + np.diag(np.broadcast_to(np.asarray(landmark_prior_info, dtype=float), (J_l.shape[1],)))
    Hxl = J_x.T @ J_l
    out = J_x.T @ J_x - Hxl @ np.linalg.solve(Hll, Hxl.T)
    return np.asarray(0.5 * (out + out.T))


def _low_rank(block: FloatArray, tol: float = 1e-12) -> FloatArray:
    w, V = np.linalg.eigh(block)
    keep = w > tol * max(float(w.max(initial=0.0)), 1e-300)
    return np.asarray(V[:, keep] * np.sqrt(w[keep]))


DENSE_MAX_DIM = 2800
"""Largest trajectory dimension for which the MI greedy may carry the dense covariance (one inverse, rank-r
downdates), chosen only when the level blocks are so large that it is cheaper; above it the level-block selected
inverse is used regardless (it never needs an ``n × n`` array). The dense path holds about four ``n × n`` arrays at
once (the information, its inverse, a downdate and its difference): ~60 MiB each here, and 464 MiB in all on a
3,702-dimensional trajectory, where the selected inverse took 255 MiB and the same picks."""


def _dense_mi_ops(
    info0: FloatArray | SparseMatrix, factors: Sequence[tuple[npt.NDArray[np.int64], FloatArray]]
) -> tuple[Callable[[int], float], Callable[[int], None]]:
    dense = np.asarray(info0) if isinstance(info0, np.ndarray) else info0.toarray()
    Sigma = np.linalg.inv(dense)

    def gain(l_: int) -> float:
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return 0.0
        M = np.eye(B.shape[1]) + B.T @ Sigma[np.ix_(cols, cols)] @ B
        return 0.5 * float(np.linalg.slogdet(M)[1])

    def add(l_: int) -> None:
        nonlocal Sigma
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return
        SB = Sigma[:, cols] @ B
        Sigma = Sigma - SB @ np.linalg.solve(np.eye(B.shape[1]) + B.T @ SB[cols], SB.T)

    return gain, add


def _sparse_mi_ops(
    info0: FloatArray | SparseMatrix, factors: Sequence[tuple[npt.NDArray[np.int64], FloatArray]]
) -> tuple[Callable[[int], float], Callable[[int], None]]:
    n = info0.shape[0]
    lam = _as_sparse(info0)
    factor = _Factor(lam)

    def gain(l_: int) -> float:
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return 0.0
        rhs = np.zeros((n, B.shape[1]))
        rhs[cols] = B
        M = np.eye(B.shape[1]) + B.T @ np.asarray(factor.lu.solve(rhs))[cols]  # Bᵀ Σ_cc B, r solves
        return 0.5 * float(np.linalg.slogdet(M)[1])

    def add(l_: int) -> None:
        nonlocal lam, factor
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return
        lam = (lam + _scatter(n, [(cols, B @ B.T)])).tocsc()
        factor = _Factor(lam)

    return gain, add


def _selected_mi_ops(
    info0: FloatArray | SparseMatrix,
    factors: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    blocks: _LevelBlocks,
) -> tuple[Callable[[int], float], Callable[[int], None]]:
    """Gains from the selected inverse of the current information (refactorised after each pick, ``O(Σ b_k³)``)."""
    D, C = blocks.store(_as_sparse(info0))
    state = {"inv": blocks.factor(D, C)}

    def gain(l_: int) -> float:
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return 0.0
        M = np.eye(B.shape[1]) + B.T @ state["inv"].block(cols) @ B
        return 0.5 * float(np.linalg.slogdet(M)[1])

    def add(l_: int) -> None:
        cols, B = factors[l_]
        if B.shape[1] == 0:
            return
        blocks.add(D, C, cols, B @ B.T)
        state["inv"] = blocks.factor(D, C)

    return gain, add


MIBackend = Literal["auto", "selected", "dense", "sparse"]
"""How the MI greedy evaluates gains (``auto``: the cheapest by a flop count; the others for tests and benchmarks).

``selected``: the level-block selected inverse of the current information, recomputed after each pick
(``budget · O(Σ b_k³)``); ``dense``: one dense inverse and rank-r downdates (``O(n³) + budget · O(n² r)``);
``sparse``: a sparse factorisation per pick and r solves per gain (memory-lean fallback above ``DENSE_MAX_DIM``)."""


def _mi_backend(n: int, budget: int, blocks: _LevelBlocks, rank: float, backend: MIBackend) -> MIBackend:
    if backend != "auto":
        return backend
    if budget * blocks.cost() <= float(n) ** 3 + budget * 2.0 * float(n) ** 2 * rank or n > DENSE_MAX_DIM:
        return "selected"
    return "dense"


@blas_single
def select_mutual_information(
    info0: FloatArray | SparseMatrix,
    contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    budget: int,
    lazy: bool = True,
    backend: MIBackend = "auto",
    min_block: int | None = None,
) -> LandmarkSelection:
    """Greedy ``F(A) = ½ log det(Λ₀ + Σ_{l∈A} Λ_l) − ½ log det Λ₀`` (monotone submodular; lazy is exact).

    Args:
        info0: (n, n) trajectory information from odometry and prior.
        contributions: per landmark, ``(cols, Λ_l)`` with ``Λ_l`` the Schur-complement block on
            the trajectory columns ``cols`` (see :func:`schur_contribution`).
        budget: number of landmarks.
        lazy: lazy evaluation (exact here, as every ``Λ_l`` is PSD).
        backend: how the gains are evaluated (:data:`MIBackend`; the same picks every way).
        min_block: smallest level block of the selected inverse (default :data:`LEVEL_BLOCK_MIN`).

    Returns:
        Picks with their marginal gains (nats); ``extra['objective']`` is ``F`` after each pick.
    """
    L = len(contributions)
    st = _status(budget, L)
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st)
    budget = min(budget, L)
    n = info0.shape[0]
    factors = [(np.asarray(c, dtype=np.int64), _low_rank(b)) for c, b in contributions]
    pattern = _as_sparse(info0) + _scatter(n, [(c, np.ones((len(c), len(c)))) for c, _ in factors])
    blocks = _LevelBlocks(pattern, min_block)
    rank = float(np.mean([B.shape[1] for _, B in factors]))
    backend = _mi_backend(n, budget, blocks, rank, backend)
    if backend == "selected":
        gain, add = _selected_mi_ops(info0, factors, blocks)
    elif backend == "dense":
        gain, add = _dense_mi_ops(info0, factors)
    else:
        gain, add = _sparse_mi_ops(info0, factors)

    picks: list[int] = []
    gains: list[float] = []
    if lazy:
        heap = [(-gain(l_), l_) for l_ in range(L)]
        heapq.heapify(heap)
        fresh: set[int] = set(range(L))
        while len(picks) < budget:
            neg, l_ = heapq.heappop(heap)
            if l_ in fresh:
                picks.append(l_)
                gains.append(-neg)
                add(l_)
                fresh = set()
            else:
                heapq.heappush(heap, (-gain(l_), l_))
                fresh.add(l_)
    else:
        remaining = set(range(L))
        while len(picks) < budget:
            g = {l_: gain(l_) for l_ in sorted(remaining)}
            l_ = max(g, key=lambda k: (g[k], -k))
            picks.append(l_)
            gains.append(g[l_])
            remaining.discard(l_)
            add(l_)
    return LandmarkSelection(picks, gains, st or "ok", {"objective": np.cumsum(gains)})


# ------------------------------------------------------------------ leverage, uniform, random
def _measure(cov: FloatArray, measure: Measure) -> float:
    if measure == "trace":
        return float(np.trace(cov))
    if measure == "max_eig":
        return float(np.linalg.eigvalsh(cov)[-1])
    return float(np.linalg.slogdet(cov)[1])


def _measure_information(
    lam: SparseMatrix, measure: Measure, blocks: _LevelBlocks | None = None, min_block: int | None = None
) -> float:
    """:func:`_measure` of ``lam⁻¹`` from a sparse factorisation of the information ``lam`` (no dense inverse).

    ``blocks``: a level-block structure that contains ``lam``'s pattern (built from it, with ``min_block``, if not
    given).
    """
    if measure == "max_eig":
        dense = lam.shape[0] <= 200
        w = np.linalg.eigvalsh(lam.toarray())[0] if dense else spla.eigsh(lam, k=1, sigma=0.0, which="LM")[0][0]
        return 1.0 / float(w)
    blocks = _LevelBlocks(lam, min_block) if blocks is None else blocks
    D, C = blocks.store(lam)
    if measure == "logdet":
        return -blocks.logdet(D, C)
    return blocks.factor(D, C).trace()


def _all_information(
    info0: FloatArray | SparseMatrix,
    contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    min_block: int | None = None,
) -> tuple[sp.csc_matrix, _LevelBlocks]:
    """``Λ₀ + Σ_l Λ_l`` and its level-block structure (which holds the pattern of every subset's information)."""
    lam = (_as_sparse(info0) + _scatter(info0.shape[0], contributions)).tocsc()
    pattern = lam + _scatter(info0.shape[0], [(c, np.ones((len(c), len(c)))) for c, _ in contributions])
    return lam, _LevelBlocks(pattern, min_block)


def _leverage_probabilities(
    info0: FloatArray | SparseMatrix,
    contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    lam: sp.csc_matrix,
    blocks: _LevelBlocks,
) -> FloatArray:
    n, N = info0.shape[0], len(contributions)
    D, C = blocks.store(lam)
    inv = blocks.factor(D, C)  # Σ = Λ_all⁻¹ on the pattern of Λ_all: every landmark's support block is in it
    # tr(Σ Λ_l) one landmark at a time: all supports at once (Σ_l |c_l|² entries, each with a dozen index arrays)
    # took ~450 MiB on a 4-minute corridor run with laps; one support at a time holds only the largest
    own: FloatArray = np.zeros(N)
    for l_, (c, B) in enumerate(contributions):
        c = np.asarray(c, dtype=np.int64)
        if len(c):
            own[l_] = float(np.sum(inv.block(c) * np.asarray(B, dtype=float)))
    # Σ (Λ₀ + Σ_l Λ_l) = I, so tr(Σ Λ₀) = n − Σ_l tr(Σ Λ_l): no other entry of Σ is needed
    base = (n - float(own.sum())) / N
    return np.asarray((base + own) / n)


@blas_single
def landmark_leverage_probabilities(
    info0: FloatArray | SparseMatrix,
    contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    min_block: int | None = None,
) -> FloatArray:
    """Mousavi & Motee eq. 29-30: ``π_l = tr(Λ_all⁻¹ (Λ₀/N + Λ_l)) / n`` (sums to 1).

    ``tr(Σ Λ_l)`` only reads ``Σ = Λ_all⁻¹`` on landmark l's support, which is inside the sparsity pattern of
    ``Λ_all``: one selected inversion (:class:`_LevelBlocks`, level blocks of at least ``min_block`` variables)
    gives all of them, without the dense inverse.
    """
    lam, blocks = _all_information(info0, contributions, min_block)
    return _leverage_probabilities(info0, contributions, lam, blocks)


@blas_single
def select_landmark_leverage(
    info0: FloatArray | SparseMatrix,
    contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]],
    budget: int,
    draws: int = 20,
    measure: Measure = "logdet",
    seed: int = 0,
) -> LandmarkSelection:
    """Leverage sampling: ``draws`` independent draws with replacement until ``budget`` distinct, keep the best.

    Scores are the sampling probabilities of the picks; ``extra['measure']`` is the kept draw's value. Each
    draw's measure comes from the level-block factorisation of ``Λ_all``'s pattern (log det: forward block
    Cholesky; trace: selected inversion; largest eigenvalue: shift-invert Lanczos).
    """
    L = len(contributions)
    st = _status(budget, L)
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st)
    budget = min(budget, L)
    lam_all, blocks = _all_information(info0, contributions)
    pi = _leverage_probabilities(info0, contributions, lam_all, blocks)
    n = info0.shape[0]
    base = _as_sparse(info0)
    D0, C0 = blocks.store(base)
    rng = np.random.default_rng(seed)
    best: tuple[float, list[int]] | None = None
    for _ in range(draws):
        chosen: dict[int, None] = {}
        while len(chosen) < budget:
            chosen[int(rng.choice(L, p=pi))] = None
        if measure == "max_eig":
            lam = (base + _scatter(n, [contributions[l_] for l_ in chosen])).tocsc()
            value = _measure_information(lam, measure)
        else:
            D, C = D0.copy(), C0.copy()
            for l_ in chosen:
                cols, B = contributions[l_]
                blocks.add(D, C, np.asarray(cols, dtype=np.int64), B)
            value = -blocks.logdet(D, C) if measure == "logdet" else blocks.factor(D, C).trace()
        if best is None or value < best[0]:
            best = (value, list(chosen))
    assert best is not None
    return LandmarkSelection(best[1], [float(pi[i]) for i in best[1]], st or "ok", {"measure": np.array([best[0]])})


def select_landmark_uniform(positions: FloatArray, budget: int) -> LandmarkSelection:
    """Spatially even: farthest-point sampling from the landmark nearest the centroid (deterministic).

    Scores are the distance of each pick to the ones before it.
    """
    L = len(positions)
    st = _status(budget, L)
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st)
    budget = min(budget, L)
    first = int(np.argmin(np.linalg.norm(positions - positions.mean(axis=0), axis=1)))
    picks, scores = [first], [float("inf")]
    dist = np.linalg.norm(positions - positions[first], axis=1)
    while len(picks) < budget:
        nxt = int(np.argmax(dist))
        picks.append(nxt)
        scores.append(float(dist[nxt]))
        dist = np.minimum(dist, np.linalg.norm(positions - positions[nxt], axis=1))
    return LandmarkSelection(picks, scores, st or "ok")


def select_landmark_random(n_landmarks: int, budget: int, seed: int = 0) -> LandmarkSelection:
    """``budget`` landmarks uniformly at random without replacement (seeded)."""
    st = _status(budget, n_landmarks)
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st)
    budget = min(budget, n_landmarks)
    picks = [int(i) for i in np.random.default_rng(seed).choice(n_landmarks, size=budget, replace=False)]
    return LandmarkSelection(picks, [float("nan")] * budget, st or "ok")
