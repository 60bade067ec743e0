"""Health checks of a solved graph: does the fit agree with what its noise models claim?

A graph can finish with a wrong map and nothing to show for it: a wrong tag size, tags that moved, an
optimiser that stopped at its cap, odometry covariances that do not describe the wheels. Each check below
gives its figures and, when it fails, one line that says what is wrong and which setting to look at:

- ``chi2``: the whitened χ² of each factor kind over its share of the degrees of freedom (``dof = dims ·
  (M − N) / M`` for M measurement and N unknown dimensions). Noise models that describe the data give about
  1 (less when they are conservative); above :data:`CHI2_PER_DOF_MAX` the fit is far outside them.
- ``tag_scale``: the shared tag scale more than :data:`SCALE_PRIOR_SIGMAS` prior sigmas from 1: the printed
  tags are not ``detect.tag_size_m``; the line names the size the data suggest (current size × scale).
- ``iterations``: the optimiser stopped at its iteration cap before converging.
- ``moved_tags``: tags whose measurements disagree with one position: their mean whitened χ² per measurement
  dimension is above :data:`TAG_CHI2_PER_DIM_MAX` and above :data:`TAG_CHI2_OVER_TYPICAL` times the median tag's
  (a tag that moved, a duplicated id, a tag on something that moves).
- ``dead_reckoning``: the solved trajectory against the odometry alone (dead reckoning composed from the
  odometry factors from the first pose, its covariance propagated along them): the largest Mahalanobis distance
  per dimension over the keyframes, with both covariances added; above :data:`DEAD_RECKONING_D2_PER_DIM_MAX`
  they disagree far beyond either's uncertainty.

The thresholds are set so that none fires on the bundled sample or held-out simulated worlds with correct
settings, and each fires on a world made to break it (docs/graph.md, "Health checks").
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import gtsam
import numpy as np

from stages.graph.factors import FactorRow, make_factor
from stages.graph.problem import GraphProblem

CHI2_PER_DOF_MAX = 5.0
"""A factor kind whose whitened χ² per degree of freedom exceeds this is far outside its noise model."""
CHI2_MIN_DOF = 5.0
"""Factor kinds with fewer degrees of freedom than this are not judged (a single prior, ...)."""
SCALE_PRIOR_SIGMAS = 3.0
"""The tag scale this many prior sigmas from 1 says the tag size setting is wrong."""
TAG_CHI2_PER_DIM_MAX = 25.0
"""A tag whose measurements' mean whitened χ² per dimension exceeds this (5 σ per dimension) ..."""
TAG_CHI2_OVER_TYPICAL = 10.0
"""... and this many times the median tag's, did not stay in one place."""
TAG_MIN_MEASUREMENTS = 3
"""Tags measured fewer times are not judged (one sighting always fits)."""
DEAD_RECKONING_D2_PER_DIM_MAX = 25.0
"""Largest squared Mahalanobis distance per dimension between the trajectory and dead reckoning (5 σ)."""

CHECKS = ("chi2", "tag_scale", "iterations", "moved_tags", "dead_reckoning")


def row_chi2(problem: GraphProblem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> np.ndarray:
    """Whitened χ² of every factor at ``values`` (robust kernels left out: the noise model's own Gaussian)."""
    out = np.empty(len(problem.rows))
    for i, row in enumerate(problem.rows):
        factor = graph.at(i) if row.robust == "none" else make_factor(replace(row, robust="none"))
        out[i] = 2.0 * float(factor.error(values))
    return out


def graph_health(
    problem: GraphProblem,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    marginals: dict[int, np.ndarray],
    iterations: int,
    max_iterations: int,
    section: str = "graph",
    tag_size_m: float | None = None,
) -> dict[str, Any]:
    """Every check of the module docstring on a solved graph; the ``health`` block of the stage's summary.

    Args:
        section: the settings section the messages name (``graph`` or ``optimize``).
        tag_size_m: the tag size the detections assumed (the scale check then names the size the data suggest).

    Returns:
        ``{"ok": bool, "warnings": [one line per failed check], "checks": {name: {"ok": bool, figures...}}}``.
    """
    chi2 = row_chi2(problem, graph, values)
    checks: dict[str, dict[str, Any]] = {}
    warnings: list[str] = []
    for name, (figures, warning) in (
        ("chi2", _chi2_check(problem, chi2)),
        ("tag_scale", _scale_check(problem, values, marginals, tag_size_m)),
        ("iterations", _iterations_check(iterations, max_iterations, section)),
        ("moved_tags", _moved_tags_check(problem, chi2)),
        ("dead_reckoning", _dead_reckoning_check(problem, values, marginals)),
    ):
        checks[name] = {"ok": warning is None, **figures}
        if warning is not None:
            warnings.append(warning)
    return {"ok": not warnings, "warnings": warnings, "checks": checks}


def _dof_share(problem: GraphProblem) -> float:
    """Degrees of freedom per measurement dimension, ``(M − N) / M``."""
    m = sum(r.dim for r in problem.rows)
    n = sum(problem.kind(k).dim for k in problem.var_types)
    return max(m - n, 0) / m if m else 0.0


def _chi2_check(problem: GraphProblem, chi2: np.ndarray) -> tuple[dict[str, Any], str | None]:
    share = _dof_share(problem)
    by_kind: dict[str, dict[str, float]] = {}
    for row, c in zip(problem.rows, chi2, strict=True):
        k = by_kind.setdefault(row.kind, {"dims": 0, "chi2": 0.0})
        k["dims"] += row.dim
        k["chi2"] += float(c)
    bad = []
    for kind, k in by_kind.items():
        k["dof"] = round(k["dims"] * share, 2)
        k["chi2_per_dof"] = round(k["chi2"] / k["dof"], 4) if k["dof"] > 0 else float("nan")
        k["chi2"] = round(k["chi2"], 3)
        if k["dof"] >= CHI2_MIN_DOF and k["chi2_per_dof"] > CHI2_PER_DOF_MAX:
            bad.append(kind)
    figures: dict[str, Any] = {"max": CHI2_PER_DOF_MAX, "by_kind": dict(sorted(by_kind.items()))}
    if not bad:
        return figures, None
    parts = ", ".join(f"{kind} {by_kind[kind]['chi2_per_dof']:.3g}" for kind in bad)
    hint = {
        "tag": "the tag measurements (tag size, camera calibration or extrinsics, moving tags; "
        "graph.tag_covariance_scale)",
        "odometry": "the odometry (its covariances understate the wheels' errors; graph.odometry_noise and "
        "graph.odometry_sigma_*)",
    }
    why = "; ".join(hint[kind] for kind in bad if kind in hint) or "their noise models"
    return figures, (
        f"the fit is far outside the noise models: whitened chi2 per degree of freedom {parts} (expected about 1, "
        f"at most {CHI2_PER_DOF_MAX:g}); check {why}"
    )


def _scale_check(
    problem: GraphProblem, values: gtsam.Values, marginals: dict[int, np.ndarray], tag_size_m: float | None
) -> tuple[dict[str, Any], str | None]:
    sk = problem.scale_key
    prior = next((r for r in problem.rows if r.kind == "scale_prior"), None)
    if sk is None or prior is None:
        return {"estimated": False}, None
    s = float(values.atDouble(sk))
    sigma = float(np.sqrt(marginals[sk][0, 0])) if sk in marginals else float("nan")
    prior_sigma = float(np.sqrt(np.asarray(prior.covariance, dtype=float).ravel()[0]))
    z = (s - 1.0) / prior_sigma
    figures: dict[str, Any] = {
        "estimated": True,
        "value": round(s, 6),
        "sigma": round(sigma, 6),
        "prior_sigma": prior_sigma,
        "prior_sigmas_from_1": round(z, 3),
        "max": SCALE_PRIOR_SIGMAS,
    }
    if tag_size_m is not None:
        figures["tag_size_m"] = tag_size_m
        figures["suggested_tag_size_m"] = round(tag_size_m * s, 4)
    if abs(z) <= SCALE_PRIOR_SIGMAS:
        return figures, None
    size = (
        f"the data suggest tags of {tag_size_m * s:.3f} m, not detect.tag_size_m={tag_size_m:g} m"
        if tag_size_m is not None
        else "the tag size the detections assumed (detect.tag_size_m) is wrong by that factor"
    )
    return figures, (
        f"the shared tag scale is {s:.3f} ± {sigma:.3f}, {abs(z):.1f} sigma of its prior "
        f"(graph.tag_scale_sigma={prior_sigma:g}) from 1: {size}; measure the printed tags' black square and "
        "set detect.tag_size_m"
    )


def _iterations_check(iterations: int, max_iterations: int, section: str) -> tuple[dict[str, Any], str | None]:
    figures = {"iterations": iterations, "max_iterations": max_iterations}
    if iterations < max_iterations:
        return figures, None
    return figures, (
        f"the optimiser stopped at its iteration cap ({section}.max_iterations={max_iterations}), so it may not "
        f"have converged and the map may not be the solution of the graph; raise {section}.max_iterations"
    )


def _moved_tags_check(problem: GraphProblem, chi2: np.ndarray) -> tuple[dict[str, Any], str | None]:
    per_tag: dict[int, list[float]] = {}
    dims: Counter[int] = Counter()
    for row, c in zip(problem.rows, chi2, strict=True):
        if row.kind == "tag" and row.tag_id is not None:
            per_tag.setdefault(int(row.tag_id), []).append(float(c))
            dims[int(row.tag_id)] += row.dim
    judged = {t: sum(cs) / dims[t] for t, cs in per_tag.items() if len(cs) >= TAG_MIN_MEASUREMENTS}
    if not judged:
        return {"tags_judged": 0}, None
    typical = float(np.median(list(judged.values())))
    limit = max(TAG_CHI2_PER_DIM_MAX, TAG_CHI2_OVER_TYPICAL * typical)
    moved = sorted((t for t, v in judged.items() if v > limit), key=lambda t: -judged[t])
    worst = max(judged, key=lambda t: judged[t])
    figures: dict[str, Any] = {
        "tags_judged": len(judged),
        "median_chi2_per_dim": round(typical, 4),
        "worst_tag": worst,
        "worst_chi2_per_dim": round(judged[worst], 4),
        "limit": round(limit, 4),
        "tags": moved,
        "chi2_per_dim": {str(t): round(judged[t], 3) for t in moved},
    }
    if not moved:
        return figures, None
    shown = ", ".join(f"{t} ({judged[t]:.3g})" for t in moved[:10]) + (" ..." if len(moved) > 10 else "")
    return figures, (
        f"{len(moved)} tag(s) look like they moved (their measurements disagree with one position; mean whitened "
        f"chi2 per dimension above {limit:.3g}, the median tag's {typical:.3g}): {shown}; a tag that moved or a "
        "duplicated id breaks the map: take it down or leave it out"
    )


def _odometry_chain(problem: GraphProblem) -> list[FactorRow | None]:
    """The odometry row between each pair of consecutive poses (None where there is none)."""
    between = {tuple(r.keys[:2]): r for r in problem.rows if r.kind == "odometry" and len(r.keys) == 2}
    keys = problem.pose_keys
    return [between.get((keys[i], keys[i + 1])) for i in range(len(keys) - 1)]


def _dead_reckoning_check(
    problem: GraphProblem, values: gtsam.Values, marginals: dict[int, np.ndarray]
) -> tuple[dict[str, Any], str | None]:
    chain = _odometry_chain(problem)
    if not chain or all(r is None for r in chain):
        return {"compared": 0}, None
    kind = problem.graph_model.pose
    keys = [k for k in problem.pose_keys]
    if not all(values.exists(k) for k in keys):
        return {"compared": 0}, None
    d2 = _dead_reckoning_d2(problem, kind, keys, chain, values, marginals)
    dim = kind.dim
    worst = int(np.argmax(d2))
    figures: dict[str, Any] = {
        "compared": len(d2),
        "max_d2_per_dim": round(float(d2[worst]) / dim, 4),
        "median_d2_per_dim": round(float(np.median(d2)) / dim, 4),
        "worst_pose": worst,
        "max": DEAD_RECKONING_D2_PER_DIM_MAX,
    }
    if d2[worst] / dim <= DEAD_RECKONING_D2_PER_DIM_MAX:
        return figures, None
    return figures, (
        f"the trajectory disagrees with dead reckoning far beyond both covariances (squared Mahalanobis distance "
        f"per dimension {d2[worst] / dim:.3g} at {problem.describe(keys[worst])}, at most "
        f"{DEAD_RECKONING_D2_PER_DIM_MAX:g}): the odometry covariances are too small for the wheels, or the tag "
        "measurements are wrong (tag size, camera calibration, extrinsics)"
    )


def _dead_reckoning_d2(
    problem: GraphProblem,
    kind: Any,
    keys: Sequence[int],
    chain: Sequence[FactorRow | None],
    values: gtsam.Values,
    marginals: dict[int, np.ndarray],
) -> np.ndarray:
    """Squared Mahalanobis distance of each pose from dead reckoning (both covariances), in time order.

    Dead reckoning starts at the solved first pose (and again at the solved pose after a gap in the odometry)
    and composes the odometry measurements; its covariance grows as ``Σ' = Ad(M⁻¹) Σ Ad(M⁻¹)ᵀ + Q``.
    """
    dim = kind.dim
    pose = kind.read(values, keys[0])
    cov = np.zeros((dim, dim))
    d2 = [0.0]
    for i, row in enumerate(chain):
        solved = kind.read(values, keys[i + 1])
        if row is None:
            pose, cov = solved, np.zeros((dim, dim))
            d2.append(0.0)
            continue
        step = kind.from_vector(np.asarray(row.measurement, dtype=float))
        Ad = np.asarray(step.inverse().AdjointMap())
        cov = Ad @ cov @ Ad.T + np.asarray(row.covariance, dtype=float).reshape(dim, dim)
        pose = pose.compose(step)
        e = np.asarray(type(pose).Logmap(pose.between(solved)), dtype=float)
        C = cov + marginals.get(keys[i + 1], np.zeros((dim, dim)))
        try:
            d2.append(float(e @ np.linalg.solve(C, e)))
        except np.linalg.LinAlgError:
            d2.append(float("inf"))
    return np.asarray(d2)


def strict_error(section: str, health: dict[str, Any]) -> str:
    """The one line a strict stage stops with: its failed checks."""
    warnings = health["warnings"]
    more = f" (and {len(warnings) - 1} more health warning(s))" if len(warnings) > 1 else ""
    return f"{section}.strict: a health check failed: {warnings[0]}{more}; the stage's results are not kept"
