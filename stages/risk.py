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
* **Σ*(x_t)**: the steady state of belief stabilisation (eq. 19) at ``x_t`` with the *given* landmark
  map restricted to the focused tags that are visible (range-bearing model, measurement noise that
  includes the landmark's own marginal, eq. 26), via
  :func:`stages.estimation.collision.stabilised_covariances`. A pose that sees no focused
  landmark gets dead reckoning from the nearest localised pose along the path,
  ``Σ(t) = Σ*(s) + min(|t − s|, cap_steps) · Q``, and ``cap_steps · Q`` when no pose is localised.
* **risk**: ``P_t = 1 − Φ(m_t / sqrt(n_tᵀ Σ_xy n_t))`` with the margin ``m_t = d_t − robot_radius_m``
  (the half-plane through the nearest return, shifted by the robot's radius), and the paper's eq. 20
  Mahalanobis measure ``(m_t n_t)ᵀ Σ_xy⁻¹ (m_t n_t)`` beside it.

Everything is planar: poses ``(x, y, yaw)`` and landmark ``(x, y)`` in the graph's map frame (a 3-D
graph is projected onto the floor plane). ``Q`` is isotropic in ``(x, y)``: the median over the graph's
odometry factors of half the trace of their translation covariance (rotation invariant, so no frame is
needed), and the median heading variance.

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

from stages.columns import STAMP_NS, TAG_ID
from stages.detect.artifacts import DETECTIONS
from stages.estimation.collision import (
    collision_risk,
    dead_reckoning_covariances,
    mahalanobis_to_obstacle,
    measurement_information,
    stabilised_covariances,
)
from stages.ingest.artifacts import EXTRINSICS, SCANS
from stages.laser import scan_beams

if TYPE_CHECKING:
    import gtsam

    from pipeline.context import StageContext
    from stages.graph.load import LoadedGraph

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class RiskParams:
    """Settings of the risk model (the select_landmarks settings carry the same names)."""

    robot_radius_m: float = 0.25
    """Radius of the robot's footprint: the margin to an obstacle is clearance − radius."""
    visibility_window_s: float = 1.0
    """A landmark is visible from a keyframe if it was measured from a keyframe this close in time."""
    max_scan_gap_s: float = 0.25
    """The laser scan used for a keyframe must be at most this far from it in time."""
    cap_steps: int = 50
    """Dead reckoning of poses that see no focused landmark is capped at this many odometry steps."""
    bearing_sigma_rad: float | None = None
    """Bearing noise of the range-bearing model; None = median of the graph's tag factors (0.02 rad if none)."""
    range_sigma_m: float | None = None
    """Range noise; None = median of the graph's tag factors (0.05 m if none)."""
    odometry_sigma_m: float | None = None
    """Translation noise per keyframe step; None = from the graph's odometry factors (0.02 m if none)."""
    odometry_sigma_rad: float | None = None
    """Heading noise per keyframe step; None = from the graph's odometry factors (0.01 rad if none)."""


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
        return LandmarkMap(self.tag_ids[keep], self.positions[keep], self.covariances[keep], self.heights[keep])


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
    Q: FloatArray
    """(3, 3) process noise per keyframe step (x, y, yaw)."""
    sigmas: tuple[float, float]
    """Bearing (rad) and range (m) noise of the range-bearing model."""
    has_laser: bool
    """Whether clearances come from laser scans (False: risk cannot be computed)."""

    def margin(self, params: RiskParams) -> FloatArray:
        """Clearance minus the robot radius (inf where no obstacle is known)."""
        return np.asarray(self.clearance_m - params.robot_radius_m)


@dataclass
class PathRisk:
    """Σ* and the collision risk of every keyframe with one landmark map and focused set."""

    sigma: FloatArray
    """(T, 3, 3) covariance of (x, y, yaw): Σ* where a focused landmark is visible, dead reckoning elsewhere."""
    localised: BoolArray
    """(T,) whether the keyframe sees a focused landmark."""
    p_collision: FloatArray
    """(T,) half-plane collision probability (NaN without laser)."""
    mahalanobis: FloatArray
    """(T,) eq. 20, squared standard deviations to the obstacle (NaN without laser, inf where no obstacle)."""

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


def _noise_from_graph(loaded: LoadedGraph, params: RiskParams) -> tuple[FloatArray, tuple[float, float]]:
    """``Q`` (isotropic in x, y) and the range-bearing sigmas, from the graph's factors unless set."""
    q_xy, q_th, b_var, r_var = [], [], [], []
    for r in loaded.rows:
        C = np.asarray(r.covariance, dtype=float)
        if r.kind == "odometry":
            if r.type == "BetweenFactorPose2":
                q_xy.append(0.5 * (C[0, 0] + C[1, 1]))
                q_th.append(C[2, 2])
            elif r.type == "BetweenFactorPose3":
                q_xy.append(0.5 * (C[3, 3] + C[4, 4]))
                q_th.append(C[2, 2])
        elif r.kind == "tag" and r.type == "BearingRangeFactor2D":
            b_var.append(C[0, 0])
            r_var.append(C[1, 1])
    s_xy = params.odometry_sigma_m or (float(np.sqrt(np.median(q_xy))) if q_xy else 0.02)
    s_th = params.odometry_sigma_rad or (float(np.sqrt(np.median(q_th))) if q_th else 0.01)
    s_b = params.bearing_sigma_rad or (float(np.sqrt(np.median(b_var))) if b_var else 0.02)
    s_r = params.range_sigma_m or (float(np.sqrt(np.median(r_var))) if r_var else 0.05)
    return np.diag([s_xy**2, s_xy**2, s_th**2]), (s_b, s_r)


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
    beams = scan_beams(scans, stamps_ns, poses, T_base_laser, rows)
    returns = beams.hit
    scan_of, ends = beams.scan[returns], beams.ends[returns]
    first = np.searchsorted(scan_of, np.arange(len(rows) + 1))
    for t, k in zip(np.flatnonzero(gap_ok), which.reshape(-1), strict=True):
        p_map = ends[first[k] : first[k + 1]]
        if len(p_map) == 0:
            continue
        x, y = poses[t, 0], poses[t, 1]
        d = np.hypot(p_map[:, 0] - x, p_map[:, 1] - y)
        j = int(np.argmin(d))
        clearance[t] = d[j]
        points[t] = p_map[j]
        if d[j] > 0:
            normals[t] = (p_map[j] - [x, y]) / d[j]
    return clearance, normals, points


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
    Q, sigmas = _noise_from_graph(loaded, params)
    if scans is not None and scans.num_rows == 0:
        scans = None  # an empty scans.parquet: no laser
    if scans is not None:
        Tbl = np.eye(4) if T_base_laser is None else np.asarray(T_base_laser, dtype=float)
        clearance, normals, points = scan_clearance(poses, stamps, scans, Tbl, params.max_scan_gap_s)
    else:
        clearance = np.full(len(stamps), np.nan)
        normals = np.tile([1.0, 0.0], (len(stamps), 1))
        points = np.full((len(stamps), 2), np.nan)
    return PathGeometry(stamps, poses, clearance, normals, points, tag_ids, visible, Q, sigmas, scans is not None)


# ---------------------------------------------------------------------------------------------- risk
def _risk_of(geometry: PathGeometry, sigma: FloatArray, params: RiskParams) -> tuple[FloatArray, FloatArray]:
    T = len(geometry.stamps_ns)
    if not geometry.has_laser:
        return np.full(T, np.nan), np.full(T, np.nan)
    margin = geometry.margin(params)
    p = collision_risk(sigma, margin, geometry.normals, [0, 1])
    maha = np.array(
        [
            mahalanobis_to_obstacle(sigma[t, :2, :2], margin[t] * geometry.normals[t])
            if np.isfinite(margin[t])
            else np.inf
            for t in range(T)
        ]
    )
    return np.asarray(p), maha


def _information(pose: FloatArray, landmarks: LandmarkMap, rows: list[int], sigmas: tuple[float, float]) -> FloatArray:
    return measurement_information(pose, landmarks.positions[rows], landmarks.covariances[rows], sigmas)


def path_risk(
    geometry: PathGeometry,
    landmarks: LandmarkMap,
    focused_tag_ids: Iterable[int],
    params: RiskParams,
    cache: dict[tuple[int, frozenset[int]], FloatArray] | None = None,
) -> PathRisk:
    """Σ* and the collision risk of every keyframe when only ``focused_tag_ids`` of ``landmarks`` are used.

    Args:
        geometry: from :func:`path_geometry` (once per run).
        landmarks: the landmark map to localise with (the full graph's, or a reduced graph's); tags
            missing from it cannot localise.
        focused_tag_ids: the tags the robot may use (all of ``landmarks.tag_ids`` for the "all" case,
            none for pure dead reckoning).
        params: the risk settings (``robot_radius_m``, ``cap_steps``).
        cache: optional dict reused across calls with the *same* geometry, landmark map and params:
            Σ* by (keyframe, set of visible focused tags), so replaying greedy picks costs only the
            poses whose visible set changed.

    Returns:
        :class:`PathRisk` with ``sigma`` (T, 3, 3), ``localised``, ``p_collision`` and ``mahalanobis``.
    """
    T = len(geometry.stamps_ns)
    focused = {int(t) for t in focused_tag_ids}
    row_of = {int(t): i for i, t in enumerate(landmarks.tag_ids)}
    cols = [(c, row_of[int(t)]) for c, t in enumerate(geometry.tag_ids) if int(t) in focused and int(t) in row_of]
    sig = np.zeros((T, 3, 3))
    localised = np.zeros(T, dtype=bool)
    if cols:
        vis = geometry.visible[:, [c for c, _ in cols]]
        todo: list[tuple[int, tuple[int, frozenset[int]]]] = []
        for t in np.flatnonzero(vis.any(axis=1)):
            rows = frozenset(r for (_, r), v in zip(cols, vis[t], strict=True) if v)
            key = (int(t), rows)
            localised[t] = True
            if cache is not None and key in cache:
                sig[t] = cache[key]
            else:
                todo.append((int(t), key))
        if todo:
            J = np.array([_information(geometry.poses[t], landmarks, sorted(k[1]), geometry.sigmas) for t, k in todo])
            S = stabilised_covariances(geometry.Q, J, params.cap_steps)
            for (t_todo, key), s_t in zip(todo, S, strict=True):
                sig[t_todo] = s_t
                if cache is not None:
                    cache[key] = s_t
    sigma = dead_reckoning_covariances(sig, localised, geometry.Q, params.cap_steps)
    p, maha = _risk_of(geometry, sigma, params)
    return PathRisk(sigma, localised, p, maha)


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
