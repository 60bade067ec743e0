"""What select_landmarks writes into ``RUN/select_landmarks/``: the focused landmarks and the path's collision risk.

Downstream stages (select_measurements, optimize, evaluate) read the landmark budget α, the strategy and the
collision-risk model from ``focused.json`` (:data:`FOCUSED`), never from the ``select_landmarks`` settings section:
the artifact's fingerprint is part of theirs, so a new α or robot radius re-runs them, and what they report is what
this stage did.

```python
FOCUSED.write(ctx.output, FocusedLandmarks.of(choice, cfg, geometry))
focused = FOCUSED.read(ctx.input("select_landmarks"))      # FocusedLandmarks: .tag_ids, .budget, .risk_params
RISK.write(ctx.output, risk_table(geometry, risk_all, risk_focused))
```
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from pipeline.contracts import ArtifactSet, Column, JsonSpec, TableSpec
from stages.columns import STAMP_NS, YAW, X, Y, Z
from stages.select_landmarks.config import SelectLandmarksConfig

if TYPE_CHECKING:
    from stages.risk import PathGeometry, PathRisk, RiskParams
    from stages.select_landmarks.core import LandmarkChoice

_F64 = pa.float64()


# focused.json ------------------------------------------------------------------------------------------
class RiskNoise(BaseModel):
    """The noise of the collision-risk model as resolved from the graph (or set in the settings)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    bearing_sigma_rad: float = Field(description="bearing noise of the tag measurements, rad")
    range_sigma_m: float = Field(description="range noise of the tag measurements, m")
    speed_sigma_mps: float = Field(description="the robot model's forward-speed noise over one control period, m/s")
    yaw_rate_sigma_radps: float = Field(description="the robot model's yaw-rate noise over one control period, rad/s")


class FocusedLandmarks(BaseModel):
    """What select_landmarks chose, and with which settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    strategy: str = Field(description="the landmark-selection strategy that ran")
    budget: int = Field(description="α, the landmark budget as run (`all`: the number of landmarks)")
    tag_ids: list[int] = Field(description="the selected tag ids, in pick order")
    scores: list[float | None] = Field(
        description="score at each pick (docs/select.md: per strategy); NaN and inf are written as null"
    )
    status: str = Field(description="`ok`, `budget_zero`, `budget_exceeds_landmarks` or `no_landmarks`")
    message: str = Field(description="the status in words")
    n_landmarks: int = Field(description="landmarks of the graph the selection chose from")
    seconds: float = Field(description="time the selection took, s")
    settings: SelectLandmarksConfig = Field(
        description="the select_landmarks settings that made the selection, the risk model included: later stages "
        "read α and the risk model here"
    )
    noise: RiskNoise = Field(
        description="the risk model's noise as resolved from the graph: `bearing_sigma_rad`, `range_sigma_m`, "
        "`speed_sigma_mps`, `yaw_rate_sigma_radps` (the robot model's motion noise; evaluate's simulated robot is this "
        "robot)"
    )

    @property
    def risk_params(self) -> RiskParams:
        """The collision-risk model the selection used."""
        return self.settings.risk_params()

    @classmethod
    def of(cls, choice: LandmarkChoice, cfg: SelectLandmarksConfig, geo: PathGeometry) -> FocusedLandmarks:
        """The record of ``choice``, made with ``cfg`` on a path of geometry ``geo``."""
        return cls(
            strategy=choice.strategy,
            budget=choice.budget,
            tag_ids=[int(t) for t in choice.tag_ids],
            scores=[float(s) if np.isfinite(s) else None for s in choice.scores],
            status=choice.status,
            message=choice.message,
            n_landmarks=choice.n_landmarks,
            seconds=choice.seconds,
            settings=cfg,
            noise=RiskNoise(
                bearing_sigma_rad=float(geo.sigmas[0]),
                range_sigma_m=float(geo.sigmas[1]),
                speed_sigma_mps=float(geo.robot.speed_sigma_mps),
                yaw_rate_sigma_radps=float(geo.robot.yaw_rate_sigma_radps),
            ),
        )


FOCUSED: Final = JsonSpec(
    "focused.json", "the focused landmarks, how they were chosen and the risk model", FocusedLandmarks
)


# risk.parquet ------------------------------------------------------------------------------------------
def _f64(name: str, doc: str) -> Column:
    return Column(name, _F64, doc)


SIGMA_STAR = Column(
    "sigma_star",
    pa.list_(_F64, 4),
    "Σ of (x, y), 2×2 row-major, m², with the focused landmarks (Σ* where one is visible, else dead reckoning)",
)
SIGMA_STAR_ALL = Column("sigma_star_all", pa.list_(_F64, 4), "the same with every landmark of the graph")
LOCALISED = Column("localised", pa.bool_(), "the keyframe sees a focused landmark")
CLEARANCE_M = _f64("clearance_m", "distance to the nearest laser return, m (inf: none known; NaN: no laser)")
NORMAL_X = _f64("normal_x", "unit vector towards that return, x (map frame)")
NORMAL_Y = _f64("normal_y", "unit vector towards that return, y (map frame)")
OBSTACLE_X = _f64("obstacle_x", "the nearest return in the map frame, x, m (NaN where none)")
OBSTACLE_Y = _f64("obstacle_y", "the nearest return in the map frame, y, m (NaN where none)")
N_VISIBLE = Column("n_visible", pa.int64(), "landmarks visible from the keyframe")
P_COLLISION_ALL = _f64("p_collision_all", "half-plane collision probability with every landmark (NaN without laser)")
P_COLLISION_FOCUSED = _f64("p_collision_focused", "the same with the focused landmarks")
MAHALANOBIS_ALL = _f64(
    "mahalanobis_all", "eq. 20: squared standard deviations to the obstacle with every landmark (inf: no obstacle)"
)
MAHALANOBIS_FOCUSED = _f64("mahalanobis_focused", "the same with the focused landmarks")
RISK_Z = Column(Z, _F64, "height of the drawn path, m (0: planar)")

RISK: Final = TableSpec(
    "risk.parquet",
    "one row per keyframe of the full graph, in time order: its pose in the map frame, Σ and the collision risk",
    [
        STAMP_NS,
        X,
        Y,
        RISK_Z,
        YAW,
        SIGMA_STAR,
        SIGMA_STAR_ALL,
        LOCALISED,
        CLEARANCE_M,
        NORMAL_X,
        NORMAL_Y,
        OBSTACLE_X,
        OBSTACLE_Y,
        N_VISIBLE,
        P_COLLISION_ALL,
        P_COLLISION_FOCUSED,
        MAHALANOBIS_ALL,
        MAHALANOBIS_FOCUSED,
    ],
)


def xy_blocks(sigma: np.ndarray) -> list[list[float]]:
    """The (x, y) block of each (3, 3) covariance, row-major (the ``sigma_star`` columns)."""
    return [s[:2, :2].ravel().tolist() for s in sigma]


def risk_table(geometry: PathGeometry, risk_all: PathRisk, risk_focused: PathRisk, z: float = 0.0) -> pa.Table:
    """:data:`RISK` of a path: its geometry, and its risk with every landmark and with the focused ones."""
    T = len(geometry.stamps_ns)
    return RISK.table(
        {
            STAMP_NS: geometry.stamps_ns,
            X: geometry.poses[:, 0],
            Y: geometry.poses[:, 1],
            RISK_Z: np.full(T, z),
            YAW: geometry.poses[:, 2],
            SIGMA_STAR: xy_blocks(risk_focused.sigma),
            SIGMA_STAR_ALL: xy_blocks(risk_all.sigma),
            LOCALISED: risk_focused.localised,
            CLEARANCE_M: geometry.clearance_m,
            NORMAL_X: geometry.normals[:, 0],
            NORMAL_Y: geometry.normals[:, 1],
            OBSTACLE_X: geometry.obstacles[:, 0],
            OBSTACLE_Y: geometry.obstacles[:, 1],
            N_VISIBLE: geometry.visible.sum(axis=1).astype(np.int64),
            P_COLLISION_ALL: risk_all.p_collision,
            P_COLLISION_FOCUSED: risk_focused.p_collision,
            MAHALANOBIS_ALL: risk_all.mahalanobis,
            MAHALANOBIS_FOCUSED: risk_focused.mahalanobis,
        }
    )


ARTIFACTS: Final = ArtifactSet(
    "select_landmarks",
    "Stage one of focused inference: the landmarks worth keeping, and the collision risk of the path with them.",
    [FOCUSED, RISK],
)
