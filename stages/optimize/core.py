"""The reduced graph, solved: pure functions shared by the optimize stage and evaluate (no run folder needed).

```python
loaded = load_graph(ctx.input("graph"))
reduced = solve_reduced(loaded, focused_tag_ids, selected_factor_indices, heights)
reduced.landmark_map          # stages.risk.LandmarkMap of the observed landmarks (reduced marginals)
reduced.focused_entropy       # ½ log det(2πe Σ_F), nats, over every focused landmark
```

Entropy convention (Mu et al. Table I's "entropy on focused landmarks"): the differential entropy of
the joint Gaussian of the focused landmark variables, ``H = ½ log det Σ_F + (d/2) log(2πe)`` nats,
``d`` = their total tangent dimension (2 per planar landmark). A focused landmark that keeps no
measurement is not in the reduced graph; it enters with an independent isotropic prior of standard
deviation ``unobserved_sigma_m`` per dimension (100 m by default, the selection's weak landmark
prior), so cases that lose focused landmarks are charged for it. ``focused_entropy_observed`` is the
same over the observed focused landmarks only.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import gtsam
import numpy as np
import numpy.typing as npt

from pipeline.errors import StageError
from stages.estimation.gaussian import entropy_from_logdet, gaussian_entropy
from stages.estimation.linear_system import landmark_prior_sigmas
from stages.graph.consider import ConsiderTerm, OdometryCalibration, consider_term
from stages.graph.factors import FactorRow, build_graph
from stages.graph.load import LoadedGraph
from stages.graph.marginals import key_dims, sparse_joint_covariance, tree_marginals
from stages.graph.models import graph_model
from stages.graph.problem import GraphProblem
from stages.graph.solve import Solution, check_problem, indeterminant_message, optimise, unanchored
from stages.graph.variables import var_kind
from stages.risk import LandmarkMap, PathGeometry, map_covariances

FloatArray = npt.NDArray[np.float64]


@dataclass
class ReducedMap:
    """A solved reduced graph and what the metrics need."""

    problem: GraphProblem
    solution: Solution
    marginals: dict[int, FloatArray]
    full_index: npt.NDArray[np.int64]
    """Factor ``i`` of the reduced graph is factor ``full_index[i]`` of the full graph; −1: a prior the reduced graph
    adds to keep its anchor (:func:`_gauge_rows`), no factor of the full graph."""
    focused_tag_ids: list[int]
    observed_tag_ids: list[int]
    """Landmarks with at least one kept measurement (the map the robot carries)."""
    landmark_map: LandmarkMap
    focused_entropy: float
    focused_entropy_observed: float
    focused_dim: int
    n_measurements: int
    """Kept landmark measurements (tag factors)."""
    dropped_unfocused: int
    """Selected measurements of landmarks outside the focused set (left out)."""
    timing_s: dict[str, float] = field(default_factory=dict)
    consider: ConsiderTerm | None = None
    """The odometry calibration's uncertainty (:mod:`stages.graph.consider`), already in ``marginals`` and the
    entropies; None when the run was not calibrated."""

    @property
    def focused_observed(self) -> list[int]:
        """Focused landmarks that kept at least one measurement."""
        obs = set(self.observed_tag_ids)
        return [t for t in self.focused_tag_ids if t in obs]


def solve_reduced(
    loaded: LoadedGraph,
    focused_tag_ids: Iterable[int],
    selected_factor_indices: Iterable[int],
    landmark_heights: Mapping[int, tuple[float, float]] | None = None,
    initialise_from: str = "dead_reckoning",
    max_iterations: int = 100,
    relative_error_tol: float = 1e-6,
    unobserved_sigma_m: float = 100.0,
    entropy_tag_ids: Iterable[int] | None = None,
    row_override: Mapping[int, FactorRow] | None = None,
) -> ReducedMap:
    """Build the reduced graph (every non-tag factor + the selected tag factors of focused landmarks), solve it.

    Args:
        loaded: the full graph (:func:`stages.graph.load.load_graph`).
        focused_tag_ids: the focused landmarks (select_landmarks' ``tag_ids``).
        selected_factor_indices: full-graph indices of the kept measurements (select_measurements'
            ``factor_index``); those of unfocused landmarks and non-tag factors are ignored.
        landmark_heights: planar graphs: tag id to (z, var z) for the written landmarks (graph's table).
        initialise_from: ``dead_reckoning`` (the full graph's initial values) or ``full_solution``.
        max_iterations, relative_error_tol: Levenberg-Marquardt settings.
        unobserved_sigma_m: prior sigma of focused landmarks without measurements, in the entropy.
        entropy_tag_ids: the landmarks the entropy is taken over (default: the focused ones). Evaluate passes
            the collision-focused set here for every case, so the "full" cases are scored on the same landmarks.
        row_override: full-graph factor index to a replacement row (same keys and type), e.g. evaluate's
            ground-truth-consistent measurements (``stages.evaluate.analysis.oracle_rows``).

    Raises:
        StageError: the reduced graph is singular (names the variable).
    """
    t0 = time.perf_counter()
    focused = sorted({int(t) for t in focused_tag_ids})
    keep, kept_tags, dropped = _reduced_factors(loaded, focused, selected_factor_indices)
    override = row_override or {}
    rows = [override.get(int(i), loaded.rows[i]) for i in keep]
    src = loaded.initial if initialise_from == "dead_reckoning" else loaded.values
    problem = loaded.restricted(rows, src, dict(landmark_heights or {}))
    gauge = _gauge_rows(loaded, problem)
    if gauge:  # the reduced graph lost its anchor: a prior in the full map's frame, not a factor of the full graph
        rows += gauge
        keep = np.concatenate([keep, np.full(len(gauge), -1, dtype=np.int64)])
        problem = loaded.restricted(rows, src, dict(landmark_heights or {}))
    observed = sorted(problem.landmark_keys)
    check_problem(problem)
    graph = build_graph(rows)
    t1 = time.perf_counter()
    solution = optimise(problem, graph, "lm", max_iterations, relative_error_tol)
    t2 = time.perf_counter()
    scored = focused if entropy_tag_ids is None else sorted({int(t) for t in entropy_tag_ids})
    focused_obs = [t for t in scored if t in set(observed)]
    marginals, joint, consider = _marginals(problem, graph, solution, focused_obs, loaded.calibration, keep)
    t3 = time.perf_counter()
    h_obs = gaussian_entropy(joint)
    missing_dims = [
        loaded.kind(loaded.landmark_keys[t]).dim for t in scored if t not in set(observed) and t in loaded.landmark_keys
    ]
    missing_dim = sum(missing_dims)
    h_missing = sum(  # independent per dimension, as the selection's weak prior
        entropy_from_logdet(float(np.sum(np.log(landmark_prior_sigmas(d, unobserved_sigma_m) ** 2))), d)
        for d in missing_dims
    )
    return ReducedMap(
        problem=problem,
        solution=solution,
        marginals=marginals,
        full_index=keep,
        focused_tag_ids=focused,
        observed_tag_ids=observed,
        landmark_map=LandmarkMap.from_graph(loaded, solution.values, marginals),
        focused_entropy=float(h_obs + h_missing),
        focused_entropy_observed=float(h_obs),
        focused_dim=int(joint.shape[0] + missing_dim),
        n_measurements=len(kept_tags),
        dropped_unfocused=int(dropped),
        timing_s={"build": round(t1 - t0, 4), "optimise": round(t2 - t1, 4), "marginals": round(t3 - t2, 4)},
        consider=consider,
    )


def _gauge_rows(loaded: LoadedGraph, problem: GraphProblem) -> list[FactorRow]:
    """Priors that anchor the reduced graph where dropping measurements left poses without one.

    A run whose only anchors are surveyed tags (``--tags``: their priors replace the first pose's) loses its anchor
    when no surveyed tag is selected: the reduced graph's poses and landmarks then float (a singular graph). Each
    such part gets a prior on its first pose at the full graph's solution with the full graph's marginal covariance,
    so the reduced map stays in the full map's frame, as uncertain there as the full map holds that pose.
    """
    out: list[FactorRow] = []
    poses = set(problem.pose_keys)
    rows = list(problem.rows)
    for _ in range(len(poses)):
        loose = set(unanchored(dataclasses.replace(problem, rows=rows)))
        first = next((k for k in problem.pose_keys if k in loose), None)
        if first is None:
            break
        model = graph_model(loaded.model)
        measurement = loaded.kind(first).vector(loaded.values, first)
        row = FactorRow("prior", model.prior_type, (first,), measurement, np.asarray(loaded.marginals[first]))
        out.append(row)
        rows.append(row)
    return out


def _reduced_factors(
    loaded: LoadedGraph, focused: list[int], selected_factor_indices: Iterable[int]
) -> tuple[npt.NDArray[np.int64], list[int], int]:
    """Full-graph indices of the reduced graph's factors (every non-tag factor and the selected tag factors of
    focused landmarks), the kept tag factors, and how many selected ones measure unfocused landmarks."""
    unknown = [t for t in focused if t not in loaded.landmark_keys]
    if unknown:
        raise StageError(
            f"focused tags {unknown[:5]} are not landmarks of the graph; re-run 'focusmap select-landmarks' "
            "after 'focusmap graph'"
        )
    fset = set(focused)
    selected = sorted({int(i) for i in selected_factor_indices})
    bad = [i for i in selected if not 0 <= i < len(loaded.rows)]
    if bad:
        raise StageError(
            f"selected factor indices {bad[:5]} are outside the graph ({len(loaded.rows)} factors); "
            "re-run 'focusmap select-measurements'"
        )
    kept_tags = [i for i in selected if loaded.rows[i].kind == "tag" and loaded.rows[i].tag_id in fset]
    dropped = sum(1 for i in selected if loaded.rows[i].kind == "tag" and loaded.rows[i].tag_id not in fset)
    keep = np.array(sorted(set(loaded.fixed_factor_indices.tolist()) | set(kept_tags)), dtype=np.int64)
    return keep, kept_tags, dropped


def marginals_of(problem: GraphProblem, graph: gtsam.NonlinearFactorGraph, solution: Solution) -> dict[int, FloatArray]:
    """Every variable's marginal covariance (tangent space) of a solved graph."""
    return _marginals(problem, graph, solution, [])[0]


def _marginals(
    problem: GraphProblem,
    graph: gtsam.NonlinearFactorGraph,
    solution: Solution,
    focused_observed: list[int],
    calibration: OdometryCalibration | None = None,
    full_index: npt.NDArray[np.int64] | None = None,
) -> tuple[dict[int, FloatArray], FloatArray, ConsiderTerm | None]:
    """Every variable's marginal covariance and the joint covariance of the observed focused landmarks, with the
    odometry calibration's consider term added when the rows were corrected by one (the calibrated odometry, as
    uncertain as the whole recording left the calibration; ``full_index``: each row's index in the full graph)."""
    try:
        values = solution.values
        linear, dims = graph.linearize(values), key_dims(values)
        landmarks = list(problem.landmark_keys.values())
        marginals = tree_marginals(linear, dims, problem.var_types, last=landmarks)
        if focused_observed:
            kv = gtsam.KeyVector([problem.landmark_keys[t] for t in focused_observed])
            try:
                joint = np.asarray(gtsam.Marginals(graph, values).jointMarginalCovariance(kv).fullMatrix(), dtype=float)
            except RuntimeError:  # GTSAM's ordering met a pivot lost to rounding (see stages.graph.marginals.eliminate)
                joint = sparse_joint_covariance(linear, dims, list(kv))
        else:
            joint = np.zeros((0, 0))
    except RuntimeError as err:
        raise StageError(indeterminant_message(problem, err, "computing marginals")) from err
    consider = consider_term(problem.rows, linear, dims, calibration, full_index)
    if consider is not None:
        marginals = consider.add_to_marginals(marginals)
        joint = joint + consider.joint([problem.landmark_keys[t] for t in focused_observed])
    return marginals, joint, consider


def landmark_errors(
    estimate: LandmarkMap, reference: Mapping[int, FloatArray], tag_ids: Iterable[int] | None = None
) -> dict[int, float]:
    """Planar (x, y) distance between estimated and reference landmark positions, by tag id.

    Only tags present in both are returned; ``tag_ids`` restricts them further.
    """
    want = None if tag_ids is None else {int(t) for t in tag_ids}
    out = {}
    for t, p in zip(estimate.tag_ids.tolist(), estimate.positions, strict=True):
        if (want is None or t in want) and t in reference:
            out[int(t)] = float(np.linalg.norm(np.asarray(p[:2]) - np.asarray(reference[t])[:2]))
    return out


def mean_or_nan(values: Iterable[float]) -> float:
    """Mean of the values (NaN when there are none)."""
    v = list(values)
    return float(np.mean(v)) if v else float("nan")


def map_bytes(var_types: Iterable[str]) -> int:
    """Bytes of a landmark map stored as float64: per landmark an id, its mean and its covariance."""
    dims = [var_kind(t).dim for t in var_types]
    return int(sum(8 * (1 + d + d * d) for d in dims))


def measurement_bytes(dims: Iterable[int]) -> int:
    """Bytes of landmark measurements stored as float64: per factor two keys, the measurement and its covariance."""
    return int(sum(8 * (2 + d + d * d) for d in dims))


def map_size(loaded: LoadedGraph, reduced: ReducedMap) -> dict[str, int | float]:
    """What the robot carries, reduced against full: landmarks, measurements, bytes."""
    full_tags = [r for r in loaded.rows if r.kind == "tag"]
    red_tags = [r for r in reduced.problem.rows if r.kind == "tag"]
    full_lm = [loaded.var_types[k] for k in loaded.landmark_keys.values()]
    red_lm = [loaded.var_types[loaded.landmark_keys[t]] for t in reduced.observed_tag_ids]
    out: dict[str, int | float] = {
        "landmarks": len(red_lm),
        "landmarks_full": len(full_lm),
        "measurements": len(red_tags),
        "measurements_full": len(full_tags),
        "map_bytes": map_bytes(red_lm),
        "map_bytes_full": map_bytes(full_lm),
        "measurement_bytes": measurement_bytes(r.dim for r in red_tags),
        "measurement_bytes_full": measurement_bytes(r.dim for r in full_tags),
    }
    full_total = out["map_bytes_full"] + out["measurement_bytes_full"]
    out["bytes_fraction"] = (out["map_bytes"] + out["measurement_bytes"]) / full_total if full_total else float("nan")
    return out


def solve_settings(cfg: object) -> dict[str, object]:
    """How a reduced graph was solved (optimize's settings that change the numbers, as in its summary's ``solve``).

    ``solve_settings(OptimizeConfig())`` equals :func:`solve_reduced`'s defaults, the solve evaluate does.
    """
    return {
        k: getattr(cfg, k) for k in ("initialise_from", "max_iterations", "relative_error_tol", "unobserved_sigma_m")
    }


def local_map(reduced: ReducedMap, geometry: PathGeometry) -> LandmarkMap:
    """The reduced map with each landmark's covariance as seen from the keyframes that see it
    (:func:`stages.risk.map_covariances`), what the risk model and the navigation's eq. 26 use."""
    lm = dataclasses.replace(reduced.landmark_map)
    graph = build_graph(reduced.problem.rows)
    lm.local, lm.joint = map_covariances(
        reduced.problem, graph, reduced.solution.values, reduced.marginals, lm, geometry, reduced.consider
    )
    return lm
