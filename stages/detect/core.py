"""From an image (or corners already detected) to detection rows: detect, filter, estimate the pose.

Shared by the stage's worker processes, the tests and the benchmark. Covariances here are for a
corner noise of 1 px (:attr:`TagPose.cov_unit`); the stage scales them once the noise is known.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from stages.camera import colmap_camera
from stages.detect.backends import Detector, TagObservation, make_detector, shortest_side_px
from stages.detect.config import DetectConfig
from stages.detect.edges import BORDER_CELLS, edge_shifts, shift_corners
from stages.detect.pose import TagPose, estimate_tag_poses
from stages.frames import CorruptFrameError, decode_frame
from stages.ingest.artifacts import CameraModel

# Reasons a detection is dropped before its pose is kept (summary keys).
DROP_REASONS = ("family", "hamming", "decision_margin", "small", "pose_failed", "reprojection")

if TYPE_CHECKING:
    import pycolmap


@dataclass
class FrameJob:
    """One frame to process: its image bytes, or corners a bag already holds (then ``data`` is None)."""

    frame: int
    stamp_ns: int
    camera: str
    format: str = ""
    width: int = 0
    height: int = 0
    step: int = 0
    data: bytes | None = None
    observations: list[TagObservation] | None = None
    measure_edges: bool = False
    """Measure where the edges of this frame's tags lie (``corner_shift_px: auto``, :mod:`stages.detect.edges`)."""


@dataclass(frozen=True, slots=True)
class DetectionRow:
    """One kept tag in one frame: where and what it is, and its pose with the covariance for 1 px corner noise.

    The stage turns it into a row of ``detections.parquet`` once the corner noise is known
    (:data:`stages.detect.artifacts.DETECTIONS`; the fields here carry the names of its columns).
    """

    frame: int
    stamp_ns: int
    camera: str
    tag_id: int
    family: str
    corners: list[float]
    """x0 y0 … x3 y3, pixels of the distorted image, OpenCV corner order."""
    size_m: float
    side_px: float
    """The tag's shortest side in the image, px."""
    decision_margin: float
    hamming: int
    pose: TagPose

    @property
    def T_camera_tag(self) -> list[float]:
        """The chosen pose, 4x4 row-major."""
        return list(self.pose.T_camera_tag.ravel().tolist())

    @property
    def alt_T_camera_tag(self) -> list[float]:
        """The other pose of the planar ambiguity, 4x4 row-major (NaN without it)."""
        alt = self.pose.alt_T_camera_tag
        return list((alt if alt is not None else np.full((4, 4), np.nan)).ravel().tolist())

    @property
    def reprojection_px(self) -> float:
        """RMS corner reprojection error of the chosen pose, px."""
        return self.pose.reprojection_px

    @property
    def ambiguity_ratio(self) -> float:
        """Squared corner error of the chosen pose over the other's."""
        return self.pose.ambiguity_ratio


@dataclass
class BatchResult:
    """Rows of a batch of frames, the frames that did not decode, and the drop counts."""

    rows: list[DetectionRow] = field(default_factory=list)
    corrupt: list[tuple[int, str]] = field(default_factory=list)
    dropped: Counter[str] = field(default_factory=Counter)
    frames: int = 0
    edge_shifts: list[float] = field(default_factory=list)
    """The measured tags' edge shifts, px (:func:`stages.detect.edges.edge_shifts`)."""


def observations_to_rows(
    observations: list[TagObservation],
    job: FrameJob,
    cfg: DetectConfig,
    camera: pycolmap.Camera,
    dropped: Counter[str],
    apply_quality: bool = True,
) -> list[DetectionRow]:
    """Filter observations by the settings and estimate each one's pose; one row per kept tag.

    ``apply_quality=False`` (detections a bag holds) keeps every family and skips the decoding checks.
    """
    return rows_with_poses([(job, camera, kept_observations(observations, cfg, dropped, apply_quality))], cfg, dropped)


def kept_observations(
    observations: list[TagObservation], cfg: DetectConfig, dropped: Counter[str], apply_quality: bool
) -> list[tuple[TagObservation, float]]:
    """The observations the settings keep, with their shortest side in px; the others counted in ``dropped``."""
    kept = []
    for obs in observations:
        if apply_quality and obs.family not in cfg.families:  # a bag's detections: any family, no decoding
            dropped["family"] += 1
            continue
        if apply_quality and obs.hamming > cfg.max_hamming:
            dropped["hamming"] += 1
            continue
        if apply_quality and cfg.backend == "apriltag3" and obs.decision_margin < cfg.min_decision_margin:
            dropped["decision_margin"] += 1
            continue
        side = shortest_side_px(obs.corners)
        if side < cfg.min_side_px:
            dropped["small"] += 1
            continue
        kept.append((obs, side))
    return kept


def _shifted(obs: TagObservation, shift_px: float) -> TagObservation:
    """The observation with each side of its quad moved outwards by ``shift_px``."""
    return replace(obs, corners=shift_corners(obs.corners, shift_px))


def reposed(
    rows: list[DetectionRow], shift_px: float, cfg: DetectConfig, processor: FrameProcessor
) -> tuple[list[DetectionRow], Counter[str]]:
    """The rows with their quads moved outwards by ``shift_px`` and their poses estimated again; those whose pose
    now fails or fits badly are left out and counted."""
    frames = []
    for r in rows:
        job = FrameJob(frame=r.frame, stamp_ns=r.stamp_ns, camera=r.camera)
        obs = TagObservation(r.tag_id, r.family, np.reshape(r.corners, (4, 2)), r.decision_margin, r.hamming)
        frames.append((job, processor.camera_of(job), [(obs, r.side_px)]))
    dropped: Counter[str] = Counter()
    return rows_with_poses(frames, cfg.model_copy(update={"corner_shift_px": shift_px}), dropped), dropped


def rows_with_poses(
    frames: list[tuple[FrameJob, pycolmap.Camera, list[tuple[TagObservation, float]]]],
    cfg: DetectConfig,
    dropped: Counter[str],
) -> list[DetectionRow]:
    """Rows of the kept observations (:func:`kept_observations`) of several frames, in order; the poses of each
    camera's tags are estimated in one batch. Those whose pose fails or fits badly are counted in ``dropped``."""
    if cfg.corner_shift_px != "auto" and cfg.corner_shift_px:
        for _, _, kept in frames:
            kept[:] = [(_shifted(o, cfg.corner_shift_px), side) for o, side in kept]
    by_camera: dict[int, list[tuple[TagObservation, float]]] = {}
    cameras: dict[int, pycolmap.Camera] = {}
    for _, camera, kept in frames:
        by_camera.setdefault(id(camera), []).extend(kept)
        cameras[id(camera)] = camera
    poses: dict[int, list[TagPose | None]] = {
        key: estimate_tag_poses([o.corners for o, _ in kept], [cfg.size_of(o.tag_id) for o, _ in kept], cameras[key])
        for key, kept in by_camera.items()
    }
    taken = dict.fromkeys(poses, 0)
    rows = []
    for job, camera, kept in frames:
        for obs, side in kept:
            pose = poses[id(camera)][taken[id(camera)]]
            taken[id(camera)] += 1
            if pose is None:
                dropped["pose_failed"] += 1
                continue
            if pose.reprojection_px > cfg.max_reprojection_px:
                dropped["reprojection"] += 1
                continue
            rows.append(
                DetectionRow(
                    frame=job.frame,
                    stamp_ns=job.stamp_ns,
                    camera=job.camera,
                    tag_id=obs.tag_id,
                    family=obs.family,
                    corners=np.asarray(obs.corners, float).ravel().tolist(),
                    size_m=cfg.size_of(obs.tag_id),
                    side_px=side,
                    decision_margin=obs.decision_margin,
                    hamming=obs.hamming,
                    pose=pose,
                )
            )
    return rows


def detect_image(
    gray: npt.NDArray[np.uint8],
    detector: Detector,
    camera: pycolmap.Camera,
    cfg: DetectConfig,
    job: FrameJob | None = None,
    dropped: Counter[str] | None = None,
) -> list[DetectionRow]:
    """Rows for the tags in one grayscale image (an image without tags gives no rows)."""
    job = job or FrameJob(frame=0, stamp_ns=0, camera="")
    return observations_to_rows(detector.detect(gray), job, cfg, camera, dropped if dropped is not None else Counter())


class FrameProcessor:
    """A detector and the camera models, built once per worker process."""

    def __init__(
        self,
        cfg: DetectConfig,
        camera: CameraModel,
        with_detector: bool = True,
        cameras: dict[str, CameraModel] | None = None,
    ) -> None:
        """``camera``: the camera of every frame; ``cameras``: of a rig, each camera by its topic (a frame's
        ``camera``), ``camera`` for the others."""
        self.cfg = cfg
        self.camera = colmap_camera(camera)
        self.cameras = {topic: colmap_camera(model) for topic, model in (cameras or {}).items()}
        self.detector = make_detector(cfg) if with_detector else None

    def camera_of(self, job: FrameJob) -> pycolmap.Camera:
        """The camera that took ``job``'s frame."""
        return self.cameras.get(job.camera, self.camera)

    def process(self, jobs: list[FrameJob]) -> BatchResult:
        """Process a batch of frames; corrupt frames are listed, not raised. The tags of the whole batch have
        their poses estimated together (:func:`~stages.detect.pose.estimate_tag_poses`)."""
        result = BatchResult()
        frames = []
        for job in jobs:
            result.frames += 1
            if job.observations is not None:
                kept = kept_observations(job.observations, self.cfg, result.dropped, apply_quality=False)
                frames.append((job, self.camera_of(job), kept))
                continue
            try:
                gray = decode_frame(job.format, job.width, job.height, job.step, job.data or b"")
            except CorruptFrameError as err:
                result.corrupt.append((job.frame, str(err)))
                continue
            assert self.detector is not None
            kept = kept_observations(self.detector.detect(gray), self.cfg, result.dropped, True)
            if job.measure_edges and kept:
                cells = [BORDER_CELLS.get(o.family, 0) for o, _ in kept]
                shifts = edge_shifts(gray, [o.corners for o, _ in kept], cells)
                result.edge_shifts += [float(v) for v in shifts if np.isfinite(v)]
            frames.append((job, self.camera_of(job), kept))
        result.rows = rows_with_poses(frames, self.cfg, result.dropped)
        return result


_PROCESSOR: FrameProcessor | None = None


def init_worker(
    cfg_data: dict[str, Any],
    camera: CameraModel,
    with_detector: bool,
    cameras: dict[str, CameraModel] | None = None,
) -> None:
    """Worker-process initializer: build the detector and cameras once."""
    global _PROCESSOR
    _PROCESSOR = FrameProcessor(DetectConfig.model_validate(cfg_data), camera, with_detector, cameras)


def process_in_worker(jobs: list[FrameJob]) -> BatchResult:
    """Worker-process task: process one batch with the processor built by :func:`init_worker`."""
    assert _PROCESSOR is not None, "init_worker was not called"
    return _PROCESSOR.process(jobs)
