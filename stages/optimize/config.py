"""Settings of the optimize stage (YAML section ``optimize``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_SIGMA_M


class OptimizeConfig(SettingsModel):
    """Re-optimise the reduced graph (odometry + prior + the selected measurements of the focused landmarks)."""

    initialise_from: Literal["dead_reckoning", "full_solution"] = Field(
        "dead_reckoning",
        description="Initial values of the reduced graph: the full graph's initial values (dead reckoning and "
        "first sightings, what a robot without the full map would have) or the full graph's solution.",
    )
    max_iterations: int = Field(100, ge=1, description="Maximum Levenberg-Marquardt iterations.")
    relative_error_tol: float = Field(1e-6, gt=0, description="Stop when the error falls by less than this fraction.")
    unobserved_sigma_m: float = Field(
        100.0,
        gt=0,
        le=MAX_SIGMA_M,
        description="A focused landmark that keeps no measurement enters the focused entropy with this isotropic "
        "standard deviation per dimension, m (the weak landmark prior of measurement selection).",
    )
    truth_file: str = Field(
        "",
        description="Ground truth of the recording (--truth): a truth YAML (docs/evaluate.md, 'Ground truth file': "
        "tags, poses as a TUM file, walls) or a simulator .ground_truth.json; empty = <name>.ground_truth.json, "
        "else <name>.truth.yaml, beside the recording, if there.",
    )
    strict: bool = Field(
        False,
        description="Make a failed health check of the reduced graph (stages/graph/health.py) an error: the stage "
        "stops and its results are not kept (--strict).",
    )
    pose_ellipse_stride: int = Field(10, ge=1, description="Draw the covariance ellipse of every n-th pose.")
