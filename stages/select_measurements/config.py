"""Settings of the select_measurements stage (YAML section ``select_measurements``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_SIGMA_M

MeasurementStrategy = Literal["information", "leverage", "uniform", "random", "all"]
STRATEGIES: tuple[str, ...] = ("information", "leverage", "uniform", "random", "all")


class SelectMeasurementsConfig(SettingsModel):
    """Stage two of focused inference: which tag measurements to keep (all odometry is always kept)."""

    strategy: MeasurementStrategy = Field(
        "information",
        description="information: Mu et al. Alg. 1, exact fast greedy on the focused entropy; leverage: Mousavi & "
        "Motee sampling; uniform: even in time (the paper's DS); random: seeded; all: every candidate.",
    )
    budget: int = Field(
        90,
        ge=0,
        description="Number of candidate measurements to keep (K: tag measurements, or loop closures with "
        "focus=poses); 0 keeps none.",
    )
    focus: Literal["selected", "all", "poses"] = Field(
        "selected",
        description="selected: the landmarks of select_landmarks are focused and their measurements are the "
        "candidates; all: every landmark (the 'full' cases of Mu et al. Table I; select_landmarks not needed); "
        "poses: every pose is focused and the loop closures (pose-to-pose edges between non-consecutive poses of "
        "an imported graph) are the candidates, so a pose graph is sparsified to K loop closures.",
    )
    focus_poses: int = Field(
        0,
        ge=0,
        le=100_000,
        description="Also focus the poses of this many riskiest keyframes (eq. 20 with the focused landmarks, from "
        "select_landmarks' risk.parquet; at least its visibility window apart), so the kept measurements also tie "
        "the path to the map where it is tight (Mu et al. eq. 23 allows any focused set W); 0 = landmarks only.",
    )
    landmark_prior_sigma_m: float = Field(
        100.0,
        gt=0,
        le=MAX_SIGMA_M,
        description="Weak isotropic prior on every landmark in the initial information (odometry and prior leave "
        "landmarks unobserved), so first gains are finite and comparable, m.",
    )
    refactor_every: int | None = Field(
        64,
        ge=1,
        description="information: greedy picks between sparse refactorisations (Woodbury in between); null = adaptive.",
    )
    seed: int = Field(0, description="Seed of the random and leverage strategies.")
    leverage_draws: int = Field(20, ge=1, description="leverage: independent draws; the best one is kept.")
    leverage_measure: Literal["logdet", "trace", "max_eig"] = Field(
        "logdet", description="leverage: measure of the focused covariance that picks the best draw."
    )
    max_replay_steps: int = Field(
        60,
        ge=0,
        description="Replay at most this many picks (evenly spaced) with the focused ellipsoids on the "
        "selection_step timeline (each costs one sparse factorisation).",
    )
