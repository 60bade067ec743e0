"""The cases of Mu et al. Table I (and other strategy pairs) on one run, without going through run folders.

```python
inputs = EvalInputs.from_pieces(loaded, scans, T_base_laser, detections, truth, sl_cfg, sm_cfg, cfg)
results = [run_case(inputs, case) for case in cases(cfg)]
```

Every case picks its landmarks with ``stages.select_landmarks.choose`` and its measurements with
``stages.select_measurements.choose``, solves the reduced graph (``stages.optimize.solve_reduced``), and
is scored on the same things: the entropy of the *collision-focused* landmarks (the Alg. 2 set with
budget α, the task's landmarks, also for the "full" cases), errors on all observed and on those focused
landmarks (against ground truth where the run has one, else against case 1), the collision probability
along the path with the case's map (``stages.risk.path_risk``), and the collision rate of Monte Carlo
LQG navigation with the case's map (``stages.navigation.simulate``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from pipeline.errors import ConfigError, StageError
from pipeline.memory import release_freed_memory
from stages.columns import STAMP_NS, TAG_ID, X, Y
from stages.evaluate import artifacts as art
from stages.evaluate.analysis import (
    MeasurementConsistency,
    NavigationMargin,
    Overconfidence,
    aligned_error,
    landmark_consistency,
    measurement_consistency,
    oracle_rows,
    overconfidence,
    residuals_by_range,
)
from stages.evaluate.config import EvaluateConfig
from stages.graph.factors import FactorRow
from stages.graph.load import LoadedGraph
from stages.laser import scan_beams
from stages.limits import MAX_GRID_CELLS
from stages.navigation import (
    NavigationParams,
    NavigationResult,
    NominalPath,
    Obstacles,
    OccupancyGrid,
    SegmentWalls,
    lqr_gains,
    nominal_path,
    ray_cast_grid,
    simulate,
    simulate_in_worker,
)
from stages.navigation.truth import MapTruth
from stages.optimize import (
    ReducedMap,
    landmark_errors,
    local_map,
    map_size,
    mean_or_nan,
    solve_reduced,
)
from stages.risk import LandmarkMap, PathRisk, RiskParams, path_risk, riskiest_keyframes
from stages.select_landmarks import LandmarkInputs, SelectLandmarksConfig
from stages.select_landmarks import choose as choose_landmarks
from stages.select_landmarks.artifacts import FocusedLandmarks
from stages.select_measurements import MeasurementChoice, SelectMeasurementsConfig, linear_system
from stages.select_measurements import choose as choose_measurements

FloatArray = npt.NDArray[np.float64]

TABLE_I: tuple[tuple[str, str, str], ...] = (
    ("optimal", "all", "all"),
    ("focus_all", "collision", "all"),
    ("focus_info", "collision", "information"),
    ("focus_ds", "collision", "uniform"),
    ("full_info", "all", "information"),
    ("full_ds", "all", "uniform"),
)
"""(case name, landmark strategy, measurement strategy) of Mu et al. Table I; DS = uniform downsampling."""
TABLE_I_LABELS = {
    "optimal": "optimal",
    "focus_all": "focus, all",
    "focus_info": "focus, info",
    "focus_ds": "focus, DS",
    "full_info": "full, info",
    "full_ds": "full, DS",
    "focus_info_poses": "focus, info + risky poses",
}


@dataclass(frozen=True)
class Case:
    """One row of the comparison."""

    name: str
    landmark_strategy: str
    measurement_strategy: str
    focus_poses: int = 0
    """The riskiest keyframes whose poses join the measurement selection's focused set (eq. 23's W)."""


def cases(cfg: EvaluateConfig) -> list[Case]:
    """The six Table I cases, then ``cfg.extra_pairs`` (named by their pair)."""
    from stages.select_landmarks import STRATEGIES as LM
    from stages.select_measurements import STRATEGIES as MS

    out = [Case(*c) for c in TABLE_I]
    for pair in cfg.extra_pairs:
        lm, _, ms = pair.partition("+")
        if lm not in LM or ms not in MS:
            raise ConfigError(
                f"evaluate.extra_pairs: {pair!r} is not 'landmark+measurement' with landmark in {list(LM)} and "
                f"measurement in {list(MS)}"
            )
        if not any(c.landmark_strategy == lm and c.measurement_strategy == ms for c in out):
            out.append(Case(pair, lm, ms))
    if cfg.focused_poses > 0:
        out.append(Case("focus_info_poses", "collision", "information", cfg.focused_poses))
    return out


@dataclass
class NavigationSetup:
    """What every case's navigation shares: the world (true path, true landmarks, walls), visibility, the robot."""

    world_path: NominalPath
    """The true path resampled every control period (the full graph's path without ground truth)."""
    visibility: list[npt.NDArray[np.int64]]
    obstacles: Obstacles
    true_landmarks: dict[int, FloatArray]
    params: NavigationParams
    min_clearance_m: float
    world: str
    """``ground_truth`` or ``full_map`` (the full graph's landmarks and laser grid stand in for the world)."""
    margin_m: FloatArray | None = None
    """(K,) clearance of the true path minus the robot radius, per step."""

    @property
    def path(self) -> NominalPath:
        """The true path (the steps every case's nominal path shares)."""
        return self.world_path


DENSE_STRATEGIES = ("mutual-information", "leverage")
"""Landmark strategies on the dense trajectory information (quadratic memory in the recording's length)."""
SEEDED = ("random", "leverage")
"""Strategies whose result depends on the seed (evaluate's ``seed`` against the upstream stage's)."""


@dataclass
class Upstream:
    """What the selection stages and optimize already computed on the run, for the case they match."""

    landmarks: FocusedLandmarks | None = None
    measurements: MeasurementChoice | None = None
    reduced: UpstreamReduced | None = None
    """optimize's reduced map (solved as evaluate solves), of ``landmarks.tag_ids`` and ``measurements``."""


@dataclass(frozen=True)
class UpstreamReduced:
    """optimize's reduced map, read only for the case it matches: it is a second graph as large as the full one (all
    the poses), which an hour's evaluate cannot afford to hold through every case."""

    focused_tag_ids: list[int]
    full_index: npt.NDArray[np.int64]
    """Its factors' full-graph indices (optimize's ``kept.parquet``)."""
    read: Callable[[], ReducedMap]


HOW_TO_GIVE_WALLS = (
    "give walls with --truth FILE (a truth YAML with a walls part, docs/evaluate.md) or record a laser to simulate it"
)


@dataclass(frozen=True)
class NavigationSkipped:
    """Why no case was navigated: ``reason`` in a few words (the headline's: ``no walls``, ``evaluate.trials=0``),
    ``why`` what the run lacks (empty when the user switched the trials off)."""

    reason: str
    why: str = ""

    @property
    def note(self) -> str:
        """The stage's note line (empty when the user switched the trials off: nothing to tell them)."""
        if not self.why:
            return ""
        return (
            f"navigation not simulated: the run has no walls for the robot to collide with ({self.why}), so the "
            f"collision rates and the other navigation columns are not computed; {HOW_TO_GIVE_WALLS}"
        )


class NoWallsError(StageError):
    """The run has nothing the simulated robot could collide with (no ground-truth walls, no laser returns)."""


@dataclass
class EvalInputs:
    """A run loaded once for every case."""

    loaded: LoadedGraph
    landmarks: LandmarkInputs
    truth: MapTruth | None
    heights: dict[int, tuple[float, float]]
    sl_cfg: SelectLandmarksConfig
    sm_cfg: SelectMeasurementsConfig
    cfg: EvaluateConfig
    scans: pa.Table | None
    T_base_laser: FloatArray | None
    upstream: Upstream = field(default_factory=Upstream)
    system: Any = None
    navigation: NavigationSetup | None = None
    focus: list[int] = field(default_factory=list)
    """The collision-focused landmarks (Alg. 2, budget α): what every case's entropy and focused error are on."""
    focus_seconds: float = 0.0
    risky_keyframes: list[int] = field(default_factory=list)
    """Keyframes by eq. 20 with the collision focus and the full map, riskiest first up to ``cfg.focused_poses``
    (in time order): the poses the ``focus_info_poses`` case focuses."""
    consistency: dict[str, MeasurementConsistency] = field(default_factory=dict)
    """Every measurement of the full graph at the truth (empty without a ground truth)."""
    by_range: list[dict[str, float]] = field(default_factory=list)
    """Tag residuals at the truth by measured range."""
    skipped: list[str] = field(default_factory=list)
    """One line per extra case that could not run on this run (the Table I cases always run or fail the stage)."""
    oracle: dict[tuple[int, int], FactorRow] = field(default_factory=dict)
    """The oracle replacement of each tag factor drawn so far, by (seed, factor index): a factor gets the same one in
    every case that keeps it (:func:`~stages.evaluate.analysis.oracle_rows`), so it is drawn once."""
    analysis: bool = True
    """Compute the measurement-consistency analysis (the report's "Why"); map realisations, which do not report it,
    switch it off."""
    navigation_skipped: NavigationSkipped | None = None
    """Why the navigation trials did not run (None: they ran); set by :func:`run_all`."""

    @property
    def risk_params(self) -> RiskParams:
        """The risk model of select_landmarks, with evaluate's robot radius when that is set."""
        params = self.landmarks.params
        if self.cfg.robot_radius_m is not None:
            params = dataclasses.replace(params, robot_radius_m=self.cfg.robot_radius_m)
        return params

    @property
    def trajectory_dim(self) -> int:
        """Poses x pose dimension: what the dense landmark strategies' limits are in."""
        return len(self.loaded.pose_keys) * self.loaded.graph_model.pose.dim

    @property
    def alpha(self) -> int:
        """Landmark budget."""
        return self.cfg.landmark_budget if self.cfg.landmark_budget is not None else self.sl_cfg.budget

    @property
    def K(self) -> int:
        """Measurement budget."""
        return self.cfg.measurement_budget if self.cfg.measurement_budget is not None else self.sm_cfg.budget

    def upstream_landmarks(self, strategy: str) -> tuple[list[int], float] | None:
        """select_landmarks' pick when it is what ``strategy`` at α with evaluate's seed would pick, else None."""
        up = self.upstream.landmarks
        if up is None or up.strategy != strategy or up.budget != self.alpha:
            return None
        if up.settings.robot_radius_m != self.sl_cfg.robot_radius_m:  # picked for another robot
            return None
        if strategy in SEEDED and up.settings.seed != self.cfg.seed:
            return None
        return list(up.tag_ids), up.seconds

    def upstream_measurements(
        self, cfg: SelectMeasurementsConfig, tags: Sequence[int], poses: Sequence[int] = ()
    ) -> MeasurementChoice | None:
        """select_measurements' choice when it is what ``cfg`` on ``tags`` (and focused ``poses``) would choose, else
        None."""
        up = self.upstream.measurements
        if up is None or (up.strategy, up.budget, up.focus) != (cfg.strategy, cfg.budget, cfg.focus):
            return None
        if list(up.focused_pose_indices) != [int(p) for p in poses]:
            return None
        if cfg.strategy in SEEDED and self.sm_cfg.seed != cfg.seed:
            return None
        want = sorted(self.loaded.landmark_keys) if cfg.focus == "all" else [int(t) for t in tags]
        return up if list(up.focused_tag_ids) == want else None

    def upstream_reduced(self, tags: Sequence[int], selected: Sequence[int]) -> ReducedMap | None:
        """optimize's reduced map when it is the solve of these landmarks and measurements, scored on the focus."""
        red = self.upstream.reduced
        if red is None or red.focused_tag_ids != sorted({int(t) for t in tags}):
            return None
        if red.focused_tag_ids != sorted({int(t) for t in self.focus}):
            return None
        rows, tagset = self.loaded.rows, set(red.focused_tag_ids)
        kept = {int(i) for i in red.full_index if i >= 0 and rows[int(i)].kind == "tag"}
        wanted = {int(i) for i in selected if rows[int(i)].kind == "tag" and rows[int(i)].tag_id in tagset}
        return red.read() if kept == wanted else None

    def reference_positions(self, optimal: LandmarkMap | None) -> tuple[dict[int, FloatArray], str]:
        """Where landmarks really are: the ground truth, else case 1's map."""
        if self.truth is not None and self.truth.has_tags:
            return dict(self.truth.tags), "ground_truth"
        lmap = optimal if optimal is not None else self.landmarks.landmarks
        return dict(zip(lmap.tag_ids.tolist(), lmap.positions, strict=True)), "optimal"


def missing_walls(inputs: EvalInputs) -> str | None:
    """Why the navigation has no walls (``evaluate.walls=auto`` and neither the ground truth's walls nor laser scans),
    else None. Only the automatic choice is judged here: an explicit ``evaluate.walls`` that cannot be met stops the
    stage in :func:`navigation_setup`."""
    truth = inputs.truth
    if inputs.cfg.walls != "auto" or (truth is not None and truth.has_walls):
        return None
    if inputs.scans is not None and inputs.scans.num_rows > 0:
        return None
    return "no laser scans and no ground truth" if truth is None else "no laser scans and no walls in the ground truth"


def skip_navigation(inputs: EvalInputs, why: str) -> None:
    """Run every case without navigation trials, saying why (a run without walls: the trials need obstacles)."""
    inputs.navigation_skipped = NavigationSkipped("no walls", why)
    inputs.navigation = None
    inputs.cfg = inputs.cfg.model_copy(update={"trials": 0})


def _scan_pose_grid(inputs: EvalInputs) -> OccupancyGrid:
    """Occupancy grid of the laser beams, each placed at the optimised path interpolated to its own time
    (deskewed, :func:`stages.laser.scan_beams`), free space carved along every beam
    (:func:`stages.navigation.ray_cast_grid`)."""
    scans = inputs.scans
    if scans is None or scans.num_rows == 0:
        raise NoWallsError("the run has no laser scans")
    geo = inputs.landmarks.geometry
    stamps = np.asarray(scans.column(STAMP_NS).to_numpy(), dtype=np.int64)
    rows = np.arange(0, scans.num_rows, inputs.cfg.scan_stride)
    rows = rows[(stamps[rows] >= geo.stamps_ns[0]) & (stamps[rows] <= geo.stamps_ns[-1])]
    beams = scan_beams(scans, geo.stamps_ns, geo.poses, inputs.T_base_laser, rows)
    if not beams.hit.any():
        raise NoWallsError("no laser scan within the path has a return")
    _check_grid_size((beams.origins, beams.ends), inputs.cfg.grid_resolution_m)
    return ray_cast_grid(beams.origins, beams.ends, beams.hit, inputs.cfg.grid_resolution_m, inputs.cfg.grid_min_hits)


def _check_grid_size(
    endpoints: npt.NDArray[np.float64] | Sequence[npt.NDArray[np.float64]], resolution_m: float, margin_m: float = 1.0
) -> None:
    """Refuse a laser grid of more than :data:`~stages.limits.MAX_GRID_CELLS` cells before allocating it.

    ``endpoints``: (N, 2) points, or several such arrays (the beams' origins and ends, not stacked into a copy)."""
    parts = [endpoints] if isinstance(endpoints, np.ndarray) else list(endpoints)
    finite = []
    for p in parts:
        ok = np.isfinite(p).all(axis=1)
        if ok.any():
            finite.append(p if ok.all() else p[ok])
    if not finite:
        return
    lo = np.min([f.min(axis=0) for f in finite], axis=0)
    hi = np.max([f.max(axis=0) for f in finite], axis=0)
    span = (hi - lo) + 2 * margin_m
    cells = float(np.prod(np.ceil(span / resolution_m) + 1))
    if cells > MAX_GRID_CELLS:
        finest = 1.1 * float(np.sqrt(np.prod(span) / MAX_GRID_CELLS))  # rounded up: the +1 cells per side
        raise ConfigError(
            f"evaluate.grid_resolution_m={resolution_m:g} makes a laser grid of {cells:.3g} cells over "
            f"{span[0]:.0f} m x {span[1]:.0f} m (at most {MAX_GRID_CELLS:.0e}); set it to {finest:.2g} m or more"
        )


def navigation_setup(inputs: EvalInputs, optimal: LandmarkMap) -> NavigationSetup:
    """The world every case navigates in: the true path, landmarks and walls (the ground truth, else the full map:
    its path, its landmarks and the laser grid at its poses), which landmarks are visible at each step, the robot."""
    cfg = inputs.cfg
    geo = inputs.landmarks.geometry
    stamps = np.asarray(geo.stamps_ns, dtype=np.int64)
    poses = inputs.truth.pose_at(stamps) if inputs.truth is not None and inputs.truth.has_poses else geo.poses
    world_path = nominal_path(stamps, poses, geo.robot.control_period_s)
    radius = inputs.risk_params.robot_radius_m
    robot = dataclasses.replace(geo.robot, robot_radius_m=radius)
    params = NavigationParams(
        robot=robot,
        trials=cfg.trials,
        lqr_position_weight=cfg.lqr_position_weight,
        lqr_heading_weight=cfg.lqr_heading_weight,
        lqr_speed_weight=cfg.lqr_control_weight,
        lqr_yaw_rate_weight=cfg.lqr_control_weight,
    )
    true_walls = inputs.truth.walls if inputs.truth is not None and inputs.truth.has_walls else None
    use_truth = cfg.walls == "ground_truth" or (cfg.walls == "auto" and true_walls is not None)
    if use_truth:
        if true_walls is None:
            raise StageError(
                "evaluate.walls=ground_truth but the run has no ground truth with walls (--truth FILE, or "
                "<name>.ground_truth.json beside its bag); use evaluate.walls=laser"
            )
        obstacles: Obstacles = SegmentWalls(true_walls)
    else:
        obstacles = _scan_pose_grid(inputs)
    clearances = obstacles.distance(world_path.poses[:, :2])
    clearance = float(clearances.min())
    if cfg.trials > 0 and clearance <= radius:
        raise StageError(
            f"the true path passes {clearance:.3f} m from an obstacle ({obstacles.kind}), inside the robot radius "
            f"{radius} m, so every trial would collide; lower evaluate.robot_radius_m below {clearance:.2f}"
        )
    step_visible = geo.visible[world_path.keyframe]
    vis = [geo.tag_ids[row] for row in step_visible]
    truth_lm, _ = inputs.reference_positions(optimal)
    world = "ground_truth" if inputs.truth is not None and inputs.truth.has_poses else "full_map"
    return NavigationSetup(world_path, vis, obstacles, truth_lm, params, clearance, world, clearances - radius)


def case_path(inputs: EvalInputs, reduced: ReducedMap) -> NominalPath:
    """The case's own trajectory estimate (its reduced graph's keyframes, planar), resampled every control period:
    the path its robot plans to follow, in its own map frame."""
    problem, values = reduced.problem, reduced.solution.values
    kind = problem.graph_model.pose
    poses = np.array([kind.planar_pose(kind.read(values, k)) for k in problem.pose_keys]).reshape(-1, 3)
    geo = inputs.landmarks.geometry
    return nominal_path(np.asarray(problem.pose_stamps_ns, dtype=np.int64), poses, geo.robot.control_period_s)


@dataclass
class CaseResult:
    """Everything measured on one case."""

    case: Case
    landmark_tag_ids: list[int]
    measurement: MeasurementChoice | None
    solved: ReducedMap | None
    """The case's solved reduced graph (``None`` once :meth:`release` dropped it)."""
    risk: PathRisk
    navigation: NavigationResult | None
    row: dict[str, Any]
    margin: NavigationMargin | None = None
    reused: list[str] = field(default_factory=list)
    """What was taken from the upstream stages' artifacts instead of recomputed (landmarks, measurements, map)."""
    local_map: LandmarkMap | None = None
    """The case's map with each landmark's covariance as seen from the keyframes that see it (risk, navigation)."""
    overconfidence: Overconfidence | None = None
    """Its worst focused landmark against the reference by its own covariance (None: not tested, case 1 without a
    ground truth)."""
    landmark_map: LandmarkMap = field(init=False)
    """The case's landmark map (positions and marginal covariances): what the tables, report and recording read."""

    def __post_init__(self) -> None:
        self.landmark_map = self.reduced.landmark_map

    @property
    def reduced(self) -> ReducedMap:
        """The case's solved reduced graph (its problem, solution and marginals)."""
        if self.solved is None:
            raise RuntimeError(f"case {self.case.name}: its solved graph was released after its navigation")
        return self.solved

    def release(self) -> None:
        """Drop the solved graph and the per-keyframe covariances once the navigation has what it needs: on an hour's
        recording each case held about 50 MB of them, and ten cases are kept to the end of the stage."""
        self.solved = None
        self.local_map = None


def _landmark_set(inputs: EvalInputs, strategy: str) -> tuple[list[int], float]:
    if strategy == "all":
        return sorted(inputs.loaded.landmark_keys), 0.0
    if strategy == "collision" and inputs.focus:
        return list(inputs.focus), inputs.focus_seconds
    reused = inputs.upstream_landmarks(strategy)
    if reused is not None:
        return reused
    if strategy in DENSE_STRATEGIES and inputs.trajectory_dim > inputs.cfg.extra_max_trajectory_dim:
        raise StageError(
            f"{strategy} works on the dense trajectory information ({inputs.trajectory_dim} dimensions here), above "
            f"evaluate.extra_max_trajectory_dim={inputs.cfg.extra_max_trajectory_dim}; raise it to compare "
            "anyway (time and memory grow with its square)"
        )
    cfg = inputs.sl_cfg.model_copy(update={"strategy": strategy, "budget": inputs.alpha, "seed": inputs.cfg.seed})
    choice = choose_landmarks(inputs.landmarks, cfg, with_risk=False)
    return list(choice.tag_ids), choice.seconds


def _fallback_focus(inputs: EvalInputs) -> tuple[list[int], float]:
    """The focus of a run without laser whose trajectory is too long for mutual information: select_landmarks' own
    pick at α when there is one (the strategy the user ran), else the spatially uniform α, with a warning line."""
    dim = inputs.trajectory_dim
    why = (
        f"this run has no laser for the collision focus, and mutual information's time and memory grow up to the "
        f"square of its trajectory ({dim} dimensions, above select_landmarks.max_trajectory_dim="
        f"{inputs.sl_cfg.max_trajectory_dim})"
    )
    up = inputs.upstream.landmarks
    if up is not None and up.budget == inputs.alpha:
        inputs.skipped.append(f"focus: {why}; every case is scored on select_landmarks' {up.strategy} pick instead")
        return list(up.tag_ids), up.seconds
    inputs.skipped.append(f"focus: {why}; every case is scored on the spatially uniform {inputs.alpha} instead")
    cfg = inputs.sl_cfg.model_copy(update={"strategy": "uniform", "budget": inputs.alpha})
    choice = choose_landmarks(inputs.landmarks, cfg, with_risk=False)
    return list(choice.tag_ids), choice.seconds


def prepare(inputs: EvalInputs) -> None:
    """Linearise once and pick the collision-focused landmarks every case is scored on."""
    if inputs.system is None:
        inputs.system = linear_system(inputs.loaded)
    if not inputs.focus:
        has_laser = inputs.landmarks.geometry.has_laser
        strategy = "collision" if has_laser else "mutual-information"
        reused = inputs.upstream_landmarks(strategy)
        if reused is None and not has_laser and inputs.trajectory_dim > inputs.sl_cfg.max_trajectory_dim:
            reused = _fallback_focus(inputs)
        if reused is not None:
            inputs.focus, inputs.focus_seconds = reused
        else:
            cfg = inputs.sl_cfg.model_copy(
                update={"strategy": strategy, "budget": inputs.alpha, "seed": inputs.cfg.seed}
            )
            choice = choose_landmarks(inputs.landmarks, cfg, with_risk=False)
            inputs.focus, inputs.focus_seconds = list(choice.tag_ids), choice.seconds
    if inputs.cfg.focused_poses > 0 and not inputs.risky_keyframes and inputs.landmarks.geometry.has_laser:
        geo = inputs.landmarks.geometry
        full = inputs.landmarks.landmarks  # with a laser, LandmarkInputs made the full graph's local covariances
        risk = path_risk(geo, full, inputs.focus, inputs.risk_params)
        window = inputs.sl_cfg.visibility_window_s
        inputs.risky_keyframes = riskiest_keyframes(risk.mahalanobis, geo.stamps_ns, inputs.cfg.focused_poses, window)
    if (
        inputs.analysis
        and inputs.truth is not None
        and inputs.truth.has_poses
        and not inputs.consistency
        and inputs.loaded.model == "planar"
    ):
        inputs.consistency = measurement_consistency(inputs.loaded, inputs.truth)
        inputs.by_range = residuals_by_range(inputs.loaded, inputs.truth)


def run_case(inputs: EvalInputs, case: Case, optimal: LandmarkMap | None = None, navigation: bool = True) -> CaseResult:
    """Select, solve, score and (``navigation``) navigate one case (``optimal``: case 1's map, the reference
    without ground truth)."""
    prepare(inputs)
    loaded = inputs.loaded
    tags, lm_seconds = _landmark_set(inputs, case.landmark_strategy)
    reused: list[str] = []
    if case.landmark_strategy != "all" and inputs.upstream_landmarks(case.landmark_strategy) is not None:
        reused.append("landmarks")
    measurement: MeasurementChoice | None = None
    if case.measurement_strategy == "all":
        selected = [i for i in loaded.tag_factor_indices.tolist() if loaded.rows[i].tag_id in set(tags)]
        ms_seconds = 0.0
    else:
        ms_focus = "all" if case.landmark_strategy == "all" else "selected"
        poses = inputs.risky_keyframes[: case.focus_poses] if case.focus_poses else []
        update = {
            "strategy": case.measurement_strategy,
            "budget": inputs.K,
            "focus": ms_focus,
            "seed": inputs.cfg.seed,
            "focus_poses": len(poses),
        }
        cfg = inputs.sm_cfg.model_copy(update=update)
        measurement = inputs.upstream_measurements(cfg, tags, poses)
        if measurement is not None:
            reused.append("measurements")
        else:
            measurement = choose_measurements(loaded, tags, cfg, inputs.system, focus_pose_indices=poses)
        selected, ms_seconds = measurement.factor_indices, measurement.seconds
    reduced = inputs.upstream_reduced(tags, selected)
    if reduced is not None:
        reused.append("reduced map")
    else:
        reduced = solve_reduced(loaded, tags, selected, inputs.heights, "dead_reckoning", entropy_tag_ids=inputs.focus)
    reference, ref_name = inputs.reference_positions(optimal if optimal is not None else reduced.landmark_map)
    errs = landmark_errors(reduced.landmark_map, reference)
    focus = set(inputs.focus)
    geo = inputs.landmarks.geometry
    lmap = local_map(reduced, geo) if geo.has_laser or inputs.cfg.trials > 0 else None
    risk = path_risk(geo, lmap or reduced.landmark_map, reduced.observed_tag_ids, inputs.risk_params)
    size = map_size(loaded, reduced)
    observed = set(reduced.observed_tag_ids)
    nan = float("nan")
    row: dict[str, Any] = {
        art.CASE: case.name,
        art.LABEL: TABLE_I_LABELS.get(case.name, case.name),
        art.LANDMARK_STRATEGY: case.landmark_strategy,
        art.MEASUREMENT_STRATEGY: case.measurement_strategy,
        art.LANDMARK_BUDGET: inputs.alpha if case.landmark_strategy != "all" else len(loaded.landmark_keys),
        art.MEASUREMENT_BUDGET: inputs.K if case.measurement_strategy != "all" else None,
        art.OBSERVED_LANDMARKS: len(observed),
        art.FOCUSED_LANDMARKS: len(focus & observed),
        art.MEASUREMENTS: reduced.n_measurements,
        art.FOCUSED_ENTROPY: reduced.focused_entropy,
        art.FOCUSED_ENTROPY_OBSERVED: reduced.focused_entropy_observed,
        art.ERROR_ALL_M: mean_or_nan(errs.values()),
        art.FOCUSED_ERROR_M: mean_or_nan(v for t, v in errs.items() if t in focus),
        art.ERROR_REFERENCE: ref_name,
        art.MAX_COLLISION_PROBABILITY: risk.max,
        art.MEAN_COLLISION_PROBABILITY: risk.mean,
        art.COLLISION_RATE: nan,
        art.COLLISION_CI_LOW: nan,
        art.COLLISION_CI_HIGH: nan,
        art.COLLISIONS: 0,
        art.TRIALS: 0,
        art.RMS_TRACKING_ERROR_M: nan,
        art.RMS_ESTIMATION_ERROR_M: nan,
        art.LANDMARK_SELECTION_S: lm_seconds,
        art.MEASUREMENT_SELECTION_S: ms_seconds,
        art.SELECTION_S: lm_seconds + ms_seconds,
        art.OPTIMISE_S: float(sum(reduced.timing_s.values())),
        art.MAP_BYTES: int(size["map_bytes"]) + int(size["measurement_bytes"]),
        art.BYTES_FRACTION: float(size["bytes_fraction"]),
        art.STATUS: measurement.message if measurement is not None else "",
    }
    row.update(_why_columns(inputs, reduced, selected, reference, focus))
    row[art.NAVIGATION_NEES] = nan
    row[art.RISK_MARGIN_SIGMAS] = risk.min_z
    # the map against its own covariance; not case 1 without a truth, whose reference is itself
    lm = reduced.landmark_map
    check = (
        overconfidence(lm.tag_ids, lm.positions, lm.covariances, reference, focus)
        if optimal is not None or ref_name == "ground_truth"
        else None
    )
    row[art.FOCUSED_NEES_MAX] = check.nees if check is not None else nan
    row[art.FOCUSED_NEES_LIMIT] = check.limit if check is not None else nan
    row[art.OVERCONFIDENT] = check.fails if check is not None else None
    result = CaseResult(case, tags, measurement, reduced, risk, None, row, reused=reused, local_map=lmap)
    result.overconfidence = check
    if navigation:
        navigate(inputs, result)
    return result


def navigate(inputs: EvalInputs, result: CaseResult) -> None:
    """Monte Carlo LQG trials of the case's robot in the world, planning and localising in the case's own map
    (when the navigation is set up); fills the row's columns."""
    call = navigation_call(inputs, result)
    if call is not None:
        record_navigation(inputs, result, simulate(*call[0], **call[1]))


def navigation_call(inputs: EvalInputs, result: CaseResult) -> tuple[tuple[Any, ...], dict[str, Any]] | None:
    """The arguments of the case's :func:`~stages.navigation.simulate` (None: the navigation is not set up)."""
    setup = inputs.navigation
    if setup is None or inputs.cfg.trials <= 0:
        return None
    path = case_path(inputs, result.reduced)
    if len(path) != len(setup.world_path):
        raise StageError(
            f"case {result.case.name}: its path has {len(path)} steps, the world's {len(setup.world_path)}; "
            "re-run 'focusmap graph'"
        )
    gains = lqr_gains(path, setup.params.Wx, setup.params.Wu)
    args = (
        path,
        gains,
        result.local_map if result.local_map is not None else result.reduced.landmark_map,
        setup.true_landmarks,
        setup.visibility,
        setup.obstacles,
        setup.params,
    )
    return args, {"seed": inputs.cfg.seed, "true_path": setup.world_path.poses}


def record_navigation(inputs: EvalInputs, result: CaseResult, nav: NavigationResult) -> None:
    """The case's navigation, its row's columns and its margin."""
    setup = inputs.navigation
    assert setup is not None
    result.navigation = nav
    result.row.update(
        {
            art.COLLISION_RATE: nav.collision_rate,
            art.COLLISION_CI_LOW: nav.ci_low,
            art.COLLISION_CI_HIGH: nav.ci_high,
            art.COLLISIONS: nav.collisions,
            art.TRIALS: nav.trials,
            art.RMS_TRACKING_ERROR_M: nav.rms_tracking_error_m,
            art.RMS_ESTIMATION_ERROR_M: nav.rms_estimation_error_m,
            art.NAVIGATION_NEES: nav.nees_per_dof,
        }
    )
    if setup.margin_m is not None and len(nav.step_rms_deviation_m) == len(setup.margin_m):
        margin = NavigationMargin(setup.margin_m, nav.step_rms_deviation_m, nav.step_ekf_sigma_m)
        result.margin = margin
        result.row.update(margin.summary())


def _why_columns(
    inputs: EvalInputs, reduced: ReducedMap, selected: Sequence[int], reference: dict[int, FloatArray], focus: set[int]
) -> dict[str, float]:
    """NEES of the focused landmarks, the kept measurements at the truth, and the oracle re-solve's errors."""
    out: dict[str, float] = dict.fromkeys((*art.WHY_COLUMNS, *art.MARGIN_COLUMNS), float("nan"))
    truth = inputs.truth
    if truth is None or not (truth.has_tags and truth.has_poses) or inputs.loaded.model != "planar":
        return out
    lm = reduced.landmark_map
    lc = landmark_consistency(lm.tag_ids, lm.positions, lm.covariances, reference, focus)
    out[art.FOCUSED_ERROR_ALIGNED_M] = aligned_error(lm.tag_ids, lm.positions, reference, focus)
    out[art.FOCUSED_SIGMA_M] = lc.mean_sigma_m
    out[art.FOCUSED_NEES] = lc.mean_nees
    out[art.FOCUSED_OUTSIDE_95] = lc.share_outside_95
    kept = [i for i in reduced.full_index.tolist() if i >= 0 and inputs.loaded.rows[i].kind == "tag"]
    mc = measurement_consistency(inputs.loaded, truth, kept).get("tag")
    if mc is not None:
        out.update({art.KEPT_TAG_NEES: mc.mean_nees, art.KEPT_RANGE_BIAS_M: float(mc.mean_residual[1])})
    if inputs.cfg.oracle_measurements and kept:
        oracle = solve_reduced(
            inputs.loaded,
            reduced.focused_tag_ids,
            kept,
            inputs.heights,
            "dead_reckoning",
            entropy_tag_ids=inputs.focus,
            row_override=_oracle_rows(inputs, truth, kept),
        )
        olm = oracle.landmark_map
        oc = landmark_consistency(olm.tag_ids, olm.positions, olm.covariances, reference, focus)
        errs = landmark_errors(olm, reference)
        out.update(
            {
                art.ORACLE_FOCUSED_ERROR_M: oc.mean_error_m,
                art.ORACLE_FOCUSED_NEES: oc.mean_nees,
                art.ORACLE_FOCUSED_ERROR_ALIGNED_M: aligned_error(olm.tag_ids, olm.positions, reference, focus),
                art.ORACLE_ERROR_ALL_M: mean_or_nan(errs.values()),
            }
        )
    return out


def _oracle_rows(inputs: EvalInputs, truth: MapTruth, kept: Sequence[int]) -> dict[int, FactorRow]:
    """:func:`~stages.evaluate.analysis.oracle_rows` of ``kept``, each factor's drawn once per seed."""
    seed = inputs.cfg.seed
    todo = [i for i in kept if (seed, i) not in inputs.oracle]
    inputs.oracle.update({(seed, i): row for i, row in oracle_rows(inputs.loaded, truth, todo, seed).items()})
    return {i: inputs.oracle[seed, i] for i in kept if (seed, i) in inputs.oracle}


MAX_QUEUED_NAVIGATIONS = 2
"""Navigations sent to the worker and not finished (one running, one waiting) before the next case waits."""


def run_all(
    inputs: EvalInputs, todo: Sequence[Case], progress: Any = None, pool: Executor | None = None
) -> list[CaseResult]:
    """Case 1 first (its map is the reference without ground truth and fixes the navigation's truth), then the rest.

    With ``pool`` (a worker process) each case's navigation trials run there while this process selects and solves
    the next case (on the sample, the trials are about a third of evaluate); the numbers are the same.
    """
    if inputs.cfg.trials <= 0:
        inputs.navigation_skipped = NavigationSkipped("evaluate.trials=0")
    elif (why := missing_walls(inputs)) is not None:
        skip_navigation(inputs, why)
    prepare(inputs)
    todo = [c for c in todo if not c.focus_poses or inputs.risky_keyframes]  # no laser: no risky poses to focus
    pending: list[tuple[CaseResult, Future[NavigationResult]]] = []

    def navigate_case(result: CaseResult) -> None:
        if pool is None:
            navigate(inputs, result)
        elif (call := navigation_call(inputs, result)) is not None:
            # a queued navigation holds its arguments (the case's path, gains and local covariances: tens of MB on
            # an hour's recording) until the worker takes it; when the worker is the slower side, wait for it rather
            # than queue every case
            while sum(not f.done() for _, f in pending) >= MAX_QUEUED_NAVIGATIONS:
                wait([f for _, f in pending if not f.done()], return_when=FIRST_COMPLETED)
            pending.append((result, pool.submit(simulate_in_worker, *call)))
        if inputs.cfg.trials > 0:  # navigated or sent (the call holds its arguments); nothing else needs the graph
            result.release()

    results: list[CaseResult] = []
    try:
        try:
            first = run_case(inputs, todo[0], navigation=False)
        except StageError as err:
            raise StageError(f"case {todo[0].name}: {err}") from err
        optimal = first.landmark_map
        if inputs.cfg.trials > 0:
            try:
                inputs.navigation = navigation_setup(inputs, optimal)
            except NoWallsError as err:
                if inputs.cfg.walls != "auto":  # the user asked for these walls: say they are not there
                    raise StageError(
                        f"evaluate.walls={inputs.cfg.walls} but {err}; {HOW_TO_GIVE_WALLS}, or set "
                        "evaluate.walls=auto (navigation is then skipped on a run without walls)"
                    ) from err
                skip_navigation(inputs, str(err))
            navigate_case(first)
        if inputs.cfg.realisations <= 0:
            inputs.scans = None  # read only by the laser grid above and the realisations: not held through the cases
        results.append(first)
        rest = todo[1:] if progress is None else progress(todo[1:], "cases")
        for case in rest:
            release_freed_memory()  # the last case's graph, solves and selection (hundreds of MB at an hour)
            try:
                result = run_case(inputs, case, optimal, navigation=False)
                navigate_case(result)
                results.append(result)
            except StageError as err:  # an extra pair that cannot run here (e.g. MI on a long trajectory): skip it
                if (case.name, case.landmark_strategy, case.measurement_strategy) in TABLE_I:
                    raise StageError(f"case {case.name}: {err}") from err
                inputs.skipped.append(f"case {case.name} skipped: {err}")
        for result, future in pending:
            record_navigation(inputs, result, future.result())
    finally:
        for _, future in pending:
            future.cancel()
    return results


def cases_table(results: Sequence[CaseResult]) -> pa.Table:
    """:data:`~stages.evaluate.artifacts.CASES`: one row per case; what was not computed (no navigation trials, no
    laser for the path risk, no ground truth for the consistency analysis: NaN in the rows) is null."""
    return art.CASES.table([_computed_only(r.row) for r in results])


def _computed_only(row: dict[str, Any]) -> dict[str, Any]:
    out = {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in row.items()}
    if not row.get(art.TRIALS):
        out[art.COLLISIONS] = None  # not 0 collisions: none counted
    return out


def map_rows(results: Sequence[CaseResult]) -> pa.Table:
    """:data:`~stages.evaluate.artifacts.MAPS`: per case, every landmark of its map with its covariance."""
    out: dict[str, list[Any]] = {c: [] for c in art.MAPS.names}
    for r in results:
        lm: LandmarkMap = r.landmark_map
        focus = set(r.landmark_tag_ids)
        for t, p, c in zip(lm.tag_ids.tolist(), lm.positions, lm.covariances, strict=True):
            out[art.CASE].append(r.case.name)
            out[TAG_ID].append(int(t))
            out[X].append(float(p[0]))
            out[Y].append(float(p[1]))
            out[art.COVARIANCE].append(np.asarray(c).ravel().tolist())
            out[art.IN_CASE_FOCUS].append(int(t) in focus)
    return art.MAPS.table(out)


def risk_rows(inputs: EvalInputs, results: Sequence[CaseResult]) -> pa.Table:
    """:data:`~stages.evaluate.artifacts.PATH_RISK`: per case and keyframe, the collision probability with its map."""
    stamps = inputs.landmarks.geometry.stamps_ns
    return art.PATH_RISK.table(
        {
            art.CASE: [r.case.name for r in results for _ in stamps],
            STAMP_NS: np.concatenate([stamps for _ in results]).astype(np.int64),
            art.P_COLLISION: np.concatenate([r.risk.p_collision for r in results]),
        }
    )


def greedy_rows(results: Sequence[CaseResult]) -> pa.Table:
    """:data:`~stages.evaluate.artifacts.GREEDY`: the focused entropy after each greedy pick (information cases)."""
    out: dict[str, list[Any]] = {c: [] for c in art.GREEDY.names}
    for r in results:
        if r.measurement is None:
            continue
        steps = r.measurement.entropy_per_step()
        if steps is None:
            continue
        out[art.CASE] += [r.case.name] * (len(steps) + 1)
        out[art.STEP] += list(range(len(steps) + 1))
        out[art.ENTROPY] += [float(r.measurement.entropy_before), *[float(s) for s in steps]]
    return art.GREEDY.table(out)
