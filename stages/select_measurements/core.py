"""Measurement selection without a run folder: :func:`choose` runs any strategy on a loaded graph.

```python
loaded = load_graph(ctx.input("graph"))
system = linear_system(loaded)                                   # optional: linearise once, reuse
choice = choose(loaded, focused_tag_ids, cfg, system)            # MeasurementChoice
graph, values = build_reduced(loaded, choice.keep_factor_indices(loaded))
```

The information matrix is linearised once at the full-graph solution; every non-tag factor (prior,
odometry, loops) is always kept; the candidates are the tag measurements of the focused landmarks.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field

from pipeline.errors import StageError
from stages.estimation.gaussian import entropy_from_logdet
from stages.estimation.linear_system import LinearSystem
from stages.estimation.measurement_selection import (
    MeasurementSelection,
    TrackerOptions,
    focused_entropy,
    select_all,
    select_information,
    select_leverage,
    select_random,
    select_uniform,
    weak_prior,
)
from stages.estimation.sparse_cov import SPDSolver, logdet_spd
from stages.select_measurements.config import SelectMeasurementsConfig

if TYPE_CHECKING:
    from stages.graph.load import LoadedGraph

FloatArray = npt.NDArray[np.float64]


def linear_system(loaded: LoadedGraph) -> LinearSystem:
    """The full graph linearised at its solution (factor ``i`` = row ``i`` of ``factors.parquet``)."""
    landmark_keys = set(loaded.landmark_keys.values())
    return LinearSystem.from_gtsam(loaded.graph, loaded.values, is_landmark=landmark_keys.__contains__)


class MeasurementChoice(BaseModel):
    """The result of one measurement selection (the content of ``selection.json`` but its ``settings``)."""

    model_config = ConfigDict(extra="forbid")

    strategy: str = Field(description="the measurement-selection strategy that ran")
    budget: int = Field(description="K, the measurement budget as run (`all`: the number of candidates)")
    focus: str = Field(description="`selected` (the focused landmarks of select_landmarks) or `all`")
    focused_tag_ids: list[int] = Field(description="the landmarks whose measurements were candidates")
    focused_pose_indices: list[int] = Field(
        default_factory=list,
        description="keyframes (rows of `graph/poses.parquet`) whose poses were focused too (`focus_poses`)",
    )
    factor_indices: list[int] = Field(
        description="kept tag-measurement factors (rows of `graph/factors.parquet`), in pick order"
    )
    gains: list[float] = Field(
        description="per pick: entropy reduction (information, nats), sampling probability (leverage), else NaN"
    )
    status: str = Field(description="`ok`, `budget_zero`, `budget_exceeds_candidates` or `no_candidates`")
    message: str = Field(description="the status in words")
    n_candidates: int = Field(description="candidate measurements (the tag factors of the focused landmarks)")
    candidates: list[int] = Field(description="candidate factor indices, in time order")
    entropy_before: float = Field(
        description="entropy (nats) of the focused landmarks with odometry, priors and the weak landmark prior only"
    )
    entropy_after: float = Field(description="the same with the kept measurements added")
    seconds: float = Field(description="time the selection took, s")
    stats: dict[str, float] = Field(default_factory=dict, description="the strategy's counters and timings")

    def keep_factor_indices(self, loaded: LoadedGraph) -> list[int]:
        """Every factor of the reduced graph (sorted): all non-tag factors plus the kept measurements; with
        ``focus: poses``, every factor but the loop closures not kept."""
        picks = {int(i) for i in self.factor_indices}
        if self.focus == "poses":
            dropped = set(self.candidates) - picks
            return [i for i in range(len(loaded.rows)) if i not in dropped]
        return sorted({int(i) for i in loaded.fixed_factor_indices} | picks)

    def entropy_per_step(self) -> FloatArray | None:
        """Focused entropy after each pick (information strategy only: before minus the cumulative gains)."""
        if self.strategy != "information" or not self.factor_indices:
            return None
        return np.asarray(self.entropy_before - np.cumsum(self.gains))


def focused_variables(loaded: LoadedGraph, system: LinearSystem, tag_ids: Iterable[int]) -> list[int]:
    """Variable indices (in ``system``) of the landmarks with these tag ids."""
    return [system.index_of_key(loaded.landmark_keys[int(t)]) for t in tag_ids]


def loop_closures(loaded: LoadedGraph) -> list[int]:
    """Pose-to-pose factors between non-consecutive poses (``kind == "loop"``), in time order (then index)."""
    loops = [i for i, r in enumerate(loaded.rows) if r.kind == "loop"]
    return sorted(loops, key=lambda i: (loaded.rows[i].stamp_ns or 0, i))


def _pose_focus(loaded: LoadedGraph, system: LinearSystem) -> tuple[list[int], list[int], list[int]]:
    """``focus: poses``: every pose variable focused, the loop closures the candidates, every other factor the base."""
    cands = loop_closures(loaded)
    if not cands:
        raise StageError(
            "select_measurements.focus=poses: the graph has no loop closures (pose-to-pose edges between "
            "non-consecutive poses) to choose from; every factor is kept as it is"
        )
    focused = [system.index_of_key(k) for k in loaded.pose_keys]
    cset = set(cands)
    return focused, cands, [i for i in range(len(loaded.rows)) if i not in cset]


def candidate_factors(loaded: LoadedGraph, tag_ids: Iterable[int]) -> list[int]:
    """Tag-measurement factors of these landmarks, in time order (then factor index)."""
    tags = {int(t) for t in tag_ids}
    cands = [int(i) for i in loaded.tag_factor_indices if loaded.rows[int(i)].tag_id in tags]
    return sorted(cands, key=lambda i: (loaded.rows[i].stamp_ns or 0, i))


def _message(status: str, budget: int, n: int, kept: int, strategy: str, n_focused: int) -> str:
    if status == "budget_zero":
        return "budget 0: no tag measurement kept (odometry and priors only)"
    if status == "budget_exceeds_candidates":
        return f"budget {budget} exceeds the {n} candidate measurements: all {n} kept"
    if status == "no_candidates":
        return "the focused landmarks have no tag measurements"
    what = f"{n_focused} focused landmarks" if n_focused >= 0 else "the poses (loop closures)"
    if strategy == "all":
        return f"all {n} candidate measurements of {what} kept"
    return f"{kept} of {n} candidate measurements of {what} kept by {strategy}"


def choose(
    loaded: LoadedGraph,
    focused_tag_ids: Sequence[int] | None,
    cfg: SelectMeasurementsConfig,
    system: LinearSystem | None = None,
    tracker: TrackerOptions | None = None,
    focus_pose_indices: Sequence[int] = (),
) -> MeasurementChoice:
    """Run one measurement-selection strategy.

    Args:
        loaded: the full graph (:func:`stages.graph.load.load_graph`).
        focused_tag_ids: the focused landmarks (``focused.json``'s ``tag_ids``); ignored with ``cfg.focus == "all"``.
        cfg: the settings (``strategy``, ``budget``, ``focus``, ...).
        system: the graph linearised at its solution (:func:`linear_system`), to reuse across calls.
        tracker: ``information``: how the greedy tracks the covariance (default :class:`TrackerOptions`; the
            variants give the same selection at different costs).
        focus_pose_indices: keyframes whose poses join the focused set (eq. 23's W), e.g. the riskiest ones
            (:func:`stages.risk.riskiest_keyframes`); the entropy is then over the landmarks and these poses.

    Raises:
        StageError: no focused landmarks, or focused tags that the graph does not have.
    """
    t0 = time.perf_counter()
    if cfg.focus == "all":
        tags = sorted(loaded.landmark_keys)
        if not tags:
            raise StageError(
                "select_measurements.focus=all: the graph has no landmarks (a pose graph); to keep the K loop "
                "closures that best localise the poses, use --set select_measurements.focus=poses"
            )
    elif cfg.focus == "poses":
        tags = []
    else:
        if not focused_tag_ids:
            raise StageError(
                "no focused landmarks (select_landmarks kept none); run 'focusmap select-landmarks RUN' with a "
                "budget above 0, or use --set select_measurements.focus=all"
            )
        tags = [int(t) for t in focused_tag_ids]
        missing = sorted(set(tags) - set(loaded.landmark_keys))
        if missing:
            raise StageError(
                f"focused tags {missing} are not in the graph; select_landmarks is stale: re-run "
                "'focusmap select-landmarks RUN'"
            )
    system = system if system is not None else linear_system(loaded)
    if cfg.focus == "poses":
        focused, cands, base = _pose_focus(loaded, system)
    else:
        focused = focused_variables(loaded, system, tags)
        focused += [system.index_of_key(loaded.pose_keys[int(i)]) for i in focus_pose_indices]
        cands = candidate_factors(loaded, tags)
        base = [int(i) for i in loaded.fixed_factor_indices]
    sigma = cfg.landmark_prior_sigma_m
    sel: MeasurementSelection
    if cfg.strategy == "information":
        sel = select_information(system, cands, focused, cfg.budget, base, sigma, cfg.refactor_every, tracker)
    elif cfg.strategy == "leverage":
        sel = select_leverage(
            system, cands, focused, cfg.budget, base, cfg.leverage_draws, cfg.leverage_measure, cfg.seed, sigma
        )
    elif cfg.strategy == "uniform":
        times = [float(loaded.rows[c].stamp_ns or 0) for c in cands]
        sel = select_uniform(cands, cfg.budget, times)
    elif cfg.strategy == "random":
        sel = select_random(cands, cfg.budget, cfg.seed)
    else:
        sel = select_all(cands)
    h0, h1 = sel.entropy_before, sel.entropy_after
    if not np.isfinite(h0):
        h0 = focused_entropy(system, base, focused, sigma)
    if not np.isfinite(h1):
        h1 = focused_entropy(system, base + list(sel.picks), focused, sigma, base) if sel.picks else h0
    budget = len(cands) if cfg.strategy == "all" else cfg.budget
    return MeasurementChoice(
        strategy=cfg.strategy,
        budget=budget,
        focus=cfg.focus,
        focused_tag_ids=tags,
        focused_pose_indices=[int(i) for i in focus_pose_indices] if cfg.focus != "poses" else [],
        factor_indices=[int(p) for p in sel.picks],
        gains=[float(g) for g in sel.gains],
        status=sel.status,
        message=_message(
            sel.status, cfg.budget, len(cands), len(sel.picks), cfg.strategy, -1 if cfg.focus == "poses" else len(tags)
        ),
        n_candidates=len(cands),
        candidates=cands,
        entropy_before=float(h0),
        entropy_after=float(h1),
        seconds=time.perf_counter() - t0,
        stats={k: float(v) for k, v in sel.stats.items()},
    )


def base_information(system: LinearSystem, base: Sequence[int], landmark_prior_sigma: float) -> sp.csc_matrix:
    """``Σ_base AᵀA`` plus the weak prior (:func:`weak_prior`): the information every replay step starts from."""
    return sp.csc_matrix(system.information(list(base)) + weak_prior(system, base, landmark_prior_sigma))


def focused_covariances(
    system: LinearSystem,
    base: Sequence[int],
    picks: Sequence[int],
    focused: Sequence[int],
    landmark_prior_sigma: float,
    base_info: sp.csc_matrix | None = None,
) -> tuple[list[FloatArray], float]:
    """Marginal covariance (tangent) of each focused variable and the focused entropy (nats), given the factors.

    One sparse factorisation of ``Λ = Σ_{base + picks} AᵀA`` + the weak prior (:func:`weak_prior`) and one solve
    with the focused columns; no dense ``n × n`` matrix. ``base_info``: :func:`base_information` of ``base``,
    assembled once by a caller that replays many steps (the base is the whole odometry chain; the picks are few).
    """
    if base_info is None:
        base_info = base_information(system, base, landmark_prior_sigma)
    info = sp.csc_matrix(base_info + system.information(list(picks))) if picks else base_info
    cols = system.columns(focused)
    E = np.zeros((system.dim, len(cols)))
    E[cols, np.arange(len(cols))] = 1.0
    X = SPDSolver(info).solve(E)
    SF = X[cols]
    del X, E
    SF = 0.5 * (SF + SF.T)
    blocks, off = [], 0
    for v in focused:
        d = system.variables[v].dim
        blocks.append(SF[off : off + d, off : off + d])
        off += d
    return blocks, entropy_from_logdet(logdet_spd(SF), len(cols))


def summary_of(choice: MeasurementChoice) -> dict[str, Any]:
    """The stage summary's selection fields."""
    return {
        "strategy": choice.strategy,
        "budget": choice.budget,
        "focus": choice.focus,
        "focused_landmarks": len(choice.focused_tag_ids),
        "candidates": choice.n_candidates,
        "selected": len(choice.factor_indices),
        "status": choice.status,
        "message": choice.message,
        "entropy_before": choice.entropy_before,
        "entropy_after": choice.entropy_after,
        "entropy_reduction": choice.entropy_before - choice.entropy_after,
        "select_seconds": round(choice.seconds, 4),
    }
