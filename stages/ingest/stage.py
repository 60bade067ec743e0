"""Ingest: read a recording once and keep what the later stages need, so they never open the bag again.

Reads camera frames, camera model, odometry, laser scans, static extrinsics and, when the bag holds
them, AprilTag detections. Writes the artifacts declared in :mod:`stages.ingest.artifacts`.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from pipeline.artifacts import StageOutput
from pipeline.context import StageContext
from pipeline.errors import InputError
from stages.columns import CORNERS, FAMILY, FRAME, STAMP_NS, TAG_ID, TOPIC
from stages.extrinsics import ExtrinsicsFile
from stages.ingest import convert, fast
from stages.ingest.artifacts import (
    CAMERA,
    CAMERAS,
    DATA,
    EXTRINSICS,
    FRAMES,
    ODOMETRY,
    SCANS,
    TAG_DETECTIONS,
    TAGS,
    CameraModel,
    Extrinsics,
    Rig,
    SensorMount,
    TagsInfo,
)
from stages.ingest.bags import RawMessage, Recording
from stages.ingest.config import IngestConfig
from stages.ingest.record import FrameLog, log_ingest
from stages.ingest.tables import TableWriter, odometry_batch_table, odometry_table, scan_batch_table, scan_table
from stages.ingest.topics import ROLES, resolve_camera_topics, resolve_topic
from stages.tag_families import bag_family
from stages.tags_file import TagsFile

R = TypeVar("R")


def _same_floats(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))


def _same_odometry(a: fast.OdometryRecord, b: fast.OdometryRecord) -> bool:
    return a[:3] == b[:3] and _same_floats(a.values, b.values)


def _same_scan(a: fast.ScanRecord, b: fast.ScanRecord) -> bool:
    limits = _same_floats(np.array(a.limits), np.array(b.limits))
    return a[:2] == b[:2] and limits and _same_floats(a.ranges, b.ranges)


def _same_image(a: fast.ImageRecord, b: fast.ImageRecord) -> bool:
    return a == b


def _same_transforms(a: list[fast.TransformRecord], b: list[fast.TransformRecord]) -> bool:
    return len(a) == len(b) and all(
        x[:2] == y[:2] and _same_floats(np.array(x.values), np.array(y.values)) for x, y in zip(a, b, strict=True)
    )


def _same_camera(a: fast.CameraInfoRecord, b: fast.CameraInfoRecord) -> bool:
    return a[:4] == b[:4] and _same_floats(a.d, b.d) and _same_floats(a.k, b.k)


def _detection_rows(msg: Any, frame: int, stamp: int, topic: str) -> list[dict[str, Any]]:
    """Rows of an apriltag_msgs ApriltagArrayStamped (ROS 1) or AprilTagDetectionArray (ROS 2)."""
    rows: list[dict[str, Any]] = []
    for det in convert.get(msg, "apriltags", "detections", default=[]):
        corners = [float(v) for c in det.corners for v in (c.x, c.y)]
        family = bag_family(str(convert.get(det, "family", default="") or ""))
        rows.append(
            {FRAME: frame, STAMP_NS: stamp, TOPIC: topic, TAG_ID: int(det.id), FAMILY: family, CORNERS: corners[:8]}
        )
    return rows


def _calibrated_topics(path: str) -> list[set[str]]:
    """The topic names (and name) of each camera of a calibration file, in the file's order."""
    from stages.camera import load_camera_file, load_camera_files

    load_camera_file(Path(path))  # one error line for an unreadable or malformed file
    return [{name, *(t for t in (m.topic, m.tag_topic) if t)} for name, m in load_camera_files(Path(path)).items()]


def _load_cameras(path: str, topics: list[str]) -> tuple[dict[str, CameraModel], dict[str, str]]:
    """The calibration of each camera topic from the file, and the name of its entry (``cam0``): the camera whose
    ``rostopic``/``tagtopic`` (or name) is the topic; a file with one camera serves a single topic whatever its
    topic names.

    Raises:
        InputError: a topic that no camera of a multi-camera file names.
    """
    from stages.camera import load_camera_file, load_camera_files

    cams = load_camera_files(Path(path))
    out: dict[str, CameraModel] = {}
    names: dict[str, str] = {}
    for topic in topics:
        found = [(n, m) for n, m in cams.items() if topic in (n, m.topic, m.tag_topic)]
        if found:
            names[topic], out[topic] = found[0]
        elif len(cams) == 1 and len(topics) == 1:
            names[topic], out[topic] = next(iter(cams)), load_camera_file(Path(path))
        else:
            listed = ", ".join(f"{n} ({m.topic}, {m.tag_topic})" for n, m in cams.items())
            raise InputError(
                f"no camera in {path!r} for topic {topic!r}; its cameras: {listed}; set its rostopic/tagtopic "
                "or pick another topic with --set ingest.detections_topic=... / ingest.image_topic=..."
            )
    return out, names


def _load_extrinsics_file(path: str) -> ExtrinsicsFile:
    from stages.extrinsics import load_extrinsics_file

    return load_extrinsics_file(Path(path))


def check_input_files(cfg: IngestConfig) -> TagsFile | None:
    """The tags file (``--tags``), read before the recording is: one line, before any stage runs, for a file that
    does not read or for a setup focusmap cannot map (a static camera rig, :func:`stages.tags_file.camera_rig_problem`:
    the ``rig_body`` of the ``--camera`` cameras.yaml entries, else a body of ``type: camera_rig``).

    Raises:
        InputError: a malformed tags or camera file, or a static camera rig.
    """
    if not cfg.tags_file:
        return None
    from stages.camera import load_camera_file, rig_bodies
    from stages.tags_file import camera_rig_problem, load_tags_file

    tags = load_tags_file(Path(cfg.tags_file))
    rigs: dict[str, str] = {}
    if cfg.camera_file:
        load_camera_file(Path(cfg.camera_file))  # one error line for an unreadable or malformed file
        rigs = rig_bodies(Path(cfg.camera_file))
    problem = camera_rig_problem(tags, rigs)
    if problem is not None:
        raise InputError(problem)
    return tags


def _tags_summary(tags: TagsFile) -> dict[str, Any]:
    """The figures of a tags file for the summary: sizes, ignored and known tags, whether T_body_odom was read."""
    return {
        "default_tag_size_m": tags.default_tag_size_m,
        "tag_sizes": len(tags.tag_sizes_m),
        "ignore_tags": len(tags.ignore_tags),
        "moving_tags": sum(len(ids) for ids in tags.moving_tags.values()),
        "known_tags": len(tags.known_tags),
        "T_body_odom": tags.T_body_odom is not None,
    }


_BATCH = 1024
"""Odometry and scan messages parsed at a time (:func:`stages.ingest.fast.odometry_batch`)."""
FRAME_GROUP_BYTES = 32 << 20
"""Image bytes per row group of ``frames.parquet`` at most (plus one frame): ingest holds one group before writing
it and detect reads one at a time, so this bounds both stages' memory on raw images (256 JPEG frames at 640x480
stay well under it)."""


def run(ctx: StageContext, cfg: IngestConfig) -> dict[str, Any]:
    """Read the recording into the run folder."""
    started = time.perf_counter()
    with Recording(ctx.source, salvage=cfg.salvage) as rec:
        if cfg.camera_file:
            ctx.outside_file(cfg.camera_file)  # a changed calibration file re-runs ingest
        if cfg.extrinsics_file:
            ctx.outside_file(cfg.extrinsics_file)
        if cfg.tags_file:
            ctx.outside_file(cfg.tags_file)
        plan = _plan(rec, cfg)
        compressed = all(rec.topics[t].type.endswith("CompressedImage") for t in plan.image_topics)
        reading = _Reading(ctx.output, plan, cfg.frame_stride, cfg.salvage, rec.format != "ros1", compressed)
        reading.frame_log = FrameLog(ctx.rec, ctx.settings.rerun.image_stride)
        for topic in plan.wanted:  # the parsers of stages.ingest.fast read a topic whose type has the standard layout
            trusted = fast.standard(rec.typestore, rec.topics[topic].type, ros1=not reading.cdr)
            if trusted is not None:
                reading.fast_ok[topic] = trusted
        total = sum(rec.topics[t].count for t in plan.wanted)
        for raw in ctx.progress(rec.messages(plan.wanted), "ingest", total=total):
            reading.add(raw)
        reading.close()
        bag = {"reader": rec.reader, "format": rec.format, "storage": rec.storage}
        bag_start, bag_end, salvaged = rec.start_ns, rec.end_ns, rec.salvaged
    camera, extrinsics, notes, warnings = _write_calibration(ctx.output, reading, _check_read(plan, reading, cfg))
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
        "warnings": warnings,
        "read_seconds": round(time.perf_counter() - started, 3),
    }
    if len(plan.camera_topics) > 1:
        summary["camera_topics"] = plan.camera_topics
    if salvaged is not None:
        summary["salvaged"] = salvaged
    if plan.tags is not None:
        summary["tags"] = _tags_summary(plan.tags)
    log_ingest(ctx, camera, extrinsics)
    return summary


@dataclass
class _Plan:
    """What to read: the topic of each role, whether tags come as detections, the calibration file, the window."""

    topics: dict[str, str | None]
    """The topic of each role; of a rig's cameras, the first one's."""
    image_topics: list[str]
    detection_topics: list[str]
    use_detections: bool
    cameras: dict[str, CameraModel] | None
    """The calibration of each camera topic from ``camera_file``; None: from the first CameraInfo message."""
    extrinsics: ExtrinsicsFile | None
    start_ns: int
    end_ns: int | None
    tags: TagsFile | None = None
    """The TagSLAM tagslam.yaml given with --tags."""
    camera_names: dict[str, str] = field(default_factory=dict)
    """The name of each camera topic's entry in ``camera_file`` (``cam0``): a camera_poses.yaml entry's name."""

    @property
    def camera_topics(self) -> list[str]:
        """The topics whose frames or detections detect reads: one per camera, the first camera's first."""
        return self.detection_topics if self.use_detections else self.image_topics

    @property
    def wanted(self) -> list[str]:
        return list(
            dict.fromkeys([*(t for t in self.topics.values() if t), *self.image_topics, *self.detection_topics])
        )

    def in_window(self, stamp_ns: int) -> bool:
        return not (stamp_ns < self.start_ns or (self.end_ns is not None and stamp_ns > self.end_ns))


def _plan(rec: Recording, cfg: IngestConfig) -> _Plan:
    """Resolve the topics and the time window; fail early when the recording cannot give frames or a camera."""
    if rec.message_count == 0:
        raise InputError(f"{rec.path.name} holds no messages; record again or pick another bag")
    calibrated = _calibrated_topics(cfg.camera_file) if cfg.camera_file else None
    images = resolve_camera_topics(rec, ROLES["image"], cfg.image_topic, calibrated)
    detections = resolve_camera_topics(rec, ROLES["detections"], cfg.detections_topic, calibrated)
    topics = {
        name: resolve_topic(rec, role, getattr(cfg, role.setting))
        for name, role in ROLES.items()
        if name not in ("image", "detections")
    }
    topics["image"] = images[0] if images else None
    topics["detections"] = detections[0] if detections else None
    topics = {name: topics[name] for name in ROLES}
    if topics["image"] is None and topics["detections"] is None:
        present = ", ".join(f"{n} ({t.type})" for n, t in sorted(rec.topics.items()))
        raise InputError(
            f"{rec.path.name} has no camera image topic (sensor_msgs/Image or CompressedImage) and no AprilTag "
            f"detections; topics present: {present}"
        )
    use_detections = bool(topics["detections"] is not None and (topics["image"] is None or cfg.detections_topic))
    if use_detections and not cfg.image_topic:
        topics["image"], images = None, []
    cameras, names = (
        _load_cameras(cfg.camera_file, detections if use_detections else images) if cfg.camera_file else (None, {})
    )
    if cameras is None and topics["camera_info"] is None:
        raise InputError(
            f"{rec.path.name} has no CameraInfo topic; pass the calibration with --camera FILE "
            "(Kalibr/TagSLAM cameras.yaml or ROS camera_info YAML)"
        )
    start_ns = rec.start_ns + int(cfg.start_s * 1e9)
    end_ns = rec.start_ns + int(cfg.end_s * 1e9) if cfg.end_s is not None else None
    if end_ns is not None and end_ns <= start_ns:
        raise InputError(f"--end {cfg.end_s} s is not after --start {cfg.start_s} s")
    if cameras is None and len(images if not use_detections else detections) > 1:
        raise InputError(
            f"{rec.path.name}: several cameras need a calibration file with one entry per camera; pass --camera "
            "cameras.yaml (Kalibr/TagSLAM, rostopic/tagtopic naming each topic)"
        )
    extrinsics = _load_extrinsics_file(cfg.extrinsics_file) if cfg.extrinsics_file else None
    if extrinsics is not None and extrinsics.kind == "tagslam camera_poses" and cfg.camera_file:
        extrinsics = _on_rig_body(extrinsics, cfg.camera_file, list(names.values()))
    tags = check_input_files(cfg)
    return _Plan(topics, images, detections, use_detections, cameras, extrinsics, start_ns, end_ns, tags, names)


def _on_rig_body(file: ExtrinsicsFile, camera_file: str, cameras: list[str]) -> ExtrinsicsFile:
    """A TagSLAM camera_poses.yaml whose base frame is the ``rig_body`` its cameras.yaml names for the cameras read
    (the first one's), whatever that body is called; ``rig`` (TagSLAM's usual name) when it names none."""
    from stages.camera import rig_bodies

    bodies = rig_bodies(Path(camera_file))
    body = next((bodies[c] for c in cameras if c in bodies), None)
    return file if body is None else replace(file, base_frame=body)


class _Reading:
    """The messages as they stream by: table writers, the static transforms, the camera and frame names."""

    def __init__(
        self,
        out: StageOutput,
        plan: _Plan,
        frame_stride: int = 1,
        salvage: bool = False,
        cdr: bool = False,
        compressed: bool = False,
    ) -> None:
        self.out, self.plan, self.frame_stride, self.salvage = out, plan, frame_stride, salvage
        self.cdr = cdr
        """Whether the messages are CDR (ROS 2) rather than ROS 1 serialized, for :mod:`stages.ingest.fast`."""
        self.dropped: dict[str, Counter[str]] = {}
        """Per topic, the messages dropped (--salvage) for each reason: values out of range, or no decoding."""
        self.frames: TableWriter[dict[str, Any]] = TableWriter(
            out,
            FRAMES,
            batch=256,
            stored=(DATA,) if compressed else (),
            weight=lambda row: len(row[DATA] or b""),
            max_bytes=FRAME_GROUP_BYTES,
        )
        """Frames; when every image topic is a CompressedImage, their bytes are stored as they are."""
        self.odom = TableWriter(out, ODOMETRY, batch=4096, table=odometry_table)
        self.scans = TableWriter(out, SCANS, batch=1024, table=scan_table)
        self.dets: TableWriter[dict[str, Any]] | None = (
            TableWriter(out, TAG_DETECTIONS, batch=4096) if plan.use_detections else None
        )
        self.fast_ok: dict[str, bool] = {}
        """Per topic, whether :mod:`stages.ingest.fast` reads its messages: the type has the standard layout in the
        decoder's type store, or (without one) the first message read both ways agreed; absent: not known yet."""
        self.edges: list[tuple[str, str, np.ndarray]] = []
        self.frame_index: dict[str, int] = {}
        self.camera = next(iter(plan.cameras.values())) if plan.cameras else None
        self.camera_topics = {*plan.image_topics, *plan.detection_topics}
        self.frame_ids: dict[str, str] = {}
        """The frame id of each camera topic's first message."""
        self.base_frame = ""
        self.odom_frame = ""
        self.scan_frame = ""
        self.pending: dict[str, list[RawMessage]] = {}
        """Per odometry or scan topic read by :mod:`stages.ingest.fast`, the messages not yet parsed (in order)."""
        self.frame_log: FrameLog | None = None
        """Where the frames drawn in the recording go as they are read."""

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
            tf = self._record(raw, fast.tf_message, lambda m, _t: convert.transform_records(m), _same_transforms)
            if tf is not None:
                self.edges.extend(convert.edges_of(tf))
        elif raw.topic in self.camera_topics:
            self._frame(raw)
        elif self.plan.in_window(raw.log_time_ns):
            self._sensor(raw)

    def _frame(self, raw: RawMessage) -> None:
        """A camera frame (image or tag detections), counted from the first in the bag for the stride."""
        index = self.frame_index.get(raw.topic, 0)
        self.frame_index[raw.topic] = index + 1
        if not self.plan.in_window(raw.log_time_ns) or index % self.frame_stride:
            return
        if raw.topic in self.plan.image_topics:
            compressed = raw.type.endswith("CompressedImage")
            parse = fast.compressed_image if compressed else fast.image
            image = self._record(raw, parse, lambda m, t: convert.image_record(m, t, compressed), _same_image)
            if image is None:
                return
            row = convert.image_record_row(image, compressed)
            if self._bad(raw, convert.image_problem(row)):
                return
            self.frame_ids.setdefault(raw.topic, image.frame_id)
            full = {FRAME: index, STAMP_NS: image.stamp_ns, TOPIC: raw.topic, **row}
            self.frames.add(full)
            if self.frame_log is not None:
                self.frame_log.add(full)
            return
        msg = self._decode(raw)
        if msg is None:
            return
        stamp = convert.stamp_ns(msg, raw.log_time_ns)
        assert self.dets is not None
        self.frame_ids.setdefault(raw.topic, convert.frame_id(msg))
        for r in _detection_rows(msg, index, stamp, raw.topic):
            self.dets.add(r)

    def _record(
        self,
        raw: RawMessage,
        parse: Callable[[bytes, bool, int], R | None],
        generic: Callable[[Any, int], R],
        same: Callable[[R, R], bool],
    ) -> R | None:
        """The message's record: read from its bytes (:mod:`stages.ingest.fast`) once the topic's first message
        read that way matched its generic decoding; else decoded (None when it does not decode and --salvage
        drops it)."""
        trusted = self.fast_ok.get(raw.topic)
        if trusted is not False:
            quick = parse(raw.data, self.cdr, raw.log_time_ns)
            if quick is not None and trusted:
                return quick
            if quick is not None:  # the topic's first message: check the layout against the generic decoding
                try:
                    decoded = generic(raw.decode(), raw.log_time_ns)
                except InputError:
                    decoded = None
                if decoded is not None:
                    self.fast_ok[raw.topic] = same(quick, decoded)
                    return decoded
        msg = self._decode(raw)
        return None if msg is None else generic(msg, raw.log_time_ns)

    def _sensor(self, raw: RawMessage) -> None:
        """The first CameraInfo in the window, odometry and laser scans."""
        topics = self.plan.topics
        if raw.topic == topics["camera_info"] and self.camera is not None:
            return  # the first calibration in the window is the one used
        if raw.topic == topics["camera_info"]:
            info = self._record(raw, fast.camera_info, lambda m, _t: convert.camera_info_record(m), _same_camera)
            if info is not None:
                self.camera = convert.camera_from_record(info, raw.topic)
        elif raw.topic in (topics["odometry"], topics["scan"]):
            if self.fast_ok.get(raw.topic):  # read in batches (stages.ingest.fast), in order
                pending = self.pending.setdefault(raw.topic, [])
                pending.append(raw)
                if len(pending) >= _BATCH:
                    self._flush(raw.topic)
            elif raw.topic == topics["odometry"]:
                self._odometry(raw)
            else:
                self._scan(raw)

    def _odometry(self, raw: RawMessage) -> None:
        odom = self._record(raw, fast.odometry, convert.odometry_record, _same_odometry)
        if odom is None or self._bad(raw, convert.odometry_record_problem(odom)):
            return
        self.base_frame = self.base_frame or odom.child_frame_id
        self.odom_frame = self.odom_frame or odom.frame_id
        self.odom.add(odom)

    def _scan(self, raw: RawMessage) -> None:
        scan = self._record(raw, fast.laser_scan, convert.scan_record, _same_scan)
        if scan is None or self._bad(raw, convert.scan_record_problem(scan)):
            return
        if self.scans.count == 0:
            self.scan_frame = scan.frame_id  # the laser's frame is that of the first scan
        self.scans.add(scan)

    def _flush(self, topic: str) -> None:
        """The odometry or scan messages waiting on ``topic``: as one batch when they share one layout and every
        value is fine, else one at a time (the same records, and the same line or drop for a damaged one)."""
        raws = self.pending.pop(topic, [])
        if not raws:
            return
        data = [r.data for r in raws]
        stamps = np.array([r.log_time_ns for r in raws], dtype=np.int64)
        if topic == self.plan.topics["odometry"]:
            odom = fast.odometry_batch(data, self.cdr, stamps)
            if odom is not None and convert.odometry_values_fine(odom.values).all():
                self.base_frame = self.base_frame or odom.child_frame_id
                self.odom_frame = self.odom_frame or odom.frame_id
                self.odom.add_table(odometry_batch_table(odom))
                return
            for r in raws:
                self._odometry(r)
            return
        scans = fast.scan_batch(data, self.cdr, stamps)
        if scans is not None and convert.scan_values_fine(scans.limits, scans.ranges).all():
            if self.scans.count == 0:
                self.scan_frame = scans.frame_id
            self.scans.add_table(scan_batch_table(scans))
            return
        for r in raws:
            self._scan(r)

    def close(self) -> None:
        for topic in list(self.pending):
            self._flush(topic)
        writers: list[TableWriter[Any]] = [self.frames, self.odom, self.scans, *([self.dets] if self.dets else [])]
        for w in writers:
            w.close()
        if self.frame_log is not None:
            self.frame_log.flush()


def _check_read(plan: _Plan, reading: _Reading, cfg: IngestConfig) -> CameraModel:
    """The camera calibration; fail when the window held no camera frame or no calibration."""
    topics = plan.topics
    if reading.frames.count == 0 and (
        reading.dets is None or not any(reading.frame_index.get(t, 0) for t in plan.detection_topics)
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
) -> tuple[CameraModel, Extrinsics, list[str], list[str]]:
    """``camera.json`` (``cameras.json`` for a rig of several) and ``extrinsics.json``: base to each camera and
    the laser, from the extrinsics file where it names the sensor, else from the static transforms."""
    plan = reading.plan
    topics = plan.camera_topics
    models = plan.cameras or {topics[0]: camera}
    models = {
        t: m.model_copy(update={"frame_id": m.frame_id or reading.frame_ids.get(t, "")}) for t, m in models.items()
    }
    camera = next(iter(models.values()))
    file, tags_notes, applied = _odometry_mount(plan.extrinsics, plan.tags, reading.base_frame)
    base = reading.base_frame or (file.base_frame if file else camera.frame_id)
    notes: list[str] = list(tags_notes)
    warnings: list[str] = []
    if file and reading.base_frame and reading.base_frame != file.base_frame and not applied:
        notes.append(
            f"the transforms of {Path(file.path).name} (from its {file.base_frame!r} frame) are taken as from the "
            f"odometry's child frame {reading.base_frame!r}"
        )
    sensors: dict[str, SensorMount] = {}
    for i, (topic, model) in enumerate(models.items()):
        names = (plan.camera_names.get(topic), topic, model.topic, model.tag_topic)
        mount = _mount(reading, file, base, model.frame_id, names)
        sensors["camera" if i == 0 else topic] = mount.model_copy(update={"topic": topic})
    if reading.scan_frame:
        sensors["laser"] = _mount(reading, file, base, reading.scan_frame, ())
    placed_cameras = [r for r, m in sensors.items() if r != "laser" and not m.assumed]
    for role, mount in sensors.items():
        if mount.assumed:
            what = "camera" if role == "camera" else ("laser" if role == "laser" else f"camera {role}")
            where = f"in {Path(file.path).name} or " if file else ""
            if len(models) > 1 and role != "laser" and placed_cameras:
                notes.append(
                    f"no transform {where}on /tf_static from {base!r} to the {what} frame {mount.frame_id!r}: the "
                    "graph estimates its mount from the tags it sees with the rig's placed cameras "
                    "(graph.rig_calibration)"
                )
                continue
            consequence = "its detections are left out of the graph" if len(models) > 1 else "identity assumed"
            warnings.append(
                f"no transform {where}on /tf_static from {base!r} to the {what} frame {mount.frame_id!r}; "
                f"{consequence}; give it with --extrinsics FILE (TagSLAM camera_poses.yaml, Kalibr camchain or "
                "frame: 4x4 T_base_frame)"
            )
    extrinsics = Extrinsics(
        base_frame=base,
        odom_frame=reading.odom_frame,
        sensors=sensors,
        file=str(Path(file.path).resolve()) if file else None,
    )
    CAMERA.write(out, camera)
    if len(models) > 1:
        CAMERAS.write(out, Rig(cameras=models))
    EXTRINSICS.write(out, extrinsics)
    if plan.tags is not None:
        TAGS.write(out, _tags_info(plan.tags, applied, tags_notes))
    else:
        out.file(TAGS.file).unlink(missing_ok=True)
    if reading.dets is None:
        out.file(TAG_DETECTIONS.file).unlink(missing_ok=True)
    return camera, extrinsics, notes, warnings


def _mount(
    reading: _Reading, file: ExtrinsicsFile | None, base: str, frame: str, names: tuple[str | None, ...]
) -> SensorMount:
    """Where ``frame`` sits: the file's entry named by the frame or one of ``names``, else the static transforms
    from ``base``, else identity (assumed)."""
    found = file.find(frame, *names) if file else None
    if file is not None and found is not None:
        entry, T = found
        info = file.information.get(entry)
        return SensorMount(
            frame_id=frame,
            T_base_sensor=T.tolist(),
            source=f"{Path(file.path).name} ({file.kind}) {entry}{file.via}",
            information=None if info is None else info.tolist(),
        )
    chained = convert.chain(reading.edges, base, frame)
    if chained is not None:
        source = "base frame" if frame == base else "/tf_static"
        return SensorMount(frame_id=frame, T_base_sensor=chained.tolist(), source=source)
    return SensorMount(frame_id=frame, T_base_sensor=np.eye(4).tolist(), assumed=True, source="identity (assumed)")


def _odometry_mount(
    file: ExtrinsicsFile | None, tags: TagsFile | None, base_frame: str
) -> tuple[ExtrinsicsFile | None, list[str], bool]:
    """The extrinsics file with its rig mounts moved into the odometry's child frame by the tags file's
    ``T_body_odom`` (``T_base_cam = T_body_odom⁻¹ T_rig_cam``), the notes of the tags file, and whether it was
    applied. Only a TagSLAM camera_poses.yaml places cameras in TagSLAM's rig body; mounts from /tf_static or
    another file are already relative to their own base and are left alone (with a note)."""
    if tags is None:
        return file, [], False
    notes = list(tags.notes)
    if tags.T_body_odom is None:
        return file, notes, False
    name = Path(tags.path).name
    if file is None or file.kind != "tagslam camera_poses":
        what = f"the mounts of {Path(file.path).name} ({file.kind})" if file else "the mounts on /tf_static"
        notes.append(
            f"T_body_odom of {name} is not applied: {what} are not in TagSLAM's rig body; give the cameras with "
            "--extrinsics camera_poses.yaml to place them in the rig"
        )
        return file, notes, False
    from stages.extrinsics import invert

    T_odom_rig = invert(tags.T_body_odom)
    moved = ExtrinsicsFile(
        file.path,
        file.kind,
        base_frame or file.base_frame,
        {entry: T_odom_rig @ T for entry, T in file.mounts.items()},
        via=f" moved into the odometry frame by T_body_odom of {name}",
        information=file.information,
    )
    notes.append(
        f"the cameras of {Path(file.path).name} (in TagSLAM's rig body) are placed in the odometry's child frame "
        f"{base_frame or file.base_frame!r} by T_body_odom of {name} (body {tags.odometry_body!r})"
    )
    return moved, notes, True


def _tags_info(tags: TagsFile, applied: bool, notes: list[str]) -> TagsInfo:
    from stages.ingest.artifacts import KnownTag, TagRemap

    return TagsInfo(
        file=str(Path(tags.path).resolve()),
        default_tag_size_m=tags.default_tag_size_m,
        tag_sizes_m=dict(sorted(tags.tag_sizes_m.items())),
        ignore_tags=tags.ignore_tags,
        moving_tags=tags.moving_tags,
        tag_id_remap=[
            TagRemap(id=r.tag_id, remap_id=r.remap_id, start_ns=r.start_ns, end_ns=r.end_ns, camera=r.camera)
            for r in tags.remaps
        ],
        known_tags=[
            KnownTag(
                id=k.tag_id,
                body=k.body,
                T_world_tag=k.T_world_tag.tolist(),
                covariance=k.covariance.tolist(),
                rotation_sigma_rad=k.rotation_sigma_rad,
                position_sigma_m=k.position_sigma_m,
            )
            for k in tags.known_tags
        ],
        odometry_body=tags.odometry_body,
        odometry_topic=tags.odometry_topic,
        T_body_odom=tags.T_body_odom.tolist() if tags.T_body_odom is not None else None,
        T_body_odom_applied=applied,
        notes=notes,
    )
