"""Self-calibrating odometry: the systematic wheel errors and the odometry noise level, estimated with the map.

Real wheel odometry has systematic errors that its message covariances do not describe: a distance scale ``k_d``
(a wrong wheel radius: reported distance = ``k_d`` x driven), a yaw-rate scale ``k_w`` (a wrong track width:
reported turn = ``k_w`` x turned) and a yaw bias ``b`` per metre driven forwards (unequal wheel radii). And the
covariances themselves may be too small, too large, zero or absent. This module estimates both:

- **Calibration** ``c = (k_d, k_w, b)``, priors N(1, σ_d²), N(1, σ_w²), N(0, σ_b²). Each odometry factor's
  measured increment ``z`` (planar ``(x, y, θ)`` in the body frame of the first keyframe; 3d: its Pose3, whose
  planar part is corrected) becomes the corrected increment ``z(c)``: ``θ_c = (θ - b x / k_d) / k_w``, the
  translation divided by ``k_d`` and turned by ``(θ_c - θ) / 2`` (the chord of an arc turns with half the
  arc's angle). The graph stays native: the inner problem is the ordinary graph with the odometry rows at
  ``z(c)``. The outer problem is solved exactly by Gauss-Newton on ``c``: at the inner optimum the graph is
  linearised, each odometry factor gets the column ``-W J_f`` for ``c`` (``J_f = ∂ Log(z(c₀)⁻¹ z(c)) / ∂c``,
  ``W`` the factor's whitening) and the prior's rows are added; solving that joint linear system gives the
  step ``δc`` (and ``δx``) of a Gauss-Newton step on poses, landmarks and ``c`` together. At convergence
  ``δc = 0`` is the joint least-squares optimum, and the marginals of the same joint system contain the
  calibration's uncertainty.
- **Noise level** (variance component estimation, Förstner): the odometry covariances are multiplied by one
  factor ``λ``, updated as ``λ ← λ · χ²_odo / r_odo`` until it settles, where ``χ²_odo`` is the odometry factors'
  whitened squared error at the optimum and ``r_odo = Σ_f (dim_f - tr(W_f A_f Σ_f A_fᵀ W_fᵀ))`` their redundancy
  (``A_f`` the factor's Jacobian, ``Σ_f`` the joint marginal of its variables): ``E[χ²] = r`` for a correct
  noise model. The tag factors' ``χ²_tag / r_tag`` is reported (``r_tag``: the total redundancy ``m - n`` minus
  the other groups'), and applied too when ``graph.noise_estimate`` is ``odometry_and_tags``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import gtsam
import numpy as np

from stages.geometry import pose3_from_vector, pose3_to_vector
from stages.graph import se2
from stages.graph.config import GraphConfig
from stages.graph.consider import OdometryCalibration
from stages.graph.factors import FactorRow, build_graph
from stages.graph.marginals import factor_row_starts, hat_trace, selected_inverse, whitened_system
from stages.graph.problem import GraphProblem
from stages.graph.solve import Solution, optimise

CALIBRATION_KEY = int(gtsam.symbol("c", 0))
"""Key of the odometry calibration ``(k_d, k_w, b)`` in the joint linear system (never in the graph's values)."""
PARAMETERS = ("distance_scale", "yaw_rate_scale", "yaw_bias_rad_per_m")
"""Names of the calibration's components, in order (the simulator's ``odometry_errors`` use the same)."""
_STEP = 1e-6
"""Finite-difference step of the correction's Jacobian."""
_CAL_STEP = 1e-5
"""Finite-difference step in the calibration for the whitened residual's Jacobian."""
LAMBDA_BOUNDS = (1e-3, 1e4)
"""The odometry (and tag) covariance scale stays within these bounds."""


@dataclass
class CalibrationResult:
    """What :func:`calibrate` found: the corrected problem, its solution and marginals, and the summary block."""

    problem: GraphProblem
    graph: gtsam.NonlinearFactorGraph
    solution: Solution
    marginals: dict[int, np.ndarray]
    summary: dict[str, Any]
    calibration: OdometryCalibration
    """The estimate, its covariance and each corrected factor's Jacobian for it (``calibration.npz``)."""


def _has_odometry(problem: GraphProblem) -> bool:
    return problem.info.get("odometry_noise") in ("messages", "settings")


def applies(problem: GraphProblem, cfg: GraphConfig) -> bool:
    """Whether the stage calibrates this problem unconditionally: built from a recording's odometry, and asked to
    (``odometry_calibration: true`` or an explicit ``noise_estimate``)."""
    wanted = cfg.odometry_calibration is True or cfg.noise_estimate in ("odometry", "odometry_and_tags")
    return wanted and _has_odometry(problem)


def tested(problem: GraphProblem, cfg: GraphConfig) -> bool:
    """Whether the stage decides from the data (``odometry_calibration: auto``, see :func:`calibration_test`)."""
    return cfg.odometry_calibration == "auto" and _has_odometry(problem) and not applies(problem, cfg)


def resolved(cfg: GraphConfig, calibration: bool) -> GraphConfig:
    """The settings with the calibration on or off and ``noise_estimate: auto`` made explicit (odometry when the
    calibration runs, else off).

    Not the tags' level too (``odometry_and_tags``): on simulated worlds with wheel errors it brings the landmarks'
    mean NEES/2 from 0.66 to 0.88 but makes the map's shape overconfident (joint NEES of all landmarks 0.40-0.67 ->
    1.9-9.5), because detect's errors are partly per tag (they do not average down, and the tag's own estimate
    absorbs them, so the residuals understate them); docs/graph.md, bench_odometry.py."""
    noise = cfg.noise_estimate
    if noise == "auto":
        noise = "odometry" if calibration else "off"
    return cfg.model_copy(update={"odometry_calibration": calibration, "noise_estimate": noise})


def calibration_test(
    problem: GraphProblem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, cfg: GraphConfig
) -> tuple[dict[str, Any], dict[int, np.ndarray]]:
    """Do the data reject uncalibrated odometry? The ``decision`` block of ``odometry_calibration: auto`` (not
    tested, ``skipped``, above ``calibration_test_max_poses`` keyframes), and the
    joint step of every landmark (its tangent vector, by key; empty when skipped) for :func:`map_shift`.

    At the uncalibrated solution the graph is linearised with the calibration as one more variable (its priors
    as configured), exactly the first round of :func:`calibrate`. Its Gauss-Newton step ``δc`` and covariance
    ``Σ_c`` give the Wald statistic ``W = δcᵀ Σ_c⁻¹ δc`` of the yaw-rate scale and the yaw bias: χ² with 2 degrees
    of freedom when the odometry has no such error and its covariances are right. Covariances that are wrong by a
    common factor scale ``W`` by its inverse, so ``W`` is divided by the odometry's own variance factor
    ``χ²/redundancy`` with the calibration free (after the joint step, the larger model's residuals, as in the
    F-test of added parameters; before it the systematic error itself would inflate the factor and hide itself).
    The distance scale is left out of the test: it and the shared tag scale are one degree of freedom, so the data
    cannot tell a long wheel from a small tag (the ``tag_scale`` health check reports that case); once the
    calibration is on it is estimated with the rest.
    """
    if len(problem.pose_keys) > cfg.calibration_test_max_poses:
        return {
            "setting": "auto",
            "applied": False,
            "rejected": False,
            "skipped": True,
            "reason": f"not tested: {len(problem.pose_keys)} keyframes > graph.calibration_test_max_poses="
            f"{cfg.calibration_test_max_poses}; set "
            "graph.odometry_calibration=true to estimate wheel errors on this recording",
        }, {}
    t0 = time.perf_counter()
    on = resolved(cfg, True)
    base = list(problem.rows)
    odo = [i for i, r in enumerate(base) if r.kind == "odometry"]
    tags = [i for i, r in enumerate(base) if r.kind == "tag"]
    prior_mean, prior_sigma = _prior(on)
    state = _State(prior_mean.copy(), _unit_noise(problem.model), 1.0)
    joint, _ = _joint_system(problem, graph, values, odo, state, prior_mean, prior_sigma, base)
    delta = joint.optimize()
    dc = np.asarray(delta.at(CALIBRATION_KEY), dtype=float)
    cov_c = np.asarray(gtsam.Marginals(joint, delta).marginalCovariance(CALIBRATION_KEY))
    stats = _noise_statistics(problem, joint, delta, odo, tags)
    free = [i for i in (1, 2) if prior_sigma[i] > 1e-8]
    wald = float(dc[free] @ np.linalg.solve(cov_c[np.ix_(free, free)], dc[free])) if free else 0.0
    r_odo = float(stats["odometry_redundancy"])
    ratio = float(stats["odometry_chi2_after_step"]) / r_odo if r_odo > 0 else 1.0
    statistic = wald / max(ratio, 1e-12)
    sig = np.sqrt(np.diag(cov_c))
    step = ", ".join(f"{PARAMETERS[i]} {prior_mean[i] + dc[i]:+.4f} ± {sig[i]:.4f}" for i in free)
    rejected = implausible(prior_mean + dc, on) if statistic > cfg.calibration_test_threshold else None
    applied = statistic > cfg.calibration_test_threshold and rejected is None
    if rejected is not None:
        reason = (
            f"the odometry and the tags disagree, but not as wheels do: the yaw calibration's statistic is "
            f"{statistic:.1f} (> {cfg.calibration_test_threshold:g}) and {rejected}; the calibration was not applied "
            "(a tag that moved or two tags with one id, or broken odometry, would do this: see the other checks)"
        )
    elif applied:
        reason = (
            f"the odometry has systematic errors: the yaw calibration's statistic is {statistic:.1f} "
            f"(> {cfg.calibration_test_threshold:g}; {step}), so the distance scale, yaw-rate scale and yaw bias "
            "were estimated with the map"
        )
    else:
        reason = (
            f"no systematic odometry error found: the yaw calibration's statistic is {statistic:.1f} "
            f"(<= {cfg.calibration_test_threshold:g}; {step})"
        )
    steps = {k: np.asarray(delta.at(k), dtype=float) for k in problem.landmark_keys.values() if delta.exists(k)}
    return {
        "setting": "auto",
        "applied": bool(applied),
        "rejected": rejected is not None,
        "reason": reason,
        "statistic": statistic,
        "wald": wald,
        "odometry_chi2_per_redundancy": ratio,
        "threshold": float(cfg.calibration_test_threshold),
        "step": {PARAMETERS[i]: float(prior_mean[i] + dc[i]) for i in range(3)},
        "sigma": {PARAMETERS[i]: float(sig[i]) for i in range(3)},
        "seconds": round(time.perf_counter() - t0, 4),
    }, steps


def map_shift(
    problem: GraphProblem, values: gtsam.Values, marginals: dict[int, np.ndarray], steps: dict[int, np.ndarray]
) -> tuple[dict[str, Any], dict[int, np.ndarray]]:
    """How far the calibration test's joint step would move the landmarks, against the uncalibrated map's own
    marginals: per landmark ``d² = δpᵀ Σ_p⁻¹ δp / n`` over its ``n`` position dimensions (``δp`` the map-frame
    position change of its step, ``Σ_p`` its position covariance); their mean (the NEES per dimension of the
    uncalibrated map against the calibrated one), median and largest, and the median and largest shift; and each
    landmark's map-frame move ``δp`` (x, y, z; by key), for the recording.

    The Wald statistic asks whether the data reject error-free wheels; this asks whether the uncalibrated map's
    covariances would cover the correction if the wheels had the errors the data point to (docs/graph.md)."""
    d2, metres = [], []
    moves: dict[int, np.ndarray] = {}
    for key in problem.landmark_keys.values():
        if key not in steps or key not in marginals:
            continue
        kind = problem.kind(key)
        J = kind.position_jacobian(kind.read(values, key))
        rows = np.flatnonzero(np.abs(J).sum(axis=1) > 0)  # the 2D kinds have no height
        move = J @ steps[key]
        dp = move[rows]
        C = J[rows] @ marginals[key] @ J[rows].T
        try:
            d2.append(float(dp @ np.linalg.solve(C, dp)) / len(rows))
        except np.linalg.LinAlgError:
            continue
        metres.append(float(np.linalg.norm(dp)))
        moves[key] = move
    if not d2:
        return {"landmarks": 0}, moves
    return {
        "landmarks": len(d2),
        "mean_d2_per_dim": float(np.mean(d2)),
        "median_d2_per_dim": float(np.median(d2)),
        "max_d2_per_dim": float(np.max(d2)),
        "median_shift_m": float(np.median(metres)),
        "max_shift_m": float(np.max(metres)),
    }, moves


SHIFT_STEP_SIGMAS = 1.0
"""The ``wheel_scale`` check also asks that the distance scale of the test's step be this many of its σ from 1: a
step within its own noise moves a precise map by about its σ by chance (a world without wheel errors: mean ``d²``
1.02 with the step at 0.64 σ; those with mild wheel errors: 1.6-2.2 σ, docs/graph.md)."""


def shift_warning(decision: dict[str, Any], cfg: GraphConfig) -> str | None:
    """The ``wheel_scale`` health check's line (None when it passes): ``auto`` left the calibration off, but the
    test's joint step would move the landmarks by more than ``graph.calibration_shift_max`` of their own σ (mean
    ``d²`` per dimension, :func:`map_shift`), and its distance scale is more than :data:`SHIFT_STEP_SIGMAS` of its σ
    from 1. The map's accuracy then rests on wheels without error, which the data cannot confirm: most of the shift
    is the distance scale's, one degree of freedom with the tag size, so a long wheel and a small tag print look
    alike and neither setting can be chosen from the data (docs/graph.md)."""
    shift = decision.get("map_shift") or {}
    mean = shift.get("mean_d2_per_dim")
    if decision.get("applied") or decision.get("rejected") or mean is None or mean <= cfg.calibration_shift_max:
        return None
    k_d = decision["step"]["distance_scale"]
    sigma = decision["sigma"]["distance_scale"]
    if abs(k_d - 1.0) <= SHIFT_STEP_SIGMAS * sigma:
        return None  # the step's own noise: it moves a precise map by chance, not because the data point anywhere
    return (
        f"the map's scale rests on the wheels: calibrating them would move the landmarks by {math.sqrt(mean):.1f} "
        f"of their sigma (root mean square; median {100 * shift['median_shift_m']:.1f} cm), though the yaw test did "
        f"not call for it ({decision['statistic']:.1f} <= {decision['threshold']:g}); a wheel distance scale of "
        f"{k_d:.4f} ± {sigma:.4f} and a tag size {100 * abs(k_d - 1):.1f} % off explain the data alike. Check "
        "detect.tag_size_m against a printed tag, then set graph.odometry_calibration=true if the wheels may be "
        "off (false accepts them as they are)"
    )


PLAUSIBLE_SIGMAS = 5.0
"""A calibration further than this many prior sigmas from its prior mean is not a wheel's error."""


def implausible(c: np.ndarray, cfg: GraphConfig) -> str | None:
    """Why the calibration ``c = (k_d, k_w, b)`` is not a wheel's systematic error (None when it may be one): a
    component further than :data:`PLAUSIBLE_SIGMAS` of its prior sigma (``graph.odometry_*_sigma``) from the prior
    mean, or a scale that is not positive. Odometry that disagrees with the tags that much (a yaw-rate scale of −0.4)
    is a fault elsewhere, which the calibration would hide by bending the odometry to fit it."""
    mean, sigma = _prior(cfg)
    far = []
    for i in range(3):
        z = abs(float(c[i]) - mean[i]) / sigma[i] if sigma[i] > 1e-8 else 0.0
        if z > PLAUSIBLE_SIGMAS or (i < 2 and c[i] <= 0):
            far.append(f"{PARAMETERS[i]} {float(c[i]):+.3f} is {z:.0f} prior sigmas from {mean[i]:g}")
    return "; ".join(far) if far else None


def corrected_increment(m: np.ndarray, c: np.ndarray, model: str) -> np.ndarray:
    """The odometry measurement ``m`` (a row's layout) corrected by the calibration ``c = (k_d, k_w, b)``."""
    if model == "planar":
        return _planar_increments(np.asarray(m[:3], dtype=float)[None], c)[0]
    pose = pose3_from_vector(m)
    t = np.asarray(pose.translation())
    th = float(pose.rotation().yaw())
    xc, yc, th_c = _planar_increments(np.array([[t[0], t[1], th]], dtype=float), c)[0]
    t_c = np.array([xc, yc, float(t[2]) / float(c[0])])
    R_c = gtsam.Rot3.Yaw(th_c - th).compose(pose.rotation())
    return pose3_to_vector(gtsam.Pose3(R_c, t_c))


def _local(model: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Log(a⁻¹ b)`` of two measurements in the factor's tangent order."""
    if model == "planar":
        return np.asarray(gtsam.Pose2.Logmap(gtsam.Pose2(*a).between(gtsam.Pose2(*b))))
    return np.asarray(gtsam.Pose3.Logmap(pose3_from_vector(a).between(pose3_from_vector(b))))


def correction_jacobian(m: np.ndarray, c: np.ndarray, model: str) -> np.ndarray:
    """``∂ Log(z(c)⁻¹ z(c + δ)) / ∂δ`` at ``δ = 0`` (dim x 3), by central differences."""
    cols = []
    for p in range(3):
        d = np.zeros(3)
        d[p] = _STEP
        lo, hi = corrected_increment(m, c - d, model), corrected_increment(m, c + d, model)
        cols.append(_local(model, lo, hi) / (2 * _STEP))
    return np.column_stack(cols)


def corrected_factor(m: np.ndarray, cov: np.ndarray, c: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """The corrected increment and its covariance ``G Σ Gᵀ`` (``G = ∂z(c)/∂m`` in the tangent, by central
    differences): the noise stays that of the measured increment. Correcting the increment but keeping ``Σ``
    would shrink the noise of a shortened increment with it, and least squares would then favour a larger
    ``k_d`` and ``k_w`` (measured on the sample: +0.55 % and +0.69 %, 2 σ, where the truth is 1)."""
    z = corrected_increment(m, c, model)
    d = len(cov)
    G = np.zeros((d, d))
    for p in range(d):
        dp = np.zeros(d)
        dp[p] = _STEP
        hi = corrected_increment(_retract(model, m, dp), c, model)
        lo = corrected_increment(_retract(model, m, -dp), c, model)
        G[:, p] = _local(model, lo, hi) / (2 * _STEP)
    C = G @ np.asarray(cov, dtype=float) @ G.T
    return z, 0.5 * (C + C.T)


def _retract(model: str, m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``m ⊕ d`` (right perturbation) in the row layout."""
    if model == "planar":
        q = gtsam.Pose2(*m).retract(d)
        return np.array([q.x(), q.y(), q.theta()])
    return pose3_to_vector(pose3_from_vector(m).retract(d))


def _whitened_residual(
    model: str, m: np.ndarray, cov: np.ndarray, c: np.ndarray, pred: Any, lam: np.ndarray | None = None
) -> np.ndarray:
    """The whitened error of a corrected odometry factor at calibration ``c`` for the predicted increment (the
    corrected covariance scaled by ``lam``, :func:`_scaled`; None: as it is)."""
    z, C = corrected_factor(m, cov, c, model)
    C = C if lam is None else _scaled(C, lam)
    zp = gtsam.Pose2(*z) if model == "planar" else pose3_from_vector(z)
    return _whitening(C) @ np.asarray(zp.localCoordinates(pred))


def _whitening(cov: np.ndarray) -> np.ndarray:
    """The square-root information GTSAM whitens a factor of this covariance with."""
    C = np.asarray(cov, dtype=float)
    return np.asarray(gtsam.noiseModel.Gaussian.Covariance(0.5 * (C + C.T)).R())


def _planar_increments(M: np.ndarray, c: np.ndarray) -> np.ndarray:
    """:func:`corrected_increment` of every planar measurement (rows of ``M``) at once."""
    k_d, k_w, b = (float(v) for v in c)
    x, y, th = M[:, 0], M[:, 1], M[:, 2]
    th_c = (th - b * x / k_d) / k_w
    half = 0.5 * (th_c - th)
    ch, sh = np.cos(half), np.sin(half)
    return np.column_stack([(ch * x - sh * y) / k_d, (sh * x + ch * y) / k_d, th_c])


def planar_corrected_factors(M: np.ndarray, covs: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`corrected_factor` of every planar measurement at once: ``(N, 3)`` increments, ``(N, 3, 3)``
    covariances (the same central differences, in :mod:`stages.graph.se2`'s batched ``Pose2`` operations)."""
    Z = _planar_increments(M, c)
    G = np.empty((len(M), 3, 3))
    for p in range(3):
        d = np.zeros((len(M), 3))
        d[:, p] = _STEP
        hi = _planar_increments(se2.retract(M, d), c)
        lo = _planar_increments(se2.retract(M, -d), c)
        G[:, :, p] = se2.local(lo, hi) / (2 * _STEP)
    C = G @ covs @ G.transpose(0, 2, 1)
    return Z, 0.5 * (C + C.transpose(0, 2, 1))


def _planar_whitened_residuals(
    M: np.ndarray, covs: np.ndarray, c: np.ndarray, pred: np.ndarray, lam: np.ndarray
) -> np.ndarray:
    """:func:`_whitened_residual` of every planar factor at once (``pred``: the predicted increments, ``(N, 3)``);
    the whitening is GTSAM's, the upper Cholesky factor of the information."""
    Z, C = planar_corrected_factors(M, covs, c)
    C = _scaled(C, lam)
    R = np.linalg.cholesky(np.linalg.inv(C)).transpose(0, 2, 1)
    return np.einsum("nij,nj->ni", R, se2.local(Z, pred))


@dataclass
class _State:
    c: np.ndarray
    lam_odo: np.ndarray
    """The odometry covariances' scale: planar, one per dimension (x, y, θ; ``D Σ D`` with ``D = diag(√λ)``); 3d,
    one for all (shape (1,))."""
    lam_tag: float


def _unit_noise(model: str) -> np.ndarray:
    """The odometry scale that leaves the covariances as they are."""
    return np.ones(3 if model == "planar" else 1)


def _scaled(cov: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Covariance(s) ``(..., d, d)`` scaled by ``lam``: one number for all, or ``D Σ D``, ``D = diag(√lam)``."""
    if len(lam) == 1:
        return float(lam[0]) * cov
    root = np.sqrt(lam)
    return cov * root[:, None] * root[None, :]


def _rows_at(
    problem: GraphProblem, base: list[FactorRow], odo: list[int], tags: list[int], s: _State
) -> list[FactorRow]:
    """The problem's rows with the odometry corrected by ``s.c`` and the covariances scaled."""
    rows = list(base)
    if problem.model == "planar" and odo:
        M = np.array([base[i].measurement[:3] for i in odo], dtype=float)
        Z, C = planar_corrected_factors(M, np.array([base[i].covariance for i in odo], dtype=float), s.c)
        for i, z, cov in zip(odo, Z, _scaled(C, s.lam_odo), strict=True):
            rows[i] = replace(base[i], measurement=z, covariance=cov)
    else:
        for i in odo:
            r = base[i]
            z, cov = corrected_factor(r.measurement, r.covariance, s.c, problem.model)
            rows[i] = replace(r, measurement=z, covariance=_scaled(cov, s.lam_odo))
    if s.lam_tag != 1.0:
        for i in tags:
            rows[i] = replace(base[i], covariance=s.lam_tag * base[i].covariance)
    return rows


def _joint_system(
    problem: GraphProblem,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    odo: list[int],
    s: _State,
    prior_mean: np.ndarray,
    prior_sigma: np.ndarray,
    base: list[FactorRow],
) -> tuple[gtsam.GaussianFactorGraph, dict[int, np.ndarray]]:
    """The graph linearised at ``values`` with the calibration as one more variable (see the module docstring).

    Returns the joint system and, per odometry factor index, its whitened Jacobian for ``c``.
    """
    lin = graph.linearize(values)
    odo_set = set(odo)
    joint = gtsam.GaussianFactorGraph()
    a_c = _planar_calibration_columns(problem, lin, values, odo, s, base) if problem.model == "planar" else {}
    for i in range(lin.size()):
        f = lin.at(i)
        if i not in odo_set:
            joint.push_back(f)
            continue
        row = problem.rows[i]
        A, b = f.jacobian()
        keys = list(f.keys())
        if i not in a_c:
            pred = values.atPose3(keys[0]).between(values.atPose3(keys[1]))
            a_c[i] = _calibration_columns(
                partial(_pose3_residual, problem.model, base[i].measurement, base[i].covariance, pred, s.lam_odo), s.c
            )
        d = row.dim
        unit = gtsam.noiseModel.Unit.Create(d)
        k1, k2 = keys
        joint.push_back(gtsam.JacobianFactor(k1, A[:, :d], k2, A[:, d:], CALIBRATION_KEY, a_c[i], b, unit))
    A0 = np.diag(1.0 / prior_sigma)
    joint.push_back(
        gtsam.JacobianFactor(CALIBRATION_KEY, A0, (prior_mean - s.c) / prior_sigma, gtsam.noiseModel.Unit.Create(3))
    )
    return joint, a_c


def _planar_calibration_columns(
    problem: GraphProblem,
    lin: gtsam.GaussianFactorGraph,
    values: gtsam.Values,
    odo: list[int],
    s: _State,
    base: list[FactorRow],
) -> dict[int, np.ndarray]:
    """Every planar odometry factor's whitened Jacobian for ``c`` at once (central differences of
    :func:`_planar_whitened_residuals`), by factor index."""
    if not odo:
        return {}
    keys = [list(lin.at(i).keys()) for i in odo]
    at = {k: i for i, k in enumerate(sorted({k for pair in keys for k in pair}))}
    poses = np.array([[p.x(), p.y(), p.theta()] for p in (values.atPose2(k) for k in at)])
    pred = se2.between(poses[[at[k1] for k1, _ in keys]], poses[[at[k2] for _, k2 in keys]])
    M = np.array([base[i].measurement[:3] for i in odo], dtype=float)
    covs = np.array([base[i].covariance for i in odo], dtype=float)
    cols = _calibration_columns(lambda c: _planar_whitened_residuals(M, covs, c, pred, s.lam_odo), s.c)
    return dict(zip(odo, cols, strict=True))


def _pose3_residual(
    model: str, m: np.ndarray, cov: np.ndarray, pred: Any, lam: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """:func:`_whitened_residual` with the calibration last, for :func:`_calibration_columns`."""
    return _whitened_residual(model, m, cov, c, pred, lam)


def _calibration_columns(residual: Callable[[np.ndarray], np.ndarray], c: np.ndarray) -> np.ndarray:
    """``∂ residual / ∂c`` at ``c`` by central differences (step ``_CAL_STEP``), one column per component of ``c``,
    stacked on a last axis: ``(d, 3)`` for one factor's residual, ``(N, d, 3)`` for a batch's."""
    cols = []
    for p in range(3):
        dp = np.zeros(3)
        dp[p] = _CAL_STEP
        cols.append((residual(c + dp) - residual(c - dp)) / (2 * _CAL_STEP))
    return np.stack(cols, axis=-1)


def _prior(cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
    """Prior mean and sigma of ``(k_d, k_w, b)``; a component that is not estimated gets a near-zero sigma."""
    tiny = 1e-9
    if not cfg.odometry_calibration:
        return np.array([1.0, 1.0, 0.0]), np.full(3, tiny)
    sig = np.array([cfg.odometry_scale_sigma, cfg.odometry_yaw_scale_sigma, cfg.odometry_yaw_bias_sigma])
    return np.array([1.0, 1.0, 0.0]), np.where(sig > 0, sig, tiny)


def calibrate(problem: GraphProblem, cfg: GraphConfig, initial: gtsam.Values | None = None) -> CalibrationResult:
    """Estimate the odometry calibration and noise level with the map (see the module docstring).

    The returned problem has the odometry rows at the corrected increments and the scaled covariances, so its
    ``factors.parquet`` rebuilds the final graph; the marginals come from the joint system and so include the
    calibration's uncertainty. ``odometry_calibration: auto`` counts as on here (the stage calls this for auto only
    when :func:`calibration_test` says so); ``initial`` (default: the problem's) starts the first solve.
    """
    t0 = time.perf_counter()
    cfg = resolved(cfg, cfg.odometry_calibration is not False)
    base = list(problem.rows)
    odo = [i for i, r in enumerate(base) if r.kind == "odometry"]
    tags = [i for i, r in enumerate(base) if r.kind == "tag"]
    prior_mean, prior_sigma = _prior(cfg)
    s = _State(prior_mean.copy(), _unit_noise(problem.model), 1.0)
    estimate_noise = cfg.noise_estimate != "off"
    initial = problem.initial if initial is None else initial
    first_error: float | None = None
    iterations = inner_iterations = 0
    history: list[dict[str, Any]] = []
    while True:
        iterations += 1
        current = replace(problem, rows=_rows_at(problem, base, odo, tags, s), initial=initial)
        graph = build_graph(current.rows)
        sol = optimise(current, graph, cfg.optimizer, cfg.max_iterations, cfg.relative_error_tol)
        inner_iterations += sol.iterations
        if first_error is None:
            first_error = sol.initial_error
        joint, a_c = _joint_system(current, graph, sol.values, odo, s, prior_mean, prior_sigma, base)
        delta = joint.optimize()
        dc = np.asarray(delta.at(CALIBRATION_KEY), dtype=float)
        marg = gtsam.Marginals(joint, delta)
        cov_c = np.asarray(marg.marginalCovariance(CALIBRATION_KEY))
        sig_c = np.sqrt(np.diag(cov_c))
        stats = _noise_statistics(current, joint, delta, odo, tags) if estimate_noise else {}
        history.append({"c": s.c.tolist(), "dc": dc.tolist(), **{k: v for k, v in stats.items() if k != "groups"}})
        new = _State(s.c + dc, s.lam_odo, s.lam_tag)
        if estimate_noise:
            new.lam_odo = _next_noise(s.lam_odo, stats)
            if cfg.noise_estimate == "odometry_and_tags":
                new.lam_tag = _clip(s.lam_tag * stats["tag_ratio"])
        step_sigmas = float(np.max(np.abs(dc) / np.maximum(sig_c, 1e-12)))
        noise_change = (
            max(float(np.max(np.abs(np.log(new.lam_odo / s.lam_odo)))), abs(math.log(new.lam_tag / s.lam_tag)))
            if estimate_noise
            else 0.0
        )
        history[-1].update(step_sigmas=step_sigmas, noise_scale_change=noise_change)
        settled = step_sigmas <= cfg.calibration_tolerance and noise_change < cfg.calibration_tolerance
        if settled or iterations >= cfg.calibration_max_iterations:
            break
        s = new
        initial = sol.values
    # the last solve is at ``s``; the last step was within the tolerance (or the cap was hit): report ``s``
    keys = list(current.var_types)
    marginals = {k: np.asarray(marg.marginalCovariance(k), dtype=float) for k in keys}
    summary = _summary(cfg, s, sig_c, cov_c, prior_sigma, stats, iterations, inner_iterations, history, settled)
    summary["seconds"] = round(time.perf_counter() - t0, 4)
    solution = Solution(
        sol.values,
        float(first_error),
        sol.final_error,
        inner_iterations,
        sol.optimizer,
        time.perf_counter() - t0,
    )
    dim = 3 if problem.model == "planar" else 6
    jacobian = np.zeros((len(odo), dim, 3))
    for n, i in enumerate(odo):
        jacobian[n] = np.linalg.solve(_whitening(current.rows[i].covariance), a_c[i])
    calibration = OdometryCalibration(s.c.copy(), cov_c, np.asarray(odo, dtype=np.int64), jacobian)
    return CalibrationResult(current, graph, solution, marginals, summary, calibration)


def _clip(lam: float) -> float:
    return float(min(max(lam, LAMBDA_BOUNDS[0]), LAMBDA_BOUNDS[1]))


MIN_REDUNDANCY_PER_DIMENSION = 10.0
"""A dimension's own noise level needs this much redundancy (its relative σ is √(2/r), 45 % at 10); below it the
dimension follows the odometry's pooled ratio."""


def _next_noise(lam: np.ndarray, stats: dict[str, Any]) -> np.ndarray:
    """Förstner's update of the odometry's noise level, ``λ ← λ χ² / r``: per dimension where the odometry has one
    level per dimension (planar), from each dimension's whitened residuals and their redundancy, so that the
    settings' or the messages' *shape* is corrected too (translation against heading: one factor for all made the
    heading overconfident where the lateral noise was stated far too large); else one for all."""
    pooled = float(stats["odometry_ratio"])
    if len(lam) == 1:
        return np.array([_clip(float(lam[0]) * pooled)])
    chi, red = stats["odometry_chi2_by_dimension"], stats["odometry_redundancy_by_dimension"]
    if len(chi) != len(lam):  # no odometry factor to tell the dimensions apart
        return np.array([_clip(float(v) * pooled) for v in lam])
    ratio = [c / r if r >= MIN_REDUNDANCY_PER_DIMENSION else pooled for c, r in zip(chi, red, strict=True)]
    return np.array([_clip(float(v) * q) for v, q in zip(lam, ratio, strict=True)])


def _noise_statistics(
    problem: GraphProblem,
    joint: gtsam.GaussianFactorGraph,
    delta: gtsam.VectorValues,
    odo: list[int],
    tags: list[int],
) -> dict[str, Any]:
    """Whitened χ², redundancy and the calibration's covariance at the optimum (see the module docstring).

    The joint system's whitened Jacobian ``J`` (factor rows in graph order, the calibration's prior last) gives
    ``H = JᵀJ``; the odometry rows' part of ``tr(J H⁻¹ Jᵀ)`` needs ``H⁻¹`` only on the blocks of each odometry
    factor's keys (:func:`stages.graph.marginals.selected_inverse`, linear in the keyframes; solves with those rows
    as right-hand sides were quadratic), and the tag rows' part is the rest of ``tr(H⁻¹ H) = n``. ``delta`` is the
    joint system's Gauss-Newton step (``joint.optimize()``, which the caller has), for the χ² after it.
    """
    J, b = whitened_system(joint)
    n = J.shape[1]
    starts = factor_row_starts([r.dim for r in problem.rows] + [3])

    def rows_of(idx: list[int]) -> np.ndarray:
        return np.concatenate([np.arange(starts[i], starts[i + 1]) for i in idx]) if idx else np.zeros(0, int)

    odo_rows, tag_rows = rows_of(odo), rows_of(tags)
    other = sorted(set(range(joint.size())) - set(odo) - set(tags))  # priors, the calibration's prior last
    other_rows = rows_of(other)
    # each row's leverage J_r H⁻¹ J_rᵀ needs H⁻¹ on its own factor's keys only: the selected inverse
    dims = {k: 3 if k == CALIBRATION_KEY else problem.kind(k).dim for k in map(int, joint.keyVector())}
    groups = [list(joint.at(i).keys()) for i in odo + other]
    Z = selected_inverse(joint, dims, groups, last=list(problem.landmark_keys.values()))

    tr_odo, tr_other = hat_trace(J, Z, odo_rows), hat_trace(J, Z, other_rows)
    # the same per dimension of the odometry's residual (whitened component d of each odometry factor)
    odo_dim = problem.rows[odo[0]].dim if odo else 0
    by_dim = [np.array([starts[i] + d for i in odo], dtype=int) for d in range(odo_dim)]
    r_odo = len(odo_rows) - tr_odo
    r_tag = len(tag_rows) - (n - tr_odo - tr_other)
    chi_odo, chi_tag = float(b[odo_rows] @ b[odo_rows]), float(b[tag_rows] @ b[tag_rows])
    # the odometry's chi-square after the joint Gauss-Newton step (the linearised optimum with the calibration free)
    step = np.concatenate([np.asarray(delta.at(k), dtype=float) for k in sorted(map(int, joint.keyVector()))])
    after = J @ step - b
    return {
        "odometry_chi2": chi_odo,
        "odometry_chi2_after_step": float(after[odo_rows] @ after[odo_rows]),
        "odometry_redundancy": r_odo,
        "odometry_ratio": chi_odo / r_odo if r_odo > 0 else 1.0,
        "odometry_chi2_by_dimension": [float(b[r] @ b[r]) for r in by_dim],
        "odometry_redundancy_by_dimension": [float(len(r) - hat_trace(J, Z, r)) for r in by_dim],
        "tag_chi2": chi_tag,
        "tag_redundancy": r_tag,
        "tag_ratio": chi_tag / r_tag if r_tag > 0 else 1.0,
    }


def _summary(
    cfg: GraphConfig,
    s: _State,
    sig_c: np.ndarray,
    cov_c: np.ndarray,
    prior_sigma: np.ndarray,
    stats: dict[str, Any],
    iterations: int,
    inner_iterations: int,
    history: list[dict[str, Any]],
    settled: bool,
) -> dict[str, Any]:
    out: dict[str, Any] = {"estimated": cfg.odometry_calibration is True}
    for name, v, sg, ps in zip(PARAMETERS, s.c, sig_c, prior_sigma, strict=True):
        out[name] = {"value": float(v), "sigma": float(sg), "prior_sigma": float(ps) if ps > 1e-8 else 0.0}
    out["correlation"] = (cov_c / np.outer(np.maximum(sig_c, 1e-300), np.maximum(sig_c, 1e-300))).round(4).tolist()
    out["noise_estimate"] = cfg.noise_estimate
    out["odometry_covariance_scale"] = float(np.exp(np.mean(np.log(s.lam_odo))))
    out["odometry_covariance_scale_by_dimension"] = s.lam_odo.tolist()
    out["tag_covariance_scale"] = s.lam_tag
    if stats:
        out["odometry_chi2_per_redundancy"] = stats["odometry_ratio"]
        out["odometry_redundancy"] = stats["odometry_redundancy"]
        out["tag_chi2_per_redundancy"] = stats["tag_ratio"]
        out["tag_redundancy"] = stats["tag_redundancy"]
    out["iterations"] = iterations
    out["inner_iterations"] = inner_iterations
    out["converged"] = settled
    out["history"] = history
    return out


__all__ = [
    "CALIBRATION_KEY",
    "PARAMETERS",
    "CalibrationResult",
    "applies",
    "calibrate",
    "calibration_test",
    "corrected_increment",
    "correction_jacobian",
    "resolved",
    "tested",
]
