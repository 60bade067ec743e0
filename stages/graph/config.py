"""Settings of the graph stage (YAML section ``graph``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_SIGMA_M

GRAPH_SOURCE = "graph"
"""``source_kind`` of a run made by ``import-graph``: its graph stage reads the graph file, not ingest and detect."""


class GraphConfig(SettingsModel):
    """The full factor graph: model, keyframes, noise, robust kernel and optimiser."""

    model: Literal["auto", "planar", "3d"] = Field(
        "auto",
        description="planar: Pose2 robot poses and (x, y) tag landmarks (ground robots); "
        "3d: Pose3 robot poses and Pose3 tags; auto: 3d when the motion is not planar (no odometry, or the "
        "odometry's height, roll or pitch vary, or tags seen from the base change height or tilt), planar "
        "otherwise (stages/graph/model_choice.py; the summary's model_choice says which and why).",
    )
    # keyframes
    keyframe_max_gap_s: float = Field(
        1.0, gt=0, description="Add an odometry keyframe where no tag was seen for this long, s."
    )
    keyframe_max_distance_m: float = Field(
        0.5, gt=0, description="Add an odometry keyframe where the robot moved this far without a tag frame, m."
    )
    keyframe_max_angle_rad: float = Field(
        0.5, gt=0, description="Add an odometry keyframe where the robot turned this much without a tag frame, rad."
    )
    # odometry
    odometry_noise: Literal["auto", "messages", "settings"] = Field(
        "auto",
        description="Noise of the odometry factors: from the messages' pose covariances (their growth between "
        "keyframes), from the settings below, or auto (messages when filled in, else settings).",
    )
    odometry_sigma_m: float = Field(
        0.01, gt=0, le=MAX_SIGMA_M, description="Odometry translation noise floor per factor, m."
    )
    odometry_sigma_per_m: float = Field(
        0.05, ge=0, description="Odometry translation noise growth per metre travelled (fraction of distance)."
    )
    odometry_sigma_rad: float = Field(0.005, gt=0, description="Odometry heading noise floor per factor, rad.")
    odometry_sigma_rad_per_rad: float = Field(
        0.05, ge=0, description="Odometry heading noise growth per radian turned (fraction of angle)."
    )
    odometry_sigma_rad_per_m: float = Field(
        0.01, ge=0, description="Odometry heading noise growth per metre travelled, rad/m."
    )
    # self-calibrating odometry (stages/graph/calibration.py)
    odometry_calibration: bool | Literal["auto"] = Field(
        "auto",
        description="Estimate the odometry's systematic errors with the map: a distance scale, a yaw-rate scale and "
        "a yaw bias per metre (priors below); the odometry factors are corrected by the estimate. auto: solve "
        "without, then turn it on when the data reject uncalibrated odometry (the yaw components' Wald statistic, "
        "scaled by the odometry's own noise level, above calibration_test_threshold; the summary's "
        "odometry_calibration.decision says which and why).",
    )
    odometry_scale_sigma: float = Field(
        0.05, ge=0, description="Prior sigma of the odometry distance scale (relative; 0: not estimated)."
    )
    odometry_yaw_scale_sigma: float = Field(
        0.05, ge=0, description="Prior sigma of the odometry yaw-rate scale (relative; 0: not estimated)."
    )
    odometry_yaw_bias_sigma: float = Field(
        0.05, ge=0, description="Prior sigma of the odometry yaw bias per metre driven, rad/m (0: not estimated)."
    )
    noise_estimate: Literal["auto", "off", "odometry", "odometry_and_tags"] = Field(
        "auto",
        description="Scale the odometry (and tag) covariances until each group's whitened chi-square matches its "
        "redundancy (variance component estimation; planar odometry: one scale per dimension x, y, θ), for "
        "messages whose covariances are wrong, zero or absent. auto: odometry when the odometry calibration runs "
        "or when the odometry's noise comes from the settings (zero or absent message covariances), else off.",
    )
    calibration_test_threshold: float = Field(
        5.99,
        gt=0,
        description="odometry_calibration=auto turns the calibration on when the Wald statistic of the yaw-rate "
        "scale and yaw bias (one joint step from the uncalibrated solution, divided by the odometry's chi-square per "
        "redundancy with the calibration free) exceeds this (5.99: the 95 % point of chi-square with 2 degrees "
        "of freedom; a missed wheel error costs the map far more than a needless calibration, docs/graph.md).",
    )
    calibration_shift_max: float = Field(
        1.0,
        gt=0,
        description="When odometry_calibration=auto leaves the calibration off, warn (health check wheel_scale) if "
        "the test's joint step would move the landmarks by more than their own sigma: the mean over landmarks of "
        "the step's squared distance per position dimension against the uncalibrated marginals above this (1.0: "
        "one sigma; not fitted). A wheel distance error and a wrong tag size look alike to the data, so the map's "
        "scale is then doubtful (docs/graph.md). A large value turns the check off.",
    )
    calibration_test_max_poses: int = Field(
        20000,
        ge=0,
        description="odometry_calibration=auto skips its test (and leaves the calibration off, with a note) above "
        "this many keyframes. The test is linear in them: a 60-minute recording (17,890 keyframes) takes 11.7 s of "
        "a 53.5 s graph stage and 46 MiB more peak memory (836 MiB; docs/graph.md). Set odometry_calibration=true "
        "to estimate the calibration on a longer recording.",
    )
    calibration_max_iterations: int = Field(
        10, ge=1, description="Most outer iterations (solve, then update the calibration and noise scales)."
    )
    calibration_tolerance: float = Field(
        0.02,
        gt=0,
        description="Stop when the calibration moves less than this many sigmas and the noise scales by less than "
        "this fraction.",
    )
    # rigs
    rig_calibration: bool = Field(
        True,
        description="A camera of a rig with no mount (no transform in --extrinsics or on /tf_static) is estimated "
        "from the tags it sees at the same moments as a placed camera: one Pose3 shared by its sightings "
        "(graph/camera_poses.yaml). false: its detections are left out.",
    )
    # no odometry
    motion_prior: bool = Field(
        True, description="Without odometry, join consecutive keyframes with a weak zero-motion prior."
    )
    motion_prior_sigma_m: float = Field(
        1.0, gt=0, le=MAX_SIGMA_M, description="Zero-motion prior translation sigma, m."
    )
    motion_prior_sigma_rad: float = Field(1.0, gt=0, description="Zero-motion prior rotation sigma, rad.")
    # prior
    prior_sigma_m: float = Field(
        1e-3, gt=0, le=MAX_SIGMA_M, description="Prior on the first pose: translation sigma, m."
    )
    prior_sigma_rad: float = Field(1e-3, gt=0, description="Prior on the first pose: rotation sigma, rad.")
    # tags
    min_tag_observations: int = Field(
        1, ge=1, description="Tags seen fewer times than this are left out of the graph (listed in the summary)."
    )
    drop_ambiguous: bool = Field(True, description="Leave out detections that detect flagged as ambiguous.")
    max_reprojection_px: float = Field(
        5.0, gt=0, description="Leave out detections whose corner RMS reprojection error exceeds this, px."
    )
    tag_covariance_scale: float = Field(
        1.0, gt=0, description="Multiply the detections' 6x6 covariances by this (variance scale)."
    )
    tag_sigma_floor_m: float = Field(
        0.005, ge=0, le=MAX_SIGMA_M, description="Floor added to the tag position sigma in every direction, m."
    )
    tag_sigma_floor_rad: float = Field(
        0.005, ge=0, description="Floor added to the tag rotation sigma (3d model), rad."
    )
    tag_scale_sigma: float = Field(
        0.005,
        ge=0,
        description="Relative tolerance of the printed tag size (0.005 = 0.5 %, an ordinary print): one shared "
        "scale s ~ N(1, sigma^2) multiplies the range (planar) / translation (3d) of every tag measurement, so a "
        "tag printed slightly large or small, or any range bias shared by all detections, is estimated against "
        "the odometry and its uncertainty enters the marginals. 0: no scale variable, the tag size is taken as "
        "exact (faster native factors, overconfident landmark covariances when the ranges share a bias; see "
        "docs/graph.md).",
    )
    robust_kernel: Literal["none", "huber", "cauchy"] = Field("none", description="Robust kernel on the tag factors.")
    robust_threshold: float = Field(
        1.345, gt=0, description="Robust kernel threshold, in whitened residual units (sigmas)."
    )
    # optimiser
    optimizer: Literal["lm", "gn", "dogleg"] = Field(
        "lm", description="Levenberg-Marquardt (lm), Gauss-Newton (gn) or Dogleg (dogleg)."
    )
    max_iterations: int = Field(100, ge=1, description="Maximum optimiser iterations.")
    relative_error_tol: float = Field(1e-6, gt=0, description="Stop when the error falls by less than this fraction.")
    strict: bool = Field(
        False,
        description="Make a failed health check (stages/graph/health.py: chi2 per factor kind, tag scale, iteration "
        "cap, moved tags, dead reckoning) an error: the stage stops and its results are not kept (--strict).",
    )
    moved_tags: Literal["flag", "drop"] = Field(
        "flag",
        description="Tags whose measurements say they moved (the moved_tags health check): flag them with a warning, "
        "or drop them: the worst one's measurements are removed and the graph solved again, until none is flagged "
        "or max_dropped_tags are gone (each dropped tag is named in a warning and in the summary).",
    )
    max_dropped_tags: int = Field(5, ge=1, le=1000, description="moved_tags=drop: at most this many tags dropped.")
    # recording
    pose_ellipse_stride: int = Field(
        10, ge=1, description="Draw the covariance ellipse of every n-th pose in graph.rrd."
    )
