"""Stage two of focused inference: choose the measurements that best localise the focused variables.

Maths (Mu et al. 2015, Problem 2 and Theorem 1). With the information ``Λ_S = Λ₀ + Σ_{j∈S} A_jᵀ A_j``
of the picks ``S``, ``Σ = Λ_S⁻¹`` and the focused block ``Σ_F = W Σ Wᵀ``, adding candidate ``c``
(whitened Jacobian ``A_c``, ``m`` rows) reduces the focused entropy by::

    gain_c = ½ log det S_c − ½ log det(S_c − U_cᵀ Σ_F⁻¹ U_c),
    S_c = I + A_c Σ A_cᵀ,   U_c = W Σ A_cᵀ

(matrix inversion lemma on ``Σ_{S+c}`` and ``det(Σ_F − U S⁻¹ Uᵀ) = det Σ_F · det(S − UᵀΣ_F⁻¹U) / det S``).
After picking ``j`` with ``V = Σ A_jᵀ`` and ``T = S_j``, ``Σ ← Σ − V T⁻¹ Vᵀ``, so for every candidate,
with ``g_c = A_c V`` and ``w = W V``::

    M_c ← M_c − g_c T⁻¹ g_cᵀ               (M_c = A_c Σ A_cᵀ)
    U_c ← U_c − w T⁻¹ g_cᵀ
    Σ_F ← Σ_F − w T⁻¹ wᵀ
    P   ← P + p E⁻¹ pᵀ,  p = P w,  E = T − wᵀ P w        (P = Σ_F⁻¹, Woodbury)
    R_c ← R_c + p E⁻¹ (wᵀ R_c − g_cᵀ)                  (R_c = P U_c, so U_cᵀ Σ_F⁻¹ U_c = U_cᵀ R_c)

The implementation (:func:`select_information`) evaluates the same gain in the equivalent
mutual-information form (``S_c − U_cᵀ Σ_F⁻¹ U_c = I + A_c Σ_{·|F} A_cᵀ``) with one tracked covariance:
``Σ`` only at the rows the gains read (the exact Schur complement of ``Λ₀`` onto the candidates' and
focused columns plus the picks), one sparse solve per step from the last factorisation plus a
Woodbury window over the picks since (a second one when more than 128 columns are focused), and
``O(N_candidates · m² · d)`` small dense work. When the candidates' columns cover most of the state, the
capacitance form instead (two solves per step with the factor of the whole compact graph, whose size
does not depend on the candidates). No dense ``n × n`` matrix is ever formed.

When every candidate touches only focused variables (a pose graph's loop closures with the poses
focused), ``Σ_{·|F} A_cᵀ = 0`` so ``K_c = 0`` and the gain is ``½ log det(I + A_c Σ A_cᵀ)``: nothing of
``Σ_F`` is needed, and the focused entropy comes from two sparse log-determinants,
``log det Σ_F = log det Λ_UU − log det Λ`` (``U`` the other variables). That is the path for focusing
thousands of pose columns, where a dense ``Σ_F`` would not fit.

Initial information ``Λ₀`` = the base factors (odometry and prior) plus a weak isotropic prior of
standard deviation ``landmark_prior_sigma`` on every landmark variable, so landmarks that the base
leaves unobserved have finite, comparable first gains.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp

from stages.estimation.blas import single_threaded_blas
from stages.estimation.gaussian import entropy_from_logdet
from stages.estimation.linear_system import Factor, LinearSystem, SparseMatrix, unanchored_poses
from stages.estimation.sparse_cov import (
    CovarianceBlocks,
    SPDSolver,
    _variable_graph,
    covariance_blocks,
    covariance_blocks_schur,
    logdet_spd,
    marginal_logdet,
    schur_complement,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

SelectionStatus = Literal["ok", "budget_zero", "budget_exceeds_candidates", "no_candidates"]
Measure = Literal["logdet", "trace", "max_eig"]


@dataclass
class MeasurementSelection:
    """Result of a measurement selection."""

    picks: list[int]
    """Factor indices (of the input system) in the order picked."""
    gains: list[float]
    """Score at each pick: entropy reduction in nats (``information``), sampling probability
    (``leverage``), NaN for strategies without a score."""
    status: SelectionStatus
    """``budget_zero``: nothing kept; ``budget_exceeds_candidates``: every candidate kept."""
    n_candidates: int
    budget: int
    entropy_before: float = float("nan")
    """Differential entropy (nats) of the focused variables under ``Λ₀``: ``½ log det(2πe Σ_F)``."""
    entropy_after: float = float("nan")
    """The same with the picks added."""
    stats: dict[str, float] = field(default_factory=dict)
    """Timings (s) and counters."""


@dataclass
class _Problem:
    """A compact sub-system: only the variables that the base, candidates and focus touch."""

    system: LinearSystem
    base: list[int]
    candidates: list[int]
    focused: list[int]
    prior: sp.csc_matrix
    info0: sp.csc_matrix
    landmark_vars: list[int]
    full_focus: bool = False
    """Every candidate touches only focused variables: ``K_c = 0``, no ``Σ_F`` tracked (``focused`` is then empty)."""


def _compact_problem(
    system: LinearSystem,
    base: Sequence[int],
    candidates: Sequence[int],
    focused: Sequence[int],
    landmark_prior_sigma: float,
) -> _Problem:
    used: dict[int, None] = {}
    for f in list(base) + list(candidates):
        for v in system.factors[f].variables:
            used[v] = None
    for v in focused:
        used[int(v)] = None
    var_ids = sorted(used)
    remap = {v: k for k, v in enumerate(var_ids)}
    variables = [system.variables[v] for v in var_ids]
    fac_ids = list(base) + list(candidates)
    factors = [
        Factor(tuple(remap[v] for v in system.factors[f].variables), system.factors[f].jacobian, system.factors[f].kind)
        for f in fac_ids
    ]
    sub = LinearSystem(variables, factors)
    nb = len(base)
    landmark_vars = sub.variables_of_kind("landmark")
    prior = weak_prior(sub, range(nb), landmark_prior_sigma)
    info0 = sp.csc_matrix(sub.information(range(nb)) + prior)
    return _Problem(
        sub,
        list(range(nb)),
        list(range(nb, len(fac_ids))),
        [remap[int(v)] for v in focused],
        prior,
        info0,
        landmark_vars,
    )


def weak_prior(system: LinearSystem, base: Iterable[int], landmark_prior_sigma: float) -> sp.csc_matrix:
    """The weak prior of ``Λ₀``: ``landmark_prior_sigma`` (rotation capped, :func:`landmark_prior_sigmas`) on every
    landmark, and on the first pose of every group that the ``base`` factors leave without an anchor."""
    landmark_vars = system.variables_of_kind("landmark")
    weak = landmark_vars + unanchored_poses(system, list(base), landmark_vars)
    return system.diagonal_prior(weak, landmark_prior_sigma) if weak else sp.csc_matrix((system.dim, system.dim))


def default_base(system: LinearSystem, candidates: Sequence[int]) -> list[int]:
    """Every factor that is not a candidate and not a landmark measurement (odometry, priors, ...)."""
    cand = set(candidates)
    return [i for i, f in enumerate(system.factors) if i not in cand and f.kind != "landmark" and f.rows]


FOCUSED_SOLVE_COLUMNS = 32
"""Identity columns solved at once for ``Σ`` at the focused columns: the right-hand side, the solution and the
solver's buffer are each ``n ×`` this many, not ``n × f``, whatever the focus."""


def _focused_cov(solver: SPDSolver, n: int, fcols: IntArray, keep: bool = True) -> tuple[FloatArray, FloatArray]:
    """``(XF, Σ_F)``: ``Σ`` at the focused columns (``n × f``; ``n × 0`` unless ``keep``) and its focused block."""
    f = len(fcols)
    XF = np.empty((n, f)) if keep else np.empty((n, 0))
    SF = np.empty((f, f))
    for j in range(0, f, FOCUSED_SOLVE_COLUMNS):
        cols = np.arange(j, min(f, j + FOCUSED_SOLVE_COLUMNS))
        E = np.zeros((n, len(cols)))
        E[fcols[cols], np.arange(len(cols))] = 1.0
        X = solver.solve(E)
        SF[:, cols] = X[fcols]
        if keep:
            XF[:, cols] = X
    return XF, 0.5 * (SF + SF.T)


def _budget_status(budget: int, n: int) -> SelectionStatus | None:
    if n == 0:
        return "no_candidates"
    if budget <= 0:
        return "budget_zero"
    if budget >= n:
        return "budget_exceeds_candidates" if budget > n else None
    return None


DENSE_FOCUS_MAX = 1024
"""Up to this many focused columns, entropies come from the dense ``Σ_F``; above, from sparse log-determinants."""


def _sparse_focused_entropy(info: sp.csc_matrix, fcols: IntArray) -> float:
    """``½ log det(2πe Σ_F)`` from sparse log-determinants (no dense ``Σ_F``)."""
    return entropy_from_logdet(marginal_logdet(info, fcols), len(fcols))


def focused_entropy(
    system: LinearSystem,
    factors: Sequence[int],
    focused: Sequence[int],
    landmark_prior_sigma: float = 100.0,
) -> float:
    """Entropy (nats) of the focused variables given the factors (plus the weak landmark prior)."""
    prob = _compact_problem(system, factors, [], focused, landmark_prior_sigma)
    fcols = prob.system.columns(prob.focused)
    if len(fcols) > DENSE_FOCUS_MAX:
        return _sparse_focused_entropy(prob.info0, fcols)
    solver = SPDSolver(prob.info0)
    _, SF = _focused_cov(solver, prob.system.dim, fcols, keep=False)
    return entropy_from_logdet(logdet_spd(SF), len(fcols))


def _within_focus(sub: LinearSystem, candidates: Sequence[int], fcols: IntArray) -> bool:
    """Every candidate's columns are focused columns."""
    focused = np.zeros(sub.dim, dtype=bool)
    focused[fcols] = True
    return all(focused[sub.factor_columns(c)].all() for c in candidates)


def _padded_candidates(sub: LinearSystem, cand: Sequence[int]) -> tuple[FloatArray, IntArray]:
    m = max(sub.factors[c].rows for c in cand)
    d = max(sub.factors[c].jacobian.shape[1] for c in cand)
    Ac = np.zeros((len(cand), m, d))
    cols = np.zeros((len(cand), d), dtype=np.int64)
    for k, c in enumerate(cand):
        J = sub.factors[c].jacobian
        Ac[k, : J.shape[0], : J.shape[1]] = J
        cc = sub.factor_columns(c)
        cols[k, : len(cc)] = cc
    return Ac, cols


def _clique_pairs(sub: LinearSystem, cand: Sequence[int]) -> Iterator[tuple[int, int]]:
    """Every (variable, variable) pair of every candidate's clique, in order."""
    for c in cand:
        vs = sub.factors[c].variables
        for a in vs:
            for b in vs:
                yield a, b


def _fill_cliques(
    blocks: CovarianceBlocks | dict[tuple[int, int], FloatArray], sub: LinearSystem, cand: Sequence[int], d: int
) -> FloatArray:
    """``Σ[cols_c, cols_c]`` for every candidate (padded to ``d × d``) from the blocks of its variable pairs."""
    out = np.zeros((len(cand), d, d))
    for k, c in enumerate(cand):
        vs = sub.factors[c].variables
        off = np.concatenate([[0], np.cumsum([sub.variables[v].dim for v in vs])])
        for ia, a in enumerate(vs):
            for ib, b in enumerate(vs):
                out[k, off[ia] : off[ia + 1], off[ib] : off[ib + 1]] = blocks[(a, b)]
    return out


def _clique_blocks(info: sp.csc_matrix, sub: LinearSystem, cand: Sequence[int], solver: SPDSolver) -> CovarianceBlocks:
    """The covariance blocks of ``info⁻¹`` at the candidates' cliques, read pair by pair (:class:`CovarianceBlocks`:
    no small array per pair is kept)."""
    variables = {v for c in cand for v in sub.factors[c].variables}
    return CovarianceBlocks(info, sub.offsets, variables, _clique_pairs(sub, cand), solver=solver)


def _clique_covariances(
    info: sp.csc_matrix,
    sub: LinearSystem,
    cand: Sequence[int],
    d: int,
    separator: Sequence[int] | None,
    solver: SPDSolver | None = None,
) -> FloatArray:
    """``Σ[cols_c, cols_c]`` for every candidate (padded to ``d × d``)."""
    pairs = list(_clique_pairs(sub, cand))
    if separator:
        blocks = covariance_blocks_schur(info, sub.offsets, pairs, separator)
    else:
        blocks = covariance_blocks(info, sub.offsets, pairs, solver=solver)
    return _fill_cliques(blocks, sub, cand, d)


@dataclass(frozen=True)
class TrackerOptions:
    """How :func:`select_information` keeps ``Σ_S`` between sparse factorisations: the same picks and gains every
    way (tested against the dense reference), at different costs. The defaults are the measured best."""

    tracker: Literal["auto", "window", "capacitance"] = "capacitance"
    """``window``: a sequential Woodbury window stored at the tracked rows, on the Schur-reduced system (cost grows
    with the candidates' rows); ``capacitance``: nothing stored at the tracked rows, two solves per step with the
    last factor of the whole compact graph (cost fixed by the graph; see :class:`_CapacitanceTracker`); ``auto``:
    ``capacitance`` once the candidates' and focused columns exceed ``capacitance_above`` of the state, else
    ``window``.

    Default ``capacitance``: its time per step is flat in the number of candidates (issue 6's target: 1.20-1.29x
    from 1,000 to 10,000 candidates) and the whole greedy stays within 5x of one GTSAM optimise plus marginals
    (0.6x for K=90, 2.6x for K=1000). ``auto`` is up to 4x cheaper per step on small candidate sets (the
    Schur-reduced window), at the price of a step cost that grows with the candidates."""
    capacitance_above: float = 0.75
    """``auto``: the fraction of the state above which the capacitance tracker is used. Measured on the benchmark
    graph (all landmarks focused, 100 steps): window 0.64 ms/step at 9% of the state and 2.5–2.7 at 77%, 3.0–3.5
    on the whole graph; capacitance 2.3 and 2.7–3.0 ms/step (flat): they tie near 75%."""
    track_focused_max: int = 128
    """``window``: up to this many focused columns, ``Σ Wᵀ`` is kept at the tracked rows instead of solved for
    per step."""
    reduce_below: float = 1.0
    """``window``: track the Schur complement of ``Λ₀`` onto the candidates' and focused columns when they are
    fewer than this fraction of the state (measured: worth it even at 77% of the state, 4.9 vs 7.2 ms/step)."""
    refactor_on_first_observation: bool = False
    """``capacitance``: also refactorise right after a pick that observes a landmark that ``Λ_last`` holds only
    through the weak prior (the pick that makes ``C`` ill-conditioned, cond ~1e6). Not needed for exactness once
    ``C`` is kept as a Cholesky factor (measured: same picks, gains within 1e-8 of the dense reference either
    way), and costly when most picks are first observations."""
    recompute_tol: float = 1e-4
    """Nats: when the pick is in doubt by more than this (its gain's error bound, :class:`_Precision`, or another
    candidate within the bounds), the tracked quantities are recomputed from the information of the picks so far.
    ``inf``: never (the bare downdates). Measured (bench graph, K=1000): 1e-6 needs 25 recomputations of ~1,000
    candidates each (4x the time), 1e-4 15 (2x), with the same picks."""


class _Refactorising:
    """What both trackers share: the sparse factor of ``Λ_last``, the picks since it, and when to refactorise.

    Refactorisation: every ``refactor_every`` picks, or (``None``) once the window's work since the last
    factorisation has cost as much as that factorisation did (at most ``max_window`` picks).
    """

    def __init__(
        self,
        info: sp.csc_matrix,
        m: int,
        add_info: Callable[[list[int]], SparseMatrix],
        refactor_every: int | None,
        max_window: int,
    ) -> None:
        self.info = info
        self.n = int(info.shape[0])
        self.m = m
        self.add_info = add_info
        self.fixed = refactor_every
        self.cap = max(1, refactor_every or max_window)
        self.window: list[int] = []
        self.refactorisations = 0
        self.factor_s = 0.0
        self.t_window = 0.0
        self._factorise()

    def _factorise(self) -> None:
        tf = time.perf_counter()
        self.solver = SPDSolver(self.info)
        self.t_factor = time.perf_counter() - tf
        self.factor_s += self.t_factor

    def _window_full(self) -> bool:
        return len(self.window) == self.cap or (self.fixed is None and self.t_window > self.t_factor)

    def _refactorise(self) -> None:
        """Fold the window's picks into ``Λ_last`` and factorise it again."""
        self.info = sp.csc_matrix(self.info + self.add_info(self.window))
        self._factorise()
        self.t_window = 0.0
        self.window = []
        self.refactorisations += 1


class _Tracker(_Refactorising):
    """``Σ_S b`` at the rows ``rows`` of the state, for sparse right-hand sides, kept exact as picks join ``Λ_S``.

    ``Σ_S = Λ_S⁻¹`` with ``Λ_S = Λ_last + Σ_{i in window} A_iᵀ A_i``: a sparse factorisation of
    ``Λ_last`` (the information at the last refactorisation) plus the sequential Woodbury correction
    ``Σ_S = Σ_last − Σ_i V_i T_i⁻¹ V_iᵀ`` over the picks since, ``V_i = Σ_{i-1} A_iᵀ``. Only the rows
    that the gains read (the candidates' and the focused columns) of each ``V_i`` are stored, and the
    correction of ``Σ_S b`` needs ``V_iᵀ b``, i.e. the stored rows at the nonzeros of ``b``. For a
    window cost growing linearly with its length, the adaptive refactorisation schedule has the least
    total cost.
    """

    def __init__(
        self,
        info: sp.csc_matrix,
        rows: IntArray | None,
        m: int,
        add_info: Callable[[list[int]], SparseMatrix],
        refactor_every: int | None,
        max_window: int = 256,
    ) -> None:
        super().__init__(info, m, add_info, refactor_every, max_window)
        self.rows = rows  # None: ``info`` is already the (Schur-reduced) information of the tracked rows
        n_rows = self.n if rows is None else len(rows)
        self.win = np.empty((self.cap * m, n_rows))  # Vᵢᵀ at ``rows``, m rows per pick
        self.win_Tinv = np.empty((self.cap, m, m))

    def solve(self, nz: IntArray, vals: FloatArray, nz_pos: IntArray) -> FloatArray:
        """``(Σ_S b)ᵀ`` at ``rows`` (shape ``q × len(rows)``) for ``b`` with rows ``vals`` at ``nz`` (``q`` columns).

        ``nz_pos``: the positions of ``nz`` in ``rows``.
        """
        rhs = np.zeros((self.n, vals.shape[1]))
        rhs[nz if self.rows is not None else nz_pos] = vals
        x = self.solver.solve(rhs)
        out = np.ascontiguousarray((x if self.rows is None else x[self.rows]).T)
        k = len(self.window)
        if k:
            tw = time.perf_counter()
            km = k * self.m
            q = vals.shape[1]
            vtb = self.win[:km, nz_pos] @ vals  # (k m, q): Vᵢᵀ b over the window
            coef = np.matmul(self.win_Tinv[:k], vtb.reshape(k, self.m, q)).reshape(km, q)
            out -= coef.T @ self.win[:km]
            self.t_window += time.perf_counter() - tw
        return out

    def add(self, j: int, Vt: FloatArray, Tinv: FloatArray) -> bool:
        """Add pick ``j`` (``Vt = (Σ_S A_jᵀ)ᵀ`` at ``rows``, ``Tinv = (I + A_j Σ_S A_jᵀ)⁻¹``); True if refactorised."""
        k = len(self.window)
        self.win[k * self.m : (k + 1) * self.m] = Vt
        self.win_Tinv[k] = Tinv
        self.window.append(j)
        if self._window_full():
            self._refactorise()
            return True
        return False


class _CapacitanceTracker(_Refactorising):
    """Solves with ``Λ_S = Λ_last + A_Wᵀ A_W`` (the picks ``W`` since the last factorisation).

    Capacitance form: ``Σ_S b = Σ_last (b − A_Wᵀ C⁻¹ A_W Σ_last b)``, ``C = I + A_W Σ_last A_Wᵀ``
    (``k m × k m``). ``C`` is kept as its Cholesky factor, bordered by each pick: with
    ``u = A_W Σ_last A_jᵀ`` and ``l = L⁻¹ u`` the new row is ``[lᵀ, chol(T_j)]``, where
    ``T_j = I + A_j Σ_last A_jᵀ − lᵀ l = I + A_j Σ_S A_jᵀ`` is the pick's own ``T``. Stored per pick: its
    columns, its Jacobian and ``W Σ_last A_jᵀ``; nothing of the size of the state or of the candidates.
    """

    def __init__(
        self,
        info: sp.csc_matrix,
        m: int,
        d: int,
        fcols: IntArray,
        add_info: Callable[[list[int]], SparseMatrix],
        refactor_every: int | None,
        weak: npt.NDArray[np.bool_] | None,
        refactor_on_first_observation: bool = False,
        max_window: int = 256,
    ) -> None:
        super().__init__(info, m, add_info, refactor_every, max_window)
        self.refactor_on_first_observation = refactor_on_first_observation
        self.cols = np.zeros((self.cap, d), dtype=np.int64)
        self.A = np.zeros((self.cap, m, d))
        self.WX = np.zeros((len(fcols), self.cap * m))  # W Σ_last A_iᵀ
        self.L = np.zeros((self.cap * m, self.cap * m))  # Cholesky factor of C
        self.weak = weak  # per compact column: only the weak prior in Λ_last
        self.first_observation_refactorisations = 0

    def solve_last(self, rhs: FloatArray) -> FloatArray:
        return self.solver.solve(rhs)

    def gather(self, x: FloatArray) -> FloatArray:
        """``A_W x`` (``k m × q``)."""
        k = len(self.window)
        return np.matmul(self.A[:k], x[self.cols[:k]]).reshape(k * self.m, x.shape[1])

    def lsolve(self, u: FloatArray) -> FloatArray:
        km = len(self.window) * self.m
        return sla.solve_triangular(self.L[:km, :km], u, lower=True, check_finite=False)

    def ltsolve(self, v: FloatArray) -> FloatArray:
        km = len(self.window) * self.m
        return sla.solve_triangular(self.L[:km, :km], v, lower=True, trans="T", check_finite=False)

    def scatter(self, y: FloatArray, rhs: FloatArray) -> None:
        """``rhs += A_Wᵀ y``."""
        k = len(self.window)
        vals = np.matmul(np.swapaxes(self.A[:k], 1, 2), y.reshape(k, self.m, y.shape[1]))
        np.add.at(rhs, self.cols[:k].ravel(), vals.reshape(-1, y.shape[1]))

    def add(self, j: int, cols: IntArray, A: FloatArray, wx: FloatArray, lt: FloatArray, T: FloatArray) -> bool:
        k = len(self.window)
        km, m = k * self.m, self.m
        self.L[km : km + m, :km] = lt
        self.L[km : km + m, km : km + m] = np.linalg.cholesky(0.5 * (T + T.T))
        self.cols[k] = cols
        self.A[k] = A
        self.WX[:, km : km + m] = wx
        self.window.append(j)
        first = False
        if self.weak is not None:
            nzc = cols[np.any(A != 0, axis=0)]
            first = bool(self.weak[nzc].any())
            self.weak[nzc] = False
        if first and self.refactor_on_first_observation:
            self.first_observation_refactorisations += 1
        elif not self._window_full():
            return False
        self._refactorise()
        return True


def _candidate_operator(Ac: FloatArray, tcols: IntArray, n: int) -> sp.csr_matrix:
    """Sparse ``B`` (``m N × n``) with row ``a N + c`` = row ``a`` of ``A_c`` at its tracked columns.

    ``B @ Z`` gives ``A_c Z[cols_c]`` for every candidate in one sparse product, as ``(m, N, q)``.
    """
    N, m, d = Ac.shape
    rows = np.broadcast_to((np.arange(m)[:, None] * N + np.arange(N)[None, :])[:, :, None], (m, N, d))
    cols = np.broadcast_to(tcols[None], (m, N, d))
    vals = np.ascontiguousarray(Ac.transpose(1, 0, 2))
    keep = vals != 0
    B = sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(m * N, n))
    B.sum_duplicates()
    return B


def _sym_pairs(m: int) -> list[tuple[int, int]]:
    return [(a, b) for a in range(m) for b in range(a, m)]


def _det_eye_plus_sym(U: FloatArray, m: int) -> FloatArray:
    """``det(I + M_c)`` for symmetric ``M_c`` stored as its upper triangle (``(m(m+1)/2, N)``, row-major pairs)."""
    if m == 1:
        return 1.0 + U[0]
    if m == 2:
        return (1.0 + U[0]) * (1.0 + U[2]) - U[1] * U[1]
    if m == 3:
        a, b, c, e, f_, g = 1.0 + U[0], U[1], U[2], 1.0 + U[3], U[4], 1.0 + U[5]
        return a * (e * g - f_ * f_) - b * (b * g - f_ * c) + c * (b * f_ - e * c)
    full = np.empty((U.shape[1], m, m))
    for k, (a, b) in enumerate(_sym_pairs(m)):
        full[:, a, b] = U[k]
        full[:, b, a] = U[k]
    full += np.eye(m)[None]
    sign, ld = np.linalg.slogdet(full)
    return np.where(sign > 0, np.exp(ld), 0.0)


def _slogdet_eye_plus_sym(U: FloatArray, m: int) -> tuple[FloatArray, FloatArray]:
    """Sign and ``log det(I + M_c)`` for symmetric ``M_c`` stored as its upper triangle (``(m(m+1)/2, N)``)."""
    full = np.empty((U.shape[1], m, m))
    for k, (a, b) in enumerate(_sym_pairs(m)):
        full[:, a, b] = U[k]
        full[:, b, a] = U[k]
    full += np.eye(m)[None]
    return np.linalg.slogdet(full)


def _inv_at_least_identity(A: FloatArray) -> FloatArray:
    """Inverse of ``T = I + A Σ Aᵀ`` or ``E = I + A Σ_{·|F} Aᵀ``, both ``⪰ I`` exactly.

    ``E = T − wᵀ Σ_F⁻¹ w`` is a difference of large, nearly equal matrices when the pick observes a landmark known
    only through the weak prior (3D tags, σ 100 m: ``T`` ~ 1e8); the rounding can leave an eigenvalue below 1 or even
    negative. Then the eigenvalues are clipped to 1 (the constraint the exact matrix meets) before inverting;
    otherwise the plain inverse, as before."""
    S = 0.5 * (A + A.T)
    if np.linalg.eigvalsh(S)[0] >= 1.0 - 1e-9:
        return _sym_inv(S)
    lam, V = np.linalg.eigh(S)
    inv = (V / np.maximum(lam, 1.0)) @ V.T
    return 0.5 * (inv + inv.T)


def _sym_inv(A: FloatArray) -> FloatArray:
    inv = np.linalg.inv(0.5 * (A + A.T))
    return 0.5 * (inv + inv.T)


@dataclass
class _Candidates:
    """The candidates' whitened Jacobians, padded to ``m × d``, and where their columns are among the tracked rows."""

    index: list[int]
    """Their factor indices in the compact system."""
    Ac: FloatArray
    """(N, m, d) Jacobians (zero padding)."""
    cols: IntArray
    """(N, d) compact columns (padding: column 0)."""
    width: IntArray
    """(N,) columns actually used."""
    rows: IntArray
    """The rows the gains read: every candidate's columns and the focused ones."""
    pos: IntArray
    """(N, d) positions of ``cols`` in ``rows`` (padding: 0, where the Jacobian is zero)."""
    fpos: IntArray
    """Positions of the focused columns in ``rows``."""


def _candidates(sub: LinearSystem, cidx: list[int], fcols: IntArray) -> _Candidates:
    Ac, cols = _padded_candidates(sub, cidx)
    d = Ac.shape[2]
    width = np.array([len(sub.factor_columns(c)) for c in cidx], dtype=np.int64)
    rows = np.unique(np.concatenate([cols.ravel(), fcols]))
    pos_of = np.full(sub.dim, -1, dtype=np.int64)
    pos_of[rows] = np.arange(len(rows))
    pos = np.where(np.arange(d)[None, :] < width[:, None], pos_of[cols], 0)
    return _Candidates(cidx, Ac, cols, width, rows, pos, pos_of[fcols])


@dataclass
class _Gains:
    """What the gains read, kept current as picks join: ``M_c`` and ``K_c`` (upper triangles), ``Σ_F`` and
    ``P = Σ_F⁻¹``, and the operator ``B`` that applies every ``A_c`` at once."""

    Mu: FloatArray
    """(m(m+1)/2, N) upper triangles of ``M_c = A_c Σ A_cᵀ``."""
    Ku: FloatArray
    """The same of ``K_c = A_c Σ_{·|F} A_cᵀ``."""
    SF: FloatArray
    P: FloatArray
    B: sp.csr_matrix
    pairs: list[tuple[int, int]]
    m: int
    picked: npt.NDArray[np.bool_]


def _solve_accuracy(info: sp.csc_matrix, solver: SPDSolver) -> float:
    """The relative forward error of a solve with ``info`` (max-norm), estimated from one probe: ``x = Λ⁻¹ b``, then
    ``Λ⁻¹ (b − Λ x)``, over ``|x|``. Covariances computed from ``info`` carry absolute errors of this times their
    size; the tracked ``M_c``, ``K_c``, ``Σ_F`` keep those absolute errors while picks shrink them."""
    n = int(info.shape[0])
    if n == 0:
        return float(np.finfo(float).eps)
    b = np.random.default_rng(0).standard_normal(n)
    x = solver.solve(b)
    e = solver.solve(b - info @ x)
    return max(float(np.max(np.abs(e)) / max(float(np.max(np.abs(x))), 1e-300)), float(np.finfo(float).eps))


RESET_FRACTION = 0.01
"""A recomputation also refreshes the candidates whose bound is above this fraction of the tolerance, so that they
do not cause the next one soon after."""


@dataclass
class _Precision:
    """When the tracked ``M_c``, ``K_c`` and ``Σ_F`` have lost too many digits to the downdates.

    Each is a covariance computed from an information matrix (``Λ₀``, or ``Λ_S`` at a recomputation) with a relative
    error ``delta`` (:func:`_solve_accuracy`, about ``cond · ε``), then only downdated (``M_c −= g T⁻¹ gᵀ``, ...): its
    absolute error stays ``delta × its size then`` while the picks shrink its value. A gain reads
    ``log det(I + M_c)``, so its error is at most about ``½ m delta · peak / (1 + now)`` over the diagonal (for
    ``M_c`` and ``K_c``); ``Σ_F`` is inverted (``P``), so its error is relative, ``delta · peak / now``.

    The greedy recomputes, from the information of the picks so far (:func:`_exact_gains`), the candidates whose bound
    exceeds ``tol`` whenever the pick is in doubt (its own bound above ``tol``, or another candidate within the
    bounds), and ``Σ_F`` before ``P`` is re-inverted from it. On camera-only 3D rigs (6-dof tags to millimetres,
    poses tied only by a weak motion prior, a weak landmark prior) ``delta`` is ~1e-9 and ``M_c`` falls from ~1e10 to
    ~10 when a tag is first measured: the downdated gains were then wrong by more than they were worth (3.5 nats of
    drift after 60 picks on a 300-pose rig, picks other than Alg. 1's from the 13th). On well-conditioned graphs
    (the planar sample: ``delta`` ~1e-13) the bounds stay far below ``tol`` and nothing is recomputed."""

    delta: FloatArray
    """Per candidate, the accuracy of the information its ``M_c``, ``K_c`` were last computed from."""
    peak_m: FloatArray
    peak_k: FloatArray
    delta_f: float
    peak_f: FloatArray
    diag: list[int]
    tol: float = 1e-4
    recomputations: int = 0
    recomputed: int = 0
    """Candidates recomputed, summed over the recomputations."""

    @classmethod
    def of(cls, g: _Gains, delta: float, tol: float = 1e-4) -> _Precision:
        diag = [k for k, (a, b) in enumerate(g.pairs) if a == b]
        n = g.Mu.shape[1]
        return cls(np.full(n, delta), g.Mu[diag].copy(), g.Ku[diag].copy(), delta, np.diag(g.SF).copy(), diag, tol)

    def bounds(self, g: _Gains) -> FloatArray:
        """Per candidate, a bound (nats) on its gain's error (``|Δ log det(I + M)| ≤ tr((I + M)⁻¹ ΔM)``)."""
        d = self.diag
        em = np.max(self.peak_m / (1.0 + np.abs(g.Mu[d])), axis=0)
        ek = np.max(self.peak_k / (1.0 + np.abs(g.Ku[d])), axis=0)
        return 0.5 * g.m * self.delta * (em + ek)

    def in_doubt(self, gain: FloatArray, j: int, g: _Gains) -> npt.NDArray[np.bool_] | None:
        """The candidates to recompute when the pick ``j`` could be wrong or its gain off by more than ``tol`` (its
        bound above ``tol``, or another candidate's gain could exceed it within the bounds), else None."""
        e = self.bounds(g)
        e[g.picked] = 0.0
        upper = gain + e
        upper[j] = -np.inf
        if e[j] <= self.tol and not upper.max() > gain[j] - e[j] + self.tol:
            return None
        return e > self.tol * RESET_FRACTION

    def focused_lost(self, g: _Gains) -> bool:
        """``Σ_F`` has lost more than ``tol`` relatively (it is about to be inverted for ``P``)."""
        sf = np.diag(g.SF)
        return bool(sf.size and float(np.max(self.delta_f * self.peak_f / np.maximum(sf, 1e-300))) > self.tol)

    def reset(self, g: _Gains, which: IntArray, delta: float) -> None:
        """``which`` candidates and ``Σ_F`` were just recomputed from an information of accuracy ``delta``."""
        self.delta[which] = delta
        self.peak_m[:, which] = g.Mu[self.diag][:, which]
        self.peak_k[:, which] = g.Ku[self.diag][:, which]
        self.delta_f, self.peak_f = delta, np.diag(g.SF).copy()
        self.recomputations += 1
        self.recomputed += len(which)


SCHUR_MAX_COLUMNS = 4096
"""The recomputation takes the Schur complement onto at most this many separator columns, else it solves."""


SCHUR_SOLVE_COLUMNS = 32
"""Separator columns solved for at once by :func:`_schur_clique_gains` (the right-hand sides, the solution, its
refinement and the solver's buffer are each ``n × columns``: ~460 MB for all 178 of an hour's recording at once)."""


def _chain_separator(info: sp.csc_matrix, sub: LinearSystem, focused: Sequence[int], max_hubs: int = 64) -> list[int]:
    """The variables to take the Schur complement onto so that the rest of ``info``'s block graph is paths: the
    landmarks, the focused variables and the hubs among the others, removed one by one from the most connected while
    some variable has more than two neighbours (at most ``max_hubs``: the shared tag scale, which every picked
    measurement joins). What is still not a path after that (loop closures) is solved for."""
    removed = np.zeros(len(sub.variables), dtype=bool)
    removed[sub.variables_of_kind("landmark")] = True
    removed[list(focused)] = True
    coo = sp.coo_matrix(_variable_graph(info, sub.offsets))
    for _ in range(max_hubs):
        keep = ~removed[coo.row] & ~removed[coo.col]
        degree = np.bincount(coo.row[keep], minlength=len(sub.variables))
        hub = int(np.argmax(degree)) if len(degree) else 0
        if not len(degree) or degree[hub] <= 2:
            break
        removed[hub] = True
    return np.flatnonzero(removed).tolist()


def _schur_clique_gains(
    info: sp.csc_matrix, sub: LinearSystem, separator: list[int], fcols: IntArray, c: _Candidates, which: IntArray
) -> tuple[FloatArray, FloatArray, Iterator[tuple[IntArray, FloatArray, FloatArray]]]:
    """``Σ[:, F]``, ``Σ_F`` and, for the ``which`` candidates, ``M_c = A_c Σ A_cᵀ`` and ``U_c = W Σ A_cᵀ``, all from
    one Schur complement of ``info`` onto the ``separator`` (which holds the focused variables).

    With ``info = [[Λ_rr, Λ_rs], [Λ_sr, Λ_ss]]``, ``X = Λ_rr⁻¹ Λ_rs`` (one solve per separator column) and
    ``C = (Λ_ss − Λ_sr X)⁻¹``: ``Σ_ss = C``, ``Σ_rs = −X C``, ``Σ_rr = Λ_rr⁻¹ + X C Xᵀ``, and the blocks of ``Λ_rr⁻¹``
    come from a block-tridiagonal recursion along the paths of the rest. Linear in the length of the recording where
    ``m`` solves per candidate are quadratic; ``M_c``, ``U_c`` and ``Σ_F`` read the same ``C``, so the differences
    the gains take (``K_c = M_c − U_cᵀ Σ_F⁻¹ U_c``) cancel as they do exactly (a candidate observing a landmark known
    only through the weak prior: ``M_c`` ~1e10, ``K_c`` ~10)."""
    n = sub.dim
    is_s = np.zeros(len(sub.variables), dtype=bool)
    is_s[separator] = True
    s_cols = sub.columns(separator)
    rest = np.flatnonzero(~is_s)
    r_cols = sub.columns(rest.tolist())
    s_pos = np.full(n, -1, dtype=np.int64)
    s_pos[s_cols] = np.arange(len(s_cols))
    r_pos = np.full(n, -1, dtype=np.int64)
    r_pos[r_cols] = np.arange(len(r_cols))
    L_rr = sp.csc_matrix(info[r_cols][:, r_cols])
    L_rs = sp.csc_matrix(info[r_cols][:, s_cols])
    L_ss = info[s_cols][:, s_cols].toarray()
    solver_r = SPDSolver(L_rr)
    X = np.empty((len(r_cols), len(s_cols)))
    for j in range(0, len(s_cols), SCHUR_SOLVE_COLUMNS):  # a few columns at a time: the dense temporaries stay small
        B = L_rs[:, j : j + SCHUR_SOLVE_COLUMNS].toarray()
        Xj = solver_r.solve(B)
        Xj += solver_r.solve(B - L_rr @ Xj)  # one step of iterative refinement
        X[:, j : j + SCHUR_SOLVE_COLUMNS] = Xj
    C = np.linalg.inv(L_ss - np.asarray(L_rs.T @ X))
    del L_rs
    C = 0.5 * (C + C.T)
    XC = _RowProduct(X, C)  # −Σ_rs, by row blocks: only the rows a chunk reads are held
    fs = s_pos[fcols]
    XF = np.empty((n, len(fcols)))
    XF[s_cols] = C[:, fs]
    for i in range(len(XC.bounds) - 1):
        XF[r_cols[XC.bounds[i] : XC.bounds[i + 1]]] = -XC.block(i)[:, fs]
    SF = C[np.ix_(fs, fs)]
    # Λ_rr⁻¹ at the rest-rest pairs of the candidates, by variable blocks, read chunk by chunk
    r_var = np.full(len(sub.variables), -1, dtype=np.int64)
    r_var[rest] = np.arange(len(rest))
    r_off = np.concatenate([[0], np.cumsum([sub.variables[v].dim for v in rest])]).astype(np.int64)

    def own(i: int) -> list[tuple[int, int, int, int]]:
        """The candidate's rest-rest variable pairs (positions among the rest) with their offsets in its clique."""
        vs = sub.factors[c.index[i]].variables
        off = np.concatenate([[0], np.cumsum([sub.variables[v].dim for v in vs])])
        return [(int(r_var[u]), int(r_var[v]), int(off[x]), int(off[y])) for x, u in enumerate(vs) for y, v in
                enumerate(vs) if r_var[u] >= 0 and r_var[v] >= 0]  # fmt: skip

    variables = {int(r_var[v]) for i in which for v in sub.factors[c.index[i]].variables if r_var[v] >= 0}
    pairs = ((u, v) for i in which for u, v, _, _ in own(int(i)))
    blocks = CovarianceBlocks(L_rr, r_off, variables, pairs, solver=solver_r) if variables else None

    def chunks() -> Iterator[tuple[IntArray, FloatArray, FloatArray]]:
        for start in range(0, len(which), SCHUR_CHUNK):
            k = which[start : start + SCHUR_CHUNK]
            per_cand = [own(int(i)) for i in k]
            yield k, *_schur_chunk(c, k, per_cand, blocks, s_pos, r_pos, C, X, XC, XF)

    return XF, SF, chunks()


class _RowProduct:
    """``X C`` (``X`` tall) read by rows: computed by row blocks of :data:`ROW_BLOCK` (the last one takes a short
    remainder), the same numbers as the whole product, of which only the last two blocks read are kept."""

    def __init__(self, X: FloatArray, C: FloatArray) -> None:
        self.X, self.C = X, C
        b = [*range(0, len(X), ROW_BLOCK), len(X)]
        if len(b) > 2 and b[-1] - b[-2] < ROW_BLOCK // 2:
            del b[-2]
        self.bounds = np.asarray(b, dtype=np.int64)
        self._kept: dict[int, FloatArray] = {}

    def block(self, i: int) -> FloatArray:
        """Rows ``bounds[i]`` to ``bounds[i + 1]`` of ``X C``."""
        blk = self._kept.pop(i, None)
        if blk is None:
            blk = self.X[self.bounds[i] : self.bounds[i + 1]] @ self.C
        self._kept[i] = blk
        while len(self._kept) > 2:
            del self._kept[next(iter(self._kept))]
        return blk

    def rows(self, idx: IntArray) -> FloatArray:
        """Rows ``idx`` of ``X C``."""
        out = np.empty((len(idx), self.C.shape[1]))
        which = np.searchsorted(self.bounds, idx, side="right") - 1
        for i in np.unique(which):
            sel = which == i
            out[sel] = self.block(int(i))[idx[sel] - self.bounds[i]]
        return out


ROW_BLOCK = 2048
"""Rows of ``X C`` computed at once by :class:`_RowProduct`. Rows of a product of a few rows can differ in the last
bit from the same rows of the whole product (other BLAS kernels); blocks of this many rows give the same numbers."""


SCHUR_CHUNK = 2048
"""Candidates whose ``Σ`` at their columns is gathered at once (each gathers rows of ``X`` and ``X C``, one per pair
of its columns off the separator: ~1 GB for the 35,000 candidates of an hour's recording in one piece)."""


def _schur_chunk(
    c: _Candidates,
    k: IntArray,
    per_cand: list[list[tuple[int, int, int, int]]],
    blocks: CovarianceBlocks | None,
    s_pos: IntArray,
    r_pos: IntArray,
    C: FloatArray,
    X: FloatArray,
    XC: _RowProduct,
    XF: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """``M_c`` and ``U_c`` of the candidates ``k`` from the Schur pieces of :func:`_schur_clique_gains`: ``Σ`` at
    their columns, separator-separator ``C``, rest-separator ``−X C``, rest-rest ``Λ_rr⁻¹`` blocks plus ``X C Xᵀ``."""
    cols, width, Ac = c.cols[k], c.width[k], c.Ac[k]
    nk, d = cols.shape
    valid = np.arange(d)[None, :] < width[:, None]
    sp_, rp = np.where(valid, s_pos[cols], -1), np.where(valid, r_pos[cols], -1)
    need = np.unique(rp[rp >= 0])
    Y = XC.rows(need)  # the rows of X C this chunk reads
    yp = np.searchsorted(need, rp)
    Sig = np.zeros((nk, d, d))
    ss = (sp_[:, :, None] >= 0) & (sp_[:, None, :] >= 0)
    a, b = np.broadcast_arrays(sp_[:, :, None], sp_[:, None, :])
    Sig[ss] = C[a[ss], b[ss]]
    rs = (rp[:, :, None] >= 0) & (sp_[:, None, :] >= 0)
    a, b = np.broadcast_arrays(yp[:, :, None], sp_[:, None, :])
    Sig[rs] = -Y[a[rs], b[rs]]
    sr = np.swapaxes(rs, 1, 2)
    Sig[sr] = np.swapaxes(Sig, 1, 2)[sr]
    rr = (rp[:, :, None] >= 0) & (rp[:, None, :] >= 0)
    a, b = np.broadcast_arrays(rp[:, :, None], yp[:, None, :])
    Sig[rr] = np.einsum("qk,qk->q", X[a[rr]], Y[b[rr]])
    for q, own in enumerate(per_cand):
        for u, v, ou, ov in own:
            assert blocks is not None
            blk = blocks[(u, v)]
            Sig[q, ou : ou + blk.shape[0], ov : ov + blk.shape[1]] += blk
    M = Ac @ Sig @ np.swapaxes(Ac, 1, 2)
    U = np.einsum("ndf,nad->nfa", XF[cols], Ac)
    return M, U


def _exact_gains(
    prob: _Problem, c: _Candidates, g: _Gains, info: sp.csc_matrix, solver: SPDSolver, which: IntArray
) -> tuple[FloatArray, float]:
    """Recompute ``Σ_F``, ``P`` and the ``which`` candidates' ``M_c``, ``K_c`` in ``g`` from ``info`` (``Λ₀`` plus
    the picks, factorised by ``solver``); returns ``Σ[:, F]`` and the solve's accuracy.

    Through the Schur complement onto the landmarks, the focused variables and the hubs
    (:func:`_schur_clique_gains`, linear in the recording's length) when that separator is small; else ``m`` solves
    per candidate."""
    n = prob.system.dim
    fcols = prob.system.columns(prob.focused)
    separator = [] if prob.full_focus else _chain_separator(info, prob.system, prob.focused)
    if separator and len(prob.system.columns(separator)) <= SCHUR_MAX_COLUMNS:
        XF, SF, chunks = _schur_clique_gains(info, prob.system, separator, fcols, c, which)
        g.SF, g.P = SF, _sym_inv(SF)
        for k, M, U in chunks:
            _store_gains(g, k, M, U, prob.full_focus)
        return XF, _solve_accuracy(info, solver)
    if prob.full_focus:
        XF, SF = np.zeros((n, 0)), np.zeros((0, 0))
    else:
        XF, SF = _focused_cov(solver, n, fcols)
    g.SF, g.P = SF, _sym_inv(SF)
    for s in range(0, len(which), 256):  # Σ A_cᵀ by solves, m right-hand sides per candidate
        k = which[s : s + 256]
        Ac, cols = c.Ac[k], c.cols[k]
        nk, m, _ = Ac.shape
        rhs = np.zeros((n, nk, m))
        np.add.at(rhs, (cols, np.arange(nk)[:, None]), np.swapaxes(Ac, 1, 2))
        X = solver.solve(rhs.reshape(n, nk * m)).reshape(n, nk, m)
        M = Ac @ X[cols, np.arange(nk)[:, None]]  # (nk, m, m)
        U = np.einsum("ndf,nad->nfa", XF[cols], Ac)
        _store_gains(g, k, M, U, prob.full_focus)
    return XF, _solve_accuracy(info, solver)


def _store_gains(g: _Gains, k: IntArray, M: FloatArray, U: FloatArray, full_focus: bool) -> None:
    """``M_c`` and ``K_c = M_c − U_cᵀ P U_c`` of the candidates ``k`` into ``g``'s upper triangles."""
    K = M - np.einsum("nfa,fg,ngb->nab", U, g.P, U, optimize=True)
    for q, (a, b) in enumerate(g.pairs):
        g.Mu[q, k] = 0.5 * (M[:, a, b] + M[:, b, a])
        g.Ku[q, k] = 0.0 if full_focus else 0.5 * (K[:, a, b] + K[:, b, a])


GAIN_CHUNK = 2048
"""Candidates whose ``Σ`` at their columns, ``M_c`` and ``U_c`` :func:`_gain_blocks` holds at once (all of an hour's
61,000 tag measurements at once, with a small array per variable pair, held a few hundred MB)."""


def _gain_blocks(
    prob: _Problem, solver: SPDSolver, XF: FloatArray, SF: FloatArray, c: _Candidates
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Upper triangles of ``M_c = A_c Σ A_cᵀ`` and ``K_c = M_c − U_cᵀ Σ_F⁻¹ U_c`` (``U_c = W Σ A_cᵀ``, from the focused
    columns ``XF``) for ``Σ = prob.info0⁻¹``, and ``P = Σ_F⁻¹``; :data:`GAIN_CHUNK` candidates at a time."""
    Ac, cols = c.Ac, c.cols
    N, m, d = Ac.shape
    blocks = _clique_blocks(prob.info0, prob.system, c.index, solver)
    P = _sym_inv(SF)
    pairs = _sym_pairs(m)
    Mu = np.empty((len(pairs), N))
    Ku = np.empty((len(pairs), N))
    for s in range(0, N, GAIN_CHUNK):
        k = slice(s, s + GAIN_CHUNK)
        Sig_c = _fill_cliques(blocks, prob.system, c.index[k], d)
        M0 = Ac[k] @ Sig_c @ np.swapaxes(Ac[k], 1, 2)
        U = np.einsum("ndf,nad->nfa", XF[cols[k]], Ac[k])  # (n_c, f, m)
        K0 = M0 - np.einsum("nfa,fg,ngb->nab", U, P, U, optimize=True)
        for q, (a, b) in enumerate(pairs):
            Mu[q, k] = M0[:, a, b]
            Ku[q, k] = K0[:, a, b]
    if prob.full_focus:
        Ku[:] = 0.0  # K_c = A_c Σ_{·|F} A_cᵀ = 0: the candidates touch only focused columns
    return Mu, Ku, P


def _initial_gains(prob: _Problem, solver: SPDSolver, XF: FloatArray, SF: FloatArray, c: _Candidates) -> _Gains:
    """``M_c``, ``K_c`` (:func:`_gain_blocks`) under ``Λ₀``, and the operator ``B``."""
    Mu, Ku, P = _gain_blocks(prob, solver, XF, SF, c)
    B = _candidate_operator(c.Ac, c.pos, len(c.rows))
    m = c.Ac.shape[1]
    return _Gains(Mu, Ku, SF, P, B, _sym_pairs(m), m, np.zeros(len(c.index), dtype=bool))


def _best_gain(g: _Gains) -> tuple[int, float]:
    """The unpicked candidate of largest ``½ log det(I + M_c) − ½ log det(I + K_c)`` (first on ties)."""
    gain = _all_gains(g)
    j = int(np.argmax(gain))
    return j, float(gain[j])


def _all_gains(g: _Gains) -> FloatArray:
    """``½ log det(I + M_c) − ½ log det(I + K_c)`` of every candidate, ``-inf`` for the picked ones."""
    if g.m > 3:  # log-determinants: a 6-dof tag under the weak priors has det(I + M_c) beyond float range
        sm, ld_m = _slogdet_eye_plus_sym(g.Mu, g.m)
        sk, ld_k = _slogdet_eye_plus_sym(g.Ku, g.m)
        gain = 0.5 * (ld_m - ld_k)
        gain = np.where(sk <= 0, -np.inf, np.where(sm <= 0, np.inf, gain))
    else:
        det_m = _det_eye_plus_sym(g.Mu, g.m)
        det_k = _det_eye_plus_sym(g.Ku, g.m)
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = 0.5 * np.log(det_m / det_k)
        if not (det_m.min() > 0 and det_k.min() > 0):  # not PD: log det = inf (as for a singular block)
            gain = np.where(det_k <= 0, -np.inf, np.where(det_m <= 0, np.inf, gain))
    gain[g.picked] = -np.inf
    return gain


@dataclass
class _Step:
    """One pick ``j``: ``Vt = (Σ A_jᵀ)ᵀ`` and ``Xt = (Σ Wᵀ p)ᵀ`` at the tracked rows, ``w = W Σ A_jᵀ``,
    ``T = I + A_j Σ A_jᵀ``, ``p = Σ_F⁻¹ w`` and ``E = T − wᵀ p`` (inverted); for the capacitance tracker also
    ``wx = W Σ_last A_jᵀ`` and ``lt = L⁻¹ A_W Σ_last A_jᵀ``."""

    Vt: FloatArray
    Xt: FloatArray
    w: FloatArray
    T: FloatArray
    Tinv: FloatArray
    p: FloatArray
    Einv: FloatArray
    wx: FloatArray | None = None
    lt: FloatArray | None = None


def _capacitance_step(ct: _CapacitanceTracker, c: _Candidates, j: int, fcols: IntArray, P: FloatArray) -> _Step:
    """The pick's quantities from two solves with the last factor (see :class:`_CapacitanceTracker`)."""
    n, m, wj = ct.n, ct.m, c.width[j]
    cj, Aj = c.cols[j, :wj], c.Ac[j, :, :wj]
    rhs = np.zeros((n, m))
    rhs[cj] = Aj.T
    x1 = ct.solve_last(rhs)  # Σ_last A_jᵀ
    T = np.eye(m) + Aj @ x1[cj]
    wx = x1[fcols]  # W Σ_last A_jᵀ
    w = wx
    k = len(ct.window)
    if k:
        lt = ct.lsolve(ct.gather(x1))  # L⁻¹ A_W Σ_last A_jᵀ
        T = T - lt.T @ lt
        y = ct.ltsolve(lt)  # C⁻¹ A_W Σ_last A_jᵀ
        w = wx - ct.WX[:, : k * m] @ y
    else:
        lt = np.zeros((0, m))
    Tinv = _inv_at_least_identity(T)
    p = P @ w
    Einv = _inv_at_least_identity(T - w.T @ p)
    rhs = np.zeros((n, 2 * m))
    rhs[fcols, m:] = p
    if k:
        y2 = ct.ltsolve(ct.lsolve(ct.WX[:, : k * m].T @ p))
        ct.scatter(np.hstack([y, -y2]), rhs)
    Z = ct.solve_last(rhs)
    V = x1 - Z[:, :m] if k else x1  # Σ_S A_jᵀ
    Vt = np.ascontiguousarray(V[c.rows].T)
    Xt = np.ascontiguousarray(Z[c.rows, m:].T)  # (Σ_S Wᵀ p)ᵀ at rows
    return _Step(Vt, Xt, w, T, Tinv, p, Einv, wx, lt)


def _window_step(
    tracker: _Tracker, c: _Candidates, j: int, fcols: IntArray, P: FloatArray, Yt: FloatArray | None
) -> _Step:
    """The pick's quantities from the window tracker; ``Σ Wᵀ p`` from ``Yt = (W Σ)ᵀ`` at the tracked rows when it is
    kept (then updated in place), else from a second solve."""
    wj = c.width[j]
    Vt = tracker.solve(c.cols[j, :wj], c.Ac[j, :, :wj].T, c.pos[j, :wj])  # (Σ A_jᵀ)ᵀ at rows
    T = np.eye(tracker.m) + c.Ac[j] @ Vt[:, c.pos[j]].T
    Tinv = _inv_at_least_identity(T)
    w = np.ascontiguousarray(Vt[:, c.fpos].T)  # W Σ A_jᵀ, (f, m)
    p = P @ w
    Einv = _inv_at_least_identity(T - w.T @ p)
    if Yt is None:
        Xt = tracker.solve(fcols, p, c.fpos)  # (Σ Wᵀ p)ᵀ at rows
    else:
        Xt = p.T @ Yt
        Yt -= (Tinv @ w.T).T @ Vt
    return _Step(Vt, Xt, w, T, Tinv, p, Einv)


def _apply_pick(g: _Gains, st: _Step) -> None:
    """``M_c −= g_c T⁻¹ g_cᵀ``, ``K_c −= k_c E⁻¹ k_cᵀ`` for every candidate, ``Σ_F −= w T⁻¹ wᵀ``, ``P += p E⁻¹ pᵀ``.

    ``H = A_c [V L_T, (V − X) L_E]`` at the candidates' columns (``T⁻¹ = L_T L_Tᵀ``, ``E⁻¹ = L_E L_Eᵀ``) is one
    sparse product; the updates run on the upper triangles.
    """
    m, N = g.m, g.Mu.shape[1]
    LT = np.linalg.cholesky(0.5 * (st.Tinv + st.Tinv.T))
    LE = np.linalg.cholesky(0.5 * (st.Einv + st.Einv.T))
    H = g.B @ np.hstack([st.Vt.T @ LT, (st.Vt - st.Xt).T @ LE])  # (m N, 2m)
    Ht = np.ascontiguousarray(H.reshape(m, N, 2 * m).transpose(0, 2, 1))  # (m, 2m, N)
    for q, (a, b) in enumerate(g.pairs):
        prod = Ht[a] * Ht[b]
        g.Mu[q] -= prod[:m].sum(axis=0)
        g.Ku[q] -= prod[m:].sum(axis=0)
    g.SF -= st.w @ st.Tinv @ st.w.T
    g.P += st.p @ st.Einv @ st.p.T


def _tracked_information(
    prob: _Problem, rows: IntArray, options: TrackerOptions
) -> tuple[bool, sp.csc_matrix, IntArray | None]:
    """Which tracker, and the information it tracks: ``(capacitance, info, rows)``, ``rows`` None when ``info`` is
    the Schur complement of ``Λ₀`` onto the tracked rows (picks only touch them, so ``Σ_S`` there is its inverse
    plus the picks: exact, and smaller)."""
    n = prob.system.dim
    mode = options.tracker
    capacitance = mode == "capacitance" or (mode == "auto" and len(rows) > options.capacitance_above * n)
    if not capacitance and len(rows) < options.reduce_below * n:
        reduced = schur_complement(prob.info0, rows)
        if reduced is not None:
            return capacitance, reduced, None
    return capacitance, prob.info0, rows


def _capacitance_tracker(
    prob: _Problem,
    add_info: Callable[[list[int]], SparseMatrix],
    m: int,
    d: int,
    fcols: IntArray,
    refactor_every: int | None,
    options: TrackerOptions,
) -> _CapacitanceTracker:
    """The capacitance tracker on ``Λ₀``, told which columns only the weak landmark prior holds."""
    sub = prob.system
    weak = np.zeros(sub.dim, dtype=bool)
    weak[sub.columns(prob.landmark_vars)] = True
    for bf in prob.base:
        weak[sub.factor_columns(bf)] = False
    return _CapacitanceTracker(
        prob.info0, m, d, fcols, add_info, refactor_every, weak, options.refactor_on_first_observation
    )


def _tracker_stats(tracker: _Tracker | _CapacitanceTracker) -> dict[str, float]:
    stats = {"factor_s": tracker.factor_s, "refactorisations": float(tracker.refactorisations)}
    if isinstance(tracker, _CapacitanceTracker):
        stats["first_observation_refactorisations"] = float(tracker.first_observation_refactorisations)
    return stats


def _greedy(
    prob: _Problem,
    c: _Candidates,
    g: _Gains,
    held: list[FloatArray],
    budget: int,
    refactor_every: int | None,
    options: TrackerOptions,
    delta0: float,
) -> tuple[list[int], list[float], dict[str, float]]:
    """``budget`` greedy steps: the best gain, the pick's quantities from the tracker, the update of every gain.

    ``held`` holds ``XF``, ``Σ`` at the focused columns (``n × f``), taken out of it so that the caller keeps no
    reference and it is freed once read (an hour's graph: 80 MB, and a recomputation makes a second one). The window
    tracker with a small focus keeps ``W Σ`` at the tracked rows (``f × rows``) current, ``W Σ −= w T⁻¹ Vᵀ``
    (4·f·m·rows flops per step), instead of a second solve per step; the capacitance tracker gets ``Σ Wᵀ p`` from its
    second solve and keeps nothing (on an hour's graph the copy is tens of MB, held through the greedy)."""
    fcols = prob.system.columns(prob.focused)
    t_red = time.perf_counter()
    capacitance, info_t, rows_t = _tracked_information(prob, c.rows, options)
    stats = {"reduce_s": time.perf_counter() - t_red}
    XF = held.pop()
    Yt = np.ascontiguousarray(XF[c.rows].T) if not capacitance and len(fcols) <= options.track_focused_max else None
    del XF

    def add_info(js: list[int]) -> SparseMatrix:
        info = prob.system.information([c.index[i] for i in js])
        return info if rows_t is not None else info[c.rows][:, c.rows]

    picks: list[int] = []
    gains: list[float] = []
    t_update = t_gain = t_exact = 0.0
    t_loop = time.perf_counter()
    precision = _Precision.of(g, delta0, options.recompute_tol)
    with single_threaded_blas():
        tracker: _Tracker | _CapacitanceTracker
        if capacitance:
            tracker = _capacitance_tracker(prob, add_info, g.m, c.Ac.shape[2], fcols, refactor_every, options)
        else:
            tracker = _Tracker(info_t, rows_t, g.m, add_info, refactor_every)

        info_s, n_folded = prob.info0, 0

        def recompute(which: npt.NDArray[np.bool_]) -> None:
            """``Σ_F`` and the ``which`` candidates again from the information of the picks so far
            (see :class:`_Precision`)."""
            nonlocal Yt, t_exact, info_s, n_folded
            tr = time.perf_counter()
            if tracker.window:
                tracker._refactorise()
            if isinstance(tracker, _CapacitanceTracker):  # its factor is of Λ₀ plus every pick now
                info_s, solver = tracker.info, tracker.solver
            else:
                info_s = sp.csc_matrix(info_s + prob.system.information([c.index[i] for i in picks[n_folded:]]))
                solver = SPDSolver(info_s)
            n_folded = len(picks)
            XF, delta = _exact_gains(prob, c, g, info_s, solver, np.flatnonzero(which & ~g.picked))
            if Yt is not None:
                Yt = np.ascontiguousarray(XF[c.rows].T)
            precision.reset(g, np.flatnonzero(which & ~g.picked), delta)
            t_exact += time.perf_counter() - tr

        for _ in range(budget):
            tg = time.perf_counter()
            gain_all = _all_gains(g)
            j = int(np.argmax(gain_all))
            doubt = precision.in_doubt(gain_all, j, g)
            if doubt is not None:
                recompute(doubt)
                gain_all = _all_gains(g)
                j = int(np.argmax(gain_all))
            gain = float(gain_all[j])
            t_gain += time.perf_counter() - tg
            picks.append(j)
            gains.append(gain)
            g.picked[j] = True
            if isinstance(tracker, _CapacitanceTracker):
                st = _capacitance_step(tracker, c, j, fcols, g.P)
            else:
                st = _window_step(tracker, c, j, fcols, g.P, Yt)
            if prob.full_focus:
                st.Xt = st.Vt  # Σ_{·|F} A_jᵀ = 0: K_c stays 0
            tu = time.perf_counter()
            _apply_pick(g, st)
            t_update += time.perf_counter() - tu
            if isinstance(tracker, _CapacitanceTracker):
                assert st.wx is not None and st.lt is not None
                refactorised = tracker.add(j, c.cols[j], c.Ac[j], st.wx, st.lt.T, st.T)
            else:
                refactorised = tracker.add(j, st.Vt, st.Tinv)
            if refactorised:
                if precision.focused_lost(g):
                    recompute(np.zeros(len(g.picked), dtype=bool))
                else:
                    g.P = _sym_inv(g.SF)
    stats |= {"loop_s": time.perf_counter() - t_loop, "update_s": t_update, "gain_s": t_gain}
    stats |= {
        "recomputations": float(precision.recomputations),
        "recomputed_candidates": float(precision.recomputed),
        "recompute_s": t_exact,
        "solve_delta": delta0,
    }
    stats |= _tracker_stats(tracker)
    stats["solve_s"] = stats["loop_s"] - t_update
    stats |= {"tracked_rows": float(len(c.rows)), "reduced": float(rows_t is None), "capacitance": float(capacitance)}
    return picks, gains, stats


def select_information(
    system: LinearSystem,
    candidates: Sequence[int],
    focused: Sequence[int],
    budget: int,
    base: Sequence[int] | None = None,
    landmark_prior_sigma: float = 100.0,
    refactor_every: int | None = 64,
    options: TrackerOptions | None = None,
) -> MeasurementSelection:
    """Greedy focused-entropy measurement selection (Mu et al. Alg. 1), exact and fast.

    The gain of Theorem 1 is evaluated in its mutual-information form: with ``W`` selecting the
    focused blocks, ``S_c − U_cᵀ Σ_F⁻¹ U_c = I + A_c Σ_{·|F} A_cᵀ`` where
    ``Σ_{·|F} = Σ − Σ Wᵀ Σ_F⁻¹ W Σ`` is the covariance of the other variables given the focused ones.
    So ``gain_c = ½ log det(I + M_c) − ½ log det(I + K_c)`` with ``M_c = A_c Σ A_cᵀ`` and
    ``K_c = A_c Σ_{·|F} A_cᵀ``, both ``m × m`` per candidate. After picking ``j`` with ``V = Σ A_jᵀ``,
    ``T = I + A_j V``, ``w = W V``, ``p = Σ_F⁻¹ w`` and ``E = T − wᵀ p`` (``= I + A_j Σ_{·|F} A_jᵀ``)::

        M_c −= g_c T⁻¹ g_cᵀ,            g_c = A_c V
        K_c −= k_c E⁻¹ k_cᵀ,            k_c = A_c Σ_{·|F} A_jᵀ = g_c − A_c (Σ Wᵀ p)
        Σ_F −= w T⁻¹ wᵀ,   Σ_F⁻¹ += p E⁻¹ pᵀ

    ``Σ`` is tracked only at the rows the gains read (candidates' and focused columns; the tracked
    sparse information is the exact Schur complement of ``Λ₀`` onto them, plus the picks). ``V`` is one
    solve (the last sparse factor plus a Woodbury window over the picks since); ``Σ Wᵀ p`` is read from
    ``W Σ`` kept at the tracked rows when at most 128 columns are focused, else a second solve. Plus
    ``O(N_candidates · m² · d)`` batched dense work. When the candidates' and focused columns exceed 75%
    of the state, the capacitance tracker (:class:`_CapacitanceTracker`) is used instead: two solves
    per step with the last factor of the whole compact graph, per-step cost independent of the
    candidates apart from the ``O(N)`` update.

    Args:
        system: the linearised full graph (whitened Jacobians at the full-graph solution).
        candidates: factor indices that may be kept (e.g. the tag measurements of the focused
            landmarks), in time order.
        focused: variable indices of the focused variables (``W`` selects their blocks).
        budget: number of measurements to keep (``K``).
        base: factor indices always kept (default: every non-candidate non-landmark factor, i.e.
            odometry and priors).
        landmark_prior_sigma: standard deviation (state units, e.g. m) of the weak isotropic prior
            put on every landmark variable in ``Λ₀``.
        refactor_every: picks between sparse refactorisations (in between, solves use the last
            factor plus a Woodbury correction over the picks since); ``None`` is adaptive:
            refactorise once the Woodbury work since the last factorisation has cost as much as
            that factorisation (at most 256 picks apart).
        options: how ``Σ_S`` is tracked (:class:`TrackerOptions`; same picks and gains, different cost).

    Returns:
        The picks in order with their entropy reductions (nats).
    """
    t0 = time.perf_counter()
    options = options or TrackerOptions()
    cand = list(dict.fromkeys(int(c) for c in candidates))
    base = default_base(system, cand) if base is None else list(base)
    prob = _compact_problem(system, base, cand, focused, landmark_prior_sigma)
    fcols = prob.system.columns(prob.focused)
    if len(fcols) == 0:
        raise ValueError("no focused variables: run landmark selection first")
    solver = SPDSolver(prob.info0)
    full = _within_focus(prob.system, prob.candidates, fcols)
    if full:  # no Σ_F: the gains do not need it, the entropy comes from sparse log-determinants
        h0 = _sparse_focused_entropy(prob.info0, fcols)
        prob.full_focus, prob.focused, fcols = True, [], np.zeros(0, dtype=np.int64)
        XF, SF = np.zeros((prob.system.dim, 0)), np.zeros((0, 0))
    else:
        XF, SF = _focused_cov(solver, prob.system.dim, fcols)
        h0 = entropy_from_logdet(logdet_spd(SF), len(fcols))
    N = len(cand)
    status = _budget_status(budget, N)
    stats: dict[str, float] = {"setup_s": time.perf_counter() - t0, "full_focus": float(full)}
    if status in ("no_candidates", "budget_zero"):
        return MeasurementSelection([], [], status or "ok", N, budget, h0, h0, stats)
    if budget >= N:
        after = focused_entropy(system, base + cand, focused, landmark_prior_sigma)
        return MeasurementSelection(cand, [float("nan")] * N, status or "ok", N, budget, h0, after, stats)
    c = _candidates(prob.system, prob.candidates, fcols)
    g = _initial_gains(prob, solver, XF, SF, c)
    stats["clique_cov_s"] = time.perf_counter() - t0 - stats["setup_s"]
    accuracy = _solve_accuracy(prob.info0, solver)
    del solver
    held = [XF]
    del XF, SF
    js, gains, loop_stats = _greedy(prob, c, g, held, budget, refactor_every, options, accuracy)
    del prob, c, g  # before the last factorisation
    stats |= loop_stats
    picks = [cand[j] for j in js]
    # the running entropy is h0 - Σ gains; the exact one takes one more factorisation. They differ when rounding in the
    # tracked covariance has built up (ill-conditioned graphs: precise 6-dof tag measurements): the drift is reported
    # and the exact value returned.
    h1 = focused_entropy(system, base + picks, focused, landmark_prior_sigma)
    stats["entropy_drift_nats"] = h0 - float(np.sum(gains)) - h1
    return MeasurementSelection(picks, gains, "ok", N, budget, h0, h1, stats)


# ---------------------------------------------------------------------------------- other strategies
def _measure(cov: FloatArray, measure: Measure) -> float:
    if measure == "trace":
        return float(np.trace(cov))
    if measure == "max_eig":
        return float(np.linalg.eigvalsh(cov)[-1])
    return logdet_spd(cov)


def leverage_probabilities(
    system: LinearSystem,
    candidates: Sequence[int],
    base: Sequence[int],
    focused: Sequence[int] = (),
    landmark_prior_sigma: float = 100.0,
) -> FloatArray:
    """Mousavi & Motee eq. 29-30 for candidate measurements.

    ``r_c = tr(Λ_all⁻¹ (Λ₀ / N + A_cᵀ A_c))`` with ``Λ_all = Λ₀ + Σ_c A_cᵀ A_c``; ``π_c = r_c / n``
    sums to 1 because ``tr(Λ_all⁻¹ Λ_all) = n``. The clique covariances of ``Λ_all`` are computed
    with the Schur complement onto the landmark variables.
    """
    cand = list(candidates)
    prob = _compact_problem(system, base, cand, focused, landmark_prior_sigma)
    sub = prob.system
    info_all = sp.csc_matrix(prob.info0 + sub.information(prob.candidates))
    Ac, _ = _padded_candidates(sub, prob.candidates)
    Sig_c = _clique_covariances(info_all, sub, prob.candidates, Ac.shape[2], prob.landmark_vars)
    lev = np.einsum("nmd,nde,nme->n", Ac, Sig_c, Ac)  # tr(A_c Σ A_cᵀ)
    n = sub.dim
    N = len(cand)
    r = lev + (n - lev.sum()) / N
    return np.asarray(r / n)


def select_leverage(
    system: LinearSystem,
    candidates: Sequence[int],
    focused: Sequence[int],
    budget: int,
    base: Sequence[int] | None = None,
    draws: int = 20,
    measure: Measure = "logdet",
    seed: int = 0,
    landmark_prior_sigma: float = 100.0,
) -> MeasurementSelection:
    """Leverage-score sampling (Mousavi & Motee Alg. 1) over candidate measurements.

    Each of ``draws`` independent draws samples candidates with replacement from ``π`` until
    ``budget`` distinct ones are chosen; the draw whose focused covariance has the smallest
    ``measure`` (``logdet``, ``trace`` or ``max_eig``) is kept. Scores are the ``π`` of the picks.
    """
    t0 = time.perf_counter()
    cand = list(dict.fromkeys(int(c) for c in candidates))
    base = default_base(system, cand) if base is None else list(base)
    N = len(cand)
    status = _budget_status(budget, N)
    h0 = focused_entropy(system, base, focused, landmark_prior_sigma)
    if status in ("no_candidates", "budget_zero"):
        return MeasurementSelection([], [], status or "ok", N, budget, h0, h0)
    if budget >= N:
        h1 = focused_entropy(system, base + cand, focused, landmark_prior_sigma)
        return MeasurementSelection(cand, [float("nan")] * N, status or "ok", N, budget, h0, h1)
    pi = leverage_probabilities(system, cand, base, focused, landmark_prior_sigma)
    t_prob = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    prob = _compact_problem(system, base, cand, focused, landmark_prior_sigma)
    fcols = prob.system.columns(prob.focused)
    best: tuple[float, list[int]] | None = None
    for _ in range(draws):
        chosen: dict[int, None] = {}
        while len(chosen) < budget:
            for c in rng.choice(N, size=2 * (budget - len(chosen)), p=pi):
                chosen[int(c)] = None
                if len(chosen) == budget:
                    break
        order = list(chosen)
        info = prob.info0 + prob.system.information([prob.candidates[i] for i in order])
        _, SF = _focused_cov(SPDSolver(info), prob.system.dim, fcols, keep=False)
        value = _measure(SF, measure)
        if best is None or value < best[0]:
            best = (value, order)
    assert best is not None
    picks = [cand[i] for i in best[1]]
    h1 = focused_entropy(system, base + picks, focused, landmark_prior_sigma)
    stats = {"probabilities_s": t_prob, "total_s": time.perf_counter() - t0}
    return MeasurementSelection(picks, [float(pi[i]) for i in best[1]], "ok", N, budget, h0, h1, stats)


def select_uniform(
    candidates: Sequence[int], budget: int, times: Sequence[float] | None = None
) -> MeasurementSelection:
    """Even downsampling in time (the paper's ``DS``): ``budget`` candidates evenly spaced in time order."""
    cand = list(dict.fromkeys(int(c) for c in candidates))
    N = len(cand)
    status = _budget_status(budget, N)
    if status in ("no_candidates", "budget_zero"):
        return MeasurementSelection([], [], status or "ok", N, budget)
    if budget >= N:
        return MeasurementSelection(cand, [float("nan")] * N, status or "ok", N, budget)
    order = np.argsort(np.asarray(times), kind="stable") if times is not None else np.arange(N)
    pos = np.unique(np.round(np.linspace(0, N - 1, budget)).astype(int))
    picks = [cand[int(order[p])] for p in pos]
    return MeasurementSelection(picks, [float("nan")] * len(picks), "ok", N, budget)


def select_random(candidates: Sequence[int], budget: int, seed: int = 0) -> MeasurementSelection:
    """``budget`` candidates drawn uniformly without replacement (seeded)."""
    cand = list(dict.fromkeys(int(c) for c in candidates))
    N = len(cand)
    status = _budget_status(budget, N)
    if status in ("no_candidates", "budget_zero"):
        return MeasurementSelection([], [], status or "ok", N, budget)
    if budget >= N:
        return MeasurementSelection(cand, [float("nan")] * N, status or "ok", N, budget)
    idx = np.random.default_rng(seed).choice(N, size=budget, replace=False)
    return MeasurementSelection([cand[int(i)] for i in idx], [float("nan")] * budget, "ok", N, budget)


def select_all(candidates: Sequence[int]) -> MeasurementSelection:
    """Keep every candidate."""
    cand = list(dict.fromkeys(int(c) for c in candidates))
    return MeasurementSelection(
        cand, [float("nan")] * len(cand), "ok" if cand else "no_candidates", len(cand), len(cand)
    )
