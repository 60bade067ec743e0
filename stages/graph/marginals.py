"""Every variable's marginal covariance from one elimination, down the Bayes tree.

``gtsam.Marginals.marginalCovariance`` answers one key at a time: each query builds the clique's joint from its
cached separator marginal and eliminates it again, about 0.4 ms a key (7,000 poses: 3 s, as long as the optimise).
Here the covariance of every clique's variables comes from its parent's, top-down, with the standard recursion
on the square-root information form of each clique's conditional ``R x_F + S x_S = d``:

    Σ_FS = −R⁻¹ S Σ_SS,    Σ_FF = R⁻¹ R⁻ᵀ − Σ_FS (R⁻¹ S)ᵀ

where ``Σ_SS`` (the separator's joint covariance) is a block of the parent clique's, since a clique's separator is
a subset of its parent's variables. That is the same covariance GTSAM's queries give (same elimination), with
small dense products per clique; a clique's covariance is dropped once its children have taken theirs.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence

import gtsam
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from stages.estimation.blas import single_threaded_blas
from stages.estimation.sparse_cov import SingularInformationError, SPDSolver


def key_dims(values: gtsam.Values) -> dict[int, int]:
    """Each variable's tangent dimension."""
    zero = values.zeroVectors()
    return {int(k): int(zero.at(k).shape[0]) for k in values.keys()}  # noqa: SIM118 (a gtsam KeyVector)


def eliminate(linear: gtsam.GaussianFactorGraph, last: Iterable[int] = ()) -> gtsam.GaussianBayesTree:
    """Multifrontal elimination with GTSAM's default (COLAMD) ordering; when that stops on an indeterminant clique
    and ``last`` names variables (the landmarks), again with those eliminated last.

    COLAMD can interleave a landmark seen from hundreds of weakly linked poses with them so that one clique's
    Cholesky meets a pivot lost to rounding, though the system is positive definite (TagSLAM's test_14 reduced to 30
    landmarks: COLAMD stops at a tag, a sparse LU of the same information has pivots >= 0.025, and the
    landmarks-last ordering, the usual one for SLAM, eliminates it in 0.1 s).

    Raises:
        RuntimeError: GTSAM's, when both orderings stop (the system is indeterminant).
    """
    try:
        return linear.eliminateMultifrontal()
    except RuntimeError:
        tail = gtsam.KeyVector([int(k) for k in last])
        if not len(tail):
            raise
        return linear.eliminateMultifrontal(gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(linear, tail))


def tree_marginals(
    linear: gtsam.GaussianFactorGraph, dims: Mapping[int, int], keys: Iterable[int], last: Iterable[int] = ()
) -> dict[int, np.ndarray]:
    """The marginal covariance of each of ``keys`` (in their order) in the Gaussian ``linear``: one multifrontal
    elimination (:func:`eliminate`: GTSAM's default ordering, else ``last`` eliminated last), then the recursion of
    the module docstring.

    Raises:
        RuntimeError: GTSAM's, when the system is indeterminant (as ``gtsam.Marginals`` raises it).
    """
    order = [int(k) for k in keys]
    want = set(order)
    out: dict[int, np.ndarray] = {}
    for ks, at, n_front, cov in _clique_covariances(eliminate(linear, last), dims):
        for k in ks:
            i = at[k]
            if i >= n_front:
                break
            if k in want:
                block = cov[i : i + dims[k], i : i + dims[k]]
                out[k] = 0.5 * (block + block.T)
    if missing := sorted(want - set(out)):
        raise RuntimeError(f"variables {missing[:5]} are not in the graph, so have no marginal")
    return {k: out[k] for k in order}  # in the order asked


def selected_inverse(
    linear: gtsam.GaussianFactorGraph,
    dims: Mapping[int, int],
    groups: Sequence[Sequence[int]],
    last: Iterable[int] = (),
) -> sp.csr_matrix:
    """The covariance ``H⁻¹`` of the Gaussian ``linear`` on the blocks of each group of keys (every pair of keys of a
    group, both ways), zero elsewhere, in :func:`whitened_system`'s column layout (keys sorted): the selected
    inverse, from the recursion of the module docstring.

    A group must be the keys of one factor of ``linear`` (or a subset of them): elimination puts them in one clique,
    whose covariance the recursion holds at some point, so the cost is that of :func:`tree_marginals`, linear where
    the tree's cliques stay small, rather than a solve per column. ``tr(H⁻¹ J_fᵀ J_f)`` (a factor's share of the
    hat matrix's trace, its "leverage") then needs only the blocks of its own keys.

    Raises:
        RuntimeError: GTSAM's, when the system is indeterminant.
    """
    ordered = sorted(int(k) for k in linear.keyVector())
    offsets = dict(zip(ordered, np.cumsum([0] + [dims[k] for k in ordered[:-1]]).tolist(), strict=True))
    n = sum(dims[k] for k in ordered)
    pending: dict[int, list[tuple[int, ...]]] = {}  # each group under each of its keys
    for g in {tuple(sorted(int(k) for k in g)) for g in groups}:
        for k in g:
            pending.setdefault(k, []).append(g)
    served: set[tuple[int, ...]] = set()
    rows, cols, vals = [], [], []
    for ks, at, n_front, cov in _clique_covariances(eliminate(linear, last), dims):
        for k in ks:
            if at[k] >= n_front:
                break
            for g in pending.get(k, ()):
                if g in served or any(j not in at for j in g):
                    continue
                served.add(g)
                local = np.concatenate([np.arange(at[j], at[j] + dims[j]) for j in g])
                glob = np.concatenate([np.arange(offsets[j], offsets[j] + dims[j]) for j in g])
                rows.append(np.repeat(glob, len(glob)))
                cols.append(np.tile(glob, len(glob)))
                vals.append(cov[np.ix_(local, local)].ravel())
    if missing := [g for gs in pending.values() for g in gs if g not in served]:
        raise RuntimeError(f"keys {list(missing[0])} share no clique: they are not one factor's")
    if not rows:
        return sp.csr_matrix((n, n))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    flat, first = np.unique(r * n + c, return_index=True)  # a pair of keys in two groups: one entry
    Z = sp.csr_matrix((v[first], (flat // n, flat % n)), shape=(n, n))
    return (Z + Z.T) * 0.5


def _clique_covariances(
    tree: gtsam.GaussianBayesTree, dims: Mapping[int, int]
) -> Iterator[tuple[list[int], dict[int, int], int, np.ndarray]]:
    """Each clique's joint covariance, top-down (the recursion of the module docstring): its keys (frontals first),
    where each key's block starts, the frontal dimension, and the covariance. A clique's covariance is dropped once
    its children have taken theirs."""
    trtri = sla.lapack.dtrtri  # R⁻¹ of a small upper-triangular R, without solve_triangular's checks
    # each clique is handed its parent's covariance and, per key of the parent, that key's indices in it
    stack: list[tuple[gtsam.GaussianBayesTreeClique, dict[int, int], np.ndarray]] = [
        (root, {}, np.zeros((0, 0))) for root in tree.roots()
    ]
    with single_threaded_blas():  # thousands of tiny products: threads only wait on each other
        while stack:
            clique, parent_at, parent_cov = stack.pop()
            cond = clique.conditional()
            ks = [int(k) for k in cond.keys()]  # noqa: SIM118 (a gtsam KeyVector)
            R = np.asarray(cond.R(), dtype=float)
            n_front = R.shape[0]
            r_inv, info = trtri(R, lower=0)
            if info != 0:
                raise RuntimeError(f"indeterminant linear system: a zero pivot in the clique of {ks[0]}")
            at: dict[int, int] = {}  # where each key's block starts in this clique's covariance
            start = 0
            for k in ks:
                at[k] = start
                start += dims[k]
            cov = np.empty((start, start))
            cov[:n_front, :n_front] = r_inv @ r_inv.T
            if start > n_front:  # a separator: its covariance is a block of the parent's
                sep = [j for k in ks if at[k] >= n_front for j in range(parent_at[k], parent_at[k] + dims[k])]
                cov_ss = parent_cov[sep][:, sep]
                a = r_inv @ np.asarray(cond.S(), dtype=float)
                cov_fs = -a @ cov_ss
                cov[:n_front, :n_front] -= cov_fs @ a.T
                cov[:n_front, n_front:] = cov_fs
                cov[n_front:, :n_front] = cov_fs.T
                cov[n_front:, n_front:] = cov_ss
            yield ks, at, n_front, cov
            stack.extend((clique[c], at, cov) for c in range(clique.nrChildren()))


def hat_trace(J: sp.csr_matrix, Z: sp.csr_matrix, rows: np.ndarray) -> float:
    """``tr(H⁻¹ J_rᵀ J_r)``, the hat matrix's trace over the rows ``rows`` of the whitened Jacobian ``J`` (their
    share of the parameters; a row set's redundancy is its count less this), with ``Z`` the
    :func:`selected_inverse` on the blocks of those rows' factors: both are sparse on the same blocks."""
    Jr = J[rows]
    return float((Jr.T @ Jr).multiply(Z).sum())


def factor_row_starts(row_dims: Sequence[int]) -> np.ndarray:
    """Where each factor's rows start in :func:`whitened_system`'s ``J`` (factor order), and the end last."""
    return np.concatenate([[0], np.cumsum(np.asarray(row_dims, dtype=np.int64))])


def whitened_system(linear: gtsam.GaussianFactorGraph) -> tuple[sp.csr_matrix, np.ndarray]:
    """The whitened Jacobian ``J`` (rows in factor order, columns by sorted key as ``sparseJacobian_`` lays them
    out) and right-hand side ``b`` of a Gaussian factor graph."""
    trip = linear.sparseJacobian_()
    ri, ci, v = trip[0].astype(np.int64) - 1, trip[1].astype(np.int64) - 1, trip[2]
    n = int(ci.max())  # the last column is b
    keep = ci < n
    m = int(ri.max()) + 1
    b = np.zeros(m)
    np.add.at(b, ri[~keep], v[~keep])
    return sp.csr_matrix((v[keep], (ri[keep], ci[keep])), shape=(m, n)), b


def sparse_joint_covariance(
    linear: gtsam.GaussianFactorGraph, dims: Mapping[int, int], keys: Iterable[int]
) -> np.ndarray:
    """The joint covariance of ``keys`` (blocks in their order) from the sparse information ``JᵀJ`` of ``linear``,
    one factorisation and one solve per column asked: for when GTSAM's elimination stops (``gtsam.Marginals`` has
    no ordering to change).

    Raises:
        RuntimeError: the information is singular.
    """
    J, _ = whitened_system(linear)
    ordered = sorted(int(k) for k in linear.keyVector())
    offset = dict(zip(ordered, np.cumsum([0] + [dims[k] for k in ordered[:-1]]).tolist(), strict=True))
    want = np.concatenate([np.arange(offset[int(k)], offset[int(k)] + dims[int(k)]) for k in keys])
    try:
        solver = SPDSolver((J.T @ J).tocsc())
    except SingularInformationError as err:
        raise RuntimeError(f"indeterminant linear system: {err}") from err
    rhs = np.zeros((J.shape[1], len(want)))
    rhs[want, np.arange(len(want))] = 1.0
    cov = np.asarray(solver.solve(rhs))[want]
    return 0.5 * (cov + cov.T)
