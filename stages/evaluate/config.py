"""Settings of the evaluate stage (YAML section ``evaluate``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_ROBOT_RADIUS_M, MAX_TRIALS, MIN_GRID_RESOLUTION_M


class EvaluateConfig(SettingsModel):
    """The six cases of Mu et al. Table I, other strategy pairs, and Monte Carlo LQG navigation on each map.

    The simulated robot is the robot model of select_landmarks (its settings as recorded in ``focused.json``: control
    period, motion and sensor noise, start covariance, visibility window), so stage one picks landmarks for the
    robot evaluated here."""

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
    extra_max_trajectory_dim: int = Field(
        3000,
        ge=0,
        description="An extra pair whose landmark strategy works on the dense trajectory information "
        "(mutual-information, leverage) is skipped, with a warning, above this many trajectory dimensions (poses x "
        "pose dimension): its time and memory grow with the square of the recording's length, and past this size "
        "they outweigh the Table I cases (a 4-minute corridor recording with laps, 3,702 dimensions: ~250 MiB more "
        "for each, and evaluate 61 s against 67 s for an 8-minute one without them).",
    )
    focused_poses: int = Field(
        10,
        ge=0,
        le=100_000,
        description="Add the case focus_info_poses: as focus, info, with the poses of this many riskiest keyframes "
        "(eq. 20, at least the visibility window apart) focused beside the landmarks (select_measurements."
        "focus_poses), so its kept measurements also tie the path to the map where it is tight; 0 = no such case.",
    )
    seed: int = Field(0, description="Seed of the random/leverage selections and of the Monte Carlo trials.")
    trials: int = Field(
        100, ge=0, le=MAX_TRIALS, description="Monte Carlo navigation trials per case (0 skips navigation)."
    )
    truth_file: str = Field(
        "",
        description="Ground truth of the recording (--truth): a truth YAML (docs/evaluate.md, 'Ground truth file': "
        "tags, poses as a TUM file, walls) or a simulator .ground_truth.json; empty = <name>.ground_truth.json, "
        "else <name>.truth.yaml, beside the recording, if there.",
    )
    walls: Literal["auto", "ground_truth", "laser"] = Field(
        "auto",
        description="Obstacles of the navigation: the ground truth's walls (when the run has one), a laser occupancy "
        "grid built at the optimised poses, or auto (ground truth when present, else laser; with neither, the "
        "navigation is skipped with a note). A source named here that the run lacks is an error.",
    )
    robot_radius_m: float | None = Field(
        None,
        gt=0,
        le=MAX_ROBOT_RADIUS_M,
        description="Collision radius of the robot, m; null = select_landmarks.robot_radius_m. Set, it is the radius "
        "of the one robot model everywhere in evaluate: the focused set is picked again for it.",
    )
    lqr_position_weight: float = Field(10.0, gt=0, description="LQR weight on the position error (W_x).")
    lqr_heading_weight: float = Field(1.0, gt=0, description="LQR weight on the heading error (W_x).")
    lqr_control_weight: float = Field(1.0, gt=0, description="LQR weight on speed and yaw-rate corrections (W_u).")
    grid_resolution_m: float = Field(
        0.05, ge=MIN_GRID_RESOLUTION_M, description="Cell size of the laser occupancy grid, m."
    )
    grid_min_hits: int = Field(2, ge=1, description="Laser returns a cell needs to count as occupied.")
    scan_stride: int = Field(2, ge=1, description="Use every n-th laser scan for the occupancy grid.")
    plots: bool = Field(True, description="Draw the report's PNG figures (needs matplotlib).")
    workers: int = Field(
        2,
        ge=1,
        le=2,
        description="Processes evaluate uses: 2 runs each case's navigation trials, and draws the maps and navigation "
        "figures, in a worker process while this one selects and solves the next case (the same numbers and "
        "pictures); 1 runs everything in this one.",
    )
    oracle_measurements: bool = Field(
        True,
        description="With a ground truth, re-solve every case with its kept tag measurements replaced by "
        "ground-truth-consistent ones (truth + noise drawn from the stated covariance) and report that error beside "
        "the real one: separates what the selection does from biases in the measurements.",
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
