"""Health checks of a solved graph: does the fit agree with what its noise models claim?

A graph can finish with a wrong map and nothing to show for it: a wrong tag size, tags that moved, an
optimiser that stopped at its cap, odometry covariances that do not describe the wheels. Each check below
gives its figures and, when it fails, one line that says what is wrong and which setting to look at:

- ``chi2``: the whitened χ² of each factor kind over its redundancy (``dof = Σ_f (dim_f − tr(J_f H⁻¹ J_fᵀ))``,
  :func:`redundancy_by_kind`; ``dims · (M − N) / M`` for M measurement and N unknown dimensions when the system
  cannot be factorised). Noise models that describe the data give about
  1 (less when they are conservative); above :data:`CHI2_PER_DOF_MAX` the fit is far outside them.
- ``tag_scale``: the shared tag scale more than :data:`SCALE_PRIOR_SIGMAS` prior sigmas from 1: the printed
  tags are not ``detect.tag_size_m``; the line names the size the data suggest (current size × scale).
- ``extrinsics``: per camera, the rotation that best turns the directions of the camera's motion between two
  sightings of a tag, as the odometry and the extrinsics give them, into those the tags measure
  (:func:`stages.graph.tag_motion.mounting_figures`, before the solve): beyond 3 degrees the camera's mounting
  rotation is off, which bends the map and moves the tag scale (so the scale check's advice would be wrong).
- ``rig``: per given camera of a rig with two or more given mounts, the mount its same-stamp sightings of the other
  given cameras' tags imply, against the given one (:func:`stages.graph.rig.given_mount_figures`, before the
  solve): more than 3 degrees, or more than 3 cm and 3 standard errors, apart, the given mount is wrong.
- ``tag_size``: the camera's motion between two sightings of one tag, as the tags measure it, against the wheel
  odometry's (:mod:`stages.graph.tag_motion`, computed before the solve): more than 10 % apart, the tag size is
  wrong (or the wheels are that far off). It catches what the scale check cannot: a size wrong by tens of percent,
  where the scale's prior holds and the odometry or its calibration bends instead.
- ``iterations``: the optimiser stopped at its iteration cap before converging.
- ``moved_tags``: tags whose measurements disagree with one position (a tag that moved, a duplicated id, a tag on
  something that moves), judged twice: at the solution (the mean whitened χ² per measurement dimension of the tag's
  factors) and against the odometry alone (the same figure after solving the tag with only its own sightings and the
  odometry between them, see :func:`tag_dead_reckoning_chi2`). Either above its floor (:data:`TAG_CHI2_PER_DIM_MAX`,
  :data:`TAG_DR_CHI2_PER_DIM_MAX`) and above :data:`TAG_CHI2_OVER_TYPICAL` times the median tag's flags the tag;
  the tags the odometry flags are named first, by its figure, then those only the solution flags, by theirs. One
  wrong tag can pull the whole solution with it (a duplicated id can shrink the map to a point through the tag
  scale), and then the solution's residuals blame the innocent tags; the odometry figure does not depend on the
  solution.
- ``dead_reckoning``: the solved trajectory against the odometry alone (dead reckoning composed from the
  odometry factors from the first pose, its covariance propagated along them): the largest Mahalanobis distance
  per dimension over the keyframes, with both covariances added; above :data:`DEAD_RECKONING_D2_PER_DIM_MAX`
  they disagree far beyond either's uncertainty.

The graph stage adds two checks of ``odometry_calibration: auto`` when it ran its test
(``stages/graph/solve_all.py``): ``odometry_calibration`` (the odometry disagrees with the tags as no wheel error
does) and ``wheel_scale`` (the calibration stayed off, but would move the map beyond its own σ: a wheel's distance
scale and the tag size cannot be told apart, :func:`stages.graph.calibration.shift_warning`).

The thresholds are set so that none fires on the bundled sample or held-out simulated worlds with correct
settings, and each fires on a world made to break it (docs/graph.md, "Health checks").
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import replace
from itertools import pairwise
from typing import Any

import gtsam
import numpy as np

from stages.graph.factors import FactorRow, build_graph, make_factor
from stages.graph.problem import GraphProblem
from stages.graph.rig import given_mount_warning
from stages.graph.tag_motion import MIN_PAIRS, MOUNT_MAX_DEG, RATIO_MAX, mounting_warning, size_warning

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
TAG_DR_CHI2_PER_DIM_MAX = 9.0
"""The same figure against the odometry alone (3 σ per dimension on average): the odometry between sightings
absorbs part of a wrong tag's disagreement, so its figure stays lower than at a solution that holds every tag."""
TAG_DR_MAX_TAGS = 400
"""At most this many tags (the most measured) are judged against the odometry (one small solve each)."""
DEAD_RECKONING_D2_PER_DIM_MAX = 25.0
"""Largest squared Mahalanobis distance per dimension between the trajectory and dead reckoning (5 σ)."""

CHECKS = ("chi2", "extrinsics", "tag_scale", "tag_size", "iterations", "moved_tags", "dead_reckoning")


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
        ("chi2", _chi2_check(problem, chi2, redundancy_by_kind(problem, graph, values))),
        ("extrinsics", _mounting_check(problem)),
        ("rig", _rig_check(problem)),
        ("tag_scale", scale_check(problem, values, marginals, tag_size_m)),
        ("tag_size", _size_check(problem, tag_size_m)),
        ("iterations", _iterations_check(iterations, max_iterations, section)),
        ("moved_tags", _moved_tags_check(problem, chi2)),
        ("dead_reckoning", _dead_reckoning_check(problem, values, marginals)),
    ):
        if warning is not None and name in ("tag_scale", "tag_size") and not checks["extrinsics"]["ok"]:
            warning += (
                " (but the camera's mounting looks rotated, see above, which also moves the scale: fix that first)"
            )
        checks[name] = {"ok": warning is None, **figures}
        if warning is not None:
            warnings.append(warning)
    return {"ok": not warnings, "warnings": warnings, "checks": checks}


def _dof_share(problem: GraphProblem) -> float:
    """Degrees of freedom per measurement dimension, ``(M − N) / M``."""
    m = sum(r.dim for r in problem.rows)
    n = sum(problem.kind(k).dim for k in problem.var_types)
    return max(m - n, 0) / m if m else 0.0


def redundancy_by_kind(
    problem: GraphProblem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
) -> dict[str, float] | None:
    """Each factor kind's redundancy at ``values``: its measurement dimensions less its share of the hat matrix's
    trace, ``Σ_f (dim_f − tr(J_f H⁻¹ J_fᵀ))`` (``E[χ²]`` of the kind when its noise model is right; the kinds' sum is
    ``M − N``). From one selected inverse on the blocks of every kind's factors but the largest kind's, which takes
    the rest of ``tr(H⁻¹ H) = N`` (an hour's tag factors would have added 140 MiB to the stage's peak); linear in the
    graph. None when the system cannot be factorised (the caller falls back to shares in proportion to the
    dimensions).

    The shares matter on reduced graphs: there an odometry chain adds no redundancy of its own (each factor places
    the next pose), so nearly all of it is the tags', where dimensions in proportion gave the tags 6 of ~120 and
    their χ² per degree of freedom read 5.9 for 0.3 (c93's focus, info; docs/graph.md)."""
    from stages.graph.marginals import factor_row_starts, hat_trace, key_dims, selected_inverse, whitened_system

    linear = graph.linearize(values)
    if linear.size() != len(problem.rows) or not problem.rows:
        return None
    dims: dict[str, int] = {}
    for row in problem.rows:
        dims[row.kind] = dims.get(row.kind, 0) + row.dim
    rest = max(dims, key=lambda kind: dims[kind])  # the largest kind takes what the others leave (tr(H⁻¹ H) = n)
    traced = [i for i, row in enumerate(problem.rows) if row.kind != rest]
    try:
        J, _ = whitened_system(linear)
        groups = [list(linear.at(i).keys()) for i in traced]
        key_dim = key_dims(values)
        Z = selected_inverse(linear, key_dim, groups, last=list(problem.landmark_keys.values()))
    except RuntimeError:
        return None
    starts = factor_row_starts([r.dim for r in problem.rows])
    if int(starts[-1]) != J.shape[0]:
        return None
    rows_of: dict[str, list[np.ndarray]] = {}
    for i in traced:
        rows_of.setdefault(problem.rows[i].kind, []).append(np.arange(starts[i], starts[i + 1]))
    out = {}
    for kind, parts in rows_of.items():
        rows = np.concatenate(parts)
        out[kind] = float(len(rows) - hat_trace(J, Z, rows))
    n = sum(key_dim[int(k)] for k in linear.keyVector())
    out[rest] = float(dims[rest] - (n - sum(dims[k] - r for k, r in out.items())))
    return out


def _chi2_check(
    problem: GraphProblem, chi2: np.ndarray, redundancy: dict[str, float] | None = None
) -> tuple[dict[str, Any], str | None]:
    share = _dof_share(problem)
    by_kind: dict[str, dict[str, float]] = {}
    for row, c in zip(problem.rows, chi2, strict=True):
        k = by_kind.setdefault(row.kind, {"dims": 0, "chi2": 0.0})
        k["dims"] += row.dim
        k["chi2"] += float(c)
    bad = []
    for kind, k in by_kind.items():
        k["dof"] = round(redundancy[kind] if redundancy is not None else k["dims"] * share, 2)
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


def scale_check(
    problem: GraphProblem, values: gtsam.Values, marginals: dict[int, np.ndarray], tag_size_m: float | None
) -> tuple[dict[str, Any], str | None]:
    """The ``tag_scale`` check: its figures and its line (None when the shared tag scale is plausible)."""
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
    if not 0.25 <= s <= 4.0:  # a collapsed or flipped map: no tag size explains it
        return figures, (
            f"the shared tag scale is {s:.3f} ± {sigma:.3f}, {abs(z):.1f} sigma of its prior from 1: no tag size "
            "explains that, the map has collapsed or flipped (a duplicated tag id, wrong extrinsics: see the other "
            "checks)"
        )
    return figures, (
        f"the shared tag scale is {s:.3f} ± {sigma:.3f}, {abs(z):.1f} sigma of its prior "
        f"(graph.tag_scale_sigma={prior_sigma:g}) from 1: {size}; measure the printed tags' black square and "
        "set detect.tag_size_m (a camera model whose focal length is off by that factor does the same)"
    )


def _mounting_check(problem: GraphProblem) -> tuple[dict[str, Any], str | None]:
    cameras = problem.info.get("camera_mounting")
    if cameras is None:  # no odometry, or a reduced graph (optimize): the graph stage judged it
        return {"judged": False}, None
    lines = [w for cam, f in cameras.items() if (w := mounting_warning(cam, f, f.get("source", "?"))) is not None]
    figures = {"judged": any("angle_deg" in f for f in cameras.values()), "max_deg": MOUNT_MAX_DEG, "cameras": cameras}
    return figures, "; ".join(lines) if lines else None


def _rig_check(problem: GraphProblem) -> tuple[dict[str, Any], str | None]:
    cameras = problem.info.get("rig_check")
    if not cameras:  # one camera, too few shared sightings, or a reduced graph (optimize): the graph stage judged it
        return {"judged": False}, None
    lines = [w for cam, f in cameras.items() if (w := given_mount_warning(cam, f)) is not None]
    return {"judged": True, "cameras": cameras}, "; ".join(lines) if lines else None


def _size_check(problem: GraphProblem, tag_size_m: float | None) -> tuple[dict[str, Any], str | None]:
    figures = problem.info.get("tag_odometry_ratio")
    if figures is None:  # no odometry, or a reduced graph (optimize): the graph stage judged it
        return {"judged": False}, None
    judged = figures.get("pairs", 0) >= MIN_PAIRS
    return {"judged": judged, **figures, "max": RATIO_MAX}, size_warning(figures, tag_size_m)


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
    dr = tag_dead_reckoning_chi2(problem, list(judged))
    dr_typical = float(np.median(list(dr.values()))) if dr else float("nan")
    dr_limit = max(TAG_DR_CHI2_PER_DIM_MAX, TAG_CHI2_OVER_TYPICAL * dr_typical) if dr else float("inf")
    by_odometry = sorted((t for t, v in dr.items() if v > dr_limit), key=lambda t: -dr[t])
    by_solution = sorted((t for t, v in judged.items() if v > limit and t not in by_odometry), key=lambda t: -judged[t])
    # the tags the odometry alone says moved first (its verdict does not depend on a solution the wrong tag may have
    # dragged along), then those only the solution blames
    moved = by_odometry + by_solution
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
    if dr:
        dr_worst = max(dr, key=lambda t: dr[t])
        figures["odometry"] = {
            "tags_judged": len(dr),
            "median_chi2_per_dim": round(dr_typical, 4),
            "worst_tag": dr_worst,
            "worst_chi2_per_dim": round(dr[dr_worst], 4),
            "limit": round(dr_limit, 4),
            "chi2_per_dim": {str(t): round(dr[t], 3) for t in moved if t in dr},
        }
    if not moved:
        return figures, None

    surveyed = {int(r.tag_id) for r in problem.rows if r.kind == "tag_prior" and r.tag_id is not None}
    figures["surveyed"] = [t for t in moved if t in surveyed]

    def shown_one(t: int) -> str:
        more = [f"{dr[t]:.3g} against the odometry"] if t in dr else []
        more += ["surveyed"] if t in surveyed else []
        return f"{t} ({', '.join([f'{judged[t]:.3g}', *more])})"

    shown = ", ".join(shown_one(t) for t in moved[:10]) + (" ..." if len(moved) > 10 else "")
    against = f"; against the odometry alone above {dr_limit:.3g}, the median's {dr_typical:.3g}" if dr else ""
    # a surveyed tag is held at its surveyed pose, so a wrong survey puts the disagreement into its measurements
    survey = (
        "; a surveyed tag whose pose in the tags file is off looks the same: check its pose there, or give it a "
        "position_noise that matches the survey"
        if figures["surveyed"]
        else ""
    )
    return figures, (
        f"{len(moved)} tag(s) look like they moved (their measurements disagree with one position; mean whitened "
        f"chi2 per dimension above {limit:.3g}, the median tag's {typical:.3g}{against}): {shown}; a tag that moved "
        f"or a duplicated id breaks the map: take it down or leave it out{survey}"
    )


def tag_dead_reckoning_chi2(problem: GraphProblem, tags: Sequence[int]) -> dict[int, float]:
    """Each tag's mean whitened χ² per measurement dimension when it is solved with the odometry alone.

    For each tag (at most :data:`TAG_DR_MAX_TAGS`, the most measured): a small graph of the poses it is seen from,
    the odometry composed between consecutive ones (its covariance propagated as in the dead-reckoning check), the
    tag's own measurements at tag scale 1; the first pose is held at its initial value (dead reckoning) and the
    first pose after a gap in the odometry is left nearly free. A tag that stayed put fits its sightings
    as well as the odometry between them allows (about 1, less with conservative noise models); a tag that moved,
    or two tags with one id, cannot. Empty without odometry between consecutive poses.
    """
    chain = _odometry_chain(problem)
    if not chain or all(r is None for r in chain):
        return {}
    model = problem.graph_model
    kind = model.pose
    index = {k: i for i, k in enumerate(problem.pose_keys)}
    by_tag: dict[int, list[FactorRow]] = {}
    for row in problem.rows:
        if row.kind == "tag" and row.tag_id is not None and int(row.tag_id) in tags and row.keys[0] in index:
            by_tag.setdefault(int(row.tag_id), []).append(row)
    reckoning = _Reckoning(kind, model.identity, chain)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    out: dict[int, float] = {}
    for tag in sorted(by_tag, key=lambda t: -len(by_tag[t]))[:TAG_DR_MAX_TAGS]:
        # at scale 1 (the shared scale's key left out: native factors), without robust kernels
        tag_rows = [replace(r, keys=r.keys[:2], robust="none") for r in by_tag[tag]]
        seen = sorted({index[r.keys[0]] for r in tag_rows})
        first = problem.pose_keys[seen[0]]
        rows = [model.prior_row(first, kind.to_vector(kind.read(problem.initial, first)), 1e-6, 1e-6)]
        for a, b in pairwise(seen):
            motion = reckoning.motion(a, b)
            key_b = problem.pose_keys[b]
            if motion is None:  # a gap: this sighting's pose is held by the tag alone
                rows.append(model.prior_row(key_b, kind.to_vector(kind.read(problem.initial, key_b)), 1e3, 1e2))
                continue
            rows.append(model.between_row("odometry", (problem.pose_keys[a], key_b), *motion, stamp_ns=0))
        rows.extend(tag_rows)
        initial = gtsam.Values()
        for key in {k for r in rows for k in r.keys}:
            var = problem.kind(key)
            var.insert(initial, key, var.read(problem.initial, key))
        graph = build_graph(rows)
        try:
            values = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        except RuntimeError:  # a tag that cannot be solved alone is not judged
            continue
        chi2 = [2.0 * graph.at(i).error(values) for i in range(len(rows) - len(tag_rows), len(rows))]
        out[tag] = float(np.sum(chi2)) / sum(r.dim for r in tag_rows)
    return out


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


class _Reckoning:
    """Dead reckoning along the odometry chain, for the motion between any two poses of one unbroken stretch.

    ``P_i`` is the composition of the odometry from the start of pose i's stretch; ``C_i`` sums each step's
    noise carried into the world frame of the stretch, ``Ad(P_{j+1}) Q_j Ad(P_{j+1})ᵀ`` for the steps before i. The
    motion from a to b is ``P_a⁻¹ P_b`` and its covariance (frame b) ``Ad(P_b⁻¹) (C_b − C_a) Ad(P_b⁻¹)ᵀ``: the same
    as composing the steps one by one and propagating ``Σ' = Ad(M⁻¹) Σ Ad(M⁻¹)ᵀ + Q``.
    """

    def __init__(self, kind: Any, identity_vector: np.ndarray, chain: Sequence[FactorRow | None]) -> None:
        self.kind = kind
        dim = kind.dim
        identity = kind.from_vector(identity_vector)
        self.poses = [identity]
        self.cov = np.zeros((len(chain) + 1, dim, dim))
        self.stretch = np.zeros(len(chain) + 1, dtype=int)
        for i, row in enumerate(chain):
            if row is None:
                self.poses.append(identity)
                self.stretch[i + 1] = self.stretch[i] + 1
                continue
            self.stretch[i + 1] = self.stretch[i]
            step = kind.from_vector(np.asarray(row.measurement, dtype=float))
            pose = self.poses[i].compose(step)
            self.poses.append(pose)
            Ad = np.asarray(pose.AdjointMap())
            self.cov[i + 1] = self.cov[i] + Ad @ np.asarray(row.covariance, dtype=float).reshape(dim, dim) @ Ad.T

    def motion(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry from pose a to pose b (measurement vector, covariance); None across a gap."""
        if self.stretch[a] != self.stretch[b]:
            return None
        Pb = self.poses[b]
        Ad = np.asarray(Pb.inverse().AdjointMap())
        cov = Ad @ (self.cov[b] - self.cov[a]) @ Ad.T
        return np.asarray(self.kind.to_vector(self.poses[a].between(Pb)), dtype=float), 0.5 * (cov + cov.T)


def strict_error(section: str, health: dict[str, Any]) -> str:
    """The one line a strict stage stops with: its failed checks."""
    warnings = health["warnings"]
    more = f" (and {len(warnings) - 1} more health warning(s))" if len(warnings) > 1 else ""
    return f"{section}.strict: a health check failed: {warnings[0]}{more}; the stage's results are not kept"
