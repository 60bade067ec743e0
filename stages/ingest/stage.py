"""Ingest: read a recording once and keep what the later stages need, so they never open the bag again.

Reads camera frames, camera model, odometry, laser scans, static extrinsics and, when the bag holds
them, AprilTag detections. Writes the artifacts declared in :mod:`stages.ingest.artifacts`.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.artifacts import StageOutput
from pipeline.context import StageContext
from pipeline.contracts import TableSpec
from pipeline.errors import InputError
from stages.columns import CORNERS, FAMILY, FRAME, FRAME_ID, STAMP_NS, TAG_ID, TOPIC
from stages.ingest import convert
from stages.ingest.artifacts import (
    CAMERA,
    CHILD_FRAME_ID,
    EXTRINSICS,
    FRAMES,
    ODOMETRY,
    SCANS,
    TAG_DETECTIONS,
    CameraModel,
    Extrinsics,
    SensorMount,
)
from stages.ingest.bags import RawMessage, Recording
from stages.ingest.config import IngestConfig
from stages.ingest.record import log_ingest
from stages.ingest.topics import ROLES, resolve_topic


def _detection_rows(msg: Any, frame: int, stamp: int, topic: str) -> list[dict[str, Any]]:
    """Rows of an apriltag_msgs ApriltagArrayStamped (ROS 1) or AprilTagDetectionArray (ROS 2)."""
    rows: list[dict[str, Any]] = []
    for det in convert.get(msg, "apriltags", "detections", default=[]):
        corners = [float(v) for c in det.corners for v in (c.x, c.y)]
        family = str(convert.get(det, "family", default="") or "tag36h11")
        if family and not family.startswith("tag"):
            family = f"tag{family}"
        rows.append(
            {FRAME: frame, STAMP_NS: stamp, TOPIC: topic, TAG_ID: int(det.id), FAMILY: family, CORNERS: corners[:8]}
        )
    return rows


class _TableWriter:
    """Stream rows of a declared table to its file in row groups, so long recordings do not fill memory."""

    def __init__(self, out: StageOutput, spec: TableSpec, batch: int = 256) -> None:
        self.spec, self.batch = spec, batch
        self.rows: list[dict[str, Any]] = []
        self.count = 0
        self.writer = spec.writer(out.file(spec.file))

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        self.count += 1
        if len(self.rows) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if self.rows:
            self.writer.write_table(self.spec.table(self.rows))
            self.rows = []

    def close(self) -> None:
        self.flush()
        self.writer.close()


def _load_camera_file(path: str) -> CameraModel:
    from stages.camera import load_camera_file

    return load_camera_file(Path(path))


def run(ctx: StageContext, cfg: IngestConfig) -> dict[str, Any]:
    """Read the recording into the run folder."""
    started = time.perf_counter()
    with Recording(ctx.source, salvage=cfg.salvage) as rec:
        if cfg.camera_file:
            ctx.outside_file(cfg.camera_file)  # a changed calibration file re-runs ingest
        plan = _plan(rec, cfg)
        reading = _Reading(ctx.output, plan, cfg.frame_stride, cfg.salvage)
        total = sum(rec.topics[t].count for t in plan.wanted)
        for raw in ctx.progress(rec.messages(plan.wanted), "ingest", total=total):
            reading.add(raw)
        reading.close()
        bag = {"reader": rec.reader, "format": rec.format, "storage": rec.storage}
        bag_start, bag_end, salvaged = rec.start_ns, rec.end_ns, rec.salvaged
    camera, extrinsics, notes = _write_calibration(ctx.output, reading, _check_read(plan, reading, cfg))
    summary = {
        "frames": reading.frames.count,
        "tag_detections": reading.dets.count if reading.dets else 0,
        "odometry": reading.odom.count,
        "scans": reading.scans.count,
        "duration_s": round((bag_end - bag_start) * 1e-9, 6),
        "start_ns": bag_start,
        "topics": {k: v for k, v in plan.topics.items() if v},
        **bag,
        "camera": camera.model_dump(include={"width", "height", "distortion_model", "frame_id", "source"}),
        "notes": notes,
        "dropped": {t: dict(sorted(c.items())) for t, c in sorted(reading.dropped.items())},
        "read_seconds": round(time.perf_counter() - started, 3),
    }
    if salvaged is not None:
        summary["salvaged"] = salvaged
    log_ingest(ctx, camera, extrinsics)
    return summary


@dataclass
class _Plan:
    """What to read: the topic of each role, whether tags come as detections, the calibration file, the window."""

    topics: dict[str, str | None]
    use_detections: bool
    camera: CameraModel | None
    """The calibration from ``camera_file``; None: from the first CameraInfo message in the window."""
    start_ns: int
    end_ns: int | None

    @property
    def wanted(self) -> list[str]:
        return [t for t in self.topics.values() if t]

    def in_window(self, stamp_ns: int) -> bool:
        return not (stamp_ns < self.start_ns or (self.end_ns is not None and stamp_ns > self.end_ns))


def _plan(rec: Recording, cfg: IngestConfig) -> _Plan:
    """Resolve the topics and the time window; fail early when the recording cannot give frames or a camera."""
    if rec.message_count == 0:
        raise InputError(f"{rec.path.name} holds no messages; record again or pick another bag")
    topics = {name: resolve_topic(rec, role, getattr(cfg, role.setting)) for name, role in ROLES.items()}
    if topics["image"] is None and topics["detections"] is None:
        present = ", ".join(f"{n} ({t.type})" for n, t in sorted(rec.topics.items()))
        raise InputError(
            f"{rec.path.name} has no camera image topic (sensor_msgs/Image or CompressedImage) and no AprilTag "
            f"detections; topics present: {present}"
        )
    use_detections = bool(topics["detections"] is not None and (topics["image"] is None or cfg.detections_topic))
    if use_detections:
        topics["image"] = None if not cfg.image_topic else topics["image"]
    camera = _load_camera_file(cfg.camera_file) if cfg.camera_file else None
    if camera is None and topics["camera_info"] is None:
        raise InputError(
            f"{rec.path.name} has no CameraInfo topic; pass the calibration with --camera FILE "
            "(Kalibr/TagSLAM cameras.yaml or ROS camera_info YAML)"
        )
    start_ns = rec.start_ns + int(cfg.start_s * 1e9)
    end_ns = rec.start_ns + int(cfg.end_s * 1e9) if cfg.end_s is not None else None
    if end_ns is not None and end_ns <= start_ns:
        raise InputError(f"--end {cfg.end_s} s is not after --start {cfg.start_s} s")
    return _Plan(topics, use_detections, camera, start_ns, end_ns)


class _Reading:
    """The messages as they stream by: table writers, the static transforms, the camera and frame names."""

    def __init__(self, out: StageOutput, plan: _Plan, frame_stride: int = 1, salvage: bool = False) -> None:
        self.out, self.plan, self.frame_stride, self.salvage = out, plan, frame_stride, salvage
        self.dropped: dict[str, Counter[str]] = {}
        """Per topic, the messages dropped (--salvage) for each reason: values out of range, or no decoding."""
        self.frames = _TableWriter(out, FRAMES)
        self.odom = _TableWriter(out, ODOMETRY, batch=4096)
        self.scans = _TableWriter(out, SCANS, batch=1024)
        self.dets = _TableWriter(out, TAG_DETECTIONS, batch=4096) if plan.use_detections else None
        self.edges: list[tuple[str, str, np.ndarray]] = []
        self.frame_index: dict[str, int] = {}
        self.camera = plan.camera
        self.image_frame_id = ""
        self.base_frame = ""
        self.odom_frame = ""
        self.scan_frame = ""

    def _bad(self, raw: RawMessage, why: str | None) -> bool:
        """Whether the message is to be dropped for ``why``; without --salvage, stop with one line."""
        if why is None:
            return False
        if not self.salvage:
            raise InputError(
                f"a {raw.type.split('/')[-1]} message on {raw.topic} (log time {raw.log_time_ns} ns) has {why}; "
                "the recording is damaged or wrong: drop such messages with --salvage"
            )
        self.dropped.setdefault(raw.topic, Counter())[why] += 1
        return True

    def _decode(self, raw: RawMessage) -> Any:
        """The message, or None when it does not decode and --salvage drops it."""
        try:
            return raw.decode()
        except InputError as err:
            if not self.salvage:
                raise InputError(f"{err}; the recording may be damaged: drop such messages with --salvage") from None
            self._bad(raw, "no decoding")
            return None

    def add(self, raw: RawMessage) -> None:
        """Take one message: a static transform, a camera frame (or its detections), or a sensor message."""
        topics = self.plan.topics
        if raw.topic == topics["tf_static"]:
            tf = self._decode(raw)
            if tf is not None:
                self.edges.extend(convert.transform_edges(tf))
        elif raw.topic in (topics["image"], topics["detections"]):
            self._frame(raw)
        elif self.plan.in_window(raw.log_time_ns):
            self._sensor(raw)

    def _frame(self, raw: RawMessage) -> None:
        """A camera frame (image or tag detections), counted from the first in the bag for the stride."""
        index = self.frame_index.get(raw.topic, 0)
        self.frame_index[raw.topic] = index + 1
        if not self.plan.in_window(raw.log_time_ns) or index % self.frame_stride:
            return
        msg = self._decode(raw)
        if msg is None:
            return
        stamp = convert.stamp_ns(msg, raw.log_time_ns)
        if raw.topic == self.plan.topics["image"]:
            row = convert.image_row(msg, compressed=raw.type.endswith("CompressedImage"))
            if self._bad(raw, convert.image_problem(row)):
                return
            self.image_frame_id = self.image_frame_id or convert.frame_id(msg)
            self.frames.add({FRAME: index, STAMP_NS: stamp, TOPIC: raw.topic, **row})
        else:
            assert self.dets is not None
            self.image_frame_id = self.image_frame_id or convert.frame_id(msg)
            for r in _detection_rows(msg, index, stamp, raw.topic):
                self.dets.add(r)

    def _sensor(self, raw: RawMessage) -> None:
        """The first CameraInfo in the window, odometry and laser scans."""
        topics = self.plan.topics
        if raw.topic == topics["camera_info"] and self.camera is not None:
            return  # the first calibration in the window is the one used
        msg = self._decode(raw)
        if msg is None:
            return
        if raw.topic == topics["camera_info"]:
            self.camera = convert.camera_from_info(msg, raw.topic)
        elif raw.topic == topics["odometry"]:
            row = convert.odometry_row(msg, convert.stamp_ns(msg, raw.log_time_ns))
            if self._bad(raw, convert.odometry_problem(row)):
                return
            self.base_frame = self.base_frame or row[CHILD_FRAME_ID]
            self.odom_frame = self.odom_frame or row[FRAME_ID]
            self.odom.add(row)
        elif raw.topic == topics["scan"]:
            row = convert.scan_row(msg, convert.stamp_ns(msg, raw.log_time_ns))
            if self._bad(raw, convert.scan_problem(row)):
                return
            if self.scans.count == 0:
                self.scan_frame = row[FRAME_ID]  # the laser's frame is that of the first scan
            self.scans.add(row)

    def close(self) -> None:
        for w in (self.frames, self.odom, self.scans, *([self.dets] if self.dets else [])):
            w.close()


def _check_read(plan: _Plan, reading: _Reading, cfg: IngestConfig) -> CameraModel:
    """The camera calibration; fail when the window held no camera frame or no calibration."""
    topics = plan.topics
    if reading.frames.count == 0 and (
        reading.dets is None or reading.frame_index.get(topics["detections"] or "", 0) == 0
    ):
        window = f" between {cfg.start_s} s and {cfg.end_s} s" if cfg.start_s or cfg.end_s else ""
        raise InputError(
            f"no camera frames on {topics['image'] or topics['detections']}{window}; widen the time window"
        )
    if reading.camera is None:
        raise InputError(f"no CameraInfo message on {topics['camera_info']} in the time window; pass --camera FILE")
    return reading.camera


def _write_calibration(
    out: StageOutput, reading: _Reading, camera: CameraModel
) -> tuple[CameraModel, Extrinsics, list[str]]:
    """``camera.json`` and ``extrinsics.json`` (base to camera and laser from the static transforms)."""
    camera_frame = camera.frame_id or reading.image_frame_id
    camera = camera.model_copy(update={"frame_id": camera_frame})
    base = reading.base_frame or camera_frame
    sensors: dict[str, SensorMount] = {}
    notes: list[str] = []
    for role, frame in (("camera", camera_frame), ("laser", reading.scan_frame)):
        if not frame:
            continue
        T = convert.chain(reading.edges, base, frame)
        assumed = T is None
        if T is None:
            notes.append(f"no static transform from {base!r} to {role} frame {frame!r}; identity assumed")
            T = np.eye(4)
        sensors[role] = SensorMount(frame_id=frame, T_base_sensor=T.tolist(), assumed=assumed)
    extrinsics = Extrinsics(base_frame=base, odom_frame=reading.odom_frame, sensors=sensors)
    CAMERA.write(out, camera)
    EXTRINSICS.write(out, extrinsics)
    if reading.dets is None:
        out.file(TAG_DETECTIONS.file).unlink(missing_ok=True)
    return camera, extrinsics, notes
