"""Ingest: read a recording once and keep what the later stages need, so they never open the bag again.

Reads camera frames, camera model, odometry, laser scans, static extrinsics and, when the bag holds
them, AprilTag detections. Writes the artifacts described in ``stages/ingest/ARTIFACTS.md``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.context import StageContext
from pipeline.errors import InputError
from stages.ingest import convert
from stages.ingest.bags import Recording
from stages.ingest.config import IngestConfig
from stages.ingest.record import log_ingest
from stages.ingest.topics import ROLES, resolve_topic


def _frames_schema() -> pa.Schema:
    return pa.schema(
        [
            ("frame", pa.int64()),
            ("stamp_ns", pa.int64()),
            ("topic", pa.string()),
            ("format", pa.string()),
            ("width", pa.int32()),
            ("height", pa.int32()),
            ("step", pa.int32()),
            ("data", pa.binary()),
        ]
    )


def _odometry_schema() -> pa.Schema:
    cols = [("stamp_ns", pa.int64())] + [
        (c, pa.float64()) for c in ("x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz", "wx", "wy", "wz")
    ]
    cols += [
        ("pose_cov", pa.list_(pa.float64(), 36)),
        ("twist_cov", pa.list_(pa.float64(), 36)),
        ("frame_id", pa.string()),
        ("child_frame_id", pa.string()),
    ]
    return pa.schema(cols)


def _scans_schema() -> pa.Schema:
    return pa.schema(
        [
            ("stamp_ns", pa.int64()),
            ("frame_id", pa.string()),
            ("angle_min", pa.float64()),
            ("angle_max", pa.float64()),
            ("angle_increment", pa.float64()),
            ("range_min", pa.float64()),
            ("range_max", pa.float64()),
            ("ranges", pa.list_(pa.float32())),
        ]
    )


def _detections_schema() -> pa.Schema:
    return pa.schema(
        [
            ("frame", pa.int64()),
            ("stamp_ns", pa.int64()),
            ("topic", pa.string()),
            ("tag_id", pa.int64()),
            ("family", pa.string()),
            ("corners", pa.list_(pa.float64(), 8)),
        ]
    )


def _detection_rows(msg: Any, frame: int, stamp: int, topic: str) -> list[dict[str, Any]]:
    """Rows of an apriltag_msgs ApriltagArrayStamped (ROS 1) or AprilTagDetectionArray (ROS 2)."""
    rows = []
    for det in convert.get(msg, "apriltags", "detections", default=[]):
        corners = [float(v) for c in det.corners for v in (c.x, c.y)]
        family = str(convert.get(det, "family", default="") or "tag36h11")
        if family and not family.startswith("tag"):
            family = f"tag{family}"
        rows.append(
            {
                "frame": frame,
                "stamp_ns": stamp,
                "topic": topic,
                "tag_id": int(det.id),
                "family": family,
                "corners": corners[:8],
            }
        )
    return rows


class _TableWriter:
    """Stream rows to a Parquet file in row groups, so long recordings do not fill memory."""

    def __init__(self, path: Path, schema: pa.Schema, batch: int = 256) -> None:
        self.path, self.schema, self.batch = path, schema, batch
        self.rows: list[dict[str, Any]] = []
        self.count = 0
        self.writer = pq.ParquetWriter(path, schema, compression="zstd")

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        self.count += 1
        if len(self.rows) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if self.rows:
            self.writer.write_table(pa.Table.from_pylist(self.rows, schema=self.schema))
            self.rows = []

    def close(self) -> None:
        self.flush()
        self.writer.close()


def _load_camera_file(path: str) -> dict[str, Any]:
    from stages.camera import load_camera_file

    return load_camera_file(Path(path))


def run(ctx: StageContext, cfg: IngestConfig) -> dict[str, Any]:
    """Read the recording into the run folder."""
    started = time.perf_counter()
    with Recording(ctx.source, salvage=cfg.salvage) as rec:
        if rec.message_count == 0:
            raise InputError(f"{rec.path.name} holds no messages; record again or pick another bag")
        topics = {name: resolve_topic(rec, role, getattr(cfg, role.setting)) for name, role in ROLES.items()}
        if topics["image"] is None and topics["detections"] is None:
            present = ", ".join(f"{n} ({t.type})" for n, t in sorted(rec.topics.items()))
            raise InputError(
                f"{rec.path.name} has no camera image topic (sensor_msgs/Image or CompressedImage) and no AprilTag "
                f"detections; topics present: {present}"
            )
        use_detections = topics["detections"] is not None and (topics["image"] is None or cfg.detections_topic)
        if use_detections:
            topics["image"] = None if not cfg.image_topic else topics["image"]
        camera: dict[str, Any] | None = _load_camera_file(cfg.camera_file) if cfg.camera_file else None
        if camera is None and topics["camera_info"] is None:
            raise InputError(
                f"{rec.path.name} has no CameraInfo topic; pass the calibration with --camera FILE "
                "(Kalibr/TagSLAM cameras.yaml or ROS camera_info YAML)"
            )
        start_ns = rec.start_ns + int(cfg.start_s * 1e9)
        end_ns = rec.start_ns + int(cfg.end_s * 1e9) if cfg.end_s is not None else None
        if end_ns is not None and end_ns <= start_ns:
            raise InputError(f"--end {cfg.end_s} s is not after --start {cfg.start_s} s")

        out = ctx.output
        frames = _TableWriter(out.file("frames.parquet"), _frames_schema())
        odom = _TableWriter(out.file("odometry.parquet"), _odometry_schema(), batch=4096)
        scans = _TableWriter(out.file("scans.parquet"), _scans_schema(), batch=1024)
        dets = (
            _TableWriter(out.file("tag_detections.parquet"), _detections_schema(), batch=4096)
            if use_detections
            else None
        )
        edges: list[tuple[str, str, np.ndarray]] = []
        frame_index: dict[str, int] = {}
        image_frame_id = ""
        wanted = [t for t in topics.values() if t]
        total = sum(rec.topics[t].count for t in wanted)
        base_frame = ""
        odom_frame = ""
        for raw in ctx.progress(rec.messages(wanted), "ingest", total=total):
            topic = raw.topic
            if topic == topics["tf_static"]:
                edges.extend(convert.transform_edges(raw.decode()))
                continue
            if topic in (topics["image"], topics["detections"]):
                index = frame_index.get(topic, 0)
                frame_index[topic] = index + 1
                if raw.log_time_ns < start_ns or (end_ns is not None and raw.log_time_ns > end_ns):
                    continue
                if index % cfg.frame_stride:
                    continue
                msg = raw.decode()
                stamp = convert.stamp_ns(msg, raw.log_time_ns)
                if topic == topics["image"]:
                    row = convert.image_row(msg, compressed=raw.type.endswith("CompressedImage"))
                    image_frame_id = image_frame_id or convert.frame_id(msg)
                    frames.add({"frame": index, "stamp_ns": stamp, "topic": topic, **row})
                else:
                    assert dets is not None
                    image_frame_id = image_frame_id or convert.frame_id(msg)
                    for r in _detection_rows(msg, index, stamp, topic):
                        dets.add(r)
                continue
            if raw.log_time_ns < start_ns or (end_ns is not None and raw.log_time_ns > end_ns):
                continue
            if topic == topics["camera_info"] and camera is not None:
                continue  # the first calibration in the window is the one used
            msg = raw.decode()
            if topic == topics["camera_info"]:
                if camera is None:
                    camera = convert.camera_from_info(msg, topic)
            elif topic == topics["odometry"]:
                row = convert.odometry_row(msg, convert.stamp_ns(msg, raw.log_time_ns))
                base_frame = base_frame or row["child_frame_id"]
                odom_frame = odom_frame or row["frame_id"]
                odom.add(row)
            elif topic == topics["scan"]:
                scans.add(convert.scan_row(msg, convert.stamp_ns(msg, raw.log_time_ns)))
        for w in (frames, odom, scans, *([dets] if dets else [])):
            w.close()
        salvaged = rec.salvaged
        reader, fmt, storage = rec.reader, rec.format, rec.storage
        bag_start, bag_end = rec.start_ns, rec.end_ns

    if frames.count == 0 and (dets is None or frame_index.get(topics["detections"] or "", 0) == 0):
        window = f" between {cfg.start_s} s and {cfg.end_s} s" if cfg.start_s or cfg.end_s else ""
        raise InputError(
            f"no camera frames on {topics['image'] or topics['detections']}{window}; widen the time window"
        )
    if camera is None:
        raise InputError(f"no CameraInfo message on {topics['camera_info']} in the time window; pass --camera FILE")

    camera_frame = camera.get("frame_id") or image_frame_id
    camera["frame_id"] = camera_frame
    base = base_frame or camera_frame
    sensors: dict[str, Any] = {}
    notes: list[str] = []
    scan_frame = ""
    if scans.count:
        scan_frame = str(pq.read_table(out.file("scans.parquet"), columns=["frame_id"]).column(0)[0])
    for role, frame in (("camera", camera_frame), ("laser", scan_frame)):
        if not frame:
            continue
        T = convert.chain(edges, base, frame)
        assumed = T is None
        if T is None:
            notes.append(f"no static transform from {base!r} to {role} frame {frame!r}; identity assumed")
            T = np.eye(4)
        sensors[role] = {"frame_id": frame, "T_base_sensor": T.tolist(), "assumed": assumed}
    out.write_json("camera.json", camera)
    out.write_json("extrinsics.json", {"base_frame": base, "odom_frame": odom_frame, "sensors": sensors})
    if dets is None:
        out.file("tag_detections.parquet").unlink(missing_ok=True)

    duration = (bag_end - bag_start) * 1e-9
    summary = {
        "frames": frames.count,
        "tag_detections": dets.count if dets else 0,
        "odometry": odom.count,
        "scans": scans.count,
        "duration_s": round(duration, 6),
        "start_ns": bag_start,
        "topics": {k: v for k, v in topics.items() if v},
        "reader": reader,
        "format": fmt,
        "storage": storage,
        "camera": {k: camera[k] for k in ("width", "height", "distortion_model", "frame_id", "source")},
        "notes": notes,
        "read_seconds": round(time.perf_counter() - started, 3),
    }
    if salvaged is not None:
        summary["salvaged"] = salvaged
    log_ingest(ctx, camera, sensors)
    return summary
