"""Landmark selection without a run folder: load the inputs once, then run any strategy with :func:`choose`.

```python
inputs = LandmarkInputs.load(ctx, cfg)                      # or LandmarkInputs.from_pieces(loaded, scans, ...)
choice = choose(inputs, cfg)                                # LandmarkChoice: tag_ids in pick order, scores, risk
choice = choose(inputs, cfg.model_copy(update={"strategy": "uniform"}))
```
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import scipy.sparse as sp

from pipeline.errors import StageError
from stages.estimation.collision import Contribution, select_collision
from stages.estimation.landmark_selection import (
    LandmarkSelection,
    schur_contribution,
    select_landmark_leverage,
    select_landmark_random,
    select_landmark_uniform,
    select_mutual_information,
)
from stages.risk import (
    LandmarkMap,
    PathGeometry,
    PathRisk,
    RiskParams,
    full_local_map,
    landmark_contributions,
    path_geometry,
    path_risk,
    read_path_inputs,
    step_margins,
)
from stages.select_landmarks.config import NEEDS_LASER, SelectLandmarksConfig

if TYPE_CHECKING:
    from pipeline.context import StageContext
    from stages.graph.load import LoadedGraph

FloatArray = npt.NDArray[np.float64]
Contributions = list[tuple[npt.NDArray[np.int64], FloatArray]]


@dataclass
class LandmarkInputs:
    """Everything the strategies read, loaded once (the graph, its landmark map and the path geometry)."""

    loaded: LoadedGraph
    landmarks: LandmarkMap
    geometry: PathGeometry
    params: RiskParams
    laser_note: str = ""
    """Why there is no laser (empty when there is)."""
    sigma_cache: dict[int, Contribution] = field(default_factory=dict, repr=False)
    """Each tag's measurement information along the path, shared by the :func:`stages.risk.path_risk` calls on
    these inputs."""
    _trajectory: tuple[sp.csc_matrix, Contributions] | None = field(default=None, repr=False)
    _trajectory_prior: float | None = field(default=None, repr=False)

    @classmethod
    def from_pieces(
        cls,
        loaded: LoadedGraph,
        scans: pa.Table | None = None,
        T_base_laser: FloatArray | None = None,
        detections: pa.Table | None = None,
        cfg: SelectLandmarksConfig | None = None,
        laser_note: str = "",
    ) -> LandmarkInputs:
        """Inputs from explicit pieces: a loaded graph, ingest's scans and laser extrinsics, detect's detections."""
        cfg = cfg or SelectLandmarksConfig()
        params = cfg.risk_params()
        if scans is not None and scans.num_rows == 0:
            scans, laser_note = None, laser_note or "the run's scans.parquet is empty"
        if scans is None and not laser_note:
            laser_note = "no laser scans were given"
        if not loaded.landmark_keys:
            raise StageError("the graph has no landmarks, so there is nothing to select; check 'focusmap graph'")
        geometry = path_geometry(loaded, scans, T_base_laser, detections, params)
        lm = full_local_map(loaded, geometry) if geometry.has_laser else LandmarkMap.from_graph(loaded)
        return cls(loaded, lm, geometry, params, laser_note)

    @classmethod
    def load(cls, ctx: StageContext, cfg: SelectLandmarksConfig) -> LandmarkInputs:
        """Inputs from a run folder: graph (required), ingest's scans and extrinsics and detect's detections if run."""
        from stages.graph.load import load_graph

        loaded = load_graph(ctx.input("graph"))
        read = read_path_inputs(ctx)
        return cls.from_pieces(loaded, read.scans, read.T_base_laser, read.detections, cfg, read.laser_note)

    @property
    def has_laser(self) -> bool:
        """Whether the collision strategy can run."""
        return self.geometry.has_laser

    def trajectory_information(self, landmark_prior_sigma: float, max_dim: int) -> tuple[sp.csc_matrix, Contributions]:
        """``Λ₀`` of the trajectory (odometry and priors; sparse) and each landmark's Schur contribution (dense on
        the poses that see it).

        Contributions are in landmark-map order (``self.landmarks.tag_ids``); cached per prior.
        """
        if self._trajectory is not None and self._trajectory_prior == landmark_prior_sigma:
            return self._trajectory
        from stages.estimation.linear_system import LinearSystem, landmark_prior_sigmas, unanchored_poses

        loaded = self.loaded
        system = LinearSystem.from_gtsam(
            loaded.graph, loaded.values, is_landmark=set(loaded.landmark_keys.values()).__contains__
        )
        pose_vars = [system.index_of_key(k) for k in loaded.pose_keys]
        pose_cols = system.columns(pose_vars)
        n = len(pose_cols)
        if n > max_dim:
            instead = "collision" if self.has_laser else "uniform (this run has no laser for collision)"
            raise StageError(
                f"mutual-information and leverage work on each landmark's dense information over the poses that "
                f"see it, so their time and memory grow up to the square of the trajectory ({n} dimensions here, "
                f"above select_landmarks.max_trajectory_dim={max_dim}); use --set "
                f"select_landmarks.strategy={instead}, a budget at or above the {len(self.landmarks.tag_ids)} "
                "landmarks, or raise the limit if time and memory allow"
            )
        col_in_traj = np.full(system.dim, -1, dtype=np.int64)
        col_in_traj[pose_cols] = np.arange(n)
        fixed = [int(i) for i in loaded.fixed_factor_indices]
        full_info = system.information(fixed)
        # a trajectory anchored only through a surveyed tag (its prior is on the landmark, outside Λ₀) has a free
        # gauge: the weak landmark prior goes on the first pose of each such group, else Λ₀ is singular
        loose = unanchored_poses(system, fixed, [])
        if loose:
            full_info = full_info + system.diagonal_prior(loose, landmark_prior_sigma)
        info0 = sp.csc_matrix(full_info[pose_cols][:, pose_cols])  # sparse: the greedy factorises it sparse
        by_landmark: dict[int, list[int]] = {k: [] for k in loaded.landmark_keys.values()}
        for i in loaded.tag_factor_indices:
            keys = loaded.rows[int(i)].keys
            for k in keys:
                if k in by_landmark:
                    by_landmark[k].append(int(i))
        contributions: Contributions = []
        for tag in self.landmarks.tag_ids:
            lkey = loaded.landmark_keys[int(tag)]
            lvar = system.index_of_key(lkey)
            lcols = system.columns([lvar])
            fids = by_landmark[lkey]
            if not fids:
                contributions.append((np.zeros(0, dtype=np.int64), np.zeros((0, 0))))
                continue
            J = system.jacobian(fids).tocsc()
            support = np.unique(np.concatenate([system.factor_columns(f) for f in fids]))
            support = support[col_in_traj[support] >= 0]
            J_x = J[:, support].toarray()
            J_l = J[:, lcols].toarray()
            B = schur_contribution(J_x, J_l, 1.0 / landmark_prior_sigmas(len(lcols), landmark_prior_sigma) ** 2)
            contributions.append((col_in_traj[support], B))
        self._trajectory = (info0, contributions)
        self._trajectory_prior = landmark_prior_sigma
        return self._trajectory


@dataclass
class LandmarkChoice:
    """The result of one landmark selection, with the collision risk of the path before and after."""

    strategy: str
    budget: int
    tag_ids: list[int]
    """Selected tag ids in the order picked."""
    scores: list[float]
    """Score at each pick: collision: max collision probability along the path after the pick; mutual-information:
    marginal gain (nats); leverage: sampling probability; uniform: distance to the earlier picks (m); else NaN."""
    status: str
    """ok | budget_zero | budget_exceeds_landmarks | no_landmarks."""
    message: str
    n_landmarks: int
    seconds: float
    risk_none: PathRisk | None = None
    """Risk with no landmark (dead reckoning everywhere); None when not computed."""
    risk_all: PathRisk | None = None
    """Risk with every landmark."""
    risk_focused: PathRisk | None = None
    """Risk with the selected landmarks."""
    extra: dict[str, Any] = field(default_factory=dict)


def collision_greedy(geo: PathGeometry, lm: LandmarkMap, budget: int, params: RiskParams) -> LandmarkSelection:
    """Mu et al. Alg. 2 (:func:`stages.estimation.collision.select_collision`) on a run's path and landmark map.

    Scores: the maximum collision probability along the path after each pick.
    """
    margin, normals = step_margins(geo, params)
    contributions = landmark_contributions(geo, lm, lm.tag_ids.tolist())
    return select_collision(geo.noise, contributions, margin, normals, budget)


def _message(status: str, budget: int, n: int, picked: int, strategy: str) -> str:
    if status == "budget_zero":
        return "budget 0: no landmark selected (every keyframe dead-reckons)"
    if status == "budget_exceeds_landmarks":
        return f"budget {budget} exceeds the {n} landmarks: all {picked} kept"
    if status == "no_landmarks":
        return "the graph has no landmarks"
    if strategy == "all":
        return f"all {n} landmarks kept"
    return f"{picked} of {n} landmarks selected by {strategy}"


def auto_strategy(inputs: LandmarkInputs, cfg: SelectLandmarksConfig) -> tuple[str, str]:
    """The strategy ``auto`` runs, and why: collision with laser scans; without, mutual information while the
    trajectory is within ``max_trajectory_dim`` (its dense information grows with the square), else uniform."""
    if inputs.has_laser:
        return "collision", "the run has laser scans"
    dim = len(inputs.loaded.pose_keys) * inputs.loaded.graph_model.pose.dim
    if dim <= cfg.max_trajectory_dim:
        return "mutual-information", f"no laser scans for collision ({inputs.laser_note})"
    return "uniform", (
        f"no laser scans for collision ({inputs.laser_note}), and the trajectory's {dim} dimensions are above "
        f"select_landmarks.max_trajectory_dim={cfg.max_trajectory_dim} for mutual-information"
    )


def choose(inputs: LandmarkInputs, cfg: SelectLandmarksConfig, with_risk: bool = True) -> LandmarkChoice:
    """Run one landmark-selection strategy on loaded inputs.

    Args:
        inputs: from :meth:`LandmarkInputs.load` or :meth:`LandmarkInputs.from_pieces`.
        cfg: the settings (``strategy``, ``budget``, ``seed``, the risk model).
        with_risk: also compute the path risk with no, all and the selected landmarks (needs laser for the
            probabilities; Σ* is computed either way).

    Raises:
        StageError: ``collision`` on a run without laser scans; a trajectory too large for the dense strategies.
    """
    t0 = time.perf_counter()
    lm = inputs.landmarks
    L = len(lm.tag_ids)
    strategy = auto_strategy(inputs, cfg)[0] if cfg.strategy == "auto" else cfg.strategy
    if strategy in NEEDS_LASER and not inputs.has_laser:
        others = "mutual-information, leverage, uniform, random or all"
        raise StageError(
            f"strategy {strategy!r} needs laser scans, and this run has none ({inputs.laser_note}); only {others} "
            f"can run here: --set select_landmarks.strategy=mutual-information"
        )
    params = inputs.params
    geo = inputs.geometry
    if strategy == "all" or (L and cfg.budget >= L):  # every landmark: no greedy to run (in tag order)
        sel = LandmarkSelection(list(range(L)), [float("nan")] * L, "ok" if L else "no_landmarks")
    elif strategy == "collision":
        sel = collision_greedy(geo, lm, cfg.budget, params)
    elif strategy in ("mutual-information", "leverage"):
        if cfg.budget <= 0:
            sel = LandmarkSelection([], [], "budget_zero")
        else:
            info0, contributions = inputs.trajectory_information(cfg.landmark_prior_sigma_m, cfg.max_trajectory_dim)
            if strategy == "mutual-information":
                sel = select_mutual_information(info0, contributions, cfg.budget)
            else:
                sel = select_landmark_leverage(
                    info0, contributions, cfg.budget, cfg.leverage_draws, cfg.leverage_measure, cfg.seed
                )
    elif strategy == "uniform":
        sel = select_landmark_uniform(lm.positions, cfg.budget)
    else:
        sel = select_landmark_random(L, cfg.budget, cfg.seed)
    if strategy != "all" and sel.status == "ok" and cfg.budget > L:
        sel.status = "budget_exceeds_landmarks"
    tag_ids = [int(lm.tag_ids[i]) for i in sel.picks]
    budget = L if strategy == "all" else cfg.budget
    choice = LandmarkChoice(
        strategy=strategy,
        budget=budget,
        tag_ids=tag_ids,
        scores=[float(s) for s in sel.scores],
        status=sel.status,
        message=_message(sel.status, cfg.budget, L, len(tag_ids), strategy),
        n_landmarks=L,
        seconds=0.0,
        extra={k: v for k, v in sel.extra.items() if k in ("objective", "measure")},
    )
    choice.seconds = time.perf_counter() - t0
    if with_risk:
        cache = inputs.sigma_cache
        choice.risk_none = path_risk(geo, lm, [], params, cache)
        choice.risk_all = path_risk(geo, lm, lm.tag_ids, params, cache)
        choice.risk_focused = path_risk(geo, lm, tag_ids, params, cache)
    return choice
