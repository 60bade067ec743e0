"""Why the cases come out as they do: consistency of the measurements and maps against the ground truth.

The issue asks evaluate to explain, not only report, where the table differs from the paper's expectation.
With a ground truth (the simulator's ``<name>.ground_truth.json``) this module measures:

* :func:`measurement_consistency`: every measurement's residual at the *true* poses and landmarks, whitened by
  its stated covariance. A consistent measurement has whitened residuals of mean 0 and χ² (NEES) equal to its
  dimension on average; a mean far from 0 is a bias, a χ² far above the dimension a covariance that is too small.
* :func:`landmark_consistency`: for a case's map, each focused landmark's error against the truth beside its
  marginal σ, and its NEES ``eᵀ Σ⁻¹ e`` (2 on average for a consistent planar landmark).
* :func:`oracle_rows`: the case's tag measurements replaced by ground-truth-consistent ones,
  ``z = h(true pose, true landmark) + ν, ν ~ N(0, R_stated)`` (seeded), so the same selection can be re-solved
  with measurements whose errors are exactly what their covariance says. If the focused error then orders as the
  entropy does (more information, smaller error) while with the real measurements it does not, the difference
  comes from the measurements, not from the selection.
* :func:`navigation_margin`: along the nominal path, the clearance minus the robot radius against the spread of the
  simulated robots around the path and the EKF's σ: how many σ of room navigation has.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stages.geometry import wrap_angle
from stages.graph.factors import FactorRow
from stages.graph.load import LoadedGraph
from stages.navigation.truth import MapTruth

FloatArray = npt.NDArray[np.float64]
CHI2_2_95 = 5.991464547107979
"""95 % quantile of χ² with 2 degrees of freedom."""


def _pose_stamps(loaded: LoadedGraph) -> dict[int, int]:
    return {int(k): int(s) for k, s in zip(loaded.pose_keys, loaded.pose_stamps_ns, strict=True)}


def predicted_bearing_range(pose: FloatArray, landmark: FloatArray) -> FloatArray:
    """Planar ``h(x, l)``: bearing (rad, in the pose's frame) and range (m) of ``landmark`` from ``pose``."""
    d = np.asarray(landmark, dtype=float)[:2] - np.asarray(pose, dtype=float)[:2]
    return np.array([float(wrap_angle(np.arctan2(d[1], d[0]) - pose[2])), float(np.hypot(d[0], d[1]))])


@dataclass(frozen=True)
class MeasurementConsistency:
    """Residuals of one kind of measurement at the truth (planar tag measurements: bearing, range)."""

    kind: str
    count: int
    mean_residual: FloatArray
    """Mean raw residual per component (tag: rad, m; odometry: m, m, rad)."""
    rms_residual: FloatArray
    stated_sigma: FloatArray
    """RMS of the stated per-component σ."""
    mean_whitened: FloatArray
    """Mean of the residual divided by its stated σ, per component (bias in σ units; 0 if unbiased)."""
    mean_nees: float
    """Mean of rᵀ R⁻¹ r (equals the dimension if the covariance is right)."""
    dim: int

    def as_dict(self) -> dict[str, object]:
        """JSON-able."""
        return {
            "kind": self.kind,
            "count": self.count,
            "dim": self.dim,
            "mean_residual": self.mean_residual.tolist(),
            "rms_residual": self.rms_residual.tolist(),
            "stated_sigma": self.stated_sigma.tolist(),
            "mean_whitened": self.mean_whitened.tolist(),
            "mean_nees": self.mean_nees,
        }


def _consistency(kind: str, residuals: list[FloatArray], covs: list[FloatArray]) -> MeasurementConsistency | None:
    if not residuals:
        return None
    r = np.asarray(residuals)
    C = np.asarray(covs)
    sig = np.sqrt(np.einsum("nii->ni", C))
    nees = np.einsum("ni,ni->n", r, np.linalg.solve(C, r[..., None])[..., 0])
    return MeasurementConsistency(
        kind=kind,
        count=len(r),
        mean_residual=r.mean(axis=0),
        rms_residual=np.sqrt((r**2).mean(axis=0)),
        stated_sigma=np.sqrt((sig**2).mean(axis=0)),
        mean_whitened=(r / sig).mean(axis=0),
        mean_nees=float(nees.mean()),
        dim=r.shape[1],
    )


def tag_residual(row: FactorRow, truth: MapTruth, stamps: Mapping[int, int]) -> FloatArray | None:
    """``z − h(true pose, true landmark)`` of a planar tag measurement (None if the truth lacks the tag)."""
    if row.type != "BearingRangeFactor2D" or row.tag_id is None or int(row.tag_id) not in truth.tags:
        return None
    pose = truth.pose_at([stamps[int(row.keys[0])]])[0]
    h = predicted_bearing_range(pose, truth.tags[int(row.tag_id)])
    z = np.asarray(row.measurement, dtype=float)
    return np.array([float(wrap_angle(z[0] - h[0])), z[1] - h[1]])


def measurement_consistency(
    loaded: LoadedGraph, truth: MapTruth, factor_indices: Iterable[int] | None = None
) -> dict[str, MeasurementConsistency]:
    """Whitened residuals at the truth of the tag measurements (``factor_indices`` or all) and of the odometry."""
    stamps = _pose_stamps(loaded)
    idx = range(len(loaded.rows)) if factor_indices is None else [int(i) for i in factor_indices]
    tr, tc, orr, oc = [], [], [], []
    for i in idx:
        row = loaded.rows[i]
        if row.kind == "tag":
            r = tag_residual(row, truth, stamps)
            if r is not None:
                tr.append(r)
                tc.append(np.asarray(row.covariance, dtype=float).reshape(2, 2))
        elif row.type == "BetweenFactorPose2" and factor_indices is None:
            a, b = truth.pose_at([stamps[int(row.keys[0])], stamps[int(row.keys[1])]])
            c, s = np.cos(a[2]), np.sin(a[2])
            d = b[:2] - a[:2]
            true_rel = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], float(wrap_angle(b[2] - a[2]))])
            m = np.asarray(row.measurement, dtype=float)
            orr.append(np.array([m[0] - true_rel[0], m[1] - true_rel[1], float(wrap_angle(m[2] - true_rel[2]))]))
            oc.append(np.asarray(row.covariance, dtype=float).reshape(3, 3))
    out = {}
    for kind, res, cov in (("tag", tr, tc), ("odometry", orr, oc)):
        c = _consistency(kind, res, cov)
        if c is not None:
            out[kind] = c
    return out


def residuals_by_range(
    loaded: LoadedGraph, truth: MapTruth, edges: Sequence[float] = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, np.inf)
) -> list[dict[str, float]]:
    """Tag residuals at the truth binned by measured range: count, mean range residual, mean whitened, NEES."""
    stamps = _pose_stamps(loaded)
    rows = []
    for row in loaded.rows:
        if row.kind != "tag":
            continue
        r = tag_residual(row, truth, stamps)
        if r is None:
            continue
        C = np.asarray(row.covariance, dtype=float).reshape(2, 2)
        rows.append((float(row.measurement[1]), r, C))
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = [(r, C) for rng, r, C in rows if lo <= rng < hi]
        if not sel:
            continue
        c = _consistency("tag", [s[0] for s in sel], [s[1] for s in sel])
        assert c is not None
        out.append(
            {
                "range_lo_m": lo,
                "range_hi_m": hi,
                "count": c.count,
                "mean_range_residual_m": float(c.mean_residual[1]),
                "mean_bearing_residual_rad": float(c.mean_residual[0]),
                "range_sigma_m": float(c.stated_sigma[1]),
                "mean_whitened_range": float(c.mean_whitened[1]),
                "mean_nees": c.mean_nees,
            }
        )
    return out


def oracle_rows(
    loaded: LoadedGraph, truth: MapTruth, factor_indices: Iterable[int], seed: int = 0
) -> dict[int, FactorRow]:
    """Ground-truth-consistent replacements of the given tag measurements: ``h(truth) + N(0, R_stated)``.

    The noise of factor ``i`` is drawn from a generator seeded by ``(seed, i)``, so a measurement gets the same
    noise in every case that keeps it (the cases differ only in which measurements they keep, as with the real
    data).
    """
    stamps = _pose_stamps(loaded)
    out: dict[int, FactorRow] = {}
    for i in factor_indices:
        row = loaded.rows[int(i)]
        if row.kind != "tag" or row.type != "BearingRangeFactor2D" or row.tag_id is None:
            continue
        if int(row.tag_id) not in truth.tags:
            continue
        pose = truth.pose_at([stamps[int(row.keys[0])]])[0]
        h = predicted_bearing_range(pose, truth.tags[int(row.tag_id)])
        C = np.asarray(row.covariance, dtype=float).reshape(2, 2)
        noise = np.random.default_rng([seed, int(i)]).multivariate_normal(np.zeros(2), C)
        z = h + noise
        z[0] = float(wrap_angle(np.array(z[0])))
        out[int(i)] = FactorRow(
            kind=row.kind,
            type=row.type,
            keys=row.keys,
            measurement=z,
            covariance=row.covariance,
            robust=row.robust,
            robust_k=row.robust_k,
            tag_id=row.tag_id,
            frame=row.frame,
            stamp_ns=row.stamp_ns,
            extra=dict(row.extra),
        )
    return out


@dataclass(frozen=True)
class LandmarkConsistency:
    """A case's focused landmarks against the truth."""

    count: int
    mean_error_m: float
    mean_sigma_m: float
    """Mean of sqrt(trace Σ / 2) (the per-axis σ)."""
    mean_nees: float
    """Mean eᵀ Σ⁻¹ e (2 if the map's covariances are right)."""
    share_outside_95: float
    """Share of landmarks with NEES above the 95 % χ²₂ quantile (0.05 if consistent)."""

    def as_dict(self) -> dict[str, float]:
        """JSON-able."""
        return {
            "count": self.count,
            "mean_error_m": self.mean_error_m,
            "mean_sigma_m": self.mean_sigma_m,
            "mean_nees": self.mean_nees,
            "share_outside_95": self.share_outside_95,
        }


def landmark_consistency(
    tag_ids: npt.ArrayLike,
    positions: FloatArray,
    covariances: FloatArray,
    reference: Mapping[int, FloatArray],
    only: Iterable[int] | None = None,
) -> LandmarkConsistency:
    """Errors, σ and NEES of a map's landmarks (those in ``only``, if given) against ``reference``."""
    want = None if only is None else {int(t) for t in only}
    errs, sigs, nees = [], [], []
    for t, p, C in zip(np.asarray(tag_ids).tolist(), positions, covariances, strict=True):
        if (want is not None and int(t) not in want) or int(t) not in reference:
            continue
        e = np.asarray(p, dtype=float)[:2] - np.asarray(reference[int(t)], dtype=float)[:2]
        C2 = np.asarray(C, dtype=float)[:2, :2]
        errs.append(float(np.linalg.norm(e)))
        sigs.append(float(np.sqrt(max(np.trace(C2), 0.0) / 2.0)))
        nees.append(float(e @ np.linalg.solve(C2, e)))
    if not errs:
        nan = float("nan")
        return LandmarkConsistency(0, nan, nan, nan, nan)
    n = np.asarray(nees)
    return LandmarkConsistency(
        len(errs), float(np.mean(errs)), float(np.mean(sigs)), float(n.mean()), float((n > CHI2_2_95).mean())
    )


OVERCONFIDENCE_FALSE_ALARM = 1e-3
"""Size of :func:`overconfidence`'s test: the chance that a map whose stated covariances are right is flagged, over all
its tested landmarks together."""


@dataclass(frozen=True)
class Overconfidence:
    """A map's focused landmarks against the reference, each by its own stated covariance: the worst one.

    Each landmark's ``eᵀ Σ⁻¹ e`` (Σ its marginal, e its planar error) is χ² with 2 degrees of freedom when the map's
    covariance is right, whatever the correlations between landmarks, so testing the largest against the χ²₂ quantile
    at ``1 − p / n`` (Bonferroni) flags a right map with probability at most ``p``. Against the full map instead of the
    truth, the error's covariance is ``Σ − Σ_full`` (the full map knows a superset of the measurements), smaller than
    Σ: testing with Σ is conservative."""

    count: int
    """Focused landmarks tested (observed by the map and in the reference)."""
    tag_id: int | None
    """The landmark with the largest NEES (None when none was tested)."""
    nees: float
    """Its ``eᵀ Σ⁻¹ e``."""
    error_m: float
    """Its planar error, m."""
    sigma_m: float
    """The map's stated σ along that error, m (``error_m / sqrt(nees)``)."""
    limit: float
    """The χ²₂ quantile at ``1 − p / count``: ``−2 ln(p / count)``."""

    @property
    def fails(self) -> bool | None:
        """The worst landmark lies outside what the map's covariance allows (None: nothing tested)."""
        return None if self.count == 0 else bool(self.nees > self.limit)

    @property
    def sigmas(self) -> float:
        """The worst error in σ along it."""
        return float(np.sqrt(self.nees))


def overconfidence(
    tag_ids: npt.ArrayLike,
    positions: FloatArray,
    covariances: FloatArray,
    reference: Mapping[int, FloatArray],
    only: Iterable[int],
    false_alarm: float = OVERCONFIDENCE_FALSE_ALARM,
) -> Overconfidence:
    """The worst of the map's landmarks in ``only`` against ``reference`` by its own covariance
    (:class:`Overconfidence`)."""
    want = {int(t) for t in only}
    worst: tuple[float, int, float] | None = None
    count = 0
    for t, p, C in zip(np.asarray(tag_ids).tolist(), positions, covariances, strict=True):
        if int(t) not in want or int(t) not in reference:
            continue
        e = np.asarray(p, dtype=float)[:2] - np.asarray(reference[int(t)], dtype=float)[:2]
        C2 = np.asarray(C, dtype=float)[:2, :2]
        try:
            nees = float(e @ np.linalg.solve(C2, e))
        except np.linalg.LinAlgError:
            continue
        if not np.isfinite(nees) or nees < 0:  # a covariance that is not positive definite says nothing
            continue
        count += 1
        if worst is None or nees > worst[0]:
            worst = (nees, int(t), float(np.linalg.norm(e)))
    if worst is None:
        nan = float("nan")
        return Overconfidence(0, None, nan, nan, nan, nan)
    nees, tag, err = worst
    sigma = err / np.sqrt(nees) if nees > 0 else float("nan")
    return Overconfidence(count, tag, nees, err, float(sigma), float(-2.0 * np.log(false_alarm / count)))


@dataclass(frozen=True)
class NavigationMargin:
    """Room to the walls along the nominal path, in metres and in σ of the simulated robots."""

    margin_m: FloatArray
    """(K,) clearance of the nominal path minus the robot radius."""
    deviation_m: FloatArray
    """(K,) RMS distance of the trials' true positions from the nominal path (active trials)."""
    ekf_sigma_m: FloatArray
    """(K,) mean EKF position σ (sqrt of the largest eigenvalue of the xy covariance)."""

    @property
    def ratio(self) -> FloatArray:
        """Margin over RMS deviation per step."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(self.margin_m / np.maximum(self.deviation_m, 1e-12))

    def summary(self) -> dict[str, float]:
        """At the tightest point (smallest margin / deviation): margin, deviation, EKF σ, ratio."""
        r = self.ratio
        if not len(r) or not np.isfinite(r).any():
            nan = float("nan")
            return {"tight_margin_m": nan, "tight_deviation_m": nan, "tight_ekf_sigma_m": nan, "margin_sigmas": nan}
        k = int(np.nanargmin(r))
        return {
            "tight_margin_m": float(self.margin_m[k]),
            "tight_deviation_m": float(self.deviation_m[k]),
            "tight_ekf_sigma_m": float(self.ekf_sigma_m[k]),
            "margin_sigmas": float(r[k]),
            "min_margin_m": float(np.min(self.margin_m)),
        }


def aligned_error(
    tag_ids: npt.ArrayLike, positions: FloatArray, reference: Mapping[int, FloatArray], only: Iterable[int]
) -> float:
    """Mean distance to ``reference`` after the best rigid planar motion (rotation + translation) of the landmarks.

    The error against the truth in the first-pose frame contains the drift of the path between the start and the
    landmarks, common to all of them; this removes it and leaves the error of the map's shape, the part a robot
    localising against the map feels. NaN with fewer than 3 landmarks.
    """
    fit = rigid_alignment(tag_ids, positions, reference, only)
    if fit is None:
        return float("nan")
    R, t = fit
    want = {int(x) for x in only}
    ids = [int(x) for x in np.asarray(tag_ids).tolist()]
    keep = [k for k, x in enumerate(ids) if x in want and x in reference]
    A = np.asarray(positions, dtype=float)[keep, :2]
    B = np.array([np.asarray(reference[ids[k]], dtype=float)[:2] for k in keep])
    moved = A @ R.T + t
    return float(np.linalg.norm(moved - B, axis=1).mean())


def rigid_alignment(
    tag_ids: npt.ArrayLike,
    positions: FloatArray,
    reference: Mapping[int, FloatArray],
    only: Iterable[int] | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """``(R, t)`` of the best rigid planar motion ``p ↦ R p + t`` of the map's landmarks onto ``reference``.

    None with fewer than 3 common landmarks.
    """
    want = None if only is None else {int(t) for t in only}
    pairs = [
        (np.asarray(p, dtype=float)[:2], np.asarray(reference[int(t)], dtype=float)[:2])
        for t, p in zip(np.asarray(tag_ids).tolist(), positions, strict=True)
        if (want is None or int(t) in want) and int(t) in reference
    ]
    if len(pairs) < 3:
        return None
    A = np.array([a for a, _ in pairs])
    B = np.array([b for _, b in pairs])
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca
