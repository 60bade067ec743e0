"""Sparse factorisation of an information matrix and the covariance blocks read from it.

Only scipy is used (SuperLU with a symmetric fill-reducing ordering and diagonal pivoting, which
for a symmetric positive-definite matrix is an LDLᵀ in disguise), so everything installs from
wheels. Covariance *blocks* are computed without forming the inverse:

* per connected component of the block-sparsity graph (different components are independent,
  their cross-covariance is exactly zero);
* a component whose variables form a path (odometry chains: the usual initial information) is
  block tridiagonal, and its diagonal and neighbour blocks come from one forward/backward
  block recursion in O(length);
* any other block is read from columns of ``Λ⁻¹`` obtained by sparse solves (exact, costs one
  solve per needed column block).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from stages.estimation.linear_system import SparseMatrix

try:  # optional, faster sparse Cholesky (CHOLMOD in a wheel)
    from cholespy import CholeskySolverD, MatrixType

    _HAVE_CHOLESPY = True
except ImportError:  # pragma: no cover - depends on the environment
    _HAVE_CHOLESPY = False

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class SingularInformationError(ValueError):
    """The information matrix is not positive definite (some direction is unobserved)."""


class SPDSolver:
    """Factorise a sparse symmetric positive-definite matrix once; solve many right-hand sides.

    Uses CHOLMOD through ``cholespy`` (a self-contained wheel) when it is installed, else SciPy's
    SuperLU with a symmetric minimum-degree ordering and diagonal pivoting.
    """

    def __init__(self, matrix: SparseMatrix, backend: str | None = None) -> None:
        A = sp.csc_matrix(matrix)
        self._A = A
        self.n = int(A.shape[0])
        self._lu: spla.SuperLU | None = None
        self._chol = None
        self._wide = False  # a solve of several columns has been made (see ``__del__``)
        self.backend = backend or ("cholmod" if _HAVE_CHOLESPY else "superlu")
        if self.n == 0:
            return
        diag = A.diagonal()
        if np.any(diag <= 0):
            raise SingularInformationError(
                f"information matrix has {int(np.sum(diag <= 0))} unobserved directions (zero diagonal): "
                "add a prior or a weak landmark prior"
            )
        if self.backend == "cholmod":
            coo = sp.coo_matrix(A)
            try:
                self._chol = CholeskySolverD(
                    self.n,
                    coo.row.astype(np.int32),
                    coo.col.astype(np.int32),
                    coo.data.astype(np.float64),
                    MatrixType.COO,
                )
            except Exception as err:  # CHOLMOD reports a non-positive-definite matrix as a plain error
                raise SingularInformationError(f"information matrix is not positive definite: {err}") from err
        else:
            self._superlu()

    def _superlu(self) -> spla.SuperLU:
        if self._lu is None:
            try:
                self._lu = spla.splu(
                    self._A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
                )
            except RuntimeError as err:  # "Factor is exactly singular"
                raise SingularInformationError(f"information matrix is singular: {err}") from err
            # each pivot against its own column's diagonal (the pivot of an LDLᵀ is that diagonal less what the
            # columns before it explain): a direction is unobserved when nearly all of it is explained. Not against
            # the largest diagonal, which made a tag surveyed to 1e-4 m (information 1e8) turn the weak landmark
            # prior's pivots (1e-4) into "not positive definite".
            d = self._lu.U.diagonal()
            own = np.empty(self.n)
            own[self._lu.perm_c] = self._A.diagonal()
            if np.any(d <= 1e-13 * own):
                raise SingularInformationError(
                    "information matrix is not positive definite (a variable or direction is unobserved: "
                    "add a prior or a weak landmark prior)"
                )
        return self._lu

    def logdet(self) -> float:
        """``log det`` of the factorised matrix (SuperLU, computed on first use)."""
        if self.n == 0:
            return 0.0
        return float(np.sum(np.log(self._superlu().U.diagonal())))

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``A⁻¹ rhs`` for a dense vector or matrix ``rhs``."""
        b = np.ascontiguousarray(rhs, dtype=np.float64)
        if self.n == 0:
            return np.zeros_like(b)
        if self._chol is not None:
            x = np.zeros_like(b)
            self._chol.solve(b, x)
            self._wide = self._wide or (b.ndim == 2 and b.shape[1] > 1)
            return x
        return np.asarray(self._superlu().solve(b))

    def __del__(self) -> None:
        # cholespy 2.2 keeps a dense buffer of the last solve's size (n × columns) that its destructor does not
        # free: every solver that solved many columns leaked them (500 MB over select_measurements' replay of a
        # 16-minute recording). One last single-column solve shrinks the buffer to n values before the solver goes.
        if getattr(self, "_wide", False) and self._chol is not None:
            z = np.zeros(self.n)
            self._chol.solve(z, np.zeros(self.n))


def _variable_graph(info: SparseMatrix, offsets: IntArray) -> sp.csr_matrix:
    """Block-sparsity pattern of ``info`` as a variable adjacency matrix (no self loops)."""
    coo = sp.coo_matrix(info)
    var_of_col = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    vr, vc = var_of_col[coo.row], var_of_col[coo.col]
    keep = (vr != vc) & (coo.data != 0)
    n = len(offsets) - 1
    g = sp.csr_matrix((np.ones(int(keep.sum())), (vr[keep], vc[keep])), shape=(n, n))
    g.data[:] = 1.0
    return g


def _path_order(graph: sp.csr_matrix, members: IntArray) -> list[int] | None:
    """The members in path order if the component is a simple path, else ``None``."""
    if len(members) == 1:
        return [int(members[0])]
    deg = np.diff(graph.indptr)[members]
    if np.any(deg > 2) or int(deg.sum()) != 2 * (len(members) - 1):
        return None
    ends = members[deg == 1]
    if len(ends) != 2:
        return None
    order = [int(ends[0])]
    prev = -1
    while len(order) < len(members):
        cur = order[-1]
        nbrs = graph.indices[graph.indptr[cur] : graph.indptr[cur + 1]]
        nxt = [int(v) for v in nbrs if v != prev]
        prev = cur
        order.append(nxt[0])
    return order


def _tridiagonal_blocks(
    info: sp.csc_matrix, offsets: IntArray, order: Sequence[int]
) -> tuple[list[FloatArray], list[FloatArray]]:
    """Diagonal blocks ``Σ_kk`` and neighbour blocks ``Σ_{k,k+1}`` of a block-tridiagonal inverse."""
    n = len(order)
    n_var = len(offsets) - 1
    pos = np.full(n_var, -1, dtype=np.int64)
    pos[np.asarray(order, dtype=np.int64)] = np.arange(n)
    dims = np.diff(offsets)
    dmax = int(dims[np.asarray(order)].max())
    coo = sp.coo_matrix(info)
    var_of_col = np.repeat(np.arange(n_var), dims)
    vr, vc = var_of_col[coo.row], var_of_col[coo.col]
    pr, pc = pos[vr], pos[vc]
    lr, lc = coo.row - offsets[vr], coo.col - offsets[vc]
    Dp = np.zeros((n, dmax, dmax))
    Bp = np.zeros((max(n - 1, 0), dmax, dmax))
    on = (pr >= 0) & (pr == pc)
    np.add.at(Dp, (pr[on], lr[on], lc[on]), coo.data[on])
    up = (pr >= 0) & (pc == pr + 1)
    np.add.at(Bp, (pr[up], lr[up], lc[up]), coo.data[up])
    dk = dims[np.asarray(order)]
    D = [Dp[k, : dk[k], : dk[k]] for k in range(n)]
    B = [Bp[k, : dk[k], : dk[k + 1]] for k in range(n - 1)]
    S_inv: list[FloatArray] = []
    S = D[0]
    for k in range(n):
        if k > 0:
            S = D[k] - B[k - 1].T @ S_inv[k - 1] @ B[k - 1]
        S_inv.append(np.linalg.inv(S).astype(np.float64, copy=False))
    diag: list[FloatArray] = [np.zeros((0, 0))] * n
    off: list[FloatArray] = [np.zeros((0, 0))] * max(n - 1, 0)
    diag[n - 1] = S_inv[n - 1]
    for k in range(n - 2, -1, -1):
        G = S_inv[k] @ B[k]  # S_k⁻¹ B_k
        off[k] = -G @ diag[k + 1]
        diag[k] = S_inv[k] + G @ diag[k + 1] @ G.T
    return diag, off


class CovarianceBlocks:
    """Blocks ``Σ[i, j]`` (``Σ = info⁻¹``) for variable pairs, without the full inverse, answered one pair at a time.

    The work is done once at construction for every pair that may be asked: the block-tridiagonal recursion of each
    path component that ``variables`` touch, and the sparse solves for the requested ``pairs`` not given by the
    recursions. Asking for a pair then only reads (pairs in different components are zero blocks), so a caller can
    gather the blocks of many pairs in bounded pieces instead of holding one small array per pair.

    Args:
        info: sparse SPD information matrix.
        offsets: column offsets of the variable blocks (``len = n_variables + 1``).
        variables: every variable the pairs name.
        pairs: the requested pairs ``(i, j)``, in order (may be a generator: it is walked once,
            and only the pairs that need solves are kept).
        solver: a factorisation of ``info`` to reuse for blocks not given by the recursions.
    """

    def __init__(
        self,
        info: SparseMatrix,
        offsets: IntArray,
        variables: Iterable[int],
        pairs: Iterable[tuple[int, int]],
        solver: SPDSolver | None = None,
    ) -> None:
        info = sp.csc_matrix(info)
        graph = _variable_graph(info, offsets)
        _, label = csgraph.connected_components(graph, directed=False)
        self.label = label
        self.dims = np.diff(offsets)
        needed_comp = np.unique(label[np.asarray(list(variables), dtype=np.int64)]).tolist()
        order_all = np.argsort(label, kind="stable")
        bounds = np.searchsorted(label[order_all], np.arange(int(label.max(initial=-1)) + 2))
        self._tri: dict[int, tuple[dict[int, int], list[FloatArray], list[FloatArray]]] = {}
        for c in needed_comp:
            members = order_all[bounds[c] : bounds[c + 1]].astype(np.int64)
            if len(members) == 1:
                v = int(members[0])
                blk = info[offsets[v] : offsets[v + 1], :][:, offsets[v] : offsets[v + 1]].toarray()
                self._tri[c] = ({v: 0}, [np.linalg.inv(blk)], [])
                continue
            order = _path_order(graph, members)
            if order is not None:
                diag, off = _tridiagonal_blocks(info, offsets, order)
                self._tri[c] = ({v: k for k, v in enumerate(order)}, diag, off)
        self._solved: dict[tuple[int, int], FloatArray] = {}
        pending = list(dict.fromkeys((int(i), int(j)) for i, j in pairs if not self._recursive(int(i), int(j))))
        if pending:
            if solver is None:
                solver = SPDSolver(info)
            dims = self.dims
            cols_needed = sorted({j for _, j in pending})
            for chunk in _column_chunks(cols_needed, dims, int(info.shape[0])):
                rhs_cols = np.concatenate([np.arange(offsets[j], offsets[j + 1]) for j in chunk])
                E = np.zeros((info.shape[0], len(rhs_cols)))
                E[rhs_cols, np.arange(len(rhs_cols))] = 1.0
                X = solver.solve(E)
                local = {}
                p = 0
                for j in chunk:
                    local[j] = X[:, p : p + dims[j]]
                    p += dims[j]
                for i, j in pending:
                    if j in local:
                        self._solved[(i, j)] = local[j][offsets[i] : offsets[i + 1], :].copy()  # frees the chunk

    def _recursive(self, i: int, j: int) -> bool:
        """The block comes from the recursions (or is zero across components): no solve."""
        if self.label[i] != self.label[j]:
            return True
        tri = self._tri.get(int(self.label[i]))
        return tri is not None and abs(tri[0][i] - tri[0][j]) <= 1

    def _read(self, i: int, j: int) -> FloatArray | None:
        """The block from the recursions (or zero across components), else None (solved for)."""
        if not self._recursive(i, j):
            return None
        if self.label[i] != self.label[j]:
            return np.zeros((self.dims[i], self.dims[j]))
        pos, diag, off = self._tri[int(self.label[i])]
        a, b = pos[i], pos[j]
        if a == b:
            return diag[a]
        return off[a] if b == a + 1 else off[b].T

    def __getitem__(self, pair: tuple[int, int]) -> FloatArray:
        i, j = int(pair[0]), int(pair[1])
        blk = self._read(i, j)
        return self._solved[(i, j)] if blk is None else blk


def covariance_blocks(
    info: SparseMatrix,
    offsets: IntArray,
    pairs: Iterable[tuple[int, int]],
    solver: SPDSolver | None = None,
) -> dict[tuple[int, int], FloatArray]:
    """Blocks ``Σ[i, j]`` (``Σ = info⁻¹``) for the requested variable pairs, without the full inverse.

    Args:
        info: sparse SPD information matrix.
        offsets: column offsets of the variable blocks (``len = n_variables + 1``).
        pairs: variable index pairs ``(i, j)``; ``(i, i)`` asks for a marginal block.
        solver: a factorisation of ``info`` to reuse for blocks not given by the recursions.

    Returns:
        ``{(i, j): Σ_ij}`` for every requested pair (see :class:`CovarianceBlocks`).
    """
    pairs = list(dict.fromkeys((int(i), int(j)) for i, j in pairs))
    variables = {v for p in pairs for v in p}
    blocks = CovarianceBlocks(info, offsets, variables, pairs, solver)
    return {p: blocks[p] for p in pairs}


SOLVE_CHUNK_BYTES = 8 * 2**20
"""Dense right-hand sides solved for at once by :func:`covariance_blocks`: the identity columns, the solution and
the solver's own buffer are each ``n × columns``, so 256 variables of 3 columns at a time on an hour's graph (54,000
columns) held ~1 GB; 8 MiB each (19 columns there) bounds the memory, and the map's local covariances on that graph
took no longer than with 32 MiB (14.2 against 16.1 s)."""


def _column_chunks(variables: Sequence[int], dims: IntArray, n: int) -> list[list[int]]:
    """``variables`` in groups whose columns make at most :data:`SOLVE_CHUNK_BYTES` of ``n``-row doubles (at least
    one variable, at most 256 per group)."""
    max_cols = max(1, SOLVE_CHUNK_BYTES // (8 * max(n, 1)))
    chunks: list[list[int]] = []
    cur: list[int] = []
    width = 0
    for j in variables:
        d = int(dims[j])
        if cur and (width + d > max_cols or len(cur) == 256):
            chunks.append(cur)
            cur, width = [], 0
        cur.append(j)
        width += d
    if cur:
        chunks.append(cur)
    return chunks


def logdet_spd(matrix: FloatArray) -> float:
    """``log det`` of a small dense SPD matrix via Cholesky."""
    if matrix.size == 0:
        return 0.0
    c = sla.cholesky(matrix, lower=True)
    return float(2.0 * np.sum(np.log(np.diag(c))))


def marginal_logdet(info: SparseMatrix, cols: IntArray) -> float:
    """``log det Σ_F`` of the marginal covariance of the columns ``cols`` of ``Σ = info⁻¹``, without forming it:
    ``log det Λ_UU − log det Λ`` (``U`` the other columns; Schur complement)."""
    A = sp.csc_matrix(info)
    other = np.setdiff1d(np.arange(A.shape[0]), cols)
    ld_all = SPDSolver(A, backend="superlu").logdet()
    ld_other = SPDSolver(sp.csc_matrix(A[other][:, other]), backend="superlu").logdet() if len(other) else 0.0
    return ld_other - ld_all


def covariance_blocks_schur(
    info: SparseMatrix,
    offsets: IntArray,
    pairs: Iterable[tuple[int, int]],
    separator: Sequence[int],
) -> dict[tuple[int, int], FloatArray]:
    """Blocks of ``info⁻¹`` via the Schur complement onto a small ``separator`` (e.g. the landmarks).

    Write ``info = [[Λ_rr, Λ_rs], [Λ_sr, Λ_ss]]`` with ``s`` the separator. With ``X = Λ_rr⁻¹ Λ_rs``
    (one sparse solve per separator column) and ``C = (Λ_ss − Λ_sr X)⁻¹`` (small, dense)::

        Σ_ss = C,   Σ_rs = −X C,   Σ_rr = Λ_rr⁻¹ + X C Xᵀ

    and the blocks of ``Λ_rr⁻¹`` come from :func:`covariance_blocks` (cheap when the rest, e.g. the
    pose chain, is a path). Exact; memory ``O(dim_r · dim_s)``.
    """
    info = sp.csc_matrix(info)
    n_var = len(offsets) - 1
    sep = sorted({int(s) for s in separator})
    is_sep = np.zeros(n_var, dtype=bool)
    is_sep[sep] = True
    rest = [v for v in range(n_var) if not is_sep[v]]
    dims = np.diff(offsets)
    r_cols = np.concatenate([np.arange(offsets[v], offsets[v + 1]) for v in rest]) if rest else np.zeros(0, int)
    s_cols = np.concatenate([np.arange(offsets[v], offsets[v + 1]) for v in sep]) if sep else np.zeros(0, int)
    # local offsets inside r and s
    r_off = np.concatenate([[0], np.cumsum(dims[rest])]).astype(np.int64)
    s_off = np.concatenate([[0], np.cumsum(dims[sep])]).astype(np.int64)
    r_pos = {v: k for k, v in enumerate(rest)}
    s_pos = {v: k for k, v in enumerate(sep)}
    L_rr = info[r_cols][:, r_cols]
    L_rs = info[r_cols][:, s_cols].toarray()
    L_ss = info[s_cols][:, s_cols].toarray()
    solver_r = SPDSolver(L_rr)
    X = solver_r.solve(L_rs) if len(s_cols) else np.zeros((len(r_cols), 0))
    C = np.linalg.inv(L_ss - L_rs.T @ X) if len(s_cols) else np.zeros((0, 0))
    C = 0.5 * (C + C.T)
    pairs = list(dict.fromkeys((int(i), int(j)) for i, j in pairs))
    rr_pairs = [(r_pos[i], r_pos[j]) for i, j in pairs if not is_sep[i] and not is_sep[j]]
    base = covariance_blocks(L_rr, r_off, rr_pairs, solver=solver_r) if rr_pairs else {}
    XC = X @ C
    out: dict[tuple[int, int], FloatArray] = {}
    for i, j in pairs:
        if is_sep[i] and is_sep[j]:
            a, b = s_pos[i], s_pos[j]
            out[(i, j)] = C[s_off[a] : s_off[a + 1], s_off[b] : s_off[b + 1]]
        elif is_sep[j]:
            a, b = r_pos[i], s_pos[j]
            out[(i, j)] = -XC[r_off[a] : r_off[a + 1], s_off[b] : s_off[b + 1]]
        elif is_sep[i]:
            a, b = s_pos[i], r_pos[j]
            out[(i, j)] = -XC[r_off[b] : r_off[b + 1], s_off[a] : s_off[a + 1]].T
        else:
            a, b = r_pos[i], r_pos[j]
            Xi = X[r_off[a] : r_off[a + 1]]
            Xj = X[r_off[b] : r_off[b + 1]]
            out[(i, j)] = base[(a, b)] + Xi @ C @ Xj.T
    return out


def schur_complement(info: SparseMatrix, keep: IntArray, max_colours: int = 96) -> sp.csc_matrix | None:
    """Exact sparse ``Λ_KK − Λ_KO Λ_OO⁻¹ Λ_OK`` (``= (Λ⁻¹[K, K])⁻¹``) onto the scalar columns ``keep``.

    ``O`` is every other column. ``Λ_OO⁻¹`` is block diagonal over the connected components of
    ``O``'s sparsity graph, so kept columns that touch disjoint sets of components can share one
    right-hand side: the kept columns are coloured greedily (same colour ⇒ no shared component),
    ``X = Λ_OO⁻¹ B`` is solved for one summed right-hand side per colour, and each entry of ``X`` is
    attributed back to the unique kept column of its colour that touches its component. For a pose
    chain with kept poses (eliminating the runs of other poses between them) that is 6 right-hand
    sides, and the result is again a block-tridiagonal chain over the kept poses.

    Returns ``None`` when more than ``max_colours`` colours would be needed (not worth it).
    """
    info = sp.csc_matrix(info)
    n = info.shape[0]
    keep = np.asarray(keep, dtype=np.int64)
    is_keep = np.zeros(n, dtype=bool)
    is_keep[keep] = True
    other = np.flatnonzero(~is_keep)
    L_KK = info[keep][:, keep]
    if len(other) == 0:
        return sp.csc_matrix(L_KK)
    L_OO = sp.csc_matrix(info[other][:, other])
    L_OK = sp.csc_matrix(info[other][:, keep])
    L_OK.eliminate_zeros()
    n_comp, comp = csgraph.connected_components(L_OO, directed=False)
    colour = np.full(len(keep), -1, dtype=np.int64)
    used: list[set[int]] = []
    for j in range(len(keep)):
        touched = set(comp[L_OK.indices[L_OK.indptr[j] : L_OK.indptr[j + 1]]].tolist())
        if not touched:
            continue
        for g, taken in enumerate(used):
            if not (taken & touched):
                taken |= touched
                colour[j] = g
                break
        else:
            if len(used) == max_colours:
                return None
            used.append(set(touched))
            colour[j] = len(used) - 1
    n_col = len(used)
    if n_col == 0:
        return sp.csc_matrix(L_KK)
    coo = sp.coo_matrix(L_OK)  # rows: O positions, cols: K positions
    B = np.zeros((len(other), n_col))
    np.add.at(B, (coo.row, colour[coo.col]), coo.data)
    solver = SPDSolver(L_OO)
    X = solver.solve(B)
    X += solver.solve(B - L_OO @ X)  # one step of iterative refinement
    owner = np.full((n_comp, n_col), -1, dtype=np.int64)
    owner[comp[coo.row], colour[coo.col]] = coo.col
    rows, cols, vals = [], [], []
    for g in range(n_col):
        j = owner[comp[coo.row], g]
        ok = j >= 0
        rows.append(coo.col[ok])
        cols.append(j[ok])
        vals.append(coo.data[ok] * X[coo.row[ok], g])
    corr = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(len(keep), len(keep))
    )
    S = sp.csc_matrix(L_KK - corr)
    return sp.csc_matrix(0.5 * (S + S.T))
