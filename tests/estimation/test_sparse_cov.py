"""SPDSolver's memory: solvers made and dropped one after another do not pile up memory (cholespy's solve buffer)."""

from __future__ import annotations

import gc
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from stages.estimation import sparse_cov
from stages.estimation.sparse_cov import SPDSolver
from tests.fixtures.memory import resident_mib

STATUS = Path("/proc/self/status")


@pytest.mark.skipif(not sparse_cov._HAVE_CHOLESPY or not STATUS.exists(), reason="CHOLMOD backend and Linux /proc")
def test_dropped_solvers_give_back_their_solve_buffers() -> None:
    """cholespy 2.2 keeps an n × columns buffer of its last solve that its destructor does not free; SPDSolver shrinks
    it before it goes. Twelve solvers of 20,000 unknowns each solving 100 columns would otherwise keep 180 MB."""
    n, cols, solvers = 20_000, 100, 12
    A = sp.diags([np.full(n - 1, -1.0), np.full(n, 4.0), np.full(n - 1, -1.0)], [-1, 0, 1], format="csc")
    B = np.random.default_rng(0).standard_normal((n, cols))
    want = SPDSolver(A, backend="superlu").solve(B)
    first = SPDSolver(A).solve(B)  # warm up: the allocator's first pools
    del first
    gc.collect()
    before = resident_mib()
    for _ in range(solvers):
        x = SPDSolver(A).solve(B)
        np.testing.assert_allclose(x, want, rtol=1e-10, atol=1e-12)
        del x
        gc.collect()
    leaked_each = n * cols * 8 / 2**20
    assert resident_mib() - before < 0.25 * solvers * leaked_each


def test_covariance_blocks_solved_in_small_chunks_equal_the_inverse(monkeypatch: pytest.MonkeyPatch) -> None:
    """covariance_blocks solves its dense right-hand sides SOLVE_CHUNK_BYTES at a time (memory on long graphs): with
    chunks of a few columns the blocks are the dense inverse's, as with one chunk."""
    rng = np.random.default_rng(5)
    dims = np.array([3] * 12 + [2] * 5)
    offsets = np.concatenate([[0], np.cumsum(dims)]).astype(np.int64)
    n = int(offsets[-1])
    J = sp.random(3 * n, n, density=0.08, random_state=7, format="csc") + sp.eye(3 * n, n)
    info = sp.csc_matrix(J.T @ J + 0.5 * sp.eye(n))
    dense = np.linalg.inv(info.toarray())
    pairs = [(int(i), int(j)) for i in range(len(dims)) for j in rng.choice(len(dims), 4, replace=False)]
    whole = sparse_cov.covariance_blocks(info, offsets, pairs)
    assert len(sparse_cov._column_chunks(list(range(len(dims))), dims, n)) == 1
    monkeypatch.setattr(sparse_cov, "SOLVE_CHUNK_BYTES", 8 * n * 5)  # 5 columns: one or two variables a chunk
    assert len(sparse_cov._column_chunks(list(range(len(dims))), dims, n)) >= 8
    chunked = sparse_cov.covariance_blocks(info, offsets, pairs)
    for i, j in pairs:
        block = dense[offsets[i] : offsets[i + 1], offsets[j] : offsets[j + 1]]
        np.testing.assert_allclose(chunked[(i, j)], block, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(chunked[(i, j)], whole[(i, j)], rtol=1e-12, atol=1e-14)


def test_covariance_blocks_read_pair_by_pair_equal_the_dict() -> None:
    """CovarianceBlocks answers pairs one at a time (a path component by its recursion, another by solves, zero across
    components) with the same blocks as covariance_blocks' dict."""
    rng = np.random.default_rng(2)
    dims = np.array([3] * 10 + [2] * 6 + [1])
    offsets = np.concatenate([[0], np.cumsum(dims)]).astype(np.int64)
    n = int(offsets[-1])
    info = sp.lil_matrix((n, n))
    for v in range(len(dims)):  # a chain 0-9, a triangle 10-12, a pair 13-14, singletons 15, 16
        sl = slice(offsets[v], offsets[v + 1])
        info[sl, sl] = 4.0 * np.eye(dims[v])
    for u, v in [(i, i + 1) for i in range(9)] + [(10, 11), (11, 12), (10, 12), (13, 14)]:
        info[offsets[u] : offsets[u + 1], offsets[v] : offsets[v + 1]] = 0.3 * rng.standard_normal((dims[u], dims[v]))
    info = sp.csc_matrix(info + info.T)
    pairs = [(int(i), int(j)) for i in range(len(dims)) for j in rng.choice(len(dims), 5, replace=False)]
    blocks = sparse_cov.CovarianceBlocks(info, offsets, {v for p in pairs for v in p}, iter(pairs))
    whole = sparse_cov.covariance_blocks(info, offsets, pairs)
    dense = np.linalg.inv(info.toarray())
    for i, j in pairs:
        np.testing.assert_array_equal(blocks[(i, j)], whole[(i, j)])
        block = dense[offsets[i] : offsets[i + 1], offsets[j] : offsets[j + 1]]
        np.testing.assert_allclose(blocks[(i, j)], block, rtol=1e-9, atol=1e-12)


def test_superlu_takes_a_surveyed_prior_beside_a_weak_one_and_still_finds_an_unobserved_direction() -> None:
    """SuperLU's positive-definiteness check judges each pivot against its own diagonal: a chain of 6-dof poses held
    by a 1e-6 prior (information 1e12) beside a landmark that only the weak 100 m prior holds (1e-4), as in a rig's
    ``Λ₀`` with a surveyed tag, is positive definite and ``marginal_logdet`` is the dense value (it stopped with "not
    positive definite": every pivot was compared with 1e-13 of the largest diagonal); a chain with a free gauge
    still stops."""
    from stages.estimation.sparse_cov import SingularInformationError, marginal_logdet

    rng = np.random.default_rng(2)
    n, d = 12, 6
    J = sp.lil_matrix(((n - 1) * d, (n + 1) * d))
    for k in range(n - 1):
        J[k * d : (k + 1) * d, k * d : (k + 2) * d] = np.hstack([-np.eye(d), np.eye(d)]) + 0.05 * rng.standard_normal(
            (d, 2 * d)
        )
    free = sp.csc_matrix(J.T @ J)
    priors = np.zeros((n + 1) * d)
    priors[:d] = 1e12  # the first pose surveyed to 1e-6 m and rad
    priors[-d:] = 1e-4  # the landmark: the weak prior only
    info = sp.csc_matrix(free + sp.diags(priors))
    cols = np.arange((n - 1) * d, (n + 1) * d)  # the last pose and the landmark
    dense = np.linalg.slogdet(np.linalg.inv(info.toarray())[np.ix_(cols, cols)])[1]
    assert marginal_logdet(info, cols) == pytest.approx(dense, abs=1e-6)
    with pytest.raises(SingularInformationError):
        SPDSolver(sp.csc_matrix(free + sp.diags(np.r_[np.zeros(n * d), np.full(d, 1e-4)])), backend="superlu")
