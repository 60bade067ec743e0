"""Settings of the select_landmarks stage (YAML section ``select_landmarks``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_RATE_SIGMA, MAX_ROBOT_RADIUS_M, MAX_SIGMA_M

if TYPE_CHECKING:  # stages.risk imports the estimation maths; settings must load without it
    from stages.risk import RiskParams

LandmarkStrategy = Literal["auto", "collision", "mutual-information", "leverage", "uniform", "random", "all"]
STRATEGIES: tuple[str, ...] = ("collision", "mutual-information", "leverage", "uniform", "random", "all")
NEEDS_LASER: tuple[str, ...] = ("collision",)


class SelectLandmarksConfig(SettingsModel):
    """Stage one of focused inference: which landmarks to keep, and the collision-risk model."""

    strategy: LandmarkStrategy = Field(
        "auto",
        description="collision: Mu et al. Alg. 2 (needs laser scans); mutual-information: Beinhofer et al. greedy; "
        "leverage: Mousavi & Motee sampling; uniform: spatially even; random: seeded; all: every landmark. auto: "
        "collision when the run has laser scans, else mutual-information up to max_trajectory_dim, else uniform "
        "(the summary's notes say which and why).",
    )
    budget: int = Field(30, ge=0, description="Number of landmarks to keep (alpha); 0 keeps none.")
    seed: int = Field(0, description="Seed of the random and leverage strategies.")
    leverage_draws: int = Field(20, ge=1, description="leverage: independent draws; the best one is kept.")
    leverage_measure: Literal["logdet", "trace", "max_eig"] = Field(
        "logdet", description="leverage: measure of the trajectory covariance that picks the best draw."
    )
    landmark_prior_sigma_m: float = Field(
        100.0,
        gt=0,
        le=MAX_SIGMA_M,
        description="mutual-information and leverage: weak prior on a landmark when its measurements are "
        "marginalised (Schur complement), m.",
    )
    max_trajectory_dim: int = Field(
        12000,
        ge=1,
        description="mutual-information and leverage work on each landmark's dense information over the poses "
        "that see it (time and memory up to quadratic in the trajectory); refuse larger "
        "trajectories (poses x pose dimension) than this.",
    )
    robot_radius_m: float = Field(
        0.25,
        ge=0,
        le=MAX_ROBOT_RADIUS_M,
        description="Robot footprint radius: the collision margin is laser clearance minus this, m.",
    )
    visibility_window_s: float = Field(
        1.0, ge=0, description="A landmark is visible from a keyframe if measured from a keyframe this close, s."
    )
    max_scan_gap_s: float = Field(
        0.25, gt=0, description="The laser scan used for a keyframe is at most this far from it in time, s."
    )
    control_period_s: float = Field(
        0.2,
        gt=0,
        le=10.0,
        description="The robot's control period, s: the path is followed, and the robot's covariance propagated, in "
        "steps this long (the risk model here and evaluate's simulated robot).",
    )
    speed_sigma_mps: float | None = Field(
        None,
        gt=0,
        le=MAX_RATE_SIGMA,
        description="The robot's forward-speed noise over one control period, m/s; null = as fast as the "
        "recording's odometry drifts (its factors' translation variance per second).",
    )
    yaw_rate_sigma_radps: float | None = Field(
        None,
        gt=0,
        le=MAX_RATE_SIGMA,
        description="The robot's yaw-rate noise over one control period, rad/s; null = from the recording's "
        "odometry factors.",
    )
    initial_sigma_m: float = Field(
        0.02, ge=0, le=MAX_SIGMA_M, description="Standard deviation of the robot's start position, m."
    )
    initial_sigma_rad: float = Field(0.01, ge=0, le=3.2, description="Standard deviation of its start heading, rad.")
    bearing_sigma_rad: float | None = Field(
        None, gt=0, description="Bearing noise of the risk model, rad; null = median of the graph's tag factors."
    )
    range_sigma_m: float | None = Field(
        None,
        gt=0,
        le=MAX_SIGMA_M,
        description="Range noise of the risk model, m; null = median of the graph's tag factors.",
    )
    ellipse_stride: int = Field(5, ge=1, description="Draw the Sigma* ellipse of every n-th keyframe in the recording.")
    max_replay_steps: int = Field(
        100, ge=0, description="Replay at most this many greedy picks on the selection_step timeline."
    )

    def risk_params(self) -> RiskParams:
        """The risk model of these settings (for :func:`stages.risk.path_risk`)."""
        from stages.risk import RiskParams

        return RiskParams(
            robot_radius_m=self.robot_radius_m,
            visibility_window_s=self.visibility_window_s,
            max_scan_gap_s=self.max_scan_gap_s,
            control_period_s=self.control_period_s,
            speed_sigma_mps=self.speed_sigma_mps,
            yaw_rate_sigma_radps=self.yaw_rate_sigma_radps,
            bearing_sigma_rad=self.bearing_sigma_rad,
            range_sigma_m=self.range_sigma_m,
            initial_sigma_m=self.initial_sigma_m,
            initial_sigma_rad=self.initial_sigma_rad,
        )
