"""Collision risk along the recorded path (Mu et al. 2015, Sec. IV-A): shared by select_landmarks, optimize, evaluate.

Per keyframe ``t`` of the full graph:

* **clearance and obstacle normal**: the laser scan nearest in time (at most ``max_scan_gap_s`` away),
  its valid returns (finite, ``range_min <= r < range_max``) put in the map frame with ``T_base_laser``
  (``ingest/extrinsics.json``) and the optimised path interpolated to each beam's own time (deskewed,
  :mod:`stages.laser`); the nearest return to the keyframe's position gives the
  clearance ``d_t`` (m, from the robot centre) and the unit normal ``n_t`` from the robot towards it.
  No scan near enough, or no valid return: ``d_t = inf`` (no obstacle known, zero risk).
* **visible landmarks** ``L(x_t)``: the tags measured from any keyframe within ``visibility_window_s``
  of ``t`` (the graph's tag factors, plus detect's detections where present, so tags whose detection the
  graph dropped as ambiguous still count as seen).
* **the robot's belief** ``Σ_t``: the robot model (:mod:`stages.estimation.robot`: unicycle, motion noise on
  (v, ω), control period, range-bearing noise, start covariance; the recording's noise where the settings leave
  it open, :func:`robot_model`) follows the path resampled every control period; its filter covariance is
  propagated step by step (heading coupled to position, no cap) and updated with the focused landmarks visible at
  the step, each with the covariance of the landmark *as seen from the step's keyframe*
  (:func:`map_covariances`; the marginal where that is not known) in eq. 26's noise
  (:func:`stages.estimation.collision.forward_covariances`). The simulated robot of evaluate is the same robot.
* **risk**: ``P_t = 1 − Φ(z_t)``, ``z_t = m_t / sqrt(n_tᵀ Σ_xy n_t)`` with the margin ``m_t = d_t − robot_radius_m``
  (the half-plane through the nearest return, shifted by the robot's radius), and the paper's eq. 20
  Mahalanobis measure ``(m_t n_t)ᵀ Σ_xy⁻¹ (m_t n_t)`` beside it. ``z_t`` is kept: it does not underflow.

Everything is planar: poses ``(x, y, yaw)`` and landmark ``(x, y)`` in the graph's map frame (a 3-D
graph is projected onto the floor plane).

API (call from any stage, no run folder needed beyond the inputs)::

    params = RiskParams(robot_radius_m=0.25)
    geometry = path_geometry(loaded, scans, T_base_laser, detections, params)   # once per run
    lmap = LandmarkMap.from_graph(loaded)                                          # or the reduced graph's map
    risk = path_risk(geometry, lmap, focused_tag_ids, params)                      # PathRisk

select_landmarks' ``risk.parquet`` is :func:`stages.select_landmarks.artifacts.risk_table` of two ``PathRisk``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from pipeline.memory import release_freed_memory
from stages.columns import STAMP_NS, TAG_ID
from stages.detect.artifacts import DETECTIONS
from stages.estimation.collision import (
    Contribution,
    StepNoise,
    forward_covariances,
    mahalanobis_to_obstacle,
    margin_sigmas,
    pair_information,
    step_information,
)
from stages.estimation.normal import normal_sf
from stages.estimation.robot import PathSteps, RobotModel, resample_path
from stages.ingest.artifacts import EXTRINSICS, SCANS
from stages.laser import scan_beams

if TYPE_CHECKING:
    import gtsam

    from pipeline.context import StageContext
    from stages.graph.consider import ConsiderTerm
    from stages.graph.load import LoadedGraph
    from stages.graph.problem import GraphProblem

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class RiskParams:
    """Settings of the risk model: the robot model's settings (the select_landmarks settings carry the same names).

    ``None`` noise levels are taken from the recording (:func:`robot_model`).
    """

    robot_radius_m: float = 0.25
    """Radius of the robot's footprint: the margin to an obstacle is clearance − radius."""
    visibility_window_s: float = 1.0
    """A landmark is visible from a keyframe if it was measured from a keyframe this close in time."""
    max_scan_gap_s: float = 0.25
    """The laser scan used for a keyframe must be at most this far from it in time."""
    control_period_s: float = 0.2
    """The robot's control period: the path is followed, and its covariance propagated, in steps this long."""
    speed_sigma_mps: float | None = None
    """Forward-speed noise over one control period; None = from the graph's odometry factors (0.05 m/s if none)."""
    yaw_rate_sigma_radps: float | None = None
    """Yaw-rate noise over one control period; None = from the graph's odometry factors (0.05 rad/s if none)."""
    bearing_sigma_rad: float | None = None
    """Bearing noise of the range-bearing model; None = median of the graph's tag factors (0.02 rad if none)."""
    range_sigma_m: float | None = None
    """Range noise; None = median of the graph's tag factors (0.05 m if none)."""
    initial_sigma_m: float = 0.02
    """Standard deviation of the start position, m."""
    initial_sigma_rad: float = 0.01
    """Standard deviation of the start heading, rad."""


@dataclass(frozen=True)
class LocalCovariances:
    """Landmark covariances given a keyframe's pose, held only for the (keyframe, landmark) pairs the path sees.

    A dense (T, L, 2, 2) array is mostly NaN (a landmark is seen from a few keyframes) and was 34 MB per map on an
    hour's recording (17,890 keyframes, 59 landmarks); here it is ~2 MB. Pairs are sorted by (keyframe, row).
    """

    keyframes: npt.NDArray[np.int64]
    """(n,) keyframe index of each pair."""
    rows: npt.NDArray[np.int64]
    """(n,) landmark row (in the map's ``tag_ids`` order) of each pair."""
    covariances: FloatArray
    """(n, 2, 2) the landmark's position covariance given that keyframe's pose."""
    n_rows: int
    """The map's number of landmarks (rows run ``0 … n_rows − 1``)."""

    @classmethod
    def from_pairs(
        cls, keyframes: npt.ArrayLike, rows: npt.ArrayLike, covariances: npt.ArrayLike, n_rows: int
    ) -> LocalCovariances:
        """The pairs in any order (each pair at most once)."""
        kf = np.asarray(keyframes, dtype=np.int64).ravel()
        rw = np.asarray(rows, dtype=np.int64).ravel()
        cov = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
        order = np.lexsort((rw, kf))
        return cls(kf[order], rw[order], cov[order], int(n_rows))

    def _codes(self, keyframes: npt.NDArray[np.int64], rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        return np.asarray(keyframes, dtype=np.int64) * max(self.n_rows, 1) + np.asarray(rows, dtype=np.int64)

    def lookup(
        self, keyframes: npt.NDArray[np.int64], rows: npt.NDArray[np.int64]
    ) -> tuple[npt.NDArray[np.bool_], FloatArray]:
        """``(found, covariances)`` for the pairs ``(keyframes[i], rows[i])``: covariances NaN where not held."""
        want = self._codes(keyframes, rows)
        have = self._codes(self.keyframes, self.rows)
        at = np.minimum(np.searchsorted(have, want), max(len(have) - 1, 0))
        found = (have[at] == want) if len(have) else np.zeros(len(want), dtype=bool)
        out = np.full((len(want), 2, 2), np.nan)
        out[found] = self.covariances[at[found]]
        return found, out

    def subset(self, keep: npt.NDArray[np.bool_]) -> LocalCovariances:
        """The pairs of the rows where ``keep`` (a mask over rows) is set, rows renumbered as the kept ones."""
        new_row = np.cumsum(keep) - 1
        sel = keep[self.rows]
        return LocalCovariances(
            self.keyframes[sel], new_row[self.rows[sel]], self.covariances[sel], int(np.count_nonzero(keep))
        )


@dataclass
class LandmarkMap:
    """A planar landmark map: positions and marginal covariances by tag id (rows in ``tag_ids`` order)."""

    tag_ids: npt.NDArray[np.int64]
    positions: FloatArray
    """(L, 2) x, y in the map frame."""
    covariances: FloatArray
    """(L, 2, 2) marginal covariance of the position."""
    heights: FloatArray
    """(L,) z in the map frame (for drawing only)."""
    local: LocalCovariances | None = None
    """Or None: covariance of landmark ``l``'s position given keyframe ``t``'s pose (the landmark as seen from that
    pose, :func:`map_covariances`), for the pairs the path sees. This is the landmark uncertainty that matters to a
    robot localising there (eq. 26); the marginal ``covariances`` also carry the drift common to the pose and the
    landmark since the first pose."""
    joint: FloatArray | None = None
    """(2L, 2L) or None: joint covariance of every landmark's (x, y), rows in ``tag_ids`` order."""

    @classmethod
    def from_graph(
        cls, loaded: LoadedGraph, values: gtsam.Values | None = None, marginals: Mapping[int, FloatArray] | None = None
    ) -> LandmarkMap:
        """The map of a loaded graph (:class:`stages.graph.load.LoadedGraph`).

        ``values`` and ``marginals`` default to the graph's own solution; pass a reduced graph's
        optimised ``gtsam.Values`` and marginals by key to get the reduced map (landmarks missing from
        ``values`` are left out).
        """
        vals = values if values is not None else loaded.values
        margs = marginals if marginals is not None else loaded.marginals
        tags, pos, covs, zs = [], [], [], []
        for tag, key in sorted(loaded.landmark_keys.items()):
            if not vals.exists(key) or key not in margs:
                continue
            kind = loaded.kind(key)
            value = kind.read(vals, key)
            xyz = kind.position(value)
            pc = kind.position_cov(value, np.asarray(margs[key]))
            tags.append(int(tag))
            pos.append(xyz[:2])
            zs.append(float(xyz[2]))
            covs.append(pc[:2, :2])
        return cls(
            np.array(tags, dtype=np.int64),
            np.array(pos, dtype=float).reshape(-1, 2),
            np.array(covs, dtype=float).reshape(-1, 2, 2),
            np.array(zs, dtype=float),
        )

    def subset(self, tag_ids: Iterable[int]) -> LandmarkMap:
        """The landmarks with the given tag ids (in this map's order)."""
        keep = np.isin(self.tag_ids, np.fromiter((int(t) for t in tag_ids), dtype=np.int64))
        local = None if self.local is None else self.local.subset(keep)
        joint = None
        if self.joint is not None:
            idx = np.flatnonzero(keep)
            cols = np.stack([2 * idx, 2 * idx + 1], axis=1).ravel()
            joint = self.joint[np.ix_(cols, cols)]
        return LandmarkMap(
            self.tag_ids[keep], self.positions[keep], self.covariances[keep], self.heights[keep], local, joint
        )

    def covariance_at(self, keyframes: npt.NDArray[np.int64], rows: npt.NDArray[np.int64]) -> FloatArray:
        """(n, 2, 2) covariance of landmark ``rows[i]`` for a robot at keyframe ``keyframes[i]``: the local one where
        known, else the marginal."""
        out = self.covariances[rows].copy()
        if self.local is not None:
            found, loc = self.local.lookup(keyframes, rows)
            ok = found & np.isfinite(loc).all(axis=(1, 2))
            out[ok] = loc[ok]
        return out


@dataclass
class PathGeometry:
    """What the risk of a path needs besides the landmark map; computed once per run."""

    stamps_ns: npt.NDArray[np.int64]
    """(T,) keyframe stamps, in time order."""
    poses: FloatArray
    """(T, 3) x, y, yaw of the optimised keyframes in the map frame."""
    clearance_m: FloatArray
    """(T,) distance from the robot centre to the nearest laser return (inf: none known; NaN: no laser at all)."""
    normals: FloatArray
    """(T, 2) unit vector from the robot towards that return (map frame)."""
    obstacles: FloatArray
    """(T, 2) the nearest return in the map frame (NaN where none)."""
    tag_ids: npt.NDArray[np.int64]
    """(L,) tag ids, the columns of ``visible``."""
    visible: BoolArray
    """(T, L) landmark ``l`` visible from keyframe ``t``."""
    robot: RobotModel
    """The robot model with every noise level resolved (the recording's where the settings leave it open)."""
    has_laser: bool
    """Whether clearances come from laser scans (False: risk cannot be computed)."""
    steps: PathSteps
    """The path resampled every control period (what the risk recursion and the navigation step through)."""
    noise: StepNoise
    """The robot's covariance propagation along ``steps``."""
    keyframe_step: npt.NDArray[np.int64]
    """(T,) the step nearest each keyframe."""

    @property
    def sigmas(self) -> tuple[float, float]:
        """Bearing (rad) and range (m) noise of the range-bearing model."""
        return self.robot.sigmas

    def margin(self, params: RiskParams) -> FloatArray:
        """Clearance minus the robot radius (inf where no obstacle is known)."""
        return np.asarray(self.clearance_m - params.robot_radius_m)


@dataclass
class PathRisk:
    """The robot's belief and the collision risk of every keyframe with one landmark map and focused set."""

    sigma: FloatArray
    """(T, 3, 3) covariance of (x, y, yaw) of the robot's filter at the keyframe (causal, along the path)."""
    localised: BoolArray
    """(T,) whether the keyframe sees a focused landmark."""
    p_collision: FloatArray
    """(T,) half-plane collision probability (NaN without laser)."""
    mahalanobis: FloatArray
    """(T,) eq. 20, squared standard deviations to the obstacle (NaN without laser, inf where no obstacle)."""
    z: FloatArray | None = None
    """(T,) margin to the obstacle in standard deviations, ``P = Φ(−z)`` (does not underflow; NaN without laser)."""

    @property
    def min_z(self) -> float:
        """The smallest margin in σ along the path (NaN without laser, inf where no obstacle is known)."""
        if self.z is None or not (~np.isnan(self.z)).any():
            return float("nan")
        return float(np.nanmin(self.z))

    @property
    def max(self) -> float:
        """Maximum collision probability along the path (NaN without laser)."""
        return float(np.max(self.p_collision)) if np.isfinite(self.p_collision).any() else float("nan")

    @property
    def mean(self) -> float:
        """Mean collision probability along the path (NaN without laser)."""
        return float(np.mean(self.p_collision)) if np.isfinite(self.p_collision).any() else float("nan")


# ---------------------------------------------------------------------------------------------- geometry
def _planar_poses(loaded: LoadedGraph) -> FloatArray:
    kind = loaded.graph_model.pose
    out = np.zeros((len(loaded.pose_keys), 3))
    for i, k in enumerate(loaded.pose_keys):
        out[i] = kind.planar_pose(kind.read(loaded.values, k))
    return out


def robot_model(loaded: LoadedGraph, params: RiskParams) -> RobotModel:
    """The robot model of ``params``, with the noise levels they leave open taken from the recording.

    Motion noise: each odometry factor's translation variance (half the trace, rotation invariant) and heading
    variance divided by the time it spans give variance rates (per second); their medians, spread over one control
    period ``dt`` as white noise on (v, ω), give ``σ_v = sqrt(rate / dt)`` (so the robot model drifts as fast as the
    recording's odometry says it does). Range-bearing noise: the median of the graph's tag factors.
    """
    stamp_of = dict(zip(loaded.pose_keys, loaded.pose_stamps_ns, strict=True))
    rate_xy, rate_th, b_var, r_var = [], [], [], []
    for r in loaded.rows:
        C = np.asarray(r.covariance, dtype=float)
        if r.kind == "odometry" and r.type in ("BetweenFactorPose2", "BetweenFactorPose3") and len(r.keys) == 2:
            t0, t1 = stamp_of.get(r.keys[0]), stamp_of.get(r.keys[1])
            if t0 is None or t1 is None or t1 == t0:
                continue
            span = abs(t1 - t0) * 1e-9
            xy, th = (
                ((C[0, 0] + C[1, 1]), C[2, 2]) if r.type == "BetweenFactorPose2" else ((C[3, 3] + C[4, 4]), C[2, 2])
            )
            rate_xy.append(0.5 * xy / span)
            rate_th.append(th / span)
        elif r.kind == "tag" and r.type == "BearingRangeFactor2D":
            b_var.append(C[0, 0])
            r_var.append(C[1, 1])
    dt = params.control_period_s
    s_v = params.speed_sigma_mps or (float(np.sqrt(np.median(rate_xy) / dt)) if rate_xy else 0.05)
    s_w = params.yaw_rate_sigma_radps or (float(np.sqrt(np.median(rate_th) / dt)) if rate_th else 0.05)
    s_b = params.bearing_sigma_rad or (float(np.sqrt(np.median(b_var))) if b_var else 0.02)
    s_r = params.range_sigma_m or (float(np.sqrt(np.median(r_var))) if r_var else 0.05)
    return RobotModel(
        robot_radius_m=params.robot_radius_m,
        control_period_s=dt,
        speed_sigma_mps=s_v,
        yaw_rate_sigma_radps=s_w,
        bearing_sigma_rad=s_b,
        range_sigma_m=s_r,
        initial_sigma_m=params.initial_sigma_m,
        initial_sigma_rad=params.initial_sigma_rad,
    )


def _visibility(
    stamps_ns: npt.NDArray[np.int64],
    tag_ids: npt.NDArray[np.int64],
    observations: Sequence[tuple[int, int]],
    window_s: float,
) -> BoolArray:
    """(T, L) from (keyframe index, tag id) observations, widened to ``±window_s`` around each keyframe."""
    T, L = len(stamps_ns), len(tag_ids)
    col = {int(t): i for i, t in enumerate(tag_ids)}
    seen = np.zeros((T, L), dtype=np.int64)
    for k, tag in observations:
        if tag in col:
            seen[k, col[tag]] = 1
    csum = np.vstack([np.zeros((1, L), dtype=np.int64), np.cumsum(seen, axis=0)])
    w = round(window_s * 1e9)
    lo = np.searchsorted(stamps_ns, stamps_ns - w, side="left")
    hi = np.searchsorted(stamps_ns, stamps_ns + w, side="right")
    return np.asarray((csum[hi] - csum[lo]) > 0)


def _nearest_index(sorted_stamps: npt.NDArray[np.int64], query: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    pos = np.clip(np.searchsorted(sorted_stamps, query), 1, max(len(sorted_stamps) - 1, 1))
    left = sorted_stamps[pos - 1]
    right = sorted_stamps[np.minimum(pos, len(sorted_stamps) - 1)]
    return np.where(np.abs(query - left) <= np.abs(right - query), pos - 1, np.minimum(pos, len(sorted_stamps) - 1))


def scan_clearance(
    poses: FloatArray,
    stamps_ns: npt.NDArray[np.int64],
    scans: pa.Table,
    T_base_laser: FloatArray,
    max_gap_s: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Clearance (T,), unit normals (T, 2) and nearest returns (T, 2) from the scan nearest each keyframe.

    ``scans`` has ingest's ``scans.parquet`` columns; ``T_base_laser`` (4×4) maps laser points into the
    base frame; ``poses`` are the keyframes' (x, y, yaw) in the map frame. Each return is placed at the
    path interpolated to its beam's own time (:func:`stages.laser.scan_beams`, deskewed), the same returns
    the navigation's occupancy grid is built from, and measured from the keyframe's position.
    """
    T = len(poses)
    clearance = np.full(T, np.inf)
    normals = np.tile([1.0, 0.0], (T, 1))
    points = np.full((T, 2), np.nan)
    if scans.num_rows == 0 or T == 0:
        return clearance, normals, points
    s_stamps = np.asarray(scans.column(STAMP_NS).to_numpy(), dtype=np.int64)
    order = np.argsort(s_stamps, kind="stable")
    s_sorted = s_stamps[order]
    nearest = order[_nearest_index(s_sorted, np.asarray(stamps_ns, dtype=np.int64))]
    gap_ok = np.abs(s_stamps[nearest] - stamps_ns) <= max_gap_s * 1e9
    rows, which = np.unique(nearest[gap_ok], return_inverse=True)
    keyframes, which = np.flatnonzero(gap_ok), which.reshape(-1)
    order = np.argsort(which, kind="stable")
    keyframes, which = keyframes[order], which[order]
    for a in range(0, len(rows), CLEARANCE_SCANS):  # a piece of the scans at a time: memory bounded, same numbers
        beams = scan_beams(scans, stamps_ns, poses, T_base_laser, rows[a : a + CLEARANCE_SCANS])
        scan_of, ends = beams.scan[beams.hit], beams.ends[beams.hit]
        del beams
        first = np.searchsorted(scan_of, np.arange(CLEARANCE_SCANS + 1))
        lo, hi = np.searchsorted(which, [a, a + CLEARANCE_SCANS])
        for t, k in zip(keyframes[lo:hi], which[lo:hi], strict=True):
            _nearest_return(poses, t, ends[first[k - a] : first[k - a + 1]], clearance, normals, points)
    return clearance, normals, points


CLEARANCE_SCANS = 512
"""Scans placed at once by :func:`scan_clearance`."""


def _nearest_return(
    poses: FloatArray, t: int, p_map: FloatArray, clearance: FloatArray, normals: FloatArray, points: FloatArray
) -> None:
    """Keyframe ``t``'s nearest of the returns ``p_map`` into ``clearance``, ``normals`` and ``points``."""
    if len(p_map) == 0:
        return
    x, y = poses[t, 0], poses[t, 1]
    d = np.hypot(p_map[:, 0] - x, p_map[:, 1] - y)
    j = int(np.argmin(d))
    clearance[t] = d[j]
    points[t] = p_map[j]
    if d[j] > 0:
        normals[t] = (p_map[j] - [x, y]) / d[j]


def path_geometry(
    loaded: LoadedGraph,
    scans: pa.Table | None,
    T_base_laser: FloatArray | None,
    detections: pa.Table | None,
    params: RiskParams,
) -> PathGeometry:
    """Per-keyframe clearance, obstacle normal and landmark visibility of a loaded graph.

    Args:
        loaded: :class:`stages.graph.load.LoadedGraph` (keyframes, tag factors, noise).
        scans: ingest's ``scans.parquet`` or None (no laser: clearances NaN, ``has_laser`` False).
        T_base_laser: 4×4 from ingest's ``extrinsics.json`` (``sensors.laser.T_base_sensor``); identity if None.
        detections: detect's ``detections.parquet`` (``stamp_ns``, ``tag_id``) or None.
        params: the risk settings.
    """
    stamps = np.asarray(loaded.pose_stamps_ns, dtype=np.int64)
    poses = _planar_poses(loaded)
    tag_ids = np.array(sorted(loaded.landmark_keys), dtype=np.int64)
    index_of_key = {k: i for i, k in enumerate(loaded.pose_keys)}
    obs: list[tuple[int, int]] = [
        (index_of_key[r.keys[0]], int(r.tag_id))
        for r in loaded.rows
        if r.kind == "tag" and r.tag_id is not None and r.keys and r.keys[0] in index_of_key
    ]
    if detections is not None and detections.num_rows and len(stamps):
        d_st = np.asarray(detections.column(STAMP_NS).to_numpy(), dtype=np.int64)
        d_tag = np.asarray(detections.column(TAG_ID).to_numpy(), dtype=np.int64)
        k = _nearest_index(stamps, d_st)
        near = np.abs(stamps[k] - d_st) <= params.visibility_window_s * 1e9
        obs += [(int(a), int(b)) for a, b in zip(k[near], d_tag[near], strict=True)]
    visible = _visibility(stamps, tag_ids, obs, params.visibility_window_s)
    robot = robot_model(loaded, params)
    if scans is not None and scans.num_rows == 0:
        scans = None  # an empty scans.parquet: no laser
    if scans is not None:
        Tbl = np.eye(4) if T_base_laser is None else np.asarray(T_base_laser, dtype=float)
        clearance, normals, points = scan_clearance(poses, stamps, scans, Tbl, params.max_scan_gap_s)
    else:
        clearance = np.full(len(stamps), np.nan)
        normals = np.tile([1.0, 0.0], (len(stamps), 1))
        points = np.full((len(stamps), 2), np.nan)
    steps = path_steps(stamps, poses, robot.control_period_s)
    A, Q = steps.transition(robot)
    noise = StepNoise(A, Q, robot.P0)
    return PathGeometry(
        stamps,
        poses,
        clearance,
        normals,
        points,
        tag_ids,
        visible,
        robot,
        scans is not None,
        steps,
        noise,
        steps.nearest_step(stamps),
    )


def path_steps(stamps_ns: npt.NDArray[np.int64], poses: FloatArray, dt_s: float) -> PathSteps:
    """The path resampled every ``dt_s`` (a single step when it has fewer than two distinct stamps)."""
    if len(np.unique(stamps_ns)) >= 2:
        return resample_path(stamps_ns, poses, dt_s)
    first = np.asarray(poses, dtype=float).reshape(-1, 3)[:1]
    if len(first) == 0:
        first = np.zeros((1, 3))
    stamp = np.asarray(stamps_ns, dtype=np.int64)[:1] if len(stamps_ns) else np.zeros(1, dtype=np.int64)
    return PathSteps(stamp, first, np.zeros((0, 2)), float(dt_s), np.zeros(1, dtype=np.int64))


# ---------------------------------------------------------------------------------------------- risk
def _run_lengths(steps: npt.NDArray[np.int64]) -> FloatArray:
    """For each of the sorted ``steps``, the length of the run of consecutive steps it belongs to."""
    if len(steps) == 0:
        return np.zeros(0)
    starts = np.flatnonzero(np.concatenate([[True], np.diff(steps) > 1]))
    lengths = np.diff(np.concatenate([starts, [len(steps)]]))
    return np.repeat(lengths, lengths).astype(float)


def landmark_contributions(
    geometry: PathGeometry, landmarks: LandmarkMap, tag_ids: Iterable[int]
) -> list[Contribution]:
    """Per tag of ``tag_ids`` (in that order): the path steps that see it and the information of a range-bearing
    measurement of it from each (eq. 26 noise with the landmark's covariance as seen from the step's keyframe,
    :meth:`LandmarkMap.covariance_at`). A tag that is not in the map, or never visible, contributes nothing.

    The landmark's error is the same at every step that sees it, not fresh noise, so over a run of ``n`` consecutive
    steps its covariance enters ``n`` times inflated: the run's measurements together carry the landmark's error
    once (the sensor noise ``R`` stays per step). Without this the belief shrinks below the landmark's own
    uncertainty the longer a landmark stays in view."""
    steps = geometry.steps
    kf = steps.keyframe
    col = {int(t): c for c, t in enumerate(geometry.tag_ids)}
    row_of = {int(t): i for i, t in enumerate(landmarks.tag_ids)}
    out: list[Contribution] = []
    for tag in tag_ids:
        c, r = col.get(int(tag)), row_of.get(int(tag))
        ks = np.flatnonzero(geometry.visible[kf, c]) if c is not None and r is not None else np.zeros(0, np.int64)
        if len(ks) == 0 or r is None:
            out.append((np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3))))
            continue
        covs = landmarks.covariance_at(kf[ks], np.full(len(ks), r, dtype=np.int64))
        covs = covs * _run_lengths(ks)[:, None, None]
        pos = np.repeat(landmarks.positions[r][None], len(ks), axis=0)
        out.append((ks.astype(np.int64), pair_information(steps.poses[ks], pos, covs, geometry.sigmas)))
    return out


def path_risk(
    geometry: PathGeometry,
    landmarks: LandmarkMap,
    focused_tag_ids: Iterable[int],
    params: RiskParams,
    cache: dict[int, Contribution] | None = None,
) -> PathRisk:
    """The robot's belief and collision risk at every keyframe when only ``focused_tag_ids`` of ``landmarks`` are used.

    The belief is the robot model's filter covariance propagated along the path every control period
    (:func:`stages.estimation.collision.forward_covariances`), updated wherever a focused landmark is visible;
    each keyframe takes the step nearest to it.

    Args:
        geometry: from :func:`path_geometry` (once per run).
        landmarks: the landmark map to localise with (the full graph's, or a reduced graph's); tags
            missing from it cannot localise.
        focused_tag_ids: the tags the robot may use (all of ``landmarks.tag_ids`` for the "all" case,
            none for pure dead reckoning).
        params: the risk settings (``robot_radius_m``).
        cache: optional dict reused across calls with the *same* geometry and landmark map: each tag's
            contribution (:func:`landmark_contributions`), so replaying greedy picks costs only the recursion.

    Returns:
        :class:`PathRisk` with ``sigma`` (T, 3, 3), ``localised``, ``p_collision``, ``mahalanobis`` and ``z``.
    """
    tags = sorted({int(t) for t in focused_tag_ids})
    if cache is None:
        contribs = landmark_contributions(geometry, landmarks, tags)
    else:
        todo = [t for t in tags if t not in cache]
        cache.update(zip(todo, landmark_contributions(geometry, landmarks, todo), strict=True))
        contribs = [cache[t] for t in tags]
    K = len(geometry.steps)
    J = step_information(contribs, range(len(contribs)), K)
    cov = forward_covariances(geometry.noise, J[None])[0]
    at = geometry.keyframe_step
    sigma = cov[at]
    localised = np.abs(J[at]).reshape(len(at), 9).max(axis=1) > 0
    T = len(geometry.stamps_ns)
    if not geometry.has_laser:
        nan = np.full(T, np.nan)
        return PathRisk(sigma, localised, nan, nan.copy(), nan.copy())
    margin = geometry.margin(params)
    z = margin_sigmas(sigma, margin, geometry.normals)
    maha = np.array(
        [
            mahalanobis_to_obstacle(sigma[t, :2, :2], margin[t] * geometry.normals[t])
            if np.isfinite(margin[t])
            else np.inf
            for t in range(T)
        ]
    )
    return PathRisk(sigma, localised, np.asarray(normal_sf(z)), maha, z)


def riskiest_keyframes(
    mahalanobis: FloatArray, stamps_ns: npt.NDArray[np.int64], n: int, min_gap_s: float
) -> list[int]:
    """The ``n`` riskiest keyframes by eq. 20 (smallest squared σ to the obstacle; inf = none known is never
    picked), at least ``min_gap_s`` apart in time, so one narrow door does not take them all. In time order."""
    order = np.argsort(np.asarray(mahalanobis, dtype=float), kind="stable")
    gap = round(min_gap_s * 1e9)
    chosen: list[int] = []
    for t in order:
        if len(chosen) >= n or not np.isfinite(mahalanobis[t]):
            break
        if all(abs(int(stamps_ns[t]) - int(stamps_ns[c])) >= gap for c in chosen):
            chosen.append(int(t))
    return sorted(chosen)


def step_margins(geometry: PathGeometry, params: RiskParams) -> tuple[FloatArray, FloatArray]:
    """Margin (K,) and obstacle normal (K, 2) of every path step: those of its nearest keyframe."""
    kf = geometry.steps.keyframe
    return geometry.margin(params)[kf], geometry.normals[kf]


@dataclass(frozen=True)
class PathInputs:
    """What the path-risk computation reads from a run folder (each None where the run lacks it)."""

    scans: pa.Table | None
    T_base_laser: FloatArray | None
    detections: pa.Table | None
    laser_note: str


def read_path_inputs(ctx: StageContext) -> PathInputs:
    """Ingest's laser scans and laser extrinsic and detect's detections, from the run's artifacts.

    ``laser_note`` says why there are no scans ("" when there are).
    """
    scans = T_base_laser = detections = None
    note = ""
    if ctx.has_input("ingest"):
        ingest = ctx.input("ingest")
        if ingest.exists(SCANS.file):
            scans = SCANS.read(ingest)
            release_freed_memory()  # the reader's buffers: ~60 MB kept after an hour's scans
            if scans.num_rows == 0:
                note = "ingest found no laser scans in the recording"
        else:
            note = f"ingest wrote no {SCANS.file} (the recording has no LaserScan topic)"
        if ingest.exists(EXTRINSICS.file):
            laser = EXTRINSICS.read(ingest).sensors.get("laser")
            if laser is not None:
                T_base_laser = np.asarray(laser.T_base_sensor, dtype=float)
    else:
        note = "the run has no ingest stage (a graph from 'focusmap import-graph')"
    if ctx.has_input("detect") and ctx.input("detect").exists(DETECTIONS.file):
        detections = DETECTIONS.read(ctx.input("detect"), columns=[STAMP_NS, TAG_ID])
    return PathInputs(scans, T_base_laser, detections, note)


def map_covariances(
    problem: GraphProblem,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    marginals: Mapping[int, FloatArray],
    landmarks: LandmarkMap,
    geometry: PathGeometry,
    consider: ConsiderTerm | None = None,
) -> tuple[LocalCovariances, FloatArray]:
    """The landmark covariances a robot navigating with the map needs, from the solved graph.

    Returns:
        ``local``: each map landmark's position covariance given the pose of each keyframe that sees it,
        ``Σ_l|t = Σ_ll − Σ_lt Σ_tt⁻¹ Σ_tl`` (held only for the pairs the path sees). With a graph anchored only by its
        first-pose prior this is the landmark's uncertainty in the frame of keyframe ``t``: what a robot standing
        there still has to fear when the map's path and landmarks drifted together since the start (the marginal
        also holds that common drift). ``joint`` (2L, 2L): the joint covariance of all map landmarks' (x, y), the
        considered states of the navigation's Schmidt filter.

    Cross blocks come from sparse solves on the graph's information matrix
    (:func:`stages.estimation.sparse_cov.covariance_blocks`), plus ``consider``'s blocks when the graph's odometry
    rows were corrected by a calibration (its uncertainty, which ``marginals`` already hold and the information
    matrix does not: :mod:`stages.graph.consider`); ``Σ_tt`` from the pose's marginal.
    """
    from stages.estimation.linear_system import information_from_gtsam
    from stages.estimation.sparse_cov import covariance_blocks

    T, L = len(geometry.stamps_ns), len(landmarks.tag_ids)
    local = LocalCovariances.from_pairs([], [], np.zeros((0, 2, 2)), L)
    joint = np.zeros((2 * L, 2 * L))
    for r in range(L):
        joint[2 * r : 2 * r + 2, 2 * r : 2 * r + 2] = landmarks.covariances[r]
    if T == 0 or L == 0 or len(problem.pose_keys) != T:
        return local, joint
    system = information_from_gtsam(graph, values)
    release_freed_memory(collect=False)  # the linearised graph's small blocks: ~90 MB on an hour's graph
    col = {int(t): c for c, t in enumerate(geometry.tag_ids)}
    var = system.index_of_key
    rows: list[tuple[int, int, list[int]]] = []  # map row, landmark variable, keyframes that see it
    for r, tag in enumerate(landmarks.tag_ids.tolist()):
        key = problem.landmark_keys.get(int(tag))
        if key is None:
            continue
        ts = [int(t) for t in np.flatnonzero(geometry.visible[:, col[int(tag)]])] if int(tag) in col else []
        rows.append((r, var(key), ts))
    pairs = [(lv_i, lv_j) for _, lv_i, _ in rows for _, lv_j, _ in rows]
    pairs += [(var(problem.pose_keys[t]), lv) for _, lv, ts in rows for t in ts]
    blocks = covariance_blocks(system.information, system.offsets, pairs)
    del system
    if consider is not None:
        key_of = {var(k): k for k in [*problem.pose_keys, *problem.landmark_keys.values()] if values.exists(k)}
        blocks = {(a, b): blk + consider.block(key_of[a], key_of[b]) for (a, b), blk in blocks.items()}
    jac: dict[int, FloatArray] = {}
    for r, _, _ in rows:
        key = problem.landmark_keys[int(landmarks.tag_ids[r])]
        jac[r] = problem.kind(key).position_jacobian(problem.kind(key).read(values, key))[:2]
    for r_i, lv_i, _ in rows:
        for r_j, lv_j, _ in rows:
            joint[2 * r_i : 2 * r_i + 2, 2 * r_j : 2 * r_j + 2] = jac[r_i] @ blocks[(lv_i, lv_j)] @ jac[r_j].T
    joint = 0.5 * (joint + joint.T)
    kfs: list[npt.NDArray[np.int64]] = []
    map_rows: list[npt.NDArray[np.int64]] = []
    covs: list[FloatArray] = []
    for r, lv, ts in rows:
        if not ts:
            continue
        S_ll = blocks[(lv, lv)]
        S_tl = np.stack([blocks[(var(problem.pose_keys[t]), lv)] for t in ts])
        S_tt = np.stack([np.asarray(marginals[problem.pose_keys[t]], dtype=float) for t in ts])
        cond = S_ll - np.swapaxes(S_tl, 1, 2) @ np.linalg.solve(S_tt, S_tl)
        cond = 0.5 * (cond + np.swapaxes(cond, 1, 2))
        kfs.append(np.asarray(ts, dtype=np.int64))
        map_rows.append(np.full(len(ts), r, dtype=np.int64))
        covs.append(jac[r] @ cond @ jac[r].T)
    if covs:
        local = LocalCovariances.from_pairs(np.concatenate(kfs), np.concatenate(map_rows), np.concatenate(covs), L)
    return local, joint


def full_local_map(loaded: LoadedGraph, geometry: PathGeometry) -> LandmarkMap:
    """The full graph's map with each landmark's covariance as seen from the keyframes that see it
    (:func:`map_covariances`), the odometry calibration's uncertainty included (select_landmarks' risk model and
    optimize's full-map risk)."""
    lm = LandmarkMap.from_graph(loaded)
    lm.local, lm.joint = map_covariances(
        loaded, loaded.graph, loaded.values, loaded.marginals, lm, geometry, loaded.consider_term()
    )
    return lm
