"""Mu et al. Alg. 1 as written (dense, every candidate's entropy from scratch): the reference the fast greedy
(:func:`stages.estimation.measurement_selection.select_information`) is checked against. Tests only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp

from stages.estimation.linear_system import LinearSystem

FloatArray = npt.NDArray[np.float64]


def reference_greedy(
    system: LinearSystem,
    candidates: Sequence[int],
    focused: Sequence[int],
    budget: int,
    base: Sequence[int],
    landmark_prior_sigma: float = 100.0,
) -> tuple[list[int], FloatArray]:
    """Alg. 1 as written: for every candidate, recompute ½ log det(W Λ⁻¹ Wᵀ) from scratch (dense)."""
    used = sorted({v for f in list(base) + list(candidates) for v in system.factors[f].variables} | set(focused))
    cols = system.columns(used)
    fidx = np.searchsorted(cols, system.columns(focused))
    lms = [v for v in used if system.variables[v].kind == "landmark"]
    lam = (system.information(base) + system.diagonal_prior(lms, landmark_prior_sigma)).toarray()[np.ix_(cols, cols)]
    infos = {c: system.information([c]).toarray()[np.ix_(cols, cols)] for c in candidates}

    E = np.zeros((len(cols), len(fidx)))
    E[fidx, np.arange(len(fidx))] = 1.0

    def entropy(L: FloatArray) -> float:
        cov_f = sla.cho_solve(sla.cho_factor(L), E)[fidx]  # the focused columns of L⁻¹, from a dense Cholesky
        return 0.5 * float(np.linalg.slogdet(cov_f)[1])

    return _greedy(entropy, lam, infos, candidates, budget)


def reference_greedy_logdet(
    system: LinearSystem,
    candidates: Sequence[int],
    focused: Sequence[int],
    budget: int,
    base: Sequence[int],
    landmark_prior_sigma: float = 100.0,
) -> tuple[list[int], FloatArray]:
    """Alg. 1 as written in information form: every candidate's focused entropy from two sparse log-determinants,
    ``log det Σ_F = log det Λ_UU − log det Λ`` (``U`` the other columns), so no covariance is ever formed. For graphs
    whose covariances span too many orders of magnitude to be trusted (6-dof tags to millimetres on a weakly tied
    3D chain), where :func:`reference_greedy`'s dense ``Λ⁻¹`` columns are themselves off."""
    from stages.estimation.sparse_cov import SPDSolver

    used = sorted({v for f in list(base) + list(candidates) for v in system.factors[f].variables} | set(focused))
    cols = system.columns(used)
    fidx = np.searchsorted(cols, system.columns(focused))
    other = np.setdiff1d(np.arange(len(cols)), fidx)
    lms = [v for v in used if system.variables[v].kind == "landmark"]
    lam = sp.csc_matrix((system.information(base) + system.diagonal_prior(lms, landmark_prior_sigma))[cols][:, cols])
    infos = {c: sp.csc_matrix(system.information([c])[cols][:, cols]) for c in candidates}

    def entropy(L: sp.csc_matrix) -> float:
        ld_all = SPDSolver(L, backend="superlu").logdet()
        ld_other = SPDSolver(sp.csc_matrix(L[other][:, other]), backend="superlu").logdet()
        return 0.5 * (ld_other - ld_all)

    return _greedy(entropy, lam, infos, candidates, budget)


def _greedy(
    entropy: Callable[[Any], float], lam: Any, infos: dict[int, Any], candidates: Sequence[int], budget: int
) -> tuple[list[int], FloatArray]:
    """Alg. 1's loop: ``budget`` times, the candidate whose information lowers ``entropy`` most, and that drop."""
    picks: list[int] = []
    gains: list[float] = []
    for _ in range(budget):
        h = entropy(lam)
        best = max(((h - entropy(lam + infos[c]), c) for c in candidates if c not in picks), key=lambda t: t[0])
        picks.append(best[1])
        gains.append(best[0])
        lam = lam + infos[best[1]]
    return picks, np.array(gains)
