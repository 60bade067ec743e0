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
mutual-information form, ``S_c − U_cᵀ Σ_F⁻¹ U_c = I + A_c Σ_{·|F} A_cᵀ`` with ``Σ_{·|F} = Λ_UU⁻¹`` on the
unfocused variables ``U`` (the covariance of the others given the focused ones)::

    gain_c = ½ log det(I + M_c) − ½ log det(I + K_c),   M_c = A_c Λ_S⁻¹ A_cᵀ,   K_c = A_c Λ_S,UU⁻¹ A_cᵀ

Both are the same kind of quantity of two information matrices, ``Λ_S`` and its unfocused block ``Λ_S,UU``,
and both are kept the same way (:class:`_Side`): computed once from ``Λ₀``'s clique covariances, then
downdated per pick (``M_c −= g_c T⁻¹ g_cᵀ``, ``g_c = A_c Λ_S⁻¹ A_jᵀ``, ``T = I + A_j Λ_S⁻¹ A_jᵀ``; ``K_c`` the
same with ``Λ_S,UU``), each side with its own tracker: one sparse solve per step from the last factorisation
plus a correction over the picks since, refined against the picks' information when that correction cancels,
and ``O(N_candidates · m² · d)`` small dense work. The tracked ``Σ`` is kept only at the rows the gains read
(the Schur complement of ``Λ₀`` onto the candidates' columns, a Woodbury window) or, the default, not at all
(the capacitance form: two solves per step with the factor of the whole compact graph). No dense ``n × n``
matrix is ever formed, and nothing of the size of the focus is tracked.

``K_c`` used to be ``M_c − U_cᵀ Σ_F⁻¹ U_c`` from the one tracked ``Σ``; when the focused variables are known
only through the weak prior that difference cancels ~9 digits (a camera-only rig hung on a surveyed tag:
negative ``K_c``, the running entropy 70 nats off, "Matrix is not positive definite"). Solving with
``Λ_S,UU`` itself, nothing cancels.

When every candidate touches only focused variables (a pose graph's loop closures with the poses
focused), ``Σ_{·|F} A_cᵀ = 0`` so ``K_c = 0`` and the gain is ``½ log det(I + A_c Σ A_cᵀ)``: only ``Λ_S`` is
tracked, and the focused entropy comes from two sparse log-determinants,
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
    base: Sequence[int] | None = None,
) -> float:
    """Entropy (nats) of the focused variables given the factors, plus the weak prior of ``base`` (:func:`weak_prior`:
    every landmark, and the first pose of a group that ``base`` leaves without an anchor; default: of ``factors``).

    A selection's entropy after its picks takes ``base`` = the factors always kept, as its gains do: with the default,
    a pick that ties a rig hung on a surveyed tag to a landmark drops the first pose's weak prior, and on TagSLAM's
    example_1 the greedy's running entropy differed from this one by 0.54 nats with every gain exact."""
    base = list(factors) if base is None else list(base)
    kept = set(base)
    prob = _compact_problem(system, base, [f for f in factors if f not in kept], focused, landmark_prior_sigma)
    info = sp.csc_matrix(prob.info0 + prob.system.information(prob.candidates)) if prob.candidates else prob.info0
    fcols = prob.system.columns(prob.focused)
    if len(fcols) > DENSE_FOCUS_MAX:
        return _sparse_focused_entropy(info, fcols)
    _, SF = _focused_cov(SPDSolver(info), prob.system.dim, fcols, keep=False)
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
    ``capacitance`` once the candidates' columns exceed ``capacitance_above`` of the state, else
    ``window``.

    Default ``capacitance``: its time per step is flat in the number of candidates (issue 6's target: 1.20-1.29x
    from 1,000 to 10,000 candidates) and the whole greedy stays within 5x of one GTSAM optimise plus marginals
    (0.6x for K=90, 2.6x for K=1000). ``auto`` is up to 4x cheaper per step on small candidate sets (the
    Schur-reduced window), at the price of a step cost that grows with the candidates."""
    capacitance_above: float = 0.75
    """``auto``: the fraction of the state above which the capacitance tracker is used. Measured on the benchmark
    graph (all landmarks focused, 100 steps): window 0.64 ms/step at 9% of the state and 2.5–2.7 at 77%, 3.0–3.5
    on the whole graph; capacitance 2.3 and 2.7–3.0 ms/step (flat): they tie near 75%."""
    reduce_below: float = 1.0
    """``window``: track the Schur complement of ``Λ₀`` onto the candidates' columns when they are
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
        self.diag = self.info.diagonal().copy()  # of Λ_S: the capacitance tracker adds its window's picks
        self._scaled_norm: float | None = None
        self.t_factor = time.perf_counter() - tf
        self.factor_s += self.t_factor

    @property
    def scaled_norm(self) -> float:
        """``‖D |Λ_last| D‖∞`` with ``D = diag(Λ_last)^-½``, for backward errors (:func:`_backward_error`)."""
        if self._scaled_norm is None:
            d = 1.0 / np.sqrt(self.info.diagonal())
            self._scaled_norm = float(np.max(d * (abs(self.info) @ d))) if len(d) else 0.0
        return self._scaled_norm

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
    that the gains read (the candidates' columns) of each ``V_i`` are stored, and the
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

    Capacitance form: ``Σ_S b = Σ_last (b − A_Wᵀ C⁻¹ A_W Σ_last b)``, ``C = I + A_W Σ_last A_Wᵀ`` (``k m × k m``).
    ``C`` is kept as its Cholesky factor, bordered by each pick: with ``u = A_W Σ_last A_jᵀ`` and ``l = L⁻¹ u`` the
    new row is ``[lᵀ, chol(T_j)]``, where ``T_j = I + A_j Σ_last A_jᵀ − lᵀ l = I + A_j Σ_S A_jᵀ`` is the pick's own
    ``T``. Stored per pick: its columns and its Jacobian; nothing of the size of the state or of the candidates.
    """

    def __init__(
        self,
        info: sp.csc_matrix,
        m: int,
        d: int,
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

    def add(self, j: int, cols: IntArray, A: FloatArray, lt: FloatArray, T: FloatArray) -> bool:
        """Add pick ``j`` (``lt = (L⁻¹ A_W Σ_last A_jᵀ)ᵀ``, ``T ⪰ I`` its own ``T``); True if refactorised."""
        k = len(self.window)
        km, m = k * self.m, self.m
        self.L[km : km + m, :km] = lt
        self.L[km : km + m, km : km + m] = np.linalg.cholesky(T)  # T ⪰ I (clipped, :func:`_at_least_identity`)
        self.cols[k] = cols
        self.A[k] = A
        np.add.at(self.diag, cols, (A**2).sum(axis=0))
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


def _at_least_identity(A: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """``(S, S⁻¹, L, cond S)`` for ``S = I + A Λ⁻¹ Aᵀ`` (``T`` or ``E``), ``⪰ I`` exactly, with ``L Lᵀ = S⁻¹``.

    From one eigen-decomposition whose eigenvalues are clipped at 1 (the bound the exact matrix meets): the rounding
    of a matrix with eigenvalues from 1 to ~1e10 (a pick that pins a pose or a landmark known only through a weak
    prior) can leave one below 1; and ``S⁻¹``'s smallest eigenvalues (``1/λ_max``) can be below its rounding, so no
    Cholesky factor of the inverse is taken (it stopped the stage: "Matrix is not positive definite")."""
    lam, Q = np.linalg.eigh(0.5 * (A + A.T))
    lam = np.maximum(lam, 1.0)
    S = (Q * lam) @ Q.T
    L = Q / np.sqrt(lam)
    inv = L @ L.T
    return 0.5 * (S + S.T), 0.5 * (inv + inv.T), L, float(lam[-1] / lam[0])


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
    """The rows the gains read: every candidate's columns."""
    pos: IntArray
    """(N, d) positions of ``cols`` in ``rows`` (padding: 0, where the Jacobian is zero)."""


def _candidates(sub: LinearSystem, cidx: list[int]) -> _Candidates:
    Ac, cols = _padded_candidates(sub, cidx)
    d = Ac.shape[2]
    width = np.array([len(sub.factor_columns(c)) for c in cidx], dtype=np.int64)
    rows = np.unique(cols.ravel())
    pos_of = np.full(sub.dim, -1, dtype=np.int64)
    pos_of[rows] = np.arange(len(rows))
    pos = np.where(np.arange(d)[None, :] < width[:, None], pos_of[cols], 0)
    return _Candidates(cidx, Ac, cols, width, rows, pos)


@dataclass
class _Gains:
    """What the gains read, kept current as picks join: the upper triangles of ``M_c = A_c Σ_S A_cᵀ`` and of
    ``K_c = A_c Σ_{·|F} A_cᵀ`` (``Σ_{·|F} = Λ_UU⁻¹`` on the unfocused columns ``U``, zero elsewhere)."""

    Mu: FloatArray
    """(m(m+1)/2, N) upper triangles of ``M_c``."""
    Ku: FloatArray
    """The same of ``K_c`` (zero when every candidate is inside the focus)."""
    pairs: list[tuple[int, int]]
    m: int
    picked: npt.NDArray[np.bool_]


def _solve_accuracy(info: sp.csc_matrix, solver: SPDSolver) -> float:
    """The relative forward error of a solve with ``info`` (max-norm), estimated from one probe: ``x = Λ⁻¹ b``, then
    ``Λ⁻¹ (b − Λ x)``, over ``|x|``. Covariances computed from ``info`` carry absolute errors of this times their
    size; the tracked ``M_c``, ``K_c`` keep those absolute errors while picks shrink them."""
    n = int(info.shape[0])
    if n == 0:
        return float(np.finfo(float).eps)
    b = np.random.default_rng(0).standard_normal(n)
    x = solver.solve(b)
    e = solver.solve(b - info @ x)
    return max(float(np.max(np.abs(e)) / max(float(np.max(np.abs(x))), 1e-300)), float(np.finfo(float).eps))


RESET_FRACTION = 0.001
"""A recomputation also refreshes the candidates whose bound is above this fraction of the tolerance, so that they
do not cause the next one soon after. Its cost hardly depends on how many (a Schur complement along the whole
recording, then a little per candidate): on the benchmark graph (K=1000) 0.001 needed 23 recomputations where 0.01
needed 30."""


@dataclass
class _Precision:
    """When the tracked ``M_c`` and ``K_c`` have lost too many digits to the downdates.

    Each is a covariance computed from an information matrix (``Λ₀``, or ``Λ_S`` at a recomputation; ``Λ_UU`` for
    ``K_c``) with a relative error ``delta`` (:func:`_solve_accuracy`, about ``cond · ε``), then only downdated
    (``M_c −= g T⁻¹ gᵀ``): its absolute error is ``delta × its size then`` plus what each downdate adds
    (:meth:`downdated`), while the picks shrink its value. A gain reads ``log det(I + M_c)``, so its error is at most
    about ``½ m err / (1 + now)`` over the diagonal, for ``M_c`` and ``K_c``.

    The greedy recomputes, from the information of the picks so far (:func:`_exact_gram`), the candidates whose bound
    exceeds ``tol`` whenever the pick is in doubt (its own bound above ``tol``, or another candidate within the
    bounds). On camera-only 3D rigs (6-dof tags to millimetres, poses tied only by a weak motion prior, a weak
    landmark prior) ``delta`` is ~1e-9 and ``M_c`` falls from ~1e10 to ~10 when a tag is first measured: the
    downdated gains were then wrong by more than they were worth (3.5 nats of drift after 60 picks on a 300-pose
    rig, picks other than Alg. 1's from the 13th). On the planar sample (``delta`` ~1e-13) three recomputations at
    K=90 (the running entropy within 8e-5 nats of the exact one; 1.1e-3 before the downdates' rounding was counted)."""

    err: list[FloatArray]
    """Per side (``M_c``, then ``K_c``), ``(m, N)``: a bound on the absolute error of each candidate's diagonal."""
    delta: list[float]
    """Per side, the accuracy of the information last factorised (``Λ₀``, or ``Λ_S`` at the last recomputation)."""
    diag: list[int]
    tol: float = 1e-4
    recomputations: int = 0
    recomputed: int = 0
    """Candidates recomputed, summed over the recomputations."""

    @classmethod
    def of(cls, grams: list[FloatArray], deltas: list[float], pairs: list[tuple[int, int]], tol: float) -> _Precision:
        diag = [k for k, (a, b) in enumerate(pairs) if a == b]
        return cls([d * np.abs(G[diag]) for G, d in zip(grams, deltas, strict=True)], list(deltas), diag, tol)

    def bounds(self, grams: list[FloatArray], m: int) -> list[FloatArray]:
        """Per side, per candidate, a bound (nats) on its share of the gain's error (``|Δ log det(I + M)| ≤
        tr((I + M)⁻¹ ΔM)``); the gain's error is at most their sum."""
        return [
            0.5 * m * np.max(err / (1.0 + np.abs(G[self.diag])), axis=0) for G, err in zip(grams, self.err, strict=True)
        ]

    def downdated(self, side: int, dm: FloatArray, cond: float) -> None:
        """A pick's downdate of one side (``dm``: the diagonals of ``g_c T⁻¹ g_cᵀ``, ``(m, N)``) added its rounding:
        the pick's solve carries a relative error ``delta`` and the downdate reads it through ``T⁻¹``, which amplifies
        an error along ``T``'s small eigenvalues by up to ``sqrt(cond T)`` (Cauchy–Schwarz on ``[[M_c, g_c],
        [g_cᵀ, T − I]] ⪰ 0``). Without this term, a pick that pinned a pose known to 100 m left errors of ~1e-7 of
        its neighbours' former ``M_c`` (``cond T`` ~1e7) that the bound put 2,000x lower."""
        self.err[side] += (2.0 * self.delta[side] * np.sqrt(cond)) * np.abs(dm)

    def in_doubt(self, gain: FloatArray, j: int, e: FloatArray, picked: npt.NDArray[np.bool_]) -> bool:
        """The pick ``j`` could be wrong or its gain off by more than ``tol`` given the bounds ``e``: its own bound is
        above ``tol``, or another candidate's gain could exceed it within the bounds."""
        e = e.copy()
        e[picked] = 0.0
        upper = gain + e
        upper[j] = -np.inf
        return bool(e[j] > self.tol or upper.max() > gain[j] - e[j] + self.tol)

    def reset(self, side: int, gram: FloatArray, which: IntArray, delta: float) -> None:
        """``which`` candidates of one side were just recomputed from an information of accuracy ``delta``."""
        self.err[side][:, which] = delta * np.abs(gram[self.diag][:, which])
        self.delta[side] = delta


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
    info: sp.csc_matrix, sub: LinearSystem, separator: list[int], c: _Candidates, which: IntArray
) -> Iterator[tuple[IntArray, FloatArray]]:
    """``M_c = A_c Σ A_cᵀ`` (``Σ = info⁻¹``) of the ``which`` candidates, chunk by chunk, from one Schur complement of
    ``info`` onto the ``separator``.

    With ``info = [[Λ_rr, Λ_rs], [Λ_sr, Λ_ss]]``, ``X = Λ_rr⁻¹ Λ_rs`` (one solve per separator column) and
    ``C = (Λ_ss − Λ_sr X)⁻¹``: ``Σ_ss = C``, ``Σ_rs = −X C``, ``Σ_rr = Λ_rr⁻¹ + X C Xᵀ``, and the blocks of ``Λ_rr⁻¹``
    come from a block-tridiagonal recursion along the paths of the rest. Linear in the length of the recording where
    ``m`` solves per candidate are quadratic."""
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
    C = _scaled_spd_inverse(L_ss - np.asarray(L_rs.T @ X))
    del L_rs
    XC = _RowProduct(X, C)  # −Σ_rs, by row blocks: only the rows a chunk reads are held
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
    for start in range(0, len(which), SCHUR_CHUNK):
        k = which[start : start + SCHUR_CHUNK]
        per_cand = [own(int(i)) for i in k]
        yield k, _schur_chunk(c, k, per_cand, blocks, s_pos, r_pos, C, X, XC)


def _scaled_spd_inverse(A: FloatArray) -> FloatArray:
    """Inverse of a small dense SPD matrix through its Jacobi scaling ``D A D`` (``D = diag(A)^-½``): the same
    inverse in exact arithmetic, and an accurate one when the variables' scales differ by many orders (a tag surveyed
    to 1e-6 m beside tags known to 100 m: ``A``'s diagonal spans 1e16, its scaled condition ~10)."""
    d = np.sqrt(np.diag(A))
    if A.size == 0 or not np.all(d > 0):
        inv = np.linalg.inv(A) if A.size else A.copy()
    else:
        inv = np.linalg.inv(A / d[:, None] / d[None, :]) / d[:, None] / d[None, :]
    return 0.5 * (inv + inv.T)


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
) -> FloatArray:
    """``M_c`` of the candidates ``k`` from the Schur pieces of :func:`_schur_clique_gains`: ``Σ`` at their columns,
    separator-separator ``C``, rest-separator ``−X C``, rest-rest ``Λ_rr⁻¹`` blocks plus ``X C Xᵀ``."""
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
    return np.asarray(Ac @ Sig @ np.swapaxes(Ac, 1, 2))


def _exact_gram(
    prob: _Problem, c: _Candidates, gram: FloatArray, info: sp.csc_matrix, solver: SPDSolver, which: IntArray
) -> float:
    """Recompute the ``which`` candidates' ``A_c info⁻¹ A_cᵀ`` into ``gram`` from ``info`` (``Λ₀`` plus the picks, of
    ``prob``'s system, factorised by ``solver``); returns the solve's accuracy.

    Through the Schur complement onto the landmarks and the hubs (:func:`_schur_clique_gains`, linear in the
    recording's length) when that separator is small; through the blocks of ``info⁻¹`` (:class:`CovarianceBlocks`)
    when there is none (the rest is a chain); else ``m`` solves per candidate."""
    n = prob.system.dim
    separator = _chain_separator(info, prob.system, [])
    if separator and len(prob.system.columns(separator)) <= SCHUR_MAX_COLUMNS:
        for k, M in _schur_clique_gains(info, prob.system, separator, c, which):
            _store_gram(gram, k, M)
        return _solve_accuracy(info, solver)
    if not separator:
        idx = [c.index[int(i)] for i in which]
        blocks = _clique_blocks(info, prob.system, idx, solver)
        for s in range(0, len(which), GAIN_CHUNK):
            k = which[s : s + GAIN_CHUNK]
            Sig_c = _fill_cliques(blocks, prob.system, [c.index[int(i)] for i in k], c.Ac.shape[2])
            _store_gram(gram, k, c.Ac[k] @ Sig_c @ np.swapaxes(c.Ac[k], 1, 2))
        return _solve_accuracy(info, solver)
    for s in range(0, len(which), 256):  # Σ A_cᵀ by solves, m right-hand sides per candidate
        k = which[s : s + 256]
        Ac, cols = c.Ac[k], c.cols[k]
        nk, m, _ = Ac.shape
        rhs = np.zeros((n, nk, m))
        np.add.at(rhs, (cols, np.arange(nk)[:, None]), np.swapaxes(Ac, 1, 2))
        X = solver.solve(rhs.reshape(n, nk * m)).reshape(n, nk, m)
        _store_gram(gram, k, Ac @ X[cols, np.arange(nk)[:, None]])
    return _solve_accuracy(info, solver)


def _store_gram(gram: FloatArray, k: IntArray, M: FloatArray) -> None:
    """``M`` (``(len(k), m, m)``) of the candidates ``k`` into ``gram``'s upper triangles (symmetrised)."""
    for q, (a, b) in enumerate(_sym_pairs(M.shape[1])):
        gram[q, k] = 0.5 * (M[:, a, b] + M[:, b, a])


GAIN_CHUNK = 2048
"""Candidates whose ``Σ`` at their columns and ``M_c`` :func:`_initial_gram` holds at once (all of an hour's 61,000
tag measurements at once, with a small array per variable pair, held a few hundred MB)."""


def _initial_gram(prob: _Problem, c: _Candidates, solver: SPDSolver) -> FloatArray:
    """Upper triangles ``(m(m+1)/2, N)`` of ``A_c Λ₀⁻¹ A_cᵀ`` for ``prob``'s ``Λ₀`` (factorised by ``solver``), from
    the clique covariances; :data:`GAIN_CHUNK` candidates at a time."""
    Ac = c.Ac
    N, m, d = Ac.shape
    blocks = _clique_blocks(prob.info0, prob.system, c.index, solver)
    pairs = _sym_pairs(m)
    Gu = np.empty((len(pairs), N))
    for s in range(0, N, GAIN_CHUNK):
        k = slice(s, s + GAIN_CHUNK)
        Sig_c = _fill_cliques(blocks, prob.system, c.index[k], d)
        M0 = Ac[k] @ Sig_c @ np.swapaxes(Ac[k], 1, 2)
        for q, (a, b) in enumerate(pairs):
            Gu[q, k] = M0[:, a, b]
    return Gu


def _conditional_problem(prob: _Problem) -> _Problem:
    """The unfocused block of ``prob``: the same factors with their Jacobians at the unfocused variables ``U`` only,
    so that its information is ``Λ_UU`` and ``A_c Λ_UU⁻¹ A_cᵀ`` is ``K_c = A_c Σ_{·|F} A_cᵀ``, the covariance of the
    candidate's prediction given the focused variables.

    ``K_c`` was ``M_c − U_cᵀ Σ_F⁻¹ U_c`` and its downdates read ``Σ_{·|F} A_jᵀ = Σ A_jᵀ − Σ Wᵀ Σ_F⁻¹ W Σ A_jᵀ``:
    differences of terms ~1e9 times larger than the result when the focused variables are known only through the
    weak prior, and the result lost every digit (``K_c`` with negative diagonals on a camera-only rig hung on a
    surveyed tag; gains off by nats, the entropy drifting 70 nats in 90 picks). Solved with ``Λ_UU`` itself, nothing
    cancels."""
    sub = prob.system
    focused = set(prob.focused)
    keep = [v for v in range(len(sub.variables)) if v not in focused]
    remap = {v: k for k, v in enumerate(keep)}
    factors = []
    for f in sub.factors:
        vs: list[int] = []
        cols: list[int] = []
        off = 0
        for v in f.variables:
            d = sub.variables[v].dim
            if v not in focused:
                vs.append(remap[v])
                cols.extend(range(off, off + d))
            off += d
        J = f.jacobian[:, np.asarray(cols, dtype=np.int64)]  # (rows, 0) on focused variables only
        factors.append(Factor(tuple(vs), J, f.kind))
    usub = LinearSystem([sub.variables[v] for v in keep], factors)
    ucols = sub.columns(keep)
    return _Problem(
        usub,
        prob.base,
        prob.candidates,
        [],
        sp.csc_matrix(prob.prior[ucols][:, ucols]),
        sp.csc_matrix(prob.info0[ucols][:, ucols]),
        [remap[v] for v in prob.landmark_vars if v not in focused],
    )


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
    """One pick ``j`` on one side: ``Vt = (Σ A_jᵀ)ᵀ`` at the tracked rows, ``T = I + A_j Σ A_jᵀ`` with its inverse, a
    factor ``T⁻¹ = L_T L_Tᵀ`` and its condition number; for the capacitance tracker also ``lt = L⁻¹ A_W Σ_last A_jᵀ``.
    ``refined``: the refinement steps its solve took (:func:`_refined`)."""

    Vt: FloatArray
    T: FloatArray
    Tinv: FloatArray
    LT: FloatArray
    cond: float
    lt: FloatArray | None = None
    refined: int = 0


REFINE_BACKWARD_ERROR = 1e-13
"""A pick's solve through the window is refined while its componentwise backward error (:func:`_backward_error`) is
above this: a sparse Cholesky solve leaves ~1e-16; a window correction that cancels (the window holds a pick that
pinned a variable known only through a weak prior: ``C`` ~1e9) left ~1e-9 and errors of 4e-7 in ``Σ A_jᵀ``."""

REFINE_MAX_STEPS = 3
"""At most this many steps of iterative refinement per solve (each gains the digits the window's correction lost)."""


@dataclass
class _Operators:
    """``Σ_S`` and ``Λ_S`` on a tracker's space (the compact state, or the tracked rows of the reduced window): the
    exact information of the picks so far, against which a solve is refined; ``diag Λ_S`` and ``‖D |Λ| D‖∞``
    (``D = diag^-½``) for its backward error."""

    sigma: Callable[[FloatArray], FloatArray]
    lam: Callable[[FloatArray], FloatArray]
    diag: FloatArray
    norm: float


def _backward_error(ops: _Operators, B: FloatArray, X: FloatArray) -> tuple[float, FloatArray]:
    """The normwise backward error of the Jacobi-scaled system ``(D Λ D)(D⁻¹ X) = D B`` (``D = diag(Λ)^-½``),
    ``‖D r‖ / (‖D Λ D‖ ‖D⁻¹ X‖ + ‖D B‖)`` in the max-norm over all of ``X``'s columns at once, and the residual
    ``r = B − Λ X``. Unchanged by a rescaling of the variables (a tag surveyed to 1e-6 m and one known to 100 m count
    alike); a direct sparse solve leaves ~1e-16. (Componentwise, it was set by rows where ``X`` is ~1e-20 and did not
    matter: 0.8 where the solve agreed with a fresh factorisation to 1e-14.)"""
    r = B - ops.lam(X)
    if not r.size:
        return 0.0, r
    d = (1.0 / np.sqrt(ops.diag))[:, None]
    num = float(np.abs(d * r).max())  # over the whole array: a column-wise max of an n × m array is 30x slower
    den = ops.norm * float(np.abs(X / d).max()) + float(np.abs(d * B).max())
    return (num / den if den > 0 else (np.inf if num > 0 else 0.0)), r


def _refined(ops: _Operators, B: FloatArray, V: FloatArray) -> tuple[FloatArray, int]:
    """``V ≈ Σ_S B`` refined against ``Λ_S``: ``V += Σ_S (B − Λ_S V)`` while the backward error is above
    :data:`REFINE_BACKWARD_ERROR` (at most :data:`REFINE_MAX_STEPS` times); returns ``V`` and the steps taken.

    The window's correction ``Σ_last A_Wᵀ C⁻¹ A_W Σ_last B`` nearly cancels ``Σ_last B`` after a pick that pinned a
    variable known only through a weak prior, and ``V`` loses as many digits as ``C``'s condition (~1e9); the
    downdates of every candidate then carried the error. The residual is computed with the picks' information
    itself (nothing inverted), so each step restores those digits."""
    steps = 0
    for _ in range(REFINE_MAX_STEPS):
        beta, r = _backward_error(ops, B, V)
        if beta <= REFINE_BACKWARD_ERROR:
            break
        V = V + ops.sigma(r)
        steps += 1
    return V, steps


def _capacitance_operators(ct: _CapacitanceTracker) -> _Operators:
    def sigma(B: FloatArray) -> FloatArray:
        x = ct.solve_last(B)
        if ct.window:
            rhs = np.zeros_like(B)
            ct.scatter(ct.ltsolve(ct.lsolve(ct.gather(x))), rhs)
            x = x - ct.solve_last(rhs)
        return x

    def lam(Y: FloatArray) -> FloatArray:
        out = np.asarray(ct.info @ Y)
        if ct.window:
            ct.scatter(ct.gather(Y), out)
        return out

    return _Operators(sigma, lam, ct.diag, ct.scaled_norm)


def _capacitance_step(ct: _CapacitanceTracker, c: _Candidates, j: int) -> _Step:
    """The pick's quantities from two solves with the last factor (see :class:`_CapacitanceTracker`), refined
    (:func:`_refined`) when the window's correction cancelled."""
    n, m, wj = ct.n, ct.m, c.width[j]
    cj, Aj = c.cols[j, :wj], c.Ac[j, :, :wj]
    B = np.zeros((n, m))
    B[cj] = Aj.T
    x1 = ct.solve_last(B)  # Σ_last A_jᵀ
    if not ct.window:
        return _pick_step(x1[c.rows], Aj, x1[cj], np.zeros((0, m)))
    lt = ct.lsolve(ct.gather(x1))  # L⁻¹ A_W Σ_last A_jᵀ
    rhs = np.zeros((n, m))
    ct.scatter(ct.ltsolve(lt), rhs)  # A_Wᵀ C⁻¹ A_W Σ_last A_jᵀ
    V, steps = _refined(_capacitance_operators(ct), B, x1 - ct.solve_last(rhs))  # Σ_S A_jᵀ
    return _pick_step(V[c.rows], Aj, V[cj], lt, steps)


def _pick_step(V: FloatArray, Aj: FloatArray, Vj: FloatArray, lt: FloatArray | None = None, refined: int = 0) -> _Step:
    """The :class:`_Step` of ``V = Σ A_jᵀ`` at the tracked rows (``Vj``: at the pick's own columns)."""
    T, Tinv, LT, cond = _at_least_identity(np.eye(Aj.shape[0]) + Aj @ Vj)
    return _Step(np.ascontiguousarray(V.T), T, Tinv, LT, cond, lt, refined)


def _window_operators(tracker: _Tracker) -> _Operators | None:
    """On the Schur-reduced window (``rows`` None: the tracked information is exact on the tracked rows), else None
    (the unreduced window keeps ``Σ_S`` at the tracked rows only: nothing to take a residual with)."""
    if tracker.rows is not None:
        return None
    every = np.arange(tracker.n)
    info = sp.csc_matrix(tracker.info + tracker.add_info(tracker.window))
    d = 1.0 / np.sqrt(info.diagonal())
    norm = float(np.max(d * (abs(info) @ d))) if len(d) else 0.0

    def sigma(B: FloatArray) -> FloatArray:
        return np.ascontiguousarray(tracker.solve(every, B, every).T)

    return _Operators(sigma, lambda Y: np.asarray(info @ Y), info.diagonal(), norm)


def _window_step(tracker: _Tracker, c: _Candidates, j: int) -> _Step:
    """The pick's quantities from the window tracker, refined (:func:`_refined`) on the reduced window."""
    wj, m = c.width[j], tracker.m
    Aj, jpos = c.Ac[j, :, :wj], c.pos[j, :wj]
    V = tracker.solve(c.cols[j, :wj], Aj.T, jpos).T  # Σ A_jᵀ at rows
    steps = 0
    ops = _window_operators(tracker) if tracker.window else None
    if ops is not None:
        B = np.zeros((tracker.n, m))
        B[jpos] = Aj.T
        V, steps = _refined(ops, B, V)
    return _pick_step(V, Aj, V[jpos], refined=steps)


def _apply_pick(gram: FloatArray, B: sp.csr_matrix, m: int, st: _Step) -> FloatArray:
    """``G_c −= g_c T⁻¹ g_cᵀ`` for every candidate (``g_c = A_c V``): ``H = A_c V L_T`` at the candidates' columns is
    one sparse product, the update runs on the upper triangles. Returns the downdates' diagonals ``(m, N)``."""
    N = gram.shape[1]
    H = B @ (st.Vt.T @ st.LT)  # (m N, m)
    Ht = np.ascontiguousarray(H.reshape(m, N, m).transpose(0, 2, 1))  # (m, m, N)
    dm = np.empty((m, N))
    for q, (a, b) in enumerate(_sym_pairs(m)):
        d = (Ht[a] * Ht[b]).sum(axis=0)
        gram[q] -= d
        if a == b:
            dm[a] = d
    return dm


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


@dataclass
class _Side:
    """One information matrix whose ``A_c Λ_S⁻¹ A_cᵀ`` the greedy keeps for every candidate: the whole compact graph
    (``M_c``), or its unfocused block (``K_c``, :func:`_conditional_problem`); each with its own tracker."""

    prob: _Problem
    c: _Candidates
    gram: FloatArray
    """``(m(m+1)/2, N)`` upper triangles, kept current (``_Gains.Mu`` or ``_Gains.Ku``, the same array)."""
    delta: float
    """The accuracy of ``Λ₀``'s solves (:func:`_solve_accuracy`)."""
    tracker: _Tracker | _CapacitanceTracker | None = None
    B: sp.csr_matrix | None = None
    update_s: float = 0.0
    """Time in the per-candidate updates (:func:`_apply_pick`)."""
    reduced: bool = False
    info_s: sp.csc_matrix | None = None
    n_folded: int = 0

    @classmethod
    def of(cls, prob: _Problem, solver: SPDSolver) -> _Side:
        """The side's candidates and their ``A_c Λ₀⁻¹ A_cᵀ``."""
        c = _candidates(prob.system, prob.candidates)
        return cls(prob, c, _initial_gram(prob, c, solver), _solve_accuracy(prob.info0, solver))

    def start(self, refactor_every: int | None, options: TrackerOptions) -> None:
        """The tracker (on ``Λ₀`` or its Schur complement onto the candidates' rows) and the candidate operator."""
        prob, c = self.prob, self.c
        capacitance, info_t, rows_t = _tracked_information(prob, c.rows, options)
        self.reduced = rows_t is None
        m = c.Ac.shape[1]

        def add_info(js: list[int]) -> SparseMatrix:
            info = prob.system.information([c.index[i] for i in js])
            return info if rows_t is not None else info[c.rows][:, c.rows]

        if capacitance:
            weak = np.zeros(prob.system.dim, dtype=bool)
            weak[prob.system.columns(prob.landmark_vars)] = True
            for bf in prob.base:
                weak[prob.system.factor_columns(bf)] = False
            self.tracker = _CapacitanceTracker(
                prob.info0, m, c.Ac.shape[2], add_info, refactor_every, weak, options.refactor_on_first_observation
            )
        else:
            self.tracker = _Tracker(info_t, rows_t, m, add_info, refactor_every)
        self.B = _candidate_operator(c.Ac, c.pos, len(c.rows))
        self.info_s = prob.info0

    def pick(self, j: int) -> tuple[_Step, FloatArray, bool]:
        """Add candidate ``j``: its step, the downdates' diagonals, and whether the tracker refactorised."""
        assert self.tracker is not None and self.B is not None
        m = self.c.Ac.shape[1]
        if isinstance(self.tracker, _CapacitanceTracker):
            st = _capacitance_step(self.tracker, self.c, j)
        else:
            st = _window_step(self.tracker, self.c, j)
        tu = time.perf_counter()
        dm = _apply_pick(self.gram, self.B, m, st)
        self.update_s += time.perf_counter() - tu
        if isinstance(self.tracker, _CapacitanceTracker):
            assert st.lt is not None
            refactorised = self.tracker.add(j, self.c.cols[j], self.c.Ac[j], st.lt.T, st.T)
        else:
            refactorised = self.tracker.add(j, st.Vt, st.Tinv)
        return st, dm, refactorised

    def recompute(self, which: IntArray, picks: list[int]) -> float:
        """The ``which`` candidates' ``A_c Λ_S⁻¹ A_cᵀ`` again from the information of the ``picks`` so far; returns
        its accuracy."""
        assert self.tracker is not None and self.info_s is not None
        if self.tracker.window:
            self.tracker._refactorise()
        if isinstance(self.tracker, _CapacitanceTracker):  # its factor is of Λ₀ plus every pick now
            self.info_s, solver = self.tracker.info, self.tracker.solver
        else:
            fold = self.prob.system.information([self.c.index[i] for i in picks[self.n_folded :]])
            self.info_s = sp.csc_matrix(self.info_s + fold)
            solver = SPDSolver(self.info_s)
        self.n_folded = len(picks)
        return _exact_gram(self.prob, self.c, self.gram, self.info_s, solver, which)

    def stats(self) -> dict[str, float]:
        t = self.tracker
        assert t is not None
        out = {"factor_s": t.factor_s, "refactorisations": float(t.refactorisations)}
        if isinstance(t, _CapacitanceTracker):
            out["first_observation_refactorisations"] = float(t.first_observation_refactorisations)
        return out


def _greedy(
    sides: list[_Side], g: _Gains, budget: int, refactor_every: int | None, options: TrackerOptions
) -> tuple[list[int], list[float], dict[str, float]]:
    """``budget`` greedy steps: the best gain, each side's step from its tracker, the update of every gain.

    ``sides[0]`` keeps ``M_c`` (``g.Mu``), ``sides[1]`` (absent when every candidate is inside the focus) ``K_c``
    (``g.Ku``); the gains are ``½ log det(I + M_c) − ½ log det(I + K_c)``."""
    t_red = time.perf_counter()
    for side in sides:
        side.start(refactor_every, options)
    stats = {"reduce_s": time.perf_counter() - t_red}
    picks: list[int] = []
    gains: list[float] = []
    t_gain = t_exact = 0.0
    refined = 0
    t_loop = time.perf_counter()
    grams = [s.gram for s in sides]
    precision = _Precision.of(grams, [s.delta for s in sides], g.pairs, options.recompute_tol)
    with single_threaded_blas():

        def recompute(redo: list[int], bounds: list[FloatArray]) -> None:
            """The sides ``redo``, at their candidates whose bound is above a share of ``RESET_FRACTION · tol``, again
            from the information of the picks so far (see :class:`_Precision`)."""
            nonlocal t_exact
            tr = time.perf_counter()
            for k in redo:
                idx = np.flatnonzero((bounds[k] > options.recompute_tol * RESET_FRACTION / len(sides)) & ~g.picked)
                precision.reset(k, sides[k].gram, idx, sides[k].recompute(idx, picks))
                precision.recomputed += len(idx)
            precision.recomputations += 1
            t_exact += time.perf_counter() - tr

        for _ in range(budget):
            tg = time.perf_counter()
            gain_all = _all_gains(g)
            j = int(np.argmax(gain_all))
            done: set[int] = set()
            while len(done) < len(sides):  # a side whose bounds alone leave the pick in doubt first, then the others
                bounds = precision.bounds(grams, g.m)
                if not precision.in_doubt(gain_all, j, np.sum(bounds, axis=0), g.picked):
                    break
                todo = [k for k in range(len(sides)) if k not in done]
                alone = [k for k in todo if precision.in_doubt(gain_all, j, bounds[k], g.picked)]
                redo = alone or [max(todo, key=lambda k: float(bounds[k].max()))]
                recompute(redo, bounds)
                done |= set(redo)
                gain_all = _all_gains(g)
                j = int(np.argmax(gain_all))
            gain = float(gain_all[j])
            t_gain += time.perf_counter() - tg
            picks.append(j)
            gains.append(gain)
            g.picked[j] = True
            for k, side in enumerate(sides):
                st, dm, _ = side.pick(j)
                precision.downdated(k, dm, st.cond)
                refined += st.refined
    t_update = sum(side.update_s for side in sides)
    stats |= {"loop_s": time.perf_counter() - t_loop, "update_s": t_update, "gain_s": t_gain}
    stats |= {
        "recomputations": float(precision.recomputations),
        "recomputed_candidates": float(precision.recomputed),
        "recompute_s": t_exact,
        "refinement_steps": float(refined),
    }
    for side in sides:
        for key, v in side.stats().items():
            stats[key] = stats.get(key, 0.0) + v
    stats["solve_s"] = stats["loop_s"] - t_update
    s0 = sides[0]
    stats |= {
        "tracked_rows": float(len(s0.c.rows)),
        "conditional_rows": float(len(sides[1].c.rows)) if len(sides) > 1 else 0.0,
        "reduced": float(s0.reduced),
        "capacitance": float(isinstance(s0.tracker, _CapacitanceTracker)),
    }
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
    focused blocks, ``S_c − U_cᵀ Σ_F⁻¹ U_c = I + A_c Σ_{·|F} A_cᵀ`` where ``Σ_{·|F} = Λ_UU⁻¹`` (on the
    unfocused columns ``U``) is the covariance of the other variables given the focused ones. So
    ``gain_c = ½ log det(I + M_c) − ½ log det(I + K_c)`` with ``M_c = A_c Σ A_cᵀ`` and
    ``K_c = A_c Σ_{·|F} A_cᵀ``, both ``m × m`` per candidate, each kept for its own information matrix
    (``Λ_S`` and ``Λ_S,UU``). After picking ``j`` with ``V = Σ A_jᵀ``, ``T = I + A_j V`` (and ``Y = Σ_{·|F} A_jᵀ``,
    ``E = I + A_j Y``)::

        M_c −= g_c T⁻¹ g_cᵀ,            g_c = A_c V
        K_c −= k_c E⁻¹ k_cᵀ,            k_c = A_c Y

    ``V`` and ``Y`` are one solve each (the last sparse factor plus a correction over the picks since,
    refined against the picks' information when it cancels). The capacitance tracker
    (:class:`_CapacitanceTracker`, default) keeps nothing at the candidates' rows: two solves per step
    with the last factor, per-step cost independent of the candidates apart from the ``O(N)`` update;
    the window tracker keeps the corrections at the candidates' rows of the Schur-reduced system. When
    a pick could be wrong by more than ``options.recompute_tol`` nats (:class:`_Precision`), the
    candidates in doubt are recomputed from the information of the picks.

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
    if full or len(fcols) > DENSE_FOCUS_MAX:  # no dense Σ_F: the entropy from sparse log-determinants
        h0 = _sparse_focused_entropy(prob.info0, fcols)
    else:
        _, SF = _focused_cov(solver, prob.system.dim, fcols, keep=False)
        h0 = entropy_from_logdet(logdet_spd(SF), len(fcols))
    N = len(cand)
    status = _budget_status(budget, N)
    stats: dict[str, float] = {"setup_s": time.perf_counter() - t0, "full_focus": float(full)}
    if status in ("no_candidates", "budget_zero"):
        return MeasurementSelection([], [], status or "ok", N, budget, h0, h0, stats)
    if budget >= N:
        after = focused_entropy(system, base + cand, focused, landmark_prior_sigma, base)
        return MeasurementSelection(cand, [float("nan")] * N, status or "ok", N, budget, h0, after, stats)
    sides = [_Side.of(prob, solver)]
    del solver
    if not full:  # K_c from the unfocused block; K_c = 0 when every candidate is inside the focus
        cprob = _conditional_problem(prob)
        sides.append(_Side.of(cprob, SPDSolver(cprob.info0)))
    m = sides[0].c.Ac.shape[1]
    Ku = sides[1].gram if not full else np.zeros_like(sides[0].gram)
    g = _Gains(sides[0].gram, Ku, _sym_pairs(m), m, np.zeros(N, dtype=bool))
    stats["clique_cov_s"] = time.perf_counter() - t0 - stats["setup_s"]
    stats["solve_delta"] = sides[0].delta
    js, gains, loop_stats = _greedy(sides, g, budget, refactor_every, options)
    del prob, sides, g  # before the last factorisation
    stats |= loop_stats
    picks = [cand[j] for j in js]
    # the running entropy is h0 - Σ gains; the exact one takes one more factorisation. They differ when rounding in the
    # tracked covariances has built up beyond the recomputations' tolerance: the drift is reported and the exact value
    # returned.
    h1 = focused_entropy(system, base + picks, focused, landmark_prior_sigma, base)
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
        h1 = focused_entropy(system, base + cand, focused, landmark_prior_sigma, base)
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
    h1 = focused_entropy(system, base + picks, focused, landmark_prior_sigma, base)
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
