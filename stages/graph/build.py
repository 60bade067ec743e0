"""Build the full SLAM problem of a recorded run from ingest's odometry and extrinsics and detect's tags.

Keyframes are the stamps of camera frames that saw tags, plus odometry stamps wherever the robot
went too long, too far or turned too much without one (so the path stays connected). Odometry is
interpolated on SE(2)/SE(3) to the keyframe stamps. Factors:

- ``prior`` on the first keyframe (it defines the map frame);
- ``odometry`` between consecutive keyframes (noise from the messages' covariances or the settings),
  or ``motion_prior`` (zero motion, weak) when the run has no odometry;
- ``tag``: one per detection. ``3d``: ``BetweenFactorPose3(X(k), L(tag))`` with ``T_base_tag =
  T_base_camera T_camera_tag`` and the detection's 6x6 covariance (right perturbation, so the
  extrinsic does not change it). ``planar``: the tag centre in the base frame, its 3x3 covariance
  ``R_base_tag Σ_tt R_base_tag^T`` projected onto (x, y), expressed as a ``BearingRangeFactor2D``
  to a ``Point2`` landmark (the bearing-range form of the same 2D relative position, to first order).
- ``tag_prior`` (``--tags`` with surveyed tags, 3d model): ``PriorFactorPose3(L(tag))`` at the tag's pose in
  TagSLAM's world frame with its 6x6 covariance (ingest's ``tags.json``). When a surveyed tag is seen, these
  priors define the map frame instead of the prior on the first keyframe, and the initial values are moved
  into that frame (from the first sighting of a surveyed tag).
- ``scale_prior`` (``graph.tag_scale_sigma > 0``): the shared tag scale ``s`` ~ N(1, sigma²); every tag
  factor then carries ``s`` as a third key and measures ``s`` times its range (planar) or translation (3d).
"""

from __future__ import annotations

import copy
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt
import pyarrow as pa
from gtsam.symbol_shorthand import L, X

from pipeline.errors import InputError, StageError
from stages.columns import FRAME, POSITION, QUATERNION, STAMP_NS, TAG_ID
from stages.detect.artifacts import AMBIGUOUS, CAMERA, DETECTIONS, REPROJECTION_PX, SIZE_M, T_CAMERA_TAG
from stages.detect.artifacts import POSE_COV as DETECTION_POSE_COV
from stages.geometry import pose3_from_matrix, pose3_from_vector, pose3_to_vector
from stages.graph.bodies import moving_body_detections
from stages.graph.config import GraphConfig
from stages.graph.factors import SCALE_KEY, FactorRow
from stages.graph.model_choice import choose_model
from stages.graph.models import MIN_PLANAR_RANGE_M, GraphModel, graph_model
from stages.graph.odometry import Odometry, growth_model, keyframes, message_cov, settings_cov, unobserved_dims
from stages.graph.problem import GraphProblem
from stages.graph.rig import (
    GIVEN_PRIOR,
    MountEstimate,
    given_mount_figures,
    inflated,
    initial_mounts,
    is_loose,
    refine_mounts,
)
from stages.graph.tag_motion import motion_pairs, mounting_figures, ratio_figures
from stages.graph.variables import SCALE
from stages.ingest.artifacts import EXTRINSICS, Extrinsics, SensorMount, TagsInfo
from stages.ingest.artifacts import POSE_COV as ODOMETRY_POSE_COV

FloatArray = npt.NDArray[np.float64]

__all__ = ["MIN_PLANAR_RANGE_M", "Odometry", "build_problem", "camera_extrinsic", "camera_mount"]

DETECTION_COLUMNS = (FRAME, STAMP_NS, CAMERA, TAG_ID, T_CAMERA_TAG, DETECTION_POSE_COV)
"""Columns of ``detections.parquet`` the graph needs."""
DETECTION_FILTER_COLUMNS = (AMBIGUOUS, REPROJECTION_PX, SIZE_M)
"""Columns of ``detections.parquet`` the graph filters on or reports (when present)."""
ODOMETRY_COLUMNS = (STAMP_NS, *POSITION, *QUATERNION, ODOMETRY_POSE_COV)
"""Columns of ``odometry.parquet`` the graph needs."""


def camera_extrinsic(extrinsics: Extrinsics | None, camera: str) -> tuple[gtsam.Pose3, str]:
    """``T_base_camera`` for a detection's ``camera`` value (a sensor role, else a sensor's frame id, else the
    ``camera`` role), and where it came from."""
    entry = camera_mount(extrinsics, camera)
    if entry is None:
        return gtsam.Pose3(), f"identity (no base-to-camera transform in {EXTRINSICS.file})"
    return pose3_from_matrix(entry.T_base_sensor), EXTRINSICS.file


def camera_mount(extrinsics: Extrinsics | None, camera: str) -> SensorMount | None:
    """The mount of a detection's ``camera`` value: the sensor of that role, else of that topic, else of that
    frame id, else the ``camera`` role; None when there is none."""
    sensors = extrinsics.sensors if extrinsics is not None else {}
    entry = sensors.get(camera)
    if entry is None:
        entry = next((s for s in sensors.values() if s.topic == camera), None)
    if entry is None:
        entry = next((s for s in sensors.values() if s.frame_id == camera), None)
    return entry if entry is not None else sensors.get("camera")


def _cameras_without_mount(cameras: list[Any], extrinsics: Extrinsics | None) -> set[str]:
    """Of a rig with several cameras, those whose mount was assumed (no transform recorded or given): their
    detections would place the tags wrongly, so the graph leaves them out (ingest warns about each)."""
    names = {str(c) for c in set(cameras)}
    if len(names) < 2:
        return set()
    mounts = {c: camera_mount(extrinsics, c) for c in names}
    return {c for c, m in mounts.items() if m is not None and m.assumed}


def build_problem(
    detections: pa.Table,
    odometry: pa.Table | None,
    extrinsics: Extrinsics | None,
    cfg: GraphConfig,
    tags: TagsInfo | None = None,
) -> GraphProblem:
    """The full graph of a run: keyframes, factors and initial values (see the module docstring); ``tags``:
    ingest's ``tags.json`` (ignored tags are left out, surveyed tags get priors).

    Raises:
        StageError: when nothing is left to build a graph from.
        InputError: when the detection table lacks a needed column.
    """
    moving = tags.moving_tags if tags else {}
    det, usable, info = _usable_detections(
        detections, cfg, extrinsics, tags.ignore_tags if tags else (), moving, keep_unmounted=cfg.rig_calibration
    )
    if tags is not None and tags.tag_id_remap:
        _remap_ids(det, tags, extrinsics, info)
    odom = Odometry.from_table(odometry)
    estimates, usable = _initial_rig(det, usable, extrinsics, cfg, info)
    if checked := _given_mounts_against_data(det, usable, extrinsics, set(estimates)):
        info["rig_check"] = checked
    if not estimates:
        return _with_cameras(*_assemble(det, usable, odom, extrinsics, cfg, tags, info))
    placed = _with_mounts(extrinsics, estimates, "initial")
    spatial = cfg.model_copy(update={"model": "3d", "odometry_calibration": False})
    subset = _rig_subset(det, usable)
    problem3, row_cameras = _assemble(det, subset, odom, placed, spatial, tags, copy.deepcopy(info))
    try:
        figures = refine_mounts(problem3.rows, row_cameras, problem3.initial, estimates)
    except RuntimeError as err:  # GTSAM: the graph with the mounts free is singular (too few sightings)
        figures = {"not_refined": " ".join(str(err).split()).split(". ")[0]}
    if len(subset) < len(usable):
        _scale_to_all_sightings(det, usable, subset, estimates, figures)
    problem = _with_cameras(
        *_assemble(det, usable, odom, _with_mounts(extrinsics, estimates, "estimated"), cfg, tags, info, estimates)
    )
    base = extrinsics.base_frame if extrinsics is not None else "base"
    given = {}
    for cam in sorted({str(det[CAMERA][r]) for r in usable} - set(estimates)):
        mount = camera_mount(extrinsics, cam)
        given[cam] = {
            "frame_id": mount.frame_id if mount is not None else cam,
            "T_base_camera": np.asarray(camera_extrinsic(extrinsics, cam)[0].matrix()).round(9).tolist(),
        }
    cameras = {}
    for cam, est in sorted(estimates.items()):
        mount = camera_mount(extrinsics, cam)
        cameras[cam] = {"frame_id": mount.frame_id if mount is not None else cam, **est.summary(base)}
        if est.covariance is not None:
            cameras[cam]["covariance"] = np.asarray(est.covariance).tolist()
    problem.info["rig_calibration"] = {
        "cameras": cameras,
        "given": given,
        "solve": figures,
        **problem.info.get("rig_calibration", {}),
    }
    return problem


def _with_cameras(problem: GraphProblem, row_cameras: list[str | None]) -> GraphProblem:
    problem.row_cameras = row_cameras
    return problem


def _assemble(
    det: dict[str, list[Any]],
    usable: np.ndarray,
    odom: Odometry | None,
    extrinsics: Extrinsics | None,
    cfg: GraphConfig,
    tags: TagsInfo | None,
    info: dict[str, Any],
    mounts: dict[str, MountEstimate] | None = None,
) -> tuple[GraphProblem, list[str | None]]:
    """The graph of the usable detections with the mounts ``extrinsics`` gives (``mounts``: cameras whose mount
    was estimated, their sightings carrying its covariance), and the camera of each row (None for non-tag rows)."""
    stamps = np.asarray(det[STAMP_NS], dtype=np.int64)
    choice = choose_model(cfg.model, odom, det, usable, lambda cam: camera_extrinsic(extrinsics, cam)[0], det[TAG_ID])
    model = graph_model(choice.model)
    info["model_choice"] = choice.summary()
    if SIZE_M in det:
        info["tag_size_m"] = _common_size(det[SIZE_M], usable)
    path = _keyframe_path(np.unique(stamps[usable]), odom, cfg, info)
    rows = _prior_rows(model, cfg, path.pose_keys[0])
    rows += _motion_rows(model, cfg, odom, path, info)
    order = usable[np.argsort(stamps[usable], kind="stable")]
    scale_keys = (SCALE_KEY,) if cfg.tag_scale_sigma > 0 else ()
    covs = {c: m.covariance for c, m in (mounts or {}).items() if m.covariance is not None}
    sightings = _tag_rows(model, cfg, det, order, path, scale_keys, extrinsics, info, covs)
    if odom is not None:
        info["tag_odometry_ratio"], info["camera_mounting"] = _tags_against_odometry(det, order, path, extrinsics)
    rows += sightings.rows
    known = _known_tag_rows(model, tags, sightings, info) if tags is not None else []
    surveyed = {int(r.tag_id): pose3_from_vector(r.measurement) for r in known if r.tag_id is not None}
    if odom is None:
        path.poses = model.chain_from_tags(len(path.stamps_ns), sightings.relative, surveyed)
    if known:
        rows = [r for r in rows if r.kind != "prior"] + known
        if odom is not None:
            _move_to_world(path, sightings, surveyed)
    initial, var_types = _initial_values(model, path, sightings, bool(scale_keys), surveyed)
    if scale_keys:
        info["tag_scale_sigma"] = cfg.tag_scale_sigma
    info["keyframes"] = len(path.stamps_ns)
    info["tag_keyframes"] = int(path.is_tag.sum())
    info["odometry_keyframes"] = int(len(path.stamps_ns) - path.is_tag.sum())
    problem = GraphProblem(
        model=model.name,
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=path.pose_keys,
        pose_stamps_ns=[int(s) for s in path.stamps_ns],
        landmark_keys=dict(sorted(sightings.landmark_keys.items())),
        landmark_heights=sightings.landmark_heights(),
        info=info,
    )
    camera_of = {id(r): c for r, c in zip(sightings.rows, sightings.cameras, strict=True)}
    return problem, [camera_of.get(id(r)) for r in rows]


RIG_MAX_MOMENTS = 400
"""The rig solve uses the sightings of at most this many moments, evenly spread over the run (its Python factors
cost about a millisecond each per iteration; a mount's six numbers need far fewer sightings than an hour holds)."""


def _rig_subset(det: dict[str, list[Any]], usable: np.ndarray) -> np.ndarray:
    """The usable rows at :data:`RIG_MAX_MOMENTS` moments evenly spread over the run (all of them when fewer)."""
    stamps = np.asarray(det[STAMP_NS], dtype=np.int64)[usable]
    moments = np.unique(stamps)
    if len(moments) <= RIG_MAX_MOMENTS:
        return usable
    kept = moments[np.linspace(0, len(moments) - 1, RIG_MAX_MOMENTS).round().astype(int)]
    return usable[np.isin(stamps, kept)]


def _scale_to_all_sightings(
    det: dict[str, list[Any]],
    usable: np.ndarray,
    subset: np.ndarray,
    estimates: dict[str, MountEstimate],
    figures: dict[str, Any],
) -> None:
    """A mount solved from a subset of the moments has the covariance of that subset: scale it by the share of the
    camera's sightings the subset holds (information grows with the number of sightings), in place."""
    cams = np.asarray([str(c) for c in det[CAMERA]], dtype=object)
    shares = {}
    for cam, est in estimates.items():
        n_all = int((cams[usable] == cam).sum())
        n_sub = int((cams[subset] == cam).sum())
        if est.covariance is not None and n_all > 0 and n_sub > 0:
            est.covariance = est.covariance * (n_sub / n_all)
            shares[cam] = round(n_sub / n_all, 4)
    figures["moments_used"] = RIG_MAX_MOMENTS
    figures["sighting_share"] = shares


def _initial_rig(
    det: dict[str, list[Any]], usable: np.ndarray, extrinsics: Extrinsics | None, cfg: GraphConfig, info: dict[str, Any]
) -> tuple[dict[str, MountEstimate], np.ndarray]:
    """Initial mounts of the rig's cameras that have none (:mod:`stages.graph.rig`), and the usable rows without
    the sightings of those that cannot be placed."""
    cams = np.asarray([str(c) for c in det[CAMERA]], dtype=object)
    if not cfg.rig_calibration:
        return {}, usable
    unmounted = _cameras_without_mount(list(cams[usable]), extrinsics)
    known = {str(c): camera_extrinsic(extrinsics, str(c))[0] for c in set(cams[usable]) - unmounted}
    loose = {}
    for c in sorted(known):
        mount = camera_mount(extrinsics, c)
        if mount is not None and is_loose(mount.information):
            info_c = np.asarray(mount.information, dtype=float)
            loose[c] = MountEstimate(c, known[c], 0, GIVEN_PRIOR, 0.0, initial=known[c], prior=info_c)
    if not unmounted and not loose:
        return {}, usable
    estimates, unplaced = initial_mounts(*_sighting_arrays(det, usable), known, unmounted)
    estimates.update(loose)
    if unplaced:
        off = np.isin(cams[usable], unplaced)
        info["rig_calibration"] = {
            "unplaced": {c: int((cams[usable] == c).sum()) for c in unplaced},
        }
        usable = usable[~off]
    return estimates, usable


def _given_mounts_against_data(
    det: dict[str, list[Any]], usable: np.ndarray, extrinsics: Extrinsics | None, estimated: set[str]
) -> dict[str, dict[str, Any]]:
    """Each given camera mount of a rig against the one its sightings shared with the other given cameras imply
    (:func:`stages.graph.rig.given_mount_figures`); empty for a single camera."""
    cams = np.asarray([str(c) for c in det[CAMERA]], dtype=object)[usable]
    given = {c: camera_extrinsic(extrinsics, c)[0] for c in sorted(set(cams) - estimated)}
    if len(given) < 2 or _cameras_without_mount(list(given), extrinsics):
        return {}
    return given_mount_figures(*_sighting_arrays(det, usable), given)


def _sighting_arrays(
    det: dict[str, list[Any]], rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The stamps, tag ids, cameras and ``T_camera_tag`` (n x 4 x 4) of the detections ``rows``, as the rig's
    functions (:mod:`stages.graph.rig`) take them."""
    return (
        np.asarray(det[STAMP_NS], dtype=np.int64)[rows],
        np.asarray(det[TAG_ID], dtype=np.int64)[rows],
        np.asarray([str(det[CAMERA][r]) for r in rows], dtype=object),
        np.asarray([det[T_CAMERA_TAG][r] for r in rows], dtype=float).reshape(-1, 4, 4),
    )


def _with_mounts(extrinsics: Extrinsics | None, estimates: dict[str, MountEstimate], how: str) -> Extrinsics:
    """``extrinsics`` with the mounts of ``estimates``' cameras in place of the assumed ones."""
    base = extrinsics if extrinsics is not None else Extrinsics(base_frame="base")
    sensors = dict(base.sensors)
    for cam, est in estimates.items():
        mount = camera_mount(base, cam)
        role = next((r for r, m in base.sensors.items() if m is mount), cam)
        frame = mount.frame_id if mount is not None else cam
        sensors[role] = SensorMount(
            frame_id=frame,
            T_base_sensor=np.asarray(est.pose.matrix()).tolist(),
            assumed=False,
            topic=mount.topic if mount is not None else cam,
            source=f"{how} from {est.pairs} sightings shared with {est.via} (graph rig calibration)",
        )
    return base.model_copy(update={"sensors": sensors})


def _common_size(sizes: list[Any], usable: np.ndarray) -> float | None:
    """The tag size most usable detections assumed (the health check names it), None when unknown."""
    counts = Counter(float(sizes[r]) for r in usable if sizes[r] is not None)
    return counts.most_common(1)[0][0] if counts else None


def _usable_detections(
    detections: pa.Table,
    cfg: GraphConfig,
    extrinsics: Extrinsics | None = None,
    ignore_tags: Any = (),
    moving_tags: dict[str, list[int]] | None = None,
    keep_unmounted: bool = False,
) -> tuple[dict[str, list[Any]], np.ndarray, dict[str, Any]]:
    """The detection columns, the indices of the rows the graph uses, and the counts of those it leaves out."""
    if missing := sorted(set(DETECTION_COLUMNS) - set(detections.column_names)):
        raise InputError(f"{DETECTIONS.file} lacks columns {missing}; re-run 'focusmap detect'")
    wanted = [c for c in (*DETECTION_COLUMNS, *DETECTION_FILTER_COLUMNS) if c in detections.column_names]
    det = detections.select(wanted).to_pydict()
    n_det = detections.num_rows
    keep = np.ones(n_det, dtype=bool)
    info: dict[str, Any] = {"detections": n_det}
    if cfg.drop_ambiguous and AMBIGUOUS in det:
        amb = np.array([bool(a) for a in det[AMBIGUOUS]], dtype=bool)
        info["dropped_ambiguous"] = int((amb & keep).sum())
        keep &= ~amb
    if REPROJECTION_PX in det:
        rep = np.asarray(det[REPROJECTION_PX], dtype=float)
        bad = ~(rep <= cfg.max_reprojection_px)
        info["dropped_reprojection"] = int((bad & keep).sum())
        keep &= ~bad
    if len(ignore_tags):
        ignored = np.isin(np.asarray(det[TAG_ID], dtype=np.int64), np.asarray(ignore_tags, dtype=np.int64))
        info["dropped_ignored_tags"] = int((ignored & keep).sum())
        info["ignored_tags_seen"] = sorted({int(t) for t, i in zip(det[TAG_ID], ignored, strict=True) if i})
        keep &= ~ignored
    if moving_tags:  # tags of a moving body (tagslam.yaml is_static: false): stages.graph.bodies
        keep &= ~moving_body_detections(det[TAG_ID], keep, moving_tags, info)
    if not keep_unmounted and (unmounted := _cameras_without_mount(det[CAMERA], extrinsics)):
        off = np.isin(np.asarray(det[CAMERA], dtype=object), sorted(unmounted))
        info["dropped_camera_without_extrinsics"] = {
            c: int((off & keep)[np.asarray(det[CAMERA]) == c].sum()) for c in sorted(unmounted)
        }
        keep &= ~off
    counts = Counter(int(t) for t, k in zip(det[TAG_ID], keep, strict=True) if k)
    rare = sorted(t for t, c in counts.items() if c < cfg.min_tag_observations)
    info["tags_dropped_few_observations"] = rare
    info["tags_seen_once"] = sorted(t for t, c in counts.items() if c == 1)
    keep &= ~np.isin(np.asarray(det[TAG_ID], dtype=np.int64), rare)
    if not keep.any():
        raise StageError(
            f"no usable tag detections among {n_det} (ambiguous, reprojection above {cfg.max_reprojection_px} px, "
            f"or tags seen fewer than {cfg.min_tag_observations} times); relax the graph settings or check detect"
        )
    return det, np.flatnonzero(keep), info


@dataclass
class _KeyframePath:
    """The keyframes: stamps, keys, dead-reckoned poses in the frame of the first, odometry there."""

    stamps_ns: np.ndarray
    is_tag: np.ndarray
    pose_keys: list[int]
    poses: list[gtsam.Pose3]
    """Dead reckoning relative to the first keyframe (identity without odometry, until the tags place them)."""
    odometry_poses: list[gtsam.Pose3]
    odometry_covs: np.ndarray

    @property
    def index(self) -> dict[int, int]:
        return {int(s): i for i, s in enumerate(self.stamps_ns)}


def _keyframe_path(
    det_stamps: np.ndarray, odom: Odometry | None, cfg: GraphConfig, info: dict[str, Any]
) -> _KeyframePath:
    """Keyframes at the tag frames (and odometry gaps), with the odometry interpolated to them."""
    stamps, is_tag = keyframes(det_stamps, odom, cfg)
    n = len(stamps)
    pose_keys = [int(X(i)) for i in range(n)]
    if odom is None:
        return _KeyframePath(stamps, is_tag, pose_keys, [gtsam.Pose3()] * n, [], np.zeros((0, 6, 6)))
    odo_poses, odo_covs = odom.at(stamps)
    info["keyframes_outside_odometry"] = int(((stamps < odom.stamps_ns[0]) | (stamps > odom.stamps_ns[-1])).sum())
    origin = odo_poses[0].inverse()
    return _KeyframePath(stamps, is_tag, pose_keys, [origin.compose(p) for p in odo_poses], odo_poses, odo_covs)


def _tags_against_odometry(
    det: dict[str, list[Any]], order: np.ndarray, path: _KeyframePath, extrinsics: Extrinsics | None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The camera motion the tags measure against the odometry's (:mod:`stages.graph.tag_motion`): the distance
    ratio over every pair, and each camera's mounting rotation."""
    cams = sorted({str(det[CAMERA][r]) for r in order})
    mounts = {cam: camera_extrinsic(extrinsics, cam) for cam in cams}
    index = {cam: i for i, cam in enumerate(cams)}
    kf_index = path.index
    T_camera_tag = np.asarray([det[T_CAMERA_TAG][r] for r in order], dtype=float).reshape(-1, 4, 4)
    pairs = motion_pairs(
        np.asarray([kf_index[int(det[STAMP_NS][r])] for r in order], dtype=np.int64),
        np.asarray([int(det[TAG_ID][r]) for r in order], dtype=np.int64),
        np.asarray([index[str(det[CAMERA][r])] for r in order], dtype=np.int64),
        np.asarray([mounts[str(det[CAMERA][r])][0].matrix() for r in order]).reshape(-1, 4, 4),
        T_camera_tag[:, :3, 3],
        np.asarray([p.matrix() for p in path.odometry_poses]).reshape(-1, 4, 4),
    )
    mounting = {}
    for cam in cams:
        mount = camera_mount(extrinsics, cam)
        source = mount.source if mount is not None and mount.source else mounts[cam][1]
        mounting[cam] = {**mounting_figures(pairs, index[cam], mounts[cam][0].rotation().matrix()), "source": source}
    return ratio_figures(pairs), mounting


def _prior_rows(model: GraphModel, cfg: GraphConfig, first_pose: int) -> list[FactorRow]:
    """The prior on the first keyframe (it defines the map frame) and, when it is estimated, the tag scale's."""
    rows = [model.prior_row(first_pose, model.identity, cfg.prior_sigma_m, cfg.prior_sigma_rad)]
    if cfg.tag_scale_sigma > 0:
        rows.append(
            FactorRow(
                "scale_prior", "PriorFactorDouble", (SCALE_KEY,), np.ones(1), np.array([[cfg.tag_scale_sigma**2]])
            )
        )
    return rows


def _motion_rows(
    model: GraphModel, cfg: GraphConfig, odom: Odometry | None, path: _KeyframePath, info: dict[str, Any]
) -> list[FactorRow]:
    """Odometry between consecutive keyframes, or a weak zero-motion prior when the run has none."""
    if odom is not None:
        rows, noise_source, fallbacks = _odometry_rows(model, cfg, odom, path, info)
    elif cfg.motion_prior:
        cov = model.pose_covariance(cfg.motion_prior_sigma_m, cfg.motion_prior_sigma_rad)
        keys, stamps = path.pose_keys, path.stamps_ns
        rows = [
            model.between_row("motion_prior", (keys[i], keys[i + 1]), model.identity, cov, int(stamps[i + 1]))
            for i in range(len(keys) - 1)
        ]
        noise_source, fallbacks = "motion_prior", 0
    else:
        rows, noise_source, fallbacks = [], "none", 0
    info["odometry_noise"] = noise_source
    info["odometry_noise_fallbacks"] = fallbacks
    if odom is None:
        info["note"] = (
            "the run has no odometry: consecutive keyframes are joined by a weak zero-motion prior"
            if cfg.motion_prior
            else "the run has no odometry and graph.motion_prior is off: poses are tied only by shared tags"
        )
    return rows


def _odometry_rows(
    model: GraphModel, cfg: GraphConfig, odom: Odometry, path: _KeyframePath, info: dict[str, Any]
) -> tuple[list[FactorRow], str, int]:
    """One odometry row per consecutive keyframe pair, its noise from the messages or the settings."""
    has_cov = bool(np.any(odom.cov != 0))
    use_msgs = cfg.odometry_noise == "messages" or (cfg.odometry_noise == "auto" and has_cov)
    unobserved = unobserved_dims(odom.cov, model)
    poses, covs, keys = path.odometry_poses, path.odometry_covs, path.pose_keys
    propagated = True
    if use_msgs:
        info["odometry_unobserved_dims"] = [nm for nm, u in zip(model.motion_dims, unobserved, strict=True) if u]
        propagated, info["odometry_covariance_growth"] = growth_model(model, poses, covs, unobserved)
    rows, fallbacks = [], 0
    for i in range(len(keys) - 1):
        a, b = poses[i], poses[i + 1]
        rel = a.between(b)
        dist = float(np.linalg.norm(np.asarray(rel.translation())))
        angle = float(np.linalg.norm(gtsam.Rot3.Logmap(rel.rotation())))
        cov = settings_cov(cfg, model, dist, angle)
        if use_msgs:
            cov, fell_back = message_cov(model, a, b, covs[i], covs[i + 1], cov, unobserved, propagated)
            fallbacks += int(fell_back)
        rows.append(
            model.between_row("odometry", (keys[i], keys[i + 1]), model.motion(a, b), cov, int(path.stamps_ns[i + 1]))
        )
    info["odometry_messages"] = len(odom.stamps_ns)
    return rows, "messages" if use_msgs else "settings", fallbacks


@dataclass
class _TagSightings:
    """The tag rows and what placing and writing the landmarks needs from them."""

    rows: list[FactorRow] = field(default_factory=list)
    landmark_keys: dict[int, int] = field(default_factory=dict)
    first_sight: dict[int, tuple[int, Any]] = field(default_factory=dict)
    """Tag id to (keyframe, landmark relative to it) of its first measurement."""
    relative: list[tuple[int, int, Any]] = field(default_factory=list)
    """(keyframe, tag id, landmark relative to the keyframe) of every measurement, in time order."""
    heights: dict[int, list[tuple[float, float]]] = field(default_factory=dict)
    """Planar: tag id to the (z, var z) of each sighting."""
    cameras: list[str] = field(default_factory=list)
    """The camera of each row."""

    def add(self, row: FactorRow, k: int, tag: int, relative: Any, height: tuple[float, float] | None) -> None:
        self.rows.append(row)
        if height is not None:
            self.heights.setdefault(tag, []).append(height)
        self.relative.append((k, tag, relative))
        self.landmark_keys.setdefault(tag, int(L(tag)))
        self.first_sight.setdefault(tag, (k, relative))

    def landmark_heights(self) -> dict[int, tuple[float, float]]:
        """Tag id to the inverse-variance weighted mean height of its sightings and that mean's variance."""
        out = {}
        for tag, hs in self.heights.items():
            z = np.array([h[0] for h in hs])
            w = 1.0 / np.array([max(h[1], 1e-12) for h in hs])
            out[tag] = (float((w * z).sum() / w.sum()), float(1.0 / w.sum()))
        return out


def _tag_rows(
    model: GraphModel,
    cfg: GraphConfig,
    det: dict[str, list[Any]],
    order: np.ndarray,
    path: _KeyframePath,
    scale_keys: tuple[int, ...],
    extrinsics: Extrinsics | None,
    info: dict[str, Any],
    mount_covs: dict[str, FloatArray] | None = None,
) -> _TagSightings:
    """One tag row per usable detection, in ``order`` (time order), from the keyframe of its frame."""
    extrinsic_cache: dict[str, tuple[gtsam.Pose3, str]] = {}
    floor = np.diag([cfg.tag_sigma_floor_rad**2] * 3 + [cfg.tag_sigma_floor_m**2] * 3)
    robust_k = cfg.robust_threshold if cfg.robust_kernel != "none" else 0.0
    kf_index = path.index
    out = _TagSightings()
    dropped_close = 0
    for r in order:
        cam = str(det[CAMERA][r])
        if cam not in extrinsic_cache:
            extrinsic_cache[cam] = camera_extrinsic(extrinsics, cam)
        Z = pose3_from_matrix(det[T_CAMERA_TAG][r])
        T_base_tag = extrinsic_cache[cam][0].compose(Z)
        cov6 = cfg.tag_covariance_scale * np.asarray(det[DETECTION_POSE_COV][r], dtype=float).reshape(6, 6) + floor
        if mount_covs and cam in mount_covs:
            cov6 = inflated(cov6, Z, mount_covs[cam])
        meas = model.tag_measurement(T_base_tag, cov6)
        if meas is None:
            dropped_close += 1
            continue
        tag, stamp = int(det[TAG_ID][r]), int(det[STAMP_NS][r])
        k = kf_index[stamp]
        keys = (path.pose_keys[k], int(L(tag)), *scale_keys)
        row = FactorRow(
            "tag",
            meas.type,
            keys,
            meas.measurement,
            meas.covariance,
            cfg.robust_kernel,
            robust_k,
            tag_id=tag,
            frame=int(det[FRAME][r]),
            stamp_ns=stamp,
        )
        out.add(row, k, tag, meas.relative, meas.height)
        out.cameras.append(cam)
    info["dropped_too_close"] = dropped_close
    info["extrinsics"] = {cam: src for cam, (_, src) in extrinsic_cache.items()}
    return out


def _initial_values(
    model: GraphModel,
    path: _KeyframePath,
    sightings: _TagSightings,
    use_scale: bool,
    surveyed: dict[int, gtsam.Pose3] | None = None,
) -> tuple[gtsam.Values, dict[int, str]]:
    """Keyframes at dead reckoning, each landmark at its surveyed pose or where it was first seen, the tag scale
    at 1."""
    initial = gtsam.Values()
    var_types: dict[int, str] = {}
    for key, pose in zip(path.pose_keys, path.poses, strict=True):
        initial.insert(key, model.initial_pose(pose))
        var_types[key] = model.pose.name
    for tag, (k, relative) in sightings.first_sight.items():
        key = sightings.landmark_keys[tag]
        if surveyed and tag in surveyed:
            initial.insert(key, surveyed[tag])
        else:
            initial.insert(key, model.initial_landmark(path.poses[k], relative))
        var_types[key] = model.tag_landmark.name
    if use_scale:
        initial.insert(SCALE_KEY, 1.0)
        var_types[SCALE_KEY] = SCALE.name
    return initial, var_types


def _known_tag_rows(
    model: GraphModel, tags: TagsInfo, sightings: _TagSightings, info: dict[str, Any]
) -> list[FactorRow]:
    """A ``tag_prior`` row on each surveyed tag the graph has a landmark for (3d model only)."""
    seen = [k for k in tags.known_tags if k.id in sightings.landmark_keys]
    info["known_tags"] = len(tags.known_tags)
    info["known_tags_seen"] = [k.id for k in seen]
    if not seen:
        return []
    if model.name != "3d":
        info.setdefault("notes", []).append(
            f"{len(seen)} surveyed tags of the tags file are not used as priors: the planar model has no tag "
            "orientation to anchor; use graph.model=3d"
        )
        info["known_tags_seen"] = []
        return []
    return [
        FactorRow(
            "tag_prior",
            "PriorFactorPose3",
            (sightings.landmark_keys[k.id],),
            pose3_to_vector(pose3_from_matrix(k.T_world_tag)),
            np.asarray(k.covariance, dtype=float),
            tag_id=k.id,
        )
        for k in seen
    ]


def _move_to_world(path: _KeyframePath, sightings: _TagSightings, surveyed: dict[int, gtsam.Pose3]) -> None:
    """Move the initial keyframes (dead reckoning) into TagSLAM's world frame: the keyframe of the first sighting
    of a surveyed tag is placed where that sighting and the tag's surveyed pose put it, the others rigidly with
    it."""
    k, tag, relative = next(s for s in sightings.relative if s[1] in surveyed)
    T_world_kf = surveyed[tag].compose(relative.inverse())
    align = T_world_kf.compose(path.poses[k].inverse())
    path.poses = [align.compose(p) for p in path.poses]


def _remap_ids(det: dict[str, list[Any]], tags: TagsInfo, extrinsics: Extrinsics | None, info: dict[str, Any]) -> None:
    """Give detections of a duplicated id the id of the tag they are of (TagSLAM's tag_id_remap), in place."""
    names: dict[str, set[str]] = {}
    remapped: Counter[int] = Counter()
    for i, (tag, stamp, cam) in enumerate(zip(det[TAG_ID], det[STAMP_NS], det[CAMERA], strict=True)):
        for r in tags.tag_id_remap:
            if int(tag) != r.id or not r.start_ns <= int(stamp) <= r.end_ns:
                continue
            if r.camera is not None:
                if cam not in names:
                    mount = camera_mount(extrinsics, str(cam))
                    names[cam] = {str(cam), *([mount.frame_id] if mount is not None else [])}
                if r.camera not in names[cam]:
                    continue
            det[TAG_ID][i] = r.remap_id
            remapped[r.remap_id] += 1
            break
    info["remapped_tag_ids"] = {str(k): v for k, v in sorted(remapped.items())}
