"""What evaluate writes into ``RUN/evaluate/``: one row per case, the case maps, their path risk, the report.

``cases.parquet`` (:data:`CASES`) is written from the rows :func:`stages.evaluate.cases.run_case` fills in, one
dict per case keyed by these columns; :func:`stages.evaluate.cases.cases_table` casts them to the declaration.
What evaluate reads comes from the declarations of the stages before it (``focused.json``, ``selection.json``,
optimize's ``kept.parquet`` and reduced graph).
"""

from __future__ import annotations

from typing import Final

import pyarrow as pa

from pipeline.contracts import ArtifactSet, Column, FileSpec, TableSpec
from stages.columns import STAMP_NS, TAG_ID, X, Y

_F64, _I64, _STR = pa.float64(), pa.int64(), pa.string()


def _f64(name: str, doc: str) -> Column:
    return Column(name, _F64, doc)


def _i64(name: str, doc: str) -> Column:
    return Column(name, _I64, doc)


# cases.parquet -----------------------------------------------------------------------------------------
CASE = Column("case", _STR, "the case: a Table I name (`optimal`, `focus_info`, …) or `landmark+measurement`")
LABEL = Column("label", _STR, "its label in the report (`focus, info`, …)")
LANDMARK_STRATEGY = Column("landmark_strategy", _STR, "the landmark-selection strategy of the case")
MEASUREMENT_STRATEGY = Column("measurement_strategy", _STR, "the measurement-selection strategy of the case")
LANDMARK_BUDGET = _i64("landmark_budget", "α (the number of landmarks for `all`)")
MEASUREMENT_BUDGET = _i64("measurement_budget", "K (null for `all`)")
OBSERVED_LANDMARKS = _i64("observed_landmarks", "landmarks with a kept measurement (the case's map)")
FOCUSED_LANDMARKS = _i64("focused_landmarks", "how many of the α collision-focused landmarks the case observes")
MEASUREMENTS = _i64("measurements", "kept tag measurements")
FOCUSED_ENTROPY = _f64(
    "focused_entropy", "entropy of the collision-focused landmarks, nats (unobserved ones with the weak prior)"
)
FOCUSED_ENTROPY_OBSERVED = _f64("focused_entropy_observed", "the same over the observed focused landmarks only")
ERROR_ALL_M = _f64("error_all_m", "mean planar error of every observed landmark, m")
FOCUSED_ERROR_M = _f64("focused_error_m", "mean planar error of the observed focused landmarks, m")
ERROR_REFERENCE = Column(
    "error_reference", _STR, "what the errors are against: the ground truth, else the `optimal` case's map"
)
MAX_COLLISION_PROBABILITY = _f64("max_collision_probability", "maximum collision probability along the path")
MEAN_COLLISION_PROBABILITY = _f64("mean_collision_probability", "mean collision probability along the path")
COLLISION_RATE = _f64("collision_rate", "share of the Monte Carlo navigation trials that collided (null: none run)")
COLLISION_CI_LOW = _f64("collision_ci_low", "95 % Wilson interval of the collision rate, low end")
COLLISION_CI_HIGH = _f64("collision_ci_high", "95 % Wilson interval of the collision rate, high end")
COLLISIONS = _i64("collisions", "trials that collided")
TRIALS = _i64("trials", "navigation trials run")
RMS_TRACKING_ERROR_M = _f64("rms_tracking_error_m", "RMS distance of the robots from the nominal path, m")
RMS_ESTIMATION_ERROR_M = _f64("rms_estimation_error_m", "RMS error of the EKF's position estimate, m")
LANDMARK_SELECTION_S = _f64("landmark_selection_s", "time of the landmark selection, s")
MEASUREMENT_SELECTION_S = _f64("measurement_selection_s", "time of the measurement selection, s")
SELECTION_S = _f64("selection_s", "the two together, s")
OPTIMISE_S = _f64("optimise_s", "time to build, solve and marginalise the reduced graph, s")
MAP_BYTES = _i64("map_bytes", "bytes of the landmarks and measurements the robot carries (float64)")
BYTES_FRACTION = _f64("bytes_fraction", "those bytes over the full graph's")
STATUS = Column("status", _STR, "the measurement selection's message (empty for `all`)")
# the consistency analysis (null without a ground truth or for a 3-D graph; docs/evaluate.md, "Why")
FOCUSED_ERROR_ALIGNED_M = _f64(
    "focused_error_aligned_m", "focused error after the best rigid planar motion onto the reference, m"
)
FOCUSED_SIGMA_M = _f64("focused_sigma_m", "mean marginal σ of the focused landmarks, m")
FOCUSED_NEES = _f64("focused_nees", "mean NEES eᵀΣ⁻¹e of the focused landmarks (2 if consistent)")
FOCUSED_OUTSIDE_95 = _f64("focused_outside_95", "share of the focused landmarks outside their 95 % bound")
KEPT_TAG_NEES = _f64("kept_tag_nees", "mean NEES of the kept tag measurements at the truth")
KEPT_RANGE_BIAS_M = _f64("kept_range_bias_m", "mean range residual of the kept tag measurements at the truth, m")
ORACLE_FOCUSED_ERROR_M = _f64(
    "oracle_focused_error_m", "focused error of the same selection with measurements drawn at the truth, m"
)
ORACLE_FOCUSED_ERROR_ALIGNED_M = _f64("oracle_focused_error_aligned_m", "the same after the rigid alignment, m")
ORACLE_FOCUSED_NEES = _f64("oracle_focused_nees", "focused NEES of the oracle re-solve")
ORACLE_ERROR_ALL_M = _f64("oracle_error_all_m", "error of every landmark of the oracle re-solve, m")
TIGHT_MARGIN_M = _f64("tight_margin_m", "at the tightest step (smallest margin / deviation): clearance − radius, m")
TIGHT_DEVIATION_M = _f64("tight_deviation_m", "there: RMS distance of the trials from the nominal pose, m")
TIGHT_EKF_SIGMA_M = _f64("tight_ekf_sigma_m", "there: the EKF's position σ, m")
MARGIN_SIGMAS = _f64("margin_sigmas", "there: margin over deviation")
MIN_MARGIN_M = _f64("min_margin_m", "smallest clearance − radius along the nominal path, m")
NAVIGATION_NEES = _f64(
    "navigation_nees",
    "mean NEES per degree of freedom of the trials' Schmidt filter (its error x̂ − x in the map frame, "
    "docs/evaluate.md); "
    "1 = consistent",
)
RISK_MARGIN_SIGMAS = _f64(
    "risk_margin_sigmas", "the risk model's smallest margin in σ along the path (z, P = Φ(−z); does not underflow)"
)
# the map against its own covariance (stages/evaluate/analysis.py, overconfidence)
FOCUSED_NEES_MAX = _f64(
    "focused_nees_max",
    "largest eᵀΣ⁻¹e of the observed focused landmarks against the reference (truth, else the `optimal` map), Σ the "
    "case's own marginal (null for `optimal` without a truth)",
)
FOCUSED_NEES_LIMIT = _f64(
    "focused_nees_limit", "the χ²₂ quantile at 1 − 0.001 / (landmarks tested) that it is held to (Bonferroni)"
)
OVERCONFIDENT = Column(
    "overconfident",
    pa.bool_(),
    "focused_nees_max above focused_nees_limit: a landmark is further off than the map's covariance allows",
)
# the entropy split and the risk model against the simulation (stages/evaluate/risk_check.py)
UNOBSERVED_FOCUSED = _i64(
    "unobserved_focused_landmarks", "collision-focused landmarks the case keeps no measurement of"
)
FOCUSED_ENTROPY_PRIOR = _f64(
    "focused_entropy_prior",
    "the part of `focused_entropy` set by the prior of the unobserved focused landmarks, nats "
    "(`focused_entropy` = `focused_entropy_observed` + this)",
)
PREDICTED_COLLISION_LOW = _f64(
    "predicted_collision_low", "the risk model's path collision probability, lower bound: max over keyframes of P"
)
PREDICTED_COLLISION_HIGH = _f64(
    "predicted_collision_high", "the same, upper (union) bound: min(1, sum over keyframes of P)"
)
RISK_DISAGREES = Column(
    "risk_disagrees",
    pa.bool_(),
    "the simulated collision rate's 95 % interval lies more than 10× outside [predicted_collision_low, "
    "predicted_collision_high] (null: no trials or no risk)",
)
CHECK_COLUMNS: Final = (
    UNOBSERVED_FOCUSED,
    FOCUSED_ENTROPY_PRIOR,
    PREDICTED_COLLISION_LOW,
    PREDICTED_COLLISION_HIGH,
    RISK_DISAGREES,
)
"""Columns filled after the cases ran (:func:`stages.evaluate.risk_check.check_columns`)."""

WHY_COLUMNS: Final = (
    FOCUSED_ERROR_ALIGNED_M,
    FOCUSED_SIGMA_M,
    FOCUSED_NEES,
    FOCUSED_OUTSIDE_95,
    KEPT_TAG_NEES,
    KEPT_RANGE_BIAS_M,
    ORACLE_FOCUSED_ERROR_M,
    ORACLE_FOCUSED_ERROR_ALIGNED_M,
    ORACLE_FOCUSED_NEES,
    ORACLE_ERROR_ALL_M,
)
"""Columns of the consistency analysis (null in cases.parquet without a ground truth)."""
MARGIN_COLUMNS: Final = (TIGHT_MARGIN_M, TIGHT_DEVIATION_M, TIGHT_EKF_SIGMA_M, MARGIN_SIGMAS, MIN_MARGIN_M)
"""Columns of the margin against the trials' deviation (null in cases.parquet without navigation)."""
CASES: Final = TableSpec(
    "cases.parquet",
    "one row per case (the six of Table I, then `evaluate.extra_pairs`)",
    [
        CASE,
        LABEL,
        LANDMARK_STRATEGY,
        MEASUREMENT_STRATEGY,
        LANDMARK_BUDGET,
        MEASUREMENT_BUDGET,
        OBSERVED_LANDMARKS,
        FOCUSED_LANDMARKS,
        MEASUREMENTS,
        FOCUSED_ENTROPY,
        FOCUSED_ENTROPY_OBSERVED,
        ERROR_ALL_M,
        FOCUSED_ERROR_M,
        ERROR_REFERENCE,
        MAX_COLLISION_PROBABILITY,
        MEAN_COLLISION_PROBABILITY,
        COLLISION_RATE,
        COLLISION_CI_LOW,
        COLLISION_CI_HIGH,
        COLLISIONS,
        TRIALS,
        RMS_TRACKING_ERROR_M,
        RMS_ESTIMATION_ERROR_M,
        LANDMARK_SELECTION_S,
        MEASUREMENT_SELECTION_S,
        SELECTION_S,
        OPTIMISE_S,
        MAP_BYTES,
        BYTES_FRACTION,
        STATUS,
        *WHY_COLUMNS,
        *MARGIN_COLUMNS,
        NAVIGATION_NEES,
        RISK_MARGIN_SIGMAS,
        FOCUSED_NEES_MAX,
        FOCUSED_NEES_LIMIT,
        OVERCONFIDENT,
        *CHECK_COLUMNS,
    ],
)

# maps.parquet ------------------------------------------------------------------------------------------
COVARIANCE = Column("covariance", pa.list_(_F64, 4), "marginal covariance of (x, y), 2×2 row-major, m²")
IN_CASE_FOCUS = Column("focused", pa.bool_(), "one of the case's own focused landmarks")
MAPS: Final = TableSpec(
    "maps.parquet",
    "per case, one row per landmark of its map",
    [
        CASE,
        TAG_ID,
        Column(X, _F64, "position x in the map frame, m"),
        Column(Y, _F64, "position y in the map frame, m"),
        COVARIANCE,
        IN_CASE_FOCUS,
    ],
)

# path_risk.parquet -------------------------------------------------------------------------------------
P_COLLISION = _f64("p_collision", "collision probability at the keyframe with the case's map")
PATH_RISK: Final = TableSpec(
    "path_risk.parquet", "per case, one row per keyframe of the full graph", [CASE, STAMP_NS, P_COLLISION]
)

# greedy.parquet ----------------------------------------------------------------------------------------
STEP = _i64("step", "picks so far (0: before the first)")
ENTROPY = _f64("entropy", "entropy of that selection's own focused landmarks after the step, nats")
GREEDY: Final = TableSpec("greedy.parquet", "per information case, one row per greedy step", [CASE, STEP, ENTROPY])

# realisations.parquet ----------------------------------------------------------------------------------
REALISATION = _i64("realisation", "index of the map realisation (its seeds: `evaluate.seed`, docs/evaluate.md)")
REALISATIONS: Final = TableSpec(
    "realisations.parquet",
    "one row per map realisation and case (the full graph's measurements redrawn; empty with "
    "`evaluate.realisations: 0`)",
    [REALISATION, CASE, COLLISION_RATE, COLLISIONS, TRIALS, FOCUSED_ENTROPY, FOCUSED_ERROR_M],
)

# the report --------------------------------------------------------------------------------------------
REPORT_MD = FileSpec(
    "report.md",
    "the full map's health checks (graph's failed ones as warning lines), Table I layout and extra columns, "
    "expectation checks, the Why analysis, figures",
)
REPORT_HTML = FileSpec("report.html", "the same with the figures embedded")
FIGURES: Final = tuple(
    FileSpec(name, what, optional=True)
    for name, what in (
        ("maps.png", "figure: every case's map with its ellipses (`evaluate.plots`)"),
        ("risk.png", "figure: collision probability along the path per case"),
        ("entropy.png", "figure: focused entropy per greedy step"),
        ("navigation.png", "figure: sample navigation trials per case (with trials)"),
        ("margin.png", "figure: clearance − radius along the path against 3 × the trials' RMS deviation"),
    )
)

ARTIFACTS: Final = ArtifactSet(
    "evaluate",
    "Every case of Mu et al. Table I (and other strategy pairs) on the run, scored on the same focused landmarks, "
    "with Monte Carlo navigation and a report.",
    [CASES, MAPS, PATH_RISK, GREEDY, REALISATIONS, REPORT_MD, REPORT_HTML, *FIGURES],
)
