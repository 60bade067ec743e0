"""Settings of the evaluate stage (YAML section ``evaluate``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_RATE_SIGMA, MAX_ROBOT_RADIUS_M, MAX_SIGMA_M, MAX_TRIALS, MIN_GRID_RESOLUTION_M


class EvaluateConfig(SettingsModel):
    """The six cases of Mu et al. Table I, other strategy pairs, and Monte Carlo LQG navigation on each map."""

    landmark_budget: int | None = Field(
        None, ge=0, description="Landmark budget alpha; null = select_landmarks.budget (the paper's office: 30)."
    )
    measurement_budget: int | None = Field(
        None, ge=0, description="Measurement budget K; null = select_measurements.budget (the paper's office: 90)."
    )
    extra_pairs: list[str] = Field(
        default_factory=lambda: ["mutual-information+information", "leverage+leverage", "random+random"],
        description="Further cases as 'landmark_strategy+measurement_strategy' (select_landmarks and "
        "select_measurements strategy names); the six Table I cases always run.",
    )
    seed: int = Field(0, description="Seed of the random/leverage selections and of the Monte Carlo trials.")
    trials: int = Field(
        100, ge=0, le=MAX_TRIALS, description="Monte Carlo navigation trials per case (0 skips navigation)."
    )
    walls: Literal["auto", "ground_truth", "laser"] = Field(
        "auto",
        description="Obstacles of the navigation: the ground truth's walls (when the run has one), a laser occupancy "
        "grid built at the optimised poses, or auto (ground truth when present, else laser).",
    )
    robot_radius_m: float | None = Field(
        None,
        gt=0,
        le=MAX_ROBOT_RADIUS_M,
        description="Collision radius of the robot, m; null = select_landmarks.robot_radius_m.",
    )
    dt_s: float = Field(0.2, gt=0, description="Time step of the navigation simulation, s.")
    visibility_window_s: float = Field(
        0.5, gt=0, description="A landmark can be measured at a step if the recording saw it within this time, s."
    )
    bearing_sigma_rad: float | None = Field(
        None, gt=0, description="Bearing noise of the simulated measurements, rad; null = the risk model's."
    )
    range_sigma_m: float | None = Field(
        None, gt=0, le=MAX_SIGMA_M, description="Range noise of the simulated measurements, m; null = the risk model's."
    )
    speed_sigma_mps: float = Field(
        0.05, ge=0, le=MAX_RATE_SIGMA, description="Actuation noise on the forward speed, m/s."
    )
    yaw_rate_sigma_radps: float = Field(
        0.05, ge=0, le=MAX_RATE_SIGMA, description="Actuation noise on the yaw rate, rad/s."
    )
    initial_sigma_m: float = Field(
        0.02, ge=0, le=MAX_SIGMA_M, description="Standard deviation of the start position, m."
    )
    initial_sigma_rad: float = Field(0.01, ge=0, description="Standard deviation of the start heading, rad.")
    lqr_position_weight: float = Field(10.0, gt=0, description="LQR weight on the position error (W_x).")
    lqr_heading_weight: float = Field(1.0, gt=0, description="LQR weight on the heading error (W_x).")
    lqr_control_weight: float = Field(1.0, gt=0, description="LQR weight on speed and yaw-rate corrections (W_u).")
    grid_resolution_m: float = Field(
        0.05, ge=MIN_GRID_RESOLUTION_M, description="Cell size of the laser occupancy grid, m."
    )
    grid_min_hits: int = Field(2, ge=1, description="Laser returns a cell needs to count as occupied.")
    scan_stride: int = Field(2, ge=1, description="Use every n-th laser scan for the occupancy grid.")
    plots: bool = Field(True, description="Draw the report's PNG figures (needs matplotlib).")
    oracle_measurements: bool = Field(
        True,
        description="With a ground truth, re-solve every case with its kept tag measurements replaced by "
        "ground-truth-consistent ones (truth + noise drawn from the stated covariance) and report that error beside "
        "the real one: separates what the selection does from biases in the measurements.",
    )
    aligned_navigation: bool = Field(
        True,
        description="With a ground truth, also navigate every case with its map moved by the best rigid motion onto "
        "the true landmarks (collision_rate_aligned): the robot then feels the map's shape errors but not the drift "
        "between the start and the landmarks that moves the whole map in the first-pose frame.",
    )
    realisations: int = Field(
        0,
        ge=0,
        le=10_000,
        description="Map realisations: redraw every tag and odometry measurement of the full graph from the ground "
        "truth (else from the full graph's solution) with its stated noise, re-run every case on each, and report per "
        "case the mean collision rate with a bootstrap interval and focus_info's paired tests (0: off; each costs "
        "about one evaluate of the six cases).",
    )
    realisation_trials: int | None = Field(
        None, ge=0, le=MAX_TRIALS, description="Navigation trials per case in each realisation; null = trials."
    )
    regime: str = Field(
        "default",
        description="Name of the navigation regime, printed in the report (configs/office_hard.yaml sets 'hard').",
    )
