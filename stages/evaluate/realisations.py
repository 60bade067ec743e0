"""Table I over many map realisations: redraw every measurement of the full graph from a world, re-run every case.

One real recording is one draw of the measurement noise; the cases' collision rates swing more between such draws
than between navigation trials on one map. A *realisation* redraws every tag and odometry measurement of the full
graph from a world with the noise each factor states, re-solves the full graph, and re-selects, re-solves and
re-navigates every case on it (:func:`stages.evaluate.cases.run_all`).

```python
world = World.of(inputs)                          # the ground truth in the map frame, else the full solution
study = run_realisations(inputs, todo, n=30, trials=200, seed=0, detections=detections)
study.table                                       # one row per realisation and case
```

The world is the ground truth in the map frame when the run has one (true tag (x, y) and true poses at the
keyframe stamps; tags the truth lacks keep the full solution's position) and otherwise the full graph's own
solution (a parametric bootstrap). Planar graphs only.

Three random streams per study, children of ``np.random.SeedSequence(seed)``: the measurement redraws, the seeds of
the seeded selections (random, leverage), the navigation trials. Realisation ``r`` takes child ``r`` of each, so
every case of a realisation sees the same redrawn graph and the same navigation seed, and adding realisations
leaves the earlier ones unchanged.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt
import pyarrow as pa

from pipeline.errors import StageError
from stages.evaluate.cases import Case, CaseResult, EvalInputs, navigate, navigation_setup, run_all
from stages.evaluate.config import EvaluateConfig
from stages.geometry import wrap_angle
from stages.graph.factors import SCALE_KEY, FactorRow, build_graph, rows_to_table
from stages.graph.load import LoadedGraph
from stages.graph.problem import GraphProblem
from stages.graph.solve import marginal_covariances, optimise
from stages.select_landmarks import LandmarkInputs

FloatArray = npt.NDArray[np.float64]

REDRAWN_KINDS = ("odometry", "loop", "tag")
"""Factor kinds whose measurement is redrawn; priors, motion priors and the tag-scale prior are kept as they are
(they define the frame or are not measurements of the world)."""
PLANAR_TYPES = {"odometry": "BetweenFactorPose2", "loop": "BetweenFactorPose2", "tag": "BearingRangeFactor2D"}


@dataclass(frozen=True)
class World:
    """Where the redrawn measurements come from: true poses (at the keyframes) and landmarks, in the map frame."""

    poses: FloatArray
    """(N, 3) x, y, yaw of every keyframe, in ``loaded.pose_keys`` order."""
    landmarks: dict[int, FloatArray]
    """Tag id to its (x, y)."""
    scale: float
    """The true tag scale (1 for a ground truth; the solution's ``s`` for the bootstrap)."""
    source: str
    """``ground_truth`` or ``full_solution`` (parametric bootstrap)."""
    missing_tags: int = 0
    """Landmarks the ground truth lacks (their world position is the full solution's)."""

    @classmethod
    def of(cls, loaded: LoadedGraph, truth: Any = None) -> World:
        """The world of a run: ``truth`` (a :class:`stages.navigation.truth.MapTruth`) if given, else the solution.

        Raises:
            StageError: the graph is not planar (one line: what to do instead).
        """
        if loaded.model != "planar":
            raise StageError(
                "evaluate.realisations redraws planar graphs only (this graph is 3d); set evaluate.realisations=0"
            )
        solved = {
            t: np.asarray(loaded.position(loaded.values, k)[:2], dtype=float) for t, k in loaded.landmark_keys.items()
        }
        s = float(loaded.values.atDouble(SCALE_KEY)) if loaded.scale_key is not None else 1.0
        if truth is None:
            poses = np.array([_pose2(loaded.values.atPose2(k)) for k in loaded.pose_keys]).reshape(-1, 3)
            return cls(poses, solved, s, "full_solution")
        poses = np.asarray(truth.pose_at(loaded.pose_stamps_ns), dtype=float)
        tags = {int(t): np.asarray(p, dtype=float)[:2] for t, p in truth.tags.items()}
        missing = [t for t in solved if t not in tags]
        lms = {t: tags.get(t, solved[t]) for t in solved}
        return cls(poses, lms, 1.0, "ground_truth", len(missing))


def _pose2(p: gtsam.Pose2) -> FloatArray:
    return np.array([p.x(), p.y(), p.theta()])


def _relative(a: FloatArray, b: FloatArray) -> gtsam.Pose2:
    return gtsam.Pose2(*a).between(gtsam.Pose2(*b))


def redraw_rows(loaded: LoadedGraph, world: World, rng: np.random.Generator) -> list[FactorRow]:
    """Every odometry, loop and tag row with its measurement drawn from the world and the row's stated covariance.

    Tag rows: ``(bearing, range / s) + ν`` at the world's pose and landmark (``s`` the world's tag scale, for rows
    that carry it); pose-to-pose rows: the world's relative pose retracted by ``ν`` (the factor's error is its
    local coordinates, so ``ν`` is its tangent-space noise). ``ν ~ N(0, covariance)``; other rows are kept.
    """
    index = {k: i for i, k in enumerate(loaded.pose_keys)}
    lm_of = {k: t for t, k in loaded.landmark_keys.items()}
    out: list[FactorRow] = []
    for row in loaded.rows:
        if row.kind not in REDRAWN_KINDS:
            out.append(row)
            continue
        if row.type != PLANAR_TYPES[row.kind]:
            raise StageError(f"evaluate.realisations cannot redraw a {row.type} factor (planar graphs only)")
        C = np.asarray(row.covariance, dtype=float).reshape(row.dim, row.dim)
        nu = rng.multivariate_normal(np.zeros(row.dim), 0.5 * (C + C.T))
        if row.kind == "tag":
            pose = world.poses[index[row.keys[0]]]
            d = world.landmarks[lm_of[row.keys[1]]] - pose[:2]
            s = world.scale if len(row.keys) == 3 else 1.0
            z = np.array([math.atan2(d[1], d[0]) - pose[2] + nu[0], math.hypot(d[0], d[1]) / s + nu[1]])
            z[0] = float(wrap_angle(np.array(z[0])))
        else:
            rel = _relative(world.poses[index[row.keys[0]]], world.poses[index[row.keys[1]]]).retract(nu)
            z = _pose2(rel)
        out.append(dataclasses.replace(row, measurement=z, extra=dict(row.extra)))
    return out


def _dead_reckoning(loaded: LoadedGraph, rows: Sequence[FactorRow]) -> gtsam.Values:
    """Initial values of the redrawn graph: poses chained along its odometry from the first keyframe's initial
    value (a pose without odometry to its predecessor keeps the recording's), landmarks at their first sighting."""
    initial = gtsam.Values()
    odo = {(r.keys[0], r.keys[1]): r for r in rows if r.kind == "odometry"}
    prev: gtsam.Pose2 | None = None
    prev_key = None
    for k in loaded.pose_keys:
        row = odo.get((prev_key, k)) if prev_key is not None else None
        if prev is not None and row is not None:
            pose = prev.compose(gtsam.Pose2(*np.asarray(row.measurement, dtype=float)))
        else:
            pose = loaded.initial.atPose2(k)
        initial.insert(k, pose)
        prev, prev_key = pose, k
    seen: set[int] = set()
    for r in rows:
        if r.kind != "tag" or r.keys[1] in seen:
            continue
        seen.add(r.keys[1])
        b, rng = float(r.measurement[0]), float(r.measurement[1])
        initial.insert(
            r.keys[1], initial.atPose2(r.keys[0]).transformFrom(gtsam.Point2(rng * math.cos(b), rng * math.sin(b)))
        )
    for k, t in loaded.var_types.items():
        if not initial.exists(k):
            if t == "Scale":
                initial.insert(k, 1.0)
            elif t == "Point2":
                initial.insert(k, loaded.initial.atPoint2(k))
            else:
                raise StageError(f"evaluate.realisations: {loaded.describe(k)} has no initial value")
    return initial


def redraw_graph(loaded: LoadedGraph, world: World, rng: np.random.Generator) -> LoadedGraph:
    """A full graph of the same structure with redrawn measurements, solved as the graph stage solves (LM, then every
    marginal from one factorisation)."""
    rows = redraw_rows(loaded, world, rng)
    initial = _dead_reckoning(loaded, rows)
    problem = GraphProblem(
        model=loaded.model,
        rows=rows,
        initial=initial,
        var_types=dict(loaded.var_types),
        pose_keys=list(loaded.pose_keys),
        pose_stamps_ns=list(loaded.pose_stamps_ns),
        landmark_keys=dict(loaded.landmark_keys),
        landmark_heights=dict(loaded.landmark_heights),
    )
    graph = build_graph(rows)
    solution = optimise(problem, graph, "lm", 100, 1e-6)
    marginals = marginal_covariances(problem, graph, solution.values, list(problem.var_types))
    return LoadedGraph(
        graph=graph,
        values=solution.values,
        initial=initial,
        factors=rows_to_table(rows),
        rows=rows,
        pose_keys=problem.pose_keys,
        pose_stamps_ns=problem.pose_stamps_ns,
        landmark_keys=problem.landmark_keys,
        landmark_heights=problem.landmark_heights,
        var_types=problem.var_types,
        model=problem.model,
        marginals=marginals,
    )


@dataclass(frozen=True)
class Streams:
    """The seeds of one realisation, one per purpose."""

    measurements: np.random.SeedSequence
    selection_seed: int
    navigation_seed: int


def streams(seed: int, n: int) -> list[Streams]:
    """Per realisation: its measurement stream and its selection and navigation seeds (independent children)."""
    meas, sel, nav = np.random.SeedSequence(seed).spawn(3)
    return [
        Streams(m, int(s.generate_state(1)[0]), int(v.generate_state(1)[0]))
        for m, s, v in zip(meas.spawn(n), sel.spawn(n), nav.spawn(n), strict=True)
    ]


def realisation_inputs(
    base: EvalInputs, loaded: LoadedGraph, detections: pa.Table | None, cfg: EvaluateConfig
) -> EvalInputs:
    """The evaluate inputs of a redrawn graph: the run's scans, truth and settings, nothing from upstream."""
    landmarks = LandmarkInputs.from_pieces(
        loaded, base.scans, base.T_base_laser, detections, base.sl_cfg, base.landmarks.laser_note
    )
    return EvalInputs(
        loaded=loaded,
        landmarks=landmarks,
        truth=base.truth,
        heights=loaded.landmark_heights,
        sl_cfg=base.sl_cfg,
        sm_cfg=base.sm_cfg,
        cfg=cfg,
        scans=base.scans,
        T_base_laser=base.T_base_laser,
        analysis=False,
    )


def run_cases(inputs: EvalInputs, todo: Sequence[Case], trials: int, navigation_seed: int) -> list[CaseResult]:
    """Every case with :func:`~stages.evaluate.cases.run_all` (selections seeded by ``inputs.cfg.seed``), then the
    navigation of every case with ``trials`` trials seeded by ``navigation_seed``.

    cases.py seeds both with ``evaluate.seed``; the navigation runs here as ``run_all`` runs it, with the seed
    swapped, so the two streams stay apart. (With a navigation seed in cases.py this is one ``run_all`` call.)
    """
    sel_cfg = inputs.cfg
    inputs.cfg = sel_cfg.model_copy(update={"trials": 0})
    results = run_all(inputs, todo)
    if trials > 0:
        inputs.cfg = sel_cfg.model_copy(update={"trials": trials, "seed": navigation_seed})
        inputs.navigation = navigation_setup(inputs, results[0].landmark_map)
        for r in results:
            navigate(inputs, r)
    inputs.cfg = sel_cfg
    return results


REALISATION = "realisation"
METRICS = ("collision_rate", "collisions", "trials", "focused_entropy", "focused_error_m")
"""What is kept per realisation and case (columns of ``cases.parquet``)."""


@dataclass
class Study:
    """The per-realisation results of every case."""

    world: str
    realisations: int
    trials: int
    seed: int
    rows: list[dict[str, Any]] = field(default_factory=list)
    """One per realisation and case: ``realisation``, ``case`` and :data:`METRICS`."""
    seconds: float = 0.0
    failed: list[str] = field(default_factory=list)
    """One line per realisation that could not be solved (skipped)."""

    def values(self, case: str, metric: str) -> FloatArray:
        """(R,) the metric of ``case`` per realisation, NaN where the realisation failed."""
        out = np.full(self.realisations, np.nan)
        for r in self.rows:
            if r["case"] == case:
                out[int(r[REALISATION])] = float(r[metric])
        return out

    @property
    def cases(self) -> list[str]:
        """Case names in first-seen order."""
        seen: dict[str, None] = {}
        for r in self.rows:
            seen.setdefault(str(r["case"]), None)
        return list(seen)


def run_realisations(
    base: EvalInputs,
    todo: Sequence[Case],
    n: int,
    trials: int,
    seed: int,
    detections: pa.Table | None = None,
    progress: Callable[[int, float], None] | None = None,
    indices: Sequence[int] | None = None,
) -> Study:
    """``n`` realisations of the run's full graph, every case on each (see the module docstring).

    ``indices``: run only these of the ``n`` (a worker's share; realisation ``r`` is the same whoever runs it).

    The realisations' cases skip what does not enter the statistics: the oracle re-solve
    (``evaluate.oracle_measurements``).
    """
    t0 = time.perf_counter()
    world = World.of(base.loaded, base.truth)
    study = Study(world.source, n, trials, seed)
    cfg = base.cfg.model_copy(update={"oracle_measurements": False})
    todo_r = set(range(n)) if indices is None else {int(i) for i in indices}
    for r, st in enumerate(streams(seed, n)):
        if r not in todo_r:
            continue
        rng = np.random.default_rng(st.measurements)
        try:
            loaded = redraw_graph(base.loaded, world, rng)
            inputs = realisation_inputs(base, loaded, detections, cfg.model_copy(update={"seed": st.selection_seed}))
            results = run_cases(inputs, todo, trials, st.navigation_seed)
        except StageError as err:
            study.failed.append(f"realisation {r}: {err}")
            continue
        for res in results:
            study.rows.append({REALISATION: r, "case": res.case.name, **{m: res.row[m] for m in METRICS}})
        if progress is not None:
            progress(r, time.perf_counter() - t0)
    study.seconds = time.perf_counter() - t0
    return study


def load_run_inputs(run_dir: Path, cfg: EvaluateConfig) -> tuple[EvalInputs, pa.Table | None]:
    """Evaluate's inputs of a finished run folder (graph, select_landmarks, select_measurements, ingest, detect),
    as the stage builds them, and detect's detections (what :func:`run_realisations` needs besides)."""
    from pipeline.artifacts import StageInput
    from pipeline.run_folder import RunFolder
    from stages.columns import STAMP_NS, TAG_ID
    from stages.detect.artifacts import DETECTIONS
    from stages.graph.load import load_graph
    from stages.ingest.artifacts import EXTRINSICS, SCANS
    from stages.navigation.truth import GroundTruth, ground_truth_file
    from stages.select_landmarks.artifacts import FOCUSED
    from stages.select_measurements.artifacts import SELECTION

    run = RunFolder(Path(run_dir))

    def stage(name: str) -> StageInput:
        return StageInput(name, run.stage_dir(name))

    loaded = load_graph(stage("graph"))
    sl_cfg = FOCUSED.read(stage("select_landmarks")).settings
    sm_cfg = SELECTION.read(stage("select_measurements")).settings
    ingest, detect = stage("ingest"), stage("detect")
    scans = SCANS.read(ingest) if ingest.exists(SCANS.file) else None
    T = None
    if ingest.exists(EXTRINSICS.file):
        laser = EXTRINSICS.read(ingest).sensors.get("laser")
        T = np.asarray(laser.T_base_sensor, dtype=float) if laser is not None else None
    detections = DETECTIONS.read(detect, columns=[STAMP_NS, TAG_ID]) if detect.exists(DETECTIONS.file) else None
    gt = ground_truth_file(run.source)
    truth = GroundTruth.load(gt).in_map(loaded.pose_stamps_ns[0]) if gt is not None else None
    landmarks = LandmarkInputs.from_pieces(loaded, scans, T, detections, sl_cfg)
    inputs = EvalInputs(loaded, landmarks, truth, loaded.landmark_heights, sl_cfg, sm_cfg, cfg, scans, T)
    return inputs, detections


REFERENCE_CASE = "focus_info"


def study_table(study: Study | None) -> pa.Table:
    """:data:`~stages.evaluate.artifacts.REALISATIONS` of a study (no rows without one)."""
    from stages.evaluate import artifacts as art

    return art.REALISATIONS.table(study.rows if study is not None else {c: [] for c in art.REALISATIONS.names})


def statistics_rows(study: Study, seed: int = 0, ref: str = REFERENCE_CASE) -> list[dict[str, Any]]:
    """Per case: mean collision rate with its bootstrap interval, mean entropy and focused error, and ``ref``'s
    paired difference in collision rate against it (``ref − case``; negative: ``ref`` collides less)."""
    from stages.evaluate.statistics import bootstrap_interval, paired

    out: list[dict[str, Any]] = []
    base = study.values(ref, "collision_rate") if ref in study.cases else None
    for case in study.cases:
        rate = study.values(case, "collision_rate")
        lo, hi = bootstrap_interval(rate, seed=seed)
        row: dict[str, Any] = {
            "case": case,
            "n": int(np.isfinite(rate).sum()),
            "mean_rate": float(np.nanmean(rate)) if np.isfinite(rate).any() else float("nan"),
            "ci_low": lo,
            "ci_high": hi,
            "mean_entropy": _nanmean(study.values(case, "focused_entropy")),
            "mean_focused_error_m": _nanmean(study.values(case, "focused_error_m")),
            "paired": None,
        }
        if base is not None and case != ref:
            row["paired"] = paired(base, rate, seed=seed)
        out.append(row)
    return out


def _nanmean(v: FloatArray) -> float:
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


def _num(v: float, fmt: str) -> str:
    return fmt.format(v) if math.isfinite(v) else "–"


def statistics_markdown(study: Study, labels: dict[str, str] | None = None, seed: int = 0) -> list[str]:
    """The report's statistics table over the realisations (markdown lines), with what it used."""
    labels = labels or {}
    world = (
        "the ground truth in the map frame"
        if study.world == "ground_truth"
        else "the full graph's own solution (parametric bootstrap; errors are against each realisation's optimal map)"
    )
    lines = [
        f"{study.realisations} map realisations × {study.trials} navigation trials per case "
        f"({study.seconds:.0f} s): every tag and odometry measurement of the full graph redrawn from {world} with its "
        f"stated noise, the full graph re-solved, every case re-selected, re-solved and navigated. Collision rate: "
        f"mean over realisations with a 95 % percentile bootstrap interval. Δ = {REFERENCE_CASE} − case, paired by "
        "realisation (negative: focus, info collides less), with the sign test and the Wilcoxon signed-rank test.",
        "",
        "| case | n | collision rate | 95 % CI | entropy (nats) | focused error (m) | Δ rate | Δ 95 % CI | "
        "lower / higher / tie | sign p | Wilcoxon p |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in statistics_rows(study, seed):
        p = r["paired"]
        cells = [
            labels.get(r["case"], r["case"]),
            str(r["n"]),
            _num(r["mean_rate"], "{:.3f}"),
            f"[{_num(r['ci_low'], '{:.3f}')}, {_num(r['ci_high'], '{:.3f}')}]",
            _num(r["mean_entropy"], "{:.1f}"),
            _num(r["mean_focused_error_m"], "{:.4f}"),
        ]
        if p is None:
            cells += ["–"] * 5
        else:
            cells += [
                _num(p.mean_diff, "{:+.3f}"),
                f"[{_num(p.ci_low, '{:+.3f}')}, {_num(p.ci_high, '{:+.3f}')}]",
                f"{p.lower} / {p.higher} / {p.ties}",
                _num(p.sign_p, "{:.3g}"),
                _num(p.wilcoxon_p, "{:.3g}"),
            ]
        lines.append("| " + " | ".join(cells) + " |")
    if study.failed:
        lines += ["", f"{len(study.failed)} realisation(s) could not be solved and are left out:"]
        lines += [f"- {f}" for f in study.failed[:5]]
    return lines


def report_section(study: Study | None, cfg: EvaluateConfig, labels: dict[str, str] | None = None) -> str:
    """The report's "Over map realisations" section (what it is when the setting is off, too)."""
    head = ["", "## Over map realisations", ""]
    if study is None:
        return "\n".join(
            [
                *head,
                "Off (`evaluate.realisations: 0`): the collision rates above come from one map, the recording's, and "
                "their intervals cover only the navigation noise on it. Set `evaluate.realisations` (30 for the "
                "paper's comparison) to redraw the map and test the differences between cases.",
                "",
            ]
        )
    return "\n".join([*head, *statistics_markdown(study, labels, cfg.seed), ""])
